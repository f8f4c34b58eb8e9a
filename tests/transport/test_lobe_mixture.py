"""The edit-robust direction mixture (:class:`LobeMixture`): a density, exact bookkeeping, and the
same tensors in expectation as the default mixture (every edit unbiased whatever the pdf)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torch_brdf.errors import SceneError, ValueRangeError
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.transport.polynomial import LobeMixture, Mixture, PolynomialSettings, precompute_polynomial

from .test_polynomial import check_oracle, glossy_box


def test_lobe_mixture_pdf_integrates_to_one_and_matches_samples(gen):
    """Per object: the mixture on its objects (pdf integrates to one and is the density the
    samples were drawn with: E[1/pdf] = 2 pi), the base mixture elsewhere."""
    mix = LobeMixture(0.4, ((0.3, 200.0), (0.3, 2000.0)), ids=(1,))
    n = 200000
    wo = torch.tensor([[0.3, 0.1, 0.948683]], dtype=torch.float64).expand(n, 3)
    wo = wo / wo.norm(dim=-1, keepdim=True)
    u = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    oid = torch.randint(0, 3, (n,), generator=gen)
    wi, pdf = mix.sample(wo, u, oid)
    valid = pdf > 0
    mirror = torch.tensor([-0.3, -0.1, 0.948683], dtype=torch.float64)
    mirror = mirror / mirror.norm()
    for o in range(3):
        m = oid == o
        inv = valid[m].double() / pdf[m].clamp_min(1e-300)
        assert float(inv.mean()) == pytest.approx(2 * math.pi, rel=0.03), o
        # E[1{cone} / pdf] = the cone's solid angle, near the mirror where the lobes sample
        for angle in (0.05, 0.2):
            cone = (wi[m] @ mirror) > math.cos(angle)
            est = float((cone.double() * inv).mean())
            assert est == pytest.approx(2 * math.pi * (1 - math.cos(angle)), rel=0.05), (o, angle, est)
    torch.testing.assert_close(mix.pdf(wi[valid], wo[valid], oid[valid]), pdf[valid])
    base = oid != 1  # the other objects sample exactly what the default mixture samples
    want_wi, want_pdf = Mixture().sample(wo[base], u[base])
    torch.testing.assert_close(wi[base], want_wi)
    torch.testing.assert_close(pdf[base], want_pdf)
    # a sharper lobe puts more of the samples near the mirror direction than the default
    near = (wi @ mirror) > math.cos(0.05)
    assert float(near[oid == 1].double().mean()) > 2 * float(near[base].double().mean())


def test_lobe_mixture_checks_its_input():
    with pytest.raises(ValueRangeError, match="diffuse \\+ the lobe weights = 1"):
        LobeMixture(0.5, ((0.25, 200.0),))
    with pytest.raises(ValueRangeError):
        LobeMixture(0.5, ((0.75, 200.0), (-0.25, 10.0)))
    sc = glossy_box(8)
    with pytest.raises(SceneError, match="unknown objects"):
        precompute_polynomial(
            sc, PolynomialSettings("4,1", spp=1, mixture=LobeMixture(objects=("nope",))), progress=False
        )
    with pytest.raises(ValueRangeError, match="resolve"):
        LobeMixture().sample(torch.zeros(1, 3), torch.zeros(1, 3), torch.zeros(1, dtype=torch.long))


def test_resolve_defaults_to_the_banded_objects():
    sc = glossy_box(8)
    T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=1, mixture=LobeMixture()), progress=False)
    banded = [k for k, b in enumerate(T.bases) if b is not None and b.J > 1]
    assert banded == [sc.object_id("back")]
    assert T.meta["mixture"][2] == banded  # the resolved ids enter the resume key


@pytest.mark.parametrize("series", ["8,1,1,1", "8,4,1"])
def test_tensors_equal_explicit_path_tracer_with_lobe_mixture(series, gen):
    """The exactness oracle with the lobe mixture: the recorded path weights divide by the
    mixture's pdf, and the tensors evaluated at any coefficients equal the explicit BRDFs on
    the same paths."""
    sc = glossy_box()
    paths: dict = {}
    spp = 4
    mix = LobeMixture(0.4, ((0.3, 200.0), (0.3, 2000.0)))
    T = precompute_polynomial(
        sc,
        PolynomialSettings(series, spp=spp, mixture=mix, tile_rows=sc.camera.height),
        seed=3,
        progress=False,
        paths=paths,
    )
    # the eye vertex's MIS entries (what the mixture's samples find on the light) are recorded
    plain: dict = {}
    no_mis = dataclasses.replace(mix, mis=False)
    precompute_polynomial(
        sc,
        PolynomialSettings(series, spp=spp, mixture=no_mis, tile_rows=sc.camera.height),
        seed=3,
        progress=False,
        paths=plain,
    )
    eye = [sum(int((r["bounce"] == 1).sum()) for r in p["rows"]) for p in (paths, plain)]
    assert eye[0] > eye[1] > 0, eye
    check_oracle(sc, T, paths, spp, gen, repeats=2)


def test_lobe_mixture_equals_default_mixture_in_expectation():
    """Same scene, independent seeds: the glossy wall's mean radiance under the default
    material and under a sharp edit (n = 1000, new colours) agrees between the default
    mixture and the lobe mixture (Welch t-test over per-seed means, |t| < 4.5), and the lobe
    mixture's spread under the sharp edit is smaller."""
    sc = glossy_box(8)
    back = sc.object_id("back")
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    edit = {"type": "blinn_phong", "kd": (0.05, 0.04, 0.03), "ks": (0.5, 0.6, 0.7), "exponent": 1000.0}
    stats: dict = {}
    for name, mix in (("default", None), ("lobes", LobeMixture())):
        rows = []
        for seed in range(12):
            T = precompute_polynomial(
                sc, PolynomialSettings("8,1,1", spp=16, mixture=mix), seed=100 + seed, progress=False
            )
            wall = T.guides.object_id == back
            R = PolynomialRenderer(T, mats, dtype=torch.float64)
            a = R.evaluate()[wall].mean()
            R.set_material("back", edit)
            rows.append(torch.stack([a, R.evaluate()[wall].mean()]))
        stats[name] = torch.stack(rows)
    a, b = stats["default"], stats["lobes"]
    se = (a.var(0) / a.shape[0] + b.var(0) / b.shape[0]).sqrt()
    t = (a.mean(0) - b.mean(0)) / se
    assert bool((t.abs() < 4.5).all()), (t, a.mean(0), b.mean(0))
    assert float(b[:, 1].std()) < float(a[:, 1].std()), (a[:, 1].std(), b[:, 1].std())
