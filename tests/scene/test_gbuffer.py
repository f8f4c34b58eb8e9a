"""The G-buffer of a camera's primary rays against direct ray queries and the meshes."""

from __future__ import annotations

import pytest
import torch
import trimesh

from torch_brdf.errors import SceneError
from torch_brdf.scene import Camera, EnvironmentMap, GBuffer, Scene, SceneObject, grid_plane, trace_gbuffer
from torch_brdf.scene.mesh import mesh_from_arrays

F64 = torch.float64


@pytest.fixture(scope="module")
def scene() -> Scene:
    """A smooth ball and a flat box over a tessellated plane, seen from above at 40x30."""
    ball = trimesh.creation.icosphere(2, radius=0.3)
    ball.apply_translation([-0.4, 0.3, 0.0])
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.4))
    box.apply_translation([0.4, 0.15, 0.1])
    objs = [
        SceneObject("floor", grid_plane(2.0, 4), "m"),
        SceneObject("ball", mesh_from_arrays(ball.vertices, ball.faces, "ball"), "m", smooth=True),
        SceneObject("box", mesh_from_arrays(box.vertices, box.faces, "box"), "m"),
        SceneObject("hidden", mesh_from_arrays(box.vertices + [0.0, -5.0, 0.0], box.faces, "hidden"), "m"),
    ]
    cam = Camera((0.0, 1.6, -2.2), (0.0, 0.1, 0.0), (0.0, 1.0, 0.0), 40.0, 40, 30)
    return Scene(objs, {"m": {"type": "lambert", "albedo": 0.5}}, [EnvironmentMap.constant(1.0, 8)], cam, workers=1)


@pytest.fixture(scope="module")
def gb(scene) -> GBuffer:
    return trace_gbuffer(scene)


def test_rows_are_the_primary_hits_of_the_camera(scene, gb):
    o, d = scene.camera.generate_rays(dtype=F64)
    hits = scene.trace(o, d)
    assert torch.equal(gb.pixels, hits.hit.nonzero().squeeze(1))
    assert torch.equal(gb.mask.view(-1), hits.hit) and gb.mask.shape == (30, 40)
    assert 0 < gb.count < 40 * 30  # some rays miss
    for name in ("object_id", "prim_id", "position"):
        assert torch.equal(getattr(gb, name), getattr(hits, name)[gb.pixels])
    torch.testing.assert_close(gb.depth, hits.t[gb.pixels], rtol=0, atol=0)
    assert set(gb.object_id.tolist()) == {0, 1, 2}
    for t in (gb.eye, gb.position, gb.normal, gb.geometric_normal, gb.depth, gb.wo, gb.weights):
        assert t.dtype == F64


def test_geometry_is_consistent(scene, gb):
    """wo points from the hit to the eye at distance depth; normals are unit to float64 rounding."""
    eye = gb.eye.expand_as(gb.position)
    torch.testing.assert_close(gb.position + gb.depth[:, None] * gb.wo, eye, atol=1e-5, rtol=0)
    for n in (gb.wo, gb.normal, gb.geometric_normal):
        torch.testing.assert_close(n.norm(dim=-1), torch.ones(gb.count, dtype=F64), atol=1e-14, rtol=0)
    flat = gb.object_id != 1
    torch.testing.assert_close(gb.normal[flat], gb.geometric_normal[flat], atol=1e-6, rtol=0)


def test_corners_and_weights_interpolate_the_hit_triangle(scene, gb):
    """Corner ids against the meshes' own faces (one loop per object), and the weighted corners
    reproduce the hit point."""
    offsets = [0]
    for o in scene.objects:
        offsets.append(offsets[-1] + len(o.mesh.vertices))
    want = torch.empty(gb.count, 3, dtype=torch.int64)
    for k, o in enumerate(scene.objects):
        sel = gb.object_id == k
        want[sel] = torch.as_tensor(o.mesh.faces, dtype=torch.int64)[gb.prim_id[sel]] + offsets[k]
    assert torch.equal(gb.vertex_ids[gb.corners], want)
    assert torch.equal(gb.vertex_ids, torch.unique(want))  # sorted, culled to the triangles hit
    torch.testing.assert_close(gb.weights.sum(-1), torch.ones(gb.count, dtype=F64), atol=1e-7, rtol=0)
    assert bool((gb.weights >= -1e-6).all())
    verts = torch.cat([torch.as_tensor(o.mesh.vertices, dtype=F64) for o in scene.objects])
    at = (verts[gb.vertex_ids[gb.corners]] * gb.weights[..., None]).sum(1)
    torch.testing.assert_close(at, gb.position, atol=1e-5, rtol=0)


def test_objects_filter_equals_selecting_rows(scene, gb):
    for objects in ("ball", 2, ["ball", "box"]):
        sub = trace_gbuffer(scene, objects=objects)
        ids = [
            scene.object_id(x) if isinstance(x, str) else x
            for x in ([objects] if isinstance(objects, str | int) else objects)
        ]
        rows = torch.isin(gb.object_id, torch.tensor(ids))
        sel = gb.select(rows)
        for name in GBuffer.__dataclass_fields__:
            a, b = getattr(sub, name), getattr(sel, name)
            assert torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b, name
        assert torch.equal(sel.vertex_ids[sel.corners], gb.vertex_ids[gb.corners][rows])
        assert len(sel.vertex_ids) < len(gb.vertex_ids)


def test_camera_argument_and_bad_objects(scene):
    small = trace_gbuffer(scene, scene.camera.with_size(20, 15), objects="ball")
    assert (small.height, small.width) == (15, 20) and bool((small.object_id == 1).all())
    with pytest.raises(SceneError):
        trace_gbuffer(scene, objects="no_such_object")
    with pytest.raises(SceneError):
        trace_gbuffer(scene, objects=[7])
    with pytest.raises(SceneError, match="cover no pixel"):
        trace_gbuffer(scene, objects="hidden")


def test_of_vertices_names_vertices_and_no_pixel():
    g = GBuffer.of_vertices(torch.arange(5), (0.0, 1.0, 2.0), 4, 3)
    assert g.count == 0 and torch.equal(g.vertex_ids, torch.arange(5)) and g.eye.tolist() == [0.0, 1.0, 2.0]
    assert not bool(g.mask.any()) and g.mask.shape == (4, 3)
