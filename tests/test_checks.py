"""Input conversion at public entry points."""

import pytest
import torch

from torch_brdf._checks import as_float_tensor, check_vectors
from torch_brdf.errors import ShapeError, ValueRangeError


def test_python_floats_keep_double_precision_when_asked():
    x = as_float_tensor(1 - 1e-9, "x", torch.float64)
    assert x.dtype == torch.float64 and float(x) < 1.0
    assert as_float_tensor([1, 2], "x").dtype == torch.get_default_dtype()
    assert as_float_tensor(torch.tensor([1.0], dtype=torch.float64), "x").dtype == torch.float64


def test_bad_inputs_are_named():
    with pytest.raises(ShapeError, match="x"):
        as_float_tensor(object(), "x")
    with pytest.raises(ShapeError):
        check_vectors(torch.zeros(4, 2), "d")
    with pytest.raises(ValueRangeError):
        check_vectors(torch.full((1, 3), float("nan")), "d")


def test_integer_checks_refuse_floats_bools_and_out_of_range():
    import numpy as np

    from torch_brdf._checks import check_count, check_int, check_seed

    assert check_count(np.int64(3), "n") == 3 and check_count(torch.tensor(4), "n") == 4
    for bad in (16.0, True, "3", None, 0, -1):
        with pytest.raises(ValueRangeError, match=r"^n must be"):
            check_count(bad, "n")
    with pytest.raises(ValueRangeError, match="n must be <= 8"):
        check_int(9, "n", 0, 8)
    assert check_seed(0) == 0 and check_seed(2**63 - 1) == 2**63 - 1
    for bad in (-1, 2**63):
        with pytest.raises(ValueRangeError, match="seed"):
            check_seed(bad)


def test_real_checks_refuse_nan_inf_and_non_numbers():
    from torch_brdf._checks import check_real

    assert check_real(2, "x") == 2.0 and check_real(float("inf"), "x", finite=False) == float("inf")
    for bad in (float("nan"), float("inf"), "1.0", False, [1.0]):
        with pytest.raises(ValueRangeError, match=r"^x must be"):
            check_real(bad, "x")
    with pytest.raises(ValueRangeError, match="x must be >= 0"):
        check_real(-1.0, "x", minimum=0.0)


def test_image_sizes_are_capped():
    from torch_brdf._checks import MAX_IMAGE_SIDE, check_image_size

    assert check_image_size(640, 480) == (640, 480)
    with pytest.raises(ValueRangeError, match="width must be <= 16384"):
        check_image_size(100000, 100000)
    with pytest.raises(ValueRangeError, match="exceeds the cap"):
        check_image_size(MAX_IMAGE_SIDE, MAX_IMAGE_SIDE)


def test_rgb_beyond_float32_is_refused():
    # lights keep RGB in float32 buffers: 1e300 became Inf and the render failed only at its end
    from torch_brdf._checks import check_rgb
    from torch_brdf.scene import DirectionalLight

    assert check_rgb([0.0, 3e38, 1.0], "radiance") == (0.0, 3e38, 1.0)
    with pytest.raises(ValueRangeError, match="radiance exceeds the float32 range"):
        check_rgb([1.0, 1e300, 1.0], "radiance")
    with pytest.raises(ValueRangeError, match="irradiance exceeds the float32 range"):
        DirectionalLight([0.0, 1.0, 0.0], 1e39)
