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
* holds an accelerometer's samples likewise: the input of step ``k`` is the mean of the
  held acceleration over ``[t_k, t_(k+1))``, ``u_k = (V(t_(k+1)) - V(t_k)) / dt`` with
  ``V(t) = int_(t_start)^t a`` (the sample itself where the log's clock is the grid's), so
  the double integrator's velocity follows the integrated acceleration at every grid time;
* interpolates the truth (when the log has one) linearly to the grid (NaN outside its
  span and inside its gaps, :data:`TRUTH_GAP_FACTOR`); for a model with a velocity, the truth's velocity where the log has one, else
  the central difference of its positions.

Models (:func:`state_size`): ``odometry`` (odometry logs: ``p' = u``, ``n = 2``), ``cv``
(planar logs, the input unused: ``p' = v``, ``v' = w``, ``n = 4``) and ``imu``
(accelerometer logs: ``p' = v``, ``v' = u``, ``n = 2 dim``).

A range bias per beacon ``b_h`` (calibrated, see :mod:`quadobs.testbed.logs.calibration`)
is subtracted before the output ``y_h = (rho_h - b_h)^2 / 2 - |a_h|^2 / 2`` is formed.

The sensor layer (:class:`~quadobs.testbed.sensors.SensorModel`, a scenario's ``noise.*``
fields) applies to the logged ranges as to simulated ones: read at its sample steps only,
with its noise and outliers added and its dropouts, drawn from its seeded streams a block
at a time (:meth:`~quadobs.testbed.sensors.SensorModel.logged_ranges`). With the default
settings it adds nothing: the log's ranges as they are.

The world's own sinks (:meth:`ReplayWorld.sinks`) add the replay's figures to the summary:
:class:`ReplayErrorSink` (RMSE, maximum and final error, convergence times against the
truth) and :class:`ReplayFiguresSink` (time per range, the GTSAM peer's offline figures).
"""

from __future__ import annotations

import math
import time

import numpy as np

from quadobs.errors import QuadobsError, as_finite_scalar
from quadobs.evaluation.convergence import ConvergenceTracker, json_time
from quadobs.testbed.sinks import EpisodeContext, EpisodeFrame, Rows, Sink
from quadobs.testbed.worlds.base import Columns, World

__all__ = [
    "MODELS",
    "ReplayErrorSink",
    "ReplayFiguresSink",
    "ReplayWorld",
    "dead_reckoning",
    "default_model",
    "grid",
    "held_samples",
    "input_width",
    "state_size",
]

#: Replay models (module docstring).
MODELS = ("odometry", "cv", "imu")


def default_model(log) -> str:
    """The model a log's inputs ask for: ``odometry`` for wheel odometry, ``imu`` for an
    accelerometer or a body IMU, ``cv`` for a log of measurements alone."""
    return {"odometry": "odometry", "imu": "imu", "imu_body": "imu", "none": "cv"}[log.input_kind]


def state_size(log, model: str) -> int:
    """The estimator state size ``n`` of ``model`` on ``log``; a one-line error where the model does not apply."""
    if model not in MODELS:
        raise QuadobsError(f"model: expected one of {', '.join(MODELS)}, got {model!r}")
    lacks = {
        "odometry": "wheel odometry (inputs.csv: time,speed,yaw_rate)",
        "imu": "an accelerometer (inputs.csv: time,ax,ay[,az]) or a body IMU (imu.csv)",
    }
    if model == "odometry" and log.input_kind != "odometry":
        raise QuadobsError(f"model odometry: the log {log.name!r} lacks {lacks['odometry']}")
    if model == "imu" and log.input_kind not in ("imu", "imu_body"):
        raise QuadobsError(f"model imu: the log {log.name!r} lacks {lacks['imu']}")
    return {"odometry": 2, "cv": 2 * log.dimension, "imu": 2 * log.dimension}[model]


def input_width(log) -> int:
    """The width of the input the replay's models read: 3 for odometry (``v_x, v_y, omega``),
    else the dimension (an acceleration in the navigation frame; zeros for a log without inputs)."""
    return 3 if log.input_kind == "odometry" else log.dimension


def held_samples(log) -> np.ndarray:
    """The log's inputs as the replay's held samples, ``time`` then :func:`input_width` columns:
    the odometry's ``speed, yaw_rate`` rows, an accelerometer's rows, a body IMU rotated into
    the navigation frame (:func:`~quadobs.testbed.attitude.navigation_accelerations`), or,
    without inputs, zeros at the log's start and end."""
    if log.input_kind == "imu_body":
        from quadobs.testbed.attitude import navigation_accelerations

        return navigation_accelerations(log)
    if log.input_kind == "none":
        return np.column_stack([[log.start, log.end], np.zeros((2, log.dimension))])
    return log.inputs


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


def held_mean(log, times: np.ndarray, samples: np.ndarray | None = None) -> np.ndarray:
    """The mean of the held accelerometer input over each grid step ``[t_k, t_(k+1))``, ``(K, dim)`` (module docstring).

    ``samples``: the ``time, a...`` rows (default: the log's inputs).
    """
    samples = log.inputs if samples is None else samples
    t, a = samples[:, 0], samples[:, 1:]
    V = np.vstack([np.zeros(a.shape[1]), np.cumsum(a[:-1] * np.diff(t)[:, None], axis=0)])
    Vg = np.column_stack([np.interp(times, t, V[:, i]) for i in range(a.shape[1])])
    return np.diff(Vg, axis=0) / np.diff(times)[:, None]


#: A truth's interval longer than this many times its median interval, and than
#: :data:`TRUTH_GAP_MIN` seconds, is a gap (a motion capture that lost the body): no truth is
#: interpolated across it, so no error is scored there.
TRUTH_GAP_FACTOR = 10.0
TRUTH_GAP_MIN = 0.5


def wide_gaps(t: np.ndarray) -> np.ndarray:
    """The indices ``i`` of the intervals ``t[i] .. t[i + 1]`` of sorted times that are gaps:
    longer than :data:`TRUTH_GAP_FACTOR` times the median interval and than
    :data:`TRUTH_GAP_MIN` seconds (none where fewer than two intervals)."""
    gaps = np.diff(np.asarray(t, dtype=float))
    if gaps.size < 2:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(gaps > max(TRUTH_GAP_FACTOR * float(np.median(gaps)), TRUTH_GAP_MIN))


def _in_truth_gap(tt: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Which grid times ``T`` lie strictly inside a gap of the truth's times ``tt``."""
    wide = wide_gaps(tt)
    if wide.size == 0:
        return np.zeros(T.size, dtype=bool)
    k = np.searchsorted(tt, T, side="right") - 1  # the truth sample at or before each time
    return np.isin(k, wide) & (T > tt[np.clip(k, 0, tt.size - 1)])


def _truth_rows(log, T: np.ndarray, n: int) -> np.ndarray:
    X = np.full((T.size, n), np.nan)
    if log.truth is None:
        return X
    dim, tt = log.dimension, log.truth[:, 0]
    inside = (T >= tt[0]) & (T <= tt[-1]) & ~_in_truth_gap(tt, T)
    for c, col in enumerate(log.truth_part("position").T):
        X[inside, c] = np.interp(T[inside], tt, col)
    if n == 2 * dim:
        V = log.truth_part("velocity")
        if V is None:
            X[:, dim:] = np.gradient(X[:, :dim], T, axis=0)
        else:
            for c, col in enumerate(V.T):
                X[inside, dim + c] = np.interp(T[inside], tt, col)
    return X


class ReplayWorld(World):
    """The rows of a logged run on the replay grid (module docstring); open loop, filled from arrays.

    Parameters
    ----------
    log : RangeLog
    dt : float
        Grid step (s).
    model : {"odometry", "cv", "imu"}
        The estimator state (:func:`state_size`): the position, or the position and the velocity.
    capacity : int
        Most steps per block.
    biases : array_like (q,), optional
        Range bias per beacon (m), subtracted from every range; default zero.
    sensors : SensorModel, optional
        The sensor layer applied to the logged ranges (default: none).
    peer_batch : bool
        :class:`ReplayFiguresSink` also solves the GTSAM peer's whole graph (Levenberg-Marquardt).

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

    def __init__(
        self,
        log,
        dt: float,
        model: str = "odometry",
        capacity: int = 8192,
        biases=None,
        sensors=None,
        peer_batch: bool = True,
    ) -> None:
        n, q = state_size(log, model), log.beacons.shape[0]
        self.log, self.model, self.dt = log, model, float(dt)
        self.sensors = None if sensors is None or sensors.adds_nothing else sensors
        self.peer_batch = bool(peer_batch)
        self.times = T = grid(log, dt)
        self.steps = K = T.size - 1
        self.biases = np.zeros(q) if biases is None else np.asarray(biases, dtype=float).reshape(q)
        self._a2 = np.einsum("hi,hi->h", log.beacons, log.beacons)
        p = input_width(log)
        self.columns = Columns(
            truth=slice(0, n),
            y=slice(n, n + q),
            u=slice(n + q, n + q + p),
            measured=slice(n + q + p, n + 2 * q + p),
            width=n + 2 * q + p,
        )
        rows = np.full((K + 1, self.columns.width), np.nan)
        rows[:, :n] = _truth_rows(log, T, n)
        rows[:K, self.columns.u] = self._inputs(T)
        self._place_ranges(rows, K, n, q)
        self._rows = rows
        self.out = np.full((int(capacity) + 1, self.columns.width), np.nan)
        self.events = np.zeros((int(capacity) + 1, 2), dtype=np.int64)
        self._k0 = 0
        #: Measurements fed in time to the estimators that take them (set by the replay), or None.
        self.in_time_count: int | None = None
        # with a sensor layer: the block's rows (row 0: step _k0), its events
        self._src: np.ndarray = rows[:0]
        self._events: np.ndarray = self.events[:0]

    def _inputs(self, T: np.ndarray) -> np.ndarray:
        """The input held over each grid step ``(K, p)`` (module docstring)."""
        if self.log.input_kind != "odometry":
            return held_mean(self.log, T, held_samples(self.log))
        P, theta = dead_reckoning(self.log, T)
        return np.column_stack([np.diff(P, axis=0) / self.dt, np.diff(theta) / self.dt])

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
        rows[k, self.columns.measured.start + h] = rho
        rows[k, n + h] = 0.5 * (rho - self.biases[h]) ** 2 - 0.5 * self._a2[h]

    def frame(self, seed: int = 0) -> EpisodeFrame:
        """The episode frame of the replay: the log's name and beacons, the grid, its input (odometry or accelerometer)."""
        log, s = self.log, self.sensors
        odometry = log.input_kind == "odometry"
        return EpisodeFrame(
            name=log.name,
            steps=self.steps,
            dt=self.dt,
            dimension=log.dimension,
            beacons=log.beacons,
            physics_rate=1.0 / self.dt,
            seed=int(seed),
            description=f"replay of the log {log.name} (model {self.model}, dt {self.dt:g} s)",
            source=log.source,
            sensor_events=s is not None and bool(s.dropout or s.outlier_probability),
            input_name="odometry" if odometry else "accelerometer",
            input_labels=("v_x (m/s)", "v_y (m/s)", "omega (rad/s)")
            if odometry
            else tuple(f"a_{a}" for a in "xyz"[: log.dimension]),
            beacon_labels=tuple(f"beacon {int(i)}" for i in log.beacon_ids),
            beacon_ids=tuple(int(i) for i in log.beacon_ids),
            time_origin=float(self.times[0]),
        )

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
        if self.sensors is not None:
            self._sense(count)
        return count

    def _sense(self, count: int) -> None:
        """The block's rows with the sensor layer on the logged ranges (module docstring), in ``_src``."""
        k0, c = self._k0, self.columns
        assert self.sensors is not None, "called with a sensor layer only"
        src = self._rows[k0 : k0 + count + 1].copy()
        draws = self.sensors.draws(k0, count)
        rho, self._events = self.sensors.logged_ranges(src[:count, c.measured], draws)
        src[:count, c.measured] = rho
        src[:count, c.y] = 0.5 * (rho - self.biases) ** 2 - 0.5 * self._a2
        if (
            self.sensors.accel_std
        ):  # an accelerometer log (the layer refuses accelerometer noise on odometry)
            src[:count, c.u] += self.sensors.input_noise(draws)
        self._src = src

    def _row(self, k: int) -> np.ndarray:
        return self._rows[k] if self.sensors is None else self._src[k - self._k0]

    def step(self, j: int, estimate=None) -> None:
        k = self._k0 + j
        self.out[j] = self._row(k)
        self.out[j + 1, self.columns.truth] = self._rows[k + 1, self.columns.truth]

    def fill(self, count: int) -> None:
        k0 = self._k0
        self.out[: count + 1] = (
            self._rows[k0 : k0 + count + 1] if self.sensors is None else self._src[: count + 1]
        )

    def commit(self, rows: int) -> None:
        """The sensor events of the first ``rows`` steps, counted in the sensor layer."""
        self.events[:rows] = 0 if self.sensors is None else self.sensors.count(self._events[:rows])

    def sinks(self, recording=None) -> list:
        """The replay's figures: :class:`ReplayErrorSink`, :class:`ReplayFiguresSink`."""
        return [ReplayErrorSink(), ReplayFiguresSink(self)]


class ReplayErrorSink(Sink):
    """Position RMSE, maximum and final error, and convergence times (5 m, 2 m) per estimator, over the rows with a truth.

    The final error is the one at the last row with a truth (a truth that ends before the log
    does still has one); it is None where the estimate there is not finite (lost).
    """

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        self.sq = {
            n: [0.0, 0, 0.0, math.nan] for n in ctx.names
        }  # sum of squares, count, max, last
        self.trackers = {n: ConvergenceTracker((5.0, 2.0)) for n in ctx.names}

    def block(self, rows: Rows) -> None:
        truth = np.flatnonzero(np.isfinite(rows.truth[:, 0]))  # the rows with a truth
        for name, err in rows.errors.items():
            ep = err["position"]
            e = np.sqrt(np.einsum("ij,ij->i", ep, ep))
            ok = np.isfinite(e)
            acc = self.sq[name]
            acc[0] += float(np.sum(e[ok] ** 2))
            acc[1] += int(ok.sum())
            acc[2] = max(acc[2], float(e[ok].max())) if ok.any() else acc[2]
            if truth.size:  # the error at the last row with a truth (NaN: the estimate is lost)
                acc[3] = float(e[truth[-1]])
            if ok.any():
                self.trackers[name].update_many(rows.t[ok], e[ok])

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {}
        for name, (ss, m, mx, last) in self.sq.items():
            t5, t2 = (json_time(t) for t in self.trackers[name].times())
            per[name] = {
                "rmse": math.sqrt(ss / m) if m else None,
                "max_error": mx if m else None,
                "final_position_error": last if math.isfinite(last) else None,
                "time_to_5m": t5,
                "time_to_2m": t2,
            }
        return {"estimators": per}


class ReplayFiguresSink(Sink):
    """Per estimator: ``seconds_per_measurement`` (its wall time over the ranges placed, from the
    episode's clock); for the GTSAM peer, ``smoothed_rmse``/``batch_rmse`` and their maxima at its
    keyframes (iSAM2's final estimate, the Levenberg-Marquardt optimum), unless interrupted, and
    the wall time of each (``smoothed_seconds``, ``batch_seconds``)."""

    def __init__(self, world: ReplayWorld) -> None:
        self.world = world

    def end(self, completed: int, interrupted: bool) -> dict:
        from quadobs.estimators.gtsam_peer import Isam2RangeOnly  # imports gtsam only when built

        per: dict[str, dict] = {}
        clock, w = self.ctx.clock, self.world
        for e, est in enumerate(self.ctx.estimators):
            entry = per[est.name] = {}
            timed = w.in_time_count is not None and hasattr(est, "inner")
            if clock is not None:
                used = w.in_time_count if timed and w.in_time_count is not None else w.placed
                entry["seconds_per_measurement"] = float(clock[e]) / max(used, 1)
            est = getattr(est, "inner", est)
            if isinstance(est, Isam2RangeOnly) and w.peer_batch and not interrupted:
                for key, solve in (
                    ("smoothed", est.online_positions),
                    ("batch", est.batch_optimum),
                ):
                    start = time.perf_counter()
                    steps, P = solve()
                    entry[f"{key}_seconds"] = time.perf_counter() - start
                    err = np.linalg.norm(P - w.truth_at(steps)[:, : P.shape[1]], axis=1)
                    err = err[np.isfinite(err)]
                    entry[f"{key}_rmse"] = float(np.sqrt(np.mean(err**2))) if err.size else None
                    entry[f"{key}_max_error"] = float(err.max()) if err.size else None
        return {"estimators": per}
