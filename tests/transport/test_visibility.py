"""Per-vertex visibility cubemaps: brute-force ray oracles, analytic planes, resume, files."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from tests.conftest import corrupted_copy
from torch_brdf.errors import FileFormatError, SceneError, ValueRangeError
from torch_brdf.records.visibility_codec import BlockVisibility
from torch_brdf.scene.builtin import grid_plane
from torch_brdf.scene.camera import Camera
from torch_brdf.scene.embree import embree_entry
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.scene.mesh import mesh_from_arrays
from torch_brdf.scene.scene import Scene, SceneObject
from torch_brdf.sphere.cubemap import CubemapBlocks
from torch_brdf.transport import _native, visibility
from torch_brdf.transport.visibility import (
    HORIZON_EPS,
    VertexVisibility,
    VisibilitySettings,
    precompute_visibility,
    scene_vertices,
)


def ball_on_plane(quads: int = 6, workers: int | None = 1, box: bool = True) -> Scene:
    """A small box floating over a tessellated plane: real shadows, few vertices."""
    import trimesh

    b = trimesh.creation.box(extents=(0.6, 0.3, 0.6))
    b.apply_translation([0.1, 0.45, 0.0])
    objs = [
        SceneObject("box", mesh_from_arrays(b.vertices, b.faces, "box"), "box"),
        SceneObject("floor", grid_plane(2.0, quads), "floor"),
    ][0 if box else 1 :]
    mats = {"box": {"type": "lambert", "albedo": 0.5}, "floor": {"type": "lambert", "albedo": 0.5}}
    cam = Camera((0.0, 1.5, -2.5), (0.0, 0.2, 0.0), (0.0, 1.0, 0.0), 45.0, 32, 24)
    return Scene(objs, mats, [EnvironmentMap.constant(1.0, 16)], cam, name="box_on_plane", workers=workers)


@pytest.fixture(scope="module")
def scene():
    return ball_on_plane()


@pytest.fixture(scope="module")
def record(scene):
    return precompute_visibility(scene, VisibilitySettings(resolution=32, chunk=16), progress=False)


def brute_force(scene: Scene, geom: CubemapBlocks, vertex: int, supersample: int = 1) -> torch.Tensor:
    """One ray per (sub)texel, one vertex at a time: (NB, S^2) visible fraction."""
    v = scene_vertices(scene)
    p, n = v.positions[vertex], v.normals[vertex]
    d = geom.supersampled_directions(supersample)  # (NB, S^2, k^2, 3)
    out = torch.zeros(geom.block_count, geom.block_size, dtype=torch.float64)
    for b in range(geom.block_count):
        for t in range(geom.block_size):
            if float(geom.directions[b, t] @ n) <= HORIZON_EPS:
                continue
            dirs = d[b, t].float()
            o = (p + scene.ray_epsilon * n).float().expand(len(dirs), 3)
            out[b, t] = (~scene.occluded(o, dirs, float("inf"))).double().mean()
    return out


def test_binary_maps_equal_brute_force_rays(scene, record):
    geom = record.geometry
    v = scene_vertices(scene)
    # a floor vertex under the box (shadowed), one far from it, and a box vertex
    floor = (v.object_ids == 1).nonzero().squeeze(-1)
    pos = v.positions[floor]
    under = int(floor[(pos[:, [0, 2]] - torch.tensor([0.1, 0.0], dtype=torch.float64)).norm(dim=-1).argmin()])
    far = int(floor[pos[:, 0].argmax()])
    for vid in (under, far, 3):
        got = record.blocks.decode([vid])[0].double()
        assert torch.equal(got, brute_force(scene, geom, vid)), vid
    # the vertex under the box really is shadowed straight up
    assert record.blocks.decode([under])[0].sum() < record.blocks.decode([far])[0].sum()


def test_unoccluded_plane_vertex_is_its_hemisphere(scene, record):
    geom = record.geometry
    v = scene_vertices(scene)
    floor = (v.object_ids == 1).nonzero().squeeze(-1)
    corner = int(floor[(v.positions[floor, 0] + v.positions[floor, 2]).argmin()])
    V = record.blocks.decode([corner])[0].double()
    # the box subtends a small solid angle from the far corner: compare the cosine-weighted
    # visible solid angle with pi minus the box's share (bounded), and the hemisphere mask
    up = (geom.directions @ v.normals[corner]) > 0
    assert bool((V[~up] == 0).all())
    cosw = geom.solid_angles * (geom.directions @ v.normals[corner]).clamp_min(0)
    full = float((cosw * up).sum())
    assert full == pytest.approx(math.pi, rel=2e-3)  # texel quadrature of the cosine
    assert 0.9 * full < float((cosw * V).sum()) <= full


def test_chunking_and_workers_do_not_change_the_record(scene, record):
    # one chunk of every vertex: ~40k rays, enough for the two-process ray casting path
    two = ball_on_plane(workers=2)
    other = precompute_visibility(two, VisibilitySettings(resolution=32, chunk=1000), progress=False)
    assert two.tracer._pool is not None
    for a, b in zip(other.blocks.to_bytes(), record.blocks.to_bytes(), strict=True):
        assert np.array_equal(a, b)


def test_interrupted_precompute_resumes(scene, record, tmp_path):
    ck = tmp_path / "ck"
    assert (
        precompute_visibility(
            scene, VisibilitySettings(resolution=32, chunk=16), checkpoint=ck, progress=False, max_chunks=2
        )
        is None
    )
    assert len(list(ck.glob("*.npz"))) == 2
    resumed = precompute_visibility(
        scene, VisibilitySettings(resolution=32, chunk=16), checkpoint=ck, progress=False, keep_checkpoint=True
    )
    assert np.array_equal(resumed.blocks.to_bytes()[0], record.blocks.to_bytes()[0])
    assert len(list(ck.glob("*.npz"))) > 2  # kept on purpose
    again = precompute_visibility(
        scene, VisibilitySettings(resolution=32, chunk=16), checkpoint=ck, progress=False
    )  # all chunks from the folder
    assert np.array_equal(again.blocks.to_bytes()[0], record.blocks.to_bytes()[0])
    assert not ck.exists()  # removed once the run succeeded (keep_checkpoint=False)
    # a different setting does not pick up these chunks
    assert (
        precompute_visibility(
            scene, VisibilitySettings(resolution=32, chunk=8), checkpoint=ck, progress=False, max_chunks=0
        )
        is None
    )


def test_save_load_round_trip_and_scene_check(scene, record, tmp_path):
    path = record.save(tmp_path / "vis.npz")
    back = VertexVisibility.load(path)
    assert torch.equal(back.blocks.decode(), record.blocks.decode())
    assert back.bytes_per_vertex == pytest.approx(record.bytes_per_vertex)
    back.check_scene(scene)
    with pytest.raises(SceneError):
        back.check_scene(ball_on_plane(quads=5))
    with pytest.raises(FileFormatError):
        VertexVisibility.load(corrupted_copy(path, tmp_path / "bad.npz"))


def test_graded_maps_within_quantisation_bound(scene):
    geom = CubemapBlocks(16, 16)
    rec = precompute_visibility(scene, VisibilitySettings(resolution=16, supersample=3, bits=6), progress=False)
    v = scene_vertices(scene)
    floor = (v.object_ids == 1).nonzero().squeeze(-1)
    vid = int(floor[(v.positions[floor, [0]] - 0.1).abs().argmin()])
    exact = brute_force(scene, geom, vid, supersample=3)
    got = rec.blocks.decode([vid])[0].double()
    assert float((got - exact).abs().max()) <= 0.5 / 63 + 1e-6
    assert bool(((exact > 0) & (exact < 1)).any())  # really anti-aliased somewhere


def test_bad_settings_raise(scene):
    with pytest.raises(ValueRangeError):
        precompute_visibility(scene, VisibilitySettings(resolution=32, supersample=2, bits=3))
    with pytest.raises(ValueRangeError):
        precompute_visibility(scene, VisibilitySettings(resolution=32, supersample=2, bits=0))
    with pytest.raises(ValueRangeError):
        precompute_visibility(scene, VisibilitySettings(resolution=40))


def test_binary_storage_is_compact(record):
    # the seed's figure is about 1 KB per vertex at 64^2 x 6; at 32^2 x 6 (24 blocks) far less
    assert record.bytes_per_vertex < 24 * 12


def previous_pipeline(scene: Scene, resolution: int, supersample: int = 1, bits: int = 0):
    """The precompute as it was before the ray fans (its code kept here as the oracle): the
    horizon by one float64 matmul, every ray's origin and direction gathered into (n, 3) arrays
    for ``Scene.occluded``, the escaping fraction scattered into dense maps, encoded texel by
    texel (0/1 floats)."""
    geom = CubemapBlocks(resolution)
    v = scene_vertices(scene)
    dirs = geom.supersampled_directions(supersample).reshape(geom.block_count * geom.block_size, -1, 3).float()
    centres = geom.directions.reshape(-1, 3)
    T, k2 = centres.shape[0], dirs.shape[1]
    up = (v.normals.to(torch.float64) @ centres.T) > HORIZON_EPS
    vi, ti = up.nonzero(as_tuple=True)
    o = (v.positions + scene.ray_epsilon * v.normals).float()[vi]
    o = o[:, None, :].expand(-1, k2, -1).reshape(-1, 3)
    occ = scene.occluded(o, dirs[ti].reshape(-1, 3), float("inf")).view(-1, k2)
    V = torch.zeros(len(v), T, dtype=torch.float32)
    V[vi, ti] = (~occ).float().mean(1)
    V = V.view(len(v), geom.block_count, geom.block_size)
    return BlockVisibility.encode((V > 0.5).float() if k2 == 1 else V, bits=bits)


@pytest.mark.parametrize("path", ["compiled", "numpy"])
@pytest.mark.parametrize(
    ("supersample", "bits", "chunk", "group"), [(1, 0, 16, 64), (1, 0, 1000, 64), (1, 0, 1000, 5), (2, 2, 7, 3)]
)
def test_record_equals_the_previous_pipeline(scene, supersample, bits, chunk, group, path, monkeypatch):
    # the box's vertices have their own normals, the floor's share one (one horizon test for all);
    # groups of cast vertices smaller than a chunk, the last one partial; the compiled loop
    # (horizon by blocks, rays straight into embree, flips) and the numpy path without it
    if path == "numpy":
        monkeypatch.setenv(_native.ENV_VAR, "0")
    elif _native.library() is None:
        pytest.skip("no C compiler here: only the numpy path runs")
    assert (visibility._native_rays(scene) is not None) == (path == "compiled")
    monkeypatch.setattr(visibility, "GROUP", group)
    got = precompute_visibility(
        scene, VisibilitySettings(resolution=32, supersample=supersample, bits=bits, chunk=chunk), progress=False
    )
    ref = previous_pipeline(scene, 32, supersample, bits)
    assert ref.num_entries > 0 and bool((ref.states == 2).any())  # real shadows, partial blocks
    for a, b in zip(got.blocks.to_bytes(), ref.to_bytes(), strict=True):
        assert np.array_equal(a, b)


def test_compiled_loop_casts_the_tracer_rays(scene):
    """The embree handle found behind embreex and the kernel's per-ray query give the occlusion
    of ``Scene.occluded`` (unbounded) on random fans; a tracer with forked workers, or an object
    that is not an embreex scene, gets no handle."""
    lib, entry = _native.library(), scene.tracer.embree_entry()
    if lib is None:
        pytest.skip("no C compiler here: only the numpy path runs")
    assert entry is not None and embree_entry(object()) is None
    assert ball_on_plane(workers=2).tracer.embree_entry() is None
    g = torch.Generator().manual_seed(3)
    origins = (torch.rand(40, 3, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([1.0, 0.5, 1.0])
    origins[:, 1] += 0.5
    dirs = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1).float()
    counts = torch.randint(0, 20, (40,), generator=g)
    texels = torch.randint(0, 300, (int(counts.sum()),), generator=g)
    out = np.zeros(len(texels), np.uint8)
    o32 = origins.float()
    hits = _native.occluded_fans(
        lib, entry, o32.numpy(), counts.numpy(), texels.numpy().astype(np.uint16), dirs.numpy(), out
    )
    want = scene.occluded(o32.repeat_interleave(counts, dim=0), dirs[texels], float("inf"))
    assert torch.equal(torch.from_numpy(out).bool(), want) and hits == int(want.sum())
    assert 0 < hits < len(texels)  # both kinds of rays


@pytest.mark.parametrize("bits", [0, 6])
def test_joined_chunks_equal_the_record_of_all_entries(bits):
    """The precompute's assembly (chunks' varint streams copied into one stream allocated once,
    each chunk dropped once copied) gives the record of the concatenated entries, bit for bit,
    and the very stream the whole record encodes to."""
    gen = torch.Generator().manual_seed(3)
    v = torch.rand(23, 6, 256, generator=gen) < 0.5
    maps = v.float() * torch.rand(23, 6, 1, generator=gen) if bits else v
    whole = BlockVisibility.encode(maps, bits)
    tiles, cuts = [], [0, 5, 5, 16, 23]  # an empty chunk too
    for s, e in itertools.pairwise(cuts):
        r = whole.select(range(s, e))
        entries = {"counts": r.counts.numpy(), "index": r.index.numpy()}
        if bits:
            entries["delta"] = r.delta.numpy()
        arrays, n_entries = visibility._chunk_stream(entries, 6, bits)
        tiles.append((arrays, {"chunk": s, "entries": n_entries}))
    joined = visibility._join_tiles(tiles, 6, bits)
    assert all(t is None for t in tiles)
    assert joined.num_entries == whole.num_entries
    for got, want in zip(joined.to_bytes(), whole.to_bytes(), strict=True):
        assert np.array_equal(got, want)
    for name in ("counts", "offsets", "index", "states"):
        assert torch.equal(getattr(joined, name), getattr(whole, name)), name
    assert (joined.delta is None) == (bits == 0) and (bits == 0 or torch.equal(joined.delta, whole.delta))
