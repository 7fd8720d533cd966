"""``ekf-bias-imu``: the anchors' range biases and the acceleration's bias as states, on body-IMU logs.

A body IMU reaches the replay's models as the navigation-frame acceleration
``u = R~ f~ + g`` (:mod:`quadobs.testbed.attitude`), and two slow errors enter it that the
white process noise of the replay's EKF does not describe:

* the accelerometer's own bias ``b`` (body frame; 0.01 to 0.5 m/s^2 for a MEMS part), seen
  as ``R b`` in the navigation frame;
* the attitude's tilt error ``delta`` (rad), seen as ``g x delta``, about ``g |delta|``:
  9.8 m/s^2 per radian. An attitude estimated from the IMU alone (the Mahony filter of
  :func:`~quadobs.testbed.attitude.estimate_attitude`) takes a multirotor's thrust for
  gravity, so its tilt lags the true one with the filter's time constant ``1 / k_P``.

Both are an acceleration error ``c`` that changes slowly: the model adds it as a state,

.. math::

    \\dot p = v, \\qquad \\dot v = u - c, \\qquad \\dot c = w_c, \\qquad
    y_h = \\tfrac12 |p|^2 - a_h^\\top p ,

linear dynamics with the quadratic outputs of the range model
(:func:`acceleration_bias_system`), on which the range-bias filter of
:mod:`quadobs.estimators.bias_states` runs unchanged (its start-up fix, the biases held in a
consider update until the innovations are consistent, the one-sided gate against
non-line-of-sight excess). The prior of ``c`` is :data:`~quadobs.testbed.logs.estimators.ACCEL_BIAS_STD`
per axis (the prior of the accelerometer's bias in ``onboard-ekf-bias``); its random walk ``w_c`` lets it move by that much over the time the error changes
on (:func:`acceleration_bias_walk`): the attitude filter's time constant where the attitude
is estimated from the IMU, else the bias's thermal drift (an hour). The filter reports the
vehicle's ``(p, v)``; ``c`` is :attr:`AccelerationBiasEKF.acceleration_bias`.

The range biases and ``c`` are told apart by the motion: a range bias is constant along one
anchor's line of sight, ``c`` integrates twice into every range's residual.
"""

from __future__ import annotations

import numpy as np

from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError
from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter

__all__ = [
    "AccelerationBiasEKF",
    "acceleration_bias_system",
    "acceleration_bias_walk",
    "build_ekf_bias_imu",
]


def acceleration_bias_system(dim: int, beacons: np.ndarray) -> QuadraticSystem:
    """The double integrator with a constant acceleration bias, ranging to ``beacons``.

    ``x = (p, v, c)``: ``A = [[0, I, 0], [0, 0, -I], [0, 0, 0]]``, ``B = (0, I, 0)``, and the
    outputs of :func:`~quadobs.core.system.vehicle_system` (``C_h = diag(I, 0, 0)``,
    ``d_h = (-a_h, 0, 0)``).
    """
    beacons = np.asarray(beacons, dtype=float)
    eye, zero = np.eye(dim), np.zeros((dim, dim))
    A = np.block([[zero, eye, zero], [zero, zero, -eye], [zero, zero, zero]])
    B = np.vstack([zero, eye, zero])
    q = beacons.shape[0]
    C = np.zeros((q, 3 * dim, 3 * dim))
    C[:, :dim, :dim] = eye
    d = np.zeros((q, 3 * dim))
    d[:, :dim] = -beacons
    return QuadraticSystem(A, B, C, d)


def acceleration_bias_walk(bias_std: float, estimated_attitude: bool, drift_time: float) -> float:
    """The random walk's intensity of ``c`` (m^2/s^5): ``bias_std^2 / T``, ``T`` the time over
    which ``c`` may change by ``bias_std``: the Mahony filter's time constant ``1 / k_P``
    (:data:`~quadobs.testbed.attitude.MAHONY_GAINS`) where the attitude is estimated from the
    IMU (its tilt error is renewed on that scale), else ``drift_time`` (the accelerometer's
    drift, :data:`~quadobs.testbed.logs.estimators.ACCEL_BIAS_TIME`)."""
    from quadobs.testbed.attitude import MAHONY_GAINS

    horizon = 1.0 / MAHONY_GAINS[0] if estimated_attitude else float(drift_time)
    return float(bias_std) ** 2 / horizon


class AccelerationBiasEKF(BiasedExtendedKalmanFilter):
    """:class:`~quadobs.estimators.bias_states.BiasedExtendedKalmanFilter` on
    ``(p, v, c, b)``: reports ``(p, v)`` (module docstring)."""

    name = "ekf-bias-imu"

    def __init__(self, dynamics, outputs, *, vehicle_n: int, dim: int, **kw) -> None:
        super().__init__(dynamics, outputs, vehicle_n=vehicle_n, **kw)
        self.dim = int(dim)

    @property
    def x_hat(self) -> np.ndarray:
        return self._x[: 2 * self.dim].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        self._settle()
        k = 2 * self.dim
        return self._P[:k, :k].copy()

    @property
    def acceleration_bias(self) -> np.ndarray:
        """The estimated acceleration bias ``c (dim,)`` (m/s^2, navigation frame), a copy."""
        return self._x[2 * self.dim : 3 * self.dim].copy()


def build_ekf_bias_imu(
    s, x0: np.ndarray, name: str, bias_std: float, drift_time: float, excess: bool = False
) -> AccelerationBiasEKF:
    """``ekf-bias-imu`` (module docstring) on the replay's setup ``s`` of a 3-D body-IMU log.

    The vehicle's process noise is the replay EKF's (``q_imu`` on the velocity), ``c`` has the
    prior ``bias_std^2`` per axis and the walk of :func:`acceleration_bias_walk`, each
    anchor's bias the setup's prior
    (:meth:`~quadobs.testbed.logs.estimators.ReplaySetup.bias_prior_std`); the rule
    ``ekf-bias``'s one-sided gate (also on a log that states its ranges Gaussian, where
    ``ekf-bias`` takes none), or with ``excess`` (``ekf-bias-imu-nlos``)
    :func:`~quadobs.testbed.logs.bias_estimators.range_rule`'s excess mixture where the
    self-calibration estimated the excess, else the same gate. The
    two are kept apart because no score on held-out ranges tells which of them places the
    vehicle better (docs/error-sources.md, in the replay: the excess estimated from the log).
    Under the mixture the filter takes the steady-offset test where ``s.steady_test`` is 1
    (:meth:`~quadobs.estimators.bias_states._VehicleBlock._steady`).
    """
    from quadobs.estimators.bias_states import BiasedRangeOutputModel, extended_system
    from quadobs.estimators.kalman import HeldInputModel
    from quadobs.estimators.robust import ExcessMixture, SkewedGate
    from quadobs.testbed.logs.bias_estimators import _gate_probability, range_rule

    if s.input_kind != "imu_body" or s.dim != 3:
        raise QuadobsError(
            f"estimators: {name!r} needs a 3-D body-IMU log (imu.csv), and the log has "
            f"{'a planar geometry' if s.dim != 3 else f'inputs of kind {s.input_kind!r}'}"
        )
    if "tdoa" in s.kinds:
        raise QuadobsError(
            f"estimators: {name!r} estimates range biases and the log holds TDOA (use ekf or ukf)"
        )
    if s.model != "imu":
        raise QuadobsError(f"estimators: {name!r} takes the model imu, not {s.model!r}")
    dim = s.dim
    system = extended_system(acceleration_bias_system(dim, s.beacons))
    n, q = 3 * dim, s.beacons.shape[0]
    V = np.zeros((n + q, n + q))
    V[dim : 2 * dim, dim : 2 * dim] = s.q_imu * np.eye(dim)
    walk = acceleration_bias_walk(bias_std, s.attitude0 is None, drift_time)  # no attitude.csv
    V[2 * dim : n, 2 * dim : n] = walk * np.eye(dim)
    dynamics = HeldInputModel(system, s.dt, V=V)
    offsets = 0.5 * np.einsum("hi,hi->h", s.beacons, s.beacons)
    outputs = BiasedRangeOutputModel(system, s.range_sigma**2 * np.eye(q), offsets=offsets)
    from quadobs.testbed.logs.start_prior import set_velocity_prior

    prior = [s.P0] * dim + [0.0] * dim + [bias_std**2] * dim  # the velocity's: as the EKF
    P = np.diag(prior + [s.bias_prior_std() ** 2] * q)
    xe = np.zeros(n + q)
    xe[: 2 * dim] = np.asarray(x0, dtype=float)[: 2 * dim]
    set_velocity_prior(s, xe, P, dim)
    rule = range_rule(s, excess=excess)  # with excess: the mixture where it is known
    if not isinstance(rule, ExcessMixture):
        rule = SkewedGate(_gate_probability(s.gate))
    est = AccelerationBiasEKF(
        dynamics,
        outputs,
        x0=xe,
        P0=P,
        vehicle_n=n,
        dim=dim,
        robust=rule,
    )
    est.steady_test = isinstance(rule, ExcessMixture) and bool(s.steady_test)
    est.name = name
    return est
