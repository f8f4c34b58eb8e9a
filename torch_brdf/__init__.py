"""torch_brdf: design BRDFs in their final scene, in PyTorch on the CPU.

Subpackages and modules, lowest layer first (a module imports only its own layer or a lower
one; ``tests/test_layers.py`` keeps it so):

* :mod:`torch_brdf.errors`: the exception hierarchy (``TorchBRDFError`` and its subclasses).
* :mod:`torch_brdf.data`: where the optional shared data folder lives.
* :mod:`torch_brdf.io`: EXR / PNG images, the versioned checksummed array files, MERL files.
* :mod:`torch_brdf.sphere`: sampling warps and pdfs, lat-long maps, cubemap blocks, DCT, Haar.
* :mod:`torch_brdf.frame`: local shading frames, half/difference angles.
* :mod:`torch_brdf.metrics`: image and BRDF error metrics (relative RMSE, PSNR, HDR-FLIP, log-RMSE ...).
* :mod:`torch_brdf.parallel`: processes and threads: usable cores and quotas, thread limits,
  forked workers, the ray-tracing process pool and the tile executor (local or Ray).
* :mod:`torch_brdf.linalg`: dense linear algebra shared by the package (the Cholesky with jitter).
* :mod:`torch_brdf.brdf`: the BRDF base class, analytic, microfacet, measured and SRBF models,
  1-D band bases.
* :mod:`torch_brdf.scene`: meshes, embree ray tracing, camera and its G-buffer, lights,
  environment maps, built-in scenes.
* :mod:`torch_brdf.export`: materials and scenes out: Mitsuba 3 XML (stock plugins), glTF 2.0, MERL.
* :mod:`torch_brdf.records`: what producers save and consumers read (basis images, multibounce
  tensors, visibility, fits) with one codec, and the one checkpoint/tile cache.
* :mod:`torch_brdf.transport`: the reference path tracer and the precomputations (multibounce
  tensors, vertex visibility, Mitsuba comparisons).
* :mod:`torch_brdf.manifold`: the GPLVM manifold of measured BRDFs, its materials and evaluation.
* :mod:`torch_brdf.inverse`: paint strokes, transfer functions and constrained BRDF fits.
* :mod:`torch_brdf.denoise`: guide buffers and denoisers of precomputed basis images (a linear
  guide-only à-trous filter, Open Image Denoise) that keep every edit exact; OIDN per frame.
* :mod:`torch_brdf.planner`: error-budget planners (the cheapest settings for an error or a time).
* :mod:`torch_brdf.render`: modules that turn records plus coefficients into images
  (basis images, multibounce polynomials, all-frequency relighting, manifold blends).
* :mod:`torch_brdf.cli`: the ``torch-brdf`` command line.
* :mod:`torch_brdf.editor`: the interactive material editor in the browser (ipywidgets, Voilà).
* :mod:`torch_brdf.report`: the speed/accuracy report (every benchmark's trade on one page).
"""

from . import errors, parallel  # noqa: F401  (parallel sets OMP_WAIT_POLICY before torch loads; errors imports no torch)
from .errors import TorchBRDFError

__version__ = "0.3.0"
__all__ = ["TorchBRDFError", "__version__", "errors", "load_scene"]


def __getattr__(name: str):
    # load_scene at the top level without importing the scene layer (embree, trimesh) eagerly
    if name == "load_scene":
        from .scene import load_scene

        return load_scene
    raise AttributeError(f"module 'torch_brdf' has no attribute {name!r}")
