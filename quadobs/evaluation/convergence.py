"""Estimation errors and convergence times, computed in a streaming fashion."""

from __future__ import annotations

import numpy as np

__all__ = ["state_errors", "ConvergenceTracker"]


def state_errors(dim: int, has_wind: bool, x_hat: np.ndarray, x: np.ndarray) -> dict[str, np.ndarray]:
    """Errors ``x_hat - x`` split into position and ground velocity (and wind).

    For the wind state ``(p, v_a, v_w)`` the ground velocity is ``v_a + v_w``. Works on
    one state ``(n,)`` or on rows of states ``(T, n)``.
    """
    e = x_hat - x
    if not has_wind:
        return {"position": e[..., :dim], "velocity": e[..., dim : 2 * dim]}
    return {
        "position": e[..., :dim],
        "velocity": e[..., dim : 2 * dim] + e[..., 2 * dim : 3 * dim],
        "air_velocity": e[..., dim : 2 * dim],
        "wind": e[..., 2 * dim : 3 * dim],
    }


class ConvergenceTracker:
    """First time after which an error norm stays below each threshold.

    Feed ``update(t, value)`` in time order. For a threshold ``c``, the result is the time
    of the first sample after the last sample with ``value >= c``: the error stays below
    ``c`` from then on. It is the first sample time if the error never reached ``c``, and
    ``None`` if the last sample is not below ``c`` (or is not finite).
    """

    def __init__(self, thresholds=(1.0, 0.1)) -> None:
        self.thresholds = tuple(float(c) for c in thresholds)
        self._since: list[float | None] = [None] * len(self.thresholds)

    def update(self, t: float, value: float) -> None:
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

    def times(self) -> list[float | None]:
        """Per threshold: the time from which the error stays below it, or ``None``."""
        return list(self._since)
