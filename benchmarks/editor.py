"""The material editor's latency in a real browser.

Runs :mod:`torch_brdf.report.benchmarks.editor` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as its
last line.
"""

from torch_brdf.report.benchmarks.editor import main

if __name__ == "__main__":
    main()
