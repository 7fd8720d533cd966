"""The quadrotor world: a Crazyflie 2.x in MuJoCo, flown by a controller on the truth or on an estimate.

Closed loop (:attr:`World.closed_loop`): each physics step ``k`` (time ``t_k``)

1. the controller (:class:`~quadobs.testbed.controllers.GeometricController`, at
   ``control.rate``) chooses the rotor thrust commands from the reference
   (:class:`~quadobs.testbed.controllers.FlightPlan`) and either the truth or, from
   ``control.switch_time`` on, the position and velocity estimated by the estimator named
   ``control.feedback`` with the attitude and body rates measured one step earlier (as
   the on-board AHRS and gyroscope give them);
2. the UWB ranges ``|p_k - a_h|`` of the tag (site ``imu``) go through the sensor layer
   (:class:`~quadobs.testbed.sensors.SensorModel`: noise, rate, dropouts, outliers);
3. ``mj_step``; MuJoCo's sensors then describe ``t_k``: the specific force ``f`` and the
   body rates in the body frame, the attitude quaternion;
4. the IMU layer (:class:`~quadobs.testbed.imu.ImuModel`) adds noise and constant biases
   to ``f`` and the rates and an attitude error to the quaternion, and the estimators'
   input is the world-frame acceleration rebuilt from them, ``u_k = R~ f~ + g``.

The estimators' model stays the double integrator ``p'' = u``: IMU and attitude errors
reach them through ``u`` as on a real vehicle.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.controllers import CRAZYFLIE, FlightPlan, GeometricController
from quadobs.testbed.imu import ImuModel, quat_to_matrix
from quadobs.testbed.scenario import ControlSpec, QuadrotorSpec
from quadobs.testbed.worlds.base import Columns, World

__all__ = ["QuadrotorWorld", "quadrotor_model_path", "FLIGHT_COLUMNS"]

_GRAVITY = np.array([0.0, 0.0, -9.81])
_mj_step = mujoco.mj_step

#: The world's own columns: reference position, true attitude quaternion, rotor commands,
#: tracking error, flown on the estimate (0/1), crashed (0/1).
FLIGHT_COLUMNS = (("reference", 3), ("attitude", 4), ("rotors", 4), ("tracking", 1), ("on_estimate", 1), ("crashed", 1))


def quadrotor_model_path() -> Path:
    """The built-in quadrotor MJCF: inside the installed package, or ``models/`` of a source checkout."""
    here = Path(__file__).resolve().parents[2]
    for candidate in (here / "_models" / "quadrotor.xml", here.parent / "models" / "quadrotor.xml"):
        if candidate.is_file():
            return candidate
    raise QuadobsError("model: the built-in quadrotor.xml was not found beside the package (broken installation)")


def _columns(q: int, q_b: int) -> tuple[Columns, dict]:
    n = 6
    spans, o = {}, n + q + 3 + q_b
    for name, width in FLIGHT_COLUMNS:
        spans[name] = slice(o, o + width)
        o += width
    cols = Columns(truth=slice(0, n), y=slice(n, n + q), u=slice(n + q, n + q + 3), measured=slice(n + q + 3, n + q + 3 + q_b), width=o, extra=spans)
    return cols, spans


class QuadrotorWorld(World):
    """A ``quadrotor`` scenario's vehicle, controller, IMU and UWB (see the module docstring).

    Parameters
    ----------
    scenario : Scenario
        ``kind = "quadrotor"``: anchors (``beacons``), trajectory, ``[control]``, ``[quadrotor]``.
    sensors : SensorModel
        The range sensor layer.
    capacity : int
        Most steps per block.
    """

    closed_loop = True

    def __init__(self, scenario, sensors, capacity: int) -> None:
        if scenario.kind != "quadrotor":
            raise QuadobsError(f"kind: the quadrotor world needs kind = \"quadrotor\", got {scenario.kind!r}")
        self.scenario, self.sensors = scenario, sensors
        self.control = control = scenario.control or ControlSpec()
        self.spec = spec = scenario.quadrotor or QuadrotorSpec()
        path = scenario.model or str(quadrotor_model_path())
        self.model = mujoco.MjModel.from_xml_path(path)
        self.model.opt.timestep = scenario.dt
        self.data = mujoco.MjData(self.model)
        self.dt = scenario.dt
        self._ids(scenario)
        self.controller = None if control.feedback == "truth" else control.feedback
        self.switch_step = int(round(control.switch_time / scenario.dt)) if self.controller else None
        self.control_every = scenario.sample_interval(control.rate, "rate", table="control")
        self.ctrl = GeometricController(CRAZYFLIE, control.position_bandwidth, control.attitude_bandwidth, control.damping)
        self.imu = ImuModel(spec, scenario.seed, scenario.sample_interval(spec.attitude_rate, "attitude_rate", table="quadrotor"))
        self.columns, self.spans = _columns(sensors.q, sensors.q_b)
        self.out = np.full((int(capacity) + 1, self.columns.width), np.nan)
        self.events = np.zeros((int(capacity) + 1, 2), dtype=np.int64)
        self._place(scenario)
        self.crashed_at: int | None = None

    def _ids(self, scenario) -> None:
        m = self.model
        try:
            joint = m.joint("quadrotor_joint")
            self._acc = m.sensor("accelerometer").adr[0]
            self._gyro = m.sensor("gyro").adr[0]
            self._quat = m.sensor("attitude").adr[0]
            self._rotors = np.array([m.actuator(f"rotor{i}").id for i in range(4)])
        except KeyError as exc:
            raise QuadobsError(f"model: the quadrotor MJCF lacks an element ({exc})") from None
        self._qp, self._qv = int(joint.qposadr[0]), int(joint.dofadr[0])
        self.anchors = np.asarray(scenario.beacons, dtype=float)

    def _place(self, scenario) -> None:
        """On the floor below the trajectory's start, level, motors off."""
        d, qp = self.data, self._qp
        mujoco.mj_resetData(self.model, d)
        start = scenario.trajectory.position(0.0)
        d.qpos[qp : qp + 2] = start[:2]
        mujoco.mj_forward(self.model, d)
        self.floor = float(d.qpos[qp + 2])
        spec = self.spec
        hovers = [(h.start, h.end) for h in spec.hovers]
        self.plan = FlightPlan(scenario.trajectory, scenario.duration, takeoff=spec.takeoff, landing=spec.landing,
                               hovers=hovers, ramp=spec.hover_ramp, floor=self.floor)
        self.attitude_meas = np.array([1.0, 0.0, 0.0, 0.0])
        self.rates_meas = np.zeros(3)

    # -- the World interface --------------------------------------------------------------

    def state(self) -> np.ndarray:
        d = self.data
        return np.concatenate([d.qpos[self._qp : self._qp + 3], d.qvel[self._qv : self._qv + 3]])

    def begin_block(self, k0: int, count: int) -> int:
        count = min(count, self.out.shape[0] - 1)
        self.k0 = k0
        self.refs = self.plan.reference((k0 + np.arange(count)) * self.dt)  # (count, 3, 3)
        self.noise = self.imu.draws(count)
        self.out[:] = np.nan
        self.out[0, self.columns.truth] = self.state()
        return count

    def step(self, j: int, estimate: np.ndarray | None = None) -> None:
        d, row, sp, k = self.data, self.out[j], self.spans, self.k0 + j
        qp, qv = self._qp, self._qv
        p = d.qpos[qp : qp + 3]
        ref = self.refs[j]
        if k % self.control_every == 0:
            self._control(k, ref, p, estimate)
        rel = p - self.anchors
        ranges = np.sqrt(np.einsum("hi,hi->h", rel, rel))
        s = self.sensors
        before = (s.outliers_injected, s.dropped)
        row[self.columns.y] = s.outputs(k, ranges)
        self.events[j] = (s.outliers_injected - before[0], s.dropped - before[1])
        row[self.columns.measured] = s.measured_ranges
        err = float(np.linalg.norm(ref[0] - p))
        row[sp["reference"]] = ref[0]
        row[sp["tracking"]] = err
        row[sp["rotors"]] = d.ctrl[self._rotors]
        row[sp["on_estimate"]] = self._on_estimate
        _mj_step(self.model, d)
        sd = d.sensordata
        quat = sd[self._quat : self._quat + 4]
        row[sp["attitude"]] = quat
        f_m, self.rates_meas, self.attitude_meas = self.imu.measure(k, j, self.noise, sd[self._acc : self._acc + 3], sd[self._gyro : self._gyro + 3], quat)
        row[self.columns.u] = quat_to_matrix(self.attitude_meas) @ f_m + _GRAVITY
        if self.crashed_at is None and (err > self.control.crash_distance or quat_to_matrix(quat)[2, 2] < 0.0):
            self.crashed_at = k
        row[sp["crashed"]] = self.crashed_at is not None
        self.out[j + 1, self.columns.truth] = self.state()

    def _control(self, k: int, ref: np.ndarray, p: np.ndarray, estimate) -> None:
        d, qv = self.data, self._qv
        self._on_estimate = self.controller is not None and k >= self.switch_step and estimate is not None
        if self.crashed_at is not None:
            d.ctrl[self._rotors] = 0.0
            return
        if self._on_estimate:
            pos, vel = estimate[:3], estimate[3:6]
            R, W = quat_to_matrix(self.attitude_meas), self.rates_meas
        else:
            pos, vel = p, d.qvel[qv : qv + 3]
            R = quat_to_matrix(d.qpos[self._qp + 3 : self._qp + 7])
            W = d.qvel[qv + 3 : qv + 6]  # a free joint's angular velocity is in the body frame
        d.ctrl[self._rotors] = self.ctrl(pos, vel, R, W, ref)

    _on_estimate = False

    def sinks(self, recording=None) -> list:
        """The episode's flight summary and recorded series (:class:`~quadobs.testbed.flight.FlightSink`)."""
        from quadobs.testbed.flight import FlightSink

        return [FlightSink(self, recording)]

    def commit(self, rows: int) -> None:
        """The sensor events were counted step by step (:meth:`step`)."""
