"""Offline design of the P-radius gains ([LE2013] section 4, problem 9, Algorithm 2).

For ``x_{k+1} = A x_k + F w_k``, ``y_{k/i} = c_i^T x_k + phi_i v_i`` with ``A in [A]``,
``||w||_inf, |v_i| <= 1``, the correction by output ``i`` (eq. 3) is
``H_{k/i} = [kappa_i H_{k/i-1}, phi_i lambda_i]``, ``kappa_i = I - lambda_i c_i^T``. A gain
``lambda`` and a matrix ``P = P^T > 0`` satisfying the LMI below make the P-radius
``L = max_{z in B} ||H z||_P^2`` of the estimated zonotope obey (eq. 4 and its step-``j`` form)

.. math::

    L_{k/j} \\le \\beta L_{k-1} + \\psi + \\phi_1^2 + \\dots + \\phi_j^2,
    \\qquad \\psi = \\max_{\\gamma \\in B^{n_w}} \\|F \\gamma\\|_2^2,

so ``L`` converges into ``(psi + sum phi^2) / (1 - beta)``, and the ellipsoid of that
P-radius is made as small as possible by maximising ``tau`` with
``(1 - beta) P / (psi + sum phi^2) >= tau I``.

Derivation of the step-``j`` LMI (second approach, section 4.2). With ``lambda_1..lambda_{j-1}``
fixed, write ``K_{j-1} = kappa_{j-1} ... kappa_1`` and ``v_l = kappa_{j-1} ... kappa_{l+1} phi_l lambda_l``
(``l < j``). By eq. (3),
``H_{k/j} zhat = kappa_j (K_{j-1} A theta + K_{j-1} F gamma + sum_l v_l eta_l) + phi_j lambda_j eta_j``
with ``theta = H_{k-1} z``. The condition
``||H_{k/j} zhat||_P^2 - beta ||theta||_P^2 - ||F gamma||^2 - sum_l phi_l^2 eta_l^2 <= 0`` for all
``(theta, gamma, eta)`` implies the P-radius bound (``eta_l^2 <= 1``, as for eq. 7). It is
``D - Xi P^{-1} Xi^T >= 0`` with ``D = diag(beta P, F^T F, phi_1^2, ..., phi_j^2)`` and
``Xi^T = [kappa_j^T P K_{j-1} A, kappa_j^T P K_{j-1} F, kappa_j^T P v_1, ..., kappa_j^T P v_{j-1}, phi_j P lambda_j]``;
with ``Y = P lambda_j``, ``M^T kappa_j^T P = M^T P - (M^T c_j) Y^T`` is affine in ``(P, Y)``, and
the Schur complement gives, for every vertex ``G_i`` of ``[A]``,

.. math::

    \\begin{bmatrix}
    \\beta P & 0 & 0 & (K G_i)^\\top P - (K G_i)^\\top c_j Y^\\top \\\\
    * & F^\\top F & 0 & (K F)^\\top P - (K F)^\\top c_j Y^\\top \\\\
    * & * & \\mathrm{diag}(\\phi_l^2) & \\begin{bmatrix} v_l^\\top P - (v_l^\\top c_j) Y^\\top \\\\ \\phi_j Y^\\top \\end{bmatrix} \\\\
    * & * & * & P
    \\end{bmatrix} \\succeq 0 .

For ``j = 1`` (``K = I``, no ``v_l``) this is problem (9); the first approach (section 4.1)
solves problem (9) for each output on its own. Condition (8) is affine in ``A`` once
``(P, Y)`` are fixed and the LMI is convex in ``A`` through the Schur complement, so it
holds on all of ``[A]`` when it holds at the vertices.

``beta`` multiplies ``P``, so for a fixed ``beta`` the problem is a semidefinite program
(solved with cvxpy and Clarabel, SCS as a fallback); ``beta`` is searched on a grid over
``(0, 1)`` and refined by a bounded scalar search around the best grid point (``tau(beta)``
is not known to be unimodal; the grid guards against a local maximum, the refinement
gives the last digits). ``beta = 1`` forces ``tau <= 0`` and is never optimal.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from quadobs.errors import QuadobsError, as_array
from quadobs.sets.zonotope import IntervalMatrix, Zonotope

__all__ = ["PRadiusDesign", "pradius_gains", "pradius_lmi_matrices", "require_lmi_solvers"]

#: A solution ``P`` with ``lambda_min(P) <= SINGULAR_RTOL lambda_max(P)`` counts as infeasible:
#: when no ``P > 0`` satisfies the LMI, the solver's supremum ``tau = 0`` is approached by a
#: ``P`` that becomes singular.
SINGULAR_RTOL = 1e-7

#: The default grid of beta values searched before refinement.
DEFAULT_BETAS = np.linspace(0.02, 0.98, 49)


@dataclass(frozen=True, eq=False)
class PRadiusDesign:
    """The result of :func:`pradius_gains`.

    Attributes
    ----------
    gains : ndarray (n_y, n_x)
        ``lambda_i`` of each output, in output order (row ``i`` corrects with ``y_{k/i}``).
    P : ndarray (n_y, n_x, n_x)
        The matrix of the P-radius certified for the correction by output ``i``.
    beta : ndarray (n_y,)
        Contraction factor of each design step.
    tau : ndarray (n_y,)
        Optimal ``tau``: the limit ellipsoid has diameter ``2 / sqrt(tau)``.
    approach : int
        1 (section 4.1) or 2 (section 4.2, Algorithm 2).
    psi : float
        ``max_{gamma in B} ||F gamma||_2^2``.
    noise_bounds : ndarray (n_y,)
        ``phi_i``.
    solver : str
    lmi_margin : float
        Smallest eigenvalue of the LMI matrices at the solution, relative to their largest
        entry (checked with NumPy, independently of the solver; ``>= -1e-6`` or the design fails).
    seconds : float
        Wall-clock time of the design.
    """

    gains: np.ndarray
    P: np.ndarray
    beta: np.ndarray
    tau: np.ndarray
    approach: int
    psi: float
    noise_bounds: np.ndarray
    solver: str
    lmi_margin: float
    seconds: float

    def offset(self, i: int) -> float:
        """The constant ``psi + phi_1^2 + ... + phi_i^2`` (approach 2) or ``psi + phi_i^2`` (approach 1) of step ``i``."""
        phi = self.noise_bounds
        return self.psi + (
            float(np.sum(phi[: i + 1] ** 2)) if self.approach == 2 else float(phi[i] ** 2)
        )


def _as_vertices(A_vertices) -> np.ndarray:
    if isinstance(A_vertices, IntervalMatrix):
        return A_vertices.vertices()
    G = as_array("A_vertices", A_vertices)
    if G.ndim == 2:
        G = G[None]
    if G.ndim != 3 or G.shape[1] != G.shape[2] or G.shape[0] == 0:
        raise QuadobsError(
            f"A_vertices: expected (n, n), (V, n, n) or an IntervalMatrix, got shape {G.shape}"
        )
    return G


def pradius_lmi_matrices(P, lam, beta, KG, KF, F, prev, prev_phi, c, phi) -> list[np.ndarray]:
    """The matrices of the step LMI (module docstring) at given ``(P, lambda, beta)``, one per vertex.

    ``KG (V, n, n)``: ``K_{j-1} G_i``; ``KF (n, n_w)``: ``K_{j-1} F``; ``prev``: the vectors ``v_l``
    and ``prev_phi`` their ``phi_l``; ``c (n,)`` and ``phi``: output ``j``. Used to check a
    solution independently of the solver (every matrix must be positive semidefinite).
    """
    P = np.asarray(P, dtype=float)
    Y = P @ lam
    n, nw, d = P.shape[0], F.shape[1], len(prev) + 1
    out = []
    for G in KG:
        Xi = np.vstack(
            [G.T @ P - np.outer(G.T @ c, Y), KF.T @ P - np.outer(KF.T @ c, Y)]
            + [(v @ P - (v @ c) * Y)[None] for v in prev]
            + [phi * Y[None]]
        )
        D = np.zeros((n + nw + d, n + nw + d))
        D[:n, :n] = beta * P
        D[n : n + nw, n : n + nw] = F.T @ F
        D[n + nw :, n + nw :] = np.diag(
            np.concatenate([np.asarray(prev_phi, dtype=float) ** 2, [phi**2]])
        )
        out.append(np.block([[D, Xi], [Xi.T, P]]))
    return out


class _StepProblem:
    """The step-``j`` SDP with ``beta`` as a cvxpy parameter (compiled once, solved per ``beta``)."""

    def __init__(self, KG, KF, F, prev, prev_phi, c, phi, offset, solver) -> None:
        import cvxpy as cp

        self.cp = cp
        n, nw, d = KG.shape[1], F.shape[1], len(prev) + 1
        self.P = P = cp.Variable((n, n), symmetric=True)
        self.Y = Y = cp.Variable(n)
        self.tau = tau = cp.Variable()
        self.beta = cp.Parameter(nonneg=True)
        self.scale = cp.Parameter(nonneg=True)  # (1 - beta) / offset
        Yr = cp.reshape(Y, (1, n), order="C")
        FtF = F.T @ F
        cons = [tau >= 0, self.scale * P - tau * np.eye(n) >> 0]
        for G in KG:
            blocks_xi = [G.T @ P - (G.T @ c)[:, None] @ Yr, KF.T @ P - (KF.T @ c)[:, None] @ Yr]
            blocks_xi += [cp.reshape(v @ P, (1, n), order="C") - float(v @ c) * Yr for v in prev]
            blocks_xi += [phi * Yr]
            Xi = cp.vstack(blocks_xi)
            Dparts = cp.bmat(
                [
                    [self.beta * P, np.zeros((n, nw)), np.zeros((n, d))],
                    [np.zeros((nw, n)), FtF, np.zeros((nw, d))],
                    [
                        np.zeros((d, n)),
                        np.zeros((d, nw)),
                        np.diag(np.concatenate([np.asarray(prev_phi) ** 2, [phi**2]])),
                    ],
                ]
            )
            big = cp.bmat([[Dparts, Xi], [Xi.T, P]])
            cons.append(0.5 * (big + big.T) >> 0)
        self.problem = cp.Problem(cp.Maximize(tau), cons)
        self.offset = offset
        self.solver = solver

    def solve(self, beta: float) -> tuple[float, np.ndarray | None, np.ndarray | None, str]:
        cp = self.cp
        self.beta.value = float(beta)
        self.scale.value = (1.0 - float(beta)) / self.offset
        used = ""
        for solver in self.solver:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter(
                        "ignore"
                    )  # "solution may be inaccurate": checked below by the caller
                    self.problem.solve(solver=solver)
                used = solver
            except cp.error.SolverError:
                continue
            if self.problem.status in ("optimal", "optimal_inaccurate"):
                break
        if self.problem.status not in ("optimal", "optimal_inaccurate") or self.tau.value is None:
            return -np.inf, None, None, used
        P = np.array(self.P.value)
        P = 0.5 * (P + P.T)
        eig = np.linalg.eigvalsh(P)
        if eig[0] <= SINGULAR_RTOL * eig[-1]:
            # sup tau = 0, approached by a P that becomes singular: no P > 0 exists
            return -np.inf, None, None, used
        return float(self.tau.value), P, np.linalg.solve(P, np.array(self.Y.value)), used


def _design_step(KG, KF, F, prev, prev_phi, c, phi, offset, betas, refine, solvers, label):
    prob = _StepProblem(KG, KF, F, prev, prev_phi, c, phi, offset, solvers)
    results = [(b, *prob.solve(b)) for b in betas]
    best = max(results, key=lambda r: r[1])
    if not np.isfinite(best[1]) or best[1] <= 0:
        raise QuadobsError(
            f"{label}: the P-radius LMI (problem 9) is infeasible for every beta in (0, 1) tried "
            f"({len(betas)} values from {min(betas):.3g} to {max(betas):.3g}); [A] may not be quadratically "
            "stable with this output, or (C, A) not detectable"
        )
    if refine and len(betas) > 1:
        from scipy.optimize import minimize_scalar

        grid = np.sort(np.asarray(betas))
        i = int(np.searchsorted(grid, best[0]))
        lo = grid[i - 1] if i > 0 else grid[0] / 2
        hi = grid[i + 1] if i + 1 < len(grid) else (grid[-1] + 1.0) / 2
        cache = {}

        def neg(b):
            r = prob.solve(b)
            cache[b] = r
            return -r[0]

        res = minimize_scalar(neg, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
        if res.x in cache and cache[res.x][0] > best[1]:
            best = (res.x, *cache[res.x])
    beta, tau, P, lam, used = best
    mats = pradius_lmi_matrices(P, lam, beta, KG, KF, F, prev, prev_phi, c, phi)
    margin = min(
        float(np.linalg.eigvalsh(0.5 * (M + M.T))[0]) / max(np.abs(M).max(), 1e-300) for M in mats
    )
    if margin < -1e-6:
        raise QuadobsError(
            f"{label}: the solver's solution violates the LMI (relative smallest eigenvalue {margin:.3g}); "
            "try another solver"
        )
    return float(beta), float(tau), P, lam, used, margin


#: The optional dependencies of the LMI design, and the extra that installs them.
LMI_EXTRA = "sets"


def require_lmi_solvers(what: str) -> None:
    """Refuse, in one line naming the extra, an LMI design without cvxpy (and its Clarabel solver).

    The core install leaves them out (about 200 MB with their dependencies): only the offline
    design of [LE2013] needs them, ``pip install 'quadobs[sets]'`` adds them.
    """
    try:
        import cvxpy  # noqa: F401
    except ImportError:
        raise QuadobsError(
            f"{what}: the LMI design needs cvxpy and Clarabel, not installed: "
            f"pip install 'quadobs[{LMI_EXTRA}]'"
        ) from None


def _design_inputs(A_vertices, F, C, noise_bounds, approach, betas):
    """The design's inputs checked (one-line errors naming each): ``G, F, C, phi, betas``."""
    G = _as_vertices(A_vertices)
    n = G.shape[1]
    F = as_array("F", F)
    if F.ndim == 1:
        F = F[:, None]
    if F.ndim != 2 or F.shape[0] != n:
        raise QuadobsError(f"F: expected shape ({n}, n_w), got {F.shape}")
    C = as_array("C", C)
    if C.ndim == 1:
        C = C[None]
    if C.ndim != 2 or C.shape[1] != n or C.shape[0] == 0:
        raise QuadobsError(f"C: expected shape (n_y, {n}), got {C.shape}")
    ny = C.shape[0]
    phi = as_array("noise_bounds", noise_bounds)
    phi = np.full(ny, float(phi)) if phi.ndim == 0 else phi
    if phi.shape != (ny,) or np.any(phi <= 0):
        raise QuadobsError(f"noise_bounds: expected {ny} positive bounds, got {noise_bounds!r}")
    if approach not in (1, 2):
        raise QuadobsError(f"approach: expected 1 or 2, got {approach!r}")
    betas = DEFAULT_BETAS if betas is None else as_array("betas", betas, (None,))
    if betas.size == 0 or np.any(betas <= 0) or np.any(betas >= 1):
        raise QuadobsError("betas: expected values in (0, 1)")
    return G, F, C, phi, betas


def pradius_gains(
    A_vertices,
    F,
    C,
    noise_bounds,
    approach: int = 2,
    *,
    betas=None,
    refine: bool = True,
    solver: str | None = None,
) -> PRadiusDesign:
    """The P-radius gains ``lambda_i`` and matrices ``P_i`` of [LE2013] sections 4.1-4.2.

    Parameters
    ----------
    A_vertices : array_like (n, n) or (V, n, n), or IntervalMatrix
        ``A``, the vertices ``G_i`` of ``[A]``, or ``[A]`` itself (its vertices are used).
    F : array_like (n, n_w) or (n,)
        Disturbance generators: ``W = F B^{n_w}``.
    C : array_like (n_y, n) or (n,)
        Output matrix, rows ``c_i^T`` in the order of the corrections.
    noise_bounds : float or array_like (n_y,)
        ``phi_i``: ``|v_{k/i}| <= phi_i``, positive.
    approach : {1, 2}
        1: each output on its own (problem 9 per output). 2: Algorithm 2, output ``j`` designed
        knowing ``lambda_1..lambda_{j-1}`` (the first gain is that of approach 1).
    betas : array_like, optional
        Grid of ``beta`` values in ``(0, 1)`` (default 49 values 0.02, 0.04, ..., 0.98).
    refine : bool
        Refine ``beta`` by a bounded scalar search around the best grid value.
    solver : str, optional
        A cvxpy solver name; default Clarabel, then SCS if Clarabel fails.

    Returns
    -------
    PRadiusDesign

    Raises
    ------
    QuadobsError
        On bad shapes or bounds, or when the LMI is infeasible for every ``beta`` tried.
    """
    t0 = time.perf_counter()
    G, F, C, phi, betas = _design_inputs(A_vertices, F, C, noise_bounds, approach, betas)
    n, ny = G.shape[1], C.shape[0]
    solvers = [solver] if solver else ["CLARABEL", "SCS"]
    require_lmi_solvers("pradius_gains")
    psi = Zonotope(np.zeros(n), F).p_radius() if F.shape[1] else 0.0

    gains = np.zeros((ny, n))
    Ps = np.zeros((ny, n, n))
    beta_out = np.zeros(ny)
    tau_out = np.zeros(ny)
    used = ""
    lmi_margin = np.inf
    K = np.eye(n)
    vs: list[np.ndarray] = []
    for j in range(ny):
        c = C[j]
        if approach == 1:
            KG, KF, prev, prev_phi, offset = G, F, [], [], psi + phi[j] ** 2
        else:
            KG, KF, prev, prev_phi = K @ G, K @ F, list(vs), list(phi[:j])
            offset = psi + float(np.sum(phi[: j + 1] ** 2))
        beta, tau, P, lam, used, margin = _design_step(
            KG, KF, F, prev, prev_phi, c, phi[j], offset, betas, refine, solvers, f"output {j}"
        )
        gains[j], Ps[j], beta_out[j], tau_out[j] = lam, P, beta, tau
        lmi_margin = min(lmi_margin, margin)
        if approach == 2:
            kappa = np.eye(n) - np.outer(lam, c)
            vs = [kappa @ v for v in vs] + [phi[j] * lam]
            K = kappa @ K
    for arr in (gains, Ps, beta_out, tau_out, phi):
        arr.setflags(write=False)
    return PRadiusDesign(
        gains,
        Ps,
        beta_out,
        tau_out,
        approach,
        float(psi),
        phi,
        used,
        float(lmi_margin),
        time.perf_counter() - t0,
    )
