"""The module contract of every renderer: ``.to(dtype)`` converts all the state it renders from.

Each renderer renders, goes to float64 and renders, comes back to float32 and renders; the
three images agree to float32 tolerance and the float64 render is float64 throughout.
"""

from __future__ import annotations

import pytest
import torch

from tests.render.test_triple import EYE, sky
from tests.transport.test_polynomial import glossy_box
from tests.transport.test_visibility import ball_on_plane
from torch_brdf.brdf.analytic import Phong
from torch_brdf.records import BasisImage
from torch_brdf.render import BasisImageRenderer, PolynomialRenderer, TripleProductRenderer
from torch_brdf.transport import PolynomialSettings, VisibilitySettings, precompute_polynomial, precompute_visibility


def _round_trip(module, render):
    """(float32 render, float64 render, float32 render after the round trip)."""
    a = render(module)
    module.to(torch.float64)
    b = render(module)
    module.to(torch.float32)
    c = render(module)
    return a, b, c


def _check(a, b, c, rtol=1e-5):
    assert a.dtype == c.dtype == torch.float32 and b.dtype == torch.float64
    scale = float(b.abs().max())
    assert scale > 0
    torch.testing.assert_close(b, a.double(), rtol=rtol, atol=rtol * scale)
    torch.testing.assert_close(c, a, rtol=rtol, atol=rtol * scale)


def test_basis_image_renderer_to(gen):
    images = torch.rand(4, 5, 6, 3, generator=gen)
    rec = BasisImage.from_dense(images, constant=torch.rand(5, 6, 3, generator=gen))
    coeff = torch.rand(4, 3, generator=gen)
    a, b, c = _round_trip(BasisImageRenderer(rec), lambda m: m(coeff.to(m.values.dtype)))
    _check(a, b, c)


@pytest.fixture(scope="module")
def tensors():
    return precompute_polynomial(glossy_box(8), PolynomialSettings("4,2,1", spp=2), seed=1, progress=False)


@pytest.mark.parametrize("frozen", [False, True])
def test_polynomial_renderer_to(tensors, frozen):
    r = PolynomialRenderer(tensors)
    r.set_material("back", Phong(0.2, 0.5, 40.0))
    if frozen:
        r.freeze("back")
    a, b, c = _round_trip(r, lambda m: m())
    assert r.dtype == torch.float32 and (r.frozen_object == "back") == frozen
    _check(a, b, c)
    # an edit after the round trip renders in the module's dtype again
    r.to(torch.float64).set_material("back", Phong(0.3, 0.4, 40.0))
    assert r().dtype == torch.float64


def test_triple_product_renderer_to():
    scene = ball_on_plane(quads=4)
    scene.lights[:] = [sky()]
    vis = precompute_visibility(scene, VisibilitySettings(resolution=16, chunk=64), progress=False)
    r = TripleProductRenderer(scene, vis)
    r.set_material("box", Phong(0.3, 0.5, 60.0))

    def render(m):
        rad, _ = m.shade(m.all_vertices(EYE))
        return rad

    a, b, c = _round_trip(r, render)
    _check(a, b, c, rtol=1e-4)
