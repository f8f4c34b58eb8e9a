"""The numerical extremes: one case per cell of the report's extremes table.

Rows are the renderers and solvers (the GI-editing polynomial renderer, the all-frequency
relighting renderer, the reference path tracer, the GPLVM fit, the QP solver); columns are the
extremes: near-mirror lobes (n = 1e4; 1e5 is refused: Blinn-Phong and Phong exponents lie in
[1e-3, 1e4]), grazing view and light, albedo 0 and 1, float32 vs
float64, ill-conditioned GPLVM kernels, near-singular QPs, a very bright sun (dynamic range
1e6), tiny and huge scenes (scale 1e-3 and 1e3). Every cell either stays finite with an error
below its stated bound, or raises a clear :mod:`torch_brdf.errors` exception (the case says
which it expects).

:data:`CASES` lists the cells and :func:`evaluate` runs one; ``test_extreme`` parametrises over
them, and ``benchmarks/extremes.py`` calls the same :func:`evaluate` on every case to print the
table that ``torch-brdf report`` renders, so no cell of that table is filled by hand. The small
scenes and helpers are the existing tests' (``glossy_box``, ``ball_on_plane``, the triple-product
``renderer``, the manifold ``small_family``, the QP ``_problem``).
"""

from __future__ import annotations

import math
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache

import pytest
import torch

from tests.inverse.test_qp import _problem
from tests.manifold.common import small_family
from tests.render.test_triple import EYE, renderer, sky
from tests.transport.test_polynomial import glossy_box
from tests.transport.test_visibility import ball_on_plane
from torch_brdf.brdf.analytic import Phong
from torch_brdf.brdf.base import Lambert
from torch_brdf.errors import TorchBRDFError
from torch_brdf.inverse.qp import solve_qp
from torch_brdf.linalg import JitterWarning
from torch_brdf.manifold.gplvm import GPLVM, fit_gplvm, gram
from torch_brdf.metrics import relative_rmse
from torch_brdf.render.polynomial import PolynomialRenderer, emitter_mask
from torch_brdf.render.triple import GenericRule, TripleProductRenderer
from torch_brdf.scene import Camera, Scene, SceneObject
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.scene.lights import AreaLight
from torch_brdf.transport.pathtrace import reference_path_trace
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

F32, F64 = torch.float32, torch.float64


@dataclass
class Outcome:
    """What a case measured: the tensors that must be finite, an error and its bound."""

    values: list[torch.Tensor]
    error: float | None = None
    bound: float | None = None
    note: str = ""


@dataclass(frozen=True)
class Case:
    """One cell: ``row`` (renderer or solver) x ``column`` (the extreme); ``run`` returns an
    :class:`Outcome`; ``expect`` is ``"finite"`` or the name of the :mod:`torch_brdf.errors`
    class it must raise."""

    row: str
    column: str
    run: Callable[[], Outcome] = field(compare=False)
    expect: str = "finite"

    @property
    def id(self) -> str:
        return f"{self.row}/{self.column}"


def _rel(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Relative RMSE of ``a`` against ``b`` in float64."""
    return relative_rmse(a.double(), b.double(), mask)


def _max_rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| / max |b| in float64."""
    return float((a.double() - b.double()).abs().max() / b.double().abs().max().clamp_min(1e-300))


# -- the GI-editing polynomial renderer ------------------------------------------------------------
@cache
def _box_tensors():
    """The 8x8 glossy Cornell box (every object editable), series 8,1,1 at 2 spp."""
    return precompute_polynomial(
        glossy_box(8, fixed_box=False), PolynomialSettings("8,1,1", spp=2), seed=0, progress=False
    )


def _poly(materials: dict, dtype: torch.dtype, tensors=None) -> torch.Tensor:
    """(H, W, 3) frame with ``materials`` (object name -> material dict; ``"*"`` = every editable object)."""
    T = tensors if tensors is not None else _box_tensors()
    R = PolynomialRenderer(T, dtype=dtype)
    for o, b in zip(T.object_names, T.bases, strict=True):
        mat = materials.get(o, materials.get("*"))
        if b is not None and mat is not None:
            R.set_material(o, mat)
    return R.evaluate()


def _poly_dtypes(materials: dict, bound: float, tensors=None, note: str = "") -> Outcome:
    a, b = _poly(materials, F32, tensors), _poly(materials, F64, tensors)
    return Outcome([a, b], _rel(a, b), bound, note or "float32 frame vs float64 frame (relative RMSE)")


def poly_near_mirror(n: float) -> Outcome:
    mat = {"back": {"type": "blinn_phong", "kd": 0.0, "ks": 1.0, "exponent": n}}
    return _poly_dtypes(mat, 1e-4, note=f"back wall Blinn-Phong n = {n:g} on 8 bands; float32 vs float64")


def poly_albedo(albedo: float) -> Outcome:
    mat = {"*": {"type": "lambert", "albedo": albedo}}
    if albedo == 0.0:  # nothing reflects: only the emitter's own pixels are lit
        img = _poly(mat, F64)
        mask = emitter_mask(_box_tensors())
        return Outcome([img], float(img[mask].abs().max()), 0.0, "largest pixel that sees no emitter (exactly 0)")
    return _poly_dtypes(mat, 1e-4, note="every object Lambert 1; float32 vs float64")


def poly_dtype() -> Outcome:
    return _poly_dtypes({}, 1e-5, note="the scene's materials; float32 vs float64 (relative RMSE)")


def _scaled(sc: Scene, s: float) -> Scene:
    """The scene with geometry and camera scaled by ``s`` (same radiance: the image is the same)."""
    objs = [SceneObject(o.name, o.mesh.copy().apply_scale(s), o.material, o.editable, o.smooth) for o in sc.objects]
    lights = [
        AreaLight(objs[li.object_id].mesh.vertices, objs[li.object_id].mesh.faces, li.radiance, li.object_id)
        if isinstance(li, AreaLight)
        else li
        for li in sc.lights
    ]
    c = sc.camera
    cam = Camera(tuple(s * x for x in c.origin), tuple(s * x for x in c.target), c.up, c.fov_deg, c.width, c.height)
    return Scene(objs, sc.materials, lights, cam, name=f"{sc.name}_x{s:g}", workers=1)


def poly_scale(s: float) -> Outcome:
    T = precompute_polynomial(
        _scaled(glossy_box(8, fixed_box=False), s), PolynomialSettings("8,1,1", spp=2), seed=0, progress=False
    )
    a, b = _poly({}, F64, T), _poly({}, F64)
    mask = emitter_mask(_box_tensors())
    return Outcome([a], _rel(a, b, mask), 0.05, f"scale {s:g} vs scale 1, same seed (relative RMSE)")


def _bright_sky() -> EnvironmentMap:
    """Sky of radiance ~1 with a sun of 1e6 (dynamic range 1e6)."""
    return EnvironmentMap.sky(
        height=32, sun_radiance=1e6, sun_angular_radius_deg=2.0, zenith_color=1.0, horizon_color=1.0
    )


def poly_bright_sun() -> Outcome:
    sc = ball_on_plane(quads=4).with_resolution(12, 9)
    sc.lights[:] = [_bright_sky()]
    T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=2), seed=0, progress=False)
    return _poly_dtypes({}, 1e-4, T, "sun 1e6 x sky, box on plane; float32 vs float64")


def poly_grazing_view() -> Outcome:
    """The camera 1 unit above the Cornell box's floor (550 units wide), looking along it."""
    sc = glossy_box(8, fixed_box=False)
    c = sc.camera
    sc.camera = Camera((278.0, 1.0, -800.0), (278.0, 1.0, 559.0), c.up, c.fov_deg, c.width, c.height)
    T = precompute_polynomial(sc, PolynomialSettings("8,1,1", spp=2), seed=0, progress=False)
    return _poly_dtypes({}, 1e-4, T, "eye 1 unit above the floor; float32 vs float64")


def poly_grazing_light() -> Outcome:
    sc = ball_on_plane(quads=4).with_resolution(12, 9)
    sc.lights[:] = [EnvironmentMap.sky(height=32, sun_direction=(1.0, 0.01, 0.0), sun_angular_radius_deg=2.0)]
    T = precompute_polynomial(sc, PolynomialSettings("4,1", spp=2), seed=0, progress=False)
    return _poly_dtypes({}, 1e-4, T, "sun 0.6 deg above the horizon; float32 vs float64")


def pathtrace_scale(s: float) -> Outcome:
    sc = glossy_box(8, fixed_box=False)
    a = reference_path_trace(_scaled(sc, s), spp=4, max_bounces=3, seed=0, progress=False)
    b = reference_path_trace(sc, spp=4, max_bounces=3, seed=0, progress=False)
    return Outcome([a], _rel(a, b, emitter_mask(_box_tensors())), 0.05, f"scale {s:g} vs scale 1, same seed")


def pathtrace_bright_sun() -> Outcome:
    sc = ball_on_plane(quads=4).with_resolution(12, 9)
    sc.lights[:] = [_bright_sky()]
    a = reference_path_trace(sc, spp=4, max_bounces=2, seed=0, progress=False)
    sc.lights[:] = [EnvironmentMap(_bright_sky().radiance * 1e-6)]
    b = reference_path_trace(sc, spp=4, max_bounces=2, seed=0, progress=False)
    return Outcome([a], _rel(a * 1e-6, b), 1e-4, "sun 1e6 x sky vs the same map scaled by 1e-6 (linearity)")


# -- the all-frequency relighting renderer ---------------------------------------------------------
@cache
def _triple_setup():
    sc = ball_on_plane(quads=8)
    sc.lights[:] = [sky()]
    return sc, precompute_visibility(sc, VisibilitySettings(resolution=32, chunk=64), progress=False)


def _triple(dtype=F64, box="phong", floor="lambert", env: EnvironmentMap | None = None) -> TripleProductRenderer:
    sc, vis = _triple_setup()
    r = renderer(sc, vis, dtype, box=box, floor=floor)
    if env is not None:
        r.set_lighting(env)
    return r


def _triple_vs_standard(r: TripleProductRenderer, bound: float, eye=EYE, note: str = "") -> Outcome:
    view = r.all_vertices(eye)
    ours, _ = r.shade(view, rule=GenericRule())
    ref = r.shade_standard(view)
    return Outcome([ours, ref], _max_rel(ours, ref), bound, note or "max error vs the dense texel sum")


def triple_near_mirror(n: float) -> Outcome:
    r = _triple(box="lambert")
    r.set_material("floor", Phong(0.05, 0.9, n))
    return _triple_vs_standard(r, 0.02, note=f"floor Phong n = {n:g}; max error vs the dense texel sum")


def triple_grazing_view() -> Outcome:
    r = _triple(box="phong", floor="phong")
    return _triple_vs_standard(r, 0.05, eye=(3.0, 0.02, 0.0), note="eye 0.02 above the floor")


def triple_grazing_light() -> Outcome:
    env = EnvironmentMap.sky(height=32, sun_direction=(1.0, 0.01, 0.0), sun_radiance=400.0, sun_angular_radius_deg=2.0)
    return _triple_vs_standard(_triple(floor="phong", env=env), 0.05, note="sun 0.6 deg above the horizon")


def triple_albedo(albedo: float) -> Outcome:
    r = _triple(box="lambert")
    r.set_material("box", Lambert(albedo))
    r.set_material("floor", Lambert(albedo))
    if albedo == 0.0:
        ours, _ = r.shade(r.all_vertices(EYE))
        return Outcome([ours], float(ours.abs().max()), 0.0, "black everywhere (exactly 0)")
    return _triple_vs_standard(r, 1e-6, note="Lambert 1 (one coefficient per block is exact)")


def triple_dtype() -> Outcome:
    a, b = _triple(F32), _triple(F64)
    va, vb = a.all_vertices(EYE), b.all_vertices(EYE)
    x, y = a.shade(va)[0], b.shade(vb)[0]
    return Outcome([x, y], _max_rel(x, y), 1e-4, "float32 vs float64 (max error)")


def triple_bright_sun() -> Outcome:
    return _triple_vs_standard(_triple(F32, floor="phong", env=_bright_sky()), 0.05, note="float32, sun 1e6 x sky")


# -- every BRDF model at exactly theta = 90 degrees ---------------------------------------------------
def _measured(name: str):
    """A small MERL table or NBRDF network of made-up values (the data folder is not needed)."""
    import tempfile
    from pathlib import Path

    import numpy as np

    from torch_brdf.brdf.measured import NBRDF, MERLTabulated
    from torch_brdf.io.merl import write_merl_table

    folder = Path(tempfile.mkdtemp())
    if name == "merl":
        values = torch.rand(1, 3, 3, 2, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
        path = write_merl_table(folder / "t.npz", values, ["x"], [0, 50, 89], [0, 2], [0, 90, 179], "merl-binary")
        return MERLTabulated(path, "x")
    rng = np.random.default_rng(0)
    w = {"names": np.array(["x"])}
    for k, shape in (("W1", (1, 6, 4)), ("b1", (1, 4)), ("W2", (1, 4, 4)), ("b2", (1, 4)), ("W3", (1, 4, 3))):
        w[k] = (0.3 * rng.standard_normal(shape)).astype(np.float32)
    w["b3"] = np.zeros((1, 3), np.float32)
    np.savez(folder / "w.npz", **w)
    return NBRDF("x", folder / "w.npz")


def _grazing_pairs(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs with theta = 90 degrees exactly (z = cos(pi/2), 6e-17, as a caller computes it):
    the grazing mirror pair (the sum is 1e-16 long), grazing to normal and back, grazing to 45
    degrees, at four azimuths."""
    wi, wo = [], []
    for phi in (0.0, 0.5, 1.7, 3.0):
        c, s = math.cos(phi), math.sin(phi)
        for ti, to in ((90, 90), (90, 0), (0, 90), (90, 45), (45, 90)):
            a, b = math.radians(ti), math.radians(to)
            wi.append([math.sin(a) * c, math.sin(a) * s, math.cos(a)])
            wo.append([-math.sin(b) * c, -math.sin(b) * s, math.cos(b)])
    return torch.tensor(wi, dtype=dtype), torch.tensor(wo, dtype=dtype)


def brdf_grazing(name: str, **params) -> Outcome:
    """Model ``name`` (default parameters, or ``params``) at theta = 90 degrees: finite, >= 0,
    float32 = float64."""
    from torch_brdf.brdf import base

    brdf = _measured(name) if name in ("merl", "nbrdf") else base.create(name, **params)
    vals = []
    with torch.no_grad():
        for dt in (F32, F64):
            vals.append(brdf.to(dt).eval(*_grazing_pairs(dt)))
    a, b = vals
    neg = float(torch.clamp(-torch.cat([a.double().flatten(), b.flatten()]), min=0).max())
    if name in ("merl", "nbrdf"):
        # a lookup (or a network of the bin angles): at a bin edge (phi_d = +-pi) the two
        # dtypes may pick neighbouring bins, so only finite, >= 0 and bounded is asked
        bound = 2.0 * float(b.max())
        return Outcome([a, b], max(float(a.max()) - bound, neg), 0.0, f"finite, >= 0; max f {float(b.max()):.3g}")
    return Outcome([a, b], max(_max_rel(a, b), neg), 1e-4, f"float32 vs float64, max f {float(b.max()):.3g}")


def ggx_grazing(roughness: float) -> Outcome:
    """Cook-Torrance GGX at the grazing mirror pair: f = F / (pi alpha^4) (the Smith terms
    give 1/alpha^2 with D = 1/(pi alpha^2)), in float32 and float64."""
    from torch_brdf.brdf.microfacet import CookTorrance

    brdf = CookTorrance("ggx", roughness=roughness, f0=1.0)
    exact = 1.0 / (math.pi * roughness**4)
    vals = []
    with torch.no_grad():
        for dt in (F32, F64):
            z = math.cos(math.pi / 2)
            vals.append(
                brdf.to(dt).eval(torch.tensor([[1.0, 0.0, z]], dtype=dt), torch.tensor([[-1.0, 0.0, z]], dtype=dt))
            )
    err = max(float((v.double() - exact).abs().max()) / exact for v in vals)
    return Outcome(vals, err, 1e-5, f"exact {exact:.4g} (float32 gave 1.7e25 at roughness 1 before)")


# -- the GPLVM manifold fit --------------------------------------------------------------------------
def gplvm(case: str) -> Outcome:
    """Ill-conditioned kernels: duplicated materials, a huge lengthscale (K ~ all ones), mu = 0."""
    obs, _ = small_family(12)
    z = obs.z.double()
    kw: dict = {}
    if "duplicates" in case:
        z = torch.cat([z, z[:4]])
    if "lengthscale" in case:
        kw["lengthscale"] = 1e4
    if "mu0" in case:
        kw["mu"] = 0.0
    s, d = gram(z)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", JitterWarning)
        fit = fit_gplvm(s, d, 2, max_iter=30, generator=torch.Generator().manual_seed(0), **kw)
        model = GPLVM(fit, z)
        w = model.weights(model.latents[:2] + 0.01)
    drop = float((fit.loglik[:-1] - fit.loglik[1:]).clamp_min(0).max() / fit.loglik.abs().max())
    return Outcome(
        [fit.latents, fit.loglik, w], drop, 1e-12, f"largest log-likelihood decrease (jitter {fit.jitter:.1e})"
    )


def gplvm_dtype() -> Outcome:
    obs, _ = small_family(16)
    fits = []
    for dt in (F32, F64):
        s, d = gram(obs.z.to(dt))
        fits.append(fit_gplvm(s, d, 2, max_iter=20, generator=torch.Generator().manual_seed(0)))
    a, b = fits
    return Outcome([a.latents, b.latents], _max_rel(a.latents, b.latents), 1e-6, "float32 vs float64 data: latents")


# -- the QP solver of inverse design --------------------------------------------------------------------
def qp_near_singular(h_value: float | None) -> Outcome:
    """Rank-deficient H (zero and duplicated columns); ``h_value`` replaces the energy bound
    (1e-9: rho_d -> 1, a near-LP; negative: infeasible)."""
    H, f, G, h = _problem(torch.Generator().manual_seed(1), n=150, singular=True)
    if h_value is not None:
        h = torch.full_like(h, h_value)
    ip = solve_qp(H, f, G, h, method="interior_point", tol=1e-14)
    ad = solve_qp(H, f, G, h, method="admm")
    gap = abs(ad.objective - ip.objective) / max(abs(ip.objective), 1e-300)
    viol = max(ip.violation, ad.violation) / max(float(h.abs().max()), 1e-300)
    return Outcome([ip.x, ad.x], max(gap, viol), 1e-6, "interior point vs ADMM objective; violation relative to h")


def qp_cond() -> Outcome:
    """A positive definite H with condition number 1e12."""
    g = torch.Generator().manual_seed(2)
    q, _ = torch.linalg.qr(torch.randn(40, 40, generator=g, dtype=F64))
    H = q @ torch.diag(torch.logspace(0, -12, 40, dtype=F64)) @ q.T
    H = (H + H.T) / 2
    f = torch.rand(40, generator=g, dtype=F64)
    G = torch.ones(1, 40, dtype=F64)
    h = torch.ones(1, dtype=F64)
    ip = solve_qp(H, f, G, h, tol=1e-12)
    ad = solve_qp(H, f, G, h, method="admm")
    gap = abs(ad.objective - ip.objective) / max(abs(ip.objective), 1e-300)
    return Outcome([ip.x, ad.x], gap, 1e-6, "cond(H) = 1e12: interior point vs ADMM objective")


#: every registered BRDF model (the extremes table has a cell for each)
_MODELS = (
    "ashikhmin_shirley",
    "blinn_phong",
    "cook_torrance",
    "distribution_based",
    "factored_1d",
    "factored_1d_fresnel",
    "lambert",
    "merl",
    "metallic_roughness",
    "nbrdf",
    "phong",
    "rough_plastic",
    "ward",
    "ward_aniso",
)

#: the cells, by renderer or solver: (extreme, run[, the errors class it must raise])
_CELLS: dict[str, list[tuple]] = {
    "polynomial (GI editing)": [
        ("near-mirror n=1e4", lambda: poly_near_mirror(1e4)),
        ("near-mirror n=1e5", lambda: poly_near_mirror(1e5), "ValueRangeError"),
        ("grazing view", poly_grazing_view),
        ("grazing light", poly_grazing_light),
        ("albedo 0", lambda: poly_albedo(0.0)),
        ("albedo 1", lambda: poly_albedo(1.0)),
        ("float32 vs float64", poly_dtype),
        ("sun 1e6", poly_bright_sun),
        ("scale 1e-3", lambda: poly_scale(1e-3)),
        ("scale 1e3", lambda: poly_scale(1e3)),
    ],
    "path tracer (reference)": [
        ("sun 1e6", pathtrace_bright_sun),
        ("scale 1e-3", lambda: pathtrace_scale(1e-3)),
        ("scale 1e3", lambda: pathtrace_scale(1e3)),
    ],
    "triple product (relighting)": [
        ("near-mirror n=1e4", lambda: triple_near_mirror(1e4)),
        ("near-mirror n=1e5", lambda: triple_near_mirror(1e5), "ValueRangeError"),
        ("grazing view", triple_grazing_view),
        ("grazing light", triple_grazing_light),
        ("albedo 0", lambda: triple_albedo(0.0)),
        ("albedo 1", lambda: triple_albedo(1.0)),
        ("float32 vs float64", triple_dtype),
        ("sun 1e6", triple_bright_sun),
    ],
    "BRDF models (theta = 90 deg)": [
        *((f"{name}, float32 and float64", lambda name=name: brdf_grazing(name)) for name in _MODELS),
        ("cook_torrance roughness 0.01", lambda: brdf_grazing("cook_torrance", roughness=0.01, f0=1.0)),
        (
            "metallic_roughness metal, roughness 0.01",
            lambda: brdf_grazing("metallic_roughness", metallic=1.0, roughness=0.01),
        ),
        ("cook_torrance GGX roughness 1, mirror pair", lambda: ggx_grazing(1.0)),
        ("cook_torrance GGX roughness 1e-4, mirror pair", lambda: ggx_grazing(1e-4)),
    ],
    "GPLVM (manifold)": [
        ("duplicated materials", lambda: gplvm("duplicates")),
        ("lengthscale 1e4", lambda: gplvm("lengthscale")),
        ("duplicates, mu = 0", lambda: gplvm("duplicates_mu0")),
        ("float32 vs float64", gplvm_dtype),
    ],
    "QP (inverse design)": [
        ("rank-deficient H", lambda: qp_near_singular(None)),
        ("cond(H) = 1e12", qp_cond),
        ("rho_d -> 1 (h = 1e-9)", lambda: qp_near_singular(1e-9)),
        ("infeasible (h < 0)", lambda: qp_near_singular(-1e-3), "InfeasibleError"),
    ],
}
CASES: list[Case] = [Case(row, col, fn, *expect) for row, cells in _CELLS.items() for col, fn, *expect in cells]


def evaluate(case: Case) -> dict:
    """Run one case. Returns a JSON-ready dict: ``row``, ``column``, ``expect``, ``status``
    (``"finite"``, the raised :mod:`torch_brdf.errors` class name, ``"non-finite"`` or
    ``"crash: <type>"``), ``ok`` (status is what the case expects and the error is within its
    bound), ``error``, ``bound``, ``note`` (the exception message for a raise). Timing belongs to the caller
    (``benchmarks/extremes.py`` adds ``seconds``)."""
    out = {"row": case.row, "column": case.column, "expect": case.expect, "error": None, "bound": None}
    try:
        res = case.run()
    except TorchBRDFError as exc:
        out.update(status=type(exc).__name__, note=str(exc).splitlines()[0][:200])
    except Exception as exc:
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        out.update(status=f"crash: {type(exc).__name__}", note=tb[:300])
    else:
        finite = all(bool(torch.isfinite(v).all()) for v in res.values)
        err_ok = res.error is not None and math.isfinite(res.error)
        out.update(
            status="finite" if finite and err_ok else "non-finite",
            error=res.error if err_ok else None,
            bound=res.bound,
            note=res.note,
        )
    within = out["error"] is None or out["bound"] is None or out["error"] <= out["bound"]
    out["ok"] = out["status"] == case.expect and (case.expect != "finite" or within)
    return out


def test_every_model_has_a_grazing_cell():
    from torch_brdf.brdf import base

    assert sorted(_MODELS) == sorted(base.available())


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_extreme(case):
    cell = evaluate(case)
    assert cell["ok"], cell
