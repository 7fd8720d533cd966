"""A Kalman-type observer for TDOA on the immersion of :mod:`quadobs.core.tdoa`.

The augmented state ``z = (xi, x)`` of :class:`~quadobs.core.tdoa.TdoaImmersion` follows
``z' = A(u) z + B u`` exactly, and each TDOA ``d_ij`` is a linear output ``c(d)^T z = y(d)``
whose row is known from the measurement. The observer is Theorem 3 of [IFAC2021] with this
time-varying ``C(t)``, run as a continuous-discrete Kalman filter:

.. math::

    z^- = \\Phi(u) z + g(u), \\quad P^- = \\Phi(u) P \\Phi(u)^\\top + Q_d, \\qquad
    K = P c / (c^\\top P c + R), \\quad z^+ = z + K (y - c^\\top z),

the prediction exact under the held input (:class:`~quadobs.core.held_input.HeldInputDiscretization`),
the correction in Joseph form, one scalar TDOA at a time.

Noise. ``R`` is the second-order variance of the relation's residual
(:func:`~quadobs.core.tdoa.relation_variance`) at the measured ``d`` and the ranges of the
current estimate (at least ``min_range``). ``Q_d = dt G(x) Q G(x)^T``: an acceleration
white noise of intensity ``accel_psd`` (m²/s³) mapped into ``z`` by
:func:`~quadobs.core.immersion.lift_jacobian` at the estimate (``G = J B``), plus ``V dt`` (a Theorem 3
tuning on ``z``, zero by default). The initial covariance is the lift of the prior
``N(x_0, P_0)`` (:func:`~quadobs.core.immersion.lifted_covariance`), so the auxiliary states
start with the spread the position prior implies.

Neither weight changes the fixed point: on noise-free data, started at the truth, the
estimate stays at the truth to rounding; started far, it converges whenever the rows
measured along the flight make the LTV pair uniformly observable (module docstring of
:mod:`quadobs.core.tdoa`).
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.core.held_input import HeldInputDiscretization, as_covariance
from quadobs.core.immersion import lift_jacobian, lifted_covariance
from quadobs.core.measurements import Measurement, TdoaModel
from quadobs.core.tdoa import TdoaImmersion, relation_variance
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.base import Estimator, Gated, check_step

__all__ = ["TdoaHandover", "TdoaObserver"]


class TdoaObserver(Estimator, Gated):
    """Theorem 3 of [IFAC2021] on the TDOA immersion (module docstring).

    Parameters
    ----------
    anchors : array_like (m, dim)
    dt : float
        The step of :meth:`step` and the grid :meth:`predict` advances on (s).
    x0 : array_like (2 dim,)
        Initial guess ``(p, v)``.
    P0 : float, (2 dim,) or (2 dim, 2 dim)
        Covariance of the initial guess of ``x``; lifted to ``z``.
    std : float
        Default standard deviation of one TDOA (m).
    accel_psd : float
        Intensity of the white acceleration noise (m²/s³): ``sigma_a^2 dt`` for an
        accelerometer of standard deviation ``sigma_a`` read every step ``dt`` and held,
        plus what the model misses; 0 (default) for an input known exactly.
    V : float, (N,) or (N, N)
        Additional process-noise intensity on ``z`` (Theorem 3's ``V``).
    pairs : sequence of (i, j), optional
        The outputs of :meth:`step`: ``y[h]`` is the TDOA of ``pairs[h]`` (NaN: not measured).
    min_range : float
        Floor of the estimated ranges in the noise of the relation (m).
    gate : float, optional
        Reject a TDOA whose normalised innovation squared exceeds it.
    """

    name = "tdoa-observer"

    def __init__(
        self,
        anchors,
        dt: float,
        x0,
        P0=25.0,
        std: float = 0.1,
        accel_psd: float = 0.0,
        V=0.0,
        pairs=(),
        min_range: float = 0.1,
        gate: float | None = None,
    ) -> None:
        self.model = TdoaImmersion(anchors)
        im = self.model.immersion
        self.dt = as_finite_scalar("dt", dt, positive=True)
        self.std = as_finite_scalar("std", std, positive=True)
        self.accel_psd = as_finite_scalar("accel_psd", accel_psd, nonnegative=True)
        self.min_range = as_finite_scalar("min_range", min_range, positive=True)
        self.gate = None if gate is None else as_finite_scalar("gate", gate, positive=True)
        n, N = im.system.n, im.dim
        x0 = as_array("x0", x0, (n,))
        Px = as_covariance("P0", P0, n)
        self.V = as_covariance("V", V, N, definite=False)
        self.pairs = tuple((int(i), int(j)) for i, j in pairs)
        m = self.model.anchors.shape[0]
        for i, j in self.pairs:
            if not (0 <= i < m and 0 <= j < m and i != j):
                raise QuadobsError(f"pairs: ({i}, {j}) is not two distinct anchors below {m}")
        self._steps: dict[float, HeldInputDiscretization] = {}
        #: The kind of measurement it takes (what a world asks before feeding it).
        self.measurement_models = {"tdoa": TdoaModel(self.model.anchors, self.std)}
        self._z = self.model.lift(x0)
        self._P = lifted_covariance(im.aux_forms, x0, Px)
        self.time = 0.0
        self.corrections = 0
        self.rejected = 0

    # -- state -----------------------------------------------------------------------------

    @property
    def z(self) -> np.ndarray:
        """The augmented estimate ``(xi, x)`` (a copy)."""
        return self._z.copy()

    @property
    def P(self) -> np.ndarray:
        """The augmented covariance (a copy)."""
        return self._P.copy()

    @property
    def x_hat(self) -> np.ndarray:
        return self._z[self.model.immersion.n_aux :].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        k = self.model.immersion.n_aux
        return self._P[k:, k:].copy()

    # -- time --------------------------------------------------------------------------------

    def _input_dimension(self) -> int:
        return self.model.immersion.system.p

    def _discretization(self, h: float) -> HeldInputDiscretization:
        key = round(h, 12)  # intervals equal to a picosecond share one discretisation
        step = self._steps.get(key)
        if step is None:
            step = HeldInputDiscretization(self.model.immersion, key if key > 0.0 else h)
            if key > 0.0 and len(self._steps) < 256:
                self._steps[key] = step
        return step

    def _advance(self, h: float, u: np.ndarray) -> None:
        step = self._discretization(h)
        Phi = step.transition(u)
        n = self.model.immersion.system.n
        im = self.model.immersion
        G = lift_jacobian(im.aux_forms, self._z[-n:]) @ im.system.B
        Q = h * (self.accel_psd * (G @ G.T) + self.V)
        self._z = Phi @ self._z + step.input_term(u)
        P = Phi @ self._P @ Phi.T + Q
        self._P = 0.5 * (P + P.T)

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        """Over ``dt`` in steps of :attr:`dt` (a last shorter one where ``dt`` is off the grid)."""
        left = dt
        while left > 1e-12 * self.dt:
            h = self.dt if left >= self.dt * (1.0 - 1e-9) else left
            self._advance(h, u)
            left -= h

    # -- measurements --------------------------------------------------------------------------

    def _correct_pair(self, i: int, j: int, d: float, sigma: float) -> None:
        c, y = self.model.row(i, j, d)
        n, dim = self.model.immersion.system.n, self.model.dim
        p = self._z[-n : -n + dim]
        anchors = self.model.anchors
        ri = max(float(np.linalg.norm(p - anchors[i])), self.min_range)
        rj = max(float(np.linalg.norm(p - anchors[j])), self.min_range)
        R = relation_variance(d, ri, rj, sigma)
        Pc = self._P @ c
        S = float(c @ Pc) + R
        nu = y - float(c @ self._z)
        self.nis = nu * nu / S
        if self.gate is not None and self.nis > self.gate:
            self.rejected += 1
            return
        K = Pc / S
        self._z = self._z + K * nu
        IKC = np.eye(c.size) - np.outer(K, c)
        P = IKC @ self._P @ IKC.T + R * np.outer(K, K)
        self._P = 0.5 * (P + P.T)
        self.corrections += 1

    def _correct_measurement(self, m: Measurement) -> None:
        """One TDOA ``m`` (``kind == "tdoa"``, ``anchors == (i, j)``) through its row."""
        if m.kind != "tdoa" or len(m.anchors) != 2:
            raise QuadobsError(f"{self.name}: takes TDOA measurements, got kind {m.kind!r}")
        sigma = self.std if math.isnan(m.std) else float(m.std)
        self._correct_pair(int(m.anchors[0]), int(m.anchors[1]), float(m.value), sigma)

    def step(self, u, y) -> None:
        """Correct with the present TDOAs of ``y (len(pairs),)`` (NaN: not measured), then
        predict over ``dt`` with ``u`` held."""
        u, y = check_step(u, y, self.model.immersion.system.p, len(self.pairs))
        for h in np.flatnonzero(np.isfinite(y)):
            i, j = self.pairs[h]
            self._correct_pair(i, j, float(y[h]), self.std)
        self._advance(self.dt, u)
        self.time = self.time + self.dt


class TdoaHandover(Estimator):
    """The TDOA observer until it has converged, then a filter on ``x`` started from its estimate.

    The observer converges from far guesses but carries ``3 dim (dim + 1) / 2`` extra states;
    near the truth an EKF on ``(p, v)`` is the more accurate (docs: TDOA). The handover
    happens at the first correction after which the observer's position spread is small
    enough for the filter's linearisation: the curvature of a TDOA, ``e^2 / (2 r)`` for an
    error ``e`` at a range ``r``, must stay below the noise, so

    .. math:: \\sqrt{\\operatorname{tr} P_{pp}} \\le \\sqrt{\\sigma\\, r_{\\min}},

    ``r_min`` the estimate's distance to its nearest anchor (at least ``min_range`` of the
    observer). The filter is made by ``make_filter(x, P, time)`` and must take the interface
    in time (``hold``, ``predict``, ``correct``).

    Parameters
    ----------
    observer : TdoaObserver
    make_filter : callable
        ``(x (n,), P (n, n), time) -> Estimator``.
    """

    name = "tdoa-handover"

    def __init__(self, observer: TdoaObserver, make_filter) -> None:
        if not isinstance(observer, TdoaObserver):
            raise QuadobsError(f"observer: expected a TdoaObserver, got {type(observer).__name__}")
        self.observer = observer
        self.make_filter = make_filter
        self.filter: Estimator | None = None
        self.handover_time = math.nan

    @property
    def active(self) -> Estimator:
        """The estimator in charge now."""
        return self.observer if self.filter is None else self.filter

    @property
    def time(self) -> float:
        return float(self.active.time)

    @time.setter
    def time(self, value: float) -> None:  # the time is the active estimator's
        pass

    @property
    def x_hat(self) -> np.ndarray:
        return self.active.x_hat

    @property
    def x_covariance(self) -> np.ndarray | None:
        return self.active.x_covariance

    @property
    def measurement_models(self) -> dict:
        """The observer's (TDOA)."""
        return self.observer.measurement_models

    @property
    def nis(self) -> float:
        """The normalised innovation squared of the active estimator's last correction."""
        return float(getattr(self.active, "nis", math.nan))

    @nis.setter
    def nis(self, value: float) -> None:  # the active estimator's
        pass

    def _ready(self) -> bool:
        obs = self.observer
        dim = obs.model.dim
        x, P = obs.x_hat, obs.x_covariance
        r = np.linalg.norm(obs.model.anchors - x[:dim], axis=1).min()
        spread = math.sqrt(max(float(np.trace(P[:dim, :dim])), 0.0))
        return spread <= math.sqrt(obs.std * max(float(r), obs.min_range))

    def _after_correction(self) -> None:
        if self.filter is None and self._ready():
            obs = self.observer
            self.filter = self.make_filter(obs.x_hat, obs.x_covariance, obs.time)
            self.filter.hold(obs.held_input())
            self.handover_time = obs.time

    def hold(self, u) -> None:
        self.observer.hold(u)
        if self.filter is not None:
            self.filter.hold(u)

    def predict(self, t: float) -> None:
        self.active.predict(t)

    def correct(self, m: Measurement) -> None:
        self.active.correct(m)
        self._after_correction()

    def step(self, u, y) -> None:
        """Pairs as outputs (the observer's ``pairs``): each present TDOA corrected in turn, then
        a prediction over ``dt``."""
        obs = self.observer
        u, y = check_step(u, y, obs.model.immersion.system.p, len(obs.pairs))
        t = self.time
        for h in np.flatnonzero(np.isfinite(y)):
            self.correct(Measurement(t, "tdoa", float(y[h]), obs.pairs[h], obs.std))
        self.hold(u)
        self.predict(t + obs.dt)
