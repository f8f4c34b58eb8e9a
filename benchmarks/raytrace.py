"""Ray tracing throughput: ``Scene.trace`` / ``Scene.occluded`` against embreex called directly.

Runs :mod:`torch_brdf.report.benchmarks.raytrace` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.raytrace import main

if __name__ == "__main__":
    main()
