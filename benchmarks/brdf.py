"""BRDF layer benchmark: evaluation throughput, 1-D projection error, band-albedo cost.

Runs :mod:`torch_brdf.report.benchmarks.brdf` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as its
last line.
"""

from torch_brdf.report.benchmarks.brdf import main

if __name__ == "__main__":
    main()
