"""The renderers' freeze and frame paths give bit-identical results whatever thread count
runs them (fixed through ``renderer.threads``), and they run under the measured count."""

from __future__ import annotations

import pytest
import torch

from tests.render.test_triple import renderer as triple_renderer
from tests.transport.test_visibility import ball_on_plane
from torch_brdf.parallel import threads as _threads
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.render.triple import PhongRule
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.scene.envmap import EnvironmentMap
from torch_brdf.transport import _native
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
from torch_brdf.transport.visibility import VisibilitySettings, precompute_visibility

COUNTS = (1, 2, 3)  # 3 > the cores of a 2-core machine: oversubscribed, still the same result


@pytest.fixture(scope="module")
def polynomial():
    sc = cornell_box(32)  # large enough that the products and scatters run in parallel
    sc.materials["glossy"] = {"type": "blinn_phong", "kd": 0.2, "ks": 0.6, "exponent": 100.0}
    sc.objects[sc.object_id("back")].material = "glossy"
    t = precompute_polynomial(sc, PolynomialSettings("8,4,1", spp=2), seed=5, progress=False)
    return t, {o.name: sc.materials[o.material] for o in sc.objects if o.editable}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_polynomial_freeze_and_frame_are_bitwise_equal_for_any_thread_count(polynomial, dtype):
    tensors, mats = polynomial
    frames, frozen = [], []
    for n in COUNTS:
        r = PolynomialRenderer(tensors, mats, dtype=dtype)
        r.threads = n
        r.freeze("back")
        frozen.append((r._frozen["F"], r._frozen["V"]))
        r.set_material("back", {"type": "blinn_phong", "kd": 0.3, "ks": 0.4, "exponent": 40.0})
        frames.append(r())
    for (f, v), img in zip(frozen[1:], frames[1:], strict=True):
        assert torch.equal(f, frozen[0][0]) and torch.equal(v, frozen[0][1])
        assert torch.equal(img, frames[0])


def test_polynomial_paths_run_under_the_measured_count(polynomial, monkeypatch):
    monkeypatch.delenv(_threads.ENV_THREADS, raising=False)
    tensors, mats = polynomial
    _threads.reset_tuning()
    seen = []
    real = PolynomialRenderer._frozen_frame.__wrapped__

    def spy(self):
        seen.append(torch.get_num_threads())
        return real(self)

    monkeypatch.setattr(PolynomialRenderer, "_frozen_frame", _threads.tuned_method(
        "polynomial.frame", lambda r: r.frozen_nbytes)(spy))  # fmt: skip
    r = PolynomialRenderer(tensors, mats)
    r.freeze("back")
    for _ in range(8):
        r()
    state = _threads.tuning_state()
    ops = {op for op, _ in state}
    assert ops == {"polynomial.freeze", "polynomial.frame"}
    frame = next(v for (op, _), v in state.items() if op == "polynomial.frame")
    tried = _threads.candidates(_threads.intra_op_threads())
    assert sorted(set(seen)) == tried  # each candidate measured on real frames
    assert frame["chosen"] in tried and seen[-1] == frame["chosen"]
    _threads.reset_tuning()


def test_triple_product_frame_is_bitwise_equal_for_any_thread_count():
    sc = ball_on_plane(quads=24)  # ~15k (vertex, block) pairs: parallel kernels
    sc.lights[:] = [EnvironmentMap.sky(height=32, sun_radiance=(400.0, 380.0, 350.0), sun_angular_radius_deg=4.0)]
    vis = precompute_visibility(sc, VisibilitySettings(resolution=32, chunk=64), progress=False)
    for path in ("shade_torch", "shade_compiled") if _native.library() is not None else ("shade_torch",):
        out = []
        for n in COUNTS:
            r = triple_renderer(sc, vis, dtype=torch.float32)
            r.threads = n
            v = r.view()
            out.append(getattr(r, path)(v, PhongRule())[0])
        for x in out[1:]:
            assert torch.equal(x, out[0]), path
