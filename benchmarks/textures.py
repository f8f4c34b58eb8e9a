"""Textures through the GI precompute and renderer: the Sec. 5.3 approximation's error.

Runs :mod:`torch_brdf.report.benchmarks.textures` (shipped with the package) with the same
options (``--help``) and the same JSON as its last line.
"""

from torch_brdf.report.benchmarks.textures import main

if __name__ == "__main__":
    main()
