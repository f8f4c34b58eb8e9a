r"""The per-vertex visibility record of all-frequency relighting (Inger et al., Sec. 4.2 and 5).

:class:`VertexVisibility` is what :func:`~torch_brdf.transport.visibility.precompute_visibility`
produces and :class:`~torch_brdf.render.triple.TripleProductRenderer` reads: the scene's
vertices (:class:`SceneVertices`, fingerprinted so a record cannot be used with another scene)
and their differential block visibility (:class:`~torch_brdf.records.visibility_codec.BlockVisibility`)
in the cubemap layout of :class:`~torch_brdf.sphere.cubemap.CubemapBlocks`. The conventions
the maps follow (horizon, graded maps) are stated in :mod:`torch_brdf.transport.visibility`.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from .._checks import MAX_SUPERSAMPLE, check_count
from ..errors import FileFormatError, SceneError
from ..scene.scene import Scene
from ..sphere.cubemap import CubemapBlocks
from .codec import Member, Record
from .visibility_codec import BlockVisibility, PackedBlockVisibility

__all__ = ["KIND", "SceneVertices", "VertexVisibility", "scene_vertices"]

KIND = "vertex-visibility"


@dataclass(frozen=True)
class SceneVertices:
    """The shading vertices of a scene: all objects' vertices, in object order.

    Attributes:
        positions: (P, 3) float64.
        normals: (P, 3) float64 unit vertex normals.
        object_ids: (P,) int64.
        offsets: (O + 1,) int64; object ``o`` owns rows ``offsets[o]:offsets[o+1]``.
    """

    positions: torch.Tensor
    normals: torch.Tensor
    object_ids: torch.Tensor
    offsets: torch.Tensor

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def fingerprint(self) -> str:
        """SHA-256 of the float32 positions and normals (ties a record to its scene)."""
        h = hashlib.sha256()
        for a in (self.positions, self.normals):
            h.update(a.to(torch.float32).numpy().tobytes())
        return h.hexdigest()


def scene_vertices(scene: Scene) -> SceneVertices:
    """Collect the scene's vertices and unit vertex normals (trimesh's area-weighted ones)."""
    pos, nrm, oid, off = [], [], [], [0]
    for o, obj in enumerate(scene.objects):
        v = torch.tensor(np.array(obj.mesh.vertices), dtype=torch.float64)
        n = torch.tensor(np.array(obj.mesh.vertex_normals), dtype=torch.float64)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        pos.append(v)
        nrm.append(n)
        oid.append(torch.full((len(v),), o, dtype=torch.int64))
        off.append(off[-1] + len(v))
    if off[-1] == 0:
        raise SceneError(f"scene {scene.name!r} has no vertices")
    return SceneVertices(torch.cat(pos), torch.cat(nrm), torch.cat(oid), torch.tensor(off, dtype=torch.int64))


def _check_vertices(v: SceneVertices) -> None:
    """Shapes and indices of loaded vertices within their ranges, as the polynomial record's
    (a checksummed file can still come from a faulty writer: an object id past the last object
    failed later as an IndexError, offsets that skip vertices shaded them with another material).

    Raises:
        FileFormatError: the first inconsistency, naming the array.
    """
    p = v.positions.shape[0]
    for what, x, shape in (
        ("positions", v.positions, (p, 3)),
        ("normals", v.normals, (p, 3)),
        ("object_ids", v.object_ids, (p,)),
    ):
        if tuple(x.shape) != shape:
            raise FileFormatError(f"vertex {what} {tuple(x.shape)}: expected {shape}")
    off = v.offsets
    if off.ndim != 1 or off.numel() < 2 or int(off[0]) != 0 or int(off[-1]) != p or bool((off.diff() < 0).any()):
        raise FileFormatError(
            f"object_offsets {off.tolist() if off.numel() <= 8 else tuple(off.shape)}: expected (O + 1,) "
            f"rising from 0 to the {p} vertices"
        )
    owner = torch.repeat_interleave(torch.arange(off.numel() - 1), off.diff())
    if not torch.equal(v.object_ids.long(), owner):
        bad = int((v.object_ids.long() != owner).nonzero()[0])
        raise FileFormatError(
            f"object_ids: vertex {bad} has object {int(v.object_ids[bad])}, its offsets say {int(owner[bad])} "
            f"(objects 0..{off.numel() - 2})"
        )


@dataclass(frozen=True)
class VertexVisibility(Record):
    """Differential visibility of every scene vertex.

    Attributes:
        geometry: the cubemap and block layout.
        vertices: the vertices the maps belong to.
        blocks: (P vertices x NB blocks) differential visibility: a
            :class:`~torch_brdf.records.visibility_codec.PackedBlockVisibility` (the file's
            varint stream, as :meth:`load` and the precompute give it: memory proportional
            to the file) or an in-memory
            :class:`~torch_brdf.records.visibility_codec.BlockVisibility`; a renderer reads
            the vertices it shades through ``blocks.select(ids)`` either way.
        supersample: k, rays per texel side (1 = binary maps).
        bits: derivative quantisation (0 = binary).
    """

    geometry: CubemapBlocks
    vertices: SceneVertices
    blocks: BlockVisibility | PackedBlockVisibility
    supersample: int = 1
    bits: int = 0

    kind = KIND
    version = 1
    schema: ClassVar[dict[str, Member]] = {
        "stream": Member("u", 1),
        "vertex_offsets": Member("iu", 1),
        "positions": Member("f", 2, finite=True),
        "normals": Member("f", 2, finite=True),
        "object_ids": Member("iu", 1),
        "object_offsets": Member("iu", 1),
    }

    @property
    def bytes_per_vertex(self) -> float:
        """Mean size of the varint-serialised maps per vertex (what :meth:`save` stores)."""
        return float(self.blocks.nbytes_per_vertex)

    def settings(self) -> dict:
        return {
            "resolution": self.geometry.resolution,
            "block": self.geometry.block,
            "supersample": self.supersample,
            "bits": self.bits,
            "vertices": len(self.vertices),
            "fingerprint": self.vertices.fingerprint,
            "entries": self.blocks.num_entries,
        }

    def check_scene(self, scene: Scene) -> None:
        """Raise SceneError unless the record was computed for this scene's vertices."""
        fp = scene_vertices(scene).fingerprint
        if fp != self.vertices.fingerprint:
            raise SceneError(
                f"visibility record does not belong to scene {scene.name!r} (vertex fingerprint differs); "
                "recompute it with precompute_visibility"
            )

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """The varint stream and the vertices for :meth:`save` (versioned, checksummed, atomic)."""
        stream, voff = self.blocks.to_bytes()
        v = self.vertices
        arrays = {
            "stream": np.asarray(stream, dtype=np.uint8),
            "vertex_offsets": np.asarray(voff, dtype=np.int64),
            "positions": v.positions.numpy(),
            "normals": v.normals.numpy(),
            "object_ids": v.object_ids.numpy(),
            "object_offsets": v.offsets.numpy(),
        }
        return arrays, self.settings()

    @classmethod
    def from_arrays(cls, arrays, meta) -> VertexVisibility:
        """The record of :meth:`to_arrays` output (FileFormatError if inconsistent)."""
        geom = CubemapBlocks(int(meta["resolution"]), int(meta["block"]))
        verts = SceneVertices(
            torch.from_numpy(arrays["positions"]),
            torch.from_numpy(arrays["normals"]),
            torch.from_numpy(arrays["object_ids"]),
            torch.from_numpy(arrays["object_offsets"]),
        )
        _check_vertices(verts)
        if len(verts) != int(meta["vertices"]) or arrays["vertex_offsets"].shape != (len(verts) + 1,):
            raise FileFormatError(
                f"{arrays['vertex_offsets'].size - 1} maps for {len(verts)} vertices (header: {meta['vertices']})"
            )
        # kept as the file's stream (checked in full, a run of vertices at a time): memory about the
        # file's size, where the CSR arrays took 11 bytes per vertex-block pair
        blocks = PackedBlockVisibility.from_bytes(
            arrays["stream"], arrays["vertex_offsets"], geom.block_count, int(meta["bits"])
        )
        if "entries" in meta and blocks.num_entries != int(meta["entries"]):
            raise FileFormatError(f"{blocks.num_entries} entries decoded, header says {meta['entries']}")
        if verts.fingerprint != meta["fingerprint"]:
            raise FileFormatError("vertex arrays do not match the stored fingerprint")
        supersample = check_count(meta["supersample"], "supersample", MAX_SUPERSAMPLE)  # the input's cap
        return cls(geom, verts, blocks, supersample, int(meta["bits"]))
