"""The widget application in-process (no browser): what the page shows for good and bad input."""

from __future__ import annotations

import json
import math

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
    assert (app.frame.width, app.frame.height) == (32, 32) and len(app.frame.pixels) == 32 * 32 * 4
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


def _typed_box(app, name):
    return next(
        w
        for row in app.panel.box.children
        for w in getattr(row, "children", ())
        if f"tb-typed-{name}" in w._dom_classes
    )


def _snapped(ctl, value):
    """What chromium's log slider sends back for ``value``: 10 ** (the nearest grid point)."""
    k = round((math.log10(value) - ctl.min) / ctl.step)
    return 10 ** (ctl.min + k * ctl.step)


def test_the_browsers_grid_echo_is_not_an_edit(app):
    # ipywidgets' FloatLogSlider sends back every value the kernel gives it, moved to its grid
    # (a new form's first value too); arriving after a typed value, it must not re-render, clear
    # that value's message and overwrite the typed box (a value typed the instant a form appears
    # would be lost).
    app.model.value = "lambert"
    app.model.value = "GGX (cook_torrance)"
    ctl, typed = app.controls["roughness"], _typed_box(app, "roughness")
    start = app.session.materials["back"]["roughness"]
    typed.value = "7"  # typed before the slider's echo arrives
    assert "tb-error" in app.message.value and "roughness" in app.message.value
    frame = bytes(app.frame.pixels)
    assert _snapped(ctl, start) != start
    ctl.value = _snapped(ctl, start)  # the echo
    assert "tb-error" in app.message.value and typed.value == "7" and bytes(app.frame.pixels) == frame
    assert app.session.materials["back"]["roughness"] == start
    typed.value = "0.5"  # in range: applied exactly as typed, and its echo changes nothing
    assert app.session.materials["back"]["roughness"] == 0.5 and "tb-error" not in app.message.value
    ctl.value = _snapped(ctl, 0.5)
    assert app.session.materials["back"]["roughness"] == 0.5 and typed.value == "0.5"
    app.controls["kd"].value = "#336699"  # another edit keeps the exact roughness
    assert app.session.materials["back"]["roughness"] == 0.5
    ctl.value = _snapped(ctl, 0.5) * 10**ctl.step  # one step of a drag is an edit
    assert app.session.materials["back"]["roughness"] == ctl.value and typed.value == f"{ctl.value:.4g}"


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


def test_every_library_model_is_in_the_menu_or_says_why(app):
    from torch_brdf.brdf import available
    from torch_brdf.data import data_path

    listed = {c.model for c in app.choices}
    assert listed | set(app.skipped) == set(available())
    assert {"factored_1d", "factored_1d_fresnel"} <= listed  # curves on the object's bands
    if data_path("merl", "nbrdf_merl100_weights.npz", required=False) is None:
        assert "not found" in app.skipped["nbrdf"] and "nbrdf: needs" in app.menu_note.value
    else:
        assert {"nbrdf", "merl"} <= listed and not app.skipped


def test_curve_form_edits_the_bands_as_they_are(app):
    import torch

    app.model.value = "blinn_phong"
    before = app.session.projected["back"].clone()
    app.model.value = "factored_1d"
    assert list(app.controls) == ["coefficients"]
    m = app.session.tensors.object_id("back")
    c = app.session.renderer.c[m].double()
    assert torch.allclose(c, before, rtol=1e-5, atol=1e-9)  # the current curve (6 digits), used as is
    lines = app.controls["coefficients"].value.splitlines()
    assert len(lines) == app.session.basis("back").J
    lines[0] = "0.5"  # a grey line
    app.controls["coefficients"].value = "\n".join(lines)
    assert torch.allclose(app.session.renderer.c[m][0].double(), torch.full((3,), 0.5, dtype=torch.float64))
    for bad, words in (("\n".join(lines[:-1]), "bands"), ("\n".join(["-1"] + lines[1:]), "must be")):
        app.controls["coefficients"].value = bad
        assert "tb-error" in app.message.value and words in app.message.value
    app.model.value = "factored_1d_fresnel"
    assert list(app.controls) == ["coefficients", "f0"]
    assert app.session.materials["back"]["type"] == "factored_1d_fresnel"


def test_measured_models_pick_a_material(app):
    names = {c.model: c for c in app.choices}
    if "nbrdf" not in names:
        pytest.skip("shared data not found: merl/nbrdf_merl100_weights.npz")
    for model in ("nbrdf", "merl"):
        app.model.value = names[model].label
        ctl = app.controls["material"]
        first = bytes(app.frame.pixels)
        ctl.value = ctl.options[-1]
        assert app.session.materials["back"] == {**dict(names[model].fixed), "type": model, "material": ctl.options[-1]}
        assert bytes(app.frame.pixels) != first and "tb-error" not in app.message.value


def test_relighting_tab_rotates_orbits_and_edits(small_tensors_file, relight_files):
    app = EditorApp(
        {
            "source": str(small_tensors_file[0]),
            "threads": 0,
            "relight_scene": str(relight_files[0]),
            "relight_visibility": str(relight_files[1]),
        }
    )
    assert app.tabs.get_title(1) == "relighting" and "data-object='box'" in app.rl_selected.value
    assert (app.rl_frame.width, app.rl_frame.height) == (32, 24) and "triple products" in app.rl_frame.info
    first = bytes(app.rl_frame.pixels)
    app.rl_rotation.value = 120.0
    turned = bytes(app.rl_frame.pixels)
    assert turned != first and "environment 120°" in app.rl_frame.info
    app.rl_orbit.value = 30.0
    assert bytes(app.rl_frame.pixels) != turned and "orbit 30°" in app.rl_frame.info
    assert [c.model for c in app.rl_panel.choices if c.on_bands] == []  # no bands to hold a curve
    app.rl_panel.model.value = "blinn_phong"
    assert app.relight.materials["box"]["type"] == "blinn_phong"
    before = bytes(app.rl_frame.pixels)
    app.rl_panel.controls["exponent"].value = 3.0
    assert bytes(app.rl_frame.pixels) != before
    app._guard(app.rl_panel.on_typed, "exponent", "-4")
    assert "tb-error" in app.message.value and "exponent" in app.message.value
    broken = EditorApp(
        {"source": str(small_tensors_file[0]), "threads": 0, "relight_scene": "cornell_box", "relight_visibility": "x"}
    )
    assert broken.relight is None and "could not open the relighting scene" in broken.rl_selected.value
    assert broken.session is not None  # the multibounce tab works


def test_frame_messages_send_the_changed_tiles_and_rebuild_the_frame():
    import numpy as np
    import torch

    from torch_brdf.editor.widgets import TILE, FrameView, decode_rgbe

    view, sent = FrameView(), []
    view.send = lambda content, buffers=None: sent.append((content, bytes(buffers[0])))
    g = torch.Generator().manual_seed(3)
    img = torch.rand(2 * TILE + 5, 3 * TILE, 3, generator=g) * 4  # edge tiles are cut short
    view.show_linear(img)
    view.show_linear(img)  # nothing changed: an empty patch
    img[TILE + 3, 2 * TILE + 1] += 1.0  # one pixel in tile (1, 2), one in the short bottom row
    img[-1, 0] = 0.0
    view.show_linear(img)
    (full, data), (empty, none), (patch, tiles) = sent
    assert full["full"] and len(data) == img.shape[0] * img.shape[1] * 4
    assert not empty["full"] and empty["tiles"] == [] and none == b""
    assert not patch["full"] and patch["base"] == full["seq"] + 1 == patch["seq"] - 1
    nx = 3
    assert patch["tiles"] == [1 * nx + 2, 2 * nx + 0]
    page = np.frombuffer(data, np.uint8).reshape(*img.shape[:2], 4).copy()  # what the page does
    off = 0
    for t in patch["tiles"]:
        y0, x0 = (t // nx) * TILE, (t % nx) * TILE
        th, tw = min(TILE, page.shape[0] - y0), min(TILE, page.shape[1] - x0)
        page[y0 : y0 + th, x0 : x0 + tw] = np.frombuffer(tiles[off : off + th * tw * 4], np.uint8).reshape(th, tw, 4)
        off += th * tw * 4
    assert off == len(tiles) and np.array_equal(page, view.frame)
    err = (decode_rgbe(page) - img).abs()
    assert bool((err <= img.amax(-1, keepdim=True) / 256).all())  # RGBE's stated precision
