"""The compiled relighting frame (transport/csrc/relight.c) against its torch twin,
``TripleProductRenderer.shade_torch``, on small generated scenes.

The two make the same decisions (levels, block cases, entries read: their counters are compared
exactly) and the same products with the sums in another order and the Phong lobe from the
kernel's own log/exp polynomials instead of torch's (vectorised) libm: the radiance agrees to
float32 rounding. The tolerance, 2e-5 of each vertex's largest channel, is ~50x the differences
seen (3e-7) and far below the rule's own error (the PSNR of the frame against the standard basis
is ~60 dB, 1e-3); it never depends on the last ulp of either side's math. The decisions do not
either: the scenes are checked to have no (vertex, block) pair within 1e-4 rad of one of the
rule's angles, where a rounding difference could choose another level.
"""

from __future__ import annotations

import math

import pytest
import torch

from tests.render.test_triple import EYE, sky
from tests.transport.test_visibility import ball_on_plane
from torch_brdf.brdf.analytic import Phong, WardAniso
from torch_brdf.brdf.base import Lambert
from torch_brdf.errors import ValueRangeError
from torch_brdf.render import _relight
from torch_brdf.render.triple import FixedRule, GenericRule, PhongRule, TripleProductRenderer
from torch_brdf.transport import _native
from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

pytestmark = pytest.mark.skipif(_native.library() is None, reason="no compiled kernel (no C compiler)")

TOL = 2e-5
MATERIALS = {
    "lambert": lambda: Lambert((0.6, 0.5, 0.4)),
    "phong_broad": lambda: Phong(0.3, 0.5, 12.0),  # below the first cut: 4 or 1 coefficients
    "phong_mid": lambda: Phong((0.2, 0.3, 0.1), (0.5, 0.4, 0.6), 120.0),  # 16, 4 or 1
    "phong_sharp": lambda: Phong(0.1, 0.8, 600.0),  # 256, 16 or 1
}


@pytest.fixture(scope="module")
def scene():
    sc = ball_on_plane(quads=8)
    sc.lights[:] = [sky()]
    return sc


@pytest.fixture(scope="module", params=[0, 2], ids=["binary", "graded"])
def vis(scene, request):
    bits = request.param
    settings = VisibilitySettings(resolution=32, chunk=64, supersample=2 if bits else 1, bits=bits)
    return precompute_visibility(scene, settings, progress=False)


def renderer(scene, vis, box, floor) -> TripleProductRenderer:
    r = TripleProductRenderer(scene, vis, dtype=torch.float32)
    r.set_material("box", MATERIALS[box]())
    r.set_material("floor", MATERIALS[floor]())
    return r


def angle_margin(r: TripleProductRenderer, view, rule: PhongRule) -> float:
    """The smallest distance (rad, float64) of a non-occluded pair's angle to the rule's angles."""
    _, a0, a1 = _relight.level_table(r, rule)
    _nrm, f, wo, _ = r._frames(view)
    c = r.geometry.centers  # (NB, 3) float64
    loc = torch.stack([f.s.double() @ c.T, f.t.double() @ c.T, f.n.double() @ c.T], -1)  # (P, NB, 3)
    z = loc[..., 2:3]
    lifted = torch.cat((loc[..., :2], z.clamp_min(1e-4)), -1)
    loc = torch.where(z > 1e-4, loc, lifted / lifted.norm(dim=-1, keepdim=True))
    w = wo.double()[:, None]
    alpha = torch.acos((-loc[..., 0] * w[..., 0] - loc[..., 1] * w[..., 1] + loc[..., 2] * w[..., 2]).clamp(-1, 1))
    alpha = alpha[view.blocks.states != 0]
    return float(torch.minimum((alpha - a0).abs(), (alpha - a1).abs()).min())


def compare(r, view, rule):
    ref, s_ref = r.shade_torch(view, rule, progress=False)
    got, s_got = r.shade_compiled(view, rule)
    assert got.dtype == ref.dtype and got.shape == ref.shape
    scale = ref.abs().amax(-1, keepdim=True).clamp_min(1e-30)
    err = float(((got - ref).abs() / scale).max())
    assert err <= TOL, f"compiled frame differs from the torch path by {err:.2e} of a vertex's radiance"
    assert s_got.as_dict() == s_ref.as_dict()  # the same levels, cases, samples and entries
    return ref, s_ref


@pytest.mark.parametrize(("box", "floor"), [("phong_mid", "lambert"), ("phong_sharp", "phong_broad")])
def test_compiled_frame_equals_torch_path_appendix_a(scene, vis, box, floor):
    r = renderer(scene, vis, box, floor)
    for scale in (None, 2.5):
        rule = PhongRule(scale=scale)
        view = r.all_vertices(EYE)
        assert angle_margin(r, view, rule) > 1e-4  # no decision within rounding of an angle
        _, stats = compare(r, view, rule)
        assert stats.cases["line6"] and stats.cases["line9"] and stats.cases["line11"]
    levels = {k for k, v in stats.sampling.items() if v}
    assert levels == ({"1", "4", "16", "256"} if box == "phong_sharp" else {"1", "4", "16"})


@pytest.mark.parametrize("level", [1, 2, 4, 16])
def test_compiled_frame_equals_torch_path_fixed_levels(scene, vis, level):
    r = renderer(scene, vis, "phong_mid", "phong_broad")
    compare(r, r.all_vertices(EYE), FixedRule(level))


def test_compiled_frame_in_a_camera_view_and_rotated_lighting(scene, vis):
    r = renderer(scene, vis, "phong_sharp", "lambert")
    view = r.view()
    assert 0 < len(view.vertex_ids) < len(r.positions)  # culled
    compare(r, view, r.rule)
    r.set_lighting(r.envmap.rotated(1.3))  # the kernel's lighting follows
    compare(r, view, r.rule)


def test_threads_do_not_change_the_frame(scene, vis, monkeypatch):
    r = renderer(scene, vis, "phong_sharp", "phong_broad")
    view = r.all_vertices(EYE)
    monkeypatch.setattr(_relight, "CHUNK", 7)  # many ranges, uneven
    r.threads = 1
    one, s1 = r.shade_compiled(view)
    r.threads = 3
    three, s3 = r.shade_compiled(view)
    assert torch.equal(one, three) and s1.as_dict() == s3.as_dict()  # vertices are independent


def test_shade_chooses_the_path(scene, vis):
    r = renderer(scene, vis, "phong_mid", "lambert")
    assert r.frame_path() == "compiled"
    assert r.frame_path(GenericRule()) == "torch"
    r.set_material("box", WardAniso(0.3, 0.4, 0.08, 0.3))
    assert r.frame_path(FixedRule(4)) == "torch"
    r.compiled = True
    with pytest.raises(ValueRangeError, match="WardAniso"):
        r.shade(r.all_vertices(EYE))
    r.compiled = False
    r.set_material("box", MATERIALS["phong_mid"]())
    assert r.frame_path() == "torch"
    d = TripleProductRenderer(scene, vis, dtype=torch.float64)
    assert d.frame_path() == "torch" and "dtype" in _relight.unsupported(d, d.rule)


def test_shade_without_the_kernel_takes_the_torch_path(scene, vis, monkeypatch):
    r = renderer(scene, vis, "phong_mid", "lambert")
    view = r.all_vertices(EYE)
    ref, _ = r.shade_torch(view, progress=False)
    monkeypatch.setattr(_native, "library", lambda: None)
    assert r.frame_path() == "torch"
    assert torch.equal(r.shade(view, progress=False)[0], ref)


@pytest.mark.parametrize("exponent", [1.0, 20.0, 200.0, 1e4])
def test_phong_lobe_polynomials(exponent):
    """The kernel's lobe against float64 math, wherever it is above float32's normal range:
    within 3e-6 + 2e-7 |y| relative, y = n log1p(-omc) (float32's own rounding of y, 6e-8 |y|,
    is as large: torch's float32 lobe has the same error), 0 past omc = 1."""
    omc = torch.cat([torch.logspace(-9, 0, 4001, dtype=torch.float64), torch.tensor([0.0, 1.0, 1.5])])
    omc32 = omc.float()
    ref = torch.exp(exponent * torch.log1p(-omc32.double().clamp(0, 1 - 2**-23)))
    ref = torch.where(omc32.double() < 1, ref, torch.zeros((), dtype=torch.float64))
    got = _relight.phong_lobe(omc32, exponent).double()
    normal = ref > 1e-37
    y = (exponent * torch.log1p(-omc32.double().clamp(0, 1 - 2**-23))).abs()
    excess = ((got - ref).abs() / ref - 2e-7 * y)[normal]
    assert float(excess.max()) < 3e-6
    assert float(torch.cat([(got - ref)[~normal].abs(), torch.zeros(1, dtype=torch.float64)]).max()) < 1e-37
    assert got[-2:].eq(0).all()


def test_lobe_equals_phong_model_to_rounding():
    b = Phong(0.0, 1.0, 300.0).requires_grad_(False)
    g = torch.Generator().manual_seed(3)
    wi = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=-1)
    wi[:, 2] = wi[:, 2].abs()
    wo = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=-1)
    wo[:, 2] = wo[:, 2].abs() + 0.1
    wo = torch.nn.functional.normalize(wo, dim=-1)
    ref = b.eval_local(wi.double(), wo.double())[:, 0]
    omc = Phong._one_minus_cos_alpha(wi.double(), wo.double())
    got = (302.0 / (2 * math.pi)) * _relight.phong_lobe(omc.float(), 300.0).double()
    keep = ref > 1e-30
    assert float(((got - ref).abs() / ref)[keep].max()) < 2e-4  # float32 omc rounding times n
