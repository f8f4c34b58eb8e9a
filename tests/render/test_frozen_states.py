"""PolynomialRenderer keeps a frozen state per object: after any sequence of edits on several
objects a frame equals the full evaluation; a state is reused while nothing it depends on
changed, brought up to date (not rebuilt) when something did, and dropped least recently used
beyond the memory bound."""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

from ..conftest import RTOL

EDITABLE = ("back", "left", "floor", "right")


@pytest.fixture(scope="module")
def tensors():
    sc = cornell_box(8)
    sc.materials["glossy"] = {"type": "blinn_phong", "kd": 0.2, "ks": 0.6, "exponent": 100.0}
    sc.objects[sc.object_id("back")].material = "glossy"
    sc.objects[sc.object_id("short_box")].editable = False  # a fixed object's factors stay inside
    out = {
        s: precompute_polynomial(sc, PolynomialSettings(s, spp=2), seed=7, progress=False) for s in ("8,1,1,1", "8,4,1")
    }
    return out, {o.name: sc.materials[o.material] for o in sc.objects if o.editable}


def _rel(a, b):
    return float((a - b).detach().abs().max() / b.detach().abs().max().clamp_min(1e-30))


def _edit(R, obj, gen, zero=False):
    """Random coefficients for ``obj`` (all zero with ``zero``: its terms vanish from the states
    frozen meanwhile, and must come back when it is edited again)."""
    T = R.tensors
    b = T.bases[T.object_id(obj)]
    draw = (lambda *s: torch.zeros(*s, dtype=torch.float64)) if zero else (
        lambda *s: torch.rand(*s, generator=gen, dtype=torch.float64))  # fmt: skip
    R.set_coefficients(obj, draw(b.size, 3), d=draw(3), c_hat=draw(b.second_size, 3) if R.two_level else None)


OPS = st.lists(
    st.tuples(st.sampled_from(("freeze", "edit", "zero", "weights", "frame")), st.sampled_from(EDITABLE)),
    min_size=4,
    max_size=14,
)


@pytest.mark.parametrize("density", [PolynomialRenderer.SPARSE_FRAME_DENSITY, 1.0])  # dense F / CSR frames
@pytest.mark.parametrize("series", ["8,1,1,1", "8,4,1"])
@settings(max_examples=8, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=OPS, seed=st.integers(0, 2**16))
def test_any_edit_sequence_frames_equal_full_evaluation(tensors, series, density, ops, seed, monkeypatch):
    monkeypatch.setattr(PolynomialRenderer, "SPARSE_FRAME_DENSITY", density)
    T, mats = tensors
    R = PolynomialRenderer(T[series], mats, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    R.freeze(ops[0][1])
    for op, obj in ops:
        if op == "freeze":
            R.freeze(obj)
        elif op in ("edit", "zero"):
            _edit(R, obj, gen, zero=op == "zero")
        elif op == "weights":
            R.set_weight_map(obj, torch.rand(T[series].height, T[series].width, generator=gen, dtype=torch.float64))
        assert _rel(R(), R.evaluate()) < RTOL[torch.float64], (op, obj)
    for obj in R.frozen_objects:  # every kept state, visited again, is exact too
        R.freeze(obj)
        assert _rel(R(), R.evaluate()) < RTOL[torch.float64], obj


def test_frames_read_the_state_of_the_object_edited_last(tensors, gen):
    T, mats = tensors
    R = PolynomialRenderer(T["8,4,1"], mats, dtype=torch.float64)
    R.freeze("back")
    R.freeze("left")
    _edit(R, "back", gen)
    img = R()
    assert R.frozen_object == "back" and R.frozen_objects == ["left", "back"]
    assert _rel(img, R.evaluate()) < RTOL[torch.float64]
    _edit(R, "right", gen)  # not frozen: frames stay on the active state, refreshed
    assert _rel(R(), R.evaluate()) < RTOL[torch.float64] and R.frozen_object == "back"


def test_switching_back_reuses_or_refreshes_the_kept_state(tensors, gen, monkeypatch):
    T, mats = tensors
    R = PolynomialRenderer(T["8,4,1"], mats, dtype=torch.float64)
    built = []
    real = PolynomialRenderer._freeze

    def counting(self, i):
        built.append(self.tensors.object_names[i])
        return real(self, i)

    monkeypatch.setattr(PolynomialRenderer, "_freeze", counting)
    R.freeze("back")
    _edit(R, "back", gen)
    R()
    R.freeze("left")  # first visit: contracted
    back = R._states[T["8,4,1"].object_id("back")]
    assert R.is_fresh("back")  # freezing left changed nothing back depends on
    R.freeze("back")
    assert built == ["back", "left"] and R._frozen is back and back.get("refreshes", 0) == 0
    _edit(R, "back", gen)
    R()
    R.freeze("left")  # back's edits moved left's constants: updated in place, not rebuilt
    assert built == ["back", "left"] and R._states[T["8,4,1"].object_id("left")]["refreshes"] == 1
    assert _rel(R(), R.evaluate()) < RTOL[torch.float64]
    R.freeze("left", cached=False)
    assert built == ["back", "left", "left"]


def test_least_recently_used_states_go_beyond_the_memory_bound(tensors):
    T, mats = tensors
    R = PolynomialRenderer(T["8,1,1,1"], mats, dtype=torch.float64)
    sizes = {}
    for obj in ("back", "left", "floor"):
        R.freeze(obj, cached=False)
        sizes[obj] = R._state_nbytes(R._frozen)
    assert R.frozen_objects == ["back", "left", "floor"]
    assert R.frozen_cache_nbytes == sum(sizes.values())
    R.max_frozen_bytes = sizes["left"] + sizes["floor"]
    R.freeze("left")  # most recently used now; back is the least and goes
    assert R.frozen_objects == ["floor", "left"] and R.frozen_cache_nbytes <= R.max_frozen_bytes
    R.max_frozen_bytes = 0  # the active state always stays
    R.freeze("right")
    assert R.frozen_objects == ["right"]
    R.drop_frozen()
    assert R.frozen_objects == [] and R.frozen_object is None
    torch.testing.assert_close(R(), R.evaluate())


def test_a_denoised_state_is_dropped_when_another_object_changes(tensors, gen):
    T, mats = tensors
    R = PolynomialRenderer(T["8,1,1,1"], mats, dtype=torch.float64)
    R.freeze("left")
    R.freeze("back", denoiser=lambda imgs, groups: imgs * 0.5)
    assert R.frozen_denoiser is not None and R.frozen_objects == ["left", "back"]
    _edit(R, "back", gen)  # its own edits keep it
    assert R.frozen_objects == ["left", "back"]
    _edit(R, "floor", gen)
    assert R.frozen_objects == ["left"] and R.frozen_object is None
    assert _rel(R(), R.evaluate()) < RTOL[torch.float64]  # no state of floor: full evaluation


def test_stream_reads_every_frame_array(tensors, monkeypatch):
    monkeypatch.setattr(PolynomialRenderer, "SPARSE_FRAME_DENSITY", 1.0)
    T, mats = tensors
    R = PolynomialRenderer(T["8,1,1,1"], mats, dtype=torch.float64)
    R.freeze("back")
    arrays = R.frame_arrays()
    assert len(arrays) == 7  # V, emission, CSR rows, columns, three channels' values
    assert float(R.stream()) == pytest.approx(sum(float(a.sum(dtype=torch.float64)) for a in arrays))


def test_csr_frame_gradients_match_finite_differences(tensors, gen, monkeypatch):
    monkeypatch.setattr(PolynomialRenderer, "SPARSE_FRAME_DENSITY", 1.0)
    T, mats = tensors
    T = T["8,4,1"]
    R = PolynomialRenderer(T, mats, dtype=torch.float64)
    b = T.bases[T.object_id("back")]
    w = torch.rand(T.height, T.width, 3, generator=gen, dtype=torch.float64)
    shapes = ((b.size, 3), (3,), (b.second_size, 3))
    args = tuple(torch.rand(*s, generator=gen, dtype=torch.float64).requires_grad_() for s in shapes)
    R.freeze("back")
    assert R._frozen_csr(R._frozen) is not None

    def loss(c, d, h):
        R.set_coefficients("back", c, d=d, c_hat=h)
        return (R() * w).sum()

    assert torch.autograd.gradcheck(loss, args, eps=1e-6, atol=1e-7, rtol=1e-5)
