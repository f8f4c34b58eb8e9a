"""Fit the GPLVM of the BRDF manifold on the MERL materials and save the fit.

    python trainers/fit_gplvm.py --q 2 --out out/gplvm_q2.npz [--split datasets/merl_split.txt]
    python trainers/fit_gplvm.py --q 5 --grid full --out out/gplvm_q5_full.npz     # streamed Gram
    python trainers/fit_gplvm.py --q 2 --binaries /path/to/brdfs --out out/merl_q2.npz

The same as ``torch-brdf fit-gplvm`` (same options, see ``--help``; the data and the cache are
described in :mod:`torch_brdf.manifold.train`). The fit goes through
:func:`torch_brdf.manifold.fit_gplvm` (seeded with ``--seed``, tqdm progress) and is saved with
:meth:`GPLVMFit.save` (versioned, checksummed, atomic). Prints one JSON summary as the last line.
torch is imported only once the options are parsed, so ``--help`` is quick.
"""

from __future__ import annotations

import sys

from torch_brdf.cli import app


def main(argv: list[str] | None = None):
    """Run ``torch-brdf fit-gplvm ARGV``; returns the JSON summary (a dict), or the exit status."""
    return app(["fit-gplvm", *(sys.argv[1:] if argv is None else argv)], standalone_mode=False, prog_name="torch-brdf")


if __name__ == "__main__":
    app(["fit-gplvm", *sys.argv[1:]], prog_name="torch-brdf")
