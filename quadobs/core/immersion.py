"""Immersion of a quadratic-output system into a state-affine (LTV) system with linear output.

Two constructions, both returning an :class:`Immersion`:

* :func:`immerse_chain`, the single-output chain of [IFAC2021, eqs. 6, 10-17]: auxiliary
  states ``z_i = 1/2 x^T C_i x``, ``i < m``, where ``m`` is the first index with
  ``C_m = 0`` (Assumption 1).
* :func:`immerse_minimal`, [ACC2024, Alg. 1] (slide eqs. 4-14, 30, 31): any ``A``, several
  outputs with linear terms, and the fewest auxiliary states, namely the dimension of the
  smallest ``A_bar``-invariant row space containing ``C_bar``.

:func:`immerse` uses the minimal construction for every system.

In both, ``z = (xi, x)``: ``xi`` holds the auxiliary states, each a quadratic form
``xi_i = 1/2 x^T L_i x``, and

.. math::

    \\dot z = \\mathcal A(u) z + \\mathcal B u, \\qquad y = \\mathcal C z, \\qquad
    \\mathcal A(u) = \\begin{bmatrix} M & U(u) \\\\ 0 & A \\end{bmatrix},\\;
    U(u)_{i,:} = u^\\top B^\\top L_i,\\;
    \\mathcal B = \\begin{bmatrix} 0 \\\\ B \\end{bmatrix},\\;
    \\mathcal C = [F \\;|\\; D],

where ``L_A(L_i) = L_i A + A^T L_i = sum_j M_ij L_j`` (the auxiliary space is
``L_A``-invariant) and ``C_h = sum_i F_hi L_i``. ``A(u)`` is affine in ``u``:
``A(u) = A_0 + sum_j u_j A_j``. The linear terms ``d_h`` need no auxiliary state (``x``
is part of ``z``), so the auxiliary space is

.. math::

    \\mathcal K = \\operatorname{span}\\{ L_A^k(C_h) : h = 1..q,\\ k \\ge 0 \\}
    \\subset \\operatorname{Sym}(n), \\qquad
    n_{aux} = \\dim \\mathcal K \\le n(n+1)/2 .

Rank decisions
--------------
The count ``dim K`` is decided on normalised data, in an orthonormal basis, so that it
depends neither on the scale of ``A`` nor on that of the ``C_h``
(:func:`lyapunov_krylov`). ``K`` is unchanged when ``A`` is replaced by
``s (A - c I)`` (``L_{sA} = s L_A`` and ``L_{A - cI} = L_A - 2c``), so the decision uses

.. math::

    \\hat A = \\frac{A - c I}{\\max(\\|A - c I\\|_2,\\ \\phi)}, \\quad
    c = \\frac{\\operatorname{tr} A}{n}, \\quad
    \\phi = \\frac{10 g}{\\texttt{rtol}}\\, 2 \\varepsilon \\max_i |A_{ii}|,
    \\qquad \\hat C_h = \\frac{C_h}{\\|C_h\\|_F},
    \\qquad \\|L_{\\hat A}\\| \\le 2 ,

(the floor ``phi`` keeps the rounding of the shift, at most ``2 eps max|A_ii|``, below
``rtol / (10 g)`` in ``A_hat``: for ``A`` a multiple of ``I`` nothing but rounding is left)

and builds ``K`` by block Arnoldi in ``Sym(n)`` with the Frobenius inner product
(classical Gram-Schmidt, applied twice): the first block is an orthonormal basis of
``span{C_hat_h}``, each next block an orthonormal basis of the part of
``L_{A_hat}(V_k)`` orthogonal to ``V_0, ..., V_k``. The singular values ``sigma`` of each
orthogonalised candidate block are the rank decisions: a direction is new when

.. math::

    \\sigma > \\tau, \\qquad \\tau = \\texttt{rtol} \\cdot \\|L_{\\hat A}\\|_{\\rm bound}
    \\quad (\\text{bound } 1 \\text{ for the first block, } 2 \\text{ after}),

``rtol`` = :data:`DEFAULT_RTOL` by default. The count is *certified* only when no
``sigma`` lies in the ambiguous band ``tau / g < sigma <= G tau``, ``G`` =
:data:`CERTIFY_GAP` (1000), ``g`` = :data:`DROP_GAP` (3): the directions kept are far
above the tolerance and those dropped below it. On integer systems up to ``n = 6``
(random, nilpotent, diagonal with spread or repeated eigenvalues, sparse, several
outputs, at scales 0.1 to 100), the kept values are ``4e-4`` and above and the dropped
ones (rounding) ``1e-10`` and below, against the band ``(7e-10, 2e-6]`` of the default
``rtol``. Otherwise :func:`immerse` raises :class:`ImmersionError`: the data are too
close to a system with another count for a floating-point answer to be trusted.

The returned immersion is then checked against the data. For each form,

.. math::

    \\frac{\\|L_A(L_i) - \\sum_j M_{ij} L_j\\|_F}{2 \\|A\\|_2 \\|L_i\\|_F} \\le \\texttt{rtol},
    \\qquad
    \\frac{\\|C_h - \\sum_i F_{hi} L_i\\|_F}{\\|C_h\\|_F} \\le \\texttt{rtol},

and its count must equal the certified ``dim K``; otherwise :class:`ImmersionError`.
An invariant space containing every ``C_h`` with the minimal dimension is ``K`` itself,
so a checked immersion is exact to the tolerance.

Bases: [ACC2024, Alg. 1] picks rows of the power sequence ``L_k = L_{k-1} A_bar``, whose
conditioning degrades like a Krylov (Vandermonde) matrix. :func:`immerse_minimal` keeps
that basis when its count is the certified one, its checks pass, and its Frobenius
condition number is at most :data:`POWER_BASIS_COND`; otherwise it returns the
orthonormal Arnoldi basis (``||L_i||_F = 1``, ``|xi_i| <= |x|^2 / 2``), with the same
block sizes. The chain of [IFAC2021] is checked the same way: its ``m`` must equal the
certified ``dim K``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import comb, prod

import numpy as np
import scipy.linalg as sla

from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError, as_finite_scalar

__all__ = [
    "CERTIFY_GAP",
    "DEFAULT_RTOL",
    "DROP_GAP",
    "POWER_BASIS_COND",
    "Immersion",
    "ImmersionError",
    "LyapunovKrylov",
    "as_immersion",
    "duplication_matrix",
    "immerse",
    "immerse_chain",
    "immerse_minimal",
    "lift_jacobian",
    "lifted_covariance",
    "lifted_input_matrix",
    "lifted_state_matrix",
    "lyapunov_krylov",
    "lyapunov_sequence",
    "lyapunov_term",
    "observability_rank",
    "quadratic_lift",
    "stacked_output_matrix",
    "vanishing_index",
    "vech",
]

#: Default relative tolerance for the rank decisions (see the module docstring).
DEFAULT_RTOL = 1e-9

#: A kept direction is certified when its singular value exceeds this factor times the
#: tolerance (module docstring).
CERTIFY_GAP = 1000.0

#: A dropped direction is certified when its singular value is at most the tolerance
#: divided by this factor (module docstring).
DROP_GAP = 3.0

#: Largest Frobenius condition number of the power basis of [ACC2024, Alg. 1] that
#: :func:`immerse_minimal` keeps; above it the orthonormal Arnoldi basis is returned.
POWER_BASIS_COND = 1e6


class ImmersionError(QuadobsError):
    """An immersion whose auxiliary count or exactness cannot be certified in floating point."""


# --------------------------------------------------------------------------------------
# The Lyapunov-operator sequence ([IFAC2021] eqs. 6 and 7)
# --------------------------------------------------------------------------------------


def lyapunov_sequence(A: np.ndarray, C: np.ndarray, count: int) -> np.ndarray:
    """``C_0 = C``, ``C_{i+1} = C_i A + A^T C_i`` (eq. 6), for ``i = 0..count``.

    Returns an array of shape ``(count + 1, n, n)``.
    """
    A = np.asarray(A, dtype=float)
    out = np.empty((count + 1,) + A.shape)
    out[0] = C
    for i in range(count):
        out[i + 1] = out[i] @ A + A.T @ out[i]
    return out


def lyapunov_term(A: np.ndarray, C: np.ndarray, i: int) -> np.ndarray:
    """Closed form ``C_i = sum_r binom(i, r) (A^T)^r C A^(i-r)`` (eq. 7)."""
    A = np.asarray(A, dtype=float)
    powers = [np.eye(A.shape[0])]
    for _ in range(i):
        powers.append(powers[-1] @ A)
    return sum(comb(i, r) * powers[r].T @ C @ powers[i - r] for r in range(i + 1))


def vanishing_index(A: np.ndarray, C: np.ndarray, rtol: float = DEFAULT_RTOL) -> int:
    """The first ``m`` with ``C_m = 0`` in the sequence of eq. (6) (Assumption 1).

    ``C_k`` counts as zero when ``||C_k||_2 <= rtol (2 ||A||_2)^k ||C||_2``; ``(2||A||)^k ||C||``
    bounds ``||C_k||`` by eq. (7), so the test is relative to the size ``C_k`` could have.

    Raises
    ------
    QuadobsError
        If ``C_k`` is not zero by ``k = n(n+1)/2``: the ``C_k`` live in the
        ``n(n+1)/2``-dimensional space of symmetric matrices, so if the sequence ever
        vanished it would have by then; no finite ``m`` exists (Assumption 1 fails).
    """
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    limit = n * (n + 1) // 2
    a_norm = 2.0 * np.linalg.norm(A, 2)
    c_norm = np.linalg.norm(C, 2)
    if c_norm == 0.0:
        return 0
    Ck = np.array(C, dtype=float)
    for k in range(limit + 1):
        if np.linalg.norm(Ck, 2) <= rtol * a_norm**k * c_norm:
            return k
        Ck = Ck @ A + A.T @ Ck
    raise QuadobsError(
        f"C: Assumption 1 fails, C_k = C_(k-1) A + A^T C_(k-1) is not zero by k = n(n+1)/2 = {limit}, "
        "so no finite m with C_m = 0 exists; the minimal immersion (immerse(system)) handles any A"
    )


# --------------------------------------------------------------------------------------
# Half-vectorisation machinery ([ACC2024] slide eqs. 4-6)
# --------------------------------------------------------------------------------------


def _vech_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the lower triangle, column-major (the ``vech`` order)."""
    cols, rows = [], []
    for j in range(n):
        for i in range(j, n):
            rows.append(i)
            cols.append(j)
    return np.array(rows), np.array(cols)


def duplication_matrix(n: int) -> np.ndarray:
    """The duplication matrix ``D_n`` (shape ``(n^2, n(n+1)/2)``): ``D_n vech(S) = vec(S)``."""
    rows, cols = _vech_pairs(n)
    D = np.zeros((n * n, rows.size))
    k = np.arange(rows.size)
    D[rows + cols * n, k] = 1.0  # column-major vec index of (i, j)
    D[cols + rows * n, k] = 1.0
    return D


def vech(S: np.ndarray) -> np.ndarray:
    """Lower-triangular half-vectorisation, column-major; works on ``(..., n, n)``."""
    S = np.asarray(S)
    rows, cols = _vech_pairs(S.shape[-1])
    return S[..., rows, cols]


def _unvech_form(g: np.ndarray, n: int) -> np.ndarray:
    """Symmetric ``L`` with ``g x^[2] = 1/2 x^T L x`` for rows ``g (..., n(n+1)/2)``."""
    rows, cols = _vech_pairs(n)
    S = np.zeros(g.shape[:-1] + (n, n))
    S[..., rows, cols] = g
    S[..., cols, rows] = g
    return 2.0 * S


def quadratic_lift(x: np.ndarray) -> np.ndarray:
    """``x^[2] = D_n^T (x kron x)`` (slide eq. 4): ``x_i^2`` on the diagonal, ``2 x_i x_j`` off it."""
    x = np.asarray(x, dtype=float)
    rows, cols = _vech_pairs(x.shape[-1])
    out = x[..., rows] * x[..., cols]
    return np.where(rows == cols, out, 2.0 * out)


def lifted_state_matrix(A: np.ndarray) -> np.ndarray:
    """``A_bar = D_n^T (A (+) A) (D_n^+)^T`` with the Kronecker sum ``A (+) A = A kron I + I kron A`` (slide eq. 6)."""
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    D = duplication_matrix(n)
    ksum = np.kron(A, np.eye(n)) + np.kron(np.eye(n), A)
    return D.T @ ksum @ np.linalg.pinv(D).T


def lifted_input_matrix(Bu: np.ndarray) -> np.ndarray:
    """``U_bar = D_n^T (Bu (+) Bu)``, with ``(Bu (+) Bu) x = Bu kron x + x kron Bu`` (slide eq. 6)."""
    b = np.asarray(Bu, dtype=float).reshape(-1, 1)
    n = b.shape[0]
    D = duplication_matrix(n)
    return D.T @ (np.kron(b, np.eye(n)) + np.kron(np.eye(n), b))


def stacked_output_matrix(system: QuadraticSystem) -> np.ndarray:
    """``C_bar`` with rows ``1/2 vech(C_h)^T`` (slide eq. 5), so that ``y = C_bar x^[2] + D x``."""
    return 0.5 * vech(system.C)


def _block_krylov(apply, W: np.ndarray, dim: int, tol_first: float, tol_next: float):
    """Block Arnoldi on row vectors: an orthonormal basis of ``span{W, apply(W), ...}``.

    ``W`` holds unit-norm rows; ``apply`` maps rows to rows. Each candidate block is
    orthogonalised against the basis twice (classical Gram-Schmidt with
    re-orthogonalisation); its singular values above the tolerance (``tol_first`` for
    ``W``, ``tol_next`` after) give the new directions (its leading right singular
    vectors). Returns ``(basis, sizes, sigma, tol)``: the orthonormal rows, the block
    sizes in Arnoldi order, and every singular value decided with its tolerance.
    """
    V = np.zeros((0, W.shape[1]))
    sizes: list[int] = []
    sigma: list[float] = []
    tols: list[float] = []
    tol = tol_first
    while W.shape[0]:
        for _ in range(2):
            W = W - (W @ V.T) @ V
        _, sv, Vt = np.linalg.svd(W, full_matrices=False)
        k = min(int(np.sum(sv > tol)), dim - V.shape[0])
        sigma.extend(sv.tolist())
        tols.extend([tol] * sv.size)
        if k == 0:
            break
        new = Vt[:k]
        V = np.vstack([V, new])
        sizes.append(k)
        W = apply(new)
        tol = tol_next
    return V, tuple(sizes), np.array(sigma), np.array(tols)


def _normalised_shifted(A: np.ndarray, rtol: float) -> np.ndarray:
    """``A_hat = (A - c I) / max(||A - c I||_2, floor)``, ``c = tr(A)/n`` (module docstring).

    The shift rounds the diagonal by up to ``2 eps max|A_ii|``; ``floor`` =
    ``10 DROP_GAP / rtol`` times that bound keeps this rounding below
    ``rtol / (10 DROP_GAP)`` in ``A_hat``, so it can never pass for a direction (for
    ``A`` a multiple of ``I``, ``A_hat`` is rounding only and ``K = span{C_h}``).
    """
    n = A.shape[0]
    A0 = A - (np.trace(A) / n) * np.eye(n)
    a = np.linalg.norm(A0, 2)
    floor = 10.0 * DROP_GAP / rtol * 2.0 * np.finfo(float).eps * float(np.abs(np.diag(A)).max())
    scale = max(a, floor)
    return A0 / scale if scale > 0.0 else np.zeros_like(A0)


def _unit_rows(C: np.ndarray) -> np.ndarray:
    """The nonzero rows of ``C``, each divided by its norm."""
    norms = np.linalg.norm(C, axis=1)
    keep = norms > 0.0
    return C[keep] / norms[keep, None]


@dataclass(frozen=True)
class LyapunovKrylov:
    """The auxiliary space ``K`` of the module docstring, from :func:`lyapunov_krylov`.

    Attributes
    ----------
    basis : ndarray, shape (r, n, n)
        Frobenius-orthonormal symmetric matrices spanning ``K``, block by block.
    sizes : tuple of int
        Block sizes in Arnoldi order (``p_0, p_1, ...`` of [ACC2024, Alg. 1]).
    sigma, tol : ndarray
        Every rank decision: the singular value and the tolerance ``tau`` it was
        compared with (kept when ``sigma > tau``).
    """

    basis: np.ndarray
    sizes: tuple[int, ...]
    sigma: np.ndarray
    tol: np.ndarray

    @property
    def rank(self) -> int:
        """``dim K``: the fewest auxiliary states."""
        return int(self.basis.shape[0])

    def ambiguity(self) -> str | None:
        """``None`` if every rank decision is certified (module docstring), else why not.

        A decision is certified when ``sigma > G tau`` (kept) or ``sigma <= tau / g``
        (dropped), ``G`` = :data:`CERTIFY_GAP`, ``g`` = :data:`DROP_GAP`.
        """
        band = (self.sigma > self.tol / DROP_GAP) & (self.sigma <= CERTIFY_GAP * self.tol)
        if not band.any():
            return None
        i = int(np.flatnonzero(band)[0])
        what = "kept" if self.sigma[i] > self.tol[i] else "dropped"
        return (
            f"the rank decisions are ambiguous: a direction {what} at relative size {self.sigma[i]:.3g} "
            f"lies between {self.tol[i] / DROP_GAP:.3g} and {CERTIFY_GAP * self.tol[i]:.3g} (tolerance "
            f"{self.tol[i]:.3g}), so the data are too close to a system with another auxiliary count "
            "to certify one in floating point"
        )


def lyapunov_krylov(A: np.ndarray, C: np.ndarray, rtol: float = DEFAULT_RTOL) -> LyapunovKrylov:
    """Orthonormal basis of the smallest ``L_A``-invariant space containing the ``C_h``.

    Block Arnoldi in ``Sym(n)`` with the Frobenius inner product on the normalised data
    ``A_hat``, ``C_hat_h`` of the module docstring, so that the result depends neither on
    the scale of ``A`` (nor on a multiple of ``I`` added to it) nor on those of the
    ``C_h``. The rank decisions use ``tau = rtol`` for the first block (unit rows) and
    ``tau = 2 rtol`` (the bound on ``||L_A_hat||``) after.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (q, n, n) or (n, n)
        Symmetric output matrices.
    rtol : float
        Relative tolerance of the rank decisions.
    """
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    C = np.asarray(C, dtype=float).reshape(-1, n, n)
    Ah = _normalised_shifted(A, rtol)

    def apply(rows: np.ndarray) -> np.ndarray:
        X = rows.reshape(-1, n, n)
        Y = Ah.T @ X + X @ Ah
        return (0.5 * (Y + np.swapaxes(Y, 1, 2))).reshape(-1, n * n)

    W = _unit_rows(C.reshape(-1, n * n))
    V, sizes, sigma, tol = _block_krylov(apply, W, n * (n + 1) // 2, rtol, 2.0 * rtol)
    V = V.reshape(-1, n, n)
    V = 0.5 * (V + np.swapaxes(V, 1, 2))
    return LyapunovKrylov(V, sizes, sigma, tol)


def observability_rank(A_bar: np.ndarray, C_bar: np.ndarray, rtol: float = DEFAULT_RTOL) -> int:
    """Rank of the observability matrix ``[C_bar; C_bar A_bar; ...; C_bar A_bar^(N-1)]``.

    Computed as :func:`lyapunov_krylov` computes ``dim K``: block Arnoldi on the rows
    (``r -> r A_hat``) with the normalised data ``A_hat = (A_bar - tr(A_bar)/N I) /
    ||.||_2`` and unit rows of ``C_bar``; a direction is new when its singular value
    exceeds ``rtol``. With ``A_bar``, ``C_bar`` of [ACC2024] (:func:`lifted_state_matrix`,
    :func:`stacked_output_matrix`) it equals the certified ``n_aux`` of
    :func:`immerse_minimal`. Works for any pair ``(A, C)``.
    """
    A_bar = np.asarray(A_bar, dtype=float)
    C_bar = np.atleast_2d(np.asarray(C_bar, dtype=float))
    N = A_bar.shape[0]
    W = _unit_rows(C_bar)
    if W.shape[0] == 0:
        return 0
    Ah = _normalised_shifted(A_bar, rtol)
    V, _, _, _ = _block_krylov(lambda rows: rows @ Ah, W, N, rtol, rtol)
    return int(V.shape[0])


# --------------------------------------------------------------------------------------
# The immersion object
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Immersion:
    """An LTV system ``z' = A(u) z + B u``, ``y = C z`` carrying ``system`` exactly.

    Parameters
    ----------
    system : QuadraticSystem
    aux_forms : ndarray, shape (n_aux, n, n)
        Symmetric ``L_i`` with ``xi_i = 1/2 x^T L_i x``.
    aux_dynamics : ndarray, shape (n_aux, n_aux)
        ``M`` with ``L_A(L_i) = sum_j M_ij L_j``.
    aux_output : ndarray, shape (q, n_aux)
        ``F`` with ``C_h = sum_i F_hi L_i``.
    method : str
        ``"chain"`` (IFAC 2021) or ``"minimal"`` (ACC 2024 Algorithm 1).
    block_sizes : tuple of int
        Sizes of the auxiliary blocks in state order (``m`` ones for the chain; the
        ranks ``p_{m-1}, ..., p_0`` for Algorithm 1, eq. 12 order).
    """

    system: QuadraticSystem
    aux_forms: np.ndarray
    aux_dynamics: np.ndarray
    aux_output: np.ndarray
    method: str
    block_sizes: tuple[int, ...]

    def __post_init__(self) -> None:
        sys_ = self.system
        n, p, q = sys_.n, sys_.p, sys_.q
        L = np.asarray(self.aux_forms, dtype=float).reshape(-1, n, n)
        k = L.shape[0]
        M = np.asarray(self.aux_dynamics, dtype=float).reshape(k, k)
        F = np.asarray(self.aux_output, dtype=float).reshape(q, k)
        if sum(self.block_sizes) != k:
            raise QuadobsError(
                f"block_sizes: they sum to {sum(self.block_sizes)}, expected n_aux = {k}"
            )
        N = k + n
        # U(u) x: row i is u^T B^T L_i x, so A_j[i, k + a] = (L_i B)[a, j].
        K = np.einsum("iab,bj->jia", L, sys_.B)
        A0 = np.zeros((N, N))
        A0[:k, :k] = M
        A0[k:, k:] = sys_.A
        Au = np.zeros((p, N, N))
        Au[:, :k, k:] = K
        Bz = np.zeros((N, p))
        Bz[k:] = sys_.B
        Cz = np.hstack([F, sys_.d])
        for name, arr in (
            ("aux_forms", L),
            ("aux_dynamics", M),
            ("aux_output", F),
            ("input_forms", K),
            ("state_matrix_constant", A0),
            ("state_matrix_input", Au),
            ("input_matrix", Bz),
            ("output_matrix", Cz),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    # Derived in __post_init__.
    #: (p, n_aux, n): the aux-x block of A(u) is sum_j u_j input_forms[j].
    input_forms: np.ndarray = field(init=False, repr=False)
    #: (N, N): A_0, the part of A(u) independent of u.
    state_matrix_constant: np.ndarray = field(init=False, repr=False)
    #: (p, N, N): A_j, the coefficient of u_j in A(u).
    state_matrix_input: np.ndarray = field(init=False, repr=False)
    #: (N, p): eq. (16) / slide eq. (14).
    input_matrix: np.ndarray = field(init=False, repr=False)
    #: (q, N): eq. (17) / slide eq. (14).
    output_matrix: np.ndarray = field(init=False, repr=False)

    @property
    def n_aux(self) -> int:
        """Number of auxiliary states."""
        return self.aux_forms.shape[0]

    @property
    def dim(self) -> int:
        """Dimension of the augmented state ``z``."""
        return self.n_aux + self.system.n

    @property
    def naive_aux(self) -> int:
        """Auxiliary count of the naive immersion ``z = (x^[2], x)``: ``n(n+1)/2``."""
        n = self.system.n
        return n * (n + 1) // 2

    def lift(self, x: np.ndarray) -> np.ndarray:
        """``x -> z = (1/2 x^T L_i x, x)`` (eq. 10 / slide eq. 12); ``x`` of shape ``(..., n)``."""
        x = np.asarray(x, dtype=float)
        if x.shape[-1:] != (self.system.n,):
            raise QuadobsError(f"x: expected shape (..., {self.system.n}), got {x.shape}")
        xi = 0.5 * np.einsum("...a,iab,...b->...i", x, self.aux_forms, x)
        return np.concatenate([xi, x], axis=-1)

    def project(self, z: np.ndarray) -> np.ndarray:
        """``z -> x``: the last ``n`` entries of ``z``; ``z`` of shape ``(..., dim)``."""
        z = np.asarray(z, dtype=float)
        if z.shape[-1:] != (self.dim,):
            raise QuadobsError(f"z: expected shape (..., {self.dim}), got {z.shape}")
        return z[..., self.n_aux :]

    def state_matrix(self, u: np.ndarray) -> np.ndarray:
        """``A(u) = A_0 + sum_j u_j A_j`` (eq. 15 / slide eq. 13) for ``u`` of shape ``(..., p)``."""
        u = np.asarray(u, dtype=float)
        if u.shape[-1:] != (self.system.p,):
            raise QuadobsError(f"u: expected shape (..., {self.system.p}), got {u.shape}")
        p, N = self.system.p, self.dim
        # sum_j u_j A_j as one matrix product: what np.tensordot(u, A_j, axes=(-1, 0)) forms,
        # without its shape bookkeeping (the interface in time calls this at every interval)
        coupling = np.dot(
            u.reshape(prod(u.shape[:-1]), p), self.state_matrix_input.reshape(p, N * N)
        )
        return self.state_matrix_constant + coupling.reshape(u.shape[:-1] + (N, N))

    def output(self, z: np.ndarray) -> np.ndarray:
        """``y = C z`` for ``z`` of shape ``(..., dim)``."""
        return np.asarray(z) @ self.output_matrix.T

    def summary(self) -> dict:
        """Sizes for reports: ``n``, ``n_aux``, the naive count ``n(n+1)/2`` and the block sizes."""
        return {
            "method": self.method,
            "n": self.system.n,
            "n_aux": self.n_aux,
            "naive_aux": self.naive_aux,
            "block_sizes": list(self.block_sizes),
        }


# --------------------------------------------------------------------------------------
# Constructions
# --------------------------------------------------------------------------------------


def as_immersion(value) -> Immersion:
    """``value``, checked to be an :class:`Immersion`; else a :class:`~quadobs.errors.QuadobsError` naming its type."""
    if not isinstance(value, Immersion):
        raise QuadobsError(f"immersion: expected an Immersion, got {type(value).__name__}")
    return value


def immerse_chain(system: QuadraticSystem, rtol: float = DEFAULT_RTOL) -> Immersion:
    """Single-output chain of [IFAC2021] (eqs. 10-17).

    ``z = (z_0, ..., z_{m-1}, x)`` with ``z_i = 1/2 x^T C_i x`` (eq. 10, 13); ``A(u)`` is the
    shift ``S_m`` on the auxiliary block with ``u^T B^T C_i`` in the last columns (eq. 15),
    ``B = (0, B)`` (eq. 16), ``C = (1, 0, ..., 0, d^T)`` (eq. 17; the paper has ``d = 0``).

    The chain is a power basis: it is returned only when ``m`` equals the certified
    ``dim K`` of :func:`lyapunov_krylov` and it passes the residual checks of the module
    docstring.

    Raises
    ------
    QuadobsError
        If the system has more than one output, or Assumption 1 fails (see
        :func:`vanishing_index`).
    ImmersionError
        If the chain's length or exactness cannot be certified.
    """
    if system.q != 1:
        raise QuadobsError(
            f"C: the chain immersion takes a single output, got q = {system.q}; use immerse_minimal"
        )
    rtol = as_finite_scalar("rtol", rtol, positive=True)
    m = vanishing_index(system.A, system.C[0], rtol)
    kry = lyapunov_krylov(system.A, system.C[0], rtol)
    why = kry.ambiguity()
    if why is not None:
        raise ImmersionError(f"C: the chain length cannot be certified, {why}")
    if m != kry.rank:
        raise ImmersionError(
            f"C: the chain stops at m = {m} but the certified minimal count is {kry.rank}: "
            "C_m is not zero relative to the data, so the chain would not be exact; use immerse(system)"
        )
    L = lyapunov_sequence(system.A, system.C[0], max(m - 1, 0))[:m]
    M = np.eye(m, k=1)
    F = np.zeros((1, m))
    if m:
        F[0, 0] = 1.0
    im = Immersion(system, L, M, F, "chain", (1,) * m)
    why = _certification_failure(im, kry.rank, rtol)
    if why is not None:
        raise ImmersionError(
            f"C: the chain immersion cannot be certified, {why}; use immerse(system)"
        )
    return im


def _pivoted_rank(E: np.ndarray, tol: float | np.floating) -> tuple[int, np.ndarray]:
    """Rank of the rows of ``E`` at absolute tolerance ``tol`` and the pivot order of the rows."""
    if E.shape[0] == 0:
        return 0, np.zeros(0, dtype=int)
    _, R, piv = sla.qr(E.T, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    return int(np.sum(diag > tol)), piv


def _algorithm1_power_basis(system: QuadraticSystem, rtol: float) -> Immersion:
    """[ACC2024, Alg. 1] in the power basis ``L_k = L_{k-1} A_bar`` (rows of it).

    1. ``p_0 = rank C_bar`` and the rank factorisation ``C_bar = F L_0``: ``L_0`` is a
       selection of ``p_0`` rows of ``C_bar`` (pivoted QR), so each auxiliary state of
       the first block is one of the outputs' quadratic parts.
    2. For ``k = 1, 2, ...``: ``p_k`` (eq. 30) counts the rows of ``L_{k-1} A_bar`` that are
       independent of ``L_0, ..., L_{k-1}``; the permutation ``P_{k-1}`` brings them first
       and they form ``L_k``; the other rows are combinations ``M_i^(k-1)`` of the rows
       found so far (eq. 31). Unlike the slide's statement of eq. 31, the combinations may
       also involve ``L_k`` itself (a dependent row can share a new direction with a
       selected one); the coefficients on ``L_k`` then enter ``A(u)`` beside ``P_k``.
    3. Stop at ``p_k = 0`` with ``m = k``; ``z`` is eq. (12),
       ``(P_{m-1} xi_{m-1}, ..., P_0 xi_0, x)``, and ``A(u), B, C`` are eqs. (13, 14).

    Its rank decisions (pivoted QR on the unnormalised power rows) are not trusted on
    their own: :func:`immerse_minimal` compares the count with the certified one and
    checks the result. Raises :class:`ImmersionError` when the rows found are not
    invariant.
    """
    n = system.n
    C_bar = stacked_output_matrix(system)
    A_bar = lifted_state_matrix(system.A)
    N = A_bar.shape[0]
    a_norm = np.linalg.norm(A_bar, 2)
    c_norm = np.linalg.norm(C_bar, 2)
    if c_norm == 0.0:
        return Immersion(
            system, np.zeros((0, n, n)), np.zeros((0, 0)), np.zeros((system.q, 0)), "minimal", ()
        )

    p0, piv = _pivoted_rank(C_bar, rtol * c_norm)
    blocks = [C_bar[np.sort(piv[:p0])]]  # L_0: rows of C_bar, in output order
    permuted: list[np.ndarray] = []  # P_k L_k, filled as the permutations are decided
    orders: list[np.ndarray] = []  # row order of each P_k (P_k L_k = L_k[order])
    basis = sla.orth(blocks[0].T).T  # orthonormal rows spanning everything found so far
    while True:
        prev = blocks[-1]
        cand = prev @ A_bar
        resid = cand - (cand @ basis.T) @ basis
        tol = rtol * np.linalg.norm(prev, 2) * a_norm
        pk, piv = _pivoted_rank(resid, tol)
        if pk == 0:
            permuted.append(prev)  # P_{m-1} = I: no row of the last block leads anywhere new
            orders.append(np.arange(prev.shape[0]))
            break
        if sum(b.shape[0] for b in blocks) + pk > N:
            raise ImmersionError("the power-basis rows exceed n(n+1)/2 auxiliary states")
        order = np.concatenate([piv[:pk], np.setdiff1d(np.arange(prev.shape[0]), piv[:pk])])
        permuted.append(prev[order])  # P_{k-1} L_{k-1}: the rows leading to new directions first
        orders.append(order)
        new = cand[order[:pk]]  # L_k: the first p_k rows of P_{k-1} L_{k-1} A_bar (eq. 31)
        blocks.append(new)
        # Extend the orthonormal basis with the new directions (re-orthogonalised once,
        # normalised so that the growth of ||A_bar||^k does not swamp earlier rows).
        fresh = resid[order[:pk]]
        fresh = fresh - (fresh @ basis.T) @ basis
        basis = np.vstack([basis, np.linalg.qr(fresh.T)[0].T])

    # eq. (12) order: highest block first.
    G = np.vstack(permuted[::-1])
    sizes = tuple(b.shape[0] for b in permuted[::-1])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    m = len(sizes)
    # M with M G = G A_bar (G has full row rank, so M is unique); least squares, then the
    # structural rows of eq. (13) (a block's leading p_{k+1} rows map onto the next block)
    # are set exactly.
    GA = G @ A_bar
    M = np.linalg.lstsq(G.T, GA.T, rcond=None)[0].T
    for k in range(m - 1):  # state block of P_k L_k sits at index m-1-k
        blk, nxt = m - 1 - k, m - 2 - k
        p_next = sizes[nxt]
        rows = slice(offsets[blk], offsets[blk] + p_next)
        # L_{k+1} rows in z are P_{k+1} L_{k+1}; the permutation was applied by row order.
        perm = permuted[k + 1]
        target = blocks[k + 1]
        idx = [int(np.flatnonzero(np.all(perm == target[r], axis=1))[0]) for r in range(p_next)]
        M[rows] = 0.0
        M[np.arange(offsets[blk], offsets[blk] + p_next), offsets[nxt] + np.array(idx)] = 1.0
    scale = max(np.linalg.norm(G, 2) * a_norm, np.finfo(float).tiny)
    err = np.linalg.norm(M @ G - GA, 2)
    if err > 1e3 * rtol * scale + 1e-12 * scale:
        raise ImmersionError(
            f"the power-basis rows are not invariant under A_bar (residual {err:.3g})"
        )
    # C_bar = F_0 L_0 (rank factorisation; L_0 holds rows of C_bar, so F_0 is well conditioned),
    # hence C = [0 ... 0 F_0 P_0^T | D] (slide eq. 14).
    F0 = np.linalg.lstsq(blocks[0].T, C_bar.T, rcond=None)[0].T
    F0[np.abs(F0) < 1e-14 * max(np.abs(F0).max(), 1.0)] = 0.0
    F = np.zeros((system.q, G.shape[0]))
    F[:, offsets[m - 1] :] = F0[:, orders[0]]
    L = _unvech_form(G, n)
    return Immersion(system, L, M, F, "minimal", sizes)


def _lyapunov_residuals(
    system: QuadraticSystem, L: np.ndarray, M: np.ndarray, F: np.ndarray
) -> tuple[float, float]:
    """The two relative residuals of the module docstring: invariance and output."""
    A = system.A
    a = 2.0 * np.linalg.norm(A, 2)
    k, n = L.shape[0], system.n
    if k == 0:
        return 0.0, 0.0
    LA = np.swapaxes(L, 1, 2) @ A
    LA = LA + np.swapaxes(LA, 1, 2)  # L_i A + A^T L_i (L_i symmetric)
    R = (LA - np.tensordot(M, L, axes=(1, 0))).reshape(k, n * n)
    num = np.linalg.norm(R, axis=1)
    den = a * np.linalg.norm(L.reshape(k, n * n), axis=1)
    inv = float(np.max(np.where(num == 0.0, 0.0, num / np.maximum(den, np.finfo(float).tiny))))
    Ch = system.C.reshape(system.q, n * n)
    Ro = Ch - F @ L.reshape(k, n * n)
    cn = np.linalg.norm(Ch, axis=1)
    on = np.linalg.norm(Ro, axis=1)
    out = float(np.max(np.where(on == 0.0, 0.0, on / np.maximum(cn, np.finfo(float).tiny))))
    return inv, out


def _certification_failure(im: Immersion, rank: int, rtol: float) -> str | None:
    """``None`` if ``im`` has the certified count and passes both residual checks, else why not."""
    if im.n_aux != rank:
        return f"its count {im.n_aux} differs from the certified minimal count {rank}"
    inv, out = _lyapunov_residuals(im.system, im.aux_forms, im.aux_dynamics, im.aux_output)
    if not inv <= rtol:
        return f"its forms are not invariant under L_A to the tolerance (relative residual {inv:.3g} > {rtol:.3g})"
    if not out <= rtol:
        return f"its forms do not reproduce the outputs to the tolerance (relative residual {out:.3g} > {rtol:.3g})"
    return None


def _orthonormal_immersion(system: QuadraticSystem, kry: LyapunovKrylov) -> Immersion:
    """The immersion in the orthonormal Arnoldi basis of ``K``, blocks in eq. (12) order.

    ``z = (V_{m-1}, ..., V_0, x)``; ``M_ij = <L_A(L_i), L_j>_F`` (zero beyond the block
    Hessenberg pattern: ``L_A(V_k)`` lies in ``V_0 + ... + V_{k+1}``) and
    ``F_hi = <C_h, L_i>_F`` on the last block (``V_0`` spans the ``C_h``).
    """
    n, q = system.n, system.q
    sizes = kry.sizes[::-1]
    m = len(sizes)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    arnoldi_offsets = np.concatenate([[0], np.cumsum(kry.sizes)]).astype(int)
    # reorder the Arnoldi blocks: block k of the state is Arnoldi block m-1-k
    order = np.concatenate(
        [np.arange(arnoldi_offsets[j], arnoldi_offsets[j + 1]) for j in range(m - 1, -1, -1)]
    )
    L = kry.basis[order]
    k = L.shape[0]
    A = system.A
    LA = np.swapaxes(L, 1, 2) @ A
    LA = LA + np.swapaxes(LA, 1, 2)
    M = LA.reshape(k, n * n) @ L.reshape(k, n * n).T
    # state block b holds Arnoldi block m-1-b; L_A of Arnoldi block j lies in blocks <= j+1,
    # i.e. state blocks >= b-1.
    for b in range(m):
        for c in range(b - 1):
            M[offsets[b] : offsets[b + 1], offsets[c] : offsets[c + 1]] = 0.0
    F = np.zeros((q, k))
    last = slice(offsets[m - 1], k)
    F[:, last] = system.C.reshape(q, n * n) @ L[last].reshape(-1, n * n).T
    return Immersion(system, L, M, F, "minimal", sizes)


def immerse_minimal(system: QuadraticSystem, rtol: float = DEFAULT_RTOL) -> Immersion:
    """[ACC2024, Alg. 1]: the fewest auxiliary states, certified.

    1. ``dim K`` and an orthonormal basis of ``K`` by block Arnoldi on the normalised data
       (:func:`lyapunov_krylov`); the count is certified when no rank decision is
       ambiguous (module docstring, "Rank decisions").
    2. Algorithm 1 in its power basis ``L_k = L_{k-1} A_bar`` (rows of ``C_bar``, then of
       ``L_{k-1} A_bar`` selected by pivoted QR; ``z`` in eq. (12) order,
       ``(P_{m-1} xi_{m-1}, ..., P_0 xi_0, x)``, and ``A(u), B, C`` of eqs. (13, 14)). It is
       returned when its count is the certified one, its Frobenius condition number is at
       most :data:`POWER_BASIS_COND`, and its residuals pass the checks.
    3. Otherwise the immersion in the orthonormal Arnoldi basis (same block sizes, eq. (12)
       order, ``||L_i||_F = 1``), checked the same way.

    The row space found is the smallest ``A_bar``-invariant space containing the rows of
    ``C_bar``, so ``n_aux`` equals the rank of the observability matrix of
    ``(A_bar, C_bar)`` (see :func:`observability_rank`). With ``C_h = 0`` for every output
    there is nothing to immerse: ``n_aux = 0`` and ``z = x``.

    Parameters
    ----------
    system : QuadraticSystem
    rtol : float
        Relative tolerance ``rtol`` of the rank decisions and of the residual checks
        (module docstring); :data:`DEFAULT_RTOL` by default.

    Raises
    ------
    ImmersionError
        If the count cannot be certified (a rank decision in the ambiguous band of the
        module docstring) or no basis passes the residual checks.
    """
    rtol = as_finite_scalar("rtol", rtol, positive=True)
    n = system.n
    kry = lyapunov_krylov(system.A, system.C, rtol)
    why = kry.ambiguity()
    if why is not None:
        raise ImmersionError(f"system: the minimal auxiliary count cannot be certified, {why}")
    if kry.rank == 0:
        return Immersion(
            system, np.zeros((0, n, n)), np.zeros((0, 0)), np.zeros((system.q, 0)), "minimal", ()
        )
    try:
        im = _algorithm1_power_basis(system, rtol)
    except ImmersionError:
        im = None
    if im is not None and im.n_aux == kry.rank:
        sv = np.linalg.svd(im.aux_forms.reshape(im.n_aux, n * n), compute_uv=False)
        if (
            sv[-1] * POWER_BASIS_COND >= sv[0]
            and _certification_failure(im, kry.rank, rtol) is None
        ):
            return im
    im = _orthonormal_immersion(system, kry)
    why = _certification_failure(im, kry.rank, rtol)
    if why is not None:
        raise ImmersionError(f"system: the minimal immersion cannot be certified, {why}")
    return im


def immerse(
    system: QuadraticSystem, method: str = "minimal", rtol: float = DEFAULT_RTOL
) -> Immersion:
    """Immerse ``system`` into an LTV system with linear output.

    Parameters
    ----------
    system : QuadraticSystem
    method : {"minimal", "chain"}
        ``"minimal"`` (default): Algorithm 1 of [ACC2024], any system.
        ``"chain"``: the single-output chain of [IFAC2021] (needs
        ``q = 1`` and Assumption 1).
    rtol : float
        Relative tolerance of the rank decisions (module docstring).
    """
    if not isinstance(system, QuadraticSystem):
        raise QuadobsError(f"system: expected a QuadraticSystem, got {type(system).__name__}")
    if method == "minimal":
        return immerse_minimal(system, rtol)
    if method == "chain":
        return immerse_chain(system, rtol)
    raise QuadobsError(f"method: unknown immersion {method!r}; expected 'minimal' or 'chain'")


def lifted_covariance(aux_forms: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance of ``z = (xi(x), x)``, ``xi_i = x^T L_i x / 2``, for ``x ~ N(m, P)`` (exact Gaussian moments).

    ``Cov(xi_i, x) = P L_i m`` and ``Cov(xi_i, xi_j) = m^T L_i P L_j m + tr(L_i P L_j P) / 2``.
    Returns ``(k + n, k + n)``.
    """
    L = np.asarray(aux_forms, dtype=float)
    m = np.asarray(mean, dtype=float)
    P = np.asarray(cov, dtype=float)
    k, n = L.shape[0], m.shape[0]
    out = np.zeros((k + n, k + n))
    out[k:, k:] = P
    cross = np.einsum("ab,ibc,c->ia", P, L, m)
    out[:k, k:] = cross
    out[k:, :k] = cross.T
    Lm = np.einsum("iab,b->ia", L, m)
    LP = np.einsum("iab,bc->iac", L, P)
    out[:k, :k] = Lm @ P @ Lm.T + 0.5 * np.einsum("iab,jba->ij", LP, LP)
    return out


def lift_jacobian(aux_forms: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``dz/dx (k + n, n)`` of the lift ``z = (xi(x), x)``, ``xi_i = x^T L_i x / 2``: rows
    ``x^T L_i`` then ``I_n``.

    A white noise ``w`` on ``x'`` enters ``z'`` through it (``xi_i' = x^T L_i x'``): a noise of
    intensity ``V_x`` on ``x'`` is ``J V_x J^T`` on ``z``, an input noise ``w`` (``x' = A x +
    B (u + w)``) is ``(J B) w``.
    """
    L = np.asarray(aux_forms, dtype=float)
    x = np.asarray(x, dtype=float)
    k, n = L.shape[0], x.shape[0]
    J = np.empty((k + n, n))
    J[:k] = L @ x
    J[k:] = np.eye(n)
    return J
