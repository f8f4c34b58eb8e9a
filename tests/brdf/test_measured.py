"""Measured BRDFs: the MERL table lookup (nearest and trilinear), the NBRDF networks (an
approximation of MERL), their tabulation on the MERL grid and datasets/nbrdf_to_merl.py."""

from __future__ import annotations

import functools
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.brdf.common import BRDFContract
from tests.conftest import shared_file
from torch_brdf.brdf.base import create
from torch_brdf.brdf.measured import NBRDF, MERLTabulated, nbrdf_input, nbrdf_mlp, tabulate_nbrdf
from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.frame import half_diff_to_directions
from torch_brdf.io.merl import (
    MERL_FILE_BYTES,
    load_merl_table,
    load_nbrdf_weights,
    merl_index_to_angles,
    read_merl_binary,
    write_merl_binary,
    write_merl_table,
)

F64 = torch.float64
REPO = Path(__file__).resolve().parents[2]
KEPT = (torch.arange(90), torch.arange(0, 90, 2), torch.arange(0, 180, 4))  # the npz layout's grid


def weights_path() -> Path:
    return shared_file("merl", "nbrdf_merl100_weights.npz")


@pytest.fixture(scope="module")
def gold() -> NBRDF:
    return NBRDF("gold-metallic-paint", weights_path())


@pytest.fixture(scope="module")
def gold_full(gold) -> torch.Tensor:
    """(3, 90, 90, 180) float64 NBRDF tabulation (about 1 s)."""
    return tabulate_nbrdf(gold)


def hemisphere(n: int, seed: int, dtype=F64) -> torch.Tensor:
    """(n, 3) random unit directions with z > 0."""
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=F64)
    v[:, 2] = v[:, 2].abs() + 1e-3
    return (v / v.norm(dim=-1, keepdim=True)).to(dtype)


def random_table(shape, seed: int) -> torch.Tensor:
    return torch.rand(3, *shape, generator=torch.Generator().manual_seed(seed), dtype=F64) * 5 + 0.1


def directions_at(theta_h, theta_d, phi_d, seed: int = 0):
    """Local (wi, wo) for half/difference angles, at a random phi_h (the BRDF is isotropic)."""
    g = torch.Generator().manual_seed(seed)
    phi_h = (torch.rand(theta_h.shape, generator=g, dtype=F64) * 2 - 1) * math.pi
    return half_diff_to_directions(theta_h, phi_h, theta_d, phi_d)


def numpy_rusinkiewicz(wi: np.ndarray, wo: np.ndarray):
    """Independent oracle: (theta_h, theta_d, phi_d) of (N, 3) local directions."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    th, ph = np.arccos(np.clip(h[:, 2], -1, 1)), np.arctan2(h[:, 1], h[:, 0])
    c, s = np.cos(-ph), np.sin(-ph)
    x, y, z = c * wi[:, 0] - s * wi[:, 1], s * wi[:, 0] + c * wi[:, 1], wi[:, 2]
    c, s = np.cos(-th), np.sin(-th)
    d = np.stack([c * x + s * z, y, -s * x + c * z], -1)
    return th, np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])


# -- NBRDF ------------------------------------------------------------------------------------------
def test_nbrdf_matches_the_readme_formula(gold):
    w = load_nbrdf_weights(weights_path())
    k = w.index("gold-metallic-paint")
    wi, wo = hemisphere(500, 1), hemisphere(500, 2)
    th, td, pd = numpy_rusinkiewicz(wi.numpy(), wo.numpy())
    pd = np.where(pd < 0, pd + np.pi, pd)  # MERL's fold
    x = np.stack([np.sin(th), 0 * th, np.cos(th), np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], -1)
    h = np.maximum(x @ w.W1[k].astype(np.float64) + w.b1[k], 0)
    h = np.maximum(h @ w.W2[k].astype(np.float64) + w.b2[k], 0)
    want = np.maximum(np.exp(h @ w.W3[k].astype(np.float64) + w.b3[k]) - 1, 0)
    got = gold.eval(wi, wo)
    assert got.dtype == F64 and got.shape == (500, 3)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-9, atol=1e-12)


def test_nbrdf_dtypes_batches_and_horizon(gold):
    wi, wo = hemisphere(60, 3).reshape(3, 4, 5, 3), hemisphere(60, 4).reshape(3, 4, 5, 3)
    f64 = gold.eval(wi, wo)
    f32 = gold.eval(wi.float(), wo.float())
    assert f64.shape == f32.shape == (3, 4, 5, 3) and f32.dtype == torch.float32
    torch.testing.assert_close(f32.double(), f64, rtol=1e-4, atol=1e-6)
    loop = torch.stack([gold.eval(a, b) for a, b in zip(wi.reshape(-1, 3), wo.reshape(-1, 3), strict=True)])
    torch.testing.assert_close(loop, f64.reshape(-1, 3), rtol=1e-12, atol=0)
    assert gold.eval(wi[0, 0], wo[0, 0, :1]).shape == (5, 3)  # broadcasting
    down = wo.clone()
    down[..., 2] = -down[..., 2]
    assert not gold.eval(wi, down).any() and not gold.eval(down, wi).any()
    assert bool((f64 >= 0).all()) and bool((f64 > 0).any())


def test_nbrdf_fold_makes_it_reciprocal_and_the_raw_network_is_not():
    blue = NBRDF("blue-acrylic", weights_path())
    wi, wo = hemisphere(400, 5), hemisphere(400, 6)
    torch.testing.assert_close(blue.eval(wi, wo), blue.eval(wo, wi), rtol=1e-10, atol=1e-12)
    raw = NBRDF("blue-acrylic", weights_path(), fold_phi_d=False)
    a, b = raw.eval(wi, wo), raw.eval(wo, wi)
    assert ((a - b).abs() / b.abs().clamp_min(1e-3)).max() > 0.01  # the NBRDF fit's +-15 % phi_d asymmetry


def test_nbrdf_names_errors_registry_and_repr(gold):
    names = NBRDF.names(weights_path())
    assert len(names) == 100 and "gold-metallic-paint" in names
    with pytest.raises(ValueRangeError, match=r"unknown NBRDF material 'gold'.*available: \['alum-bronze'"):
        NBRDF("gold", weights_path())
    m = create({"type": "nbrdf", "material": "gold-metallic-paint", "weights": str(weights_path())})
    assert isinstance(m, NBRDF) and m.model_name == "nbrdf"
    assert "APPROXIMATION" in repr(gold) and "gold-metallic-paint" in repr(gold)
    assert "approximation" in (NBRDF.__doc__ or "").lower()
    assert gold.W2.dtype == torch.float32 and set(dict(gold.named_buffers())) == {"W1", "b1", "W2", "b2", "W3", "b3"}
    assert gold.to(F64).W1.dtype == F64


def test_nbrdf_gradients_flow_to_directions(gold):
    wi = hemisphere(8, 7).requires_grad_()
    gold.eval(wi, hemisphere(8, 8)).sum().backward()
    assert torch.isfinite(wi.grad).all() and wi.grad.abs().sum() > 0


def test_nbrdf_mlp_and_input_shapes():
    x = nbrdf_input(torch.zeros(2, 1), torch.full((1, 4), math.pi / 2), torch.zeros(()))
    assert x.shape == (2, 4, 6)
    assert torch.equal(x[0, 0], torch.tensor([0.0, 0.0, 1.0, 1.0, 0.0, x[0, 0, 5].item()]))
    w = [torch.zeros(6, 2), torch.zeros(2), torch.zeros(2, 2), torch.zeros(2), torch.zeros(2, 3), torch.zeros(3)]
    assert torch.equal(nbrdf_mlp(x, *w), torch.zeros(2, 4, 3))  # exp(0) - 1


# -- the sample table and the tabulation --------------------------------------------------------------
def assert_float16_rounding(ours: np.ndarray, ref: np.ndarray) -> None:
    """Same -1 mask; values equal or one float16 step apart (float32 summation order)."""
    assert ours.dtype == ref.dtype == np.float16 and ours.shape == ref.shape
    assert np.array_equal(ours == -1, ref == -1)
    o, r = ours.astype(np.float64), ref.astype(np.float64)
    assert np.all(np.abs(o - r) <= np.spacing(np.abs(ref)).astype(np.float64))
    assert (o == r).mean() > 0.99


def test_tabulation_reproduces_the_shared_sample_to_float16_rounding():
    data = load_merl_table(shared_file("merl", "merl_nbrdf_sample_f16.npz"))
    for k, name in enumerate(data.names):
        t = tabulate_nbrdf(NBRDF(name, weights_path()), data.theta_h_index, data.theta_d_index, data.phi_d_index)
        ours = np.where(t.numpy() < 0, -1, t.numpy()).astype(np.float16)
        assert_float16_rounding(ours, data.brdf[k].numpy())


def test_tabulation_uses_lower_edges_and_the_horizon_mask(gold):
    t = tabulate_nbrdf(gold, [0, 30, 89], [0, 80, 89], [0, 90])
    assert t.shape == (3, 3, 3, 2) and t.dtype == F64
    th, td, pd = merl_index_to_angles(torch.tensor([30]), torch.tensor([80]), torch.tensor([90]))
    torch.testing.assert_close(t[:, 1, 1, 1], gold.eval_angles(th, td, pd)[0], rtol=1e-5, atol=1e-7)
    assert bool((t[:, 2, 2, 0] == -1).all())  # theta_h + theta_d > 90 deg in the plane: below the horizon
    assert bool((t[:, 2, 2, 1] > 0).all())  # ... but still above it at phi_d = 90 deg
    assert bool((t[:, 0, 0] >= 0).all())
    assert bool((t[:, 1, 1, 0] >= 0).all())  # wi.z = +1e-16 at (30, 80, 0) counts as above


# -- MERLTabulated --------------------------------------------------------------------------------------
def test_nearest_lookup_is_the_tabulated_value_at_bin_centres(gold, gold_full):
    brdf = MERLTabulated(gold_full, name="gold", source="nbrdf")
    g = torch.Generator().manual_seed(9)
    i = [torch.randint(0, n, (4000,), generator=g) for n in (90, 90, 180)]
    wi, wo = directions_at(*merl_index_to_angles(*i, at="centre"), seed=1)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    f = brdf.eval(wi, wo)
    table = gold_full[:, i[0], i[1], i[2]].t()
    valid = up & (table[:, 0] >= 0)
    assert valid.sum() > 2000 and (~valid).sum() > 100
    assert torch.equal(f[valid], table[valid])  # exactly the table entry
    assert not f[~valid].any()  # below the horizon, or a missing bin: 0
    # ... which is the NBRDF at the angles used for tabulation (lower edges; float32 network there)
    nb = gold.eval_angles(*merl_index_to_angles(*i, at="lower"))
    torch.testing.assert_close(f[valid], nb[valid], rtol=2e-5, atol=1e-7)


def test_downsampled_shared_sample_lookup_at_coarse_bin_centres(gold):
    data = load_merl_table(shared_file("merl", "merl_nbrdf_sample_f16.npz"))
    brdf = MERLTabulated.from_table(data, "gold-metallic-paint")
    assert brdf.name == "gold-metallic-paint" and brdf.is_approximation and brdf.table.dtype == torch.float32
    g = torch.Generator().manual_seed(10)
    k = [torch.randint(0, len(kept), (3000,), generator=g) for kept in KEPT]
    centre = [kept[kk] + step / 2 for kept, kk, step in zip(KEPT, k, (1, 2, 4), strict=True)]  # index space
    wi, wo = directions_at(*merl_index_to_angles(*centre), seed=2)
    f = brdf.eval(wi, wo)
    table = data.table("gold-metallic-paint")[:, k[0], k[1], k[2]].t().float()
    valid = (wi[:, 2] > 0) & (wo[:, 2] > 0) & (table[:, 0] >= 0)
    assert torch.equal(f[valid].float(), table[valid])
    nb = gold.eval_angles(*merl_index_to_angles(*(kept[kk] for kept, kk in zip(KEPT, k, strict=True))))
    torch.testing.assert_close(f[valid], nb[valid], rtol=1e-3, atol=1e-4)  # float16 rounding


def test_downsampled_nearest_is_index_selection_of_the_full_table():
    full = random_table((90, 90, 180), 11)
    coarse = MERLTabulated(full[:, :, ::2][:, :, :, ::4], theta_d_index=KEPT[1], phi_d_index=KEPT[2])
    fine = MERLTabulated(full)
    g = torch.Generator().manual_seed(12)
    th = torch.rand(2000, generator=g, dtype=F64) * math.pi / 2
    td = torch.rand(2000, generator=g, dtype=F64) * math.pi / 2
    pd = (torch.rand(2000, generator=g, dtype=F64) * 2 - 1) * math.pi
    # every angle maps to the kept bin at or below its full-resolution bin
    from torch_brdf.io.merl import merl_indices

    i_h, i_d, i_p = merl_indices(th, td, pd)
    want = full[:, i_h, i_d - i_d % 2, i_p - i_p % 4].t()
    assert torch.equal(coarse.lookup(th, td, pd), want)
    assert torch.equal(fine.lookup(th, td, pd), full[:, i_h, i_d, i_p].t())


def oracle_trilinear(table: np.ndarray, kept, u) -> np.ndarray:
    """Independent trilinear oracle: per axis a fractional position by np.interp (clamped;
    phi_d with ghost nodes one period away), then the 8-corner blend."""
    pos = []
    for axis, (kk, uu) in enumerate(zip(kept, u, strict=True)):
        kk = np.asarray(kk, dtype=np.float64)
        n = len(kk)
        if axis < 2:
            p = np.interp(uu, kk, np.arange(n))
            k0 = np.minimum(np.floor(p).astype(int), n - 1)
            pos.append((k0, np.minimum(k0 + 1, n - 1), p - k0))
        else:
            xp = np.concatenate([[kk[-1] - 180], kk, [kk[0] + 180]])
            p = np.interp(np.mod(uu, 180), xp, np.arange(-1, n + 1))
            f = np.floor(p)
            pos.append((f.astype(int) % n, (f.astype(int) + 1) % n, p - f))
    out = 0
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                w = (pos[0][2] if a else 1 - pos[0][2]) * (pos[1][2] if b else 1 - pos[1][2])
                w = w * (pos[2][2] if c else 1 - pos[2][2])
                out = out + w * table[:, pos[0][a], pos[1][b], pos[2][c]]
    return out.T


def test_trilinear_matches_an_independent_oracle():
    kept = (torch.tensor([0, 5, 20, 60, 89]), torch.tensor([0, 30, 89]), torch.tensor([10, 70, 100, 170]))
    table = random_table((5, 3, 4), 13)
    brdf = MERLTabulated(
        table, theta_h_index=kept[0], theta_d_index=kept[1], phi_d_index=kept[2], interpolation="trilinear"
    )
    g = torch.Generator().manual_seed(14)
    th = torch.rand(3000, generator=g, dtype=F64) * math.pi / 2
    td = torch.rand(3000, generator=g, dtype=F64) * math.pi / 2
    pd = (torch.rand(3000, generator=g, dtype=F64) * 2 - 1) * math.pi
    u = (
        np.sqrt(th.numpy() / (np.pi / 2)) * 90,
        td.numpy() / (np.pi / 2) * 90,
        np.where(pd < 0, pd + np.pi, pd) / np.pi * 180,
    )
    want = oracle_trilinear(table.numpy(), [k.numpy() for k in kept], u)
    np.testing.assert_allclose(brdf.lookup(th, td, pd).numpy(), want, rtol=1e-12, atol=1e-12)


def test_trilinear_wraps_phi_d_and_agrees_with_nearest_on_lower_edges(gold_full):
    tri = MERLTabulated(gold_full.clamp_min(0), interpolation="trilinear")
    near = MERLTabulated(gold_full.clamp_min(0))
    i = torch.tensor([40]), torch.tensor([30]), torch.tensor([179.5], dtype=F64)
    got = tri.lookup(*merl_index_to_angles(*i))
    torch.testing.assert_close(got[0], (gold_full[:, 40, 30, 179] + gold_full[:, 40, 30, 0]) / 2, rtol=1e-9, atol=0)
    g = torch.Generator().manual_seed(15)
    j = [torch.randint(0, n, (3000,), generator=g) for n in (90, 90, 180)]
    angles = [a * (1 + 1e-13) for a in merl_index_to_angles(*j)]  # nudged onto the safe side of the edge
    torch.testing.assert_close(tri.lookup(*angles), near.lookup(*angles), rtol=1e-9, atol=1e-12)


def test_missing_bins_zero_for_nearest_and_renormalised_for_trilinear():
    table = torch.full((3, 90, 90, 180), 2.0, dtype=F64)
    table[:, 10:20] = -1.0  # theta_h bins 10..19 missing
    th = merl_index_to_angles(torch.tensor([9.5, 12.0, 19.5, 25.0], dtype=F64), [0], [0])[0]
    td, pd = torch.full((4,), 0.3, dtype=F64), torch.full((4,), 1.0, dtype=F64)
    near = MERLTabulated(table).lookup(th, td, pd)[:, 0]
    tri = MERLTabulated(table, interpolation="trilinear").lookup(th, td, pd)[:, 0]
    assert near.tolist() == [2.0, 0.0, 0.0, 2.0]
    assert tri.tolist() == [2.0, 0.0, 2.0, 2.0]  # 9.5 and 19.5 blend a valid bin with a missing one


def test_constructor_paths_errors_and_registry(tmp_path, gold_full):
    path = write_merl_binary(tmp_path / "gold.binary", gold_full)
    m = create("merl", table=str(path))
    assert isinstance(m, MERLTabulated) and m.name == "gold" and m.table.shape == (3, 90, 90, 180)
    assert torch.equal(MERLTabulated.from_binary(path).table, read_merl_binary(path))
    two = random_table((90, 45, 45), 16).expand(2, 3, 90, 45, 45)
    npz = write_merl_table(tmp_path / "t.npz", two, ["a", "b"], *KEPT, source="nbrdf")
    m = MERLTabulated(npz, "b", interpolation="trilinear")
    assert m.name == "b" and m.is_approximation and "APPROXIMATION" in repr(m) and "trilinear" in repr(m)
    with pytest.raises(ValueRangeError, match="holds 2 materials"):
        MERLTabulated(npz)
    with pytest.raises(ValueRangeError, match="unknown material 'c'"):
        MERLTabulated(npz, "c")
    with pytest.raises(ValueRangeError, match="interpolation"):
        MERLTabulated(gold_full, interpolation="cubic")
    with pytest.raises(ShapeError, match=r"\(3, Th, Td, Tp\)"):
        MERLTabulated(torch.zeros(90, 90, 180))
    with pytest.raises(ShapeError, match="theta_d_index"):
        MERLTabulated(torch.zeros(3, 90, 45, 180))
    with pytest.raises(ValueRangeError, match="strictly increasing"):
        MERLTabulated(torch.zeros(3, 90, 2, 180), theta_d_index=[4, 2])
    assert "APPROXIMATION" not in repr(MERLTabulated(gold_full))
    assert MERLTabulated(gold_full).to(torch.float32).table.dtype == torch.float32


# -- the shared BRDF contract (tests/brdf/common.py) ----------------------------------------------------
@functools.cache
def _gold_table(downsampled: bool) -> torch.Tensor:
    return tabulate_nbrdf(NBRDF("gold-metallic-paint", weights_path()), *(KEPT if downsampled else ()))


def _kept() -> dict:
    return {"theta_h_index": KEPT[0], "theta_d_index": KEPT[1], "phi_d_index": KEPT[2]}


class TestNBRDFContract(BRDFContract):
    def make(self, dtype):
        return NBRDF("gold-metallic-paint", weights_path()).to(dtype)


class TestMERLNearestContract(BRDFContract):
    """The full 90 x 90 x 180 table, MERL's own lookup."""

    def make(self, dtype):
        return MERLTabulated(_gold_table(False), source="nbrdf").to(dtype)


class TestMERLTrilinearContract(BRDFContract):
    """The downsampled (90, 45, 45) layout with its horizon mask, trilinear lookup."""

    def make(self, dtype):
        return MERLTabulated(_gold_table(True), interpolation="trilinear", source="nbrdf", **_kept()).to(dtype)


# -- datasets/nbrdf_to_merl.py --------------------------------------------------------------------------
def load_script():
    spec = importlib.util.spec_from_file_location("nbrdf_to_merl", REPO / "datasets" / "nbrdf_to_merl.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run(script, capsys, *argv) -> dict:
    assert script.main([str(a) for a in argv]) == 0
    out = capsys.readouterr().out
    assert "approximation of MERL" in out
    return json.loads(out.strip().splitlines()[-1])


def test_script_npz_reproduces_the_sample_and_resumes(tmp_path, capsys):
    sample = load_merl_table(shared_file("merl", "merl_nbrdf_sample_f16.npz"))
    script = load_script()
    out = tmp_path / "sample.npz"
    args = ("npz", out, "--weights", weights_path(), "--materials", "gold-metallic-paint,blue-acrylic")
    assert run(script, capsys, *args)["written"] == ["blue-acrylic", "gold-metallic-paint"]
    ours = load_merl_table(out)
    assert ours.names == sample.names and ours.source == "nbrdf"
    for k in ("theta_h_index", "theta_d_index", "phi_d_index", "theta_h", "theta_d", "phi_d"):
        assert torch.equal(getattr(ours, k), getattr(sample, k)), k
    assert_float16_rounding(ours.brdf.numpy(), sample.brdf.numpy())
    mtime = out.stat().st_mtime_ns
    assert run(script, capsys, *args)["skipped"] == ["blue-acrylic", "gold-metallic-paint"]
    assert out.stat().st_mtime_ns == mtime
    assert script.main(["npz", str(out), "--weights", str(weights_path()), "--materials", "nope"]) == 1
    assert "unknown NBRDF material 'nope'" in capsys.readouterr().err


def test_script_binary_writes_real_format_files_and_resumes(tmp_path, capsys, gold_full):
    script = load_script()
    args = ("binary", tmp_path, "--weights", weights_path(), "--materials", "gold-metallic-paint")
    assert run(script, capsys, *args)["written"] == ["gold-metallic-paint"]
    path = tmp_path / "gold-metallic-paint.binary"
    assert path.stat().st_size == MERL_FILE_BYTES
    back = read_merl_binary(path)
    scale = torch.tensor([1 / 1500, 1.15 / 1500, 1.66 / 1500], dtype=F64).view(3, 1, 1, 1)
    assert torch.equal(read_merl_binary(path, scaled=False), gold_full / scale)
    torch.testing.assert_close(back, gold_full, rtol=2.3e-16, atol=0)
    assert run(script, capsys, *args)["skipped"] == ["gold-metallic-paint"]
    assert script._binary_ok(path)
    path.write_bytes(path.read_bytes()[:1000])  # a damaged output does not count as done
    assert not script._binary_ok(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gold-metallic-paint.binary"]
