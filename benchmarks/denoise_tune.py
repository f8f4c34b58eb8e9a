"""Tune the linear guide-only filters on the cached frames of ``benchmarks/denoise.py``.

Runs :mod:`torch_brdf.report.benchmarks.denoise_tune` (shipped with the package, so that
``torch-brdf report`` runs it from an install) with the same options (``--help``) and the same
JSON as its last line.
"""

from torch_brdf.report.benchmarks.denoise_tune import main

if __name__ == "__main__":
    main()
