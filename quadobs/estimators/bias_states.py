"""Per-anchor range biases as states of the EKF and the UKF.

The filters' state is extended with one constant bias per anchor, ``x_e = (x, b)``: the
dynamics ``x' = A x + B u``, ``b' = w_b`` (a random walk of intensity ``bias_walk``,
zero for constant biases) and the measurement of anchor ``h`` in the norm space of
:class:`~quadobs.estimators.kalman.OutputModel`,

.. math::

    h_h(x_e) = |p - a_h| + b_h, \\qquad
    \\frac{\\partial h_h}{\\partial x_e} = \\Big[\\frac{(p - a_h)^\\top}{|p - a_h|},\\ 0,\\ e_h^\\top\\Big],

which is :class:`~quadobs.core.measurements.RangeModel` with ``bias="state"``: its
:meth:`~quadobs.core.measurements.RangeModel.extra_states` give the biases' prior.
Everything else (exact held-input prediction, Joseph update, robust rules) is the
filters' own.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from quadobs.core.measurements import RangeModel
from quadobs.core.system import QuadraticSystem
from quadobs.errors import QuadobsError
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)

__all__ = [
    "BiasedExtendedKalmanFilter",
    "BiasedRangeOutputModel",
    "BiasedUnscentedKalmanFilter",
    "biased_models",
    "extended_system",
]


def extended_system(system: QuadraticSystem) -> QuadraticSystem:
    """``system`` with one constant state per output appended: ``A_e = blockdiag(A, 0)``,
    ``B_e = (B, 0)``, ``C_e,h = blockdiag(C_h, 0)``, ``d_e,h = (d_h, 0)``."""
    n, q = system.n, system.q
    A = np.zeros((n + q, n + q))
    A[:n, :n] = system.A
    B = np.vstack([system.B, np.zeros((q, system.p))])
    C = np.zeros((q, n + q, n + q))
    C[:, :n, :n] = system.C
    d = np.hstack([system.d, np.zeros((q, q))])
    return QuadraticSystem(A, B, C, d)


class BiasedRangeOutputModel(OutputModel):
    """The norm-space range model with each output's bias read from the extended state.

    Built by :func:`biased_models`; ``system`` is the :func:`extended_system`, ``offsets``
    the anchors' ``|a_h|^2 / 2``.
    """

    def predict(self, x: np.ndarray) -> np.ndarray:
        q = self.system.q
        return super().predict(x) + x[..., -q:]

    def linearize(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = self.system.q
        s, J = super().linearize(x)
        J = J.copy()
        J[:, -q:] += np.eye(q)
        return s + x[-q:], J


def biased_models(
    system: QuadraticSystem,
    dt: float,
    sigma: float,
    input_std: float,
    P0: np.ndarray,
    model: RangeModel,
    bias_walk: float = 0.0,
) -> tuple[HeldInputModel, BiasedRangeOutputModel, np.ndarray]:
    """The dynamics, measurement model and prior of a filter with bias states.

    Parameters
    ----------
    system : QuadraticSystem
        A range system (:func:`quadobs.core.system.vehicle_system`).
    dt, sigma, input_std : float
        Physics step (s), range noise (m), accelerometer noise (m/s^2).
    P0 : ndarray (n, n)
        The prior of ``x``.
    model : RangeModel
        With ``bias="state"``: its extra states give the biases' prior.
    bias_walk : float
        Random-walk intensity of the biases (m^2/s).
    """
    extra = model.extra_states()
    if len(extra) != system.q:
        raise QuadobsError(
            f"model: expected one bias state per output ({system.q}), got {len(extra)} "
            "(RangeModel(bias='state'))"
        )
    ext = extended_system(system)
    n, q = system.n, system.q
    V = np.zeros((n + q, n + q))
    V[n:, n:] = bias_walk * np.eye(q)
    dynamics = HeldInputModel(ext, dt, V=V, input_covariance=input_std**2)
    offsets = 0.5 * np.einsum("hi,hi->h", system.d, system.d)
    outputs = BiasedRangeOutputModel(ext, sigma**2 * np.eye(q), offsets=offsets)
    Pe = np.zeros((n + q, n + q))
    Pe[:n, :n] = P0
    Pe[n:, n:] = np.diag([e.prior_std**2 for e in extra])
    return dynamics, outputs, Pe


class _VehicleBlock:
    """Reports the vehicle's state ``x`` (the first ``n`` entries) and keeps the biases apart."""

    vehicle_n: int = 0
    # the filter's own (the class this one is mixed into); declared for the type checker only
    _x: np.ndarray
    _P: np.ndarray
    if TYPE_CHECKING:

        def _settle(self) -> None: ...

    @property
    def x_hat(self) -> np.ndarray:
        return self._x[: self.vehicle_n].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        self._settle()
        k = self.vehicle_n
        return self._P[:k, :k].copy()

    @property
    def biases(self) -> np.ndarray:
        """The estimated per-anchor biases ``(q,)`` (m)."""
        return self._x[self.vehicle_n :].copy()


class BiasedExtendedKalmanFilter(_VehicleBlock, ExtendedKalmanFilter):
    """:class:`~quadobs.estimators.kalman.ExtendedKalmanFilter` on ``(x, b)`` (:func:`biased_models`);
    :attr:`x_hat` is ``x``, :attr:`biases` is ``b``."""

    name = "ekf-bias"

    def __init__(self, dynamics, outputs, *, vehicle_n: int, **kw) -> None:
        super().__init__(dynamics, outputs, **kw)
        self.vehicle_n = int(vehicle_n)


class BiasedUnscentedKalmanFilter(_VehicleBlock, UnscentedKalmanFilter):
    """:class:`~quadobs.estimators.kalman.UnscentedKalmanFilter` on ``(x, b)`` (:func:`biased_models`)."""

    name = "ukf-bias"

    def __init__(self, dynamics, outputs, *, vehicle_n: int, **kw) -> None:
        super().__init__(dynamics, outputs, **kw)
        self.vehicle_n = int(vehicle_n)
