"""Processes and threads: how many, how they are started, and where tiles of work run.

* :mod:`~torch_brdf.parallel.threads`: usable cores (affinity and cgroup quota), worker and tile
  process counts (``TORCH_BRDF_WORKERS``), torch and BLAS thread limits (``TORCH_BRDF_THREADS``),
  thread counts measured per operation, and how workers are forked and set up.
* :mod:`~torch_brdf.parallel.tracepool`: the calling process plus forked children tracing the
  chunks of a ray batch from shared memory.
* :mod:`~torch_brdf.parallel.tiles`: the tile executor of the precomputations: tiles in this
  process, in forked processes or as Ray tasks, checkpointed and assembled in tile order.

Only :mod:`~torch_brdf.parallel.threads` is imported with the package (it sets
``OMP_WAIT_POLICY`` before torch loads and caps torch's threads once it has); the other two
are imported where they are used.
"""

from . import threads

__all__ = ["threads"]
