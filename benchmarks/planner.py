"""The error-budget planners against fixed defaults: GI editing, inverse design,
relighting, ...

Runs :mod:`torch_brdf.report.benchmarks.planner` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.planner import main

if __name__ == "__main__":
    main()
