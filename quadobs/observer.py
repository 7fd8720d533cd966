"""The Kalman-type observer of Theorem 3 (``000_f34cd1199256bdad.txt``) on the augmented system.

Theorem 3 (Besançon 2007) for ``z' = A(u) z + B u``, ``y = C z``:

.. math::

    \\dot{\\hat z} = A(u)\\hat z + B u + K (y - C \\hat z), \\quad K = M C^\\top W^{-1}, \\\\
    \\dot M = A(u) M + M A(u)^\\top - M C^\\top W^{-1} C M + V + \\theta M .

It is run here as a continuous-discrete filter, one call of :meth:`AugmentedObserver.step`
per physics step: first the correction with the output sampled at the start of the step
(skipped, output by output, where the sample is missing: NaN), then the exact prediction
over the step with the input held (:class:`~quadobs.discretize.HeldInputDiscretization`).
The correction uses the Joseph form ``P = (I - K C) P (I - K C)^T + K R K^T`` with
``R = W / T`` (``T`` the sampling period of the output), and the covariance is
re-symmetrised after every operation, so it stays symmetric positive definite. For a
noise-free system whose initial estimate is exact, the estimate stays exact to rounding.
"""

from __future__ import annotations

import numpy as np

from .discretize import HeldInputDiscretization, as_covariance
from .errors import QuadobsError, as_array, as_finite_scalar
from .immersion import Immersion

__all__ = ["Estimator", "AugmentedObserver"]


class Estimator:
    """What the testbed needs from a state estimator.

    ``step(u, y)`` consumes the output sampled at the start of a physics step (``(q,)``,
    NaN where missing) and the input held over the step (``(p,)``), and leaves the
    estimate at the end of the step in :attr:`x_hat`. :attr:`x_covariance` is ``None`` for
    estimators without one.
    """

    name: str = "estimator"

    def step(self, u: np.ndarray, y: np.ndarray) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    @property
    def x_hat(self) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    @property
    def x_covariance(self) -> np.ndarray | None:
        return None


class AugmentedObserver(Estimator):
    """Theorem 3's observer on an immersion, advanced one held-input step at a time.

    Parameters
    ----------
    immersion : Immersion
        From :func:`quadobs.immerse`.
    dt : float
        Physics step (s): the estimate advances by ``dt`` per :meth:`step`.
    V : float or array_like
        Continuous process-noise intensity (scalar times ``I_N``, diagonal, or ``(N, N)``).
    W : float or array_like
        Continuous output-noise intensity (scalar times ``I_q``, diagonal, or ``(q, q)``),
        positive definite.
    S0 : float or array_like
        Initial covariance ``M_0`` (scalar times ``I_N``, diagonal, or ``(N, N)``).
    theta : float
        Forgetting factor (``theta >= 0``).
    x0 : array_like (n,), optional
        Initial estimate of ``x``; the augmented estimate starts at ``lift(x0)``. Default zero.
    z0 : array_like (N,), optional
        Initial augmented estimate (overrides ``x0``).
    sample_period : float or array_like (q,), optional
        Period ``T_h`` of the samples of each output (s), default ``dt``; the discrete
        output covariance is ``R_hl = W_hl / sqrt(T_h T_l)`` (``R = W / T`` for one rate).
    gate : float, optional
        Reject a correction whose normalised innovation squared exceeds ``gate``
        (a chi-square quantile for ``q`` degrees of freedom); counted in :attr:`rejected`.

    Notes
    -----
    The paper's example (section 6) uses ``S_0 = 100 I``, ``V = 1e-4 I``, ``W = I`` and
    writes ``I_6``; the augmented state there has ``N = 9`` entries and the output is
    scalar, so the scenario ``ifac2021`` reads them as ``S_0 = 100 I_9``,
    ``V = 1e-4 I_9`` and ``W = 1``.
    """

    name = "augmented"

    def __init__(
        self,
        immersion: Immersion,
        dt: float,
        *,
        V=1e-4,
        W=1.0,
        S0=100.0,
        theta: float = 0.0,
        x0=None,
        z0=None,
        sample_period: float | None = None,
        gate: float | None = None,
    ) -> None:
        if not isinstance(immersion, Immersion):
            raise QuadobsError(f"immersion: expected an Immersion, got {type(immersion).__name__}")
        self.immersion = immersion
        self.model = HeldInputDiscretization(immersion, dt, V, theta)
        N, q, n = immersion.dim, immersion.system.q, immersion.system.n
        if sample_period is None:
            period = np.full(q, self.model.dt)
        else:
            period = as_array("sample_period", sample_period)
            if period.ndim == 0:
                period = np.full(q, float(period))
            elif period.shape != (q,):
                raise QuadobsError(f"sample_period: expected a scalar or shape ({q},), got {period.shape}")
            if np.any(period <= 0):
                raise QuadobsError("sample_period: must be positive")
        self.W = as_covariance("W", W, q)
        scale = 1.0 / np.sqrt(period)
        self.R = self.W * np.outer(scale, scale)
        if z0 is not None:
            z = as_array("z0", z0, (N,))
        else:
            z = immersion.lift(np.zeros(n) if x0 is None else as_array("x0", x0, (n,)))
        self.z = z.copy()
        self.P = as_covariance("S0", S0, N).copy()
        self.gate = None if gate is None else as_finite_scalar("gate", gate, positive=True)
        self.rejected = 0
        self.corrections = 0
        self.nis = float("nan")
        self._C = immersion.output_matrix
        self._eye = np.eye(N)
        self._k = immersion.n_aux
        m = self.model
        self._growth = float(np.exp(m.theta * m.dt))
        self._F0, self._F1 = m.transition_constant, m.transition_input
        self._G0, self._G2 = m.input_linear, m.input_quadratic
        self._Q0, self._Q1, self._Q2 = m.noise_constant, m.noise_linear, m.noise_quadratic
        self._Phi = self._F0.copy()

    # -- estimator interface -----------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        return self.z[self._k :]

    @property
    def x_covariance(self) -> np.ndarray:
        k = self._k
        return self.P[k:, k:]

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Correct with ``y`` (output at the start of the step), then predict over the step with ``u`` held."""
        self.correct(y)
        self.predict(u)

    # -- the two halves ----------------------------------------------------------------

    def correct(self, y: np.ndarray) -> None:
        """Kalman correction with the outputs present in ``y`` (NaN marks a missing sample)."""
        y = np.asarray(y, dtype=float)
        present = ~np.isnan(y)
        if not present.any():
            self.nis = float("nan")
            return
        if present.all():
            C, R, yv = self._C, self.R, y
        else:
            C, R, yv = self._C[present], self.R[np.ix_(present, present)], y[present]
        P, z = self.P, self.z
        PCt = P @ C.T
        S = C @ PCt + R
        nu = yv - C @ z
        Sinv_nu = np.linalg.solve(S, nu)
        self.nis = float(nu @ Sinv_nu)
        if self.gate is not None and self.nis > self.gate:
            self.rejected += 1
            return
        K = np.linalg.solve(S, PCt.T).T
        self.z = z + K @ nu
        IKC = self._eye - K @ C
        P = IKC @ P @ IKC.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        self.corrections += 1

    def predict(self, u: np.ndarray) -> None:
        """Exact propagation over one step with ``u`` held (``P`` with ``Q_d(u)`` and forgetting)."""
        u = np.asarray(u, dtype=float)
        k = self._k
        Phi = self._Phi
        Phi[:k, k:] = self._F0[:k, k:] + np.tensordot(u, self._F1, axes=(0, 0))
        z = Phi @ self.z
        z[:k] += np.tensordot(u, self._G2, axes=(0, 0)) @ u
        z[k:] += self._G0 @ u
        self.z = z
        Q = self._Q0 + np.tensordot(u, self._Q1, axes=(0, 0)) + np.tensordot(np.outer(u, u), self._Q2, axes=((0, 1), (0, 1)))
        P = self._growth * (Phi @ self.P @ Phi.T) + Q
        self.P = 0.5 * (P + P.T)
