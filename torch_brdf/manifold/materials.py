r"""The BRDF manifold's material records and scene (seed Sec. 3.3), with no rendering.

* :func:`material_record`: the per-material images as one
  :class:`~torch_brdf.records.BasisImage` with ``J = N`` materials, so that blending them
  (:func:`torch_brdf.render.manifold.blend`) is ``record.image(b)``;
* :func:`merl_material` / :func:`with_material`: a row of ``Z`` as a ``"merl"`` scene material
  (negative interpolant values clamped at 0, which is what the MERL lookup does anyway);
* :func:`sphere_scene`: the sphere-on-a-plane scene the manifold's materials are shown in.

The images themselves are rendered by :func:`torch_brdf.render.manifold.render_rows`.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence

import torch
import trimesh

from ..errors import SceneError, ShapeError
from ..records.basis_image import BasisImage
from ..scene.camera import Camera
from ..scene.envmap import EnvironmentMap
from ..scene.mesh import mesh_from_arrays
from ..scene.scene import Scene, SceneObject
from .data import MERLGrid, to_table

__all__ = ["material_record", "merl_material", "random_record", "sphere_scene", "with_material"]


def sphere_scene(resolution: int = 64, envmap: EnvironmentMap | None = None) -> Scene:
    """A sphere (icosphere, radius 0.8) on a grey plane under an environment map (default: the sky).

    The sphere's material is ``"sample"`` (replaced per material); the plane is Lambert 0.5.
    """
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    sphere.apply_translation([0, 0.8, 0])
    s = 10.0
    plane = mesh_from_arrays([(-s, 0, -s), (-s, 0, s), (s, 0, s), (s, 0, -s)], [[0, 1, 2], [0, 2, 3]], "plane")
    objects = [
        SceneObject("sample", mesh_from_arrays(sphere.vertices, sphere.faces, "sample"), "sample", smooth=True),
        SceneObject("plane", plane, "plane", editable=False),
    ]
    materials = {
        "sample": {"type": "lambert", "albedo": (0.5, 0.5, 0.5)},
        "plane": {"type": "lambert", "albedo": (0.5, 0.5, 0.5)},
    }
    env = envmap if envmap is not None else EnvironmentMap.sky(sun_radiance=(600.0, 570.0, 520.0))
    cam = Camera((0.0, 1.6, -3.2), (0.0, 0.7, 0.0), (0.0, 1.0, 0.0), 35.0, resolution, resolution)
    return Scene(objects, materials, [env], cam, name="manifold_sphere")


def merl_material(row: torch.Tensor, grid: MERLGrid) -> dict:
    """A scene material dict (``"merl"``, nearest lookup) for one row of ``Z`` on ``grid``.

    Negative values (possible for interpolants) are clamped to 0, which is what the MERL lookup
    would do with them anyway; invalid (below-horizon) bins are missing (-1).
    """
    t = to_table(torch.as_tensor(row, dtype=torch.float64).clamp_min(0), grid)
    th, td, pd = grid.indices
    return {"type": "merl", "table": t, "theta_h_index": th, "theta_d_index": td, "phi_d_index": pd}


def with_material(scene: Scene, material_key: str, material: dict) -> Scene:
    """A copy of ``scene`` with ``materials[material_key]`` replaced."""
    if material_key not in scene.materials:
        raise SceneError(f"scene {scene.name!r} has no material {material_key!r}; it has {sorted(scene.materials)}")
    return dataclasses.replace(scene, materials={**scene.materials, material_key: material})


def material_record(
    images: torch.Tensor, names: Sequence[str] = (), constant: torch.Tensor | None = None, meta: dict | None = None
) -> BasisImage:
    """The per-material images as one :class:`BasisImage` (``J = N`` materials, ``values (C, N, P)``).

    The image is *affine* in the BRDF (seed Sec. 3.3: paths that never meet the material do not
    depend on it). With ``constant`` = the render with a black material (all-zero row), the record
    holds ``I_i - constant`` and ``constant``, so ``record.image(b) = constant + sum_i b_i (I_i -
    constant)`` is exact for any weights; without it, ``sum_i b_i I_i`` (seed Eq. 8) is exact only
    when ``sum_i b_i = 1`` or nothing but the material is visible.

    Args:
        images: (N, H, W, C) one image per training material (in the fit's row order).
        names: material names (recorded in the basis label's digest and ``meta``).
        constant: (H, W, C) render with the material set to zero, or None.
    """
    images = torch.as_tensor(images)
    if images.ndim != 4:
        raise ShapeError(f"Expected images of shape (N, H, W, C); got {tuple(images.shape)}")
    digest = hashlib.sha256("\n".join(names).encode()).hexdigest()[:8] if names else "unnamed"
    if constant is not None:
        constant = torch.as_tensor(constant).to(images.dtype)
        if constant.shape != images.shape[1:]:
            raise ShapeError(f"Expected constant of shape {tuple(images.shape[1:])}; got {tuple(constant.shape)}")
        images = images - constant
    return BasisImage.from_dense(
        images,
        constant=constant,
        basis=f"materials:{images.shape[0]}:{digest}",
        meta={**(meta or {}), "names": list(names), "affine": constant is not None},
    )


def random_record(n: int, height: int, width: int, generator: torch.Generator | None = None) -> BasisImage:
    """A synthetic (N, H, W, 3) material record with random values (for timing the blend only)."""
    v = torch.rand(3, n, height * width, generator=generator)
    return BasisImage(v, torch.arange(height * width), height, width, basis=f"materials:{n}:random")
