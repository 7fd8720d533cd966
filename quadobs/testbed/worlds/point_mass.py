"""MuJoCo ground truth: the vehicle driven by a commanded acceleration, and its raw sensors.

One :meth:`VehicleSim.step` is one ``mj_step``. MuJoCo computes the sensors inside
``mj_step`` *before* integrating, so after the call ``sensordata`` describes the state
at the start of the step: the ranges ``rho_h(t_k)``, the accelerometer reading for the
control held over ``[t_k, t_k + dt)`` and the velocity at ``t_k``, while ``qpos``/``qvel``
hold the state at ``t_{k+1}``. The estimators consume exactly this: the output sampled at
``t_k`` and the input held over the step, and produce an estimate at ``t_{k+1}``.
"""

from __future__ import annotations

import threading

import mujoco
import numpy as np

from quadobs.errors import QuadobsError, as_array, deferred_interrupts
from quadobs.testbed.blocks import block_count
from quadobs.testbed.worlds.base import Columns, World
from quadobs.testbed.worlds.model import VehicleModel, load_vehicle_model

__all__ = ["VehicleSim", "BlockStepper", "PointMassWorld"]

_mj_step = mujoco.mj_step
_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CTRL = int(mujoco.mjtState.mjSTATE_CTRL.value)
_SAME_ROTATION = (int(mujoco.mjtSameFrame.mjSAMEFRAME_BODY), int(mujoco.mjtSameFrame.mjSAMEFRAME_BODYROT))


class VehicleSim:
    """The vehicle in ``R^dim`` (``dim`` = 2 or 3) with beacons, and optionally a wind.

    Parameters
    ----------
    dim : int
        2 (motion in the plane ``z = 0``) or 3.
    beacons : array_like (q_b, dim)
    timestep : float
    wind : array_like (dim,), optional
    model_path : str, optional
        A user MJCF with the names listed in :data:`~quadobs.testbed.worlds.model.REQUIRED_ELEMENTS`.
    """

    def __init__(self, dim: int, beacons, *, timestep: float = 1e-3, wind=None, model_path=None) -> None:
        if dim not in (2, 3):
            raise QuadobsError(f"dimension: must be 2 or 3, got {dim}")
        self.dim = dim
        beacons = as_array("beacons", beacons, (None, dim))
        self.wind = None if wind is None else as_array("wind", wind, (dim,))
        self.vm: VehicleModel = load_vehicle_model(beacons, path=model_path, timestep=timestep, wind=self.wind)
        self.model = self.vm.model
        self.data = mujoco.MjData(self.model)
        self.dt = float(self.model.opt.timestep)
        self._wind3 = np.array(self.model.opt.wind, dtype=float)
        self._force = np.zeros(3)
        vm = self.vm
        self._qp = slice(vm.qpos_adr, vm.qpos_adr + 3)
        self._qv = slice(vm.qvel_adr, vm.qvel_adr + 3)
        self._acc = slice(vm.accel_adr, vm.accel_adr + 3)
        self._vel = slice(vm.velocimeter_adr, vm.velocimeter_adr + 3)
        self._off = np.stack([np.arange(a, a + 3) for a in vm.offset_adr])  # (q_b, 3)

    # -- state ---------------------------------------------------------------------

    def reset(self, position, velocity) -> None:
        """Place the vehicle at ``position`` with ground velocity ``velocity`` (both ``(dim,)``), level and not rotating."""
        p = as_array("position", position, (self.dim,))
        v = as_array("velocity", velocity, (self.dim,))
        mujoco.mj_resetData(self.model, self.data)
        qa = self.vm.qpos_adr
        self.data.qpos[qa : qa + 3] = 0.0
        self.data.qpos[qa : qa + self.dim] = p
        self.data.qpos[qa + 3 : qa + 7] = (1.0, 0.0, 0.0, 0.0)
        self.data.qvel[self._qv] = 0.0
        self.data.qvel[self.vm.qvel_adr : self.vm.qvel_adr + self.dim] = v
        mujoco.mj_forward(self.model, self.data)

    @property
    def time(self) -> float:
        return float(self.data.time)

    def position(self) -> np.ndarray:
        """True position now (MuJoCo's ``qpos``), ``(dim,)``."""
        return self.data.qpos[self._qp][: self.dim].copy()

    def velocity(self) -> np.ndarray:
        """True ground velocity now (MuJoCo's ``qvel``), ``(dim,)``."""
        return self.data.qvel[self._qv][: self.dim].copy()

    def state(self) -> np.ndarray:
        """True estimator state now: ``(p, v)``, or ``(p, v_a, v_w)`` with wind (``v_a = v - v_w``)."""
        return self.state_of(self.data.qpos, self.data.qvel)

    def state_of(self, qpos, qvel) -> np.ndarray:
        """The estimator state of ``qpos``, ``qvel`` (the model's full vectors), as :meth:`state`."""
        p = qpos[self._qp][: self.dim].copy()
        v = qvel[self._qv][: self.dim].copy()
        if self.wind is None:
            return np.concatenate([p, v])
        return np.concatenate([p, v - self.wind, self.wind])

    # -- stepping ------------------------------------------------------------------

    def controls(self, accelerations) -> np.ndarray:
        """Actuator controls ``(T, nu)`` realising the accelerations ``(T, dim)``: force ``m (a - g)`` per step."""
        acc = np.asarray(accelerations, dtype=float).reshape(-1, self.dim)
        f = np.zeros((acc.shape[0], 3))
        f[:, : self.dim] = acc
        f -= self.vm.gravity
        out = np.array(np.broadcast_to(self.data.ctrl, (acc.shape[0], self.model.nu)))
        out[:, self.vm.actuator_ids] = self.vm.mass * f
        return out

    def step(self, acceleration) -> None:
        """One physics step with the force ``m (a - g)`` held: the vehicle accelerates by ``a``."""
        f = self._force
        f[:] = 0.0
        f[: self.dim] = acceleration
        f -= self.vm.gravity
        self.data.ctrl[self.vm.actuator_ids] = self.vm.mass * f
        mujoco.mj_step(self.model, self.data)

    # -- sensors (describing the start of the last step) ---------------------------

    def ranges(self) -> np.ndarray:
        """``|p - a_h|`` from the beacon-relative position sensors, ``(q_b,)``."""
        rel = self.data.sensordata[self._off]
        return np.sqrt(np.einsum("hi,hi->h", rel, rel))

    def accelerometer(self) -> np.ndarray:
        """World-frame acceleration from the accelerometer (which reads ``R^T (a - g)``), ``(dim,)``."""
        R = self.data.site_xmat[self.vm.site_id].reshape(3, 3)
        return (R @ self.data.sensordata[self._acc] + self.vm.gravity)[: self.dim]

    def airspeed(self) -> float:
        """``|v - wind|`` from the velocimeter and MuJoCo's ``opt.wind``."""
        R = self.data.site_xmat[self.vm.site_id].reshape(3, 3)
        return float(np.linalg.norm(R @ self.data.sensordata[self._vel] - self._wind3))


class BlockStepper:
    """Steps a :class:`VehicleSim` through a block of commanded accelerations, one step per call.

    Each :meth:`step` is one ``mj_step`` followed by one compiled read (see
    :mod:`quadobs.testbed.worlds._read`; NumPy when Numba is missing) that writes the sensors at
    the start of step ``j`` into row ``j`` of :attr:`out` and the true state at its end
    into row ``j + 1``, and loads the control of step ``j + 1``. Given a sensor model, the
    same call applies it: the row also gets the outputs ``y``, the measured input ``u`` and
    the measured ranges, the values :meth:`SensorModel.outputs` and
    :meth:`SensorModel.input` would give for that step.

    Columns of :attr:`out` (slices): :attr:`truth` ``(n)``, :attr:`ranges` ``(q_b)``,
    :attr:`accel` ``(dim)``, :attr:`airspeed` ``(1)``, and with a sensor model :attr:`y`
    ``(q)``, :attr:`u` ``(dim)``, :attr:`measured` ``(q_b)``.

    Parameters
    ----------
    sim : VehicleSim
    capacity : int
        Most steps per block.
    sensors : SensorModel, optional
        The sensor layer to apply in the same call (its noise is drawn a block at a time,
        from the same streams in the same order as step-by-step calls).
    """

    def __init__(self, sim: VehicleSim, capacity: int, sensors=None) -> None:
        self.sim = sim
        self.sensors = sensors
        dim, qb = sim.dim, sim.vm.offset_adr.shape[0]
        n = dim * (3 if sim.wind is not None else 2)
        self.truth = slice(0, n)
        self.ranges = slice(n, n + qb)
        self.accel = slice(n + qb, n + qb + dim)
        self.airspeed = slice(n + qb + dim, n + qb + dim + 1)
        width = n + qb + dim + 1
        sensor_consts = [0.0, 0.0, 0.0, 0.0]
        if sensors is not None:
            q = sensors.q
            self.y = slice(width, width + q)
            self.u = slice(width + q, width + q + dim)
            self.measured = slice(width + q + dim, width + q + dim + qb)
            sensor_consts = [1.0, self.y.start, self.u.start, self.measured.start, *sensors.step_params()]
            width += q + dim + qb
        self.out = np.zeros((int(capacity) + 1, width))
        #: per step of the block: outliers delivered and samples dropped (see :meth:`commit`)
        self.events = np.zeros((int(capacity) + 1, 2), dtype=np.int64)
        vm = sim.vm
        wind3 = np.zeros(3) if sim.wind is None else sim._wind3
        self._consts = np.concatenate(
            [
                [dim, qb, 0.0 if sim.wind is None else 1.0, vm.qpos_adr, vm.qvel_adr, vm.site_id, vm.accel_adr, vm.velocimeter_adr],
                vm.gravity,
                wind3,
                vm.offset_adr.astype(float),
                sensor_consts,
            ]
        )
        self._ctrls = np.zeros((0, sim.model.nu))
        self._draws = np.zeros((1, 1 if sensors is None else sensors.draw_width))
        self._work = np.zeros((2, 9))  # the site's rotation; the quaternion at the start of the step, and its flag
        self._model, self._data = sim.model, sim.data
        try:
            from quadobs.testbed.worlds._read import read_step
        except ImportError:  # pragma: no cover - Numba missing: the NumPy path
            read_step = None
        self._read = read_step
        self._ahead = self._current = self._filled = self.warnings = None  # see prefetch, begin_ahead, fill
        self._buf_i = 0
        self._rollout = self._block_physics(int(capacity)) if read_step is not None else None
        self._work[1, 4] = 0.0 if self._rollout is None else 1.0
        if self._rollout is None:
            self.prepare_steps()

    def prepare_steps(self) -> None:
        """Load (or compile) the kernel of :meth:`step` now, on scratch copies, rather than in the first step."""
        read_step, sim, qb = self._read, self.sim, self.sim.vm.offset_adr.shape[0]
        if read_step is not None:
            d = sim.data
            scratch = self._consts.copy()
            scratch[14 + qb] = 0.0  # no sensor layer on the scratch row
            read_step(0, self.out[:2].copy(), np.zeros((1, sim.model.nu)), d.ctrl.copy(), d.sensordata.copy(),
                      d.site_xmat.copy(), d.qpos.copy(), d.qvel.copy(), scratch, self._draws.copy(), self._work.copy())

    def _block_physics(self, capacity: int):
        """Buffers of the one-call block (``mujoco.rollout``), or ``None`` where the model does not allow it.

        The block's rows need the orientation of the site at the start of each step; it is
        recomputed from the state's quaternion, which is exact when the vehicle is a free
        body of the world and the site shares its frame's rotation (the shipped model).
        Two sets of buffers: the block being read and the one :meth:`prefetch` computes.
        """
        from mujoco import rollout

        from quadobs.testbed.worlds._read import read_block

        m, vm = self.sim.model, self.sim.vm
        body = int(m.site_bodyid[vm.site_id])
        jnt = int(m.body_jntadr[body])
        if not (m.body_parentid[body] == 0 and m.body_jntnum[body] == 1 and m.jnt_type[jnt] == mujoco.mjtJoint.mjJNT_FREE
                and m.jnt_qposadr[jnt] == vm.qpos_adr and int(m.site_sameframe[vm.site_id]) in _SAME_ROTATION):
            return None
        self._state0 = np.zeros(mujoco.mj_stateSize(m, _FULL))
        self._bufs = [(np.zeros((1, capacity, self._state0.size)), np.zeros((1, capacity, m.nsensordata))) for _ in range(2)]
        self._cols = (1 + vm.qpos_adr, 1 + m.nq + vm.qvel_adr)  # qpos, qvel in a state row (after time)
        self._pool = rollout.Rollout(nthread=0)
        self._read_block = read_block  # loaded (or compiled) now: the kernel of the default path
        scratch = self._consts.copy()
        scratch[14 + vm.offset_adr.shape[0]] = 0.0
        states, sensors = self._bufs[0]
        read_block(1, self.out[:2].copy(), states[0, :1], sensors[0, :1], self._state0, *self._cols, scratch,
                   self._draws.copy(), self._work.copy())
        return self._pool

    def _physics(self, buf, ctrls, state0, warmstart) -> np.ndarray:
        """One block's physics: ``mujoco.rollout`` from ``state0`` under ``ctrls`` into ``buf``.

        Returns MuJoCo's warning counts after it (:func:`warning_counts`). Runs in the
        calling thread or in :meth:`prefetch`'s; the rollout releases the GIL.
        """
        m, d = self._model, self._data
        count = ctrls.shape[0]
        states, sensors = buf
        self._rollout.rollout([m], [d], state0[None], ctrls[None], control_spec=_CTRL, skip_checks=True, nstep=count,
                              initial_warmstart=warmstart[None], state=states[:, :count], sensordata=sensors[:, :count],
                              chunk_size=1)
        return warning_counts(d)

    def fill(self, count: int) -> None:
        """Every step of the block begun by :meth:`begin`: rows ``0 .. count`` as ``count`` calls of :meth:`step` write them.

        One ``mujoco.rollout`` call for the physics (the same ``mj_step`` on the same data, so
        the same states and sensor values) and one compiled call (:func:`~quadobs.testbed.worlds._read.read_block`)
        for the readings and the sensor layer; the steps one at a time where the model does
        not allow it. A block begun by :meth:`begin_ahead` has its physics done already.
        """
        if self._rollout is None or count == 0:
            for j in range(count):
                self.step(j)
            return
        ahead, self._current = self._current, None
        if ahead is not None:
            if ahead.count != count:
                raise QuadobsError(f"fill: the block begun ahead has {ahead.count} steps, not {count}")
            buf, state0, self.warnings = ahead.buf, ahead.state0, ahead.warnings
        else:
            m, d = self._model, self._data
            mujoco.mj_getState(m, d, self._state0, _FULL)
            buf, state0 = self._bufs[1 - self._buf_i], self._state0
            self.warnings = self._physics(buf, self._ctrls, state0, d.qacc_warmstart.copy())
        self._buf_i = 0 if buf is self._bufs[0] else 1
        self._filled = count
        self._read_block(count, self.out, buf[0][0], buf[1][0], state0, *self._cols, self._consts, self._draws, self._work)

    def prefetch(self, accelerations, k0: int) -> bool:
        """Start the physics of the next block (steps ``k0, k0 + 1, ...``) in a background thread.

        Called after :meth:`fill`: the block starts where the one just filled ends, with
        the same warm start, so its states are those :meth:`begin` and :meth:`fill` would
        give (bit for bit). :meth:`begin_ahead` then starts it, while the block just filled
        is read by its consumers. Returns ``False`` (nothing started) where the block path
        does not apply.
        """
        if self._rollout is None or self._filled is None or self._ahead is not None:
            return False
        ctrls = np.ascontiguousarray(self.sim.controls(accelerations))
        if ctrls.shape[0] + 1 > self.out.shape[0]:
            raise QuadobsError(f"accelerations: at most {self.out.shape[0] - 1} steps per block, got {ctrls.shape[0]}")
        states = self._bufs[self._buf_i][0]
        state0 = states[0, self._filled - 1].copy()  # the full physics state at the end of the block just filled
        buf = self._bufs[1 - self._buf_i]
        with deferred_interrupts():  # a started thread is always known to close()
            self._ahead = _Ahead(self, int(k0), ctrls, state0, self._data.qacc_warmstart.copy(), buf)
        return True

    def ahead_of(self, k0: int, count: int) -> bool:
        """Whether :meth:`prefetch` started exactly the block of steps ``[k0, k0 + count)``."""
        a = self._ahead
        return a is not None and a.k0 == k0 and a.count == count

    def begin_ahead(self, k0: int) -> int:
        """Start the block :meth:`prefetch` computed (waiting for its thread); fill it with :meth:`fill`.

        Row 0 gets the truth at the block's start and the block's noise is drawn, as in
        :meth:`begin`. Returns the number of steps.
        """
        ahead = self._ahead
        if ahead is None or ahead.k0 != k0:
            raise QuadobsError(f"begin_ahead: no block prefetched at step {k0}")
        ahead.wait()
        self._ahead = None
        s0, nq, nv = ahead.state0, self._model.nq, self._model.nv
        qa = self.sim.vm.qpos_adr
        count = self._start(ahead.ctrls, k0, self.sim.state_of(s0[1 : 1 + nq], s0[1 + nq : 1 + nq + nv]), s0[1 + qa + 3 : 1 + qa + 7])
        self._current = ahead
        return count

    def close(self) -> None:
        """Wait for a block computing in the background, if any (its result is dropped).

        The wait (one block of physics, tens of milliseconds) is not cut by a signal, which
        is delivered after it.
        """
        ahead = self._ahead
        if ahead is not None:
            with deferred_interrupts():
                ahead.thread.join()
            self._ahead = None

    def _drop_ahead(self) -> None:
        """Undo a prefetched block that is not the next one begun: the data back at its start."""
        ahead = self._ahead
        self.close()
        m, d = self._model, self._data
        mujoco.mj_setState(m, d, ahead.state0, _FULL)
        d.qacc_warmstart[:] = ahead.warmstart
        d.warning.number[:], d.warning.lastinfo[:] = ahead.warnings_before

    def warning_counts(self) -> np.ndarray:
        """MuJoCo's warning counts after the block just filled (while the next one may be computing)."""
        return warning_counts(self._data) if self.warnings is None else self.warnings

    def _start(self, ctrls, k0: int, truth0, quat0) -> int:
        """A block's start: its controls, step, noise, the truth of row 0 and the site's quaternion."""
        count = ctrls.shape[0]
        if count + 1 > self.out.shape[0]:
            raise QuadobsError(f"accelerations: at most {self.out.shape[0] - 1} steps per block, got {count}")
        self._ctrls = ctrls
        self._k0 = int(k0)
        if self.sensors is not None and self._read is not None:
            self._draws = self.sensors.draws(self._k0, count)
        self.out[0, self.truth] = truth0
        self._work[1, :4] = quat0
        self._filled = None
        return count

    def begin(self, accelerations, k0: int = 0) -> int:
        """Start a block of steps ``k0, k0 + 1, ...`` with these commanded accelerations ``(T, dim)``.

        Row 0 of :attr:`out` gets the current truth; with a sensor model, the block's noise
        is drawn now. A block prefetched but not begun is undone first.
        """
        if self._ahead is not None:
            self._drop_ahead()
        sim, d = self.sim, self._data
        qa = sim.vm.qpos_adr
        count = self._start(np.ascontiguousarray(sim.controls(accelerations)), k0, sim.state(), d.qpos[qa + 3 : qa + 7])
        d.ctrl[:] = self._ctrls[0]
        self.warnings = self._current = None
        self._args = (self.out, self._ctrls, d.ctrl, d.sensordata, d.site_xmat, d.qpos, d.qvel, self._consts, self._draws, self._work)
        return count

    def commit(self, rows: int) -> None:
        """Count the dropouts and outliers of the first ``rows`` steps of the block in the sensor model.

        Their per-step counts ``[outliers, dropped]`` are then in :attr:`events` rows ``[0, rows)``.
        """
        if self.sensors is not None and self._read is not None:
            self.events[:rows] = self.sensors.commit(self._draws[:rows])

    def step(self, j: int) -> None:
        """Step ``j`` of the block: ``mj_step``, then read row ``j`` (sensors) and ``j + 1`` (truth)."""
        _mj_step(self._model, self._data)
        if self._read is not None:
            self._read(j, *self._args)
            return
        sim = self.sim
        d = self._data
        row = self.out[j]
        row[self.ranges] = sim.ranges()
        row[self.accel] = sim.accelerometer()
        row[self.airspeed] = sim.airspeed()
        self.out[j + 1, self.truth] = sim.state()
        if self.sensors is not None:
            s = self.sensors
            before = (s.outliers_injected, s.dropped)
            row[self.y] = s.outputs(self._k0 + j, row[self.ranges], row[self.airspeed][0] if sim.wind is not None else None)
            self.events[j] = (s.outliers_injected - before[0], s.dropped - before[1])
            row[self.measured] = s.measured_ranges
            row[self.u] = s.input(row[self.accel])
        if j + 1 < self._ctrls.shape[0]:
            d.ctrl[:] = self._ctrls[j + 1]


def warning_counts(data) -> np.ndarray:
    """MuJoCo's warnings of ``data``, ``(2, mjNWARNING)``: the counts and the last info (``mjtWarning`` order)."""
    w = data.warning
    return np.stack([w.number, w.lastinfo]).astype(np.int64)


class _Ahead:
    """The physics of a block computed in a background thread (:meth:`BlockStepper.prefetch`)."""

    def __init__(self, stepper: BlockStepper, k0: int, ctrls, state0, warmstart, buf) -> None:
        self.k0, self.count, self.ctrls, self.state0, self.warmstart, self.buf = k0, ctrls.shape[0], ctrls, state0, warmstart, buf
        self.warnings_before = warning_counts(stepper._data)
        self.warnings = self.error = None
        # not a daemon: the interpreter waits for it at exit rather than free the data under it
        self.thread = threading.Thread(target=self._run, args=(stepper,), name="quadobs-physics", daemon=False)
        self.thread.start()

    def _run(self, stepper: BlockStepper) -> None:
        try:
            self.warnings = stepper._physics(self.buf, self.ctrls, self.state0, self.warmstart)
        except BaseException as exc:  # noqa: BLE001 - handed to the thread that waits
            self.error = exc

    def wait(self) -> None:
        """Join the thread (at most one block of physics; a signal is delivered after it) and re-raise its error."""
        with deferred_interrupts():  # a join cut by an exception can leave the thread marked as stopped
            self.thread.join()
        if self.error is not None:
            raise self.error


class PointMassWorld(World):
    """The first world: the MuJoCo point-mass vehicle (:class:`VehicleSim`) on the scenario's trajectory.

    Open loop: the commanded accelerations of a block come from the reference trajectory,
    and each step is one ``mj_step`` plus one compiled read that also applies the sensor
    layer (:class:`BlockStepper`), so :attr:`out` holds the truth, the raw readings and
    ``y``, ``u`` of every step.

    Parameters
    ----------
    scenario : Scenario
        A ``vehicle`` scenario: dimension, beacons, wind, model, trajectory, ``dt``.
    sensors : SensorModel
        The sensor layer (noise, rates, dropouts, outliers).
    capacity : int
        Most steps per block.
    """

    def __init__(self, scenario, sensors, capacity: int, pipelined: bool = True) -> None:
        traj = scenario.trajectory
        sim = VehicleSim(scenario.dimension, scenario.beacons, timestep=scenario.dt, wind=scenario.wind, model_path=scenario.model)
        sim.reset(traj.position(0.0), traj.velocity_at(0.0))
        self.sim, self.dt, self._traj = sim, scenario.dt, traj
        self.stepper = st = BlockStepper(sim, capacity, sensors)
        self.out, self.events = st.out, st.events
        self.columns = Columns(
            truth=st.truth, y=st.y, u=st.u, measured=st.measured, width=st.out.shape[1],
            extra={"ranges": st.ranges, "accel": st.accel, "airspeed": st.airspeed},
        )
        self.pipelined = bool(pipelined)
        self._steps, self._capacity, self._k0 = int(scenario.steps), int(capacity), 0

    def state(self) -> np.ndarray:
        return self.sim.state()

    def _accelerations(self, k0: int, count: int) -> np.ndarray:
        dt = self.dt
        return self._traj.step_accelerations(0.0, dt, count, start=k0)

    def begin_block(self, k0: int, count: int) -> int:
        self._k0 = k0
        if self.stepper.ahead_of(k0, count):
            return self.stepper.begin_ahead(k0)
        return self.stepper.begin(self._accelerations(k0, count), k0)

    def step(self, j: int, estimate: np.ndarray | None = None) -> None:
        self.stepper.step(j)

    def fill(self, count: int) -> None:
        """The block's rows; then, pipelined, the next block's physics starts in the background."""
        self.stepper.fill(count)
        k1 = self._k0 + count
        if self.pipelined and k1 < self._steps:
            self.stepper.prefetch(self._accelerations(k1, block_count(k1, self._steps, self._capacity)), k1)

    def commit(self, rows: int) -> None:
        self.stepper.commit(rows)

    def physics_warnings(self) -> np.ndarray:
        return self.stepper.warning_counts()

    def prepare(self, path: str) -> None:
        if path == "step":
            self.stepper.prepare_steps()

    def close(self) -> None:
        self.stepper.close()
