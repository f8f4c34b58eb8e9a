"""Is a numba kernel faster than torch for the GI precompute's per-tile reduction?

Runs :mod:`torch_brdf.report.benchmarks.reduce_numba` (shipped with the package, so that
``torch-brdf report`` runs it from an install) with the same options (``--help``) and the same
JSON as its last line.
"""

from torch_brdf.report.benchmarks.reduce_numba import main

if __name__ == "__main__":
    main()
