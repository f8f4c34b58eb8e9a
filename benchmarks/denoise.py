"""Denoising precomputed basis images against a path tracer with a per-frame denoiser.

Runs :mod:`torch_brdf.report.benchmarks.denoise` (shipped with the package, so that ``torch-brdf
report`` runs it from an install) with the same options (``--help``) and the same JSON as
its last line.
"""

from torch_brdf.report.benchmarks.denoise import main

if __name__ == "__main__":
    main()
