"""Ray for the executor tests: a private temporary folder and home per cluster, startup
timeouts generous enough for a loaded 2-core machine, and a sweep that stops every process
the tests started (and only those: the ones whose command line names the private folder).

Ray writes its auth token under ``~/.ray`` and its sockets under ``RAY_TMPDIR``; both point
into the private folder, whose short path keeps Ray's socket paths under 107 bytes.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
from pathlib import Path

#: environment of the Ray processes: agents and workers that start slowly under load are
#: waited for (defaults 15 s / 60 s) instead of failing the node
SLOW_START = {"RAY_agent_register_timeout_ms": "180000", "RAY_worker_register_timeout_seconds": "300"}


@contextlib.contextmanager
def private_ray_env():
    """A temporary folder (yielded) set as ``RAY_TMPDIR`` and ``HOME`` with :data:`SLOW_START`;
    on exit every process naming the folder is killed and the environment restored."""
    tmp = tempfile.mkdtemp(prefix="tbrt")
    env = {"RAY_TMPDIR": tmp, "HOME": tmp, **SLOW_START}
    saved = {k: os.environ.get(k) for k in (*env, "RAY_AUTH_MODE")}
    os.environ.update(env)
    # a Ray started earlier in this process set RAY_AUTH_MODE=token, with which `ray start`
    # refuses to create the new cluster's token (in the new home): let each cluster make its own
    os.environ.pop("RAY_AUTH_MODE", None)
    try:
        yield tmp
    finally:
        stop_processes_under(tmp)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(tmp, ignore_errors=True)


def stop_processes_under(folder: str) -> list[int]:
    """SIGKILL the processes whose command line names ``folder`` (the Ray processes we started);
    returns their PIDs."""
    killed = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit() and int(p.name) != os.getpid():
            try:
                if folder.encode() in (p / "cmdline").read_bytes():
                    os.kill(int(p.name), signal.SIGKILL)
                    killed.append(int(p.name))
            except OSError:
                pass
    return killed


def init_local(tmp: str, num_cpus: int):
    """A local Ray instance in ``tmp`` (:func:`~torch_brdf.parallel.tiles.connect_ray`,
    which retries a start that timed out); returns the ray module."""
    from torch_brdf.parallel.tiles import connect_ray

    return connect_ray(None, num_cpus=num_cpus, _temp_dir=tmp)
