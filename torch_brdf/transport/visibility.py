r"""Per-vertex visibility cubemaps by ray casting (Inger et al., Sec. 4.2 and 5).

Every vertex of the scene gets a ``6 x R x R`` cubemap in the one world orientation of
:class:`~torch_brdf.sphere.cubemap.CubemapBlocks`, split into ``16 x 16`` blocks and stored
differentially (:class:`~torch_brdf.transport.visibility_codec.BlockVisibility`): binary maps
as the indices where visibility flips, anti-aliased maps from ``k x k`` supersampled binary
rays with quantised derivatives.

Conventions (fixed here, relied on by :mod:`torch_brdf.render.triple`):

- a texel is visible when its centre direction is above the vertex's tangent plane
  (``n . w > HORIZON_EPS`` with the vertex normal) and the ray from the vertex escapes the scene;
  texels below the horizon are 0, so the renderer may use the unclamped cosine;
- graded maps: the fraction of the ``k x k`` sub-texel rays that escape (the horizon test
  stays at the texel centre), quantised to ``2^bits - 1`` levels;
- vertices are those of the scene's objects in order, with the meshes' vertex normals
  (smooth objects interpolate them for shading as well).

:func:`precompute_visibility` works in chunks of vertices; each finished chunk is written
atomically to a checkpoint folder, so an interrupted run resumes where it stopped and gives
the same record. Ray casting is deterministic, so the record does not depend on the
chunking or on the number of ray-casting processes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .._checks import MAX_CUBEMAP_RESOLUTION, check_count, check_int
from ..errors import FileFormatError, SceneError, ValueRangeError
from ..io.arrays import load_arrays, save_arrays
from ..scene.scene import Scene
from ..sphere.cubemap import CubemapBlocks
from .visibility_codec import BlockVisibility

__all__ = ["SceneVertices", "VertexVisibility", "precompute_visibility", "scene_vertices"]

KIND = "vertex-visibility"
CHUNK_KIND = "vertex-visibility-chunk"
BITS = (0, 2, 6, 8)
#: a texel is above the horizon when n . w > HORIZON_EPS (texels exactly on it are dropped,
#: whatever the summation order of the dot product)
HORIZON_EPS = 1e-9


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


@dataclass(frozen=True)
class VertexVisibility:
    """Differential visibility of every scene vertex.

    Attributes:
        geometry: the cubemap and block layout.
        vertices: the vertices the maps belong to.
        blocks: (P vertices x NB blocks) differential visibility.
        supersample: k, rays per texel side (1 = binary maps).
        bits: derivative quantisation (0 = binary).
    """

    geometry: CubemapBlocks
    vertices: SceneVertices
    blocks: BlockVisibility
    supersample: int = 1
    bits: int = 0

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
        }

    def check_scene(self, scene: Scene) -> None:
        """Raise SceneError unless the record was computed for this scene's vertices."""
        fp = scene_vertices(scene).fingerprint
        if fp != self.vertices.fingerprint:
            raise SceneError(
                f"visibility record does not belong to scene {scene.name!r} (vertex fingerprint differs); "
                "recompute it with precompute_visibility"
            )

    def save(self, path: str | Path) -> Path:
        """Write the record (varint stream + vertices), versioned, checksummed and atomic."""
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
        return save_arrays(path, arrays, KIND, meta=self.settings())

    @classmethod
    def load(cls, path: str | Path) -> VertexVisibility:
        """Read a record written by :meth:`save` (FileFormatError if corrupt or inconsistent)."""
        arrays, meta = load_arrays(path, KIND)
        try:
            geom = CubemapBlocks(int(meta["resolution"]), int(meta["block"]))
            verts = SceneVertices(
                torch.from_numpy(arrays["positions"]),
                torch.from_numpy(arrays["normals"]),
                torch.from_numpy(arrays["object_ids"]),
                torch.from_numpy(arrays["object_offsets"]),
            )
            blocks = BlockVisibility.from_bytes(
                arrays["stream"], arrays["vertex_offsets"], geom.block_count, int(meta["bits"])
            )
        except (KeyError, ValueRangeError) as exc:
            raise FileFormatError(f"{path}: incomplete visibility record ({exc})") from exc
        if len(verts) != int(meta["vertices"]) or blocks.counts.shape[0] != len(verts):
            raise FileFormatError(f"{path}: {blocks.counts.shape[0]} maps for {len(verts)} vertices")
        if verts.fingerprint != meta["fingerprint"]:
            raise FileFormatError(f"{path}: vertex arrays do not match the stored fingerprint")
        return cls(geom, verts, blocks, int(meta["supersample"]), int(meta["bits"]))


def _chunk_visibility(
    scene: Scene, geom: CubemapBlocks, pos: torch.Tensor, nrm: torch.Tensor, dirs: torch.Tensor, bits: int
) -> BlockVisibility:
    """Visibility of a few vertices: (m, NB, S^2) by casting the rays above each horizon."""
    m = pos.shape[0]
    centres = geom.directions.reshape(-1, 3)  # (T, 3) float64: the horizon test is exact-ish
    T, k2 = centres.shape[0], dirs.shape[1]
    up = (nrm.to(torch.float64) @ centres.T) > HORIZON_EPS  # (m, T) horizon at texel centres
    vi, ti = up.nonzero(as_tuple=True)
    o = (pos + scene.ray_epsilon * nrm).float()[vi]
    if k2 == 1:
        occ = scene.occluded(o, dirs[ti, 0], float("inf"))
        V = torch.zeros(m, T, dtype=torch.bool)
        V[vi, ti] = ~occ
        return BlockVisibility.encode(V.view(m, geom.block_count, geom.block_size), bits=0)
    o = o[:, None, :].expand(-1, k2, -1).reshape(-1, 3)
    occ = scene.occluded(o, dirs[ti].reshape(-1, 3), float("inf")).view(-1, k2)
    V = torch.zeros(m, T, dtype=torch.float32)
    V[vi, ti] = (~occ).float().mean(1)
    V = V.view(m, geom.block_count, geom.block_size)
    return BlockVisibility.encode(V, bits=bits)


def _settings_key(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def precompute_visibility(
    scene: Scene,
    resolution: int = 64,
    block: int = 16,
    supersample: int = 1,
    bits: int = 0,
    chunk: int = 256,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    max_chunks: int | None = None,
) -> VertexVisibility:
    """Visibility cubemaps of every vertex of ``scene``.

    Args:
        scene: the scene (its tracer casts the rays; ``scene.workers`` processes).
        resolution: R, texels per cubemap face side (64 or 128 in the seed).
        block: S, texels per block side.
        supersample: k; ``k x k`` rays per texel. ``k > 1`` needs ``bits`` in {2, 6, 8}.
        bits: 0 for binary maps, else the derivative quantisation of graded maps.
        chunk: vertices per work unit (and checkpoint file).
        checkpoint: folder for finished chunks; a run with the same settings resumes from it.
        progress: tqdm bar over chunks.
        max_chunks: stop after this many new chunks (returns None); for tests of resuming.
    Returns:
        :class:`VertexVisibility` (or None when stopped by ``max_chunks``).
    Raises:
        ValueRangeError: bad resolution (not a positive integer multiple of ``block``, or
            above :data:`~torch_brdf._checks.MAX_CUBEMAP_RESOLUTION`), supersample, bits or chunk.
    """
    resolution = check_count(resolution, "resolution", MAX_CUBEMAP_RESOLUTION)
    block, supersample, chunk = (
        check_count(v, k) for v, k in ((block, "block"), (supersample, "supersample"), (chunk, "chunk"))
    )
    max_chunks = None if max_chunks is None else check_int(max_chunks, "max_chunks", 0)
    geom = CubemapBlocks(resolution, block)
    if bits not in BITS:
        raise ValueRangeError(f"bits must be one of {BITS} (0 = binary); got {bits}")
    if int(supersample) != supersample or supersample < 1:
        raise ValueRangeError(f"supersample must be an integer >= 1; got {supersample}")
    if (supersample > 1) != (bits > 0):
        raise ValueRangeError(
            f"graded visibility needs supersample > 1 and bits in (2, 6, 8); binary needs supersample = 1 and "
            f"bits = 0; got supersample={supersample}, bits={bits}"
        )
    if chunk < 1:
        raise ValueRangeError(f"chunk must be >= 1; got {chunk}")
    verts = scene_vertices(scene)
    settings = {
        "resolution": resolution,
        "block": block,
        "supersample": supersample,
        "bits": bits,
        "vertices": len(verts),
        "fingerprint": verts.fingerprint,
        "chunk": chunk,
    }
    key = _settings_key(settings)
    ckdir = None if checkpoint is None else Path(checkpoint)
    if ckdir is not None:
        ckdir.mkdir(parents=True, exist_ok=True)
    dirs = geom.supersampled_directions(supersample).reshape(geom.block_count * geom.block_size, -1, 3).float()
    starts = list(range(0, len(verts), chunk))
    parts: list[BlockVisibility | None] = [None] * len(starts)
    done = 0
    bar = tqdm(starts, desc=f"visibility {scene.name} ({resolution}^2x6)", unit="chunk", disable=not progress)
    for c, s in enumerate(bar):
        path = None if ckdir is None else ckdir / f"vis_{key}_{c:06d}.npz"
        if path is not None and path.is_file():
            arrays, _meta = load_arrays(path, CHUNK_KIND)
            parts[c] = BlockVisibility.from_bytes(arrays["stream"], arrays["vertex_offsets"], geom.block_count, bits)
            continue
        if max_chunks is not None and done >= max_chunks:
            bar.close()
            return None
        e = min(s + chunk, len(verts))
        part = _chunk_visibility(scene, geom, verts.positions[s:e], verts.normals[s:e], dirs, bits)
        if path is not None:
            stream, voff = part.to_bytes()
            save_arrays(path, {"stream": stream, "vertex_offsets": voff}, CHUNK_KIND, meta={"chunk": c, "key": key})
        parts[c] = part
        done += 1
    return VertexVisibility(geom, verts, BlockVisibility.concat(parts), supersample, bits)
