"""A Gaussian filter started from a multilateration of its first round of ranges.

Linearising a range ``|p - a_h|`` at an estimate ``e`` metres off errs by up to
``e^2 / (2 |p - a_h|)``: from a prior as wide as the anchors' geometry the first corrections
of an EKF point the wrong way, and the estimate can wander far from both the guess and the
truth before it settles (from 50 m off on a car park, 150 m). The start-up here replaces what
came of that prior by what one round of ranges says on its own, the rule that the bias filters
(:mod:`quadobs.estimators.bias_states`) and the heading filters
(:mod:`quadobs.estimators.heading_ekf`) follow (the joint fix of position and velocity below
is this module's alone):

* **When.** The prior position's largest standard deviation exceeds the scale on which a
  range bends over it, half the anchors' extent ``e = max_h |a_h - c|`` (``c`` their
  centroid), and at least the range noise ``sigma``.
* **Waiting.** The filter predicts and corrects as usual, the EKF with each range's variance grown by the
  second-order term of its linearisation as noise (the UKF's sigma points already spread over
  it: :class:`FixedStartUKF`), ``sigma^2 + tr((H_2 P)^2) / 2`` with
  ``H_2 = (I - u u^T) / rho`` the Hessian of ``|p - a_h|`` at the estimate (the variance term
  of the Gaussian second-order filter; in the plane, 35 m of standard deviation for a 50 m prior at 50 m
  from the anchor, nothing once the position is known): a correction linearised far from the
  truth is weighed by what its linearisation may miss (ranges in time, :meth:`correct`; a
  grid step's outputs, :meth:`correct_outputs`, are corrected as they are). It keeps its ranges (the latest per
  anchor, with the position the prediction alone gives at its time: the estimate less the
  corrections' effect carried through the dynamics) until every anchor has one or, an anchor
  silent, two rounds' worth (``2 q``) have come. After ``4 q`` ranges without a fix (anchors
  in too few directions) the filter goes on as it is, without the second-order term.
* **Fix.** The ranges of a moving vehicle are of different times: range ``h`` taken at
  ``t_h`` is a range from ``p(t) - Delta_h`` with ``Delta_h = p^-(t) - p^-(t_h)`` the motion
  the prediction alone gives since (exact for odometry, whose displacement does not depend on
  the unknown start). So it is a range from ``p(t)`` to the anchor moved to ``a_h + Delta_h``,
  and the quadratic outputs ``y_h = (rho_h^2 - |a_h'|^2) / 2 = c - a_h'^T p`` (``c =
  |p|^2 / 2`` common to all) are linear in ``p`` and ``c``
  (:func:`~quadobs.estimators.robust.multilateration` with ``variances``): the weighted least
  squares with the weights ``w_h = 1 / v_h`` (``v_h = var y_h = rho_h^2 sigma_h^2 +
  sigma_h^4 / 2``) and ``c`` as an unknown, the best linear unbiased fix, the same whatever
  the anchors' order, has the covariance

  .. math:: P_{fix} = (D_w^\\top W D_w)^{-1} + (P^-_{pp}(t) - P^-_{pp}(t_0)),

  ``D_w`` the rows ``-(a_h' - abar_w')`` about the weighted mean, ``W = diag(w)``
  (:func:`~quadobs.estimators.robust.multilateration_covariance`; from the first anchor's
  output, as before, the fix depended on the anchors' order), the last term the uncertainty the prediction
  alone added to the position since the oldest range used (``P^-`` carried from the prior of
  the other states, a velocity, with the process noise): the variance of the displacement
  for the process noise's independent increments, larger than it for a velocity's prior error
  ``e_v`` (``P_vv (t^2 - t_0^2)`` against ``P_vv (t - t_0)^2``), so conservative. The position takes the fix and
  ``P_fix``, its correlations with the other states dropped, in place of what the corrections
  made of it from the wide prior.
* **Joint fix.** Where the state holds more than the position (a velocity), the fix above
  leaves those states at their prior, and the motion of the round's ranges at the prior's
  velocity. From a velocity prior of ``s_v`` per axis, ``P_fix`` holds ``s_v^2 (t - t_0)^2``
  of it (the last term above) and the position's spread grows by ``s_v`` per second after the
  fix. Where ``P_fix``'s largest standard deviation still exceeds the threshold of **When**
  (half the anchors' extent), the fix has not done its work: the UKF's sigma points still
  spread over the anchors, where a range is flat over them, and from the observer's 10 m/s
  the ``rover-room`` UKF (a round of 0.2 s, ``P_fix`` 1.9 m per axis against a threshold of
  0.9 m) never took its velocity in (its position spread 733 m after 90 s against a 14 m
  prior). There the round's ranges, which are of different times, fix the position and the
  other states together: with ``x^-`` the prediction alone and the unknown
  ``theta = x(t) - x^-(t)``, range ``h`` taken at ``t_h`` is
  ``rho_h = |p^-(t_h) + [Phi(t_h, t) theta]_p - a_h| + n_h`` (``Phi(t_h, t) = exp(-A (t - t_h))``,
  the dynamics back from ``t``), and ``theta`` is the Gauss-Newton minimiser (from the
  multilateration's position) of

  .. math:: \\sum_h (\\rho_h - |p_h(\\theta) - a_h|)^2 / \\sigma_h^2 + \\theta_o^T P_{oo}^{-1} \\theta_o,

  the second term the prior of the other states ``o`` (``P_oo`` the prediction's, the
  position's prior left out: it is what the fix replaces). Where the minimum ``chi^2``
  exceeds its degrees of freedom ``dof`` (the ranges less the position's ``dim``: ranges that
  disagree with one another, biased, of another time than assumed or off the line of sight)
  the ranges' variances are taken ``s = chi^2 / dof`` times their stated ones and the minimiser
  found again with them (the prior's weight kept: the ranges' disagreement says nothing of
  it). The covariance is the inverse of the normal matrix
  ``H = J^T R^-1 J / s + diag(0, P_oo^-1)`` (``s = 1`` where ``chi^2 <= dof``), plus the
  process noise added since the start-up was armed (conservative: the ranges relate the
  states of their times to the state now through the noise between them alone). The steps
  are halved until the objective falls: ranges that disagree can make plain Gauss-Newton
  steps swing between two points. The state and its covariance take
  ``x^- + theta`` and that covariance in place of what the waiting corrections made of them.
  In the ``rover-room`` (seed 3) the velocity's standard deviation falls from 10 to 0.7 and
  0.8 m/s per axis at the fix, 0.2 s in (the position's 7 and 9 cm). Where the normal matrix is singular or the steps do not settle, the
  position alone is fixed as above, as is a state of the position alone (odometry), and a
  fix whose ``P_fix`` is within the threshold (``quadrotor-uwb-realistic``'s rounds of
  0.08 s, the replay's 2 m/s). The joint fix asks more of one round: its velocity is the
  ranges' rates over the round, which one range off the line of sight by a metre moves by
  metres per second (on ``quadrotor-uwb-realistic``'s rounds, where it is not needed, it made
  seed 5's UKF lock out and end uninformed).
* **No second correction.** The ranges the fix is made of (the latest of each anchor: the range
  that completed the round, or all the outputs of the grid step that did) are not corrected
  by again. ``P_fix`` is the covariance of an error made of their noise; a correction by one of
  them would take that noise as independent of the estimate's error and count it twice. In
  the linear case ``z = H p + n`` fixed by least squares, ``p_fix = (H^T R^-1 H)^-1 H^T R^-1 z``
  with ``P_fix = (H^T R^-1 H)^-1``, a correction by ``z`` leaves the mean where it is (the
  residual ``z - H p_fix`` is ``R^-1``-orthogonal to ``H``) and halves the covariance,
  ``(2 H^T R^-1 H)^-1 = P_fix / 2``, while the error's is still ``P_fix``. Growing ``P_fix`` so
  that the correction would shrink it back is no remedy: the fix takes the ``q - 1``
  differences of the outputs, not the ranges themselves, so no factor makes the second
  correction exact, while leaving it out is: the position and ``P_fix`` are what those
  ranges say. The step's :attr:`nis` is then NaN (no correction).
* **No fix.** A filter still waiting at the end of its run, or one that gave up without a
  fix, never took the position its ranges give; it ran from its prior, correcting every range
  with the grown variance above. :func:`not_started` records it, and the testbed's summaries
  give it a ``startup`` entry beside its figures
  (:func:`quadobs.testbed.divergence.startup_record`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from quadobs.core.measurements import Measurement
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.robust import multilateration, multilateration_covariance

#: The most Gauss-Newton steps of the joint fix (from the multilateration: a few where the
#: ranges agree; ranges that disagree (non-line-of-sight) slow its convergence to linear).
JOINT_STEPS = 50
#: The joint fix has settled when its step is below this many of its standard deviations
#: (``step^T H step``, ``H`` the normal matrix).
JOINT_TOLERANCE = 1e-4

__all__ = [
    "FixedStartEKF",
    "FixedStartUKF",
    "MultilaterationStart",
    "not_started",
    "start_threshold",
]


def start_threshold(anchors: np.ndarray, sigma: float) -> float:
    """The prior position's standard deviation (m) beyond which the filter starts from a fix:
    half the anchors' extent ``max_h |a_h - c| / 2``, at least ``sigma``."""
    a = np.asarray(anchors, dtype=float)
    extent = float(np.max(np.linalg.norm(a - a.mean(axis=0), axis=1)))
    return max(0.5 * extent, float(sigma))


def not_started(est) -> dict | None:
    """The record of a filter whose start-up from a multilateration never set its position
    (this module's, the bias filters' of :mod:`quadobs.estimators.bias_states`, the heading
    filters' of :mod:`quadobs.estimators.heading_ekf`), as a lock-out's ``diverged``
    (:class:`~quadobs.estimators.robust.LockOut`): ``{"time", "step", "reason"}``, else None.

    Armed and still waiting at the end of the run (its anchors never heard in enough
    directions, or no range at all: ``fix_pending``), or given up without a fix
    (``fix_abandoned``, the time at which it was: anchors in too few directions over four
    rounds, or a fix the filter refused), its estimate is what its prior and corrections from
    a prior as wide as the anchors' geometry made of it: it ran, as the filter without the
    start-up would have (one anchor alone can still bring it in, as the IFAC 2021 setting's
    EKF shows), and the summary says that it never took its position from a fix
    (:func:`quadobs.testbed.divergence.startup_record`). ``step`` counts the filter's own steps (``time / dt``). A
    wrapper (:class:`~quadobs.estimators.base.Wrapper`, one taking a log's measurements in
    time) is read through its ``inner``; a model average
    (:class:`~quadobs.estimators.model_average.ModelAverage`) gives the earliest of its
    members' records, the reason naming the member.
    """
    from quadobs.estimators.model_average import ModelAverage

    while est is not None and not hasattr(est, "fixes"):
        if isinstance(est, ModelAverage):
            return min(
                (
                    {**r, "reason": f"member {m.name}: {r['reason']}"}
                    for m in est.members
                    if (r := not_started(m))
                ),
                key=lambda r: r["time"],
                default=None,
            )
        est = getattr(est, "inner", None)
    if est is None or est.fixes:
        return None
    if getattr(est, "fix_pending", False):
        t = float(est.time)
        why = "no multilateration fix from its ranges by the end of the run"
    else:
        abandoned = getattr(est, "fix_abandoned", None)
        if abandoned is None:
            return None
        t = float(abandoned)
        why = "its multilateration fix given up (anchors in too few directions)"
    dynamics = getattr(est, "dynamics", est)  # a Kalman filter's step, else the filter's own
    dt = float(getattr(dynamics, "dt", 0.0))
    step = int(round(t / dt)) if dt > 0.0 else 0
    return {"time": t, "step": step, "reason": why}


class MultilaterationStart:
    """Mixed into a filter of :mod:`quadobs.estimators.kalman`: the start-up of the module
    docstring. :meth:`start_from_fix` arms it (a filter never armed behaves as its class).

    Attributes
    ----------
    fix_pending : bool
        Waiting for a round of ranges.
    fixes : list of float
        Times (s) at which the position was set by multilateration.
    fix_abandoned : float or None
        Time (s) at which the start-up was given up without a fix (:func:`not_started`).
    """

    fix_pending: bool = False
    fix_abandoned: float | None = None
    fixes: list
    _dim: int
    _waited: int
    _at: np.ndarray
    _P_at: np.ndarray
    _t_at: np.ndarray
    _var_y: np.ndarray
    _offset: np.ndarray
    _offsets: np.ndarray
    _P_dr: np.ndarray
    # the filter's own; declared for the type checker only
    _x: np.ndarray
    _P: np.ndarray
    _F: np.ndarray
    _latest: np.ndarray
    _intervals: dict
    _time: float
    q: int
    if TYPE_CHECKING:
        outputs: OutputModel
        dynamics: HeldInputModel

        def _settle(self) -> None: ...
        def _model_of(self, m: Measurement): ...

    def start_from_fix(self, dim: int, threshold: float) -> None:
        """Arm the start-up when the prior position (``x[:dim]``) has a standard deviation
        above ``threshold`` (:func:`start_threshold`) on some axis and the outputs are ranges
        with their offsets (``y_h = rho_h^2 / 2 - |a_h|^2 / 2``, as the replay's EKF has them)."""
        self._dim = d = int(dim)
        self._threshold = float(threshold)
        self.fixes = []
        self._waited = 0
        self._at = np.full((self.q, d), np.nan)
        self._P_at = np.zeros((self.q, d, d))
        self._t_at = np.full(self.q, np.inf)
        self._var_y = np.full(self.q, np.nan)
        # x - offset: the prediction alone from the start; P_dr: its error's covariance from
        # the prior of the states other than the position (a velocity) and the process noise
        self._offset = np.zeros_like(self._x)
        self._P_dr = self._P.copy()
        self._P_dr[:d, :] = 0.0
        self._P_dr[:, :d] = 0.0
        self._P_q = np.zeros_like(self._P)  # the process noise's part of P_dr
        self._kept: list[tuple] = []  # every range kept: (h, rho, s2, t, x^-(t))
        offsets = self.outputs.offsets
        self._offsets = np.zeros(self.q) if offsets is None else offsets
        prior_std = math.sqrt(float(np.max(np.diag(self._P)[:d])))
        self.fix_pending = offsets is not None and prior_std > threshold

    # -- the prediction alone, beside the filter's own while a fix is pending --------------

    def predict_step(self, u: np.ndarray) -> None:
        super().predict_step(u)  # type: ignore[misc]
        if self.fix_pending:
            self._carry(self._F, self.dynamics.Q)

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        step = self.dynamics.dt
        super()._propagate(dt, u)  # type: ignore[misc]
        if self.fix_pending and abs(dt - step) > 1e-9 * step:  # the step: predict_step did it
            hit = self._intervals.get(dt)
            F, _, Q = hit if hit is not None else self.dynamics.over(dt)
            self._carry(F, Q)

    def _carry(self, F: np.ndarray, Q: np.ndarray) -> None:
        """Carry the corrections' offset and the prediction's covariance over an interval."""
        self._offset = F @ self._offset
        P = F @ self._P_dr @ F.T + Q
        self._P_dr = 0.5 * (P + P.T)
        P = F @ self._P_q @ F.T + Q
        self._P_q = 0.5 * (P + P.T)

    # -- keeping the ranges, and the fix ---------------------------------------------------

    def _keep(self, h: int, y: float, s2: float | None) -> None:
        """Keep output ``h`` (``y = rho^2 / 2 - |a_h|^2 / 2``, a range ``rho`` of variance ``s2``,
        by default the filter's own ``R_hh``) for the fix, with the predicted position and its
        covariance now; the output's variance is ``rho^2 s2 + s2^2 / 2``."""
        d = self._dim
        if s2 is None:
            s2 = float(self.outputs.R[h, h])
        rho2 = 2.0 * (y + float(self._offsets[h]))
        self._latest[h] = y
        self._var_y[h] = rho2 * s2 + 0.5 * s2 * s2
        self._at[h] = (self._x - self._offset)[:d]
        self._P_at[h] = self._P_dr[:d, :d]
        self._t_at[h] = self._time
        self._waited += 1
        self._kept.append((h, math.sqrt(rho2), s2, self._time, self._x - self._offset))

    def _correct_measurement(self, m: Measurement) -> None:
        if not (self.fix_pending and m.kind == "range"):
            super()._correct_measurement(m)  # type: ignore[misc]
            return
        h, yh, _ = self._model_of(m).quadratic_output(m)
        s2 = m.std**2 if math.isfinite(m.std) else float(self.outputs.R[h, h])
        self._keep(h, yh, s2)
        if self._try_fix():  # the fix is made of this range: it is not corrected by again
            self.nis, self.nis_dof = float("nan"), 0
            return
        before = self._x.copy()
        extra = self._waiting_variance(h) if self.fix_pending else 0.0
        if extra > 0.0:  # the linearisation's second-order term as noise (module docstring)
            m = replace(m, std=math.sqrt(s2 + extra))
        super()._correct_measurement(m)  # type: ignore[misc]
        if self.fix_pending:
            self._offset += self._x - before

    def correct_outputs(self, y: np.ndarray) -> None:
        if not self.fix_pending:
            super().correct_outputs(y)  # type: ignore[misc]
            return
        y = np.asarray(y, dtype=float)
        for h in np.flatnonzero(~np.isnan(y)):
            self._keep(int(h), float(y[h]), None)
        if self._try_fix():  # the fix is made of every output of the step (the latest of each)
            self.nis, self.nis_dof = float("nan"), 0
            return
        before = self._x.copy()
        super().correct_outputs(y)  # type: ignore[misc]
        if self.fix_pending:
            self._offset += self._x - before

    def _waiting_variance(self, h: int) -> float:
        """The variance a waiting correction of range ``h`` adds to the range's own: the
        second-order term (:meth:`_curvature_variance`) that a correction linearised at the
        estimate leaves out."""
        return self._curvature_variance(h)

    def _curvature_variance(self, h: int) -> float:
        """The variance of the second-order term of ``|p - a_h|`` about the estimate for
        ``p ~ N(x, P)``: ``tr((H_2 P)^2) / 2`` with the Hessian ``H_2 = (I - u u^T) / rho``
        (``u`` the unit vector from the anchor, ``rho`` the predicted range)."""
        self._settle()
        d = self._dim
        r = self._x[:d] + self.outputs.system.d[h, :d]
        rho = float(np.linalg.norm(r))
        if rho == 0.0:
            return 0.0
        u = r / rho
        HP = (np.eye(d) - np.outer(u, u)) @ self._P[:d, :d] / rho
        return 0.5 * float(np.trace(HP @ HP))

    def _try_fix(self) -> bool:
        """Set the position from the kept ranges once a round is in (module docstring); whether
        it was set (the ranges kept then are in the fix, and are not corrected by again)."""
        q = self.q
        if np.isnan(self._latest).any() and self._waited < 2 * q:
            return False
        fixed = self._fix()
        if fixed is None:
            if self._waited >= 4 * q:
                self.fix_pending = False
                self.fix_abandoned = self._time
            return False
        cols, p, cov = fixed
        self._settle()
        wide = math.sqrt(float(np.max(np.linalg.eigvalsh(cov)))) > self._threshold
        joint = self._joint_fix(p) if wide and cols.size == self._dim < self._x.size else None
        if joint is not None:  # the position and the other states (a velocity) together
            self._x, self._P = joint
        else:
            self._x[cols] = p
            self._P[cols, :] = 0.0
            self._P[:, cols] = 0.0
            self._P[np.ix_(cols, cols)] = cov
        self.fix_pending = False
        self.fixes.append(self._time)
        return True

    def _fix(self):
        """``(columns, position, covariance)`` of the time-aligned multilateration, or None."""
        system = self.outputs.system
        d, dim = np.array(system.d, dtype=float), self._dim
        rows = np.flatnonzero(~np.isnan(self._latest))
        shift = np.zeros((self.q, dim))
        now = (self._x - self._offset)[:dim]
        shift[rows] = now - self._at[rows]  # Delta_h: the motion predicted since range h
        a = -d[:, :dim]
        moved = a + shift
        y = self._latest + 0.5 * (np.sum(a * a, axis=1) - np.sum(moved * moved, axis=1))
        d[:, :dim] = -moved
        fixed = multilateration(system.C, d, y, variances=self._var_y)
        if fixed is None or np.any(fixed[0] >= dim):
            return None
        cols = fixed[0]
        oldest = rows[np.argmin(self._t_at[rows])]
        growth = self._P_dr[np.ix_(cols, cols)] - self._P_at[oldest][np.ix_(cols, cols)]
        try:  # full rank, yet singular to working precision (anchors nearly in line, far off)
            cov = multilateration_covariance(d[rows][:, cols], self._var_y[rows]) + growth
        except np.linalg.LinAlgError:
            return None  # no fix from this round; the next may give one
        return cols, fixed[1], 0.5 * (cov + cov.T)

    def _back(self, tau: float) -> np.ndarray:
        """``Phi(t - tau, t)``: the state ``tau`` seconds ago as a map of the state now (the
        model's dynamics without input and noise, ``exp(-A tau)``)."""
        if tau <= 0.0:
            return np.eye(self._x.size)
        return np.linalg.inv(self.dynamics.over(tau)[0])

    def _joint_fix(self, p: np.ndarray):
        """``(x, P)`` of the joint fix of the position and the other states (module docstring,
        "Joint fix") from every range kept, started at the position ``p`` of the
        multilateration; None where its steps do not settle or the other states' prior is not
        positive definite."""
        d, x_pred = self._dim, self._x - self._offset
        try:
            info = np.linalg.inv(self._P_dr[d:, d:])  # the prior of the other states
            np.linalg.cholesky(info)
        except np.linalg.LinAlgError:
            return None
        anchors = -np.asarray(self.outputs.system.d, dtype=float)[:, :d]
        h = np.array([k[0] for k in self._kept])
        rho = np.array([k[1] for k in self._kept])
        w = 1.0 / np.sqrt([k[2] for k in self._kept])
        M = np.array([self._back(self._time - k[3])[:d] for k in self._kept])  # (N, d, n)
        at = np.array([k[4][:d] for k in self._kept])
        theta = np.zeros_like(x_pred)
        theta[:d] = p - x_pred[:d]
        prior = np.zeros((self._x.size, self._x.size))
        prior[d:, d:] = info
        ranges = _KeptRanges(at, M, anchors[h], rho, w, prior)
        theta = ranges.minimise(theta, 1.0)
        dof = rho.size - d
        scale = 1.0
        if theta is not None and dof > 0 and ranges.objective(theta, 1.0) > dof:
            scale = ranges.objective(theta, 1.0) / dof  # the ranges' variance, re-weighted
            theta = ranges.minimise(theta, scale)
        if theta is None:
            return None
        J = ranges.jacobian(theta, scale)
        cov = np.linalg.inv(J.T @ J + prior) + self._P_q
        return x_pred + theta, 0.5 * (cov + cov.T)


class _KeptRanges:
    """The joint fix's least squares (module docstring, "Joint fix"): ranges ``rho`` (N,) with
    weights ``w = 1 / sigma`` taken at positions ``at + M theta`` (``at`` (N, d), ``M`` (N, d, n))
    from ``anchors`` (N, d), and the other states' prior information ``prior`` (n, n)."""

    def __init__(self, at, M, anchors, rho, w, prior):
        self.at, self.M, self.anchors, self.rho, self.w, self.prior = at, M, anchors, rho, w, prior

    def _offsets(self, theta):
        r = self.at + np.einsum("ndk,k->nd", self.M, theta) - self.anchors
        return r, np.linalg.norm(r, axis=1)

    def objective(self, theta, scale: float) -> float:
        """``sum (rho - |p_h - a_h|)^2 w^2 / scale + theta^T prior theta``."""
        _, dist = self._offsets(theta)
        e = (self.rho - dist) * self.w
        return float(e @ e) / scale + float(theta @ self.prior @ theta)

    def jacobian(self, theta, scale: float) -> np.ndarray:
        """The weighted ranges' Jacobian (N, n), ``u_h^T M_h w_h / sqrt(scale)``."""
        r, dist = self._offsets(theta)
        return np.einsum("nd,ndk->nk", r / dist[:, None], self.M) * (self.w / scale**0.5)[:, None]

    def minimise(self, theta, scale: float):
        """Gauss-Newton with its step halved until the objective falls (two points between
        which the plain steps would swing, as ranges that disagree can make them); the
        minimiser, or None where it does not settle in :data:`JOINT_STEPS` steps."""
        f = self.objective(theta, scale)
        for _ in range(JOINT_STEPS):
            dist = self._offsets(theta)[1]
            if np.any(dist == 0.0):
                return None
            J = self.jacobian(theta, scale)
            e = (self.rho - dist) * self.w / scale**0.5
            H = J.T @ J + self.prior
            step = np.linalg.solve(H, J.T @ e - self.prior @ theta)
            if step @ H @ step < JOINT_TOLERANCE**2:  # in standard deviations of the fix
                return theta + step
            for _ in range(30):
                trial = theta + step
                f_trial = self.objective(trial, scale)
                if f_trial < f:
                    break
                step = 0.5 * step
            else:
                return theta  # no step lowers it: the minimum, to rounding
            theta, f = trial, f_trial
            if not np.all(np.isfinite(theta)):
                return None
        return None


class FixedStartEKF(MultilaterationStart, ExtendedKalmanFilter):
    """:class:`~quadobs.estimators.kalman.ExtendedKalmanFilter` with the start-up of the module
    docstring (armed by :meth:`~MultilaterationStart.start_from_fix`)."""


class FixedStartUKF(MultilaterationStart, UnscentedKalmanFilter):
    """:class:`~quadobs.estimators.kalman.UnscentedKalmanFilter` with the start-up of the module
    docstring (armed by :meth:`~MultilaterationStart.start_from_fix`).

    Its waiting corrections take each range with the range's own variance: the sigma points
    ``Z_i = |X_i - a_h|`` already follow the range's curvature over the prior, so the
    unscented ``S = sum W^c_i (Z_i - z^-)^2 + sigma^2`` carries what the curvature adds;
    adding ``tr((H_2 P)^2) / 2`` to ``sigma^2`` as the EKF does would count it twice. For
    ``P = s^2 I`` in the plane at ``rho = s`` from the anchor (the default ``alpha = 1``,
    ``beta = 2``, ``kappa = 0``) the range's variance is ``0.60 s^2`` (sampled), the sigma
    points' spread ``1.18 s^2``, the EKF's linear ``s^2`` with the term ``s^2 / 2`` ``1.5 s^2``,
    and the spread with the term again ``1.68 s^2``."""

    def _waiting_variance(self, h: int) -> float:
        return 0.0
