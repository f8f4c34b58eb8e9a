"""trainers/fit_gplvm.py on a small grid (loaded from its file)."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest

from tests.conftest import shared_file
from torch_brdf.manifold import GPLVM, GPLVMFit, read_split

REPO = Path(__file__).resolve().parents[2]


def _load(rel: str, name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / rel)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_trainer_fits_the_training_split_and_saves(tmp_path, monkeypatch, capsys):
    shared_file("merl", "nbrdf_merl100_weights.npz")
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path / "cache"))
    trainer = _load("trainers/fit_gplvm.py", "fit_gplvm")
    out = tmp_path / "fit.npz"
    split = REPO / "datasets" / "merl_split.txt"
    argv = ["--q", "2", "--out", str(out), "--grid", "15,15,30", "--split", str(split), "--max-iter", "20"]
    summary = trainer.main(argv)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == summary
    fit = GPLVMFit.load(out)
    train, _ = read_split(split)
    assert fit.names == tuple(train) and fit.q == 2 and fit.iterations >= 1
    assert bool((fit.loglik[1:] >= fit.loglik[:-1]).all())
    # a second run reuses the cached observation matrix (no error, same data, same result)
    again = trainer.main(argv)
    assert again["loglik"] == summary["loglik"]
    b = GPLVM(fit).weights(fit.latents[3])
    assert abs(float(b[3]) - 1.0) < 1e-6


@pytest.mark.reference
def test_gpy_peer_optimises_the_same_objective():
    """The manifold benchmark's GPy driver: GPy's GPLVM objective (noise mu - 1e-8, its +1e-8 added
    back) equals Eq. 6 at the start, and its latents are scored with our log-likelihood."""
    pytest.importorskip("GPy")
    from tests.manifold.common import small_family
    from torch_brdf.report.benchmarks import manifold as bench

    obs, _ = small_family(12)
    res = bench.gpy_peer(obs, 2, 1e-6, 20, seconds_cap=60.0)
    assert res["gpy_objective_gap"] < 1e-9
    assert res["ours_iterations"] >= 1 and math.isfinite(res["gpy_loglik"])
    if res["gpy_s_to_our_loglik"] is not None:
        assert res["gpy_loglik"] >= res["ours_loglik"] - 1e-8 * abs(res["ours_loglik"])
