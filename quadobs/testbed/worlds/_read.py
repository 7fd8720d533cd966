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
"""

from __future__ import annotations

import math

from numba import njit

from quadobs._kernels.observer import sensor_step

__all__ = ["read_step"]


@njit(cache=True, nogil=True, error_model="numpy")
def read_step(j, out, ctrls, ctrl, sensordata, site_xmat, qpos, qvel, consts, draws):
    dim = int(consts[0])
    qb = int(consts[1])
    wind = consts[2] != 0.0
    qa = int(consts[3])
    va = int(consts[4])
    site = int(consts[5])
    acc = int(consts[6])
    vel = int(consts[7])
    n = 3 * dim if wind else 2 * dim
    row = out[j]
    # sensors at the start of step j: ranges, accelerometer (world frame), airspeed
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
        sensor_step(row, n, n + qb, n + qb + dim, int(consts[ps + 1]), int(consts[ps + 2]), int(consts[ps + 3]), draws, j, consts, ps + 4)
    # truth at the end of step j (start of j + 1)
    nxt = out[j + 1]
    for i in range(dim):
        nxt[i] = qpos[qa + i]
        v = qvel[va + i]
        if wind:
            nxt[dim + i] = v - consts[11 + i]
            nxt[2 * dim + i] = consts[11 + i]
        else:
            nxt[dim + i] = v
    # the control of the next step
    if j + 1 < ctrls.shape[0]:
        for i in range(ctrl.shape[0]):
            ctrl[i] = ctrls[j + 1, i]
