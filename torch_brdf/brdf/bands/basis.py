r"""Box bands over a 1-D parameterisation :math:`\gamma(\omega_i, \omega_o)` (Ben-Artzi et al.
2008, Appendix A): the band edges (:func:`band_edges`) and the basis (:class:`BandBasis`).
"""

from __future__ import annotations

import hashlib
import math

import torch
from torch import nn

from ..._checks import MAX_BANDS, check_int
from ...errors import ValueRangeError
from ...frame import polar_angle
from ._geometry import HALF_PI, anisotropy_ratio, half_and_diff

__all__ = ["VARIABLES", "BandBasis", "band_edges"]

#: The 1-D parameterisations and their domains.
VARIABLES = {
    "theta_h": (0.0, HALF_PI),
    "theta_d": (0.0, HALF_PI),
    "theta_i": (0.0, HALF_PI),
    "theta_o": (0.0, HALF_PI),
    "anisotropy_ratio": (0.0, 1.0),
}


def band_edges(J: int, spacing: str | float = "uniform", domain: tuple[float, float] = (0.0, HALF_PI)) -> torch.Tensor:
    r"""Band edges (J + 1,) float64 over ``domain`` = [lo, hi].

    ``spacing``:

    * ``"uniform"``: :math:`\gamma_k = lo + (hi - lo) k/J`;
    * ``"sqrt"``: MERL's half-angle mapping (index :math:`\propto\sqrt{\theta_h}`), edges
      :math:`lo + (hi - lo)(k/J)^2`, dense near ``lo``;
    * a number :math:`p > 0`: power law :math:`lo + (hi - lo)(k/J)^p` (``"sqrt"`` is p = 2);
    * ``"log:t0"`` (e.g. ``"log:0.02"``): uniform in :math:`\ln(1 + (\gamma - lo)/t_0)`,
      constant *relative* band width away from ``lo`` -- every lobe wider than :math:`t_0`
      is resolved with about the same relative error;
    * ``"lobe:n"`` or ``"lobe:n:beta"`` (e.g. ``"lobe:100"``): bands adapted to a Blinn-like
      lobe :math:`\cos^n\gamma \approx e^{-n\gamma^2/2}` -- the L2-optimal density of
      piecewise-constant bands, :math:`\propto (w\,f'^2)^{1/3}` with the near-pole measure
      :math:`w \propto \gamma`, is :math:`\propto \gamma e^{-n\gamma^2/3}`; a fraction
      ``beta`` (default 0.2) of the bands is spread uniformly so the whole domain stays
      editable. Edges: the CDF :math:`(1-\beta)\frac{1 - e^{-n\gamma^2/3}}{1 - e^{-n\,
      hi^2/3}} + \beta\frac{\gamma}{hi}` inverted at :math:`k/J` (for ``lo = 0``);
    * ``"top:..."``: any of the above mirrored so the bands are dense near ``hi``.

    Raises:
        ValueRangeError: ``J`` not an integer in [1, ``MAX_BANDS``] (4096), an unknown or
            out-of-range spacing, or one whose edges do not increase strictly (zero-width bands).
    """
    J = check_int(J, "J", 1, MAX_BANDS)  # 16.7 was cut to 16, 10**9 allocated until killed
    lo, hi = float(domain[0]), float(domain[1])
    t = torch.arange(J + 1, dtype=torch.float64) / J
    mirror = isinstance(spacing, str) and spacing.startswith("top:")
    sp = spacing[4:] if mirror else spacing
    if isinstance(sp, (int, float)):
        if not sp > 0:
            raise ValueRangeError(f"power spacing must be > 0; got {sp}")
        g = t**sp
    elif sp == "uniform":
        g = t
    elif sp == "sqrt":
        g = t**2
    elif isinstance(sp, str) and sp.startswith("log:"):
        t0 = float(sp[4:]) / (hi - lo)
        if not t0 > 0:
            raise ValueRangeError(f"log spacing needs t0 > 0; got {sp!r}")
        g = torch.expm1(t * math.log1p(1 / t0)) * t0
    elif isinstance(sp, str) and sp.startswith("lobe:"):
        g = _lobe_grid(t, sp, hi - lo)
    else:
        want = "'uniform', 'sqrt', a power, 'log:t0', 'lobe:n[:beta]' or 'top:...'"
        raise ValueRangeError(f"unknown spacing {spacing!r}; expected {want}")
    if mirror:
        g = 1 - g.flip(0)
    g[0], g[-1] = 0.0, 1.0
    e = lo + (hi - lo) * g
    empty = int((~(e[1:] > e[:-1])).sum())  # NaN counts as empty
    if empty:  # e.g. "lobe:inf" or a power of 1e300: zero-width bands that no BRDF value falls in
        raise ValueRangeError(
            f"spacing {spacing!r} gives {empty} of {J} bands of zero width (or NaN edges); "
            "use a finite, smaller lobe exponent or power, or fewer bands"
        )
    return e


def _lobe_grid(t: torch.Tensor, spec: str, scale: float) -> torch.Tensor:
    parts = spec.split(":")
    try:
        n = float(parts[1])
        beta = float(parts[2]) if len(parts) > 2 else 0.2
    except (IndexError, ValueError) as exc:
        raise ValueRangeError(f"lobe spacing is 'lobe:n' or 'lobe:n:beta'; got {spec!r}") from exc
    if not (n > 0 and 0 <= beta <= 1):
        raise ValueRangeError(f"lobe spacing needs n > 0 and 0 <= beta <= 1; got {spec!r}")
    a = n * scale * scale / 3

    def cdf(x: torch.Tensor) -> torch.Tensor:  # x in [0, 1] (fraction of the domain)
        return (1 - beta) * torch.expm1(-a * x * x) / math.expm1(-a) + beta * x

    lo, hi = torch.zeros_like(t), torch.ones_like(t)
    for _ in range(80):  # bisection: cdf is increasing
        mid = 0.5 * (lo + hi)
        below = cdf(mid) < t
        lo, hi = torch.where(below, mid, lo), torch.where(below, hi, mid)
    return 0.5 * (lo + hi)


class BandBasis(nn.Module):
    r"""``J`` box bands over a 1-D parameterisation :math:`\gamma(\omega_i, \omega_o)` (Eq. 30).

    Band ``j`` is :math:`[\gamma_j, \gamma_{j+1})` (the last band includes the upper end);
    values outside the domain are clamped into the first/last band.

    Args:
        variable: one of :data:`VARIABLES`.
        J: number of bands (ignored when ``edges`` is given).
        spacing: see :func:`band_edges`; default ``"sqrt"`` for ``theta_h`` (dense near the
            specular peak, like MERL's mapping), ``"top:sqrt"`` for ``anisotropy_ratio``
            (dense near :math:`\gamma_r = 1`, the highlight), ``"uniform"`` otherwise.
        edges: explicit increasing edges (J + 1,) covering the domain.
        symmetric: for ``theta_i``/``theta_o``, use the reciprocal basis
            :math:`\frac12(\mathbb 1_j(\theta_i) + \mathbb 1_j(\theta_o))`.
        n_u: the AS exponent, required for ``anisotropy_ratio``.
    """

    def __init__(
        self,
        variable: str = "theta_h",
        J: int = 64,
        spacing: str | float | None = None,
        edges=None,
        symmetric: bool = True,
        n_u: float | None = None,
    ):
        super().__init__()
        if variable not in VARIABLES:
            raise ValueRangeError(f"unknown band variable {variable!r}; expected one of {sorted(VARIABLES)}")
        self.variable = variable
        self.domain = VARIABLES[variable]
        if variable == "anisotropy_ratio":
            if n_u is None or not n_u > 0:
                raise ValueRangeError(f"the 'anisotropy_ratio' basis needs n_u > 0; got {n_u}")
            self.n_u = float(n_u)
        else:
            self.n_u = None
        self.symmetric = bool(symmetric) and variable in ("theta_i", "theta_o")
        if edges is not None:
            e = torch.as_tensor(edges, dtype=torch.float64).reshape(-1).clone()
            lo, hi = self.domain
            if e.numel() < 2 or bool((e[1:] <= e[:-1]).any()):
                raise ValueRangeError("band edges must be strictly increasing with at least 2 values")
            if abs(float(e[0]) - lo) > 1e-9 or abs(float(e[-1]) - hi) > 1e-9:
                got = f"[{float(e[0])}, {float(e[-1])}]"
                raise ValueRangeError(f"band edges must span the domain [{lo}, {hi}]; got {got}")
            e[0], e[-1] = lo, hi
            self.spacing = "custom"
        else:
            if spacing is None:
                spacing = {"theta_h": "sqrt", "anisotropy_ratio": "top:sqrt"}.get(variable, "uniform")
            self.spacing = spacing
            e = band_edges(J, spacing, self.domain)
        self.register_buffer("edges", e)

    @property
    def J(self) -> int:
        return self.edges.numel() - 1

    @property
    def anisotropic(self) -> bool:
        return self.variable == "anisotropy_ratio"

    def _apply(self, fn, recurse=True):
        # the edges define the bands: keep them float64 under .to(dtype)/.float()/.half(), so a
        # model converted to float32 has the same bands (and cache key) as in float64
        super()._apply(fn, recurse)
        if self.edges.dtype != torch.float64:
            self.edges = self.edges.to(torch.float64)
        return self

    def extra_repr(self) -> str:
        s = f"variable={self.variable!r}, J={self.J}, spacing={self.spacing!r}"
        if self.symmetric:
            s += ", symmetric=True"
        if self.n_u is not None:
            s += f", n_u={self.n_u}"
        return s

    def spec(self) -> dict:
        """JSON-able identity of the basis (variable, edges digest, symmetry, n_u) for cache keys."""
        digest = hashlib.sha256(self.edges.detach().cpu().double().numpy().tobytes()).hexdigest()[:16]
        return {
            "variable": self.variable,
            "J": self.J,
            "edges_sha": digest,
            "symmetric": self.symmetric,
            "n_u": None if self.n_u is None else self.n_u.hex(),
        }

    # -- the parameterisation -----------------------------------------------------------------
    def gamma(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        r""":math:`\gamma(\omega_i, \omega_o)` for local directions (*B, 3) -> (*B,).

        For the symmetric ``theta_i``/``theta_o`` basis returns the pair
        :math:`(\theta_i, \theta_o)`."""
        v = self.variable
        if v == "theta_h":
            h, _, _ = half_and_diff(wi, wo)
            return polar_angle(h)
        if v == "theta_d":
            return half_and_diff(wi, wo)[2]
        if v == "anisotropy_ratio":
            h, _, _ = half_and_diff(wi, wo)
            return anisotropy_ratio(h, self.n_u)
        ti, to = polar_angle(wi), polar_angle(wo)
        if self.symmetric:
            return ti, to
        return ti if v == "theta_i" else to

    def index(self, gamma: torch.Tensor) -> torch.Tensor:
        """Band id (long, same shape) of values ``gamma``; clamped into [0, J - 1]."""
        inner = self.edges[1:-1].to(gamma.dtype).contiguous()
        return torch.bucketize(gamma.detach().contiguous(), inner, right=True)

    def membership(self, wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r"""The bands of each pair as ``(a, b)``, long (*B,) each, with
        :math:`\sum_j c_j b_j = \frac12(c_a + c_b)` (``a == b`` for one-hot bases)."""
        g = self.gamma(wi, wo)
        if isinstance(g, tuple):
            return self.index(g[0]), self.index(g[1])
        k = self.index(g)
        return k, k

    def evaluate(self, c: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        r""":math:`f = \sum_j c_j b_j(\gamma(\omega_i, \omega_o))`.

        Args:
            c: (J, C) coefficients.
            wi: (*B, 3) local directions.
            wo: as ``wi``.
        Returns:
            (*B, C), differentiable in ``c``.
        """
        a, b = self.membership(wi, wo)
        if self.symmetric:
            return 0.5 * (c[a] + c[b])
        return c[a]

    def design(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Dense basis values :math:`b_j(\\omega_i, \\omega_o)`: (*B, J) (for tests and small problems)."""
        a, b = self.membership(wi, wo)
        eye = torch.eye(self.J, dtype=wi.dtype, device=wi.device)
        return 0.5 * (eye[a] + eye[b])

    # -- hierarchy ----------------------------------------------------------------------------
    def groups(self, J_new: int) -> torch.Tensor:
        """Coarse band of every fine band (J,) long, merging adjacent bands into ``J_new``
        contiguous groups of (nearly) equal count: fine band j -> floor(j J_new / J)."""
        if not 1 <= J_new <= self.J:
            raise ValueRangeError(f"J_new must lie in [1, {self.J}]; got {J_new}")
        return torch.arange(self.J) * J_new // self.J

    def coarsened(self, J_new: int) -> BandBasis:
        """The basis whose band g is the union of the fine bands of group g (:meth:`groups`)."""
        g = self.groups(J_new)
        first = torch.searchsorted(g, torch.arange(J_new))
        e = torch.cat([self.edges[first], self.edges[-1:]])
        return BandBasis(self.variable, edges=e, symmetric=self.symmetric, n_u=self.n_u)

    # -- sampling support ---------------------------------------------------------------------
    def band_solid_angles(self) -> torch.Tensor:
        r"""(J,) float64 solid angle of the direction set each band samples from
        (see :meth:`Factored1D.sample_local`): the ring :math:`\theta\in[\gamma_j,\gamma_{j+1})`
        about the normal for ``theta_h`` (half vectors) and ``theta_i``/``theta_o``, and the
        ring of angular radius :math:`[2\gamma_j, 2\gamma_{j+1})` about :math:`\omega_o` for
        ``theta_d`` (:math:`\omega_i\cdot\omega_o = \cos 2\theta_d`)."""
        e = self.edges
        if self.variable == "theta_d":
            e = 2 * e
        return 2 * math.pi * (torch.cos(e[:-1]) - torch.cos(e[1:]))
