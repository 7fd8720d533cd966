"""Compiled (Numba) kernels of the augmented observer: one fused correct + predict per call.

Imported lazily by :mod:`quadobs.estimators.augmented` and :mod:`quadobs.estimators.augmented_batch` (the estimator core
imports with NumPy and SciPy alone). The arithmetic is that of the NumPy reference of
:class:`~quadobs.estimators.augmented.AugmentedObserver` (``backend="numpy"``), with the products
associated to follow the structure of the matrices:

* the transition ``Phi(u) = F0 + sum_j u_j F1[j]`` changes only in its aux-x block
  ([IFAC2021] eqs. 22, 26a-c) and is sparse (block upper triangular;
  ``e^{A dt}`` of a nilpotent ``A`` is a short polynomial in ``A``): it is kept as a dense
  buffer whose aux-x block is rewritten each step and traversed by its structural
  nonzeros (CSR);
* ``Q_d(u) = sum_r mono_r(u) Qc[r]`` over the monomials ``1, u_j, u_j u_l (j <= l)``
  (``Qc`` from ``Q0, Q1, Q2`` of :class:`~quadobs.core.held_input.HeldInputDiscretization`)
  is assembled from the nonzero upper-triangular entries of the ``Qc[r]`` (COO);
* the output matrix ``C = [F | D]`` is sparse (CSR);
* the Joseph form ``(I - K C) P (I - K C)^T + K R K^T`` is evaluated as
  ``X = P - K (P C^T)^T`` then ``X - (X C^T) K^T + K R K^T``: the same products,
  associated so that each is ``O(N^2 q)`` rather than ``O(N^3)``;
* the state moves by ``K nu = (P C^T) S^{-1} nu``, with ``S`` factored once (Cholesky).

The covariance is written as its upper triangle and mirrored, so it is exactly
symmetric. Nothing is allocated per call.

Calling convention. Passing an array from Python to a compiled function costs tens of
nanoseconds, more than most of the arithmetic here, so the operands travel packed:

``ic`` (int64)
    header ``[N, k, p, q, nm, nq, o_phi_ptr, o_phi_col, o_qi, o_qj, o_qr, o_c_ptr, o_c_col,
    o_iw, o_fblk, o_F1, o_G0, o_G2, o_qv, o_cval, o_R]`` (offsets ``o_*`` into ``ic`` or
    ``fc``), then the CSR of ``Phi``, the COO of ``Qc``, the CSR of ``C``, and ``q``
    integers of work;
``fc`` (float64)
    ``[growth, gate]``, then the constant aux-x block of ``F0 (k, n)``, ``F1 (p, k, n)``,
    ``G0 (n, p)``, ``G2 (p, k, p)``, the ``Qc`` values, the ``C`` values and ``R (q, q)``,
    each row-major at its offset;
``W`` (float64 work, :func:`work_size`)
    ``Phi``, ``T`` (or ``X``) (``N * N`` each), ``P C^T``, ``K``, ``X C^T``,
    ``K R`` (``N * q`` each), ``zt (N)``, ``mono (nm)``, ``L (q * q)``, ``nu``, ``w``, ``tmp``
    (``q`` each), then the observer's ``stats = [nis, corrections, rejected, trace(P)]``.

A single observer keeps ``z``, ``P`` and ``W`` in one buffer ``S = [z | P | W]``
(:func:`augmented_step` then takes five arrays), a batch one row ``[z | P | stats]`` per
member and a shared ``W``; the kernels index these flat buffers by offset (slicing views
inside a kernel costs reference counting). :class:`quadobs.estimators.augmented.KernelModel` builds
``ic`` and ``fc``.
"""

from __future__ import annotations

import math

from numba import njit

__all__ = [
    "HEADER",
    "augmented_correct",
    "augmented_predict",
    "augmented_step",
    "augmented_step_batch",
    "augmented_step_block",
    "augmented_step_record",
    "batch_refused",
    "range_outputs",
    "sensor_step",
    "work_size",
]

_OPTS = dict(cache=True, nogil=True, error_model="numpy")

#: Length of the header of ``ic``.
HEADER = 21


def work_size(N: int, q: int, nm: int) -> int:
    """Length of the work buffer ``W`` (stats included) for ``N`` states, ``q`` outputs, ``nm`` monomials."""
    return 2 * N * N + 4 * N * q + N + nm + q * q + 3 * q + 4


@njit(**_OPTS)
def _cholesky_nis(W, oL, onu, otmp, ow, q, r):
    """Cholesky ``L L^T`` of the ``r x r`` innovation covariance held at ``W[oL:]`` (row stride ``q``, lower
    triangle, in place), ``w = (L L^T)^{-1} nu`` into ``W[ow:]`` (``nu`` at ``W[onu:]``, ``W[otmp:]``
    scratch); returns the NIS ``nu^T w``."""
    # Cholesky of the innovation covariance, L L^T, in place in the lower triangle.
    for j in range(r):
        s = W[oL + j * q + j]
        for t in range(j):
            s -= W[oL + j * q + t] * W[oL + j * q + t]
        d = math.sqrt(s)
        W[oL + j * q + j] = d
        for i in range(j + 1, r):
            s = W[oL + i * q + j]
            for t in range(j):
                s -= W[oL + i * q + t] * W[oL + j * q + t]
            W[oL + i * q + j] = s / d
    # w = (L L^T)^{-1} nu; NIS = nu^T w.
    for i in range(r):
        s = W[onu + i]
        for t in range(i):
            s -= W[oL + i * q + t] * W[otmp + t]
        W[otmp + i] = s / W[oL + i * q + i]
    for i in range(r - 1, -1, -1):
        s = W[otmp + i]
        for t in range(i + 1, r):
            s -= W[oL + t * q + i] * W[ow + t]
        W[ow + i] = s / W[oL + i * q + i]
    nis = 0.0
    for a in range(r):
        nis += W[onu + a] * W[ow + a]
    return nis


@njit(**_OPTS)
def _correct(S, zo, po, so, W, wo, y, fc, ic):
    N = ic[0]
    q = ic[3]
    nm = ic[4]
    o_cptr = ic[11]
    o_ccol = ic[12]
    o_iw = ic[13]
    o_cval = ic[19]
    o_R = ic[20]
    r = 0
    for h in range(q):
        if not math.isnan(y[h]):
            ic[o_iw + r] = h
            r += 1
    if r == 0:
        S[so + 0] = math.nan
        return 0
    gate = fc[1]
    oX = N * N
    oPC = 2 * N * N  # P C^T, then K, X C^T, K R: (N, q) row-major
    oK = oPC + N * q
    oXC = oK + N * q
    oKR = oXC + N * q
    oL = oKR + N * q + N + nm  # L (q, q), then nu, w, tmp
    onu = oL + q * q
    ow = onu + q
    otmp = ow + q

    # P C^T (P symmetric: row m of P is column m), innovation nu, its covariance C P C^T + R (lower).
    for a in range(r):
        h = ic[o_iw + a]
        for i in range(N):
            W[wo + oPC + i * q + a] = 0.0
        s = y[h]
        for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
            m = ic[o_ccol + t]
            c = fc[o_cval + t]
            s -= c * S[zo + m]
            for i in range(N):
                W[wo + oPC + i * q + a] += c * S[po + m * N + i]
        W[wo + onu + a] = s
    for a in range(r):
        h = ic[o_iw + a]
        for b in range(a + 1):
            s = fc[o_R + h * q + ic[o_iw + b]]
            for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
                s += fc[o_cval + t] * W[wo + oPC + ic[o_ccol + t] * q + b]
            W[wo + oL + a * q + b] = s
    nis = _cholesky_nis(W, wo + oL, wo + onu, wo + otmp, wo + ow, q, r)
    S[so + 0] = nis
    if nis > gate:
        S[so + 2] += 1.0
        return 2
    # K = P C^T (L L^T)^{-1}, row by row; z += K nu = P C^T w.
    for i in range(N):
        for a in range(r):
            s = W[wo + oPC + i * q + a]
            for t in range(a):
                s -= W[wo + oL + a * q + t] * W[wo + otmp + t]
            W[wo + otmp + a] = s / W[wo + oL + a * q + a]
        for a in range(r - 1, -1, -1):
            s = W[wo + otmp + a]
            for t in range(a + 1, r):
                s -= W[wo + oL + t * q + a] * W[wo + oK + i * q + t]
            W[wo + oK + i * q + a] = s / W[wo + oL + a * q + a]
        s = 0.0
        for a in range(r):
            s += W[wo + oPC + i * q + a] * W[wo + ow + a]
        S[zo + i] += s
    # Joseph form: X = (I - K C) P = P - K (P C^T)^T, then X (I - K C)^T + K R K^T.
    for i in range(N):
        for j in range(N):
            s = S[po + (i) * N + j]
            for a in range(r):
                s -= W[wo + oK + i * q + a] * W[wo + oPC + j * q + a]
            W[wo + oX + i * N + j] = s
    for a in range(r):
        h = ic[o_iw + a]
        for i in range(N):
            s = 0.0
            for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
                s += W[wo + oX + i * N + ic[o_ccol + t]] * fc[o_cval + t]
            W[wo + oXC + i * q + a] = s
            s = 0.0
            for b in range(r):
                s += W[wo + oK + i * q + b] * fc[o_R + ic[o_iw + b] * q + h]
            W[wo + oKR + i * q + a] = s
    tr = 0.0
    for i in range(N):
        for j in range(i, N):
            s = W[wo + oX + i * N + j]
            for a in range(r):
                s += (W[wo + oKR + i * q + a] - W[wo + oXC + i * q + a]) * W[wo + oK + j * q + a]
            S[po + (i) * N + j] = s
            S[po + (j) * N + i] = s
        tr += S[po + (i) * N + i]
    S[so + 1] += 1.0
    S[so + 3] = tr
    return 1


@njit(**_OPTS)
def _predict(S, zo, po, so, W, wo, u, fc, ic):
    N = ic[0]
    k = ic[1]
    p = ic[2]
    q = ic[3]
    nq = ic[5]
    o_pptr = ic[6]
    o_pcol = ic[7]
    o_qi = ic[8]
    o_qj = ic[9]
    o_qr = ic[10]
    o_fblk = ic[14]
    o_F1 = ic[15]
    o_G0 = ic[16]
    o_G2 = ic[17]
    o_qv = ic[18]
    n = N - k
    growth = fc[0]
    oT = N * N  # Phi at 0, T at oT
    ozt = 2 * N * N + 4 * N * q
    omono = ozt + N
    # Phi(u): only the aux-x block depends on u.
    for a in range(k):
        for b in range(n):
            s = fc[o_fblk + a * n + b]
            for j in range(p):
                s += u[j] * fc[o_F1 + (j * k + a) * n + b]
            W[wo + a * N + k + b] = s
    # z <- Phi z + g(u)
    for i in range(N):
        s = 0.0
        for t in range(ic[o_pptr + i], ic[o_pptr + i + 1]):
            m = ic[o_pcol + t]
            s += W[wo + i * N + m] * S[zo + m]
        W[wo + ozt + i] = s
    for a in range(k):
        s = 0.0
        for j in range(p):
            uj = u[j]
            for l in range(p):
                s += uj * fc[o_G2 + (j * k + a) * p + l] * u[l]
        W[wo + ozt + a] += s
    for b in range(n):
        s = 0.0
        for j in range(p):
            s += fc[o_G0 + b * p + j] * u[j]
        W[wo + ozt + k + b] += s
    for i in range(N):
        S[zo + i] = W[wo + ozt + i]
    # T = Phi P: row i of T combines the rows of P picked by row i of Phi.
    for i in range(N):
        for j in range(N):
            W[wo + oT + i * N + j] = 0.0
        for t in range(ic[o_pptr + i], ic[o_pptr + i + 1]):
            m = ic[o_pcol + t]
            f = W[wo + i * N + m]
            for j in range(N):
                W[wo + oT + i * N + j] += f * S[po + (m) * N + j]
    # P <- growth T Phi^T + Q_d(u), written straight into P (T holds all that is needed of
    # the old P): the upper triangle, mirrored, then the entries of Q_d(u) added to both.
    for i in range(N):
        for j in range(i, N):
            s = 0.0
            for t in range(ic[o_pptr + j], ic[o_pptr + j + 1]):
                m = ic[o_pcol + t]
                s += W[wo + oT + i * N + m] * W[wo + j * N + m]
            s *= growth
            S[po + (i) * N + j] = s
            S[po + (j) * N + i] = s
    W[wo + omono] = 1.0
    for j in range(p):
        W[wo + omono + 1 + j] = u[j]
    c = omono + 1 + p
    for j in range(p):
        for l in range(j, p):
            W[wo + c] = u[j] * u[l]
            c += 1
    for t in range(nq):
        i = ic[o_qi + t]
        j = ic[o_qj + t]
        v = fc[o_qv + t] * W[wo + omono + ic[o_qr + t]]
        S[po + (i) * N + j] += v
        if i != j:
            S[po + (j) * N + i] += v
    tr = 0.0
    for i in range(N):
        tr += S[po + (i) * N + i]
    S[so + 3] = tr


@njit(**_OPTS)
def augmented_correct(y, S, fc, ic):
    """Kalman correction of ``S = [z | P | W]`` with the outputs present in ``y`` (NaN = missing).

    The stats at the end of ``S`` record the NIS, count the corrections and the
    rejections, and hold the trace of ``P``. Returns 0 (nothing present: predict only),
    1 (corrected) or 2 (rejected by the gate, ``NIS > fc[1]``).
    """
    N = ic[0]
    return _correct(S, 0, N, S.shape[0] - 4, S, N + N * N, y, fc, ic)


@njit(**_OPTS)
def augmented_predict(u, S, fc, ic):
    """Exact prediction of ``S = [z | P | W]`` over one step with ``u`` held:
    ``z <- Phi(u) z + g(u)``, ``P <- e^{theta dt} Phi(u) P Phi(u)^T + Q_d(u)``."""
    N = ic[0]
    _predict(S, 0, N, S.shape[0] - 4, S, N + N * N, u, fc, ic)


@njit(**_OPTS)
def _refused(u, y, ic):
    """Whether ``u (p,)`` holds a non-finite value or ``y (q,)`` an infinite one (NaN in ``y``: missing)."""
    for j in range(ic[2]):
        if not math.isfinite(u[j]):
            return True
    for h in range(ic[3]):
        if math.isinf(y[h]):
            return True
    return False


@njit(**_OPTS)
def augmented_step(u, y, S, fc, ic):
    """:func:`augmented_correct` with ``y`` then :func:`augmented_predict` with ``u``; returns the correction
    code, or -1, changing nothing, when ``u`` holds a non-finite value or ``y`` an infinite one."""
    if _refused(u, y, ic):
        return -1
    N = ic[0]
    so = S.shape[0] - 4
    code = _correct(S, 0, N, so, S, N + N * N, y, fc, ic)
    _predict(S, 0, N, so, S, N + N * N, u, fc, ic)
    return code


@njit(**_OPTS)
def batch_refused(U, Y, ic):
    """The first member ``b`` whose ``U[b]`` holds a non-finite value or ``Y[b]`` an infinite one
    (NaN in ``Y``: missing), else -1."""
    p = ic[2]
    q = ic[3]
    for b in range(U.shape[0]):
        for j in range(p):
            if not math.isfinite(U[b, j]):
                return b
        for h in range(q):
            if math.isinf(Y[b, h]):
                return b
    return -1


@njit(**_OPTS)
def augmented_step_batch(U, Y, SB, W, fc, ic):
    """:func:`augmented_step` for each member ``b`` of a batch, one after the other.

    ``U (B, p)``, ``Y (B, q)``; row ``b`` of ``SB (B, N + N * N + 4)`` holds member ``b``'s
    ``[z | P | stats]``; the model (``fc``, ``ic``) and the work buffer ``W``
    (:func:`work_size`) are shared. Calls running at the same time (threads) need their
    own ``W`` and ``ic`` (the end of ``ic`` is integer work). Every member's operands are
    checked first (:func:`batch_refused`): returns 0, or ``-1 - b`` when member ``b`` is
    refused, and then no member has changed.
    """
    bad = batch_refused(U, Y, ic)
    if bad >= 0:
        return -1 - bad
    N = ic[0]
    so = SB.shape[1] - 4
    for b in range(SB.shape[0]):
        Sb = SB[b]
        _correct(Sb, 0, N, so, W, 0, Y[b], fc, ic)
        _predict(Sb, 0, N, so, W, 0, U[b], fc, ic)
    return 0


@njit(**_OPTS)
def range_outputs(ranges, noise, std, beacon_term, measured, y):
    """``measured = ranges + std * noise``, ``y = measured^2 / 2 - beacon_term`` (:class:`quadobs.testbed.sensors.SensorModel`)."""
    for h in range(ranges.shape[0]):
        rho = ranges[h] + std * noise[h] if std != 0.0 else ranges[h]
        measured[h] = rho
        y[h] = rho * rho * 0.5 - beacon_term[h]


@njit(**_OPTS)
def _step_record(u, y, S, fc, ic, out):
    N = ic[0]
    k = ic[1]
    if _refused(u, y, ic):
        return -1
    so = S.shape[0] - 4
    for i in range(N - k):
        out[i] = S[k + i]
    out[N - k] = S[so + 3]
    code = _correct(S, 0, N, so, S, N + N * N, y, fc, ic)
    _predict(S, 0, N, so, S, N + N * N, u, fc, ic)
    out[N - k + 1] = S[so]
    out[N - k + 2] = S[so + 2]
    return code


@njit(**_OPTS)
def augmented_step_record(u, y, S, fc, ic, out):
    """:func:`augmented_step`, recording ``out = [x_hat, trace(P)]`` before it and ``[NIS, rejected]`` after it.

    ``out`` has ``n + 3`` entries (``n = N - k``): ``x_hat (n)`` and ``trace(P)`` before the
    step, then the step's NIS and the running count of corrections rejected by the gate
    (``stats[2]``) after it; this is
    :meth:`quadobs.estimators.base.Estimator.step_and_record` in one call. Returns -1, and
    changes nothing, when ``u`` holds a non-finite value or ``y`` an infinite one (NaN in
    ``y``: a missing sample).
    """
    return _step_record(u, y, S, fc, ic, out)


@njit(**_OPTS)
def augmented_step_block(U, Y, S, fc, ic, out):
    """:func:`augmented_step_record` over the rows of a block, in one call.

    Row ``j`` of ``U (m, p)``, ``Y (m, q)`` is the step's input and outputs and row ``j`` of
    ``out (m, n + 3)`` gets its record, exactly as ``m`` calls of
    :func:`augmented_step_record` (the same arithmetic, in the same order, so the same bits)
    without ``m - 1`` crossings from Python. Returns the number of corrections applied, or
    ``-1 - j`` when row ``j`` is refused (a non-finite ``u`` or an infinite ``y``): rows
    ``0 .. j - 1`` are then done and nothing of row ``j`` or later has changed the state.
    """
    applied = 0
    for j in range(U.shape[0]):
        code = _step_record(U[j], Y[j], S, fc, ic, out[j])
        if code < 0:
            return -1 - j
        if code == 1:
            applied += 1
    return applied


@njit(**_OPTS)
def sensor_step(row, o_rng, o_acc, o_air, o_y, o_u, o_meas, draws, j, params, po):
    """The sensor layer of one step (:meth:`quadobs.testbed.sensors.SensorModel.outputs` and ``input``), in ``row``.

    Reads the exact ranges, acceleration and airspeed at ``row[o_rng:]``, ``row[o_acc:]``,
    ``row[o_air]``; writes ``y (q)``, ``u (dim)`` and the measured ranges ``(q_b)`` at
    ``o_y``, ``o_u``, ``o_meas``. ``draws[j]`` is the step's row of
    :meth:`~quadobs.testbed.sensors.SensorModel.draws`, ``params[po:]`` holds
    :meth:`~quadobs.testbed.sensors.SensorModel.step_params`. Same operations, in the same order,
    as the NumPy code, so the same values.
    """
    qb = int(params[po + 0])
    q = int(params[po + 1])
    dim = int(params[po + 2])
    range_std = params[po + 3]
    p_out = params[po + 4]
    std_out = params[po + 5]
    air_std = params[po + 6]
    dropout = params[po + 7]
    accel_std = params[po + 8]
    flags = int(draws[j, draws.shape[1] - 1])
    if flags & 1:
        for h in range(qb):
            rho = row[o_rng + h] + range_std * draws[j, h] if range_std != 0.0 else row[o_rng + h]
            if p_out != 0.0 and draws[j, qb + h] < p_out:
                rho = rho + std_out * draws[j, 2 * qb + h]
            row[o_meas + h] = rho
            row[o_y + h] = 0.5 * rho * rho - params[po + 9 + h]
    else:
        for h in range(qb):
            row[o_meas + h] = math.nan
            row[o_y + h] = math.nan
    if q > qb:
        if flags & 2:
            s = row[o_air] + (air_std * draws[j, 3 * qb] if air_std != 0.0 else 0.0)
            row[o_y + qb] = 0.5 * s * s
        else:
            row[o_y + qb] = math.nan
    if dropout != 0.0:
        od = 3 * qb + 1
        for h in range(q):
            if draws[j, od + h] < dropout and not math.isnan(row[o_y + h]):
                row[o_y + h] = math.nan
                if h < qb:
                    row[o_meas + h] = math.nan
    oa = 3 * qb + 1 + q
    for i in range(dim):
        row[o_u + i] = row[o_acc + i] + accel_std * draws[j, oa + i] if accel_std != 0.0 else row[o_acc + i]
