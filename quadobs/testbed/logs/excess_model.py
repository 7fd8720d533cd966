"""The ranges' non-line-of-sight excess, estimated from a log that does not state it.

The replay's range-bias filters weigh a range by the radio's excess model where it is known
(:class:`~quadobs.estimators.robust.ExcessMixture`: each range corrected by its expected
excess), else by a one-sided gate that leaves a long range out
(:class:`~quadobs.estimators.robust.SkewedGate`). A real log seldom states its radio's excess,
but its ranges show it: the self-calibration's prequential residuals
(:func:`~quadobs.testbed.logs.calibration.prediction_residuals`, each range against the EKF's
prediction before it corrects with it; the truth is never read) spread around each anchor's
centre by the line-of-sight noise and the prediction's error, and a blocked path adds a
positive excess.

The model. Residual ``i`` of anchor ``h`` is

.. math::

    r_i = \\mu_h + \\varepsilon_i + \\delta_i e_i, \\qquad
    \\varepsilon_i \\sim \\mathcal N(0, \\sigma^2), \\quad
    \\delta_i \\sim \\mathrm{Bernoulli}(\\pi), \\quad
    \\log e_i \\sim \\mathcal N(\\log e_{50}, s^2),

a Gaussian and a Gaussian shifted by a log-normal excess, the latter's median ``e_50`` and
shape ``s`` those of :class:`~quadobs.estimators.robust.ExcessMixture`. ``log e`` is discretised
on :data:`GRID` (``u_k``, evenly spaced: the log-normal's weights are then those of a
Gaussian on ``u``), and the expectation-maximisation of the mixture runs
:data:`ITERATIONS` times (a fixed count: the same data, the same figures) from a start read
off the residuals (each anchor's median, the pooled median absolute deviation, ``pi = 0.2``,
``e_50 = 3 sigma``, ``s = 0.5``). With the responsibilities ``gamma_i0`` (line of sight) and
``gamma_ik`` (excess ``e_k``) of the E-step, the M-step is closed:

.. math::

    \\pi = \\overline{1 - \\gamma_{i0}}, \\quad
    \\log e_{50} = \\frac{\\sum_{ik} \\gamma_{ik} u_k}{\\sum_{ik} \\gamma_{ik}}, \\quad
    s^2 = \\frac{\\sum_{ik} \\gamma_{ik} (u_k - \\log e_{50})^2}{\\sum_{ik} \\gamma_{ik}}, \\quad
    \\mu_h = \\overline{r_i - \\textstyle\\sum_k \\gamma_{ik} e_k}\\big|_h, \\quad
    \\sigma^2 = \\overline{\\textstyle\\sum_k \\gamma_{ik} (r_i - \\mu_h - e_k)^2}

(``e_0 = 0``; ``s`` kept at least the grid's spacing).

When the data identify it. Any heavy tail fits a mixture better than one Gaussian, the
prediction's own error included, so the likelihood alone cannot tell. What tells an excess
from a heavy-tailed error is its sign: beyond :data:`TAIL` fitted standard deviations of the
line-of-sight core, an error of either sign is as often below the centre as above it, an
excess only above. The excess is taken (:func:`excess_model`) only where

* the ranges' line-of-sight noise is known (stated by ``ranges.csv`` or estimated from the
  ranges, :mod:`~quadobs.testbed.logs.range_noise`): where the ranges do not show their own
  noise (a log whose ranges to one anchor come half a second to a second apart, Plaza's), the residuals are the prediction's
  error more than the radio's, and the gate stays (the noise's value only gates: the tails
  are counted in the fitted core's ``sigma``, which holds the prediction's error as well, and
  is not compared with it);
* the residuals beyond ``TAIL sigma`` (the fitted core's) above each anchor's median residual
  outnumber those below it beyond chance (the median, not the fitted ``mu_h``: the fit's
  centres sit below a symmetric tail's centre wherever it puts excess on the upper half, and
  counted about them a symmetric tail looks one-sided):
  the one-sided binomial test of ``U`` above among ``U + L`` at the level
  :data:`SIGNIFICANCE`, and at least :data:`MIN_TAIL` of them above (the log-normal's two
  parameters are then fitted to no fewer: the median's relative standard error
  ``1.25 s / sqrt(n)`` is 17 % at ``s = 0.6``);
* the fitted excess is resolved from the noise (``e_50 >= sigma``) and not everywhere
  (``pi <= 0.9``).

Else the filters keep the one-sided gate: a default that cannot be estimated stays as it was.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadobs.core.quantiles import binomial_upper_tail

__all__ = [
    "EXCESS_KEYS",
    "GRID",
    "ITERATIONS",
    "MIN_TAIL",
    "SIGNIFICANCE",
    "TAIL",
    "ExcessFit",
    "calibrated_excess",
    "excess_model",
    "excess_nll",
    "fit_excess",
    "known_noise",
    "tail_signs",
]

#: The setup options that state the excess (:class:`~quadobs.testbed.logs.estimators.ReplaySetup`).
EXCESS_KEYS = ("nlos_median", "nlos_shape")
#: The log-excess grid ``u_k = log e_k`` (e from 1 cm to 100 m, 0.08 apart in ``log e``: a
#: tenth of the smallest shape a radio is likely to state).
GRID = np.linspace(math.log(1e-2), math.log(1e2), 120)
#: The expectation-maximisation's iterations (a fixed count).
ITERATIONS = 100
#: The tail, in standard deviations of the line-of-sight core, whose sign is counted.
TAIL = 3.0
#: The level of the one-sided binomial test of the tails' signs.
SIGNIFICANCE = 1e-3
#: The fewest residuals in the upper tail for an excess to be estimated.
MIN_TAIL = 20


@dataclass(frozen=True)
class ExcessFit:
    """The fitted mixture (module docstring) and whether the residuals identify it.

    Attributes
    ----------
    median, shape : float
        The excess's log-normal median ``e_50`` (m) and shape ``s``.
    fraction : float
        ``pi``: the fraction of residuals with an excess.
    sigma : float
        The line-of-sight core's standard deviation (m).
    centres : ndarray (q,)
        Each anchor's centre ``mu_h`` (m; NaN where it has no residual).
    upper, lower : int
        Residuals beyond ``TAIL sigma`` above and below each anchor's median residual (a
        centre that does not depend on the fit; :func:`tail_signs`).
    p_value : float
        The one-sided binomial test's probability of ``upper`` or more among ``upper + lower``.
    n : int
        The residuals fitted.
    """

    median: float
    shape: float
    fraction: float
    sigma: float
    centres: np.ndarray
    upper: int
    lower: int
    p_value: float
    n: int

    def summary(self) -> dict:
        """As plain data."""
        return {
            "median": self.median,
            "shape": self.shape,
            "fraction": self.fraction,
            "sigma": self.sigma,
            "upper_tail": self.upper,
            "lower_tail": self.lower,
            "p_value": self.p_value,
            "residuals": self.n,
        }


def _responsibilities(d: np.ndarray, sigma: float, pi: float, log_w: np.ndarray) -> np.ndarray:
    """``gamma (n, 1 + K)``: each residual's posterior over line of sight and the excesses
    ``e_k``, given ``d = r - mu_h``."""
    ll = np.empty((d.size, 1 + GRID.size))
    ll[:, 0] = d
    np.subtract(d[:, None], np.exp(GRID)[None, :], out=ll[:, 1:])
    ll *= ll
    ll *= -0.5 / sigma**2
    ll[:, 0] += math.log1p(-pi)
    ll[:, 1:] += math.log(pi) + log_w
    ll -= ll.max(axis=1, keepdims=True)
    np.exp(ll, out=ll)
    ll /= ll.sum(axis=1, keepdims=True)
    return ll


def fit_excess(
    r: np.ndarray,
    h: np.ndarray,
    q: int,
    iterations: int = ITERATIONS,
    sigma: float | None = None,
) -> ExcessFit:
    """The mixture of the module docstring fitted to the residuals ``r (n,)`` of the anchors
    ``h (n,)`` (``q`` anchors; non-finite residuals left out) by ``iterations`` steps of
    expectation-maximisation; ``sigma`` (m): the line-of-sight core's standard deviation held
    at that value instead of fitted (a study, ``sims/check_excess.py --diagnose``: the replay
    fits it, as the core must hold the prediction's error, ``docs/error-sources.md``)."""
    keep = np.isfinite(r)
    r, h = np.asarray(r, dtype=float)[keep], np.asarray(h)[keep]
    counts = np.bincount(h, minlength=q).astype(float)
    median = np.array([np.median(r[h == j]) if counts[j] else np.nan for j in range(q)])
    mu = median.copy()
    held = sigma is not None
    core = float(sigma) if sigma is not None else 1.4826 * float(np.median(np.abs(r - mu[h])))
    core = max(core, 1e-6)
    pi, m, s = 0.2, math.log(3.0 * core), 0.5
    e, du = np.exp(GRID), float(GRID[1] - GRID[0])
    for _ in range(int(iterations)):
        log_w = -0.5 * ((GRID - m) / s) ** 2
        log_w -= math.log(np.exp(log_w - log_w.max()).sum()) + log_w.max()
        g = _responsibilities(r - mu[h], core, pi, log_w)
        gx = g[:, 1:]
        mass = float(gx.sum())
        pi = min(max(mass / r.size, 1e-6), 1.0 - 1e-6)
        if mass > 0.0:
            m = float((gx @ GRID).sum() / mass)
            s = max(math.sqrt(float((gx @ (GRID - m) ** 2).sum() / mass)), du)
        shift = gx @ e  # E[excess | r]
        sums = np.bincount(h, weights=r - shift, minlength=q)
        mu = np.where(counts > 0, sums / np.maximum(counts, 1.0), np.nan)
        if not held:
            D2 = r - mu[h]
            D2 = np.subtract(D2[:, None], np.concatenate([[0.0], e])[None, :]) ** 2
            core = max(math.sqrt(float(np.einsum("ik,ik->", g, D2)) / r.size), 1e-6)
    upper, lower, p = tail_signs(r - median[h], core)
    return ExcessFit(math.exp(m), s, pi, core, mu, upper, lower, p, int(r.size))


def tail_signs(d: np.ndarray, sigma: float) -> tuple[int, int, float]:
    """``(U, L, p)``: the deviations ``d`` beyond ``TAIL sigma`` above (``U``) and below
    (``L``) their centre, and the one-sided binomial test's probability of ``U`` or more
    among ``U + L`` at one half,

    .. math::

        p = \\sum_{k \\ge U} \\binom{U + L}{k} 2^{-(U + L)}

    (1 where ``U = 0``). The centre must not depend on the fit under test: centres fitted
    under the excess (``mu_h`` of the M-step) are pulled below a symmetric heavy tail's
    centre by the excess the fit puts on its upper half, which lengthens the upper tail
    against the lower; :func:`fit_excess` gives each anchor's median residual."""
    upper, lower = int(np.sum(d > TAIL * sigma)), int(np.sum(d < -TAIL * sigma))
    p = binomial_upper_tail(upper, upper + lower)
    return upper, lower, p


def excess_nll(r, median: float, shape: float, fraction: float, sigma: float) -> np.ndarray:
    """The negative log-likelihood of the residuals ``r`` (centred: ``mu_h = 0``, as a filter that
    holds each anchor's bias predicts a range) under the mixture of the module docstring,

    .. math::

        -\\log \\Big[ (1 - \\pi) \\, \\phi_\\sigma(r) + \\pi \\sum_k w_k \\, \\phi_\\sigma(r - e_k)
        \\Big],

    ``phi_sigma`` the density of ``N(0, sigma^2)``, ``w_k`` the log-normal's weights on
    :data:`GRID` (median ``e_50``, shape ``s``, normalised on the grid)."""
    r = np.asarray(r, dtype=float)
    log_w = -0.5 * ((GRID - math.log(median)) / max(shape, 1e-6)) ** 2
    log_w -= np.logaddexp.reduce(log_w)
    z = np.concatenate([[0.0], np.exp(GRID)])
    ll = -0.5 * ((r[:, None] - z[None, :]) / sigma) ** 2
    ll[:, 0] += math.log1p(-fraction)
    ll[:, 1:] += math.log(fraction) + log_w
    return -(np.logaddexp.reduce(ll, axis=1) - math.log(sigma * math.sqrt(2.0 * math.pi)))


def excess_model(r, h, q: int, noise: float | None) -> tuple[ExcessFit | None, bool, str]:
    """``(fit, identified, reason)``: the excess fitted to the residuals ``r`` of the anchors
    ``h`` and whether the filters take it (module docstring), ``noise`` the ranges' known
    line-of-sight standard deviation (m; None: unknown, nothing is fitted)."""
    if noise is None or not noise > 0.0:
        return None, False, "not estimated: the ranges' line-of-sight noise is not known"
    r = np.asarray(r, dtype=float)
    if int(np.isfinite(r).sum()) < 2 * MIN_TAIL:
        return None, False, "not estimated: too few residuals"
    fit = fit_excess(r, h, q)
    said = (
        f"median {fit.median:.3f} m, shape {fit.shape:.2f}, fraction {fit.fraction:.2f}, core "
        f"{fit.sigma:.3f} m; beyond {TAIL:g} sd {fit.upper} above, {fit.lower} below"
    )
    if fit.upper < MIN_TAIL or fit.p_value > SIGNIFICANCE:
        why = f"the tails do not differ in sign beyond chance (p = {fit.p_value:.2g})"
    elif fit.median < fit.sigma or fit.fraction > 0.9:
        why = "the excess is not resolved from the noise"
    else:
        return fit, True, f"estimated: {said}"
    return fit, False, f"not identified ({why}): {said}"


def known_noise(log) -> float | None:
    """The ranges' line-of-sight standard deviation (m) where the log gives it: the median of
    the stated ``std`` where every range states one, else the ranges' own estimate
    (:func:`~quadobs.testbed.logs.range_noise.stated_range_noise`), else None."""
    from quadobs.testbed.logs.range_noise import stated_range_noise

    std = np.asarray(getattr(log, "range_std", np.empty(0)), dtype=float)
    if std.size and np.all(np.isfinite(std)):
        return float(np.median(std))
    return stated_range_noise(log)


def calibrated_excess(log, residuals, options: dict) -> tuple[dict, str]:
    """The self-calibration's step for the excess: ``(summary, reason)``, and ``options``
    given ``nlos_median`` and ``nlos_shape`` where the residuals (the calibration's chosen
    replay, :class:`~quadobs.testbed.logs.calibration.Residuals`) identify it. A log that
    states its ranges Gaussian (``range_errors``), or whose options already state the
    excess, is left as it is."""
    if getattr(log, "range_errors", "") == "gaussian":
        return {"chosen": False}, "not estimated: the log states its ranges Gaussian"
    if any(k in options for k in EXCESS_KEYS):
        return {"chosen": False}, "as given"
    fit, ok, why = excess_model(residuals.r, residuals.h, log.beacons.shape[0], known_noise(log))
    if ok and fit is not None:
        options["nlos_median"], options["nlos_shape"] = fit.median, fit.shape
    summary = {"chosen": ok, **({} if fit is None else fit.summary())}
    return summary, why
