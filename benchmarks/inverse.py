"""Inverse BRDF design benchmark (Iwasaki et al.): transfer functions, cuts, and the constrained
solve.

Runs :mod:`torch_brdf.report.benchmarks.inverse` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.inverse import main

if __name__ == "__main__":
    main()
