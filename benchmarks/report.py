"""The speed/accuracy report: every benchmark, one page.

    python benchmarks/report.py [--quick] [--out out/report] [--results FOLDER] [--only NAME ...]

The same as ``torch-brdf report``: runs every benchmark (``--quick``: their small versions),
keeps each one's JSON and log under ``<out>/runs/``, and writes ``<out>/report.html`` (self-
contained) with one PNG per figure beside it. ``--results`` reads a folder of saved JSON (run
records, bare benchmark objects or captured stdout ``<name>.out``) instead of running. Prints
one JSON object as the last line: the page and PNGs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch_brdf.report import BENCHMARKS, make_report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/report"), help="folder of the page, PNGs and run records")
    ap.add_argument("--quick", action="store_true", help="run every benchmark with --quick")
    ap.add_argument("--results", type=Path, default=None, help="read saved benchmark JSON from this folder")
    ap.add_argument("--only", nargs="*", default=None, choices=BENCHMARKS, help="run only these benchmarks")
    ap.add_argument("--timeout", type=float, default=None, help="seconds per benchmark")
    args = ap.parse_args()
    page = make_report(args.out, args.quick, args.results, args.only, None, args.timeout)
    print(json.dumps({"report": str(page), "pngs": sorted(str(p) for p in page.parent.glob("*.png"))}))


if __name__ == "__main__":
    main()
