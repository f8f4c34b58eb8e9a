"""Inverse material design with global illumination: fits through the polynomial
tensors.

Runs :mod:`torch_brdf.report.benchmarks.inverse_gi` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.inverse_gi import main

if __name__ == "__main__":
    main()
