r"""Where the tiles of a precomputation run: in this process (``local``) or on a Ray cluster (``ray``).

A precomputation splits its work into tiles; tile ``k`` is a pure function of (context, k),
where the *context* holds the scene and the settings (the seed included), so a tile gives
the same arrays wherever and however often it runs. :func:`run_tiles` computes the tiles
that are not yet in the :class:`~torch_brdf.records.cache.TileCache`, writes each finished
tile atomically into it on the driver (a restarted driver resumes from them), and returns
every tile's arrays in tile order, so the assembled record does not depend on the executor,
the number of workers, or the order in which tiles finish.

Executors:

- ``local`` (default): with one process (``processes=1``, or a single tile to compute) tiles
  run one after another in this process, with one torch thread (on a shared 2-core machine
  torch's second thread spin-waits and made the 64² precompute 30x slower under load); ray
  casting still uses the scene's forked trace workers. With more (default: one per usable core,
  or 1 on a busy machine, :func:`~torch_brdf.parallel.threads.tile_processes`), tiles run at
  once in that many forked processes, each tracing its own rays with one torch thread (the
  torch stages of a tile are serial, so this is what keeps every core busy); this process
  writes the checkpoint and assembles, in tile order, as for one process.
- ``ray``: one Ray task per tile (``pip install torch_brdf[cluster]``). The context is put
  into the object store once and each worker process fetches it once (it is cached per
  worker under its key), so per task only the tile index travels; the worker also encodes
  the tile's checkpoint file (checksums, zip) and the driver only writes its bytes (atomically,
  as for ``local``), which keeps the driver's serial work small. A task whose worker dies
  is retried by Ray up to ``max_retries`` times; after that :class:`TileError` names the
  tile. Workers trace with one process and one torch thread each (Ray runs one task per CPU).
"""

from __future__ import annotations

import copy
import ctypes
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, ThreadPoolExecutor, wait
from typing import Any, Protocol

import numpy as np
from tqdm.auto import tqdm

from ..errors import TorchBRDFError, ValueRangeError
from .threads import configure_worker, forking, single_thread, tile_processes, worker_setup

__all__ = [
    "EXECUTORS",
    "TileError",
    "TileWork",
    "connect_ray",
    "run_tiles",
    "single_process",
    "tile_tick",
    "wait_tile_processes",
]

EXECUTORS = ("local", "ray")

#: a tile's result: arrays (to cache) and JSON-able metadata.
TileResult = tuple[dict[str, np.ndarray], dict[str, Any]]
TileFn = Callable[[Any, int], TileResult]


class TileCache(Protocol):
    """Where finished tiles are kept: what :func:`run_tiles` asks of
    :class:`torch_brdf.records.cache.TileCache` (``folder`` None: nothing is written)."""

    folder: Any

    def load(self, k: int) -> TileResult | None: ...

    def save(self, k: int, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None: ...

    def encode(self, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> bytes: ...

    def save_encoded(self, k: int, data: bytes) -> None: ...


class Tiles(list):
    """The (arrays, meta) of every tile in tile order; ``write_seconds``: time spent saving tiles (in
    the writer thread, beside the assembly);
    ``nodes``: the Ray node ids that computed tiles in this call (empty for ``local``);
    ``processes``: local processes that computed tiles at once (0 for Ray)."""

    write_seconds: float = 0.0
    processes: int = 0

    def __init__(self, items):
        super().__init__(items)
        self.nodes: set[str] = set()


class TileError(TorchBRDFError, RuntimeError):
    """A tile could not be computed (its worker died more often than the retries allow)."""


# what :func:`tile_tick` calls while a tile runs here or in a forked tile process (None elsewhere)
_TICK: Callable[[int], None] | None = None


def tile_tick(steps: int = 1) -> None:
    """Report that the running tile finished ``steps`` of its ``steps_per_tile`` (e.g. a pass
    group): moves :func:`run_tiles`' bar within a tile. A no-op outside :func:`run_tiles` and on
    Ray (whose bar moves per finished tile)."""
    if _TICK is not None:
        _TICK(steps)


# per-worker-process cache of fetched contexts (key -> context); a worker keeps one.
_CONTEXTS: dict[str, Any] = {}


def connect_ray(address: str | None = None, attempts: int = 3, **init_kwargs):
    """Start or join Ray and return the module.

    ``address``: None or ``"auto"`` uses the running Ray instance of this process if any, else
    starts a local one (``ray.init()``; ``init_kwargs`` go to it, e.g. ``num_cpus``); any other
    value is the address of an existing cluster (``ray.init(address=...)``). Ray gives a new
    node a hard-coded 30 s to come up, which a loaded machine can miss: a start that fails is
    tried again, ``attempts`` times in all.
    """
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the extra
        raise TorchBRDFError("executor='ray' needs Ray: pip install 'torch_brdf[cluster]'") from exc
    kwargs = {"include_dashboard": False, "log_to_driver": False, **init_kwargs}
    if address not in (None, "auto", "local"):
        kwargs["address"] = address
    for attempt in range(max(1, attempts)):
        if ray.is_initialized():
            break
        try:
            ray.init(**kwargs)
        except Exception as exc:
            ray.shutdown()
            if attempt == max(1, attempts) - 1:
                where = kwargs.get("address", "a local instance")
                raise TorchBRDFError(f"Ray did not start or connect ({where}): {exc}") from exc
    return ray


def single_process(scene):
    """A shallow copy of ``scene`` that traces in the calling process only (``workers = 1``):
    what a Ray task or a forked tile process gets, since those already run one per CPU. Shares
    the embree scene (:meth:`~torch_brdf.scene.raytrace.RayTracer.in_process`)."""
    out = copy.copy(scene)
    out.workers = 1
    out._tracer = scene._tracer.in_process()
    return out


class TileWork:
    """A tile function's context as named fields (``TileWork(scene=..., chunk=...)``); Ray
    workers get :meth:`for_ray`, in which ``scene`` (if any) traces in its own process only."""

    def __init__(self, **fields: Any):
        self.__dict__.update(fields)

    def for_ray(self) -> TileWork:
        if "scene" not in self.__dict__:
            return self
        return TileWork(**{**self.__dict__, "scene": single_process(self.scene)})


def _run_in_worker(fn: TileFn, key: str, holder: list, index: int, cache: TileCache, meta: dict):
    """A Ray task's body: the cached context of ``key`` (fetched from the object store once per
    worker process), then tile ``index`` with one torch thread; returns its arrays, meta, the
    bytes of its checkpoint file (encoded here, so the driver only writes them) and the node."""
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        import ray

        ctx = ray.get(holder[0])  # Ray's own in-memory transport; no file is read
        _CONTEXTS.clear()
        _CONTEXTS[key] = ctx
    configure_worker(1)  # Ray runs one task per CPU; a task's own threads would oversubscribe
    arrays, tile_meta = fn(ctx, index)
    import ray

    data = cache.encode(arrays, {**meta, **tile_meta})
    return arrays, tile_meta, data, ray.get_runtime_context().get_node_id()


def _once(work: Callable[[], None] | None) -> Callable[[], None]:
    """``work`` with one torch thread on the first call; later calls (and None) do nothing."""
    left = [work]

    def run() -> None:
        todo, left[0] = left[0], None
        if todo is not None:
            with single_thread():
                todo()

    return run


def _pending(
    cache: TileCache, num_tiles: int, max_new: int | None, cost: Sequence[float] | None
) -> tuple[Tiles, list[int], list[int]]:
    """The cached tiles loaded (``meta["cached"]`` True), the tiles to compute in tile order (at
    most ``max_new``) and the order workers start them in (decreasing ``cost``, ties in tile order)."""
    out = Tiles([None] * num_tiles)
    todo = []
    for k in range(num_tiles):
        done = cache.load(k)
        if done is None:
            todo.append(k)
        else:
            out[k] = (done[0], {**done[1], "cached": True})
    if max_new is not None:
        todo = todo[: max(0, max_new)]
    if cost is not None and len(cost) != num_tiles:
        raise ValueRangeError(f"cost has {len(cost)} numbers for {num_tiles} tiles")
    # the order in which workers start them (one process computes them in tile order instead)
    start = todo if cost is None else sorted(todo, key=lambda k: -float(cost[k]))  # ties: tile order
    return out, todo, start


def run_tiles(
    fn: TileFn,
    context: Any,
    num_tiles: int,
    cache: TileCache,
    executor: str = "local",
    address: str | None = None,
    max_retries: int = 3,
    desc: str = "tiles",
    progress: bool = True,
    ray_context: Any | None = None,
    meta: dict[str, Any] | None = None,
    consume: Callable[[int, dict[str, np.ndarray], dict[str, Any]], None] | None = None,
    max_new: int | None = None,
    processes: int | None = None,
    steps_per_tile: Sequence[int] | None = None,
    idle: Callable[[], None] | None = None,
    cost: Sequence[float] | None = None,
) -> Tiles:
    """Every tile's (arrays, meta), in tile order, computing those not in ``cache``.

    Args:
        fn: ``fn(context, k) -> (arrays, meta)``, a module-level function (Ray pickles it by name).
        context: what ``fn`` needs besides the tile index (scene, settings, seed).
        num_tiles: tiles ``0 .. num_tiles - 1``.
        cache: finished tiles (loaded instead of computed; new ones saved as they finish).
        executor: ``"local"`` or ``"ray"``.
        address: Ray only, see :func:`connect_ray`.
        max_retries: Ray only: times a tile is run again after its worker died.
        desc: the label of the tqdm bar over finished tiles.
        progress: whether that bar shows.
        ray_context: Ray only: the object shipped to workers instead of ``context`` (e.g. the
            scene without its forked trace workers); default ``context.for_ray()`` when
            ``context`` has it (:class:`TileWork`), else ``context``.
        meta: saved beside every tile (with the tile's own meta).
        consume: ``consume(k, arrays, meta)`` is called for the tiles in tile order as soon as
            tile ``k`` and all before it are finished (so the driver assembles while workers
            compute), with one torch thread; the tile is then dropped from the result.
        max_new: compute at most this many tiles not in ``cache`` (the first ones missing; the
            others stay None in the result): for tests of resuming.
        processes: local only: tiles computed at once in forked processes (each gets
            ``ray_context`` as for Ray); None: :func:`~torch_brdf.parallel.threads.tile_processes` (one
            per usable core, 1 on a busy machine); 1: all in this process (needed when ``fn``
            fills something of ``context``'s, e.g. an oracle).
        steps_per_tile: the bar's units per tile (``num_tiles`` counts, e.g. pass groups), which
            ``fn`` reports as it goes with :func:`tile_tick` (locally, forked processes
            included); None: one unit per tile.
        idle: work of this process that does not depend on the tiles (e.g. a record's side
            buffers), called once: while forked processes or Ray tasks compute the tiles (so it
            is not serial after them), else after the tiles; always, even when every tile was
            cached.
        cost: the expected cost of each tile (``num_tiles`` numbers in any unit, e.g. its paths):
            tiles computed by forked processes or Ray tasks start in decreasing order of it (ties
            in tile order), so that the last ones to start, which decide whether the workers run
            out of work together, are the short ones; None: in tile order. Only the order of the
            work changes, never a tile's arrays (``consume`` still sees the tiles in tile order).
    Returns:
        :class:`Tiles`, ``num_tiles`` (arrays, meta), None where consumed; ``meta["cached"]``
        is True for loaded tiles.
    Raises:
        TileError: a tile failed on Ray after ``max_retries`` retries (or raised).
    """
    if executor not in EXECUTORS:
        raise ValueRangeError(f"executor must be one of {EXECUTORS}; got {executor!r}")
    if max_retries < 0:
        raise ValueRangeError(f"max_retries must be >= 0; got {max_retries}")
    out, todo, start = _pending(cache, num_tiles, max_new, cost)
    steps = [1] * num_tiles if steps_per_tile is None else [max(1, int(n)) for n in steps_per_tile]
    if len(steps) != num_tiles:
        raise ValueRangeError(f"steps_per_tile has {len(steps)} counts for {num_tiles} tiles")
    ticked = [0] * num_tiles  # units of each tile already shown
    initial = sum(n for n, x in zip(steps, out, strict=True) if x is not None)
    bar = tqdm(total=sum(steps), initial=initial, desc=desc, disable=not progress)
    nxt = [0]  # the next tile to consume

    def advance(k: int, n: int) -> None:
        n = max(0, min(n, steps[k] - ticked[k]))  # never past the tile's own units
        ticked[k] += n
        bar.update(n)

    def drain() -> None:
        if consume is None:
            return
        with single_thread():
            while nxt[0] < num_tiles and out[nxt[0]] is not None:
                consume(nxt[0], *out[nxt[0]])
                out[nxt[0]] = None
                nxt[0] += 1

    writer = _TileWriter(cache, meta or {})

    def finish(k: int, res: TileResult, encoded: bytes | None = None) -> None:
        writer.save(k, res, encoded)
        out[k] = (res[0], {**res[1], "cached": False})
        advance(k, steps[k])
        drain()

    done = False
    try:
        drain()
        if ray_context is None:
            ray_context = context.for_ray() if hasattr(context, "for_ray") else context
        nproc = max(1, min(tile_processes(processes), len(todo))) if executor == "local" else 0
        out.processes = nproc
        run_idle = _once(idle)
        if executor == "local" and nproc > 1:
            _run_forked(fn, ray_context, start, finish, advance, nproc, cache, meta or {}, run_idle)
        elif executor == "local":
            with single_thread():
                for k in todo:
                    finish(k, _ticking(lambda n, k=k: advance(k, n), fn, context, k))
        elif todo:
            _run_ray(fn, ray_context, start, finish, address, max_retries, out.nodes, cache, meta or {}, run_idle)
        run_idle()
        done = True
    finally:
        bar.close()
        # every finished tile's file is written before this returns (or raises), resumable
        out.write_seconds = writer.close(raise_errors=done)
    return out


class _TileWriter:
    """The tile files of a run, written by one background thread in the order the tiles finish:
    writing a file is mostly a system call that releases the GIL, so the driver
    assembles tile k while tile k - 1 is written, and its serial work per tile is the larger of
    the two rather than their sum. Nothing is started without a checkpoint folder. The thread
    is made at the first write, after the forked tile processes have started."""

    def __init__(self, cache: TileCache, meta: dict[str, Any]):
        self.cache, self.meta = cache, meta
        self.pool: ThreadPoolExecutor | None = None
        self.futures: list = []

    def save(self, k: int, res: TileResult, encoded: bytes | None) -> None:
        """Write tile ``k`` (its encoded bytes, else its arrays and meta) in the thread."""
        if self.cache.folder is None:
            return
        if self.pool is None:
            self.pool = ThreadPoolExecutor(1, thread_name_prefix="torch_brdf-tile-writer")
        self.futures.append(self.pool.submit(self._write, k, res, encoded))

    def _write(self, k: int, res: TileResult, encoded: bytes | None) -> float:
        t0 = time.perf_counter()
        if encoded is None:
            self.cache.save(k, res[0], {**self.meta, **res[1]})
        else:
            self.cache.save_encoded(k, encoded)
        return time.perf_counter() - t0

    def close(self, raise_errors: bool = True) -> float:
        """Wait for every write: their seconds (a failed write's error is raised when
        ``raise_errors``, after the others are done)."""
        if self.pool is None:
            return 0.0
        self.pool.shutdown(wait=True)
        self.pool, futures, self.futures = None, self.futures, []
        errors = [e for f in futures if (e := f.exception()) is not None]
        if errors and raise_errors:
            raise errors[0]
        return sum(f.result() for f in futures if f.exception() is None)


def _ticking(report: Callable[[int], None], fn: TileFn, context: Any, k: int) -> TileResult:
    """``fn(context, k)`` with :func:`tile_tick` calling ``report``."""
    global _TICK
    _TICK = report
    try:
        return fn(context, k)
    finally:
        _TICK = None


# what forked tile processes run: set before forking, inherited by the children (the last two
# items: the queue on which they report (tile, units) for :func:`tile_tick`, and the folder,
# None or in memory, through which they hand their arrays back: see :func:`_handed`)
_FORKED: tuple[TileFn, Any, TileCache, dict, Any, str | None] | None = None

#: a forked tile's arrays of at least this many bytes go back through a file in the run's folder
#: (tmpfs where there is one) rather than pickled through the pool's pipe, during which the
#: process would wait for the driver to read them (~0.1 s per tile of ~20 MB at 256²)
HAND_BACK_BYTES = 1 << 20


#: prefix of the hand-back folders; the creating process's id follows it
HAND_PREFIX = "torch_brdf-tiles-"


def _remove_stale_hand_folders(root: str) -> None:
    """Remove the hand-back folders in ``root`` whose creating process is gone (a driver killed
    with SIGKILL cannot remove its own; tmpfs holds them in memory until the next boot). A
    folder whose process id is alive is kept, even if the id was reused."""
    for name in os.listdir(root):
        pid = name[len(HAND_PREFIX) :].split("-", 1)[0]
        if not name.startswith(HAND_PREFIX) or not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(os.path.join(root, name), ignore_errors=True)
        except PermissionError:  # alive, another user's
            continue


def _hand_folder(root: str = "/dev/shm") -> str | None:
    """A fresh private folder for the forked tiles' arrays: in /dev/shm (memory) when it exists
    and is writable, else None (the arrays go through the pipe). Folders left by killed
    drivers are removed first."""
    if not os.access(root, os.W_OK):
        return None
    try:
        _remove_stale_hand_folders(root)
        return tempfile.mkdtemp(prefix=f"{HAND_PREFIX}{os.getpid()}-", dir=root)
    except OSError:
        return None


def _handed(arrays: dict[str, np.ndarray], folder: str | None, k: int):
    """A forked tile's arrays as they travel to the driver: the arrays themselves, or (large
    ones, with a folder) the file that holds their bytes one after another and each array's
    (name, dtype, shape); :func:`_received` reverses it."""
    if folder is None or sum(v.nbytes for v in arrays.values()) < HAND_BACK_BYTES:
        return arrays
    path, layout = os.path.join(folder, f"tile{k}-{os.getpid()}.bin"), []
    with open(path, "wb") as f:
        for name, v in arrays.items():
            v = np.ascontiguousarray(v)
            f.write(v.reshape(-1).view(np.uint8).data)  # the bytes, no copy
            layout.append((name, v.dtype.str, v.shape))
    return ("file", path, layout)


def _received(handed) -> dict[str, np.ndarray]:
    """The arrays of :func:`_handed` (views into one buffer read from the file, which is removed)."""
    if isinstance(handed, dict):
        return handed
    _, path, layout = handed
    buf = np.fromfile(path, dtype=np.uint8)
    os.unlink(path)
    out, at = {}, 0
    for name, dtype, shape in layout:
        d = np.dtype(dtype)
        n = int(np.prod(shape, dtype=np.int64)) * d.itemsize
        out[name] = buf[at : at + n].view(d).reshape(shape)
        at += n
    return out


def _keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory in this process for reuse (no ``mmap`` for large
    blocks, no trimming of the heap): a forked tile process allocates and frees the same large
    buffers pass group after pass group, which otherwise come back as fresh pages (measured on
    the 256², 16 spp box in one process: 38-71k minor page faults and 0.09-0.17 s of system
    time per precompute against 8-32k and 0.02-0.07 s, 5-6% less CPU, the same peak memory).
    Only for forked tile processes, which exit after their tiles. False where the C library
    has no ``mallopt`` (not glibc): nothing changes then."""
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc: its default behaviour stays
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h> parameter numbers
    return bool(mallopt(m_mmap_threshold, 1 << 30)) and bool(mallopt(m_trim_threshold, 1 << 31))


def _forked_init() -> None:
    worker_setup(1)
    _keep_freed_memory()


def _forked_tile(k: int) -> tuple[tuple, bytes | None]:
    """Tile ``k`` in a forked process, its arrays as :func:`_handed` sends them, and the bytes of
    its checkpoint file (encoded here, as a Ray task does, so the driver only writes them; None
    without a checkpoint folder)."""
    fn, ctx, cache, meta, ticks, folder = _FORKED
    try:
        arrays, tile_meta = _ticking(lambda n: ticks.put((k, n)), fn, ctx, k)
    except (KeyboardInterrupt, SystemExit) as exc:  # would kill the worker: report it as the tile's error
        raise TileError(f"tile {k} stopped: {type(exc).__name__}: {exc}") from None
    return (_handed(arrays, folder, k), tile_meta), cache.encode(arrays, {**meta, **tile_meta})


# forked tile processes of finished runs that may still be exiting (see :func:`wait_tile_processes`)
_EXITING: list = []


def wait_tile_processes() -> None:
    """Wait until the forked tile processes of finished runs have exited (a run returns while
    they free their memory), e.g. before reading the CPU time of this process's children."""
    while _EXITING:
        _EXITING.pop().join()


def _run_forked(
    fn: TileFn, context: Any, todo: Sequence[int], finish, advance, processes: int, cache, meta, idle=None
) -> None:
    """Tiles ``todo`` in ``processes`` forked processes (one torch thread each); ``finish`` runs
    here as each tile arrives (any order; it assembles in tile order), ``advance(k, n)`` as the
    processes report progress within tile ``k``, ``idle()`` once the tiles are under way. A
    tile's exception is raised here; a process that dies (killed, out of memory) raises
    ``BrokenProcessPool``; either way, and on Ctrl-C, the other processes are stopped."""
    global _FORKED
    _EXITING[:] = [p for p in _EXITING if p.is_alive()]  # those of earlier runs that are gone
    folder = _hand_folder()
    with forking() as mp:
        ticks = mp.SimpleQueue()

        def report() -> None:
            while not ticks.empty():
                advance(*ticks.get())

        _FORKED = (fn, context, cache, meta, ticks, folder)
        pool = ProcessPoolExecutor(processes, mp, initializer=_forked_init)
        received = False
        try:
            with single_thread():
                futures = {pool.submit(_forked_tile, k): k for k in todo}
                if idle is not None:
                    idle()
                pending = set(futures)
                while pending:
                    done, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
                    report()
                    for f in done:
                        (handed, tile_meta), encoded = f.result()
                        finish(futures[f], (_received(handed), tile_meta), encoded)
            received = True
        except BaseException:
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                proc.terminate()  # running tiles are not waited for
            raise
        finally:
            # every tile received: the processes exit (freeing their memory) while this one
            # goes on; the pool's own thread reaps them (:func:`wait_tile_processes` waits)
            if received:
                _EXITING.extend((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=not received, cancel_futures=True)
            _FORKED = None
            ticks.close()
            if folder is not None:  # files of tiles never received (an error, Ctrl-C)
                shutil.rmtree(folder, ignore_errors=True)


def _run_ray(
    fn, context, todo: Sequence[int], finish, address, max_retries: int, nodes: set, cache, meta, idle=None
) -> None:
    ray = connect_ray(address)
    key = f"{fn.__module__}.{fn.__qualname__}:{uuid.uuid4().hex}"  # this run's context
    ref = ray.put(context)  # once; tasks carry only the reference (wrapped, so Ray does not resolve it)
    # SPREAD: tiles go to every node from the start, instead of filling the first node whose
    # CPU frees up first (short tiles could otherwise all run on one node of a small cluster)
    task = ray.remote(num_cpus=1, max_retries=max_retries, scheduling_strategy="SPREAD")(_run_in_worker)
    pending = {task.remote(fn, key, [ref], k, cache, meta): k for k in todo}
    if idle is not None:
        idle()
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for r in ready:
                k = pending.pop(r)
                try:
                    res = ray.get(r)
                except Exception as exc:
                    raise TileError(
                        f"tile {k} failed on Ray (after up to {max_retries} retries): {type(exc).__name__}: {exc}"
                    ) from exc
                arrays = {n: v if v.flags.writeable else v.copy() for n, v in res[0].items()}  # zero-copy views
                nodes.add(res[3])
                finish(k, (arrays, res[1]), res[2])
    finally:
        for r in pending:
            ray.cancel(r, force=True)
