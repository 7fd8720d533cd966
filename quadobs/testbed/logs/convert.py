"""Conversions a user's own data may need before it is a log (docs/replaying-your-data.md).

Wheel odometry often arrives as the pose it integrates (``x, y, yaw`` in its own frame, as
``nav_msgs/Odometry.pose`` or an encoder log's running sum), where ``inputs.csv`` holds the
speed and the yaw rate. :func:`odometry_from_poses` inverts the replay's dead reckoning
(:func:`~quadobs.testbed.worlds.replay.dead_reckoning`): each input row is held from its time
to the next, the heading grows by ``omega_i dt_i`` and the position moves by ``v_i dt_i``
along the interval's middle heading,

.. math::

    \\omega_i = \\frac{\\psi_{i+1} - \\psi_i}{\\Delta t_i}, \\qquad
    v_i = \\frac{(P_{i+1} - P_i)^\\top (\\cos \\bar\\psi_i, \\sin \\bar\\psi_i)}{\\Delta t_i},
    \\qquad \\bar\\psi_i = \\frac{\\psi_i + \\psi_{i+1}}{2},

``psi`` the yaw unwrapped: the step's component along the middle heading, so that the poses
come back exactly where the vehicle moves along it (negative going backwards), and a sideways
slip of the odometry's own is left out. The odometry frame's origin and orientation do not
enter: the log's ``heading0`` is the heading at the first row in the anchors' frame, which
the poses do not tell.

A differential drive logs its wheels instead: :func:`odometry_from_wheels` takes the left and
right wheels' ground speeds (each wheel's rate times its radius) and the track ``b`` (the
distance between the wheels' contact points), ``v = (v_r + v_l) / 2``, ``omega = (v_r - v_l)
/ b``, turning left (counter-clockwise seen from above, the sign of a yaw rate about an
upward axis) when the right wheel is the faster.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["odometry_from_poses", "odometry_from_wheels"]


def odometry_from_poses(t, x, y, yaw) -> np.ndarray:
    """``inputs.csv``'s rows ``time, speed, yaw_rate`` (``(K, 3)``) from odometry poses.

    Parameters
    ----------
    t : array_like (K,)
        Times (s), strictly increasing.
    x, y : array_like (K,)
        The odometry's position (m), in its own frame.
    yaw : array_like (K,)
        Its heading (rad), in the same frame; wrapped or not.

    Returns
    -------
    ndarray (K, 3)
        The speed and yaw rate held over each interval (module docstring); the last row holds
        the one before it (nothing follows it).
    """
    t, x, y, yaw = (np.asarray(v, dtype=float).ravel() for v in (t, x, y, yaw))
    if not (t.size == x.size == y.size == yaw.size) or t.size < 2:
        raise QuadobsError(
            "odometry_from_poses: t, x, y, yaw: equal lengths of at least 2 expected"
        )
    if not np.all(np.isfinite(np.concatenate([t, x, y, yaw]))):
        raise QuadobsError("odometry_from_poses: every value must be a finite number")
    dt = np.diff(t)
    if np.any(dt <= 0.0):
        k = int(np.flatnonzero(dt <= 0.0)[0])
        raise QuadobsError(
            f"odometry_from_poses: times must increase (row {k + 2}: {float(t[k + 1])!r} after {float(t[k])!r})"
        )
    psi = np.unwrap(yaw)
    mid = 0.5 * (psi[:-1] + psi[1:])
    speed = (np.diff(x) * np.cos(mid) + np.diff(y) * np.sin(mid)) / dt
    rate = np.diff(psi) / dt
    return np.column_stack([t, np.append(speed, speed[-1]), np.append(rate, rate[-1])])


def odometry_from_wheels(t, left, right, track: float) -> np.ndarray:
    """``inputs.csv``'s rows ``time, speed, yaw_rate`` (``(K, 3)``) of a differential drive.

    Parameters
    ----------
    t : array_like (K,)
        Times (s), strictly increasing.
    left, right : array_like (K,)
        The left and right wheels' ground speeds (m/s: a wheel's rate in rad/s times its
        radius), positive forwards.
    track : float
        The distance between the wheels' contact points (m), positive.

    Returns
    -------
    ndarray (K, 3)
        ``v = (v_r + v_l) / 2`` and ``omega = (v_r - v_l) / track`` (module docstring).
    """
    t, left, right = (np.asarray(v, dtype=float).ravel() for v in (t, left, right))
    if not (t.size == left.size == right.size) or t.size < 2:
        raise QuadobsError(
            "odometry_from_wheels: t, left, right: equal lengths of at least 2 expected"
        )
    if not np.all(np.isfinite(np.concatenate([t, left, right]))):
        raise QuadobsError("odometry_from_wheels: every value must be a finite number")
    if not (np.isfinite(track) and track > 0.0):
        raise QuadobsError(f"odometry_from_wheels: track: a positive distance in m, got {track!r}")
    dt = np.diff(t)
    if np.any(dt <= 0.0):
        k = int(np.flatnonzero(dt <= 0.0)[0])
        raise QuadobsError(
            f"odometry_from_wheels: times must increase (row {k + 2}: {t[k + 1]} after {t[k]})"
        )
    return np.column_stack([t, 0.5 * (right + left), (right - left) / float(track)])
