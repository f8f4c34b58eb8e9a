r"""The two views of BRDF Explorer the editor shows beside the frame: the lobe in the plane of
incidence (a polar plot, drawn as SVG) and a lit sphere.

Polar plot: light from :math:`\theta_i` on the left, :math:`\omega_o` swept through the plane
of incidence, radius :math:`f_r(\omega_i, \omega_o)\cos\theta_o` (the reflected radiance per
unit irradiance; luminance-weighted RGB), normalised to the larger of the two curves: the
model as given and, when passed, the 1-D curve the renderer uses (the model projected onto
the object's bands), so what the bands lose is visible.

Lit sphere: orthographic view along -z, one directional light of irradiance :math:`\pi` at
normal incidence (a white Lambertian sphere is 1 where the light is overhead), no ambient.
"""

from __future__ import annotations

import math

import torch

from ..brdf import BRDF
from ..frame import Frame

_LUMA = (0.2126, 0.7152, 0.0722)


def plane_lobe(brdf: BRDF, theta_i_deg: float = 45.0, n: int = 181) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed outgoing angles (n,) in radians (positive: the mirror side) and the luminance of
    :math:`f_r\\cos\\theta_o` (n,) float64, light at ``theta_i_deg`` on the negative side."""
    ti = math.radians(theta_i_deg)
    to = torch.linspace(-math.pi / 2, math.pi / 2, n, dtype=torch.float64)[1:-1]
    wo = torch.stack([torch.sin(to), torch.zeros_like(to), torch.cos(to)], -1)
    wi = torch.tensor([-math.sin(ti), 0.0, math.cos(ti)], dtype=torch.float64).expand_as(wo)
    with torch.no_grad():
        f = brdf.eval_local(wi, wo).to(torch.float64)
    f = f.unsqueeze(-1).expand(-1, 3) if f.ndim == 1 else f
    y = (f * torch.tensor(_LUMA, dtype=torch.float64)).sum(-1) * torch.cos(to)
    return to, y.clamp_min(0)


def lobe_svg(brdf: BRDF, rendered: BRDF | None = None, theta_i_deg: float = 45.0, size: int = 240) -> str:
    """An SVG polar plot (``size`` px square) of :func:`plane_lobe` for ``brdf`` (orange) and
    ``rendered`` (blue, the banded curve), with the surface, normal and light direction."""
    curves = [(brdf, "#e8710a", "model")] + ([(rendered, "#1a73e8", "bands")] if rendered is not None else [])
    data = [(plane_lobe(b, theta_i_deg), c, lab) for b, c, lab in curves]
    peak = max(float(y.max()) for (_, y), _, _ in data) or 1.0
    cx, cy, r = size / 2, size * 0.62, size * 0.46
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" class="tb-lobe">',
        f'<rect width="{size}" height="{size}" fill="white"/>',
        f'<line x1="4" y1="{cy}" x2="{size - 4}" y2="{cy}" stroke="#888"/>',
        f'<line x1="{cx}" y1="{cy}" x2="{cx}" y2="{cy - r}" stroke="#ccc" stroke-dasharray="3,3"/>',
    ]
    ti = math.radians(theta_i_deg)
    lx, ly = cx - r * math.sin(ti), cy - r * math.cos(ti)
    parts.append(f'<line x1="{cx}" y1="{cy}" x2="{lx:.1f}" y2="{ly:.1f}" stroke="#d4a000" stroke-width="2"/>')
    for (to, y), color, label in data:
        rr = (y / peak * r).tolist()
        pts = " ".join(
            f"{cx + q * math.sin(a):.1f},{cy - q * math.cos(a):.1f}" for a, q in zip(to.tolist(), rr, strict=True)
        )
        parts.append(f'<polyline points="{cx},{cy} {pts} {cx},{cy}" fill="none" stroke="{color}" stroke-width="1.6">')
        parts.append(f"<title>{label}</title></polyline>")
    legend = " · ".join(f'<tspan fill="{c}">{lab}</tspan>' for _, c, lab in data)
    parts.append(f'<text x="6" y="14" font-size="11" font-family="monospace">{legend}</text>')
    parts.append(
        f'<text x="6" y="{size - 6}" font-size="10" font-family="monospace">'
        f"θi {theta_i_deg:.0f}° · max f·cos {peak:.3g}</text></svg>"
    )
    return "".join(parts)


def lit_sphere(brdf: BRDF, size: int = 96, light=(-0.5, 0.55, 0.67)) -> torch.Tensor:
    """(size, size, 3) float32 radiance of a sphere of ``brdf`` under one directional light
    (``light`` points towards the light, camera space: x right, y up, z towards the viewer)."""
    g = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-g, g, indexing="ij")
    inside = x * x + y * y < 1
    n = torch.stack([x[inside], y[inside], (1 - x[inside] ** 2 - y[inside] ** 2).clamp_min(0).sqrt()], -1)
    wi = torch.nn.functional.normalize(torch.tensor(light, dtype=torch.float64), dim=0).expand_as(n)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(n)
    frame = Frame.from_normal(n, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand_as(n))  # anisotropy along x
    with torch.no_grad():
        f = brdf.eval(wi, wo, frame).to(torch.float64)
    cos = (n * wi).sum(-1).clamp_min(0)
    out = torch.full((size, size, 3), 0.02, dtype=torch.float64)
    out[inside] = f * (math.pi * cos)[:, None]
    return out.float()
