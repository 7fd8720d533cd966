"""Guaranteed (zonotopic) localisation on the augmented system of a quadratic-output system.

The immersion (:mod:`quadobs.core.immersion`) turns ``x' = A x + B u``, ``y_h = x^T C_h x / 2 + d_h^T x``
into ``z' = A(u) z + B u``, ``y = C z`` with ``z = (xi, x)``, and
:class:`~quadobs.core.held_input.HeldInputDiscretization` gives its exact step under a held input,
``z_{k+1} = Phi(u) z_k + g(u)``, ``Phi(u) = F0 + sum_j u_j F1[j]`` (``F1`` in the ``xi``-``x``
block), ``g(u) = (u^T G2_a u, G0 u)``. :class:`ZonotopicAugmentedEstimator` runs [LE2013, Alg. 1]
on it, a zonotope ``Z_k`` in ``z``-space that contains the true
``z_k = lift(x_k)`` whenever the noise bounds hold. Every source of error is bounded:

Output noise (one strip per sampled output). A range ``rho~ = rho + n``, ``|n| <= nbar``, gives
``y = rho~^2/2 - k_h`` (``k_h = |a_h|^2/2``; ``k = 0`` for the airspeed). The true range lies in
``[max(0, |rho~| - nbar), |rho~| + nbar]`` (``|rho~|`` is what ``y`` keeps, and ``rho >= 0``), so the
true output ``y* = rho^2/2 - k_h`` lies in the strip with centre and half-width

.. math::

    y_c = \\tfrac14(\\rho_{hi}^2 + \\rho_{lo}^2) - k_h, \\qquad
    \\phi = \\tfrac14(\\rho_{hi}^2 - \\rho_{lo}^2)
    \\;(= \\bar n\\,|\\tilde\\rho|,\\; y_c = y + \\bar n^2/2 \\text{ when } |\\tilde\\rho| \\ge \\bar n),

which is exact (both ends are reached); the bound grows with the measured range.

Input error. The accelerometer gives ``u = u* + du`` with ``|du_j| <= ubar``. The true step is
``Phi(u*) z + g(u*) = Phi(u) z + g(u) - E(x) du - J(u) du + q(du)``, where
``E(x) = [E_1 x, ..., E_p x]`` (``E_j`` = ``F1[j]`` in the ``xi`` rows), ``J(u)`` has the rows
``((G2_a + G2_a^T) u)^T`` for ``xi`` and ``G0`` for ``x``, and ``q(du)_a = du^T G2_a du``,
``|q_a| <= ubar^2 sum |G2_a|``. With ``x`` in the ``x``-part ``p_x (+) H_x B`` of ``Z_k``,
``E(x) + J(u)`` lies in the interval matrix with centre ``E(p_x) + J(u)`` and radius
``[|E_j H_x| 1]_j``, so by Property 4 the error lies in
``ubar (E(p_x) + J(u)) B^p (+) rs(ubar rad) B^N (+) box(q)``: ``p`` generators and a box.

Discretisation. The step map is exact for a held input (block exponentials), and the MuJoCo
truth integrates the double integrator with RK4, which is exact for a held force; what
remains is floating-point rounding, covered by a box of relative size :data:`ROUNDING_MARGIN`
of the set's extent added at every step (and the same relative margin on the strips and
the input bound). This covers rounding only: a model whose truth is *not* the held-input
double integrator (drag, rotation) would need its own error bound.

The gain of each strip is online: segment (F-radius) minimisation,
``lambda = H H^T c / (c^T H H^T c + phi^2)`` (``H H^T`` plays the role of a covariance), so it
changes every step; any gain keeps the guarantee, the gain only sets the size.
"""

from __future__ import annotations

import numpy as np

from quadobs.core.held_input import HeldInputDiscretization
from quadobs.core.immersion import Immersion, as_immersion
from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError, as_array
from quadobs.estimators.base import (
    Counted,
    HalfSteps,
    Immersed,
    SetValued,
    check_step,
    measurement_models,
)
from quadobs.sets.zonotope import Zonotope, reduce_generators, strip_update

__all__ = ["ROUNDING_MARGIN", "ZonotopicAugmentedEstimator", "lift_box", "range_strip"]

#: Relative margin per step for floating-point rounding (see the module docstring).
ROUNDING_MARGIN = 1e-12


def range_strip(y: float, offset: float, bound: float) -> tuple[float, float]:
    """``(y_c, phi)``: the true output ``rho^2/2 - offset`` lies in ``[y_c - phi, y_c + phi]``.

    ``y = rho~^2/2 - offset`` with ``rho~ = rho + n``, ``|n| <= bound``, ``rho >= 0`` (module docstring).
    """
    rho = np.sqrt(max(2.0 * (y + offset), 0.0))
    lo = max(0.0, rho - bound)
    hi = rho + bound
    yc = 0.25 * (hi * hi + lo * lo) - offset
    phi = 0.25 * (hi * hi - lo * lo)
    return yc, phi + ROUNDING_MARGIN * (abs(y) + offset + 1.0)


def lift_box(immersion: Immersion, x0, radius) -> Zonotope:
    """A zonotope containing ``lift(x)`` for every ``x`` in the box ``x0 ± radius``.

    With ``x = x0 + d``: ``xi_i = x0^T L_i x0 / 2 + (L_i x0)^T d + d^T L_i d / 2``. The linear
    part is kept exactly (generator ``k``: ``r_k ((L x0)_k, e_k)``, correlating ``xi`` with ``x``);
    the quadratic remainder is bounded by interval arithmetic,
    ``d^T L d / 2 in sum_k L_kk [0, r_k^2]/2 + sum_{k<l} |L_kl| r_k r_l [-1, 1]``, and boxed.
    """
    n = immersion.system.n
    x0 = as_array("x0", x0, (n,))
    r = as_array("radius", radius, (n,))
    if np.any(r < 0):
        raise QuadobsError("radius: must be non-negative")
    L = immersion.aux_forms
    k = immersion.n_aux
    Lx = L @ x0  # (k, n)
    diag = np.einsum("ikk->ik", L) * r**2 / 2.0  # (k, n)
    lo = np.minimum(diag, 0.0).sum(axis=1)
    hi = np.maximum(diag, 0.0).sum(axis=1)
    off = np.abs(L) * np.outer(r, r)
    cross = 0.5 * (off.sum(axis=(1, 2)) - np.einsum("ikk->i", off))
    lo, hi = lo - cross, hi + cross
    center = immersion.lift(x0)
    center[:k] += 0.5 * (lo + hi)
    H = np.zeros((k + n, n + k))
    H[:k, :n] = Lx * r
    H[k:, :n] = np.diag(r)
    H[:k, n:] = np.diag(0.5 * (hi - lo))
    H = H[:, np.any(H != 0, axis=0)]
    return Zonotope(center, H)


class ZonotopicAugmentedEstimator(HalfSteps, SetValued, Immersed, Counted):
    """Algorithm 1 on the exactly discretised augmented system (module docstring).

    Parameters
    ----------
    immersion : Immersion
    dt : float
        Step (s): one :meth:`step` per held input.
    x0 : array_like (n,)
        Centre of the initial box of ``x``.
    radius : array_like (n,)
        Half-widths of the initial box; the true initial state must lie in it.
    output_offsets : array_like (q,)
        ``k_h`` with ``y_h = rho~_h^2 / 2 - k_h`` (``|a_h|^2/2`` for a range, 0 for the airspeed).
    output_bounds : array_like (q,)
        ``nbar_h``: bound on the error of the measured range (or airspeed).
    input_bound : float or array_like (p,)
        ``ubar``: bound on each component of the accelerometer error.
    max_generators : int
        Order bound after each step (default ``10 N``).
    reduction : str or callable
        Method of :func:`~quadobs.sets.zonotope.reduce_generators`. The default ``"parallelotope"``
        encloses the discarded generators in a parallelotope framed by some of them: the set is
        reduced every step, and boxing in fixed axes (``"combastel"``) or in axes that turn
        from step to step (``"pca"``) compounds over thousands of steps and destroys the
        correlation between ``xi`` and ``x`` through which the ranges inform ``x``; the set then
        grows without bound (measured on ``ifac2021-bounded``).

    Attributes
    ----------
    zonotope : Zonotope
        The set of ``z`` at the time of :attr:`x_hat` (after :meth:`step`: the next step's start).
    bounds : ndarray (n, 2)
        Interval hull of the ``x``-part: guaranteed lower and upper bounds of each state.
    """

    name = "zonotope"

    def __init__(
        self,
        immersion: Immersion,
        dt: float,
        *,
        x0,
        radius,
        output_offsets,
        output_bounds,
        input_bound=0.0,
        max_generators: int | None = None,
        reduction="parallelotope",
    ) -> None:
        self.immersion = as_immersion(immersion)
        self.model = HeldInputDiscretization(immersion, dt)
        sys_ = immersion.system
        n, p, q, k, N = sys_.n, sys_.p, sys_.q, immersion.n_aux, immersion.dim
        self._k, self._n, self._N = k, n, N
        self.offsets = as_array("output_offsets", output_offsets, (q,))
        self.output_bounds = as_array("output_bounds", output_bounds, (q,))
        if np.any(self.output_bounds < 0):
            raise QuadobsError("output_bounds: must be non-negative")
        ub = as_array("input_bound", input_bound)
        self.input_bound = (
            np.full(p, float(ub)) if ub.ndim == 0 else as_array("input_bound", ub, (p,))
        )
        if np.any(self.input_bound < 0):
            raise QuadobsError("input_bound: must be non-negative")
        self.max_generators = 10 * N if max_generators is None else int(max_generators)
        reduce_generators(np.zeros((N, 0)), self.max_generators)  # validates max_generators
        self.reduction = reduction
        self.C = immersion.output_matrix
        m = self.model
        self._F0, self._F1, self._G0, self._G2 = (
            m.transition_constant,
            m.transition_input,
            m.input_linear,
            m.input_quadratic,
        )
        # G2_a + G2_a^T, arranged (k, p, p); |G2| summed per aux row for the quadratic remainder
        self._G2s = np.transpose(m.input_quadratic, (1, 0, 2)) + np.transpose(
            m.input_quadratic, (1, 2, 0)
        )
        self._G2abs = np.abs(m.input_quadratic).sum(axis=(0, 2))
        self._Phi = self._F0.copy()
        self.zonotope = lift_box(immersion, x0, radius)
        self.corrections = 0
        self.measurement_models = measurement_models(sys_, None)
        self._intervals: dict[float, HeldInputDiscretization] = {}
        self._time = 0.0

    # -- estimator interface -------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        return self.zonotope.center[self._k :]

    @property
    def bounds(self) -> np.ndarray:
        """Guaranteed bounds of ``x``: the interval hull of the set's ``x``-part, ``(n, 2)``."""
        return self.zonotope.interval_hull()[self._k :]

    def contains(self, x, *, tol: float = 1e-9) -> bool:
        """Whether ``lift(x)`` lies in the current set (a linear program; for checks, not every step)."""
        return bool(self.zonotope.contains(self.immersion.lift(x), tol=tol, method="lp"))

    def step(self, u, y) -> None:
        """Intersect with the strips of the outputs present in ``y``, then predict over the step with ``u`` held.

        A non-finite ``u``, an infinite ``y`` or a wrong shape raises :class:`QuadobsError`
        and leaves the set unchanged.
        """
        u, y = check_step(u, y, self._F1.shape[0], self.offsets.shape[0])  # before the set changes
        self.correct_outputs(y)
        self.predict_step(u)
        self._time += self.model.dt

    def _input(self, u) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        if u.shape != (self._F1.shape[0],) or not np.isfinite(u).all():
            u = as_array("u", u, (self._F1.shape[0],))  # raises, naming the problem
        return u

    # -- the two halves -------------------------------------------------------------

    def _input_dimension(self) -> int:
        return self._F1.shape[0]

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        """The set over ``dt`` (exact: the held-input discretisation over that interval, cached by
        its length)."""
        if abs(dt - self.model.dt) <= 1e-9 * self.model.dt:
            self.predict_step(u)
            return
        model = self._intervals.get(dt)
        if model is None:
            model = HeldInputDiscretization(self.immersion, dt)
            if len(self._intervals) < 64:
                self._intervals[dt] = model
        self.predict_step(u, model)

    def _correct_measurement(self, m: Measurement) -> None:
        """Intersect with the strip of a range (its error bound the output's ``output_bounds``)."""
        model = self._model_of(m)
        if model.kind != "range":
            raise QuadobsError(f"{self.name}: takes ranges only, not {m.kind} measurements")
        y = np.full(self.offsets.shape, np.nan)
        y[m.anchors[0]] = model.unbiased(m) ** 2 / 2.0 - self.offsets[m.anchors[0]]
        self.correct_outputs(y)

    def correct_outputs(self, y) -> None:
        """One strip per sampled output (NaN: not sampled), segment-minimising gains."""
        y = np.asarray(y, dtype=float)
        if y.shape != self.offsets.shape or np.isinf(y).any():
            y = as_array("y", y, self.offsets.shape, allow_nan=True)  # raises, naming the problem
        present = np.flatnonzero(~np.isnan(y))
        if present.size == 0:
            return
        Z = self.zonotope
        p, H = Z.center, Z.generators
        for h in present:
            yc, phi = range_strip(float(y[h]), float(self.offsets[h]), float(self.output_bounds[h]))
            p, H = strip_update(p, H, self.C[h], yc, phi)  # segment gain; new contiguous arrays
            self.corrections += 1
        p.setflags(write=False)
        H.setflags(write=False)
        self.zonotope = Zonotope._trusted(p, H)

    def predict_step(self, u, model: HeldInputDiscretization | None = None) -> None:
        """Exact held-input step of the set, plus the input-error and rounding terms (module docstring).

        Over the estimator's own step, or over ``model.dt`` with ``model`` (the interface in time).
        """
        u = self._input(u)
        k, N = self._k, self._N
        Z = self.zonotope
        pz, H = Z.center, Z.generators
        if model is None:
            model = self.model
            F1, G0, G2s, G2abs = self._F1, self._G0, self._G2s, self._G2abs
            Phi = model.transition(u, out=self._Phi)
        else:
            F1, G0, G2 = model.transition_input, model.input_linear, model.input_quadratic
            G2s = np.transpose(G2, (1, 0, 2)) + np.transpose(G2, (1, 2, 0))
            G2abs = np.abs(G2).sum(axis=(0, 2))
            Phi = model.transition(u)
        center = Phi @ pz + model.input_term(u)
        gens = [Phi @ H]
        ubar = self.input_bound * (1.0 + ROUNDING_MARGIN) + ROUNDING_MARGIN * (1.0 + np.abs(u))
        box = np.zeros(N)
        if np.any(ubar > 0):
            px, Hx = pz[k:], H[k:]
            mid = np.zeros((N, u.shape[0]))
            mid[:k] = np.einsum("jan,n->aj", F1, px) + np.einsum("apq,q->ap", G2s, u)
            mid[k:] = G0
            gens.append(mid * ubar)
            rad = np.abs(np.einsum("jan,nm->ajm", F1, Hx)).sum(axis=2)  # (k, p)
            box[:k] += rad @ ubar + G2abs * float(np.max(ubar)) ** 2
        extent = np.abs(center) + np.abs(H).sum(axis=1)
        box += ROUNDING_MARGIN * (1.0 + extent)
        if not (
            np.isfinite(center).all() and np.isfinite(box).all()
        ):  # box grows with |H|: catches H too
            raise QuadobsError("zonotope: the set is no longer finite (overflow)")
        gens.append(np.diag(box))
        Hn = np.hstack(gens)
        Hn = reduce_generators(Hn, self.max_generators, self.reduction)
        center.setflags(write=False)
        Hn.setflags(write=False)
        self.zonotope = Zonotope._trusted(center, Hn)
