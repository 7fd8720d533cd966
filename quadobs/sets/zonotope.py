"""Zonotopes and interval matrices: the set calculus of [LE2013] section 2.

A zonotope ``Z = p (+) H B^m = {p + H z : ||z||_inf <= 1}`` is stored as its centre
``p (n,)`` and generator matrix ``H (n, m)``. Everything returns new objects:

* Property 1: :meth:`Zonotope.minkowski_sum` (``p1 + p2``, ``[H1 H2]``), also ``Z1 + Z2``;
* Property 2: :meth:`Zonotope.linear_map` (``K p``, ``K H``), also ``K @ Z``;
* Property 3: :meth:`Zonotope.reduce`, with a pluggable method (:data:`REDUCTION_METHODS`:
  ``"combastel"``, the norm sort of the paper, ``"girard"``, ``"pca"``, ``"parallelotope"``,
  or a callable);
* Properties 4 and 5: :func:`interval_zonotope` (``p (+) [M] B^m``) and
  :func:`interval_image` (``[A] Z``, the outer approximation at the end of section 4.1);
* Property 6: :meth:`Zonotope.strip_intersection` (the family ``Z^(lambda)``), on raw arrays
  :func:`strip_update` (the one implementation, used by every zonotopic estimator), with the
  segment (F-radius) gain :func:`segment_gain`;
* sizes: :meth:`~Zonotope.interval_hull`, :meth:`~Zonotope.p_radius`,
  :meth:`~Zonotope.f_radius`, :meth:`~Zonotope.volume`, :meth:`~Zonotope.support`;
* membership: :meth:`~Zonotope.contains` (half-spaces or a linear program),
  :meth:`~Zonotope.halfspaces`, :meth:`~Zonotope.vertices` (plane zonotopes).

Combinatorial quantities (volume, half-spaces, P-radius in more than two dimensions)
enumerate subsets of generators; they refuse (``QuadobsError``) beyond
:data:`MAX_SUBSETS` subsets rather than run for hours.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from itertools import combinations, product
from math import comb
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError, as_array

__all__ = [
    "MAX_SUBSETS",
    "REDUCTION_METHODS",
    "IntervalMatrix",
    "Zonotope",
    "interval_image",
    "interval_zonotope",
    "reduce_generators",
    "row_sum_diag",
    "segment_gain",
    "strip_update",
]

#: Largest number of generator subsets a combinatorial method may enumerate.
MAX_SUBSETS = 200_000


def row_sum_diag(M: np.ndarray) -> np.ndarray:
    """``rs(M)``: the diagonal matrix of the row sums of ``|M|`` (section 2)."""
    M = np.asarray(M, dtype=float)
    return np.diag(np.abs(M).sum(axis=1))


def _drop_zero_columns(H: np.ndarray) -> np.ndarray:
    keep = np.any(H != 0.0, axis=0)
    return H if keep.all() else H[:, keep]


# --------------------------------------------------------------------------------------
# Order reduction (Property 3 and alternatives)
# --------------------------------------------------------------------------------------


def _reduce_combastel(H: np.ndarray, s: int) -> np.ndarray:
    """Property 3: keep the ``s - n`` longest generators (Euclidean norm), box the rest with ``rs``."""
    n = H.shape[0]
    order = np.argsort(-np.einsum("ij,ij->j", H, H), kind="stable")
    keep, rest = H[:, order[: s - n]], H[:, order[s - n :]]
    return np.hstack([keep, row_sum_diag(rest)])


def _reduce_girard(H: np.ndarray, s: int) -> np.ndarray:
    """Girard (2005): box the generators with the smallest ``||h||_1 - ||h||_inf`` (the flattest ones)."""
    n = H.shape[0]
    a = np.abs(H)
    score = a.sum(axis=0) - a.max(axis=0)
    order = np.argsort(score, kind="stable")
    rest, keep = H[:, order[: H.shape[1] - (s - n)]], H[:, order[H.shape[1] - (s - n) :]]
    return np.hstack([keep, row_sum_diag(rest)])


def _reduce_pca(H: np.ndarray, s: int) -> np.ndarray:
    """Norm sort as in Property 3, but the rest is boxed along the principal axes of ``H H^T``.

    With ``T`` orthogonal (the left singular vectors of ``H``), ``H_Q B ⊆ T rs(T^T H_Q) B``;
    the box is aligned with the zonotope rather than with the coordinate axes, which
    matters when the coordinates have very different scales.
    """
    n = H.shape[0]
    T = np.linalg.svd(H, full_matrices=False)[0]
    if T.shape[1] < n:
        T = np.linalg.qr(np.hstack([T, np.eye(n)]))[0][:, :n]
    order = np.argsort(-np.einsum("ij,ij->j", H, H), kind="stable")
    keep, rest = H[:, order[: s - n]], H[:, order[s - n :]]
    return np.hstack([keep, T @ row_sum_diag(T.T @ rest)])


_GEQP3_LWORK: dict[tuple[int, int], int] = {}


def _pivoted_qr_diag(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(|diag R|, piv)`` of ``A[:, piv] = Q R`` (QR with column pivoting, LAPACK ``geqp3``).

    The call of ``scipy.linalg.qr(A, mode="economic", pivoting=True)`` without forming ``Q``
    (same routine, same workspace, so the same numbers); the workspace size is queried once
    per shape.
    """
    from scipy.linalg import lapack

    lwork = _GEQP3_LWORK.get(A.shape)
    if lwork is None:
        lwork = _GEQP3_LWORK[A.shape] = int(lapack.dgeqp3(A, lwork=-1)[-2][0].real)
    qr, jpvt, _, _, info = lapack.dgeqp3(A, lwork=lwork)
    if info < 0:
        raise QuadobsError(f"generators: the pivoted QR failed (argument {-info} of geqp3)")
    return np.abs(np.diag(qr)), jpvt - 1


def _reduce_parallelotope(H: np.ndarray, s: int) -> np.ndarray:
    """Norm sort as in Property 3, but the rest is enclosed in a parallelotope framed by some of its own generators.

    ``n`` columns ``T`` of ``H_Q`` are chosen by QR with column pivoting (the longest, then the
    most independent), and ``H_Q B ⊆ T rs(T^{-1} H_Q) B`` (Kühn 1998's idea against the wrapping
    effect). A generator of the frame is represented exactly (its coordinates are a unit
    vector), so a box produced by an earlier reduction and then mapped linearly is taken
    over as the frame instead of being boxed again in the coordinate axes: repeated
    reductions after linear maps do not compound.
    """
    import scipy.linalg as sla

    n = H.shape[0]
    order = np.argsort(-np.einsum("ij,ij->j", H, H), kind="stable")
    keep, rest = H[:, order[: s - n]], H[:, order[s - n :]]
    if not np.isfinite(rest).all():
        raise QuadobsError(
            "generators: non-finite entries; the parallelotope reduction needs a finite set"
        )
    diag, piv = _pivoted_qr_diag(rest)
    good = int(np.sum(diag > 1e-9 * max(diag[0] if diag.size else 0.0, 1e-300)))
    T = rest[:, piv[:good]]
    if good < n:  # complete the frame with directions orthogonal to the rest's span
        Q = sla.qr(rest, mode="economic", pivoting=True)[0]
        basis = np.linalg.qr(np.hstack([Q[:, :good], np.eye(n)]))[0]
        T = np.hstack([T, basis[:, good:n]])
    coords = np.linalg.solve(T, rest)
    return np.hstack([keep, T * np.abs(coords).sum(axis=1)])


#: Named reduction methods ``f(H (n, m), s) -> H' (n, s)`` with ``H B^m ⊆ H' B^s``.
REDUCTION_METHODS: dict[str, Callable[[np.ndarray, int], np.ndarray]] = {
    "combastel": _reduce_combastel,
    "girard": _reduce_girard,
    "pca": _reduce_pca,
    "parallelotope": _reduce_parallelotope,
}


def reduce_generators(
    H: np.ndarray, max_generators: int, method: str | Callable = "combastel"
) -> np.ndarray:
    """Generators of an outer approximation ``H' B^s ⊇ H B^m`` with at most ``max_generators`` columns.

    Parameters
    ----------
    H : ndarray (n, m)
    max_generators : int
        ``s >= n``; nothing happens when ``m <= s``.
    method : str or callable
        A key of :data:`REDUCTION_METHODS` or ``f(H, s) -> H'`` (its result must have at
        most ``s`` columns; containment is the callable's responsibility).
    """
    n, m = H.shape
    s = int(max_generators)
    if s < n:
        raise QuadobsError(f"max_generators: must be at least the dimension {n}, got {s}")
    if m <= s:
        return H
    if callable(method):
        fn: Callable[..., Any] = method
    else:
        found = REDUCTION_METHODS.get(method)
        if found is None:
            raise QuadobsError(
                f"method: unknown reduction {method!r}; expected one of {', '.join(REDUCTION_METHODS)} or a callable"
            )
        fn = found
    out = np.asarray(fn(H, s), dtype=float)
    if out.ndim != 2 or out.shape[0] != n or out.shape[1] > s:
        raise QuadobsError(
            f"method: the reduction returned shape {out.shape}, expected ({n}, <= {s})"
        )
    return out


# --------------------------------------------------------------------------------------
# The zonotope
# --------------------------------------------------------------------------------------


def segment_gain(
    H: np.ndarray, c: np.ndarray, phi: float, Hc: np.ndarray | None = None
) -> np.ndarray:
    """Segment (F-radius) minimisation: ``argmin_lambda ||H(lambda)||_F^2`` over Property 6's family.

    For ``H(lambda) = [(I - lambda c^T) H, phi lambda]``,
    ``d/dlambda ||H(lambda)||_F^2 = -2 (I - lambda c^T) H H^T c + 2 phi^2 lambda = 0`` gives

    .. math::

        \\lambda = \\frac{H g}{g^\\top g + \\phi^2}, \\qquad g = H^\\top c

    (``0`` when the denominator is not positive: a degenerate set and an exact output).

    Parameters
    ----------
    H : ndarray (n, m)
        Generators of the set.
    c : ndarray (n,)
        Normal of the strip ``|c^T x - y| <= phi``.
    phi : float
        Half-width of the strip.
    Hc : ndarray (m,), optional
        ``H^T c`` when already at hand.

    Returns
    -------
    ndarray (n,)

    Examples
    --------
    >>> segment_gain(np.eye(2), np.array([1.0, 0.0]), 1.0).tolist()
    [0.5, 0.0]
    """
    g = H.T @ c if Hc is None else Hc
    den = float(g @ g) + phi * phi
    return H @ g / den if den > 0 else np.zeros_like(c)


def strip_update(
    p: np.ndarray, H: np.ndarray, c: np.ndarray, y: float, phi: float, lam: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Property 6 on raw arrays: a zonotope containing ``(p (+) H B^m) ∩ {x : |c^T x - y| <= phi}``.

    .. math::

        p^{(\\lambda)} = p + \\lambda (y - c^\\top p), \\qquad
        H^{(\\lambda)} = [(I - \\lambda c^\\top) H, \\ \\phi \\lambda],

    valid for any ``lambda (n,)`` ([LE2013, Property 6]). The one implementation of the strip
    intersection: :meth:`Zonotope.strip_intersection` (validated) and the estimators' loops
    (unvalidated, float64 arrays of matching shapes) call it.

    Parameters
    ----------
    p : ndarray (n,)
    H : ndarray (n, m)
    c : ndarray (n,)
    y, phi : float
        Centre and half-width (``phi >= 0``) of the strip.
    lam : ndarray (n,), optional
        The gain; ``None``: :func:`segment_gain`.

    Returns
    -------
    (ndarray (n,), ndarray (n, m + 1))
        New arrays (contiguous): the centre and generators.
    """
    Hc = H.T @ c
    if lam is None:
        lam = segment_gain(H, c, phi, Hc)
    p_new = p + lam * (y - c @ p)
    m = H.shape[1]
    H_new = np.empty((H.shape[0], m + 1))
    np.subtract(H, np.outer(lam, Hc), out=H_new[:, :m])
    np.multiply(phi, lam, out=H_new[:, m])
    return p_new, H_new


@dataclass(frozen=True, eq=False)
class Zonotope:
    """``Z = p (+) H B^m`` (section 2): centre ``center (n,)``, generators ``generators (n, m)``.

    Raises
    ------
    QuadobsError
        On a wrong shape or a non-finite entry.
    """

    center: np.ndarray
    generators: np.ndarray

    __array_ufunc__ = None  # ``K @ Z`` with a NumPy ``K`` calls :meth:`__rmatmul__`

    def __post_init__(self) -> None:
        p = as_array("center", self.center, (None,))
        g = self.generators
        if np.size(g) == 0:
            g = np.zeros((p.shape[0], 0))
        H = as_array("generators", g, (p.shape[0], None))
        p.setflags(write=False)
        H.setflags(write=False)
        object.__setattr__(self, "center", p)
        object.__setattr__(self, "generators", H)

    # -- construction ----------------------------------------------------------------

    @classmethod
    def _trusted(cls, center: np.ndarray, generators: np.ndarray) -> Zonotope:
        """A zonotope from arrays already checked: float64, ``(n,)`` and ``(n, m)``, finite, read-only, owned by it.

        For the hot loops of the estimators: no conversion and no validation.
        """
        Z = object.__new__(cls)
        Z.__dict__.update(center=center, generators=generators)
        return Z

    @classmethod
    def from_box(cls, lower, upper) -> Zonotope:
        """The box ``[lower, upper]`` (``(n,)`` each) as a zonotope with ``n`` generators."""
        lo = as_array("lower", lower, (None,))
        hi = as_array("upper", upper, (lo.shape[0],))
        if np.any(hi < lo):
            raise QuadobsError("upper: must not be below lower")
        with np.errstate(over="ignore"):
            center, radius = 0.5 * lo + 0.5 * hi, 0.5 * hi - 0.5 * lo
        if not (np.isfinite(center).all() and np.isfinite(radius).all()):
            raise QuadobsError(
                "upper: the box [lower, upper] is too large to represent in double precision"
            )
        return cls(center, np.diag(radius))

    @property
    def dim(self) -> int:
        return self.center.shape[0]

    @property
    def order(self) -> int:
        """Number of generators ``m``."""
        return self.generators.shape[1]

    # -- Properties 1, 2, 3 -----------------------------------------------------------

    def minkowski_sum(self, other: Zonotope | np.ndarray) -> Zonotope:
        """Property 1: ``(p1 + p2) (+) [H1 H2] B``; a vector ``(n,)`` translates."""
        if isinstance(other, Zonotope):
            if other.dim != self.dim:
                raise QuadobsError(f"other: dimension {other.dim} differs from {self.dim}")
            return Zonotope(
                self.center + other.center, np.hstack([self.generators, other.generators])
            )
        v = as_array("other", other, (self.dim,))
        return Zonotope(self.center + v, self.generators)

    __add__ = minkowski_sum

    def linear_map(self, K) -> Zonotope:
        """Property 2: ``K Z = K p (+) K H B``."""
        K = as_array("K", K, (None, self.dim))
        return Zonotope(K @ self.center, K @ self.generators)

    def __rmatmul__(self, K) -> Zonotope:
        return self.linear_map(K)

    def reduce(self, max_generators: int, method: str | Callable = "combastel") -> Zonotope:
        """Property 3: an outer approximation with at most ``max_generators`` generators (see :func:`reduce_generators`)."""
        H = reduce_generators(self.generators, max_generators, method)
        return self if H is self.generators else Zonotope(self.center, H)

    def drop_zero_generators(self) -> Zonotope:
        """The same set without its zero columns."""
        H = _drop_zero_columns(self.generators)
        return self if H is self.generators else Zonotope(self.center, H)

    # -- Property 6 -------------------------------------------------------------------

    def strip_intersection(self, c, y: float, phi: float, lam=None) -> Zonotope:
        """Property 6: ``Z ∩ {x : |c^T x - y| <= phi} ⊆ p^(lam) (+) [(I - lam c^T) H, phi lam] B``.

        ``p^(lam) = p + lam (y - c^T p)``; valid for any ``lam (n,)``; ``None``: the segment
        gain (:func:`segment_gain`). Computed by :func:`strip_update`.
        """
        c = as_array("c", c, (self.dim,))
        if lam is not None:
            lam = as_array("lam", lam, (self.dim,))
        if not phi >= 0:
            raise QuadobsError(f"phi: the strip half-width must be non-negative, got {phi}")
        return Zonotope(*strip_update(self.center, self.generators, c, float(y), float(phi), lam))

    # -- sizes ------------------------------------------------------------------------

    def interval_hull(self) -> np.ndarray:
        """The smallest box containing ``Z``: ``(n, 2)`` rows ``[p_i - r_i, p_i + r_i]``, ``r = |H| 1``."""
        r = np.abs(self.generators).sum(axis=1)
        return np.stack([self.center - r, self.center + r], axis=1)

    def widths(self) -> np.ndarray:
        """Widths ``2 |H| 1`` of the interval hull, ``(n,)``."""
        return 2.0 * np.abs(self.generators).sum(axis=1)

    def f_radius(self) -> float:
        """F-radius: the Frobenius norm ``||H||_F`` (the quantity segment minimisation minimises, squared)."""
        return float(np.linalg.norm(self.generators))

    def support(self, d) -> np.ndarray:
        """Support function ``h_Z(d) = d^T p + ||H^T d||_1`` for ``d (n,)`` or ``(k, n)``."""
        d = np.asarray(d, dtype=float)
        return d @ self.center + np.abs(d @ self.generators).sum(axis=-1)

    def _subsets(self, size: int) -> int:
        count = comb(self.order, size)
        if count > MAX_SUBSETS:
            raise QuadobsError(
                f"zonotope: {count} subsets of {size} of its {self.order} generators exceed MAX_SUBSETS = {MAX_SUBSETS}; "
                "reduce the order first"
            )
        return count

    def volume(self) -> float:
        """Exact volume ``2^n sum_{|S| = n} |det H_S|`` over the ``n``-subsets ``S`` of generators."""
        n, m = self.dim, self.order
        if m < n:
            return 0.0
        self._subsets(n)
        H = self.generators
        if n == 1:
            return float(2.0 * np.abs(H).sum())
        if n == 2:
            i, j = np.triu_indices(m, 1)
            det = H[0, i] * H[1, j] - H[1, i] * H[0, j]
            return float(4.0 * np.abs(det).sum())
        idx = np.array(list(combinations(range(m), n)))
        return float(2.0**n * np.abs(np.linalg.det(H[:, idx].transpose(1, 0, 2))).sum())

    def halfspaces(self) -> tuple[np.ndarray, np.ndarray]:
        """Facet description ``Z = {x : G x <= b}``, ``G`` with unit rows.

        For a full-dimensional zonotope each facet normal is orthogonal to ``n - 1``
        generators: ``g`` spans the null space of ``H_T^T`` (``|T| = n - 1``, rank ``n - 1``),
        and ``±g^T x <= ±g^T p + ||H^T g||_1``. Duplicated normals are kept (harmless).

        Raises
        ------
        QuadobsError
            If ``H`` does not have rank ``n`` (the zonotope is flat) or too many subsets.
        """
        n, m = self.dim, self.order
        H = self.generators
        if np.linalg.matrix_rank(H) < n:
            raise QuadobsError(
                "zonotope: the generators do not span the space (flat zonotope); no facet description"
            )
        if n == 1:
            G = np.array([[1.0]])
        else:
            self._subsets(n - 1)
            normals = []
            for T in combinations(range(m), n - 1):
                sub = H[:, T]
                u, s, _ = np.linalg.svd(sub, full_matrices=True)
                if s[-1] <= 1e-12 * max(s[0], 1e-300):
                    continue
                normals.append(u[:, -1])
            G = np.array(normals)
        G = np.vstack([G, -G])
        b = G @ self.center + np.abs(G @ H).sum(axis=1)
        return G, b

    def vertex_candidates(self) -> np.ndarray:
        """Points of ``Z`` that include all its vertices: ``p + H sign(H^T g)`` for normals ``g`` of ``(n-1)``-subsets.

        Each vertex maximises ``g^T x`` over a full-dimensional cone of directions, whose
        boundary holds a direction orthogonal to ``n - 1`` generators; the generators
        orthogonal to such a direction take every sign. Returns ``(k, n)``.
        """
        n, m = self.dim, self.order
        H, p = self.generators, self.center
        if m == 0:
            return p[None]
        if m <= n or n == 1:
            if m > 20:
                raise QuadobsError(
                    f"zonotope: 2^{m} sign vectors to enumerate; reduce the order first"
                )
            signs = np.array(list(product((-1.0, 1.0), repeat=m)))
            return p + signs @ H.T
        self._subsets(n - 1)
        pts = []
        for T in combinations(range(m), n - 1):
            u, s, _ = np.linalg.svd(H[:, T], full_matrices=True)
            g = u[:, -1]
            proj = g @ H
            scale = np.abs(H).sum() * 1e-12
            zero = np.flatnonzero(np.abs(proj) <= scale)
            base = np.sign(proj)
            for pattern in product((-1.0, 1.0), repeat=len(zero)):
                z = base.copy()
                z[zero] = pattern
                pts.append(H @ z)
        d = np.array(pts)
        # zonotopes are centrally symmetric: p - H z is a vertex too
        return p + np.vstack([d, -d])

    def p_radius(self, P=None) -> float:
        """P-radius ``L = max_{z in Z} ||z - p||_P^2`` (section 2), exactly.

        The maximum of a convex function over ``Z`` is attained at a vertex, so it is
        taken over :meth:`vertex_candidates`. ``P`` defaults to the identity.
        """
        n = self.dim
        P = np.eye(n) if P is None else as_array("P", P, (n, n))
        if self.order == 0:
            return 0.0
        d = self.vertex_candidates() - self.center
        return float(np.max(np.einsum("ki,ij,kj->k", d, P, d)))

    def vertices(self) -> np.ndarray:
        """Vertices of a plane zonotope in counter-clockwise order, ``(2m', 2)`` (``m'`` non-zero generators)."""
        if self.dim != 2:
            raise QuadobsError(
                f"vertices: only plane zonotopes (n = 2) are supported, got n = {self.dim}"
            )
        H = _drop_zero_columns(self.generators)
        p = self.center
        if H.shape[1] == 0:
            return p[None].copy()
        # point every generator into the upper half plane, then sort by angle
        flip = (H[1] < 0) | ((H[1] == 0) & (H[0] < 0))
        G = np.where(flip, -H, H)
        ang = np.arctan2(G[1], G[0])
        G = G[:, np.argsort(ang, kind="stable")]
        start = p - G.sum(
            axis=1
        )  # lowest-angle walk starts at the extreme point in direction (0, -1) side
        steps = 2.0 * np.hstack([G, -G])
        return start + np.vstack([np.zeros(2), np.cumsum(steps.T, axis=0)[:-1]])

    # -- membership -------------------------------------------------------------------

    def contains(self, x, *, tol: float = 1e-9, method: str = "auto") -> np.ndarray | bool:
        """Whether the points ``x (n,)`` or ``(k, n)`` lie in ``Z`` (to a relative tolerance).

        ``method="halfspace"`` tests the facet inequalities; ``"lp"`` solves
        ``min ||z||_inf s.t. H z = x - p`` per point (HiGHS, through
        ``scipy.optimize.linprog``); ``"auto"`` uses half-spaces when there are at most
        5000 of them. The tolerance is relative to the size of ``Z`` (``sum |H|``).
        """
        x = np.asarray(x, dtype=float)
        single = x.ndim == 1
        X = np.atleast_2d(x)
        if X.shape[1] != self.dim:
            raise QuadobsError(f"x: expected points of dimension {self.dim}, got shape {x.shape}")
        if method == "auto":
            n, m = self.dim, self.order
            cheap = (
                n <= m
                and comb(m, max(n - 1, 0)) <= 2500
                and np.linalg.matrix_rank(self.generators) == n
            )
            method = "halfspace" if cheap else "lp"
        if method == "halfspace":
            G, b = self.halfspaces()
            scale = max(np.abs(self.generators).sum(), 1.0)
            inside = np.all(X @ G.T <= b + tol * scale, axis=1)
        elif method == "lp":
            inside = np.array([self.inf_norm_coordinates(row) <= 1.0 + tol for row in X])
        else:
            raise QuadobsError(f"method: expected 'auto', 'halfspace' or 'lp', got {method!r}")
        return bool(inside[0]) if single else inside

    def inf_norm_coordinates(self, x) -> float:
        """``min {||z||_inf : p + H z = x}`` (``inf`` when ``x`` is outside the affine hull); ``<= 1`` iff ``x in Z``."""
        from scipy.optimize import linprog

        x = as_array("x", x, (self.dim,))
        n, m = self.dim, self.order
        if m == 0:
            return 0.0 if np.allclose(x, self.center) else np.inf
        # variables (z, t): minimise t, H z = x - p, z - t <= 0, -z - t <= 0
        c = np.zeros(m + 1)
        c[-1] = 1.0
        A_eq = np.hstack([self.generators, np.zeros((n, 1))])
        eye = np.eye(m)
        A_ub = np.vstack([np.hstack([eye, -np.ones((m, 1))]), np.hstack([-eye, -np.ones((m, 1))])])
        res = linprog(
            c,
            A_ub=A_ub,
            b_ub=np.zeros(2 * m),
            A_eq=A_eq,
            b_eq=x - self.center,
            bounds=[(None, None)] * m + [(0, None)],
            method="highs",
        )
        if res.status == 2:
            return float("inf")
        if res.status != 0:
            raise QuadobsError(f"contains: the linear program failed ({res.message})")
        return float(res.fun)


# --------------------------------------------------------------------------------------
# Interval matrices (Properties 4 and 5)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class IntervalMatrix:
    """``[M]`` with entries ``[lower_ij, upper_ij]`` (section 2); ``mid`` and ``rad`` derived.

    Raises
    ------
    QuadobsError
        On mismatched shapes, non-finite entries or ``upper < lower``.
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self) -> None:
        lo = as_array("lower", self.lower, ndim=2)
        hi = as_array("upper", self.upper, lo.shape)
        if np.any(hi < lo):
            i, j = (int(v) for v in np.argwhere(hi < lo)[0])
            raise QuadobsError(
                f"upper: entry ({i}, {j}) is below the lower bound ({hi[i, j]} < {lo[i, j]})"
            )
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @classmethod
    def from_mid_rad(cls, mid, rad) -> IntervalMatrix:
        mid = as_array("mid", mid, ndim=2)
        rad = as_array("rad", rad, mid.shape)
        if np.any(rad < 0):
            raise QuadobsError("rad: radii must be non-negative")
        return cls(mid - rad, mid + rad)

    @classmethod
    def point(cls, M) -> IntervalMatrix:
        M = as_array("M", M, ndim=2)
        return cls(M, M)

    @property
    def shape(self) -> tuple[int, int]:
        return self.lower.shape

    @property
    def mid(self) -> np.ndarray:
        return 0.5 * (self.lower + self.upper)

    @property
    def rad(self) -> np.ndarray:
        return 0.5 * (self.upper - self.lower)

    def vertices(self) -> np.ndarray:
        """``vert[M]``: every matrix with each interval entry at one of its ends, ``(2^q, r, c)``.

        ``q`` counts the entries with a non-zero radius (the point entries do not double
        the count).
        """
        lo, hi = self.lower, self.upper
        idx = np.argwhere(hi > lo)
        if len(idx) > 20:
            raise QuadobsError(
                f"vertices: {len(idx)} interval entries give 2^{len(idx)} vertices (at most 20 entries)"
            )
        out = np.repeat(lo[None], 2 ** len(idx), axis=0)
        for v, choice in enumerate(product((0, 1), repeat=len(idx))):
            for (i, j), c in zip(idx, choice):
                out[v, i, j] = hi[i, j] if c else lo[i, j]
        return out

    def contains(self, M, tol: float = 0.0) -> bool:
        M = np.asarray(M, dtype=float)
        return bool(np.all(M >= self.lower - tol) and np.all(M <= self.upper + tol))

    def __matmul__(self, N) -> IntervalMatrix:
        """Property 5: ``[M] N`` with ``mid = mid[M] N`` and ``rad = rad[M] |N|``."""
        N = (
            as_array("N", N, (self.shape[1], None))
            if np.ndim(N) == 2
            else as_array("N", N, (self.shape[1],))[:, None]
        )
        return IntervalMatrix.from_mid_rad(self.mid @ N, self.rad @ np.abs(N))


def interval_zonotope(center, M: IntervalMatrix) -> Zonotope:
    """Property 4: ``p (+) [M] B^m ⊆ p (+) [mid[M], rs(rad[M])] B^(m+n)`` (zero columns dropped)."""
    p = as_array("center", center, (M.shape[0],))
    return Zonotope(p, _drop_zero_columns(np.hstack([M.mid, row_sum_diag(M.rad)])))


def interval_image(A: IntervalMatrix, Z: Zonotope) -> Zonotope:
    """Outer approximation of ``{A z : A in [A], z in Z}`` (end of section 4.1).

    ``[A] p ⊆ mid[A] p (+) rs(rad[A] |p|) B`` and (Properties 4, 5)
    ``[A] H B ⊆ [mid[A] H, rs(rad[A] |H|)] B``; the two diagonal generator blocks are
    boxes, so their sum is the single box ``diag(rad[A] (|p| + |H| 1))``. Returns
    ``mid[A] p (+) [mid[A] H, diag(rad[A] (|p| + |H| 1))] B``.
    """
    if A.shape != (Z.dim, Z.dim):
        raise QuadobsError(
            f"A: expected an interval matrix of shape ({Z.dim}, {Z.dim}), got {A.shape}"
        )
    mid, rad = A.mid, A.rad
    box = rad @ (np.abs(Z.center) + np.abs(Z.generators).sum(axis=1))
    H = mid @ Z.generators
    if np.any(box > 0):
        H = np.hstack([H, _drop_zero_columns(np.diag(box))])
    return Zonotope(mid @ Z.center, H)
