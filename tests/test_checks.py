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
