"""Compiled (Numba) kernels of the quadrotor world's physics step: controller, IMU, ranges, row writes.

The arithmetic is that of the NumPy reference in :mod:`quadobs.testbed.controllers`
(:class:`~quadobs.testbed.controllers.GeometricController`, the geometric controller of
[LEE2010, eqs. 15-16] with its mixer) and :mod:`quadobs.testbed.imu`
(:class:`~quadobs.testbed.imu.ImuModel`, ``u = R~ f~ + g``), written with scalars on
buffers that are rewritten in place: nothing is allocated per call. Only the order of
floating-point sums differs from NumPy's, so the two agree to rounding.

Calling conventions (operands packed):

``gains`` (float64, 8): ``k_x, k_v, k_R, k_W, mass, tan(max_tilt), thrust_max, yaw``.
``imu`` (float64, 9): ``b_a (3), b_w (3), sigma_a, sigma_w, sigma_q``.
``rotor`` (float64, 6): ``k_u, k_d, a_1, a_2, T_min, T_max`` (:meth:`~quadobs.testbed.rotors.RotorModel.packed`).
"""

from __future__ import annotations

import math

from numba import njit

__all__ = ["body_imu", "control", "lead", "post_step", "pre_step", "quat_matrix", "rotor_step"]

_G = 9.81


@njit(cache=True)
def quat_matrix(q, R):
    """Fill ``R (3, 3)`` with the rotation of the unit quaternion ``q = (w, x, y, z)``."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True)
def control(p, v, R, W, ref, gains, J, mix_inv, out):
    """Rotor thrusts into ``out (4,)`` from position, velocity, attitude ``R``, body rates ``W`` and ``ref (3, 3)``.

    ``F = m (k_x e_p + k_v e_v + r'' + g e_3)`` (tilt limited, pointing up), ``R_d`` from
    ``F`` and the yaw, ``M = J (-k_R e_R - k_W W) + W x J W`` [LEE2010, eqs. 15-16],
    ``T = clip(A^-1 [F . R e_3, M], 0, T_max)``.
    """
    kx, kv, kR, kW, mass = gains[0], gains[1], gains[2], gains[3], gains[4]
    a0 = kx * (ref[0, 0] - p[0]) + kv * (ref[1, 0] - v[0]) + ref[2, 0]
    a1 = kx * (ref[0, 1] - p[1]) + kv * (ref[1, 1] - v[1]) + ref[2, 1]
    a2 = max(kx * (ref[0, 2] - p[2]) + kv * (ref[1, 2] - v[2]) + ref[2, 2] + _G, 0.2 * _G)
    horiz = math.hypot(a0, a1)
    limit = gains[5] * a2
    if horiz > limit:
        a0 *= limit / horiz
        a1 *= limit / horiz
    F0, F1, F2 = mass * a0, mass * a1, mass * a2
    nF = math.sqrt(F0 * F0 + F1 * F1 + F2 * F2)
    b30, b31, b32 = F0 / nF, F1 / nF, F2 / nF
    c0, c1 = math.cos(gains[7]), math.sin(gains[7])  # b1c = (c0, c1, 0)
    b20, b21, b22 = -b32 * c1, b32 * c0, b30 * c1 - b31 * c0  # b3 x b1c
    n2 = math.sqrt(b20 * b20 + b21 * b21 + b22 * b22)
    b20, b21, b22 = b20 / n2, b21 / n2, b22 / n2
    b10, b11, b12 = b21 * b32 - b22 * b31, b22 * b30 - b20 * b32, b20 * b31 - b21 * b30  # b2 x b3
    # E = Rd^T R (E_ij = b_i . R e_j), Rd = [b1 b2 b3]; e_R = vee(E - E^T) / 2
    E01 = b10 * R[0, 1] + b11 * R[1, 1] + b12 * R[2, 1]
    E02 = b10 * R[0, 2] + b11 * R[1, 2] + b12 * R[2, 2]
    E10 = b20 * R[0, 0] + b21 * R[1, 0] + b22 * R[2, 0]
    E12 = b20 * R[0, 2] + b21 * R[1, 2] + b22 * R[2, 2]
    E20 = b30 * R[0, 0] + b31 * R[1, 0] + b32 * R[2, 0]
    E21 = b30 * R[0, 1] + b31 * R[1, 1] + b32 * R[2, 1]
    eR0, eR1, eR2 = 0.5 * (E21 - E12), 0.5 * (E02 - E20), 0.5 * (E10 - E01)
    w0, w1, w2 = W[0], W[1], W[2]
    j0, j1, j2 = J[0] * w0, J[1] * w1, J[2] * w2
    M0 = J[0] * (-kR * eR0 - kW * w0) + (w1 * j2 - w2 * j1)
    M1 = J[1] * (-kR * eR1 - kW * w1) + (w2 * j0 - w0 * j2)
    M2 = J[2] * (-kR * eR2 - kW * w2) + (w0 * j1 - w1 * j0)
    f = F0 * R[0, 2] + F1 * R[1, 2] + F2 * R[2, 2]
    tmax = gains[6]
    for i in range(4):
        t = mix_inv[i, 0] * f + mix_inv[i, 1] * M0 + mix_inv[i, 2] * M1 + mix_inv[i, 3] * M2
        out[i] = min(max(t, 0.0), tmax)


@njit(cache=True)
def pre_step(p, anchors, ref, ctrl, on_estimate, ranges, row, o_ref, o_track, o_rot, o_on):
    """Ranges ``|p - a_h|`` into ``ranges``; reference, tracking error, rotor commands and ``on_estimate`` into ``row``; returns the tracking error."""
    for h in range(anchors.shape[0]):
        d0, d1, d2 = p[0] - anchors[h, 0], p[1] - anchors[h, 1], p[2] - anchors[h, 2]
        ranges[h] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    e0, e1, e2 = ref[0] - p[0], ref[1] - p[1], ref[2] - p[2]
    err = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    for i in range(3):
        row[o_ref + i] = ref[i]
    row[o_track] = err
    for i in range(4):
        row[o_rot + i] = ctrl[i]
    row[o_on] = on_estimate
    return err


@njit(cache=True)
def post_step(sd, ia, ig, iq, n, imu, update, att, rates, R, row, o_att, o_u, p, v, nxt):
    """The IMU after ``mj_step``: measured rates into ``rates``, the held attitude ``att`` (renewed when ``update``), ``u = R~ f~ + g`` and the true attitude into ``row``.

    ``f~ = f + b_a + sigma_a n[:3]``, ``w~ = w + b_w + sigma_w n[3:6]``,
    ``q~ = q (x) [1, sigma_q n[6:9] / 2]`` normalised; the true position ``p`` and
    velocity ``v`` after the step into ``nxt[:6]``. Returns whether the vehicle is upside
    down (``R_22 < 0`` of the true attitude).
    """
    for i in range(3):
        nxt[i] = p[i]
        nxt[3 + i] = v[i]
    for i in range(4):
        row[o_att + i] = sd[iq + i]
    for i in range(3):
        rates[i] = sd[ig + i] + imu[3 + i] + imu[7] * n[3 + i]
    if update:
        w, x, y, z = sd[iq], sd[iq + 1], sd[iq + 2], sd[iq + 3]
        if imu[8] != 0.0:
            a, b, c = 0.5 * imu[8] * n[6], 0.5 * imu[8] * n[7], 0.5 * imu[8] * n[8]
            q0 = w - x * a - y * b - z * c
            q1 = x + w * a + y * c - z * b
            q2 = y + w * b + z * a - x * c
            q3 = z + w * c + x * b - y * a
            s = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
            att[0], att[1], att[2], att[3] = q0 / s, q1 / s, q2 / s, q3 / s
        else:
            att[0], att[1], att[2], att[3] = w, x, y, z
    quat_matrix(att, R)
    f0 = sd[ia] + imu[0] + imu[6] * n[0]
    f1 = sd[ia + 1] + imu[1] + imu[6] * n[1]
    f2 = sd[ia + 2] + imu[2] + imu[6] * n[2]
    row[o_u] = R[0, 0] * f0 + R[0, 1] * f1 + R[0, 2] * f2
    row[o_u + 1] = R[1, 0] * f0 + R[1, 1] * f1 + R[1, 2] * f2
    row[o_u + 2] = R[2, 0] * f0 + R[2, 1] * f1 + R[2, 2] * f2 - _G
    x, y = sd[iq + 1], sd[iq + 2]
    return 1.0 - 2.0 * (x * x + y * y) < 0.0


@njit(cache=True)
def rotor_step(command, running, w, rotor, h, thrust):
    """Rotor speeds ``w (4,)`` (rpm) advanced by ``h`` with the thrust ``command (4,)`` held; their thrusts into ``thrust``.

    The identified model of :mod:`quadobs.testbed.rotors`, integrated exactly: spinning up
    ``w_c + (w - w_c) exp(-k_u h)``, spinning down ``w_c (w + w_c s) / (w_c + w s)``,
    ``s = tanh(k_d w_c h)``; the command clamped to ``[T_min, T_max]`` while ``running``,
    0 otherwise; ``T = max(a_1 w + a_2 w^2, 0)``.
    """
    ku, kd, a1, a2 = rotor[0], rotor[1], rotor[2], rotor[3]
    decay = math.exp(-ku * h)
    for i in range(4):
        c = 0.0
        if running:
            T = min(max(command[i], rotor[4]), rotor[5])
            c = (-a1 + math.sqrt(a1 * a1 + 4.0 * a2 * T)) / (2.0 * a2)
        w0 = w[i]
        if c > w0:
            w1 = c + (w0 - c) * decay
        elif c > 0.0:
            s = math.tanh(kd * c * h)
            w1 = c * (w0 + c * s) / (c + w0 * s)
        else:
            w1 = w0 / (1.0 + kd * w0 * h)
        w[i] = w1
        thrust[i] = max(a1 * w1 + a2 * w1 * w1, 0.0)


@njit(cache=True)
def lead(desired, state, tau_up, tau_down, rate, alpha, out):
    """``out = T_d + tau s``, ``s`` the derivative of ``T_d`` low-passed: ``s += alpha ((T_d - T_prev) rate - s)``.

    ``tau = tau_up`` where ``s > 0`` (spinning up), ``tau_down`` otherwise; ``state (8,)``
    holds ``T_prev`` then ``s`` and is renewed.
    """
    for i in range(4):
        d = (desired[i] - state[i]) * rate
        s = state[4 + i] + alpha * (d - state[4 + i])
        out[i] = desired[i] + (tau_up if s > 0.0 else tau_down) * s
        state[i] = desired[i]
        state[4 + i] = s


@njit(cache=True)
def body_imu(sd, ia, n, imu, rates, out):
    """The body IMU sample into ``out (6,)``: ``f~ = f + b_a + sigma_a n[:3]`` and the measured rates."""
    for i in range(3):
        out[i] = sd[ia + i] + imu[i] + imu[6] * n[i]
        out[3 + i] = rates[i]
