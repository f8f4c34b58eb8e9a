"""scene.trace against trimesh's own (pure numpy, float64) ray-mesh intersection."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from trimesh.ray.ray_triangle import RayMeshIntersector

from tests.conftest import shared_file
from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.scene import RayTracer, cornell_box, load_mesh, mesh_from_arrays


def _trimesh_closest(mesh: trimesh.Trimesh, o: np.ndarray, d: np.ndarray):
    """(tri, t): closest-hit triangle (-1 on miss) and distance (inf) from trimesh."""
    tri, ray, loc = RayMeshIntersector(mesh).intersects_id(o, d, multiple_hits=False, return_locations=True)
    out_tri = np.full(len(o), -1)
    out_t = np.full(len(o), np.inf)
    out_tri[ray] = tri
    out_t[ray] = np.einsum("ij,ij->i", loc - o[ray], d[ray])
    return out_tri, out_t


def _near_edge(mesh: trimesh.Trimesh, tri: np.ndarray, points: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """Whether ``points`` lie within ``tol`` (in barycentric terms) of an edge of ``tri``."""
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], points)
    return bary.min(axis=1) < tol


def _compare(mesh: trimesh.Trimesh, ours_tri, ours_t, o, d):
    ref_tri, ref_t = _trimesh_closest(mesh, o, d)
    ours_hit, ref_hit = ours_tri >= 0, ref_tri >= 0
    # hit/miss: disagreements only at triangle edges/silhouettes (ties), and rare
    differ = np.nonzero(ours_hit != ref_hit)[0]
    for i in differ:
        j, t = (ours_tri[i], ours_t[i]) if ours_hit[i] else (ref_tri[i], ref_t[i])
        assert _near_edge(mesh, np.array([j]), (o[i] + t * d[i])[None])[0], (
            f"ray {i}: hit/miss differ away from an edge"
        )
    assert len(differ) <= 1e-3 * len(o)
    both = ours_hit & ref_hit
    np.testing.assert_allclose(ours_t[both], ref_t[both], rtol=1e-4, atol=1e-6 * float(np.abs(o).max()))
    other_tri = both & (ours_tri != ref_tri)
    # a different triangle at the same distance is a tie on a shared edge or vertex
    assert _near_edge(mesh, ours_tri[other_tri], o[other_tri] + ours_t[other_tri, None] * d[other_tri]).all()
    return int(both.sum()), int(ref_hit.sum())


def _random_rays(lo, hi, n, rng, near_axis_jitter: float, n_random: int):
    """Rays from points in (slightly enlarged) bounds: ``n - n_random`` near-axis-aligned
    directions (jittered by ``near_axis_jitter`` rad, which keeps trimesh's candidate search
    fast) and ``n_random`` isotropic directions."""
    ext = hi - lo
    o = lo - 0.1 * ext + rng.random((n, 3)) * 1.2 * ext
    d = np.zeros((n, 3))
    m = n - n_random
    d[np.arange(m), rng.integers(0, 3, m)] = rng.choice([-1.0, 1.0], m)
    d[:m] += rng.normal(size=(m, 3)) * near_axis_jitter
    d[m:] = rng.normal(size=(n_random, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def test_trace_matches_trimesh_bunny():
    mesh = load_mesh(shared_file("meshes", "bunny.ply"))
    rng = np.random.default_rng(7)
    o, d = _random_rays(*mesh.bounds, 100_000, rng, near_axis_jitter=0.05, n_random=500)
    hits = RayTracer([mesh], [True]).trace(torch.from_numpy(o).float(), torch.from_numpy(d).float())
    both, n_ref = _compare(
        mesh, hits.prim_id.numpy(), hits.t.double().numpy(), o.astype(np.float32).astype(np.float64), d
    )
    assert n_ref > 20_000 and both >= 0.999 * n_ref


def test_trace_matches_trimesh_cornell_box():
    scene = cornell_box(16)
    meshes = [ob.mesh for ob in scene.objects]
    combined = trimesh.util.concatenate(meshes)
    rng = np.random.default_rng(8)
    lo, hi = combined.bounds
    o = lo + rng.random((100_000, 3)) * (hi - lo)  # inside the box: isotropic directions
    d = rng.normal(size=(100_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = o.astype(np.float32).astype(np.float64)
    hits = scene.trace(torch.from_numpy(o).float(), torch.from_numpy(d).float())
    offsets = np.cumsum([0] + [len(m.faces) for m in meshes])
    gtri = np.where(hits.hit.numpy(), offsets[hits.object_id.clamp_min(0).numpy()] + hits.prim_id.numpy(), -1)
    both, n_ref = _compare(combined, gtri, hits.t.double().numpy(), o, d)
    assert both >= 0.999 * n_ref > 80_000  # the front of the box is open


def test_hits_fields_on_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=2.0)
    tracer = RayTracer([mesh_from_arrays(sphere.vertices, sphere.faces)], [True])
    g = torch.Generator().manual_seed(3)
    d = torch.nn.functional.normalize(torch.randn(4096, 3, generator=g, dtype=torch.float64), dim=-1)
    o = -5 * d + 0.2 * torch.randn(4096, 3, generator=g, dtype=torch.float64)
    h = tracer.trace(o, d)
    assert h.t.dtype == torch.float64 and bool(h.hit.all())
    torch.testing.assert_close(h.position, o + h.t[:, None] * d, rtol=0, atol=1e-5)
    # facets of a radius-2 icosphere: normals within a facet's angular size of the radial direction
    radial = torch.nn.functional.normalize(h.position, dim=-1)
    assert float((h.geometric_normal * radial).sum(-1).min()) > 0.999
    assert float((h.normal * radial).sum(-1).min()) > 0.9995
    torch.testing.assert_close(h.normal.norm(dim=-1), torch.ones(4096, dtype=torch.float64))
    w = torch.stack((1 - h.barycentrics.sum(-1), h.barycentrics[:, 0], h.barycentrics[:, 1]), -1)
    assert bool((w > -1e-5).all())


def test_object_ids_misses_and_occlusion():
    scene = cornell_box(16)
    o, d = scene.camera.generate_rays()
    h = scene.trace(o, d)
    assert bool(h.hit.all())  # the box is closed towards the camera's view
    ids = set(h.object_id.unique().tolist())
    assert ids == set(range(len(scene.objects)))  # every part, the light included, is in view
    # occluded(inf) == hit; occluded below the hit distance == False
    assert torch.equal(scene.occluded(o, d, float("inf")), h.hit)
    assert not bool(scene.occluded(o, d, h.t * 0.99).any())
    assert bool(scene.occluded(o, d, h.t * 1.01).all())
    # away from everything: misses report -1 and inf
    far = scene.trace(torch.tensor([[0.0, 1e4, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]))
    assert int(far.object_id) == -1 and int(far.prim_id) == -1 and float(far.t) == float("inf")
    assert float(far.position.abs().sum()) == 0.0


def test_spawn_avoids_self_intersection():
    scene = cornell_box(32)
    o, d = scene.camera.generate_rays()
    h = scene.trace(o, d)
    assert int((~h.hit).sum()) > 0  # the image corners look past the box
    o, d = o[h.hit], d[h.hit]
    h = scene.trace(o, d)
    # continue every path in the mirror direction about the geometric normal
    n = h.geometric_normal
    r = d - 2 * (d * n).sum(-1, keepdim=True) * n
    h2 = scene.trace(scene.spawn(h.position, n, r), r)
    same = (h2.object_id == h.object_id) & (h2.prim_id == h.prim_id)
    assert not bool((same & (h2.t < 1.0)).any())
    # and going back through the surface from the spawned side finds the surface itself
    back = scene.spawn(h.position, n, -d)
    cos = (d * n).sum(-1).abs()
    assert bool(scene.occluded(back, d, 2 * scene.ray_epsilon / cos).all())
    assert not bool(scene.occluded(back, d, 0.5 * scene.ray_epsilon / cos).any())


def test_bad_ray_input():
    scene = cornell_box(8)
    with pytest.raises(ShapeError, match=r"origins to have shape \(N, 3\)"):
        scene.trace(torch.zeros(5, 2), torch.zeros(5, 2))
    with pytest.raises(ShapeError, match="same shape"):
        scene.trace(torch.zeros(5, 3), torch.ones(4, 3))
    with pytest.raises(ValueRangeError, match="NaN"):
        scene.trace(torch.full((2, 3), float("nan")), torch.ones(2, 3))


def test_non_finite_or_half_precision_rays_and_bounds_are_refused():
    scene = cornell_box(8)
    o, d = scene.camera.generate_rays()
    with pytest.raises(ValueRangeError, match="t_max holds 64 NaN"):
        scene.occluded(o, d, float("nan"))  # must not mean "not occluded"
    assert bool(scene.occluded(o, d, float("inf")).any())  # inf stays "unbounded"
    with pytest.raises(ShapeError, match="float16"):
        scene.trace(o.half(), d.half())
    with pytest.raises(ShapeError, match="float16"):
        scene.occluded(o, d.half(), 1.0)
    with pytest.raises(ValueRangeError, match="position"):
        scene.spawn(o * float("nan"), d, d)
    with pytest.raises(ValueRangeError, match="directions"):
        scene.spawn(o, d, d * float("inf"))
    with pytest.raises(ValueRangeError, match="raster x"):
        scene.camera.rays_through(torch.tensor([float("nan")]), torch.tensor([1.0]))


@pytest.mark.parametrize("workers", [1, 2])
def test_occluded_fans_equal_occluded(workers):
    # fans of rays from shared origins (e.g. a vertex's cubemap texels), some sharing their
    # directions, one empty; enough rays for the two-process pool with workers=2
    box = cornell_box(8)
    scene = RayTracer([o.mesh for o in box.objects], [o.smooth for o in box.objects], workers=workers)
    rng = np.random.default_rng(3)
    lo, hi = (x.numpy() for x in scene.bbox)
    origins = (lo + (0.1 + 0.8 * rng.random((7, 3))) * (hi - lo)).astype(np.float32)
    d = rng.normal(size=(9000, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    fans = np.array([[0, 9000], [100, 0], [0, 9000], [4000, 5000], [17, 1], [0, 3000], [2000, 7000]])
    got = scene.occluded_fans(origins, fans, d[:, None, :].repeat(2, 1)[:, 0])  # a strided (D, 3) view
    rays = np.concatenate([np.arange(a, a + n) for a, n in fans])
    o = torch.from_numpy(np.repeat(origins, fans[:, 1], axis=0))
    ref = scene.occluded(o, torch.from_numpy(d[rays]), float("inf")).numpy()
    assert got.shape == (int(fans[:, 1].sum()),) and np.array_equal(got, ref)
    assert scene._parallel(len(got)) == (workers == 2)  # the pool path with two workers
    assert 0 < got.mean() < 1
    with pytest.raises(ValueRangeError, match="within"):
        scene.occluded_fans(origins, fans + [[0, 1]], d)
    with pytest.raises(ShapeError, match="float32"):
        scene.occluded_fans(origins, fans, d.astype(np.float64))
    with pytest.raises(ShapeError, match=r"fans \(m, 2\)"):
        scene.occluded_fans(origins, fans[:3], d)
    d[5] = np.nan
    with pytest.raises(ValueRangeError, match="finite"):
        scene.occluded_fans(origins, fans, d)
