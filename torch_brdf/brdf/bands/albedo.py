r"""Equivalent (diffuse) albedo of factored BRDFs (Ben-Artzi et al. 2008, Appendix B).

The paper picks the diffuse equivalent of a BRDF to match "the output power for a uniform
incident radiance field" (Eq. 36):

.. math::
    d = \frac1\pi\iint\rho(\omega_i, \omega_o)\cos\theta_i\cos\theta_o\,d\omega_i\,d\omega_o
      = \frac1\pi\sum_j c_j e_j, \qquad
    e_j = \iint\rho_q(\omega_i, \omega_o)\,b_j(\gamma(\omega_i, \omega_o))
          \cos\theta_i\cos\theta_o\,d\omega_i\,d\omega_o \quad (37).

So :math:`d` is the bihemispherical reflectance: the directional albedo
:math:`a(\omega_o) = \int\rho\cos\theta_i\,d\omega_i` averaged over outgoing directions with
the weight :math:`\cos\theta_o/\pi` (equivalently, the cosine-weighted average over incident
directions, by reciprocity). A Lambertian :math:`\rho = a/\pi` has :math:`d = a`, and
:math:`\sum_j e_j = \pi^2` for :math:`\rho_q = 1`. Note that :math:`e_j` itself is
:math:`\pi` times the bihemispherical albedo of :math:`\rho_q b_j`; we keep the paper's
normalisation so that Eq. 37 reads as printed.

:math:`e_j` depends only on the parameterisation (basis variable, band edges, symmetry,
quotient), not on the scene, so it is computed once by dense seeded Monte Carlo in float64
and cached on disk (:func:`band_albedos`). The estimator is stratified per band: each band
gets the same number of samples with the band variable jittered-stratified inside the band,
so narrow bands (the first :math:`\theta_h` bands are :math:`\sim 10^{-5}` rad wide at
J = 256) are as precise as wide ones; within a band the four sample coordinates form a
Latin hypercube (each jittered-stratified in its marginal), which stays unbiased. Per variable, with :math:`u` uniform:

* ``theta_h``: :math:`\theta_h` uniform in the band, :math:`\phi_h` uniform, :math:`\omega_d`
  cosine-weighted; weight :math:`\Delta_j\sin\theta_h\cdot2\pi\cdot4\pi` (from
  :math:`d\omega_i d\omega_o = 4\cos\theta_d\,d\omega_h\,d\omega_d`).
* ``theta_d``: :math:`\theta_d` uniform in the band, :math:`\phi_d` uniform, :math:`h`
  cosine-weighted; weight :math:`\Delta_j\sin\theta_d\,2\pi\cdot4\cos\theta_d\cdot\pi/\cos\theta_h`.
* ``theta_i`` (``theta_o``): that angle uniform in the band, its azimuth uniform, the other
  direction cosine-weighted; weight :math:`\Delta_j\sin\theta\cos\theta\,2\pi\cdot\pi`.
  The symmetric basis averages the two halves.
* ``anisotropy_ratio``: :math:`\phi_h` from a tabulated proposal :math:`\propto` the
  interval length below (exact pdf), then :math:`\cos\theta_h` uniform on the
  interval where :math:`\gamma_r = \cos\theta_h^{\,n_u\sin^2\phi_h}` lies in the band,
  :math:`[a^{1/k}, b^{1/k}]` with :math:`k = n_u\sin^2\phi_h`; :math:`\omega_d` cosine-weighted.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings

import torch
from tqdm.auto import tqdm

from ...data import cache_dir
from ...errors import FileFormatError, ValueRangeError
from ...frame import half_diff_to_directions, spherical_angles
from ...io.arrays import load_arrays, save_arrays
from ...sphere.warps import square_to_cosine_hemisphere
from .basis import BandBasis
from .quotients import Quotient, make_quotient

__all__ = ["EquivalentAlbedoCacheWarning", "band_albedos", "cache_dir", "equivalent_albedo"]

#: bump when the estimator changes, so old cache entries are not reused
ESTIMATOR_VERSION = 1
_KIND = "equivalent-albedo"


class EquivalentAlbedoCacheWarning(UserWarning):
    """A cache entry could not be read (corrupt, wrong kind or version) and was recomputed,
    or could not be written."""


def _key(basis: BandBasis, quotient: Quotient, samples_per_band: int, seed: int) -> tuple[str, dict]:
    spec = {
        "estimator": ESTIMATOR_VERSION,
        "basis": basis.spec(),
        "quotient": quotient.key,
        "samples_per_band": int(samples_per_band),
        "seed": int(seed),
    }
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:32], spec


def band_albedos(
    basis: BandBasis,
    quotient: str | Quotient = "one",
    samples_per_band: int = 16384,
    seed: int = 0,
    cache: bool = True,
    progress: bool | None = None,
) -> torch.Tensor:
    r""":math:`e_j` of Eq. 37 for every band, by per-band stratified Monte Carlo (float64).

    Computed once per parameterisation (basis variable, edges, symmetry, :math:`n_u`,
    quotient, ``samples_per_band``, ``seed``) and cached in
    ``cache_dir()/equivalent_albedo/<sha256 of that>.npz`` through
    :func:`torch_brdf.io.save_arrays` (atomic, checksummed). A corrupt or unreadable entry
    is recomputed with an :class:`EquivalentAlbedoCacheWarning`. The computation runs band
    chunk by band chunk with a tqdm bar; interrupting it (Ctrl-C) raises
    ``KeyboardInterrupt`` and writes nothing, so the cache never holds partial results.

    Args:
        basis: the bands.
        quotient: :math:`\rho_q` (name or :class:`Quotient`; RGB quotients give (J, 3)).
        samples_per_band: Monte Carlo samples per band (per half for the symmetric
            ``theta_i``/``theta_o`` basis).
        seed: seed of the torch generator.
        cache: read and write the disk cache.
        progress: show a progress bar (None: only on a terminal).
    Returns:
        e: (J,) or (J, 3) float64; :math:`\sum_j e_j \approx \pi^2` for :math:`\rho_q = 1`.
    """
    if samples_per_band < 1:
        raise ValueRangeError(f"samples_per_band must be >= 1; got {samples_per_band}")
    q = make_quotient(quotient)
    key, spec = _key(basis, q, samples_per_band, seed)
    path = cache_dir() / "equivalent_albedo" / f"{key}.npz"
    if cache and path.exists():
        try:
            arrays, meta = load_arrays(path, kind=_KIND)
            if meta.get("spec") != json.loads(json.dumps(spec)) or "e" not in arrays:
                raise FileFormatError(f"{path}: cache entry does not match its key")
            return torch.from_numpy(arrays["e"]).to(torch.float64)
        except FileFormatError as exc:
            msg = f"equivalent-albedo cache entry unusable, recomputing: {exc}"
            warnings.warn(msg, EquivalentAlbedoCacheWarning, stacklevel=2)
    e = _compute(basis, q, samples_per_band, seed, progress)
    if cache:
        try:
            save_arrays(path, {"e": e.numpy()}, kind=_KIND, meta={"spec": spec})
        except OSError as exc:  # a read-only cache must not break rendering
            msg = f"could not write the equivalent-albedo cache ({exc}); continuing without it"
            warnings.warn(msg, EquivalentAlbedoCacheWarning, stacklevel=2)
    return e


def _compute(basis: BandBasis, q: Quotient, n: int, seed: int, progress: bool | None) -> torch.Tensor:
    gen = torch.Generator().manual_seed(int(seed))
    edges = basis.edges.detach().double().cpu()
    J = basis.J
    out = torch.zeros(J, q.channels, dtype=torch.float64)
    halves = ("i", "o") if basis.symmetric else (None,)
    step = max(1, (1 << 18) // n)
    disable = None if progress is None else not progress  # None: tqdm shows a bar only on a terminal
    with tqdm(total=J * len(halves), desc="equivalent albedo e_j", unit="band", disable=disable, leave=False) as bar:
        for half in halves:
            for s in range(0, J, step):
                js = torch.arange(s, min(J, s + step))
                out[js] += _estimate(basis, q, edges, js, n, gen, half) / len(halves)
                bar.update(len(js))
    return out[:, 0] if q.channels == 1 else out


def _estimate(
    basis: BandBasis, q: Quotient, edges: torch.Tensor, js: torch.Tensor, n: int, gen: torch.Generator, half
) -> torch.Tensor:
    """Mean estimates of e_j for the bands ``js``: (len(js), C)."""
    dt = torch.float64
    m = js.numel()
    a, b = edges[js][:, None], edges[js + 1][:, None]  # (m, 1)
    # Latin hypercube per band: every coordinate is jittered-stratified in its marginal
    perm = torch.argsort(torch.rand(m, 4, n, generator=gen, dtype=dt), dim=-1)
    lhs = ((perm + torch.rand(m, 4, n, generator=gen, dtype=dt)) / n).permute(0, 2, 1)  # (m, n, 4)
    strata, u = lhs[..., 0], lhs[..., 1:]
    var = basis.variable
    if var in ("theta_h", "anisotropy_ratio"):
        phi_h, pdf_phi = 2 * math.pi * u[..., 0], torch.full_like(u[..., 0], 1 / (2 * math.pi))
        if var == "anisotropy_ratio":
            phi_h, pdf_phi = _ratio_azimuths(basis.n_u, a, b, u[..., 0])
        wd = square_to_cosine_hemisphere(u[..., 1:].reshape(-1, 2)).reshape(m, n, 3)
        theta_d, phi_d = spherical_angles(wd)
        if var == "theta_h":
            theta_h = a + (b - a) * strata
            # 4 cos(theta_d) of the measure over the cosine pdf cos(theta_d)/pi of omega_d -> 4 pi
            weight = (b - a) * torch.sin(theta_h) * (2 * math.pi) * (4 * math.pi)
        else:
            k = basis.n_u * torch.sin(phi_h) ** 2
            inv = torch.where(k > 0, 1 / k, torch.full_like(k, math.inf))
            lo, hi = a.clamp_min(0) ** inv, b**inv  # cos(theta_h) interval of the band
            ct = lo + (hi - lo) * strata
            theta_h = torch.acos(ct.clamp(-1.0, 1.0))
            weight = (hi - lo) / pdf_phi * (4 * math.pi)
        wi, wo = half_diff_to_directions(theta_h, phi_h, theta_d, phi_d)
    elif var == "theta_d":
        theta_d = a + (b - a) * strata
        phi_d = 2 * math.pi * u[..., 0]
        hv = square_to_cosine_hemisphere(u[..., 1:].reshape(-1, 2)).reshape(m, n, 3)
        theta_h, phi_h = spherical_angles(hv)
        wi, wo = half_diff_to_directions(theta_h, phi_h, theta_d, phi_d)
        ch = hv[..., 2].clamp_min(1e-300)  # cosine pdf of h: cos(theta_h)/pi
        weight = (b - a) * torch.sin(theta_d) * (2 * math.pi) * 4 * torch.cos(theta_d) * math.pi / ch
    else:  # theta_i / theta_o: the banded direction is "wb", the other one cosine-weighted
        which = half if half is not None else ("i" if var == "theta_i" else "o")
        theta = a + (b - a) * strata
        phi = 2 * math.pi * u[..., 0]
        st = torch.sin(theta)
        wb = torch.stack((st * torch.cos(phi), st * torch.sin(phi), torch.cos(theta)), -1)
        wc = square_to_cosine_hemisphere(u[..., 1:].reshape(-1, 2)).reshape(m, n, 3)
        wi, wo = (wb, wc) if which == "i" else (wc, wb)
        # cos(theta_b) sin(theta_b) dtheta dphi for the banded one; pi / cos for the cosine one
        weight = (b - a) * st * torch.cos(theta) * (2 * math.pi) * math.pi
        val = q(wi, wo).to(dt)
        val = val if val.ndim == 3 else val.unsqueeze(-1)
        ok = ((wi[..., 2] > 0) & (wo[..., 2] > 0)).unsqueeze(-1)
        return torch.where(ok, val * weight.unsqueeze(-1), 0.0).mean(1)
    ci, co = wi[..., 2], wo[..., 2]
    ok = (ci > 0) & (co > 0)
    val = q(wi, wo).to(dt)
    val = val if val.ndim == 3 else val.unsqueeze(-1)
    w = torch.where(ok, weight * ci.clamp_min(0) * co.clamp_min(0), 0.0)
    return (val * w.unsqueeze(-1)).mean(1)


def _ratio_azimuths(n_u: float, a: torch.Tensor, b: torch.Tensor, u: torch.Tensor, per_quadrant: int = 128):
    r"""Azimuths for the ``anisotropy_ratio`` bands, drawn piecewise-constant in proportion to
    the length :math:`L(\phi) = b^{1/k} - a^{1/k}` of the band's :math:`\cos\theta_h`
    interval (tabulated at cell centres, mixed 9:1 with uniform-in-angle). :math:`L` changes
    fastest where :math:`k = n_u\sin^2\phi \to 0`, so the cells are cubically refined towards
    :math:`\phi = 0, \pi` (smallest ~:math:`10^{-6}` rad). Returns (phi, pdf), (m, n) each."""
    t = (torch.arange(per_quadrant + 1, dtype=u.dtype) / per_quadrant) ** 3 * (math.pi / 2)
    edges = torch.cat([t, math.pi - t.flip(0)[1:], math.pi + t[1:], 2 * math.pi - t.flip(0)[1:]])
    width = edges[1:] - edges[:-1]
    pc = 0.5 * (edges[1:] + edges[:-1])
    k = n_u * torch.sin(pc) ** 2
    inv = torch.where(k > 0, 1 / k, torch.full_like(k, math.inf))
    length = b**inv - a.clamp_min(0) ** inv  # (m, cells)
    mass = length * width
    tot = mass.sum(-1, keepdim=True)
    uni = width / (2 * math.pi)
    prob = torch.where(tot > 0, 0.9 * mass / tot.clamp_min(1e-300), 0.9 * uni) + 0.1 * uni
    cdf = torch.cumsum(prob, -1)
    cdf[:, -1] = 1.0
    cell = torch.searchsorted(cdf, u.contiguous(), right=True).clamp_max(width.numel() - 1)
    lo = torch.where(cell > 0, cdf.gather(1, (cell - 1).clamp_min(0)), torch.zeros_like(u))
    p = prob.gather(1, cell)
    frac = ((u - lo) / p).clamp(0.0, 1.0)
    return edges[cell] + frac * width[cell], p / width[cell]


def equivalent_albedo(factored, e: torch.Tensor | None = None, **kwargs) -> torch.Tensor:
    r"""Diffuse-equivalent albedo :math:`d = \frac1\pi\sum_j c_j e_j` (Eq. 37), RGB.

    Differentiable in the coefficients. For a :class:`~.factored.FresnelFactored1D` the band
    albedos of its full Fresnel quotient are used.

    Args:
        factored: a :class:`~.factored.Factored1D` (anything with ``basis``,
            ``coefficients`` and ``albedo_quotient()``).
        e: (J,) or (J, 3) precomputed :math:`e_j`; default :func:`band_albedos` of the
            factored BRDF's basis and quotient with ``kwargs``.
    Returns:
        d: (3,) in the coefficients' dtype.
    """
    if e is None:
        e = band_albedos(factored.basis, factored.albedo_quotient(), **kwargs)
    c = factored.coefficients
    e = e.to(c)
    e = e.unsqueeze(-1) if e.ndim == 1 else e
    if e.shape[0] != c.shape[0]:
        raise ValueRangeError(f"e has {e.shape[0]} bands, the factored BRDF {c.shape[0]}")
    return (c * e).sum(0) / math.pi
