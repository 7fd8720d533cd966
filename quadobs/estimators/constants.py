"""Constant states: the entries of a filter's state that no process noise moves, and their start.

A filter that holds an anchor's range bias ``b_h``, its squared-range offset ``e_h`` or the
tag's lever arm ``l`` as states models each as a constant, ``c' = 0``. Learnt online from a
prior of decimetres, such states settle over tens of seconds, and until they do the position
carries their error. A constant is one value over the whole span, ``c_k = c_N`` for every step
``k``, so its smoothed distribution at any time, ``p(c_k | y_1..y_N)``, is the filter's last,
``p(c_N | y_1..y_N)``: the estimate filtered to the end of the data is the smoothed one (exactly
for a linear-Gaussian model, to the filter's linearisation otherwise). The replay's self-calibration therefore runs such a
filter once over the log and may start it again from the constants it ended with
(:mod:`quadobs.testbed.logs.constants_start`).

An estimator holds constant states where it provides

``constant_states``
    the indices of those states in its state vector (an empty array where it holds none);
``constants_estimate()``
    their estimate and covariance ``(mean (c,), covariance (c, c))``;
``start_constants(mean, covariance)``
    their prior set to ``mean`` and ``covariance``, uncorrelated with the other states,
    before the first measurement: the state, its covariance, and the prior that a start-up
    fix or a re-initialisation returns them to.

The functions below read these from any estimator, and from each member of a
:class:`~quadobs.estimators.model_average.ModelAverage`.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["ConstantStates", "constant_filters", "set_constants_prior"]


class ConstantStates:
    """The estimate and the start of the constant states of a filter that keeps its state in
    ``_x``, its covariance in ``_P`` and its prior in ``_P0`` (and ``_x0`` where it keeps one),
    the indices in ``constant_states`` (module docstring). A filter whose start-up reads the
    constants' prior (a fix's spread, the state a re-initialisation returns to) updates it in
    :meth:`_started_constants`."""

    _x: np.ndarray
    _P: np.ndarray
    _P0: np.ndarray

    @property
    def constant_states(self) -> np.ndarray:  # pragma: no cover - each filter's own
        raise NotImplementedError

    def _settled(self) -> None:
        """The covariance brought up to date (a filter that propagates it lazily)."""
        settle = getattr(self, "_settle", None)
        if settle is not None:
            settle()

    def constants_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """The constant states' estimate and covariance ``(mean (c,), covariance (c, c))``."""
        self._settled()
        idx = self.constant_states
        return self._x[idx].copy(), self._P[np.ix_(idx, idx)].copy()

    def start_constants(self, mean, covariance) -> None:
        """The constant states' prior ``N(mean, covariance)``, uncorrelated with the other
        states, before the first measurement: in the state, its covariance and the prior a
        start-up fix or a re-initialisation returns to."""
        self._settled()
        idx = self.constant_states
        set_constants_prior(self._P, self._x, idx, mean, covariance)
        x0 = getattr(self, "_x0", None)
        set_constants_prior(self._P0, self._x.copy() if x0 is None else x0, idx, mean, covariance)
        self._started_constants()

    def _started_constants(self) -> None:
        """What the filter derives from the constants' prior, set again after a start."""


def constant_filters(est) -> list:
    """The filters of ``est`` that hold constant states: ``est`` itself, or the members of a
    model average (:attr:`~quadobs.estimators.model_average.ModelAverage.members`) that do."""
    members = getattr(est, "members", None)
    found = list(members) if members is not None else [est]
    return [f for f in found if np.size(getattr(f, "constant_states", ())) > 0]


def set_constants_prior(P: np.ndarray, x: np.ndarray, idx: np.ndarray, mean, covariance):
    """``x`` and ``P`` (both changed in place) with the entries ``idx`` set to ``mean`` and
    covariance ``covariance``, their cross-covariances with the other entries zero; refused in
    one line where the shapes disagree or the covariance is not a finite symmetric
    positive semi-definite matrix."""
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(covariance, dtype=float)
    c = idx.size
    if mean.shape != (c,) or cov.shape != (c, c):
        raise QuadobsError(
            f"start_constants: expected a mean ({c},) and a covariance ({c}, {c}), got "
            f"{mean.shape} and {cov.shape}"
        )
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        raise QuadobsError("start_constants: the mean and the covariance must be finite")
    cov = 0.5 * (cov + cov.T)
    if np.min(np.linalg.eigvalsh(cov)) < -1e-12 * max(1.0, float(np.max(np.abs(cov)))):
        raise QuadobsError("start_constants: the covariance is not positive semi-definite")
    x[idx] = mean
    P[idx, :] = 0.0
    P[:, idx] = 0.0
    P[np.ix_(idx, idx)] = cov
