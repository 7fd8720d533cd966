"""The quadrotor's inertial sensors: accelerometer, gyroscope and attitude (AHRS) errors.

Given MuJoCo's exact readings at ``t_k`` (specific force ``f`` and body rates ``w`` in
the body frame, attitude quaternion ``q``, world from body):

* accelerometer: ``f~ = f + b_a + sigma_a n``;
* gyroscope: ``w~ = w + b_w + sigma_w n``;
* attitude: ``q~ = q (x) [1, sigma_q n / 2]`` (normalised; a small rotation error about
  each body axis), sampled every ``attitude_every`` steps and held in between.

``n`` are standard normal draws, new each step; the biases ``b_a``, ``b_w`` are constant
over the episode, drawn once with standard deviations ``accel_bias`` and ``gyro_bias``.
Every draw comes from a stream of its own derived from the scenario's seed, so the
IMU errors of a seed do not depend on the other sensors.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BIAS_HORIZON", "IMU_SPAWN_KEY", "ImuModel", "input_noise_std", "quat_to_matrix"]

#: The spawn key of the IMU's random stream (beside :func:`~quadobs.testbed.sensors.spawn_streams`'s).
IMU_SPAWN_KEY = (1016,)

#: The horizon ``tau`` (s) over which a filter without a state for an inertial sensor's constant
#: bias ``b`` (accelerometer or gyroscope) takes it as a white noise of intensity ``b^2 tau``
#: (per sample of ``dt``: variance ``b^2 tau / dt``): over a window ``tau`` that noise's mean
#: has the bias's variance, so ``tau`` stands for how long the filter remembers its input
#: before the ranges (10 Hz and faster in the testbed) re-set what the input moved. On
#: ``quadrotor-uwb`` this term keeps the EKF consistent (docs/quadrotor.md: without it its NEES
#: is about 24 for 6 expected). The live EKF's input (:func:`input_noise_std`), the live
#: on-board EKF (:func:`quadobs.testbed.factories.onboard_ekf`) and the replay's gyroscope
#: (:func:`quadobs.testbed.logs.estimators.gyro_noise`) take it from here.
BIAS_HORIZON = 1.0


def quat_to_matrix(q) -> np.ndarray:
    """The rotation matrix ``(3, 3)`` of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = q
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ]
    )


def input_noise_std(
    spec,
    attitude_every: float,
    dt: float,
    gravity: float = 9.81,
    horizon: float | None = None,
) -> float:
    """The white input noise (m/s^2 per physics step) equivalent to the IMU's errors on ``u = R~ f~ + g``.

    To first order ``u - a = R (b_a + sigma_a n) + R [dtheta]x f`` with ``dtheta`` the AHRS
    error, drawn every ``m = attitude_every`` steps and held. Near hover ``|f| = gravity``
    and the attitude error moves ``u`` by ``gravity * dtheta`` across the thrust. A value held
    over ``m`` steps has the low-frequency power of a white sequence of ``m`` times its
    variance. The constant bias ``b_a`` (standard deviation ``accel_bias``) is matched over
    the filters' memory ``horizon`` (s): its mean over that window equals that of a white
    sequence of variance ``b^2 horizon / dt``. So

    .. math:: \\sigma_u^2 = \\sigma_a^2 + m\\,(g\\,\\sigma_q)^2 + b^2\\,\\frac{\\tau}{\\Delta t},

    one level for the three axes (the vertical axis, nearly along the thrust, is
    over-stated). Measured on ``quadrotor-uwb`` (30 s, 0.1 s window means), the white part
    is 0.20 m/s^2 across the thrust and 0.03 m/s^2 along it, as the first two terms give.

    As an intensity on ``v' = u`` (m^2/s^3), ``q = sigma_u^2 dt = N_a^2 + m dt (g sigma_q)^2 +
    b^2 tau`` with ``N_a = sigma_a sqrt(dt)`` the accelerometer's density: the live filters
    take it from the scenario's ``[quadrotor]`` table, the replay from the figures a log states
    (:func:`quadobs.testbed.logs.estimators.imu_input_noise`), through this one function.

    Parameters
    ----------
    spec : QuadrotorSpec
        ``accel_std`` (``sigma_a``), ``accel_bias`` (``b``) and ``attitude_std`` (``sigma_q``).
    attitude_every : float
        Physics steps between attitude samples (``m``; a log's attitude interval over its IMU
        interval need not be a whole number).
    dt : float
        Physics step (s).
    gravity : float
        m/s^2.
    horizon : float
        The window ``tau`` (s) over which the bias is matched (default :data:`BIAS_HORIZON`).
    """
    tau = BIAS_HORIZON if horizon is None else horizon
    white = spec.accel_std**2 + float(attitude_every) * (gravity * spec.attitude_std) ** 2
    return float(np.sqrt(white + spec.accel_bias**2 * tau / dt))


def _perturb(q: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``q (x) [1, angle / 2]``, normalised."""
    w, x, y, z = q
    a, b, c = 0.5 * angle
    out = np.array(
        [
            w - x * a - y * b - z * c,
            x + w * a + y * c - z * b,
            y + w * b + z * a - x * c,
            z + w * c + x * b - y * a,
        ]
    )
    return out / np.sqrt(out @ out)


class ImuModel:
    """Noise and biases of the accelerometer, gyroscope and attitude sensor (see the module docstring).

    Parameters
    ----------
    spec : QuadrotorSpec
        ``accel_std``, ``accel_bias``, ``gyro_std``, ``gyro_bias``, ``attitude_std``.
    seed : int
        The scenario's seed.
    attitude_every : int
        Physics steps between attitude samples.
    """

    def __init__(self, spec, seed: int, attitude_every: int = 1) -> None:
        self.rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=IMU_SPAWN_KEY))
        self.accel_std, self.gyro_std, self.attitude_std = (
            spec.accel_std,
            spec.gyro_std,
            spec.attitude_std,
        )
        self.accel_bias = spec.accel_bias * self.rng.standard_normal(3)
        self.gyro_bias = spec.gyro_bias * self.rng.standard_normal(3)
        self.attitude_every = int(attitude_every)
        self.attitude = np.array([1.0, 0.0, 0.0, 0.0])

    def draws(self, count: int) -> np.ndarray:
        """Standard normal draws of ``count`` steps, ``(count, 9)``: accelerometer, gyroscope, attitude."""
        return self.rng.standard_normal((count, 9))

    def measure(
        self, k: int, j: int, noise: np.ndarray, f, w, q
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Measured specific force ``(3,)``, body rates ``(3,)`` and attitude ``(4,)`` at step ``k`` (row ``j`` of ``noise``)."""
        n = noise[j]
        f_m = f + self.accel_bias + self.accel_std * n[:3]
        w_m = w + self.gyro_bias + self.gyro_std * n[3:6]
        if k % self.attitude_every == 0:
            self.attitude = (
                _perturb(q, self.attitude_std * n[6:9]) if self.attitude_std else np.array(q)
            )
        return f_m, w_m, self.attitude
