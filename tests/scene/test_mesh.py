"""Mesh loading and validation: round trips through OBJ/PLY, and the bad-mesh policy
(NaN -> MeshError, zero-area faces dropped with a warning, bad indices, bad files)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import trimesh

from torch_brdf.errors import FileFormatError, MeshError, TorchBRDFError
from torch_brdf.scene import DegenerateFacesWarning, RayTracer, load_mesh, mesh_from_arrays
from torch_brdf.scene.mesh import validate_mesh


def _canonical_triangles(mesh: trimesh.Trimesh) -> np.ndarray:
    """(F, 9) triangle corner coordinates, each triangle rotated (winding kept) to start at
    its lexicographically smallest corner, rows sorted: equal for equal oriented triangle sets."""
    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    out = []
    for t in tri:
        k = min(range(3), key=lambda i, t=t: tuple(t[i]))
        out.append(np.roll(t, -k, axis=0).reshape(-1))
    out = np.array(out)
    return out[np.lexsort(out.T[::-1])]


def _asymmetric_box() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.apply_translation((0.5, -1.25, 2.0))
    return box


@pytest.mark.parametrize(
    ("filename", "export_kwargs"),
    [("box.obj", {}), ("box.ply", {}), ("box_ascii.ply", {"encoding": "ascii"})],
)
def test_load_round_trip(tmp_path, filename, export_kwargs):
    src = _asymmetric_box()
    path = tmp_path / filename
    src.export(path, **export_kwargs)
    mesh = load_mesh(path)
    assert isinstance(mesh, trimesh.Trimesh)
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
    assert mesh.faces.shape == (12, 3)
    np.testing.assert_allclose(_canonical_triangles(mesh), _canonical_triangles(src), atol=1e-6)
    # orientation kept: the closed box has positive signed volume
    assert mesh.volume == pytest.approx(6.0, rel=1e-6)


def test_multi_part_obj_is_concatenated(tmp_path):
    a = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    b = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    b.apply_translation((3.0, 0.0, 0.0))
    scene = trimesh.Scene({"a": a, "b": b})
    path = tmp_path / "two.obj"
    scene.export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 24
    assert mesh.area == pytest.approx(12.0)
    np.testing.assert_allclose(mesh.bounds, [[-0.5, -0.5, -0.5], [3.5, 0.5, 0.5]], atol=1e-6)


def test_mesh_from_arrays_returns_a_validated_copy():
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    mesh = mesh_from_arrays(v, [[0, 1, 2]], "tri")
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])
    assert mesh.area == pytest.approx(0.5)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_vertex_raises_mesh_error_naming_the_mesh(bad):
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [bad, 0, 1]]
    with pytest.raises(MeshError, match="teapot"):
        mesh_from_arrays(v, [[0, 1, 2], [1, 2, 3]], "teapot")


def test_vertices_beyond_float32_raise_mesh_error(tmp_path):
    # finite in float64 but Inf in the float32 that embree traces: an unchecked render would run
    obj = tmp_path / "huge.obj"
    obj.write_text("v 0 0 0\nv 1e300 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"huge\.obj.*1 vertices exceed the float32 range"):
        load_mesh(obj)
    with pytest.raises(MeshError, match="float32 range"):  # also what a TOML 'scale' makes
        validate_mesh(trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False).apply_scale(1e39))


def test_nan_vertex_in_files_raises_mesh_error_naming_the_file(tmp_path):
    obj = tmp_path / "broken.obj"
    obj.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"broken\.obj"):
        load_mesh(obj)
    with pytest.raises(MeshError, match="widget"):
        load_mesh(obj, name="widget")
    src = trimesh.Trimesh(
        vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]], faces=[[0, 1, 2], [0, 1, 3]], process=False
    )
    ply = tmp_path / "broken.ply"
    src.export(ply)
    with pytest.raises(MeshError, match=r"broken\.ply"):
        load_mesh(ply)


# A unit square (faces 0 and 2), a triangle next to it (face 4) and two zero-area faces:
# a repeated index (face 1) and three exactly collinear vertices (face 3).
_V = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]]
_F = [[0, 1, 2], [0, 0, 1], [0, 2, 3], [0, 4, 5], [1, 4, 2]]
_KEPT = [[0, 1, 2], [0, 2, 3], [1, 4, 2]]


def test_degenerate_faces_are_dropped_with_a_warning():
    with pytest.warns(DegenerateFacesWarning, match=r"'square'.*\b2\b.*\b5\b") as rec:
        mesh = mesh_from_arrays(_V, _F, "square")
    assert len(rec) == 1
    np.testing.assert_array_equal(mesh.faces, _KEPT)
    np.testing.assert_array_equal(mesh.vertices, np.asarray(_V, dtype=np.float64))


def test_validate_mesh_does_not_modify_its_input():
    src = trimesh.Trimesh(vertices=_V, faces=_F, process=False)
    with pytest.warns(DegenerateFacesWarning):
        out = validate_mesh(src, "square")
    assert len(src.faces) == 5 and len(out.faces) == 3
    assert out is not src


def test_prim_ids_index_the_cleaned_mesh():
    """After dropping, triangle ids are dense: a ray at kept face k reports prim_id k."""
    with pytest.warns(DegenerateFacesWarning):
        mesh = mesh_from_arrays(_V, _F, "square")
    tracer = RayTracer([mesh], [False])
    centroids = torch.tensor(np.array(mesh.triangles_center))
    origins = centroids + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    hits = tracer.trace(origins, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64).expand(3, 3))
    assert hits.object_id.tolist() == [0, 0, 0]
    assert hits.prim_id.tolist() == [0, 1, 2]


def test_degenerate_faces_in_a_file_are_dropped_too(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 1 2\nf 1 3 4\n")
    with pytest.warns(DegenerateFacesWarning, match=r"quad\.obj.*\b1\b"):
        mesh = load_mesh(path)
    assert len(mesh.faces) == 2
    assert mesh.area == pytest.approx(1.0)


def test_no_warning_for_clean_meshes():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = mesh_from_arrays(_V[:4], [[0, 1, 2], [0, 2, 3]], "clean")
    assert len(mesh.faces) == 2


def test_all_degenerate_raises_mesh_error():
    with pytest.raises(MeshError, match="needle"):
        mesh_from_arrays([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2], [0, 0, 1]], "needle")


@pytest.mark.parametrize("faces", [[[0, 1, 3]], [[0, 1, -1]], [[0, 1, 2], [2, 1, 99]]])
def test_out_of_range_indices_raise_mesh_error(faces):
    with pytest.raises(MeshError, match="tri"):
        mesh_from_arrays([[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces, "tri")


def test_out_of_range_index_in_a_file_is_a_torch_brdf_error(tmp_path):
    # trimesh fails while reading (FileFormatError); either way the package's own error
    path = tmp_path / "badidx.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises((MeshError, FileFormatError), match=r"badidx\.obj"):
        load_mesh(path)


def test_no_faces_raises_mesh_error():
    with pytest.raises(MeshError, match="empty"):
        mesh_from_arrays([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.zeros((0, 3), dtype=np.int64), "empty")


def test_faces_of_wrong_shape_raise_mesh_error():
    with pytest.raises(MeshError):
        mesh_from_arrays([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [0, 1], "tri")


def test_vertices_of_wrong_shape_raise_mesh_error():
    with pytest.raises(MeshError, match="tri"):
        mesh_from_arrays([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], "tri")


def test_missing_file_raises_file_format_error(tmp_path):
    with pytest.raises(FileFormatError, match=r"nope\.obj"):
        load_mesh(tmp_path / "nope.obj")
    with pytest.raises(FileFormatError):
        load_mesh(tmp_path)  # a folder is not a mesh file


def test_corrupt_ply_raises_file_format_error(tmp_path):
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01not a ply at all\xff" * 8)
    with pytest.raises(FileFormatError, match=r"garbage\.ply"):
        load_mesh(garbage)
    whole = tmp_path / "whole.ply"
    _asymmetric_box().export(whole)
    truncated = tmp_path / "truncated.ply"
    raw = whole.read_bytes()
    truncated.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FileFormatError, match=r"truncated\.ply"):
        load_mesh(truncated)


def test_obj_without_faces_is_rejected(tmp_path):
    # OBJ has no magic number: trimesh reads text without 'v'/'f' lines as an empty mesh
    path = tmp_path / "text.obj"
    path.write_text("this is not\na mesh\n")
    with pytest.raises((MeshError, FileFormatError), match=r"text\.obj"):
        load_mesh(path)


def test_unsupported_file_type_raises_file_format_error(tmp_path):
    path = tmp_path / "mesh.xyzq"
    path.write_text("1 2 3\n")
    with pytest.raises(FileFormatError):
        load_mesh(path)


def test_errors_share_the_package_base_class():
    assert issubclass(MeshError, TorchBRDFError) and issubclass(FileFormatError, TorchBRDFError)


@pytest.mark.parametrize(
    "vertices",
    [
        [[0.1, 0.2, 0.3], [0.2, 0.4, 0.6], [0.3, 0.6, 0.9], [1.0, 0.0, 0.0]],  # collinear, not exactly in binary
        [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0 + 1e-9, 0.0], [1.0, 0.0, 0.0]],  # collinear once in float32
    ],
)
def test_numerically_collinear_faces_are_dropped(vertices):
    with pytest.warns(DegenerateFacesWarning, match="dropped 1 of 2"):
        m = mesh_from_arrays(vertices, [[0, 1, 2], [0, 1, 3]], "sliver")
    assert len(m.faces) == 1
    tracer = RayTracer([m], [False])
    assert bool(torch.isfinite(tracer.face_normals).all())
