"""Compiled reading of one physics step (Numba): truth, raw sensors and the next control, in one call.

After ``mj_step`` the sensors describe the start of the step and ``qpos``/``qvel`` its end
(:mod:`quadobs.testbed.worlds.point_mass`). :func:`read_step` writes, into row ``j`` of a block
array, the same quantities as :meth:`VehicleSim.ranges`, :meth:`VehicleSim.accelerometer`,
:meth:`VehicleSim.airspeed` and, into row ``j + 1``, :meth:`VehicleSim.state`, and loads
the control of the next step into ``ctrl``: one call from Python instead of a dozen small
NumPy operations.

With a sensor model, the same call also applies the sensor layer to the step's readings
(:func:`quadobs._kernels.observer.sensor_step`, with the step's row of pre-drawn noise ``draws[j]``)
and writes the outputs ``y``, the measured input ``u`` and the measured ranges into the row.

``consts`` (float64): ``[dim, q_b, wind?, qpos_adr, qvel_adr, site_id, accel_adr,
velocimeter_adr, gravity (3), wind (3), offset_adr (q_b), sensors?, o_y, o_u, o_meas,
sensor parameters...]``. Row layout: ``truth (n)``, ``ranges (q_b)``, ``accel (dim)``,
``airspeed (1)``, then, with sensors, ``y (q)``, ``u (dim)``, ``measured ranges (q_b)``.

:func:`read_block` does the same for a whole block whose physics came from one
``mujoco.rollout`` call (states and sensor data of every step): the site's orientation at
the start of each step is computed from the state's quaternion as MuJoCo's forward pass
computes it (``mju_normalize4`` then ``mju_quat2Mat``), and :func:`read_step` computes it
the same way from the quaternion it saved at the previous step, so both write the same
bits. (After an RK4 ``mj_step``, ``site_xmat`` holds the orientation of the integrator's
last stage, not of the start of the step; it is read only for models where the block
path is not available.)
"""

from __future__ import annotations

import math
from typing import Any

from numba import njit

from quadobs._kernels.observer import sensor_step

__all__ = ["read_block", "read_step", "site_rotation"]


_OPTS: dict[str, Any] = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_OPTS)
def _readings(row, j, sensordata, site_xmat, site, consts, draws):
    """Row ``j``'s sensors at the start of the step (ranges, world-frame acceleration, airspeed), then the sensor layer."""
    dim = int(consts[0])
    qb = int(consts[1])
    wind = consts[2] != 0.0
    acc = int(consts[6])
    vel = int(consts[7])
    n = 3 * dim if wind else 2 * dim
    o = n
    for h in range(qb):
        a = int(consts[14 + h])
        s = 0.0
        for i in range(3):
            s += sensordata[a + i] * sensordata[a + i]
        row[o + h] = math.sqrt(s)
    o += qb
    for i in range(dim):
        s = 0.0
        for m in range(3):
            s += site_xmat[site, 3 * i + m] * sensordata[acc + m]
        row[o + i] = s + consts[8 + i]
    o += dim
    s2 = 0.0
    for i in range(3):
        s = 0.0
        for m in range(3):
            s += site_xmat[site, 3 * i + m] * sensordata[vel + m]
        s -= consts[11 + i]
        s2 += s * s
    row[o] = math.sqrt(s2)
    ps = 14 + qb  # the sensor layer
    if consts[ps] != 0.0:
        sensor_step(
            row,
            n,
            n + qb,
            n + qb + dim,
            int(consts[ps + 1]),
            int(consts[ps + 2]),
            int(consts[ps + 3]),
            draws,
            j,
            consts,
            ps + 4,
        )


@njit(**_OPTS)
def _truth(nxt, qpos, qa, qvel, va, consts):
    """The true estimator state from ``qpos``, ``qvel`` (at offsets ``qa``, ``va``) into ``nxt``."""
    dim = int(consts[0])
    wind = consts[2] != 0.0
    for i in range(dim):
        nxt[i] = qpos[qa + i]
        v = qvel[va + i]
        if wind:
            nxt[dim + i] = v - consts[11 + i]
            nxt[2 * dim + i] = consts[11 + i]
        else:
            nxt[dim + i] = v


@njit(**_OPTS)
def read_step(j, out, ctrls, ctrl, sensordata, site_xmat, qpos, qvel, consts, draws, work):
    """Row ``j`` (sensors, sensor layer), row ``j + 1`` (truth) and the next control, after one ``mj_step``.

    ``work (2, 9)``: with ``work[1, 4] != 0`` the site's rotation at the start of the step
    is computed from the quaternion ``work[1, :4]`` saved at the previous call (see
    :func:`read_block`) into ``work[0]``; otherwise ``site_xmat`` is read.
    """
    qa = int(consts[3])
    if work[1, 4] != 0.0:
        site_rotation(work, work[1, 0], work[1, 1], work[1, 2], work[1, 3])
        for i in range(4):
            work[1, i] = qpos[qa + 3 + i]  # the start of the next step
        _readings(out[j], j, sensordata, work, 0, consts, draws)
    else:
        _readings(out[j], j, sensordata, site_xmat, int(consts[5]), consts, draws)
    _truth(out[j + 1], qpos, qa, qvel, int(consts[4]), consts)
    if j + 1 < ctrls.shape[0]:
        for i in range(ctrl.shape[0]):
            ctrl[i] = ctrls[j + 1, i]


@njit(**_OPTS)
def site_rotation(rot, w, x, y, z):
    """``rot[0] = mju_quat2Mat(mju_normalize4(q))``: a free body's orientation matrix from its ``qpos`` quaternion, as MuJoCo computes it."""
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if norm < 1e-15:  # mjMINVAL
        w, x, y, z = 1.0, 0.0, 0.0, 0.0
    elif abs(norm - 1.0) > 1e-15:
        inv = 1.0 / norm
        w, x, y, z = w * inv, x * inv, y * inv, z * inv
    r = rot[0]
    if w == 1.0 and x == 0.0 and y == 0.0 and z == 0.0:
        for i in range(9):
            r[i] = 1.0 if i % 4 == 0 else 0.0
        return
    q00, q01, q02, q03 = w * w, w * x, w * y, w * z
    q11, q12, q13, q22, q23, q33 = x * x, x * y, x * z, y * y, y * z, z * z
    r[0] = q00 + q11 - q22 - q33
    r[4] = q00 - q11 + q22 - q33
    r[8] = q00 - q11 - q22 + q33
    r[1] = 2 * (q12 - q03)
    r[2] = 2 * (q13 + q02)
    r[3] = 2 * (q12 + q03)
    r[5] = 2 * (q23 - q01)
    r[6] = 2 * (q13 - q02)
    r[7] = 2 * (q23 + q01)


@njit(**_OPTS)
def read_block(count, out, states, sensordata, state0, qo, vo, consts, draws, work):
    """Rows ``0 .. count`` of a block from ``mujoco.rollout``'s ``states (count, nstate)`` and ``sensordata (count, nsd)``.

    ``state0`` is the full physics state before the block; ``qo``, ``vo`` the columns of
    the vehicle's ``qpos`` and ``qvel`` in a state row; ``work (2, 9)`` as for :func:`read_step`.
    """
    for j in range(count):
        prev = state0 if j == 0 else states[j - 1]
        site_rotation(work, prev[qo + 3], prev[qo + 4], prev[qo + 5], prev[qo + 6])
        _readings(out[j], j, sensordata[j], work, 0, consts, draws)
        _truth(out[j + 1], states[j], qo, states[j], vo, consts)
    for i in range(4):
        work[1, i] = states[count - 1, qo + 3 + i]
