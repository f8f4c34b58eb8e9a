"""The numerical extremes table: every case of tests/test_extremes.py, evaluated.

    python benchmarks/extremes.py [--quick] [--only SUBSTRING ...]

Runs :func:`tests.test_extremes.evaluate` -- the function ``test_extreme`` asserts on -- on
every case of :data:`tests.test_extremes.CASES`, so each cell of the report's table is what the
test checks, never typed by hand. Needs the repository checkout (it imports ``tests``, found
beside the package's source or in the working directory); without one it exits with a line
saying so, and the report shows the table as not measured.
``--quick`` changes nothing (the cases are already small; it is accepted for the report's
runner). Prints one line per case, then one JSON object as the last line: ``cells`` (per case:
``row``, ``column``, ``expect``, ``status``, ``ok``, ``error``, ``bound``, ``note``,
``seconds``), ``failed`` (how many cells are not ``ok``) and ``seconds``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _cases():
    """``tests.test_extremes``'s CASES and evaluate, from the repository checkout."""
    for root in (Path(__file__).resolve().parents[3], Path.cwd()):
        if (root / "tests" / "test_extremes.py").is_file():
            sys.path.insert(0, str(root))
            break
    try:
        from tests.test_extremes import CASES, evaluate
    except ImportError as exc:
        raise SystemExit(
            f"the extremes table evaluates the test suite's cases (tests/test_extremes.py), which only a source "
            f"checkout has: run it from the repository root ({type(exc).__name__}: {exc})"
        ) from None
    return CASES, evaluate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="accepted for the report's runner (the cases are small)")
    ap.add_argument(
        "--only", action="append", default=None, help="only cases whose row/column contains this (repeatable)"
    )
    args = ap.parse_args()
    cases, evaluate = _cases()
    t0 = time.perf_counter()
    cells = []
    for case in cases:
        if args.only and not any(o in case.id for o in args.only):
            continue
        c0 = time.perf_counter()
        cell = evaluate(case)
        cell["seconds"] = time.perf_counter() - c0
        cells.append(cell)
        print(f"{'ok ' if cell['ok'] else 'BAD'} {case.id}: {cell['status']} error {cell['error']}", flush=True)
    out = {"cells": cells, "failed": sum(not c["ok"] for c in cells), "seconds": time.perf_counter() - t0}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
