"""The speed/accuracy report: every benchmark's trade in one page.

:func:`make_report` runs the benchmarks -- the modules of :mod:`.benchmarks`, shipped with the
package (``benchmarks/<name>.py`` in the repository runs the same ones), or the scripts of a
given folder -- (or reads their saved JSON from a results folder), turns each capability's
numbers into error-vs-cost figures (:mod:`.sections`) and writes ``report.html`` -- self-
contained, figures embedded -- plus one PNG per figure (:mod:`.page`). ``torch-brdf report``
and ``python benchmarks/report.py`` call it.
The numerical-extremes table is ``benchmarks/extremes.py``'s output, which evaluates the cases
of ``tests/test_extremes.py`` (so it needs a source checkout; elsewhere the page says it did not
run).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from tqdm.auto import tqdm

from ..data import progress_default
from ..errors import TorchBRDFError, ValueRangeError
from .page import machine, write_page
from .run import BENCHMARKS, find_benchmarks, load_results, run_benchmark
from .sections import sections

__all__ = ["BENCHMARKS", "load_results", "make_report", "run_benchmark"]


def make_report(
    out_dir: str | os.PathLike,
    quick: bool = False,
    results: str | os.PathLike | None = None,
    only: Sequence[str] | None = None,
    benchmarks: str | os.PathLike | None = None,
    timeout: float | None = None,
    progress: bool | None = None,
) -> Path:
    """Run the benchmarks (or read ``results``) and write the report into ``out_dir``.

    Args:
        out_dir: folder for ``report.html``, the PNGs and (when benchmarks run) the run records
            ``runs/<name>.json`` with their logs.
        quick: pass ``--quick`` to every benchmark (the small version).
        results: a folder of saved run records or benchmark JSON (see
            :func:`~torch_brdf.report.run.load_results`) instead of running anything; a benchmark
            missing there is run only if named in ``only``.
        only: run just these benchmarks (default all of :data:`BENCHMARKS`).
        benchmarks: a folder of benchmark scripts to run by path instead of the package's
            modules (None, the default: :data:`~torch_brdf.report.run.PACKAGE`, no checkout needed).
        timeout: seconds allowed per benchmark (default 1800 quick, 14400 full).
        progress: tqdm bar over the benchmarks (default: on in a terminal).
    Returns:
        the path of ``report.html``.
    Raises:
        ValueRangeError: an unknown benchmark name in ``only``.
        DataNotFoundError: ``benchmarks`` is not a folder of benchmark scripts.
        FileFormatError: ``results`` is not a folder of JSON.
        TorchBRDFError: matplotlib is not installed (the ``report`` extra).
    """
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise TorchBRDFError("the report's figures need matplotlib: pip install 'torch_brdf[report]'") from exc
    out = Path(out_dir)
    names = list(only) if only else list(BENCHMARKS)
    if not only and results is None and benchmarks is not None:  # any script added to the folder runs too
        names += [
            p.stem
            for p in sorted(find_benchmarks(benchmarks).glob("*.py"))
            if p.stem[0] != "_" and p.stem not in names and p.stem != "report"
        ]
    unknown = sorted(set(only or ()) - set(BENCHMARKS))
    if unknown:
        raise ValueRangeError(f"unknown benchmark(s) {unknown}; known: {list(BENCHMARKS)}")
    recs = load_results(results) if results is not None else {}
    todo = names if results is None else [n for n in (only or ()) if n not in recs]
    if todo:
        bench = None if benchmarks is None else find_benchmarks(benchmarks)
        limit = timeout if timeout is not None else (1800.0 if quick else 14400.0)
        bar = tqdm(todo, desc="benchmarks", unit="script", disable=not progress_default(progress))
        for name in bar:
            bar.set_postfix_str(name)
            recs[name] = run_benchmark(name, bench, quick, out / "runs", limit)
    meta = {
        "mode": "quick" if quick else ("saved runs (see the runs table)" if results is not None else "full"),
        **machine(),
    }
    if results is not None:
        meta["results read from"] = str(results)
    title = "torch_brdf speed/accuracy report" + (" (quick)" if quick else "")
    ordered = {n: recs[n] for n in BENCHMARKS if n in recs} | {n: r for n, r in recs.items() if n not in BENCHMARKS}
    return write_page(ordered, sections(ordered), out, title, meta)
