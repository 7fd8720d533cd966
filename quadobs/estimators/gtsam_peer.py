"""The peer on logged data: GTSAM's iSAM2 on a range-only pose graph [KAESS2012].

A factor graph over planar poses ``X_i = (x, y, theta)`` and the beacons ``L_h``:

* a prior on ``X_0``: the initial guess of the position (standard deviation
  ``sqrt(P0)`` per axis) and the odometry's heading origin (``heading_sigma``);
* a tight prior on each beacon at its surveyed position (``1e-3`` m);
* ``BetweenFactorPose2`` between consecutive poses: the odometry composed over the steps
  between them, ``Delta = prod_k Pose2(R(theta^o_k)^T v_k dt, omega_k dt)``, with
  ``theta^o`` the odometry's heading (integrated from ``heading0``), so each factor is the
  body-frame motion the wheels measured; its covariance ``diag(q_xy, q_xy, q_theta) T``
  for ``T`` seconds between the poses;
* ``RangeFactor2D(X_i, L_h, rho)`` for each range, with a Huber loss (``huber`` standard
  deviations) on ``rho = sqrt(2 y_h + |a_h|^2)`` of standard deviation ``range_sigma``.

A pose is added only at a step that has ranges (a keyframe), and iSAM2 is updated then;
between keyframes the estimate is the last keyframe's estimate composed with the
odometry since. So :attr:`Isam2RangeOnly.x_hat` at each step is iSAM2's online estimate
(its current solution of the graph so far). :meth:`Isam2RangeOnly.batch_optimum` solves
the whole graph by Levenberg-Marquardt (started at iSAM2's final estimate): the offline
optimum, reported beside the online figures.

``gtsam`` is imported when an estimator is built (the ``data`` extra).
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.base import Counted, Estimator, check_step

__all__ = ["Isam2RangeOnly", "import_gtsam"]


def import_gtsam():
    """The ``gtsam`` module, or a one-line error saying how to install it."""
    try:
        import gtsam
    except ImportError:
        raise QuadobsError(
            "isam2: needs the gtsam package; install the data extra (pip install 'quadobs[data]')"
        ) from None
    return gtsam


class Isam2RangeOnly(Estimator, Counted):
    """iSAM2 with ``RangeFactor2D`` and odometry ``BetweenFactorPose2`` as an online estimator (module docstring).

    Parameters
    ----------
    beacons : array_like (q, 2)
        Beacon positions, in the order of the outputs ``y``.
    dt : float
        Step (s).
    x0 : array_like (2,) or (4,)
        Initial guess of the state (position first; a velocity part is ignored).
    heading0 : float
        The odometry's heading at the first step (rad).
    P0 : float
        Variance of the initial position guess per axis (m^2).
    n : {2, 4}
        Size of :attr:`x_hat`: the position, or the position and the velocity (the odometry
        velocity rotated into the estimated heading).
    range_sigma : float
        Range standard deviation (m).
    huber : float
        Huber threshold in standard deviations.
    q_xy, q_theta : float
        Odometry noise intensities (m^2/s, rad^2/s).
    heading_sigma : float
        Standard deviation of the heading prior (rad).
    """

    name = "isam2"

    def __init__(
        self,
        beacons,
        dt: float,
        *,
        x0,
        heading0: float,
        P0: float = 2500.0,
        n: int = 2,
        range_sigma: float = 1.0,
        huber: float = 3.0,
        q_xy: float = 0.1,
        q_theta: float = 1e-3,
        heading_sigma: float = 0.05,
    ) -> None:
        gtsam = self._g = import_gtsam()
        self.beacons = as_array("beacons", beacons, (None, 2))
        self.dt = as_finite_scalar("dt", dt, positive=True)
        if n not in (2, 4):
            raise QuadobsError(f"n: expected 2 or 4, got {n}")
        x0 = as_array("x0", x0, (n,))
        self.n, self.q = n, self.beacons.shape[0]
        self._a2 = np.einsum("hi,hi->h", self.beacons, self.beacons)
        self.q_xy, self.q_theta = float(q_xy), float(q_theta)
        self._range_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(float(huber)),
            gtsam.noiseModel.Isotropic.Sigma(1, float(range_sigma)),
        )
        self.isam = gtsam.ISAM2(gtsam.ISAM2Params())
        self.graph, self.values = (
            gtsam.NonlinearFactorGraph(),
            gtsam.Values(),
        )  # the whole log, for the batch optimum
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        sd = math.sqrt(as_finite_scalar("P0", P0, positive=True))
        pose0 = gtsam.Pose2(float(x0[0]), float(x0[1]), float(heading0))
        g.add(
            gtsam.PriorFactorPose2(
                self._x(0),
                pose0,
                gtsam.noiseModel.Diagonal.Sigmas(np.array([sd, sd, heading_sigma])),
            )
        )
        v.insert(self._x(0), pose0)
        tight = gtsam.noiseModel.Isotropic.Sigma(2, 1e-3)
        for h, a in enumerate(self.beacons):
            g.add(gtsam.PriorFactorPoint2(self._l(h), np.array(a), tight))
            v.insert(self._l(h), np.array(a))
        self._update(g, v)
        self.key, self.key_steps = 0, [0]
        self.pose = pose0  # iSAM2's estimate of the last keyframe
        self.acc, self.acc_time = gtsam.Pose2(), 0.0  # odometry since the last keyframe
        self.theta_odo, self.k = float(heading0), 0
        self.corrections = 0
        self._v = np.zeros(2)

    def _x(self, i: int) -> int:
        return self._g.symbol("x", i)

    def _l(self, h: int) -> int:
        return self._g.symbol("l", h)

    def _update(self, g, v) -> None:
        self.graph.push_back(g)
        self.values.insert(v)
        self.isam.update(g, v)

    def _keyframe(self, y: np.ndarray, present: np.ndarray) -> None:
        """A new pose (unless this is the first step) with the odometry factor and the ranges; iSAM2 update."""
        gtsam = self._g
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if self.k > self.key_steps[-1]:
            T = max(self.acc_time, self.dt)
            noise = gtsam.noiseModel.Diagonal.Sigmas(
                np.sqrt(np.array([self.q_xy, self.q_xy, self.q_theta]) * T)
            )
            g.add(
                gtsam.BetweenFactorPose2(self._x(self.key), self._x(self.key + 1), self.acc, noise)
            )
            self.key += 1
            self.key_steps.append(self.k)
            v.insert(self._x(self.key), self.pose.compose(self.acc))
            self.acc, self.acc_time = gtsam.Pose2(), 0.0
        for h in np.flatnonzero(present):
            rho = math.sqrt(max(2.0 * y[h] + self._a2[h], 0.0))
            g.add(gtsam.RangeFactor2D(self._x(self.key), self._l(int(h)), rho, self._range_noise))
        self._update(g, v)
        self.pose = self.isam.calculateEstimatePose2(self._x(self.key))
        self.corrections += int(present.sum())

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Ranges of this step (a keyframe and an iSAM2 update when there are any), then the odometry over it."""
        u, y = check_step(u, y, 3, self.q)
        present = ~np.isnan(y)
        if present.any():
            self._keyframe(y, present)
        c, s = math.cos(self.theta_odo), math.sin(self.theta_odo)
        d = u[:2] * self.dt
        self.acc = self.acc.compose(
            self._g.Pose2(c * d[0] + s * d[1], -s * d[0] + c * d[1], u[2] * self.dt)
        )
        self.acc_time += self.dt
        self.theta_odo += u[2] * self.dt
        self._v = u[:2]
        self.k += 1

    @property
    def x_hat(self) -> np.ndarray:
        """The last keyframe's iSAM2 estimate composed with the odometry since: ``(x, y)`` (and the velocity)."""
        p = self.pose.compose(self.acc)
        if self.n == 2:
            return np.array([p.x(), p.y()])
        turn = p.theta() - self.theta_odo  # estimated minus odometry heading
        c, s = math.cos(turn), math.sin(turn)
        v = self._v
        return np.array([p.x(), p.y(), c * v[0] - s * v[1], s * v[0] + c * v[1]])

    def online_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """The keyframes' steps ``(m,)`` and iSAM2's current (smoothed) positions of them ``(m, 2)``."""
        est = self.isam.calculateEstimate()
        return np.array(self.key_steps), np.array(
            [est.atPose2(self._x(i)).translation() for i in range(self.key + 1)]
        )

    def batch_optimum(self) -> tuple[np.ndarray, np.ndarray]:
        """The keyframes' steps ``(m,)`` and their positions ``(m, 2)`` in the Levenberg-Marquardt optimum of the whole graph.

        Started at iSAM2's final estimate of every variable.
        """
        gtsam = self._g
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        opt = gtsam.LevenbergMarquardtOptimizer(
            self.graph, self.isam.calculateEstimate(), params
        ).optimize()
        return np.array(self.key_steps), np.array(
            [opt.atPose2(self._x(i)).translation() for i in range(self.key + 1)]
        )
