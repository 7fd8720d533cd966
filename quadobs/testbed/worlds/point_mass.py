"""MuJoCo ground truth: the vehicle driven by a commanded acceleration, and its raw sensors.

One :meth:`VehicleSim.step` is one ``mj_step``. MuJoCo computes the sensors inside
``mj_step`` *before* integrating, so after the call ``sensordata`` describes the state
at the start of the step: the ranges ``rho_h(t_k)``, the accelerometer reading for the
control held over ``[t_k, t_k + dt)`` and the velocity at ``t_k``, while ``qpos``/``qvel``
hold the state at ``t_{k+1}``. The estimators consume exactly this: the output sampled at
``t_k`` and the input held over the step, and produce an estimate at ``t_{k+1}``.
"""

from __future__ import annotations

import collections
import queue
import threading
import weakref
from typing import Any

import mujoco
import numpy as np

from quadobs.errors import QuadobsError, as_array, deferred_interrupts
from quadobs.testbed.blocks import block_count
from quadobs.testbed.worlds.base import Columns, World
from quadobs.testbed.worlds.model import VehicleModel, load_vehicle_model

__all__ = ["BlockStepper", "PointMassWorld", "VehicleSim"]

_mj_step = mujoco.mj_step
_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CTRL = int(mujoco.mjtState.mjSTATE_CTRL.value)
_SAME_ROTATION = (
    int(mujoco.mjtSameFrame.mjSAMEFRAME_BODY),
    int(mujoco.mjtSameFrame.mjSAMEFRAME_BODYROT),
)


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

    def __init__(
        self, dim: int, beacons, *, timestep: float = 1e-3, wind=None, model_path=None
    ) -> None:
        if dim not in (2, 3):
            raise QuadobsError(f"dimension: must be 2 or 3, got {dim}")
        self.dim = dim
        beacons = as_array("beacons", beacons, (None, dim))
        self.wind = None if wind is None else as_array("wind", wind, (dim,))
        self.vm: VehicleModel = load_vehicle_model(
            beacons, path=model_path, timestep=timestep, wind=self.wind
        )
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

    @classmethod
    def of(cls, scenario) -> VehicleSim:
        """The vehicle of a scenario (its dimension, beacons, step, wind and model), placed at the
        start of its trajectory."""
        sim = cls(
            scenario.dimension,
            scenario.beacons,
            timestep=scenario.dt,
            wind=scenario.wind,
            model_path=scenario.model,
        )
        traj = scenario.trajectory
        sim.reset(traj.position(0.0), traj.velocity_at(0.0))
        return sim

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
            sensor_consts = [
                1.0,
                self.y.start,
                self.u.start,
                self.measured.start,
                *sensors.step_params(),
            ]
            width += q + dim + qb
        self.out = np.zeros((int(capacity) + 1, width))
        #: per step of the block: outliers delivered and samples dropped (see :meth:`commit`)
        self.events = np.zeros((int(capacity) + 1, 2), dtype=np.int64)
        vm = sim.vm
        wind3 = np.zeros(3) if sim.wind is None else sim._wind3
        self._consts = np.concatenate(
            [
                [
                    dim,
                    qb,
                    0.0 if sim.wind is None else 1.0,
                    vm.qpos_adr,
                    vm.qvel_adr,
                    vm.site_id,
                    vm.accel_adr,
                    vm.velocimeter_adr,
                ],
                vm.gravity,
                wind3,
                vm.offset_adr.astype(float),
                sensor_consts,
            ]
        )
        self._ctrls = np.zeros((0, sim.model.nu))
        self._draws = np.zeros((1, 1 if sensors is None else sensors.draw_width))
        self._work = np.zeros(
            (2, 9)
        )  # the site's rotation; the quaternion at the start of the step, and its flag
        self._model, self._data = sim.model, sim.data
        try:
            from quadobs.testbed.worlds._read import read_step
        except ImportError:  # pragma: no cover - Numba missing: the NumPy path
            read_step = None
        self._read = read_step
        # see prefetch, begin_ahead, fill
        self._current: _Ahead | None = None
        self._filled: int | None = None
        self.warnings: np.ndarray | None = None
        # What the next prefetched block continues, from step _next_k: (buffers, last row), (queued block, None)
        # or (None, None), the data's current state.
        self._last: tuple[Any, Any] | None = None
        self._next_k = 0
        self._queued: collections.deque[_Ahead] = (
            collections.deque()
        )  # blocks handed to the physics thread
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
            read_step(
                0,
                self.out[:2].copy(),
                np.zeros((1, sim.model.nu)),
                d.ctrl.copy(),
                d.sensordata.copy(),
                d.site_xmat.copy(),
                d.qpos.copy(),
                d.qvel.copy(),
                scratch,
                self._draws.copy(),
                self._work.copy(),
            )

    def _block_physics(self, capacity: int):
        """Buffers of the one-call block (``mujoco.rollout``), or ``None`` where the model does not allow it.

        The block's rows need the orientation of the site at the start of each step; it is
        recomputed from the state's quaternion, which is exact when the vehicle is a free
        body of the world and the site shares its frame's rotation (the shipped model).
        Three sets of buffers: the block being read and two that :meth:`prefetch` computes ahead.
        """
        from mujoco import rollout

        from quadobs.testbed.worlds._read import read_block

        m, vm = self.sim.model, self.sim.vm
        body = int(m.site_bodyid[vm.site_id])
        jnt = int(m.body_jntadr[body])
        if not (
            m.body_parentid[body] == 0
            and m.body_jntnum[body] == 1
            and m.jnt_type[jnt] == mujoco.mjtJoint.mjJNT_FREE
            and m.jnt_qposadr[jnt] == vm.qpos_adr
            and int(m.site_sameframe[vm.site_id]) in _SAME_ROTATION
        ):
            return None
        self._state0 = np.zeros(mujoco.mj_stateSize(m, _FULL))
        self._bufs = [
            (np.zeros((1, capacity, self._state0.size)), np.zeros((1, capacity, m.nsensordata)))
            for _ in range(3)
        ]
        self._cols = (
            1 + vm.qpos_adr,
            1 + m.nq + vm.qvel_adr,
        )  # qpos, qvel in a state row (after time)
        self._pool = rollout.Rollout(nthread=0)
        self._read_block = read_block  # loaded (or compiled) now: the kernel of the default path
        scratch = self._consts.copy()
        scratch[14 + vm.offset_adr.shape[0]] = 0.0
        states, sensors = self._bufs[0]
        read_block(
            1,
            self.out[:2].copy(),
            states[0, :1],
            sensors[0, :1],
            self._state0,
            *self._cols,
            scratch,
            self._draws.copy(),
            self._work.copy(),
        )
        return self._pool

    def _physics(self, buf, ctrls, state0, warmstart) -> np.ndarray:
        """One block's physics: ``mujoco.rollout`` from ``state0`` under ``ctrls`` into ``buf``.

        Returns MuJoCo's warning counts after it (:func:`warning_counts`). Runs in the
        calling thread or in :meth:`prefetch`'s; the rollout releases the GIL.
        """
        m, d = self._model, self._data
        count = ctrls.shape[0]
        states, sensors = buf
        assert self._rollout is not None, "block physics without mujoco.rollout"
        self._rollout.rollout(
            [m],
            [d],
            state0[None],
            ctrls[None],
            control_spec=_CTRL,
            skip_checks=True,
            nstep=count,
            initial_warmstart=warmstart[None],
            state=states[:, :count],
            sensordata=sensors[:, :count],
            chunk_size=1,
        )
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
                raise QuadobsError(
                    f"fill: the block begun ahead has {ahead.count} steps, not {count}"
                )
            buf, state0, self.warnings = ahead.buf, ahead.state0, ahead.warnings
        else:
            m, d = self._model, self._data
            mujoco.mj_getState(m, d, self._state0, _FULL)
            buf, state0 = self._next_buffer(), self._state0
            self.warnings = self._physics(buf, self._ctrls, state0, d.qacc_warmstart.copy())
        if not self._queued:  # else the next block queued continues the last one queued
            self._last, self._next_k = (buf, count - 1), self._k0 + count
        self._filled = count
        self._read_block(
            count,
            self.out,
            buf[0][0],
            buf[1][0],
            state0,
            *self._cols,
            self._consts,
            self._draws,
            self._work,
        )

    def _next_buffer(self):
        """The next buffer set in turn: blocks take them in order, so the oldest comes back first."""
        buf = self._bufs[self._buf_i]
        self._buf_i = (self._buf_i + 1) % len(self._bufs)
        return buf

    def can_prefetch(self) -> bool:
        """Whether :meth:`prefetch` has a free buffer set and a block to continue from."""
        busy = len(self._queued) + (self._current is not None)
        return self._rollout is not None and self._last is not None and busy < len(self._bufs)

    def prefetch(self, accelerations, k0: int) -> bool:
        """Queue the physics of the next block (steps ``k0, k0 + 1, ...``) on the background thread.

        The block continues the last one queued, else the one begun or just filled: the
        thread starts it from that block's final full physics state, with the data's warm
        start and warning counts as that block left them, so its states are those
        :meth:`begin` and :meth:`fill` would give (bit for bit). Blocks queue while buffer
        sets are free (three: the one being read and two ahead), so the thread runs block
        after block while the reader catches up. :meth:`begin_ahead` then starts each in
        turn. Returns ``False`` (nothing queued) where the block path does not apply or no
        buffer set is free.
        """
        if not self.can_prefetch():
            return False
        ctrls = np.ascontiguousarray(self.sim.controls(accelerations))
        if ctrls.shape[0] + 1 > self.out.shape[0]:
            raise QuadobsError(
                f"accelerations: at most {self.out.shape[0] - 1} steps per block, got {ctrls.shape[0]}"
            )
        ahead = _Ahead(self, int(k0), ctrls, self._last, self._next_buffer())
        with deferred_interrupts():  # a queued block is always known to close()
            _PhysicsWorker.of_this_thread().submit(ahead)
            self._queued.append(ahead)
        self._last, self._next_k = (ahead, None), ahead.k0 + ahead.count
        return True

    def follow_data(self, k0: int) -> bool:
        """Make the next :meth:`prefetch` start from the data's current state, as step ``k0``.

        Blocks queued before are undone first. Returns ``False`` where the block path does
        not apply.
        """
        if self._rollout is None:
            return False
        if self._queued:
            self._drop_ahead()
        self._last, self._next_k = (None, None), int(k0)
        return True

    @property
    def next_k(self) -> int:
        """The step where the next block :meth:`prefetch` queues starts."""
        return self._next_k

    def ahead_of(self, k0: int, count: int) -> bool:
        """Whether the next block queued by :meth:`prefetch` is exactly the block of steps ``[k0, k0 + count)``."""
        a = self._queued[0] if self._queued else None
        return a is not None and a.k0 == k0 and a.count == count

    def begin_ahead(self, k0: int) -> int:
        """Start the next block :meth:`prefetch` queued (waiting for its physics); fill it with :meth:`fill`.

        Row 0 gets the truth at the block's start and the block's noise is drawn, as in
        :meth:`begin`. Returns the number of steps.
        """
        if not self._queued or self._queued[0].k0 != k0:
            raise QuadobsError(f"begin_ahead: no block prefetched at step {k0}")
        ahead = self._queued[0]
        ahead.wait()
        self._queued.popleft()
        self._current = ahead
        s0, nq, nv = ahead.state0, self._model.nq, self._model.nv
        assert s0 is not None, "a block waited for has run or raised"
        qa = self.sim.vm.qpos_adr
        return self._start(
            ahead.ctrls,
            k0,
            self.sim.state_of(s0[1 : 1 + nq], s0[1 + nq : 1 + nq + nv]),
            s0[1 + qa + 3 : 1 + qa + 7],
        )

    def close(self) -> None:
        """Drop the blocks queued in the background.

        Blocks not started are cancelled; the one computing is waited for (one block of
        physics, tens of milliseconds), not cut by a signal, which is delivered after it.
        """
        for ahead in self._queued:
            ahead.cancelled = True
        self._finish_queued()

    def _finish_queued(self) -> _Ahead | None:
        """Wait for every queued block and forget them; returns the first (or ``None``)."""
        first = self._queued[0] if self._queued else None
        for ahead in self._queued:
            ahead.wait(reraise=False)
        self._queued.clear()
        self._current = None
        self._last = None
        return first

    def _drop_ahead(self) -> None:
        """Undo the queued blocks (the next one begun is not theirs): the data back at the first one's start."""
        first = self._finish_queued()
        if (
            first is None or first.state0 is None
        ):  # cancelled before it ran: the data was never moved on
            return
        m, d = self._model, self._data
        mujoco.mj_setState(m, d, first.state0, _FULL)
        d.qacc_warmstart[:] = first.warmstart
        assert first.warnings_before is not None, "set with state0"
        d.warning.number[:], d.warning.lastinfo[:] = first.warnings_before

    def warning_counts(self) -> np.ndarray:
        """MuJoCo's warning counts after the block just filled (while the next one may be computing)."""
        return warning_counts(self._data) if self.warnings is None else self.warnings

    def _start(self, ctrls, k0: int, truth0, quat0) -> int:
        """A block's start: its controls, step, noise, the truth of row 0 and the site's quaternion."""
        count = ctrls.shape[0]
        if count + 1 > self.out.shape[0]:
            raise QuadobsError(
                f"accelerations: at most {self.out.shape[0] - 1} steps per block, got {count}"
            )
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
        if self._queued:
            self._drop_ahead()
        self._last = None
        sim, d = self.sim, self._data
        qa = sim.vm.qpos_adr
        count = self._start(
            np.ascontiguousarray(sim.controls(accelerations)),
            k0,
            sim.state(),
            d.qpos[qa + 3 : qa + 7],
        )
        d.ctrl[:] = self._ctrls[0]
        self.warnings = self._current = None
        self._args = (
            self.out,
            self._ctrls,
            d.ctrl,
            d.sensordata,
            d.site_xmat,
            d.qpos,
            d.qvel,
            self._consts,
            self._draws,
            self._work,
        )
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
            row[self.y] = s.outputs(
                self._k0 + j,
                row[self.ranges],
                row[self.airspeed][0] if sim.wind is not None else None,
            )
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
    """The physics of one block, computed by the stepper's :class:`_PhysicsWorker` (:meth:`BlockStepper.prefetch`).

    ``after`` is where the block starts: ``(buffers, row)``, a row of a block whose physics
    is done, ``(block, None)``, the end of the block queued before it, or ``(None, None)``,
    the state of the data (the first block). The start state,
    the warm start and the warning counts are read when the block runs, after the one
    before it, on the thread that runs both.
    """

    def __init__(self, stepper: BlockStepper, k0: int, ctrls, after, buf) -> None:
        self.k0, self.count, self.ctrls, self.after, self.buf = (
            k0,
            ctrls.shape[0],
            ctrls,
            after,
            buf,
        )
        self.state0: np.ndarray | None = None
        self.warmstart: np.ndarray | None = None
        self.warnings_before: np.ndarray | None = None
        self.warnings: np.ndarray | None = None
        self.error: BaseException | None = None
        self.cancelled = False
        self.stepper: BlockStepper | None = stepper
        self.done = threading.Event()

    def run(self) -> None:
        """In the worker: the block's rollout; an error is kept for the thread that waits."""
        stepper, self.stepper = self.stepper, None
        assert stepper is not None, "a block runs once"
        try:
            src, row = self.after
            if isinstance(src, _Ahead):
                if (
                    src.error is not None or src.state0 is None
                ):  # the block before failed or never ran
                    self.error = src.error
                    return
                src, row = src.buf, src.count - 1
            if self.cancelled:
                return
            m, d = stepper._model, stepper._data
            if src is None:  # the first block: from the data as it stands
                self.state0 = np.empty(mujoco.mj_stateSize(m, _FULL))
                mujoco.mj_getState(m, d, self.state0, _FULL)
            else:
                self.state0 = src[0][
                    0, row
                ].copy()  # the full physics state where this block starts
            self.warmstart, self.warnings_before = d.qacc_warmstart.copy(), warning_counts(d)
            self.warnings = stepper._physics(self.buf, self.ctrls, self.state0, self.warmstart)
        except BaseException as exc:
            self.error = exc
        finally:
            self.after = None
            self.done.set()

    def wait(self, *, reraise: bool = True) -> None:
        """Wait for the block (at most a few blocks of physics; a signal is delivered after it) and re-raise its error."""
        with deferred_interrupts():
            self.done.wait()
        if reraise and self.error is not None:
            raise self.error


class _PhysicsWorker:
    """A thread that computes the blocks handed to it, one after the other.

    One per thread that reads blocks (:meth:`of_this_thread`), kept for the life of that
    thread and shared by its episodes, rather than one per block or per episode: the
    scheduler keeps a long-lived thread on the core it settled on, whereas a new thread
    starts on the core of the thread that creates it and shares it with the reader until
    it is moved (measured: a block's physics then took up to twice as long, and runs
    varied accordingly). A daemon, so that it never holds the interpreter at exit; a
    finaliser (run when the reading thread ends, or at exit before the interpreter is torn
    down) lets the blocks handed to it end first, so that a model is never freed under a
    running rollout.
    """

    _local = threading.local()

    def __init__(self) -> None:
        self.jobs: queue.SimpleQueue = queue.SimpleQueue()
        self.ended = threading.Event()
        self.thread = threading.Thread(
            target=self._serve, args=(self.jobs, self.ended), name="quadobs-physics", daemon=True
        )
        self.thread.start()
        weakref.finalize(self, _end_worker, self.jobs, self.ended, self.thread)

    @classmethod
    def of_this_thread(cls) -> _PhysicsWorker:
        """The calling thread's worker, started on first use (again in a forked child)."""
        worker = getattr(cls._local, "worker", None)
        if worker is None or not worker.thread.is_alive():
            cls._local.worker = worker = cls()
        return worker

    @staticmethod
    def _serve(jobs: queue.SimpleQueue, ended: threading.Event) -> None:
        try:
            while (job := jobs.get()) is not None:
                job.run()
        finally:
            ended.set()

    def submit(self, job: _Ahead) -> None:
        self.jobs.put(job)


def _end_worker(jobs: queue.SimpleQueue, ended: threading.Event, thread: threading.Thread) -> None:
    """End a worker's thread once the blocks handed to it are done.

    Runs as its reading thread ends (or at exit), where ``threading.current_thread()`` (and
    so ``Thread.join``) would register a placeholder thread for good: the thread's end is
    an event, and identities are compared. Nothing to wait for in a forked child, where
    the thread does not exist.
    """
    me = threading.get_ident()
    if ended.is_set() or not thread.is_alive() or thread.ident == me:
        return
    jobs.put(None)
    if me == threading.main_thread().ident:
        with deferred_interrupts():  # at exit: a signal waits for the block in flight
            ended.wait()
    else:
        ended.wait()


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
        sim = VehicleSim.of(scenario)
        self.sim, self.dt, self._traj = sim, scenario.dt, traj
        self.scenario = scenario
        self.stepper = st = BlockStepper(sim, capacity, sensors)
        self.out, self.events = st.out, st.events
        self.columns = Columns(
            truth=st.truth,
            y=st.y,
            u=st.u,
            measured=st.measured,
            width=st.out.shape[1],
            extra={"ranges": st.ranges, "accel": st.accel, "airspeed": st.airspeed},
        )
        self.pipelined = bool(pipelined)
        self._steps, self._capacity, self._k0 = int(scenario.steps), int(capacity), 0
        self._queue = False  # queue blocks ahead: once the block path is in use (prepare, fill)

    def state(self) -> np.ndarray:
        return self.sim.state()

    def _accelerations(self, k0: int, count: int) -> np.ndarray:
        dt = self.dt
        return self._traj.step_accelerations(0.0, dt, count, start=k0)

    def begin_block(self, k0: int, count: int) -> int:
        self._k0 = k0
        st = self.stepper
        if self._queue and not st.ahead_of(
            k0, count
        ):  # the first block: its physics on the thread too
            st.follow_data(k0)
        self._queue_ahead()
        if st.ahead_of(k0, count):  # its physics queued in the background: wait for it
            return st.begin_ahead(k0)
        return st.begin(self._accelerations(k0, count), k0)

    def _queue_ahead(self) -> None:
        """Queue the physics of the blocks that follow, while the stepper has buffers for them."""
        st = self.stepper
        while self._queue and st.can_prefetch() and st.next_k < self._steps:
            k = st.next_k
            st.prefetch(self._accelerations(k, block_count(k, self._steps, self._capacity)), k)

    def step(self, j: int, estimate: np.ndarray | None = None) -> None:
        self.stepper.step(j)

    def fill(self, count: int) -> None:
        """The block's rows; then, pipelined, the physics of the blocks that follow is queued in the background."""
        self.stepper.fill(count)
        self._queue = self.pipelined
        self._queue_ahead()

    def commit(self, rows: int) -> None:
        self.stepper.commit(rows)

    def physics_warnings(self) -> np.ndarray:
        return self.stepper.warning_counts()

    @property
    def computes_ahead(self) -> bool:
        return self._queue and self.stepper._rollout is not None

    def prepare(self, path: str) -> None:
        self._queue = self.pipelined and path == "block"
        if path == "step":
            self.stepper.prepare_steps()

    def close(self) -> None:
        self.stepper.close()
