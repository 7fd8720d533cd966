"""The augmented observer refined into an EKF once converged: global convergence and Cramér-Rao accuracy.

The augmented observer (Theorem 3 [IFAC2021], :class:`~quadobs.estimators.augmented.AugmentedObserver`)
converges from any initial guess because it treats the auxiliary states ``z_aux`` as free
coordinates; for the same reason its covariance spreads over directions where
``z != lift(x)``, which cannot occur, and its final error stays above the posterior
Cramér-Rao bound (PCRB). An EKF on ``x`` with the true noise levels reaches the bound
once its linearisation error is small compared with the noise, but diverges from a far
guess. :class:`RefinedObserver` runs both, in three phases:

1. **Augmented phase.** The observer runs and is reported. At every measurement step its
   prediction ``x^o`` is tested against the true measurement model of the EKF
   (:class:`~quadobs.estimators.kalman.OutputModel`):
   ``nis^o = nu^T (H P^o_x H^T + R)^{-1} nu``, ``nu = z - h(x^o)``, with ``P^o_x`` the
   observer's ``x`` block. A handover is tried when, over the last ``M`` updates, the sum of
   ``nis^o`` stays below the ``confidence`` quantile of ``chi^2`` with their degrees of
   freedom, and the curvature index

   .. math::

       \\eta = \\max_h \\sqrt{\\tfrac12 \\operatorname{tr}(\\nabla^2 h_h\\, P^o_x\\, \\nabla^2 h_h\\, P^o_x)} \\,/\\, \\sqrt{R_{hh}}

   (the standard deviation of the second-order term of ``h_h`` under ``N(x^o, P^o_x)``,
   over the noise's) is at most ``curvature`` (0.1): the linearisation error is then small
   against the noise.

2. **Handover by replay.** Instead of starting an EKF at ``(x^o, P^o_x)``, which would
   discard the information gathered before the handover (with a noise-free accelerometer
   the final variance then grows as ``t_end / (t_end - t_h)``), every measurement since
   step 0 is re-processed by a Kalman filter linearised about a reference trajectory
   ``xbar``, started from the prior ``(x_0, P_0)``. With ``d_k`` the response to the
   inputs (``d_0 = 0``, ``d_{k+1} = F d_k + G u_k``), the noise-free trajectory through
   ``xbar_k`` is ``xbar_j = F^{j-k} (xbar_k - d_k) + d_j``, and each measurement is used as
   ``z_j ~ h(xbar_j) + H_j (x_j - xbar_j)``. The pass is repeated with ``xbar_k`` set to its
   own result (``iterations`` times): with ``Q = 0`` this is Gauss-Newton on the batch
   maximum a posteriori estimate of ``x_0``, started from the observer's estimate, i.e.
   inside the basin of the global minimum. The replay is accepted when its last ``M`` innovations pass the same
   ``chi^2`` test and its last iteration moved ``xbar_k`` by less than the ``confidence``
   quantile of ``chi^2(n)`` in its own covariance; otherwise the observer stays in charge
   and the next try waits twice as long.

3. **EKF phase.** An :class:`~quadobs.estimators.kalman.ExtendedKalmanFilter` continues from
   the replay's ``(x_k, P_k)`` and is reported. Why it is at the bound: the EKF's
   covariance recursion is the PCRB recursion with ``H`` evaluated at ``x_hat`` instead
   of the truth; once ``eta << 1`` the difference ``H(x_hat) - H(x)`` is of the order of
   the error, itself of the order of ``sqrt(PCRB)``, and the neglected second-order
   term is below the noise, so the EKF is the (first-order) efficient estimator. The
   observer keeps running unchanged as a fallback: if over the last ``M`` updates the
   EKF's own NIS sum exceeds the ``guard`` quantile of ``chi^2``, or more than half of
   them were rejected by the gate, the estimator hands back to the observer (divergence
   guard) and may hand over again later.

Mode switches are kept as data: :attr:`RefinedObserver.mode` and
:attr:`RefinedObserver.switches`, a list of ``(step, from, to, reason)``; :meth:`RefinedObserver.summary`
gives them as a dict.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from quadobs.core.quantiles import chi2_ppf
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.base import Estimator, Gated, Immersed, Switching
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    gate_quantile,
    step_power,
)
from quadobs.estimators.robust import LockOut

__all__ = ["HandoverPolicy", "RefinedObserver", "curvature_index"]


def _NO_LOCKOUT() -> LockOut:
    """The EKF's own lock-out is off here: the hand-back to the observer is this estimator's."""
    return LockOut(timeout=math.inf)


#: The two modes of :class:`RefinedObserver`.
MODES = ("augmented", "ekf")


@dataclass(frozen=True)
class HandoverPolicy:
    """When :class:`RefinedObserver` hands over to the EKF, and when it hands back.

    Parameters
    ----------
    window : int
        ``M``: the number of measurement updates of the consistency windows.
    confidence : float
        Quantile of ``chi^2`` that the observer's (and the replay's) windowed NIS must stay
        under for a handover.
    guard : float
        Quantile of ``chi^2`` that the EKF's windowed NIS must exceed to hand back.
    curvature : float
        Largest curvature index ``eta`` (see the module docstring) for a handover. The
        neglected second-order term adds ``eta^2`` of the noise's variance to an innovation
        that the EKF models as linear: ``0.1`` keeps that error of its covariance at 1 %. (At
        ``eta`` near 1, handovers in the first seconds of ``ifac2021-noisy`` left the EKF
        overconfident, NEES about 10 over the runs concerned.)
    iterations : int
        Most Gauss-Newton passes of the replay.
    tolerance : float
        The replay has converged when its last pass moved the estimate by at most this
        much in its own metric (``delta^T P^-1 delta``).
    """

    window: int = 50
    confidence: float = 0.99
    guard: float = 0.9999
    curvature: float = 0.1
    iterations: int = 6
    tolerance: float = 1e-2

    def __post_init__(self) -> None:
        for name in ("window", "iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise QuadobsError(f"{name}: expected a positive integer, got {v!r}")
        for name in ("confidence", "guard"):
            v = as_finite_scalar(name, getattr(self, name), positive=True)
            if not v < 1:
                raise QuadobsError(f"{name}: must be below 1, got {v}")
        as_finite_scalar("curvature", self.curvature, positive=True)
        as_finite_scalar("tolerance", self.tolerance, positive=True)


def curvature_index(outputs: OutputModel, x: np.ndarray, P: np.ndarray) -> float:
    """``eta``: the largest ratio of the second-order term's standard deviation to the noise's.

    For output ``h`` with Hessian ``K_h`` at ``x`` and ``e ~ N(0, P)``, the term
    ``e^T K_h e / 2`` has standard deviation ``sqrt(tr(K_h P K_h P) / 2)``. ``K_h = C_h`` in
    the output space; in the norm space ``s_h = sqrt(2 (x^T C_h x / 2 + d_h^T x + c_h))``,
    ``K_h = C_h / s_h - g_h g_h^T / s_h^3`` with ``g_h = C_h x + d_h``.

    Examples
    --------
    >>> import numpy as np
    >>> from quadobs.core.system import QuadraticSystem
    >>> sys_ = QuadraticSystem(np.zeros((1, 1)), np.ones((1, 1)), np.ones((1, 1, 1)))
    >>> round(curvature_index(OutputModel(sys_, 1.0), np.ones(1), np.eye(1)), 3)
    0.707
    """
    sys_ = outputs.system
    x = np.asarray(x, dtype=float)
    g = sys_.C @ x + sys_.d  # (q, n)
    if outputs.offsets is None:
        K = sys_.C
    else:
        s = outputs.predict(x)
        with np.errstate(divide="ignore", invalid="ignore"):
            K = sys_.C / s[:, None, None] - np.einsum("hi,hj->hij", g, g) / (s**3)[:, None, None]
        K = np.where(np.isfinite(K), K, np.inf)
    KP = K @ P
    spread = np.sqrt(0.5 * np.maximum(np.einsum("hij,hji->h", KP, KP), 0.0))
    return float(np.max(spread / np.sqrt(np.diag(outputs.R))))


def linearize_all(outputs: OutputModel, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`OutputModel.linearize` at each row of ``X (N, n)``: ``(h (N, q), dh/dx (N, q, n))``."""
    sys_ = outputs.system
    g = np.einsum("hab,kb->kha", sys_.C, X)
    J = g + sys_.d
    y = np.einsum("kha,ka->kh", 0.5 * g + sys_.d, X)
    if outputs.offsets is None:
        return y, J
    s = np.sqrt(np.maximum(2.0 * (y + outputs.offsets), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(s > 0.0, 1.0 / s, 0.0)
    return s, J * scale[..., None]


_QUANTILES: dict[tuple[float, int], float] = {}


def chi2_quantile(q: float, dof: int) -> float:
    """The ``q`` quantile of ``chi^2(dof)``, cached (the windows ask for few distinct values)."""
    key = (q, int(dof))
    hit = _QUANTILES.get(key)
    if hit is None:
        hit = _QUANTILES[key] = chi2_ppf(q, dof)
    return hit


def _mahalanobis(delta: np.ndarray, P: np.ndarray) -> float:
    """``delta^T P^-1 delta`` (infinite for a singular ``P``)."""
    try:
        return float(delta @ np.linalg.solve(P, delta))
    except np.linalg.LinAlgError:
        return float("inf")


class _Window:
    """The last ``M`` updates' NIS and degrees of freedom, with running sums (rejected ones kept apart)."""

    def __init__(self, size: int) -> None:
        self.items: deque[tuple[float, int, bool]] = deque()
        self.size = size
        self.nis = 0.0
        self.dof = 0
        self.rejected = 0
        self.infinite = 0  # accepted updates with a non-finite NIS (they fail the test)

    def push(self, nis: float, dof: int, rejected: bool) -> None:
        if len(self.items) == self.size:
            self._add(*self.items.popleft(), sign=-1)
        self.items.append((nis, dof, rejected))
        self._add(nis, dof, rejected, sign=1)

    def _add(self, nis: float, dof: int, rejected: bool, sign: int) -> None:
        if rejected:
            self.rejected += sign
            return
        self.dof += sign * dof
        if np.isfinite(nis):
            self.nis += sign * nis
        else:
            self.infinite += sign

    @property
    def full(self) -> bool:
        return len(self.items) == self.size

    def passes(self, q: float) -> bool:
        """Whether the accepted updates' NIS sum is below the ``q`` quantile of ``chi^2`` (their dof)."""
        if self.dof <= 0 or self.infinite:
            return False
        return max(self.nis, 0.0) <= chi2_quantile(q, self.dof)

    def rejected_fraction(self) -> float:
        return self.rejected / max(len(self.items), 1)


class RefinedObserver(Estimator, Gated, Immersed, Switching):
    """The augmented observer, handing over to an EKF on ``x`` once converged (see the module docstring).

    Parameters
    ----------
    observer : AugmentedObserver
        Theorem 3's observer, started at the initial guess; it runs for the whole episode.
    dynamics : HeldInputModel
        The exact held-input dynamics of ``x`` with the true process noise.
    outputs : OutputModel
        The measurement model with the true noise (or the observer's ``R`` when noise-free).
    x0 : array_like (n,)
        The initial guess (the prior mean of the replay).
    P0 : float or array_like
        Its covariance (the prior of the replay).
    gate : float, optional
        NIS gate of the EKF and the replay (as for the observer).
    policy : HandoverPolicy, optional

    Attributes
    ----------
    mode : str
        ``"augmented"`` or ``"ekf"``: which estimate is reported.
    switches : list of tuple
        ``(step, from, to, reason)`` for every change of mode.
    attempts : int
        Replays tried.

    Examples
    --------
    See :func:`quadobs.testbed.factories.refined_observer` for one built from a scenario.
    """

    name = "augmented-refined"

    def __init__(
        self,
        observer: AugmentedObserver,
        dynamics: HeldInputModel,
        outputs: OutputModel,
        *,
        x0,
        P0,
        gate: float | None = None,
        policy: HandoverPolicy | None = None,
        robust=None,
    ) -> None:
        if not isinstance(observer, AugmentedObserver):
            raise QuadobsError(
                f"observer: expected an AugmentedObserver, got {type(observer).__name__}"
            )
        probe = ExtendedKalmanFilter(
            dynamics, outputs, x0=x0, P0=P0, gate=gate
        )  # validates the models
        n, q = probe.n, probe.q
        if observer.immersion.system.n != n or observer.immersion.system.q != q:
            raise QuadobsError(
                "observer: its system's dimensions differ from the dynamics' and outputs'"
            )
        self.observer, self.dynamics, self.outputs = observer, dynamics, outputs
        self.immersion = observer.immersion
        self.policy = policy if policy is not None else HandoverPolicy()
        if not isinstance(self.policy, HandoverPolicy):
            raise QuadobsError(
                f"policy: expected a HandoverPolicy, got {type(self.policy).__name__}"
            )
        self.gate = probe.gate
        #: The EKF's robust correction (:mod:`quadobs.estimators.robust`); its lock-out is the
        #: hand-back to the observer below.
        self.robust = robust
        self.n, self.q = n, q
        self._x0 = as_array("x0", x0, (n,)).copy()
        self._P0 = probe.x_covariance.copy()
        self._F, self._G = dynamics.F, dynamics.G
        self._Finv = np.linalg.inv(dynamics.F)
        self._powers = np.eye(n)[None]  # F^{-m}, m = 0 .. (see _back)
        self._d = np.zeros(n)
        self._k = 0
        self._log_steps: list[int] = []
        self._log_y: list[np.ndarray] = []
        self._log_d: list[np.ndarray] = []
        self._ekf: ExtendedKalmanFilter | None = None
        self._obs_window = _Window(self.policy.window)
        self._ekf_window = _Window(self.policy.window)
        self._next_try, self._wait = 0, self.policy.window
        self._updates = 0  # measurement steps so far
        self.mode = "augmented"
        self.switches: list[tuple[int, str, str, str]] = []
        self.attempts = 0
        self.nis = float("nan")
        self.corrections = 0
        self.rejected = 0
        self.measurement_models = observer.measurement_models
        self._time = observer.time

    # -- estimator interface -----------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        src = self.observer if self._ekf is None else self._ekf
        return np.array(src.x_hat, dtype=float)

    @property
    def x_covariance(self) -> np.ndarray:
        src = self.observer if self._ekf is None else self._ekf
        return np.array(src.x_covariance, dtype=float)

    @property
    def covariance_trace(self) -> float:
        if self._ekf is None:
            return self.observer.covariance_trace
        return float(np.trace(self._ekf.x_covariance))

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Correct with ``y`` and predict over the step with ``u`` held, in the current mode."""
        u = AugmentedObserver._checked("u", u, (self.dynamics.system.p,))
        y = AugmentedObserver._checked("y", y, (self.q,))
        present = ~np.isnan(y)
        has = bool(present.any())
        if has:
            self._updates += 1
            self._log_steps.append(self._k)
            self._log_y.append(y.copy())
            self._log_d.append(self._d.copy())
        if self._ekf is None:
            self._augmented_step(u, y, present, has)
        else:
            self._ekf_step(u, y, has)
        self._d = self._F @ self._d + self._G @ u
        self._k += 1
        self._time += self.dynamics.dt

    # -- the interface in time ---------------------------------------------------------
    #
    # The observer and, once handed over, the EKF are advanced by their own predict(t) and
    # correct(m). The handover's replay reprocesses the measurements on the grid of steps; in
    # time the EKF starts instead at the observer's estimate and covariance, once the same
    # window of NIS and the curvature index allow it (the module docstring's tests).

    def _input_dimension(self) -> int:
        return self.dynamics.system.p

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        t = self._time + dt
        for est in (self.observer, self._ekf):
            if est is not None:
                est.hold(u)
                est.predict(t)

    def _correct_measurement(self, m) -> None:
        model = self._model_of(m)
        self._updates += 1
        obs = self.observer
        if self._ekf is None:
            before = (obs.corrections, obs.rejected)
            xo, Po = obs.x_hat, np.array(obs.x_covariance)
            nis = self._measurement_nis(model, m, xo, Po)
            self._obs_window.push(nis, 1, self.gate is not None and nis > self.gate)
            w = self._obs_window
            if (
                self._updates >= self._next_try
                and w.full
                and w.passes(self.policy.confidence)
                and curvature_index(self.outputs, xo, Po) <= self.policy.curvature
            ):
                self._handover_in_time(xo, Po)
            obs.correct(m)
            if self._ekf is None:
                self.nis = obs.nis
                self.corrections += obs.corrections - before[0]
                self.rejected += obs.rejected - before[1]
                return
        else:
            obs.correct(m)
        ekf = self._ekf
        ekf.correct(m)
        self.nis = ekf.nis
        rejected = self._count(ekf.nis)
        self._ekf_window.push(ekf.nis, 1, rejected)
        w = self._ekf_window
        if w.full and (w.rejected_fraction() > 0.5 or not w.passes(self.policy.guard)):
            self._ekf = None
            self._obs_window = _Window(self.policy.window)
            self._next_try = self._updates + self.policy.window
            self._switch("ekf", "augmented", "EKF rejected or inconsistent")

    def _measurement_nis(self, model, m, x, P) -> float:
        """NIS of one range under the true measurement model at ``(x, P)``."""
        h, yh, var = model.quadratic_output(m)
        idx = np.array([h])
        z = self.outputs.measure(np.array([yh]), idx)
        zp, H = self.outputs.linearize(x)
        R = self.outputs.R[h, h] if np.isnan(m.std) else m.std**2
        if self.outputs.offsets is None and not np.isnan(m.std):
            R = var
        nu = float(z[0] - zp[h])
        S = float(H[h] @ P @ H[h]) + R
        return nu * nu / S if S > 0 else float("inf")

    def _ekf_at(self, x: np.ndarray, P: np.ndarray, measurements=None) -> ExtendedKalmanFilter:
        """The EKF handed over to, started at ``x``, ``P``: this estimator's models, gate and robust
        rule, without a lock-out of its own (:func:`_NO_LOCKOUT`); ``measurements`` for the
        interface in time."""
        return ExtendedKalmanFilter(
            self.dynamics,
            self.outputs,
            x0=x,
            P0=P,
            gate=self.gate,
            measurements=measurements,
            robust=self.robust,
            lockout=_NO_LOCKOUT(),
        )

    def _handover_in_time(self, x: np.ndarray, P: np.ndarray) -> None:
        self.attempts += 1
        ekf = self._ekf_at(x, P, measurements=list(self.measurement_models.values()))
        ekf.time = self._time
        ekf.hold(self.observer.held_input())
        self._ekf = ekf
        self._ekf_window = _Window(self.policy.window)
        self._switch("augmented", "ekf", "observer consistent (in time: at its estimate)")

    # -- the two modes -----------------------------------------------------------------

    def _augmented_step(self, u, y, present, has) -> None:
        obs = self.observer
        before = (obs.corrections, obs.rejected)
        handed = None
        if has:
            xo, Po = obs.x_hat.copy(), np.array(obs.x_covariance)
            self._observer_test(xo, Po, y, present)
            if (
                self._updates >= self._next_try
                and self._obs_window.full
                and self._obs_window.passes(self.policy.confidence)
            ):
                if curvature_index(self.outputs, xo, Po) <= self.policy.curvature:
                    handed = self._try_handover(xo, Po)
        obs.step(u, y)
        if handed is None:
            self.nis = obs.nis
            self.corrections += obs.corrections - before[0]
            self.rejected += obs.rejected - before[1]
            return
        self._ekf = handed
        self.nis = handed.nis
        self._count(handed.nis, handed.nis_dof)
        handed.predict_step(u)
        self._switch("augmented", "ekf", "observer consistent: replay accepted")

    def _ekf_step(self, u, y, has) -> None:
        ekf = self._ekf
        assert ekf is not None, "called in the EKF's mode only"
        self.observer.step(u, y)  # the fallback keeps running
        before = (ekf.rejected, ekf.corrections)
        ekf.step(u, y)
        self.nis = ekf.nis
        if not has:
            return
        if self.robust is None and self.gate is None:
            rejected = self._count(ekf.nis)
        else:  # the EKF's own rule decided (its gate judges each output of the step alone)
            n_rejected, n_accepted = ekf.rejected - before[0], ekf.corrections - before[1]
            self.rejected += n_rejected
            self.corrections += n_accepted
            rejected = n_rejected > 0 and n_accepted == 0  # the step brought nothing
        self._ekf_window.push(ekf.nis, ekf.nis_dof, rejected)
        w = self._ekf_window
        if w.full and (w.rejected_fraction() > 0.5 or not w.passes(self.policy.guard)):
            reason = (
                "EKF updates rejected by the gate"
                if w.rejected_fraction() > 0.5
                else "EKF NIS above the guard"
            )
            self._ekf = None
            self._obs_window = _Window(self.policy.window)
            self._next_try, self._wait = self._updates + self.policy.window, self.policy.window
            self._switch("ekf", "augmented", reason)

    def _count(self, nis: float, dof: int = 1) -> bool:
        """Count an update of the reported filter (its NIS of ``dof`` outputs); returns whether
        the gate, stated per output, rejects it at that many degrees of freedom
        (:func:`~quadobs.estimators.kalman.gate_quantile`)."""
        if not np.isfinite(nis):
            return False
        rejected = self.gate is not None and nis > gate_quantile(self.gate, dof)
        if rejected:
            self.rejected += 1
        else:
            self.corrections += 1
        return rejected

    def _switch(self, old: str, new: str, reason: str) -> None:
        self.mode = new
        self.switches.append((self._k, old, new, reason))

    # -- the handover ------------------------------------------------------------------

    def _observer_test(self, xo, Po, y, present) -> None:
        """Push the NIS of the observer's prediction under the true measurement model."""
        idx = np.flatnonzero(present)
        z = self.outputs.measure(y[idx], idx)
        zp, H = self.outputs.linearize(xo)
        nu = z - zp[idx]
        H = H[idx]
        S = H @ Po @ H.T + self.outputs.R[np.ix_(idx, idx)]
        try:
            nis = float(nu @ np.linalg.solve(S, nu))
        except np.linalg.LinAlgError:
            nis = np.inf
        rejected = self.gate is not None and nis > self.gate
        self._obs_window.push(nis, idx.size, rejected)

    def _try_handover(self, x_obs: np.ndarray, P_obs: np.ndarray) -> ExtendedKalmanFilter | None:
        """Replay every measurement about the trajectory through ``x_obs`` (Gauss-Newton); an EKF at the result, or ``None``."""
        self.attempts += 1
        pol = self.policy
        steps = np.array(self._log_steps)
        Y, D = np.array(self._log_y), np.array(self._log_d)
        x_ref = np.asarray(x_obs, dtype=float)
        for _ in range(pol.iterations):
            x, P, window = self._replay(steps, Y, D, x_ref)
            moved = _mahalanobis(x - x_ref, P)
            x_ref = x
            if moved <= pol.tolerance:
                break
        ok = (
            moved <= pol.tolerance
            and window.passes(pol.confidence)
            and _mahalanobis(x - x_obs, P + P_obs) <= chi2_quantile(pol.confidence, self.n)
            and curvature_index(self.outputs, x, P) <= pol.curvature
        )
        if not ok:
            self._next_try = self._updates + self._wait
            self._wait = min(2 * self._wait, 4 * pol.window)
            return None
        ekf = self._ekf_at(x, P)
        ekf.nis, ekf.nis_dof = window.items[-1][0], window.items[-1][1]
        self._ekf_window = _Window(pol.window)
        for item in window.items:
            self._ekf_window.push(*item)
        return ekf

    def _replay(
        self, steps, Y, D, x_ref, batch: bool = True
    ) -> tuple[np.ndarray, np.ndarray, _Window]:
        """One Kalman pass over the logged measurements, linearised about the noise-free trajectory through ``x_ref``.

        Without process noise, without a gate and with a diagonal ``R``, the measurements
        before the last ``M`` are processed at once in information form (:meth:`_batch`,
        the same posterior as the sequential pass); the last ``M`` are processed one by one
        for the window's NIS. ``batch=False`` forces the sequential pass throughout.
        """
        refs = self._reference(steps, D, x_ref)
        out = self.outputs
        Z = out.measure(Y)  # NaN where missing
        zps, Hs = linearize_all(out, refs)
        split = max(len(steps) - self.policy.window, 0) if batch and self._batchable else 0
        if split:
            x, P = self._batch(
                steps[:split], Z[:split], zps[:split], Hs[:split], refs[:split], D[:split]
            )
            last, d_last = int(steps[split - 1]), D[split - 1]
        else:
            x, P, last, d_last = self._x0.copy(), self._P0.copy(), 0, np.zeros(self.n)
        F, Q, R, q = self._F, self.dynamics.Q, out.R, self.q
        window = _Window(self.policy.window)
        powers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for i in range(split, len(steps)):
            j = steps[i]
            m = int(j - last)
            if m:
                Fm, Qm = powers.get(m) or powers.setdefault(m, step_power(F, Q, m))
                x = Fm @ x + (D[i] - Fm @ d_last)
                P = Fm @ P @ Fm.T + Qm
            last, d_last = j, D[i]
            zp, H, z = zps[i], Hs[i], Z[i]
            idx = np.flatnonzero(~np.isnan(z))
            if idx.size < q:
                zp, H, z, Ri = zp[idx], H[idx], z[idx], R[np.ix_(idx, idx)]
            else:
                Ri = R
            nu = z - zp - H @ (x - refs[i])
            PHt = P @ H.T
            Sinv = np.linalg.inv(H @ PHt + Ri)
            nis = float(nu @ Sinv @ nu)
            rejected = self.gate is not None and nis > self.gate
            window.push(nis, idx.size, rejected)
            if rejected:
                continue
            K = PHt @ Sinv
            x = x + K @ nu
            P = P - K @ PHt.T
            P = 0.5 * (P + P.T)
        return x, P, window

    @property
    def _batchable(self) -> bool:
        """Whether :meth:`_batch` applies: no process noise, no gate, a diagonal ``R``."""
        R = self.outputs.R
        return (
            self.gate is None
            and not np.any(self.dynamics.Q)
            and not np.any(R - np.diag(np.diag(R)))
        )

    def _batch(self, steps, Z, zps, Hs, refs, D) -> tuple[np.ndarray, np.ndarray]:
        """The posterior of ``x_k`` (``k = steps[-1]``) from the prior and these measurements, in information form.

        With ``Q = 0``, ``x_j = F^{j-k} (x_k - d_k) + d_j``, so the linearised measurement is
        ``z_j - h(xbar_j) = A_j delta + v_j`` with ``delta = x_k - xbar_k`` and
        ``A_j = H_j F^{j-k}``; the prior ``x_0 ~ N(x_0, P_0)`` is
        ``F^{-k} delta ~ N(x_0 - xbar_0, P_0)``. Then

        .. math::

            J = B_0^T P_0^{-1} B_0 + \\sum_j A_j^T R^{-1} A_j, \\quad
            J \\hat\\delta = B_0^T P_0^{-1} (x_0 - \\bar x_0) + \\sum_j A_j^T R^{-1} (z_j - h(\\bar x_j)),

        ``B_0 = F^{-k}``, ``x_k = xbar_k + delta_hat``, ``P_k = J^{-1}``: the batch least
        squares solution, equal to the sequential Kalman pass's (missing entries weigh zero).
        """
        B = self._back(steps)
        B0 = self._powers[steps[-1]]  # F^{-k}
        present = ~np.isnan(Z)
        w = np.where(present, 1.0 / np.diag(self.outputs.R), 0.0)  # (N, q)
        r = np.where(present, Z - zps, 0.0)
        A = Hs @ B  # (N, q, n)
        J = np.einsum("kha,kh,khb->ab", A, w, A)
        b = np.einsum("kha,kh,kh->a", A, w, r)
        xbar0 = B0 @ (refs[-1] - D[-1])  # the reference at step 0 (d_0 = 0)
        P0B = np.linalg.solve(self._P0, B0)
        J = J + B0.T @ P0B
        b = b + P0B.T @ (self._x0 - xbar0)
        J = 0.5 * (J + J.T)
        P = np.linalg.inv(J)
        return refs[-1] + P @ b, 0.5 * (P + P.T)

    def _back(self, steps) -> np.ndarray:
        """``F^{j-k}`` at the logged steps ``j`` (``k`` the last one), ``(N, n, n)``, from a cached table of powers of ``F^{-1}``.

        The table holds ``F^{-m}`` for ``m = 0 .. L - 1`` and doubles when a longer log needs it
        (``F^{-(m + L)} = F^{-m} F^{-L}``): ``log2`` vectorised products instead of one per step.
        """
        need = int(steps[-1]) + 1
        table = self._powers
        while table.shape[0] < need:
            table = np.concatenate([table, table @ (table[-1] @ self._Finv)])
        self._powers = table
        return table[steps[-1] - steps]

    def _reference(self, steps, D, x_ref) -> np.ndarray:
        """``xbar_j = F^{j-k} (x_ref - d_k) + d_j`` at the logged steps ``j`` (``k`` the last one)."""
        return np.einsum("kab,b->ka", self._back(steps), x_ref - D[-1]) + D

    # -- reporting ---------------------------------------------------------------------

    def summary(self) -> dict:
        """The mode switches as plain data (for a recording's events or a summary).

        Returns
        -------
        dict
            ``mode``, ``attempts``, ``switches`` (list of ``{"step", "from", "to", "reason"}``)
            and ``handover_step`` (the step of the first handover, ``None`` without one).
        """
        first = next((s for s, _, to, _ in self.switches if to == "ekf"), None)
        return {
            "mode": self.mode,
            "attempts": self.attempts,
            "handover_step": first,
            "switches": [
                {"step": s, "from": a, "to": b, "reason": r} for s, a, b, r in self.switches
            ],
        }
