"""Is the input exciting enough? The PE report and the live excitation monitor.

The augmented observer converges when the pair ``(A(u(t)), C)`` is uniformly observable
([IFAC2021] Definition 2 and Theorem 3), which depends on the input.
This module answers, for a scenario's input (before a run) or for the measured input
(during a run):

* the **Gramian measure** ``mu(t) = lambda_min W(t, t + delta)`` over sliding windows
  (:mod:`quadobs.observability.gramian`, eq. 27, exact for a held input), for any immersion, single or
  multiple outputs. ``mu > 0`` on every window is uniform observability over the record
  (Definition 2, eq. 2); ``mu = 0`` on a window means that window's outputs cannot
  determine the state (Theorem 1);
* **Proposition 4**, generalised: with ``u = 0`` (or when the input never enters ``A(u)``,
  ``B^T C_r = 0`` for all ``r``) the pair is the constant ``(A_0, C)``, observable only if
  its Kalman rank is ``N``; for the paper's single output without linear term that rank is
  ``m < N``, so such windows are never observable;
* the **sufficient conditions** of Propositions 5-8 (eqs. 29, 31, 37, 41; see
  :mod:`quadobs.observability.conditions`), for a single output under Assumption 1; for several outputs
  they are reported as not applicable.

Input derivatives (for the conditions) are analytic for a scenario's reference
(:meth:`quadobs.testbed.trajectory.SinusoidTrajectory.derivative`, orders ``2 + k``), or repeated
second-order central differences of a sampled input (``np.gradient``, one-sided at the
ends), at most :data:`MAX_FD_ORDER`; a condition needing more is reported "not evaluated".

Time conventions: the report's windows are ``[t, t + delta]`` (the paper's ``W(t, t + delta)``)
and it quotes their start ``t``; the live monitor's windows end at the current time,
``[t - delta, t]``, since only the past input is known during a run.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from quadobs.core.immersion import Immersion, observability_rank
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.observability.conditions import (
    DEFAULT_ZERO_RTOL,
    ChainStructure,
    ConditionSeries,
    chain_structure,
    condition_eq29,
    condition_eq31,
    condition_eq37,
    condition_eq41,
    r_sequence,
)
from quadobs.observability.gramian import (
    GramianModel,
    compose,
    eig_extremes,
    reduce_window,
    scaled_min_eig,
)

__all__ = [
    "GRAMIAN_RTOL",
    "MAX_FD_ORDER",
    "ConditionResult",
    "ExcitationMonitor",
    "ExcitationReport",
    "HeldInput",
    "HeldInputSignal",
    "Proposition4",
    "excitation_report",
    "proposition4",
]

#: A window Gramian counts as singular when the smallest eigenvalue of its unit-diagonal
#: form (:func:`quadobs.observability.gramian.scaled_min_eig`) is at most this: exact zeros (zero,
#: constant or straight-line input) land near 1e-16.
GRAMIAN_RTOL = 1e-12
#: Highest derivative order taken by finite differences of a sampled input.
MAX_FD_ORDER = 2


# --------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class HeldInputSignal:
    """An input *signal* held over consecutive steps: ``u(t) = values[k]`` on ``[t0 + k h, t0 + (k + 1) h)``.

    The data the excitation report reads (samples, and derivatives for Propositions 5-8), not
    a model: the system's exact step under such an input is
    :class:`~quadobs.core.held_input.HeldInputDiscretization` (augmented state) or
    :class:`~quadobs.estimators.kalman.HeldInputModel` (original state).

    Parameters
    ----------
    values : array_like (T, p)
    dt : float
        The hold step ``h`` (s).
    t0 : float
        Start time (s).
    analytic : callable, optional
        ``analytic(t, k)`` returns the ``k``-th derivative of the underlying smooth input at
        times ``t (T,)`` as ``(T, p)``; without it, derivatives are finite differences.
    source : str
        A few words on where the input comes from (printed by the report).
    """

    values: np.ndarray
    dt: float
    t0: float = 0.0
    analytic: Callable[[np.ndarray, int], np.ndarray] | None = None
    source: str = "samples"

    def __post_init__(self) -> None:
        v = as_array("u", self.values)
        if v.ndim == 1:
            v = v[:, None]
        if v.ndim != 2 or v.shape[0] < 1:
            raise QuadobsError(f"u: expected shape (T, p) with T >= 1, got {np.shape(self.values)}")
        v.setflags(write=False)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "dt", as_finite_scalar("dt", self.dt, positive=True))
        object.__setattr__(self, "t0", as_finite_scalar("t0", self.t0))

    @property
    def steps(self) -> int:
        return self.values.shape[0]

    @property
    def duration(self) -> float:
        return self.steps * self.dt

    @property
    def midpoints(self) -> np.ndarray:
        """``t0 + (k + 1/2) h``: where a held sample best represents a smooth input (it is its mean over the step)."""
        return self.t0 + (np.arange(self.steps) + 0.5) * self.dt

    def available_order(self) -> int | None:
        """Highest derivative order available (``None``: any, analytic)."""
        return None if self.analytic is not None else MAX_FD_ORDER

    def derivatives(self, count: int) -> np.ndarray:
        """``u, u', ..., u^(count-1)`` at the step midpoints: ``(count, T, p)``.

        Raises
        ------
        QuadobsError
            When a sampled input is asked for more than :data:`MAX_FD_ORDER` derivatives.
        """
        out = np.empty((count,) + self.values.shape)
        if self.analytic is not None:
            t = self.midpoints
            for k in range(count):
                out[k] = self.analytic(t, k)
            return out
        if count - 1 > MAX_FD_ORDER:
            raise QuadobsError(
                f"u: derivative of order {count - 1} needed; a sampled input gives finite differences up to order {MAX_FD_ORDER}"
            )
        out[0] = self.values
        for k in range(1, count):
            if self.steps < 3:
                raise QuadobsError("u: finite differences need at least 3 samples")
            out[k] = np.gradient(out[k - 1], self.dt, axis=0, edge_order=2)
        return out


#: The former name of :class:`HeldInputSignal`.
HeldInput = HeldInputSignal


# --------------------------------------------------------------------------------------
# Proposition 4
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Proposition4:
    """Proposition 4 of [IFAC2021], generalised to any immersion.

    Attributes
    ----------
    input_enters : bool
        Whether ``A(u)`` depends on ``u`` (some ``B^T L_i != 0``; for the chain, some
        ``B^T C_r != 0``).
    zero_input_rank : int
        Kalman observability rank of ``(A_0, C)``, the pair under ``u = 0``.
    dim : int
        ``N``.
    statement : str
        What follows, in words.
    """

    input_enters: bool
    zero_input_rank: int
    dim: int
    statement: str

    @property
    def zero_input_observable(self) -> bool:
        return self.zero_input_rank == self.dim

    @property
    def excitation_needed(self) -> bool:
        """The state cannot be observed without a (suitable) nonzero input."""
        return not self.zero_input_observable

    @property
    def never_observable(self) -> bool:
        """No input can help: ``A(u)`` does not depend on ``u`` and ``(A_0, C)`` is not observable."""
        return not self.input_enters and not self.zero_input_observable


def proposition4(immersion: Immersion) -> Proposition4:
    """Check Proposition 4 for ``immersion``: does the system need excitation, and can the input provide it?"""
    N = immersion.dim
    rank = observability_rank(immersion.state_matrix_constant, immersion.output_matrix)
    enters = bool(np.any(immersion.input_forms != 0.0))
    if not enters and rank < N:
        text = (
            f"B^T L_i = 0 for every auxiliary form: the input never enters A(u), so (A(u), C) = (A_0, C) for every input, "
            f"whose observability rank is {rank} < N = {N}: the augmented system is not observable whatever the input (Proposition 4)"
        )
    elif rank < N:
        text = (
            f"with u = 0, (A_0, C) has observability rank {rank} < N = {N}: windows where the input vanishes are not "
            "observable (Proposition 4); the input must excite the system"
        )
    else:
        text = f"with u = 0, (A_0, C) already has full observability rank N = {N}: the outputs observe the state without excitation"
    return Proposition4(enters, rank, N, text)


def explain_windows(immersion: Immersion, u: np.ndarray, first: np.ndarray, length: int) -> str:
    """Why the windows starting at samples ``first`` (of ``length`` samples of ``u (T, p)``) are singular.

    Counts the windows whose input is zero (Proposition 4: the pair is ``(A_0, C)``),
    constant (``A(u)`` constant: the Kalman rank of ``(A(u), C)`` decides) or varying.
    """
    N = immersion.dim
    zero = const = vary = 0
    rank_c = None
    for i in first:
        w = u[i : i + length]
        if not np.any(w):
            zero += 1
            continue
        mean = w.mean(axis=0)
        if np.abs(w - mean).max() <= 1e-9 * np.abs(mean).max():
            const += 1
            rank_c = observability_rank(immersion.state_matrix(mean), immersion.output_matrix)
        else:
            vary += 1
    parts = []
    if zero:
        rank0 = observability_rank(immersion.state_matrix_constant, immersion.output_matrix)
        parts.append(f"{zero} with zero input (Proposition 4: (A_0, C) has rank {rank0} < {N})")
    if const:
        parts.append(
            f"{const} with a constant input (A(u) constant, (A(u), C) has rank {rank_c} < {N})"
        )
    if vary:
        parts.append(f"{vary} with a varying input too poor over the window")
    return "singular windows: " + ", ".join(parts) if parts else ""


# --------------------------------------------------------------------------------------
# The report
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ConditionResult:
    """One test over the sliding windows.

    Attributes
    ----------
    key : str
        ``"gramian"``, ``"eq29"``, ``"eq31"``, ``"eq37"`` or ``"eq41"``.
    title : str
    status : str
        ``"holds"`` (every window), ``"fails"`` (some window), ``"not applicable"`` or
        ``"not evaluated"``.
    detail : str
        The reason for "not applicable"/"not evaluated", or what the numbers say.
    starts : ndarray (W,)
        Window start times (s).
    margin, relative : ndarray (W,)
        The margin of each window and its unit-free form (see :mod:`quadobs.observability.conditions`).
    holds : ndarray of bool (W,)
    """

    key: str
    title: str
    status: str
    detail: str = ""
    starts: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    margin: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    relative: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    holds: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool), repr=False)

    @property
    def evaluated(self) -> bool:
        return self.status in ("holds", "fails")

    @property
    def worst(self) -> int | None:
        """Index of the window with the smallest margin (the first failing one if any fails)."""
        if not self.margin.size:
            return None
        return int(np.argmin(self.margin))

    def failing_spans(self, window: float) -> list[tuple[float, float]]:
        """Maximal runs of failing windows as time spans ``[first start, last start + window]``."""
        spans = []
        bad = ~self.holds
        i = 0
        while i < bad.size:
            if bad[i]:
                j = i
                while j + 1 < bad.size and bad[j + 1]:
                    j += 1
                spans.append((float(self.starts[i]), float(self.starts[j] + window)))
                i = j + 1
            else:
                i += 1
        return spans

    def to_dict(self, window: float) -> dict:
        out: dict[str, Any] = {"title": self.title, "status": self.status, "detail": self.detail}
        if self.evaluated:
            w = self.worst
            out.update(
                {
                    "windows": int(self.margin.size),
                    "windows_holding": int(self.holds.sum()),
                    "min_margin": float(self.margin[w]),
                    "worst_window": [float(self.starts[w]), float(self.starts[w] + window)],
                    "relative_margin_at_worst": float(self.relative[w]),
                    "min_relative_margin": float(self.relative.min()),
                    "failing": [list(s) for s in self.failing_spans(window)],
                }
            )
        return out


def _series(
    key: str, title: str, starts: np.ndarray, cs: ConditionSeries, detail: str = ""
) -> ConditionResult:
    status = "holds" if bool(np.all(cs.holds)) else "fails"
    return ConditionResult(key, title, status, detail, starts, cs.margin, cs.relative, cs.holds)


@dataclass(frozen=True, eq=False)
class ExcitationReport:
    """The PE report of an input for a system (see :func:`excitation_report`).

    Attributes
    ----------
    name : str
    window, step, stride : float
        Window length ``delta``, hold step ``h`` and spacing of the window starts (s).
    immersion : Immersion
    prop4 : Proposition4
    gramian : ConditionResult
        Margin ``mu = lambda_min W(t, t + delta)``; relative: the unit-diagonal form's.
    conditions : list of ConditionResult
        eqs. 29, 31, 37, 41 (each possibly "not applicable"/"not evaluated").
    weakest : list of (str, float)
        The eigenvector of ``mu`` in the worst window, its largest components by name.
    explanation : str
        How many singular windows have a zero, constant or varying input (else "").
    threshold : float or None
        The live monitor's threshold on ``mu``, for the count of windows below it.
    source : str
    chain_m : int or None
        ``m`` of Assumption 1 when the chain conditions apply.
    """

    name: str
    window: float
    step: float
    stride: float
    immersion: Immersion
    prop4: Proposition4
    gramian: ConditionResult
    conditions: list
    weakest: list
    explanation: str
    threshold: float | None
    source: str
    chain_m: int | None

    @property
    def persistently_exciting(self) -> bool:
        """``W(t, t + delta)`` is nonsingular for every window of the record."""
        return self.gramian.status == "holds"

    @property
    def mu(self) -> float:
        """Smallest ``mu`` over the windows: the ``mu`` of Definition 2 for this ``delta`` and record."""
        return float(self.gramian.margin.min())

    def below_threshold(self) -> int:
        if self.threshold is None:
            return 0
        return int(np.sum(self.gramian.margin < self.threshold))

    def verdict(self) -> str:
        g = self.gramian
        if self.prop4.never_observable:
            return "NOT OBSERVABLE for any input (Proposition 4)"
        if self.persistently_exciting:
            good = [c.key for c in self.conditions if c.status == "holds"]
            extra = f"; sufficient condition(s) {', '.join(good)} hold too" if good else ""
            low = self.below_threshold()
            if low:
                extra += (
                    f"; but mu is below the monitor threshold {self.threshold:g} on {low} of {self.gramian.margin.size} "
                    "windows (weakly exciting there: the live monitor would flag them)"
                )
            return (
                f"PERSISTENTLY EXCITING over the record: W(t, t + {self.window:g}) >= mu I with mu = {self.mu:.3g} "
                f"for every window (Definition 2){extra}"
            )
        spans = g.failing_spans(self.window)
        total = sum(b - a for a, b in spans)
        return (
            f"NOT persistently exciting with delta = {self.window:g} s: W is singular on {int((~g.holds).sum())} of "
            f"{g.holds.size} windows, within {len(spans)} span(s) covering {total:.3g} s"
        )

    def to_dict(self) -> dict:
        """Plain data (JSON): settings, Proposition 4, the Gramian and each condition, the verdict."""
        g = self.gramian.to_dict(self.window)
        g["weakest_direction"] = [[n, float(c)] for n, c in self.weakest]
        if self.explanation:
            g["explanation"] = self.explanation
        if self.threshold is not None:
            g["threshold"] = self.threshold
            g["windows_below_threshold"] = self.below_threshold()
        return {
            "name": self.name,
            "source": self.source,
            "window": self.window,
            "step": self.step,
            "stride": self.stride,
            "immersion": self.immersion.summary(),
            "outputs": int(self.immersion.system.q),
            "chain_m": self.chain_m,
            "proposition4": {
                "input_enters": self.prop4.input_enters,
                "zero_input_rank": self.prop4.zero_input_rank,
                "dim": self.prop4.dim,
                "statement": self.prop4.statement,
            },
            "gramian": g,
            "conditions": {c.key: c.to_dict(self.window) for c in self.conditions},
            "persistently_exciting": self.persistently_exciting,
            "verdict": self.verdict(),
        }

    def format(self) -> str:
        """The report as text (what ``quadobs excitation`` prints)."""
        im = self.immersion
        lines = [
            f"excitation report: {self.name}",
            f"  input: {self.source}",
            f"  windows: delta = {self.window:g} s, starts every {self.stride:g} s over "
            f"[{self.gramian.starts[0]:g}, {self.gramian.starts[-1] + self.window:g}] s, hold step h = {self.step:g} s",
            f"  system: n = {im.system.n}, p = {im.system.p}, q = {im.system.q} output(s); {im.method} immersion, "
            f"{im.n_aux} auxiliary state(s), N = {im.dim}",
            f"  Proposition 4: {self.prop4.statement}",
            "",
            f"  {'test':34s} {'status':15s} {'min margin':>11s} {'rel.':>9s}  worst window",
        ]
        for c in [self.gramian, *self.conditions]:
            if c.evaluated:
                w = c.worst
                rel = c.relative[w]
                lines.append(
                    f"  {c.title:34s} {c.status:15s} {c.margin[w]:11.3e} {rel:9.2e}  "
                    f"[{c.starts[w]:.2f}, {c.starts[w] + self.window:.2f}] s"
                )
                if c.status == "fails":
                    spans = c.failing_spans(self.window)
                    shown = ", ".join(f"[{a:.2f}, {b:.2f}]" for a, b in spans[:4]) + (
                        " ..." if len(spans) > 4 else ""
                    )
                    lines.append(
                        f"  {'':34s} fails on {int((~c.holds).sum())}/{c.holds.size} windows, within {shown} s"
                    )
            else:
                lines.append(f"  {c.title:34s} {c.status:15s} {c.detail}")
            if c is self.gramian:
                comp = ", ".join(f"{v:+.2f} {n}" for n, v in self.weakest)
                lines.append(f"  {'':34s} weakest direction at worst window: {comp}")
                if self.explanation:
                    lines.append(f"  {'':34s} {self.explanation}")
                if self.threshold is not None:
                    lines.append(
                        f"  {'':34s} mu below the monitor threshold {self.threshold:g} on "
                        f"{self.below_threshold()}/{self.gramian.margin.size} windows"
                    )
        lines += [
            "",
            "  margins: mu = lambda_min W(t, t+delta) (Gramian, Definition 2); lambda_min of the window integral (eqs. 31, 37, 41);",
            "  the determinant integral (eq. 29). rel. = the same for the integral scaled to a unit diagonal (unit-free, in [0, 1];",
            "  eq. 29: over its Hadamard bound); a window holds when rel. > 1e-12 (Gramian) or 1e-10 (eqs. 29-41).",
            "  eqs. 29-41 are sufficient conditions: a failing one is inconclusive; the Gramian is necessary and sufficient.",
            "",
            f"  verdict: {self.verdict()}",
        ]
        return "\n".join(lines)


def _weakest(
    vec: np.ndarray, immersion: Immersion, names: list[str] | None
) -> list[tuple[str, float]]:
    n = immersion.system.n
    xn = names if names is not None and len(names) == n else [f"x_{i}" for i in range(n)]
    labels = [f"xi_{i}" for i in range(immersion.n_aux)] + list(xn)
    order = np.argsort(-np.abs(vec))
    big = np.abs(vec[order[0]])
    return [(labels[i], float(vec[i])) for i in order[:4] if abs(vec[i]) >= 0.1 * big]


def _window_grid(u: HeldInputSignal, immersion: Immersion, window: float, stride: float | None):
    """Window length ``L`` and stride ``s`` (steps), window starts (s) and the input with rounding-level samples zeroed."""
    h = u.dt
    window = as_finite_scalar("window", window, positive=True)
    L = int(round(window / h))
    if L < 2 or abs(L * h - window) > 1e-9 * window:
        raise QuadobsError(
            f"window: {window} s must be a multiple of the hold step {h:g} s (at least two steps)"
        )
    if L > u.steps:
        raise QuadobsError(f"window: {window} s is longer than the input ({u.duration:g} s)")
    s = (
        max(1, int(round(0.05 / h)))
        if stride is None
        else int(round(as_finite_scalar("stride", stride, positive=True) / h))
    )
    if s < 1 or (stride is not None and abs(s * h - stride) > 1e-9 * stride):
        raise QuadobsError(
            f"stride: {stride} s must be a positive multiple of the hold step {h:g} s"
        )
    if u.values.shape[1] != immersion.system.p:
        raise QuadobsError(
            f"u: {u.values.shape[1]} input(s), the system has p = {immersion.system.p}"
        )
    starts = u.t0 + h * np.arange(0, u.steps - L + 1, s)
    # Samples at rounding level of the record's largest are zero (a sampled input that
    # should vanish carries ~1e-16 relative residue, which would make W nonsingular).
    values = np.array(u.values)
    values[np.abs(values).max(axis=1) <= 1e-12 * np.abs(values).max(initial=0.0)] = 0.0

    return L, s, starts, values


def _chain_conditions(system, u: HeldInputSignal, starts, L: int, s: int, kappa, rtol: float):
    """The sufficient conditions of Propositions 5-8 [IFAC2021] over every window, and the chain they use (or ``None``)."""
    h = u.dt
    conditions = []
    titles = {
        "eq29": "eq. 29 (Prop. 5) int det",
        "eq31": "eq. 31 (Prop. 6) Gramian of (A, r_m)",
        "eq37": "eq. 37 (Prop. 7) int r_m'r_m",
        "eq41": "eq. 41 (Prop. 8) int U_bar U_bar'",
    }
    chain: ChainStructure | None = None
    try:
        chain = chain_structure(system, kappa)
    except QuadobsError as exc:
        reason = str(exc).removeprefix("system: ")
        conditions = [ConditionResult(k, t, "not applicable", reason) for k, t in titles.items()]
    if chain is not None:
        m = chain.m
        avail = u.available_order()
        if avail is not None and m - 1 > avail:
            need = (
                f"needs u^({m - 1}); finite differences of the sampled input go up to order {avail}"
            )
            for k in ("eq31", "eq37", "eq41"):
                conditions.append(ConditionResult(k, titles[k], "not evaluated", need))
        else:
            D = u.derivatives(m)
            r_m = r_sequence(chain, D, m)[m]
            conditions.append(
                _series(
                    "eq31", titles["eq31"], starts, condition_eq31(system.A, r_m, h, L, s, rtol)
                )
            )
            if chain.real_eigenvalues():
                conditions.append(
                    _series("eq37", titles["eq37"], starts, condition_eq37(r_m, h, L, s, rtol))
                )
            else:
                conditions.append(
                    ConditionResult(
                        "eq37", titles["eq37"], "not applicable", "A has complex eigenvalues"
                    )
                )
            why = []
            if not chain.real_eigenvalues():
                why.append("A has complex eigenvalues")
            if not chain.gamma_observable():
                why.append("(A, Gamma) is not Kalman observable")
            if not chain.affine_free():
                why.append("d^T A^m != 0, so r_m is not Gamma^T U_bar")
            if why:
                conditions.append(
                    ConditionResult("eq41", titles["eq41"], "not applicable", "; ".join(why))
                )
            else:
                ubar = np.concatenate(list(D), axis=1)  # (T, p m): u, u', ..., u^(m-1)
                conditions.append(
                    _series("eq41", titles["eq41"], starts, condition_eq41(ubar, h, L, s, rtol))
                )
        kap = chain.kappa
        if avail is not None and kap - 1 > avail:
            conditions.insert(
                0,
                ConditionResult(
                    "eq29",
                    titles["eq29"],
                    "not evaluated",
                    f"needs u^({kap - 1}) (kappa = {kap}); finite differences of the sampled input go up to order {avail}",
                ),
            )
        else:
            r_all = r_sequence(chain, u.derivatives(kap), kap)
            res = _series(
                "eq29",
                titles["eq29"] + f", kappa = {kap}",
                starts,
                condition_eq29(r_all, m, h, L, s, rtol),
            )
            conditions.insert(0, res)
    return conditions, chain


def excitation_report(
    immersion: Immersion,
    u: HeldInputSignal,
    window: float,
    *,
    stride: float | None = None,
    kappa: int | None = None,
    threshold: float | None = None,
    names: list[str] | None = None,
    name: str = "input",
    rtol: float = DEFAULT_ZERO_RTOL,
) -> ExcitationReport:
    """Evaluate the Gramian measure, Proposition 4 and the conditions of eqs. 29-41 over sliding windows.

    Parameters
    ----------
    immersion : Immersion
        The Gramian is taken in this immersion's coordinates (the observer's).
    u : HeldInputSignal
    window : float
        ``delta`` (s): a multiple of ``u.dt``, at most the input's duration.
    stride : float, optional
        Spacing of the window starts (s), a multiple of ``u.dt``; default the multiple
        nearest 0.05 s.
    kappa : int, optional
        Last index of eq. 29 (default ``m + n - 1``).
    threshold : float, optional
        The monitor's threshold on ``mu``, to count the windows below it.
    names : list of str, optional
        Names of the original state's entries (for the weakest direction).
    rtol : float
        Relative zero test of the sufficient conditions (:mod:`quadobs.observability.conditions`).
    """
    if not isinstance(u, HeldInputSignal):
        raise QuadobsError(f"u: expected a HeldInputSignal, got {type(u).__name__}")
    h = u.dt
    L, s, starts, values = _window_grid(u, immersion, window, stride)

    # The Gramian (eq. 27) over every window.
    gm = GramianModel(immersion, h)
    W = gm.sliding(values, L, s)
    lo, _, vecs = eig_extremes(W)
    rel = scaled_min_eig(W)
    g_ok = rel > GRAMIAN_RTOL
    gram = ConditionResult(
        "gramian",
        "Gramian mu = lambda_min W(t,t+delta)",
        "holds" if g_ok.all() else "fails",
        "",
        starts,
        lo,
        rel,
        g_ok,
    )
    worst = gram.worst
    weakest = _weakest(vecs[worst], immersion, names)
    explanation = explain_windows(immersion, values, np.flatnonzero(~g_ok) * s, L)
    p4 = proposition4(immersion)

    conditions, chain = _chain_conditions(immersion.system, u, starts, L, s, kappa, rtol)
    return ExcitationReport(
        name=name,
        window=L * h,
        step=h,
        stride=s * h,
        immersion=immersion,
        prop4=p4,
        gramian=gram,
        conditions=conditions,
        weakest=weakest,
        explanation=explanation,
        threshold=threshold,
        source=u.source,
        chain_m=None if chain is None else chain.m,
    )


# --------------------------------------------------------------------------------------
# The live monitor
# --------------------------------------------------------------------------------------


class ExcitationMonitor:
    """Sliding-window Gramian measure of the input applied so far, updated every few steps.

    Feed :meth:`push` the input of every physics step, or :meth:`push_many` several at
    once (up to :attr:`room`, the steps left in the current chunk). The input is averaged over hold
    steps of ``block`` physics steps (a hold step's mean acceleration, as in
    :func:`scenario_input`); each hold step contributes its transition and Gramian
    ``(Phi(u), G(u))`` (:class:`~quadobs.observability.gramian.GramianModel`), and the window's
    ``W(t - delta, t)`` is their ordered composition (:func:`quadobs.observability.gramian.compose`).
    The inputs are buffered and processed by chunks of ``c = gcd(window_blocks,
    update_blocks)`` hold steps (one update period with the defaults): a chunk's terms are
    composed in time order in one compiled call (:mod:`quadobs._kernels.gramian`; without
    Numba, reduced as a tree by :func:`~quadobs.observability.gramian.reduce_window`), and the chunks enter a two-stack sliding-window
    aggregation (new chunks are composed onto a back aggregate; old ones leave from a front
    stack of suffix aggregates rebuilt from the back once per window). That is about three
    ``N x N`` compositions per chunk, amortised, and no subtraction, so ``W`` is as exact
    as :func:`~quadobs.observability.gramian.reduce_window`'s. Every ``update_blocks`` hold steps, once
    a window is full, ``mu = lambda_min W`` is computed and compared with ``threshold``.

    Low segments: a segment ``[a, b)`` means the windows ending at the update times
    ``a, ..., b - update period`` had ``mu < threshold`` and the one ending at ``b`` did
    not (``b`` is the end of the run if the measure never recovered). A window ending at
    ``t`` covers the input applied over ``[t - delta, t)``.

    Parameters
    ----------
    immersion : Immersion
    dt : float
        Physics step (s).
    block, window_blocks, update_blocks : int
        From :meth:`quadobs.testbed.scenario.ExcitationSpec.grid`.
    threshold : float
    """

    def __init__(
        self,
        immersion: Immersion,
        dt: float,
        *,
        block: int,
        window_blocks: int,
        update_blocks: int,
        threshold: float,
    ) -> None:
        self.dt = as_finite_scalar("dt", dt, positive=True)
        self.block, self.L, self.update_blocks = int(block), int(window_blocks), int(update_blocks)
        if self.block < 1 or self.L < 2 or self.update_blocks < 1:
            raise QuadobsError(
                "excitation: block >= 1, window_blocks >= 2 and update_blocks >= 1 are required"
            )
        self.threshold = as_finite_scalar("threshold", threshold, nonnegative=True)
        self.immersion = immersion
        self.model = GramianModel(immersion, self.block * self.dt)
        p = immersion.system.p
        self._chunk = math.gcd(self.L, self.update_blocks)  # hold steps per chunk
        self._buf = np.zeros((self._chunk * self.block, p))
        self._n_buf = 0
        self._blocks = 0
        try:  # a chunk's terms in one compiled call; NumPy (the same quantities) without Numba
            from quadobs._kernels.gramian import held_run_terms
        except ImportError:  # pragma: no cover
            held_run_terms = None  # type: ignore[assignment]  # Numba missing: the NumPy path
        self._kernel = held_run_terms
        N = immersion.dim
        self._work = np.empty((3, N, N))
        self._front: list[tuple[np.ndarray, np.ndarray]] = []  # suffix aggregates, oldest last
        self._back: list[tuple[np.ndarray, np.ndarray]] = []  # chunks in time order
        self._back_agg: tuple[np.ndarray, np.ndarray] | None = None
        self.steps = 0
        #: Latest measure (NaN until the first window is full), the time its window ends, its weakest direction.
        self.measure = float("nan")
        self.measure_time = float("nan")
        self.lambda_max = float("nan")
        self.direction = np.full(immersion.dim, np.nan)
        #: Orthonormal basis (N, k) of the eigenvectors of W whose eigenvalue is below the threshold.
        self.unexcited = np.zeros((immersion.dim, 0))
        self.updates = 0
        self.min_measure = float("inf")
        self.min_time: float | None = None
        self.low_segments: list[list[float]] = []
        self._low_since: float | None = None
        self._warned = False
        self.warning: str | None = None
        if (
            self._kernel is not None
        ):  # load (or compile) it now rather than inside a run's first chunk
            self._chunk_terms(np.zeros((1, p)))

    def _chunk_terms(self, means: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Transition and Gramian over the hold steps ``means (c, p)``, composed in time order."""
        m = self.model
        if self._kernel is None:
            return reduce_window(*m.step_terms(means))
        Phi, G, T = self._work
        P, W = np.empty_like(Phi), np.empty_like(Phi)
        d = m.discretization
        self._kernel(
            means,
            d.transition_constant,
            d.transition_input,
            m.gramian_constant,
            m.gramian_linear,
            m.gramian_quadratic,
            P,
            W,
            Phi,
            G,
            T,
        )
        return P, W

    @property
    def window(self) -> float:
        return self.L * self.block * self.dt

    @property
    def update_period(self) -> float:
        return self.update_blocks * self.block * self.dt

    @property
    def low(self) -> bool:
        return self._low_since is not None

    @property
    def room(self) -> int:
        """Physics steps until the next chunk is complete (the next step at which the measure may change)."""
        return self._buf.shape[0] - self._n_buf

    def push(self, u: np.ndarray) -> bool:
        """Take the input held over the next physics step; returns whether the measure was recomputed.

        ``u (p,)`` must be finite; a refused ``u`` raises :class:`QuadobsError` and changes nothing.
        """
        row = self._buf[self._n_buf]
        if not (isinstance(u, np.ndarray) and u.shape == row.shape):
            u = as_array("u", u, row.shape)  # raises, naming the problem
        row[:] = u
        if not math.isfinite(row.dot(row)):  # the row only counts once _n_buf moves past it
            as_array("u", u, row.shape)
        self._n_buf += 1
        self.steps += 1
        if self._n_buf < self._buf.shape[0]:
            return False
        return self._chunk_done()

    def push_many(self, U: np.ndarray) -> bool:
        """Take the inputs of the next ``len(U)`` physics steps at once (``U (k, p)``, ``k <= room``).

        The same as ``k`` calls of :meth:`push` (returns what the last one would): a caller
        that feeds exactly :attr:`room` steps at a time sees every recomputation at the step
        where it happens, for one call per chunk instead of one per step.
        """
        U = as_array("U", U, (None, self._buf.shape[1]))
        k = U.shape[0]
        if k > self.room:
            raise QuadobsError(
                f"push_many: {k} steps given, but the chunk has room for {self.room}"
            )
        self._buf[self._n_buf : self._n_buf + k] = U
        self._n_buf += k
        self.steps += k
        if self._n_buf < self._buf.shape[0]:
            return False
        return self._chunk_done()

    def _chunk_done(self) -> bool:
        self._n_buf = 0
        means = self._buf.reshape(self._chunk, self.block, -1).mean(axis=1)
        self._add(self._chunk_terms(means))
        self._blocks += self._chunk
        if self._blocks < self.L or self._blocks % self.update_blocks:
            return False
        self._update()
        return True

    def _add(self, term: tuple[np.ndarray, np.ndarray]) -> None:
        if self._blocks >= self.L:  # drop the oldest chunk
            if not self._front:
                agg = None
                for t in reversed(self._back):
                    agg = t if agg is None else compose(t, agg)
                    self._front.append(agg)
                self._back, self._back_agg = [], None
            self._front.pop()
        self._back.append(term)
        self._back_agg = term if self._back_agg is None else compose(self._back_agg, term)

    def window_gramian(self) -> np.ndarray:
        """``W`` over the hold steps in the window (the last ``window_blocks`` of them, or fewer at the start)."""
        N = self.immersion.dim
        if self._front and self._back_agg is not None:
            return compose(self._front[-1], self._back_agg)[1]
        if self._front:
            return self._front[-1][1]
        return self._back_agg[1] if self._back_agg is not None else np.zeros((N, N))

    def _update(self) -> None:
        W = self.window_gramian()
        lam, vecs = np.linalg.eigh(0.5 * (W + W.T))
        lo, hi = lam[0], lam[-1]
        t = self.steps * self.dt
        self.measure, self.lambda_max, self.direction = float(lo), float(hi), vecs[:, 0]
        self.unexcited = vecs[:, lam < self.threshold]
        self.measure_time = t
        self.updates += 1
        if lo < self.min_measure:
            self.min_measure, self.min_time = float(lo), t
        if lo < self.threshold:
            if self._low_since is None:
                self._low_since = t
                if not self._warned:
                    self._warned = True
                    self.warning = (
                        f"excitation low at t = {t:.3f} s: mu = lambda_min W(t - {self.window:g}, t) = {lo:.3g} is below "
                        f"the threshold {self.threshold:g}; the input does not excite every direction, so the estimate "
                        "may drift there (reported once per episode; see summary 'excitation.low_segments')"
                    )
        elif self._low_since is not None:
            self.low_segments.append([self._low_since, t])
            self._low_since = None

    def pop_warning(self) -> str | None:
        """The first-crossing warning, once (then ``None``)."""
        w, self.warning = self.warning, None
        return w

    def summary(self) -> dict:
        """``window``, ``threshold``, ``update_period``, ``step``, ``updates``, ``min_measure`` and its time,
        ``low_segments`` (open segments closed at the current time) and ``low_time``."""
        segs = [list(s) for s in self.low_segments]
        if self._low_since is not None:
            segs.append([self._low_since, self.steps * self.dt])
        return {
            "window": self.window,
            "threshold": self.threshold,
            "update_period": self.update_period,
            "step": self.block * self.dt,
            "updates": self.updates,
            "min_measure": None if not np.isfinite(self.min_measure) else self.min_measure,
            "min_measure_time": self.min_time,
            "low_segments": segs,
            "low_time": float(sum(b - a for a, b in segs)),
        }
