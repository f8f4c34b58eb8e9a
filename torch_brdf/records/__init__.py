"""Records: what the precomputations save and the renderers read, with one codec and one cache.

The floor between the producers (:mod:`torch_brdf.transport`, :mod:`torch_brdf.manifold`,
:mod:`torch_brdf.inverse`) and the consumers (:mod:`torch_brdf.render`):

- :class:`BasisImage`: an image linear in basis coefficients ("pixels x basis x channels"),
  shared by the first-order multibounce term, the inverse-design transfer functions and the
  manifold's per-material images;
- :class:`PolynomialTensors` (with :class:`Series`, :class:`ObjectBasis`, :class:`TermTable`,
  :class:`TensorBlock`): the multibounce tensors;
- :class:`VertexVisibility`, :class:`BlockVisibility` and :class:`PackedBlockVisibility` (the
  file's varint stream kept as it is): per-vertex differential visibility;
- :class:`GuideBuffers`: a view's denoiser guides, saved with the multibounce tensors;
- :class:`GPLVMFit`: a fitted BRDF manifold; :class:`FitResult`: an inverse-design SRBF fit.

Every record derives from :class:`Record` (``kind``, ``version``, ``to_arrays``/``from_arrays``;
``save``/``load`` are atomic, checksummed, pickle-free and refuse corrupt files with
:class:`~torch_brdf.errors.FileFormatError`). :class:`Checkpoint` and :class:`TileCache` are
the one checkpoint / resume mechanism of every precomputation.
"""

from .basis_image import BasisImage, float16_error
from .cache import (
    ArraySpec,
    CacheSchema,
    Checkpoint,
    CorruptCacheWarning,
    MetaSpec,
    TileCache,
    remove_cache,
    settings_key,
)
from .codec import Member, Record, check_schema, load_record, save_record
from .fits import FitResult, GPLVMFit
from .guides import GuideBuffers
from .polynomial import ObjectBasis, PolynomialTensors, Series, TensorBlock, TermTable
from .visibility import SceneVertices, VertexVisibility, scene_vertices
from .visibility_codec import BlockVisibility, PackedBlockVisibility

__all__ = [
    "ArraySpec",
    "BasisImage",
    "BlockVisibility",
    "CacheSchema",
    "Checkpoint",
    "CorruptCacheWarning",
    "FitResult",
    "GPLVMFit",
    "GuideBuffers",
    "Member",
    "MetaSpec",
    "ObjectBasis",
    "PackedBlockVisibility",
    "PolynomialTensors",
    "Record",
    "SceneVertices",
    "Series",
    "TensorBlock",
    "TermTable",
    "TileCache",
    "VertexVisibility",
    "check_schema",
    "float16_error",
    "load_record",
    "remove_cache",
    "save_record",
    "scene_vertices",
    "settings_key",
]
