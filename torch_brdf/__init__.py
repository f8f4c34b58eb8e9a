"""torch_brdf: design BRDFs in their final scene, in PyTorch on the CPU.

Subpackages: :mod:`torch_brdf.scene` (meshes, embree ray tracing, camera, lights,
built-in scenes), :mod:`torch_brdf.io` (EXR/PNG, versioned array files),
:mod:`torch_brdf.sphere` (warps, lat-long maps), :mod:`torch_brdf.transport`
(path tracing), :mod:`torch_brdf.errors` (the exception hierarchy).
"""

from . import _threads, errors  # noqa: F401  (_threads first: sets OMP_WAIT_POLICY before torch loads)
from .errors import TorchBRDFError

__version__ = "0.1.0"
__all__ = ["TorchBRDFError", "__version__", "errors"]
