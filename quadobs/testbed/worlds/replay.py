"""A world that replays a logged range-only run (:class:`~quadobs.testbed.logs.RangeLog`).

The time grid. The estimators advance by a fixed step ``dt``; the log's own clocks are
irregular (ranges every 0.12 to 0.35 s, odometry every 0.01 to 0.35 s, in Plaza2). The
replay uses the grid ``t_k = t_start + k dt`` (``t_start``: the first odometry time),
``k = 0 .. K - 1``, ``K = floor((t_end - t_start) / dt)``, and

* places each range at its own step: a range taken at ``t`` is the output ``y_k`` of
  ``k = floor((t - t_start) / dt)`` (read at ``t_k``, at most ``dt`` early: a position
  error of at most ``|v| dt``, 0.1 m at 1 m/s and ``dt = 0.1`` s). A second range to the
  same beacon in the same step is dropped (counted in ``merged``); ranges to different
  beacons in one step are corrected together;
* holds the odometry between its samples: the dead-reckoned pose ``(P(t), theta(t))`` is
  integrated at the odometry's own times at the mid-step heading,

  .. math:: \\theta_i = \\theta_{i-1} + \\omega_{i-1} \\Delta t_i, \\qquad
            P_i = P_{i-1} + s_{i-1} \\Delta t_i
            \\begin{bmatrix} \\cos \\bar\\theta \\\\ \\sin \\bar\\theta \\end{bmatrix},
            \\quad \\bar\\theta = \\tfrac12 (\\theta_{i-1} + \\theta_i),

  interpolated linearly to the grid, and the input held over ``[t_k, t_(k+1))`` is
  ``u_k = ((P(t_(k+1)) - P(t_k)) / dt, (theta(t_(k+1)) - theta(t_k)) / dt)``, so the single
  integrator ``p' = u`` reproduces the dead reckoning at every grid time;
* interpolates the truth (when the log has one) linearly to the grid (NaN outside its
  span); for the constant-velocity model its velocity is the central difference.

A range bias per beacon ``b_h`` (calibrated, see :mod:`quadobs.testbed.logs.calibration`)
is subtracted before the output ``y_h = (rho_h - b_h)^2 / 2 - |a_h|^2 / 2`` is formed.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError, as_finite_scalar
from quadobs.testbed.worlds.base import Columns, World

__all__ = ["ReplayWorld", "dead_reckoning", "grid", "MODELS"]

#: Replay models: the estimator state they use (``n``).
MODELS = {"odometry": 2, "cv": 4}


def grid(log, dt: float) -> np.ndarray:
    """The replay's step times ``t_k`` (s, the log's clock), ``K`` of them."""
    dt = as_finite_scalar("dt", dt, positive=True)
    K = int(math.floor((log.end - log.start) / dt + 1e-9))
    if K < 1:
        raise QuadobsError(f"dt: {dt:g} s is longer than the log ({log.end - log.start:g} s)")
    return log.start + dt * np.arange(K + 1)


def dead_reckoning(log, times: np.ndarray, origin=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckoned positions ``(T, 2)`` and headings ``(T,)`` at ``times``, from ``origin`` and ``heading0``."""
    t, s, w = log.inputs[:, 0], log.inputs[:, 1], log.inputs[:, 2]
    dt = np.diff(t)
    theta = log.heading0 + np.concatenate([[0.0], np.cumsum(w[:-1] * dt)])
    mid = 0.5 * (theta[:-1] + theta[1:])
    step = (s[:-1] * dt)[:, None] * np.column_stack([np.cos(mid), np.sin(mid)])
    P = np.asarray(origin, dtype=float) + np.vstack([[0.0, 0.0], np.cumsum(step, axis=0)])
    x = np.interp(times, t, P[:, 0])
    y = np.interp(times, t, P[:, 1])
    return np.column_stack([x, y]), np.interp(times, t, theta)


def _truth_rows(log, T: np.ndarray, n: int) -> np.ndarray:
    X = np.full((T.size, n), np.nan)
    if log.truth is None:
        return X
    tt = log.truth[:, 0]
    inside = (T >= tt[0]) & (T <= tt[-1])
    for c in range(2):
        X[inside, c] = np.interp(T[inside], tt, log.truth[:, 1 + c])
    if n == 4:
        X[:, 2:4] = np.gradient(X[:, :2], T, axis=0)
    return X


class ReplayWorld(World):
    """The rows of a logged run on the replay grid (module docstring); open loop, filled from arrays.

    Parameters
    ----------
    log : RangeLog
    dt : float
        Grid step (s).
    model : {"odometry", "cv"}
        The estimator state: position (``n = 2``) or position and velocity (``n = 4``).
    capacity : int
        Most steps per block.
    biases : array_like (q,), optional
        Range bias per beacon (m), subtracted from every range; default zero.

    Attributes
    ----------
    times : ndarray (K + 1,)
        The grid (the last entry: the time of the final row).
    steps : int
        ``K``.
    merged : int
        Ranges dropped because another range to the same beacon fell in the same step.
    placed : int
        Ranges placed on the grid.
    """

    def __init__(self, log, dt: float, model: str = "odometry", capacity: int = 8192, biases=None) -> None:
        if model not in MODELS:
            raise QuadobsError(f"model: expected one of {', '.join(MODELS)}, got {model!r}")
        self.log, self.model, self.dt = log, model, float(dt)
        self.times = T = grid(log, dt)
        self.steps = K = T.size - 1
        n, q = MODELS[model], log.beacons.shape[0]
        self.biases = np.zeros(q) if biases is None else np.asarray(biases, dtype=float).reshape(q)
        self.columns = Columns(
            truth=slice(0, n), y=slice(n, n + q), u=slice(n + q, n + q + 3),
            measured=slice(n + q + 3, n + 2 * q + 3), width=n + 2 * q + 3,
        )
        rows = np.full((K + 1, self.columns.width), np.nan)
        rows[:, :n] = _truth_rows(log, T, n)
        P, theta = dead_reckoning(log, T)
        rows[:K, n + q : n + q + 2] = np.diff(P, axis=0) / self.dt
        rows[:K, n + q + 2] = np.diff(theta) / self.dt
        self._place_ranges(rows, K, n, q)
        self._rows = rows
        self.out = np.full((int(capacity) + 1, self.columns.width), np.nan)
        self.events = np.zeros((int(capacity) + 1, 2), dtype=np.int64)
        self._k0 = 0

    def _place_ranges(self, rows: np.ndarray, K: int, n: int, q: int) -> None:
        log = self.log
        k = np.floor((log.ranges[:, 0] - log.start) / self.dt + 1e-9).astype(np.int64)
        h = log.beacon_index(log.ranges[:, 1])
        inside = (k >= 0) & (k < K)
        k, h, rho = k[inside], h[inside], log.ranges[inside, 2]
        first = np.unique(k * q + h, return_index=True)[1]  # the first range of each (step, beacon)
        self.merged = int(k.size - first.size)
        self.placed = int(first.size)
        k, h, rho = k[first], h[first], rho[first]
        rows[k, n + q + 3 + h] = rho
        a2 = np.einsum("hi,hi->h", log.beacons, log.beacons)
        rows[k, n + h] = 0.5 * (rho - self.biases[h]) ** 2 - 0.5 * a2[h]

    def truth_at(self, steps) -> np.ndarray:
        """The true state at the given grid steps ``(m, n)`` (NaN without a truth)."""
        return self._rows[np.asarray(steps), self.columns.truth].copy()

    def state(self) -> np.ndarray:
        """The truth at ``t_0`` (NaN without one)."""
        return self._rows[0, self.columns.truth].copy()

    def begin_block(self, k0: int, count: int) -> int:
        self._k0 = int(k0)
        count = min(int(count), self.out.shape[0] - 1, self.steps - k0)
        self._count = count
        self.out[0, self.columns.truth] = self._rows[k0, self.columns.truth]
        return count

    def step(self, j: int, estimate=None) -> None:
        k = self._k0 + j
        self.out[j] = self._rows[k]
        self.out[j + 1, self.columns.truth] = self._rows[k + 1, self.columns.truth]

    def fill(self, count: int) -> None:
        k0 = self._k0
        self.out[: count + 1] = self._rows[k0 : k0 + count + 1]
