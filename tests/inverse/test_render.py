"""Re-rendering (Eq. 22) and the p(h) image."""

from __future__ import annotations

import pytest
import torch

from tests.inverse.conftest import F0, KD, true_coefficients
from torch_brdf.inverse import FitResult, distribution_image, rerender, srbf_brdf
from torch_brdf.inverse.energy import default_basis


def _result():
    c = true_coefficients()[:, None].expand(-1, 3).clone()
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    return FitResult(c, t(KD), t(F0), 0.0, 0.0, 0, 0.0, True, 0.0)


def test_rerender_in_the_fitting_view_equals_the_record(view):
    scene, _, _, _, rec = view
    img = rerender(scene, "teapot", _result(), light_samples=128, generator=torch.Generator().manual_seed(7))
    assert img.shape == (rec.height, rec.width, 3)
    torch.testing.assert_close(img, rec.image(_result().record_coefficients()), rtol=1e-12, atol=1e-14)


def test_rerender_new_light_and_view(view):
    scene = view[0]
    cam = scene.camera.with_size(40, 30)
    env = scene.environment.rotated(2.0)
    g = torch.Generator().manual_seed(1)
    a = rerender(scene, "teapot", _result(), camera=cam, light_samples=64, generator=g)
    b = rerender(scene, "teapot", _result(), camera=cam, environment=env, light_samples=64, generator=g)
    assert a.shape == (30, 40, 3) and bool(torch.isfinite(b).all())
    assert float((a - b).abs().max()) > 1e-3  # the rotated sky moves the highlights


def test_distribution_image_and_brdf():
    c = true_coefficients()
    img = distribution_image(c, size=65)
    assert img.shape == (65, 65)
    pole = default_basis().eval(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)) @ c
    assert float(img[32, 32]) == pytest.approx(float(pole), rel=1e-12)  # pixel (32, 32) looks at the pole
    assert float(img[0, 0]) == 0.0 and float(img.min()) >= 0.0
    brdf = srbf_brdf(_result())
    wi = torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64)
    wo = torch.tensor([[0.0, -0.6, 0.8]], dtype=torch.float64)
    p = (default_basis().eval(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)) @ c).item()
    den = 0.8 + 0.8 - 0.64
    fresnel = torch.tensor(F0, dtype=torch.float64) + (1 - torch.tensor(F0, dtype=torch.float64)) * 0.2**5
    want = torch.tensor(KD, dtype=torch.float64) / torch.pi + p * fresnel / den
    torch.testing.assert_close(brdf.double().eval(wi, wo)[0], want, rtol=1e-6, atol=0)
