"""Wheel odometry of a planar ground robot: speed along the direction of travel and yaw rate.

A wheeled robot that does not slip moves along its heading, so its heading is the direction
of its velocity, ``theta = atan2(v_y, v_x)``, and its odometry reports the speed ``s = |v|``
and the yaw rate

.. math::

    \\omega = \\dot\\theta = \\frac{v_x a_y - v_y a_x}{|v|^2} ,

from the velocity ``v`` and the acceleration ``a`` of the point it tracks. The sensor
(``[odometry]``, :class:`~quadobs.testbed.scenario.OdometrySpec`) samples them at ``rate``
with the errors of wheel encoders and a yaw-rate gyroscope:

.. math::

    \\tilde s = (1 + \\epsilon_s)\\, s + \\sigma_s n_s, \\qquad
    \\tilde\\omega = \\omega + b_\\omega + \\sigma_\\omega n_\\omega ,

``epsilon_s`` the wheel-scale error (a wheel radius off by that fraction), ``b_omega`` the
yaw rate's constant bias, ``n_s, n_omega`` standard normal, each from its own stream spawned
from the seed, one draw per sample whether or not its standard deviation is zero: the same
seed gives the same samples, however the samples are cut into blocks.

A robot halted by a stop (``[[trajectory.stops]]``) keeps its heading, the direction of
travel of its path (:meth:`~quadobs.testbed.trajectory.SinusoidTrajectory.path_velocity`):
at a standstill the heading is that direction, the yaw rate zero, and the encoders read a
speed of exactly zero (no wheel turns; the speed's noise draw is taken all the same). Wheel
slip in turns (``turn_slip``, s/rad) makes the speed read more in proportion to the yaw rate,
``(1 + epsilon_s + k_slip |omega|) s``, as wheels that skid through a turn turn further
than the robot moves.

The dead-reckoned heading then drifts by ``b_omega t`` and the position by the scale error
times the distance travelled: what the replay's estimators of an odometry log must absorb
(:mod:`quadobs.testbed.logs.estimators`).
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["WheelOdometry", "heading_and_yaw_rate", "odometry_of"]

#: Speed (m/s) below which the direction of travel, and with it the yaw rate, is undefined.
STANDSTILL = 1e-9


def heading_and_yaw_rate(
    v: np.ndarray, a: np.ndarray, direction: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The speed ``|v|``, heading ``atan2(v_y, v_x)`` and yaw rate ``(v_x a_y - v_y a_x) / |v|^2``
    of planar velocities ``v (K, 2)`` and accelerations ``a (K, 2)`` (module docstring).

    ``direction (K, 2)``, optional: the direction of travel of the path (a stop's held
    heading); where the speed is below :data:`STANDSTILL` the heading is its angle and the yaw
    rate zero.

    Raises
    ------
    QuadobsError
        Where the speed is (nearly) zero without a ``direction``: a robot at a standstill has
        no direction of travel.
    """
    speed = np.hypot(v[:, 0], v[:, 1])
    still = speed < STANDSTILL
    if direction is not None and still.any():
        heading = np.arctan2(v[:, 1], v[:, 0])
        heading[still] = np.arctan2(direction[still, 1], direction[still, 0])
        yaw_rate = np.zeros(speed.size)
        moving = ~still
        vm, am = v[moving], a[moving]
        yaw_rate[moving] = (vm[:, 0] * am[:, 1] - vm[:, 1] * am[:, 0]) / speed[moving] ** 2
        return speed, heading, yaw_rate
    if speed.size and float(speed.min()) < STANDSTILL:
        raise QuadobsError(
            "odometry: the vehicle stops (speed below 1e-9 m/s): its heading is its direction of "
            "travel, undefined at a standstill; give the trajectory a speed that stays positive"
        )
    heading = np.arctan2(v[:, 1], v[:, 0])
    yaw_rate = (v[:, 0] * a[:, 1] - v[:, 1] * a[:, 0]) / speed**2
    return speed, heading, yaw_rate


class WheelOdometry:
    """The odometry sensor of a ``[odometry]`` table, seeded (module docstring).

    Parameters
    ----------
    spec : OdometrySpec
        ``rate``, ``speed_std``, ``scale_error``, ``yaw_rate_std``, ``yaw_rate_bias``.
    seed : int
    dt : float
        The physics step (s); a sample is taken every ``round(1 / (rate dt))`` steps.
    trajectory : SinusoidTrajectory, optional
        The reference path, whose direction of travel is the heading held at a stop.
    """

    def __init__(self, spec, seed: int, dt: float, trajectory=None) -> None:
        self.spec = spec
        self.trajectory = trajectory
        self.every = max(1, int(round(1.0 / (spec.rate * dt))))
        speed, yaw = np.random.SeedSequence([int(seed), 0x0D0]).spawn(2)
        self._speed_rng = np.random.default_rng(speed)
        self._yaw_rng = np.random.default_rng(yaw)

    def direction(self, t: np.ndarray | None) -> np.ndarray | None:
        """The path's direction of travel at times ``t`` where the path has stops (else ``None``)."""
        tr = self.trajectory
        if t is None or tr is None or not tr.stops.size:
            return None
        return tr.path_velocity(t)

    def sample(
        self, v: np.ndarray, a: np.ndarray, t: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The measured ``(speed, yaw_rate)`` ``(K, 2)``, and the true heading ``(K,)``, of ``K``
        samples at times ``t (K,)`` with true velocities ``v (K, 2)`` and accelerations ``a (K, 2)``."""
        c = self.spec
        speed, heading, yaw_rate = heading_and_yaw_rate(v, a, self.direction(t))
        n_s = self._speed_rng.standard_normal(speed.size)
        n_w = self._yaw_rng.standard_normal(speed.size)
        out = np.empty((speed.size, 2))
        scale = 1.0 + c.scale_error
        if c.turn_slip:
            scale = scale + c.turn_slip * np.abs(yaw_rate)
        out[:, 0] = scale * speed + c.speed_std * n_s
        out[speed < STANDSTILL, 0] = 0.0  # at rest the encoders count nothing
        out[:, 1] = yaw_rate + c.yaw_rate_bias + c.yaw_rate_std * n_w
        return out, heading, yaw_rate


def odometry_of(scenario) -> WheelOdometry | None:
    """The odometry sensor of a scenario's ``[odometry]`` table (``None`` without one)."""
    spec = getattr(scenario, "odometry", None)
    if spec is None:
        return None
    return WheelOdometry(spec, scenario.seed, scenario.dt, getattr(scenario, "trajectory", None))
