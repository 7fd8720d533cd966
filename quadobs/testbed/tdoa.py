"""TDOA on a fixed grid: a TDoA3-like schedule, pairs as outputs, and a run on the reference flight.

The tag of a TDoA3 system (Bitcraze's Loco Positioning System) hears the anchors' packets in a
random order and forms a difference of distances between each packet and the one before it
from another anchor. Here every ``interval`` physics steps one packet arrives, from an anchor
drawn uniformly among those other than the previous one, and the TDOA of the pair
``(current, previous)`` is

.. math:: d_{ij} = |p - a_i| - |p - a_j| + \\sigma n, \\qquad n \\sim N(0, 1).

On the grid the outputs are the ``m (m - 1)`` ordered pairs (:func:`ordered_pairs`): ``y[h]``
is the TDOA of ``pairs[h]`` at a step where it was measured, NaN elsewhere, so an estimator's
``step(u, y)`` takes TDOA like ranges. :func:`measurements` gives the same samples as
:class:`~quadobs.core.measurements.Measurement` events for the interface in time.

:func:`reference_run` flies the scenario's reference trajectory (the point-mass world's
motion, sampled exactly), measures the acceleration with the scenario's accelerometer noise
and runs estimators on TDOA with the radio's ``std`` and ``rate`` (``[radio]`` with
``protocol = "tdoa"``). Random draws come from streams spawned from the seed, one for the
schedule and one per noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadobs.core.measurements import Measurement, TdoaModel
from quadobs.errors import QuadobsError
from quadobs.estimators.base import Estimator
from quadobs.testbed.scenario import Scenario

__all__ = [
    "PairsInTime",
    "TdoaFlight",
    "WorldTdoaFlight",
    "build_tdoa_handover",
    "build_tdoa_observer",
    "fly_reference",
    "fly_world",
    "measurements",
    "ordered_pairs",
    "reference_run",
    "tdoa3_sequence",
    "tdoa_ekf",
    "tdoa_handover",
    "tdoa_observer",
    "tdoa_outputs",
]


def ordered_pairs(m: int) -> list[tuple[int, int]]:
    """The ``m (m - 1)`` ordered anchor pairs ``(i, j)``, ``i != j``, row-major."""
    if m < 2:
        raise QuadobsError(f"anchors: a TDOA needs at least two anchors, got {m}")
    return [(i, j) for i in range(m) for j in range(m) if i != j]


def tdoa3_sequence(rng: np.random.Generator, m: int, count: int) -> np.ndarray:
    """``count + 1`` anchor indices heard in turn: each uniform among the ``m - 1`` anchors other
    than the one before (TDoA3's random transmission order)."""
    if m < 2:
        raise QuadobsError(f"anchors: a TDOA needs at least two anchors, got {m}")
    seq = np.empty(count + 1, dtype=np.int64)
    seq[0] = rng.integers(m)
    steps = rng.integers(1, m, size=count)  # a shift of 1..m-1 never repeats the anchor
    for k in range(count):
        seq[k + 1] = (seq[k] + steps[k]) % m
    return seq


def tdoa_outputs(
    positions: np.ndarray,
    anchors: np.ndarray,
    interval: int,
    std: float,
    rng_order: np.random.Generator,
    rng_noise: np.random.Generator,
) -> np.ndarray:
    """TDOA outputs on the grid ``(T, m (m - 1))``: one pair every ``interval`` steps, NaN elsewhere.

    Parameters
    ----------
    positions : ndarray (T, dim)
        True positions at the steps.
    anchors : ndarray (m, dim)
    interval : int
        Physics steps between packets (``physics_rate / rate``).
    std : float
        Standard deviation of the TDOA noise (m).
    """
    if interval < 1:
        raise QuadobsError(f"interval: expected a positive number of steps, got {interval}")
    T, m = positions.shape[0], anchors.shape[0]
    pairs = ordered_pairs(m)
    index = {pair: h for h, pair in enumerate(pairs)}
    steps = np.arange(0, T, interval)
    seq = tdoa3_sequence(rng_order, m, steps.size)
    noise = std * rng_noise.standard_normal(steps.size)
    Y = np.full((T, len(pairs)), np.nan)
    for s, k in enumerate(steps):
        i, j = int(seq[s + 1]), int(seq[s])
        p = positions[k]
        d = np.linalg.norm(p - anchors[i]) - np.linalg.norm(p - anchors[j])
        Y[k, index[(i, j)]] = d + noise[s]
    return Y


def measurements(Y: np.ndarray, dt: float, std: float) -> list[list[Measurement]]:
    """The grid outputs of :func:`tdoa_outputs` as events: per step, its TDOA measurements."""
    m = int(round((1.0 + np.sqrt(1.0 + 4.0 * Y.shape[1])) / 2.0))
    pairs = ordered_pairs(m)
    out: list[list[Measurement]] = []
    for k, row in enumerate(Y):
        out.append(
            [
                Measurement(k * dt, "tdoa", float(row[h]), pairs[h], std)
                for h in np.flatnonzero(np.isfinite(row))
            ]
        )
    return out


@dataclass(frozen=True)
class TdoaFlight:
    """The reference flight of a scenario with its TDOA and measured input.

    Attributes
    ----------
    t : ndarray (T,)
        Times of the steps (s).
    truth : ndarray (T + 1, 2 dim)
        ``(p, v)`` at ``t`` and at the end of the last step.
    inputs : ndarray (T, dim)
        Measured acceleration held over each step.
    outputs : ndarray (T, m (m - 1))
        TDOA of :func:`ordered_pairs` at the start of each step, NaN where none.
    pairs : list of (int, int)
    std : float
        The TDOA noise (m).
    """

    t: np.ndarray
    truth: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    pairs: list[tuple[int, int]]
    std: float


def _accel_std(scenario: Scenario) -> float:
    quad = scenario.quadrotor
    return float(scenario.noise.sigma("accel") or (quad.accel_std if quad is not None else 0.0))


def fly_reference(scenario: Scenario, seed: int | None = None) -> TdoaFlight:
    """Sample the scenario's reference motion on the physics grid and its TDOA (``[radio]`` with ``protocol = "tdoa"``).

    The acceleration is held over each step at its value at the step's midpoint, and the
    truth integrated exactly with it, so the truth is the flight the estimators' model
    describes; the accelerometer adds its white noise.
    """
    spec = scenario.tdoa
    if spec is None:
        raise QuadobsError(f'scenario {scenario.name!r}: has no [radio] with protocol = "tdoa"')
    if scenario.has_wind:
        raise QuadobsError(f"scenario {scenario.name!r}: TDOA runs take no wind")
    seed = scenario.seed if seed is None else int(seed)
    rng_order, rng_noise, rng_accel = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, 27]).spawn(3)
    )
    dt, T, dim = scenario.dt, scenario.steps, scenario.dimension
    t = np.arange(T) * dt
    accel = scenario.trajectory.derivative(t + 0.5 * dt, 2)
    x = np.empty((T + 1, 2 * dim))
    x[0] = scenario.true_state(0.0)
    for k in range(T):
        p, v, a = x[k, :dim], x[k, dim:], accel[k]
        x[k + 1, :dim] = p + dt * v + 0.5 * dt * dt * a
        x[k + 1, dim:] = v + dt * a
    inputs = accel + _accel_std(scenario) * rng_accel.standard_normal(accel.shape)
    interval = scenario.sample_interval(spec.rate, "rate", "radio")
    Y = tdoa_outputs(x[:T, :dim], scenario.beacons, interval, spec.std, rng_order, rng_noise)
    pairs = ordered_pairs(scenario.beacons.shape[0])
    return TdoaFlight(t, x, inputs, Y, pairs, float(spec.std))


def reference_run(flight: TdoaFlight, estimators: dict[str, Estimator]) -> dict[str, np.ndarray]:
    """Run each estimator on the flight with ``step(u, y)``; returns its estimates ``(T + 1, n)``,
    row 0 the initial guess, row ``k + 1`` the estimate at the end of step ``k``."""
    out = {}
    for name, est in estimators.items():
        X = np.empty((flight.t.size + 1, flight.truth.shape[1]))
        X[0] = est.x_hat
        for k in range(flight.t.size):
            est.step(flight.inputs[k], flight.outputs[k])
            X[k + 1] = est.x_hat
        out[name] = X
    return out


class PairsInTime(Estimator):
    """Pairs as outputs for an estimator that takes TDOA at their own times: ``step(u, y)``
    corrects with each present pair, holds ``u`` and predicts over ``dt``."""

    def __init__(self, inner: Estimator, pairs, dt: float, std: float) -> None:
        self.inner, self.pairs, self.dt, self.std = inner, list(pairs), float(dt), float(std)
        self.name = inner.name

    @property
    def x_hat(self) -> np.ndarray:
        return self.inner.x_hat

    def step(self, u, y) -> None:
        t = self.inner.time
        for h in np.flatnonzero(np.isfinite(y)):
            self.inner.correct(Measurement(t, "tdoa", float(y[h]), self.pairs[h], self.std))
        self.inner.hold(u)
        self.inner.predict(t + self.dt)


@dataclass(frozen=True)
class WorldTdoaFlight:
    """A MuJoCo flight (point mass or quadrotor) with TDOA estimators aboard (:func:`fly_world`).

    Attributes
    ----------
    t : ndarray (T + 1,)
    truth : ndarray (T + 1, 2 dim)
    estimates : dict of name -> ndarray (T + 1, 2 dim)
        Row ``k``: the estimate at ``t_k`` (before the TDOA of step ``k``).
    flown_on : str or None
        The estimator the quadrotor's controller flew on from ``control.switch_time``.
    crashed_at : float or None
        When the quadrotor crashed (tracking error beyond ``control.crash_distance`` or upside
        down); ``None`` for the point mass.
    """

    t: np.ndarray
    truth: np.ndarray
    estimates: dict[str, np.ndarray]
    flown_on: str | None
    crashed_at: float | None


def _world(scenario: Scenario, seed: int):
    """The MuJoCo world of ``scenario`` (its sensor layer's ranges are not used here)."""
    from quadobs.testbed.sensors import SensorModel, spawn_streams

    sensors = SensorModel(scenario, spawn_streams(seed))
    if scenario.kind == "quadrotor":
        from quadobs.testbed.worlds.quadrotor import QuadrotorWorld

        return QuadrotorWorld(scenario, sensors, 4096)
    from quadobs.testbed.worlds import PointMassWorld

    return PointMassWorld(scenario, sensors, 4096, pipelined=False)


def fly_world(
    scenario: Scenario, make_estimators, flown_on: str | None = None, seed: int | None = None
) -> tuple[WorldTdoaFlight, dict[str, Estimator]]:
    """Run the MuJoCo world of ``scenario`` with TDOA estimators aboard.

    ``make_estimators(x_0)`` builds them (taking pairs as outputs, :func:`ordered_pairs`) from
    the vehicle's true initial state ``x_0`` (for the quadrotor, on the ground); they are
    returned beside the flight. Each step ``k``: the quadrotor's controller reads the estimate of
    ``flown_on`` (from ``control.switch_time`` on; the truth before), the world steps, and the
    TDOA of the step (the schedule and noise of :func:`tdoa_outputs`, from the true position at
    ``t_k``) with the world's input ``u_k`` (the point mass's measured acceleration; the
    quadrotor's ``R~ f~ + g``) go to every estimator's ``step``.
    """
    spec = scenario.tdoa
    if spec is None or scenario.has_wind:
        raise QuadobsError(
            f'scenario {scenario.name!r}: needs a [radio] with protocol = "tdoa", and no wind'
        )
    seed = scenario.seed if seed is None else int(seed)
    scenario = scenario.with_overrides(seed=seed)
    if scenario.kind == "quadrotor":
        if flown_on is None:
            raise QuadobsError("flown_on: a quadrotor needs the estimator it flies on")
        scenario = scenario.with_settings({"control.feedback": flown_on})
    world = _world(scenario, seed)
    estimators = make_estimators(world.state())
    if flown_on is not None and flown_on not in estimators:
        raise QuadobsError(f"flown_on: {flown_on!r} is not one of {sorted(estimators)}")
    T, cols, a = scenario.steps, world.columns, scenario.beacons
    n = 2 * scenario.dimension
    rng_order, rng_noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, 27]).spawn(2)
    )
    interval = scenario.sample_interval(spec.rate, "rate", "radio")
    packets = np.arange(0, T, interval)
    seq = tdoa3_sequence(rng_order, a.shape[0], packets.size)
    noise = spec.std * rng_noise.standard_normal(packets.size)
    index = {pair: h for h, pair in enumerate(ordered_pairs(a.shape[0]))}
    truth = np.empty((T + 1, n))
    est = {name: np.empty((T + 1, n)) for name in estimators}
    y = np.full(len(index), np.nan)
    k0 = 0
    while k0 < T:
        count = world.begin_block(k0, T - k0)
        for j in range(count):
            k = k0 + j
            for name, e in estimators.items():
                est[name][k] = e.x_hat
            world.step(j, est[flown_on][k] if flown_on is not None else None)
            row = world.out[j]
            truth[k] = row[cols.truth]
            y[:] = np.nan
            if k % interval == 0:
                s = k // interval
                i, jj = int(seq[s + 1]), int(seq[s])
                p = truth[k, : a.shape[1]]
                y[index[(i, jj)]] = np.linalg.norm(p - a[i]) - np.linalg.norm(p - a[jj]) + noise[s]
            u = row[cols.u]
            for e in estimators.values():
                e.step(u, y)
        world.commit(count)
        truth[k0 + count] = world.out[count, cols.truth]
        k0 += count
    world.close()
    for name, e in estimators.items():
        est[name][T] = e.x_hat
    crashed_at = getattr(world, "crashed_at", None)
    crashed = None if crashed_at is None else crashed_at * scenario.dt
    flight = WorldTdoaFlight(np.arange(T + 1) * scenario.dt, truth, est, flown_on, crashed)
    return flight, estimators


# -- the TDOA estimators of a scenario ([radio] protocol = "tdoa") -----------------------------


def _radio_tdoa(scenario: Scenario, name: str):
    spec = scenario.tdoa
    if spec is None:
        raise QuadobsError(
            f"estimators: {name!r} takes TDOA, and scenario {scenario.name!r} has no [radio] "
            'with protocol = "tdoa"'
        )
    return spec


def tdoa_ekf(scenario: Scenario, x0: np.ndarray, P0: np.ndarray, time: float = 0.0):
    """The scenario's EKF (:func:`~quadobs.testbed.factories.baseline_settings`) correcting with
    TDOA through :class:`~quadobs.core.measurements.TdoaModel`, started at ``x0, P0`` at ``time``."""
    from quadobs.estimators.kalman import ExtendedKalmanFilter
    from quadobs.testbed.factories import baseline_settings

    spec = _radio_tdoa(scenario, "tdoa-ekf")
    s = baseline_settings(scenario)
    model = TdoaModel(scenario.beacons, spec.std)
    ekf = ExtendedKalmanFilter(s.dynamics, s.outputs, x0=x0, P0=P0, measurements=[model])
    ekf.time = time
    return ekf


def tdoa_observer(scenario: Scenario, x0: np.ndarray, P0: np.ndarray):
    """The TDOA observer (:class:`~quadobs.estimators.tdoa_observer.TdoaObserver`) of the
    scenario, started at ``x0`` with covariance ``P0``: the radio's ``std``, the baseline's
    input noise as the acceleration white noise (``sigma_u^2 dt``), pairs as outputs
    (:func:`ordered_pairs`) for a run on the grid."""
    from quadobs.estimators.tdoa_observer import TdoaObserver
    from quadobs.testbed.factories import baseline_settings

    spec = _radio_tdoa(scenario, "tdoa-observer")
    s = baseline_settings(scenario)
    Q = np.asarray(s.dynamics.input_covariance, dtype=float)  # an array once the model is built
    return TdoaObserver(
        scenario.beacons,
        scenario.dt,
        x0,
        P0=P0,
        std=float(spec.std),
        accel_psd=float(Q[0, 0]) * scenario.dt,
        pairs=ordered_pairs(scenario.beacons.shape[0]),
    )


def tdoa_handover(scenario: Scenario, x0: np.ndarray, P0: np.ndarray):
    """The TDOA observer handing over to :func:`tdoa_ekf`
    (:class:`~quadobs.estimators.tdoa_observer.TdoaHandover`)."""
    from quadobs.estimators.tdoa_observer import TdoaHandover

    def filter_from(x, P, t):
        return tdoa_ekf(scenario, x, P, t)

    return TdoaHandover(tdoa_observer(scenario, x0, P0), filter_from)


def _baseline_P0(scenario: Scenario) -> np.ndarray:
    from quadobs.testbed.factories import baseline_settings

    return np.array(baseline_settings(scenario).P0, dtype=float)


def build_tdoa_observer(scenario: Scenario, x0: np.ndarray, name: str = "tdoa-observer"):
    """Entry point ``tdoa-observer``: :func:`tdoa_observer` with the baseline's ``P0``."""
    _radio_tdoa(scenario, name)
    return tdoa_observer(scenario, x0, _baseline_P0(scenario))


def build_tdoa_handover(scenario: Scenario, x0: np.ndarray, name: str = "tdoa-handover"):
    """Entry point ``tdoa-handover``: :func:`tdoa_handover` with the baseline's ``P0``."""
    _radio_tdoa(scenario, name)
    return tdoa_handover(scenario, x0, _baseline_P0(scenario))
