"""The GI precompute through the local executor and through Ray with 1 and 2 workers, and a scale-
out model.

Runs :mod:`torch_brdf.report.benchmarks.scaleout` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.scaleout import main

if __name__ == "__main__":
    main()
