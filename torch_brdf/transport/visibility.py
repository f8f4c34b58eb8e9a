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
the same record. The chunks are the tiles of :func:`~torch_brdf.parallel.tiles.run_tiles`:
they run in this process (``executor="local"``) or as Ray tasks (``"ray"``). Ray casting is
deterministic, so the record does not depend on the chunking, the executor or on the number
of ray-casting processes.

Where a chunk's rays are cast in its own process (forked tiles, Ray tasks, ``workers=1``) and
the compiled kernel builds (:mod:`~torch_brdf.transport._native`), one C loop per chunk does
all of it: the horizon block by block (four corner texels decide most blocks), each ray
straight into embree's ``rtcOccluded1`` on the tracer's own scene (the same query
``EmbreeScene.run`` makes, in the same order), and the flips as the rays come back. Otherwise
(no compiler, ``TORCH_BRDF_NATIVE=0``, or a tracer that spreads rays over its forked workers)
the numpy path below casts one embreex call per vertex. Both give the same record bit for bit.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from .._checks import MAX_CUBEMAP_RESOLUTION, MAX_SUPERSAMPLE, check_count, check_fields, check_int
from ..data import progress_default
from ..errors import FileFormatError, ValueRangeError
from ..parallel.threads import single_thread
from ..parallel.tiles import TileWork, run_tiles
from ..records.cache import ArraySpec, CacheSchema, MetaSpec, TileCache, settings_key
from ..records.visibility import SceneVertices, VertexVisibility, scene_vertices
from ..records.visibility_codec import BLOCK_TEXELS, BlockVisibility, PackedBlockVisibility, packed_entries
from ..scene.scene import Scene
from ..sphere.cubemap import CubemapBlocks
from . import _native

__all__ = [
    "SceneVertices",
    "VertexVisibility",
    "VisibilitySettings",
    "precompute_visibility",
    "scene_vertices",
    "visibility_fraction",
]

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
        pos: (m, 3) vertex positions.
        nrm: (m, 3) unit vertex normals.
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
    native = _native_rays(scene)
    if native is not None and dirs.shape[1] > 1:
        V = _native.visibility_fans(*native, *_fan_inputs(scene, geom, pos, nrm), dirs.numpy(), HORIZON_EPS, geom.block)
        return torch.from_numpy(V).view(pos.shape[0], geom.block_count, geom.block_size)
    V = _visible(scene, geom, pos, nrm, dirs.numpy())
    if V.dtype == bool:
        V = V.astype(np.float32)
    return torch.from_numpy(V).view(pos.shape[0], geom.block_count, geom.block_size)


def _lap(split: dict[str, float] | None, stage: str, t0: float) -> float:
    """Add the CPU seconds since ``t0`` to ``split[stage]`` (when profiling); the time now."""
    t = time.process_time()
    if split is not None:
        split[stage] = split.get(stage, 0.0) + t - t0
    return t


#: vertices cast together: their up directions (16 B a ray, ~200 KB a vertex at 64^2) are
#: gathered into one buffer reused from group to group (not 100 MB of fresh pages a chunk);
#: 64 measured faster than 16 (numpy's per-call costs) and 4 (1.7x the CPU overhead)
GROUP = 64


def _visible(scene: Scene, geom: CubemapBlocks, pos: torch.Tensor, nrm: torch.Tensor, dirs: np.ndarray, split=None):
    """Cast the rays above each vertex's horizon, in numpy: one fan of rays per vertex (one
    embree call, no (m T, 3) origin array); the horizon test and the gather of the up
    directions once per distinct normal of a group of :data:`GROUP` vertices (a flat
    object's vertices share theirs).

    Args:
        pos, nrm: (m, 3) float64 vertex positions and unit normals.
        dirs: (T, k^2, 3) float32 ray directions per texel.
        split: profiling: CPU seconds per stage (horizon, gather, embree, scatter) are added to it.
    Returns:
        (m, T): bool, the texel's ray escapes (``k = 1``), else float32, the fraction of its
        ``k^2`` rays that escape; 0 where the texel centre is below the horizon (``n . w <=
        HORIZON_EPS`` in float64).
    """
    t = time.process_time()
    centres = _centres(geom)  # (3, T) float64
    normals = nrm.to(torch.float64).numpy()
    origins = (pos + scene.ray_epsilon * nrm).float().numpy()
    m, T, k2 = normals.shape[0], centres.shape[1], dirs.shape[1]
    # directions padded to 16 bytes: np.compress moves one complex128 per ray, 1.4x faster
    padded = np.zeros((T, k2, 4), np.float32)
    padded[..., :3] = dirs
    rows = padded.view(np.complex128).reshape(T, k2)
    rows = rows[:, 0] if k2 == 1 else rows  # 1-D: numpy's fast path
    buf = np.empty((min(m, GROUP) * T,) + rows.shape[1:], np.complex128)
    out = np.zeros((m, T), bool if k2 == 1 else np.float32)
    for g in range(0, m, GROUP):
        normal, inverse = np.unique(normals[g : g + GROUP], axis=0, return_inverse=True)
        up = np.empty((len(normal), T), bool)
        for u, n in enumerate(normal):  # one (3,) x (3, T) product per normal: its rows stay in cache
            np.greater(n @ centres, HORIZON_EPS, out=up[u])
        counts = np.count_nonzero(up, axis=1)
        starts = np.cumsum(counts) - counts
        t = _lap(split, "horizon", t)
        for u in range(len(normal)):
            np.compress(up[u], rows, axis=0, out=buf[starts[u] : starts[u] + counts[u]])
        fans = np.stack([starts[inverse.reshape(-1)], counts[inverse.reshape(-1)]], axis=1) * k2
        d = buf[: counts.sum()].view(np.float32).reshape(-1, 4)[:, :3]
        t = _lap(split, "gather", t)
        free = ~scene.occluded_fans(origins[g : g + GROUP], fans, d)
        t = _lap(split, "embree", t)
        if k2 > 1:
            free = np.count_nonzero(free.reshape(-1, k2), axis=1).astype(np.float32) / np.float32(k2)
        out[g : g + GROUP][up[inverse.reshape(-1)]] = free
        t = _lap(split, "scatter", t)
    return out


def _native_rays(scene: Scene):
    """``(kernel, embree entry)`` when the compiled kernel casts the rays itself (the whole fan
    loop: horizon, rays, flips, in one pass per vertex), else None: no compiler
    (``TORCH_BRDF_NATIVE=0``), a tracer with forked trace workers (the numpy path spreads its
    rays over them), or an embree handle that cannot be checked. Same record either way."""
    lib = _native.library()
    entry = None if lib is None else scene.tracer.embree_entry()
    return None if entry is None else (lib, entry)


def _fan_inputs(scene: Scene, geom: CubemapBlocks, pos: torch.Tensor, nrm: torch.Tensor):
    """The kernel's (m, 3) float32 origins, (m, 3) float64 normals and (3, T) float64 centres
    (the same values as :func:`_visible`'s)."""
    origins = (pos + scene.ray_epsilon * nrm).float().numpy()
    return origins, nrm.to(torch.float64).numpy(), _centres(geom)


def _centres(geom: CubemapBlocks) -> np.ndarray:
    """(3, T) float64 texel-centre directions in block order, C-contiguous."""
    return np.ascontiguousarray(geom.directions.reshape(-1, 3).numpy().T)


def _chunk_entries(
    scene: Scene,
    geom: CubemapBlocks,
    pos: torch.Tensor,
    nrm: torch.Tensor,
    dirs: torch.Tensor,
    bits: int,
    split: dict[str, float] | None = None,
) -> dict[str, np.ndarray]:
    """The differential entries of a few vertices' maps (``counts`` (m, NB) int16, ``index``
    (F,) uint8, graded maps also ``delta`` (F,) int16), by casting the rays above each horizon;
    binary maps go from the rays' results to the flips through bits packed 8 a byte.
    ``split`` (profiling, binary maps): CPU seconds per stage are added to it (``kernel`` when
    the compiled kernel casts the rays; else horizon, gather, embree, scatter, flips)."""
    if dirs.shape[1] > 1:
        rec = BlockVisibility.encode(_fraction(scene, geom, pos, nrm, dirs), bits=bits)
        return {"counts": rec.counts.numpy(), "index": rec.index.numpy(), "delta": rec.delta.numpy()}
    native = _native_rays(scene)
    if native is not None and geom.block_size == BLOCK_TEXELS:  # flips as uint8 texel positions
        t = time.process_time()
        counts, index = _native.visibility_fans(
            *native, *_fan_inputs(scene, geom, pos, nrm), dirs.numpy(), HORIZON_EPS, geom.block
        )
        _lap(split, "kernel", t)
        return {"counts": counts, "index": index}
    vis = _visible(scene, geom, pos, nrm, dirs.numpy(), split)
    t = time.process_time()
    counts, index = packed_entries(np.packbits(vis.reshape(len(vis), geom.block_count, geom.block_size), axis=-1))
    _lap(split, "flips", t)
    return {"counts": counts, "index": index}


def _chunk_stream(entries: dict[str, np.ndarray], nb: int, bits: int) -> dict[str, np.ndarray]:
    """A chunk's entries as the record file's varint ``stream`` and ``vertex_offsets`` (what the
    record keeps and saves: the chunks are joined by copying bytes, never re-encoded whole)."""
    rec = BlockVisibility.from_entries(nb, bits, entries["counts"], entries["index"], entries.get("delta"))
    stream, vertex_offsets = rec.to_bytes()
    return {"stream": stream, "vertex_offsets": vertex_offsets}, rec.num_entries


def _chunk_schema(block_count: int, bits: int) -> CacheSchema:
    """What a finished chunk file must hold: the varint ``stream`` of ``n`` vertices and their
    ``vertex_offsets`` (n + 1,), a stream that parses in full (as a record file's) into the
    ``entries`` its metadata states."""
    arrays = {"stream": ArraySpec("uint8", (None,)), "vertex_offsets": ArraySpec("int64", (None,))}

    def check(arrays: dict, meta: dict, sizes: dict) -> None:
        vo = arrays["vertex_offsets"]
        if "n" in sizes and vo.shape != (sizes["n"] + 1,):
            raise FileFormatError(f"chunk vertex offsets {vo.shape}: expected ({sizes['n'] + 1},)")
        got = PackedBlockVisibility.from_bytes(arrays["stream"], vo, block_count, bits).num_entries
        if got != meta["entries"]:
            raise FileFormatError(f"chunk stream holds {got} entries; its metadata says {meta['entries']}")

    return CacheSchema(arrays=arrays, meta={"chunk": MetaSpec(int, 0), "entries": MetaSpec(int, 0)}, check=check)


def _visibility_chunk(work: TileWork, c: int):
    """Chunk ``c``: its varint stream (a pure function of the work: scene, geom, positions,
    normals, dirs, bits, chunk)."""
    s = c * work.chunk
    e = min(s + work.chunk, work.positions.shape[0])
    entries = _chunk_entries(work.scene, work.geom, work.positions[s:e], work.normals[s:e], work.dirs, work.bits)
    arrays, n_entries = _chunk_stream(entries, work.geom.block_count, work.bits)
    return arrays, {"chunk": c, "entries": n_entries}


def _join_tiles(tiles: list, nb: int, bits: int) -> PackedBlockVisibility:
    """The record of the chunks' streams, in order, copied into one stream allocated once; each
    chunk is dropped from ``tiles`` once copied, so the resident peak is about the record
    itself (the chunks' bytes move into pages of the stream as it fills): no CSR arrays (11
    bytes per vertex-block pair) and no re-encoding of the whole record."""
    n_vertices = sum(a["vertex_offsets"].size - 1 for a, _ in tiles)
    n_bytes = sum(a["stream"].size for a, _ in tiles)
    stream = np.empty(n_bytes, dtype=np.uint8)
    vertex_offsets = np.empty(n_vertices + 1, dtype=np.int64)
    vertex_offsets[0] = 0
    v, b, entries = 0, 0, 0
    for i, (a, meta) in enumerate(tiles):
        m, k = a["vertex_offsets"].size - 1, a["stream"].size
        stream[b : b + k] = a["stream"]
        vertex_offsets[v + 1 : v + m + 1] = a["vertex_offsets"][1:] + b
        entries += int(meta["entries"])
        v, b = v + m, b + k
        tiles[i] = None
    return PackedBlockVisibility(nb, bits, torch.from_numpy(stream), torch.from_numpy(vertex_offsets), entries)


@dataclass(frozen=True)
class VisibilitySettings:
    """The settings of :func:`precompute_visibility` (frozen; :meth:`key` feeds the resume key).

    Args:
        resolution: R, texels per cubemap face side (64 or 128 in the seed).
        block: S, texels per block side (R a multiple of it).
        supersample: k; ``k x k`` rays per texel. ``k > 1`` needs ``bits`` in {2, 6, 8}.
        bits: 0 for binary maps, else the derivative quantisation of graded maps.
        chunk: vertices per work unit (and checkpoint file).
    Raises:
        ValueRangeError: bad resolution (not a positive integer multiple of ``block``, or
            above :data:`~torch_brdf._checks.MAX_CUBEMAP_RESOLUTION`), supersample, bits or
            chunk (the exception's ``setting`` names the field).
    """

    resolution: int = 64
    block: int = 16
    supersample: int = 1
    bits: int = 0
    chunk: int = 256

    def __post_init__(self):
        check_fields(
            self,
            {
                "resolution": lambda v: check_count(v, "resolution", MAX_CUBEMAP_RESOLUTION),
                "block": lambda v: check_count(v, "block"),
                "supersample": lambda v: check_count(v, "supersample", MAX_SUPERSAMPLE),
                "chunk": lambda v: check_count(v, "chunk"),
            },
        )
        check_fields(self, {"resolution": lambda v: CubemapBlocks(v, self.block).resolution, "bits": _check_bits})
        if (self.supersample > 1) != (self.bits > 0):
            exc = ValueRangeError(
                f"graded visibility needs supersample > 1 and bits in (2, 6, 8); binary needs supersample = 1 and "
                f"bits = 0; got supersample={self.supersample}, bits={self.bits}"
            )
            exc.setting = "supersample"
            raise exc

    def key(self) -> dict[str, int]:
        """Every field (what the resume key covers besides the scene's vertices)."""
        return asdict(self)


def _check_bits(bits) -> int:
    if bits not in BITS:
        raise ValueRangeError(f"bits must be one of {BITS} (0 = binary); got {bits}")
    return int(bits)


def precompute_visibility(
    scene: Scene,
    settings: VisibilitySettings | None = None,
    *,
    checkpoint: str | Path | None = None,
    progress: bool | None = None,
    max_chunks: int | None = None,
    keep_checkpoint: bool = False,
    executor: str = "local",
    address: str | None = None,
    max_retries: int = 3,
    processes: int | None = None,
    **old,
) -> VertexVisibility:
    """Visibility cubemaps of every vertex of ``scene``.

    Args:
        scene: the scene (its tracer casts the rays; ``scene.workers`` processes).
        settings: :class:`VisibilitySettings` (cubemap resolution, block, supersampling, bits,
            chunk; None: its defaults).
        checkpoint: folder for finished chunks (a :class:`~torch_brdf.records.cache.TileCache`); a
            run with the same settings resumes from it; removed on success unless ``keep_checkpoint``.
        progress: tqdm bar over chunks (None: on when attached to a terminal or notebook).
        max_chunks: stop after this many new chunks (returns None); for tests of resuming.
        keep_checkpoint: keep the finished chunks after success (e.g. until the record is
            saved, then :func:`~torch_brdf.records.cache.remove_cache` of the folder, as
            ``torch-brdf precompute-visibility`` does: a kill before the save loses nothing).
        executor: where the chunks run (``"local"`` or ``"ray"``), see
            :func:`~torch_brdf.parallel.tiles.run_tiles`; the record is the same bit for bit.
        address: as ``executor``.
        max_retries: as ``executor``.
        processes: ``local`` only: chunks computed at once in forked processes (None: one per
            usable core; 1: one after another in this process, rays on ``scene.workers``).
    Returns:
        :class:`VertexVisibility` (or None when stopped by ``max_chunks``).
    Raises:
        TypeError: settings given one by one (``resolution=``, ``bits=``...).
    """
    if old or not isinstance(settings, (VisibilitySettings, type(None))):
        given = sorted(old) + ([] if isinstance(settings, (VisibilitySettings, type(None))) else [repr(settings)])
        raise TypeError(
            "precompute_visibility(scene, settings, *, checkpoint, progress, ...) takes its settings from a "
            f"VisibilitySettings, e.g. precompute_visibility(scene, VisibilitySettings(resolution=32, chunk=64)); "
            f"got {', '.join(given)}"
        )
    s = VisibilitySettings() if settings is None else settings
    max_chunks = None if max_chunks is None else check_int(max_chunks, "max_chunks", 0)
    geom = CubemapBlocks(s.resolution, s.block)
    resolution, supersample, bits, chunk = s.resolution, s.supersample, s.bits, s.chunk
    verts = scene_vertices(scene)
    # chunk files hold the varint stream of their vertices ("tile": "stream")
    facts = {"vertices": len(verts), "fingerprint": verts.fingerprint, "tile": "stream"}
    key = settings_key({**s.key(), **facts}, scene, parts=("geometry",))  # every mesh (occluders too), not lights
    schema = _chunk_schema(geom.block_count, bits)
    nv = len(verts)
    cache = TileCache(checkpoint, CHUNK_KIND, key, "vis", schema, lambda c: {"n": min(chunk, nv - c * chunk)})
    with single_thread():  # small torch ops: a second thread only waits (milliseconds under load)
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
    with single_thread():  # small torch ops: a second thread only waits (milliseconds under load)
        blocks = _join_tiles(tiles, geom.block_count, bits)
    if not keep_checkpoint:
        cache.remove()
    return VertexVisibility(geom, verts, blocks, supersample, bits)
