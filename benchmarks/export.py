"""Export benchmark: how closely each stock Mitsuba model and the glTF material reproduce the
library's BRDFs, and what an export costs.

Runs :mod:`torch_brdf.report.benchmarks.export` (shipped with the package) with the same
options (``--help``) and the same JSON as its last line.
"""

from torch_brdf.report.benchmarks.export import main

if __name__ == "__main__":
    main()
