"""Estimation errors and convergence times, streamed (one episode) or batched (many runs).

Convergence time, the one convention of the library
----------------------------------------------------
For an error norm ``e(t_i)`` sampled at ``t_0 < t_1 < ... < t_{T-1}`` and a threshold ``c``,
the convergence time is the first sample time from which the error stays below ``c``:

.. math::

    t_c = t_{i^* + 1}, \\qquad i^* = \\max\\{i : e(t_i) \\ge c\\},

``t_c = t_0`` when the error is never at or above ``c``, and ``t_c = NaN`` ("not converged")
when the last sample is not below ``c``. A NaN error counts as not below. Times are
floats everywhere (:class:`ConvergenceTracker` for one episode, :func:`convergence_times`
for the runs of a campaign); a JSON summary writes a NaN time as ``null``
(:func:`json_time`).
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError, as_array

__all__ = ["ConvergenceTracker", "convergence_times", "json_time", "state_errors"]


def state_errors(
    dim: int, has_wind: bool, x_hat: np.ndarray, x: np.ndarray
) -> dict[str, np.ndarray]:
    """Errors ``x_hat - x`` split into position and ground velocity (and wind); the position only when ``n < 2 dim``.

    For the wind state ``(p, v_a, v_w)`` the ground velocity is ``v_a + v_w``. Works on
    one state ``(n,)`` or on rows of states ``(T, n)``.
    """
    e = x_hat - x
    if e.shape[-1] < 2 * dim:  # a state without a velocity (a vehicle driven by its odometry)
        return {"position": e[..., :dim]}
    if not has_wind:
        return {"position": e[..., :dim], "velocity": e[..., dim : 2 * dim]}
    return {
        "position": e[..., :dim],
        "velocity": e[..., dim : 2 * dim] + e[..., 2 * dim : 3 * dim],
        "air_velocity": e[..., dim : 2 * dim],
        "wind": e[..., 2 * dim : 3 * dim],
    }


class ConvergenceTracker:
    """Convergence times (module docstring) of a stream of error norms, one per threshold.

    Feed :meth:`update` (one sample) or :meth:`update_many` (a block of samples) in time
    order; :meth:`times` gives, per threshold, the time from which the error stays below
    it, NaN if the last sample is not below it.

    Parameters
    ----------
    thresholds : sequence of float

    Examples
    --------
    >>> tr = ConvergenceTracker((1.0, 0.1))
    >>> tr.update_many([0.0, 1.0, 2.0, 3.0], [2.0, 0.5, 1.5, 0.5])
    >>> tr.times()
    [3.0, nan]
    """

    def __init__(self, thresholds=(1.0, 0.1)) -> None:
        self.thresholds = tuple(float(c) for c in thresholds)
        self._since: list[float | None] = [None] * len(self.thresholds)  # None: not below now

    def update(self, t: float, value: float) -> None:
        """One sample ``value`` at time ``t``."""
        for i, c in enumerate(self.thresholds):
            if not value < c:  # also catches NaN
                self._since[i] = None
            elif self._since[i] is None:
                self._since[i] = t

    def update_many(self, t, values) -> None:
        """:meth:`update` with each sample of ``t (T,)`` and ``values (T,)`` in order, vectorised."""
        t = np.asarray(t, dtype=float)
        values = np.asarray(values, dtype=float)
        if not t.size:
            return
        for i, c in enumerate(self.thresholds):
            above = np.flatnonzero(~(values < c))  # also catches NaN
            if above.size:
                last = int(above[-1])
                self._since[i] = float(t[last + 1]) if last + 1 < t.size else None
            elif self._since[i] is None:
                self._since[i] = float(t[0])

    def times(self) -> list[float]:
        """Per threshold: the time from which the error stays below it, or NaN (not converged)."""
        return [math.nan if s is None else float(s) for s in self._since]


def convergence_times(times: np.ndarray, errors: np.ndarray, threshold: float) -> np.ndarray:
    """Per run, the convergence time (module docstring) of ``errors`` below ``threshold``.

    The batched form of :class:`ConvergenceTracker` (the same rule, one tracker per run).

    Parameters
    ----------
    times : (T,)
    errors : (R, T)
        Error norms; NaN counts as not below.
    threshold : float

    Returns
    -------
    ndarray (R,)
        The time (``times[0]`` if always below), NaN if the last sample is not below.

    Examples
    --------
    >>> convergence_times([0.0, 1.0, 2.0], [[2.0, 0.5, 0.5], [0.5, 0.5, 2.0]], 1.0).tolist()
    [1.0, nan]
    """
    t = as_array("times", times, (None,))
    err = np.asarray(errors, dtype=float)
    if err.ndim != 2 or err.shape[1] != t.shape[0]:
        raise QuadobsError(f"errors: expected shape (runs, {t.shape[0]}), got {err.shape}")
    out = np.full(err.shape[0], np.nan)
    for r in range(err.shape[0]):
        tracker = ConvergenceTracker((threshold,))
        tracker.update_many(t, err[r])
        out[r] = tracker.times()[0]
    return out


def json_time(t: float, digits: int = 9) -> float | None:
    """A convergence time for a JSON summary: rounded to ``digits``, ``None`` (``null``) for NaN.

    Examples
    --------
    >>> json_time(1.0000000001), json_time(float("nan"))
    (1.0, None)
    """
    return None if math.isnan(t) else round(float(t), digits)
