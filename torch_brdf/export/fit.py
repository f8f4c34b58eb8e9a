r"""Fits of stock renderer models to any BRDF of the library, by cosine-weighted least squares
over the hemisphere, and the error measure every export reports.

The error of an approximation :math:`\hat f` of :math:`f` is the cosine-weighted relative L2
norm of :func:`torch_brdf.brdf.bands.projection_error`,

.. math:: \epsilon = \Big(\iint \|f - \hat f\|^2\cos\theta_i\cos\theta_o\,d\omega_i d\omega_o
          \Big/ \iint \|f\|^2\cos\theta_i\cos\theta_o\,d\omega_i d\omega_o\Big)^{1/2},

estimated on a fixed, seeded set of pairs (:class:`FitPairs`): :math:`\omega_o` cosine-
distributed, :math:`\omega_i` from the mixture of the cosine lobe and the BRDF's own sampler
(so narrow lobes are covered), each pair weighted by :math:`\cos\theta_i\cos\theta_o/q`.

Stock models and their torch stand-ins (the fit runs on the stand-in; the exporter then
re-measures the error against Mitsuba's own plugin when Mitsuba is installed):

* ``diffuse``: :class:`~torch_brdf.brdf.base.Lambert` (exact; closed-form least squares).
* ``roughconductor`` (GGX, ``material="none"``, i.e. :math:`F = 1`, times
  ``specular_reflectance`` :math:`R`): :math:`R\,D\,G_1G_1/(4\cos\theta_i\cos\theta_o)`, the
  :class:`~torch_brdf.brdf.microfacet.CookTorrance` GGX lobe with :math:`F_0 = 1` (Mitsuba's
  microfacet masking is the separable Smith one, as ours).
* ``diffuse+roughconductor``: ``blendbsdf`` of the two with weight :math:`w`:
  :math:`(1-w)\rho/\pi + w\,R\,D\,G_1G_1/(4\cos\theta_i\cos\theta_o)`, fitted as
  :math:`k_d/\pi + k_s D G_1G_1/(4\ldots)` with :math:`\max k_d + \max k_s \le 1` (the
  glossy-plus-diffuse shape of Blinn-Phong, Ward or Cook-Torrance with a diffuse base).
* ``principled``: the glTF :class:`~torch_brdf.brdf.gltf.MetallicRoughness`. Not exact:
  Mitsuba's principled masks with the separable Smith :math:`G_1G_1` where glTF's is
  height-correlated (a few percent for a metal, from grazing pairs; ``benchmarks/export.py``
  prints it as ``principled_residual``), and its dielectric diffuse is
  Disney's (retro-reflection, :math:`(1 - F_L/2)(1 - F_V/2)`), not Lambert times
  :math:`1 - F`. The export re-measures the error with Mitsuba.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..brdf import BRDF, Lambert, MetallicRoughness
from ..brdf.base import Clamped
from ..brdf.microfacet import GGXNDF, safe_pair
from ..errors import ExportError
from ..frame import half_terms

__all__ = ["STOCK_MODELS", "FitPairs", "StockFit", "fit_error", "fit_stock"]

#: Mitsuba stock plugins the fit can target.
STOCK_MODELS = ("diffuse", "roughconductor", "principled", "diffuse+roughconductor")


@dataclass(frozen=True)
class FitPairs:
    """Seeded direction pairs and weights of the cosine-weighted measure.

    Attributes:
        wi, wo: (N, 3) float64 local directions above the horizon.
        weight: (N,) float64 :math:`\\cos\\theta_i\\cos\\theta_o / q(\\omega_i, \\omega_o)`.
    """

    wi: torch.Tensor
    wo: torch.Tensor
    weight: torch.Tensor

    @staticmethod
    def build(brdf, n: int = 2048, seed: int = 0) -> FitPairs:
        """Pairs for ``brdf`` (its sampler, when it has one, covers its lobe)."""
        g = torch.Generator().manual_seed(seed)
        dt = torch.float64
        u = torch.rand(3, n, 2, generator=g, dtype=dt)

        def cosine(uu):
            r, p = uu[:, 0].sqrt(), 2 * math.pi * uu[:, 1]
            return torch.stack([r * p.cos(), r * p.sin(), (1 - uu[:, 0]).clamp_min(0).sqrt()], -1)

        wo = cosine(u[0])
        wi = cosine(u[1])
        half = n // 2
        sampler = getattr(brdf, "sample_local", None)
        pdf_fn = getattr(brdf, "pdf_local", None)
        with torch.no_grad():
            if sampler is not None and pdf_fn is not None:
                ws, _ = sampler(wo[:half].to(_dtype(brdf)), u[2, :half].to(_dtype(brdf)))
                wi[:half] = ws.to(dt)
                pdf_b = pdf_fn(wi.to(_dtype(brdf)), wo.to(_dtype(brdf))).to(dt)
            else:
                pdf_b = wi[:, 2].clamp_min(0) / math.pi
        q_i = 0.5 * wi[:, 2].clamp_min(0) / math.pi + 0.5 * pdf_b
        ok = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6) & (q_i > 0)
        wi, wo, q_i = wi[ok], wo[ok], q_i[ok]
        # q(wo) = cos_o / pi: cos_i cos_o / (q_i q_o) = pi cos_i / q_i
        weight = math.pi * wi[:, 2] / q_i
        return FitPairs(wi, wo, weight)


def _dtype(brdf) -> torch.dtype:
    p = next(iter(brdf.parameters()), None) if isinstance(brdf, torch.nn.Module) else None
    return torch.float64 if p is None else p.dtype


def _eval(brdf, wi, wo) -> torch.Tensor:
    dt = _dtype(brdf)
    f = brdf.eval_local(wi.to(dt), wo.to(dt)).to(torch.float64)
    return f.expand(*wi.shape[:-1], 3) if f.shape[-1:] == (1,) or f.ndim == wi.ndim - 1 else f


def fit_error(f: torch.Tensor, g: torch.Tensor, weight: torch.Tensor) -> float:
    """Cosine-weighted relative L2 error of ``g`` against ``f`` ((N, 3) each) with the
    :class:`FitPairs` weights (N,)."""
    num = (weight[:, None] * (f - g) ** 2).sum()
    den = (weight[:, None] * f * f).sum().clamp_min(1e-300)
    return math.sqrt(float(num / den))


@dataclass(frozen=True)
class StockFit:
    """One fitted stock model.

    Attributes:
        model: a name of :data:`STOCK_MODELS`.
        params: the plugin's parameters (plain floats / RGB lists).
        proxy: the torch stand-in with those parameters (a BRDF).
        error: cosine-weighted relative L2 error of the stand-in against the source.
        exact: the source is this stock model by construction (no fit was needed).
    """

    model: str
    params: dict
    proxy: BRDF
    error: float
    exact: bool = False


class _ScaledConductor(BRDF):
    """Mitsuba's ``roughconductor`` with ``material="none"`` (F = 1): R times the GGX lobe."""

    def __init__(self, reflectance=0.9, alpha=0.2):
        super().__init__()
        self.register_constrained("reflectance", reflectance, Clamped(0.0, 1.0), shape=(3,))
        self.register_constrained("alpha", alpha, Clamped(1e-3, 1.0))

    def eval_local(self, wi, wo):
        dist = GGXNDF(self.alpha.to(wi.dtype))
        si, so, up = safe_pair(wi, wo)
        ht = half_terms(si, so)
        spec = 0.25 * dist.D(ht.s) * dist.G1_over_cos(si) * dist.G1_over_cos(so)
        f = spec.unsqueeze(-1) * self.reflectance.to(wi.dtype)
        return torch.where(up.unsqueeze(-1), f, torch.zeros((), dtype=wi.dtype))


class _DiffuseConductor(_ScaledConductor):
    """``blendbsdf`` of ``diffuse`` and ``roughconductor``: kd / pi + R x the GGX lobe."""

    def __init__(self, kd=0.3, reflectance=0.5, alpha=0.2):
        super().__init__(reflectance, alpha)
        self.register_constrained("kd", kd, Clamped(0.0, 1.0), shape=(3,))

    def eval_local(self, wi, wo):
        up = ((wi[..., 2] > 0) & (wo[..., 2] > 0)).unsqueeze(-1)
        diffuse = torch.where(up, self.kd.to(wi.dtype) / math.pi, torch.zeros((), dtype=wi.dtype))
        return super().eval_local(wi, wo) + diffuse


def _adam(model: BRDF, pairs: FitPairs, f: torch.Tensor, steps: int) -> float:
    params = [p for p in model.parameters()]
    opt = torch.optim.Adam(params, lr=0.05)
    den = (pairs.weight[:, None] * f * f).sum().clamp_min(1e-300)
    for _ in range(steps):
        opt.zero_grad()
        g = model.eval_local(pairs.wi, pairs.wo)
        loss = (pairs.weight[:, None] * (g - f) ** 2).sum() / den
        loss.backward()
        opt.step()
        with torch.no_grad():  # keep the raw values inside their Clamped ranges
            for name, t in model._constraints.items():
                raw = getattr(model, "raw_" + name)
                raw.copy_(t.forward(raw))
    with torch.no_grad():
        return fit_error(f, model.eval_local(pairs.wi, pairs.wo), pairs.weight)


def _fit_diffuse(f, pairs) -> StockFit:
    w = pairs.weight[:, None]
    albedo = (math.pi * (w * f).sum(0) / w.sum()).clamp(0.0, 1.0)
    proxy = Lambert(albedo.tolist()).double()
    with torch.no_grad():
        err = fit_error(f, proxy.eval_local(pairs.wi, pairs.wo), pairs.weight)
    return StockFit("diffuse", {"reflectance": albedo.tolist()}, proxy, err)


def _fit_conductor(f, pairs, steps) -> StockFit:
    best = None
    for alpha in (0.1, 0.4):
        m = _ScaledConductor(0.8, alpha).double()
        err = _adam(m, pairs, f, steps)
        if best is None or err < best[0]:
            best = (err, m)
    err, m = best
    params = {"alpha": float(m.alpha.detach()), "specular_reflectance": m.reflectance.detach().tolist()}
    return StockFit("roughconductor", params, m, err)


def _fit_blend(f, pairs, steps) -> StockFit:
    best = None
    for alpha in (0.1, 0.4):
        m = _DiffuseConductor(0.3, 0.5, alpha).double()
        err = _adam(m, pairs, f, steps)
        if best is None or err < best[0]:
            best = (err, m)
    err, m = best
    with torch.no_grad():
        kd, ks = m.kd.double(), m.reflectance.double()
        total = float(kd.max() + ks.max())
        if total > 1:  # blendbsdf needs max kd + max ks <= 1: scale both (and re-measure)
            with torch.no_grad():
                m.kd = kd / total
                m.reflectance = ks / total
            kd, ks = kd / total, ks / total
            err = fit_error(f, m.eval_local(pairs.wi, pairs.wo), pairs.weight)
        w = float(ks.max()) / max(float(ks.max() + kd.max()), 1e-300)
        params = {
            "weight": w,
            "reflectance": (kd / max(1 - w, 1e-12)).clamp(0, 1).tolist(),
            "alpha": float(m.alpha.detach()),
            "specular_reflectance": (ks / max(w, 1e-12)).clamp(0, 1).tolist(),
        }
    return StockFit("diffuse+roughconductor", params, m, err)


def _fit_principled(f, pairs, steps) -> StockFit:
    best = None
    for metallic, roughness in ((0.0, 0.5), (1.0, 0.5)):
        m = MetallicRoughness(0.5, metallic, roughness).double()
        err = _adam(m, pairs, f, steps)
        if best is None or err < best[0]:
            best = (err, m)
    err, m = best
    return StockFit("principled", principled_params(m), m, err)


def principled_params(m: MetallicRoughness) -> dict:
    """Mitsuba ``principled`` parameters of a glTF model (``specular`` 0.5 is f0 = 0.04;
    sheen, clearcoat, tint, anisotropy and transmission off)."""
    with torch.no_grad():
        return {
            "base_color": m.base_color.double().tolist(),
            "metallic": float(m.metallic),
            "roughness": float(m.roughness),
            "specular": 0.5,
            "spec_tint": 0.0,
            "sheen": 0.0,
            "clearcoat": 0.0,
            "anisotropic": 0.0,
            "spec_trans": 0.0,
        }


def fit_stock(
    brdf, models: tuple[str, ...] = STOCK_MODELS, pairs: FitPairs | None = None, steps: int = 100
) -> list[StockFit]:
    """Fit each stock model of ``models`` to ``brdf`` (any object with ``eval_local``).

    Args:
        brdf: the source BRDF.
        models: names from :data:`STOCK_MODELS`.
        pairs: the measure (default :meth:`FitPairs.build` of ``brdf``, seeded).
        steps: Adam steps per start (the diffuse fit is closed-form).
    Returns:
        the fits, best (smallest error) first.
    Raises:
        ExportError: an unknown model name, or a source that gives non-finite values.
    """
    bad = [m for m in models if m not in STOCK_MODELS]
    if bad:
        raise ExportError(f"unknown stock model(s) {bad}; available: {list(STOCK_MODELS)}")
    pairs = pairs or FitPairs.build(brdf)
    with torch.no_grad():
        f = _eval(brdf, pairs.wi, pairs.wo)
    if not bool(torch.isfinite(f).all()):
        raise ExportError("the BRDF gives non-finite values on the hemisphere; it cannot be fitted")
    fits = []
    for name in models:
        if name == "diffuse":
            fits.append(_fit_diffuse(f, pairs))
        elif name == "roughconductor":
            fits.append(_fit_conductor(f, pairs, steps))
        elif name == "diffuse+roughconductor":
            fits.append(_fit_blend(f, pairs, steps))
        else:
            fits.append(_fit_principled(f, pairs, steps))
    return sorted(fits, key=lambda s: s.error)
