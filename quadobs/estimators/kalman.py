"""Extended and unscented Kalman filters on the original state: the baselines.

What a user would pick instead of the augmented observer: a Kalman filter on the
original state ``x`` (position, velocity, and wind where present) of the
:class:`~quadobs.core.system.QuadraticSystem`, linearised at the estimate (EKF) or through an
unscented transform (UKF) at each measurement.

Dynamics and prediction
-----------------------
The dynamics ``x' = A x + B u`` are linear, so the prediction over one step of length
``dt`` with the input held is exact, shared by both filters and computed once:

.. math::

    \\exp\\left(\\begin{bmatrix} A & B \\\\ 0 & 0 \\end{bmatrix} dt\\right)
    = \\begin{bmatrix} F & G \\\\ 0 & I \\end{bmatrix}, \\qquad
    x^- = F x + G u, \\qquad P^- = F P F^\\top + Q_d .

``Q_d`` has two parts (:class:`HeldInputModel`): the continuous intensity ``V`` of a
white noise on ``x'`` (Van Loan, ``Q_V = int_0^dt e^{A s} V e^{A^T s} ds``) and a white
noise of covariance ``Sigma_u`` on the measured input held over each step, which enters
exactly as ``G Sigma_u G^T``. For an accelerometer read every physics step with
standard deviation ``sigma_a`` (the testbed's sensor), ``Q_d = sigma_a^2 G G^T`` is the
true process noise, not a tuning. The UKF's prediction is the same exact linear map (an
unscented transform of a linear map returns its mean and covariance exactly).

Between measurements only the mean is advanced each step; the covariance is advanced
in one go when it is needed (a measurement, or a read of :attr:`x_covariance`) with
``F^m`` and ``Q_m = sum_{i<m} F^i Q_d F^iT`` (:func:`step_power`, cached by ``m``): the
same numbers as ``m`` single steps, at the cost of one.

Measurements
------------
:class:`OutputModel` says in which space a filter compares the outputs ``y`` (``(q,)``,
NaN where no sample: those outputs are skipped and a step with none is prediction only):

* ``"output"`` space: ``z = y``, ``h(x) = 1/2 x^T C_h x + d_h^T x``, Jacobian
  ``x^T C_h + d_h^T``, with a constant covariance ``R`` (e.g. the augmented observer's
  ``W / T``);
* ``"norm"`` space, for outputs that are half a squared norm up to a known constant
  (``y_h + c_h = s_h^2 / 2``, as for a range ``s_h = |p - a_h|`` with
  ``c_h = |a_h|^2 / 2``, or an airspeed with ``c = 0``): the filter recovers the
  measured ``s~_h = sqrt(2 (y_h + c_h))`` (the exact inverse of the sensor layer's map,
  :mod:`quadobs.testbed.sensors`) and uses ``h_h(x) = sqrt(2 (1/2 x^T C_h x + d_h^T x + c_h))``
  with Jacobian ``(x^T C_h + d_h^T) / h_h(x)``. With the sensor's standard deviation
  ``sigma_h`` this is the exact measurement model ``s~ = s + N(0, sigma^2)``, the one of
  the Cramér-Rao bound (:mod:`quadobs.evaluation.ensemble`).

Updates use the present outputs only. The EKF uses the Joseph form
``P = (I - K H) P (I - K H)^T + K R K^T``. The UKF uses the scaled unscented transform
(Julier and Uhlmann; Wan and van der Merwe) with ``2 n + 1`` sigma points
``x, x +- sqrt(n + lambda) L_i`` (``L L^T = P``), ``lambda = alpha^2 (n + kappa) - n``,
weights ``W_0^m = lambda / (n + lambda)``, ``W_0^c = W_0^m + 1 - alpha^2 + beta``,
``W_i = 1 / (2 (n + lambda))``; the defaults ``alpha = 1, beta = 2, kappa = 0`` keep
every weight non-negative, so the innovation covariance is positive definite by
construction. ``P = P - K S K^T``. Covariances are re-symmetrised after each operation.

Both filters store the normalised innovation squared ``nis = nu^T S^-1 nu`` of their
last update (NaN when there was none) and its degrees of freedom :attr:`nis_dof` (the
number of outputs used), and can reject an update whose NIS exceeds ``gate``, a threshold
stated for one output: outputs of one time (a grid step's, a batch of ranges) are gated each
alone, one scalar correction after the other where their noise is uncorrelated.

Scenario defaults (the estimators ``"ekf"`` and ``"ukf"``): see
:func:`quadobs.testbed.factories.baseline_settings`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from quadobs.core.held_input import (
    as_covariance,
    held_input_interval,
    held_input_step,
    van_loan,
    van_loan_interval,
)
from quadobs.core.measurements import Measurement, MeasurementModel
from quadobs.core.quantiles import chi2_isf
from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.base import Gated, HalfSteps, measurement_models, step_operands
from quadobs.estimators.robust import (
    LockOut,
    multilateration,
    reinitialised_covariance,
    reweight,
)

__all__ = [
    "ExtendedKalmanFilter",
    "HeldInputModel",
    "OutputModel",
    "UnscentedKalmanFilter",
    "gate_quantile",
    "step_power",
]


# --------------------------------------------------------------------------------------
# Models
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class HeldInputModel:
    """Exact one-step map ``x+ = F x + G u + w``, ``w ~ N(0, Q)``, of ``x' = A x + B u`` with ``u`` held.

    The original state's counterpart of the augmented
    :class:`~quadobs.core.held_input.HeldInputDiscretization`: ``(F, G)`` from
    :func:`~quadobs.core.held_input.held_input_step` and ``Q_V`` from
    :func:`~quadobs.core.held_input.van_loan`, the same maths in one place; this class only adds
    the measured-input noise ``G Sigma_u G^T`` of the Kalman baselines and the PCRB.
    For the double integrator ``F = [[I, dt I], [0, I]]``, ``G = [dt^2/2 I; dt I]`` and
    ``V = blockdiag(0, sigma^2 I)`` gives ``Q_V = sigma^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I``.

    Parameters
    ----------
    system : QuadraticSystem
    dt : float
        Step length (s).
    V : float or array_like, optional
        Continuous intensity of a white noise on ``x'`` (scalar times ``I_n``, diagonal or
        ``(n, n)``); Van Loan's integral over the step.
    input_covariance : float or array_like, optional
        Covariance ``Sigma_u`` of a white noise on the measured input, held over each
        step (scalar times ``I_p``, diagonal or ``(p, p)``); adds ``G Sigma_u G^T``.

    Attributes
    ----------
    F : ndarray (n, n)
        ``e^{A dt}``.
    G : ndarray (n, p)
        ``int_0^dt e^{A s} ds B``.
    Q : ndarray (n, n)
        The discrete process-noise covariance (positive semidefinite).
    """

    system: QuadraticSystem
    dt: float
    V: np.ndarray | float = 0.0
    input_covariance: np.ndarray | float = 0.0
    F: np.ndarray = field(init=False, repr=False)
    G: np.ndarray = field(init=False, repr=False)
    Q: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.system, QuadraticSystem):
            raise QuadobsError(
                f"system: expected a QuadraticSystem, got {type(self.system).__name__}"
            )
        dt = as_finite_scalar("dt", self.dt, positive=True)
        n, p = self.system.n, self.system.p
        V = as_covariance("V", self.V, n, definite=False)
        Su = as_covariance("input_covariance", self.input_covariance, p, definite=False)
        F, G = held_input_step(self.system.A, self.system.B, dt)
        Q = van_loan(self.system.A, V, dt)[1] if V.any() else np.zeros((n, n))
        Q = Q + G @ Su @ G.T
        Q = 0.5 * (Q + Q.T)
        object.__setattr__(self, "dt", dt)
        for name, arr in (("V", V), ("input_covariance", Su), ("F", F), ("G", G), ("Q", Q)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def over(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(F, G, Q)`` of the same model over an interval of ``dt`` seconds (any ``dt > 0``),
        by the same exponentials as the step's own: ``Q = Q_V(dt) + G Sigma_u G^T``, the
        measured input's error held over the interval.

        Where ``A^2 = 0`` the exponentials' series end after their linear terms:
        ``F = I + A dt``, ``G = B dt + A B dt^2 / 2`` and
        ``Q_V = V dt + (A V + V A^T) dt^2 / 2 + A V A^T dt^3 / 3`` (exact).
        """
        dt = as_finite_scalar("dt", dt, positive=True)
        sys_ = self.system
        A, B, V = sys_.A, sys_.B, self.V
        if not (A @ A).any():  # A^2 = 0 (single and double integrators): the series ends at A
            F = np.eye(A.shape[0]) + dt * A
            G = dt * B + (0.5 * dt * dt) * (A @ B)
            AV = A @ V
            Q = dt * V + (0.5 * dt * dt) * (AV + AV.T) + (dt**3 / 3.0) * (AV @ A.T)
            Q = Q + G @ self.input_covariance @ G.T
            return F, G, 0.5 * (Q + Q.T)
        F, G = held_input_interval(sys_.A, sys_.B, dt)
        V = np.asarray(self.V)  # stored as an array when the model is built
        Q = van_loan_interval(sys_.A, V, dt)[1] if V.any() else np.zeros_like(F)
        Q = Q + G @ self.input_covariance @ G.T
        return F, G, 0.5 * (Q + Q.T)


@dataclass(frozen=True, eq=False)
class OutputModel:
    """How a filter compares the outputs ``y``: the space, and the noise covariance there.

    Parameters
    ----------
    system : QuadraticSystem
    R : float or array_like
        Measurement-noise covariance in the chosen space (scalar times ``I_q``, diagonal or
        ``(q, q)``), positive definite.
    offsets : array_like (q,), optional
        ``c_h`` with ``y_h + c_h = s_h^2 / 2``: selects the ``"norm"`` space (see the module
        docstring). ``None`` (default): the ``"output"`` space ``z = y``.
    """

    system: QuadraticSystem
    R: Any  # a float, a diagonal or (q, q) as given; (q, q) once built
    offsets: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.system, QuadraticSystem):
            raise QuadobsError(
                f"system: expected a QuadraticSystem, got {type(self.system).__name__}"
            )
        q = self.system.q
        R = as_covariance("R", self.R, q)
        R.setflags(write=False)
        object.__setattr__(self, "R", R)
        if self.offsets is not None:
            c = as_array("offsets", self.offsets, (q,))
            c.setflags(write=False)
            object.__setattr__(self, "offsets", c)

    @property
    def space(self) -> str:
        """``"output"`` or ``"norm"``."""
        return "output" if self.offsets is None else "norm"

    def measure(self, y: np.ndarray, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The measurement ``z`` of the outputs ``y`` (already restricted to ``idx``)."""
        if self.offsets is None:
            return y
        return np.sqrt(np.maximum(2.0 * (y + self.offsets[idx]), 0.0))

    def predict(self, x: np.ndarray) -> np.ndarray:
        """``z = h(x)`` for ``x`` of shape ``(..., n)``; returns ``(..., q)``."""
        y = self.system.output(x)
        if self.offsets is None:
            return y
        return np.sqrt(np.maximum(2.0 * (y + self.offsets), 0.0))

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """``dh/dx (q, n)`` at ``x (n,)``; in the norm space, zero rows where ``h(x) = 0``."""
        return self.linearize(x)[1]

    def linearize(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(h(x) (q,), dh/dx (q, n))`` at ``x (n,)`` in one pass (``g_h = C_h x``, ``y_h = (g_h / 2 + d_h) . x``)."""
        sys_ = self.system
        g = sys_.C @ x
        J = g + sys_.d
        y = (0.5 * g + sys_.d) @ x
        if self.offsets is None:
            return y, J
        s = np.sqrt(np.maximum(2.0 * (y + self.offsets), 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(s > 0.0, 1.0 / s, 0.0)
        return s, J * scale[:, None]


@functools.lru_cache(maxsize=64)
def gate_quantile(gate: float, dof: int) -> float:
    """The NIS threshold of ``dof`` outputs for a gate stated per output: ``gate`` for one, else
    the quantile of ``chi^2(dof)`` of the same probability ``P = P(chi^2(1) <= gate) =
    erf(sqrt(gate / 2))`` (10.83 -> ``P = 0.999`` -> 13.82 for two outputs)."""
    if dof == 1:
        return float(gate)
    tail = math.erfc(math.sqrt(0.5 * gate))  # P(chi^2(1) > gate), accurate in the tail
    return chi2_isf(tail, dof)


def step_power(F: np.ndarray, Q: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """``(F^m, Q_m)``: the map of ``m`` steps ``x+ = F x + w``, ``w ~ N(0, Q)``, with ``Q_m = sum_{i<m} F^i Q F^iT``.

    By doubling, in ``O(log m)`` products: ``m`` steps then ``l`` steps compose as
    ``(F^l F^m, F^l Q_m F^lT + Q_l)``.
    """
    n = F.shape[0]
    res = (np.eye(n), np.zeros((n, n)))
    base = (np.asarray(F, dtype=float), np.asarray(Q, dtype=float))
    while m > 0:
        if m & 1:
            Fb, Qb = base
            res = (Fb @ res[0], Fb @ res[1] @ Fb.T + Qb)
        m >>= 1
        if m:
            Fb, Qb = base
            base = (Fb @ Fb, Fb @ Qb @ Fb.T + Qb)
    Fm, Qm = res
    return Fm, 0.5 * (Qm + Qm.T)


# --------------------------------------------------------------------------------------
# Filters
# --------------------------------------------------------------------------------------


class _GaussianFilter(HalfSteps, Gated):
    """Shared prediction, lazy covariance, missing outputs, NIS and gating (see the module docstring)."""

    name = "gaussian"
    #: A start-up (:mod:`quadobs.estimators.startup`, :mod:`quadobs.estimators.bias_states`)
    #: waiting for its fix: measurements of one time are then corrected one at a time.
    fix_pending: bool = False

    def __init__(
        self,
        dynamics: HeldInputModel,
        outputs: OutputModel,
        *,
        x0,
        P0,
        gate: float | None = None,
        robust=None,
        lockout: LockOut | None = None,
        measurements=None,
    ) -> None:
        if not isinstance(dynamics, HeldInputModel):
            raise QuadobsError(
                f"dynamics: expected a HeldInputModel, got {type(dynamics).__name__}"
            )
        if not isinstance(outputs, OutputModel):
            raise QuadobsError(f"outputs: expected an OutputModel, got {type(outputs).__name__}")
        if outputs.system.n != dynamics.system.n:
            raise QuadobsError(
                f"outputs: state dimension {outputs.system.n} differs from the dynamics' {dynamics.system.n}"
            )
        n = dynamics.system.n
        self.dynamics, self.outputs = dynamics, outputs
        self.n, self.q = n, outputs.system.q
        self._x = as_array("x0", x0, (n,)).copy()
        self._P = as_covariance("P0", P0, n, definite=False).copy()
        self.gate = None if gate is None else as_finite_scalar("gate", gate, positive=True)
        self.nis = float("nan")
        self.nis_dof = 0
        self.corrections = 0
        self.rejected = 0
        self._pending = 0
        self._powers: dict[int, tuple[np.ndarray, np.ndarray]] = {0: (np.eye(n), np.zeros((n, n)))}
        self._F, self._G = dynamics.F, dynamics.G
        self.measurement_models = measurement_models(dynamics.system, measurements)
        self._intervals: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._time = 0.0
        # Robust corrections and lock-out (:mod:`quadobs.estimators.robust`).
        self.robust = robust
        self.lockout = lockout if lockout is not None else LockOut()
        self._P0 = self._P.copy()
        self._latest = np.full(self.q, np.nan)  # the latest value of each output

    # -- estimator interface -----------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        """The estimate ``(n,)`` (a copy)."""
        return self._x.copy()

    @property
    def x_covariance(self) -> np.ndarray:
        """Its covariance ``(n, n)`` (a copy)."""
        self._settle()
        return self._P.copy()

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Update with ``y`` (outputs at the start of the step), then predict over the step with ``u`` held.

        A non-finite ``u``, an infinite ``y`` or a wrong shape raises :class:`QuadobsError`
        and leaves the filter unchanged.
        """
        u, y = step_operands(u, y, self._G.shape[1], self.q)
        self.correct_outputs(y)
        self.predict_step(u)
        self._time += self.dynamics.dt

    def predict_step(self, u: np.ndarray) -> None:
        """Exact mean prediction over one step ``x = F x + G u``; the covariance follows lazily.

        The second half of :meth:`step`; leaves :attr:`time` as it is.
        """
        self._x = self._F @ self._x + self._G @ np.asarray(u, dtype=float)
        self._pending += 1

    def correct_outputs(self, y: np.ndarray) -> None:
        """Update with the outputs present in ``y`` (NaN marks a missing sample).

        The first half of :meth:`step`; leaves :attr:`time` as it is.
        """
        y = np.asarray(y, dtype=float)
        present = ~np.isnan(y)
        if not present.any():
            self.nis, self.nis_dof = float("nan"), 0
            return
        idx = np.flatnonzero(present) if not present.all() else slice(None)
        self._latest[idx] = y[idx]
        self._settle()
        R = self.outputs.R if isinstance(idx, slice) else self.outputs.R[np.ix_(idx, idx)]
        self._correct_rows(y[idx], idx, R)

    def _correct_rows(self, y: np.ndarray, idx, R: np.ndarray) -> None:
        """Correct with the outputs ``idx`` (indices, or ``slice(None)``: all) of values ``y`` and
        noise ``R``, the one place where outputs of one time are corrected by (a grid step's,
        :meth:`correct_outputs`, and a batch of ranges, :meth:`correct_many`).

        Without a rule (no :attr:`gate`, no :attr:`robust`): one joint correction. With one, and
        uncorrelated noise: one scalar correction after the other, each output judged on its own
        with one degree of freedom, as a measurement at its own time is. A consistent filter's
        joint NIS of ``k`` outputs follows ``chi^2(k)``: the gate 10.83 (``P = 0.999`` for one
        output) would reject 1.3 % of its rounds of 3 ranges and 21 % of those of 8, not 0.1 %,
        and one outlier would take the other outputs of its time with it. The recorded
        :attr:`nis` is then the sum of the scalar corrections' NIS (rejected ones included) with
        :attr:`nis_dof` ``= k``: for a linear model, the joint NIS itself (the sequential
        innovations are independent, ``nu^T S^-1 nu = sum_i nu_i^2 / s_i``). Correlated noise
        cannot be split: one joint correction, gated at the quantile of ``chi^2(k)`` of the
        gate's probability (:meth:`gate_threshold`)."""
        z = self.outputs.measure(y, idx)
        k = z.shape[0]
        if (
            (self.robust is not None or self.gate is not None)
            and k > 1
            and np.count_nonzero(R - np.diag(np.diag(R))) == 0
        ):
            rows = np.arange(self.q)[idx]
            total = 0.0
            for i in range(k):
                self._update(z[i : i + 1], rows[i : i + 1], R[i : i + 1, i : i + 1])
                total += self.nis
            self.nis, self.nis_dof = total, k
            return
        self._update(z, idx, R)

    def gate_threshold(self, dof: int) -> float:
        """The NIS threshold of a joint correction of ``dof`` outputs: :attr:`gate` for one (the
        gate is stated per output), else the quantile of ``chi^2(dof)`` of the same probability,
        ``P = P(chi^2(1) <= gate) = erf(sqrt(gate / 2))`` (e.g. 10.83 -> ``P = 0.999`` -> 13.82
        for two outputs); ``inf`` without a gate."""
        return math.inf if self.gate is None else gate_quantile(self.gate, dof)

    # -- the interface in time ---------------------------------------------------------

    def _input_dimension(self) -> int:
        return self._G.shape[1]

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        """Exact prediction over ``dt`` with ``u`` held: the step's own map when ``dt`` is its step
        (within ``1e-9`` relative), else :meth:`HeldInputModel.over` (cached by ``dt``)."""
        if abs(dt - self.dynamics.dt) <= 1e-9 * self.dynamics.dt:
            self.predict_step(u)
            return
        self._settle()
        hit = self._intervals.get(dt)
        if hit is None:
            hit = self.dynamics.over(dt)
            if len(self._intervals) < 256:
                self._intervals[dt] = hit
        F, G, Q = hit
        self._x = F @ self._x + G @ u
        P = F @ self._P @ F.T + Q
        self._P = 0.5 * (P + P.T)

    def _correct_measurement(self, m: Measurement) -> None:
        """A range of the system's anchors goes through the filter's own output space (the
        arithmetic of :meth:`correct_outputs` with that output alone; its variance ``m.std^2``, or
        ``R_hh`` when ``m`` has none); any other kind through its model's ``h`` and Jacobian on the
        position (:meth:`_update_model`), with variance ``model.sigma(m)^2``."""
        model = self._model_of(m)
        self._settle()
        if model.kind != "range":
            s = model.sigma(m)
            self._update_model(m, model, np.array([[s * s]]))
            return
        h, yh, var = model.quadratic_output(m)
        self._latest[h] = yh
        idx = np.array([h])
        if math.isnan(m.std):
            R = self.outputs.R[np.ix_(idx, idx)]
        else:
            R = np.array([[m.std**2 if self.outputs.space == "norm" else var]])
        self._update(self.outputs.measure(np.array([yh]), idx), idx, R)

    def _update_model(self, m: Measurement, model: MeasurementModel, R: np.ndarray) -> None:
        """Update with one measurement through ``model.h`` on the position ``x[:d]``."""
        raise NotImplementedError  # pragma: no cover - interface

    def correct_many(self, measurements) -> None:
        """Ranges of the system's anchors taken at the current time, one per anchor: ONE joint
        correction by the vector of them, the arithmetic of :meth:`correct_outputs` with those
        outputs present (each range's variance ``m.std^2``, or ``R_hh`` when it states none, as in
        :meth:`correct`). Anything else (another kind, two ranges of one anchor, a single
        measurement), and any batch while a start-up waits for its fix (:attr:`fix_pending`),
        one measurement after the other (:meth:`Estimator.correct_many`).

        With a ``gate`` or a robust rule, ranges of uncorrelated noise are corrected one after
        the other, each gated alone, as a grid step's outputs are (:meth:`_correct_rows`)."""
        measurements = list(measurements)
        joint = None if self.fix_pending else self._joint_outputs(measurements)
        if joint is None:
            super().correct_many(measurements)
            return
        idx, y, R = joint
        self._latest[idx] = y
        self._settle()
        self._correct_rows(y, idx, R)

    def _joint_outputs(self, measurements: list):
        """``(idx, y, R)``: the anchors (ascending), quadratic outputs and noise of ranges one per
        anchor, each checked as :meth:`correct` checks it; ``None`` when they are not such a batch."""
        if len(measurements) < 2:
            return None
        rows = []
        for m in measurements:
            self._check_measurement(m)
            model = self._model_of(m)
            if model.kind != "range":
                return None
            h, yh, var = model.quadratic_output(m)
            s2 = m.std**2 if self.outputs.space == "norm" else var
            rows.append((h, yh, math.nan if math.isnan(m.std) else s2))
        rows.sort(key=lambda r: r[0])
        idx = np.array([r[0] for r in rows])
        if np.any(np.diff(idx) == 0):
            return None
        R = self.outputs.R[np.ix_(idx, idx)].copy()
        for k, (_, _, s2) in enumerate(rows):
            if not math.isnan(s2):
                R[k, :] = 0.0
                R[:, k] = 0.0
                R[k, k] = s2
        return idx, np.array([r[1] for r in rows]), R

    # -- internals ---------------------------------------------------------------------

    def _power(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        """``(F^m, Q_m)`` (:func:`step_power`), cached by ``m``."""
        hit = self._powers.get(m)
        if hit is None:
            hit = step_power(self._F, self.dynamics.Q, m)
            if len(self._powers) < 256:
                self._powers[m] = hit
        return hit

    def _settle(self) -> None:
        m = self._pending
        if m:
            Fm, Qm = self._power(m)
            P = Fm @ self._P @ Fm.T + Qm
            self._P = 0.5 * (P + P.T)
            self._pending = 0

    def _accept(self, nu: np.ndarray, S: np.ndarray) -> tuple[bool, np.ndarray]:
        """NIS of the innovation, and whether the gate lets the update through; returns ``S^-1 nu``."""
        try:
            Sinv_nu = np.linalg.solve(S, nu)
        except np.linalg.LinAlgError:
            Sinv_nu = np.linalg.lstsq(S, nu, rcond=None)[0]
        self.nis = float(nu @ Sinv_nu)
        self.nis_dof = int(nu.shape[0])
        if self.gate is not None and self.nis > self.gate_threshold(self.nis_dof):
            self.rejected += 1
            self._watch(False, nu)
            return False, Sinv_nu
        self.corrections += 1
        self._watch(True, nu)
        return True, Sinv_nu

    @property
    def diverged(self) -> dict | None:
        """``None``, or the time, step and reason at which the filter was given up (:class:`~quadobs.estimators.robust.LockOut`)."""
        return self.lockout.diverged

    def uninformed(self) -> dict | None:
        """``None``, or the record of a filter that took corrections and still ends with a
        position spread wider than its prior's, ``sqrt(tr P_pp) > sqrt(tr P0_pp)`` (``p`` the
        first ``dim`` states): its measurements never informed it, whatever its gate accepted.
        The UKF's transform of a range over sigma points farther apart than the anchors is
        flat (``P_xz ~ 0``, :class:`UnscentedKalmanFilter`): each range is accepted at a small
        NIS while the velocity's prior is never reduced and ``P_pp`` grows with it.
        ``{"position_spread", "prior_spread"}`` (m) and ``corrections``."""
        if self.corrections == 0:
            return None
        d = self.outputs.system.p
        P = self.x_covariance
        spread = math.sqrt(float(np.trace(P[:d, :d])))
        prior = math.sqrt(float(np.trace(self._P0[:d, :d])))
        if not spread > prior:
            return None
        return {"position_spread": spread, "prior_spread": prior, "corrections": self.corrections}

    def _robust(self, nu: np.ndarray, S: np.ndarray, R: np.ndarray):
        """``(S, R)`` re-weighted by :attr:`robust`, or ``None`` when it rejects the correction."""
        if self.robust is None:
            return S, R
        R_w = reweight(self.robust, nu, S, R)
        if R_w is None:
            self.nis = float(nu @ np.linalg.solve(S, nu))
            self.nis_dof = int(nu.shape[0])
            self.rejected += 1
            self._watch(False, nu)
            return None
        return (S, R) if R_w is R else (S + (R_w - R), R_w)

    def _gain(self, nu: np.ndarray, S: np.ndarray, R: np.ndarray, cross: np.ndarray):
        """The gain of a correction with innovation ``nu``, its covariance ``S``, the outputs' ``R``
        and the state-output cross-covariance ``cross`` (``P H^T``, ``P_xz``).

        The robust rule re-weights ``(S, R)`` (:meth:`_robust`) and the gate judges the NIS
        (:meth:`_accept`); when both let the correction through, the gain is the optimal
        ``K = cross S^-1`` as :meth:`_shape_gain` shapes it, and the mean moves, ``x += K nu``.
        Returns ``(K, S, R, optimal)`` (``S``, ``R`` re-weighted; ``optimal`` whether ``K`` is
        the optimal gain itself) for the covariance's update, or ``None`` when the correction is
        refused.
        """
        robust = self._robust(nu, S, R)
        if robust is None:
            return None
        S, R = robust
        ok, _ = self._accept(nu, S)
        if not ok:
            return None
        K_opt = np.linalg.solve(S, cross.T).T
        K = self._shape_gain(K_opt, nu, S)
        self._x = self._x + K @ nu
        return K, S, R, K is K_opt

    def _watch(self, accepted: bool, nu: np.ndarray) -> None:
        """Lock-out: re-initialise the covariance, or give the filter up (see :mod:`~quadobs.estimators.robust`)."""
        lock, t = self.lockout, self._time
        if not lock.observe(t, accepted, float(np.max(np.abs(nu)))):
            return
        span = lock.span(t)
        reason = lock.reason(t)
        largest, dim = lock.largest, self.outputs.system.p
        if lock.reset(t, int(round(t / self.dynamics.dt)), reason):
            self._P = reinitialised_covariance(self._P, self._P0, largest, dim, span)
            system = self.outputs.system
            fixed = multilateration(system.C, system.d, self._latest, centred=True)
            if fixed is not None:
                self._x[fixed[0]] = fixed[1]

    def _update(self, z: np.ndarray, idx, R: np.ndarray) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _shape_gain(self, K: np.ndarray, nu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """The gain the update uses, given the optimal one ``K`` for the innovation ``nu`` with
        covariance ``S``: ``K`` itself (a subclass may zero rows of states that must not take this
        correction; the covariance update then follows the gain used)."""
        return K


class ExtendedKalmanFilter(_GaussianFilter):
    """EKF on ``x``: exact held-input prediction, update linearised at the predicted estimate.

    Parameters
    ----------
    dynamics : HeldInputModel
    outputs : OutputModel
    x0 : array_like (n,)
        Initial estimate.
    P0 : float or array_like
        Initial covariance (scalar times ``I_n``, diagonal or ``(n, n)``), positive semidefinite.
    gate : float, optional
        Reject an update whose NIS exceeds ``gate`` (counted in :attr:`rejected`): a threshold
        for one output, the quantile of ``chi^2(1)`` of the probability ``P`` it keeps (10.83
        for ``P = 0.999``). Outputs of one time with uncorrelated noise are gated each alone
        (:meth:`_correct_rows`); a joint correction of ``k`` correlated ones at the
        ``chi^2(k)`` quantile of the same ``P`` (:meth:`gate_threshold`).

    Notes
    -----
    Update (Joseph form), with ``H = dh/dx`` at the predicted ``x``:
    ``S = H P H^T + R``, ``K = P H^T S^-1``, ``x += K (z - h(x))``,
    ``P = (I - K H) P (I - K H)^T + K R K^T``.
    """

    name = "ekf"

    def _update(self, z: np.ndarray, idx, R: np.ndarray) -> None:
        z_pred, H = self.outputs.linearize(self._x)
        self._joseph(z - z_pred[idx], H[idx], R)

    def _update_model(self, m: Measurement, model: MeasurementModel, R: np.ndarray) -> None:
        d = model.dimension
        H = np.zeros((1, self.n))
        H[0, :d] = model.jacobian(self._x[:d], m)
        self._joseph(np.array([model.unbiased(m) - model.h(self._x[:d], m)]), H, R)

    def _joseph(self, nu: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        P = self._P
        PHt = P @ H.T
        gain = self._gain(nu, H @ PHt + R, R, PHt)
        if gain is None:
            return
        K, _, R, _ = gain
        IKH = np.eye(self.n) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        self._P = 0.5 * (P + P.T)


class UnscentedKalmanFilter(_GaussianFilter):
    """UKF on ``x``: exact held-input prediction, update through the scaled unscented transform.

    Parameters
    ----------
    dynamics, outputs
        As for :class:`ExtendedKalmanFilter`.
    alpha, beta, kappa : float
        Scaled unscented transform parameters (see the module docstring); defaults
        ``1, 2, 0``.
    **kwargs
        The keywords of :class:`ExtendedKalmanFilter` (``x0``, ``P0``, ``gate``, ``robust``,
        ``lockout``, ``measurements``), with their meanings.

    Notes
    -----
    Sigma points ``X_0 = x``, ``X_{i}, X_{n+i} = x +- sqrt(n + lambda) L_{:, i}`` with
    ``L`` the lower Cholesky factor of ``P`` (a symmetric eigen-square-root if ``P`` is only
    semidefinite); ``Z_i = h(X_i)``, ``z^- = sum W^m_i Z_i``,
    ``S = sum W^c_i (Z_i - z^-)(Z_i - z^-)^T + R``, ``P_xz = sum W^c_i (X_i - x)(Z_i - z^-)^T``,
    ``K = P_xz S^-1``, ``x += K (z - z^-)``, ``P -= K S K^T``.
    """

    name = "ukf"

    def __init__(
        self,
        dynamics: HeldInputModel,
        outputs: OutputModel,
        *,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        **kwargs,
    ) -> None:
        super().__init__(dynamics, outputs, **kwargs)
        n = self.n
        self.alpha = as_finite_scalar("alpha", alpha, positive=True)
        self.beta = as_finite_scalar("beta", beta)
        self.kappa = as_finite_scalar("kappa", kappa)
        lam = self.alpha**2 * (n + self.kappa) - n
        if not n + lam > 0:
            raise QuadobsError(
                f"alpha, kappa: need alpha^2 (n + kappa) > 0, got {n + lam:.3g} for n = {n}"
            )
        self._scale = float(np.sqrt(n + lam))
        wm = np.full(2 * n + 1, 0.5 / (n + lam))
        wm[0] = lam / (n + lam)
        wc = wm.copy()
        wc[0] += 1.0 - self.alpha**2 + self.beta
        self._wm, self._wc = wm, wc

    def sigma_points(self) -> np.ndarray:
        """The ``(2 n + 1, n)`` sigma points of the current ``(x, P)``."""
        self._settle()
        return self._sigma(self._x, self._P)

    def _sigma(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        try:
            L = np.linalg.cholesky(P)
        except np.linalg.LinAlgError:
            w, U = np.linalg.eigh(P)
            L = U * np.sqrt(np.maximum(w, 0.0))
        D = self._scale * L.T
        return np.concatenate([x[None], x + D, x - D])

    def _update(self, z: np.ndarray, idx, R: np.ndarray) -> None:
        X = self._sigma(self._x, self._P)
        self._unscented(z, X, self.outputs.predict(X)[:, idx], R)

    def _update_model(self, m: Measurement, model: MeasurementModel, R: np.ndarray) -> None:
        X = self._sigma(self._x, self._P)
        d = model.dimension
        Z = np.array([[model.h(X[i, :d], m)] for i in range(X.shape[0])])
        self._unscented(np.array([model.unbiased(m)]), X, Z, R)

    def _unscented(self, z: np.ndarray, X: np.ndarray, Z: np.ndarray, R: np.ndarray) -> None:
        x, P = self._x, self._P
        z_pred = self._wm @ Z
        dZ = Z - z_pred
        dX = X - x
        S = (dZ.T * self._wc) @ dZ + R
        Pxz = (dX.T * self._wc) @ dZ
        gain = self._gain(z - z_pred, S, R, Pxz)
        if gain is None:
            return
        K, S, _, optimal = gain
        if optimal:
            P = P - K @ S @ K.T
        else:  # any other gain: P - K Pxz^T - Pxz K^T + K S K^T
            P = P - K @ Pxz.T - Pxz @ K.T + K @ S @ K.T
        self._P = 0.5 * (P + P.T)
