r"""Rendering interpolated materials by blending (seed Sec. 3.3).

* (a) Fixed view, direct lighting (seed Eq. 8): :math:`I_* = \sum_i b_i I_i`. The per-material
  images are one :class:`~torch_brdf.records.BasisImage` with ``J = N`` materials
  (:func:`~torch_brdf.manifold.materials.material_record`), so blending is ``record.image(b)``.
* (c) Global illumination (seed Eq. 11-12): images :math:`I_i` rendered with full path tracing
  are blended the same way; this drops the paths that meet the edited material twice or more
  (:math:`L_{2+}`). :func:`gi_blend_error` measures that error against a true render of the
  interpolated BRDF.

Renders use :func:`torch_brdf.transport.pathtrace.path_trace` with the material as a
``"merl"`` table (:class:`~torch_brdf.brdf.measured.MERLTabulated`, nearest lookup). That
lookup treats negative entries as missing (0), so an interpolant with negative values is
rendered clamped at 0 (:func:`~torch_brdf.manifold.materials.merl_material`): blending and
rendering-the-blend then differ by exactly the negative part (the seed's stated limitation);
with ``max_bounces=1`` and a fixed seed the path tracer is otherwise exactly linear in a non-negative table (NEE and the
continuation directions do not depend on the table), which the tests check.
"""

from __future__ import annotations

import torch
from tqdm.auto import tqdm

from ..data import progress_default
from ..errors import ShapeError
from ..manifold.data import MERLGrid
from ..manifold.materials import merl_material, with_material
from ..metrics import relative_l1, relative_rmse
from ..records.basis_image import BasisImage
from ..scene.scene import Scene
from ..transport.pathtrace import PathTraceSettings, path_trace


def render_rows(
    scene: Scene,
    material_key: str,
    rows: torch.Tensor,
    grid: MERLGrid,
    spp: int = 4,
    max_bounces: int = 1,
    seed: int = 0,
    progress: bool | None = None,
) -> torch.Tensor:
    """Path-trace ``scene`` once per row of ``Z`` used as the material ``material_key``.

    The same seed for every material, so the images share their random numbers (the blend
    of images then has no extra noise against a render of the blend).

    Args:
        rows: (N, 3 * B) BRDF rows on ``grid``.
    Returns:
        (N, H, W, 3) float32 linear radiance.
    """
    rows = torch.as_tensor(rows)
    if rows.ndim != 2:
        raise ShapeError(f"Expected rows of shape (N, 3 * B); got {tuple(rows.shape)}")
    out = []
    for r in tqdm(rows, desc="render materials", disable=not progress_default(progress)):
        sc = with_material(scene, material_key, merl_material(r, grid))
        out.append(path_trace(sc, PathTraceSettings(spp=spp, max_bounces=max_bounces), seed=seed, progress=False))
    return torch.stack(out)


def blend(record: BasisImage, weights: torch.Tensor) -> torch.Tensor:
    """Seed Eq. 8 / 12: :math:`I_* = \\sum_i b_i I_i` as an (H, W, C) image from ``weights`` (N,)."""
    return record.image(torch.as_tensor(weights).to(record.values.dtype))


def gi_blend_error(blended: torch.Tensor, reference: torch.Tensor) -> dict[str, float]:
    """Relative errors of a blended GI image against a render of the interpolated BRDF.

    Returns:
        ``{"rel_l1": sum|a-b| / sum|b|, "rel_rmse": rms(a-b) / rms(b)}`` (:mod:`torch_brdf.metrics`).
    Raises:
        ShapeError: the shapes differ; ValueRangeError: the reference is all zero.
    """
    return {"rel_l1": relative_l1(blended, reference), "rel_rmse": relative_rmse(blended, reference)}


__all__ = ["blend", "gi_blend_error", "render_rows"]
