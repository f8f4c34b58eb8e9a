"""Resume never mixes stale work: every cache's key holds the scene's content.

The scenario: interrupt a run after it saved a checkpoint, edit the scene's light
and albedo, run the same command again: the result must equal a fresh run of the edited scene
(without the scene's content digest in the key, the render would resume the old scene's
passes and give an image of neither scene). Also: a damaged render checkpoint is moved aside with a warning naming it.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
import trimesh

from tests.records.contract import corrupt_payload
from torch_brdf.records import CorruptCacheWarning, settings_key
from torch_brdf.scene import Scene
from torch_brdf.transport import pathtrace
from torch_brdf.transport.pathtrace import PathTraceSettings, path_trace


def _box_desc(albedo: float, radiance: float) -> dict:
    """A closed emissive box seen from inside, as a scene description (the TOML layout)."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    return {
        "name": "box",
        "camera": {"origin": [0.0, 0.0, 0.0], "target": [0.0, 0.0, 1.0], "fov_deg": 60.0, "width": 8, "height": 8},
        "materials": {"wall": {"type": "lambert", "albedo": albedo}},
        "objects": [
            {
                "name": "cube",
                "vertices": box.vertices.tolist(),
                "faces": box.faces[:, ::-1].tolist(),
                "material": "wall",
            }
        ],
        "lights": [{"type": "area", "object": "cube", "radiance": radiance}],
    }


def _interrupt_after(module, name: str, n: int, monkeypatch) -> None:
    """Make ``module.name`` raise KeyboardInterrupt on its ``n``-th call (a killed run)."""
    real, calls = getattr(module, name), {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, flaky)


def test_content_digest_sees_every_part():
    base = Scene.from_dict(_box_desc(0.5, 1.0))
    d = base.content_digest()
    assert d == Scene.from_dict(_box_desc(0.5, 1.0)).content_digest()  # a function of content only
    assert dataclasses.replace(base, name="other").content_digest() == d
    assert Scene.from_dict(_box_desc(0.6, 1.0)).content_digest() != d  # material
    assert Scene.from_dict(_box_desc(0.5, 1.5)).content_digest() != d  # light
    assert base.with_resolution(9).content_digest() != d  # camera
    moved = _box_desc(0.5, 1.0)
    moved["objects"][0]["translate"] = [0.0, 1e-3, 0.0]
    assert Scene.from_dict(moved).content_digest() != d  # geometry
    # geometry only (visibility): lights, materials and camera do not count
    assert Scene.from_dict(_box_desc(0.6, 2.0)).content_digest(("geometry",)) == base.content_digest(("geometry",))
    assert settings_key({"spp": 4}, base) != settings_key({"spp": 4}, Scene.from_dict(_box_desc(0.5, 1.5)))
    assert settings_key({"spp": 4}, base) != settings_key({"spp": 4})


def test_render_resume_after_scene_edit_equals_fresh_render(tmp_path, monkeypatch):
    old, new = Scene.from_dict(_box_desc(0.5, 1.0)), Scene.from_dict(_box_desc(0.8, 2.5))
    kw = dict(settings=PathTraceSettings(spp=6, max_bounces=2), seed=5, progress=False, checkpoint_every=2)
    ckpt = tmp_path / "render.ckpt.npz"
    _interrupt_after(pathtrace, "_radiance", 5, monkeypatch)  # killed in pass 5, after the pass-4 checkpoint
    with pytest.raises(KeyboardInterrupt):
        path_trace(old, checkpoint=ckpt, **kw)
    monkeypatch.undo()
    assert ckpt.exists()
    resumed = path_trace(new, checkpoint=ckpt, **kw)
    fresh = path_trace(new, **kw)
    assert torch.equal(resumed, fresh)
    assert not torch.allclose(fresh, path_trace(old, **kw), rtol=0.1)  # the edit matters


def test_damaged_render_checkpoint_is_moved_aside_and_recomputed(tmp_path):
    scene = Scene.from_dict(_box_desc(0.5, 1.0))
    kw = dict(settings=PathTraceSettings(spp=4, max_bounces=2), seed=1, progress=False, checkpoint_every=2)
    ckpt = tmp_path / "render.ckpt.npz"
    full = path_trace(scene, checkpoint=ckpt, **kw)
    corrupt_payload(ckpt, ckpt)
    with pytest.warns(CorruptCacheWarning, match="render.ckpt.npz"):
        again = path_trace(scene, checkpoint=ckpt, **kw)
    assert torch.equal(again, full)
    assert (tmp_path / "render.ckpt.npz.corrupt").exists()


def test_precompute_tiles_after_scene_edit_equal_fresh_precompute(tmp_path, monkeypatch):
    from torch_brdf.scene.builtin import cornell_box
    from torch_brdf.scene.lights import AreaLight
    from torch_brdf.transport.polynomial import PolynomialSettings, driver, precompute_polynomial

    old = cornell_box(8)
    old.objects[old.object_id("short_box")].editable = False  # its albedo is baked into the tensors
    light = old.area_lights[old.object_id("light")]
    mesh = old.objects[light.object_id].mesh
    materials = {**old.materials, old.objects[old.object_id("short_box")].material: {"type": "lambert", "albedo": 0.2}}
    new = dataclasses.replace(
        old,
        materials=materials,
        lights=[AreaLight(mesh.vertices, mesh.faces, light.radiance * 3, object_id=light.object_id)],
    )
    # processes=1: the interruption counts tile calls in this process (on a quiet machine tiles
    # would otherwise run in forked processes, which the monkeypatch does not count)
    kw = dict(settings=PolynomialSettings(series="8,1", spp=2, tile_rows=2), seed=3, progress=False, processes=1)
    _interrupt_after(driver, "_tile_entries", 3, monkeypatch)  # two tiles saved, then killed
    with pytest.raises(KeyboardInterrupt):
        precompute_polynomial(old, checkpoint=tmp_path, **kw)
    monkeypatch.undo()
    assert len(list(tmp_path.glob("tile*.npz"))) == 2
    resumed = precompute_polynomial(new, checkpoint=tmp_path, **kw)
    fresh = precompute_polynomial(new, **kw)
    stale = precompute_polynomial(old, **kw)
    assert torch.equal(resumed.emission, fresh.emission)
    assert len(resumed.blocks) == len(fresh.blocks)
    for a, b in zip(resumed.blocks, fresh.blocks, strict=True):
        assert torch.equal(a.values, b.values) and torch.equal(a.pixels, b.pixels)
    assert not torch.equal(stale.emission, fresh.emission)  # the edit matters


def test_transfer_cache_after_scene_edit_equals_fresh_design(tmp_path):
    from torch_brdf.inverse.design import DesignConfig, design
    from torch_brdf.inverse.strokes import Brush, Stroke
    from torch_brdf.records import BasisImage
    from torch_brdf.scene import EnvironmentMap, teatray

    old = teatray((32, 24))
    env = old.environment
    brighter = env.radiance.clone()
    brighter[:, : brighter.shape[1] // 2] *= 3.0  # one half of the sky, so the transfer changes shape
    new = dataclasses.replace(
        old,
        materials={**old.materials, "teapot": {"type": "lambert", "albedo": (0.2, 0.5, 0.3)}},
        lights=[EnvironmentMap(brighter, rotation_y=env.rotation_y)],
    )
    strokes = [Stroke(torch.tensor([[14.0, 12.0]]), Brush(color=(2.0, 2.0, 2.0), diameter=4))]
    cfg = DesignConfig("teapot", downsample=2, light_samples=16, render_scale=0.5, constrained=False)
    design(old, strokes, cfg, tmp_path / "out", progress=False)
    resumed = design(new, strokes, cfg, tmp_path / "out", progress=False)
    fresh = design(new, strokes, cfg, tmp_path / "fresh", progress=False)
    a = BasisImage.load(tmp_path / "out" / "transfer.npz", dtype=torch.float64)
    b = BasisImage.load(tmp_path / "fresh" / "transfer.npz", dtype=torch.float64)
    assert torch.equal(a.values, b.values)
    assert resumed["objective"] == fresh["objective"]


def _toml(desc: dict) -> str:
    """The description as TOML (the few shapes :func:`_box_desc` uses)."""

    def val(v):
        return json.dumps(v)  # numbers, strings and nested lists read the same in TOML

    lines = [f"name = {val(desc['name'])}", "[camera]"]
    lines += [f"{k} = {val(v)}" for k, v in desc["camera"].items()]
    for name, mat in desc["materials"].items():
        lines += [f"[materials.{name}]", *(f"{k} = {val(v)}" for k, v in mat.items())]
    for table in ("objects", "lights"):
        for item in desc[table]:
            lines += [f"[[{table}]]", *(f"{k} = {val(v)}" for k, v in item.items())]
    return "\n".join(lines) + "\n"


def test_cli_render_resume_after_scene_edit(tmp_path, monkeypatch):
    """The user's command: kill ``torch-brdf render scene.toml``, edit light and albedo, run again."""
    from typer.testing import CliRunner

    from torch_brdf.cli import app
    from torch_brdf.io import read_exr

    scene = tmp_path / "scene.toml"
    scene.write_text(_toml(_box_desc(0.5, 1.0)))
    args = ["render", str(scene), "--spp", "8", "--bounces", "2", "--seed", "3"]
    _interrupt_after(pathtrace, "_radiance", 6, monkeypatch)  # after the pass-4 checkpoint
    killed = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a" / "img")])
    monkeypatch.undo()
    assert killed.exit_code != 0 and (tmp_path / "a" / "img.ckpt.npz").exists()
    scene.write_text(_toml(_box_desc(0.8, 2.5)))
    again = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a" / "img")])
    fresh = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "b" / "img"), "--no-resume"])
    assert again.exit_code == 0 and fresh.exit_code == 0, (again.output, fresh.output)
    assert torch.equal(read_exr(tmp_path / "a" / "img.exr"), read_exr(tmp_path / "b" / "img.exr"))
