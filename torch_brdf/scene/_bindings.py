"""Every foreign-function signature of torch_brdf, declared once from a table.

torch_brdf calls C code through :mod:`ctypes` in two places: its compiled kernel (the C files
of ``transport/csrc``, built by :mod:`torch_brdf.transport._native`) and a few functions of the
embree library that embreex loaded (:mod:`torch_brdf.scene.embree`). Their signatures live
here and only here: :data:`KERNEL` maps each kernel entry point to ``(restype, argtypes)``,
:data:`EMBREE` does the same for embree, and :func:`declare` sets them on a loaded library.
``tests/transport/test_kernel_bindings.py`` fails on a ``.restype``/``.argtypes`` assignment or
a ``CFUNCTYPE`` prototype anywhere else in the package, and checks :data:`KERNEL` against the
prototypes of ``transport/csrc/kernel.h`` (names, argument counts and C types) and against the
symbols the built library exports.

The module sits in the scene layer, the lowest one that calls foreign code (scene's embree
check), so both the scene layer and the transport layer read it without an upward import.
What each kernel entry does, its pure-torch twin and its test: ``docs/kernel.md``.
"""

from __future__ import annotations

import ctypes
from typing import Any

__all__ = ["EMBREE", "KERNEL", "declare"]

P = ctypes.c_void_p  # any pointer: an array's data (ptr()), a handle, a function's address, or None
I64 = ctypes.c_int64
INT = ctypes.c_int  # C int (int32_t on every platform the kernel builds on)
F32 = ctypes.c_float
F64 = ctypes.c_double
I64_P = ctypes.POINTER(ctypes.c_int64)  # an int64_t the entry writes (ctypes.byref)

Signature = tuple[Any, list[Any]]

#: kernel entry point -> (restype, argtypes), file by file as ``kernel.h`` declares them
KERNEL: dict[str, Signature] = {
    # rng.c
    "tb_rand": (None, [P, I64, INT, P]),
    # reduce.c
    "tb_new": (P, [INT, INT, P]),
    "tb_free": (None, [P]),
    "tb_clear": (None, [P]),
    "tb_size": (I64, [P]),
    "tb_max_count": (INT, [P]),
    "tb_add_sums": (INT, [P, I64, P, P, P, P, P, P, P]),
    "tb_emit": (INT, [P, I64, I64, I64, P, P, P, P, P, P, P, P, P, P, P, I64, I64, P, P, INT, I64, P, P, INT]),
    "tb_reduce": (INT, [P, INT, P, P, I64_P]),
    "tb_reduce_into": (INT, [P, INT, P]),
    # blocks.c
    "tb_blocks": (I64, [I64, INT, P, P, P, P, I64, I64, P, P, P, P, P, P]),
    # tile.c
    "tb_tile_new": (P, [INT, P]),
    "tb_tile_free": (None, [P]),
    "tb_tile_add": (INT, [P, P]),
    "tb_tile_size": (I64, [P]),
    "tb_tile_max_count": (INT, [P]),
    "tb_tile_export": (I64, [P, INT, P, P]),
    "tb_tile_blocks": (I64, [P, P, I64, I64, P, P, P, P, P, P, P]),
    # lights.c
    "tb_area_points": (None, [I64, P, P, P, I64, P, P, P, P, P]),
    "tb_area_finish": (None, [I64, P, P, P, P, P, P, F32, P, P, P, P, P, P, P]),
    "tb_area_sample": (I64, [I64, P, P, I64, P, P, P, F32, P, P, P, F32, P, P, P, P, P, P, P]),
    "tb_wf_area_sample": (I64, [P, I64, P, I64, P, P, P, F32, P, P, P, F32, P, P, P, P, P, P, P]),
    # camera.c
    "tb_camera_local": (I64, [I64, P, P, I64, I64, P, F64, F64, P]),
    "tb_camera_finish": (None, [I64, P, P, P, P, P]),
    # vertex.c
    "tb_frame": (None, [I64, P, P, P, P, P]),
    "tb_unoccluded": (I64, [I64, P, P, P]),
    "tb_light_gather": (None, [I64, P, P, P, P, F32, P, P, P, P, P, P, P, P, P]),
    "tb_layers": (None, [I64, INT, I64, P, P, P, P, P, P, P, P]),
    "tb_sincos": (None, [I64, P, P, P]),
    "tb_mixture": (None, [I64, P, P, F32, F32, F32, F32, P, P, P, P]),
    "tb_advance": (I64, [I64, P, P, P, P, INT, P, P, INT, P, P, P, P, P, I64, P, I64, P, F32, P, P, P]),
    "tb_fixed_f": (None, [I64, P, P, P, P, P, P]),
    "tb_gather": (None, [I64, P, INT, P, P, P]),
    # wavefront.c
    "tb_wf_start": (I64, [I64, P, P, P, P, P, P, I64, I64, I64]),
    "tb_wf_compact": (I64, [I64, P, P, P, P, P, P, P, I64, I64, I64]),
    "tb_wf_light_hits": (I64, [I64, P, P, P, P, P, F32, P, P, P, P, INT, P, P, P, P, P, P, P, P, P]),
    # visibility.c
    "tb_vis_fans": (I64, [P, P, I64, P, P, I64, P, P, I64, F64, I64, P, P, P]),
    "tb_occluded_fans": (I64, [P, P, I64, P, P, P, P, P]),
    # rays.c
    "tb_trace_hits": (I64, [P, P, I64, P, P, P, P, P, P, P, P, P, P, P, P]),
    "tb_occluded_rays": (I64, [P, P, I64, P, P, I64, P, P, P]),
    "tb_intersect_only": (I64, [P, P, I64, P, P, P, P]),
    # relight.c
    "tb_phong_lobe": (None, [I64, P, F32, P]),
    "tb_relight": (INT, [I64, INT, P, P, P, P, P, P, P, P, F32, F32, P, P, P, P, F32, P, P, P, P, P, P, P]),
}

#: embree functions called directly (scene/embree.py embree_entry) -> (restype, argtypes)
EMBREE: dict[str, Signature] = {
    "rtcGetSceneDevice": (P, [P]),  # RTCDevice rtcGetSceneDevice(RTCScene): takes a reference
    "rtcReleaseDevice": (None, [P]),
}


def declare(lib: ctypes.CDLL, table: dict[str, Signature]) -> ctypes.CDLL:
    """Set the signature of every function of ``table`` on ``lib`` (loaded with
    :class:`ctypes.CDLL`) and return ``lib``.

    Raises:
        AttributeError: ``lib`` lacks a function of ``table`` (a kernel built from other sources).
    """
    for name, (restype, argtypes) in table.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, list(argtypes)
    return lib
