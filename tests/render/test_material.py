"""MaterialProjector: one way from a BRDF to an object's band coefficients (renderer and editor).

Oracles: the exact cases against their closed forms, the projections against
:func:`~torch_brdf.brdf.bands.project` / :class:`~torch_brdf.brdf.bands.Projector` called
directly, the Fresnel split against Eq. 32 written out.
"""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import RTOL
from torch_brdf.brdf import Lambert, create
from torch_brdf.brdf.bands import Factored1D, FresnelFactored1D, Projector, project
from torch_brdf.errors import ValueRangeError
from torch_brdf.records.polynomial import ObjectBasis
from torch_brdf.render.material import MaterialProjector

COARSE = {"n_theta_d": 2, "n_phi_d": 4, "n_phi_h": 4, "order": 2}


def test_lambert_is_exact_and_keeps_its_graph():
    albedo = torch.tensor([0.2, 0.5, 0.8])
    brdf = Lambert(albedo)
    c, curve = MaterialProjector(ObjectBasis(J=4))(brdf)
    assert c.shape == (4, 3) and c is curve
    torch.testing.assert_close(c, (brdf.reflectance / math.pi).reshape(1, 3).expand(4, 3))
    c.sum().backward()
    (raw,) = brdf.parameters()
    assert raw.grad is not None and bool((raw.grad != 0).all())
    const, _ = MaterialProjector(ObjectBasis(J=4), graph=False)(Lambert(albedo))
    assert const.dtype == torch.float64 and not const.requires_grad


def test_a_curve_on_the_same_bands_and_quotient_is_used_as_is():
    basis = ObjectBasis(J=6)
    mp = MaterialProjector(basis)
    coefficients = torch.rand(6, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    curve = Factored1D(mp.bands, coefficients)
    assert mp.on_bands(curve)
    torch.testing.assert_close(mp.curve(curve), curve.coefficients)
    other = Factored1D(mp.bands, coefficients, quotient="distribution")  # another quotient
    assert not mp.on_bands(other)
    torch.testing.assert_close(mp.curve(other), project(other, mp.bands, "one"))  # projected, not taken as is


def test_other_brdfs_are_projected_by_the_full_or_the_coarse_rule():
    basis = ObjectBasis(J=8)
    brdf = create({"type": "blinn_phong", "kd": 0.2, "ks": 0.5, "exponent": 30.0})
    full = MaterialProjector(basis).curve(brdf)
    torch.testing.assert_close(full, project(brdf, basis.band_basis(), basis.quotient))
    fast = MaterialProjector(basis, COARSE, graph=False)
    direct = Projector(basis.band_basis(), basis.quotient, False, **COARSE)(brdf)
    torch.testing.assert_close(fast.curve(brdf), direct)
    assert len(fast._projectors) == 1  # built once, reused


def test_the_fresnel_layer_splits_the_curve_by_f0():
    basis = ObjectBasis(J=4, fresnel=True)
    mp = MaterialProjector(basis, graph=False)
    brdf = Lambert(torch.tensor([0.3, 0.6, 0.9]))
    c, curve = mp(brdf, f0=[0.1, 0.5, 1.0])
    f = torch.tensor([0.1, 0.5, 1.0], dtype=torch.float64)
    torch.testing.assert_close(c, torch.cat([curve * f, curve * (1 - f)], 0))
    c1, _ = mp(brdf)  # no f0: 1, the BRDF as given
    torch.testing.assert_close(c1, torch.cat([curve, torch.zeros_like(curve)], 0))
    layered = FresnelFactored1D(mp.bands, curve.clone(), f0=0.25)
    c2, _ = mp(layered)  # its own two layers (Eq. 32 with its F0), kept as float32 parameters
    torch.testing.assert_close(c2, torch.cat([curve * 0.25, curve * 0.75], 0), rtol=RTOL[torch.float32], atol=0)
    for bad in (1.5, -0.1, float("nan")):
        with pytest.raises(ValueRangeError, match="f0"):
            mp(brdf, f0=bad)


def test_f0_on_an_object_without_the_fresnel_layer_is_refused():
    with pytest.raises(ValueRangeError, match="Fresnel"):
        MaterialProjector(ObjectBasis(J=2))(Lambert(torch.tensor(0.5)), f0=0.5, name="wall")
