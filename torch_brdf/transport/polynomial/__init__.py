r"""Monte Carlo precomputation of the multibounce polynomial tensors (Ben-Artzi et al. 2008).

With interreflections the image is a polynomial in the scene's BRDF coefficients
(Sec. 3, Eq. 14-16): bounce :math:`N` is a degree-:math:`N` polynomial. With a *BRDF series*
:math:`(J_N, \dots, J_1)` (Sec. 4.1, Eq. 17-19) the eye vertex uses the object's full band
basis, an optional low-frequency second bounce uses a coarsened basis (Sec. 4.3), and all
later vertices use the diffuse equivalent :math:`d_m` of each object (Sec. 4.2, App. B). The
pixel value is then (Eq. 26, Eq. 29)

.. math::
    B(x) = E(x) + \sum_{N=1}^{\bar N}\sum_j\sum_t T^N_{jt}(x)\, c_j\, \hat c_{w_t}\,\bar d_{z_t},

where a *term* :math:`t` is a pair (second-bounce coefficient slot :math:`w_t`, or none;
multiset :math:`z_t` of the objects of the diffuse-equivalent vertices) and
:math:`\bar d_z = \prod_{m\in z} d_m` (Eq. 25). Symmetry (Sec. 4): with diffuse equivalents
the order of the later vertices does not matter, so a term holds a *multiset*, stored as a
count per object.

Estimator (Sec. 5.1). A batched (wavefront) path tracer from the eye on embree:

* directions are sampled independently of the final BRDF, from a mixture of a cosine lobe
  (70%) and a Blinn lobe of exponent 200 about the mirror direction (30%) (:class:`Mixture`);
  opt-in, :class:`LobeMixture` samples glossy objects from several lobe widths and combines
  next-event estimation at their eye vertex with its samples by MIS (edits sharper than the
  material; the weights depend on pdfs only, so the polynomial stays exact);
* next-event estimation at every vertex to every light of the scene (area lights, the
  environment, directional lights; or the environment's median-cut point lights,
  ``env_point_lights=K``, as the seed does);
* each light sample at vertex :math:`N` of a path adds its weight to exactly one entry per
  basis layer: the band :math:`j` of :math:`(\omega_i, \omega_o)` at the eye vertex (Eq. 22),
  the second-bounce slot :math:`w` for a low-frequency second bounce, and the multiset of the
  objects of vertices :math:`3..N` (or :math:`2..N`). Editable objects contribute their
  quotient :math:`\rho_q` and band indicator at banded vertices and :math:`\cos/\pi` at
  diffuse-equivalent vertices (Eq. 23-24); *fixed* objects (``SceneObject.editable`` False)
  contribute their full BRDF :math:`f\cos` and no index (Sec. 5.3);
* emission seen directly from the eye is the constant term :math:`E`; emission reached by a
  continuation ray is not counted (NEE covers it), as in
  :func:`torch_brdf.transport.pathtrace.path_trace`, so a scene of Lambertian objects
  evaluated at their albedos estimates the same image.

Bookkeeping. Per pass group, entries are reduced to per-path sums (so the per-entry Monte
Carlo variance is the variance over paths, not over light samples); sums and sums of squares
accumulate per tile; a tile's entries become one block per (eye object, bounce) that numbers
the terms and pixels occurring in that tile and stores only the entries that occur, sparse
(:class:`TensorBlock`). A pixel whose jittered samples see two objects has a record under each.

Layout: :mod:`.bases` (the series and each object's basis), :mod:`.settings` (what decides a
run: :class:`PolynomialSettings`), :mod:`.sampler` (the direction mixture), :mod:`.tracer`
(the symbolic path tracer), :mod:`.reduce` (entries to sparse blocks) and :mod:`.driver`
(:func:`precompute_polynomial`); the record itself is
:class:`~torch_brdf.records.polynomial.PolynomialTensors`.

Reproducibility. Tile ``k`` with pass group ``g`` draws from its own generator seeded by
``(seed, k, g)``; each finished tile is written atomically to the checkpoint folder, so an
interrupted run resumes at the first unfinished tile and the result equals an uninterrupted
run bit for bit (at most one tile of work is lost).
"""

from ...records.polynomial import PolynomialTensors, TensorBlock, TermTable
from ...scene.lights import PointLights
from .bases import ObjectBasis, Series, plan_bases, with_fixed
from .driver import precompute_polynomial, spp_map_of
from .sampler import EyeStrata, LobeMixture, Mixture
from .settings import PolynomialSettings

__all__ = [
    "EyeStrata",
    "LobeMixture",
    "Mixture",
    "ObjectBasis",
    "PointLights",
    "PolynomialSettings",
    "PolynomialTensors",
    "Series",
    "TensorBlock",
    "TermTable",
    "plan_bases",
    "precompute_polynomial",
    "spp_map_of",
    "with_fixed",
]
