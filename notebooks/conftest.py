"""pytest (``--nbmake``) runs the notebooks small: ``TORCH_BRDF_NB_SMALL=1`` unless already set.

Each notebook reads it for its sizes, so a reader gets the nice defaults (bigger images, more
samples) and CI the quick ones; the kernels nbmake starts inherit this process's environment.
"""

import os

os.environ.setdefault("TORCH_BRDF_NB_SMALL", "1")
