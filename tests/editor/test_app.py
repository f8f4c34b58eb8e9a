"""The widget application in-process (no browser): what the page shows for good and bad input."""

from __future__ import annotations

import json

import pytest

from tests.conftest import corrupted_copy

pytest.importorskip("anywidget", reason="the editor extra is not installed (pip install -e '.[editor]')")

from torch_brdf.editor.app import EditorApp, srgb8_fast
from torch_brdf.editor.server import write_notebook


@pytest.fixture(scope="module")
def app(small_tensors_file):
    return EditorApp({"source": str(small_tensors_file[0]), "threads": 0})


def test_start_selects_the_back_wall_and_shows_a_frame(app):
    assert app.session.selected == "back" and "data-object='back'" in app.selected.value
    assert (app.frame.width, app.frame.height) == (32, 32) and len(app.frame.pixels) == 32 * 32 * 3
    assert "frame" in app.frame.info and "primary rays" in app.status.value
    assert "<svg" in app.lobe.value and app.sphere.width == 96


def test_form_follows_the_model_and_refuses_typed_values(app):
    app.model.value = "GGX (cook_torrance)"
    assert list(app.controls) == ["roughness", "f0", "kd"]
    assert app.session.materials["back"]["type"] == "cook_torrance"
    app._guard(app._on_typed, "roughness", "7")
    assert "tb-error" in app.message.value and "roughness" in app.message.value
    app._guard(app._on_typed, "roughness", "abc")
    assert "not a number" in app.message.value


def test_clicks_and_fixed_objects(app, small_tensors_file, small_scene):
    from torch_brdf.editor import object_id_buffer

    ids = object_id_buffer(small_tensors_file[1], small_scene)[0]
    y, x = (ids == small_scene.object_id("light")).nonzero()[0].tolist()
    app._guard(app.click, x, y)
    assert "fixed" in app.message.value and app.session.selected == "back"


def test_bad_sources_show_a_message_and_keep_the_session(app, tmp_path, small_tensors_file):
    before = app.session
    app.open(str(corrupted_copy(small_tensors_file[0], tmp_path / "c.npz")))
    assert "could not open" in app.message.value and app.session is before
    fresh = EditorApp({"source": "no_such_scene", "threads": 0})
    assert fresh.session is None and "unknown scene" in fresh.message.value


def test_notebook_embeds_the_config(tmp_path):
    nb = json.loads(write_notebook(tmp_path / "e.ipynb", {"source": "x.npz"}).read_text())
    assert "EditorApp" in nb["cells"][0]["source"] and "x.npz" in nb["cells"][0]["source"]


def test_fast_srgb_is_to_srgb8_within_one_level(gen):
    import torch

    from torch_brdf.io import to_srgb8

    img = torch.rand(64, 64, 3, generator=gen) * 1.5 - 0.1
    img[0, 0] = torch.tensor([0.0, 1e-5, 0.0031308])
    for exposure in (0.0, -1.5, 2.0):
        diff = srgb8_fast(img, exposure).int() - to_srgb8(img, exposure=exposure).int()
        assert int(diff.abs().max()) <= 1
