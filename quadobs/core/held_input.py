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
(``[[M, K_j, 0], [0, A, B], [0, 0, 0]]``, :func:`held_input_step` at ``u = e_j``), so a step costs a few small matrix products and
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

import math
from dataclasses import dataclass, field
from functools import cache
from itertools import combinations

import numpy as np
import scipy.linalg as sla

from quadobs.core.immersion import Immersion, as_immersion
from quadobs.errors import QuadobsError, as_array, as_finite_scalar

__all__ = [
    "HeldInputDiscretization",
    "as_covariance",
    "expm_exact",
    "expm_series_numpy",
    "held_input_interval",
    "held_input_step",
    "van_loan",
    "van_loan_interval",
]


#: Largest magnitude of a covariance entry: the filters' products (``K R K^T``, ``C P C^T``)
#: square it, and double precision overflows past about 1e308.
COVARIANCE_MAX = 1e100


def as_covariance(name: str, value, dim: int, *, definite: bool = True) -> np.ndarray:
    """A scalar (times the identity), a vector (diagonal) or a ``(dim, dim)`` symmetric matrix.

    Raises :class:`QuadobsError` when the value is not symmetric positive (semi)definite,
    or has an entry that is not finite or beyond :data:`COVARIANCE_MAX` in magnitude.
    """
    arr = as_array(name, value)
    if arr.ndim == 0:
        arr = float(arr) * np.eye(dim)
    elif arr.ndim == 1:
        if arr.shape != (dim,):
            raise QuadobsError(
                f"{name}: expected a scalar, ({dim},) or ({dim}, {dim}), got shape {arr.shape}"
            )
        arr = np.diag(arr)
    elif arr.shape != (dim, dim):
        raise QuadobsError(
            f"{name}: expected a scalar, ({dim},) or ({dim}, {dim}), got shape {arr.shape}"
        )
    if dim and not (np.isfinite(arr).all() and np.abs(arr).max() <= COVARIANCE_MAX):
        raise QuadobsError(
            f"{name}: covariance entries must be finite and at most {COVARIANCE_MAX:g} in magnitude"
        )
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=1e-12 * max(np.abs(arr).max(), 1.0)):
        raise QuadobsError(f"{name}: covariance must be symmetric")
    arr = 0.5 * arr + 0.5 * arr.T
    eig = np.linalg.eigvalsh(arr) if dim else np.zeros(0)
    if dim and not (eig.min() > 0 if definite else eig.min() >= -1e-12 * max(eig.max(), 1.0)):
        kind = "positive definite" if definite else "positive semidefinite"
        raise QuadobsError(
            f"{name}: covariance must be {kind} (smallest eigenvalue {eig.min():.3g})"
        )
    return arr


def held_input_step(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact one-step map of ``x' = A x + B u`` with ``u`` held over ``dt``: ``x+ = Phi x + Gamma u``.

    One exponential of the block matrix gives both blocks:

    .. math::

        \\exp\\left(\\begin{bmatrix} A & B \\\\ 0 & 0 \\end{bmatrix} dt\\right)
        = \\begin{bmatrix} \\Phi & \\Gamma \\\\ 0 & I \\end{bmatrix}, \\qquad
        \\Phi = e^{A dt}, \\quad \\Gamma = \\int_0^{dt} e^{A s} ds\\, B .

    The only place the project discretises a linear system under a held input: the
    augmented system at ``u = e_j`` (:class:`HeldInputDiscretization`, ``A = A(e_j)``,
    ``B = (0, B)``) and the original state of the Kalman baselines
    (:class:`quadobs.estimators.kalman.HeldInputModel`).

    Parameters
    ----------
    A : ndarray (n, n)
    B : ndarray (n, p)
    dt : float
        Step length (s).

    Returns
    -------
    Phi : ndarray (n, n)
    Gamma : ndarray (n, p)

    Examples
    --------
    The double integrator: ``Phi = [[1, dt], [0, 1]]``, ``Gamma = [dt^2 / 2, dt]``.

    >>> Phi, Gamma = held_input_step(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), 0.5)
    >>> np.round(Phi, 12).tolist(), np.round(Gamma, 12).ravel().tolist()
    ([[1.0, 0.5], [0.0, 1.0]], [0.125, 0.5])
    """
    n, p = A.shape[0], B.shape[1]
    big = np.zeros((n + p, n + p))
    big[:n, :n] = A
    big[:n, n:] = B
    E = sla.expm(big * dt)
    return E[:n, :n].copy(), E[:n, n:].copy()


def van_loan(A: np.ndarray, V: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(e^{A dt}, int_0^dt e^{A s} V e^{A^T s} ds)`` by Van Loan's block exponential.

    .. math::

        \\exp\\left(\\begin{bmatrix} -A & V \\\\ 0 & A^\\top \\end{bmatrix} dt\\right)
        = \\begin{bmatrix} \\cdot & E_{12} \\\\ 0 & E_{22} \\end{bmatrix}, \\qquad
        \\Phi = E_{22}^\\top, \\quad Q_d = \\Phi E_{12} .

    The discrete covariance of a white noise of intensity ``V`` on ``x' = A x`` over one
    step (symmetrised); used for ``Q_d(u)`` of :class:`HeldInputDiscretization`, ``Q_V`` of
    :class:`quadobs.estimators.kalman.HeldInputModel` and the step Gramian of
    :class:`quadobs.observability.gramian.GramianModel` (with ``A^T`` and ``C^T C``).

    Examples
    --------
    White acceleration noise of intensity ``s2`` on a double integrator:
    ``Q_d = s2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]``.

    >>> Phi, Q = van_loan(np.array([[0.0, 1.0], [0.0, 0.0]]), np.diag([0.0, 2.0]), 0.5)
    >>> np.round(Q / 2.0, 12).tolist()
    [[0.041666666667, 0.125], [0.125, 0.5]]
    """
    N = A.shape[0]
    big = np.zeros((2 * N, 2 * N))
    big[:N, :N] = -A
    big[:N, N:] = V
    big[N:, N:] = A.T
    E = sla.expm(big * dt)
    Phi = E[N:, N:].T
    Q = Phi @ E[:N, N:]
    return Phi, 0.5 * (Q + Q.T)


def expm_series_numpy(M: np.ndarray) -> np.ndarray | None:
    """The finite series ``sum_{i<k} M^i / i!`` when ``M^k`` is exactly zero for some ``k <= n``, else ``None``.

    The NumPy reference of the compiled :func:`quadobs._kernels.held_input.expm_series`
    (the same operations in the same order):

    .. math::

        T_0 = I, \\qquad T_i = (T_{i-1} M) / i, \\qquad e^M = \\sum_{i < k} T_i
        \\quad \\text{when } T_k = 0 .
    """
    n = M.shape[0]
    out = np.eye(n)
    term = np.eye(n)
    for i in range(1, n + 1):
        term = term @ M / i
        if not term.any():
            return out
        out = out + term
    return None


@cache
def _compiled_series():
    """:func:`quadobs._kernels.held_input.expm_series` when Numba imports, else ``None``."""
    try:
        from quadobs._kernels.held_input import expm_series
    except ImportError:
        return None
    return expm_series


def expm_exact(M: np.ndarray) -> np.ndarray:
    """``e^M``: the finite series ``sum_{i<k} M^i / i!`` when ``M^k`` is exactly zero for some
    ``k <= n`` (a nilpotent matrix, as the replay models' ``A`` and their immersions' ``A(u)``
    and Van Loan blocks are), else :func:`scipy.linalg.expm`. Exact either way; the series
    costs a few products where ``expm`` costs a Padé approximant with scaling and squaring.

    The series is compiled (:func:`quadobs._kernels.held_input.expm_series`) when Numba
    imports, else :func:`expm_series_numpy`; both give the same bits.

    Examples
    --------
    >>> expm_exact(np.array([[0.0, 2.0], [0.0, 0.0]])).tolist()
    [[1.0, 2.0], [0.0, 1.0]]
    """
    series = _compiled_series()
    if series is None:
        out = expm_series_numpy(M)
        return sla.expm(M) if out is None else out
    M = np.ascontiguousarray(M, dtype=float)
    n = M.shape[0]
    out, term, work = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    return out if series(M, out, term, work) else sla.expm(M)


def held_input_interval(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`held_input_step` through :func:`expm_exact`: the same map, for intervals of any
    length taken one at a time (the interface in time); the precomputed steps keep
    :func:`held_input_step`."""
    n, p = A.shape[0], B.shape[1]
    big = np.zeros((n + p, n + p))
    big[:n, :n] = A
    big[:n, n:] = B
    E = expm_exact(big * dt)
    return E[:n, :n].copy(), E[:n, n:].copy()


def van_loan_interval(A: np.ndarray, V: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`van_loan` through :func:`expm_exact` (see :func:`held_input_interval`)."""
    N = A.shape[0]
    big = np.zeros((2 * N, 2 * N))
    big[:N, :N] = -A
    big[:N, N:] = V
    big[N:, N:] = A.T
    E = expm_exact(big * dt)
    Phi = E[N:, N:].T
    Q = Phi @ E[:N, N:]
    return Phi, 0.5 * (Q + Q.T)


def _rows(a: np.ndarray, width: int) -> np.ndarray:
    """``a`` as a matrix of ``width`` columns (one row per leading index; also for ``width = 0``)."""
    return a.reshape(math.prod(a.shape[:-1]) if a.ndim > 1 else 1, width)


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
        im = as_immersion(self.immersion)
        dt = as_finite_scalar("dt", self.dt, positive=True)
        theta = as_finite_scalar("theta", self.theta, nonnegative=True)
        k, n, p, N = im.n_aux, im.system.n, im.system.p, im.dim
        V = as_covariance("V", self.V, N, definite=False)

        # Phi(e_j) and Gamma(e_j) of the augmented system z' = A(e_j) z + (0, B) u: the blocks
        # that do not depend on u come from j = 0, Phi_12 and the aux part of Gamma from each j.
        F0 = np.zeros((N, N))
        F1 = np.zeros((p, k, n))
        G2 = np.zeros((p, k, p))
        for j in range(max(p, 1)):
            e = np.zeros(p)
            if p:
                e[j] = 1.0
            Phi, Gamma = held_input_step(im.state_matrix(e), im.input_matrix, dt)
            if j == 0:
                F0[:k, :k] = Phi[:k, :k]
                F0[k:, k:] = Phi[k:, k:]
                G0 = Gamma[k:].copy()
            if p:
                F1[j] = Phi[:k, k:]
                G2[j] = Gamma[:k]

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

    def transition(self, u: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``Phi(u)``, the augmented transition over one step with ``u`` held ([IFAC2021, eq. 22, 26a-c]).

        .. math::

            \\Phi(u) = F_0 + \\begin{bmatrix} 0 & \\sum_j u_j F_1[j] \\\\ 0 & 0 \\end{bmatrix}

        (``F0`` = :attr:`transition_constant`, ``F1`` = :attr:`transition_input`). The one
        place ``Phi(u)`` is built: the estimators, the Gramian and the bounds call it.

        Parameters
        ----------
        u : array_like (..., p)
        out : ndarray (N, N), optional
            For a single ``u``: a buffer whose entries outside the ``xi``-``x`` block already
            hold ``F0`` (e.g. a copy of :attr:`transition_constant`); only that block is
            written, in place (the per-step loops of the estimators).

        Returns
        -------
        ndarray (..., N, N)
            ``out`` when given.
        """
        u = np.asarray(u, dtype=float)
        k, n, p = self.immersion.n_aux, self.immersion.system.n, self.immersion.system.p
        F0 = self.transition_constant
        if out is None:
            out = np.broadcast_to(F0, u.shape[:-1] + F0.shape).copy()
        # sum_j u_j F1[j] as one matrix product (what np.tensordot(u, F1, axes=(-1, 0)) forms)
        coupling = np.dot(_rows(u, p), self.transition_input.reshape(p, k * n))
        out[..., :k, k:] = F0[:k, k:] + coupling.reshape(u.shape[:-1] + (k, n))
        return out

    def input_term(self, u: np.ndarray) -> np.ndarray:
        """``g(u) = int_0^dt Phi_s(u) ds B u`` (exact, quadratic in ``u``); returns ``(..., N)``.

        ``g(u) = (sum_j u_j G2[j] u, G0 u)`` with ``G2`` = :attr:`input_quadratic` and
        ``G0`` = :attr:`input_linear`.
        """
        u = np.asarray(u, dtype=float)
        k, p = self.immersion.n_aux, self.immersion.system.p
        Gu = np.dot(_rows(u, p), self.input_quadratic.reshape(p, k * p)).reshape(
            u.shape[:-1] + (k, p)
        )
        if u.ndim == 1:
            return np.concatenate([Gu @ u, self.input_linear @ u])
        aux = np.einsum("...al,...l->...a", Gu, u)
        return np.concatenate([aux, u @ self.input_linear.T], axis=-1)

    def process_noise(self, u: np.ndarray) -> np.ndarray:
        """``Q_d(u) = Q0 + sum_j u_j Q1[j] + sum_{j,l} u_j u_l Q2[j, l]`` (module docstring); returns ``(..., N, N)``."""
        u = np.asarray(u, dtype=float)
        p, N = self.immersion.system.p, self.immersion.dim
        uu = _rows((u[..., :, None] * u[..., None, :]).reshape(u.shape[:-1] + (p * p,)), p * p)
        lin = np.dot(_rows(u, p), self.noise_linear.reshape(p, N * N)).reshape(
            u.shape[:-1] + (N, N)
        )
        quad = np.dot(uu, self.noise_quadratic.reshape(p * p, N * N)).reshape(u.shape[:-1] + (N, N))
        return self.noise_constant + lin + quad

    def predict(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Exact ``z(t + dt)`` from ``z(t)`` under the held input ``u`` (batched)."""
        z = np.asarray(z, dtype=float)
        return np.einsum("...ab,...b->...a", self.transition(u), z) + self.input_term(u)
