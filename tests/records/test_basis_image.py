"""BasisImage: the shared "pixels x basis x channels" record."""

import pytest
import torch

from tests.conftest import corrupted_copy
from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.render import BasisImage, BasisImageRenderer, float16_error


def _record(gen, j=5, h=6, w=7, c=3, dtype=torch.float64):
    images = torch.rand(j, h, w, c, generator=gen, dtype=dtype)
    const = torch.rand(h, w, c, generator=gen, dtype=dtype)
    mask = torch.rand(h, w, generator=gen) > 0.3
    return images, const, mask, BasisImage.from_dense(images, const, mask, basis="test:5")


def test_image_equals_dense_sum(gen):
    images, const, mask, rec = _record(gen)
    a = torch.rand(5, 3, generator=gen, dtype=torch.float64)
    want = torch.einsum("jhwc,jc->hwc", images, a) + const
    got = rec.image(a, background=-1.0)
    torch.testing.assert_close(got[mask], want[mask])
    assert bool((got[~mask] == -1.0).all())
    # scalar coefficients apply to every channel
    torch.testing.assert_close(rec.image(a[:, 0])[mask], (torch.einsum("jhwc,j->hwc", images, a[:, 0]) + const)[mask])


def test_gradients_and_module(gen):
    _, _, _, rec = _record(gen)
    a = torch.rand(5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: rec.pixel_values(x), (a,))
    m = BasisImageRenderer(rec).to(torch.float32)
    assert m(a.detach().float()).dtype == torch.float32


def test_save_load_roundtrip_and_float16(tmp_path, gen):
    _, _, _, rec = _record(gen, dtype=torch.float32)
    var = rec.values.square()
    rec = BasisImage(rec.values, rec.pixels, rec.height, rec.width, rec.constant, var, rec.basis, {"spp": 4})
    back = BasisImage.load(rec.save(tmp_path / "r.npz"))
    assert torch.equal(back.values, rec.values) and torch.equal(back.variance, rec.variance)
    assert back.meta == {"spp": 4} and back.basis == "test:5"
    half = BasisImage.load(rec.save(tmp_path / "h.npz", storage="float16"))
    err = float(((half.values - rec.values).abs() / rec.values.abs()).max())
    assert err <= 2.0**-11 and err == pytest.approx(float16_error(rec.values), rel=1e-6)
    assert float16_error(torch.tensor([1e6])) == float("inf")
    with pytest.raises(FileFormatError):
        BasisImage.load(corrupted_copy(tmp_path / "r.npz", tmp_path / "bad.npz"))


def test_bad_input(gen):
    _, _, _, rec = _record(gen)
    with pytest.raises(ShapeError):
        rec.image(torch.ones(4))
    with pytest.raises(ValueRangeError):
        rec.image(torch.full((5,), float("nan")))
    with pytest.raises(ShapeError):
        BasisImage(torch.ones(3, 2, 4), torch.tensor([0, 1, 2, 99]), 3, 3)
