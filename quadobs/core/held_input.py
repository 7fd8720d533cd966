"""Exact discretisation of the augmented system under an input held over each step.

Over a step of length ``dt`` with ``u`` constant, ``z' = A(u) z + B u`` ([IFAC2021]
eq. 14) has the exact solution ``z(t + dt) = Phi(u) z(t) + g(u)``. Because
``A(u) = [[M, U(u)], [0, A]]`` is block upper triangular and only the off-diagonal block
depends on ``u``, linearly (eq. 20, 21), the transition matrix (eq. 22, 26a-c)

.. math::

    \\Phi(u) = \\begin{bmatrix} e^{M dt} & \\Phi_{12}(u) \\\\ 0 & e^{A dt} \\end{bmatrix},
    \\qquad \\Phi_{12}(u) = \\int_0^{dt} e^{M (dt - s)} U(u) e^{A s} ds

is *affine* in ``u``, and the input term ``g(u)`` is quadratic in ``u``. All their
coefficients are computed once, from matrix exponentials of block matrices
(``[[M, K_j, 0], [0, A, B], [0, 0, 0]]``), so a step costs a few small matrix products and
is exact to rounding for any held input, not only small ``dt``.

Covariance. Theorem 3's Riccati equation
``M' = A M + M A^T - M C^T W^{-1} C M + V + theta M`` is discretised as a
continuous-discrete Kalman filter: between measurements ``P`` follows
``P' = (A + theta/2 I) P + P (A + theta/2 I)^T + V`` exactly,

.. math::

    P^- = e^{\\theta dt} \\Phi P \\Phi^\\top + Q_d(u), \\qquad
    Q_d(u) = \\int_0^{dt} e^{\\theta s} \\Phi_s(u) V \\Phi_s(u)^\\top ds,

with ``Q_d(u)`` a quadratic polynomial in ``u`` whose coefficients are obtained from
Van Loan's block exponential at a few inputs. A measurement sampled every ``T`` seconds
with continuous noise intensity ``W`` has discrete covariance ``R = W / T``, so the
discrete filter tends to Theorem 3's observer as ``T -> 0``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
import scipy.linalg as sla

from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.core.immersion import Immersion

__all__ = ["HeldInputDiscretization", "van_loan", "as_covariance"]


def as_covariance(name: str, value, dim: int, *, definite: bool = True) -> np.ndarray:
    """A scalar (times the identity), a vector (diagonal) or a ``(dim, dim)`` symmetric matrix.

    Raises :class:`QuadobsError` when the value is not symmetric positive (semi)definite.
    """
    arr = as_array(name, value)
    if arr.ndim == 0:
        arr = float(arr) * np.eye(dim)
    elif arr.ndim == 1:
        if arr.shape != (dim,):
            raise QuadobsError(f"{name}: expected a scalar, ({dim},) or ({dim}, {dim}), got shape {arr.shape}")
        arr = np.diag(arr)
    elif arr.shape != (dim, dim):
        raise QuadobsError(f"{name}: expected a scalar, ({dim},) or ({dim}, {dim}), got shape {arr.shape}")
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=1e-12 * max(np.abs(arr).max(), 1.0)):
        raise QuadobsError(f"{name}: covariance must be symmetric")
    arr = 0.5 * (arr + arr.T)
    eig = np.linalg.eigvalsh(arr) if dim else np.zeros(0)
    if dim and (eig.min() <= 0 if definite else eig.min() < -1e-12 * max(eig.max(), 1.0)):
        kind = "positive definite" if definite else "positive semidefinite"
        raise QuadobsError(f"{name}: covariance must be {kind} (smallest eigenvalue {eig.min():.3g})")
    return arr


def van_loan(A: np.ndarray, V: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(e^{A dt}, int_0^dt e^{A s} V e^{A^T s} ds)`` by Van Loan's block exponential."""
    N = A.shape[0]
    big = np.zeros((2 * N, 2 * N))
    big[:N, :N] = -A
    big[:N, N:] = V
    big[N:, N:] = A.T
    E = sla.expm(big * dt)
    Phi = E[N:, N:].T
    Q = Phi @ E[:N, N:]
    return Phi, 0.5 * (Q + Q.T)


def quadratic_coefficients(f, p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients of a matrix-valued quadratic polynomial from its values.

    For ``f(u) = F0 + sum_j u_j F1[j] + sum_{j,l} u_j u_l F2[j, l]`` (``F2`` symmetric in
    ``j, l``), recover ``F0``, ``F1 (p, ...)`` and ``F2 (p, p, ...)`` exactly from the values
    at ``u = 0``, ``+-e_j`` and ``e_j + e_l``:
    ``F1[j] = (f(e_j) - f(-e_j)) / 2``, ``F2[j, j] = (f(e_j) + f(-e_j)) / 2 - F0`` and
    ``F2[j, l] = (f(e_j + e_l) - F0 - F1[j] - F1[l] - F2[j, j] - F2[l, l]) / 2``.
    """
    F0 = np.asarray(f(np.zeros(p)))
    F1 = np.zeros((p,) + F0.shape)
    F2 = np.zeros((p, p) + F0.shape)
    for j in range(p):
        e = np.zeros(p)
        e[j] = 1.0
        fp, fm = f(e), f(-e)
        F1[j] = 0.5 * (fp - fm)
        F2[j, j] = 0.5 * (fp + fm) - F0
    for j, l in combinations(range(p), 2):
        e = np.zeros(p)
        e[[j, l]] = 1.0
        cross = f(e) - F0 - F1[j] - F1[l] - F2[j, j] - F2[l, l]
        F2[j, l] = F2[l, j] = 0.5 * cross
    return F0, F1, F2


@dataclass(frozen=True, eq=False)
class HeldInputDiscretization:
    """Exact one-step map of an :class:`~quadobs.core.immersion.Immersion` with the input held.

    Parameters
    ----------
    immersion : Immersion
    dt : float
        Step length (s), positive.
    V : float or array_like, optional
        Continuous process-noise intensity of Theorem 3 (scalar, diagonal, or ``(N, N)``);
        ``0`` gives no process noise.
    theta : float
        Forgetting factor of Theorem 3 (``theta >= 0``).

    Attributes
    ----------
    transition_constant : ndarray (N, N)
        ``Phi(0) = blockdiag(e^{M dt}, e^{A dt})``.
    transition_input : ndarray (p, n_aux, n)
        ``Phi_12(u) = sum_j u_j transition_input[j]``.
    input_linear : ndarray (n, p)
        ``x`` part of ``g(u)``: ``int_0^dt e^{A s} ds B u``.
    input_quadratic : ndarray (p, n_aux, p)
        auxiliary part of ``g(u)``: ``sum_j u_j input_quadratic[j] @ u``.
    noise_constant, noise_linear, noise_quadratic : ndarray
        ``Q_d(u) = Q0 + sum_j u_j Q1[j] + sum_{j,l} u_j u_l Q2[j, l]`` with ``Q2`` symmetric
        in ``(j, l)``; shapes ``(N, N)``, ``(p, N, N)``, ``(p, p, N, N)``.
    """

    immersion: Immersion
    dt: float
    V: np.ndarray | float = 0.0
    theta: float = 0.0
    transition_constant: np.ndarray = field(init=False, repr=False)
    transition_input: np.ndarray = field(init=False, repr=False)
    input_linear: np.ndarray = field(init=False, repr=False)
    input_quadratic: np.ndarray = field(init=False, repr=False)
    noise_constant: np.ndarray = field(init=False, repr=False)
    noise_linear: np.ndarray = field(init=False, repr=False)
    noise_quadratic: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        im = self.immersion
        if not isinstance(im, Immersion):
            raise QuadobsError(f"immersion: expected an Immersion, got {type(im).__name__}")
        dt = as_finite_scalar("dt", self.dt, positive=True)
        theta = as_finite_scalar("theta", self.theta, nonnegative=True)
        k, n, p, N = im.n_aux, im.system.n, im.system.p, im.dim
        V = as_covariance("V", self.V, N, definite=False)
        A, B = im.system.A, im.system.B

        F0 = np.zeros((N, N))
        F1 = np.zeros((p, k, n))
        G2 = np.zeros((p, k, p))
        size = k + n + p
        for j in range(max(p, 1)):
            big = np.zeros((size, size))
            big[:k, :k] = im.aux_dynamics
            if p:
                big[:k, k : k + n] = im.input_forms[j]
            big[k : k + n, k : k + n] = A
            big[k : k + n, k + n :] = B
            E = sla.expm(big * dt)
            if j == 0:
                F0[:k, :k] = E[:k, :k]
                F0[k:, k:] = E[k : k + n, k : k + n]
                G0 = E[k : k + n, k + n :].copy()
            if p:
                F1[j] = E[:k, k : k + n]
                G2[j] = E[:k, k + n :]

        # Q_d(u) is a quadratic polynomial in u: recover its coefficients exactly from its
        # values at u = 0, +-e_j and e_j + e_l (Van Loan at each).
        shift = 0.5 * theta * np.eye(N)

        def qd(u: np.ndarray) -> np.ndarray:
            return van_loan(im.state_matrix(u) + shift, V, dt)[1]

        Q0, Q1, Q2 = quadratic_coefficients(qd, p)

        growth = theta * dt
        blocks = (F0, F1, G0, G2, Q0, Q1, Q2)
        if not (growth < 700.0 and all(np.isfinite(b).all() for b in blocks)):
            raise QuadobsError(
                f"dt: the model discretised over dt = {dt:g} s (theta = {theta:g}) is not finite in double precision; "
                "use a shorter step or a smaller theta"
            )
        object.__setattr__(self, "dt", dt)
        object.__setattr__(self, "theta", theta)
        object.__setattr__(self, "V", V)
        for name, arr in (
            ("transition_constant", F0),
            ("transition_input", F1),
            ("input_linear", G0),
            ("input_quadratic", G2),
            ("noise_constant", Q0),
            ("noise_linear", Q1),
            ("noise_quadratic", Q2),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def transition(self, u: np.ndarray) -> np.ndarray:
        """``Phi(u)`` for ``u`` of shape ``(..., p)``; returns ``(..., N, N)``."""
        u = np.asarray(u, dtype=float)
        k = self.immersion.n_aux
        out = np.broadcast_to(self.transition_constant, u.shape[:-1] + self.transition_constant.shape).copy()
        out[..., :k, k:] += np.tensordot(u, self.transition_input, axes=(-1, 0))
        return out

    def input_term(self, u: np.ndarray) -> np.ndarray:
        """``g(u) = int_0^dt Phi_s(u) ds B u`` (exact, quadratic in ``u``); returns ``(..., N)``."""
        u = np.asarray(u, dtype=float)
        aux = np.einsum("...j,jal,...l->...a", u, self.input_quadratic, u)
        return np.concatenate([aux, u @ self.input_linear.T], axis=-1)

    def process_noise(self, u: np.ndarray) -> np.ndarray:
        """``Q_d(u)`` (see the module docstring); returns ``(..., N, N)``."""
        u = np.asarray(u, dtype=float)
        return (
            self.noise_constant
            + np.tensordot(u, self.noise_linear, axes=(-1, 0))
            + np.einsum("...j,...l,jlab->...ab", u, u, self.noise_quadratic)
        )

    def predict(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Exact ``z(t + dt)`` from ``z(t)`` under the held input ``u`` (batched)."""
        z = np.asarray(z, dtype=float)
        return np.einsum("...ab,...b->...a", self.transition(u), z) + self.input_term(u)
