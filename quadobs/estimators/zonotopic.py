"""Zonotopic guaranteed state estimation [LE2013, Alg. 1].

For ``x_{k+1} = A x_k + w_k``, ``y_k = C x_k + v_k`` with ``A in [A]``, ``w_k in W = F B^{n_w}``,
``|v_{k/i}| <= phi_i`` and ``x_0 in X_0``, :class:`ZonotopicEstimator` keeps a zonotope
``X_k`` that contains every state consistent with the model and the measurements:

1. prediction (eq. 2): ``X_k^- = A X_{k-1} (+) W``; with an interval ``[A]``, the outer
   approximation of section 4.1, ``mid[A] p (+) [mid[A] H, rs(rad[A]|H|), rs(rad[A]|p|), F] B``
   (:func:`~quadobs.sets.zonotope.interval_image`);
2. correction (eq. 3): for ``i = 1..n_y``, the strip ``|c_i^T x - y_{k/i}| <= phi_i`` is
   intersected by Property 6 with a gain ``lambda_i``; any gain gives a set that contains
   the intersection, so containment never depends on the gain, only the size does;
3. order reduction (Property 3) to at most ``max_generators`` generators.

Gains (:data:`GAINS`):

* P-radius (sections 4.1, 4.2): fixed gains designed offline (:func:`quadobs.pradius_gains`);
* segment minimisation (Alamo, Bravo and Camacho 2005): the ``lambda`` minimising the
  F-radius ``||H(lambda)||_F^2 = ||(I - lambda c^T) H||_F^2 + phi^2 ||lambda||^2``,
  in closed form ``lambda = H H^T c / (c^T H H^T c + phi^2)`` (:func:`segment_gain`);
* volume minimisation (Alamo et al. 2005): the ``lambda`` minimising the volume of
  Property 6's zonotope, a convex piecewise-linear function of ``lambda`` minimised
  exactly by a linear program (:func:`volume_gain`).

The online step has two implementations (``backend``): the reference, written with the set
calculus of :mod:`quadobs.sets.zonotope` (a new :class:`~quadobs.sets.zonotope.Zonotope` per
operation, every operand validated), and compiled kernels (:mod:`quadobs._kernels.zonotope`)
that rewrite one buffer in place and hand back one zonotope per step; they agree to rounding.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import combinations
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError, as_array
from quadobs.estimators.base import Estimator, SetValued
from quadobs.sets.zonotope import IntervalMatrix, Zonotope, reduce_generators
from quadobs.sets.zonotope import segment_gain as zonotope_segment_gain

__all__ = ["GAINS", "ZonotopicEstimator", "segment_gain", "volume_gain", "volume_gain_terms"]


def segment_gain(Z: Zonotope, c: np.ndarray, phi: float) -> np.ndarray:
    """Segment (F-radius) minimisation: ``argmin_lambda ||H(lambda)||_F^2`` of Property 6's family.

    ``lambda = H H^T c / (c^T H H^T c + phi^2)``: :func:`quadobs.sets.zonotope.segment_gain`
    on the generators of ``Z``.
    """
    return zonotope_segment_gain(Z.generators, c, phi)


def volume_gain_terms(H: np.ndarray, c: np.ndarray) -> tuple[float, np.ndarray]:
    """``(a, G)`` with ``vol(H(lambda)) = 2^n (a |1 - c^T lambda| + phi sum_T |G_T lambda|)``.

    For Property 6's generators ``[(I - lambda c^T) H, phi lambda]``, an ``n``-subset of the
    first block has ``det((I - lambda c^T) H_S) = (1 - c^T lambda) det H_S``; a subset holding
    ``phi lambda`` and ``H_T`` (``|T| = n - 1``) has, by column operations,
    ``det([(I - lambda c^T) H_T, phi lambda]) = phi det([H_T, lambda]) = phi G_T lambda`` with
    ``G_T[i] = det([H_T, e_i])``. So ``a = sum_S |det H_S|``.
    """
    n, m = H.shape
    if m >= n:
        idx = np.array(list(combinations(range(m), n)))
        a = (
            float(np.abs(np.linalg.det(H[:, idx].transpose(1, 0, 2))).sum())
            if n > 1
            else float(np.abs(H).sum())
        )
    else:
        a = 0.0
    if n == 1:
        return a, np.ones((1, 1))
    if m < n - 1:
        return a, np.zeros((0, n))
    T = np.array(list(combinations(range(m), n - 1)))
    sub = H[:, T].transpose(1, 0, 2)  # (k, n, n-1)
    G = np.empty((len(T), n))
    eye = np.eye(n)
    for i in range(n):
        G[:, i] = np.linalg.det(
            np.concatenate([sub, np.broadcast_to(eye[:, i, None], (len(T), n, 1))], axis=2)
        )
    return a, G


def volume_gain(Z: Zonotope, c: np.ndarray, phi: float) -> np.ndarray:
    """Volume minimisation: ``argmin_lambda vol(Z(lambda))`` of Property 6's family, by a linear program.

    Minimises ``a s_0 + phi sum_T s_T`` over ``(lambda, s)`` with ``s_0 >= |1 - c^T lambda|`` and
    ``s_T >= |G_T lambda|`` (:func:`volume_gain_terms`), with HiGHS. The objective is convex,
    so the optimum is global.
    """
    return _volume_gain(Z.generators, c, phi)


def _volume_gain(H: np.ndarray, c: np.ndarray, phi: float) -> np.ndarray:
    """:func:`volume_gain` on the generators ``H (n, m)`` of the set."""
    from scipy.optimize import linprog

    n = H.shape[0]
    a, G = volume_gain_terms(H, c)
    k = G.shape[0]
    # variables: lambda (n), s0, s_T (k)
    cost = np.concatenate([np.zeros(n), [a], np.full(k, phi)])
    A_ub = np.zeros((2 + 2 * k, n + 1 + k))
    b_ub = np.zeros(2 + 2 * k)
    A_ub[0, :n], A_ub[0, n], b_ub[0] = -c, -1.0, -1.0  # 1 - c^T lam <= s0
    A_ub[1, :n], A_ub[1, n], b_ub[1] = c, -1.0, 1.0  # c^T lam - 1 <= s0
    A_ub[2 : 2 + k, :n], A_ub[2 : 2 + k, n + 1 :] = G, -np.eye(k)
    A_ub[2 + k :, :n], A_ub[2 + k :, n + 1 :] = -G, -np.eye(k)
    res = linprog(
        cost,
        A_ub=A_ub,
        b_ub=b_ub,
        bounds=[(None, None)] * n + [(0, None)] * (1 + k),
        method="highs",
    )
    if res.status != 0:
        raise QuadobsError(f"volume_gain: the linear program failed ({res.message})")
    return res.x[:n]


#: Online gain rules ``f(Z, c, phi) -> lambda``.
GAINS: dict[str, Callable[[Zonotope, np.ndarray, float], np.ndarray]] = {
    "segment": segment_gain,
    "volume": volume_gain,
}


class ZonotopicEstimator(Estimator, SetValued):
    """Algorithm 1: a zonotope guaranteed to contain the state of an uncertain linear system.

    The system has no input: :meth:`step` takes ``(u, y)`` with an empty ``u`` (shape
    ``(0,)``), as every :class:`~quadobs.estimators.base.Estimator`, or ``y`` alone.

    Parameters
    ----------
    A : array_like (n, n) or IntervalMatrix
        The state matrix, or the interval matrix ``[A]`` it lies in.
    F : array_like (n, n_w) or (n,)
        ``W = F B^{n_w}``.
    C : array_like (n_y, n)
        Output rows ``c_i^T``, corrected in this order.
    noise_bounds : float or array_like (n_y,)
        ``phi_i`` (``V = diag(phi) B^{n_y}``).
    X0 : Zonotope
        Initial set.
    gain : str, PRadiusDesign, array_like (n_y, n) or callable
        ``"segment"``, ``"volume"``, fixed gains (a :class:`~quadobs.sets.pradius.PRadiusDesign` or
        their ``(n_y, n)`` array), or ``f(Z, c, phi) -> lambda``.
    max_generators : int
        Order bound applied after each correction (the paper's example: 20).
    reduction : str or callable
        Reduction method of :func:`~quadobs.sets.zonotope.reduce_generators`.
    backend : {"auto", "numba", "numpy"}
        ``"numba"``: :meth:`step` runs compiled kernels (:mod:`quadobs._kernels.zonotope`) on a
        buffer that is rewritten in place, for fixed, ``"segment"`` and ``"volume"`` gains
        with the ``"combastel"`` reduction (the volume gain's linear program stays in
        Python); ``"numpy"``: the reference, :meth:`predict` then :meth:`correct` with the
        set calculus of :mod:`quadobs.sets.zonotope`. The two agree to rounding. ``"auto"``
        (default) picks ``"numba"`` where it applies and Numba imports.

    Attributes
    ----------
    zonotope : Zonotope
        The current set: ``X_0`` before the first step, then ``X_k`` after ``k`` steps.
    backend : str
        ``"numba"`` or ``"numpy"`` (what ``"auto"`` resolved to).
    """

    def __init__(
        self,
        A,
        F,
        C,
        noise_bounds,
        X0: Zonotope,
        gain="segment",
        *,
        max_generators: int = 20,
        reduction="combastel",
        backend: str = "auto",
    ) -> None:
        if isinstance(A, IntervalMatrix):
            self.A_interval = A
            self.A = A.mid
            self.uncertain = bool(np.any(A.rad > 0))
        else:
            self.A = as_array("A", A, ndim=2)
            self.A_interval = IntervalMatrix.point(self.A)
            self.uncertain = False
        n = self._n = self.A.shape[0]
        if self.A.shape != (n, n):
            raise QuadobsError(f"A: expected a square matrix, got shape {self.A.shape}")
        F = as_array("F", F)
        self.F = F[:, None] if F.ndim == 1 else F
        if self.F.shape[0] != n:
            raise QuadobsError(f"F: expected {n} rows, got shape {self.F.shape}")
        C = as_array("C", C)
        self.C = C[None] if C.ndim == 1 else C
        if self.C.ndim != 2 or self.C.shape[1] != n:
            raise QuadobsError(f"C: expected shape (n_y, {n}), got {self.C.shape}")
        ny = self.C.shape[0]
        phi = as_array("noise_bounds", noise_bounds)
        self.phi = np.full(ny, float(phi)) if phi.ndim == 0 else phi
        if self.phi.shape != (ny,) or np.any(self.phi < 0):
            raise QuadobsError(f"noise_bounds: expected {ny} non-negative bounds")
        if not isinstance(X0, Zonotope) or X0.dim != n:
            raise QuadobsError(f"X0: expected a Zonotope of dimension {n}")
        self.fixed_gains: Any = None  # (ny, n), or None with a gain rule
        self.gain_rule: Any = None  # a callable, or None with fixed gains
        if isinstance(gain, str):
            if gain not in GAINS:
                raise QuadobsError(
                    f"gain: unknown rule {gain!r}; expected one of {', '.join(GAINS)}, fixed gains or a callable"
                )
            self.gain_rule = GAINS[gain]
        elif callable(gain):
            self.gain_rule = gain
        else:
            gains = getattr(gain, "gains", gain)
            self.fixed_gains = as_array("gain", gains, (ny, n))
        self.max_generators = int(max_generators)
        self.reduction = reduction
        reduce_generators(np.zeros((n, 0)), self.max_generators)  # validates max_generators
        self.backend = self._choose_backend(backend)
        self._Z: Zonotope | None = None
        self._S: Any = None  # the compiled kernels' state buffer, once loaded
        if self.backend == "numba":
            self._setup_kernel()
        self.zonotope = X0.reduce(self.max_generators, reduction)
        self.steps = 0

    # -- the compiled path -----------------------------------------------------------------

    def _kernel_mode(self) -> int | None:
        """Gain mode of :mod:`quadobs._kernels.zonotope` (0 fixed, 1 segment, 2 volume), or None."""
        if not (isinstance(self.reduction, str) and self.reduction == "combastel"):
            return None
        if self.fixed_gains is not None:
            return 0
        if self.gain_rule is segment_gain:
            return 1
        if self.gain_rule is volume_gain:
            return 2
        return None

    def _choose_backend(self, backend: str) -> str:
        from quadobs.estimators.augmented import resolve_backend

        if backend not in ("auto", "numba", "numpy"):
            raise QuadobsError(
                f"backend: expected one of ('auto', 'numba', 'numpy'), got {backend!r}"
            )
        supported = self._kernel_mode() is not None
        if backend == "numba" and not supported:
            raise QuadobsError(
                "backend: 'numba' runs fixed, 'segment' or 'volume' gains with the 'combastel' reduction; "
                f"got gain {self.gain_rule or 'fixed'!r} and reduction {self.reduction!r} (use backend='numpy')"
            )
        resolved = resolve_backend(backend)
        return resolved if supported else "numpy"

    def _setup_kernel(self) -> None:
        n, nw, ny = self.A.shape[0], self.F.shape[1], self.C.shape[0]
        mode = self._kernel_mode()
        gains = self.fixed_gains if self.fixed_gains is not None else np.zeros((ny, n))
        parts = [self.A_interval.mid, self.A_interval.rad, self.F, self.C, self.phi, gains]
        self._fc = np.ascontiguousarray(np.concatenate([np.ravel(a) for a in parts]))
        self._ic = np.array(
            [n, nw, ny, self.max_generators, 0, mode, int(self.uncertain)], dtype=np.int64
        )
        self._bind_kernels()

    def _bind_kernels(self) -> None:
        import quadobs._kernels.zonotope as zk

        self._kstep, self._kpredict, self._kstrip, self._kreduce = (
            zk.zonotope_step,
            zk.zonotope_predict,
            zk.zonotope_strip,
            zk.zonotope_reduce,
        )

    def _load(self, Z: Zonotope) -> None:
        """Copy ``Z`` into the buffer ``S`` of the kernels, enlarging it when needed."""
        from quadobs._kernels.zonotope import out_offset, state_size

        n, m = Z.dim, Z.order
        grow = n + self.F.shape[1] + self.C.shape[0]  # columns added by one predict + correct
        cap = max(m, self.max_generators) + grow
        if self._S is None or int(self._ic[4]) < cap:
            self._ic[4] = cap
            self._S = np.zeros(state_size(n, cap))
            self._out = out_offset(n, cap)
            self._H = self._S[1 + n : 1 + n + n * cap].reshape(n, cap)
            # compile (or load) the kernels now, on scratch copies, rather than in the first step
            S, ic = self._S.copy(), self._ic.copy()
            if self._kernel_mode() != 2:
                self._kstep(np.full(self.C.shape[0], np.nan), S, self._fc, ic)
            else:
                self._kpredict(S, self._fc, ic)
                self._kstrip(S, self._fc, ic, 0, 0.0, np.zeros(n))
                self._kreduce(S, ic)
        self._S[0] = m
        self._S[1 : 1 + n] = Z.center
        self._H[:, :m] = Z.generators
        self._m = m

    def _build(self) -> Zonotope:
        """The set of the buffer, from the block ``[p, H]`` written at the end of a kernel step."""
        n, m, o = self._n, self._m, self._out
        buf = self._S[o : o + n + n * m].copy()
        buf.setflags(write=False)  # and so its views
        return Zonotope._trusted(buf[:n], buf[n:].reshape(n, m))

    @property
    def zonotope(self) -> Zonotope:
        """The current set: ``X_0`` before the first step, then ``X_k`` after ``k`` steps."""
        if self._Z is None:
            self._Z = self._build()
        return self._Z

    @zonotope.setter
    def zonotope(self, Z: Zonotope) -> None:
        if not isinstance(Z, Zonotope) or Z.dim != self.A.shape[0]:
            raise QuadobsError(f"zonotope: expected a Zonotope of dimension {self.A.shape[0]}")
        self._Z = Z
        if self.backend == "numba":
            self._load(Z)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        for key in ("_kstep", "_kpredict", "_kstrip", "_kreduce"):
            state.pop(key, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self.backend == "numba":
            self._H = self._S[
                1 + self.A.shape[0] : 1 + self.A.shape[0] + self.A.shape[0] * int(self._ic[4])
            ].reshape(self.A.shape[0], -1)
            self._bind_kernels()

    def _step_kernel(self, y) -> None:
        """:meth:`step` on the buffer (validation of ``y`` as :meth:`correct`)."""
        try:
            y = np.asarray(y, dtype=np.float64)
        except (TypeError, ValueError):
            y = as_array("y", y, (self.C.shape[0],), allow_nan=True)
        if y.shape != (self.C.shape[0],):
            y = as_array("y", y, (self.C.shape[0],), allow_nan=True)
        S, fc, ic = self._S, self._fc, self._ic
        if ic[5] != 2:
            m = self._kstep(y, S, fc, ic)
            if m < 0:
                as_array("y", y, allow_nan=True)  # raises, naming the infinity
        else:
            if np.isinf(y).any():
                as_array("y", y, allow_nan=True)
            self._kpredict(S, fc, ic)
            for i, c in enumerate(self.C):
                if y[i] != y[i]:
                    continue
                lam = _volume_gain(self._H[:, : int(S[0])], c, float(self.phi[i]))
                self._kstrip(S, fc, ic, i, float(y[i]), lam)
            m = self._kreduce(S, ic)
        self._m = m
        self._Z = None

    name = "zonotope-linear"

    @property
    def x_hat(self) -> np.ndarray:
        """Centre of the current set ``(n,)`` (read-only; a step makes a new set)."""
        return self.zonotope.center

    @property
    def bounds(self) -> np.ndarray:
        """Interval hull of the current set ``(n, 2)``: guaranteed bounds of each state."""
        return self.zonotope.interval_hull()

    def predict(self) -> Zonotope:
        """Step 1 of Algorithm 1: ``A X (+) W`` (outer approximation for an interval ``[A]``)."""
        from quadobs.sets.zonotope import interval_image

        Z = self.zonotope
        if self.uncertain:
            Zp = interval_image(self.A_interval, Z)
        else:
            Zp = Zonotope(self.A @ Z.center, self.A @ Z.generators)
        self.zonotope = Zonotope(Zp.center, np.hstack([Zp.generators, self.F]))
        return self.zonotope

    def correct(self, y) -> Zonotope:
        """Step 2 of Algorithm 1: one strip per output (NaN entries skipped), then order reduction."""
        y = as_array("y", y, (self.C.shape[0],), allow_nan=True)
        Z = self.zonotope
        for i, c in enumerate(self.C):
            if np.isnan(y[i]):
                continue
            lam = (
                self.fixed_gains[i]
                if self.fixed_gains is not None
                else self.gain_rule(Z, c, float(self.phi[i]))
            )
            Z = Z.strip_intersection(c, float(y[i]), float(self.phi[i]), lam)
        self.zonotope = Z.reduce(self.max_generators, self.reduction)
        return self.zonotope

    def step(self, u, y=None) -> Zonotope:
        """Predict to the next sample, then correct with its output ``y (n_y,)`` (a bad ``y`` changes nothing).

        Called as ``step(u, y)`` with ``u`` of shape ``(0,)`` (the system has no input), or as
        ``step(y)``. Returns the new set.
        """
        if y is None:
            y = u
        elif np.shape(u) != (0,):
            raise QuadobsError(
                f"u: the system has no input, expected shape (0,), got {np.shape(u)}"
            )
        if self.backend == "numba":
            self._step_kernel(y)
        else:
            y = as_array("y", y, (self.C.shape[0],), allow_nan=True)
            self.predict()
            self.correct(y)
        self.steps += 1
        return self.zonotope
