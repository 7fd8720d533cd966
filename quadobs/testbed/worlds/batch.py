"""A batch of vehicles stepped together with MuJoCo's rollout, and their raw sensors.

:class:`VehicleBatch` holds ``B`` states of one compiled vehicle model and advances them all
by one physics step per :meth:`VehicleBatch.step`, with ``mujoco.rollout`` (a C loop over
the batch, optionally over a pool of threads). As for :class:`~quadobs.testbed.worlds.VehicleSim`,
after a step the sensors describe its start (ranges, accelerometer, airspeed) and the
states its end; the values agree with ``B`` separate :class:`VehicleSim` to rounding.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import rollout

from quadobs.errors import QuadobsError, as_array
from quadobs.testbed.worlds.model import VehicleModel, load_vehicle_model

__all__ = ["VehicleBatch"]

_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CTRL = mujoco.mjtState.mjSTATE_CTRL


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (``w, x, y, z``)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(q.shape[:-1] + (3, 3))


class VehicleBatch:
    """``B`` vehicles in ``R^dim`` with the same beacons (and wind), stepped together.

    Parameters
    ----------
    dim : int
        2 or 3.
    beacons : array_like (q_b, dim)
    batch : int
        Number of vehicles ``B``.
    timestep : float
    wind : array_like (dim,), optional
    model_path : str, optional
        A user MJCF (see :func:`~quadobs.testbed.worlds.load_vehicle_model`).
    threads : int
        Threads of the rollout pool; 0 (default) steps the batch on the calling thread.
    """

    def __init__(
        self,
        dim: int,
        beacons,
        batch: int,
        *,
        timestep: float = 1e-3,
        wind=None,
        model_path=None,
        threads: int = 0,
    ) -> None:
        if dim not in (2, 3):
            raise QuadobsError(f"dimension: must be 2 or 3, got {dim}")
        if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1:
            raise QuadobsError(f"batch: expected a positive integer, got {batch!r}")
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
            raise QuadobsError(f"threads: expected a non-negative integer, got {threads!r}")
        self.dim, self.batch, self.threads = dim, int(batch), int(threads)
        beacons = as_array("beacons", beacons, (None, dim))
        self.wind = None if wind is None else as_array("wind", wind, (dim,))
        self.vm: VehicleModel = load_vehicle_model(
            beacons, path=model_path, timestep=timestep, wind=self.wind
        )
        m = self.model = self.vm.model
        vm = self.vm
        if m.site_bodyid[vm.site_id] != m.body("vehicle").id:
            raise QuadobsError("model: site 'imu' must be on body 'vehicle' for batched stepping")
        self.dt = float(m.opt.timestep)
        self._site_rot = _quat_to_mat(np.array(m.site_quat[vm.site_id], dtype=float))
        self._wind3 = np.array(m.opt.wind, dtype=float)
        self.nstate = mujoco.mj_stateSize(m, _FULL)
        self._qpos = 1 + vm.qpos_adr  # FULLPHYSICS state: time, qpos, qvel, ...
        self._qvel = 1 + m.nq + vm.qvel_adr
        B = self.batch
        self._pool = rollout.Rollout(nthread=self.threads)
        self._datas = [mujoco.MjData(m) for _ in range(max(self.threads, 1))]
        self._models = [m] * B
        self._chunk = max(1, B // (max(self.threads, 1) * 10))
        # two state buffers, swapped each step: the state now and the one at the start of the last step
        self._states = [np.zeros((B, 1, self.nstate)), np.zeros((B, 1, self.nstate))]
        self._state, self._start = self._states[0][:, 0], self._states[1][:, 0]
        self._sensordata = np.zeros((B, 1, m.nsensordata))
        self._control = np.zeros((B, 1, mujoco.mj_stateSize(m, _CTRL)))
        self._force = np.zeros((B, 3))
        self._off = np.stack([np.arange(a, a + 3) for a in vm.offset_adr])  # (q_b, 3)

    def close(self) -> None:
        """Stop the rollout's thread pool (also done at exit)."""
        self._pool.close()

    def __enter__(self) -> VehicleBatch:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- state ---------------------------------------------------------------------

    def reset(self, positions, velocities) -> None:
        """Place vehicle ``b`` at ``positions[b]`` with ground velocity ``velocities[b]`` (``(B, dim)`` each), level."""
        P = as_array("positions", positions, (self.batch, self.dim))
        V = as_array("velocities", velocities, (self.batch, self.dim))
        d = self._datas[0]
        mujoco.mj_resetData(self.model, d)
        template = np.zeros(self.nstate)
        mujoco.mj_getState(self.model, d, template, _FULL)
        S = np.tile(template, (self.batch, 1))
        qa, va = self._qpos, self._qvel
        S[:, qa : qa + 3] = 0.0
        S[:, qa : qa + self.dim] = P
        S[:, qa + 3 : qa + 7] = (1.0, 0.0, 0.0, 0.0)
        S[:, va : va + 6] = 0.0
        S[:, va : va + self.dim] = V
        self._state[...] = S
        self._start[...] = S
        self._sensordata[...] = np.nan

    def positions(self) -> np.ndarray:
        """True positions now, ``(B, dim)``."""
        return self._state[:, self._qpos : self._qpos + self.dim].copy()

    def velocities(self) -> np.ndarray:
        """True ground velocities now, ``(B, dim)``."""
        return self._state[:, self._qvel : self._qvel + self.dim].copy()

    def states(self) -> np.ndarray:
        """True estimator states now, ``(B, n)``: ``(p, v)``, or ``(p, v - w, w)`` with wind."""
        p, v = self.positions(), self.velocities()
        if self.wind is None:
            return np.concatenate([p, v], axis=1)
        return np.concatenate([p, v - self.wind, np.broadcast_to(self.wind, p.shape)], axis=1)

    # -- stepping ------------------------------------------------------------------

    def controls(self, accelerations) -> np.ndarray:
        """Actuator controls ``(B, nu)`` realising the accelerations ``(B, dim)``: force ``m (a - g)``."""
        f = self._force
        f[:, : self.dim] = accelerations
        f[:, self.dim :] = 0.0
        f -= self.vm.gravity
        ctrl = self._control[:, 0]
        ctrl[:, self.vm.actuator_ids] = self.vm.mass * f
        return ctrl

    def step(self, accelerations) -> None:
        """One physics step of every vehicle with its acceleration ``(B, dim)`` held."""
        self.controls(accelerations)
        nxt = self._states[1] if self._state.base is self._states[0] else self._states[0]
        self._pool.rollout(
            self._models,
            self._datas,
            self._state,
            self._control,
            control_spec=_CTRL.value,
            skip_checks=True,
            nstep=1,
            state=nxt,
            sensordata=self._sensordata,
            chunk_size=self._chunk,
        )
        self._start, self._state = self._state, nxt[:, 0]

    # -- sensors (describing the start of the last step) ---------------------------

    def _site_rotation(self) -> np.ndarray:
        qa = self._qpos
        return (
            _quat_to_mat(self._start[:, qa + 3 : qa + 7]) @ self._site_rot
        )  # orientation at the start of the step

    def ranges(self) -> np.ndarray:
        """``|p - a_h|`` of each vehicle, ``(B, q_b)``."""
        rel = self._sensordata[:, 0][:, self._off]  # (B, q_b, 3)
        return np.sqrt(np.einsum("bhi,bhi->bh", rel, rel))

    def accelerometer(self) -> np.ndarray:
        """World-frame accelerations, ``(B, dim)``."""
        a = self._sensordata[:, 0, self.vm.accel_adr : self.vm.accel_adr + 3]
        return (np.einsum("bij,bj->bi", self._site_rotation(), a) + self.vm.gravity)[:, : self.dim]

    def airspeed(self) -> np.ndarray:
        """``|v - wind|`` of each vehicle, ``(B,)``."""
        v = self._sensordata[:, 0, self.vm.velocimeter_adr : self.vm.velocimeter_adr + 3]
        rel = np.einsum("bij,bj->bi", self._site_rotation(), v) - self._wind3
        return np.sqrt(np.einsum("bi,bi->b", rel, rel))
