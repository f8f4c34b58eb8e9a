"""The numerical extremes table: every case of tests/test_extremes.py, evaluated.

Runs :mod:`torch_brdf.report.benchmarks.extremes` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.extremes import main

if __name__ == "__main__":
    main()
