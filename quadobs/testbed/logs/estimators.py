"""The estimators a replay runs, built from a :class:`ReplaySetup` (the log, the model, the noise).

Names: ``augmented`` (the observer of [IFAC2021, Thm. 3] on the immersion of the replay
model), ``ekf`` (the EKF on the original state, in the range ("norm") space), ``isam2``
(the GTSAM peer, :mod:`quadobs.estimators.gtsam_peer`): the entry points of the group
``quadobs.replay_estimators`` (:data:`REPLAY_ENTRY_POINT_GROUP`) declared in quadobs'
``pyproject.toml``, beside which other packages declare theirs, ``factory(setup, x0,
name) -> Estimator`` with ``setup`` a :class:`ReplaySetup`. The simulated scenarios'
group ``quadobs.estimators`` is kept apart: its factories take a scenario.

Noise (the defaults of :class:`ReplaySetup`; the same for every estimator). The defaults
are round priors, chosen without looking at any log's truth: a metre for a radio range, the
odometry's own root-mean-square speed over a second for the odometry (:func:`log_defaults`),
``1e-3`` rad^2/s for its heading, a m/s^2 over a second for an unknown acceleration, a tenth
of a m/s^2 for an accelerometer. The replay's
self-calibration (:mod:`quadobs.testbed.logs.calibration`, the default of ``quadobs
replay``) replaces the model's process-noise intensity with one it picks from the log's
ranges, never from the truth. No default is tied to one log's scale.

* ranges: a measurement's own standard deviation where the log gives one, else
  ``range_sigma`` (1 m; a TDOA ``sqrt(2) range_sigma``, :meth:`ReplaySetup.measurement_std`);
  where the ``ranges.csv`` of a body-IMU or odometry log states none, ``range_sigma`` is the
  ranges' own noise where they show it (:func:`~quadobs.testbed.logs.range_noise.stated_range_noise`,
  in :func:`log_defaults`; the Plaza logs do not, and keep the prior).
  The augmented observer's output is the half squared range, of variance
  ``rho^2 sigma^2 + sigma^4 / 2`` for each range ``rho`` in time (in the cascade
  ``augmented-heading``, ``rho`` the larger of the measured range and the one its estimate
  predicts: :func:`build_augmented_heading`); on the grid (a replay with a
  sensor layer) ``R = (rho_med range_sigma)^2`` with ``rho_med`` the median measured range;
* odometry (model ``odometry``): a white noise of intensity ``q_xy`` on ``p'`` (it covers the
  speed noise, the wheel-scale error and the heading drift of the odometry, each an error of the
  velocity in proportion to the speed): by default ``q_xy = s_rms^2 T`` (:func:`odometry_noise`)
  with ``s_rms`` the log's root-mean-square odometry speed and ``T`` =
  :data:`ODOMETRY_ERROR_TIME` (1 s), a velocity error of the order of the speed itself over a
  second; the fixed 1 m^2/s before it was that prior for a vehicle at 1 m/s only (Plaza1:
  ``s_rms`` 1.06 m/s, ``q_xy`` 1.13 m^2/s; Plaza2 3.46 m/s, 11.9; the ``rover-room`` robot
  0.36 m/s, 0.13);
* model ``cv``: a white acceleration of intensity ``q_acc`` (1 m^2/s^3);
* model ``imu``: the accelerometer's white noise, of intensity ``q_imu`` (``1e-2`` m^2/s^3)
  on ``v' = u``; the initial velocity with variance 4 m^2/s^2 per axis, as for ``cv``. Where
  the log states its accelerometer's bias (``meta.csv`` key ``accel_bias``, written by
  ``quadobs run --export-log`` with ``accel_noise`` and ``attitude_std``), ``q_imu`` is the live
  filters' rule on the stated figures (:func:`imu_input_noise`); where it states only a density
  (``accel_noise``), its square, floored at :data:`ACCEL_NOISE` for the bias and attitude error
  that the density leaves out (:func:`log_defaults`);
* the auxiliary states ``xi_i = x^T L_i x / 2`` of the augmented observer: the same noise
  ``w`` on ``x'`` drives ``xi_i'`` through ``x^T L_i w``, so in time the observer's process
  noise is ``V(z) = J V_x J^T`` with ``J = [x^T L_1; ...; x^T L_k; I]`` at its estimate
  (:func:`_noise_map`), with no scale constant; its fixed ``V`` (the grid's step) bounds
  ``|p|`` by the largest anchor distance from the origin (``|p| <= max |a_h|`` for a vehicle
  inside the anchors' hull, the norm being convex);
* the initial guess ``x0`` with variance ``P0`` per position axis, from the guess's own
  uncertainty (:func:`initial_variance`): the square of the initial offset where the guess is
  the truth moved by it (``50^2`` m^2 for the replay's default 50 m), else (a guess given as
  such, or the anchors' centroid) ``(|p0 - c| + e)^2``, with ``e`` the anchors' extent, the
  largest distance of an anchor from their centroid ``c``, which bounds the distance of any
  point of their hull from ``c`` (the distance being convex); the augmented observer's initial covariance is that
  of ``lift(x)`` for ``x ~ N(x0, P0 I)`` on the position: ``var xi = P0 |p0|^2 + P0^2``,
  ``cov(xi, p) = P0 p0``; the EKF and the UKF, where ``P0`` exceeds the square of half the
  anchors' extent (the scale on which a range bends over the prior), correct their first
  round of ranges with the linearisation's second-order term as noise and then take the
  position from a multilateration of that round, each range moved by the motion the
  prediction alone gives since it came (:mod:`quadobs.estimators.startup`);
* no gate on the NIS (``gate``: a threshold; a gate at 10.83, the 0.999 quantile of
  chi-square with 1 degree of freedom, rejects the ranges that disagree with a drifting
  odometry heading, and the estimates diverge).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from quadobs.core.immersion import immerse
from quadobs.core.measurements import (
    RANGE_BIAS_PRIOR_STD,
    MeasurementModel,
    RangeModel,
    TdoaModel,
)
from quadobs.core.system import (
    QuadraticSystem,
    constant_velocity_system,
    odometry_system,
    vehicle_system,
)
from quadobs.errors import QuadobsError
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.augmented_tuning import (
    anchor_scale,
    derived_observer,
    guess_variance,
    state_noise_map,
)
from quadobs.estimators.base import Estimator
from quadobs.estimators.kalman import (
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.robust import ExcessMixture
from quadobs.estimators.startup import (
    FixedStartEKF,
    FixedStartUKF,
    MultilaterationStart,
    start_threshold,
)
from quadobs.testbed.imu import BIAS_HORIZON
from quadobs.testbed.logs.height_estimators import known_offsets
from quadobs.testbed.logs.start_prior import StartPrior, set_velocity_prior, start_prior

__all__ = [
    "ACCEL_NOISE",
    "REPLAY_ENTRY_POINT_GROUP",
    "REPLAY_ESTIMATORS",
    "TUNING",
    "ReplaySetup",
    "accel_noise",
    "build_augmented_bias",
    "build_augmented_heading",
    "build_ekf_bias",
    "build_ekf_heading",
    "build_isam2",
    "build_onboard_ekf",
    "build_onboard_ekf_bias",
    "build_replay_estimators",
    "build_ukf_bias",
    "build_ukf_heading",
    "build_ukf_height_lever",
    "build_ukf_lever",
    "gyro_noise",
    "imu_input_noise",
    "initial_variance",
    "log_defaults",
    "log_range_std",
    "odometry_noise",
    "parse_tuning",
    "replay_estimator_names",
    "replay_setup",
]

#: The entry-point group of the estimators of logged data.
REPLAY_ENTRY_POINT_GROUP = "quadobs.replay_estimators"


@dataclass(frozen=True, eq=False)
class ReplaySetup:
    """What the replay's estimators are built from.

    Attributes
    ----------
    beacons : ndarray (q, dim)
    dt : float
    model : {"odometry", "cv", "imu"}
    heading0 : float
        The odometry's heading at the first step (rad; 0 for an accelerometer log).
    range_median : float
        Median measured range (m).
    range_sigma, q_xy, q_theta, q_acc, q_imu, gate : float
        Noise settings (module docstring).
    P0 : float
        Variance of the initial position guess per axis (m^2); :func:`replay_setup` derives it
        (:func:`initial_variance`) unless it is given.
    range_bias : {0, 1}
        1: the GTSAM peer estimates a constant range bias per anchor as a state
        (:class:`~quadobs.estimators.gtsam_peer.PeerNoise` ``bias="state"``); 0 (default): none.
    input_kind : {"odometry", "imu", "imu_body", "none"}
        The log's inputs (:class:`~quadobs.testbed.logs.format.RangeLog`).
    kinds : tuple of str
        The kinds of measurement the log holds (``"range"``, ``"tdoa"``).
    frame : {"enu", "ned"}
        The log's navigation frame (z up or down).
    gravity : float
        The log's magnitude of gravity (m/s^2).
    attitude0 : ndarray (4,) or None
        The body-to-navigation quaternion ``(qw, qx, qy, qz)`` at the start: the first sample
        of the log's ``attitude.csv``, else the odometry heading's yaw where the log gives
        one, else None (unknown).
    imu_period : float or None
        The median interval of a body IMU's samples (s), else None.
    gyro_noise : float or None
        The log's stated gyroscope white-noise density (rad/s/sqrt(Hz); ``meta.csv``), else None.
    gyro_bias : float or None
        The log's stated standard deviation of the gyroscope's constant bias per axis (rad/s;
        ``meta.csv``), else None.
    range_errors : str
        The log's stated error model of its ranges (``meta.csv`` ``range_errors``):
        ``"gaussian"``, ``"nlos"``, or ``""`` (unknown, as ``"nlos"``).
    range_std_stated : float or None
        The median of the standard deviations that ``ranges.csv`` states, where every row
        states one (its ``std`` column), else None.
    alignment0 : ndarray (4,) or None
        Where a body-IMU log has no ``attitude.csv``: the initial alignment's quaternion (the
        tilt from the first half second's median specific force, heading zero;
        :func:`~quadobs.testbed.attitude.initial_alignment`), else None.
    nlos_median, nlos_shape : float or None
        The log-normal non-line-of-sight excess of the ranges (median, m; shape), stated by the
        log (``meta.csv``) or estimated from it
        (:func:`~quadobs.testbed.logs.excess_model.excess_model`); None: unknown (the
        bias-state filters then take the one-sided gate,
        :func:`~quadobs.testbed.logs.bias_estimators.range_rule`).
    nlos_prior : float
        The stationary probability that a range is non-line-of-sight in the excess mixture's
        per-anchor chain of sight (:class:`~quadobs.estimators.robust.ExcessMixture` ``nlos``;
        ``--tune nlos_prior=...``); the default is the mixture's uninformed 0.5
        (``docs/error-sources.md``, "Stress": what lower values do on the flights).
    q_xy_heading : float
        The white noise on the position of the heading filters (m^2/s per axis;
        :func:`build_ekf_heading`): the speed's noise alone, where ``q_xy`` of the model
        ``odometry`` also carries the heading's drift. Its prior is ``q_xy``'s (1 m^2/s; a log
        of odometry sets ``q_xy = s_rms^2 T`` and this to ``(HEADING_SPEED_ERROR s_rms)^2 T``,
        :func:`log_defaults`).
    start : StartPrior or None
        Whether the log's first half second shows the vehicle at rest, and the velocity's
        bound that would follow, and the velocity that the ranges of that window tell
        (:mod:`~quadobs.testbed.logs.start_prior`): the filters' prior where it is applied
        (``--tune velocity_std=log``), else reported only.
    velocity_std : float or None
        The velocity's prior standard deviation per axis (m/s) of the filters with a velocity
        state (``--tune velocity_std=...``); None: the ``start``'s prior where
        ``--tune velocity_std=log`` applies it, else
        :data:`~quadobs.testbed.logs.start_prior.UNKNOWN_VELOCITY_STD`
        (:func:`~quadobs.testbed.logs.start_prior.velocity_prior`).
    steady_test : float
        1 (the default) or 0: the steady-offset test of the bias filters under the excess
        mixture (``ekf-bias-imu-nlos``; :meth:`quadobs.estimators.bias_states._VehicleBlock._steady`,
        ``--tune steady_test=0`` turns it off).
    bias_prior : float or None
        The prior standard deviation (m) of each anchor's range bias in the filters that hold
        the biases as states (``ekf-bias``, ``ukf-bias``, ``augmented-bias``, ``ekf-bias-imu``,
        ``ekf-bias-imu-nlos``; :meth:`bias_prior_std`). None (the default): the range model's
        0.5 m. ``--tune bias_prior=log`` asks the self-calibration for the spread of its
        calibrated biases (:func:`~quadobs.testbed.logs.calibration.biases_spread`; measured,
        not the default: docs/error-sources.md). The filters that hold the anchors' heights
        (``ekf-height``, ``ukf-height``, ``augmented-height``, ``ukf-height-lever``) keep the
        range model's 0.5 m: their calibrated biases also hold the heights' share.
    offsets : (ndarray (q,), ndarray (q, q)) or None
        The prior mean (m^2) and covariance (m^4) of the anchors' squared-range offsets
        ``e_h = dz_h^2 / 2`` where the log states the anchors' heights and the tag's
        (:func:`~quadobs.testbed.logs.height_estimators.known_offsets`), else None: the
        filters that hold the offsets take the storey's prior
        (:data:`~quadobs.testbed.logs.height_estimators.E_MEAN`, ``E_STD``).
    stated_heights : float
        1 (the default) or 0: whether the filters take :attr:`offsets` (``--tune
        stated_heights=0`` turns them off; the self-calibration does where the ranges
        contradict them, :func:`~quadobs.testbed.logs.calibration.check_stated_heights`).
    lever_arm : (float, float) or None
        The tag's place on the vehicle as the log states it (``meta.csv`` ``tag_x``, ``tag_y``:
        forwards and to the left of the odometry's point, m), else None: the filters that hold
        the lever arm (``ukf-lever``, ``ukf-height-lever``) start from it with the prior
        :data:`~quadobs.estimators.heading_ekf.STATED_LEVER_STD` per axis, else from zero with
        :data:`~quadobs.estimators.heading_ekf.LEVER_ARM_STD`.
    tag_pattern : float
        1 or 0 (the default): whether ``ukf-height-lever`` holds the tag's pattern as two states
        (:data:`~quadobs.estimators.heading_ekf.TAG_PATTERN_STD`); set by the self-calibration
        where the held-out ranges ask for it (step 10,
        :mod:`~quadobs.testbed.logs.constants_start`), or by ``--tune tag_pattern``.
    constants_start : dict or None
        ``{filter name: (mean (c,), covariance (c, c))}``: the prior of the constant states of
        the filter of that name (a member of an average too): the constants a first pass
        through the log ended with, set by the self-calibration where the second pass from
        them predicts the held-out ranges at least as well
        (:mod:`~quadobs.testbed.logs.constants_start`); the filters not named keep their own.
    """

    beacons: np.ndarray
    dt: float
    model: str
    heading0: float
    range_median: float
    range_sigma: float = 1.0
    q_xy: float = 1.0
    q_theta: float = 1e-3
    q_acc: float = 1.0
    q_imu: float = 1e-2
    gate: float | None = None
    P0: float = 2500.0
    input_kind: str = "odometry"
    range_bias: float = 0.0
    kinds: tuple = ("range",)
    frame: str = "enu"
    gravity: float = 9.80665
    attitude0: np.ndarray | None = None
    imu_period: float | None = None
    gyro_noise: float | None = None
    gyro_bias: float | None = None
    range_errors: str = ""
    range_std_stated: float | None = None
    q_xy_heading: float = 1.0
    alignment0: np.ndarray | None = None
    nlos_median: float | None = None
    nlos_shape: float | None = None
    start: StartPrior | None = None
    nlos_prior: float = ExcessMixture.nlos
    velocity_std: float | None = None
    steady_test: float = 1.0
    bias_prior: float | None = None
    offsets: tuple | None = None
    stated_heights: float = 1.0
    lever_arm: tuple | None = None
    tag_pattern: float = 0.0
    constants_start: dict | None = None
    system: QuadraticSystem = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.range_bias not in (0, 1):
            raise QuadobsError(
                f"range_bias: expected 0 (off) or 1 (a state), got {self.range_bias!r}"
            )
        for key in ("steady_test", "stated_heights", "tag_pattern"):  # the setup's switches
            if getattr(self, key) not in (0, 1):
                raise QuadobsError(f"{key}: expected 0 (off) or 1 (on), got {getattr(self, key)!r}")
        for key in TUNING:
            if key in ("range_bias", *SWITCHES):
                continue
            value = getattr(self, key)
            if not (key in ("gate", "velocity_std", "bias_prior") and value is None) and not (
                isinstance(value, (int, float)) and 0 < value < math.inf
            ):
                raise QuadobsError(
                    f"{key}: expected a positive finite number{' or none' if key == 'gate' else ''}, got {value!r}"
                )
        dim = self.beacons.shape[1]
        inputs = 3 if self.input_kind == "odometry" else dim
        if self.model == "odometry" and dim != 2:
            raise QuadobsError("model odometry: planar logs only")
        make = {
            "odometry": lambda: odometry_system(self.beacons),
            "cv": lambda: constant_velocity_system(self.beacons, inputs),
            "imu": lambda: vehicle_system(dim, self.beacons),
        }.get(self.model)
        if make is None:
            raise QuadobsError(f"model: expected odometry, cv or imu, got {self.model!r}")
        object.__setattr__(self, "system", make())

    @property
    def n(self) -> int:
        return self.system.n

    def bias_prior_std(self) -> float:
        """The range biases' prior standard deviation (m): :attr:`bias_prior`, else the
        range model's (:data:`~quadobs.core.measurements.RANGE_BIAS_PRIOR_STD`, 0.5 m)."""
        return RANGE_BIAS_PRIOR_STD if self.bias_prior is None else float(self.bias_prior)

    @property
    def dim(self) -> int:
        """Dimension of the positions."""
        return int(self.beacons.shape[1])

    def measurement_std(self) -> dict:
        """The standard deviation by kind given to the measurements that the log gives none:
        ``range_sigma``, and ``sqrt(2) range_sigma`` for a TDOA (the difference of two ranges of
        independent errors). In the augmented observer a range's own standard deviation sets
        its output's variance ``rho^2 sigma^2 + sigma^4 / 2``
        (:meth:`~quadobs.core.measurements.RangeModel.quadratic_output`)."""
        return {"range": self.range_sigma, "tdoa": math.sqrt(2.0) * self.range_sigma}

    def measurement_models(self) -> list:
        """The models of the log's measurement kinds: ranges and TDOA with ``range_sigma``
        (a TDOA is the difference of two ranges of independent errors: ``sqrt(2) range_sigma``)."""
        models: list[MeasurementModel] = []
        if "range" in self.kinds:
            models.append(RangeModel(self.beacons, self.range_sigma))
        if "tdoa" in self.kinds:
            models.append(TdoaModel(self.beacons, self.measurement_std()["tdoa"]))
        return models


#: ``--tune KEY=log``: a setting taken from the log itself. ``velocity_std=log``: the velocity's
#: prior from the log's start where it is identified
#: (:func:`~quadobs.testbed.logs.start_prior.start_prior`), else the unknown start's;
#: ``bias_prior=log``: the spread of the self-calibration's biases
#: (:func:`~quadobs.testbed.logs.calibration.biases_spread`).
FROM_LOG = "log"
LOG_VELOCITY = FROM_LOG


def velocity_from_log(options) -> bool:
    """Whether the tuning asks for the velocity's prior from the log's start
    (``velocity_std=log``, :data:`LOG_VELOCITY`)."""
    return bool(options) and options.get("velocity_std") == LOG_VELOCITY


def tuning_fields(options) -> dict:
    """The tuning as :class:`ReplaySetup`'s fields: ``velocity_std=log`` goes to
    :func:`log_frame` (:func:`velocity_from_log`), not to the setup; ``bias_prior=log`` is the
    self-calibration's to resolve (a number by then,
    :func:`~quadobs.testbed.logs.calibration.calibrate`); ``anchor_sigma`` and ``stated_std``
    act on the log before the replay
    (:func:`~quadobs.testbed.logs.range_noise.with_anchor_noise`)."""
    return {
        k: v
        for k, v in (options or {}).items()
        if not (k in ("velocity_std", "bias_prior") and v == FROM_LOG)
        and k not in ("anchor_sigma", "stated_std")
    }


#: The settings of :class:`ReplaySetup` a user may tune (``quadobs replay --tune KEY=VALUE``).
TUNING = (
    "range_sigma", "q_xy", "q_theta", "q_acc", "q_imu", "gate", "P0", "range_bias",
    "q_xy_heading", "velocity_std", "nlos_prior", "steady_test", "bias_prior", "stated_heights",
    "anchor_sigma", "tag_pattern", "stated_std",
)  # fmt: skip
#: The tuning's switches (0 off, 1 on).
SWITCHES = ("steady_test", "stated_heights", "anchor_sigma", "tag_pattern", "stated_std")


def parse_tuning(settings) -> dict:
    """``["q_xy=1", "gate=none", ...]`` as setup options (``gate=none``: no gate); one-line errors naming the setting."""
    out: dict[str, float | str | None] = {}
    for text in settings:
        key, sep, raw = text.partition("=")
        key = key.strip()
        if not sep or key not in TUNING:
            raise QuadobsError(
                f"--tune: expected KEY=VALUE with KEY one of {', '.join(TUNING)}, got {text!r}"
            )
        if key == "gate" and raw.strip().lower() == "none":
            out[key] = None
            continue
        if key in ("velocity_std", "bias_prior") and raw.strip().lower() == FROM_LOG:
            out[key] = FROM_LOG  # the log's start prior (start_prior), the biases' spread
            continue
        try:
            out[key] = float(raw)
        except ValueError:
            raise QuadobsError(f"--tune {key}: expected a number, got {raw.strip()!r}") from None
        if key in SWITCHES and out[key] not in (0.0, 1.0):
            raise QuadobsError(f"--tune {key}: expected 0 (off) or 1 (on), got {raw.strip()!r}")
        if key == "nlos_prior" and not 0.0 < out[key] < 1.0:  # type: ignore[operator]
            raise QuadobsError(
                f"--tune nlos_prior: expected a probability in (0, 1), got {raw.strip()!r}"
            )
    return out


def initial_variance(log, offset: float | None = None, range_sigma: float = 1.0, x0=None) -> float:
    """The variance ``P0`` (m^2 per axis) of an initial position guess (module docstring).

    ``offset``: the guess is the truth moved by that distance (m): ``max(offset, sigma)^2``, a
    guess at the truth itself being as uncertain as one range (``range_sigma``). Otherwise the
    vehicle is taken to be within the anchors' hull, every point of which lies within the
    extent ``e = max_h |a_h - c|`` of their centroid ``c`` (the distance being convex): a guess
    ``x0`` (default ``c``) is then within ``|p0 - c| + e`` of it, and ``P0`` is that squared.
    """
    return guess_variance(log.beacons, range_sigma, offset=offset, x0=x0)


#: The time (s) over which the odometry's velocity may be wrong by its own typical speed
#: (:func:`odometry_noise`).
ODOMETRY_ERROR_TIME = 1.0
#: The least speed (m/s) of :func:`odometry_noise`: a log that never moves still gets a
#: process noise (a centimetre per second over a second).
ODOMETRY_SPEED_FLOOR = 0.01
#: The heading filters' share of the odometry's velocity error (:func:`log_defaults`): their
#: position noise is the error of the speed's magnitude alone (a wheel's scale, a few per cent;
#: slip in turns), taken as an eighth of the speed over :data:`ODOMETRY_ERROR_TIME` (the middle,
#: on a log scale, of the shares 0.07 to 0.25 that the calibration picked from held-out ranges
#: on Plaza1, Plaza2 and the simulated wheeled robot: docs/error-sources.md); the error across
#: the track, up to the whole speed where the heading is wrong, is their heading state.
HEADING_SPEED_ERROR = 0.125


def odometry_noise(log) -> float:
    """The default odometry process-noise intensity ``q_xy`` (m^2/s) of a log: ``s_rms^2 T``.

    ``s_rms^2`` is the time-weighted mean of the squared odometry speed (each sample held to
    the next, as the replay integrates it), at least :data:`ODOMETRY_SPEED_FLOOR` squared;
    ``T`` is :data:`ODOMETRY_ERROR_TIME`. The errors that the odometry model leaves to this
    noise (the speed's scale, the heading's drift) are errors of the velocity in proportion to
    the speed, so the intensity scales with the square of the speed, and no constant of one
    log's scale enters: a robot at 0.35 m/s in a room gets 0.12 m^2/s, a car at 3.5 m/s 12.
    """
    t, speed = log.inputs[:, 0], log.inputs[:-1, 1]
    span = np.diff(t)
    total = float(np.sum(span))
    mean_square = float(np.sum(span * speed * speed)) / total if total > 0 else 0.0
    return max(mean_square, ODOMETRY_SPEED_FLOOR**2) * ODOMETRY_ERROR_TIME


def log_defaults(log) -> dict:
    """The setup options whose defaults a log sets (:class:`ReplaySetup`): ``q_xy`` of an
    odometry log (:func:`odometry_noise`) and the heading filters' ``q_xy_heading``, the share
    :data:`HEADING_SPEED_ERROR` of it squared (their position noise is the error of the speed's
    magnitude alone, a part of what ``q_xy`` carries; the fixed 1 m^2/s before it was the
    prior of a vehicle at 8 m/s, 560 times this one for a robot at 0.34 m/s, which the
    calibration kept where its test did not decide: docs/error-sources.md), ``q_imu`` from the IMU's stated figures
    (:func:`imu_input_noise`), ``range_sigma`` from the ranges of a log that states none
    (:func:`~quadobs.testbed.logs.range_noise.stated_range_noise`); empty for a log that gives
    none of them. :func:`replay_setup` fills
    them where ``options`` does not set them; the self-calibration takes them as its prior."""
    out = {}
    if log.input_kind == "odometry" and log.inputs.shape[0] >= 2:
        out["q_xy"] = odometry_noise(log)
        out["q_xy_heading"] = HEADING_SPEED_ERROR**2 * out["q_xy"]
    q = imu_input_noise(log)
    if q is not None:
        out["q_imu"] = q
    from quadobs.testbed.logs.range_noise import OWN_NOISE_KINDS, stated_range_noise

    sigma = stated_range_noise(log) if log.input_kind in OWN_NOISE_KINDS else None
    if sigma is not None:  # ranges stating no std: their own noise, where they show it
        out["range_sigma"] = sigma
    return out


def replay_setup(
    log, world, options: dict | None = None, initial_offset: float | None = None, x0=None
) -> ReplaySetup:
    """The setup of a replay of ``log`` on ``world`` (:class:`~quadobs.testbed.worlds.replay.ReplayWorld`),
    ``options`` its noise settings; ``P0``, unless given, from the initial guess ``x0`` or its
    ``initial_offset`` from the truth (:func:`initial_variance`)."""
    from quadobs.testbed.worlds.replay import dead_reckoning

    options = {**log_defaults(log), **dict(options or {})}
    if "P0" not in options:
        sigma = options.get("range_sigma", ReplaySetup.range_sigma)
        options["P0"] = initial_variance(log, initial_offset, sigma, x0)

    heading = (
        float(dead_reckoning(log, world.times[:1])[1][0]) if log.input_kind == "odometry" else 0.0
    )
    kinds = tuple(k for k, table in (("range", log.ranges), ("tdoa", log.tdoa)) if table.shape[0])
    return ReplaySetup(
        log.beacons,
        world.dt,
        world.model,
        heading,
        _typical_range(log),
        input_kind=log.input_kind,
        kinds=kinds,
        **log_frame(log, options.get("range_sigma"), velocity_from_log(options)),
        **tuning_fields(options),
    )


def log_frame(log, range_sigma: float | None = None, apply_start: bool = False) -> dict:
    """The setup's fields read from the log's frame, attitude and IMU: ``frame``, ``gravity``,
    ``attitude0``, ``imu_period``, ``gyro_noise``, ``gyro_bias``, ``range_errors``,
    ``range_std_stated``, the anchors' squared-range ``offsets`` where the log states the
    heights (:func:`~quadobs.testbed.logs.height_estimators.known_offsets`), and the velocity's prior at the ``start``
    (:func:`~quadobs.testbed.logs.start_prior.start_prior`, ``range_sigma`` the standard
    deviation of a range that states none; :class:`ReplaySetup`)."""
    attitude0 = None
    if log.attitude is not None and log.attitude.shape[0]:
        attitude0 = np.array(log.attitude[0, 1:5], dtype=float)
    elif math.isfinite(log.heading0):
        attitude0 = np.array([math.cos(log.heading0 / 2), 0.0, 0.0, math.sin(log.heading0 / 2)])
    period = None
    if log.input_kind == "imu_body" and log.inputs.shape[0] > 1:
        from quadobs.testbed.logs.schema import sampling_period

        period = sampling_period(log.inputs[:, 0])
    gyro = float(getattr(log, "gyro_noise", math.nan))
    gyro_bias = float(getattr(log, "gyro_bias", math.nan))
    alignment0 = None
    if log.input_kind == "imu_body" and attitude0 is None and log.inputs.shape[0]:
        alignment0 = _alignment(log)
    return {
        "frame": log.frame,
        "gravity": float(log.gravity),
        "attitude0": attitude0,
        "imu_period": period,
        "gyro_noise": gyro if math.isfinite(gyro) else None,
        "gyro_bias": gyro_bias if math.isfinite(gyro_bias) else None,
        "range_errors": str(getattr(log, "range_errors", "")),
        "range_std_stated": log_range_std(log),
        "alignment0": alignment0,
        "start": start_prior(log, range_sigma=range_sigma, apply=apply_start),
        "offsets": known_offsets(log),
        "lever_arm": getattr(log, "tag_offset", None),
    }


def log_range_std(log) -> float | None:
    """The median of the log's stated range standard deviations where every row states one
    (:attr:`ReplaySetup.range_std_stated`), else None."""
    std = np.asarray(getattr(log, "range_std", np.empty(0)), dtype=float)
    if std.size == 0 or not np.all(np.isfinite(std)):
        return None
    return float(np.median(std))


def _alignment(log) -> np.ndarray:
    """The initial alignment of a body IMU (:func:`~quadobs.testbed.attitude.initial_alignment`)
    in the log's frame: it turns the resting specific force to ``+z`` (``enu``, gravity down);
    in ``ned`` that rotation is followed by the turn by ``pi`` about ``x`` (``qw, qx, qy, qz ->
    -qx, qw, -qz, qy``), which takes ``+z`` to ``-z``."""
    from quadobs.testbed.attitude import initial_alignment

    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    q, _ = initial_alignment(t, f, w, float(log.gravity))
    if log.frame == "ned":
        q = np.array([-q[1], q[0], -q[3], q[2]])
    return q


def _typical_range(log) -> float:
    """The median measured range; for a log without ranges, the median distance of the anchors
    from their centroid (the geometry's scale)."""
    if log.ranges.shape[0]:
        return float(np.median(log.ranges[:, 2]))
    return anchor_scale(log.beacons)


def _acceleration_noise(s: ReplaySetup) -> float:
    """The white acceleration's intensity (m^2/s^3) of a model with a velocity."""
    return s.q_imu if s.model == "imu" else s.q_acc


def _process_noise(s: ReplaySetup) -> np.ndarray:
    """Continuous intensity on ``x`` (module docstring)."""
    if s.model == "odometry":
        return s.q_xy * np.eye(2)
    return np.diag([0.0] * s.dim + [_acceleration_noise(s)] * s.dim)


def build_augmented(s: ReplaySetup, x0: np.ndarray, name: str = "augmented") -> AugmentedObserver:
    """The observer of [IFAC2021, Thm. 3] on the immersion of the replay model [ACC2024, Alg. 1],
    tuned by the rule that a simulated scenario's ``[observer] tuning = "derived"`` also takes
    (:func:`~quadobs.estimators.augmented_tuning.derived_observer`): the setup's noise, anchors,
    median range and prior.

    Ranges only: a log holding TDOA is refused by name (its measurements have no
    quadratic-output form in this observer).
    """
    if "tdoa" in s.kinds:
        raise QuadobsError(
            f"estimators: {name!r} takes ranges only, and the log holds TDOA "
            "(no quadratic-output form in the observer; use ekf or ukf)"
        )
    x0 = np.asarray(x0, dtype=float)
    est = derived_observer(
        immerse(s.system), s.dt, Vx=_process_noise(s), beacons=s.beacons,
        range_sigma=s.range_sigma, typical_range=s.range_median, x0=x0, P0=s.P0, gate=s.gate,
    )  # fmt: skip
    est.name = name
    return est


def _noise_map(s: ReplaySetup, im, extra: np.ndarray | None = None):
    """``z -> V(z)``: the model's white noise on ``x'`` mapped into the augmented state at the
    estimate (module docstring). With ``xi_i = x^T L_i x / 2`` (the immersion's auxiliary forms),
    a noise ``w`` of intensity ``V_x`` on ``x'`` drives ``xi_i'`` by ``x^T L_i w``, so
    ``V(z) = J V_x J^T`` with ``J = [x^T L_1; ...; x^T L_k; I_n]``: no constant of any scale.
    ``extra`` ``(n, n)``, read at each call, is added to ``V_x`` (an input's error that its
    owner updates in place: :class:`~quadobs.estimators.heading_ekf.HeadingCascade`)."""
    return state_noise_map(im, _process_noise(s), extra)


def build_ekf(s: ReplaySetup, x0: np.ndarray, name: str = "ekf", cls=FixedStartEKF):
    """The EKF on ``x`` in the range space (:class:`~quadobs.estimators.kalman.OutputModel` with
    offsets); where its prior position is wider than half the anchors' extent, its first round
    of ranges weighs the linearisation's second-order term and then fixes the position by
    multilateration (:mod:`quadobs.estimators.startup`)."""
    dyn = HeldInputModel(s.system, s.dt, V=_process_noise(s))
    out = OutputModel(
        s.system, s.range_sigma**2, offsets=0.5 * np.einsum("hi,hi->h", s.beacons, s.beacons)
    )
    x0, P0 = np.array(x0, dtype=float), np.diag(np.full(s.n, s.P0))
    if s.n > s.dim:  # the velocity, for the models that have one
        set_velocity_prior(s, x0, P0, s.dim)
    est = cls(dyn, out, x0=x0, P0=P0, gate=s.gate, measurements=s.measurement_models())
    if isinstance(est, MultilaterationStart) and "range" in s.kinds:
        est.start_from_fix(s.dim, start_threshold(s.beacons, s.range_sigma))
    est.name = name
    return est


def build_ukf(s: ReplaySetup, x0: np.ndarray, name: str = "ukf") -> UnscentedKalmanFilter:
    """The UKF on ``x``, with the EKF's models, noise and start-up (:func:`build_ekf`)."""
    return build_ekf(s, x0, name, FixedStartUKF)


def build_isam2(s, x0: np.ndarray, name: str = "isam2") -> Estimator:
    """Entry point ``isam2``: the GTSAM peer (:func:`quadobs.testbed.logs.peer.build_peer`); logged data only."""
    if not isinstance(s, ReplaySetup):
        raise QuadobsError(
            f"estimators: {name!r} runs on logged data only (quadobs replay), not in a simulated scenario"
        )
    from quadobs.testbed.logs.peer import build_peer

    return build_peer(s, x0, name)


def build_tdoa_observer(s: ReplaySetup, x0: np.ndarray, name: str = "tdoa-observer") -> Estimator:
    """Entry point ``tdoa-observer`` (:mod:`quadobs.testbed.logs.tdoa_estimators`)."""
    from quadobs.testbed.logs import tdoa_estimators

    return tdoa_estimators.build_tdoa_observer(s, x0, name)


def build_tdoa_handover(s: ReplaySetup, x0: np.ndarray, name: str = "tdoa-handover") -> Estimator:
    """Entry point ``tdoa-handover`` (:mod:`quadobs.testbed.logs.tdoa_estimators`)."""
    from quadobs.testbed.logs import tdoa_estimators

    return tdoa_estimators.build_tdoa_handover(s, x0, name)


def build_ekf_bias(s: ReplaySetup, x0: np.ndarray, name: str = "ekf-bias") -> Estimator:
    """Entry point ``ekf-bias`` (:mod:`quadobs.testbed.logs.bias_estimators`)."""
    from quadobs.testbed.logs import bias_estimators

    return bias_estimators.build_ekf_bias(s, x0, name, _process_noise(s))


def build_ukf_bias(s: ReplaySetup, x0: np.ndarray, name: str = "ukf-bias") -> Estimator:
    """Entry point ``ukf-bias`` (:mod:`quadobs.testbed.logs.bias_estimators`)."""
    from quadobs.testbed.logs import bias_estimators

    return bias_estimators.build_ukf_bias(s, x0, name, _process_noise(s))


def build_ekf_height(s: ReplaySetup, x0: np.ndarray, name: str = "ekf-height") -> Estimator:
    """Entry point ``ekf-height`` (:mod:`quadobs.testbed.logs.height_estimators`)."""
    from quadobs.testbed.logs import height_estimators

    return height_estimators.build_ekf_height(s, x0, name, _process_noise(s))


def build_ukf_height(s: ReplaySetup, x0: np.ndarray, name: str = "ukf-height") -> Estimator:
    """Entry point ``ukf-height`` (:mod:`quadobs.testbed.logs.height_estimators`)."""
    from quadobs.testbed.logs import height_estimators

    return height_estimators.build_ukf_height(s, x0, name, _process_noise(s))


def build_augmented_height(s: ReplaySetup, x0: np.ndarray, name: str = "augmented-height"):
    """Entry point ``augmented-height`` (:mod:`quadobs.testbed.logs.height_estimators`)."""
    from quadobs.testbed.logs import height_estimators

    return height_estimators.build_augmented_height(s, x0, name, _process_noise(s))


def build_augmented_bias(s: ReplaySetup, x0: np.ndarray, name: str = "augmented-bias"):
    """Entry point ``augmented-bias`` (:mod:`quadobs.testbed.logs.bias_estimators`): the settings
    of :func:`build_augmented`'s observer for the same log and guess."""
    from quadobs.testbed.logs import bias_estimators

    observer = build_augmented(s, x0, name)
    return bias_estimators.build_augmented_bias(s, x0, name, observer)


#: The gyroscope's white noise (rad^2/s) of :func:`build_onboard_ekf`, its floor (:func:`gyro_noise`):
#: the Crazyflie firmware's Kalman filter states its gyro noise as 0.1 rad/s per axis over its
#: 10 ms prediction step, an intensity of ``0.1^2 * 0.01 = 1e-4`` rad^2/s (a few times a
#: consumer MEMS gyroscope's noise density, which leaves room for its unmodelled bias).
GYRO_NOISE = 1e-4


def gyro_noise(s: ReplaySetup) -> float:
    """The gyroscope's white-noise intensity (rad^2/s).

    Where the log states the gyroscope's bias (:attr:`ReplaySetup.gyro_bias`, ``meta.csv``
    key ``gyro_bias``, the standard deviation ``b_g`` of its constant bias per axis), the rule
    of the live on-board filter (:func:`quadobs.testbed.factories.onboard_ekf`): the bias
    matched over the horizon ``tau`` (:data:`~quadobs.testbed.imu.BIAS_HORIZON`), as the accelerometer's in
    :func:`quadobs.testbed.imu.input_noise_std`,

    .. math:: q_g = N_g^2 + b_g^2\\,\\tau,

    ``N_g`` the stated density (0 if none). Otherwise the square of the stated density
    (:attr:`ReplaySetup.gyro_noise`) where it exceeds :data:`GYRO_NOISE`, else
    :data:`GYRO_NOISE`: a density alone is the sensor's white noise only, the filter has no
    gyroscope-bias state, and a bias of the order of 0.002 rad/s (a consumer MEMS part's) is
    not in it. On the exported ``quadrotor-uwb`` flight (20 s, density 1.6e-4 rad/s/sqrt(Hz),
    bias 0.002 rad/s) the density alone gave the filter 0.0276 m of position RMSE after 5 s,
    the floor 0.0265 m. A rule that gives zero (a gyroscope stated perfect) takes the floor.
    """
    density2 = 0.0 if s.gyro_noise is None else float(s.gyro_noise) ** 2
    if s.gyro_bias is not None:
        stated = density2 + float(s.gyro_bias) ** 2 * BIAS_HORIZON
        if stated > 0.0:
            return stated
    return max(density2, GYRO_NOISE)


#: The floor of the accelerometer's white-noise intensity (m^2/s^3) of the model ``imu``
#: (:func:`accel_noise`): the Crazyflie firmware's Kalman filter adds a horizontal acceleration
#: process noise of 0.5 m/s^2 over its 10 ms prediction step, an intensity of
#: ``0.5^2 * 0.01 = 2.5e-3`` m^2/s^3 (:data:`GYRO_NOISE` is from the same filter). It stands
#: for what a stated density leaves out: the input ``u = R~ f~ + g`` rebuilt from the IMU also
#: carries the accelerometer's bias and the attitude's error times gravity, and a bias ``b``
#: matched over a filter memory ``tau`` weighs as a white noise of intensity ``b^2 tau``
#: (:func:`quadobs.testbed.imu.input_noise_std`): the floor is ``b = 0.05`` m/s^2 over a second.
ACCEL_NOISE = 2.5e-3


def accel_noise(density: float | None) -> float | None:
    """The model ``imu``'s accelerometer white-noise intensity ``q_imu`` (m^2/s^3) from a log's
    stated density (m/s^2/sqrt(Hz), ``meta.csv`` key ``accel_noise``): its square where it
    exceeds :data:`ACCEL_NOISE`, else :data:`ACCEL_NOISE`; None where the log states none (the
    setup's default :attr:`ReplaySetup.q_imu` then stands)."""
    if density is None or not math.isfinite(float(density)):
        return None
    return max(float(density) ** 2, ACCEL_NOISE)


def _median_interval(table) -> float:
    """The median interval (s) between a table's rows (its first column the time); NaN if
    fewer than two rows or none positive."""
    from quadobs.testbed.logs.schema import sampling_period

    if table is None or table.shape[0] < 2:
        return math.nan
    return sampling_period(table[:, 0])


def imu_input_noise(log) -> float | None:
    """The model ``imu``'s input-noise intensity ``q_imu`` (m^2/s^3) from the IMU figures a log
    states (``meta.csv``); None where it states none (the default :attr:`ReplaySetup.q_imu`).

    Where the log states the accelerometer's bias (``accel_bias``, the standard deviation
    ``b`` of its constant bias per axis), ``q_imu`` is the rule of the live filters,
    :func:`quadobs.testbed.imu.input_noise_std` itself:

    .. math:: q_{imu} = N_a^2 + m\\,h\\,(g\\,\\sigma_q)^2 + b^2\\,\\tau,

    ``N_a`` the density ``accel_noise`` (0 if not stated), ``sigma_q`` the attitude's error
    ``attitude_std`` with ``m h`` the median interval of ``attitude.csv`` (the term is 0 where
    either is missing: an attitude estimated in the replay has no stated error), ``g`` the log's
    gravity, ``h`` the median IMU interval and ``tau`` (:data:`~quadobs.testbed.imu.BIAS_HORIZON`) the
    horizon over which the bias is matched. An exported simulated flight states every figure, so its replay takes the same
    ``q_imu`` as the live filters (4.4e-4 m^2/s^3 for ``quadrotor-uwb`` and ``quadrotor-tdoa``).

    Where the log states a density and no bias, :func:`accel_noise` (the density's square,
    floored at :data:`ACCEL_NOISE` for the bias and attitude error it leaves out); so too where
    the stated figures give zero (an IMU stated perfect: the replay's filters need a positive
    intensity).
    """
    from types import SimpleNamespace

    from quadobs.testbed.imu import input_noise_std

    density = float(getattr(log, "accel_noise", math.nan))
    bias = float(getattr(log, "accel_bias", math.nan))
    h = _median_interval(log.inputs)
    if not (math.isfinite(bias) and math.isfinite(h)):
        return accel_noise(density)
    attitude_std = float(getattr(log, "attitude_std", math.nan))
    period = _median_interval(getattr(log, "attitude", None))
    if not (math.isfinite(attitude_std) and math.isfinite(period)):
        attitude_std, period = 0.0, h
    spec = SimpleNamespace(
        accel_std=density / math.sqrt(h) if math.isfinite(density) else 0.0,
        accel_bias=bias,
        attitude_std=attitude_std,
    )
    q = input_noise_std(spec, period / h, h, gravity=float(log.gravity)) ** 2 * h
    return q if q > 0.0 else accel_noise(density)


#: The initial yaw error (rad) of :func:`build_onboard_ekf` where the log gives no attitude and
#: no heading: the standard deviation of a heading uniform on the circle, ``pi / sqrt(3)``.
UNKNOWN_YAW_STD = math.pi / math.sqrt(3.0)


#: The prior standard deviation of each axis of the accelerometer's bias in
#: :func:`build_onboard_ekf_bias` (m/s^2): 0.2 m/s^2 (20 mg), the zero-g offset a consumer MEMS
#: accelerometer's data sheet states, and the GTSAM peer's prior on the same bias
#: (:class:`~quadobs.estimators.gtsam_peer.PeerNoise`).
ACCEL_BIAS_STD = 0.2

#: The time (s) over which that bias may wander by :data:`ACCEL_BIAS_STD` (an hour: thermal
#: drift); its random walk's intensity is ``ACCEL_BIAS_STD^2 / ACCEL_BIAS_TIME``.
ACCEL_BIAS_TIME = 3600.0


def build_onboard_ekf(
    s: ReplaySetup, x0: np.ndarray, name: str = "onboard-ekf", accel_bias: bool = False
) -> Estimator:
    """Entry point ``onboard-ekf``: the Crazyflie's on-board EKF
    (:class:`~quadobs.estimators.onboard_ekf.OnboardEKF`) on a 3-D body-IMU log.

    The replay holds the log's raw body IMU ``u = (f, omega)`` for it (``replay_input =
    "imu_body"``). Its noise is the setup's stated noise: ranges (or TDOA) ``range_sigma``; the
    filter adds ``sigma_a^2 h^2`` to the velocity over each interval ``h`` between IMU samples,
    so the accelerometer's white noise of intensity ``q_imu`` (m^2/s^3) is the per-sample
    ``sigma_a = sqrt(q_imu / h_s)`` at the log's median IMU interval ``h_s`` (``q_imu h`` per
    interval ``h = h_s``), and the gyroscope's likewise from :func:`gyro_noise` (the log's
    stated density where it exceeds the floor :data:`GYRO_NOISE`). Its initial
    attitude is :attr:`ReplaySetup.attitude0` with 0.05 rad per axis; without one, the IMU's
    initial alignment (:attr:`ReplaySetup.alignment0`: the tilt from the resting specific
    force, so a body frame of any orientation, forward-right-down included, starts the right
    way up) with yaw zero, 0.05 rad in roll and pitch and :data:`UNKNOWN_YAW_STD` in yaw. Gravity is the
    log's, along ``-z`` (enu) or ``+z`` (ned). The position prior is ``P0`` per axis, the
    velocity's :func:`~quadobs.testbed.logs.start_prior.velocity_prior` (as :func:`build_ekf`).
    """
    from scipy.spatial.transform import Rotation

    from quadobs.estimators.onboard_ekf import OnboardEKF

    if s.input_kind != "imu_body" or s.dim != 3:
        raise QuadobsError(
            f"estimators: {name!r} needs a 3-D body-IMU log (imu.csv), and the log has "
            f"{'a planar geometry' if s.dim != 3 else f'inputs of kind {s.input_kind!r}'}"
        )
    if s.frame not in ("enu", "ned"):
        raise QuadobsError(f"estimators: {name!r} takes a frame enu or ned, got {s.frame!r}")
    models = s.measurement_models()
    if len(models) != 1:
        raise QuadobsError(f"estimators: {name!r} takes ranges or TDOA, and the log holds both")
    h = s.imu_period if s.imu_period is not None and s.imu_period > 0 else s.dt
    if s.attitude0 is None:
        q = np.array([1.0, 0.0, 0.0, 0.0]) if s.alignment0 is None else s.alignment0
        R0 = Rotation.from_quat(np.asarray(q, dtype=float)[[1, 2, 3, 0]]).as_matrix()
        att_std = np.array([0.05, 0.05, UNKNOWN_YAW_STD])
    else:
        q = np.asarray(s.attitude0, dtype=float)
        R0, att_std = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix(), np.full(3, 0.05)
    x0, P0 = np.array(x0, dtype=float)[:6], np.diag(np.full(6, s.P0))
    set_velocity_prior(s, x0, P0, 3)
    est = OnboardEKF(
        models[0],
        h,
        accel_std=math.sqrt(s.q_imu / h),
        gyro_std=math.sqrt(gyro_noise(s) / h),
        x0=x0,
        P0=P0,
        attitude_std=att_std,
        gate=s.gate,
        R0=R0,
        gravity=np.array([0.0, 0.0, -s.gravity if s.frame == "enu" else s.gravity]),
        **(
            {
                "accel_bias_std": ACCEL_BIAS_STD,
                "accel_bias_walk": ACCEL_BIAS_STD**2 / ACCEL_BIAS_TIME,
            }
            if accel_bias
            else {}
        ),
    )
    est.name = name
    est.replay_input = "imu_body"
    return est


def build_onboard_ekf_bias(s: ReplaySetup, x0: np.ndarray, name: str = "onboard-ekf-bias"):
    """Entry point ``onboard-ekf-bias``: :func:`build_onboard_ekf` with the accelerometer's bias as
    a state (prior :data:`ACCEL_BIAS_STD` per axis, random walk ``ACCEL_BIAS_STD^2 /
    ACCEL_BIAS_TIME``; :class:`~quadobs.estimators.onboard_ekf.OnboardEKF`)."""
    return build_onboard_ekf(s, x0, name, accel_bias=True)


def build_ekf_heading(s: ReplaySetup, x0: np.ndarray, name: str = "ekf-heading", cls=None):
    """Entry point ``ekf-heading``: the EKF of an odometry log with the heading and the yaw rate's
    bias as states (:class:`~quadobs.estimators.heading_ekf.HeadingEKF`).

    Its noise is the setup's: ``q_xy_heading`` on the position (the speed's noise: the
    heading's drift is a state here, not position noise), ``q_theta`` on the heading, ranges (or
    TDOA) ``range_sigma``; the bias's random walk ``GYRO_BIAS_STD^2 / GYRO_BIAS_TIME``. Its prior:
    the position ``P0`` per axis, the heading's correction 0 with ``HEADING_STD`` (the log's
    start heading being ``heading0``), the bias 0 with ``GYRO_BIAS_STD``
    (:mod:`quadobs.estimators.heading_ekf`).
    """
    from quadobs.estimators import heading_ekf as hk

    if s.model != "odometry" or s.input_kind != "odometry":
        raise QuadobsError(
            f"estimators: {name!r} needs a planar log with wheel odometry (inputs.csv: "
            f"time,speed,yaw_rate) and the model odometry, and the replay has the model {s.model!r}"
        )
    state0 = np.zeros(4)
    state0[:2] = np.asarray(x0, dtype=float)[:2]
    est = (cls or hk.HeadingEKF)(
        s.beacons,
        x0=state0,
        P0=np.array([s.P0, s.P0, hk.HEADING_STD**2, hk.GYRO_BIAS_STD**2]),
        dt=s.dt,
        q_xy=s.q_xy_heading,
        q_theta=s.q_theta,
        q_bias=hk.GYRO_BIAS_STD**2 / hk.GYRO_BIAS_TIME,
        range_sigma=s.range_sigma,
        heading0=s.heading0,
        gate=s.gate,
        measurements=s.measurement_models(),
    )
    est.name = name
    return est


def build_ukf_heading(s: ReplaySetup, x0: np.ndarray, name: str = "ukf-heading"):
    """Entry point ``ukf-heading``: the UKF of :func:`build_ekf_heading`'s model and noise."""
    from quadobs.estimators.heading_ekf import HeadingUKF

    return build_ekf_heading(s, x0, name, HeadingUKF)


def lever_prior(s: ReplaySetup) -> dict:
    """The lever arm's prior of the heading filters that hold it: the log's stated place of the
    tag with :data:`~quadobs.estimators.heading_ekf.STATED_LEVER_STD` per axis, else zero with
    :data:`~quadobs.estimators.heading_ekf.LEVER_ARM_STD` (:attr:`ReplaySetup.lever_arm`)."""
    from quadobs.estimators.heading_ekf import LEVER_ARM_STD, STATED_LEVER_STD

    if s.lever_arm is None:
        return {"lever_arm_std": LEVER_ARM_STD}
    return {"lever_arm_std": STATED_LEVER_STD, "lever_arm": tuple(s.lever_arm)}


def build_ukf_lever(s: ReplaySetup, x0: np.ndarray, name: str = "ukf-lever"):
    """Entry point ``ukf-lever``: :func:`build_ukf_heading` with the tag's lever arm as two more
    states, prior :func:`lever_prior` (mean 0 and :data:`~quadobs.estimators.heading_ekf.LEVER_ARM_STD`
    per axis where the log does not state the tag's place; the ranges are the tag's, ``|p +
    R(theta) l - a_h|``; the position reported is the odometry's point ``p``:
    :mod:`quadobs.estimators.heading_ekf`)."""
    from functools import partial

    from quadobs.estimators.heading_ekf import HeadingUKF

    return build_ekf_heading(s, x0, name, partial(HeadingUKF, **lever_prior(s)))


def build_ukf_height_lever(s: ReplaySetup, x0: np.ndarray, name: str = "ukf-height-lever"):
    """Entry point ``ukf-height-lever``: :func:`build_ukf_lever` with each anchor's range bias
    ``b_h`` and squared-range offset ``e_h = dz_h^2 / 2`` as two more states (priors of
    :func:`~quadobs.testbed.logs.height_estimators.heading_height_options`, as ``ekf-height``'s):
    the tag off the odometry's point and the anchors above it, together (``rho_h = sqrt(|p +
    R(theta) l - a_h|^2 + 2 e_h) + b_h``; :mod:`quadobs.estimators.heading_ekf`), with Huber's
    bound at the replay's gate on each range's innovation less its expected non-line-of-sight
    excess (:func:`~quadobs.testbed.logs.height_estimators.excess_rule`)."""
    from functools import partial

    from quadobs.estimators.heading_ekf import TAG_PATTERN_STD, HeadingUKF
    from quadobs.testbed.logs.height_estimators import heading_height_options

    options = heading_height_options(s, name)
    if s.tag_pattern:
        options["tag_pattern_std"] = TAG_PATTERN_STD
    cls = partial(HeadingUKF, **lever_prior(s), **options)
    return build_ekf_heading(s, x0, name, cls)


def build_augmented_heading(s: ReplaySetup, x0: np.ndarray, name: str = "augmented-heading"):
    """Entry point ``augmented-heading``: the augmented observer of the odometry model
    (:func:`build_augmented`) in a cascade behind :func:`build_ukf_heading`, whose estimated
    heading turns the odometry it integrates
    (:class:`~quadobs.estimators.heading_ekf.HeadingCascade`). The observer's position noise is
    the heading filters' ``q_xy_heading`` (its input is turned by the estimated heading, so its
    noise is the speed's alone, as theirs) plus the turned input's own error, the heading filter's
    covariance carried through the turn (``Q_u``, written by the cascade before each interval into
    the array its noise map adds). A range's output variance is taken at the larger of the
    measured and the predicted range (``range_variance = "larger"``): a range read short (an
    outlier near an anchor) gets no more weight than the prediction gives it. The cascade's
    prediction is good enough for it (its input follows the estimated heading); the plain
    observer's, on a drifting dead-reckoned heading, is not, and keeps the measured range."""
    import dataclasses

    from quadobs.estimators.heading_ekf import HeadingCascade

    heading = build_ukf_heading(s, x0, f"{name}:ukf-heading")
    inner = dataclasses.replace(s, q_xy=s.q_xy_heading)
    observer = build_augmented(inner, x0)
    observer.range_variance = "larger"  # a range read short gets no more weight than predicted
    extra = np.zeros((2, 2))  # the turned input's error, written by the cascade
    observer.noise_of = _noise_map(inner, observer.immersion, extra)
    est = HeadingCascade(observer, heading, input_noise=extra)
    est.name = name
    return est


def build_ekf_bias_imu(s: ReplaySetup, x0: np.ndarray, name: str = "ekf-bias-imu") -> Estimator:
    """Entry point ``ekf-bias-imu``: the range biases and the acceleration's bias as states
    (:func:`quadobs.testbed.logs.imu_bias.build_ekf_bias_imu`; the acceleration bias's prior
    :data:`ACCEL_BIAS_STD`, its drift over :data:`ACCEL_BIAS_TIME` where the log has an attitude)."""
    from quadobs.testbed.logs import imu_bias

    return imu_bias.build_ekf_bias_imu(s, x0, name, ACCEL_BIAS_STD, ACCEL_BIAS_TIME)


#: Why ``ekf-bias-imu-nlos`` and ``ekf-bias-imu-average`` are ``ekf-bias-imu`` on a log
#: (their ``same_as``, in the summary).
NO_EXCESS = "no non-line-of-sight excess identified in the log"


def build_ekf_bias_imu_nlos(
    s: ReplaySetup, x0: np.ndarray, name: str = "ekf-bias-imu-nlos"
) -> Estimator:
    """Entry point ``ekf-bias-imu-nlos``: ``ekf-bias-imu`` weighing each range by the
    non-line-of-sight excess's mixture where the self-calibration estimated the excess from
    the log (:mod:`quadobs.testbed.logs.excess_model`), with the steady-offset test
    (``steady_test`` of the setup, on by default), else the same filter."""
    from quadobs.estimators.robust import ExcessMixture
    from quadobs.testbed.logs import imu_bias
    from quadobs.testbed.logs.bias_estimators import range_rule

    est = imu_bias.build_ekf_bias_imu(s, x0, name, ACCEL_BIAS_STD, ACCEL_BIAS_TIME, excess=True)
    if not isinstance(range_rule(s, excess=True), ExcessMixture):
        est.same_as = ("ekf-bias-imu", NO_EXCESS)  # the summary says it is that filter
    return est


def build_ekf_bias_imu_average(
    s: ReplaySetup, x0: np.ndarray, name: str = "ekf-bias-imu-average"
) -> Estimator:
    """Entry point ``ekf-bias-imu-average``: ``ekf-bias-imu`` and ``ekf-bias-imu-nlos``
    averaged with equal weights (:class:`~quadobs.estimators.model_average.ModelAverage`):
    the two read a range longer than line of sight by rival models (the one-sided gate, the
    excess mixture), and no score on held-out ranges tells which places the vehicle better
    (docs/error-sources.md). Where the self-calibration identified no excess the two are one
    filter, and the average is ``ekf-bias-imu`` alone."""
    from quadobs.estimators.model_average import ModelAverage
    from quadobs.estimators.robust import ExcessMixture
    from quadobs.testbed.logs.bias_estimators import range_rule

    members = [build_ekf_bias_imu(s, x0, name)]  # a log it cannot take: refused by its name
    members[0].name = "ekf-bias-imu"  # the member's own, which the self-calibration reads
    if isinstance(range_rule(s, excess=True), ExcessMixture):
        members.append(build_ekf_bias_imu_nlos(s, x0))
    average = ModelAverage(members, name)
    if len(members) == 1:
        average.same_as = ("ekf-bias-imu", NO_EXCESS)  # the average is that filter
    return average


#: The built-in estimators of logged data (as declared in pyproject.toml; a test checks that they agree).
#: An estimator that reads a body IMU as its input (the Crazyflie's on-board EKF,
#: ``u = (f_body, omega_body)``) is registered here beside them and marks its instances with
#: ``replay_input = "imu_body"``: the replay then holds the log's raw body IMU samples for it
#: instead of the navigation-frame acceleration (:mod:`quadobs.testbed.logs.events`).
REPLAY_ESTIMATORS = {
    "augmented": build_augmented,
    "ekf": build_ekf,
    "ukf": build_ukf,
    "isam2": build_isam2,
    "onboard-ekf": build_onboard_ekf,
    "ekf-heading": build_ekf_heading,
    "ukf-heading": build_ukf_heading,
    "augmented-heading": build_augmented_heading,
    "onboard-ekf-bias": build_onboard_ekf_bias,
    "tdoa-observer": build_tdoa_observer,
    "tdoa-handover": build_tdoa_handover,
    "ekf-bias": build_ekf_bias,
    "ukf-bias": build_ukf_bias,
    "augmented-bias": build_augmented_bias,
    "ekf-bias-imu": build_ekf_bias_imu,
    "ekf-bias-imu-nlos": build_ekf_bias_imu_nlos,
    "ekf-bias-imu-average": build_ekf_bias_imu_average,
    "ekf-height": build_ekf_height,
    "ukf-height": build_ukf_height,
    "augmented-height": build_augmented_height,
    "ukf-lever": build_ukf_lever,
    "ukf-height-lever": build_ukf_height_lever,
}


def _entry_points() -> dict:
    import importlib.metadata

    return {ep.name: ep for ep in importlib.metadata.entry_points(group=REPLAY_ENTRY_POINT_GROUP)}


def replay_estimator_names() -> list[str]:
    """The selectable names in ``quadobs replay``, sorted."""
    return sorted(set(REPLAY_ESTIMATORS) | set(_entry_points()))


def _factory(name: str):
    if name in REPLAY_ESTIMATORS:
        return REPLAY_ESTIMATORS[name]
    ep = _entry_points().get(name)
    if ep is None:
        raise QuadobsError(
            f"estimators: unknown estimator {name!r} for logged data; available: {', '.join(replay_estimator_names())}"
        )
    try:
        return ep.load()
    except Exception as exc:
        raise QuadobsError(
            f"estimators: entry point {name!r} ({ep.value}) cannot be loaded: {type(exc).__name__}"
        ) from None


def build_replay_estimators(
    setup: ReplaySetup, names: list[str], x0: np.ndarray
) -> list[Estimator]:
    """The named estimators, all from ``x0`` (built-in names first, then the entry points)."""
    if len(set(names)) != len(names):
        raise QuadobsError(f"estimators: names must be distinct, got {names}")
    out = []
    for name in names:
        from quadobs.testbed.registry import call_factory

        factory = _factory(name)
        origin = "built-in" if name in REPLAY_ESTIMATORS else "entry point"
        est = call_factory(factory, name, origin, setup, np.array(x0, dtype=float))
        if not isinstance(est, Estimator):
            raise QuadobsError(
                f"estimators: the factory of {name!r} returned {type(est).__name__}, not an Estimator"
            )
        est.name = name
        _start_constants(est, setup.constants_start)
        out.append(est)
    return out


def _start_constants(est, starts: dict | None) -> None:
    """The constant states' priors of ``starts`` (:attr:`ReplaySetup.constants_start`) set in
    ``est`` and in each member of an average, by the filter's name."""
    from quadobs.estimators.constants import constant_filters

    if not starts:
        return
    for f in constant_filters(est):
        start = starts.get(f.name)
        if start is not None:
            f.start_constants(*start)
