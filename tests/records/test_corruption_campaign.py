"""Corruption campaign over every array file reader, with fixed seeds.

Every record type, a checkpoint, a cache tile, a MERL table, NBRDF weights and a MERL binary
file are damaged by random byte flips and truncations (and, for our checksummed files, by
flips whose whole-file digest is then recomputed, so that the zip, inflate and ``.npy``
header layers behind the digest see the damage too). Crafted files ask for huge arrays, are
zip bombs of a few KB, or carry headers of the wrong JSON type. Each load must either give
a value or raise ``FileFormatError``: no other exception (in particular no ``MemoryError``),
and the traced peak memory of the whole campaign stays below :data:`PEAK_BOUND`.
"""

from __future__ import annotations

import hashlib
import io
import json
import tracemalloc
import zipfile

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.records import test_records as contracts
from torch_brdf.errors import FileFormatError
from torch_brdf.io.arrays import FORMAT, load_arrays, read_npz, save_arrays
from torch_brdf.io.merl import MERL_FILE_BYTES, load_merl_table, load_nbrdf_weights, read_merl_binary, write_merl_table
from torch_brdf.records import Checkpoint, TileCache

SEED = 20261201
PEAK_BOUND = 64 << 20  # bytes traced at once during the whole campaign (files here are a few KB)
_DIGEST = b"torch_brdf-sha256:"
_TAIL = 2 + len(_DIGEST) + 64  # comment length field + comment

RECORDS = [
    contracts.TestBasisImage,
    contracts.TestPolynomialTensors,
    contracts.TestBlockVisibility,
    contracts.TestVertexVisibility,
    contracts.TestGPLVMFit,
    contracts.TestFitResult,
]


def _files(tmp_path):
    """name -> (path, loader, sealed) for one intact file of every kind."""
    gen = torch.Generator().manual_seed(SEED)
    out = {}
    for case in RECORDS:
        rec = case().make(gen)
        path = rec.save(tmp_path / f"{type(rec).__name__}.npz")
        out[type(rec).__name__] = (path, type(rec).load, True)
    ck = tmp_path / "render.ckpt.npz"
    Checkpoint(ck, "pathtrace-checkpoint", {"spp": 4}).save({"sum": np.ones((16, 3))}, {"passes_done": 2})
    out["checkpoint"] = (ck, lambda p: Checkpoint(p, "pathtrace-checkpoint", {"spp": 4}).load(), True)
    tiles = TileCache(tmp_path / "tiles", "multibounce-tile", {"spp": 4})
    tiles.save(0, {"emission": np.zeros((4, 3)), "r_weight": np.arange(12.0)}, {"rays": {"closest": 3}})
    (tile,) = (tmp_path / "tiles").glob("*.npz")
    out["tile"] = (tile, lambda p: load_arrays(p, kind="multibounce-tile"), True)
    values = torch.rand(2, 3, 3, 2, 3, generator=gen, dtype=torch.float64)
    table = write_merl_table(tmp_path / "t.npz", values, ["x", "y"], [0, 50, 89], [0, 2], [0, 90, 179], "nbrdf")
    out["merl_table"] = (table, load_merl_table, False)
    rng = np.random.default_rng(SEED)
    w = {"names": np.array(["a", "b"])}
    for k, shape in (("W1", (2, 6, 4)), ("b1", (2, 4)), ("W2", (2, 4, 4)), ("b2", (2, 4)), ("W3", (2, 4, 3))):
        w[k] = rng.standard_normal(shape).astype(np.float32)
    w["b3"] = np.zeros((2, 3), np.float32)
    np.savez(tmp_path / "nbrdf.npz", **w)
    out["nbrdf"] = (tmp_path / "nbrdf.npz", load_nbrdf_weights, False)
    return out


def _seal(raw: bytes) -> bytes:
    """Recompute the whole-file digest of an array file (a crafted or re-sealed damaged file)."""
    body = raw[:-_TAIL] if raw[-_TAIL + 2 : -64] == _DIGEST else raw[:-2]
    comment = _DIGEST + hashlib.sha256(body).hexdigest().encode()
    return body + len(comment).to_bytes(2, "little") + comment


def _outcome(load, path) -> str | None:
    """None when ``load`` returned or raised FileFormatError; else the raw exception's name."""
    try:
        load(path)
    except FileFormatError:
        pass
    except Exception as exc:  # the campaign counts what escapes
        return f"{type(exc).__name__}: {exc}"[:200]
    return None


def _npy(shape, descr="<f8", body=b"", fortran=False, text=None) -> bytes:
    head = text if text is not None else repr({"descr": descr, "fortran_order": fortran, "shape": shape})
    head = head.encode("latin1")
    head += b" " * (-(10 + len(head) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(head).to_bytes(2, "little") + head + body


def _zip(members: dict[str, bytes], method=zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=method) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def _header(obj) -> bytes:
    return _npy((len(json.dumps(obj)),), "|u1", json.dumps(obj).encode())


def _crafted() -> dict[str, bytes]:
    """Files built to make a reader allocate or crash; each is sealed with a valid digest."""
    good = {"format": FORMAT, "kind": "test", "version": 1, "meta": {}, "checksum": "0" * 64}
    files = {
        "huge shape": _zip({"a.npy": _npy((10**12,), body=bytes(16)), "__header__.npy": _header(good)}),
        "huge 2-d shape": _zip({"a.npy": _npy((2**40, 2**40), body=bytes(8))}),
        "shape overflow": _zip({"a.npy": _npy((2**62, 2**62, 2**62), "<c16")}),
        "negative shape": _zip({"a.npy": _npy((-1,), body=bytes(8))}),
        "float shape": _zip({"a.npy": _npy((1.5,), body=bytes(8))}),
        "object dtype": _zip({"a.npy": _npy((1,), "|O", bytes(8))}),
        "structured dtype": _zip({"a.npy": _npy((1,), [("x", "<f8")], bytes(8))}),
        "bad npy header syntax": _zip({"a.npy": _npy((), text="{'descr': '<f8', 'shape': (1,")}),
        "npy header a list": _zip({"a.npy": _npy((), text="[1, 2, 3]")}),
        "npy version 9": _zip({"a.npy": b"\x93NUMPY\x09\x00" + bytes(60)}),
        "header a list": _zip({"__header__.npy": _header([1, 2, 3])}),
        "header deep nesting": _zip({"__header__.npy": _npy((200000,), "|u1", b"[" * 100000 + b"]" * 100000)}),
        "header version text": _zip({"__header__.npy": _header({**good, "version": "one"})}),
        "header kind_version list": _zip({"__header__.npy": _header({**good, "kind_version": [1]})}),
        "header meta list": _zip({"__header__.npy": _header({**good, "meta": [1]})}),
        "header not utf8": _zip({"__header__.npy": _npy((2,), "|u1", b"\xff\xfe")}),
        "header float32": _zip({"__header__.npy": _npy((1,), "<f4", bytes(4))}),
        "not npy member": _zip({"a.txt": b"hello"}),
    }
    # a zip bomb of a few KB: a deflated member of 8 MiB of zeros behind a valid .npy header
    data = _npy((1 << 20,), "<f8")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        z.writestr("a.npy", data + bytes(8 << 20))
    files["zip bomb"] = buf.getvalue()
    assert len(files["zip bomb"]) < 16 << 10
    # a member with the encrypted flag, and one with an unknown compression method
    raw = bytearray(_zip({"a.npy": _npy((1,), body=bytes(8))}))
    enc, meth = bytearray(raw), bytearray(raw)
    cd = raw.rfind(b"PK\x01\x02")
    for off in (6, cd + 8):
        enc[off] |= 0x01
    for off in (8, cd + 10):
        meth[off] = 99
    files["encrypted flag"], files["unknown method"] = bytes(enc), bytes(meth)
    return {k: _seal(v) for k, v in files.items()}


def test_corruption_campaign(tmp_path):
    files = _files(tmp_path)
    rng = np.random.default_rng(SEED)
    bad = tmp_path / "bad"
    bad.mkdir()
    raw_errors: list[str] = []
    cases = 0
    tracemalloc.start()
    try:
        for name, (path, load, sealed) in files.items():
            assert _outcome(load, path) is None  # the intact file loads
            raw = path.read_bytes()
            for i in range(150):
                data = bytearray(raw)
                mode = i % 3
                if mode == 0:  # raw byte flips (1-3 bytes)
                    for pos in rng.integers(0, len(raw), rng.integers(1, 4)):
                        data[pos] ^= int(rng.integers(1, 256))
                elif mode == 1:  # truncation
                    data = data[: int(rng.integers(0, len(raw)))]
                else:  # a flip before the digest, re-sealed when the file has one (reaches the parsers)
                    pos = int(rng.integers(0, len(raw) - (_TAIL if sealed else 0)))
                    data[pos] ^= int(rng.integers(1, 256))
                    data = bytearray(_seal(bytes(data))) if sealed else data
                target = bad / f"{name}{path.suffix}"
                target.write_bytes(bytes(data))
                problem = _outcome(load, target)
                cases += 1
                if problem:
                    raw_errors.append(f"{name} case {i}: {problem}")
        for name, data in _crafted().items():
            target = bad / "crafted.npz"
            target.write_bytes(data)
            for reader in (lambda p: load_arrays(p), lambda p: read_npz(p), load_merl_table, load_nbrdf_weights):
                problem = _outcome(reader, target)
                cases += 1
                if problem:
                    raw_errors.append(f"crafted {name}: {problem}")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    print(f"corruption campaign: {cases} cases, {len(raw_errors)} raw exceptions, traced peak {peak / 2**20:.1f} MiB")
    assert cases >= 1000
    assert raw_errors == []
    assert peak < PEAK_BOUND


def test_crafted_files_are_refused(tmp_path):
    """Every crafted file is refused by the array-file reader (none is silently accepted)."""
    for name, data in _crafted().items():
        (tmp_path / "c.npz").write_bytes(data)
        with pytest.raises(FileFormatError):
            load_arrays(tmp_path / "c.npz")
        assert name  # every crafted case above


def test_declared_size_cap(tmp_path, monkeypatch):
    path = save_arrays(tmp_path / "x.npz", {"a": np.zeros(1 << 18)}, kind="test")  # 2 MiB
    monkeypatch.setenv("TORCH_BRDF_MAX_ARRAY_BYTES", str(1 << 20))
    with pytest.raises(FileFormatError, match="TORCH_BRDF_MAX_ARRAY_BYTES"):
        load_arrays(path)
    monkeypatch.setenv("TORCH_BRDF_MAX_ARRAY_BYTES", str(4 << 20))
    assert load_arrays(path)[0]["a"].shape == (1 << 18,)


def test_compressed_save_never_writes_a_bomb(tmp_path):
    """Zeros compress 1000:1; the writer stores them rather than write a file the reader refuses."""
    path = save_arrays(tmp_path / "z.npz", {"a": np.zeros(1 << 19)}, kind="test", compress=True)
    assert np.array_equal(load_arrays(path)[0]["a"], np.zeros(1 << 19))


def test_merl_binary_damage(tmp_path):
    """Header flips, truncations and NaN of the 35 MB MERL binary file (a few cases: it is large)."""
    from torch_brdf.io.merl import write_merl_binary

    table = torch.rand(3, 90, 90, 180, generator=torch.Generator().manual_seed(SEED), dtype=torch.float64)
    path = write_merl_binary(tmp_path / "m.binary", table, scaled=False)
    raw = path.read_bytes()
    assert len(raw) == MERL_FILE_BYTES
    bad = tmp_path / "bad.binary"
    rng = np.random.default_rng(SEED)
    cases = [raw[: int(n)] for n in rng.integers(0, len(raw), 4)] + [raw + b"\0"]
    for pos in range(12):  # every header byte
        data = bytearray(raw[:64])
        data[pos] ^= 0x40
        cases.append(bytes(data) + raw[64:])
    cases.append(raw[:12] + np.full(1, np.nan).tobytes() + raw[20:])
    for data in cases:
        bad.write_bytes(data)
        with pytest.raises(FileFormatError):
            read_merl_binary(bad)


@pytest.mark.parametrize(
    ("case", "key", "value"),
    [
        (contracts.TestBlockVisibility, "block_count", 10**9),  # (P, NB) tables of 30 GiB
        (contracts.TestBlockVisibility, "block_count", 2**40),
        (contracts.TestVertexVisibility, "resolution", 2**20),  # 768 GiB
        (contracts.TestPolynomialTensors, "height", 10**9),  # emission of another frame
    ],
)
def test_sizes_from_metadata_are_bounded(tmp_path, case, key, value):
    """Metadata that would size an allocation is checked against the arrays before allocating."""
    rec = case().make(torch.Generator().manual_seed(SEED))
    arrays, meta = rec.to_arrays()
    path = save_arrays(tmp_path / "r.npz", arrays, kind=rec.kind, meta={**meta, key: value}, kind_version=rec.version)
    tracemalloc.start()
    try:
        with pytest.raises(FileFormatError):
            type(rec).load(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < PEAK_BOUND


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=4),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=6,
)


@settings(max_examples=150, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_record_fields_mutated_by_hypothesis(tmp_path_factory, data):
    """Valid files (correct checksums) whose metadata values or arrays are replaced: each
    record type gives a record or FileFormatError, never another exception."""
    case = data.draw(st.sampled_from(RECORDS), label="record")
    rec = case().make(torch.Generator().manual_seed(SEED))
    arrays, meta = rec.to_arrays()
    if data.draw(st.booleans(), label="mutate meta"):
        key = data.draw(st.sampled_from(sorted(meta)), label="key")
        meta[key] = data.draw(_JSON, label="value")
    else:
        name = data.draw(st.sampled_from(sorted(arrays)), label="array")
        a = arrays[name]
        how = data.draw(st.sampled_from(["nan", "dtype", "shape", "drop", "extra", "huge"]), label="how")
        if how == "nan" and a.dtype.kind == "f" and a.size:
            a = a.copy()
            a.reshape(-1)[data.draw(st.integers(0, a.size - 1))] = np.nan
        elif how == "dtype":
            a = a.astype(data.draw(st.sampled_from([np.float16, np.int8, np.uint64, np.bool_, np.complex64])))
        elif how == "shape":
            a = a.reshape(-1)[: data.draw(st.integers(0, a.size))]
        elif how == "drop":
            a = None
        elif how == "extra":
            arrays["unexpected"] = np.zeros(2)
        else:
            with np.errstate(over="ignore"):
                a = np.full(a.shape, np.iinfo(np.int64).max if a.dtype.kind in "iu" else 1e300).astype(a.dtype)
        if a is None:
            del arrays[name]
        else:
            arrays[name] = a
    path = tmp_path_factory.mktemp("h") / "r.npz"
    save_arrays(path, arrays, kind=rec.kind, meta=meta, kind_version=rec.version)
    problem = _outcome(type(rec).load, path)
    assert problem is None, problem
