"""The one checkpoint / tile cache: keys, resume, corrupt files, removal."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.records.contract import corrupt_payload
from torch_brdf.errors import FileFormatError
from torch_brdf.records import BasisImage, Checkpoint, CorruptCacheWarning, TileCache, remove_cache, settings_key


def test_settings_key_is_order_free_and_sensitive():
    assert settings_key({"a": 1, "b": [1, 2]}) == settings_key({"b": [1, 2], "a": 1})
    assert settings_key({"a": 1}) != settings_key({"a": 2})
    assert settings_key("abc") == "abc" and len(settings_key({})) == 16


def test_tiles_resume_only_under_their_key(tmp_path):
    cache = TileCache(tmp_path / "t", "test-tile", {"spp": 4})
    assert cache.load(0) is None
    cache.save(0, {"x": np.arange(3.0)}, meta={"rays": 7})
    arrays, meta = cache.load(0)
    assert np.array_equal(arrays["x"], np.arange(3.0)) and meta["rays"] == 7
    assert cache.load(1) is None
    assert TileCache(tmp_path / "t", "test-tile", {"spp": 8}).load(0) is None  # other settings
    cache.remove()
    assert not (tmp_path / "t").exists()
    off = TileCache(None, "test-tile", {"spp": 4})  # no folder: caches nothing
    off.save(0, {"x": np.zeros(1)})
    assert off.load(0) is None


def test_tile_removal_keeps_other_files(tmp_path):
    # a checkpoint folder the user shares with other files: only the tiles go
    (tmp_path / "notes.txt").write_text("mine")
    cache = TileCache(tmp_path, "test-tile", "k", prefix="vis")
    cache.save(0, {"x": np.zeros(2)})
    cache.remove()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_corrupt_tile_is_moved_aside_and_recomputed(tmp_path):
    cache = TileCache(tmp_path, "test-tile", "k")
    cache.save(3, {"x": np.arange(100.0)})
    (path,) = tmp_path.glob("tile00003_k.npz")
    corrupt_payload(path, path)
    with pytest.warns(CorruptCacheWarning):
        assert cache.load(3) is None
    assert not path.exists() and (tmp_path / (path.name + ".corrupt")).exists()
    cache.save(3, {"x": np.arange(100.0)})
    assert np.array_equal(cache.load(3)[0]["x"], np.arange(100.0))


def test_checkpoint_corruption_policy(tmp_path):
    path = tmp_path / "c.npz"
    Checkpoint(path, "test-ckpt", "k").save({"x": np.arange(100.0)}, {"done": 2})
    assert Checkpoint(path, "test-ckpt", "k").load()[1]["done"] == 2
    assert Checkpoint(path, "test-ckpt", "other").load() is None
    corrupt_payload(path, path)
    with pytest.raises(FileFormatError):
        Checkpoint(path, "test-ckpt", "k").load()
    with pytest.warns(CorruptCacheWarning):
        assert Checkpoint(path, "test-ckpt", "k", on_corrupt="recompute").load() is None
    with pytest.raises(ValueError):
        Checkpoint(path, "test-ckpt", "k", on_corrupt="ignore")


def test_checkpointed_record_is_a_plain_record_file(tmp_path, gen):
    rec = BasisImage.from_dense(torch.rand(2, 3, 4, 3, generator=gen), meta={"settings": {"n": 1}})
    ck = Checkpoint(tmp_path / "r.npz", BasisImage.kind, {"n": 1}, on_corrupt="recompute")
    assert ck.load_record(BasisImage) is None
    ck.save_record(rec, storage="float64")
    back = ck.load_record(BasisImage, dtype=torch.float64)
    assert torch.equal(back.values, rec.values.double()) and back.meta == rec.meta
    assert torch.equal(BasisImage.load(tmp_path / "r.npz").values, rec.values)  # readable without the cache
    assert Checkpoint(tmp_path / "r.npz", BasisImage.kind, {"n": 2}).load_record(BasisImage) is None
    remove_cache(tmp_path / "r.npz")
    assert not (tmp_path / "r.npz").exists()
    remove_cache(None)
