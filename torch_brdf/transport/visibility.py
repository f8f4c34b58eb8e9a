r"""Per-vertex visibility cubemaps by ray casting (Inger et al., Sec. 4.2 and 5).

Every vertex of the scene gets a ``6 x R x R`` cubemap in the one world orientation of
:class:`~torch_brdf.sphere.cubemap.CubemapBlocks`, split into ``16 x 16`` blocks and stored
differentially (:class:`~torch_brdf.records.visibility_codec.BlockVisibility`): binary maps
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
the same record. The chunks are the tiles of :func:`~torch_brdf.transport.executor.run_tiles`:
they run in this process (``executor="local"``) or as Ray tasks (``"ray"``). Ray casting is
deterministic, so the record does not depend on the chunking, the executor or on the number
of ray-casting processes.
"""

from __future__ import annotations

from pathlib import Path

import torch

from .._checks import MAX_CUBEMAP_RESOLUTION, check_count, check_int
from ..data import progress_default
from ..errors import ValueRangeError
from ..records.cache import TileCache, settings_key
from ..records.visibility import SceneVertices, VertexVisibility, scene_vertices
from ..records.visibility_codec import BlockVisibility
from ..scene.scene import Scene
from ..sphere.cubemap import CubemapBlocks
from .executor import TileWork, run_tiles

__all__ = ["SceneVertices", "VertexVisibility", "precompute_visibility", "scene_vertices", "visibility_fraction"]

CHUNK_KIND = "vertex-visibility-chunk"
BITS = (0, 2, 6, 8)
#: a texel is above the horizon when n . w > HORIZON_EPS (texels exactly on it are dropped,
#: whatever the summation order of the dot product)
HORIZON_EPS = 1e-9


def visibility_fraction(
    scene: Scene, geom: CubemapBlocks, pos: torch.Tensor, nrm: torch.Tensor, supersample: int = 1
) -> torch.Tensor:
    """The undecoded visibility of a few vertices: the fraction of each texel's ``k x k`` rays
    that escape (0 below the horizon, tested at the texel centre; 0 or 1 when ``k = 1``).

    Args:
        scene: the scene (its tracer casts the rays).
        geom: cubemap layout.
        pos, nrm: (m, 3) vertex positions and unit normals.
        supersample: k, rays per texel side.
    Returns:
        (m, NB, S^2) float32; encode it with
        :meth:`~torch_brdf.records.visibility_codec.BlockVisibility.encode` (``bits=0`` after
        ``> 0.5`` for binary maps).
    """
    dirs = geom.supersampled_directions(supersample).reshape(geom.block_count * geom.block_size, -1, 3).float()
    return _fraction(scene, geom, pos, nrm, dirs)


def _fraction(scene: Scene, geom: CubemapBlocks, pos: torch.Tensor, nrm: torch.Tensor, dirs: torch.Tensor):
    """:func:`visibility_fraction` for precomputed (T, k^2, 3) ray directions."""
    m = pos.shape[0]
    centres = geom.directions.reshape(-1, 3)  # (T, 3) float64: the horizon test is exact-ish
    T, k2 = centres.shape[0], dirs.shape[1]
    up = (nrm.to(torch.float64) @ centres.T) > HORIZON_EPS  # (m, T) horizon at texel centres
    vi, ti = up.nonzero(as_tuple=True)
    o = (pos + scene.ray_epsilon * nrm).float()[vi]
    o = o[:, None, :].expand(-1, k2, -1).reshape(-1, 3)
    occ = scene.occluded(o, dirs[ti].reshape(-1, 3), float("inf")).view(-1, k2)
    V = torch.zeros(m, T, dtype=torch.float32)
    V[vi, ti] = (~occ).float().mean(1)
    return V.view(m, geom.block_count, geom.block_size)


def _chunk_visibility(
    scene: Scene, geom: CubemapBlocks, pos: torch.Tensor, nrm: torch.Tensor, dirs: torch.Tensor, bits: int
) -> BlockVisibility:
    """Visibility of a few vertices: (m, NB, S^2) by casting the rays above each horizon."""
    V = _fraction(scene, geom, pos, nrm, dirs)
    if dirs.shape[1] == 1:
        return BlockVisibility.encode(V > 0.5, bits=0)
    return BlockVisibility.encode(V, bits=bits)


def _visibility_chunk(work: TileWork, c: int):
    """Chunk ``c``: its differential stream and vertex offsets (a pure function of the work:
    scene, geom, positions, normals, dirs, bits, chunk)."""
    s = c * work.chunk
    e = min(s + work.chunk, work.positions.shape[0])
    part = _chunk_visibility(work.scene, work.geom, work.positions[s:e], work.normals[s:e], work.dirs, work.bits)
    stream, voff = part.to_bytes()
    return {"stream": stream, "vertex_offsets": voff}, {"chunk": c}


def precompute_visibility(
    scene: Scene,
    resolution: int = 64,
    block: int = 16,
    supersample: int = 1,
    bits: int = 0,
    chunk: int = 256,
    checkpoint: str | Path | None = None,
    progress: bool | None = None,
    max_chunks: int | None = None,
    keep_checkpoint: bool = False,
    executor: str = "local",
    address: str | None = None,
    max_retries: int = 3,
    processes: int | None = None,
) -> VertexVisibility:
    """Visibility cubemaps of every vertex of ``scene``.

    Args:
        scene: the scene (its tracer casts the rays; ``scene.workers`` processes).
        resolution: R, texels per cubemap face side (64 or 128 in the seed).
        block: S, texels per block side.
        supersample: k; ``k x k`` rays per texel. ``k > 1`` needs ``bits`` in {2, 6, 8}.
        bits: 0 for binary maps, else the derivative quantisation of graded maps.
        chunk: vertices per work unit (and checkpoint file).
        checkpoint: folder for finished chunks (a :class:`~torch_brdf.records.cache.TileCache`); a
            run with the same settings resumes from it; removed on success unless ``keep_checkpoint``.
        progress: tqdm bar over chunks (None: on when attached to a terminal or notebook).
        max_chunks: stop after this many new chunks (returns None); for tests of resuming.
        keep_checkpoint: keep the finished chunks after success.
        executor, address, max_retries: where the chunks run (``"local"`` or ``"ray"``), see
            :func:`~torch_brdf.transport.executor.run_tiles`; the record is the same bit for bit.
        processes: ``local`` only: chunks computed at once in forked processes (None: one per
            usable core; 1: one after another in this process, rays on ``scene.workers``).
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
    key = settings_key(settings, scene, parts=("geometry",))  # every mesh (occluders too), not lights
    cache = TileCache(checkpoint, CHUNK_KIND, key, prefix="vis")
    dirs = geom.supersampled_directions(supersample).reshape(geom.block_count * geom.block_size, -1, 3).float()
    num = -(-len(verts) // chunk)
    work = TileWork(scene=scene, geom=geom, positions=verts.positions, normals=verts.normals, dirs=dirs)
    work.bits, work.chunk = bits, chunk
    desc = f"visibility {scene.name} ({resolution}^2x6)"
    show = progress_default(progress)
    tiles = run_tiles(
        _visibility_chunk,
        work,
        num,
        cache,
        executor,
        address,
        max_retries,
        desc,
        show,
        max_new=max_chunks,
        processes=processes,
    )
    if any(t is None for t in tiles):
        return None  # stopped by max_chunks
    parts = [BlockVisibility.from_bytes(a["stream"], a["vertex_offsets"], geom.block_count, bits) for a, _ in tiles]
    if not keep_checkpoint:
        cache.remove()
    return VertexVisibility(geom, verts, BlockVisibility.concat(parts), supersample, bits)
