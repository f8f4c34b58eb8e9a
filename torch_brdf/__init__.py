"""torch_brdf: design BRDFs in their final scene, in PyTorch on the CPU.

Subpackages and modules, lowest layer first (a module imports only its own layer or a lower
one; ``tests/test_layers.py`` keeps it so):

* :mod:`torch_brdf.errors`: the exception hierarchy (``TorchBRDFError`` and its subclasses).
* :mod:`torch_brdf.data`: where the optional shared data folder lives.
* :mod:`torch_brdf.io`: EXR / PNG images, the versioned checksummed array files, MERL files.
* :mod:`torch_brdf.sphere`: sampling warps and pdfs, lat-long maps, cubemap blocks, DCT, Haar.
* :mod:`torch_brdf.frame`: local shading frames, half/difference angles.
* :mod:`torch_brdf.metrics`: image and BRDF error metrics (relative RMSE, PSNR, HDR-FLIP, log-RMSE ...).
* :mod:`torch_brdf.linalg`: dense linear algebra shared by the package (the Cholesky with jitter).
* :mod:`torch_brdf.brdf`: the BRDF base class, analytic, microfacet, measured and SRBF models,
  1-D band bases.
* :mod:`torch_brdf.scene`: meshes, embree ray tracing, camera and its G-buffer, lights,
  environment maps, built-in scenes.
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
"""

import importlib
import importlib.util
import os
import sys

from . import errors
from .errors import TorchBRDFError

#: torch was imported before torch_brdf (then OMP_WAIT_POLICY set here cannot take effect)
_TORCH_FIRST = "torch" in sys.modules
if not _TORCH_FIRST:  # libgomp reads it when torch loads it: only effective before that
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


class _AfterTorch:
    """A meta-path finder that runs :mod:`torch_brdf._threads` (thread caps) right after torch
    loads, so that ``import torch_brdf`` itself stays free of torch: ``torch-brdf --help`` and
    ``python trainers/X.py --help`` answer without the seconds torch takes to import."""

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec("torch")
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            del spec.loader.exec_module  # back to the loader's own method
            importlib.import_module(f"{__name__}._threads")

        spec.loader.exec_module = exec_module
        return spec

    def invalidate_caches(self):
        pass


if _TORCH_FIRST:
    from . import _threads  # noqa: F401
elif not any(isinstance(f, _AfterTorch) for f in sys.meta_path):
    sys.meta_path.insert(0, _AfterTorch())

__version__ = "0.1.0"
__all__ = ["TorchBRDFError", "__version__", "errors"]
