r"""Inverse material design with global illumination through the polynomial tensors.

With every other object's coefficients held, the image is a polynomial in the edited objects'
band curves :math:`c_m` (Ben-Artzi et al. 2008, Eq. 26-28): the eye vertex is linear in
:math:`c_m`, later bounces see :math:`c_m` through its diffuse equivalent
:math:`d_m = \frac1\pi\sum_j c_{m,j} e_j` (App. B, Eq. 37) and the second-bounce coarsening
(both linear in :math:`c_m`). :func:`fit_image` minimises, per colour channel,

.. math:: L(c) = \tfrac12\sum_p w_p\,(B_p(c) - B^*_p)^2 + \tfrac\lambda2\sum_m\|D c_m\|^2
          \quad\text{s.t.}\quad c \ge 0,\qquad \tfrac1\pi\sum_j c_{m,j} e_{m,j} \le 1\ \ \forall m,

(the smoothness regulariser: :math:`D` takes first differences of each curve over adjacent
bands; ``smoothness`` = :math:`\lambda`, default 0) by projected Gauss-Newton: at the iterate
:math:`c_k` the residual is linearised, :math:`B(c) \approx B(c_k) + A(c - c_k)` with the exact
Jacobian :math:`A` from the renderer's own evaluation (the image is linear in the eye
coefficients for fixed :math:`d`: one plain frame per coefficient, all channels at once, plus one
forward-mode derivative in each :math:`d_m`; with a two-level series, forward-mode derivatives
per coefficient), and the constrained quadratic model

.. math:: \min_c\ \tfrac12 c^\top(A^\top W A + \lambda D^\top D + \mu I)c
          - (A^\top W (A c_k - r_k) + \mu c_k)^\top c

is solved exactly by the inverse-design QP solver (:func:`torch_brdf.inverse.solve_qp`: non-negative
bounds and the energy rows :math:`e_m/\pi`). A backtracking line search along the feasible
segment :math:`c_k \to c_{QP}` (the feasible set is convex, so every point on it is feasible)
keeps the loss monotone; :math:`\mu` (Levenberg damping, :math:`10^{-12}` of the largest
diagonal entry unless the step is rejected) makes singular systems (few painted pixels,
bands no painted pixel sees) well posed: the step is the smallest change that fits.

Evaluation is :class:`~torch_brdf.render.PolynomialRenderer` (frozen when one object is edited,
Eq. 28); nothing of its math is repeated here. The report (:class:`ImageFit`) holds the loss
curve and the KKT residual of the last iterate, computed from the last QP's multipliers.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.autograd.forward_ad as fwAD
from tqdm.auto import tqdm

from .._checks import as_float_tensor, check_finite
from ..data import progress_default
from ..errors import ShapeError, ValueRangeError
from ..inverse.qp import solve_qp
from ..inverse.strokes import paint_at, pixel_xy
from .polynomial import PolynomialRenderer, _term_factors

__all__ = ["ImageFit", "blinn_phong_family", "energy_row", "fit_image", "object_mask", "paint_image"]


@dataclass(frozen=True)
class ImageFit:
    """Result of :func:`fit_image`.

    Attributes:
        coefficients: object name -> (size, C) float64 fitted band coefficients.
        albedo: object name -> (C,) diffuse equivalent :math:`\\frac1\\pi\\sum_j c_j e_j` (<= 1).
        loss: final :math:`\\frac12\\sum_p w_p (B_p - B^*_p)^2` (summed over channels, without the
            regulariser).
        loss_curve: the loss before the first and after every iteration.
        kkt_residual: max over channels of the relative KKT residual of the last iterate
            (stationarity with the last QP's multipliers, complementarity, feasibility), each
            relative to :math:`\\max(\\|A^\\top W B^*\\|_\\infty, 10^{-300})`.
        violation: largest constraint violation (:math:`-c_j`, :math:`d - 1`), >= 0.
        iterations: Gauss-Newton iterations.
        converged: the relative loss change, the step or the KKT residual fell below ``tol``.
        image: (H, W, C) the render of the fitted coefficients (all pixels; one full frame of the
            renderer, evaluated on first access, not during the fit).
        parameters: object name -> (K, C) fitted :math:`\theta` of the objects fitted in a family.
    """

    coefficients: dict[str, torch.Tensor]
    albedo: dict[str, torch.Tensor]
    loss: float
    loss_curve: list[float]
    kkt_residual: float
    violation: float
    iterations: int
    converged: bool
    render: Callable[[], torch.Tensor] = field(repr=False, compare=False)
    parameters: dict[str, torch.Tensor] = field(default_factory=dict)

    @functools.cached_property
    def image(self) -> torch.Tensor:
        return self.render()


def energy_row(renderer: PolynomialRenderer, obj) -> torch.Tensor:
    r"""(size, C) float64: the row :math:`e_j/\pi` (layers stacked) with :math:`d = \sum_j row_j c_j`."""
    return torch.cat(renderer.albedo_weights(obj), 0) / math.pi


def blinn_phong_family(renderer: PolynomialRenderer, obj, exponent: float) -> torch.Tensor:
    r"""(size, 2) float64: the curves of Blinn-Phong (kd = 1, ks = 0) and (kd = 0, ks = 1) at
    ``exponent`` on ``obj``'s bands, projected by the renderer (:meth:`~PolynomialRenderer.set_material`),
    so that :math:`c = B\,(k_d, k_s)^\top` (the model is linear in kd and ks). The object's
    coefficients are restored."""
    m = renderer.tensors.object_id(obj)
    keep = (renderer.c[m], renderer.d[m], renderer.c_hat[m])
    cols = []
    for kd, ks in ((1.0, 0.0), (0.0, 1.0)):
        renderer.set_material(m, {"type": "blinn_phong", "kd": kd, "ks": ks, "exponent": float(exponent)})
        cols.append(renderer.c[m][:, 0].detach().double().clone())
    renderer.set_coefficients(m, keep[0], d=keep[1], c_hat=keep[2])
    return torch.stack(cols, 1)


def paint_image(image, strokes, mask, display_size=None, keep_weight: float = 1.0):
    """Painted strokes (Eq. 23 of the inverse-design seed, :func:`torch_brdf.inverse.paint`) as a
    target image and fit weights for :func:`fit_image`.

    Args:
        image: (H, W, C) the current render (strokes that scale colours scale these).
        strokes: list of :class:`~torch_brdf.inverse.Stroke` (points in the display frame).
        mask: (H, W) bool, the paintable pixels (e.g. :func:`object_mask` of the edited objects).
        display_size: ``(width, height)`` of the frame the stroke points refer to (default (W, H)).
        keep_weight: fit weight of unpainted pixels of ``mask`` (they keep their current colour;
            0: only the painted pixels count).
    Returns:
        (target (H, W, C) float64, weights (H, W) float64): painted colours over ``image``, and
        1 on painted pixels, ``keep_weight`` on the rest of ``mask``, 0 elsewhere.
    Raises:
        ShapeError: image or mask of the wrong shape; ValueRangeError: no stroke touches ``mask``.
    """
    img = as_float_tensor(image, "image").detach().double()
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ShapeError(f"Expected image of shape (H, W, 3); got {tuple(img.shape)}")
    H, W = img.shape[:2]
    m = torch.as_tensor(mask).bool()
    if m.shape != (H, W):
        raise ShapeError(f"Expected mask of shape ({H}, {W}); got {tuple(m.shape)}")
    pix = m.reshape(-1).nonzero().squeeze(1)
    st = paint_at(pixel_xy(pix, W, H, display_size), img.reshape(-1, 3)[pix], strokes, keep_weight)
    target = img.reshape(-1, 3).clone()
    target[pix] = st.target
    weights = torch.zeros(H * W, dtype=torch.float64)
    weights[pix] = st.weight
    return target.reshape(H, W, 3), weights.reshape(H, W)


def object_mask(tensors, obj) -> torch.Tensor:
    """(H, W) bool: the pixels whose eye ray sees ``obj`` (its first-bounce blocks)."""
    m = tensors.object_id(obj)
    out = torch.zeros(tensors.height * tensors.width, dtype=torch.bool)
    for b in tensors.blocks:
        if b.object_id == m and b.bounce == 1:
            out[b.pixels] = True
    return out.reshape(tensors.height, tensors.width)


def _diff(n: int, J: int) -> torch.Tensor:
    """First differences of each J-band layer of an n-vector: ((J - 1) n / J, n)."""
    rows = []
    for k in range(n // J):
        for j in range(J - 1):
            r = torch.zeros(n, dtype=torch.float64)
            r[k * J + j], r[k * J + j + 1] = -1.0, 1.0
            rows.append(r)
    return torch.stack(rows) if rows else torch.zeros(0, n, dtype=torch.float64)


class _Reduced:
    r"""The image on the painted pixels as a polynomial in the edited objects' curves, frozen once.

    With every other object's coefficients held (Eq. 27-28 generalised to several edited
    objects :math:`m \in E`), each painted pixel :math:`s` is

    .. math:: B_s = E_s + \sum_k g_k(d)\,\Big(\sum_{m\in E}\sum_j c_{m,j} F^m_{kjs} + V_{ks}\Big),
              \qquad g_k(d) = \prod_{m\in E} d_m^{\,n_{km}},

    :math:`k` running over the monomials of the edited diffuse equivalents that the stored terms
    hold (the other objects' factors are folded into :math:`F` and :math:`V`). ``F[m]`` is
    dense over the painted pixels that see object ``m`` directly: (C, K, J_m, S_m); ``V``
    (C, K, S), ``E`` (C, S). One pass over the stored entries builds it; afterwards an image,
    its loss and the exact Jacobian cost O(J K S) and no longer touch the full frame. Series
    without a second level and without weight maps only (:func:`fit_image` falls back to
    frame-by-frame evaluation otherwise). ``bases[m]`` (J_m, K_m): the curve is
    :math:`c_m = B_m y_m` and ``F`` is stored for :math:`y_m` (a family fit then never touches
    the J_m band axis again).
    """

    def __init__(
        self, renderer: PolynomialRenderer, ids: list[int], sel: torch.Tensor, bases: list[torch.Tensor] | None = None
    ):
        dt = renderer.dtype
        S = int(sel.sum())
        pos = torch.full((sel.numel(),), -1, dtype=torch.long)
        pos[sel] = torch.arange(S)
        d_all = renderer._d_all()
        masked, mono, expo = {}, {}, []
        keys: dict[tuple, int] = {}
        for n, table in renderer.tensors.terms.items():
            other = table.counts.clone()
            other[:, ids] = 0
            masked[n] = _term_factors(other, d_all).T  # (C, T): the held objects' d factors
            idx = []
            for row in table.counts[:, ids].tolist():
                idx.append(keys.setdefault(tuple(row), len(keys)))
            mono[n] = torch.tensor(idx, dtype=torch.long)
        expo = torch.tensor(sorted(keys, key=keys.get), dtype=torch.long).reshape(len(keys), len(ids))
        Km = max(len(keys), 1)
        own = {m: torch.zeros(S, dtype=torch.bool) for m in ids}
        for q, b in enumerate(renderer.blocks):
            if b.object_id in own:
                s = pos[renderer._coords[q][2]]
                own[b.object_id][s[s >= 0]] = True
        self.idx = [own[m].nonzero().squeeze(1) for m in ids]  # (S_m,) positions in S
        sizes = [renderer.tensors.bases[m].size for m in ids]
        F = [torch.zeros(3, Km * sz * ix.numel(), dtype=dt) for sz, ix in zip(sizes, self.idx, strict=True)]
        V = torch.zeros(3, Km * S, dtype=dt)
        for q, b in enumerate(renderer.blocks):
            j, t, pix = renderer._coords[q]
            s = pos[pix]
            keep = s >= 0
            if not bool(keep.any()):
                continue
            j, t, s = j[keep], t[keep], s[keep]
            vals = getattr(renderer, f"block{q}")[:, keep] * masked[b.bounce][:, t]
            k = mono[b.bounce][t]
            if b.object_id in own:
                e = ids.index(b.object_id)
                loc = torch.full((S,), -1, dtype=torch.long)
                loc[self.idx[e]] = torch.arange(self.idx[e].numel())
                F[e].index_add_(1, (k * sizes[e] + j) * self.idx[e].numel() + loc[s], vals)
            else:
                V.index_add_(1, k * S + s, vals * renderer._eye(b.object_id)[j].T)
        self.F = [f.reshape(3, Km, sz, -1) for f, sz in zip(F, sizes, strict=True)]
        if bases is not None:
            self.F = [F if b is None else b.T.to(dt) @ F for F, b in zip(self.F, bases, strict=True)]
        self.V = V.reshape(3, Km, S)
        self.E = renderer.emission[:, sel]
        self.expo = expo  # (K, M)
        self.S, self.dtype = S, dt

    def monomials(self, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """g (C, K) and dg/dd_m (M, C, K) at the diffuse equivalents d (M, C), by repeated products."""
        M, K = self.expo.shape[1], self.expo.shape[0]
        pw = [torch.ones(M, 3, dtype=d.dtype)]
        top = int(self.expo.max()) if self.expo.numel() else 0
        for _ in range(top):
            pw.append(pw[-1] * d)
        P = torch.stack(pw)  # (top + 1, M, C)
        fac = P[self.expo, torch.arange(M)[None, :]]  # (K, M, C): d_m^{n_km}
        g = fac.prod(1).T
        dg = torch.zeros(M, 3, K, dtype=d.dtype)
        for m in range(M):
            e = self.expo[:, m]
            lower = P[(e - 1).clamp_min(0), m] * e[:, None].to(d.dtype)  # n d^(n-1)
            rest = torch.cat([fac[:, :m], fac[:, m + 1 :]], 1).prod(1)
            dg[m] = (lower * rest).T
        return g, dg

    def _u(self, cs: list[torch.Tensor]) -> torch.Tensor:
        r"""(C, K, S): V plus each object's eye-linear part :math:`\sum_j c_j F_{kjs}`."""
        U = self.V.clone()
        for c, F, ix in zip(cs, self.F, self.idx, strict=True):
            part = (c.T.to(self.dtype)[:, None, None, :] @ F).squeeze(2)  # (C, K, S_m)
            U[:, :, ix] += part
        return U

    def image(self, cs: list[torch.Tensor], d: torch.Tensor) -> torch.Tensor:
        """(S, C) the painted pixels for curves cs[m] (J_m, C) and diffuse equivalents d (M, C)."""
        g, _ = self.monomials(d.to(self.dtype))
        return (self.E + (g[:, :, None] * self._u(cs)).sum(1)).T.double()

    def jacobian(self, cs: list[torch.Tensor], d: torch.Tensor, rows: list[torch.Tensor]) -> torch.Tensor:
        """(C, S, n) exact d image / d c (all curves stacked), with d = row . c."""
        g, dg = self.monomials(d.to(self.dtype))
        U = self._u(cs)
        cols = []
        for m, (F, ix) in enumerate(zip(self.F, self.idx, strict=True)):
            A = torch.zeros(3, self.S, F.shape[2], dtype=self.dtype)
            A[:, ix] = (g[:, None, :] @ F.flatten(2)).reshape(3, F.shape[2], -1).transpose(1, 2)
            dI = (dg[m][:, :, None] * U).sum(1)  # (C, S) d image / d d_m
            cols.append(A.double() + dI.double()[:, :, None] * rows[m].T[:, None, :])
        return torch.cat(cols, 2)


def _fit_inputs(H: int, W: int, target, weights, albedo_max: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``fit_image``'s target (H, W, 3) and weights (H, W, 3), float64, checked."""
    tgt = as_float_tensor(target, "target").to(torch.float64)
    if tgt.shape != (H, W, 3):
        raise ShapeError(f"Expected target of shape ({H}, {W}, 3); got {tuple(tgt.shape)}")
    check_finite(tgt, "target")
    w = torch.ones(H, W, 3, dtype=torch.float64) if weights is None else as_float_tensor(weights, "weights").double()
    if w.ndim == 2:
        w = w[..., None].expand(H, W, 3)
    if w.shape != (H, W, 3):
        raise ShapeError(f"Expected weights of shape ({H}, {W}[, 3]); got {tuple(w.shape)}")
    check_finite(w, "weights")
    if bool((w < 0).any()):
        raise ValueRangeError("weights must be >= 0")
    if not albedo_max > 0:
        raise ValueRangeError(f"albedo_max must be > 0; got {albedo_max}")
    return tgt, w


def _family_blocks(families: dict, ids: list[int], labels: list[str], sizes: list[int]) -> list[torch.Tensor]:
    """Per fitted object its matrix B (size, K): the family's, or the identity for a free curve."""
    blocks = []
    for k, (m, lab) in enumerate(zip(ids, labels, strict=True)):
        fam = families.get(lab, families.get(m))
        if fam is None:
            blocks.append(torch.eye(sizes[k], dtype=torch.float64))
        else:
            fam = as_float_tensor(fam, "family").double()
            if fam.ndim != 2 or fam.shape[0] != sizes[k] or bool((fam < 0).any()):
                raise ShapeError(
                    f"Expected a non-negative family matrix ({sizes[k]}, K) for {lab!r}; got {tuple(fam.shape)}"
                )
            blocks.append(fam)
    return blocks


def _losses(img: torch.Tensor, bp: torch.Tensor, wp: torch.Tensor) -> torch.Tensor:
    """Per channel (C,): half the weighted squared residual of the painted pixels (P, C)."""
    r = img - bp
    return 0.5 * (wp * r * r).sum(0)


def _gauss_newton_step(A, img, bp, wp, R2, y, G, h, scale, kkt) -> torch.Tensor:
    """The next iterate (nt, C): per channel the QP of the Gauss-Newton model at ``y`` with the
    Jacobian ``A`` (C, P, nt); fills ``scale`` and ``kkt`` (C,) (the KKT residual at ``y``)."""
    nt = y.shape[0]
    r = img - bp  # (P, C)
    y_new = y.clone()
    for ch in range(3):
        Aw = A[ch].T * wp[:, ch]
        Hc = Aw @ A[ch] + R2
        scale[ch] = max(float((Aw @ bp[:, ch]).abs().max()), float(Hc.abs().max()), 1e-300)
        mu = 1e-12 * max(float(Hc.diagonal().max()), 1e-300)
        g = Aw @ r[:, ch] + R2 @ y[:, ch]  # gradient of the loss at y
        f = Hc @ y[:, ch] - g + mu * y[:, ch]
        yq, u, z = _qp_step(Hc + mu * torch.eye(nt, dtype=torch.float64), f, G[ch], h)
        y_new[:, ch] = yq
        # KKT at the iterate: g + G^T u - z = 0, z y = 0, u (G y - h) = 0
        stat = (g + G[ch].T @ u - z).abs().max()
        comp = max(float((z * y[:, ch]).abs().max()), float((u * (G[ch] @ y[:, ch] - h)).abs().max()))
        kkt[ch] = max(float(stat), comp) / scale[ch]
    return y_new


def _backtrack(y, y_new, img, lc, frame, losses, reg):
    """Backtracking per channel (the loss is separable in the channels): (iterate, its image,
    its losses) of the longest step to ``y_new`` (halved per channel up to 40 times) that does
    not raise the channel's loss; ``y`` itself when none does."""
    step = y_new - y
    alpha = torch.ones(3, dtype=torch.float64)
    base = lc + reg(y)
    for _ in range(40):
        trial = y + step * alpha
        timg = frame(trial)
        tl = losses(timg)
        bad = (tl + reg(trial)) > base * (1 + 1e-15) + 1e-300
        if not bool(bad.any()):
            return trial, timg, tl
        alpha = torch.where(bad, alpha * 0.5, alpha)
    return y, img, lc


class _FitModel:
    """The image of ``fit_image``'s variables y (c = B y) on the painted pixels and its exact
    Jacobian: through the reduced tensors (``red``) when they exist, else the renderer."""

    def __init__(self, renderer, ids, splits, pspl, sel, B, rows, rows_y, red):
        self.renderer, self.ids, self.splits, self.pspl, self.sel = renderer, ids, splits, pspl, sel
        self.B, self.rows, self.rows_y, self.red = B, rows, rows_y, red
        self.n, self.dt = B.shape[0], renderer.dtype

    def render(self, xc):
        for k, m in enumerate(self.ids):
            self.renderer.set_coefficients(m, xc[self.splits[k] : self.splits[k + 1]].to(self.dt))
        return self.renderer()

    def parts(self, yc):
        """The fitted variables per object and the diffuse equivalents (M, C)."""
        ys = [yc[self.pspl[k] : self.pspl[k + 1]] for k in range(len(self.ids))]
        return ys, torch.stack([(r * v).sum(0) for r, v in zip(self.rows_y, ys, strict=True)])

    def frame(self, yc):
        """(P, C): the painted pixels."""
        if self.red is not None:
            return self.red.image(*self.parts(yc))
        return self.render(self.B @ yc).detach().reshape(-1, 3)[self.sel].double()

    def jacobian(self, xc):
        """(C, P, nt): d image / d y, exact (y are the curves c or family parameters)."""
        if self.red is not None:
            return self.red.jacobian(*self.parts(xc), self.rows_y)
        xc = self.B @ xc
        if self.renderer.two_level:
            return self._jacobian_dual(xc) @ self.B
        # the image is linear in the eye coefficients c for fixed diffuse equivalents d
        # (Eq. 26/28), and d = row . c: columns = (image(e_i; d) - image(0; d)) + dI/dd * row_i
        renderer, ids, splits, dt, sel = self.renderer, self.ids, self.splits, self.dt, self.sel
        self.render(xc)
        ds = [renderer.d[m].detach().clone() for m in ids]

        def plain(xe):
            for k, m in enumerate(ids):
                renderer.set_coefficients(m, xe[splits[k] : splits[k + 1]].to(dt), d=ds[k])
            return renderer().detach().reshape(-1, 3)[sel].double()

        zero = torch.zeros(self.n, 3, dtype=torch.float64)
        base = plain(zero)
        cols = []
        for i in range(self.n):
            e = zero.clone()
            e[i] = 1.0
            cols.append(plain(e) - base)
        A = torch.stack(cols, -1)  # (P, C, n)
        for k in range(len(ids)):
            with fwAD.dual_level():
                for q, mm in enumerate(ids):
                    dq = ds[q].to(dt)
                    if q == k:
                        dq = fwAD.make_dual(dq, torch.ones_like(dq))
                    renderer.set_coefficients(mm, xc[splits[q] : splits[q + 1]].to(dt), d=dq)
                tangent = fwAD.unpack_dual(renderer()).tangent  # None: no bounce sees d (1 bounce)
            if tangent is not None:
                dd = tangent.reshape(-1, 3)[sel].double()  # (P, C)
                A[:, :, splits[k] : splits[k + 1]] += dd[:, :, None] * self.rows[k].T[None]
        return A.permute(1, 0, 2) @ self.B

    def _jacobian_dual(self, xc):
        """Forward mode, one pass per coefficient (all channels at once)."""
        cols = []
        for i in range(self.n):
            with fwAD.dual_level():
                t = torch.zeros(self.n, 3, dtype=torch.float64)
                t[i] = 1.0
                img = self.render(fwAD.make_dual(xc, t))
                cols.append(fwAD.unpack_dual(img).tangent.reshape(-1, 3)[self.sel].double())
        return torch.stack(cols, -1).permute(1, 0, 2)


def fit_image(
    renderer: PolynomialRenderer,
    objects,
    target,
    weights=None,
    init: dict | None = None,
    smoothness: float = 0.0,
    max_iter: int = 30,
    tol: float = 1e-12,
    albedo_max: float = 1.0,
    families: dict | None = None,
    progress: bool | None = None,
) -> ImageFit:
    r"""Fit the band curves of ``objects`` so that the render matches ``target`` on the painted pixels.

    Args:
        renderer: a :class:`PolynomialRenderer` holding the other objects' materials (use
            ``max_bounces=1`` for the direct-lighting-only fit). Its dtype should be float64
            for tight fits. The fitted coefficients are left set on it.
        objects: an editable object name (or id) or a list of them.
        target: (H, W, C) target image (a painted image, or a full render).
        weights: (H, W) or (H, W, C) fit weights >= 0 (the stroke mask); default all ones.
        init: object -> (size, C) starting coefficients; default the renderer's current ones.
        smoothness: :math:`\lambda` of the first-difference regulariser (see the module).
        max_iter: Gauss-Newton iterations.
        tol: stop when the loss changes by less than ``tol`` relative (or the step is zero).
        albedo_max: the bound on each object's diffuse equivalent d (energy conservation: 1).
        families: object -> (size, K) non-negative matrix B: fit the K parameters
            :math:`\theta \ge 0` of the curve :math:`c = B\theta` instead of the free curve
            (a library BRDF linear in its parameters, e.g. :func:`blinn_phong_family`: kd and
            ks at a fixed exponent); ``ImageFit.parameters`` holds :math:`\theta` (K, C).
        progress: tqdm bar over the iterations (None: on in a terminal or notebook).
    Returns:
        :class:`ImageFit`.
    Raises:
        ShapeError: target or weights of the wrong shape.
        ValueRangeError: negative weights, NaN/Inf, ``albedo_max <= 0``.
    """
    names = [objects] if isinstance(objects, (str, int)) else list(objects)
    if not names:
        raise ValueRangeError("fit_image needs at least one object")
    tgt, w = _fit_inputs(renderer.height, renderer.width, target, weights, albedo_max)
    sel = w.reshape(-1, 3).sum(1) > 0
    wp = w.reshape(-1, 3)[sel]  # (P, C)
    bp = tgt.reshape(-1, 3)[sel]
    ids = [renderer.tensors.object_id(o) for o in names]
    labels = [renderer.tensors.object_names[m] for m in ids]
    rows = [energy_row(renderer, m) for m in ids]
    sizes = [r.shape[0] for r in rows]
    n = sum(sizes)
    splits = torch.tensor([0] + sizes).cumsum(0).tolist()
    init = init or {}
    x = torch.zeros(n, 3, dtype=torch.float64)
    for k, (m, lab) in enumerate(zip(ids, labels, strict=True)):
        c0 = init.get(lab, init.get(m, renderer.c[m]))
        c0 = as_float_tensor(c0, "init").detach().double().reshape(sizes[k], -1).expand(sizes[k], 3)
        x[splits[k] : splits[k + 1]] = c0
    G = torch.zeros(3, len(ids), n, dtype=torch.float64)  # per channel: one energy row per object
    for k, r in enumerate(rows):
        G[:, k, splits[k] : splits[k + 1]] = r.T
    h = torch.full((len(ids),), float(albedo_max), dtype=torch.float64)
    D = torch.block_diag(*[_diff(s, renderer.tensors.bases[m].J) for s, m in zip(sizes, ids, strict=True)])
    R2 = smoothness * (D.T @ D) if smoothness else torch.zeros(n, n, dtype=torch.float64)
    # the fitted variables y: c = B y (B = identity for free curves)
    families = families or {}
    blocks = _family_blocks(families, ids, labels, sizes)
    psizes = [b.shape[1] for b in blocks]
    B = torch.block_diag(*blocks)
    pspl = torch.tensor([0] + psizes).cumsum(0).tolist()
    y = torch.linalg.lstsq(B, x).solution.clamp_min(0) if families else x
    G, R2 = G @ B, B.T @ R2 @ B
    y = _project_start(y, G, h)
    x = B @ y
    fast = not renderer.two_level and not renderer.weight_maps
    red = _Reduced(renderer, ids, sel, [blocks[k] if families else None for k in range(len(ids))]) if fast else None
    rows_y = [b.T @ r for b, r in zip(blocks, rows, strict=True)]  # d = rows_y . y
    if not fast and len(ids) == 1 and renderer.frozen_object != labels[0]:
        renderer.freeze(ids[0])
    dt = renderer.dtype
    model = _FitModel(renderer, ids, splits, pspl, sel, B, rows, rows_y, red)
    frame, losses = model.frame, lambda img: _losses(img, bp, wp)
    reg = lambda yc: 0.5 * torch.einsum("jc,jk,kc->c", yc, R2, yc)  # noqa: E731
    img = frame(y)
    lc = losses(img)
    curve = [float(lc.sum())]
    scale = torch.ones(3, dtype=torch.float64)
    kkt = torch.zeros(3, dtype=torch.float64)
    converged, iters = False, 0
    bar = tqdm(total=max_iter, desc="fit image", unit="iter", disable=not progress_default(progress))
    for iters in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
        y_new = _gauss_newton_step(model.jacobian(y), img, bp, wp, R2, y, G, h, scale, kkt)
        trial, timg, tl = _backtrack(y, y_new, img, lc, frame, losses, reg)
        moved = float((trial - y).abs().max())
        y, img, old = trial, timg, float(lc.sum())
        x = B @ y
        lc = tl
        curve.append(float(lc.sum()))
        bar.update(1)
        bar.set_postfix(loss=f"{curve[-1]:.4g}")
        if abs(old - curve[-1]) <= tol * max(old, 1e-300) or moved == 0.0 or float(kkt.max()) <= tol:
            converged = True
            break
    bar.close()
    coeffs = {lab: x[splits[k] : splits[k + 1]].clone() for k, lab in enumerate(labels)}
    params = {
        lab: y[pspl[k] : pspl[k + 1]].clone()
        for k, lab in enumerate(labels)
        if psizes[k] != sizes[k] or lab in families
    }
    alb = {lab: (rows[k] * coeffs[lab]).sum(0) for k, lab in enumerate(labels)}
    viol = max(float((-x).clamp_min(0).max()), max(float((a - albedo_max).clamp_min(0).max()) for a in alb.values()))
    for k, m in enumerate(ids):
        renderer.set_coefficients(m, x[splits[k] : splits[k + 1]].to(dt))

    def final() -> torch.Tensor:
        return model.render(x).detach()

    return ImageFit(coeffs, alb, curve[-1], curve, float(kkt.max()), viol, iters, converged, final, params)


def _qp_step(H: torch.Tensor, f: torch.Tensor, G: torch.Tensor, h: torch.Tensor):
    """The QP step (x, row multipliers, bound multipliers): the unconstrained minimiser
    :math:`H^{-1} f` when it is feasible (then it is the QP's solution, all multipliers 0),
    else :func:`~torch_brdf.inverse.solve_qp` (interior point + polishing)."""
    try:
        x = torch.linalg.solve(H, f)
        if bool(torch.isfinite(x).all()) and bool((x >= 0).all()) and bool((G @ x <= h).all()):
            return x, torch.zeros(G.shape[0], dtype=x.dtype), torch.zeros_like(x)
    except RuntimeError:  # singular to working precision: the QP's interior point copes
        pass
    q = solve_qp(H, f, G, h)
    return q.x, q.row_dual, q.bound_dual


def _project_start(x: torch.Tensor, G: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """A feasible start: clamp to >= 0, then scale each object's curve down to its energy bound."""
    x = x.clamp_min(0)
    for ch in range(3):
        for k in range(G.shape[1]):
            on = G[ch, k] != 0
            d = float(G[ch, k] @ x[:, ch])
            if d > float(h[k]):
                x[on, ch] = x[on, ch] * (float(h[k]) / d)
    return x
