"""The observability Gramian of the augmented system under a held input.

For ``z' = A(u(t)) z``, ``y = C z`` ([IFAC2021] eqs. 14-17, or the
multi-output immersion of [ACC2024] slide eqs. 12-14) the Gramian of
Theorem 1 over a window is (eq. 27 in block form)

.. math::

    W(t, t + \\delta) = \\int_t^{t+\\delta} \\Phi(s, t)^\\top \\mathcal C^\\top \\mathcal C\\, \\Phi(s, t)\\, ds,

and the pair ``(A(u), C)`` is uniformly observable (Definition 2, eq. 2) when
``W(t, t + delta) >= mu I`` for every ``t``. The measure of excitation of a window is
``mu = lambda_min(W)``.

Method
------
The input is a sequence of samples ``u_k`` held over ``[t_k, t_k + h)`` (a recorded
accelerometer, or the mean commanded acceleration over each step of an analytic
reference). On such a step ``A(u)`` is constant and block upper triangular,
``[[M, U(u_k)], [0, A]]`` (eq. 20; ``M = S_m`` for the chain, the general auxiliary
dynamics for Algorithm 1), so the transition is given in closed form by the blocks of
eqs. 22, 26a-c: ``Phi_11 = e^{M h}``, ``Phi_22 = e^{A h}`` and ``Phi_12`` the integral of
eq. 26c, which is linear in ``u_k`` (:meth:`quadobs.core.held_input.HeldInputDiscretization.transition`).
Transitions over longer intervals are products of these; no Peano-Baker series is
needed. The integral of eq. 27 over one step,

.. math::

    G(u_k) = \\int_0^h e^{A(u_k)^\\top s} \\mathcal C^\\top \\mathcal C e^{A(u_k) s} ds,

is a quadratic polynomial in ``u_k`` (``C Phi(s)`` is affine in ``u_k``); its
coefficients are computed once from Van Loan's block exponential at ``u = 0, +-e_j,
e_j + e_l``. Over consecutive steps the window Gramian composes exactly:

.. math::

    W_{[a, c)} = W_{[a, b)} + \\Phi(b, a)^\\top W_{[b, c)} \\Phi(b, a), \\qquad
    \\Phi(c, a) = \\Phi(c, b) \\Phi(b, a).

So ``W`` is exact (to rounding) for the held input: there is no quadrature error. For
an input that varies within a step, the only approximation is the hold itself, whose
error is ``O(h)`` in ``Phi_12`` for an arbitrary sample and ``O(h^2)`` when ``u_k`` is
the mean of ``u`` over the step (what :func:`quadobs.testbed.excitation.scenario_input` uses).

Sliding windows are evaluated for every start at once with a doubling table
(``O(T log L)`` batched matrix products for ``T`` steps and windows of ``L`` steps); the
same composition, as a balanced tree, gives one window's Gramian in ``O(log L)``
batched products (the live monitor).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from quadobs.core.held_input import HeldInputDiscretization, quadratic_coefficients, van_loan
from quadobs.core.immersion import Immersion, as_immersion
from quadobs.errors import QuadobsError, as_array, as_finite_scalar

__all__ = [
    "GramianModel",
    "compose",
    "eig_extremes",
    "reduce_window",
    "scaled_min_eig",
    "sliding_windows",
]


def compose(
    first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate two consecutive segments ``(Phi, W)`` (``first`` earlier); batched over leading axes.

    ``Phi = Phi_2 Phi_1`` and ``W = W_1 + Phi_1^T W_2 Phi_1`` (module docstring).
    """
    P1, W1 = first
    P2, W2 = second
    return P2 @ P1, W1 + np.swapaxes(P1, -1, -2) @ W2 @ P1


def reduce_window(Phi: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transition and Gramian over the whole sequence of steps ``(Phi (L, N, N), G (L, N, N))``.

    A balanced tree of :func:`compose` (``ceil(log2 L)`` batched levels); an odd tail is
    carried to the next level unchanged. ``L = 0`` gives ``(I, 0)``.
    """
    L, N = Phi.shape[0], Phi.shape[-1]
    if L == 0:
        return np.eye(N), np.zeros((N, N))
    P, W = Phi, G
    while P.shape[0] > 1:
        half = P.shape[0] // 2
        Pc, Wc = compose(
            (P[0 : 2 * half : 2], W[0 : 2 * half : 2]), (P[1 : 2 * half : 2], W[1 : 2 * half : 2])
        )
        if P.shape[0] % 2:
            Pc = np.concatenate([Pc, P[-1:]])
            Wc = np.concatenate([Wc, W[-1:]])
        P, W = Pc, Wc
    return P[0], W[0]


def sliding_windows(Phi: np.ndarray, G: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
    """Gramians of every window of ``length`` consecutive steps: ``W_i`` over steps ``i .. i + length - 1``.

    Doubling table: level ``j`` holds the segments of ``2^j`` steps starting at each step;
    a window is the ordered composition of the levels in the binary expansion of
    ``length``. Returns ``(Phi_w, W_w)`` of shape ``(T - length + 1, N, N)``.
    """
    T = Phi.shape[0]
    if not 1 <= length <= T:
        raise QuadobsError(
            f"window: {length} steps, expected between 1 and the {T} steps of the input"
        )
    count = T - length + 1
    seg_P, seg_W = Phi, G  # segments of 2^j steps, starting at 0 .. T - 2^j
    acc_P: np.ndarray | None = None
    acc_W: np.ndarray | None = None
    offset, j, rest = 0, 0, length
    while rest:
        span = 1 << j
        if rest & 1:
            part = (seg_P[offset : offset + count], seg_W[offset : offset + count])
            if acc_P is None or acc_W is None:
                acc_P, acc_W = part
            else:
                acc_P, acc_W = compose((acc_P, acc_W), part)
            offset += span
        rest >>= 1
        if rest:
            n_next = seg_P.shape[0] - span
            seg_P, seg_W = compose(
                (seg_P[:n_next], seg_W[:n_next]),
                (seg_P[span : span + n_next], seg_W[span : span + n_next]),
            )
            j += 1
    assert acc_P is not None and acc_W is not None, "length >= 1 steps"
    return acc_P, acc_W


def eig_extremes(W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lambda_min, lambda_max, v_min)`` of symmetric ``W (..., N, N)``; ``v_min`` the unit eigenvector of ``lambda_min``."""
    W = 0.5 * (W + np.swapaxes(W, -1, -2))
    lam, vec = np.linalg.eigh(W)
    return lam[..., 0], lam[..., -1], vec[..., :, 0]


def scaled_min_eig(W: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue of the unit-diagonal form ``D^{-1/2} W D^{-1/2}``, ``D = diag(W)``; in ``[0, 1]`` up to rounding.

    Singularity does not depend on the units of the coordinates, and this form removes
    them: it is unchanged by any diagonal rescaling of the state, so its size against
    rounding (``~1e-16``) decides whether ``W`` is singular to working precision. A zero
    diagonal entry (a coordinate that does not reach the output at all) gives 0.
    """
    W = 0.5 * (W + np.swapaxes(W, -1, -2))
    d = np.diagonal(W, axis1=-2, axis2=-1)
    ok = np.all(d > 0, axis=-1)
    safe = np.where(d > 0, d, 1.0)
    r = 1.0 / np.sqrt(safe)
    S = W * r[..., :, None] * r[..., None, :]
    lam = np.linalg.eigvalsh(np.where(ok[..., None, None], S, np.eye(W.shape[-1])))[..., 0]
    return np.where(ok, lam, 0.0)


@dataclass(frozen=True, eq=False)
class GramianModel:
    """Per-step transition and Gramian of an :class:`~quadobs.core.immersion.Immersion` for a held input.

    Parameters
    ----------
    immersion : Immersion
        Any immersion (chain or minimal); the output matrix is ``immersion.output_matrix``.
    dt : float
        Length ``h`` of a hold step (s).

    Attributes
    ----------
    discretization : HeldInputDiscretization
        Supplies ``Phi(u) = F0 + sum_j u_j F1[j]`` (eqs. 22, 26a-c for a held input).
    gramian_constant, gramian_linear, gramian_quadratic : ndarray
        ``G(u) = G0 + sum_j u_j G1[j] + sum_{j,l} u_j u_l G2[j, l]``; shapes ``(N, N)``,
        ``(p, N, N)``, ``(p, p, N, N)``.
    """

    immersion: Immersion
    dt: float
    discretization: HeldInputDiscretization = field(init=False, repr=False)
    gramian_constant: np.ndarray = field(init=False, repr=False)
    gramian_linear: np.ndarray = field(init=False, repr=False)
    gramian_quadratic: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        im = as_immersion(self.immersion)
        dt = as_finite_scalar("dt", self.dt, positive=True)
        p = im.system.p
        CtC = im.output_matrix.T @ im.output_matrix

        def step_gramian(u: np.ndarray) -> np.ndarray:
            return van_loan(im.state_matrix(u).T, CtC, dt)[1]

        G0, G1, G2 = quadratic_coefficients(step_gramian, p)
        object.__setattr__(self, "dt", dt)
        object.__setattr__(self, "discretization", HeldInputDiscretization(im, dt))
        for name, arr in (
            ("gramian_constant", G0),
            ("gramian_linear", G1),
            ("gramian_quadratic", G2),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def dim(self) -> int:
        """Dimension ``N`` of the augmented state."""
        return self.immersion.dim

    def _inputs(self, u) -> np.ndarray:
        u = as_array("u", u)
        p = self.immersion.system.p
        if u.ndim == 1 and p == 1 and u.shape != (1,):
            u = u[:, None]
        if u.shape[-1:] != (p,):
            raise QuadobsError(f"u: expected shape (..., {p}), got {u.shape}")
        return u

    def step_gramian(self, u) -> np.ndarray:
        """``G(u)``: the Gramian of one held step, ``(..., N, N)`` for ``u (..., p)``."""
        u = self._inputs(u)
        p, N = u.shape[-1], self.dim
        uu = (u[..., :, None] * u[..., None, :]).reshape(u.shape[:-1] + (p * p,))
        flat = u @ self.gramian_linear.reshape(p, N * N) + uu @ self.gramian_quadratic.reshape(
            p * p, N * N
        )
        return self.gramian_constant + flat.reshape(u.shape[:-1] + (N, N))

    def step_terms(self, u) -> tuple[np.ndarray, np.ndarray]:
        """``(Phi(u_k), G(u_k))`` for a sequence ``u (T, p)``: shapes ``(T, N, N)`` each."""
        u = self._inputs(u)
        return self.discretization.transition(u), self.step_gramian(u)

    def gramian(self, u) -> np.ndarray:
        """``W(t_0, t_0 + T h)`` for the held samples ``u (T, p)``, ``(N, N)``."""
        Phi, G = self.step_terms(u)
        return reduce_window(Phi, G)[1]

    def sliding(self, u, length: int, stride: int = 1) -> np.ndarray:
        """Gramians of the windows of ``length`` steps starting at steps ``0, stride, 2 stride, ...``.

        Returns ``(n_windows, N, N)``; window ``i`` covers steps ``i stride .. i stride + length - 1``.
        """
        Phi, G = self.step_terms(u)
        W = sliding_windows(Phi, G, int(length))[1]
        return W[:: max(int(stride), 1)]
