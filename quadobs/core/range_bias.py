"""Constant per-anchor range biases as states of the immersion: the derivation and the model.

A two-way range to anchor ``h`` with a constant bias ``b_h`` (antenna delay) is
``rho_h = |p - a_h| + b_h``. The bias does not fit the quadratic-output form of
[IFAC2021, eq. 2] as it stands: ``rho_h^2 / 2 = |p - a_h|^2 / 2 + b_h |p - a_h| + b_h^2 / 2``
has the non-polynomial term ``b_h |p - a_h|``. Squaring the other side instead,

.. math::

    (\\rho_h - b_h)^2 = |p - a_h|^2
    \\iff
    \\underbrace{\\tfrac12 \\rho_h^2 - \\tfrac12 |a_h|^2}_{y_h}
    = \\underbrace{\\tfrac12 |p|^2 - a_h^\\top p}_{\\mathcal C_h z}
      + \\rho_h\\, b_h - \\tfrac12 c_h, \\qquad c_h := b_h^2 ,

the output is *linear* in the augmented state ``zeta = (z, b, c)``, with ``z`` the
immersion's state [IFAC2021, eq. 10] and, as new constant states, the biases ``b`` and
their squares ``c`` (treated, like the auxiliary states, as free coordinates). The
coefficient of ``b_h`` is the *measured* range ``rho_h``: the output row of a measurement

.. math:: \\mathcal C_h(\\rho_h) = [\\,\\mathcal C_h \\;|\\; \\rho_h e_h^\\top \\;|\\; -\\tfrac12 e_h^\\top\\,]

is known at the time of the measurement, exactly as the input-dependent ``A(u)`` of
[IFAC2021, eq. 15] is known, so the system ``zeta' = blockdiag(A(u), 0, 0) zeta +
(B u, 0, 0)``, ``y_h = C_h(rho_h) zeta`` is state-affine with a known time-varying output
matrix, and the Kalman-like observer of Theorem 3 applies to it unchanged.

Noise. With ``rho_h`` measured as ``rho_h + eps``, ``eps ~ N(0, sigma^2)``, the same
identity gives ``y_h - rho_h b_h = C_h z - c_h / 2 + eps |p - a_h| + eps^2 / 2``: the
equation error has mean ``sigma^2 / 2`` (subtracted) and variance
``sigma^2 |p - a_h|^2 + sigma^4 / 2``, used as the correction's ``R`` with the measured
range for ``|p - a_h|`` (:func:`output_row`). The bias's own noise enters through the
coefficient ``rho_h`` only at second order (``eps b_h``, below ``sigma`` times the bias).

Observability ([IFAC2021, Thm. 3] asks the pair ``(A(u), C)`` to be uniformly observable;
[ACC2024] states it as persistence of excitation of the regressor). The new columns of
anchor ``h`` are ``rho_h(t)`` and the constant ``-1/2``; over a window they are linearly
independent of each other, and of the position columns, only when ``rho_h(t)`` is not
constant and not an affine function of the components of ``p(t)`` and ``|p(t)|^2``. A
vehicle hovering still (``rho_h`` constant) cannot tell ``b_h`` from ``c_h``, as no
estimator can tell a range bias from a position offset without motion; a vehicle that
moves around the anchors, as a flight does, excites them. :func:`excitation_gramian`
gives the Gramian of a sampled window, whose smallest eigenvalue is the margin (tested
on the quadrotor's figure eight).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadobs.core.held_input import held_input_step, van_loan
from quadobs.core.immersion import Immersion
from quadobs.errors import QuadobsError

__all__ = ["BiasedRangeImmersion", "excitation_gramian", "output_row"]


@dataclass(frozen=True, eq=False)
class BiasedRangeImmersion:
    """The immersion of a range system extended with a bias ``b_h`` and its square ``c_h`` per anchor.

    Parameters
    ----------
    immersion : Immersion
        Of a system whose outputs are ranges in the form of
        :func:`quadobs.core.system.vehicle_system`, ``y_h = |p|^2 / 2 - a_h^T p``.

    Attributes
    ----------
    m : int
        Anchors (outputs), each with ``b_h`` and ``c_h``.
    dim : int
        ``N + 2 m``: the immersion's state, the biases, their squares.
    """

    immersion: Immersion
    squares: bool = False

    @property
    def m(self) -> int:
        return int(self.immersion.system.q)

    @property
    def dim(self) -> int:
        return self.immersion.dim + (2 if self.squares else 1) * self.m

    @property
    def bias_slice(self) -> slice:
        """Where ``b`` sits in ``zeta``."""
        N = self.immersion.dim
        return slice(N, N + self.m)

    def lift(self, x: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """``zeta = (lift(x), b[, b^2])`` (``b`` default zero)."""
        b = np.zeros(self.m) if b is None else np.asarray(b, dtype=float)
        if b.shape != (self.m,):
            raise QuadobsError(f"b: expected shape ({self.m},), got {b.shape}")
        parts = [self.immersion.lift(x), b] + ([b * b] if self.squares else [])
        return np.concatenate(parts)

    def project(self, zeta: np.ndarray) -> np.ndarray:
        """``x`` from ``zeta``."""
        return self.immersion.project(zeta[: self.immersion.dim])

    def biases(self, zeta: np.ndarray) -> np.ndarray:
        """``b`` from ``zeta``."""
        return zeta[self.bias_slice]

    def output_row(self, h: int, rho: float) -> np.ndarray:
        """``C_h(rho) (dim,)`` of the exact form (``squares=True``): see :func:`output_row`."""
        return output_row(self.immersion.output_matrix[h], h, self.m, rho)

    def measurement(self, h: int, rho: float, zeta: np.ndarray) -> tuple[np.ndarray, float]:
        """The output row and the output of a range ``rho`` to anchor ``h``: ``(row, y)`` with
        ``y ~ row @ zeta`` (up to noise).

        Exact form (``squares=True``): ``row = [C_h | rho e_h | -e_h/2]``,
        ``y = rho^2/2 - |a_h|^2/2``. Linearised form (default): ``b_h^2`` replaced by its
        tangent at the current estimate ``bh`` (:data:`zeta`'s bias),
        ``row = [C_h | (rho - bh) e_h]``, ``y = rho^2/2 - |a_h|^2/2 - bh^2/2``, exact up to
        ``-(b_h - bh)^2 / 2`` (see the module docstring).
        """
        C_h = self.immersion.output_matrix[h]
        y = 0.5 * rho * rho - self._offsets[h]
        if self.squares:
            return output_row(C_h, h, self.m, rho), y
        bh = float(zeta[self.immersion.dim + h])
        row = np.zeros(self.dim)
        row[: C_h.shape[0]] = C_h
        row[C_h.shape[0] + h] = rho - bh
        return row, y - 0.5 * bh * bh

    @property
    def _offsets(self) -> np.ndarray:
        d = self.immersion.system.d
        return 0.5 * np.einsum("hi,hi->h", d, d)  # |a_h|^2 / 2, as d_h = (-a_h, 0)

    def transition(
        self, u: np.ndarray, tau: float, V: np.ndarray, walk: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(Phi, g, Q)``: the exact map of ``zeta`` over ``tau`` seconds with ``u`` held.

        ``Phi = blockdiag(e^{A(u) tau}, I)``, ``g = (Gamma(u) u, 0)`` and
        ``Q = blockdiag(Q_V(u), walk tau I_m, 0)``: ``V`` is the intensity on ``z``
        (Van Loan), ``walk`` a random-walk intensity on the biases (m^2/s) for biases that
        drift; their squares are kept constant.
        """
        im, N, m = self.immersion, self.immersion.dim, self.m
        A = im.state_matrix(u)
        Phi_z, Gam = held_input_step(A, im.input_matrix, tau)
        Q_z = van_loan(A, V, tau)[1] if V.any() else np.zeros((N, N))
        D = self.dim
        Phi, Q = np.eye(D), np.zeros((D, D))
        Phi[:N, :N], Q[:N, :N] = Phi_z, Q_z
        Q[N : N + m, N : N + m] = walk * tau * np.eye(m)
        g = np.zeros(D)
        g[:N] = Gam @ u
        return Phi, g, Q


def output_row(C_h: np.ndarray, h: int, m: int, rho: float) -> np.ndarray:
    """The output row of a range ``rho`` to anchor ``h``: ``[C_h | rho e_h | -1/2 e_h]``.

    Parameters
    ----------
    C_h : ndarray (N,)
        The immersion's output row of anchor ``h``.
    h, m : int
        The anchor, and the number of anchors.
    rho : float
        The measured range (m).

    Examples
    --------
    On the exact state, the row reproduces ``rho^2/2 - |a|^2/2``:

    >>> import numpy as np
    >>> from quadobs.core.immersion import immerse
    >>> from quadobs.core.system import vehicle_system
    >>> a = np.array([[3.0, 0.0, 1.0], [0.0, 4.0, 0.0]])
    >>> ext = BiasedRangeImmersion(immerse(vehicle_system(3, a)), squares=True)
    >>> x, b = np.array([1.0, 2.0, 0.5, 0.1, 0.0, 0.0]), np.array([0.3, -0.2])
    >>> rho = np.linalg.norm(x[:3] - a[0]) + b[0]
    >>> bool(np.isclose(ext.output_row(0, rho) @ ext.lift(x, b), rho**2 / 2 - a[0] @ a[0] / 2))
    True
    """
    row = np.zeros(C_h.shape[0] + 2 * m)
    row[: C_h.shape[0]] = C_h
    row[C_h.shape[0] + h] = rho
    row[C_h.shape[0] + m + h] = -0.5
    return row


def excitation_gramian(
    ext: BiasedRangeImmersion, xs: np.ndarray, us: np.ndarray, rhos: np.ndarray, dt: float
) -> np.ndarray:
    """The observability Gramian ``sum_k Phi_k^T C_k^T C_k Phi_k`` of a sampled window.

    Parameters
    ----------
    ext : BiasedRangeImmersion
    xs : ndarray (K, n)
        Unused but for its length (the Gramian of a state-affine system does not depend on
        the state); kept for the caller's symmetry with the trajectory it samples.
    us : ndarray (K, p)
        The inputs held over each step.
    rhos : ndarray (K, m)
        The ranges at each step (every anchor measured at each step).
    dt : float
        Step (s).

    Returns
    -------
    ndarray (dim, dim)
        Positive definite exactly when the window determines ``zeta`` (uniform
        observability over it); its smallest eigenvalue is the margin.
    """
    D = ext.dim
    G, Phi = np.zeros((D, D)), np.eye(D)
    zeta = np.zeros(D)  # the linearised form's rows at bh = 0
    for k in range(len(xs)):
        for h in range(ext.m):
            row = ext.measurement(h, float(rhos[k, h]), zeta)[0] @ Phi
            G += np.outer(row, row)
        step, _, _ = ext.transition(us[k], dt, np.zeros((ext.immersion.dim,) * 2), 0.0)
        Phi = step @ Phi
    return 0.5 * (G + G.T)
