"""Compiled (Numba) kernels of the augmented observer: one fused correct + predict per call.

Imported lazily by :mod:`quadobs.estimators.augmented` and :mod:`quadobs.estimators.augmented_batch` (the estimator core
imports with NumPy and SciPy alone). The arithmetic is that of the NumPy reference of
:class:`~quadobs.estimators.augmented.AugmentedObserver` (``backend="numpy"``), with the products
associated to follow the structure of the matrices:

* the transition ``Phi(u) = F0 + sum_j u_j F1[j]`` changes only in its aux-x block
  ([IFAC2021] eqs. 22, 26a-c) and is block upper triangular, ``[[A, B(u)], [0, E]]`` with
  ``E = e^{A_x dt}`` constant; it is kept as a dense buffer whose aux-x block is
  rewritten each step;
* ``Q_d(u) = sum_r mono_r(u) Qc[r]`` over the monomials ``1, u_j, u_j u_l (j <= l)``
  (``Qc`` from ``Q0, Q1, Q2`` of :class:`~quadobs.core.held_input.HeldInputDiscretization`);
* the output matrix ``C = [F | D]`` is sparse (CSR);
* the Joseph form ``(I - K C) P (I - K C)^T + K R K^T`` is evaluated as
  ``X = P - K (C P)`` then ``X - (X C^T) K^T + K R K^T``: the same products,
  associated so that each is ``O(N^2 q)`` rather than ``O(N^3)``;
* the state moves by ``K nu = (C P)^T S^{-1} nu``, with ``S`` factored once (Cholesky).

The covariance is written as its upper triangle and mirrored, so it is exactly
symmetric. Nothing is allocated per call.

Two paths for the prediction
----------------------------
Its cost is the product ``Phi P Phi^T``. When ``Phi`` is sparse (the vehicles: ``e^{A dt}``
of a nilpotent ``A`` is a short polynomial in ``A``; ``N = 7 .. 13``, 30 to 45 % nonzero)
the *sparse path* (:func:`_predict_sparse`) traverses ``Phi`` by its structural nonzeros
(CSR) and adds the nonzero upper-triangular entries of the ``Qc[r]`` (COO): ``1.5 nnz N``
multiply-adds, at 2 to 3 GFlop/s (short loops, indices through the CSR). When ``Phi`` is
dense (a random ``A`` of size ``n = 5 .. 8`` gives ``N = 20 .. 44``, 80 % nonzero: the
auxiliary block ``e^{M dt}`` is full) that is ``O(N^3)`` at the same rate, so past a
threshold the *dense path* (:func:`_predict_dense`) does the products with BLAS
(``np.dot`` on contiguous 2-D views of the flat buffers, which Numba hands to the
``dgemm`` of SciPy's BLAS), using the block structure of ``Phi``:

.. math::

    T_{:k} = \\Phi_{:k} P, \\quad T_{k:} = E P_{k:}, \\quad
    P_{:k} \\leftarrow T_{:k} \\Phi^\\top, \\quad
    \\operatorname{triu}(P_{k:,k:}) \\leftarrow \\operatorname{triu}(T_{k:,k:} E^\\top),

``2 k N^2 + n^2 N + n^3 / 2`` multiply-adds instead of ``2 N^3`` (``k`` auxiliary states,
``n = N - k``), then ``P <- growth P + Q_d(u)`` on the upper triangle with the ``Qc[r]``
stored dense, mirrored. :func:`dense_path` decides, once per model: the dense path is taken
when the sparse product ``Phi P`` would cost at least :data:`DENSE_MIN_WORK` multiply-adds
(``nnz N``, below which the fixed cost of the BLAS calls dominates) and ``Phi`` is at least
a quarter full (:data:`DENSE_MIN_FILL`: the dense path does ``~2 N^3`` multiply-adds at 5 to
8 times the sparse path's rate, so it pays when ``1.5 nnz N > 2 N^3 / 6``). Every built-in
scenario stays on the sparse path, whose results are unchanged to the bit. The dense path
agrees with the NumPy reference to rounding (``1e-12`` of the covariance's scale over
thousands of steps, tested). Measured at ``N = 38`` (``docs/benchmarks.md``): about 9 us a
step in the kernel against 55 us on the sparse path; the products are two thirds of it, at
0.9 of the single-thread ``dgemm`` rate of that size.

Loops over a row index a slice of the flat buffer from 0 (``row = W[o : o + N]``,
``row[j]``): Numba wraps negative indices, and with an index ``o + j`` whose sign LLVM
cannot prove that test stays in the loop and keeps it from being vectorised.

Calling convention. Passing an array from Python to a compiled function costs tens of
nanoseconds, more than most of the arithmetic here, so the operands travel packed:

``ic`` (int64)
    header ``[N, k, p, q, nm, nq, o_phi_ptr, o_phi_col, o_qi, o_qj, o_qr, o_c_ptr, o_c_col,
    o_iw, o_fblk, o_F1, o_G0, o_G2, o_qv, o_cval, o_R, dense, o_Qc, o_E]`` (offsets ``o_*``
    into ``ic`` or ``fc``; ``dense``: 1 for the dense path), then the CSR of ``Phi``, the
    COO of ``Qc``, the CSR of ``C``, and ``q`` integers of work;
``fc`` (float64)
    ``[growth, gate]``, then the constant aux-x block of ``F0 (k, n)``, ``F1 (p, k, n)``,
    ``G0 (n, p)``, ``G2 (p, k, p)``, the ``Qc`` values (COO), the ``C`` values, ``R (q, q)``
    and, for the dense path only, ``Qc (nm, N, N)`` and ``E (n, n)``, each row-major at its
    offset;
``W`` (float64 work, :func:`work_size`)
    ``Phi``, ``T`` (or ``X``) (``N * N`` each), ``C P``, ``K^T`` (``(q, N)`` each),
    ``X C^T`` (first ``L^{-1} C P``, ``(q, N)``), ``K R`` (``(N, q)`` each), ``zt (N)``,
    ``mono (nm)``, ``L (q * q)``, ``nu``, ``w``, ``tmp`` (``q`` each), then the observer's
    ``stats = [nis, corrections, rejected, trace(P)]``.

A single observer keeps ``z``, ``P`` and ``W`` in one buffer ``S = [z | P | W]``
(:func:`augmented_step` then takes five arrays), a batch one row ``[z | P | stats]`` per
member and a shared ``W``; the kernels index these flat buffers by offset, through 1-D
slices (about a nanosecond each; a reshaped 2-D view costs some 25 ns, and is made only on
the dense path). :class:`quadobs.estimators.augmented.KernelModel` builds ``ic`` and ``fc``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

__all__ = [
    "DENSE_MIN_FILL",
    "DENSE_MIN_WORK",
    "HEADER",
    "augmented_correct",
    "augmented_predict",
    "augmented_step",
    "augmented_step_batch",
    "augmented_step_block",
    "augmented_step_record",
    "batch_refused",
    "dense_path",
    "range_outputs",
    "sensor_step",
    "work_size",
]

_OPTS: dict[str, Any] = dict(cache=True, nogil=True, error_model="numpy")
#: The helpers: inlined into each kernel (Numba IR), which compiles in about 3 s less than as
#: separately compiled callees, at the same speed.
_INLINE: dict[str, Any] = dict(_OPTS, inline="always")

#: The integer header of ``ic``, in order (module docstring): the one list that the builder
#: (:class:`quadobs.estimators.augmented.KernelModel`) writes by name and the kernels read by name.
HEADER_FIELDS = (
    "N",
    "k",
    "p",
    "q",
    "nm",
    "nq",
    "o_phi_ptr",
    "o_phi_col",
    "o_qi",
    "o_qj",
    "o_qr",
    "o_c_ptr",
    "o_c_col",
    "o_iw",
    "o_fblk",
    "o_F1",
    "o_G0",
    "o_G2",
    "o_qv",
    "o_cval",
    "o_R",
    "dense",
    "o_Qc",
    "o_E",
)
#: Length of the header of ``ic``.
HEADER = len(HEADER_FIELDS)
_AT = {name: i for i, name in enumerate(HEADER_FIELDS)}
#: Where each field sits: the kernels read ``ic[H_N]`` (compile-time constants).
H_N, H_K, H_P, H_Q = (_AT["N"], _AT["k"], _AT["p"], _AT["q"])
H_NM, H_NQ, H_O_PHI_PTR, H_O_PHI_COL = (_AT["nm"], _AT["nq"], _AT["o_phi_ptr"], _AT["o_phi_col"])
H_O_QI, H_O_QJ, H_O_QR, H_O_C_PTR = (_AT["o_qi"], _AT["o_qj"], _AT["o_qr"], _AT["o_c_ptr"])
H_O_C_COL, H_O_IW, H_O_FBLK, H_O_F1 = (_AT["o_c_col"], _AT["o_iw"], _AT["o_fblk"], _AT["o_F1"])
H_O_G0, H_O_G2, H_O_QV, H_O_CVAL = (_AT["o_G0"], _AT["o_G2"], _AT["o_qv"], _AT["o_cval"])
H_O_R, H_DENSE, H_O_QC, H_O_E = (_AT["o_R"], _AT["dense"], _AT["o_Qc"], _AT["o_E"])
#: Least ``nnz(Phi) N`` (multiply-adds of the sparse ``Phi P``) for the dense path.
DENSE_MIN_WORK = 1000
#: Least share of structural nonzeros in ``Phi`` for the dense path.
DENSE_MIN_FILL = 0.25


def dense_path(N: int, nnz: int) -> bool:
    """Whether an observer with ``N`` states and ``nnz`` structural nonzeros in ``Phi`` predicts on the dense path.

    ``nnz N >= DENSE_MIN_WORK`` and ``nnz >= DENSE_MIN_FILL N^2`` (module docstring, "Two paths
    for the prediction"). The vehicles (``nnz N`` from 154 to 637) stay on the sparse path.
    """
    return nnz * N >= DENSE_MIN_WORK and nnz >= DENSE_MIN_FILL * N * N


def work_size(N: int, q: int, nm: int) -> int:
    """Length of the work buffer ``W`` (stats included) for ``N`` states, ``q`` outputs, ``nm`` monomials."""
    return 2 * N * N + 4 * N * q + N + nm + q * q + 3 * q + 4


@njit(**_INLINE)
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


@njit(**_INLINE)
def _output_header(ic):
    """The fields of the header that the correction reads: ``N, q, nm`` and the offsets of
    ``C`` (CSR pointers, columns, values), of the indices of the outputs present and of ``R``."""
    return (
        ic[H_N],
        ic[H_Q],
        ic[H_NM],
        ic[H_O_C_PTR],
        ic[H_O_C_COL],
        ic[H_O_IW],
        ic[H_O_CVAL],
        ic[H_O_R],
    )


@njit(**_INLINE)
def _innovation(S, zo, po, W, wo, y, fc, ic, r):
    """For the ``r`` outputs present (indices in ``ic[o_iw:]``): the rows ``C_a P`` (``CP (q, N)`` at
    ``W[wo + 2 N^2:]``), the innovation ``nu`` and the lower triangle of ``C P C^T + R`` (``L``)."""
    N, q, nm, o_cptr, o_ccol, o_iw, o_cval, o_R = _output_header(ic)
    oPC = 2 * N * N
    oL = oPC + 4 * N * q + N + nm
    onu = oL + q * q
    P = S[po : po + N * N]
    CP = W[wo + oPC : wo + oPC + q * N]
    # Row a of C P (P symmetric: row m of P is column m), and nu.
    for a in range(r):
        h = ic[o_iw + a]
        CPa = CP[a * N : (a + 1) * N]
        for i in range(N):
            CPa[i] = 0.0
        s = y[h]
        for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
            m = ic[o_ccol + t]
            c = fc[o_cval + t]
            s -= c * S[zo + m]
            Pm = P[m * N : (m + 1) * N]
            for i in range(N):
                CPa[i] += c * Pm[i]
        W[wo + onu + a] = s
    for a in range(r):
        h = ic[o_iw + a]
        for b in range(a + 1):
            s = fc[o_R + h * q + ic[o_iw + b]]
            for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
                s += fc[o_cval + t] * CP[b * N + ic[o_ccol + t]]
            W[wo + oL + a * q + b] = s


@njit(**_INLINE)
def _gain(S, zo, W, wo, ic, r):
    """``K^T = (L L^T)^{-1} C P`` (``(q, N)`` at ``W[wo + 2 N^2 + N q:]``, the ``X C^T`` area as scratch)
    and ``z += K nu = (C P)^T w``; entry by entry the operations of a row-by-row solve, in its order."""
    N = ic[H_N]
    q = ic[H_Q]
    nm = ic[H_NM]
    oPC = 2 * N * N
    oK = oPC + N * q
    oY = oK + N * q
    ozt = oPC + 4 * N * q
    oL = ozt + N + nm
    ow = oL + q * q + q
    CP = W[wo + oPC : wo + oPC + q * N]
    Kt = W[wo + oK : wo + oK + q * N]
    Y = W[wo + oY : wo + oY + q * N]
    L = W[wo + oL : wo + oL + q * q]
    for a in range(r):  # forward: Y = L^{-1} C P
        Ya = Y[a * N : (a + 1) * N]
        CPa = CP[a * N : (a + 1) * N]
        for i in range(N):
            Ya[i] = CPa[i]
        for t in range(a):
            f = L[a * q + t]
            Yt = Y[t * N : (t + 1) * N]
            for i in range(N):
                Ya[i] -= f * Yt[i]
        d = L[a * q + a]
        for i in range(N):
            Ya[i] /= d
    for a in range(r - 1, -1, -1):  # back: K^T = L^{-T} Y
        Ka = Kt[a * N : (a + 1) * N]
        Ya = Y[a * N : (a + 1) * N]
        for i in range(N):
            Ka[i] = Ya[i]
        for t in range(a + 1, r):
            f = L[t * q + a]
            Kb = Kt[t * N : (t + 1) * N]
            for i in range(N):
                Ka[i] -= f * Kb[i]
        d = L[a * q + a]
        for i in range(N):
            Ka[i] /= d
    zt = W[wo + ozt : wo + ozt + N]
    for i in range(N):
        zt[i] = 0.0
    for a in range(r):
        f = W[wo + ow + a]
        CPa = CP[a * N : (a + 1) * N]
        for i in range(N):
            zt[i] += CPa[i] * f
    for i in range(N):
        S[zo + i] += zt[i]


@njit(**_INLINE)
def _joseph(S, po, W, wo, fc, ic, r):
    """``P <- X - (X C^T) K^T + K R K^T`` with ``X = P - K C P`` (``X`` in ``W[wo + N^2:]``), the upper
    triangle computed and mirrored; returns ``trace(P)``."""
    N, q, nm, o_cptr, o_ccol, o_iw, o_cval, o_R = _output_header(ic)
    oPC = 2 * N * N
    oK = oPC + N * q
    oXC = oK + N * q  # X C^T, K R: (N, q)
    oKR = oXC + N * q
    otmp = oKR + N * q + N + nm + q * q + 2 * q
    P = S[po : po + N * N]
    X = W[wo + N * N : wo + 2 * N * N]
    CP = W[wo + oPC : wo + oPC + q * N]
    Kt = W[wo + oK : wo + oK + q * N]
    for i in range(N):  # X = (I - K C) P = P - K (C P)
        Xi = X[i * N : (i + 1) * N]
        Pi = P[i * N : (i + 1) * N]
        for j in range(N):
            Xi[j] = Pi[j]
        for a in range(r):
            f = Kt[a * N + i]
            CPa = CP[a * N : (a + 1) * N]
            for j in range(N):
                Xi[j] -= f * CPa[j]
    for a in range(r):
        h = ic[o_iw + a]
        for i in range(N):
            s = 0.0
            for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
                s += X[i * N + ic[o_ccol + t]] * fc[o_cval + t]
            W[wo + oXC + i * q + a] = s
            s = 0.0
            for b in range(r):
                s += Kt[b * N + i] * fc[o_R + ic[o_iw + b] * q + h]
            W[wo + oKR + i * q + a] = s
    tr = 0.0
    for i in range(N):
        for a in range(r):
            W[wo + otmp + a] = W[wo + oKR + i * q + a] - W[wo + oXC + i * q + a]
        Pi = P[i * N + i : (i + 1) * N]
        Xi = X[i * N + i : (i + 1) * N]
        for j in range(N - i):
            Pi[j] = Xi[j]
        for a in range(r):
            f = W[wo + otmp + a]
            Ka = Kt[a * N + i : (a + 1) * N]
            for j in range(N - i):
                Pi[j] += f * Ka[j]
        for j in range(i + 1, N):
            P[j * N + i] = P[i * N + j]
        tr += P[i * N + i]
    return tr


@njit(**_OPTS)
def _correct(S, zo, po, so, W, wo, y, fc, ic):
    """The correction (module docstring): returns 0 (nothing present), 1 (corrected) or 2 (rejected by the gate)."""
    N = ic[H_N]
    q = ic[H_Q]
    nm = ic[H_NM]
    o_iw = ic[H_O_IW]
    r = 0
    for h in range(q):
        if not math.isnan(y[h]):
            ic[o_iw + r] = h
            r += 1
    if r == 0:
        S[so + 0] = math.nan
        return 0
    oL = 2 * N * N + 4 * N * q + N + nm  # L (q, q), then nu, w, tmp
    onu = oL + q * q
    ow = onu + q
    otmp = ow + q
    _innovation(S, zo, po, W, wo, y, fc, ic, r)
    nis = _cholesky_nis(W, wo + oL, wo + onu, wo + otmp, wo + ow, q, r)
    S[so + 0] = nis
    if nis > fc[1]:
        S[so + 2] += 1.0
        return 2
    _gain(S, zo, W, wo, ic, r)
    S[so + 3] = _joseph(S, po, W, wo, fc, ic, r)
    S[so + 1] += 1.0
    return 1


@njit(**_INLINE)
def _transition(W, wo, u, fc, ic):
    """``Phi(u)`` in ``W[wo:]``: only its aux-x block depends on ``u`` (``F0`` block plus ``sum_j u_j F1[j]``)."""
    N = ic[H_N]
    k = ic[H_K]
    p = ic[H_P]
    o_fblk = ic[H_O_FBLK]
    o_F1 = ic[H_O_F1]
    n = N - k
    for a in range(k):
        row = W[wo + a * N + k : wo + (a + 1) * N]  # slices indexed from 0: unit stride, vectorised
        f0 = fc[o_fblk + a * n : o_fblk + (a + 1) * n]
        for b in range(n):
            row[b] = f0[b]
        for j in range(p):
            uj = u[j]
            f1 = fc[o_F1 + (j * k + a) * n : o_F1 + (j * k + a + 1) * n]
            for b in range(n):
                row[b] += uj * f1[b]


@njit(**_INLINE)
def _input_term(W, wo, u, fc, ic):
    """``zt += g(u)``, ``g(u) = (u^T G2[., a, .] u, G0 u)``, ``zt`` at its place in ``W[wo:]``."""
    N = ic[H_N]
    k = ic[H_K]
    p = ic[H_P]
    q = ic[H_Q]
    o_G0 = ic[H_O_G0]
    o_G2 = ic[H_O_G2]
    ozt = 2 * N * N + 4 * N * q
    for a in range(k):
        s = 0.0
        for j in range(p):
            uj = u[j]
            for l in range(p):
                s += uj * fc[o_G2 + (j * k + a) * p + l] * u[l]
        W[wo + ozt + a] += s
    for b in range(N - k):
        s = 0.0
        for j in range(p):
            s += fc[o_G0 + b * p + j] * u[j]
        W[wo + ozt + k + b] += s


@njit(**_INLINE)
def _monomials(W, wo, u, ic):
    """``mono = (1, u_j, u_j u_l (j <= l))`` at its place in ``W[wo:]``; returns its offset there."""
    N = ic[H_N]
    p = ic[H_P]
    omono = 2 * N * N + 4 * N * ic[H_Q] + N
    W[wo + omono] = 1.0
    for j in range(p):
        W[wo + omono + 1 + j] = u[j]
    c = omono + 1 + p
    for j in range(p):
        for l in range(j, p):
            W[wo + c] = u[j] * u[l]
            c += 1
    return omono


@njit(**_INLINE)
def _products(S, po, W, wo, fc, ic):
    """``P <- Phi P Phi^T`` (upper triangle) by blocks, ``Phi = [[A, B], [0, E]]`` (``E = e^{A_x dt}``, ``(n, n)``, at ``fc[ic[H_O_E]:]``).

    ``T = Phi P`` as ``T[:k] = Phi[:k] P`` and ``T[k:] = E P[k:]``; then ``P[:k] = T[:k] Phi^T`` and
    the upper triangle of ``P[k:, k:] = T[k:, k:] E^T`` (three ``dgemm`` on contiguous views and
    ``n^3 / 2`` products): ``(2 k N^2 + n^2 N + n^3 / 2)`` multiply-adds instead of ``2 N^3``.
    """
    N = ic[H_N]
    k = ic[H_K]
    n = N - k
    NN = N * N
    o_e = ic[H_O_E]
    Phi = W[wo : wo + NN].reshape((N, N))
    P = S[po : po + NN].reshape((N, N))
    E = fc[o_e : o_e + n * n].reshape((n, n))
    T_top = W[wo + NN : wo + NN + k * N].reshape((k, N))
    T_bot = W[wo + NN + k * N : wo + 2 * NN].reshape((n, N))
    np.dot(Phi[:k], P, T_top)
    np.dot(E, P[k:], T_bot)
    np.dot(T_top, Phi.T, P[:k])
    for i in range(n):
        Ti = T_bot[i, k:]
        for j in range(i, n):
            Ej = E[j]
            s = 0.0
            for m in range(n):
                s += Ti[m] * Ej[m]
            P[k + i, k + j] = s


@njit(**_INLINE)
def _predict_dense(S, zo, po, so, W, wo, u, fc, ic):
    """The prediction with dense products (module docstring, "Two paths for the prediction").

    ``z <- Phi z + g(u)`` (``dgemv``), ``P <- Phi P Phi^T`` by blocks (:func:`_products`), then on
    the upper triangle ``P_ij <- growth P_ij + sum_r mono_r(u) Qc[r]_ij`` with ``Qc`` dense
    (``fc[ic[H_O_QC]:]``, ``(nm, N, N)``), mirrored, so that ``P`` is exactly symmetric.
    """
    N = ic[H_N]
    nm = ic[H_NM]
    o_qd = ic[H_O_QC]
    NN = N * N
    ozt = 2 * NN + 4 * N * ic[H_Q]
    _transition(W, wo, u, fc, ic)
    Phi = W[wo : wo + NN].reshape((N, N))
    P = S[po : po + NN].reshape((N, N))
    z = S[zo : zo + N]
    zt = W[wo + ozt : wo + ozt + N]
    Qc = fc[o_qd : o_qd + nm * NN]
    np.dot(Phi, z, zt)
    _input_term(W, wo, u, fc, ic)
    for i in range(N):
        z[i] = zt[i]
    _products(S, po, W, wo, fc, ic)
    omono = _monomials(W, wo, u, ic)
    growth = fc[0]
    tr = 0.0
    for i in range(N):
        Pi = P[i, i:]  # row slices, indexed from 0: unit stride, no negative-index wraparound
        for j in range(N - i):
            Pi[j] *= growth
        for r in range(nm):
            m = W[wo + omono + r]
            Qi = Qc[r * NN + i * N + i : (r * N + i + 1) * N]
            for j in range(N - i):
                Pi[j] += Qi[j] * m
        for j in range(i + 1, N):
            P[j, i] = P[i, j]
        tr += P[i, i]
    S[so + 3] = tr


@njit(**_OPTS)
def _predict_sparse(S, zo, po, so, W, wo, u, fc, ic):
    """The prediction through the structure of ``Phi`` (CSR) and of ``Q_d`` (COO), module docstring."""
    N = ic[H_N]
    q = ic[H_Q]
    nq = ic[H_NQ]
    o_pptr = ic[H_O_PHI_PTR]
    o_pcol = ic[H_O_PHI_COL]
    o_qi = ic[H_O_QI]
    o_qj = ic[H_O_QJ]
    o_qr = ic[H_O_QR]
    o_qv = ic[H_O_QV]
    growth = fc[0]
    oT = N * N  # Phi at 0, T at oT
    ozt = 2 * N * N + 4 * N * q
    _transition(W, wo, u, fc, ic)
    # z <- Phi z + g(u)
    for i in range(N):
        s = 0.0
        for t in range(ic[o_pptr + i], ic[o_pptr + i + 1]):
            m = ic[o_pcol + t]
            s += W[wo + i * N + m] * S[zo + m]
        W[wo + ozt + i] = s
    _input_term(W, wo, u, fc, ic)
    for i in range(N):
        S[zo + i] = W[wo + ozt + i]
    # T = Phi P: row i of T combines the rows of P picked by row i of Phi.
    for i in range(N):
        Ti = W[wo + oT + i * N : wo + oT + (i + 1) * N]  # slices indexed from 0: unit stride
        for j in range(N):
            Ti[j] = 0.0
        for t in range(ic[o_pptr + i], ic[o_pptr + i + 1]):
            m = ic[o_pcol + t]
            f = W[wo + i * N + m]
            Pm = S[po + m * N : po + (m + 1) * N]
            for j in range(N):
                Ti[j] += f * Pm[j]
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
    omono = _monomials(W, wo, u, ic)
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
    N = ic[H_N]
    return _correct(S, 0, N, S.shape[0] - 4, S, N + N * N, y, fc, ic)


@njit(**_OPTS)
def augmented_predict(u, S, fc, ic):
    """Exact prediction of ``S = [z | P | W]`` over one step with ``u`` held:
    ``z <- Phi(u) z + g(u)``, ``P <- e^{theta dt} Phi(u) P Phi(u)^T + Q_d(u)``."""
    N = ic[H_N]
    if ic[H_DENSE]:
        _predict_dense(S, 0, N, S.shape[0] - 4, S, N + N * N, u, fc, ic)
    else:
        _predict_sparse(S, 0, N, S.shape[0] - 4, S, N + N * N, u, fc, ic)


@njit(**_OPTS)
def _refused(u, y, ic):
    """Whether ``u (p,)`` holds a non-finite value or ``y (q,)`` an infinite one (NaN in ``y``: missing)."""
    for j in range(ic[H_P]):
        if not math.isfinite(u[j]):
            return True
    for h in range(ic[H_Q]):
        if math.isinf(y[h]):
            return True
    return False


@njit(**_OPTS)
def augmented_step(u, y, S, fc, ic):
    """:func:`augmented_correct` with ``y`` then :func:`augmented_predict` with ``u``; returns the correction
    code, or -1, changing nothing, when ``u`` holds a non-finite value or ``y`` an infinite one."""
    if _refused(u, y, ic):
        return -1
    N = ic[H_N]
    so = S.shape[0] - 4
    code = _correct(S, 0, N, so, S, N + N * N, y, fc, ic)
    if ic[H_DENSE]:
        _predict_dense(S, 0, N, so, S, N + N * N, u, fc, ic)
    else:
        _predict_sparse(S, 0, N, so, S, N + N * N, u, fc, ic)
    return code


@njit(**_OPTS)
def batch_refused(U, Y, ic):
    """The first member ``b`` whose ``U[b]`` holds a non-finite value or ``Y[b]`` an infinite one
    (NaN in ``Y``: missing), else -1."""
    p = ic[H_P]
    q = ic[H_Q]
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
    N = ic[H_N]
    so = SB.shape[1] - 4
    for b in range(SB.shape[0]):
        Sb = SB[b]
        _correct(Sb, 0, N, so, W, 0, Y[b], fc, ic)
        if ic[H_DENSE]:
            _predict_dense(Sb, 0, N, so, W, 0, U[b], fc, ic)
        else:
            _predict_sparse(Sb, 0, N, so, W, 0, U[b], fc, ic)
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
    N = ic[H_N]
    k = ic[H_K]
    if _refused(u, y, ic):
        return -1
    so = S.shape[0] - 4
    for i in range(N - k):
        out[i] = S[k + i]
    out[N - k] = S[so + 3]
    code = _correct(S, 0, N, so, S, N + N * N, y, fc, ic)
    if ic[H_DENSE]:
        _predict_dense(S, 0, N, so, S, N + N * N, u, fc, ic)
    else:
        _predict_sparse(S, 0, N, so, S, N + N * N, u, fc, ic)
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
        row[o_u + i] = (
            row[o_acc + i] + accel_std * draws[j, oa + i] if accel_std != 0.0 else row[o_acc + i]
        )
