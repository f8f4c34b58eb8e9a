r"""A bridge to Mitsuba 3: render our :class:`~torch_brdf.scene.scene.Scene` as a reference.

Mitsuba is an optional peer (the ``reference`` extra); nothing else in torch_brdf imports
it. :func:`to_mitsuba_dict` translates a scene into a ``mi.load_dict`` description and
:func:`render_mitsuba` renders it, so that our path tracer
(:func:`~torch_brdf.transport.pathtrace.path_trace`) and everything built on it can be
checked against an independent renderer at equal settings.

Mapping (each point checked by ``tests/transport/test_mitsuba.py``):

* **Depth.** Our ``max_bounces`` counts surface vertices per path (1 = direct lighting);
  Mitsuba's ``max_depth`` counts path segments including the camera ray, so
  ``max_depth = max_bounces + 1``. Both count emitters seen directly from the eye.
* **Camera.** ``perspective`` with ``fov_axis = "y"``, our vertical ``fov_deg`` and
  ``to_world = look_at(origin, target, up)``. Mitsuba's look-at frame has
  ``left = up x forward``, i.e. minus our ``right = forward x up``, and its film's
  column axis runs along minus its camera-space x, so columns increase along our
  ``right`` in both and images come out unmirrored, row 0 at the top (verified on the
  Cornell box: red wall on the left in both). Pixels are box-filtered
  (``rfilter = box``), like our uniform jitter inside each pixel.
* **Materials.** ``lambert`` becomes ``diffuse``; ``blinn_phong`` becomes the Python BSDF
  ``torch_brdf_blinn_phong`` (:func:`register_blinn_phong`), our exact formula;
  ``metallic_roughness`` the Python BSDF ``torch_brdf_metallic_roughness`` (the glTF model:
  Mitsuba's stock ``principled`` is Disney's, not glTF's, see :mod:`torch_brdf.export`). All are
  wrapped in ``twosided`` because our surfaces are two-sided (normals flipped towards the
  arriving ray). Other models raise :class:`~torch_brdf.errors.SceneError`.
* **Lights.** :class:`~torch_brdf.scene.lights.AreaLight` becomes an ``area`` emitter on
  its object's mesh (one-sided, front = counter-clockwise normal, as
  :meth:`AreaLight.emitted`); an area light without an object (``object_id < 0``) gets an
  invisible mesh of its own (black ``diffuse``).
  :class:`~torch_brdf.scene.lights.DirectionalLight` becomes ``directional`` (Mitsuba's
  ``direction`` is the direction of travel: minus ours).
  :class:`~torch_brdf.scene.envmap.EnvironmentMap` becomes ``envmap`` with
  ``to_world = rotate_y(rotation_y)``; the direction convention is the same (row 0 = +y,
  :math:`\phi = \operatorname{atan2}(x, -z)`). A map with the (default) bilinear lookup is
  handed over as it is (the same reconstruction); a ``lookup="nearest"`` map, cell-centred and
  piecewise constant, is upsampled to match (:func:`_envmap_bitmap`).
* **Meshes** are ``mi.Mesh`` objects filled through ``mi.traverse`` (no temporary files);
  smooth objects carry trimesh's vertex normals, flat ones none (face normals), as in
  :class:`~torch_brdf.scene.raytrace.RayTracer`.

Estimators differ (Mitsuba: MIS between emitter and BSDF sampling, Russian roulette from
depth 5; ours: NEE only) but both are unbiased for the same integral.

Variants. ``scalar_rgb`` works wherever Mitsuba installs. ``llvm_ad_rgb`` is ~3x faster
(and runs the Python BSDF vectorised) but needs a recent LLVM (Debian's ``libllvm19``):
with an older one the first render *aborts the Python process* (LLVM "Cannot select
fminimum"), which no ``try`` can catch. :func:`llvm_available` therefore probes it in a
subprocess, and :func:`default_variant` uses it only when the probe passed.
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
import time
from typing import Any

import numpy as np
import torch

from ..brdf import create
from ..errors import SceneError, TorchBRDFError, ValueRangeError
from ..scene.envmap import EnvironmentMap
from ..scene.lights import AreaLight, DirectionalLight, PointLight
from ..scene.scene import Scene

__all__ = [
    "BLINN_PHONG_PLUGIN",
    "METALLIC_ROUGHNESS_PLUGIN",
    "default_variant",
    "llvm_available",
    "mitsuba_available",
    "register_blinn_phong",
    "render_mitsuba",
    "set_variant",
    "to_mitsuba_dict",
]

#: plugin name of the Python Blinn-Phong BSDF (see :func:`register_blinn_phong`)
BLINN_PHONG_PLUGIN = "torch_brdf_blinn_phong"
#: plugin name of the Python glTF metallic-roughness BSDF (see :func:`register_blinn_phong`)
METALLIC_ROUGHNESS_PLUGIN = "torch_brdf_metallic_roughness"
#: material types :func:`to_mitsuba_dict` can translate
SUPPORTED_MATERIALS = ("lambert", "blinn_phong", "metallic_roughness")

_LLVM_OK: bool | None = None  # probe result, cached per process
_REGISTERED: set[str] = set()  # variants with the Python BSDF registered

# A tiny scene rendered by the llvm probe: a diffuse sphere under a constant environment.
_PROBE = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective", "fov": 45,
               "film": {"type": "hdrfilm", "width": 4, "height": 4},
               "sampler": {"type": "independent", "sample_count": 2}},
    "sphere": {"type": "sphere", "center": [0, 0, 5], "radius": 1.0, "bsdf": {"type": "diffuse"}},
    "env": {"type": "constant", "radiance": 1.0},
})
img = mi.render(scene)
print("OK", float(mi.TensorXf(img).numpy().mean()))
"""


# -------------------------------------------------------------------------- availability
def mitsuba_available() -> bool:
    """True if ``import mitsuba`` succeeds (installed and loadable); no variant is set."""
    if importlib.util.find_spec("mitsuba") is None:
        return False
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return False
    return True


def _import_mitsuba():
    try:
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "torch_brdf.transport.mitsuba needs Mitsuba 3: pip install 'torch_brdf[reference]' "
            f"(or pip install mitsuba); import failed: {exc}"
        ) from exc
    return mi


def llvm_available(timeout: float = 180.0) -> bool:
    """Whether Mitsuba's ``llvm_ad_rgb`` variant can render on this machine.

    Renders a 4x4 image in a *subprocess* (a failing LLVM aborts the process that renders,
    uncatchably) and caches the answer for the rest of this process.

    Args:
        timeout: seconds to wait for the probe (it JIT-compiles a path tracer; a few
            seconds normally). A probe that times out counts as unavailable.
    Returns:
        True if the probe printed its result and exited cleanly.
    """
    global _LLVM_OK
    if _LLVM_OK is None:
        if not mitsuba_available():
            _LLVM_OK = False
        else:
            try:
                r = subprocess.run(
                    [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=timeout, check=False
                )
                _LLVM_OK = r.returncode == 0 and r.stdout.startswith("OK")
            except (subprocess.TimeoutExpired, OSError):
                _LLVM_OK = False
    return _LLVM_OK


def default_variant() -> str:
    """``"llvm_ad_rgb"`` if :func:`llvm_available`, else ``"scalar_rgb"``."""
    return "llvm_ad_rgb" if llvm_available() else "scalar_rgb"


def set_variant(variant: str | None = None):
    """Make ``variant`` (None: :func:`default_variant`) Mitsuba's current variant and
    register the Python BSDF for it.

    Args:
        variant: a Mitsuba variant name such as ``"scalar_rgb"`` or ``"llvm_ad_rgb"``.
    Returns:
        the ``mitsuba`` module, set to that variant.
    Raises:
        ImportError: Mitsuba is not installed.
        ValueRangeError: the variant is not installed, or is an ``llvm`` variant whose
            subprocess probe failed.
    """
    mi = _import_mitsuba()
    variant = variant or default_variant()
    if variant not in mi.variants():
        raise ValueRangeError(f"Mitsuba variant {variant!r} is not available; installed: {mi.variants()}")
    if variant.startswith("llvm") and not llvm_available():
        raise ValueRangeError(
            f"Mitsuba variant {variant!r} failed its subprocess probe (rendering would abort this "
            "process; install libllvm19); use 'scalar_rgb'"
        )
    if mi.variant() != variant:
        mi.set_variant(variant)
    register_blinn_phong()
    return mi


# -------------------------------------------------------------------------- Blinn-Phong BSDF
def _lobe_mixture_sample(mi, dr, bsdf, wi, spec, wo_s, wo_d, active, f_cos):
    """The BSDF sample of a diffuse + glossy mixture, once its two candidate directions are drawn:
    the glossy one where ``spec``, its mixture pdf, its flags and the weight f cos / pdf."""
    bs = mi.BSDFSample3f()
    bs.wo = dr.select(spec, wo_s, wo_d)
    bs.pdf = bsdf._pdf(wi, bs.wo)
    bs.eta = 1.0
    bs.sampled_type = dr.select(
        spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection), mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
    )
    bs.sampled_component = dr.select(spec, mi.UInt32(1), mi.UInt32(0))
    ok = active & (mi.Frame3f.cos_theta(wi) > 0) & (bs.pdf > 0)
    weight = f_cos(bs.wo) / dr.maximum(bs.pdf, 1e-30)
    return bs, dr.select(ok, weight, 0.0)


def _blinn_phong_class(mi):
    import drjit as dr

    class BlinnPhongBSDF(mi.BSDF):
        r"""Our :class:`~torch_brdf.brdf.analytic.BlinnPhong` as a one-sided Mitsuba BSDF:

        .. math:: f = \frac{k_d}{\pi} + k_s\,\frac{n+2}{8\pi}\cos^n\theta_h,

        ``eval`` returning :math:`f\cos\theta` of the light direction (Mitsuba's
        convention). Sampling mixes the cosine hemisphere (probability :math:`1-p`) and
        :math:`h \sim \frac{n+2}{2\pi}\cos^{n+1}\theta_h` reflected about ``wi``
        (probability :math:`p = \bar k_s / (\bar k_d + \bar k_s)`, channel means), with
        pdf :math:`(1-p)\cos\theta/\pi + p\,D_n\cos\theta_h / (4\,\omega_i\cdot h)`.

        Properties: ``kd``, ``ks`` (3 floats each, :class:`mi.ScalarColor3f`), ``exponent``.
        """

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.kd = mi.Color3f(props["kd"])
            self.ks = mi.Color3f(props["ks"])
            self.n = float(props["exponent"])
            kd_m, ks_m = dr.mean(props["kd"]), dr.mean(props["ks"])
            self.p_spec = float(ks_m / (kd_m + ks_m)) if kd_m + ks_m > 0 else 0.5
            self.m_components = [
                mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide,
                mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide,
            ]
            self.m_flags = self.m_components[0] | self.m_components[1]

        def _f_cos(self, wi, wo):
            cos_i = mi.Frame3f.cos_theta(wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            h = dr.normalize(wi + wo)
            cos_h = dr.maximum(mi.Frame3f.cos_theta(h), 0.0)
            spec = (self.n + 2.0) / (8.0 * dr.pi) * dr.power(cos_h, self.n)
            f = self.kd * dr.inv_pi + self.ks * spec
            return dr.select((cos_i > 0) & (cos_o > 0), f * cos_o, 0.0)

        def _pdf(self, wi, wo):
            cos_i = mi.Frame3f.cos_theta(wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            h = dr.normalize(wi + wo)
            cos_h = dr.maximum(mi.Frame3f.cos_theta(h), 0.0)
            d = (self.n + 2.0) / (2.0 * dr.pi) * dr.power(cos_h, self.n)
            spec = d * cos_h / (4.0 * dr.maximum(dr.dot(wo, h), 1e-12))
            pdf = (1.0 - self.p_spec) * cos_o * dr.inv_pi + self.p_spec * spec
            return dr.select((cos_i > 0) & (cos_o > 0), pdf, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wi = si.wi
            spec = sample1 < self.p_spec
            wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
            cos_h = dr.power(sample2.x, 1.0 / (self.n + 2.0))
            sin_h = dr.safe_sqrt(1.0 - cos_h * cos_h)
            s, c = dr.sincos(2.0 * dr.pi * sample2.y)
            h = mi.Vector3f(sin_h * c, sin_h * s, cos_h)
            wo_s = 2.0 * dr.dot(wi, h) * h - wi
            return _lobe_mixture_sample(mi, dr, self, wi, spec, wo_s, wo_d, active, lambda wo: self._f_cos(wi, wo))

        def eval(self, ctx, si, wo, active=True):
            return dr.select(active, self._f_cos(si.wi, wo), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            return dr.select(active, self._pdf(si.wi, wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return dr.select(active, self._f_cos(si.wi, wo), 0.0), dr.select(active, self._pdf(si.wi, wo), 0.0)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"BlinnPhongBSDF[kd={self.kd}, ks={self.ks}, exponent={self.n}]"

    return BlinnPhongBSDF


def _metallic_roughness_class(mi):
    import drjit as dr

    class MetallicRoughnessBSDF(mi.BSDF):
        r"""Our :class:`~torch_brdf.brdf.gltf.MetallicRoughness` (the glTF 2.0 model) as a
        one-sided Mitsuba BSDF, written independently of the torch code from the formula:
        :math:`(1-m)(1-F_{0.04})c/\pi + F_{f_0} D V` with GGX :math:`\alpha = r^2` and the
        height-correlated visibility. Sampling: Mitsuba's GGX visible normals with
        probability 1/2, else the cosine hemisphere.

        Properties: ``base_color`` (3 floats, :class:`mi.ScalarColor3f`), ``metallic``,
        ``roughness``.
        """

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.c = mi.Color3f(props["base_color"])
            # an image texture of the base colour (texels times the factor), or None
            self.c_tex = props["base_color_texture"] if "base_color_texture" in props else None
            self.m = float(props["metallic"])
            self.alpha = max(float(props["roughness"]) ** 2, 1e-5)
            self.f0 = (1.0 - self.m) * 0.04 + self.m * self.c
            self.dist = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.alpha, True)
            self.m_components = [
                mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide,
                mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide,
            ]
            self.m_flags = self.m_components[0] | self.m_components[1]

        def _f_cos(self, wi, wo, si=None):
            ci, co = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
            c = self.c if self.c_tex is None or si is None else self.c_tex.eval(si)
            f0 = (1.0 - self.m) * 0.04 + self.m * c
            h = dr.normalize(wi + wo)
            x = dr.power(1.0 - dr.clip(dr.dot(wi, h), 0.0, 1.0), 5.0)
            a2 = self.alpha * self.alpha
            ch = mi.Frame3f.cos_theta(h)
            d = a2 / (dr.pi * dr.square(ch * ch * (a2 - 1.0) + 1.0))
            vis = 0.5 / dr.maximum(
                co * dr.safe_sqrt(ci * ci * (1.0 - a2) + a2) + ci * dr.safe_sqrt(co * co * (1.0 - a2) + a2), 1e-30
            )
            fr = f0 + (1.0 - f0) * x
            f = (1.0 - self.m) * (1.0 - (0.04 + 0.96 * x)) * c * dr.inv_pi + fr * d * vis
            return dr.select((ci > 0) & (co > 0), f * co, 0.0)

        def _pdf(self, wi, wo):
            ci, co = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
            h = dr.normalize(wi + wo)
            spec = self.dist.pdf(wi, h) / (4.0 * dr.maximum(dr.dot(wo, h), 1e-12))
            pdf = 0.5 * co * dr.inv_pi + 0.5 * spec
            return dr.select((ci > 0) & (co > 0), pdf, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wi = si.wi
            spec = sample1 < 0.5
            wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
            h, _ = self.dist.sample(wi, sample2)
            wo_s = 2.0 * dr.dot(wi, h) * h - wi
            return _lobe_mixture_sample(mi, dr, self, wi, spec, wo_s, wo_d, active, lambda wo: self._f_cos(wi, wo, si))

        def eval(self, ctx, si, wo, active=True):
            return dr.select(active, self._f_cos(si.wi, wo, si), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            return dr.select(active, self._pdf(si.wi, wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return dr.select(active, self._f_cos(si.wi, wo, si), 0.0), dr.select(active, self._pdf(si.wi, wo), 0.0)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"MetallicRoughnessBSDF[base_color={self.c}, metallic={self.m}, alpha={self.alpha}]"

    return MetallicRoughnessBSDF


def register_blinn_phong() -> None:
    """Register the Python BSDFs ``torch_brdf_blinn_phong`` and
    ``torch_brdf_metallic_roughness`` for Mitsuba's current variant (once per variant;
    :func:`render_mitsuba` calls it)."""
    mi = _import_mitsuba()
    v = mi.variant()
    if v is None:
        raise ValueRangeError("set a Mitsuba variant (mi.set_variant) before registering the BSDF")
    if v not in _REGISTERED:
        cls = _blinn_phong_class(mi)
        mi.register_bsdf(BLINN_PHONG_PLUGIN, lambda props: cls(props))
        mr_cls = _metallic_roughness_class(mi)
        mi.register_bsdf(METALLIC_ROUGHNESS_PLUGIN, lambda props: mr_cls(props))
        _REGISTERED.add(v)


# -------------------------------------------------------------------------- translation
def _rgb(x) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(c) for c in torch.as_tensor(x).reshape(-1).tolist()]}


def _bsdf_dict(key: str, material: dict[str, Any], mi) -> dict[str, Any]:
    kind = material.get("type")
    if kind not in SUPPORTED_MATERIALS:
        raise SceneError(
            f"material {key!r} has type {kind!r}, which the Mitsuba bridge cannot translate; "
            f"supported: {list(SUPPORTED_MATERIALS)}"
        )
    try:
        brdf = create(material)  # validates and clamps the parameters as our renderer does
    except TorchBRDFError as exc:
        raise SceneError(f"material {key!r}: {exc}") from exc
    with torch.no_grad():
        if kind == "lambert":
            inner = {"type": "diffuse", "reflectance": _rgb(brdf.reflectance)}
        elif kind == "metallic_roughness":
            inner = {
                "type": METALLIC_ROUGHNESS_PLUGIN,
                "base_color": mi.ScalarColor3f(*brdf.base_color.tolist()),
                "metallic": float(brdf.metallic),
                "roughness": float(brdf.roughness),
            }
        else:
            inner = {
                "type": BLINN_PHONG_PLUGIN,
                "kd": mi.ScalarColor3f(*brdf.kd.tolist()),
                "ks": mi.ScalarColor3f(*brdf.ks.tolist()),
                "exponent": float(brdf.exponent),
            }
    return {"type": "twosided", "bsdf": inner}


def _envmap_bitmap(radiance: torch.Tensor, max_width: int = 2048) -> np.ndarray:
    r"""Our nearest-texel lat-long map resampled for Mitsuba's ``envmap``.

    Mitsuba 3.9 interpolates its bitmap bilinearly, with columns cell-centred like ours
    (column :math:`j` at :math:`\phi = (j + \tfrac12)\,2\pi/W`) but rows *vertex*-centred
    (row :math:`i` at :math:`\theta = i\pi/(H-1)`, row 0 at the pole), and it has no
    nearest-neighbour option. So the map is upsampled by an integer factor :math:`k`
    (the largest with :math:`kW \le` ``max_width``, at least 1): :math:`kW` columns and :math:`kH + 1` rows
    whose values are our texels at those positions, rows that fall on one of our row
    boundaries taking the mean of the two rows. Bilinear blending is then confined to
    bands one fine texel wide around our texel edges, and symmetric about them.

    Args:
        radiance: (H, W, 3) our map.
        max_width: largest width of the result.
    Returns:
        (kH + 1, kW, 3) float32 array.
    """
    L = radiance.detach().double().cpu().numpy()
    H, W = L.shape[:2]
    k = max(1, max_width // W)
    cols = L[:, np.arange(k * W) // k]  # (H, kW, 3)
    i = np.arange(k * H + 1)
    lo, hi = np.clip((i - 1) // k, 0, H - 1), np.clip(i // k, 0, H - 1)
    boundary = (i % k == 0)[:, None, None]
    rows = np.where(boundary, 0.5 * (cols[lo] + cols[hi]), cols[hi])
    rows[0], rows[-1] = cols[0], cols[-1]  # the poles
    return np.ascontiguousarray(rows, dtype=np.float32)


def _mesh(mi, name: str, vertices, faces, normals, bsdf, emitter=None, uv=None):
    """An ``mi.Mesh`` with the given arrays: vertices (V, 3), faces (F, 3), normals (V, 3) or
    None, uv (V, 2) in our convention (v up) or None."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    mesh = mi.Mesh(
        name, len(v), len(f), props=props, has_vertex_normals=normals is not None, has_vertex_texcoords=uv is not None
    )
    params = mi.traverse(mesh)
    vtype, ftype = type(params["vertex_positions"]), type(params["faces"])
    params["vertex_positions"] = vtype(v.ravel())
    params["faces"] = ftype(f.ravel())
    if normals is not None:
        params["vertex_normals"] = vtype(np.ascontiguousarray(normals, dtype=np.float32).ravel())
    if uv is not None:  # Mitsuba's bitmap rows run down from v = 0: flip v
        t = np.asarray(uv, dtype=np.float64)
        t = np.stack([t[:, 0], 1.0 - t[:, 1]], -1)
        params["vertex_texcoords"] = vtype(np.ascontiguousarray(t, dtype=np.float32).ravel())
    params.update()
    return mesh


def _textured(mi, bsdf: dict[str, Any], material: dict[str, Any], texture) -> dict[str, Any]:
    """``bsdf`` with its base colour replaced by ``texture`` times the material's factor: a
    ``bitmap`` of the linear texels (``raw``: no second sRGB decoding), bilinear, repeating,
    as :meth:`~torch_brdf.scene.textures.Texture.lookup`. The factor is multiplied into the
    texels, which a bilinear lookup keeps exact."""
    inner = dict(bsdf["bsdf"]) if bsdf.get("type") == "twosided" else dict(bsdf)
    if inner["type"] == METALLIC_ROUGHNESS_PLUGIN:
        factor = np.asarray(list(inner["base_color"]), dtype=np.float64)
        img = texture.image.double().numpy() * factor
        inner["base_color_texture"] = mi.load_dict(
            {
                "type": "bitmap",
                "bitmap": mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)),
                "raw": True,
                "filter_type": "bilinear",
                "wrap_mode": "repeat",
            }
        )
        return {"type": "twosided", "bsdf": inner} if bsdf.get("type") == "twosided" else inner
    slot = {"diffuse": "reflectance", "principled": "base_color"}.get(inner["type"])
    if slot is None:
        raise SceneError(
            f"material of type {material.get('type')!r} with a texture has no Mitsuba translation; "
            "textured: lambert, metallic_roughness"
        )
    factor = np.asarray(inner[slot]["value"], dtype=np.float64).reshape(-1)
    img = texture.image.double().numpy() * factor
    inner[slot] = {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "repeat",
    }
    return {"type": "twosided", "bsdf": inner} if bsdf.get("type") == "twosided" else inner


def to_mitsuba_dict(scene: Scene, spp: int, max_bounces: int, seed: int = 0, variant: str | None = None) -> dict:
    """A ``mi.load_dict`` description of ``scene`` rendered like
    :func:`~torch_brdf.transport.pathtrace.path_trace` (see the module docstring).

    Sets the Mitsuba variant (``variant``, or :func:`default_variant` when None), since the
    meshes and BSDFs in the dict are objects of that variant.

    Args:
        scene: objects with ``lambert`` / ``blinn_phong`` / ``metallic_roughness`` materials; area, directional and
            environment-map lights; the pinhole camera gives an (H, W) film.
        spp: samples per pixel (>= 1).
        max_bounces: surface vertices per path as in ``path_trace`` (>= 1);
            Mitsuba's ``max_depth`` is ``max_bounces + 1``.
        seed: seed of Mitsuba's ``independent`` sampler.
        variant: Mitsuba variant to build for.
    Returns:
        dict with keys ``type``, ``integrator``, ``sensor``, one ``obj_<i>`` per object
        (``mi.Mesh``), and ``light_<k>`` per non-area light (or area light without object).
    Raises:
        SceneError: a material or light the bridge cannot translate (named in the message).
        ValueRangeError: spp or max_bounces < 1, or an unavailable variant.
        ImportError: Mitsuba is not installed.
    """
    if int(spp) < 1 or int(max_bounces) < 1:
        raise ValueRangeError(f"spp and max_bounces must be >= 1; got spp={spp}, max_bounces={max_bounces}")
    mi = set_variant(variant)
    cam = scene.camera
    lo, hi = scene.tracer.bbox
    extent = float(np.linalg.norm(np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)))
    dist = float(np.linalg.norm(np.asarray(cam.origin) - 0.5 * (np.asarray(lo) + np.asarray(hi))))
    far = max(1e4, 4.0 * (extent + dist))
    out: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_bounces) + 1, "hide_emitters": False},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": float(cam.fov_deg),
            "near_clip": far * 1e-7,
            "far_clip": far,
            "to_world": mi.ScalarTransform4f().look_at(origin=cam.origin, target=cam.target, up=cam.up),
            "film": {
                "type": "hdrfilm",
                "width": cam.width,
                "height": cam.height,
                "pixel_format": "rgb",
                "rfilter": {"type": "box"},
            },
            "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        },
    }
    area = scene.area_lights
    bsdfs: dict[str, dict] = {}
    for i, obj in enumerate(scene.objects):
        if obj.material not in bsdfs:
            bsdfs[obj.material] = _bsdf_dict(obj.material, scene.materials[obj.material], mi)
        emitter = None
        if i in area:
            emitter = {"type": "area", "radiance": _rgb(area[i].radiance)}
        normals = np.asarray(obj.mesh.vertex_normals) if obj.smooth else None
        bsdf = bsdfs[obj.material]
        if "base_color" in obj.textures:
            bsdf = _textured(mi, bsdf, scene.materials[obj.material], obj.textures["base_color"])
        uv = obj.uv if obj.textures else None
        out[f"obj_{i}"] = _mesh(mi, obj.name, obj.mesh.vertices, obj.mesh.faces, normals, bsdf, emitter, uv)
    for k, light in enumerate(scene.lights):
        key = f"light_{k}"
        if isinstance(light, AreaLight):
            if light.object_id >= 0:
                continue  # attached to its object above
            tri = light.triangles.double().numpy().reshape(-1, 3)
            faces = np.arange(len(tri)).reshape(-1, 3)
            black = {"type": "diffuse", "reflectance": _rgb([0.0, 0.0, 0.0])}
            out[key] = _mesh(mi, key, tri, faces, None, black, {"type": "area", "radiance": _rgb(light.radiance)})
        elif isinstance(light, DirectionalLight):
            out[key] = {
                "type": "directional",
                "direction": [-float(c) for c in light.direction.tolist()],
                "irradiance": _rgb(light.irradiance),
            }
        elif isinstance(light, PointLight):
            out[key] = {
                "type": "point",
                "position": [float(c) for c in light.position.tolist()],
                "intensity": _rgb(light.intensity),
            }
        elif isinstance(light, EnvironmentMap):
            out[key] = {
                "type": "envmap",
                "bitmap": mi.Bitmap(
                    np.ascontiguousarray(light.radiance.detach().cpu().numpy(), dtype=np.float32)
                    if light.bilinear
                    else _envmap_bitmap(light.radiance)
                ),
                "to_world": mi.ScalarTransform4f().rotate([0.0, 1.0, 0.0], math.degrees(light.rotation_y)),
            }
        else:
            raise SceneError(f"light {k} of type {type(light).__name__} has no Mitsuba translation")
    return out


# -------------------------------------------------------------------------- rendering
def render_mitsuba(
    scene: Scene,
    spp: int,
    max_bounces: int,
    seed: int = 0,
    variant: str | None = None,
    return_seconds: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, float]:
    """Render ``scene`` with Mitsuba 3 at the settings of ``path_trace``.

    Args:
        scene: see :func:`to_mitsuba_dict`.
        spp: samples per pixel.
        max_bounces: surface vertices per path (1 = direct lighting).
        seed: sampler seed; the image is a deterministic function of the arguments.
        variant: Mitsuba variant; None picks :func:`default_variant` (``llvm_ad_rgb`` only
            after its subprocess probe passed).
        return_seconds: also return the wall-clock seconds of ``mi.render`` alone: scene
            translation and loading are excluded; for the ``llvm`` variants a 1-spp render
            is run first so that JIT compilation is excluded too (Dr.Jit caches kernels).
    Returns:
        (H, W, 3) float32 linear radiance, row 0 at the top; with ``return_seconds`` the
        tuple (image, seconds).
    """
    desc = to_mitsuba_dict(scene, spp, max_bounces, seed, variant)
    mi = _import_mitsuba()
    mscene = mi.load_dict(desc)
    if return_seconds and mi.variant().startswith(("llvm", "cuda")):
        mi.render(mscene, seed=int(seed), spp=1)  # warm-up: compile the kernels
    t0 = time.perf_counter()
    img = mi.render(mscene, seed=int(seed), spp=int(spp))
    arr = np.array(img, dtype=np.float32)  # forces evaluation in the JIT variants
    seconds = time.perf_counter() - t0
    out = torch.from_numpy(np.ascontiguousarray(arr[..., :3]))
    return (out, seconds) if return_seconds else out
