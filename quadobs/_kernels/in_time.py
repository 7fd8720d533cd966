"""Compiled (Numba) kernels of the augmented observer's interface in time.

The observer of [IFAC2021, Thm. 3] fed one measurement at its own time does two things per
measurement: the exact prediction over the interval since the last one (the input held) and
the correction by one scalar output. Both kernels here work in place on ``z`` and ``P`` and on
work arrays allocated once per observer; neither allocates.

**Prediction over ``dt``** (:func:`interval_predict`). For ``z' = A(u) z + B u`` with ``A(u)``
nilpotent (``A^m = 0``: the augmented double integrator and odometry models, whose state
graph has no cycle), both exponentials of the interval are finite sums of the powers
``F_i = (A dt)^i / i!``:

.. math::

    \\Phi = \\sum_{i \\ge 0} F_i, \\qquad g = \\sum_{i \\ge 1} F_{i-1} B u\\, dt / i,

and Van Loan's block ``exp([[-A, V], [0, A^T]] dt)`` has the terms ``[[X_i, Y_i], [0, Z_i]]``
with ``X_i = (-1)^i F_i``, ``Z_i = F_i^T`` and

.. math::

    Y_i = \\left(X_{i-1} V dt + Y_{i-1} (A dt)^\\top\\right) / i, \\qquad
    Q_d = \\Phi \\sum_{i \\ge 1} Y_i,

the same series as :func:`quadobs.core.held_input.van_loan_interval` takes through
:func:`~quadobs.core.held_input.expm_exact`, block by block: the zero blocks are never
multiplied and ``A`` is multiplied through its nonzeros only (CSR). The series stops at the
first term that is exactly zero. Then ``z <- Phi z + g`` and
``P <- (M + M^T) / 2`` with ``M = Phi P Phi^T + (Q_d + Q_d^T) / 2``. The sums run in another
order than the reference's products, so the two agree to rounding, not bit for bit (about
``1e-13`` relative over 2000 steps of ``quadrotor-uwb``, tested to ``1e-12`` per interval).

**Correction by one scalar output** (:func:`scalar_correct`). For ``y_h = c^T z + e``,
``var e = r``, the Joseph form ``P+ = (I - k c^T) P (I - k c^T)^T + r k k^T`` with
``k = P c / s``, ``s = c^T P c + r``, as its two factors for a symmetric ``P``:

.. math::

    W = P (I - k c^\\top)^\\top = P - (P c) k^\\top, \\qquad
    P^+ = (I - k c^\\top) W + r k k^\\top = W - k (c^\\top W) + r k k^\\top ,

``O(N^2)`` where the matrix products cost ``O(N^3)`` (``W`` is formed entry by entry, only
``c^T W`` is kept). Expanded, this is ``P - k (P c)^T - (P c) k^T + s k k^T``, but that sum
cancels ``P``'s large terms against each other and can leave a direction's variance at zero
or below where the noise ``r`` is far below ``P``'s; the factored form keeps ``r k k^T`` apart
and the result positive semi-definite, as the Joseph form is meant to. The lower triangle is
formed and mirrored, so that ``P`` stays exactly symmetric; a NIS that is not a number (a
zero or non-finite innovation variance) is rejected as one above the gate.
"""

from __future__ import annotations

from numba import njit

__all__ = ["interval_predict", "scalar_correct", "state_noise"]


@njit(cache=True, nogil=True, error_model="numpy")
def state_noise(z, L, Vx, extra, V, J, JV):
    """``V = (J (V_x + E) J^T + (.)^T) / 2`` with ``J = [x^T L_1; ...; x^T L_k; I_n]`` at ``z = (xi, x)``.

    Parameters
    ----------
    z : ndarray (N,)
    L : ndarray (k, n, n)
        The auxiliary states' symmetric forms ``xi_i = x^T L_i x / 2``.
    Vx, extra : ndarray (n, n)
        The noise intensity on ``x'`` and a term added to it (zeros where none).
    V : ndarray (N, N)
        Receives the augmented noise intensity.
    J, JV : ndarray (N, n)
        Work arrays.
    """
    k, n = L.shape[0], L.shape[1]
    N = k + n
    for i in range(k):
        for a in range(n):
            acc = 0.0
            for b in range(n):
                acc += L[i, a, b] * z[k + b]
            J[i, a] = acc
    for i in range(n):
        for a in range(n):
            J[k + i, a] = 1.0 if i == a else 0.0
    for i in range(N):
        for b in range(n):
            acc = 0.0
            for a in range(n):
                acc += J[i, a] * (Vx[a, b] + extra[a, b])
            JV[i, b] = acc
    for i in range(N):
        for j in range(i + 1):
            acc = 0.0
            for a in range(n):
                acc += JV[i, a] * J[j, a]
            V[i, j] = acc
    for i in range(N):  # J (V_x + E) J^T is symmetric in exact arithmetic: the two halves averaged
        for j in range(i):
            acc = 0.0
            for a in range(n):
                acc += JV[j, a] * J[i, a]
            V[j, i] = acc
    for i in range(N):
        for j in range(i):
            s = 0.5 * (V[i, j] + V[j, i])
            V[i, j] = s
            V[j, i] = s


@njit(cache=True, nogil=True, error_model="numpy")
def _sparse_times(F, Adt, ptr, col, out, scale):
    """``out = (F A dt) / scale`` with ``A dt`` through its structural nonzeros (row ``c``:
    ``col[ptr[c]:ptr[c+1]]``); returns whether ``out`` has a nonzero entry."""
    N = F.shape[0]
    nonzero = False
    for a in range(N):
        for b in range(N):
            out[a, b] = 0.0
        for c in range(N):
            f = F[a, c]
            if f != 0.0:
                for idx in range(ptr[c], ptr[c + 1]):
                    b = col[idx]
                    out[a, b] += f * Adt[c, b]
        for b in range(N):
            x = out[a, b] / scale
            out[a, b] = x
            if x != 0.0:
                nonzero = True
    return nonzero


@njit(cache=True, nogil=True, error_model="numpy")
def _van_loan_term(F, sign, Vdt, Y, Adt, ptr, col, out, scale):
    """``out = (sign F V dt + Y (A dt)^T) / scale``; returns whether it has a nonzero entry."""
    N = F.shape[0]
    nonzero = False
    for a in range(N):
        for b in range(N):
            out[a, b] = 0.0
        for c in range(N):
            f = F[a, c]
            if f != 0.0:
                f = sign * f
                for b in range(N):
                    out[a, b] += f * Vdt[c, b]
        for b in range(N):
            acc = out[a, b]
            for idx in range(ptr[b], ptr[b + 1]):
                acc += Y[a, col[idx]] * Adt[b, col[idx]]
            x = acc / scale
            out[a, b] = x
            if x != 0.0:
                nonzero = True
    return nonzero


@njit(cache=True, nogil=True, error_model="numpy")
def interval_predict(z, P, u, dt, A0, Au, Bz, ptr, col, V, W, w, stats):
    """The exact prediction of ``z`` and ``P`` over ``dt`` with ``u`` held (module docstring).

    Parameters
    ----------
    z : ndarray (N,)
    P : ndarray (N, N)
        Updated in place (only when the function returns ``True``).
    u : ndarray (p,)
    dt : float
    A0, Au : ndarray (N, N), (p, N, N)
        ``A(u) = A0 + sum_j u_j Au[j]``.
    Bz : ndarray (N, p)
    ptr, col : ndarray of int64
        The structural nonzeros of ``A(u)`` for every ``u`` (CSR: the union of the patterns).
    V : ndarray (N, N)
        The process-noise intensity over the interval.
    W : ndarray (8, N, N), w : ndarray (3, N)
        Work arrays.
    stats : ndarray (4,)
        Its last entry receives ``trace P`` (with the prediction).

    Returns
    -------
    bool
        ``True`` when a term of Van Loan's series was exactly zero within ``2 N`` terms (the
        prediction is done); ``False`` otherwise (``z`` and ``P`` unchanged: the caller takes
        the general exponential).
    """
    Adt, F, Fn, Y, Yn, Phi, E12, Vdt = W[0], W[1], W[2], W[3], W[4], W[5], W[6], W[7]
    b, g, zt = w[0], w[1], w[2]
    _interval_operands(u, dt, A0, Au, Bz, ptr, col, V, Adt, Vdt, b)
    if not _series(Adt, Vdt, b, ptr, col, F, Fn, Y, Yn, Phi, E12, g):
        return False
    _transition(z, P, Phi, g, E12, W[1], W[2], W[3], zt, stats)
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _interval_operands(u, dt, A0, Au, Bz, ptr, col, V, Adt, Vdt, b):
    """``A(u) dt`` on its structural nonzeros (zero elsewhere), ``V dt`` and ``b = B u dt``."""
    N, p = A0.shape[0], Au.shape[0]
    for r in range(N):
        for c in range(N):
            Adt[r, c] = 0.0
            Vdt[r, c] = V[r, c] * dt
        for idx in range(ptr[r], ptr[r + 1]):
            c = col[idx]
            acc = 0.0
            for j in range(p):
                acc += u[j] * Au[j, r, c]
            Adt[r, c] = (A0[r, c] + acc) * dt
        acc = 0.0
        for j in range(p):
            acc += Bz[r, j] * u[j]
        b[r] = acc * dt


@njit(cache=True, nogil=True, error_model="numpy")
def _series(Adt, Vdt, b, ptr, col, F, Fn, Y, Yn, Phi, E12, g):
    """``Phi``, ``g`` and ``E12 = sum_i Y_i`` (module docstring) until a term is exactly zero;
    returns whether one was within ``2 N`` terms. ``F, Fn, Y, Yn``: work arrays."""
    N = Adt.shape[0]
    for r in range(N):
        g[r] = 0.0
        for c in range(N):
            one = 1.0 if r == c else 0.0
            F[r, c] = one
            Phi[r, c] = one
            Y[r, c] = 0.0
            E12[r, c] = 0.0
    f_nonzero = True  # F_(i-1) != 0: once a power of A dt is zero, so are the later ones
    sign = 1.0  # (-1)^(i-1): X_(i-1) = sign F_(i-1)
    for i in range(1, 2 * N + 1):
        fi = float(i)
        if f_nonzero:
            for a in range(N):  # g += F_(i-1) b / i
                acc = 0.0
                for c in range(N):
                    acc += F[a, c] * b[c]
                g[a] += acc / fi
        y_nonzero = _van_loan_term(F, sign, Vdt, Y, Adt, ptr, col, Yn, fi)
        if f_nonzero:
            f_nonzero = _sparse_times(F, Adt, ptr, col, Fn, fi)
            for a in range(N):
                for c in range(N):
                    Phi[a, c] += Fn[a, c]
            F, Fn = Fn, F  # the new power becomes the current one (buffers swapped, not copied)
        for a in range(N):
            for c in range(N):
                E12[a, c] += Yn[a, c]
        Y, Yn = Yn, Y
        sign = -sign
        if not (y_nonzero or f_nonzero):
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _transition(z, P, Phi, g, E12, Q, T, M, zt, stats):
    """``z <- Phi z + g``; ``P <- (M + M^T) / 2``, ``M = Phi P Phi^T + (Q + Q^T) / 2``,
    ``Q = Phi E12``; ``stats[3] = trace P``. ``Q, T, M, zt``: work arrays."""
    N = z.shape[0]
    for a in range(N):
        acc = 0.0
        for c in range(N):
            acc += Phi[a, c] * z[c]
        zt[a] = acc + g[a]
    for a in range(N):
        z[a] = zt[a]
    for a in range(N):  # Q = Phi E12, T = Phi P (Phi's zeros skipped)
        for c in range(N):
            Q[a, c] = 0.0
            T[a, c] = 0.0
        for m in range(N):
            f = Phi[a, m]
            if f != 0.0:
                for c in range(N):
                    Q[a, c] += f * E12[m, c]
                    T[a, c] += f * P[m, c]
    for a in range(N):
        for c in range(N):
            acc = 0.0
            for m in range(N):
                acc += T[a, m] * Phi[c, m]
            M[a, c] = acc + 0.5 * (Q[a, c] + Q[c, a])
    trace = 0.0
    for a in range(N):
        for c in range(N):
            P[a, c] = 0.5 * (M[a, c] + M[c, a])
        trace += P[a, a]
    stats[3] = trace


@njit(cache=True, nogil=True, error_model="numpy")
def scalar_correct(z, P, C, h, yh, r, gate, stats, work):
    """The Joseph-form correction of ``z`` and ``P`` by the output ``y_h = C[h] z`` of variance ``r``.

    ``O(N^2)`` (module docstring). ``stats = [nis, corrections, rejected, trace P]`` is updated
    as by the compiled grid step: the NIS always, then either the rejection (NIS above
    ``gate``: nothing else changes) or the correction, its count and the trace.

    Parameters
    ----------
    z : ndarray (N,)
    P : ndarray (N, N)
        Symmetric; updated in place.
    C : ndarray (q, N)
    h : int
    yh, r, gate : float
        The output, its variance, the NIS gate (``inf``: none).
    stats : ndarray (4,)
    work : ndarray (2, N)
        Work array: ``P c`` and ``c^T W``.
    """
    N = z.shape[0]
    Pc = work[0]
    cW = work[1]
    s = 0.0
    cz = 0.0
    for i in range(N):
        acc = 0.0
        for j in range(N):
            cj = C[h, j]
            if cj != 0.0:
                acc += P[i, j] * cj
        Pc[i] = acc
    for i in range(N):
        ci = C[h, i]
        if ci != 0.0:
            s += ci * Pc[i]
            cz += ci * z[i]
    s = s + r
    nu = yh - cz
    nis = nu * nu / s
    stats[0] = nis
    if not nis <= gate:  # above the gate, or not a number
        stats[2] += 1.0
        return
    for j in range(N):  # (c^T W)_j = sum_i c_i (P_ij - Pc_i k_j)
        kj = Pc[j] / s
        acc = 0.0
        for i in range(N):
            ci = C[h, i]
            if ci != 0.0:
                acc += ci * (P[i, j] - Pc[i] * kj)
        cW[j] = acc
    for i in range(N):
        z[i] += Pc[i] / s * nu
    trace = 0.0
    for i in range(N):
        ki = Pc[i] / s
        for j in range(i + 1):
            kj = Pc[j] / s
            v = ((P[i, j] - Pc[i] * kj) - ki * cW[j]) + r * (ki * kj)
            P[i, j] = v
            P[j, i] = v
        trace += P[i, i]
    stats[1] += 1.0
    stats[3] = trace
