"""``datasets/originals.py``: every data file has a pinned original source (or says why not),
and the conversions do what the data folder's files need, on small inputs made here (the
sources themselves are downloads, which the tests never make)."""

from __future__ import annotations

import hashlib
import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

from torch_brdf.data import REGISTRY

_SPEC = importlib.util.spec_from_file_location(
    "originals", Path(__file__).resolve().parents[1] / "datasets" / "originals.py"
)
originals = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(originals)


def test_every_file_has_a_pinned_source_or_a_reason():
    for name in REGISTRY:
        if name in originals.NOT_REBUILT:
            assert originals.NOT_REBUILT[name]
            continue
        keys, _ = originals.recipe(name)
        for key in keys:
            url, digest = originals.SOURCES[key]
            # a commit, never a branch: the bytes at the URL cannot change under the pin
            assert re.match(r"^https://raw\.githubusercontent\.com/[\w.-]+/[\w.-]+/[0-9a-f]{40}/", url), url
            assert re.fullmatch(r"[0-9a-f]{64}", digest), key
    assert set(originals.NOT_REBUILT) <= set(REGISTRY)


def test_cornell_part_faces_into_the_room():
    # the back wall (z = 559.2) as one quad wound away from the room, with a normal and a stray vertex
    src = b"v 0 0 559.2\nv 556 0 559.2\nv 556 548.8 559.2\nv 0 548.8 559.2\nv 9 9 9\nvn 0 0 1\nf 1 4 3 2\n"
    src = src.replace(b"f 1 4 3 2", b"f 1//1 2//1 3//1 4//1")
    out = originals.cornell_part("back", src).decode()
    v = np.array([[float(x) for x in ln.split()[1:]] for ln in out.splitlines() if ln.startswith("v ")])
    f = np.array([[int(x) - 1 for x in ln.split()[1:]] for ln in out.splitlines() if ln.startswith("f ")])
    assert len(v) == 4 and len(f) == 2  # unused vertex and normals dropped, the quad as a fan
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (n[:, 2] < 0).all()  # towards the camera side of the room (smaller z)


def test_strip_dragon_drops_the_ground_quad():
    body = np.array([[0, 1, 0], [1, 2, 0], [0, 2, 1]], np.float32)
    ground = np.array([[-25, 0, -25], [25, 0, -25], [-25, 0, 25], [25, 0, 25]], np.float32)
    xyz = np.concatenate([body, ground])
    vdt = np.dtype([(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")] + [("flags", "<i4")])
    v = np.zeros(len(xyz), vdt)
    v["x"], v["y"], v["z"] = xyz.T
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,)), ("flags", "<i4")])
    f = np.zeros(3, fdt)
    f["n"], f["i"] = 3, [[0, 1, 2], [3, 4, 5], [4, 6, 5]]
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
        "property float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty int flags\n"
        "element face 3\nproperty list uchar int vertex_indices\nproperty int flags\nend_header\n"
    )
    out = originals.strip_dragon(header.encode() + v.tobytes() + f.tobytes())
    import trimesh

    mesh = trimesh.load(trimesh.util.wrap_as_stream(out), file_type="ply", process=False)
    assert np.array_equal(np.asarray(mesh.vertices, np.float32), body)
    assert np.array_equal(np.asarray(mesh.faces), [[0, 1, 2]])


def test_convert_envmap_keeps_the_power_and_reads_rgbe():
    pytest.importorskip("OpenEXR")
    from torch_brdf.io import read_exr

    g = np.random.default_rng(3)
    img = g.random((8, 16, 3)).astype(np.float32) * 4
    # flat RGBE scanlines: mantissas m with a shared exponent e, value = m * 2^(e - 136) = m * 16 here
    e = np.full((8, 16, 1), 140, np.uint8)
    rgbe = np.concatenate([np.floor(img * 16).clip(0, 255).astype(np.uint8), e], axis=-1)
    data = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 8 +X 16\n" + rgbe.tobytes()
    src = originals.read_rgbe(data)
    assert np.array_equal(src, rgbe[..., :3].astype(np.float32) * 16)
    out = read_exr_bytes(originals.convert_envmap(data, False, 8), read_exr)
    assert out.shape == (4, 8, 3)
    w_src = np.sin((np.arange(8) + 0.5) * np.pi / 8)[:, None, None]
    # block averages weighted by solid angle: each output texel's mean equals its block's weighted mean
    num = (src * w_src).reshape(4, 2, 8, 2, 3).sum(axis=(1, 3))
    den = np.broadcast_to(w_src, (8, 16, 1)).reshape(4, 2, 8, 2, 1).sum(axis=(1, 3))
    np.testing.assert_allclose(out, num / den, rtol=1e-6)


def read_exr_bytes(data: bytes, read_exr):
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.exr"
        path.write_bytes(data)
        return np.asarray(read_exr(path))


def test_rebuild_keeps_only_what_matches_its_pin(tmp_path, monkeypatch):
    good = b"solid\n"
    monkeypatch.setattr(originals, "REGISTRY", {"meshes/teapot.obj": hashlib.sha256(good).hexdigest()})
    monkeypatch.setattr(originals, "download", lambda key, progress=False: good)
    report = originals.rebuild(tmp_path, ["meshes/teapot.obj"])
    assert report["written"] == ["meshes/teapot.obj"] and (tmp_path / "meshes" / "teapot.obj").read_bytes() == good
    report = originals.rebuild(tmp_path, ["meshes/teapot.obj"])  # present and right: kept, not downloaded
    assert report["kept"] == ["meshes/teapot.obj"]
    monkeypatch.setattr(originals, "download", lambda key, progress=False: b"other bytes\n")
    (tmp_path / "meshes" / "teapot.obj").unlink()
    report = originals.rebuild(tmp_path, ["meshes/teapot.obj"])
    assert report["mismatch"] == ["meshes/teapot.obj"] and not (tmp_path / "meshes" / "teapot.obj").exists()
    assert not list((tmp_path / "meshes").iterdir())  # no temporary file left behind
