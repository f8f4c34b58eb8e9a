"""All-frequency relighting with locally adaptive triple products: speed, accuracy, storage.

Runs :mod:`torch_brdf.report.benchmarks.triple_product` (shipped with the package, so that
``torch-brdf report`` runs it from an install) with the same options (``--help``) and the same
JSON as its last line.
"""

from torch_brdf.report.benchmarks.triple_product import main

if __name__ == "__main__":
    main()
