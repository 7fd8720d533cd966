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
``W`` (float64 work, :func:`work_layout`, :func:`work_size`)
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
from collections import namedtuple
from typing import Any

import numpy as np
from numba import njit

__all__ = [
    "DENSE_MIN_FILL",
    "DENSE_MIN_WORK",
    "HEADER",
    "WorkLayout",
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
    "work_layout",
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


#: The offsets of the parts of the work buffer ``W`` (module docstring); ``Phi`` is at 0.
WorkLayout = namedtuple("WorkLayout", "T CP Kt XC KR zt mono L nu w tmp stats")


def work_layout(N: int, q: int, nm: int) -> WorkLayout:
    """Where each part of ``W`` starts, for ``N`` states, ``q`` outputs and ``nm`` monomials.

    ``Phi, T (N * N)``, ``C P, K^T, X C^T, K R (q N)``, ``zt (N)``, ``mono (nm)``, ``L (q * q)``,
    ``nu, w, tmp (q)``, ``stats (4)``, one after the other: the one statement of the layout, read by
    :func:`work_size` and, compiled, by every kernel.
    """
    T = N * N
    CP = T + N * N
    Kt = CP + q * N
    XC = Kt + q * N
    KR = XC + N * q
    zt = KR + N * q
    mono = zt + N
    L = mono + nm
    nu = L + q * q
    w = nu + q
    tmp = w + q
    return WorkLayout(T, CP, Kt, XC, KR, zt, mono, L, nu, w, tmp, tmp + q)


def work_size(N: int, q: int, nm: int) -> int:
    """Length of the work buffer ``W`` (stats included) for ``N`` states, ``q`` outputs, ``nm`` monomials."""
    return work_layout(N, q, nm).stats + 4


_work_layout = njit(**_INLINE)(work_layout)


@njit(**_INLINE)
def _layout(ic):
    """:func:`work_layout` of the observer described by the header of ``ic``."""
    return _work_layout(ic[H_N], ic[H_Q], ic[H_NM])


# -- row operations (inlined: the loops LLVM sees are those written out in place) -------------


@njit(**_INLINE)
def _row(A, i, n):
    """Row ``i`` of a row-major matrix of ``n`` columns held flat in ``A``: a slice indexed from 0."""
    return A[i * n : (i + 1) * n]


@njit(**_INLINE)
def _fill(x, value, n):
    """``x[:n] = value``."""
    for i in range(n):
        x[i] = value


@njit(**_INLINE)
def _copy(x, y, n):
    """``x[:n] = y[:n]``."""
    for i in range(n):
        x[i] = y[i]


@njit(**_INLINE)
def _add_scaled(x, f, y, n):
    """``x[:n] += f y[:n]``."""
    for i in range(n):
        x[i] += f * y[i]


@njit(**_INLINE)
def _sub_scaled(x, f, y, n):
    """``x[:n] -= f y[:n]``."""
    for i in range(n):
        x[i] -= f * y[i]


@njit(**_INLINE)
def _divide(x, d, n):
    """``x[:n] /= d``."""
    for i in range(n):
        x[i] /= d


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
    """The fields of the header that the correction reads: ``N, q`` and the offsets of ``C`` (CSR
    pointers, columns, values), of the indices of the outputs present and of ``R``."""
    return (
        ic[H_N],
        ic[H_Q],
        ic[H_O_C_PTR],
        ic[H_O_C_COL],
        ic[H_O_IW],
        ic[H_O_CVAL],
        ic[H_O_R],
    )


@njit(**_INLINE)
def _innovation(S, zo, po, W, wo, y, fc, ic, r):
    """For the ``r`` outputs present (indices in ``ic[o_iw:]``): the rows ``C_a P`` (``CP (q, N)``),
    the innovation ``nu`` and the lower triangle of ``C P C^T + R`` (``L``), in ``W[wo:]``."""
    N, q, o_cptr, o_ccol, o_iw, o_cval, o_R = _output_header(ic)
    lay = _layout(ic)
    P = S[po : po + N * N]
    CP = W[wo + lay.CP : wo + lay.CP + q * N]
    # Row a of C P (P symmetric: row m of P is column m), and nu.
    for a in range(r):
        h = ic[o_iw + a]
        CPa = _row(CP, a, N)
        _fill(CPa, 0.0, N)
        s = y[h]
        for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
            m = ic[o_ccol + t]
            c = fc[o_cval + t]
            s -= c * S[zo + m]
            _add_scaled(CPa, c, _row(P, m, N), N)
        W[wo + lay.nu + a] = s
    for a in range(r):
        h = ic[o_iw + a]
        for b in range(a + 1):
            s = fc[o_R + h * q + ic[o_iw + b]]
            for t in range(ic[o_cptr + h], ic[o_cptr + h + 1]):
                s += fc[o_cval + t] * CP[b * N + ic[o_ccol + t]]
            W[wo + lay.L + a * q + b] = s


@njit(**_INLINE)
def _gain(S, zo, W, wo, ic, r):
    """``K^T = (L L^T)^{-1} C P`` (``(q, N)``, the ``X C^T`` area as scratch) and
    ``z += K nu = (C P)^T w``; entry by entry the operations of a row-by-row solve, in its order."""
    N = ic[H_N]
    q = ic[H_Q]
    lay = _layout(ic)
    CP = W[wo + lay.CP : wo + lay.CP + q * N]
    Kt = W[wo + lay.Kt : wo + lay.Kt + q * N]
    Y = W[wo + lay.XC : wo + lay.XC + q * N]
    L = W[wo + lay.L : wo + lay.L + q * q]
    for a in range(r):  # forward: Y = L^{-1} C P
        Ya = _row(Y, a, N)
        _copy(Ya, _row(CP, a, N), N)
        for t in range(a):
            _sub_scaled(Ya, L[a * q + t], _row(Y, t, N), N)
        _divide(Ya, L[a * q + a], N)
    for a in range(r - 1, -1, -1):  # back: K^T = L^{-T} Y
        Ka = _row(Kt, a, N)
        _copy(Ka, _row(Y, a, N), N)
        for t in range(a + 1, r):
            _sub_scaled(Ka, L[t * q + a], _row(Kt, t, N), N)
        _divide(Ka, L[a * q + a], N)
    zt = W[wo + lay.zt : wo + lay.zt + N]
    _fill(zt, 0.0, N)
    for a in range(r):
        _add_scaled(zt, W[wo + lay.w + a], _row(CP, a, N), N)
    for i in range(N):
        S[zo + i] += zt[i]


@njit(**_INLINE)
def _mirror(P, N, i):
    """Row ``i`` of the upper triangle of ``P (N, N)`` (flat) copied into column ``i`` below the diagonal."""
    for j in range(i + 1, N):
        P[j * N + i] = P[i * N + j]


@njit(**_INLINE)
def _joseph(S, po, W, wo, fc, ic, r):
    """``P <- X - (X C^T) K^T + K R K^T`` with ``X = P - K C P`` (``X`` in the ``T`` area of ``W[wo:]``),
    the upper triangle computed and mirrored; returns ``trace(P)``."""
    N, q, o_cptr, o_ccol, o_iw, o_cval, o_R = _output_header(ic)
    lay = _layout(ic)
    oXC = lay.XC  # X C^T, K R: (N, q)
    oKR = lay.KR
    otmp = lay.tmp
    P = S[po : po + N * N]
    X = W[wo + lay.T : wo + lay.T + N * N]
    CP = W[wo + lay.CP : wo + lay.CP + q * N]
    Kt = W[wo + lay.Kt : wo + lay.Kt + q * N]
    for i in range(N):  # X = (I - K C) P = P - K (C P)
        Xi = _row(X, i, N)
        _copy(Xi, _row(P, i, N), N)
        for a in range(r):
            _sub_scaled(Xi, Kt[a * N + i], _row(CP, a, N), N)
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
        _copy(Pi, X[i * N + i : (i + 1) * N], N - i)
        for a in range(r):
            _add_scaled(Pi, W[wo + otmp + a], Kt[a * N + i : (a + 1) * N], N - i)
        _mirror(P, N, i)
        tr += P[i * N + i]
    return tr


@njit(**_OPTS)
def _correct(S, zo, po, so, W, wo, y, fc, ic):
    """The correction (module docstring): returns 0 (nothing present), 1 (corrected) or 2 (rejected by the gate)."""
    q = ic[H_Q]
    o_iw = ic[H_O_IW]
    r = 0
    for h in range(q):
        if not math.isnan(y[h]):
            ic[o_iw + r] = h
            r += 1
    if r == 0:
        S[so + 0] = math.nan
        return 0
    lay = _layout(ic)
    _innovation(S, zo, po, W, wo, y, fc, ic, r)
    nis = _cholesky_nis(W, wo + lay.L, wo + lay.nu, wo + lay.tmp, wo + lay.w, q, r)
    S[so + 0] = nis
    if nis > fc[1]:
        S[so + 2] += 1.0
        return 2
    _gain(S, zo, W, wo, ic, r)
    S[so + 3] = _joseph(S, po, W, wo, fc, ic, r)
    S[so + 1] += 1.0
    return 1


@njit(**_INLINE)
def _input_header(ic):
    """The fields of the header that the input terms of the prediction read: ``N, k, p`` and the
    offsets of the aux-x block of ``F0``, of ``F1``, ``G0`` and ``G2``."""
    return (ic[H_N], ic[H_K], ic[H_P], ic[H_O_FBLK], ic[H_O_F1], ic[H_O_G0], ic[H_O_G2])


@njit(**_INLINE)
def _transition(W, wo, u, fc, ic):
    """``Phi(u)`` in ``W[wo:]``: only its aux-x block depends on ``u`` (``F0`` block plus ``sum_j u_j F1[j]``)."""
    N, k, p, o_fblk, o_F1, _, _ = _input_header(ic)
    n = N - k
    for a in range(k):
        row = W[wo + a * N + k : wo + (a + 1) * N]  # slices indexed from 0: unit stride, vectorised
        _copy(row, fc[o_fblk + a * n : o_fblk + (a + 1) * n], n)
        for j in range(p):
            _add_scaled(row, u[j], fc[o_F1 + (j * k + a) * n : o_F1 + (j * k + a + 1) * n], n)


@njit(**_INLINE)
def _input_term(W, wo, u, fc, ic):
    """``zt += g(u)``, ``g(u) = (u^T G2[., a, .] u, G0 u)``, ``zt`` at its place in ``W[wo:]``."""
    N, k, p, _, _, o_G0, o_G2 = _input_header(ic)
    ozt = _layout(ic).zt
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
    p = ic[H_P]
    omono = _layout(ic).mono
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
    oT = wo + _layout(ic).T
    Phi = W[wo : wo + NN].reshape((N, N))
    P = S[po : po + NN].reshape((N, N))
    E = fc[o_e : o_e + n * n].reshape((n, n))
    T_top = W[oT : oT + k * N].reshape((k, N))
    T_bot = W[oT + k * N : oT + NN].reshape((n, N))
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
    ozt = _layout(ic).zt
    _transition(W, wo, u, fc, ic)
    Phi = W[wo : wo + NN].reshape((N, N))
    z = S[zo : zo + N]
    zt = W[wo + ozt : wo + ozt + N]
    Qc = fc[o_qd : o_qd + nm * NN]
    np.dot(Phi, z, zt)
    _input_term(W, wo, u, fc, ic)
    _copy(z, zt, N)
    _products(S, po, W, wo, fc, ic)
    omono = _monomials(W, wo, u, ic)
    growth = fc[0]
    P = S[po : po + NN]
    tr = 0.0
    for i in range(N):
        Pi = P[i * N + i : (i + 1) * N]  # row slices, indexed from 0: unit stride, no wraparound
        for j in range(N - i):
            Pi[j] *= growth
        for r in range(nm):
            _add_scaled(Pi, W[wo + omono + r], Qc[r * NN + i * N + i : (r * N + i + 1) * N], N - i)
        _mirror(P, N, i)
        tr += P[i * N + i]
    S[so + 3] = tr


@njit(**_OPTS)
def _predict_sparse(S, zo, po, so, W, wo, u, fc, ic):
    """The prediction through the structure of ``Phi`` (CSR) and of ``Q_d`` (COO), module docstring."""
    N = ic[H_N]
    nq = ic[H_NQ]
    o_pptr = ic[H_O_PHI_PTR]
    o_pcol = ic[H_O_PHI_COL]
    o_qi = ic[H_O_QI]
    o_qj = ic[H_O_QJ]
    o_qr = ic[H_O_QR]
    o_qv = ic[H_O_QV]
    growth = fc[0]
    lay = _layout(ic)
    oT = lay.T
    ozt = lay.zt
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
        _fill(Ti, 0.0, N)
        for t in range(ic[o_pptr + i], ic[o_pptr + i + 1]):
            m = ic[o_pcol + t]
            _add_scaled(Ti, W[wo + i * N + m], S[po + m * N : po + (m + 1) * N], N)
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


@njit(**_INLINE)
def _predict(S, zo, po, so, W, wo, u, fc, ic):
    """The prediction on the path the model takes (``ic[H_DENSE]``, :func:`dense_path`)."""
    if ic[H_DENSE]:
        _predict_dense(S, zo, po, so, W, wo, u, fc, ic)
    else:
        _predict_sparse(S, zo, po, so, W, wo, u, fc, ic)


@njit(**_INLINE)
def _step(S, zo, po, so, W, wo, u, y, fc, ic):
    """:func:`_correct` with ``y`` then :func:`_predict` with ``u``; returns the correction code."""
    code = _correct(S, zo, po, so, W, wo, y, fc, ic)
    _predict(S, zo, po, so, W, wo, u, fc, ic)
    return code


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
    _predict(S, 0, N, S.shape[0] - 4, S, N + N * N, u, fc, ic)


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
    return _step(S, 0, N, S.shape[0] - 4, S, N + N * N, u, y, fc, ic)


@njit(**_OPTS)
def batch_refused(U, Y, ic):
    """The first member ``b`` whose ``U[b]`` holds a non-finite value or ``Y[b]`` an infinite one
    (NaN in ``Y``: missing), else -1."""
    for b in range(U.shape[0]):
        if _refused(U[b], Y[b], ic):
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
        _step(SB[b], 0, N, so, W, 0, U[b], Y[b], fc, ic)
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
    code = _step(S, 0, N, so, S, N + N * N, u, y, fc, ic)
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
