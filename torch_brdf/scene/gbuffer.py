r"""What the camera sees: the G-buffer of its primary rays.

:func:`trace_gbuffer` casts one ray through each pixel centre and keeps the pixels that hit
the scene (or only some objects) as one :class:`GBuffer` record: per kept pixel the object
and triangle hit, the hit point, geometric and shading normals, depth and the direction
back to the eye, plus the triangle's corner vertices and barycentric weights (for renderers
that shade vertices and interpolate, such as the relighting renderer). Renderers and
precomputations that work on "the pixels of a view" take this record instead of casting
primary rays of their own; :class:`~torch_brdf.scene.raytrace.Hits` stays the result of a
ray query.

Everything is float64. Embree traces in float32 (the positions and normals carry float32
rounding); the normals are renormalised in float64 so that shading frames built on them are
orthonormal to float64 precision (otherwise local directions are off unit length by ~1e-7).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import SceneError
from .camera import Camera
from .scene import Scene

__all__ = ["GBuffer", "trace_gbuffer"]

F64 = torch.float64


@dataclass(frozen=True)
class GBuffer:
    r"""The primary hits of a view, one row per kept pixel (P rows), float64.

    Vertex ids number the scene's vertices object by object, in object order (the numbering
    of :class:`~torch_brdf.scene.raytrace.RayTracer` and of the visibility records).

    Attributes:
        height, width: frame size in pixels.
        eye: (3,) the camera position.
        pixels: (P,) int64 flat row-major indices into the ``height x width`` frame.
        object_id: (P,) int64 scene object hit.
        prim_id: (P,) int64 triangle hit, within its object.
        position: (P, 3) hit points.
        geometric_normal: (P, 3) unit counter-clockwise face normals.
        normal: (P, 3) unit shading normals.
        depth: (P,) distance from the eye to the hit.
        wo: (P, 3) unit directions from the hit towards the eye.
        vertex_ids: (V,) int64 sorted ids of the vertices of the triangles hit.
        corners: (P, 3) int64 rows into ``vertex_ids`` of each hit triangle's corners.
        weights: (P, 3) barycentric weights of the corners, :math:`(1-u-v, u, v)`.
    """

    height: int
    width: int
    eye: torch.Tensor
    pixels: torch.Tensor
    object_id: torch.Tensor
    prim_id: torch.Tensor
    position: torch.Tensor
    geometric_normal: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    wo: torch.Tensor
    vertex_ids: torch.Tensor
    corners: torch.Tensor
    weights: torch.Tensor

    @property
    def count(self) -> int:
        """P, the number of kept pixels."""
        return self.pixels.shape[0]

    @property
    def mask(self) -> torch.Tensor:
        """(H, W) bool: the kept pixels."""
        m = torch.zeros(self.height * self.width, dtype=torch.bool)
        m[self.pixels] = True
        return m.view(self.height, self.width)

    def select(self, rows: torch.Tensor) -> GBuffer:
        """The G-buffer of some of the rows (``rows``: (P,) bool or (K,) int64 indices), with
        ``vertex_ids`` and ``corners`` narrowed to the triangles still hit."""
        per_row = (self.pixels, self.object_id, self.prim_id, self.position, self.geometric_normal)
        per_row += (self.normal, self.depth, self.wo)
        vids, corners = _vertex_rows(self.vertex_ids[self.corners[rows]])
        return GBuffer(
            self.height, self.width, self.eye, *(x[rows] for x in per_row), vids, corners, self.weights[rows]
        )

    @classmethod
    def of_vertices(cls, vertex_ids: torch.Tensor, eye, height: int, width: int) -> GBuffer:
        """A G-buffer that covers no pixel but names vertices seen from ``eye`` ((3,)): for
        shading vertices without an image (baselines, tests)."""
        none = torch.zeros(0, dtype=torch.int64)
        v3 = torch.zeros(0, 3, dtype=F64)
        vids = torch.as_tensor(vertex_ids, dtype=torch.int64)
        e = torch.as_tensor(eye, dtype=F64).reshape(3)
        return cls(height, width, e, none, none, none, v3, v3, v3, none.to(F64), v3, vids, none.view(0, 3), v3)


def _vertex_rows(global_corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(V,) sorted vertex ids of (P, 3) corner ids and the (P, 3) rows into them."""
    vids, inverse = torch.unique(global_corners.reshape(-1), return_inverse=True)
    return vids, inverse.view(-1, 3)


def trace_gbuffer(
    scene: Scene, camera: Camera | None = None, objects: str | int | Sequence[str | int] | None = None
) -> GBuffer:
    """Cast one primary ray per pixel centre and keep the pixels that hit the scene.

    Args:
        scene: the scene.
        camera: the view (default ``scene.camera``); e.g. ``scene.camera.with_size(160, 120)``.
        objects: keep only the pixels whose closest hit is this object or one of these
            objects (names or ids); default every hit.
    Returns:
        :class:`GBuffer` of the kept pixels, in row-major pixel order.
    Raises:
        SceneError: an unknown object, or ``objects`` given and covering no pixel of the view.
    """
    cam = camera if camera is not None else scene.camera
    o, d = cam.generate_rays(dtype=F64)
    hits = scene.trace(o.float(), d.float())  # embree's float32 either way; rows kept go to float64 below
    keep = hits.hit
    if objects is not None:
        wanted = [objects] if isinstance(objects, str | int) else list(objects)
        ids = [scene.object_id(x) if isinstance(x, str) else int(x) for x in wanted]
        for i in ids:
            if not 0 <= i < len(scene.objects):
                raise SceneError(f"object id {i} out of range for {len(scene.objects)} objects")
        keep = torch.isin(hits.object_id, torch.tensor(ids, dtype=torch.int64))
        if not bool(keep.any()):
            names = [scene.objects[i].name for i in ids]
            raise SceneError(f"objects {names} cover no pixel of the {cam.width}x{cam.height} view")
    idx = keep.nonzero().squeeze(1)
    obj, prim = hits.object_id[idx], hits.prim_id[idx]
    tracer = scene.tracer
    vids, corners = _vertex_rows(tracer.faces[tracer.face_offsets[obj] + prim])
    uv = hits.barycentrics[idx].to(F64)
    return GBuffer(
        height=cam.height,
        width=cam.width,
        eye=torch.tensor(cam.origin, dtype=F64),
        pixels=idx,
        object_id=obj,
        prim_id=prim,
        position=hits.position[idx].to(F64),
        geometric_normal=F.normalize(hits.geometric_normal[idx].to(F64), dim=-1),
        normal=F.normalize(hits.normal[idx].to(F64), dim=-1),
        depth=hits.t[idx].to(F64),
        wo=-d[idx],
        vertex_ids=vids,
        corners=corners,
        weights=torch.stack((1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]), -1),
    )
