r"""Editable 1-D factorised BRDFs on box bands (Ben-Artzi et al. 2008, Appendix A).

A factored BRDF is a fixed *quotient* times an editable 1-D curve (Eq. 30):

.. math::
    \rho(\omega_i, \omega_o) = \rho_q(\omega_i, \omega_o)\, f(\gamma), \qquad
    f(\gamma) = \sum_{j=1}^{J} c_j\, b_j(\gamma(\omega_i, \omega_o)),

with :math:`b_j` the indicator ("box") of band :math:`j` of a 1-D parameterisation
:math:`\gamma` of the 4-D domain and :math:`c` an RGB ``(J, 3)`` tensor.

Parameterisations (:class:`BandBasis` ``variable``):

* ``"theta_h"``, ``"theta_d"``: Rusinkiewicz half / difference angles in :math:`[0, \pi/2]`;
  both are symmetric in :math:`(\omega_i, \omega_o)`, so the BRDF is reciprocal whenever
  the quotient is.
* ``"theta_i"``, ``"theta_o"``: polar angle of one direction. A factor of :math:`\theta_i`
  alone is *not* reciprocal; the paper (Appendix A) lists these parameterisations for a
  fixed view and does not discuss reciprocity. With ``symmetric=True`` (the default) we use
  the symmetrised basis :math:`b_j = \tfrac12(\mathbb 1_j(\theta_i) + \mathbb 1_j(\theta_o))`,
  still linear in :math:`c` and reciprocal by construction (then ``theta_i`` and
  ``theta_o`` coincide). ``symmetric=False`` gives the literal, one-sided factor.
* ``"anisotropy_ratio"``: :math:`\gamma_r = (\cos\theta_h)^{n_u \sin^2\phi_h}\in[0, 1]`, the
  Ashikhmin-Shirley anisotropy-ratio factor of Eq. 33-35 (read with the squares of the AS
  model, :math:`n_u\cos^2\phi_h + n_v\sin^2\phi_h`, which the printed equations drop). With
  the quotient :class:`AnisotropicLobe` the AS specular lobe is
  :math:`\rho_{qu}\,\gamma_r^{\,r}`, :math:`r = n_v/n_u`, so editing :math:`f(\gamma_r)`
  edits the elongation ratio at fixed width :math:`n_u`.

Quotients (:func:`make_quotient`; all non-negative and reciprocal). The paper puts
"normalization constants and the GAF" into :math:`\rho_q` but names no quotient per model;
we use:

* ``"one"``: :math:`1`. Blinn-Phong (:class:`~torch_brdf.brdf.analytic.BlinnPhong`,
  :math:`k_d/\pi + k_s\frac{n+2}{8\pi}\cos^n\theta_h`) is exactly a function of
  :math:`\theta_h`, so its normalisation and diffuse offset live in :math:`c` and only the
  banding error remains.
* ``"distribution"``: :math:`1/(\cos\theta_i + \cos\theta_o - \cos\theta_i\cos\theta_o)`,
  Ashikhmin's distribution-based BRDF (Iwasaki et al. Eq. 11 without Fresnel): :math:`f` is
  then the half-vector distribution :math:`p(h)`.
* ``"microfacet"``: :math:`1/(4\cos\theta_i\cos\theta_o)`: :math:`f` is :math:`D(h)`.
* ``"cook_torrance"``: :math:`G_{TS}/(4\cos\theta_i\cos\theta_o)` with the parameter-free
  V-groove GAF of Cook and Torrance, :math:`G_{TS} = \min(1, 2\cos\theta_h\cos\theta_o/
  \cos\theta_d, 2\cos\theta_h\cos\theta_i/\cos\theta_d)`.
* ``"ashikhmin_shirley"``: :math:`1/(\cos\theta_d\max(\cos\theta_i, \cos\theta_o))` (AS 2000,
  their :math:`(h\cdot k)\max(n\cdot k_1, n\cdot k_2)`).

Parameterised: :class:`SmithQuotient` (the Smith :math:`G_1G_1/(4\cos\cos)` of a
Cook-Torrance BRDF of known roughness). Wrappers: :class:`SchlickFresnel` -- the Fresnel
two-layer form of Eq. 31-32: the second layer's quotient
:math:`\rho_{q2} = (1-\cos\theta_d)^5\rho_q` (``f0=None``), or the full Schlick factor
:math:`F_0 + (1 - F_0)(1-\cos\theta_d)^5` for a known RGB :math:`F_0`
(:class:`FresnelFactored1D` sums the two layers); :class:`AnisotropicLobe` -- Eq. 35's
:math:`\rho_{qu} = \rho_q(\cos\theta_h)^{n_u\cos^2\phi_h}`.

Projection (:func:`project`) is cosine-weighted least squares over all pairs
:math:`(\omega_i, \omega_o)` with the weight :math:`\cos\theta_i\cos\theta_o\,d\omega_i
d\omega_o` (the measure of Appendix B's Eq. 36), by a dense deterministic quadrature in
Rusinkiewicz coordinates (:class:`PairQuadrature`), in float64. Coarsening merges adjacent
bands with the equivalent-albedo weights :math:`e_j` of :mod:`.albedo`, which
keeps the equivalent albedo :math:`d = \frac1\pi\sum_j c_j e_j` of every level identical
(see :meth:`Factored1D.coarsen`).

Accuracy of box bands (cosine-weighted relative L2 error, quotient ``"one"``, a pure
Blinn-Phong lobe :math:`k_d = 0, k_s = 1`): the error of a piecewise-constant fit is about
band width x slope / :math:`\sqrt{12}`, so it halves with every doubling of J. At J = 64 MERL's
``"sqrt"`` spacing gives 2.1% / 4.1% / 7.3% for n = 10 / 100 / 1000; ``"log:0.02"`` 2.5% /
3.1% / 4.0%; ``"lobe:100"`` (bands adapted to n = 100) 6.4% / 1.4% / 7.8%. No fixed spacing
reaches 2% at J = 64 for all three; J = 128 with ``"sqrt"`` gives 1.1% / 2.0% / 3.7%.

The package, one module per job (imports run down this list only):

* :mod:`._geometry`: half vector / difference angle (from :mod:`torch_brdf.frame`), the
  anisotropy-ratio factor;
* :mod:`.quotients`: :class:`Quotient` and the named and parameterised quotients;
* :mod:`.basis`: :func:`band_edges`, :class:`BandBasis`;
* :mod:`.albedo`: the equivalent albedo :math:`e_j` of Appendix B and its disk cache
  (:func:`band_albedos`, :func:`equivalent_albedo`);
* :mod:`.projection`: :class:`PairQuadrature`, :func:`project`, :class:`Projector`, :func:`projection_error`;
* :mod:`.factored`: :class:`Factored1D`, :class:`FresnelFactored1D`, coarsening.
"""

from ._geometry import HALF_PI, anisotropy_ratio, half_and_diff
from .albedo import EquivalentAlbedoCacheWarning, band_albedos, cache_dir, equivalent_albedo
from .basis import VARIABLES, BandBasis, band_edges
from .factored import Factored1D, FresnelFactored1D, coarsen_coefficients
from .projection import PairQuadrature, Projector, project, projection_error
from .quotients import AnisotropicLobe, Quotient, SchlickFresnel, SmithQuotient, make_quotient

__all__ = [
    "HALF_PI",
    "VARIABLES",
    "AnisotropicLobe",
    "BandBasis",
    "EquivalentAlbedoCacheWarning",
    "Factored1D",
    "FresnelFactored1D",
    "PairQuadrature",
    "Projector",
    "Quotient",
    "SchlickFresnel",
    "SmithQuotient",
    "anisotropy_ratio",
    "band_albedos",
    "band_edges",
    "cache_dir",
    "coarsen_coefficients",
    "equivalent_albedo",
    "half_and_diff",
    "make_quotient",
    "project",
    "projection_error",
]
