"""The augmented observer with a range bias per anchor as a state (:mod:`quadobs.core.range_bias`).

Theorem 3's Kalman-like observer [IFAC2021, Thm. 3] on ``zeta = (z, b, c)``: the
immersion's state, the per-anchor biases and their squares. Each range is one scalar
correction at its own time with the output row ``C_h(rho_h) = [C_h | rho_h e_h | -e_h/2]``
(the measured range is its coefficient) and the output ``y_h = rho_h^2/2 - |a_h|^2/2 -
sigma^2/2``, with ``R_h = sigma^2 rho_h^2 + sigma^4/2`` from the stated range noise
``sigma`` (the derivation is in :mod:`quadobs.core.range_bias`):

.. math::

    S = C_h P C_h^\\top + R_h, \\quad K = P C_h^\\top / S, \\quad
    \\zeta \\mathrel{+}= K (y_h - C_h \\zeta), \\quad
    P = (I - K C_h) P (I - K C_h)^\\top + K R_h K^\\top .

Between measurements ``zeta`` and ``P`` follow the exact held-input map
(:class:`~quadobs.core.held_input.HeldInputDiscretization` on a physics step,
:meth:`~quadobs.core.range_bias.BiasedRangeImmersion.transition` over any other interval),
``P`` grown by ``e^{theta tau}`` as in Theorem 3. The estimate of ``x`` is the ``x`` block
of ``zeta``, the biases its ``b`` block (:attr:`BiasedAugmentedObserver.biases`).

Being linear in ``zeta``, the observer converges from any initial guess once the motion
excites the bias columns (:func:`~quadobs.core.range_bias.excitation_gramian`); an optional
robust rule (:mod:`quadobs.estimators.robust`) re-weights or gates each range.
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np

from quadobs.core.held_input import HeldInputDiscretization, as_covariance
from quadobs.core.immersion import Immersion
from quadobs.core.measurements import RANGE_BIAS_PRIOR_STD, Measurement
from quadobs.core.range_bias import BiasedRangeImmersion
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.base import Estimator, Gated, Immersed, step_operands
from quadobs.estimators.robust import reweight

__all__ = ["BiasedAugmentedObserver"]


class BiasedAugmentedObserver(Estimator, Gated, Immersed):
    """Theorem 3's observer with per-anchor range biases as states (see the module docstring).

    Parameters
    ----------
    immersion : Immersion
        Of a range system (:func:`quadobs.core.system.vehicle_system`); its outputs are the anchors.
    dt : float
        The physics step (s): :meth:`step` and the fast path of :meth:`predict`.
    sigma : float
        Standard deviation of one range (m).
    V : float or array_like
        Process-noise intensity on the immersion's state ``z`` (as for the augmented observer).
    P0 : float or array_like
        Initial covariance of ``z``.
    bias_std : float
        Prior standard deviation of each bias (m); its square's prior is ``3 bias_std^2``.
    squares : bool
        Carry ``c_h = b_h^2`` as states (the exact form, not uniformly observable: see
        :mod:`quadobs.core.range_bias`) instead of the tangent at the estimate (default).
    bias_walk : float
        Random-walk intensity of the biases (m^2/s); 0 for constant biases.
    theta : float
        Forgetting factor of Theorem 3.
    x0 : array_like (n,), optional
        Initial estimate (biases start at zero).
    robust : ChiSquareGate, Huber or None
        Robust rule on each range.
    """

    name = "augmented-bias"
    #: The biases' prior standard deviation (m) when none is given
    #: (:data:`~quadobs.core.measurements.RANGE_BIAS_PRIOR_STD`).
    DEFAULT_BIAS_STD = RANGE_BIAS_PRIOR_STD

    def __init__(
        self,
        immersion: Immersion,
        dt: float,
        *,
        sigma: float,
        V=1e-4,
        P0=100.0,
        bias_std: float = DEFAULT_BIAS_STD,
        squares: bool = False,
        bias_walk: float = 0.0,
        theta: float = 0.0,
        x0=None,
        robust=None,
    ) -> None:
        if not isinstance(immersion, Immersion):
            raise QuadobsError(f"immersion: expected an Immersion, got {type(immersion).__name__}")
        self.ext = ext = BiasedRangeImmersion(immersion, squares)
        self.immersion = immersion
        N, n, m = immersion.dim, immersion.system.n, ext.m
        self.sigma = as_finite_scalar("sigma", sigma, positive=True)
        self.bias_walk = as_finite_scalar("bias_walk", bias_walk, nonnegative=True)
        s = as_finite_scalar("bias_std", bias_std, positive=True)
        self.model = HeldInputDiscretization(immersion, dt, V, theta)
        self.dt, self.theta = self.model.dt, self.model.theta
        self._V = cast(np.ndarray, self.model.V)  # an array once the discretization is built
        d = immersion.system.d
        self._offsets = 0.5 * np.einsum("hi,hi->h", d, d)  # |a_h|^2 / 2 (d_h = (-a_h, 0))
        x = np.zeros(n) if x0 is None else as_array("x0", x0, (n,))
        self._zeta = ext.lift(x)
        P = np.zeros((ext.dim, ext.dim))
        P[:N, :N] = as_covariance("P0", P0, N)
        P[N : N + m, N : N + m] = s**2 * np.eye(m)
        if ext.squares:
            P[N + m :, N + m :] = (3.0 * s**2) ** 2 * np.eye(m)
        self._P = P
        self.robust = robust
        self.gate = None
        self.time = 0.0
        self._u = np.zeros(immersion.system.p)
        self.nis = float("nan")
        self.corrections = self.rejected = 0

    # -- the estimator interface -----------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        return self.ext.project(self._zeta).copy()

    @property
    def x_covariance(self) -> np.ndarray:
        k = self.immersion.n_aux
        N = self.immersion.dim
        return self._P[k:N, k:N].copy()

    @property
    def biases(self) -> np.ndarray:
        """The estimated per-anchor biases ``(m,)`` (m)."""
        return self.ext.biases(self._zeta).copy()

    @property
    def zeta(self) -> np.ndarray:
        """The whole estimate ``(z, b, c)`` (a copy)."""
        return self._zeta.copy()

    def hold(self, u: np.ndarray) -> None:
        """Hold the input ``u (p,)`` from the current time on."""
        self._u = as_array("u", u, self._u.shape).copy()

    def predict(self, t: float) -> None:
        """Propagate to time ``t`` (s) with the held input (exact)."""
        tau = float(t) - self.time
        if not math.isfinite(tau) or tau < 0.0:
            raise QuadobsError(f"t: cannot predict back from {self.time} s to {t} s")
        if tau == 0.0:
            return
        if abs(tau - self.dt) <= 1e-12 * self.dt:
            Phi, g, Q = self._step_map(self._u)
        else:
            Phi, g, Q = self.ext.transition(self._u, tau, self._V, self.bias_walk)
        grow = math.exp(self.theta * tau)
        self._zeta = Phi @ self._zeta + g
        P = grow * (Phi @ self._P @ Phi.T) + Q
        self._P = 0.5 * (P + P.T)
        self.time = float(t)

    def _step_map(self, u: np.ndarray):
        """``(Phi, g, Q)`` over one physics step from the precomputed held-input coefficients."""
        N, m, D = self.immersion.dim, self.ext.m, self.ext.dim
        Phi, Q, g = np.eye(D), np.zeros((D, D)), np.zeros(D)
        Phi[:N, :N] = self.model.transition(u)
        Q[:N, :N] = self.model.process_noise(u)
        Q[N : N + m, N : N + m] = self.bias_walk * self.dt * np.eye(m)
        g[:N] = self.model.input_term(u)
        return Phi, g, Q

    def correct(self, m: Measurement) -> None:
        """One range ``m`` (kind ``"range"``, ``anchors = (h,)``, ``value = rho``) at the current time."""
        if m.kind != "range":
            raise QuadobsError(f"{self.name}: takes ranges, got a {m.kind!r} measurement")
        sigma = self.sigma if math.isnan(m.std) else float(m.std)
        self._correct(int(m.anchors[0]), float(m.value), sigma)

    def _correct(self, h: int, rho: float, sigma: float) -> None:
        row, y = self.ext.measurement(h, rho, self._zeta)
        y -= 0.5 * sigma * sigma
        R = np.array([[sigma * sigma * rho * rho + 0.5 * sigma**4]])
        P = self._P
        Pc = P @ row
        S = np.array([[row @ Pc + R[0, 0]]])
        nu = np.array([y - row @ self._zeta])
        self.nis = float(nu[0] ** 2 / S[0, 0])
        R_w = reweight(self.robust, nu, S, R)
        if R_w is None:
            self.rejected += 1
            return
        s = row @ Pc + R_w[0, 0]
        K = Pc / s
        self._zeta = self._zeta + K * nu[0]
        IKC = np.eye(P.shape[0]) - np.outer(K, row)
        P = IKC @ P @ IKC.T + R_w[0, 0] * np.outer(K, K)
        self._P = 0.5 * (P + P.T)
        self.corrections += 1

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Fixed-grid shorthand: each present output ``y_h = rho_h^2/2 - |a_h|^2/2`` as a range
        at the current time, then :meth:`predict` over one step with ``u`` held."""
        u, y = step_operands(u, y, self._u.shape[0], self.ext.m)
        for h in np.flatnonzero(~np.isnan(y)):
            rho = math.sqrt(max(2.0 * (float(y[h]) + self._offsets[h]), 0.0))
            self._correct(int(h), rho, self.sigma)
        self._u = np.array(u, dtype=float)
        self.predict(self.time + self.dt)
