r"""Take a material out of torch_brdf: Mitsuba 3 XML (stock plugins only), glTF 2.0 materials,
MERL ``.binary`` tables, and whole scenes as Mitsuba XML or glTF with replaced materials.

Any BRDF the library holds is accepted (a :class:`~torch_brdf.brdf.base.BRDF` module or a
scene material dict): analytic models, edited band curves
(:class:`~torch_brdf.brdf.bands.Factored1D`), the BRDFs of a strokes or ``fit_image`` fit,
a GPLVM latent point (its ``merl`` material dict), MERL tables and NBRDFs.

What is exact (written directly) and what is fitted:

==========================  =========================================  ===========================
source                      Mitsuba 3 XML                              glTF 2.0
==========================  =========================================  ===========================
``lambert``                 ``diffuse`` (exact)                        exact (see below)
``metallic_roughness``      ``principled`` (fitted: separable         ``pbrMetallicRoughness`` (exact)
                            masking; Disney's diffuse for
                            dielectrics)
``cook_torrance`` GGX,      ``roughconductor`` (exact)                 fitted
:math:`F_0 = 1`, no diffuse
``rough_plastic``           ``roughplastic`` (exact);                  fitted
                            ``smooth``: ``plastic`` (exact)
anything else               fitted: ``diffuse``, ``roughconductor``,   fitted metallic-roughness
                            ``principled``, ``blendbsdf`` of diffuse
                            and roughconductor: the best one
==========================  =========================================  ===========================

A Lambert material is written to glTF exactly as metallic 0 with ``KHR_materials_specular``
``specularFactor`` 0 (which removes the dielectric's specular layer).

A fit is the cosine-weighted least-squares fit of :mod:`torch_brdf.export.fit`; its error is
the cosine-weighted relative L2 error of :func:`torch_brdf.brdf.bands.projection_error`. For
Mitsuba the error is re-measured against Mitsuba's own plugin when Mitsuba is installed
(``error_measured_with`` in the report). MERL export tabulates the BRDF on MERL's grid
(bin lower edges, as :func:`~torch_brdf.brdf.measured.tabulate_nbrdf`), which is exact at
those angles and piecewise constant between them.

Every file is written atomically (:func:`torch_brdf.io.atomic.replacing`), with a JSON
report beside it (``<file>.export.json``): format, target model and parameters, whether it
was exact, the fit error and the tolerance. A ``tolerance`` that the best fit does not meet
raises :class:`~torch_brdf.errors.ExportError` and writes nothing.
"""

from __future__ import annotations

import copy
import json
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..brdf import BRDF, CookTorrance, Lambert, MetallicRoughness, RoughPlastic, create
from ..errors import ExportError, TorchBRDFError
from ..frame import half_diff_to_directions
from ..io.atomic import replacing
from ..io.merl import MERL_RES, merl_index_to_angles, write_merl_binary
from .fit import STOCK_MODELS, FitPairs, StockFit, fit_error, fit_stock

__all__ = [
    "FORMATS",
    "STOCK_MODELS",
    "ExportReport",
    "FitPairs",
    "export_material",
    "export_scene_mitsuba",
    "fit_stock",
    "gltf_material",
    "mitsuba_bsdf",
    "replace_gltf_materials",
    "tabulate_merl",
]

#: export formats and their file suffixes
FORMATS = {"mitsuba": ".xml", "gltf": ".gltf", "merl": ".binary"}


@dataclass
class ExportReport:
    """What an export wrote (saved as ``<file>.export.json``).

    Attributes:
        format: ``"mitsuba"``, ``"gltf"`` or ``"merl"``.
        path: the file written.
        source: the source BRDF's model name.
        target: the written model (e.g. ``"principled"``, ``"pbrMetallicRoughness"``, ``"merl"``).
        exact: the target reproduces the source by construction.
        error: cosine-weighted relative L2 error of the written model (0 when exact).
        error_measured_with: how ``error`` was measured.
        tolerance: the user's tolerance, or None.
        params: the written parameters.
        candidates: other fitted models and their errors.
        notes: anything the user should know.
    """

    format: str
    path: str
    source: str
    target: str
    exact: bool
    error: float
    error_measured_with: str
    tolerance: float | None = None
    params: dict = field(default_factory=dict)
    candidates: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)


def as_brdf(material) -> BRDF:
    """A BRDF from a BRDF module or a scene material dict (``{"type": ..., ...}``).

    Raises:
        ExportError: anything else, or a dict the registry refuses.
    """
    if isinstance(material, torch.nn.Module) and hasattr(material, "eval_local"):
        return material
    if isinstance(material, dict):
        try:
            return create(material)
        except TorchBRDFError as exc:
            raise ExportError(f"cannot build the material to export: {exc}") from exc
    raise ExportError(f"expected a BRDF or a material dict to export; got {type(material).__name__}")


def _name_of(brdf) -> str:
    return getattr(brdf, "model_name", type(brdf).__name__)


def _rgb_list(t: torch.Tensor) -> list[float]:
    return [float(x) for x in t.detach().double().reshape(-1).tolist()]


# -- Mitsuba -----------------------------------------------------------------------------------
def _exact_mitsuba(brdf) -> StockFit | None:
    """The stock plugin that reproduces ``brdf`` exactly, or None."""
    with torch.no_grad():
        if type(brdf) is Lambert:
            return StockFit("diffuse", {"reflectance": _rgb_list(brdf.reflectance)}, brdf, 0.0, exact=True)
        if (
            type(brdf) is CookTorrance
            and brdf.distribution == "ggx"
            and bool((brdf.f0 == 1).all())
            and not bool(brdf.kd.any())
        ):
            params = {"alpha": float(brdf.roughness), "specular_reflectance": [1.0, 1.0, 1.0]}
            return StockFit("roughconductor", params, brdf, 0.0, exact=True)
        if type(brdf) is RoughPlastic:
            params = {} if brdf.smooth else {"distribution": brdf.distribution, "alpha": float(brdf.roughness)}
            params.update(
                int_ior=float(brdf.eta),
                ext_ior=1.0,
                diffuse_reflectance=_rgb_list(brdf.diffuse_reflectance),
                specular_reflectance=_rgb_list(brdf.specular_reflectance),
                nonlinear=brdf.nonlinear,
            )
            return StockFit("plastic" if brdf.smooth else "roughplastic", params, brdf, 0.0, exact=True)
    return None


#: what an exact mapping still differs by, per written plugin (the report's notes)
_EXACT_NOTES = {
    "roughplastic": "the same function; Mitsuba integrates the coat's transmittance table by its own rule "
    "(within 0.2% pointwise of ours)",
    "plastic": "Mitsuba's delta coat for our sharp coat lobe; its internal diffuse reflectance is a "
    "polynomial fit (within 1% of ours)",
}


def mitsuba_bsdf(model: str, params: dict, name: str = "material") -> ET.Element:
    """The ``<bsdf>`` element of a stock plugin, wrapped in ``twosided`` (our surfaces are
    two-sided), with ``id=name``.

    Args:
        model: a name of :data:`STOCK_MODELS` (``"diffuse+roughconductor"`` is a
            ``blendbsdf`` of the two).
        params: the parameters (RGB lists or floats) as :class:`StockFit` holds them.
    """
    outer = ET.Element("bsdf", type="twosided", id=name)
    if model == "diffuse+roughconductor":
        blend = ET.SubElement(outer, "bsdf", type="blendbsdf")
        ET.SubElement(blend, "float", name="weight", value=f"{float(params['weight']):.9g}")
        _plugin(blend, "diffuse", {"reflectance": params["reflectance"]})
        _plugin(blend, "roughconductor", {k: params[k] for k in ("alpha", "specular_reflectance")})
    else:
        _plugin(outer, model, params)
    return outer


def _plugin(parent: ET.Element, model: str, params: dict) -> None:
    inner = ET.SubElement(parent, "bsdf", type=model)
    if model == "roughconductor":
        ET.SubElement(inner, "string", name="distribution", value="ggx")
        ET.SubElement(inner, "string", name="material", value="none")
    for key, value in params.items():
        if isinstance(value, bool):
            ET.SubElement(inner, "boolean", name=key, value="true" if value else "false")
        elif isinstance(value, str):
            ET.SubElement(inner, "string", name=key, value=value)
        elif isinstance(value, list | tuple):
            ET.SubElement(inner, "rgb", name=key, value=", ".join(f"{v:.9g}" for v in value))
        else:
            ET.SubElement(inner, "float", name=key, value=f"{float(value):.9g}")


def _mitsuba_error(model: str, params: dict, brdf, pairs: FitPairs) -> float | None:
    """The error of Mitsuba's own plugin against ``brdf`` on ``pairs`` (scalar variant), or
    None without Mitsuba."""
    try:
        import mitsuba as mi
    except ImportError:
        return None
    before = mi.variant()
    scalar = [v for v in mi.variants() if v.startswith("scalar_rgb")]
    if not scalar:
        return None
    try:
        mi.set_variant(scalar[0])
        xml = ET.tostring(mitsuba_bsdf(model, params, "m")[0], encoding="unicode")
        bsdf = mi.load_string(_wrap_bsdf(xml))
        ctx, si = mi.BSDFContext(), mi.SurfaceInteraction3f()
        vals = []
        for a, b in zip(pairs.wo.tolist(), pairs.wi.tolist(), strict=True):
            si.wi = mi.Vector3f(*a)
            vals.append(list(bsdf.eval(ctx, si, mi.Vector3f(*b))))
        g = torch.tensor(vals, dtype=torch.float64) / pairs.wi[:, 2:]
        with torch.no_grad():
            f = brdf.eval_local(pairs.wi.to(_dt(brdf)), pairs.wo.to(_dt(brdf))).double()
        return fit_error(f, g, pairs.weight)
    finally:
        if before is not None and before != mi.variant():
            mi.set_variant(before)


def _wrap_bsdf(inner_xml: str) -> str:
    # a bare <bsdf> element loads as the plugin itself (Mitsuba's load_string needs a version)
    return inner_xml.replace("<bsdf ", '<bsdf version="3.0.0" ', 1)


def _dt(brdf) -> torch.dtype:
    p = next(iter(brdf.parameters()), None) if isinstance(brdf, torch.nn.Module) else None
    return torch.float64 if p is None else p.dtype


def _mitsuba_choice(brdf, tolerance: float | None, models: tuple[str, ...]) -> tuple[StockFit, dict, str, list]:
    exact = _exact_mitsuba(brdf)
    notes = []
    if exact is not None:
        notes += [_EXACT_NOTES[exact.model]] if exact.model in _EXACT_NOTES else []
        return exact, {}, "exact mapping", notes
    pairs = FitPairs.build(brdf)
    fits = fit_stock(brdf, models, pairs)
    checked = {f.model: _mitsuba_error(f.model, f.params, brdf, pairs) for f in fits}
    measured = {f.model: f.error if checked[f.model] is None else checked[f.model] for f in fits}
    if all(v is not None for v in checked.values()):
        how = "Mitsuba 3 (scalar_rgb) evaluating the written plugin on the fit's pairs"
    else:
        how = "the torch stand-in of the plugin (Mitsuba not installed)"
    best = min(fits, key=lambda f: measured[f.model])
    cands = {f.model: {"error": measured[f.model], "proxy_error": f.error} for f in fits}
    best = StockFit(best.model, best.params, best.proxy, measured[best.model])
    return best, cands, how, notes


def _check_tolerance(error: float, tolerance: float | None, what: str) -> None:
    if tolerance is not None and not error <= tolerance:
        raise ExportError(
            f"{what}: the best fit has error {error:.4g} (cosine-weighted relative L2), above the "
            f"tolerance {tolerance:g}; nothing was written"
        )


def _write_text(path: Path, text: str) -> None:
    try:
        with replacing(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as exc:
        raise ExportError(f"cannot write {path}: {exc.strerror or exc}") from exc


def _write_report(report: ExportReport) -> None:
    _write_text(Path(report.path + ".export.json"), report.to_json() + "\n")


def _xml_text(root: ET.Element) -> str:
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


# -- glTF --------------------------------------------------------------------------------------
def gltf_material(brdf, name: str = "material", tolerance: float | None = None) -> tuple[dict, ExportReport]:
    """A glTF 2.0 material dict for ``brdf`` and the report of how it was made.

    ``metallic_roughness`` is written exactly; ``lambert`` exactly as metallic 0 with
    ``KHR_materials_specular`` (``specularFactor`` 0 removes the dielectric's specular
    layer); anything else as the least-squares fit of the metallic-roughness model.

    Raises:
        ExportError: the fit's error exceeds ``tolerance``.
    """
    brdf = as_brdf(brdf)
    notes = []
    ext = {}
    if type(brdf) is MetallicRoughness:
        mr, exact, err, how = brdf, True, 0.0, "exact mapping"
    elif type(brdf) is Lambert:
        mr = MetallicRoughness(brdf.reflectance.detach(), 0.0, 1.0)
        exact, err, how = True, 0.0, "exact mapping"
        ext = {"KHR_materials_specular": {"specularFactor": 0.0}}
    else:
        fit = fit_stock(brdf, ("principled",))[0]
        mr, exact, err, how = fit.proxy, False, fit.error, "cosine-weighted least squares (the glTF model itself)"
    _check_tolerance(err, tolerance, f"glTF export of {_name_of(brdf)}")
    pbr = {
        "baseColorFactor": [*_rgb_list(mr.base_color), 1.0],
        "metallicFactor": float(mr.metallic.detach()),
        "roughnessFactor": float(mr.roughness.detach()),
    }
    mat = {"name": name, "pbrMetallicRoughness": pbr}
    if ext:
        mat["extensions"] = ext
    report = ExportReport(
        "gltf", "", _name_of(brdf), "pbrMetallicRoughness", exact, err, how, tolerance, mat, {}, notes
    )
    return mat, report


def read_gltf_material(mat: dict) -> BRDF:
    """The BRDF of a glTF material written by :func:`gltf_material` (factors only): the
    metallic-roughness model, or Lambert for metallic 0 with ``specularFactor`` 0."""
    pbr = mat.get("pbrMetallicRoughness", {})
    c = pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0])[:3]
    m, r = float(pbr.get("metallicFactor", 1.0)), float(pbr.get("roughnessFactor", 1.0))
    spec = mat.get("extensions", {}).get("KHR_materials_specular", {})
    if m == 0.0 and float(spec.get("specularFactor", 1.0)) == 0.0:
        return Lambert(c)
    return MetallicRoughness(c, m, r)


def replace_gltf_materials(
    src: str | os.PathLike, dst: str | os.PathLike, materials: dict[str, Any], tolerance: float | None = None
) -> list[ExportReport]:
    """Re-write the glTF ``src`` as ``dst`` with the named materials replaced (everything else,
    buffers and textures included, kept as it is; textures of a replaced material are dropped
    from it, since the factors now carry the material).

    Args:
        src, dst: ``.gltf`` files (JSON; buffers referenced by relative URI stay valid when
            ``dst`` is in the same folder).
        materials: glTF material name -> BRDF or material dict.
    Raises:
        ExportError: a name that is not a material of ``src``, a fit above the tolerance,
            or an unreadable / unwritable file.
    """
    src, dst = Path(src), Path(dst)
    try:
        doc = json.loads(src.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ExportError(f"cannot read the glTF file {src}: {exc}") from exc
    mats = doc.get("materials", [])
    names = [m.get("name") for m in mats]
    unknown = [n for n in materials if n not in names]
    if unknown:
        raise ExportError(f"{src}: no material named {unknown}; its materials: {names}")
    reports = []
    used_ext = set(doc.get("extensionsUsed", []))
    for key, brdf in materials.items():
        mat, rep = gltf_material(brdf, key, tolerance)
        mats[names.index(key)] = mat
        used_ext.update(mat.get("extensions", {}))
        rep.path = str(dst)
        reports.append(rep)
    if used_ext:
        doc["extensionsUsed"] = sorted(used_ext)
    _write_text(dst, json.dumps(doc, indent=2) + "\n")
    _write_text(Path(str(dst) + ".export.json"), json.dumps([asdict(r) for r in reports], indent=2) + "\n")
    return reports


# -- MERL --------------------------------------------------------------------------------------
def tabulate_merl(brdf, chunk: int = 1 << 18) -> torch.Tensor:
    """``brdf`` on MERL's grid, (3, 90, 90, 180) float64, at the bins' lower-edge angles
    (:func:`~torch_brdf.io.merl.merl_index_to_angles`), :math:`\\phi_h = 0`; bins whose
    directions are at or below the horizon are -1 (MERL's missing-bin marker)."""
    brdf = copy.deepcopy(as_brdf(brdf)).double()  # the table holds float64
    th, td, pd = merl_index_to_angles(*(torch.arange(n) for n in MERL_RES), at="lower", dtype=torch.float64)
    out = torch.empty(*MERL_RES, 3, dtype=torch.float64)
    dt = _dt(brdf)
    rows = max(1, chunk // (MERL_RES[1] * MERL_RES[2]))
    with torch.no_grad():
        for s in range(0, MERL_RES[0], rows):
            TH, TD, PD = torch.meshgrid(th[s : s + rows], td, pd, indexing="ij")
            wi, wo = half_diff_to_directions(TH, torch.zeros_like(TH), TD, PD)
            f = brdf.eval_local(wi.to(dt), wo.to(dt)).double()
            below = (wi[..., 2] <= 0) | (wo[..., 2] <= 0)
            out[s : s + rows] = torch.where(below.unsqueeze(-1), torch.full_like(f, -1.0), f)
    return out.permute(3, 0, 1, 2).contiguous()


# -- the one entry point -----------------------------------------------------------------------
def export_material(
    material,
    path: str | os.PathLike,
    fmt: str | None = None,
    tolerance: float | None = None,
    name: str = "material",
    models: tuple[str, ...] = STOCK_MODELS,
) -> ExportReport:
    """Export one material to ``path`` and write its report beside it.

    Args:
        material: a BRDF or a scene material dict.
        path: the file; its folder must exist.
        fmt: ``"mitsuba"``, ``"gltf"`` or ``"merl"`` (None: from the suffix, :data:`FORMATS`).
        tolerance: the largest fit error accepted (cosine-weighted relative L2); None: any.
        name: the material's id / name in the file.
        models: the stock Mitsuba models a fit may use.
    Returns:
        the :class:`ExportReport` (also written as ``<path>.export.json``).
    Raises:
        ExportError: an unknown format, a fit above ``tolerance``, an unwritable path.
    """
    path = Path(path)
    if fmt is None:
        fmt = next((k for k, v in FORMATS.items() if path.suffix.lower() == v), None)
        if fmt is None:
            raise ExportError(f"cannot tell the format of {path} from its suffix; use one of {FORMATS}")
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; available: {list(FORMATS)}")
    if not path.parent.is_dir():
        raise ExportError(f"cannot write {path}: folder {path.parent} does not exist")
    brdf = as_brdf(material)
    if fmt == "mitsuba":
        best, cands, how, notes = _mitsuba_choice(brdf, tolerance, models)
        _check_tolerance(best.error, tolerance, f"Mitsuba export of {_name_of(brdf)}")
        root = ET.Element("scene", version="3.0.0")
        root.append(mitsuba_bsdf(best.model, best.params, name))
        _write_text(path, _xml_text(root))
        report = ExportReport(
            "mitsuba", str(path), _name_of(brdf), best.model, best.exact, best.error, how, tolerance,
            best.params, cands, notes,
        )  # fmt: skip
    elif fmt == "gltf":
        mat, report = gltf_material(brdf, name, tolerance)
        doc = {"asset": {"version": "2.0", "generator": "torch_brdf"}, "materials": [mat]}
        if "extensions" in mat:
            doc["extensionsUsed"] = sorted(mat["extensions"])
        _write_text(path, json.dumps(doc, indent=2) + "\n")
        report.path = str(path)
    else:
        table = tabulate_merl(brdf)
        try:
            write_merl_binary(path, table)
        except OSError as exc:
            raise ExportError(f"cannot write {path}: {exc.strerror or exc}") from exc
        report = ExportReport(
            "merl", str(path), _name_of(brdf), "merl", True, 0.0,
            "tabulated at the bins' lower-edge angles (exact there; piecewise constant between)",
            tolerance, {"resolution": list(MERL_RES)}, {},
            ["bins at or below the horizon hold -1 (missing)"],
        )  # fmt: skip
    _write_report(report)
    return report


# -- scenes ------------------------------------------------------------------------------------
def _vec(x) -> str:
    return ", ".join(f"{float(v):.9g}" for v in x)


def export_scene_mitsuba(
    scene,
    path: str | os.PathLike,
    tolerance: float | None = None,
    spp: int = 64,
    max_bounces: int = 4,
) -> list[ExportReport]:
    """Write ``scene`` as a Mitsuba 3 XML scene with stock plugins only: meshes as ``.ply``
    files in ``<stem>_meshes/`` (vertex normals for smooth objects), every material as in
    :func:`export_material`, area lights as ``area`` emitters on their shapes, directional
    lights, environment maps (``envmap`` of an EXR written beside the scene; Mitsuba's
    bilinear lookup differs from ours by ~0.5% on a sky map) and the camera (``perspective``,
    vertical fov, ``lookat``), with a ``path`` integrator of ``max_depth = max_bounces + 1``.

    Returns:
        one report per material (also written to ``<path>.export.json``).
    Raises:
        ExportError: a light without a stock equivalent, a fit above ``tolerance``, an
            unwritable path.
    """
    from ..io import write_exr
    from ..scene.envmap import EnvironmentMap
    from ..scene.lights import AreaLight, DirectionalLight

    path = Path(path)
    if not path.parent.is_dir():
        raise ExportError(f"cannot write {path}: folder {path.parent} does not exist")
    mesh_dir = path.parent / f"{path.stem}_meshes"
    root = ET.Element("scene", version="3.0.0")
    integ = ET.SubElement(root, "integrator", type="path")
    ET.SubElement(integ, "integer", name="max_depth", value=str(int(max_bounces) + 1))
    cam = scene.camera
    sensor = ET.SubElement(root, "sensor", type="perspective")
    ET.SubElement(sensor, "string", name="fov_axis", value="y")
    ET.SubElement(sensor, "float", name="fov", value=f"{float(cam.fov_deg):.9g}")
    tw = ET.SubElement(sensor, "transform", name="to_world")
    ET.SubElement(tw, "lookat", origin=_vec(cam.origin), target=_vec(cam.target), up=_vec(cam.up))
    sampler = ET.SubElement(sensor, "sampler", type="independent")
    ET.SubElement(sampler, "integer", name="sample_count", value=str(int(spp)))
    film = ET.SubElement(sensor, "film", type="hdrfilm")
    ET.SubElement(film, "integer", name="width", value=str(cam.width))
    ET.SubElement(film, "integer", name="height", value=str(cam.height))
    ET.SubElement(film, "rfilter", type="box")
    reports = []
    for key in sorted({o.material for o in scene.objects}):
        brdf = as_brdf(scene.materials[key])
        best, cands, how, notes = _mitsuba_choice(brdf, tolerance, STOCK_MODELS)
        _check_tolerance(best.error, tolerance, f"material {key!r}")
        root.append(mitsuba_bsdf(best.model, best.params, f"mat_{key}"))
        reports.append(
            ExportReport("mitsuba", str(path), _name_of(brdf), best.model, best.exact, best.error, how, tolerance,
                         {"material": key, **best.params}, cands, notes)
        )  # fmt: skip
    area = {lt.object_id: lt for lt in scene.lights if isinstance(lt, AreaLight) and lt.object_id >= 0}
    try:
        mesh_dir.mkdir(exist_ok=True)
        for i, obj in enumerate(scene.objects):
            fname = mesh_dir / f"{i:03d}_{_safe(obj.name)}.ply"
            mesh = obj.mesh.copy()
            data = mesh.export(file_type="ply", include_attributes=False, vertex_normal=bool(obj.smooth))
            with replacing(fname) as tmp, open(tmp, "wb") as fh:
                fh.write(data)
            shape = ET.SubElement(root, "shape", type="ply", id=f"obj_{i}")
            ET.SubElement(shape, "string", name="filename", value=f"{mesh_dir.name}/{fname.name}")
            if not obj.smooth:
                ET.SubElement(shape, "boolean", name="face_normals", value="true")
            ET.SubElement(shape, "ref", id=f"mat_{obj.material}")
            if i in area:
                em = ET.SubElement(shape, "emitter", type="area")
                ET.SubElement(em, "rgb", name="radiance", value=_vec(area[i].radiance.reshape(-1).tolist()))
        for k, light in enumerate(scene.lights):
            if isinstance(light, AreaLight):
                if light.object_id < 0:
                    raise ExportError(f"light {k}: an area light without an object has no shape to export")
                continue
            if isinstance(light, DirectionalLight):
                em = ET.SubElement(root, "emitter", type="directional")
                ET.SubElement(em, "vector", name="direction", value=_vec((-light.direction).tolist()))
                ET.SubElement(em, "rgb", name="irradiance", value=_vec(light.irradiance.reshape(-1).tolist()))
            elif isinstance(light, EnvironmentMap):
                exr = path.parent / f"{path.stem}_env{k}.exr"
                write_exr(exr, light.radiance.detach().float())
                em = ET.SubElement(root, "emitter", type="envmap")
                ET.SubElement(em, "string", name="filename", value=exr.name)
                tw = ET.SubElement(em, "transform", name="to_world")
                ET.SubElement(tw, "rotate", y="1", angle=f"{math.degrees(float(light.rotation_y)):.9g}")
            else:
                raise ExportError(f"light {k} of type {type(light).__name__} has no stock Mitsuba emitter")
    except OSError as exc:
        raise ExportError(f"cannot write the scene's files next to {path}: {exc.strerror or exc}") from exc
    _write_text(path, _xml_text(root))
    _write_text(Path(str(path) + ".export.json"), json.dumps([asdict(r) for r in reports], indent=2) + "\n")
    return reports


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in str(name))[:60] or "object"
