"""Loading and validating triangle meshes.

Policy for bad meshes (documented here and in the scenes guide):

* NaN/Inf vertex coordinates (or beyond float32, which embree traces), face indices out of
  range, or no faces at all raise
  :class:`~torch_brdf.errors.MeshError` naming the mesh: there is no safe repair.
* Zero-area (degenerate) faces — repeated or collinear vertices, judged on the float32
  coordinates that embree traces — are dropped with a :class:`DegenerateFacesWarning` that
  says how many; if every face is degenerate, :class:`MeshError` is raised. Dropping keeps
  the remaining triangle ids dense, so ``prim_id`` indexes the cleaned mesh.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import trimesh

from ..errors import FileFormatError, MeshError


class DegenerateFacesWarning(UserWarning):
    """Some faces of a mesh had zero area and were dropped."""


def load_mesh(path: str | Path, name: str | None = None) -> trimesh.Trimesh:
    """Read an OBJ/PLY/... file with trimesh (no processing) and validate it.

    Multi-part files are concatenated into one mesh.

    Raises:
        FileFormatError: the file is missing or trimesh cannot read it.
        MeshError: see :func:`validate_mesh`.
    """
    path = Path(path)
    label = name or path.name
    if not path.is_file():
        raise FileFormatError(f"mesh file not found: {path}")
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except (ValueError, KeyError, IndexError, OSError, TypeError, NotImplementedError) as exc:
        raise FileFormatError(f"cannot read mesh {path}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise FileFormatError(f"mesh file {path} holds no triangle mesh (got {type(loaded).__name__})")
    return validate_mesh(loaded, label)


def validate_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """Check a mesh and return a cleaned copy (degenerate faces dropped, see module doc).

    Args:
        mesh: a trimesh mesh (not modified).
        name: used in error messages.
    Returns:
        A new ``trimesh.Trimesh`` with float64 vertices and int64 faces, ``process=False``.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"mesh {name!r}: vertices must have shape (V, 3); got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MeshError(f"mesh {name!r}: needs at least one triangle face (F, 3); got {f.shape}")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise MeshError(f"mesh {name!r}: {int(bad.sum())} vertices have NaN/Inf coordinates")
    big = (np.abs(v) > np.finfo(np.float32).max).any(axis=1)
    if big.any():  # embree traces float32: these would become Inf there
        raise MeshError(
            f"mesh {name!r}: {int(big.sum())} vertices exceed the float32 range "
            f"(max {np.finfo(np.float32).max:.4g}, largest here {np.abs(v).max():.4g}); rescale the mesh"
        )
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"mesh {name!r}: face indices outside [0, {len(v)}) (min {f.min()}, max {f.max()})")
    # judged on the float32 coordinates embree traces: a face is degenerate when its edges
    # are (numerically) parallel, |e1 x e2| <= 1e-7 |e1| |e2|, so its normal is undefined
    tri = v.astype(np.float32).astype(np.float64)[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cross = np.linalg.norm(np.cross(e1, e2), axis=1)
    degenerate = cross <= 1e-7 * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    if degenerate.all():
        raise MeshError(f"mesh {name!r}: all {len(f)} faces have zero area")
    if degenerate.any():
        warnings.warn(
            f"mesh {name!r}: dropped {int(degenerate.sum())} of {len(f)} zero-area faces",
            DegenerateFacesWarning,
            stacklevel=2,
        )
        f = f[~degenerate]
    return trimesh.Trimesh(vertices=v, faces=f.astype(np.int64), process=False)


def mesh_from_arrays(vertices, faces, name: str = "mesh") -> trimesh.Trimesh:
    """Build and validate a mesh from (V, 3) vertices and (F, 3) faces."""
    try:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"mesh {name!r}: vertices and faces must be numeric arrays: {exc}") from exc
    if v.ndim != 2 or v.shape[-1] != 3:
        raise MeshError(f"mesh {name!r}: vertices must have shape (V, 3); got {v.shape}")
    if f.size % 3 or f.size == 0:
        raise MeshError(f"mesh {name!r}: faces must hold 3 indices per triangle; got {f.size} indices")
    return validate_mesh(trimesh.Trimesh(vertices=v, faces=f.reshape(-1, 3), process=False), name)
