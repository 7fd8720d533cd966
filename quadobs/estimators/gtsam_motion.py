"""The peer's motion between nodes, one class per input kind (:mod:`quadobs.estimators.gtsam_peer`).

Each motion owns the variables of a node, the prior on the first node, the inputs held
since the last node (accumulated by :meth:`advance`), the factor that joins two nodes
(:meth:`close`) and the current estimate (the last node's, read back from iSAM2 and
propagated with the held inputs). The input ``u`` that :meth:`hold` takes, by kind:

* ``odometry``: ``(speed, yaw_rate)`` in the body frame, or, on the replay's grid,
  ``(v_x, v_y, omega)`` with the velocity in the dead-reckoning frame of the odometry
  (rotated into the body frame by the integrated odometry heading);
* ``none``: anything (ignored);
* ``accel_nav``: the acceleration ``(d,)`` in the navigation frame (gravity removed);
* ``imu_body``: the specific force ``(3,)`` then the angular rate ``(3,)``, body frame.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.gtsam_factors import double_integrator_factor

__all__ = ["MOTIONS", "make_motion"]

#: The input kinds the peer takes.
MOTIONS = ("odometry", "none", "accel_nav", "imu_body")

#: The shortest interval the double integrator's covariance is formed over (s): a floor that
#: keeps its information finite for two nodes a few microseconds apart.
_T_FLOOR = 1e-4


def make_motion(gtsam, kind: str, dim: int, noise):
    """The motion of ``kind`` (:data:`MOTIONS`) in ``dim`` dimensions."""
    if kind == "odometry":
        return OdometryMotion(gtsam, noise)
    if kind == "imu_body":
        return ImuMotion(gtsam, noise)
    return DoubleIntegratorMotion(gtsam, dim, noise, driven=kind == "accel_nav")


class OdometryMotion:
    """Planar poses joined by the odometry composed between them (``BetweenFactorPose2``)."""

    position_type = "pose2"
    grid_inputs = 3
    factorization = "CHOLESKY"

    def __init__(self, gtsam, noise) -> None:
        self.g, self.noise = gtsam, noise
        self.acc, self.acc_time = gtsam.Pose2(), 0.0
        self.u = np.zeros(3)
        self._v = np.zeros(2)

    def position_key(self, i: int) -> int:
        return self.g.symbol("x", i)

    def start(self, graph, values, x0, P0: float, heading0: float) -> None:
        g, sd = self.g, math.sqrt(P0)
        self.pose = g.Pose2(float(x0[0]), float(x0[1]), float(heading0))
        sigmas = np.array([sd, sd, self.noise.heading_sigma])
        graph.add(
            g.PriorFactorPose2(
                self.position_key(0), self.pose, g.noiseModel.Diagonal.Sigmas(sigmas)
            )
        )
        values.insert(self.position_key(0), self.pose)
        self.theta_odo = float(heading0)

    def hold(self, u: np.ndarray) -> None:
        if u.shape not in ((2,), (3,)):
            raise QuadobsError(
                f"u: odometry expects (speed, yaw_rate) or (v_x, v_y, omega), got shape {u.shape}"
            )
        self.u = u.copy()

    def advance(self, T: float) -> None:
        u, g = self.u, self.g
        if u.size == 3:  # the grid's velocity in the odometry's frame, into the body frame
            c, s = math.cos(self.theta_odo), math.sin(self.theta_odo)
            d = u[:2] * T
            self.acc = self.acc.compose(
                g.Pose2(c * d[0] + s * d[1], -s * d[0] + c * d[1], u[2] * T)
            )
            self._v = u[:2]
        else:  # constant speed and yaw rate: the arc
            self.acc = self.acc.compose(g.Pose2.Expmap(np.array([u[0] * T, 0.0, u[1] * T])))
            c, s = math.cos(self.theta_odo + u[1] * T), math.sin(self.theta_odo + u[1] * T)
            self._v = np.array([c * u[0], s * u[0]])
        self.theta_odo += u[-1] * T
        self.acc_time += T

    def close(self, graph, values, i: int, j: int) -> None:
        g, n = self.g, self.noise
        T = max(self.acc_time, _T_FLOOR)
        sigmas = np.sqrt(np.array([n.q_xy, n.q_xy, n.q_theta]) * T)
        graph.add(
            g.BetweenFactorPose2(
                self.position_key(i),
                self.position_key(j),
                self.acc,
                g.noiseModel.Diagonal.Sigmas(sigmas),
            )
        )
        values.insert(self.position_key(j), self.pose.compose(self.acc))
        self.pose = self.pose.compose(self.acc)
        self.acc, self.acc_time = g.Pose2(), 0.0

    def read(self, isam, i: int) -> None:
        self.pose = isam.calculateEstimatePose2(self.position_key(i))

    def current(self, n: int) -> np.ndarray:
        p = self.pose.compose(self.acc)
        if n == 2:
            return np.array([p.x(), p.y()])
        turn = p.theta() - self.theta_odo  # the estimated minus the odometry's heading
        c, s = math.cos(turn), math.sin(turn)
        v = self._v
        return np.array([p.x(), p.y(), c * v[0] - s * v[1], s * v[0] + c * v[1]])


class DoubleIntegratorMotion:
    """Position and velocity vectors joined by the double integrator (constant velocity, or driven by ``accel_nav``)."""

    position_type = "point"
    #: iSAM2's factorization: QR, since the double integrator over 10 ms ties the positions
    #: about 1e5 times tighter than a 10 m prior, a Hessian that gtsam's Cholesky declares
    #: indeterminate while QR on the Jacobian solves it
    factorization = "QR"

    def __init__(self, gtsam, dim: int, noise, driven: bool) -> None:
        self.g, self.d, self.noise, self.driven = gtsam, dim, noise, driven
        self.q = noise.q_imu if driven else noise.q_acc
        self.grid_inputs = dim if driven else None
        self.a = np.zeros(dim)
        self._reset()

    def _reset(self) -> None:
        self.dp, self.dv, self.T = np.zeros(self.d), np.zeros(self.d), 0.0

    def position_key(self, i: int) -> int:
        return self.g.symbol("x", i)

    def velocity_key(self, i: int) -> int:
        return self.g.symbol("v", i)

    def start(self, graph, values, x0, P0: float, heading0: float) -> None:
        g, d = self.g, self.d
        self.p = np.array(x0[:d], dtype=float)
        self.v = np.array(x0[d:], dtype=float) if x0.size == 2 * d else np.zeros(d)
        iso = g.noiseModel.Isotropic.Sigma
        graph.add(g.PriorFactorVector(self.position_key(0), self.p, iso(d, math.sqrt(P0))))
        graph.add(
            g.PriorFactorVector(self.velocity_key(0), self.v, iso(d, self.noise.velocity_sigma))
        )
        values.insert(self.position_key(0), self.p)
        values.insert(self.velocity_key(0), self.v)

    def hold(self, u: np.ndarray) -> None:
        if not self.driven:
            return
        if u.shape != (self.d,):
            raise QuadobsError(
                f"u: accel_nav expects the acceleration ({self.d},), got shape {u.shape}"
            )
        self.a = u.copy()

    def advance(self, T: float) -> None:
        self.dp += self.dv * T + 0.5 * self.a * T**2
        self.dv += self.a * T
        self.T += T

    def close(self, graph, values, i: int, j: int) -> None:
        keys = (
            self.position_key(i),
            self.velocity_key(i),
            self.position_key(j),
            self.velocity_key(j),
        )
        graph.add(
            double_integrator_factor(self.g, keys, self.T, self.dp, self.dv, self.q, _T_FLOOR)
        )
        self.p, self.v = self.p + self.v * self.T + self.dp, self.v + self.dv
        values.insert(keys[2], self.p)
        values.insert(keys[3], self.v)
        self._reset()

    def read(self, isam, i: int) -> None:
        self.p = np.asarray(isam.calculateEstimateVector(self.position_key(i)), dtype=float)
        self.v = np.asarray(isam.calculateEstimateVector(self.velocity_key(i)), dtype=float)

    def current(self, n: int) -> np.ndarray:
        p = self.p + self.v * self.T + self.dp
        return p if n == self.d else np.concatenate([p, self.v + self.dv])


class ImuMotion:
    """Pose3, velocity and IMU bias joined by gtsam's ``CombinedImuFactor`` (preintegration, bias random walk)."""

    position_type = "pose3"
    grid_inputs = 6
    factorization = "QR"  # as the double integrator's: nodes 10 ms apart

    def __init__(self, gtsam, noise) -> None:
        self.g, self.noise = gtsam, noise
        eye = np.eye(3)
        make = gtsam.PreintegrationCombinedParams
        params = (make.MakeSharedU if noise.frame == "enu" else make.MakeSharedD)(noise.gravity)
        params.setAccelerometerCovariance(noise.q_imu * eye)
        params.setGyroscopeCovariance(noise.q_gyro * eye)
        params.setIntegrationCovariance(1e-8 * eye)
        params.setBiasAccCovariance(noise.accel_bias_walk * eye)
        params.setBiasOmegaCovariance(noise.gyro_bias_walk * eye)
        self.params = params
        self.bias = gtsam.imuBias.ConstantBias()
        self.pim = gtsam.PreintegratedCombinedMeasurements(params, self.bias)
        self.u: np.ndarray | None = None

    def position_key(self, i: int) -> int:
        return self.g.symbol("x", i)

    def velocity_key(self, i: int) -> int:
        return self.g.symbol("v", i)

    def _keys(self, i: int) -> tuple[int, int, int]:
        return self.g.symbol("x", i), self.velocity_key(i), self.g.symbol("b", i)

    def start(self, graph, values, x0, P0: float, heading0: float) -> None:
        g, n = self.g, self.noise
        kx, kv, kb = self._keys(0)
        self.pose = g.Pose3(g.Rot3.Ypr(float(heading0), 0.0, 0.0), np.array(x0[:3], dtype=float))
        self.vel = np.array(x0[3:], dtype=float) if x0.size == 6 else np.zeros(3)
        sd = math.sqrt(P0)
        roll, pitch, yaw = n.attitude_sigma
        # Pose3's tangent: rotation (about the body's x, y, z) then translation
        sig = np.array([roll, pitch, yaw, sd, sd, sd])
        graph.add(g.PriorFactorPose3(kx, self.pose, g.noiseModel.Diagonal.Sigmas(sig)))
        graph.add(
            g.PriorFactorVector(kv, self.vel, g.noiseModel.Isotropic.Sigma(3, n.velocity_sigma))
        )
        bias_sig = np.array([n.accel_bias_sigma] * 3 + [n.gyro_bias_sigma] * 3)
        graph.add(g.PriorFactorConstantBias(kb, self.bias, g.noiseModel.Diagonal.Sigmas(bias_sig)))
        values.insert(kx, self.pose)
        values.insert(kv, self.vel)
        values.insert(kb, self.bias)

    def hold(self, u: np.ndarray) -> None:
        if u.shape != (6,):
            raise QuadobsError(
                f"u: imu_body expects the specific force and angular rate (6,), got shape {u.shape}"
            )
        self.u = u.copy()

    def advance(self, T: float) -> None:
        if self.u is None:
            raise QuadobsError("isam2: an imu_body log needs an input held before time moves on")
        self.pim.integrateMeasurement(self.u[:3], self.u[3:], T)

    def close(self, graph, values, i: int, j: int) -> None:
        g = self.g
        ki, kj = self._keys(i), self._keys(j)
        graph.add(g.CombinedImuFactor(ki[0], ki[1], kj[0], kj[1], ki[2], kj[2], self.pim))
        state = self.pim.predict(g.NavState(self.pose, self.vel), self.bias)
        self.pose, self.vel = state.pose(), np.asarray(state.velocity(), dtype=float)
        values.insert(kj[0], self.pose)
        values.insert(kj[1], self.vel)
        values.insert(kj[2], self.bias)
        self.pim.resetIntegrationAndSetBias(self.bias)

    def read(self, isam, i: int) -> None:
        kx, kv, kb = self._keys(i)
        self.pose = isam.calculateEstimatePose3(kx)
        self.vel = np.asarray(isam.calculateEstimateVector(kv), dtype=float)
        self.bias = isam.calculateEstimateConstantBias(kb)
        if self.pim.deltaTij() == 0.0:  # integrate from here on with the new bias estimate
            self.pim.resetIntegrationAndSetBias(self.bias)

    def current(self, n: int) -> np.ndarray:
        if self.pim.deltaTij() > 0.0:
            state = self.pim.predict(self.g.NavState(self.pose, self.vel), self.bias)
            p, v = np.asarray(state.position()), np.asarray(state.velocity())
        else:
            p, v = np.asarray(self.pose.translation()), self.vel
        return np.array(p, dtype=float) if n == 3 else np.concatenate([p, v]).astype(float)
