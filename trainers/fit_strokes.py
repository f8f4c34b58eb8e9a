"""Fit a BRDF to painted strokes (Iwasaki et al.): transfer functions, strokes, constrained fit, re-render.

    python trainers/fit_strokes.py teatray --object teapot --strokes strokes.json --out out/inverse

The same as ``torch-brdf fit-strokes`` (same options, see ``--help``). The strokes file format
is documented in :mod:`torch_brdf.inverse.design`. Outputs (atomic, versioned and checksummed
where they are arrays): ``fit.npz`` (coefficients, kd, f0 and the solver report),
``transfer.npz`` (the transfer record; reused on a rerun with the same settings, so an
interrupted run resumes after it), ``render.exr`` and ``render.png``. The summary is printed as
one JSON line. Seeded (``--seed``), tqdm progress. torch is imported only once the options are
parsed, so ``--help`` is quick.
"""

import sys

from torch_brdf.cli import app

if __name__ == "__main__":
    app(["fit-strokes", *sys.argv[1:]], prog_name="torch-brdf")
