"""Compiled (Numba) transition and Gramian of a run of held steps, for the excitation monitor.

Imported lazily by :class:`quadobs.observability.excitation.ExcitationMonitor`; without Numba the
monitor uses the NumPy path (:meth:`quadobs.observability.gramian.GramianModel.step_terms` and
:func:`quadobs.observability.gramian.reduce_window`), which computes the same quantities.
"""

from __future__ import annotations

from numba import njit

__all__ = ["held_run_terms"]


@njit(cache=True, nogil=True, error_model="numpy")
def _product(A, B, out, accumulate):
    """``out = A B`` (``accumulate``: ``out += A B``) for square ``(N, N)`` operands, ``out`` distinct from both."""
    N = out.shape[0]
    for a in range(N):
        for b in range(N):
            s = out[a, b] if accumulate else 0.0
            for c in range(N):
                s += A[a, c] * B[c, b]
            out[a, b] = s


@njit(cache=True, nogil=True, error_model="numpy")
def held_run_terms(U, F0, F1, G0, G1, G2, P, W, Phi, G, T):
    """``(Phi, W)`` over consecutive held steps ``U (T, p)``, composed in time order.

    Step ``t`` has the transition ``Phi_t = F0 + E(sum_j u_j F1[j])`` (``F1 (p, k, N - k)``
    written into the aux-x block ``[:k, k:]``, :class:`quadobs.core.held_input.HeldInputDiscretization`)
    and the Gramian ``G_t = G0 + sum_j u_j G1[j] + sum_jl u_j u_l G2[j, l]``
    (:class:`quadobs.observability.gramian.GramianModel`). With ``P_0 = I``, ``W_0 = 0``:

    ``W_(t+1) = W_t + P_t^T G_t P_t``, ``P_(t+1) = Phi_t P_t``

    (:func:`quadobs.observability.gramian.compose` applied step by step). Writes ``P (N, N)`` and
    ``W (N, N)``; ``Phi``, ``G``, ``T`` are ``(N, N)`` work arrays.
    """
    N = F0.shape[0]
    k = F1.shape[1]
    p = U.shape[1]
    for a in range(N):  # element loops rather than slice assignments, which compile Numba's
        for b in range(N):  # broadcasting and its error messages (seconds on a first run)
            P[a, b] = 1.0 if a == b else 0.0
            W[a, b] = 0.0
    for t in range(U.shape[0]):
        for a in range(N):
            for b in range(N):
                Phi[a, b] = F0[a, b]
                G[a, b] = G0[a, b]
        for j in range(p):
            uj = U[t, j]
            for a in range(k):
                for b in range(N - k):
                    Phi[a, k + b] += uj * F1[j, a, b]
            for a in range(N):
                for b in range(N):
                    G[a, b] += uj * G1[j, a, b]
            for l in range(p):
                ujl = uj * U[t, l]
                for a in range(N):
                    for b in range(N):
                        G[a, b] += ujl * G2[j, l, a, b]
        _product(G, P, T, False)  # T = G P
        _product(P.T, T, W, True)  # W += P^T G P
        _product(Phi, P, T, False)  # T = Phi P
        for a in range(N):
            for b in range(N):
                P[a, b] = T[a, b]
