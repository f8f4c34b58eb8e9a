"""Running the benchmarks and keeping what they print (the report's input).

Each benchmark, a module of :mod:`torch_brdf.report.benchmarks` (shipped with the package, so an
install writes its report without a source checkout; ``benchmarks/<name>.py`` in the repository
runs the same module) or a script of a given folder, prints progress and then one JSON object as
its LAST line. A
run record (:func:`run_benchmark`) keeps that object under ``result`` with what the report
needs beside it: the command, the seconds, the load average before and after, the peak
resident memory and the CPU seconds of the process (and of the children it waited for: forked
tiles, not Ray's workers), the return code, and, when the run failed, the error and the tail
of its output. Records are plain JSON files,
``<folder>/<name>.json``; :func:`load_results` reads a folder of them back, and also accepts a
benchmark's bare JSON object or its captured stdout (``<name>.out``, last line JSON).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ..errors import DataNotFoundError, FileFormatError
from ..io.atomic import replacing

#: the record format written by :func:`run_benchmark`
FORMAT = "torch_brdf.report.run/1"

#: the benchmark scripts the report runs, in this order (fast, then the long ones)
BENCHMARKS = (
    "extremes",
    "brdf",
    "raytrace",
    "planner",
    "inverse",
    "triple_product",
    "polynomial",
    "scaleout",
    "inverse_gi",
    "denoise",
    "denoise_tune",  # after denoise: it reads denoise's cached parts (and makes what is missing)
    "manifold",
    "editor",
    "load",
    "reduce_numba",
    "textures",
    "export",
)

#: extra environment per benchmark (as its docstring asks)
ENV = {"manifold": {"OPENBLAS_NUM_THREADS": "1"}}

#: options the report adds to a benchmark's ``--quick`` (``torch-brdf report --quick``), so that
#: the whole quick report takes minutes: fewer repeats, rounds, frames, splits and peer seconds,
#: never other keys or another meaning. A benchmark run by hand with ``--quick`` alone keeps its
#: own quick sizes (the docs quote figures of those runs, saved in ``docs/results``).
QUICK_ARGS: dict[str, list[str]] = {
    # one round of precompute vs embree alone (the embreex variants on two chunks, scaled), the
    # first of the three frames, a 16-quad plane: the same keys on a smaller scene
    "triple_product": "--rounds 1 --frames 1 --plane-quads 16 --embree-chunks 2".split(),
    # two random 80/20 splits instead of five (mean and std need two)
    "manifold": "--splits 2".split(),
    # the manifold planner: one pool order (one plan) and the first 80 held-out materials
    "planner": "--orders 1 --heldout 80".split(),
    # one quiet/loaded alternation per stage instead of two
    "load": "--rounds 1".split(),
    # Ray's start bounded at 120 s instead of 300 (a busy machine's retries; the page then shows
    # the skip in a cell and the local figures)
    "scaleout": "--ray-start-s 120".split(),
}

#: the package of the benchmark modules (``python -m PACKAGE.<name>``)
PACKAGE = "torch_brdf.report.benchmarks"

# Runs a benchmark module (or a script, given its path) as __main__ and reports the peak RSS and
# the CPU seconds (user + system) of itself and its waited-for children on stderr at exit (a
# script's sibling-module imports work as with ``python script``).
_WRAPPER = """
import atexit, os, resource, runpy, sys
path = sys.argv[1]
sys.argv = sys.argv[1:]
def _peak():
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    sys.stderr.write("\\n__peak_rss_kb__ %d\\n" % max(me.ru_maxrss, kids.ru_maxrss))
    sys.stderr.write("__cpu_s__ %.3f\\n" % (me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime))
atexit.register(_peak)
if path.endswith(".py"):
    sys.path.insert(0, os.path.dirname(os.path.abspath(path)))
    runpy.run_path(path, run_name="__main__")
else:
    runpy.run_module(path, run_name="__main__", alter_sys=True)
"""


def find_benchmarks(folder: str | os.PathLike | None = None) -> Path:
    """A folder of benchmark scripts: ``folder`` if given, else ``./benchmarks``, else the one
    beside the package's source (a checkout). Needed only to run scripts by path: by default
    the report runs the package's own modules (:data:`PACKAGE`).

    Raises:
        DataNotFoundError: no such folder.
    """
    here = Path(__file__).resolve().parents[2] / "benchmarks"
    for cand in [Path(folder)] if folder is not None else [Path("benchmarks"), here]:
        if (cand / "polynomial.py").is_file():
            return cand.resolve()
    raise DataNotFoundError(
        f"no benchmarks folder at {folder or 'benchmarks/ or ' + str(here)}; run from the repository root, "
        "pass --benchmarks, or leave it out to run the installed package's benchmark modules"
    )


def last_json(text: str) -> dict[str, Any] | None:
    """The last line of ``text`` that parses as a JSON object, or None."""
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                obj = json.loads(line)
            except json.JSONDecodeError:
                return None
            return obj if isinstance(obj, dict) else None
    return None


def _tail(text: str, lines: int = 25) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def run_benchmark(
    name: str,
    bench_dir: str | os.PathLike | None,
    quick: bool,
    out_dir: Path | None = None,
    timeout: float | None = None,
    args: Iterable[str] = (),
) -> dict[str, Any]:
    """Run the benchmark ``name`` (``--quick`` and its :data:`QUICK_ARGS` if asked, then
    ``args``) and return its run record: the module ``PACKAGE.<name>`` in the working directory
    when ``bench_dir`` is None, else the script ``bench_dir/<name>.py`` in the folder above it.

    A failure (non-zero exit, timeout, no JSON on the last line) is recorded in ``error``, never
    raised: the report shows it. With ``out_dir`` the record is written to ``<name>.json`` and
    the full output to ``<name>.log``.
    """
    target = f"{PACKAGE}.{name}" if bench_dir is None else str(Path(bench_dir) / f"{name}.py")
    cmd = [sys.executable, "-c", _WRAPPER, target, *(["--quick", *QUICK_ARGS.get(name, ())] if quick else [])]
    cmd += list(args)
    shown = " ".join(["python", *(["-m", target] if bench_dir is None else [f"benchmarks/{name}.py"]), *cmd[4:]])
    env = dict(os.environ)
    root = None
    if bench_dir is not None:  # the scripts' folder's parent: a checkout's root
        root = str(Path(bench_dir).resolve().parent)
        env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    env.update(ENV.get(name, {}))
    rec: dict[str, Any] = {"format": FORMAT, "name": name, "command": shown, "quick": bool(quick)}
    rec["started"] = time.strftime("%Y-%m-%d %H:%M:%S")
    rec["load_before"] = os.getloadavg()[0]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=root)
        out, err, rc = p.stdout, p.stderr, p.returncode
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else exc.stdout or ""
        err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else exc.stderr or ""
        rc, err = None, err + f"\ntimed out after {timeout:g} s"
    rec["seconds"] = time.perf_counter() - t0
    rec["load_after"] = os.getloadavg()[0]
    rec["returncode"] = rc
    marks, kept = {}, []  # the wrapper's lines (the last of each wins), the rest of stderr kept
    for ln in err.splitlines():
        key, _, value = ln.partition(" ")
        if key in ("__peak_rss_kb__", "__cpu_s__"):
            marks[key] = float(value)
        else:
            kept.append(ln)
    err = "\n".join(kept)
    rec["peak_rss_mb"] = marks["__peak_rss_kb__"] / 1024 if "__peak_rss_kb__" in marks else None
    rec["cpu_s"] = marks.get("__cpu_s__")
    rec["result"] = last_json(out) if rc == 0 else None
    rec["error"] = None
    if rc != 0:
        rec["error"] = f"exit status {rc}" if rc is not None else f"timed out after {timeout:g} s"
    elif rec["result"] is None:
        rec["error"] = "the last line printed is not a JSON object"
    if rec["error"]:
        rec["log_tail"] = _tail(out + "\n" + err)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / f"{name}.log").write_text(out + "\n--- stderr ---\n" + err)
        write_record(rec, out_dir / f"{name}.json")
    return rec


def write_record(rec: dict[str, Any], path: Path) -> None:
    """Write a run record as JSON (atomically)."""
    with replacing(path) as tmp:
        Path(tmp).write_text(json.dumps(rec, indent=1, allow_nan=True))


def load_results(folder: str | os.PathLike) -> dict[str, dict[str, Any]]:
    """Run records by benchmark name from ``folder``: ``<name>.json`` (a run record or a bare
    benchmark JSON object) or ``<name>.out`` (a benchmark's stdout; its last line is the object).

    Raises:
        FileFormatError: the folder does not exist, a ``.json`` file is not JSON, or
            ``extremes.json`` is not the extremes benchmark's object.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileFormatError(f"results folder {folder} does not exist")
    recs: dict[str, dict[str, Any]] = {}
    for path in sorted(folder.glob("*.out")):
        obj = last_json(path.read_text())
        err = None if obj is not None else f"{path.name}: the last line is not a JSON object"
        recs[path.stem] = {"name": path.stem, "result": obj, "error": err, "command": f"(read from {path.name})"}
    for path in sorted(folder.glob("*.json")):
        try:
            obj = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise FileFormatError(f"{path}: not JSON ({exc})") from exc
        if not isinstance(obj, dict):
            raise FileFormatError(f"{path}: expected a JSON object; got {type(obj).__name__}")
        if obj.get("format") != FORMAT:
            obj = {"name": path.stem, "result": obj, "error": None, "command": f"(read from {path.name})"}
        if path.stem == "extremes" and not obj.get("error"):
            _check_extremes(obj.get("result"), path)
        recs[path.stem] = obj
    return recs


def _check_extremes(result: Any, path: Path) -> None:
    """Refuse an ``extremes`` result that is not ``benchmarks/extremes.py``'s object (a list
    ``cells`` of objects with ``row``, ``column`` and ``ok``): the report would otherwise show
    "not measured" for a file that was given on purpose.

    Raises:
        FileFormatError: naming the file and what is missing.
    """
    cells = result.get("cells") if isinstance(result, dict) else None
    if not isinstance(cells, list) or not cells:
        raise FileFormatError(
            f"{path}: not benchmarks/extremes.py output (expected an object with a non-empty list 'cells')"
        )
    for i, cell in enumerate(cells):
        missing = [k for k in ("row", "column", "ok") if not isinstance(cell, dict) or k not in cell]
        if missing:
            raise FileFormatError(f"{path}: cells[{i}] lacks {', '.join(missing)} (not benchmarks/extremes.py output)")
