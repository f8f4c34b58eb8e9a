r"""The one place that decides torch_brdf's parallelism: processes, intra-op threads, BLAS threads.

- :func:`usable_cores`: the CPUs this process may run on (``os.sched_getaffinity``) capped by
  the cgroup v2 (``cpu.max``) or v1 (``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``) CPU quota.
- :func:`worker_count`: processes that trace rays (the caller plus forked children); argument,
  else ``TORCH_BRDF_WORKERS``, else the usable cores (at most :data:`MAX_DEFAULT_WORKERS`).
- :func:`intra_op_threads`: torch threads of the calling process; argument, else
  ``TORCH_BRDF_THREADS``, else torch's own count capped at the usable cores (set when torch loads).
- :func:`tile_processes`: processes that compute tiles at once: argument, else
  ``TORCH_BRDF_WORKERS``, else the usable cores unless the machine is busy (then 1).
- :func:`available_memory`: bytes the system can still give (``MemAvailable``), e.g. to bound
  how many tiles run at once.
- :func:`configure_worker`: what every worker process runs first: one torch thread and one
  BLAS thread (a worker is one of several processes that share the cores).
- :func:`forking` / :func:`worker_setup`: how the trace pool and the tile executor start
  their forked workers (BLAS found before the fork; workers leave Ctrl-C to the parent).
- :func:`limit_threads` / :func:`single_thread`: torch *and* numpy/scipy BLAS threads inside a
  block (measured: OpenBLAS inside a torch loop is 5-6x slower per call when both
  run their own threads on 2 cores).
- :func:`tuned`: the renderer's freeze and frame paths run with the thread count that was
  fastest for their (op, size class): each candidate is timed on real calls (no extra work),
  the fastest is kept in memory, and a call much slower than measured (another program took a
  core) starts a new measurement. ``TORCH_BRDF_THREADS``, :func:`set_threads` or the
  ``threads`` argument fix the count instead.

Busy cores: GNU OpenMP (torch's CPU backend, ``libgomp``) lets idle worker threads spin for
up to ~300k pause loops after each parallel region unless ``OMP_WAIT_POLICY=PASSIVE``; that
spinning takes a core from any other program (and from our own forked workers). libgomp reads
the variable once, when torch loads it, so this module sets it (unless the user did) before
importing torch; ``import torch_brdf`` before ``import torch`` to get it, or export it.
:func:`omp_wait_policy` says what the loaded runtime got.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import multiprocessing
import operator
import os
import signal
import sys
import threading
import time
import warnings
from contextlib import contextmanager
from pathlib import Path

_TORCH_FIRST = "torch" in sys.modules
if not _TORCH_FIRST:  # libgomp reads it when torch loads it: only effective before that
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
_WAIT_POLICY_AT_LOAD = os.environ.get("OMP_WAIT_POLICY")

from ..errors import ValueRangeError  # noqa: E402  (torch is imported where it is used: see _AfterTorch)

#: environment variable: torch intra-op threads of the calling process (a positive integer).
ENV_THREADS = "TORCH_BRDF_THREADS"
#: environment variable: processes that trace rays, the caller included (a positive integer).
ENV_WORKERS = "TORCH_BRDF_WORKERS"
#: default cap on tracing processes: a round of the trace pool has 32 chunks to share.
MAX_DEFAULT_WORKERS = 8

_CGROUP_ROOT = "/sys/fs/cgroup"
_PROC_CGROUP = "/proc/self/cgroup"


# -- cores --------------------------------------------------------------------------------------
def _affinity_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _quota(quota: str | None, period: str | None) -> float | None:
    """CPUs allowed by a (quota, period) pair; None when unlimited or unreadable."""
    if quota is None or period is None or quota in ("max", "-1"):
        return None
    try:
        q, p = int(quota), int(period)
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def cgroup_cpu_limit(root: str | os.PathLike = _CGROUP_ROOT, proc_cgroup: str | os.PathLike = _PROC_CGROUP):
    """The CPU quota of this process's cgroup in CPUs (e.g. 1.5), or None when there is none.

    Reads cgroup v2 ``cpu.max`` ("max 100000" or "150000 100000") along the process's path
    and its parents, else cgroup v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (quota -1 =
    unlimited); the tightest limit on the path counts.

    Args:
        root: the cgroup mount (tests pass a temporary folder).
        proc_cgroup: the process's cgroup membership file (``/proc/self/cgroup``).
    """
    root = Path(root)
    lines = (_read(Path(proc_cgroup)) or "").splitlines()
    limits = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        rel = rel.lstrip("/")
        if controllers == "":  # cgroup v2 unified hierarchy
            hybrid = root / "unified"  # v2 mounted beside the v1 controllers (hybrid)
            bases = [hybrid if hybrid.is_dir() else root]
            pairs = lambda d: (_read(d / "cpu.max") or "").split()  # noqa: E731
        elif "cpu" in controllers.split(","):  # cgroup v1 cpu controller
            bases = [root / controllers, root / "cpu,cpuacct", root / "cpu"]
            pairs = lambda d: [_read(d / "cpu.cfs_quota_us"), _read(d / "cpu.cfs_period_us")]  # noqa: E731
        else:
            continue
        for base in bases:
            if not base.is_dir():
                continue
            d = base / rel
            while True:
                qp = pairs(d)
                if len(qp) == 2:
                    limit = _quota(*qp)
                    if limit is not None:
                        limits.append(limit)
                if d == base or base not in d.parents:
                    break
                d = d.parent
            break
    return min(limits) if limits else None


def usable_cores(root: str | os.PathLike = _CGROUP_ROOT, proc_cgroup: str | os.PathLike = _PROC_CGROUP) -> int:
    """CPUs this process can use: its affinity mask, capped by the cgroup CPU quota (rounded
    up: a quota of 1.5 CPUs keeps two threads busy part of the time); at least 1."""
    cores = _affinity_count()
    limit = cgroup_cpu_limit(root, proc_cgroup)
    if limit is not None:
        cores = min(cores, math.ceil(limit - 1e-9))
    return max(1, cores)


# -- counts ---------------------------------------------------------------------------------------
def _positive(value, what: str) -> int:
    """``value`` (an int, or a string of one) as a positive int, else :class:`ValueRangeError`."""
    try:
        n = int(value.strip()) if isinstance(value, str) else operator.index(value)
    except (TypeError, ValueError):
        n = 0
    if isinstance(value, bool) or n < 1:
        raise ValueRangeError(f"{what} must be a positive integer; got {value!r}")
    return n


def _from_env(name: str) -> int | None:
    raw = os.environ.get(name)
    if raw is None or raw.strip() == "" or raw.strip().lower() == "auto":
        return None
    return _positive(raw, f"environment variable {name}")


def worker_count(workers: int | None = None) -> int:
    """Processes that trace a large batch of rays, the caller included.

    Args:
        workers: explicit count (wins); None reads ``TORCH_BRDF_WORKERS`` (a positive
            integer; unset, empty or ``auto`` = default), else the usable cores, at most
            :data:`MAX_DEFAULT_WORKERS`.
    Raises:
        ValueRangeError: a count that is not a positive integer.
    """
    if workers is not None:
        return _positive(workers, "workers")
    env = _from_env(ENV_WORKERS)
    return env if env is not None else min(usable_cores(), MAX_DEFAULT_WORKERS)


#: the machine counts as busy for :func:`tile_processes` above this 1-minute load per usable core.
BUSY_LOAD_PER_CORE = 2.0


def tile_processes(processes: int | None = None, load: float | None = None) -> int:
    """Processes that compute tiles at once (each a single-threaded worker tracing its own rays).

    Args:
        processes: explicit count (wins); None reads ``TORCH_BRDF_WORKERS``, else takes
            :func:`worker_count`'s default, or 1 when the 1-minute load average is above
            :data:`BUSY_LOAD_PER_CORE` per usable core: beside other sessions a second process
            mostly splits the same CPU share (Linux groups a session's processes,
            ``sched_autogroup``) and costs extra CPU time and page faults (measured 0.79x at
            load 13 on 2 cores).
        load: the load average to judge by (default ``os.getloadavg()[0]``; tests pass one).
    """
    if processes is not None or _from_env(ENV_WORKERS) is not None:
        return worker_count(processes)
    cores = usable_cores()
    if load is None:
        try:
            load = os.getloadavg()[0]
        except OSError:  # pragma: no cover - not available
            load = 0.0
    return 1 if load > BUSY_LOAD_PER_CORE * cores else min(cores, MAX_DEFAULT_WORKERS)


def available_memory(meminfo: str | os.PathLike = "/proc/meminfo") -> int | None:
    """Bytes of memory available to new work (Linux ``MemAvailable``: free memory plus what
    the page cache can give back); None when unknown (not Linux, unreadable)."""
    for line in (_read(Path(meminfo)) or "").splitlines():
        if line.startswith("MemAvailable:"):
            parts = line.split()
            if len(parts) >= 2 and parts[1].isdigit():
                return int(parts[1]) * 1024  # kB
    return None


def intra_op_threads(threads: int | None = None) -> int:
    """torch intra-op threads for the calling process: the argument, else ``TORCH_BRDF_THREADS``,
    else torch's own count capped at the usable cores (torch counts the affinity mask but not a
    cgroup quota). Raises :class:`ValueRangeError` on a count that is not a positive integer."""
    import torch

    if threads is not None:
        return _positive(threads, "threads")
    env = _from_env(ENV_THREADS)
    return env if env is not None else max(1, min(torch.get_num_threads(), usable_cores()))


def omp_wait_policy() -> str:
    """``OMP_WAIT_POLICY`` as torch's OpenMP runtime read it when torch loaded: the value (e.g.
    "PASSIVE"), or "default" (libgomp spins a while, then sleeps). When torch was imported
    before torch_brdf the current value is reported with " (if set before torch loaded)"."""
    if _TORCH_FIRST:
        value = os.environ.get("OMP_WAIT_POLICY")
        return "default" if value is None else f"{value.upper()} (if set before torch loaded)"
    return (_WAIT_POLICY_AT_LOAD or "default").upper()


# -- applying them ------------------------------------------------------------------------------------
_BLAS = None


def _blas_controller():
    global _BLAS
    if _BLAS is None:
        from threadpoolctl import ThreadpoolController

        _BLAS = ThreadpoolController()
    return _BLAS


@contextmanager
def limit_threads(n: int, blas: bool = True):
    """``n`` torch intra-op threads (and ``n`` BLAS threads when ``blas``) inside the block;
    both restored on exit."""
    import torch

    n = _positive(n, "threads")
    old = torch.get_num_threads()
    if n != old:
        torch.set_num_threads(n)
    try:
        if blas:
            with _blas_controller().limit(limits=n, user_api="blas"):
                yield
        else:
            yield
    finally:
        if n != old:
            torch.set_num_threads(old)


@contextmanager
def single_thread(enabled: bool = True):
    """One torch thread and one BLAS thread inside the block (restored on exit).

    Small kernels (a 147 x 192 product, a 100 x 100 Cholesky) are up to ~10-40x slower with two
    threads on a shared 2-core machine (thread hand-off under load), and scipy's OpenBLAS inside
    a torch loop 5-6x (thread oversubscription). ``enabled=False`` leaves the settings alone.
    """
    if not enabled:
        yield
        return
    with limit_threads(1):
        yield


def prepare_fork() -> None:
    """Call in the parent before forking workers: finds the BLAS libraries now, so that
    :func:`configure_worker` in a child only calls into them (no ``dlopen`` after fork)."""
    _blas_controller()


def configure_worker(threads: int = 1) -> None:
    """Run first in every worker process: ``threads`` torch threads and BLAS threads (one
    worker per core; a worker's own threads would compete with its siblings). BLAS threads
    are set when the parent called :func:`prepare_fork` (else the environment variables
    below reach only libraries loaded later)."""
    import torch

    os.environ["OMP_NUM_THREADS"] = os.environ["OPENBLAS_NUM_THREADS"] = str(threads)
    os.environ["MKL_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    if _BLAS is not None:
        _BLAS.limit(limits=threads, user_api="blas")


def worker_setup(threads: int = 1) -> None:
    """Run first in every forked worker: Ctrl-C is left to the parent (which stops its workers),
    and :func:`configure_worker` with ``threads`` threads."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    configure_worker(threads)


@contextmanager
def forking():
    """The ``fork`` multiprocessing context, for starting workers inside the block: the parent's
    BLAS libraries are found first (:func:`prepare_fork`), and Python's warning about forking a
    process that runs threads (>= 3.12) is silenced, since every worker starts with
    :func:`worker_setup` and uses one thread of each kind."""
    prepare_fork()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*fork.*", category=DeprecationWarning)
        yield multiprocessing.get_context("fork")


def cap_to_usable() -> None:
    """Set torch's thread count to :func:`intra_op_threads` (never more than the usable cores;
    ``TORCH_BRDF_THREADS`` sets it outright). Called on import."""
    import torch

    n = intra_op_threads()
    if n != torch.get_num_threads():
        torch.set_num_threads(n)


# -- measured thread counts --------------------------------------------------------------------------
#: calls per candidate count while measuring (the fastest of them counts).
TRIALS = 2
#: a chosen count is measured again after this many consecutive calls slower than
#: ``SLOW_FACTOR`` times its measured time (another program now shares the cores).
SLOW_CALLS = 5
SLOW_FACTOR = 1.8

_override: int | None = None


def set_threads(n: int | None) -> None:
    """Fix the thread count of every :func:`tuned` path (None = measure again)."""
    global _override
    _override = None if n is None else _positive(n, "threads")


def candidates(cores: int | None = None) -> list[int]:
    """Thread counts worth trying: 1, powers of two below the core count, and the core count."""
    cores = usable_cores() if cores is None else cores
    out, n = [1], 2
    while n < cores:
        out.append(n)
        n *= 2
    if cores > 1:
        out.append(cores)
    return out


def size_class(size: int) -> int:
    """The bucket of a work size that shares a measurement: ``floor(log2(size))``."""
    return max(0, int(size)).bit_length()


class _Tuning:
    """Measurements of one (op, size class)."""

    def __init__(self, counts: list[int]):
        self.counts = counts
        self.times: dict[int, list[float]] = {n: [] for n in counts}
        self.chosen: int | None = None
        self.slow = 0

    def next_count(self) -> int:
        if self.chosen is not None:
            return self.chosen
        return min(self.counts, key=lambda n: (len(self.times[n]), n))  # round robin, 1 first

    def record(self, n: int, seconds: float) -> None:
        if self.chosen is None:
            self.times[n].append(seconds)
            if all(len(t) >= TRIALS for t in self.times.values()):
                self.chosen = min(self.counts, key=lambda k: (min(self.times[k]), k))
            return
        best = min(self.times[n])
        self.slow = self.slow + 1 if seconds > SLOW_FACTOR * best else 0
        if self.slow >= SLOW_CALLS:  # conditions changed: measure again
            self.times = {k: [] for k in self.counts}
            self.chosen, self.slow = None, 0


_tunings: dict[tuple[str, int], _Tuning] = {}
_lock = threading.Lock()


def tuning_state() -> dict[tuple[str, int], dict]:
    """What :func:`tuned` measured: (op, size class) -> chosen count and per-count seconds."""
    with _lock:
        return {k: {"chosen": t.chosen, "times": {n: list(v) for n, v in t.times.items()}} for k, t in _tunings.items()}


def reset_tuning() -> None:
    """Forget every measurement (the next calls measure again)."""
    with _lock:
        _tunings.clear()


@contextmanager
def tuned(op: str, size: int, threads: int | None = None):
    """Run the block with the torch thread count that is fastest for ``op`` at ``size``.

    The first calls of an (op, size class) try each of :func:`candidates` in turn
    (:data:`TRIALS` each, timed); later calls use the fastest. The count is fixed instead by
    ``threads``, then :func:`set_threads`, then ``TORCH_BRDF_THREADS``. BLAS threads are left
    alone (these paths call none). Yields the count used.

    Args:
        op: the operation's name, e.g. ``"polynomial.frame"``.
        size: its work size (e.g. elements streamed); sizes within a factor 2 share a measurement.
        threads: fixed count (wins over everything).
    """
    import torch

    fixed = threads if threads is not None else _override
    if fixed is None:
        fixed = _from_env(ENV_THREADS)
    if fixed is not None:
        with limit_threads(_positive(fixed, "threads"), blas=False):
            yield torch.get_num_threads()
        return
    key = (op, size_class(size))
    with _lock:
        t = _tunings.get(key)
        if t is None:
            t = _tunings[key] = _Tuning(candidates(intra_op_threads()))
        n = t.next_count()
    with limit_threads(n, blas=False):
        t0 = time.perf_counter()
        yield n
        dt = time.perf_counter() - t0
    with _lock:
        t.record(n, dt)


def tuned_method(op: str, size):
    """Decorate a method so that it runs under :func:`tuned` (the instance's ``threads``
    attribute, when set, fixes the count).

    Args:
        op: the operation's name.
        size: ``size(self, *args, **kwargs) -> int``, the call's work size.
    """

    def decorate(fn):
        @functools.wraps(fn)
        def run(self, *args, **kwargs):
            with tuned(op, size(self, *args, **kwargs), getattr(self, "threads", None)):
                return fn(self, *args, **kwargs)

        return run

    return decorate


def _cap_quietly() -> None:
    import torch

    try:
        cap_to_usable()
    except ValueRangeError as exc:  # reported again where the count is used
        warnings.warn(f"torch_brdf: {exc}; keeping torch's {torch.get_num_threads()} threads", stacklevel=3)


class _AfterTorch:
    """A meta-path finder that caps torch's threads (:func:`cap_to_usable`) right after torch
    loads, so that ``import torch_brdf`` itself does not load torch: ``torch-brdf --help`` and
    ``python trainers/X.py --help`` answer without the seconds torch takes to import."""

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec("torch")
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            del spec.loader.exec_module  # the loader's own method again
            _cap_quietly()

        spec.loader.exec_module = exec_module
        return spec


if "torch" in sys.modules:
    _cap_quietly()
elif not any(isinstance(f, _AfterTorch) for f in sys.meta_path):
    sys.meta_path.insert(0, _AfterTorch())
