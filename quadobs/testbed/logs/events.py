"""A log as a time-ordered stream of inputs and measurements, and the estimators run on it in time.

The replay feeds every measurement at its own timestamp: nothing is floored onto a grid,
merged or dropped. Between two events the estimator propagates exactly with the input held
since the last input sample (:meth:`~quadobs.estimators.base.Estimator.predict`); at a
measurement it corrects (:meth:`~quadobs.estimators.base.Estimator.correct`). Recording and
evaluation stay on the replay's grid ``t_k`` (:mod:`quadobs.testbed.worlds.replay`):
:class:`InTimeOnGrid` presents an estimator that takes measurements in time to the
episode's loop as one that steps on the grid, each step ``[t_k, t_(k+1))`` consuming the
events inside it and ending with a prediction to ``t_(k+1)``; the row the loop records
at ``t_k`` is the estimate at ``t_k``.

Measurements that share a timestamp exactly (a log that stamps a round of anchors with one
time, as ``quadobs run --export-log`` of a scenario without a radio does) are one measurement
vector, and the estimator takes them in one call,
:meth:`~quadobs.estimators.base.Estimator.correct_many`: the Kalman filters correct by them
jointly, as they correct by a grid step's outputs, rather than relinearising between them;
measurements at distinct times stay one at a time. An input sampled at the same time is held
first.

Inputs held between samples (:func:`held_inputs`):

* odometry: over ``[t_i, t_(i+1))`` the world-frame velocity and the yaw rate
  ``((P_(i+1) - P_i) / dt_i, (theta_(i+1) - theta_i) / dt_i)`` of the dead reckoning
  (:func:`~quadobs.testbed.worlds.replay.dead_reckoning`), so the single integrator
  reproduces the dead-reckoned pose at every odometry time, as the grid replay does at the
  grid times;
* an accelerometer in the navigation frame: the sample itself, held to the next one.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError
from quadobs.estimators.base import Counted, Estimator, Gated, Immersed, InnerClock, Switching

__all__ = ["InTimeOnGrid", "LogEvents", "held_inputs", "in_time", "takes_time"]


def takes_time(est: Estimator) -> bool:
    """Whether ``est`` implements the interface in time (``hold``, ``predict(t)``, ``correct(m)``):
    through the base class's hooks, or with its own ``predict``."""
    cls = type(est)
    return cls._propagate is not Estimator._propagate or cls.predict is not Estimator.predict


def held_inputs(log, raw: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(times (I,), inputs (I, p))``: each input held from its time to the next (module docstring).

    ``raw``: a body IMU's own samples ``(f_body, omega_body)`` (for estimators that read them),
    rather than the navigation-frame acceleration of
    :func:`~quadobs.testbed.worlds.replay.held_samples`. The last sample is held to the end.
    """
    from quadobs.testbed.worlds.replay import dead_reckoning, held_samples

    if raw:
        if log.input_kind != "imu_body":
            raise QuadobsError(f"{log.name}: the log lacks a body IMU (imu.csv)")
        return log.inputs[:, 0].copy(), log.inputs[:, 1:].copy()
    samples = held_samples(log)
    t = samples[:, 0]
    if log.input_kind != "odometry":
        return t.copy(), samples[:, 1:].copy()
    P, theta = dead_reckoning(log, t)
    dt = np.diff(t)
    U = np.zeros((t.size, 3))
    moving = dt > 0.0
    U[:-1][moving, :2] = np.diff(P, axis=0)[moving] / dt[moving, None]
    U[:-1][moving, 2] = np.diff(theta)[moving] / dt[moving]
    U[-1] = U[-2] if t.size > 1 else 0.0
    return t.copy(), U


class LogEvents:
    """The measurements of a log at their own times, and its inputs as held samples.

    Parameters
    ----------
    log : RangeLog
    biases : array_like (q,), optional
        Range bias per beacon (m), subtracted from each range (and their difference from
        each TDOA).
    start, end : float
        The span replayed (s): measurements in ``[start, end)`` are used.
    std : dict, optional
        The standard deviation, by kind, of the measurements that the log gives none.

    Attributes
    ----------
    measurements : list of Measurement
        In time order (:meth:`~quadobs.testbed.logs.format.RangeLog.measurements`).
    times : ndarray (M,)
        Their times.
    """

    def __init__(self, log, biases=None, *, start: float, end: float, std=None) -> None:
        q = log.beacons.shape[0]
        b = np.zeros(q) if biases is None else np.asarray(biases, dtype=float).reshape(q)
        std = std or {}
        self.measurements = []
        for m in log.measurements():
            if not start <= m.t < end:
                continue
            bias = b[m.anchors[0]] if m.kind == "range" else b[m.anchors[0]] - b[m.anchors[1]]
            sigma = std.get(m.kind, math.nan) if math.isnan(m.std) else m.std
            if bias or sigma != m.std:
                m = Measurement(m.t, m.kind, m.value - float(bias), m.anchors, sigma)
            self.measurements.append(m)
        self.times = np.array([m.t for m in self.measurements])
        self.log = log
        self._inputs: dict[bool, tuple[np.ndarray, np.ndarray]] = {}
        self.start, self.end = float(start), float(end)

    @property
    def count(self) -> int:
        """Measurements in the span."""
        return len(self.measurements)

    def inputs(self, raw: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """:func:`held_inputs` of the log (computed once each)."""
        if raw not in self._inputs:
            self._inputs[raw] = held_inputs(self.log, raw)
        return self._inputs[raw]


class InTimeOnGrid(InnerClock):
    """An estimator that takes measurements in time, stepped on the replay's grid (module docstring).

    Its :meth:`step` ignores the row's ``u`` and ``y`` (the grid's placement, kept for the
    recording) and consumes the events of ``[t_k, t_(k+1))`` instead. Build it with
    :func:`in_time`, which also gives it the abilities of the estimator it wraps.
    """

    def __init__(self, est: Estimator, events: LogEvents, grid: np.ndarray) -> None:
        self.inner, self.events, self.grid = est, events, np.asarray(grid, dtype=float)
        self.name = est.name
        self._k = 0
        self._i = 0  # next input
        self._j = 0  # next measurement
        self.nis = math.nan
        est.time = self.grid[0]
        self._it, self._u = events.inputs(getattr(est, "replay_input", None) == "imu_body")
        first = int(np.searchsorted(self._it, self.grid[0], side="right")) - 1
        if first >= 0:
            est.hold(self._u[first])
        self._i = first + 1

    # the wrapped estimator's abilities (declared by the class :func:`in_time` builds)
    gate = property(lambda self: self.inner.gate)
    corrections = property(lambda self: self.inner.corrections)
    rejected = property(lambda self: self.inner.rejected)
    immersion = property(lambda self: self.inner.immersion)
    mode = property(lambda self: self.inner.mode)
    switches = property(lambda self: self.inner.switches)
    # the inner filter's robust rule and lock-out record (re-initialisations, a filter given
    # up), for the summary (quadobs.testbed.episode, quadobs.testbed.divergence)
    robust = property(lambda self: getattr(self.inner, "robust", None))
    lockout = property(lambda self: getattr(self.inner, "lockout", None))
    # and the bias filters' steady-offset test, where it is on (quadobs.estimators.bias_states)
    steady_test = property(lambda self: getattr(self.inner, "steady_test", False))
    steady_offsets = property(lambda self: getattr(self.inner, "steady_offsets", []))

    def summary(self) -> dict:
        summary = self.inner.summary  # type: ignore[attr-defined]  # Switching declares it
        return summary()

    def step(self, u, y) -> None:
        """Consume the events of the next grid step and predict to its end."""
        k = self._k
        if k + 1 >= self.grid.size:
            raise QuadobsError(f"{self.name}: stepped past the end of the replay's grid")
        t_next = self.grid[k + 1]
        est, ev = self.inner, self.events
        it, mt, U = self._it, ev.times, self._u
        i, j = self._i, self._j
        nis = math.nan
        while True:
            ti = it[i] if i < it.size else math.inf
            tm = mt[j] if j < mt.size else math.inf
            if min(ti, tm) >= t_next:
                break
            if ti <= tm:
                est.predict(ti)
                est.hold(U[i])
                i += 1
            else:
                est.predict(tm)
                last = j + 1
                while last < mt.size and mt[last] == tm:
                    last += 1
                if last == j + 1:
                    est.correct(ev.measurements[j])
                else:  # one time, one measurement vector (module docstring)
                    est.correct_many(ev.measurements[j:last])
                nis = est.nis
                j = last
        est.predict(t_next)
        self._i, self._j, self._k = i, j, k + 1
        self.nis = nis


_ABILITIES = (Gated, Counted, Immersed, Switching)
_CLASSES: dict[tuple, type] = {}


def in_time(est: Estimator, events: LogEvents, grid: np.ndarray) -> InTimeOnGrid:
    """``est`` wrapped in :class:`InTimeOnGrid`, declaring the abilities ``est`` declares."""
    bases = tuple(a for a in _ABILITIES if isinstance(est, a))
    if Gated in bases and Counted in bases:
        bases = tuple(a for a in bases if a is not Counted)
    cls = _CLASSES.get(bases)
    if cls is None:
        cls = _CLASSES[bases] = type("InTimeOnGrid", (InTimeOnGrid, *bases), {})
    return cls(est, events, grid)
