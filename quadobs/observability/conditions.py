"""Persistence-of-excitation conditions of [IFAC2021] section 5.

They are stated for the single-output chain: ``y = 1/2 x^T C x`` and Assumption 1
(``C_m = 0`` for the sequence ``C_{i+1} = C_i A + A^T C_i`` of eq. 6). The observability
rows of the augmented pair are ``N_i = [e_i | r_i(t)]`` (proof of Proposition 5) with

.. math::

    r_0 = d^\\top, \\qquad r_{i+1} = r_i A + \\dot r_i + u^\\top B^\\top C_i \\quad \\text{(eq. 28)}.

The paper has no linear output term (``d = 0``, ``r_0 = 0``). With ``y = 1/2 x^T C x + d^T x``
the same differentiation of ``f_p(t) = C Phi(t + t_p, t_p) d`` in the proof of
Proposition 6 gives ``f_p^(k) = C_m S^k Phi_11 d_1 + (C_m S^k Phi_12 + r_k Phi_22) d_2``
with the recursion above started at ``r_0 = d^T``, so Propositions 5 to 7 hold
unchanged with that ``r``; this module uses it (for ``d = 0`` it is eq. 28 exactly).

By induction (eqs. 38, 39), ``r_k = d^T A^k + sum_{i<k} u^(i)T Gamma_{i+1,k}`` with
``Gamma_{1,k+1} = Gamma_{1,k} A + B^T C_k``,
``Gamma_{i+1,k+1} = Gamma_{i+1,k} A + Gamma_{i,k}`` and ``Gamma_{k+1,k} = 0``.

The sufficient conditions, each evaluated over sliding windows ``[t, t + delta]``:

* eq. 29 (Proposition 5): ``int det(sum_{i=m}^{kappa} r_i^T r_i) >= mu``; each ``r_i^T r_i``
  has rank one, so ``kappa >= m + n - 1`` is needed for a nonzero determinant
  (default ``kappa = m + n - 1``; derivatives of ``u`` up to order ``kappa - 1``);
* eq. 31 (Proposition 6): ``int Phi_22(s,t)^T r_m^T r_m Phi_22(s,t) ds >= mu I``, the
  Gramian of the pair ``(A, r_m(t))``;
* eq. 37 (Proposition 7, ``A`` with real eigenvalues): ``int r_m^T r_m >= mu I``;
* eq. 41 (Proposition 8, ``A`` with real eigenvalues and ``(A, Gamma)`` observable):
  ``int U_bar U_bar^T >= mu I`` with ``U_bar = (u, u', ..., u^(m-1))`` (eq. 40); it needs
  ``r_m = Gamma^T U_bar`` exactly, i.e. ``d^T A^m = 0``.

Integrals are the midpoint rule on the hold grid: the integrand is evaluated at the step
midpoints ``t_k + h/2`` and a window covers whole steps, so a window's integral is
``h`` times a sum of samples (exact zeros stay exact). Its error is at most
``delta h^2 max|f''| / 24`` for a smooth integrand. The margin of a window is the
smallest eigenvalue of the integral (the determinant integral for eq. 29). Whether it
is zero does not depend on units, so it is decided on the unit-diagonal form of the
integral (:func:`quadobs.observability.gramian.scaled_min_eig`): a window holds when that form's
smallest eigenvalue exceeds ``rtol`` (:data:`DEFAULT_ZERO_RTOL`), well above rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from numpy.lib.stride_tricks import sliding_window_view

from quadobs.core.immersion import lyapunov_sequence, observability_rank, vanishing_index
from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError
from quadobs.observability.gramian import scaled_min_eig, sliding_windows

__all__ = [
    "DEFAULT_ZERO_RTOL",
    "ChainStructure",
    "ConditionSeries",
    "chain_structure",
    "condition_eq29",
    "condition_eq31",
    "condition_eq37",
    "condition_eq41",
    "gamma_matrices",
    "r_sequence",
    "window_sums",
]

#: Relative size below which a window's margin counts as zero (module docstring).
DEFAULT_ZERO_RTOL = 1e-10


def gamma_matrices(A: np.ndarray, B: np.ndarray, Cs: np.ndarray, kmax: int) -> list[np.ndarray]:
    """``Gamma_{i+1,k}`` (eq. 39) for ``k = 0..kmax``: entry ``k`` has shape ``(k, p, n)``, row block ``i`` is ``Gamma_{i+1,k}``.

    ``Cs`` holds ``C_0 .. C_{kmax-1}`` (eq. 6) at least.
    """
    A, B = np.asarray(A, float), np.asarray(B, float)
    n, p = B.shape
    out = [np.zeros((0, p, n))]
    for k in range(kmax):
        prev = out[-1]
        nxt = np.zeros((k + 1, p, n))
        if k:
            nxt[:k] = prev @ A  # Gamma_{i+1,k} A
            nxt[1 : k + 1] += prev  # + Gamma_{i,k} (shifted one derivative up)
        nxt[0] += B.T @ Cs[k]  # Gamma_{0,k} = B^T C_k enters Gamma_{1,k+1}
        out.append(nxt)
    return out


@dataclass(frozen=True, eq=False)
class ChainStructure:
    """The single-output chain data behind eqs. 28-41.

    Attributes
    ----------
    system : QuadraticSystem
    m : int
        First index with ``C_m = 0`` (Assumption 1).
    kappa : int
        Last index of eq. 29's sum (``m + n - 1`` unless given).
    Cs : ndarray (kappa + 1, n, n)
        ``C_0 .. C_kappa`` (eq. 6; zero from ``m`` on).
    gammas : list of ndarray
        ``gammas[k]`` is ``(k, p, n)``: ``Gamma_{1,k} .. Gamma_{k,k}``.
    drift : ndarray (kappa + 1, n)
        ``d^T A^k``, the input-free part of ``r_k``.
    """

    system: QuadraticSystem
    m: int
    kappa: int
    Cs: np.ndarray = field(repr=False)
    gammas: list = field(repr=False)
    drift: np.ndarray = field(repr=False)

    @property
    def Gamma(self) -> np.ndarray:
        """``Gamma`` of eq. 40: ``(p m, n)``, the blocks ``Gamma_{1,m} .. Gamma_{m,m}`` stacked."""
        g = self.gammas[self.m]
        return g.reshape(-1, self.system.n)

    def real_eigenvalues(self, rtol: float = 1e-9) -> bool:
        """Whether ``A`` has real eigenvalues (Propositions 7, 8)."""
        ev = np.linalg.eigvals(self.system.A)
        scale = max(np.abs(ev).max(), 1.0)
        return bool(np.all(np.abs(ev.imag) <= rtol * scale))

    def gamma_observable(self) -> bool:
        """Whether ``(A, Gamma)`` is Kalman observable (Proposition 8)."""
        return observability_rank(self.system.A, self.Gamma) == self.system.n

    def affine_free(self, rtol: float = 1e-12) -> bool:
        """Whether ``r_m = Gamma^T U_bar`` exactly, i.e. ``d^T A^m = 0`` (always so for ``d = 0``)."""
        scale = (
            max(float(np.abs(self.system.d).max()), 1e-300)
            * max(float(np.linalg.norm(self.system.A, 2)), 1.0) ** self.m
        )
        return bool(np.abs(self.drift[self.m]).max() <= rtol * scale)


def chain_structure(system: QuadraticSystem, kappa: int | None = None) -> ChainStructure:
    """The chain quantities of ``system``.

    Raises
    ------
    QuadobsError
        If the system has several outputs (section 5 treats one), or Assumption 1 fails,
        or ``kappa < m + 1``.
    """
    if not isinstance(system, QuadraticSystem):
        raise QuadobsError(f"system: expected a QuadraticSystem, got {type(system).__name__}")
    if system.q != 1:
        raise QuadobsError(
            f"system: the PE conditions of Propositions 5-8 are stated for a single output, this system has q = {system.q}; "
            "use the Gramian measure (quadobs.observability.gramian), which applies to any immersion"
        )
    m = vanishing_index(system.A, system.C[0])
    n = system.n
    if m == 0:
        raise QuadobsError(
            "system: C = 0, the output is linear; the PE conditions concern a quadratic output"
        )
    kappa = m + n - 1 if kappa is None else int(kappa)
    if kappa < m + 1:
        raise QuadobsError(
            f"kappa: must be at least m + 1 = {m + 1} (det(r_m^T r_m) = 0), got {kappa}"
        )
    Cs = lyapunov_sequence(system.A, system.C[0], kappa)
    Cs[m:] = 0.0  # Assumption 1: exactly zero from m on
    gammas = gamma_matrices(system.A, system.B, Cs, kappa)
    drift = np.empty((kappa + 1, n))
    drift[0] = system.d[0]
    for k in range(kappa):
        drift[k + 1] = drift[k] @ system.A
    return ChainStructure(system, m, kappa, Cs, gammas, drift)


def r_sequence(
    chain: ChainStructure, derivatives: np.ndarray, kmax: int | None = None
) -> np.ndarray:
    """``r_0 .. r_kmax`` (eq. 28 via eq. 38) at the sample times.

    Parameters
    ----------
    chain : ChainStructure
    derivatives : ndarray (K, T, p)
        ``u, u', ..., u^(K-1)`` at ``T`` times; ``K >= kmax``.
    kmax : int, optional
        Default ``chain.kappa``.

    Returns
    -------
    ndarray (kmax + 1, T, n)
    """
    kmax = chain.kappa if kmax is None else int(kmax)
    if kmax > chain.kappa:
        raise QuadobsError(f"kmax: at most kappa = {chain.kappa}, got {kmax}")
    D = np.asarray(derivatives, dtype=float)
    if D.ndim != 3 or D.shape[0] < kmax or D.shape[2] != chain.system.p:
        raise QuadobsError(
            f"derivatives: expected shape (>= {kmax}, T, {chain.system.p}), got {D.shape}"
        )
    T, n = D.shape[1], chain.system.n
    out = np.empty((kmax + 1, T, n))
    for k in range(kmax + 1):
        out[k] = chain.drift[k]
        if k:
            out[k] += np.einsum("itp,ipn->tn", D[:k], chain.gammas[k])
    return out


@dataclass(frozen=True)
class ConditionSeries:
    """A sufficient condition evaluated over sliding windows.

    Attributes
    ----------
    margin : ndarray (W,)
        Smallest eigenvalue of the window integral (eq. 29: the determinant integral).
    relative : ndarray (W,)
        The margin without units, in ``[0, 1]``: the smallest eigenvalue of the integral
        scaled to a unit diagonal (:func:`quadobs.observability.gramian.scaled_min_eig`); eq. 29: the
        determinant integral over ``int prod_i (R)_ii``, its Hadamard bound.
    holds : ndarray of bool (W,)
        ``relative > rtol``.
    """

    margin: np.ndarray
    relative: np.ndarray
    holds: np.ndarray


def window_sums(F: np.ndarray, length: int, stride: int = 1) -> np.ndarray:
    """``h``-free sums of ``F (T, ...)`` over windows of ``length`` samples starting every ``stride``.

    Direct sums (no running differences), so a window of zeros sums to exactly zero.
    """
    F = np.asarray(F, dtype=float)
    T = F.shape[0]
    if not 1 <= length <= T:
        raise QuadobsError(f"window: {length} samples, expected between 1 and {T}")
    view = sliding_window_view(F, length, axis=0)[:: max(int(stride), 1)]
    return view.sum(axis=-1)


def _eig_condition(Wins: np.ndarray, rtol: float) -> ConditionSeries:
    Wins = 0.5 * (Wins + np.swapaxes(Wins, -1, -2))
    lo = np.linalg.eigvalsh(Wins)[..., 0]
    rel = scaled_min_eig(Wins)
    return ConditionSeries(lo, rel, rel > rtol)


def condition_eq37(
    r_m: np.ndarray, h: float, length: int, stride: int = 1, rtol: float = DEFAULT_ZERO_RTOL
) -> ConditionSeries:
    """Eq. 37: ``lambda_min(int_t^{t+delta} r_m^T r_m ds)`` per window; ``r_m (T, n)`` at the step midpoints."""
    R = np.einsum("ta,tb->tab", r_m, r_m)
    return _eig_condition(h * window_sums(R, length, stride), rtol)


def condition_eq41(
    ubar: np.ndarray, h: float, length: int, stride: int = 1, rtol: float = DEFAULT_ZERO_RTOL
) -> ConditionSeries:
    """Eq. 41: ``lambda_min(int U_bar U_bar^T ds)`` per window; ``ubar (T, p m)``."""
    R = np.einsum("ta,tb->tab", ubar, ubar)
    return _eig_condition(h * window_sums(R, length, stride), rtol)


def condition_eq31(
    A: np.ndarray,
    r_m: np.ndarray,
    h: float,
    length: int,
    stride: int = 1,
    rtol: float = DEFAULT_ZERO_RTOL,
) -> ConditionSeries:
    """Eq. 31: ``lambda_min(int Phi_22(s,t)^T r_m^T r_m Phi_22(s,t) ds)``, ``Phi_22(s, t) = e^{A (s - t)}`` (eq. 26b).

    The Gramian of the pair ``(A, r_m(t))``, composed step by step like
    :func:`quadobs.observability.gramian.sliding_windows` with the step term
    ``h e^{A^T h/2} r_m^T r_m e^{A h/2}`` (midpoint rule) and the step transition ``e^{A h}``.
    """
    A = np.asarray(A, dtype=float)
    T, n = r_m.shape
    E = sla.expm(A * h)
    Eh = sla.expm(A * 0.5 * h)
    q = r_m @ Eh  # (T, n): r_m(s_k) e^{A h/2}
    G = h * np.einsum("ta,tb->tab", q, q)
    Phi = np.broadcast_to(E, (T, n, n))
    W = sliding_windows(Phi, G, length)[1][:: max(int(stride), 1)]
    return _eig_condition(W, rtol)


def condition_eq29(
    r: np.ndarray, m: int, h: float, length: int, stride: int = 1, rtol: float = DEFAULT_ZERO_RTOL
) -> ConditionSeries:
    """Eq. 29: ``int det(sum_{i=m}^{kappa} r_i^T r_i) ds`` per window; ``r (kappa + 1, T, n)``.

    The determinant at each sample is ``prod_i R_ii det(R_hat)`` with ``R_hat`` the
    unit-diagonal form of ``R = sum r_i^T r_i``; a sample whose ``R_hat`` has its smallest
    eigenvalue below ``rtol`` (singular to working precision) counts as zero. The
    relative margin divides by ``int prod_i R_ii``, the Hadamard bound of the determinant.
    """
    R = np.einsum("ita,itb->tab", r[m:], r[m:])
    d = np.diagonal(R, axis1=-2, axis2=-1)
    hadamard = np.prod(d, axis=-1)
    ok = np.all(d > 0, axis=-1)
    s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    Rh = R * s[:, :, None] * s[:, None, :]
    det_h = np.where(ok, np.linalg.det(Rh), 0.0)
    det_h = np.where(scaled_min_eig(R) > rtol, det_h, 0.0)
    margin = h * window_sums(hadamard * det_h, length, stride)
    scale = h * window_sums(hadamard, length, stride)
    rel = np.divide(margin, scale, out=np.zeros_like(margin), where=scale > 0)
    return ConditionSeries(margin, rel, margin > 0)
