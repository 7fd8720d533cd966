"""The quadrotor world: a Crazyflie 2.x in MuJoCo, flown by a controller on the truth or on an estimate.

Closed loop (:attr:`World.closed_loop`): each physics step ``k`` (time ``t_k``)

1. the controller (:class:`~quadobs.testbed.controllers.GeometricController`, at
   ``control.rate``) chooses the rotor thrusts (with integral action on the position
   error, ``control.integral_bandwidth``, and commanded through the lead that inverts
   the identified rotor lag, :func:`~quadobs.testbed.controllers.lead`) from the reference
   (:class:`~quadobs.testbed.controllers.FlightPlan`) and either the truth or, from
   ``control.switch_time`` on, the position and velocity estimated by the estimator named
   ``control.feedback`` with the attitude and body rates measured one step earlier (as
   the on-board AHRS and gyroscope give them);
2. the UWB ranges ``|p_k - a_h|`` of the tag (site ``imu``) go through the sensor layer
   (:class:`~quadobs.testbed.sensors.SensorModel`: noise, rate, dropouts, outliers);
3. (with ``[quadrotor] gust_speed``) the wind of the gusts is set on MuJoCo's fluid model;
   the rotors' speeds follow the commands over the step (the identified asymmetric
   dynamics of :mod:`quadobs.testbed.rotors`, compiled), and their thrusts drive the
   MuJoCo actuators over the step;
4. ``mj_step``; MuJoCo's sensors then describe ``t_k``: the specific force ``f`` and the
   body rates in the body frame, the attitude quaternion;
5. the IMU layer (:class:`~quadobs.testbed.imu.ImuModel`) adds noise and constant biases
   to ``f`` and the rates and an attitude error to the quaternion, and the estimators'
   input is the world-frame acceleration rebuilt from them, ``u_k = R~ f~ + g``.

The estimators' model stays the double integrator ``p'' = u``: IMU and attitude errors
reach them through ``u`` as on a real vehicle.

Steps 1, 2 (the ranges), 3 and 5 run compiled (:mod:`quadobs._kernels.quadrotor`, the same
arithmetic as :class:`~quadobs.testbed.controllers.GeometricController` and
:class:`~quadobs.testbed.imu.ImuModel`) on buffers allocated once.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.controllers import CRAZYFLIE, LEAD_FILTER, FlightPlan, GeometricController
from quadobs.testbed.imu import ImuModel
from quadobs.testbed.rotors import IDENTIFIED, RotorModel
from quadobs.testbed.scenario import ControlSpec, QuadrotorSpec
from quadobs.testbed.worlds.base import Columns, World
from quadobs.testbed.worlds.model import builtin_model_path
from quadobs.testbed.worlds.radio_feed import RadioFeed

__all__ = ["FLIGHT_COLUMNS", "QuadrotorWorld", "quadrotor_model_path"]

_mj_step = mujoco.mj_step

#: The world's own columns: reference position, true attitude quaternion, rotor commands,
#: tracking error, flown on the estimate (0/1), crashed (0/1), the rotors' thrusts (N).
FLIGHT_COLUMNS = (
    ("reference", 3),
    ("attitude", 4),
    ("rotors", 4),
    ("tracking", 1),
    ("on_estimate", 1),
    ("crashed", 1),
    ("thrust", 4),
)


def quadrotor_model_path() -> Path:
    """The built-in quadrotor MJCF (:func:`~quadobs.testbed.worlds.model.builtin_model_path`)."""
    return builtin_model_path("quadrotor.xml")


def rotor_model(spec: QuadrotorSpec) -> RotorModel:
    """The identified rotor (:data:`~quadobs.testbed.rotors.IDENTIFIED`), or its time constants at hover set by ``[quadrotor] rotor_tau_up``/``rotor_tau_down``.

    One of them given alone scales the other by the identified ratio ``tau_d / tau_u``.
    """
    up, down = spec.rotor_tau_up, spec.rotor_tau_down
    if up is None and down is None:
        return IDENTIFIED
    tau_u, tau_d = IDENTIFIED.time_constants(CRAZYFLIE.mass)
    if up is None:
        assert down is not None, "both None returned above"
        up = down * tau_u / tau_d
    if down is None:
        down = up * tau_d / tau_u
    return IDENTIFIED.with_time_constants(CRAZYFLIE.mass, up, down)


def _columns(q: int, q_b: int) -> tuple[Columns, dict]:
    n = 6
    spans, o = {}, n + q + 3 + q_b
    for name, width in FLIGHT_COLUMNS:
        spans[name] = slice(o, o + width)
        o += width
    cols = Columns(
        truth=slice(0, n),
        y=slice(n, n + q),
        u=slice(n + q, n + q + 3),
        measured=slice(n + q + 3, n + q + 3 + q_b),
        width=o,
        extra=spans,
    )
    return cols, spans


class QuadrotorWorld(RadioFeed, World):
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
            raise QuadobsError(
                f'kind: the quadrotor world needs kind = "quadrotor", got {scenario.kind!r}'
            )
        self.scenario, self.sensors = scenario, sensors
        self.control = control = scenario.control or ControlSpec()
        self.spec = spec = scenario.quadrotor or QuadrotorSpec()
        path = scenario.model or str(quadrotor_model_path())
        self.model = mujoco.MjModel.from_xml_path(path)
        self.model.opt.timestep = scenario.dt
        self.rotor = rotor_model(spec)
        self.data = mujoco.MjData(self.model)
        self.dt = scenario.dt
        self._ids(scenario)
        self.controller = None if control.feedback == "truth" else control.feedback
        self.switch_step = (
            int(round(control.switch_time / scenario.dt)) if self.controller else None
        )
        self.control_every = scenario.sample_interval(control.rate, "rate", table="control")
        self.ctrl = GeometricController(
            CRAZYFLIE, control.position_bandwidth, control.attitude_bandwidth, control.damping
        )
        self.imu = ImuModel(
            spec,
            scenario.seed,
            scenario.sample_interval(spec.attitude_rate, "attitude_rate", table="quadrotor"),
        )
        self.columns, self.spans = _columns(sensors.q, sensors.q_b)
        self.out = np.full((int(capacity) + 1, self.columns.width), np.nan)
        self.events = np.zeros((int(capacity) + 1, 2), dtype=np.int64)
        self._place(scenario)
        self.crashed_at: int | None = None
        self.crash_cause: str | None = None
        #: The latest body IMU sample ``(f~ (3), w~ (3))`` (what an IMU-driven estimator holds).
        self.body_imu = np.zeros(6)
        #: Called as ``log_tap(j, k)`` at the end of each step when set (a log export's
        #: :class:`~quadobs.testbed.logs.export.QuadrotorLogTap`); ``None``: nothing.
        self.log_tap = None
        self._compiled()
        self._radio_setup(scenario)

    def _compiled(self) -> None:
        """Packed operands and views of the compiled step (:mod:`quadobs._kernels.quadrotor`), loaded now rather than in the first step."""
        from quadobs._kernels import quadrotor as kq

        self._kq, c, d, qp, qv = kq, self.ctrl, self.data, self._qp, self._qv
        self._gains = np.array([c.kx, c.kv, c.kR, c.kW, c.p.mass, c.tan_tilt, c.p.thrust_max, 0.0])
        imu = self.imu
        self._imu = np.concatenate(
            [imu.accel_bias, imu.gyro_bias, [imu.accel_std, imu.gyro_std, imu.attitude_std]]
        )
        self._p, self._v = d.qpos[qp : qp + 3], d.qvel[qv : qv + 3]
        self._q, self._w = d.qpos[qp + 3 : qp + 7], d.qvel[qv + 3 : qv + 6]
        self._ranges, self._R, self._Rc = np.zeros(len(self.anchors)), np.eye(3), np.eye(3)
        self._thrusts, self._thrust, self._speeds = np.zeros(4), np.zeros(4), np.zeros(4)
        self._commands, self._lead_state = np.zeros(4), np.zeros(8)
        self._ref, self._acc_i = np.zeros((3, 3)), np.zeros(3)
        self._ki = self.control.integral_bandwidth * self.ctrl.kx
        self._rotor = self.rotor.packed()
        tau_u, tau_d = IDENTIFIED.time_constants(CRAZYFLIE.mass)  # what the controller knows
        lead_on = self.control.rotor_lead
        rate = self.control.rate
        self._lead = (
            tau_u if lead_on else 0.0,
            tau_d if lead_on else 0.0,
            rate,
            1.0 / (1.0 + LEAD_FILTER * rate),
        )
        cols, sp = self.columns, self.spans
        self._o_crashed = sp["crashed"].start
        self._o_thrust = sp["thrust"]
        self._o = (
            sp["reference"].start,
            sp["tracking"].start,
            sp["rotors"].start,
            sp["on_estimate"].start,
            sp["attitude"].start,
            cols.u.start,
        )

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
        body = m.body("quadrotor").id
        m.body_mass[body] *= self.spec.mass_scale
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
        self.plan = FlightPlan(
            scenario.trajectory,
            scenario.duration,
            takeoff=spec.takeoff,
            landing=spec.landing,
            hovers=hovers,
            ramp=spec.hover_ramp,
            floor=self.floor,
        )
        self.attitude_meas = np.array([1.0, 0.0, 0.0, 0.0])
        self.rates_meas = np.zeros(3)

    # -- the World interface --------------------------------------------------------------

    def state(self) -> np.ndarray:
        d = self.data
        return np.concatenate([d.qpos[self._qp : self._qp + 3], d.qvel[self._qv : self._qv + 3]])

    def attitude(self) -> np.ndarray:
        """The true body-to-world quaternion ``(w, x, y, z)`` of the vehicle now (a copy)."""
        return self._q.copy()

    def begin_block(self, k0: int, count: int) -> int:
        count = min(count, self.out.shape[0] - 1)
        self.k0 = k0
        self.refs = self.plan.reference((k0 + np.arange(count)) * self.dt)  # (count, 3, 3)
        self.noise = self.imu.draws(count)
        self.out[:] = np.nan
        self.out[0, self.columns.truth] = self.state()
        return count

    def step(self, j: int, estimate: np.ndarray | None = None) -> None:
        d, row, k, kq, o = self.data, self.out[j], self.k0 + j, self._kq, self._o
        if k % self.control_every == 0:
            self._control(k, self.refs[j], estimate)
        err = kq.pre_step(
            self._p,
            self.anchors,
            self.refs[j, 0],
            self._commands,
            float(self._on_estimate),
            self._ranges,
            row,
            o[0],
            o[1],
            o[2],
            o[3],
        )
        s = self.sensors
        o0, d0 = s.outliers_injected, s.dropped
        row[self.columns.y] = s.outputs(k, self._ranges)
        ev = self.events[j]
        ev[0], ev[1] = s.outliers_injected - o0, s.dropped - d0
        row[self.columns.measured] = s.measured_ranges
        if self.spec.gust_speed:
            self._gust(k * self.dt)
        kq.rotor_step(
            self._commands,
            self.crashed_at is None,
            self._speeds,
            self._rotor,
            self.dt,
            self._thrust,
        )
        d.ctrl[self._rotors] = self._thrust
        row[self._o_thrust] = self._thrust
        if self.radio is not None:
            self._radio_step(k, row)
        _mj_step(self.model, d)
        upside = kq.post_step(
            d.sensordata,
            self._acc,
            self._gyro,
            self._quat,
            self.noise[j],
            self._imu,
            k % self.imu.attitude_every == 0,
            self.attitude_meas,
            self.rates_meas,
            self._R,
            row,
            o[4],
            o[5],
            self._p,
            self._v,
            self.out[j + 1],
        )
        kq.body_imu(
            d.sensordata, self._acc, self.noise[j], self._imu, self.rates_meas, self.body_imu
        )
        if self.log_tap is not None:
            self.log_tap(j, k)
        if self.crashed_at is None and (err > self.control.crash_distance or upside):
            self.crashed_at = k
            self.crash_cause = (
                "turned upside down"
                if upside
                else f"tracking error {err:.2f} m > control.crash_distance {self.control.crash_distance:g} m"
            )
        row[self._o_crashed] = self.crashed_at is not None

    def _control(self, k: int, ref: np.ndarray, estimate) -> None:
        self._on_estimate = (
            self.switch_step is not None and k >= self.switch_step and estimate is not None
        )
        p = estimate[:3] if self._on_estimate else self._p
        ref = self._integral(ref, p)
        if self.crashed_at is not None:
            self._thrusts[:] = 0.0
        elif self._on_estimate:
            self._kq.quat_matrix(self.attitude_meas, self._Rc)
            self._kq.control(
                estimate[:3],
                estimate[3:6],
                self._Rc,
                self.rates_meas,
                ref,
                self._gains,
                self.ctrl.J,
                self.ctrl.mix_inv,
                self._thrusts,
            )
        else:  # a free joint's angular velocity is in the body frame
            self._kq.quat_matrix(self._q, self._Rc)
            self._kq.control(
                self._p,
                self._v,
                self._Rc,
                self._w,
                ref,
                self._gains,
                self.ctrl.J,
                self.ctrl.mix_inv,
                self._thrusts,
            )
        tu, td, rate, alpha = self._lead
        self._kq.lead(self._thrusts, self._lead_state, tu, td, rate, alpha, self._commands)

    def _gust(self, t: float) -> None:
        """The wind of ``[quadrotor] gust_speed`` at ``t`` into MuJoCo's fluid model (``opt.wind``)."""
        w, T = self.spec.gust_speed, self.spec.gust_period
        wind = self.model.opt.wind
        wind[0] = w * math.sin(2.0 * math.pi * t / T)
        wind[1] = w * math.sin(2.0 * math.pi * t / (1.7 * T) + 1.0)

    def _integral(self, ref: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The reference with the integral action ``k_i int (r - p) dt`` added to its acceleration.

        Each axis's term is held within 3 m/s^2 (anti-windup). Returns a buffer reused by the next call.
        """
        out, acc = self._ref, self._acc_i
        out[:] = ref
        if self._ki:
            period = self.control_every * self.dt
            for i in range(3):
                acc[i] = min(max(acc[i] + self._ki * (ref[0, i] - p[i]) * period, -3.0), 3.0)
            out[2] += acc
        return out

    _on_estimate = False

    def sinks(self, recording=None) -> list:
        """The episode's flight summary and recorded series (:class:`~quadobs.testbed.flight.FlightSink`)."""
        from quadobs.testbed.flight import FlightSink

        return [FlightSink(self, recording)]

    def commit(self, rows: int) -> None:
        """The sensor events were counted step by step (:meth:`step`)."""

    # -- the UWB radio's measurement feed (:mod:`quadobs.testbed.worlds.radio_feed`) -----------

    def _radio_step(self, k: int, row: np.ndarray) -> None:
        """The radio's measurements of ``[t_k, t_k+1)``, from the tag's position and velocity at ``t_k``."""
        self._radio_take(k, self._p, self._v)
        row[self.columns.y] = np.nan
        row[self.columns.measured] = np.nan
