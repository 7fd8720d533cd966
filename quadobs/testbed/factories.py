"""Estimators built from a scenario: the settings each estimator family takes from a :class:`Scenario`.

The estimator classes (:mod:`quadobs.estimators`) know nothing of scenarios; these
factories read a scenario's system, noise, sampling rates and tuning and build them.
The ``build_*`` functions are the built-in entry points of the group
``quadobs.estimators`` (``factory(scenario, x0, name) -> Estimator``, declared in
``pyproject.toml``); the registry (:mod:`quadobs.testbed.registry`) finds them by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadobs.core.held_input import as_covariance
from quadobs.core.immersion import immerse
from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.augmented_tuning import anchor_scale, derived_observer, guess_variance
from quadobs.estimators.base import Estimator, Gated, Immersed, Subset, Wrapper
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.refined import RefinedObserver
from quadobs.estimators.zonotopic_vehicle import ZonotopicAugmentedEstimator
from quadobs.testbed.ranges_in_time import RangesInTime
from quadobs.testbed.scenario import QuadrotorSpec, Scenario


def output_periods(scenario: Scenario) -> np.ndarray:
    """Sampling period (s) of each output: the ranges, then the airspeed."""
    n = scenario.noise
    periods = [
        scenario.dt * scenario.sample_interval(n.range_rate, "range_rate")
    ] * scenario.beacons.shape[0]
    if scenario.has_wind:
        periods.append(scenario.dt * scenario.sample_interval(n.airspeed_rate, "airspeed_rate"))
    return np.array(periods)


def _matrix_subset(value, idx: tuple[int, ...]):
    if np.ndim(value) == 0:
        return value
    arr = np.asarray(value, dtype=float)
    return arr[list(idx)] if arr.ndim == 1 else arr[np.ix_(idx, idx)]


class OutputSubset(Wrapper, Gated, Immersed, Subset):
    """An augmented observer that reads some of the outputs only (``y[outputs]``): a scenario's variant."""

    inner: AugmentedObserver | RangesInTime

    def __init__(
        self,
        inner: AugmentedObserver | RangesInTime,
        outputs: tuple[int, ...],
        name: str,
        *,
        q: int | None = None,
    ) -> None:
        self.inner = inner
        self.outputs = np.asarray(outputs, dtype=int)
        self.name = name
        self.q = int(self.outputs.max()) + 1 if q is None else int(q)

    def step(self, u, y) -> None:
        """The inner observer's step on ``y[outputs]``; ``y`` must hold all ``q`` outputs."""
        if np.shape(y) != (self.q,):
            raise QuadobsError(f"y: expected shape ({self.q},), got {np.shape(y)}")
        self.inner.step(u, np.asarray(y, dtype=float)[self.outputs])

    def step_and_record(self, u, y, out) -> None:
        self.inner.step_and_record(u, np.asarray(y)[self.outputs], out)

    @property
    def nis(self) -> float:  # type: ignore[override]  # the wrapped estimator's, never set on the wrapper
        return self.inner.nis

    @property
    def gate(self) -> float | None:  # type: ignore[override]  # the wrapped estimator's, never set on the wrapper
        return self.inner.gate

    @property
    def corrections(self) -> int:  # type: ignore[override]  # the wrapped estimator's, never set on the wrapper
        return self.inner.corrections

    @property
    def rejected(self) -> int:  # type: ignore[override]  # the wrapped estimator's, never set on the wrapper
        return self.inner.rejected

    @property
    def immersion(self):
        return self.inner.immersion


def augmented_observer(
    scenario: Scenario, x0: np.ndarray, outputs: tuple[int, ...] | None = None
) -> AugmentedObserver:
    """Theorem 3's observer for ``scenario`` (optionally on a subset of the outputs), starting at ``lift(x0)``.

    ``[observer] tuning = "derived"``: ``V``, ``W`` and the initial covariance by the rule of
    the replay (:func:`derived_settings`), else ``S0``, ``V`` and ``W`` as the table gives them.
    """
    system = scenario.system()
    periods = output_periods(scenario)
    W = scenario.observer.W
    if outputs is not None:
        system = QuadraticSystem(
            system.A, system.B, system.C[list(outputs)], system.d[list(outputs)]
        )
        periods = periods[list(outputs)]
        W = _matrix_subset(W, outputs)
    im = immerse(system, method=scenario.observer.immersion)
    obs = scenario.observer
    if obs.tuning == "derived":
        beacons = scenario.beacons if outputs is None else scenario.beacons[list(outputs)]
        settings = derived_settings(scenario, x0)
        return derived_observer(
            im,
            scenario.dt,
            beacons=beacons,
            x0=x0,
            sample_period=periods,
            gate=obs.gate,
            **settings,
        )
    return AugmentedObserver(
        im,
        scenario.dt,
        V=np.asarray(obs.V, dtype=float),
        W=np.asarray(W, dtype=float),
        P0=np.asarray(obs.S0, dtype=float),
        theta=obs.theta,
        x0=x0,
        sample_period=periods,
        gate=obs.gate,
    )


def derived_settings(scenario: Scenario, x0: np.ndarray) -> dict:
    """The figures of ``[observer] tuning = "derived"``
    (:func:`~quadobs.estimators.augmented_tuning.derived_observer`) from the scenario's statements.

    * ``Vx``: the input noise of the EKF and UKF (:func:`_input_std`, the quadrotor IMU's
      equivalent or ``noise.accel_std``) as an intensity ``sigma_u^2 dt`` on the velocity;
    * ``range_sigma``: ``noise.range_std`` (or its bound's);
    * ``typical_range``: the anchors' median distance from their centroid
      (:func:`~quadobs.estimators.augmented_tuning.anchor_scale`; a log's replay takes its
      median measured range instead);
    * ``P0``: ``max(position_spread, range_sigma)^2`` for a random guess, else the distance
      of the guess from the anchors' centroid plus their extent, squared
      (:func:`~quadobs.estimators.augmented_tuning.guess_variance`, as a replay's guess).

    Raises
    ------
    QuadobsError
        A scenario with an airspeed output (wind) or without a stated range noise.
    """
    if scenario.has_wind:
        raise QuadobsError(
            'observer.tuning: "derived" takes ranges only, and a [wind] scenario has an airspeed '
            "output; give S0, V and W instead"
        )
    sigma = float(scenario.noise.sigma("range"))
    if not sigma > 0.0:
        raise QuadobsError(
            'observer.tuning: "derived" needs the stated range noise (noise.range_std or '
            "range_bound), and the ranges are noise-free; give S0, V and W instead"
        )
    n, dim = scenario.state_dim, scenario.dimension
    Vx = np.zeros((n, n))
    Vx[dim:, dim:] = _input_std(scenario) ** 2 * scenario.dt * np.eye(n - dim)
    init = scenario.initial
    spread = init.position_spread if init.kind == "random" else None
    return {
        "Vx": Vx,
        "range_sigma": sigma,
        "typical_range": anchor_scale(scenario.beacons),
        "P0": guess_variance(scenario.beacons, sigma, offset=spread, x0=x0),
    }


def live_observer(
    scenario: Scenario, x0: np.ndarray, outputs: tuple[int, ...] | None = None
) -> AugmentedObserver | RangesInTime:
    """The ``"augmented"`` estimator (and its variants): :func:`augmented_observer`; with
    ``tuning = "derived"`` in a world that samples its ranges on the grid (no ``[radio]``),
    handed each range at its own time with its own variance and the state-dependent process
    noise, as a replay takes a log's (:class:`~quadobs.testbed.ranges_in_time.RangesInTime`)."""
    obs = augmented_observer(scenario, x0, outputs)
    if scenario.observer.tuning != "derived" or scenario.radio is not None:
        return obs
    return RangesInTime(obs, scenario.dt, scenario.noise.sigma("range"))


@dataclass(frozen=True, eq=False)
class BaselineSettings:
    """What the ``"ekf"`` and ``"ukf"`` estimators of a scenario use (see :func:`baseline_settings`).

    Attributes
    ----------
    dynamics : HeldInputModel
    outputs : OutputModel
    P0 : ndarray (n, n)
    noise_source : str
        ``"sensors"`` (the scenario's true noise levels) or ``"observer"`` (the augmented
        observer's ``W / T``, used when a sensor is noise-free).
    prior_source : str
        ``"initial"`` (the spreads of a random initial guess) or ``"observer"`` (the state
        block of the observer's ``S0``).
    """

    dynamics: HeldInputModel
    outputs: OutputModel
    P0: np.ndarray
    noise_source: str
    prior_source: str


def _state_block(value, N: int, n: int) -> np.ndarray:
    """The ``x`` block (the last ``n`` of ``N`` entries) of a scalar or diagonal setting."""
    if np.ndim(value) == 0:
        return float(value) * np.eye(n)
    arr = np.asarray(value, dtype=float)
    if arr.shape != (N,):
        raise QuadobsError(
            f"observer.S0: expected a scalar or {N} entries (the augmented state), got {arr.size}"
        )
    return np.diag(arr[N - n :])


def initial_covariance(scenario: Scenario) -> tuple[np.ndarray, str]:
    """The initial covariance shared by the baselines and the Cramér-Rao bound, and where it comes from.

    For ``[initial] kind = "random"`` the guess is the truth plus Gaussian errors of
    standard deviation ``position_spread`` (positions) and ``velocity_spread``
    (velocities, wind): its covariance ``diag(spread^2)`` is the true prior
    (``"initial"``). For ``"zero"`` and ``"point"`` there is no distribution to take it
    from, and the state block of the augmented observer's ``S0`` (the paper's tuning) is
    used (``"observer"``), so that all the filters start with the same uncertainty on
    ``x``.
    """
    n, dim = scenario.state_dim, scenario.dimension
    init = scenario.initial
    if init.kind == "random":
        spread = np.full(n, init.velocity_spread)
        spread[:dim] = init.position_spread
        return np.diag(spread**2), "initial"
    N = immerse(scenario.system(), method=scenario.observer.immersion).dim
    return _state_block(scenario.observer.S0, N, n), "observer"


def baseline_settings(scenario: Scenario) -> BaselineSettings:
    """Noise and prior of the EKF and UKF for ``scenario``, chosen for a fair comparison.

    * Measurements: when every sensor the outputs come from is noisy (ranges, and the
      airspeed in wind scenarios), the filters work in the norm space (ranges,
      airspeed) with the sensors' true variances ``R = diag(sigma_h^2)``: this is the
      exact likelihood of Gaussian measurements (for bounded, uniform noise,
      ``sigma = bound / sqrt(3)``, its standard deviation). When a sensor is noise-free there is no true
      level to use (``R = 0`` is not a filter), and they use the augmented observer's
      tuning instead, in the output space: ``R_hl = W_hl / sqrt(T_h T_l)``, exactly the
      observer's ``R``.
    * Process noise: the accelerometer's true noise variance, ``Q_d = sigma_a^2 G G^T`` per physics
      step (zero for a noise-free accelerometer: the MuJoCo vehicle then follows the
      model exactly). For a quadrotor scenario ``sigma_a`` is the level equivalent to the
      IMU and attitude errors of its ``[quadrotor]`` table
      (:func:`quadobs.testbed.imu.input_noise_std`); ``noise.accel_std`` is not used there.
    * Prior: :func:`initial_covariance`.
    """
    system = scenario.system()
    noise = scenario.noise
    stds = [noise.sigma("range")] * scenario.beacons.shape[0]
    offsets = list(0.5 * np.einsum("hi,hi->h", scenario.beacons, scenario.beacons))
    if scenario.has_wind:
        stds.append(noise.sigma("airspeed"))
        offsets.append(0.0)
    sigma = np.array(stds)
    if np.all(sigma > 0):
        outputs = OutputModel(system, np.diag(sigma**2), offsets=np.array(offsets))
        source = "sensors"
    else:
        periods = output_periods(scenario)
        W = as_covariance("observer.W", np.asarray(scenario.observer.W, dtype=float), system.q)
        scale = 1.0 / np.sqrt(periods)
        outputs = OutputModel(system, W * np.outer(scale, scale))
        source = "observer"
    dynamics = HeldInputModel(system, scenario.dt, input_covariance=_input_std(scenario) ** 2)
    P0, prior = initial_covariance(scenario)
    return BaselineSettings(dynamics, outputs, P0, source, prior)


def _input_std(scenario: Scenario) -> float:
    """The input-noise level of the baselines: ``noise.accel_std``, or the quadrotor IMU's equivalent."""
    if scenario.kind == "quadrotor" and scenario.quadrotor is not None:
        from quadobs.testbed.imu import input_noise_std

        spec = scenario.quadrotor
        every = scenario.sample_interval(spec.attitude_rate, "attitude_rate", table="quadrotor")
        return input_noise_std(spec, every, scenario.dt)
    return scenario.noise.sigma("accel")


def robust_settings(scenario: Scenario) -> dict:
    """The filters' robust correction and lock-out from ``[noise]`` (:mod:`quadobs.estimators.robust`).

    ``noise.gate`` (a probability) gives a chi-square gate with one degree of freedom per
    output corrected; ``noise.huber`` Huber's M-estimator; both at once are refused.
    """
    from quadobs.estimators.robust import ChiSquareGate, Huber, LockOut

    noise = scenario.noise
    if noise.gate is not None and noise.huber is not None:
        raise QuadobsError("noise.huber: cannot be combined with noise.gate (choose one rule)")
    rule: ChiSquareGate | Huber | None = None
    if noise.gate is not None:
        rule = ChiSquareGate(noise.gate)
    elif noise.huber is not None:
        rule = Huber(noise.huber)
    return {"robust": rule, "lockout": LockOut(noise.lockout or lockout_window(scenario))}


#: Corrections a lock-out window holds by default (:func:`lockout_window`).
LOCKOUT_CORRECTIONS = 30


def lockout_window(scenario: Scenario) -> float:
    """The default lock-out window (s): the time the scenario's ranges take to bring
    :data:`LOCKOUT_CORRECTIONS` corrections (the radio's rate, or every range output at its
    sample rate). Under the model with a gate of probability 0.999, more than half of 30
    corrections rejected has a probability below 1e-40; a real lock-out is caught in a
    fraction of a second at UWB rates."""
    radio = getattr(scenario, "radio", None)
    if radio is not None:
        rate = radio.rate if radio.rates is None else float(sum(radio.rates))
    else:
        rate = float(np.sum(1.0 / output_periods(scenario)))
    return LOCKOUT_CORRECTIONS / rate


def radio_models(scenario: Scenario) -> dict:
    """``{"measurements": [TdoaModel]}`` for a scenario whose radio sends TDOAs (the filters then
    correct with ``h`` and its Jacobian, :class:`~quadobs.core.measurements.TdoaModel`), else ``{}``."""
    radio = getattr(scenario, "radio", None)
    if radio is None or radio.protocol != "tdoa":
        return {}
    from quadobs.core.measurements import TdoaModel

    return {"measurements": [TdoaModel(scenario.beacons, radio.std)]}


def _gaussian_filter(cls, scenario: Scenario, x0: np.ndarray):
    """A filter of class ``cls`` on the baseline models of ``scenario`` (:func:`baseline_settings`),
    its gate, robust rule (:func:`robust_settings`) and radio (:func:`radio_models`), started at ``x0``."""
    s = baseline_settings(scenario)
    return cls(
        s.dynamics,
        s.outputs,
        x0=x0,
        P0=s.P0,
        gate=scenario.observer.gate,
        **robust_settings(scenario),
        **radio_models(scenario),
    )


def extended_kalman_filter(scenario: Scenario, x0: np.ndarray) -> ExtendedKalmanFilter:
    """The ``"ekf"`` estimator of ``scenario`` (:func:`baseline_settings`), started at ``x0``."""
    return _gaussian_filter(ExtendedKalmanFilter, scenario, x0)


def unscented_kalman_filter(scenario: Scenario, x0: np.ndarray) -> UnscentedKalmanFilter:
    """The ``"ukf"`` estimator of ``scenario`` (:func:`baseline_settings`), started at ``x0``;
    from a multilateration of its first round of ranges where :func:`ukf_starts_from_fix` says so.

    The unscented transform of a range over a prior wider than the anchors' geometry is flat:
    for a mean among the anchors, sigma points ``+-s`` metres either side of it (``s`` the
    prior's spread, ``sqrt(n) sigma`` with the default scaling) lie at nearly the same range
    ``|X_i - a_h| ~ s`` from an anchor, so ``P_xz ~ 0``, ``S ~ s^2`` and each correction
    barely moves the estimate nor shrinks ``P``: the velocity's prior is never reduced and the
    position's spread grows with it. The fix of :mod:`quadobs.estimators.startup` (the
    replay's UKF, :func:`quadobs.testbed.logs.estimators.build_ukf`) replaces that prior by what
    one round of ranges says."""
    if not ukf_starts_from_fix(scenario):
        return _gaussian_filter(UnscentedKalmanFilter, scenario, x0)
    from quadobs.estimators.startup import FixedStartUKF, start_threshold

    est = _gaussian_filter(FixedStartUKF, scenario, x0)
    est.start_from_fix(
        scenario.dimension, start_threshold(scenario.beacons, scenario.noise.sigma("range"))
    )
    return est


def ukf_starts_from_fix(scenario: Scenario) -> bool:
    """Whether the ``"ukf"`` of ``scenario`` starts from a multilateration
    (:mod:`quadobs.estimators.startup`): its outputs are ranges alone, from at least
    ``dimension + 1`` anchors (a fix exists), each with its noise in the range space, and its
    prior position's largest standard deviation exceeds
    :func:`~quadobs.estimators.startup.start_threshold` (half the anchors' extent, at least the
    range noise). Elsewhere (a prior within the anchors' geometry, one anchor, the airspeed
    among the outputs, time differences) it is the plain :class:`UnscentedKalmanFilter`, as before."""
    from quadobs.estimators.startup import start_threshold

    radio = getattr(scenario, "radio", None)
    if radio is not None and radio.protocol == "tdoa":
        return False
    if scenario.has_wind or scenario.beacons.shape[0] < scenario.dimension + 1:
        return False
    sigma = scenario.noise.sigma("range")
    if not sigma > 0:
        return False
    P0, _ = initial_covariance(scenario)
    prior_std = math.sqrt(float(np.max(np.diag(P0)[: scenario.dimension])))
    return prior_std > start_threshold(scenario.beacons, sigma)


def zonotope_estimator(scenario: Scenario, x0: np.ndarray) -> ZonotopicAugmentedEstimator:
    """The ``"zonotope"`` estimator of a scenario.

    The initial box is centred at the initial guess ``x0`` with the half-widths of the
    scenario's ``[zonotope]`` table. The guarantee needs bounded errors, so the scenario must
    use bounded noise (``noise.*_bound``), no outliers, and a non-random initial guess.

    Raises
    ------
    QuadobsError
        Naming the scenario field that makes a guarantee impossible.
    """
    noise = scenario.noise
    sensors = (
        [("range", "range_std")]
        + ([("airspeed", "airspeed_std")] if scenario.has_wind else [])
        + [("accel", "accel_std")]
    )
    for sensor, field_ in sensors:
        if getattr(noise, field_):
            raise QuadobsError(
                f"noise.{field_}: estimator 'zonotope' needs bounded noise, but {sensor} noise is Gaussian "
                f"({getattr(noise, field_)}); use noise.{sensor}_bound"
            )
    if noise.outlier_probability:
        raise QuadobsError(
            "noise.outlier_probability: estimator 'zonotope' needs bounded noise; outliers are unbounded"
        )
    if scenario.initial.kind == "random":
        raise QuadobsError(
            "initial.kind: estimator 'zonotope' needs the true initial state in a known box; a 'random' guess has a "
            "Gaussian (unbounded) error, use 'zero' or 'point' with zonotope.position_bound and velocity_bound"
        )
    system = scenario.system()
    im = immerse(system, method=scenario.observer.immersion)
    dim = scenario.dimension
    spec = scenario.zonotope
    radius = np.full(system.n, spec.velocity_bound)
    radius[:dim] = spec.position_bound
    q_b = scenario.beacons.shape[0]
    offsets = np.zeros(system.q)
    offsets[:q_b] = 0.5 * np.einsum("hi,hi->h", scenario.beacons, scenario.beacons)
    bounds = np.full(system.q, noise.range_bound)
    if scenario.has_wind:
        bounds[q_b] = noise.airspeed_bound
    return ZonotopicAugmentedEstimator(
        im,
        scenario.dt,
        x0=x0,
        radius=radius,
        output_offsets=offsets,
        output_bounds=bounds,
        input_bound=noise.accel_bound,
        max_generators=spec.max_generators or None,
        reduction=spec.reduction,
    )


def refined_observer(scenario: Scenario, x0: np.ndarray) -> RefinedObserver:
    """The ``"augmented-refined"`` estimator of ``scenario``: the augmented observer handing over to an EKF.

    The observer is :func:`augmented_observer`; the EKF it hands over to, and the replay's
    prior, use :func:`baseline_settings` (the true noise levels, or the observer's ``R``
    when a sensor is noise-free) and the scenario's gate.
    """
    s = baseline_settings(scenario)
    obs = augmented_observer(scenario, x0)
    return RefinedObserver(
        obs,
        s.dynamics,
        s.outputs,
        x0=x0,
        P0=s.P0,
        gate=scenario.observer.gate,
        robust=robust_settings(scenario)["robust"],
    )


def onboard_ekf(scenario: Scenario, x0: np.ndarray):
    """The Crazyflie's on-board EKF (:class:`~quadobs.estimators.onboard_ekf.OnboardEKF`) for a quadrotor scenario.

    Its sensor noise is the scenario's: ranges ``noise.range_std`` (1 cm if noise-free),
    accelerometer and gyroscope the ``[quadrotor]`` white noise with each constant bias
    matched over the horizon ``tau`` (:data:`~quadobs.testbed.imu.BIAS_HORIZON`, 1 s:
    ``sigma^2 = std^2 + bias^2 tau / dt``, as :func:`quadobs.testbed.imu.input_noise_std`
    does for the EKF's input); the position
    and velocity prior as the EKF's (:func:`baseline_settings`); the attitude starts
    level with 0.05 rad per axis.
    """
    from quadobs.estimators.onboard_ekf import OnboardEKF, range_model
    from quadobs.testbed.imu import BIAS_HORIZON

    if scenario.kind != "quadrotor":
        raise QuadobsError(
            f'onboard-ekf: needs a body IMU (kind = "quadrotor"), not kind = {scenario.kind!r}'
        )
    q, dt = scenario.quadrotor or QuadrotorSpec(), scenario.dt
    accel = math.sqrt(q.accel_std**2 + q.accel_bias**2 * BIAS_HORIZON / dt)
    gyro = math.sqrt(q.gyro_std**2 + q.gyro_bias**2 * BIAS_HORIZON / dt)
    std = scenario.noise.range_std or 0.01
    return OnboardEKF(
        range_model(scenario.beacons, std),
        dt,
        accel_std=accel,
        gyro_std=gyro,
        x0=x0,
        P0=baseline_settings(scenario).P0,
        gate=scenario.observer.gate,
    )


# -- the built-in entry points: factory(scenario, x0, name) -> Estimator -----------------


def _entry_point(make, doc: str):
    """A factory ``(scenario, x0, name) -> Estimator`` that builds with ``make(scenario, x0)`` and names the result."""

    def factory(scenario: Scenario, x0: np.ndarray, name: str) -> Estimator:
        est = make(scenario, x0)
        est.name = name
        return est

    factory.__name__ = factory.__qualname__ = f"build_{doc}"
    factory.__doc__ = f"Entry point ``{doc}``: :func:`{make.__name__}`, named as requested."
    return factory


build_augmented = _entry_point(live_observer, "augmented")
build_ekf = _entry_point(extended_kalman_filter, "ekf")
build_ukf = _entry_point(unscented_kalman_filter, "ukf")
build_zonotope = _entry_point(zonotope_estimator, "zonotope")
build_refined = _entry_point(refined_observer, "augmented-refined")
build_onboard_ekf = _entry_point(onboard_ekf, "onboard-ekf")


# -- per-anchor range biases as states (quadobs.core.range_bias, quadobs.estimators.bias_states) --


def _range_sigma(scenario: Scenario) -> float:
    """The stated range noise: the radio's ``std``, else ``noise.range_std`` (or its bound's)."""
    radio = getattr(scenario, "radio", None)
    sigma = radio.std if radio is not None else scenario.noise.sigma("range")
    if not sigma > 0.0:
        raise QuadobsError(
            "noise.range_std: estimating range biases needs the stated range noise (positive)"
        )
    return float(sigma)


def bias_filter_models(scenario: Scenario):
    """``(dynamics, outputs, P0)`` of the bias filters' extended state (the vehicle's state and
    a bias per anchor) for ``scenario``, as ``ekf-bias`` and ``ukf-bias`` build them
    (:func:`~quadobs.estimators.bias_states.biased_models`)."""
    from quadobs.core.measurements import RangeModel
    from quadobs.estimators.bias_states import biased_models

    if scenario.has_wind:
        raise QuadobsError("wind: bias states are for range-only systems (no airspeed output)")
    system, sigma = scenario.system(), _range_sigma(scenario)
    P0, _ = initial_covariance(scenario)
    model = RangeModel(scenario.beacons, sigma, bias="state")
    return biased_models(
        system,
        scenario.dt,
        sigma,
        _input_std(scenario),
        P0,
        model,
        bias_std=bias_prior_std(scenario),
    )


def _bias_filter(scenario: Scenario, x0: np.ndarray, cls):
    system = scenario.system()
    dyn, out, Pe = bias_filter_models(scenario)
    xe = np.concatenate([np.asarray(x0, dtype=float), np.zeros(system.q)])
    return cls(dyn, out, x0=xe, P0=Pe, vehicle_n=system.n, **bias_robust_settings(scenario))


def bias_prior_std(scenario: Scenario) -> float | None:
    """The biases' prior standard deviation (m) where the radio states their spread: its
    ``bias_std`` when its biases are drawn with one (``radio.biases`` not given); else ``None``,
    the range model's prior (0.5 m, the upper end of antenna delays). The stated spread is
    the hardware's figure, as ``radio.std`` is the stated range noise (:func:`_range_sigma`):
    a prior wider than it leaves the weak directions (a position offset against a pattern of
    biases) to the data alone."""
    radio = getattr(scenario, "radio", None)
    if radio is None or radio.biases is not None or not radio.bias_std > 0.0:
        return None
    return float(radio.bias_std)


def bias_robust_settings(scenario: Scenario) -> dict:
    """The bias-state filters' robust rule: :func:`robust_settings`, with a chi-square gate made
    a :class:`~quadobs.estimators.robust.SkewedGate` (the same probability, and ranges longer
    than line of sight at the one-sided 95 % level rejected: non-line-of-sight excess is
    positive, and a bias state would otherwise take it in). Where the radio states its
    non-line-of-sight excess (``radio.nlos_median``, ``radio.nlos_shape``), the gate is
    instead an :class:`~quadobs.estimators.robust.ExcessMixture` of that excess at the same
    probability: each range corrected by its expected excess, none rejected for being long
    unless beyond the excess's own tail."""
    from quadobs.estimators.robust import ChiSquareGate, ExcessMixture, SkewedGate

    settings = robust_settings(scenario)
    rule = settings["robust"]
    if isinstance(rule, ChiSquareGate):
        radio = getattr(scenario, "radio", None)
        if radio is not None and radio.nlos_median > 0.0:
            settings["robust"] = ExcessMixture(
                radio.nlos_median, radio.nlos_shape, probability=rule.probability
            )
        else:
            settings["robust"] = SkewedGate(rule.probability)
    return settings


def biased_extended_kalman_filter(scenario: Scenario, x0: np.ndarray):
    """The ``"ekf-bias"`` estimator: the EKF with one range bias per anchor as a state
    (prior :meth:`~quadobs.core.measurements.RangeModel.extra_states`), the scenario's robust rule."""
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter

    return _bias_filter(scenario, x0, BiasedExtendedKalmanFilter)


def biased_unscented_kalman_filter(scenario: Scenario, x0: np.ndarray):
    """The ``"ukf-bias"`` estimator: the UKF with one range bias per anchor as a state."""
    from quadobs.estimators.bias_states import BiasedUnscentedKalmanFilter

    return _bias_filter(scenario, x0, BiasedUnscentedKalmanFilter)


def biased_augmented_observer(scenario: Scenario, x0: np.ndarray):
    """The ``"augmented-bias"`` estimator: Theorem 3's observer with the range biases in the
    immersion (:mod:`quadobs.core.range_bias`): ``V``, ``S0`` and ``theta`` of ``[observer]``,
    ``R`` from the stated range noise."""
    from quadobs.estimators.augmented_bias import BiasedAugmentedObserver

    if scenario.has_wind:
        raise QuadobsError("wind: bias states are for range-only systems (no airspeed output)")
    obs = scenario.observer
    im = immerse(scenario.system(), method=obs.immersion)
    return BiasedAugmentedObserver(
        im,
        scenario.dt,
        sigma=_range_sigma(scenario),
        V=np.asarray(obs.V, dtype=float),
        P0=np.asarray(obs.S0, dtype=float),
        theta=obs.theta,
        x0=x0,
        robust=_huber_only(scenario),
        bias_std=bias_prior_std(scenario) or BiasedAugmentedObserver.DEFAULT_BIAS_STD,
    )


def _huber_only(scenario: Scenario):
    """The observer's robust rule: Huber's when the scenario asks for it; a chi-square gate is
    not applied to it, as its covariance is a tuning (``V``, ``S0``), not a calibrated one, and
    the gate would lock it out of the global convergence it is there for."""
    from quadobs.estimators.robust import Huber

    rule = robust_settings(scenario)["robust"]
    return rule if isinstance(rule, Huber) else None


build_ekf_bias = _entry_point(biased_extended_kalman_filter, "ekf-bias")
build_ukf_bias = _entry_point(biased_unscented_kalman_filter, "ukf-bias")
build_augmented_bias = _entry_point(biased_augmented_observer, "augmented-bias")
