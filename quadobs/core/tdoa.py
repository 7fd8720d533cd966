"""Time differences of arrival in the quadratic-output framework: the squared-twice relation.

A TDOA between anchors ``i`` and ``j`` measures ``d_ij = r_i - r_j`` with ``r_k = |p - a_k|``.
This is not a quadratic form of the vehicle's state ``x = (p, v)`` (a difference of square
roots), so it is not an output of the class of [IFAC2021, eq. 4] / [ACC2024] as it stands.

Squaring ``d + r_j = r_i`` once gives, with ``w = a_i - a_j`` and
``c = (|a_i|^2 - |a_j|^2) / 2`` (so that ``r_i^2 - r_j^2 = -2 g``, ``g = w^T p - c``),

.. math:: g + \\tfrac12 d^2 + d\\, r_j = 0 ,

linear in ``(p, r_j)`` with the measured coefficient ``d``. The reference range ``r_j`` has
the dynamics ``r_j' = (p - a_j)^T v / r_j``, which is not polynomial: every derivative of
``r_j`` brings a higher power of ``1 / r_j``, so no finite polynomial immersion carries it.
Squaring a second time, ``(g + d^2/2)^2 = d^2 r_j^2``, removes it:

.. math::

    \\tfrac12\\, p^\\top C(d)\\, p + \\ell(d)^\\top p = y(d), \\qquad
    C(d) = 2 (w w^\\top - d^2 I), \\quad
    \\ell(d) = (d^2 - 2c)\\, w + 2 d^2 a_j, \\quad
    y(d) = d^2 (|a_j|^2 + c) - c^2 - \\tfrac14 d^4 ,

a quadratic output of ``x`` whose matrices are affine in the measured ``d^2``. Every such
form lies in ``span{ diag(S, 0) : S in Sym(dim) }``, so the immersion of the double
integrator with the outputs ``diag(E, 0)``, ``E`` running over a basis of ``Sym(dim)``
(:func:`tdoa_system`), makes each TDOA a *linear* output of the augmented state
``z = (xi, x)`` with a row known from the measurement (:meth:`TdoaImmersion.row`). Its
auxiliary states are the forms ``diag(S, 0)``, ``[[0, S], [S, 0]]`` and ``diag(0, S)``
(``L_A`` of the first is the second, of the second twice the third, of the third zero):
``3 dim (dim + 1) / 2`` of them, 18 in space and 9 in the plane, whatever the anchors.

Branches. The first squaring adds ``r_i + r_j = -d``, impossible for
``|d| < |a_i - a_j|`` (the triangle inequality); the second adds ``r_j - r_i = d``: the
relation holds on both sheets of the hyperboloid ``|r_i - r_j| = |d|``. The sign is lost
in one measurement, not in the estimate: the observer reconstructs ``z``, whose true value
satisfies every relation at every time, and the mirrored sheets of different pairs do not
share a trajectory (observability below).

Noise. The relation's residual ``G(d) = (g + d^2/2)^2 - d^2 r_j^2`` at the measured
``d + n`` is, to second order, ``G' n + G'' n^2 / 2`` with, at the truth,
``G' = -2 d r_i r_j`` and ``G'' = 2 d^2 - 2 d r_j - 2 r_j^2``, so its variance is
``G'^2 sigma^2 + G''^2 sigma^4 / 2`` (:func:`relation_variance`). At ``d = 0`` the first
order vanishes together with the relation's gradient in ``p`` (``g^2 = 0`` is a double
root); in the augmented coordinates the row is still informative (it constrains ``xi``
and ``p`` jointly) and the noise enters at second order only.

Observability. At one instant the rows of the pairs measured act on the ``pp`` block of
``xi`` (``dim (dim + 1) / 2`` entries) and on ``p``; nine generic rows in space (five in
the plane) determine them, and the dynamics carry the rest (``pv`` from the rate of
``pp``, ``vv`` from its second derivative, ``v`` from ``p'``). With fewer pairs at a time,
uniform observability of the LTV pair ``(A(u), C(t))`` needs persistent excitation: the
pairs measured over a window, at the positions flown, must give rows of full rank on the
augmented state (Theorem 3 of [IFAC2021] with ``C(t)`` in place of ``C``).
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.core.immersion import Immersion, immerse
from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError, as_array

__all__ = [
    "TdoaImmersion",
    "pair_constants",
    "relation_residual",
    "relation_variance",
    "symmetric_basis",
    "tdoa_system",
]


def symmetric_basis(dim: int) -> np.ndarray:
    """A basis ``E (dim (dim + 1) / 2, dim, dim)`` of ``Sym(dim)``: ``e_k e_k^T`` on the
    diagonal, ``e_k e_l^T + e_l e_k^T`` off it (``k < l``), row-major."""
    out = []
    for k in range(dim):
        for l in range(k, dim):
            E = np.zeros((dim, dim))
            E[k, l] = E[l, k] = 1.0
            out.append(E)
    return np.array(out)


def _coordinates(S: np.ndarray) -> np.ndarray:
    """Coordinates of a symmetric ``S`` in :func:`symmetric_basis` (upper triangle, row-major)."""
    rows, cols = np.triu_indices(S.shape[0])
    return S[rows, cols]


def tdoa_system(dim: int) -> QuadraticSystem:
    """The double integrator ``x = (p, v)`` in ``R^dim`` with the outputs ``diag(E, 0)``,
    ``E`` in :func:`symmetric_basis`: the quadratic parts that any TDOA relation can take.

    Its immersion (:func:`quadobs.core.immersion.immerse`) has ``3 dim (dim + 1) / 2``
    auxiliary states (module docstring).
    """
    if dim not in (2, 3):
        raise QuadobsError(f"dim: expected 2 or 3, got {dim}")
    eye, zero = np.eye(dim), np.zeros((dim, dim))
    A = np.block([[zero, eye], [zero, zero]])
    B = np.vstack([zero, eye])
    basis = symmetric_basis(dim)
    C = np.zeros((basis.shape[0], 2 * dim, 2 * dim))
    C[:, :dim, :dim] = basis
    return QuadraticSystem(A, B, C)


def pair_constants(anchors: np.ndarray, i: int, j: int) -> tuple[np.ndarray, float]:
    """``w = a_i - a_j`` and ``c = (|a_i|^2 - |a_j|^2) / 2``: ``r_i^2 - r_j^2 = -2 (w^T p - c)``."""
    ai, aj = anchors[i], anchors[j]
    return ai - aj, 0.5 * float(ai @ ai - aj @ aj)


def relation_residual(anchors: np.ndarray, i: int, j: int, d: float, p: np.ndarray) -> float:
    """``G(d) = 1/2 p^T C(d) p + l(d)^T p - y(d)`` (module docstring); zero on both sheets of
    ``|r_i - r_j| = |d|``."""
    w, c = pair_constants(anchors, i, j)
    g = float(w @ p) - c
    rj2 = float((p - anchors[j]) @ (p - anchors[j]))
    return (g + 0.5 * d * d) ** 2 - d * d * rj2


def relation_variance(d: float, ri: float, rj: float, sigma: float) -> float:
    """Variance of the relation's residual for a TDOA ``d`` with noise ``N(0, sigma^2)``,
    to second order: ``G'^2 sigma^2 + G''^2 sigma^4 / 2`` with ``G' = -2 d r_i r_j`` and
    ``G'' = 2 d^2 - 2 d r_j - 2 r_j^2`` (module docstring)."""
    g1 = -2.0 * d * ri * rj
    g2 = 2.0 * d * d - 2.0 * d * rj - 2.0 * rj * rj
    return g1 * g1 * sigma * sigma + 0.5 * g2 * g2 * sigma**4


class TdoaImmersion:
    """The immersion of :func:`tdoa_system` and the linear rows of TDOA measurements on it.

    Parameters
    ----------
    anchors : array_like, shape (m, dim)
        Anchor positions; distinct.

    Attributes
    ----------
    immersion : Immersion
        ``z = (xi, x)``, ``z' = A(u) z + B u`` exactly ([ACC2024, Alg. 1]).
    """

    def __init__(self, anchors) -> None:
        anchors = as_array("anchors", anchors)
        if anchors.ndim != 2 or anchors.shape[1] not in (2, 3) or anchors.shape[0] < 2:
            raise QuadobsError(
                f"anchors: expected shape (m, 2) or (m, 3) with m >= 2, got {anchors.shape}"
            )
        gaps = np.linalg.norm(anchors[:, None] - anchors[None], axis=-1)
        np.fill_diagonal(gaps, np.inf)
        if gaps.min() == 0.0:
            i, j = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
            raise QuadobsError(f"anchors: anchors {i} and {j} coincide; a TDOA needs two places")
        self.anchors = anchors
        self.dim = int(anchors.shape[1])
        self.immersion: Immersion = immerse(tdoa_system(self.dim))
        # F of the immersion maps an output (a basis form) to auxiliary coefficients.
        self._aux_rows = np.asarray(self.immersion.aux_output, dtype=float)
        self._identity = _coordinates(np.eye(self.dim))

    @property
    def dim_z(self) -> int:
        """Dimension of the augmented state ``z``."""
        return self.immersion.dim

    def lift(self, x: np.ndarray) -> np.ndarray:
        """``z = (xi(x), x)`` for ``x (..., 2 dim)``."""
        return self.immersion.lift(x)

    def row(self, i: int, j: int, d: float) -> tuple[np.ndarray, float]:
        """The row ``c (N,)`` and value ``y`` with ``c^T z = y`` for a TDOA ``d = r_i - r_j``.

        ``c = (F^T s(d), l(d), 0)`` with ``s(d)`` the coordinates of ``C(d) = 2 w w^T - 2 d^2 I``
        in the output basis (module docstring).
        """
        m = self.anchors.shape[0]
        if not (0 <= i < m and 0 <= j < m and i != j):
            raise QuadobsError(f"anchors: expected two distinct indices below {m}, got ({i}, {j})")
        if not math.isfinite(d):
            raise QuadobsError(f"value: a TDOA must be finite, got {d}")
        w, c = pair_constants(self.anchors, i, j)
        dd = d * d
        s = 2.0 * _coordinates(np.outer(w, w)) - 2.0 * dd * self._identity
        k, dim = self.immersion.n_aux, self.dim
        row = np.zeros(self.dim_z)
        row[:k] = s @ self._aux_rows
        row[k : k + dim] = (dd - 2.0 * c) * w + 2.0 * dd * self.anchors[j]
        aj2 = float(self.anchors[j] @ self.anchors[j])
        return row, dd * (aj2 + c) - c * c - 0.25 * dd * dd
