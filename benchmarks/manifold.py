"""BRDF manifold benchmark: GPLVM fits, interpolation, held-out reconstruction vs PCA, blending.

Runs :mod:`torch_brdf.report.benchmarks.manifold` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.manifold import main

if __name__ == "__main__":
    main()
