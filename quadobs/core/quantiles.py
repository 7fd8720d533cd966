"""Quantiles and distribution functions of the laws the gates and tests use.

The filters' gates and the self-calibration's tests need a few functions of five laws: the
chi-square's quantile, upper quantile and distribution function, the normal's, Student's t
and Fisher's F quantiles, and the binomial tail of the sign test. ``scipy.stats`` gives them, but
importing it costs about a second per process (it loads every distribution and test of the
package), and every replay, run and campaign worker would pay it before its first step.
These are the special functions ``scipy.stats`` itself evaluates for these laws
(``scipy.special``: the regularised incomplete gamma function's inverses, the normal's,
Student's t and Fisher's F inverse distribution functions, the incomplete beta function),
so the values are the same floats; ``tests/core/test_quantiles.py`` checks them against
``scipy.stats``:

.. math::

    F_{\\chi^2_k}(x) = P(k/2, x/2), \\qquad
    F^{-1}_{\\chi^2_k}(q) = 2 P^{-1}(k/2, q), \\qquad
    \\bar F^{-1}_{\\chi^2_k}(q) = 2 Q^{-1}(k/2, q), \\qquad
    \\Phi^{-1}(q) = \\sqrt{2}\\, \\mathrm{erf}^{-1}(2q - 1) \\;(\\texttt{ndtri}),

``P`` and ``Q = 1 - P`` the regularised lower and upper incomplete gamma functions
(Abramowitz and Stegun, eq. 26.4.19). They are meant for probabilities inside ``(0, 1)``,
positive degrees of freedom and ``x >= 0``, as the callers pass them: ``scipy.stats`` also
checks its arguments and handles the ends (``q = 0`` or ``1``) itself, which these do not.
"""

from __future__ import annotations

from scipy import special

__all__ = [
    "binomial_upper_tail",
    "chi2_cdf",
    "chi2_isf",
    "chi2_ppf",
    "fisher_ppf",
    "norm_ppf",
    "student_t_ppf",
]


def binomial_upper_tail(k: int, n: int) -> float:
    """``P(X >= k)`` for ``X ~ Binomial(n, 1/2)`` (the one-sided p-value of the sign test of
    ``k`` successes in ``n``): the regularised incomplete beta function
    ``I_{1/2}(k, n - k + 1)`` (Abramowitz and Stegun, eq. 26.5.24), in constant time for any
    ``n``."""
    k, n = int(k), int(n)
    if k <= 0:
        return 1.0
    if k > n:
        return 0.0
    return float(special.betainc(k, n - k + 1, 0.5))


def chi2_cdf(x: float, dof: float) -> float:
    """``P(chi^2(dof) <= x)``."""
    return float(special.chdtr(dof, x))


def chi2_ppf(q: float, dof: float) -> float:
    """The ``q`` quantile of ``chi^2(dof)``: the ``x`` with ``P(chi^2(dof) <= x) = q``."""
    return float(2.0 * special.gammaincinv(0.5 * dof, q))


def chi2_isf(q: float, dof: float) -> float:
    """The upper ``q`` quantile of ``chi^2(dof)``: the ``x`` with ``P(chi^2(dof) > x) = q``,
    accurate where ``q`` is small (no ``1 - q`` formed)."""
    return float(special.chdtri(dof, q))


def norm_ppf(q: float) -> float:
    """The ``q`` quantile of the standard normal law."""
    return float(special.ndtri(q))


def student_t_ppf(q: float, dof: float) -> float:
    """The ``q`` quantile of Student's t law with ``dof`` degrees of freedom."""
    return float(special.stdtrit(dof, q))


def fisher_ppf(q: float, dfn: float, dfd: float) -> float:
    """The ``q`` quantile of Fisher's ``F(dfn, dfd)`` law."""
    return float(special.fdtri(dfn, dfd, q))
