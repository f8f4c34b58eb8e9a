"""MERL files: the .binary format (bit-exact round trips, clear errors), the index
conventions (floor and the phi_d fold pinned at bin edges), the downsampled npz layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.conftest import shared_file
from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.io.merl import (
    MERL_FILE_BYTES,
    MERL_RES,
    MERL_SCALE,
    load_merl_table,
    load_nbrdf_weights,
    merl_coordinates,
    merl_flat_index,
    merl_fold_phi_d,
    merl_index_to_angles,
    merl_indices,
    merl_phi_d_index,
    merl_theta_d_index,
    merl_theta_h_index,
    read_merl_binary,
    write_merl_binary,
    write_merl_table,
)

F64 = torch.float64
SCALE = torch.tensor(MERL_SCALE, dtype=F64).view(3, 1, 1, 1)


def t64(*v) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def below(x: float) -> float:
    return float(np.nextafter(x, -np.inf))


# -- index conventions ------------------------------------------------------------------------
def merl_reference(theta_h: float, theta_d: float, phi_d: float) -> tuple[int, int, int]:
    """BRDFRead.cpp's theta_half_index / theta_diff_index / phi_diff_index, statement by
    statement, in scalar float64 (each operation correctly rounded on every CPU)."""
    res_h, res_d, res_p = 90, 90, 360  # BRDF_SAMPLING_RES_THETA_H, _THETA_D, _PHI_D
    if theta_h <= 0.0:
        i_h = 0
    else:
        theta_half_deg = (theta_h / (math.pi / 2.0)) * res_h
        i_h = min(max(int(math.sqrt(theta_half_deg * res_h)), 0), res_h - 1)
    i_d = min(max(int(theta_d / (math.pi * 0.5) * res_d), 0), res_d - 1)
    if phi_d < 0.0:
        phi_d += math.pi
    i_p = min(max(int(phi_d / math.pi * res_p / 2), 0), res_p // 2 - 1)
    return i_h, i_d, i_p


def ulp_neighbours(x: float, k: int = 3) -> list[float]:
    out = [x]
    lo = hi = x
    for _ in range(k):
        lo, hi = below(lo), float(np.nextafter(hi, np.inf))
        out += [lo, hi]
    return out


def test_indices_are_merls_lookup_within_ulps_of_every_edge():
    # The lower edges and +-3 ulps around them are where the last ulp of a square root or a
    # division decides the bin; the index functions must agree with MERL's scalar lookup there
    # (they compare against exact edge tables, so this holds on every CPU).
    for axis, n, edge in (
        (0, 90, lambda i: (i / 90) ** 2 * math.pi / 2),
        (1, 90, lambda i: i * (math.pi / 2) / 90),
        (2, 180, lambda i: i * math.pi / 180),
    ):
        xs = [x for i in range(n + 1) for x in ulp_neighbours(edge(i))]
        xs += [-x for x in xs if axis == 2]  # the negative half of phi_d folds back
        fn = (merl_theta_h_index, merl_theta_d_index, merl_phi_d_index)[axis]
        want = [merl_reference(x, x, x)[axis] for x in xs]
        assert fn(torch.tensor(xs, dtype=F64)).tolist() == want


def test_indices_are_merls_lookup_on_random_angles():
    g = np.random.default_rng(13)
    th, td = g.uniform(-0.1, 1.7, 4000), g.uniform(-0.1, 1.7, 4000)
    pd = g.uniform(-math.pi, math.pi, 4000)
    got = merl_indices(*(torch.from_numpy(a) for a in (th, td, pd)))
    want = np.array([merl_reference(*v) for v in zip(th.tolist(), td.tolist(), pd.tolist(), strict=True)])
    for axis in range(3):
        assert got[axis].tolist() == want[:, axis].tolist()


def test_floor_puts_exact_edges_in_the_upper_bin():
    # Edges exact in binary floating point: pi/8 / (pi/2) * 90 * 90 = 2025 and sqrt = 45 exactly;
    # pi/4 -> theta_d 45; pi/2 -> phi_d 90.
    assert merl_theta_h_index(t64(math.pi / 8)).item() == 45
    assert merl_theta_d_index(t64(math.pi / 4)).item() == 45
    assert merl_theta_d_index(t64(below(math.pi / 4))).item() == 44
    assert merl_phi_d_index(t64(math.pi / 2)).item() == 90
    assert merl_phi_d_index(t64(below(math.pi / 2))).item() == 89
    # One ulp below pi/8, MERL's own arithmetic (2025 - 2^-42, whose square root rounds to 45)
    # still says 45; sqrt(theta/(pi/2)) * 90 in float64 would say 44. MERL's lookup is the
    # reference, and the answer does not depend on the CPU's vectorised square root.
    assert merl_reference(below(math.pi / 8), 0.0, 0.0)[0] == 45
    assert merl_theta_h_index(t64(below(math.pi / 8))).item() == 45
    assert merl_indices(t64(0.0), t64(0.0), t64(0.0)) == (0, 0, 0)


def test_clamping_at_both_ends():
    assert merl_theta_h_index(t64(-0.1, 0.0, math.pi / 2, 2.0)).tolist() == [0, 0, 89, 89]
    assert merl_theta_d_index(t64(0.0, below(math.pi / 2), math.pi / 2)).tolist() == [0, 89, 89]
    assert merl_phi_d_index(t64(0.0, below(math.pi), math.pi)).tolist() == [0, 179, 179]


def test_phi_d_fold_adds_pi_to_negative_angles():
    eps = 1e-9
    phi = t64(-eps, -0.0, -math.pi / 2, -math.pi + 1e-6, math.pi - eps, math.pi, -(math.pi / 2 + 1e-6))
    assert merl_phi_d_index(phi).tolist() == [179, 0, 90, 0, 179, 179, 89]
    folded = merl_fold_phi_d(phi)
    assert bool((folded >= 0).all()) and bool((folded <= math.pi).all())
    # The smallest negative angle folds onto pi itself and is clamped into the last bin.
    assert merl_phi_d_index(t64(-5e-324)).item() == 179


def test_bin_centres_address_their_bins_in_both_dtypes():
    i_h, i_d, i_p = torch.arange(90), torch.arange(90), torch.arange(180)
    for dtype in (torch.float32, torch.float64):
        th, td, pd = merl_index_to_angles(i_h, i_d, i_p, at="centre", dtype=dtype)
        assert torch.equal(merl_theta_h_index(th), i_h)
        assert torch.equal(merl_theta_d_index(td), i_d)
        assert torch.equal(merl_phi_d_index(pd), i_p)
        assert torch.equal(merl_phi_d_index(pd - math.pi), i_p)  # the negative half folds back


def test_lower_edges_are_not_safe_lookup_points():
    # MERL's index -> angle map computed in float64 rounds some edges down a bin:
    # documented in torch_brdf.io.merl; use centres to address bins.
    _, td, _ = merl_index_to_angles(torch.arange(90), torch.arange(90), torch.arange(180), at="lower")
    assert merl_theta_d_index(td[19]).item() == 18
    th, td, pd = merl_index_to_angles(torch.arange(90), torch.arange(90), torch.arange(180), at="lower")
    nudge = 1 + 1e-12
    assert torch.equal(merl_theta_h_index(th * nudge), torch.arange(90))
    assert torch.equal(merl_theta_d_index(td * nudge), torch.arange(90))
    assert torch.equal(merl_phi_d_index(pd * nudge), torch.arange(180))


def test_lower_edge_formulas_match_the_readme():
    i = torch.tensor([0, 1, 45, 89], dtype=F64)
    th, td, pd = merl_index_to_angles(i, i, i)
    assert torch.allclose(th, (i / 90.0) ** 2 * math.pi / 2)
    assert torch.allclose(td, i * (math.pi / 2) / 90)
    assert torch.allclose(pd, i * math.pi / 180)
    with pytest.raises(ValueRangeError):
        merl_index_to_angles(i, i, i, at="middle")


def test_coordinates_floor_to_the_indices(gen):
    th = torch.rand(1000, generator=gen, dtype=F64) * math.pi / 2
    td = torch.rand(1000, generator=gen, dtype=F64) * math.pi / 2
    pd = (torch.rand(1000, generator=gen, dtype=F64) * 2 - 1) * math.pi
    u = merl_coordinates(th, td, pd)
    for ui, ii, res in zip(u, merl_indices(th, td, pd), MERL_RES, strict=True):
        assert torch.equal(ui.floor().clamp(0, res - 1).long(), ii)


def test_flat_index_is_c_order():
    a = torch.arange(90 * 90 * 180).reshape(MERL_RES)
    i_h, i_d, i_p = torch.tensor([0, 3, 89]), torch.tensor([0, 7, 89]), torch.tensor([0, 11, 179])
    assert torch.equal(a.reshape(-1)[merl_flat_index(i_h, i_d, i_p)], a[i_h, i_d, i_p])


# -- the .binary file ----------------------------------------------------------------------------
def _header(dims=MERL_RES) -> bytes:
    return np.asarray(dims, dtype="<i4").tobytes()


def _sparse_file(path, header: bytes, size: int):
    """A file with ``header`` and zeros up to ``size`` bytes (sparse: instant)."""
    with open(path, "wb") as f:
        f.write(header)
        f.truncate(size)
    return path


def test_missing_short_wrong_size_and_wrong_header_raise(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        read_merl_binary(tmp_path / "nope.binary")
    (tmp_path / "short.binary").write_bytes(b"\x5a\x00\x00")
    with pytest.raises(FileFormatError, match=r"truncated.*header"):
        read_merl_binary(tmp_path / "short.binary")
    _sparse_file(tmp_path / "trunc.binary", _header(), 12 + 8 * 1000)
    with pytest.raises(FileFormatError, match="truncated: 8,012 bytes, expected 34,992,012"):
        read_merl_binary(tmp_path / "trunc.binary")
    _sparse_file(tmp_path / "long.binary", _header(), MERL_FILE_BYTES + 8)
    with pytest.raises(FileFormatError, match="trailing bytes"):
        read_merl_binary(tmp_path / "long.binary")
    _sparse_file(tmp_path / "dims.binary", _header((90, 90, 360)), MERL_FILE_BYTES)
    with pytest.raises(FileFormatError, match=r"header dims \(90, 90, 360\), expected \(90, 90, 180\)"):
        read_merl_binary(tmp_path / "dims.binary")
    _sparse_file(tmp_path / "bigendian.binary", np.asarray(MERL_RES, dtype=">i4").tobytes(), MERL_FILE_BYTES)
    with pytest.raises(FileFormatError, match="header dims"):
        read_merl_binary(tmp_path / "bigendian.binary")


def test_non_finite_values_raise(tmp_path):
    path = _sparse_file(tmp_path / "nan.binary", _header(), MERL_FILE_BYTES)
    with open(path, "r+b") as f:
        f.seek(12 + 8 * 12345)
        f.write(np.array([np.nan], dtype="<f8").tobytes())
    with pytest.raises(FileFormatError, match="1 non-finite"):
        read_merl_binary(path)


def test_sparse_zero_file_reads_as_zeros(tmp_path):
    path = _sparse_file(tmp_path / "zeros.binary", _header(), MERL_FILE_BYTES)
    t = read_merl_binary(path)
    assert t.shape == (3, 90, 90, 180) and t.dtype == F64 and not bool(t.any())


def test_write_checks_input_and_leaves_nothing_behind(tmp_path):
    with pytest.raises(ShapeError, match=r"\(3, 90, 90, 180\)"):
        write_merl_binary(tmp_path / "a.binary", torch.zeros(3, 90, 90, 90))
    bad = torch.zeros(3, 90, 90, 180, dtype=F64)
    bad[1, 2, 3, 4] = float("inf")
    with pytest.raises(ValueRangeError, match="non-finite"):
        write_merl_binary(tmp_path / "a.binary", bad)
    with pytest.raises(FileNotFoundError):
        write_merl_binary(tmp_path / "no" / "dir" / "a.binary", torch.zeros(3, 90, 90, 180))
    assert list(tmp_path.iterdir()) == []


def test_nbrdf_binary_round_trip_is_bit_exact(tmp_path):
    """One full-size (35 MB) table tabulated from an NBRDF: raw numbers bit-exact, scaled
    values bit-exact after one pass through the format, byte layout as documented."""
    from torch_brdf.brdf.measured import NBRDF, tabulate_nbrdf

    weights = shared_file("merl", "nbrdf_merl100_weights.npz")
    values = tabulate_nbrdf(NBRDF("gold-metallic-paint", weights))  # (3, 90, 90, 180) float64, -1 = masked
    path = write_merl_binary(tmp_path / "gold-metallic-paint.binary", values)
    assert path.stat().st_size == MERL_FILE_BYTES == 34_992_012

    raw = read_merl_binary(path, scaled=False)
    assert torch.equal(raw, values / SCALE)  # the stored numbers are exactly value / scale

    back = read_merl_binary(path)
    assert back.dtype == F64 and back.shape == (3, 90, 90, 180)
    assert torch.equal(back, raw * SCALE)  # reading applies the scale exactly like MERL's reader
    exact = back == values
    assert exact[0].all()  # float32-derived values times 1/1500 always come back exactly
    assert exact.double().mean() > 0.85  # the rest is within one ulp (not representable at all)
    assert torch.allclose(back, values, rtol=2.3e-16, atol=0)
    assert torch.equal(back < 0, values < 0) and bool((back[values < 0] == -1).all())

    # Anything that came out of a MERL file goes back in and out bit-exactly.
    path2 = write_merl_binary(tmp_path / "again.binary", back)
    assert torch.equal(read_merl_binary(path2), back)

    # Byte layout: header, then R, G, B blocks in C order [theta_h][theta_d][phi_d].
    blob = path.read_bytes()
    assert np.frombuffer(blob[:12], "<i4").tolist() == [90, 90, 180]
    for c, ih, id_, ip in [(0, 0, 0, 0), (1, 10, 20, 30), (2, 89, 89, 179)]:
        flat = c * 90 * 90 * 180 + int(merl_flat_index(torch.tensor(ih), torch.tensor(id_), torch.tensor(ip)))
        stored = np.frombuffer(blob[12 + 8 * flat : 20 + 8 * flat], "<f8")[0]
        assert stored == raw[c, ih, id_, ip].item()


def test_raw_round_trip_is_bit_exact_for_any_bits(tmp_path):
    # Random bit patterns cover every exponent (denormals, -0, huge); NaN/Inf cannot be written.
    g = torch.Generator().manual_seed(3)
    bits = torch.randint(-(2**63), 2**63 - 1, (3, *MERL_RES), generator=g, dtype=torch.int64)
    raw = bits.view(F64).clone()
    raw[~torch.isfinite(raw)] = -0.0
    raw.view(-1)[:4] = torch.tensor([5e-324, -5e-324, 1.7976931348623157e308, -1.0], dtype=F64)
    path = write_merl_binary(tmp_path / "raw.binary", raw, scaled=False)
    assert torch.equal(read_merl_binary(path, scaled=False).view(torch.int64), raw.view(torch.int64))


# -- the downsampled npz layout --------------------------------------------------------------------
def _small_table_arrays() -> dict[str, np.ndarray]:
    ih, id_, ip = np.arange(0, 90, 30), np.arange(0, 90, 45), np.arange(0, 180, 60)
    th, td, pd = merl_index_to_angles(ih, id_, ip)
    brdf = np.linspace(0, 3, 2 * 3 * 3 * 2 * 3).reshape(2, 3, 3, 2, 3).astype(np.float16)
    brdf[0, :, 0, 0, 0] = -1
    return {
        "brdf": brdf,
        "names": np.array(["a-material", "b-material"]),
        "theta_h_index": ih.astype(np.int16),
        "theta_d_index": id_.astype(np.int16),
        "phi_d_index": ip.astype(np.int16),
        "theta_h": th.numpy().astype(np.float32),
        "theta_d": td.numpy().astype(np.float32),
        "phi_d": pd.numpy().astype(np.float32),
        "scale": np.asarray(MERL_SCALE),
        "source": np.array("merl-binary"),
    }


def test_small_table_loads(tmp_path):
    arrays = _small_table_arrays()
    np.savez_compressed(tmp_path / "t.npz", **arrays)
    d = load_merl_table(tmp_path / "t.npz")
    assert d.names == ("a-material", "b-material") and len(d) == 2
    assert d.brdf.shape == (2, 3, 3, 2, 3) and d.brdf.dtype == torch.float16
    assert d.theta_d_index.tolist() == [0, 45] and d.theta_d_index.dtype == torch.int64
    assert d.source == "merl-binary" and not d.is_approximation
    assert torch.equal(d.table("b-material"), torch.from_numpy(arrays["brdf"][1]))
    with pytest.raises(ValueRangeError, match="unknown material 'c'"):
        d.index("c")


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a: a.pop("phi_d"), r"missing arrays \['phi_d'\]"),
        (lambda a: a.update(brdf=a["brdf"][:, :2]), "brdf must have shape"),
        (lambda a: a.update(brdf=a["brdf"].astype(np.int32)), "brdf must be floating"),
        (lambda a: a.update(names=np.array([1, 2])), "names must be"),
        (lambda a: a.update(names=np.array(["x", "x"])), "not unique"),
        (lambda a: a.update(theta_d_index=np.array([45, 0], np.int16)), "strictly increasing"),
        (lambda a: a.update(phi_d_index=np.array([0, 60, 180], np.int16)), r"within 0..179"),
        (lambda a: a.update(theta_h=a["theta_h"] + 0.01), "lower-edge angles"),
        (lambda a: a.update(scale=np.ones(3)), "scale must be"),
        (lambda a: a.update(source=np.array(["x", "y"])), "source must be"),
        (lambda a: a["brdf"].__setitem__((1, 0, 0, 0, 0), -0.5), "negative values other than -1"),
        (lambda a: a["brdf"].__setitem__((1, 0, 0, 0, 0), np.inf), "NaN/Inf"),
        (lambda a: a.update(names=np.array(["x", None], dtype=object)), "without pickle"),
    ],
)
def test_bad_tables_raise(tmp_path, change, message):
    arrays = _small_table_arrays()
    change(arrays)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FileFormatError, match=message):
        load_merl_table(tmp_path / "bad.npz")


def test_not_a_table_file_raises(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        load_merl_table(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(FileFormatError, match="not a readable npz"):
        load_merl_table(tmp_path / "junk.npz")


def test_write_merl_table_round_trip(tmp_path):
    ih, id_, ip = [0, 50, 89], [0, 2], [0, 90, 179]
    values = torch.rand(2, 3, 3, 2, 3, generator=torch.Generator().manual_seed(0), dtype=F64) * 100
    values[1, 2, 0, 1, 1] = -3.0  # any negative becomes -1
    path = write_merl_table(tmp_path / "t.npz", values, ["x", "y"], ih, id_, ip, source="nbrdf")
    d = load_merl_table(path)
    assert d.names == ("x", "y") and d.source == "nbrdf" and d.is_approximation
    assert torch.equal(d.brdf, values.clamp_min(-1).where(values >= 0, -1.0).half())
    assert d.phi_d_index.tolist() == ip and torch.allclose(
        d.phi_d.double(), torch.tensor(ip, dtype=F64) * math.pi / 180
    )
    with np.load(path, allow_pickle=False) as z:  # the stored dtypes of the shared layout
        assert {k: z[k].dtype.str for k in ("brdf", "theta_h_index", "theta_h", "scale")} == {
            "brdf": "<f2", "theta_h_index": "<i2", "theta_h": "<f4", "scale": "<f8",
        }  # fmt: skip
    with pytest.raises(ValueRangeError, match="float16 maximum"):
        write_merl_table(tmp_path / "u.npz", values * 1e4, ["x", "y"], ih, id_, ip, source="nbrdf")
    with pytest.raises(ShapeError):
        write_merl_table(tmp_path / "u.npz", values, ["x"], ih, id_, ip, source="nbrdf")
    with pytest.raises(ValueRangeError, match="source"):
        write_merl_table(tmp_path / "u.npz", values, ["x", "y"], ih, id_, ip, source="measured")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.npz"]


def test_shared_sample_table_loads_without_pickle():
    d = load_merl_table(shared_file("merl", "merl_nbrdf_sample_f16.npz"))
    assert d.names == ("blue-acrylic", "gold-metallic-paint")
    assert d.brdf.shape == (2, 3, 90, 45, 45) and d.brdf.dtype == torch.float16
    assert d.theta_h_index.tolist() == list(range(90))
    assert d.theta_d_index.tolist() == list(range(0, 90, 2))
    assert d.phi_d_index.tolist() == list(range(0, 180, 4))
    assert d.source == "nbrdf" and d.is_approximation
    missing = d.brdf[:, 0] == -1
    assert abs(missing.double().mean().item() - 0.233) < 0.001  # the NBRDF table's 23.3 % horizon mask


def test_nbrdf_weights_load_and_validate(tmp_path):
    w = load_nbrdf_weights(shared_file("merl", "nbrdf_merl100_weights.npz"))
    assert len(w.names) == len(set(w.names)) == 100 and "blue-acrylic" in w.names
    assert w.W1.shape == (100, 6, 21) and w.W3.shape == (100, 21, 3) and w.b3.dtype == np.float32
    np.savez(tmp_path / "w.npz", names=np.array(["a"]), W1=np.zeros((1, 6, 4)), b1=np.zeros((1, 4)))
    with pytest.raises(FileFormatError, match="missing arrays"):
        load_nbrdf_weights(tmp_path / "w.npz")
    shapes = {"W1": (1, 6, 4), "b1": (1, 4), "W2": (1, 4, 4), "b2": (1, 4), "W3": (1, 4, 3), "b3": (1, 2)}
    np.savez(tmp_path / "w.npz", names=np.array(["a"]), **{k: np.zeros(s) for k, s in shapes.items()})
    with pytest.raises(FileFormatError, match=r"b3 must be float \(1, 3\)"):
        load_nbrdf_weights(tmp_path / "w.npz")
