"""The Crazyflie's on-board estimator as a peer: an error-state EKF driven by the IMU, corrected by UWB ranges or TDOA.

Written from the papers: the filter of [MUELLER2015] (position, body-frame velocity and
an attitude error propagated with the accelerometer and the rate gyroscope, corrected
with two-way UWB ranges) with the attitude reset of [MUELLER2017] (the covariance
correction step for Kalman filtering with an attitude).

State. The nominal state is the position ``p`` (world), the velocity ``v`` in the body
frame and the attitude ``R`` (world from body); the filter's error state is
``e = (dp, dv, delta)`` (9), the attitude error ``delta`` defined by ``R_true = R exp([delta]x)``.

Prediction over ``h`` with the held input ``u = (f, w)`` (specific force and body rates,
body frame): the world acceleration ``a = R f + g`` is held, so
``p <- p + R v h + a h^2 / 2``, ``R v <- R v + a h``, ``R <- R exp([w h]x)``; the error
covariance ``P <- F P F^T + Q`` with ``F = I + A h`` and, from
``p' = R v``, ``v' = -w x v + f + R^T g``, ``R' = R [w]x``,

.. math::

    A = \\begin{bmatrix} 0 & R & -R[v]_\\times \\\\ 0 & -[w]_\\times & [R^T g]_\\times \\\\
        0 & 0 & -[w]_\\times \\end{bmatrix}, \\qquad
    Q = \\operatorname{diag}(0, \\sigma_a^2 h^2 I, \\sigma_w^2 h^2 I),

``sigma_a``, ``sigma_w`` the accelerometer's and gyroscope's noise per sample of length ``h``.

Correction with one scalar measurement ``z`` of model ``h(p)``
(:class:`~quadobs.core.measurements.RangeModel` or
:class:`~quadobs.core.measurements.TdoaModel`): ``H = [grad h(p)^T, 0, 0]``,
``K = P H^T / (H P H^T + sigma^2)``, ``e = K (z - h(p))``, ``P <- (I - K H) P (I - K H)^T +
sigma^2 K K^T``; then the error is moved into the nominal state (``p += dp``, ``v += dv``,
``R <- R exp([delta]x)``) and, as ``delta`` is now zero in the new attitude's frame, the
covariance is carried over with the reset's Jacobian [MUELLER2017]:
``P <- G P G^T``, ``G = diag(I, I, I - [delta / 2]x)``.

The estimate it reports is the vehicle's ``(p, R v)`` (world position and velocity) and
its covariance ``T P T^T``, ``T = [[I, 0, 0], [0, R, -R [v]x]]``.

The accelerometer's bias as a state (``accel_bias_std``; the replay's ``onboard-ekf-bias``).
A constant bias ``b`` (``f_m = f + b + n``, body frame; a MEMS accelerometer's offset of 0.01
to 0.5 m/s^2) integrates into a velocity error ``R b t`` between ranges. With
``accel_bias_std`` given, the error state gains ``db`` (12 states), a random walk of
intensity ``q_b``: the prediction uses ``f_m - b``, ``A`` gains ``d dv' / d db = -I`` and ``Q``
gains ``q_b h`` on ``db``; a correction moves ``db`` into ``b`` with the rest of the error (the
attitude reset leaves it as it is). In the body frame ``b`` is told apart from a tilt of the
attitude (which also adds a constant horizontal specific force, ``R^T g``) once the vehicle
yaws or changes its tilt, and along the thrust axis by the height, which the ranges give.
Without it (the default) the filter is the 9-state one above.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.core.measurements import Measurement, MeasurementModel, RangeModel
from quadobs.errors import QuadobsError
from quadobs.estimators.base import Estimator, Gated

__all__ = ["OnboardEKF", "rotation_exp", "skew"]

_GRAVITY = np.array([0.0, 0.0, -9.81])


def skew(w: np.ndarray) -> np.ndarray:
    """``[w]x``: the matrix with ``[w]x b = w x b``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rotation_exp(phi: np.ndarray) -> np.ndarray:
    """``exp([phi]x)`` (Rodrigues)."""
    angle = math.sqrt(float(phi @ phi))
    K = skew(phi)
    if angle < 1e-9:
        return np.eye(3) + K + 0.5 * K @ K
    return (
        np.eye(3) + (math.sin(angle) / angle) * K + ((1.0 - math.cos(angle)) / angle**2) * (K @ K)
    )


class OnboardEKF(Estimator, Gated):
    """The IMU-driven error-state EKF of [MUELLER2015] with the reset of [MUELLER2017] (module docstring).

    Parameters
    ----------
    model : MeasurementModel
        What the outputs ``y`` of :meth:`step` are: one measurement per anchor for a
        :class:`~quadobs.core.measurements.RangeModel` (``y[i]`` the range to anchor ``i``).
    dt : float
        Step of :meth:`step` (s).
    accel_std, gyro_std : float
        Noise of one accelerometer (m/s^2) and gyroscope (rad/s) sample over ``dt``.
    x0 : ndarray (6,)
        Initial position and world velocity.
    P0 : ndarray (6, 6)
        Their initial covariance.
    attitude_std : float or array_like (3,)
        Initial attitude error (rad, per body axis or one for all).
    gate : float or None
        Largest normalised innovation squared accepted (None: every measurement).
    R0 : ndarray (3, 3), optional
        Initial attitude (world from body); default level, heading zero.
    gravity : array_like (3,), optional
        Gravity in the world frame (m/s^2); default ``(0, 0, -9.81)`` (z up).
    accel_bias_std : float, optional
        With it, the accelerometer's bias is a state (module docstring), of this prior standard
        deviation per axis (m/s^2) and mean zero; default none (9 states).
    accel_bias_walk : float
        The intensity of the bias's random walk (m^2/s^5).
    """

    #: ``"imu_body"`` where a replay is to hold the log's raw body IMU samples as its input.
    replay_input: str | None = None

    def __init__(
        self,
        model: MeasurementModel,
        dt: float,
        *,
        accel_std: float,
        gyro_std: float,
        x0,
        P0,
        attitude_std: float | np.ndarray = 0.05,
        gate: float | None = None,
        R0: np.ndarray | None = None,
        gravity: np.ndarray | None = None,
        accel_bias_std: float | None = None,
        accel_bias_walk: float = 0.0,
    ) -> None:
        if model.dimension != 3:
            raise QuadobsError("onboard-ekf: needs anchors in 3-D")
        self.model, self.dt = model, float(dt)
        self.p = np.array(x0[:3], dtype=float)
        self.R = np.eye(3) if R0 is None else np.array(R0, dtype=float)
        self.g = _GRAVITY.copy() if gravity is None else np.array(gravity, dtype=float)
        self.v = self.R.T @ np.array(x0[3:6], dtype=float)  # the body-frame velocity
        self.P = np.zeros((9, 9) if accel_bias_std is None else (12, 12))
        self.P[:6, :6] = np.asarray(P0, dtype=float)
        self.P[6:9, 6:9] = np.diag(np.broadcast_to(np.square(attitude_std), (3,)))
        self.b = np.zeros(3)  # the accelerometer's bias (body frame), zero when not a state
        if accel_bias_std is not None:
            self.P[9:, 9:] = np.eye(3) * float(accel_bias_std) ** 2
        self.q_b = float(accel_bias_walk)
        self.q_v, self.q_a = accel_std**2, gyro_std**2
        self.gate = gate
        self.u = np.zeros(6)
        self.imu_source: np.ndarray | None = None
        self.t = 0.0
        self.rejected = self.corrections = 0
        self._beacon_term = 0.5 * np.einsum("hi,hi->h", model.anchors, model.anchors)
        self._ranges = [
            Measurement(0.0, model.kind, 0.0, (i,)) for i in range(model.anchors.shape[0])
        ]

    # -- the time interface ------------------------------------------------------------

    @property
    def time(self) -> float:
        """The current time (s)."""
        return self.t

    @time.setter
    def time(self, value: float) -> None:
        t = float(value)
        if not math.isfinite(t):
            raise QuadobsError(f"time: expected a finite number of seconds, got {value!r}")
        self.t = t

    def bind_imu(self, source: np.ndarray) -> None:
        """Read the held input of :meth:`step` from ``source (6,)`` (a world's latest body IMU sample)."""
        self.imu_source = source

    def hold(self, u) -> None:
        """Hold the body IMU sample ``u = (f (3), w (3))`` from the current time on."""
        u = np.asarray(u, dtype=float)
        if u.shape != (6,) or not np.all(np.isfinite(u)):
            raise QuadobsError(
                f"onboard-ekf: u must be 6 finite values (specific force, body rates), got {u.shape}"
            )
        self.u[:] = u

    def predict(self, t: float) -> None:
        """Propagate to ``t`` with the held IMU sample."""
        h = float(t) - self.t
        if h < 0.0:
            raise QuadobsError(f"onboard-ekf: cannot predict back in time ({t} < {self.t})")
        if h > 0.0:
            self._propagate_imu(h)
        self.t = float(t)

    def correct(self, m: Measurement) -> None:
        """One range or TDOA ``m`` at the current time (its kind must be the model's)."""
        if m.kind != self.model.kind:
            raise QuadobsError(
                f"onboard-ekf: takes {self.model.kind!r} measurements, got {m.kind!r}"
            )
        self._update(m, float(m.value))

    def step(self, u, y) -> None:
        """Correct with the outputs ``y (q,)`` (NaN: none), then predict over ``dt`` with the body IMU ``u (6,)`` (or the bound source).

        ``y`` are the testbed's range outputs [IFAC2021, eq. 2],
        ``y_i = rho_i^2 / 2 - |a_i|^2 / 2``: each is turned back into the range ``rho_i``.
        """
        y = np.asarray(y, dtype=float)
        for i, m in enumerate(self._ranges):
            if i < y.shape[0] and not math.isnan(y[i]):
                self._update(m, math.sqrt(max(2.0 * (y[i] + self._beacon_term[i]), 0.0)))
        self.hold(self.imu_source if self.imu_source is not None else u)
        self.predict(self.t + self.dt)

    # -- the filter --------------------------------------------------------------------

    # a filter run away overflows to inf or NaN; the episode's watch reports it as diverged
    # (quadobs.testbed.divergence), so NumPy's warnings would only repeat it
    @np.errstate(over="ignore", invalid="ignore")
    def _propagate_imu(self, h: float) -> None:
        f, w = self.u[:3] - self.b, self.u[3:]
        R, v = self.R, self.v
        n = self.P.shape[0]
        A = np.zeros((n, n))
        A[0:3, 3:6] = R
        A[0:3, 6:9] = -R @ skew(v)
        A[3:6, 3:6] = -skew(w)
        A[3:6, 6:9] = skew(R.T @ self.g)
        A[6:9, 6:9] = -skew(w)
        if n > 9:
            A[3:6, 9:12] = -np.eye(3)
        F = np.eye(n) + A * h
        P = F @ self.P @ F.T
        P[3:6, 3:6] += np.eye(3) * (self.q_v * h * h)
        P[6:9, 6:9] += np.eye(3) * (self.q_a * h * h)
        if n > 9:
            P[9:, 9:] += np.eye(3) * (self.q_b * h)
        self.P = 0.5 * (P + P.T)
        a = R @ f + self.g
        vw = R @ v
        self.p += vw * h + 0.5 * a * h * h
        vw += a * h
        self.R = R @ rotation_exp(w * h)
        self.v = self.R.T @ vw

    @np.errstate(over="ignore", invalid="ignore")
    def _update(self, m: Measurement, z: float) -> None:
        model = self.model
        g = model.jacobian(self.p, m)
        sigma2 = model.sigma(m) ** 2
        Ph = self.P[:, :3] @ g
        S = float(g @ Ph[:3]) + sigma2
        r = z - model.h(self.p, m)
        self.nis = r * r / S
        if self.gate is not None and self.nis > self.gate:
            self.rejected += 1
            return
        K = Ph / S
        n = self.P.shape[0]
        IKH = np.eye(n)
        IKH[:, :3] -= np.outer(K, g)
        self.P = IKH @ self.P @ IKH.T + sigma2 * np.outer(K, K)
        e = K * r
        self.p += e[:3]
        self.v += e[3:6]
        delta = e[6:9]
        if n > 9:
            self.b += e[9:]
        self.R = self.R @ rotation_exp(delta)
        G = np.eye(n)
        G[6:9, 6:9] -= 0.5 * skew(delta)
        self.P = G @ self.P @ G.T
        self.corrections += 1

    # -- what the testbed reads --------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        return np.concatenate([self.p, self.R @ self.v])

    @property
    def attitude(self) -> np.ndarray:
        """The estimated attitude ``R (3, 3)`` (world from body), a copy."""
        return self.R.copy()

    @property
    def accel_bias(self) -> np.ndarray:
        """The accelerometer's bias ``b (3,)`` (m/s^2, body frame; zero when not a state), a copy."""
        return self.b.copy()

    @property
    def x_covariance(self) -> np.ndarray:
        T = np.zeros((6, self.P.shape[0]))
        T[:3, :3] = np.eye(3)
        T[3:, 3:6] = self.R
        T[3:, 6:9] = -self.R @ skew(self.v)
        return T @ self.P @ T.T


def range_model(anchors, std: float) -> RangeModel:
    """The two-way range model of the filter's outputs (no bias)."""
    return RangeModel(anchors, std=std)
