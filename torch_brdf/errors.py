"""One exception hierarchy for bad input.

Every error that torch_brdf raises because of what it was given derives from
:class:`TorchBRDFError`, so callers can catch the package's complaints in one place
and still tell them apart. Messages name the offending thing (file, argument, object)
and say what was expected and what came.
"""

from __future__ import annotations


class TorchBRDFError(Exception):
    """Base class of every bad-input error raised by torch_brdf."""


class ShapeError(TorchBRDFError, ValueError):
    """A tensor has the wrong shape or dtype for a public entry point."""


class ValueRangeError(TorchBRDFError, ValueError):
    """A value is NaN/Inf, negative where it must not be, or outside its range."""


class FileFormatError(TorchBRDFError, ValueError):
    """A file is missing, truncated, corrupt, or not in the expected layout."""


class MeshError(TorchBRDFError, ValueError):
    """A mesh is unusable: NaN vertices, no faces, or only degenerate faces."""


class SceneError(TorchBRDFError, ValueError):
    """A scene description is inconsistent (unknown material, duplicate name, ...)."""


class CameraError(TorchBRDFError, ValueError):
    """A camera is degenerate (parallel up/forward, zero field of view, ...)."""


class DataNotFoundError(TorchBRDFError, FileNotFoundError):
    """Optional shared data (meshes, env maps, MERL) is not where it was looked for."""


class WriteError(TorchBRDFError, OSError):
    """A file could not be written (disk full, read-only file system, permission denied): an
    :class:`OSError` with the ``errno`` of the cause and ``filename`` the file that was being
    written, whose message names it."""


class NumericalError(TorchBRDFError, ArithmeticError):
    """A computation cannot be carried out stably (e.g. a Cholesky factorisation still fails
    at the largest allowed jitter); the message names the quantity and the limit reached."""


class InfeasibleError(TorchBRDFError, ValueError):
    """Constraints admit no solution (e.g. energy conservation with diffuse albedo >= 1)."""


class ExportError(TorchBRDFError, ValueError):
    """A material cannot be exported as asked: an unknown object, an unwritable path, or a
    fit of a stock model whose error exceeds the tolerance the user set."""
