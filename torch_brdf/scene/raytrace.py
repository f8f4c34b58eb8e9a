r"""Ray tracing on torch tensors with embreex.

:class:`RayTracer` puts every scene object into one embree scene as its own geometry,
so embree's ``geomID`` is the object id and ``primID`` the triangle index inside that
object. Rays go in and :class:`Hits` come out as torch tensors; the per-ray work after
embree (positions, normals) is a handful of batched gathers, no Python loop per ray.

Embree traces in float32. Positions are interpolated from the triangle's vertices with
the hit's barycentrics (more accurate on the surface than ``o + t d``), geometric normals
are the counter-clockwise face normals :math:`\mathrm{normalize}((v_1-v_0)\times(v_2-v_0))`
(trimesh's convention, *not* flipped towards the ray), shading normals interpolate the
vertex normals of smooth objects and equal the geometric normal on flat ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from embreex import mesh_construction, rtcore_scene

from .._checks import check_vectors
from ..errors import ShapeError

#: embree leaves ``tfar`` at this value on a miss (we report ``inf`` instead).
_EMBREE_FAR = 1e37


@dataclass(frozen=True)
class Hits:
    """Closest hits of a batch of P rays. Misses have ``object_id == -1``.

    Attributes:
        t: (P,) ray parameter of the hit (distance for unit directions); ``inf`` on a miss.
        object_id: (P,) int64 scene object index; -1 on a miss.
        prim_id: (P,) int64 triangle index within that object; -1 on a miss.
        barycentrics: (P, 2) embree's (u, v): position = (1-u-v) v0 + u v1 + v v2.
        position: (P, 3) hit point; 0 on a miss.
        geometric_normal: (P, 3) unit counter-clockwise face normal; 0 on a miss.
        normal: (P, 3) unit shading normal; 0 on a miss.
    """

    t: torch.Tensor
    object_id: torch.Tensor
    prim_id: torch.Tensor
    barycentrics: torch.Tensor
    position: torch.Tensor
    geometric_normal: torch.Tensor
    normal: torch.Tensor

    @property
    def hit(self) -> torch.Tensor:
        """(P,) bool, True where the ray hit something."""
        return self.object_id >= 0

    def __len__(self) -> int:
        return self.t.shape[0]


def _rays_to_numpy(origins, directions) -> tuple[np.ndarray, np.ndarray, torch.dtype]:
    o = check_vectors(origins, "origins")
    d = check_vectors(directions, "directions")
    if o.shape != d.shape:
        raise ShapeError(
            f"Expected origins and directions of the same shape; got {tuple(o.shape)} and {tuple(d.shape)}"
        )
    dtype = o.dtype
    o_np = np.ascontiguousarray(o.detach().to(torch.float32).cpu().numpy())
    d_np = np.ascontiguousarray(d.detach().to(torch.float32).cpu().numpy())
    return o_np, d_np, dtype


class RayTracer:
    """An embree scene over a list of meshes, one geometry per mesh.

    Args:
        meshes: the objects' meshes, in object-id order.
        smooth: per mesh, whether shading normals interpolate vertex normals (True) or
            equal the face normal (False).
    """

    def __init__(self, meshes: Sequence[trimesh.Trimesh], smooth: Sequence[bool]):
        if len(meshes) == 0:
            raise ShapeError("RayTracer needs at least one mesh")
        self._scene = rtcore_scene.EmbreeScene()
        verts, faces, vnormals, fnormals = [], [], [], []
        offsets_v, offsets_f = [0], [0]
        for m in meshes:
            v = np.asarray(m.vertices, dtype=np.float32)
            f = np.asarray(m.faces, dtype=np.int32)
            mesh_construction.TriangleMesh(self._scene, v, f)
            verts.append(v)
            faces.append(f.astype(np.int64) + offsets_v[-1])
            tri = v.astype(np.float64)[f]
            fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            fn /= np.linalg.norm(fn, axis=1, keepdims=True)
            fnormals.append(fn)
            vnormals.append(np.asarray(m.vertex_normals, dtype=np.float64))
            offsets_v.append(offsets_v[-1] + len(v))
            offsets_f.append(offsets_f[-1] + len(f))
        self.num_objects = len(meshes)
        self.vertices = torch.from_numpy(np.concatenate(verts))  # (V, 3) float32
        self.faces = torch.from_numpy(np.concatenate(faces))  # (F, 3) global vertex ids
        self.face_normals = torch.from_numpy(np.concatenate(fnormals).astype(np.float32))
        self.vertex_normals = torch.from_numpy(np.concatenate(vnormals).astype(np.float32))
        self.face_offsets = torch.tensor(offsets_f[:-1], dtype=torch.int64)
        self.smooth = torch.tensor([bool(s) for s in smooth], dtype=torch.bool)
        if len(self.smooth) != len(meshes):
            raise ShapeError(f"smooth has {len(self.smooth)} flags for {len(meshes)} meshes")
        lo, hi = self.vertices.min(0).values.double(), self.vertices.max(0).values.double()
        self.bbox = (lo, hi)
        extent = float((hi - lo).norm())
        magnitude = float(torch.maximum(lo.abs(), hi.abs()).max())
        #: distance by which ray origins are pushed off surfaces (self-intersection).
        self.ray_epsilon = max(1e-5 * extent, 64 * float(np.finfo(np.float32).eps) * magnitude, 1e-7)

    # -- queries ---------------------------------------------------------------------------
    def trace(self, origins, directions) -> Hits:
        """Closest hit of each ray.

        Args:
            origins: (P, 3) ray origins (already offset from surfaces, see :meth:`spawn`).
            directions: (P, 3) ray directions (unit length for ``t`` to be a distance).
        Returns:
            :class:`Hits` with fields in the dtype of ``origins``.
        """
        o_np, d_np, dtype = _rays_to_numpy(origins, directions)
        res = self._scene.run(o_np, d_np, output=1)
        return self._hits_from_embree(res, dtype)

    def occluded(self, origins, directions, t_max) -> torch.Tensor:
        """Whether anything lies on each ray within ``(0, t_max)``.

        Args:
            origins: (P, 3); directions: (P, 3); t_max: (P,) or a scalar (``inf`` allowed).
        Returns:
            (P,) bool tensor.
        """
        o_np, d_np, _ = _rays_to_numpy(origins, directions)
        tm = torch.as_tensor(t_max, dtype=torch.float32).expand(o_np.shape[0])
        tm_np = np.ascontiguousarray(tm.clamp(max=_EMBREE_FAR).detach().cpu().numpy())
        res = self._scene.run(o_np, d_np, dists=tm_np, query="OCCLUDED")
        return torch.from_numpy(res != -1)

    def spawn(self, position, geometric_normal, directions) -> torch.Tensor:
        """Ray origins pushed off a surface to the side ``directions`` leave towards.

        Args:
            position: (P, 3) surface points; geometric_normal: (P, 3) unit normals;
            directions: (P, 3) outgoing directions.
        Returns:
            (P, 3) origins ``position + sign(d . n) * ray_epsilon * n``.
        """
        side = torch.where((directions * geometric_normal).sum(-1, keepdim=True) >= 0, 1.0, -1.0)
        return position + (side * self.ray_epsilon).to(position.dtype) * geometric_normal

    # -- internals -------------------------------------------------------------------------
    def _hits_from_embree(self, res: dict, dtype: torch.dtype) -> Hits:
        geom = torch.from_numpy(res["geomID"]).long()
        hit = geom >= 0
        g = geom.clamp_min(0)
        prim = torch.where(hit, torch.from_numpy(res["primID"]).long(), -1)
        gface = torch.where(hit, self.face_offsets[g] + prim, 0)
        u = torch.from_numpy(res["u"])
        v = torch.from_numpy(res["v"])
        tri = self.faces[gface]  # (P, 3)
        w = torch.stack((1 - u - v, u, v), -1)  # (P, 3)
        pos = torch.einsum("pk,pkc->pc", w, self.vertices[tri])
        ng = self.face_normals[gface]
        ns = torch.einsum("pk,pkc->pc", w, self.vertex_normals[tri])
        ns = torch.where(self.smooth[g][:, None], ns, ng)
        ns = ns / ns.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        m = hit[:, None]
        zero = pos.new_zeros(())
        t = torch.where(hit, torch.from_numpy(res["tfar"]), float("inf"))
        return Hits(
            t=t.to(dtype),
            object_id=torch.where(hit, geom, -1),
            prim_id=prim,
            barycentrics=torch.where(m, torch.stack((u, v), -1), zero).to(dtype),
            position=torch.where(m, pos, zero).to(dtype),
            geometric_normal=torch.where(m, ng, zero).to(dtype),
            normal=torch.where(m, ns, zero).to(dtype),
        )
