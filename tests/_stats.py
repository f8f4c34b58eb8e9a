"""The one chi-square test of the suite (Mitsuba 3's ``chi2.py``), used by every sampler test.

Cells whose expected count is below :data:`CHI2_MIN_EXPECTED` are pooled, in increasing
order of expectation, until the pool expects at least that many; a cell expecting nothing
must receive (almost) nothing. The test rejects at one family-wise significance,
:data:`CHI2_SIGNIFICANCE`, with the Šidák correction for a suite of ``family_size`` tests,
so every sampler test uses the same threshold. Seeded tests make the outcome deterministic.
"""

from __future__ import annotations

import torch
from scipy.stats import chi2 as chi2_dist

CHI2_SIGNIFICANCE = 0.01  # family-wise, before the Šidák correction
CHI2_MIN_EXPECTED = 5.0  # Mitsuba's min_exp_frequency
ZERO_CELL_FRACTION = 1e-5  # samples allowed in a cell of expectation 0, as a fraction of n


def chi2_pvalue(observed: torch.Tensor, expected: torch.Tensor, n: int | None = None) -> float:
    """Pearson chi-square p-value of counts against expected counts, with Mitsuba's pooling.

    Args:
        observed: (K,) counts per cell (any shape; flattened).
        expected: (K,) expected counts per cell.
        n: the number of samples (default: the observed total).
    Returns:
        The p-value. Fails if a cell with zero expectation received more than
        ``ZERO_CELL_FRACTION * n`` samples.
    """
    obs = observed.double().reshape(-1)
    exp = expected.double().reshape(-1).clamp_min(0)
    n = float(obs.sum()) if n is None else n
    stat, dof, pooled_o, pooled_e = 0.0, 0, 0.0, 0.0
    for i in torch.argsort(exp).tolist():
        o, e = float(obs[i]), float(exp[i])
        if e == 0.0:
            assert o <= ZERO_CELL_FRACTION * n, f"{o} samples in a cell whose expected count is 0"
        elif e < CHI2_MIN_EXPECTED or 0 < pooled_e < CHI2_MIN_EXPECTED:
            pooled_o += o
            pooled_e += e
        else:
            stat += (o - e) ** 2 / e
            dof += 1
    if pooled_e > 0:
        stat += (pooled_o - pooled_e) ** 2 / pooled_e
        dof += 1
    return float(chi2_dist.sf(stat, max(dof - 1, 1)))


def chi2_threshold(family_size: int = 1) -> float:
    """The p-value below which a test of a suite of ``family_size`` tests fails (Šidák)."""
    return 1 - (1 - CHI2_SIGNIFICANCE) ** (1 / max(family_size, 1))


def assert_chi2(
    observed: torch.Tensor, expected: torch.Tensor, n: int | None = None, family_size: int = 1, what: str = ""
) -> float:
    """Assert that the counts pass the chi-square test (see :func:`chi2_pvalue`); returns the p-value."""
    p_value, alpha = chi2_pvalue(observed, expected, n), chi2_threshold(family_size)
    assert p_value > alpha, f"{what}chi-square p-value {p_value:.3g} <= {alpha:.3g}"
    return p_value
