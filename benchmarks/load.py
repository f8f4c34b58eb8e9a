"""Load sensitivity: the key stages quiet and beside one competing CPU-bound process.

Runs :mod:`torch_brdf.report.benchmarks.load` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as its
last line.
"""

from torch_brdf.report.benchmarks.load import main

if __name__ == "__main__":
    main()
