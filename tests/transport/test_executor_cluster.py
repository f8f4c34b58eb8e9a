"""A two-node Ray cluster on this machine, started the way the cluster guide starts one
(``ray start --head`` plus ``ray start --address``): a precompute joined through the address
equals the local executor bit for bit, and its tiles ran on both nodes.

The test starts both nodes as subprocesses in a private temporary folder and stops them
(and everything they spawned) whatever happens; generous deadlines, no wall-clock asserts.
It skips, saying why, when the ``cluster`` extra (Ray) is not installed.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.transport._ray import private_ray_env
from torch_brdf.records.polynomial import PolynomialTensors
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

#: the run, as keywords here and as source in the driver script
SOURCE = 'settings=PolynomialSettings(series="64,1,1,1", spp=4, tile_rows=2), seed=3, progress=False'
SETTINGS = {"settings": PolynomialSettings(series="64,1,1,1", spp=4, tile_rows=2), "seed": 3, "progress": False}
START_S = 600  # a node start under load 15-20 on 2 cores can take minutes
DRIVER = """
from torch_brdf.scene.builtin import cornell_box_glossy
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial
T = precompute_polynomial(cornell_box_glossy(16), {settings}, executor="ray", address="{address}")
T.save("{out}")
print(T.meta["ray_nodes"])
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(args: list[str], tmp: str) -> subprocess.Popen:
    """``ray start ARGS --block`` in its own session (so the whole group can be stopped)."""
    ray_cli = [sys.executable, "-m", "ray.scripts.scripts", "start", *args, "--num-cpus=1", "--block"]
    ray_cli += ["--disable-usage-stats", f"--temp-dir={tmp}"]
    with open(Path(tmp) / f"start_{len(list(Path(tmp).glob('start_*')))}.log", "wb") as log:
        return subprocess.Popen(ray_cli, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=os.environ)


#: what ``ray start`` prints when its raylet missed Ray's own fixed 30 s to register (a loaded
#: machine); the node is then started again, as a user would
STARTUP_TIMEOUT = "timed out during startup"


def _log(tmp: str, k: int) -> str:
    return (Path(tmp) / f"start_{k}.log").read_text(errors="replace")


def _restart_if_timed_out(procs: list[subprocess.Popen], i: int, args: list[str], tmp: str, deadline: float) -> None:
    """If node ``i`` exited because it timed out during startup, start it again (before the
    deadline); any other exit fails the test with the node's log."""
    if procs[i].poll() is None:
        return
    log = _log(tmp, len(list(Path(tmp).glob("start_*"))) - 1)
    assert STARTUP_TIMEOUT in log and time.monotonic() < deadline, log
    _stop(procs[i])
    procs[i] = _start(args, tmp)


def _stop(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


def _alive_nodes(ray) -> int:
    return sum(bool(n["Alive"]) for n in ray.nodes())


def test_two_node_cluster_equals_local(tmp_path):
    ray = pytest.importorskip("ray", reason="the cluster extra (Ray) is not installed")
    sc = cornell_box_glossy(16)  # 8 tiles of 2 rows
    precompute_polynomial(sc, **SETTINGS).save(tmp_path / "local.npz")  # compared as saved, like T
    local = PolynomialTensors.load(tmp_path / "local.npz")
    if ray.is_initialized():
        ray.shutdown()
    procs: list[subprocess.Popen] = []
    with private_ray_env() as tmp:
        try:
            address = f"127.0.0.1:{_free_port()}"
            head = ["--head", f"--port={address.split(':')[1]}", "--include-dashboard=false"]
            procs.append(_start(head, tmp))
            deadline = time.monotonic() + START_S
            while True:  # the head accepts drivers once its GCS and raylet are up
                _restart_if_timed_out(procs, 0, head, tmp, deadline)
                try:
                    ray.init(address=address, log_to_driver=False)
                    break
                except Exception:
                    ray.shutdown()
                    assert time.monotonic() < deadline, "the head node did not start"
                    time.sleep(2)
            procs.append(_start([f"--address={address}"], tmp))
            while _alive_nodes(ray) < 2:
                _restart_if_timed_out(procs, 1, [f"--address={address}"], tmp, deadline)
                assert time.monotonic() < deadline, "the second node did not join"
                time.sleep(1)
            ray.shutdown()
            # the driver in a process of its own, as `torch-brdf precompute --ray ADDRESS` runs
            # (a process that ran another Ray instance before keeps stale Ray state)
            out = Path(tmp) / "T.npz"
            code = DRIVER.format(settings=SOURCE, address=address, out=str(out))
            run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=START_S)
            assert run.returncode == 0, run.stdout + run.stderr
            T = PolynomialTensors.load(out)
            nodes = int(run.stdout.strip().splitlines()[-1])
        finally:
            ray.shutdown()
            for p in reversed(procs):
                _stop(p)
    xa, xb = local.to_arrays()[0], T.to_arrays()[0]
    assert sorted(xa) == sorted(xb) and all(np.array_equal(xa[k], xb[k]) for k in xa)
    assert T.meta["rays"] == local.meta["rays"]
    assert nodes == 2  # tiles ran on the head and on the joined node
