"""BRDF editing with global illumination: precomputation, freezing, frames, and accuracy.

Runs :mod:`torch_brdf.report.benchmarks.polynomial` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.polynomial import main

if __name__ == "__main__":
    main()
