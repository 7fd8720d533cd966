"""Anchors above or below a planar tag: a constant offset of each squared range as a state.

A planar log gives its anchors' survey in the plane (``beacons.csv`` with ``x, y``), while a
real anchor hangs on a wall or near the ceiling and the tag rides on a robot: each range is
the 3-D distance,

.. math::

    \\rho_h = \\sqrt{|p - a_h|^2 + \\delta z_h^2} + b_h + n ,

``delta z_h`` the anchor's height above the tag and ``b_h`` its bias (antenna delay). Its
apparent bias against the planar distance ``r = |p - a_h|``, ``sqrt(r^2 + dz^2) - r``, is no
constant: from ``|dz|`` at the anchor's foot it falls as ``dz^2 / (2 r)``; a constant bias
state follows it only where the robot keeps its distance. In the squared range the height
is a constant, and it enters the quadratic output of [IFAC2021, eq. 2] linearly:

.. math::

    y_h = \\frac{(\\rho_h - b_h)^2 - |a_h|^2}{2}
        = \\frac{|p|^2}{2} - a_h^\\top p + e_h , \\qquad e_h = \\frac{\\delta z_h^2}{2} ,

a constant auxiliary state beside the biases. The filters here carry ``x_e = (x, b, e)``
(``b' = 0``, ``e' = 0``) and compare the range in the norm space of
:class:`~quadobs.estimators.kalman.OutputModel`:

.. math::

    h_h(x_e) = \\sqrt{2 (y_h(x) + |a_h|^2 / 2 + e_h)} + b_h , \\qquad
    \\frac{\\partial h_h}{\\partial x} = \\frac{(p - a_h)^\\top}{s_h}, \\quad
    \\frac{\\partial h_h}{\\partial b_h} = 1, \\quad
    \\frac{\\partial h_h}{\\partial e_h} = \\frac{1}{s_h},

``s_h = sqrt(|p - a_h|^2 + 2 e_h)`` the predicted 3-D distance (clamped at zero where the
state makes the square negative). ``b`` and ``e`` are told apart by how the range changes
with the distance: ``e_h / s_h`` shrinks as the robot moves away, ``b_h`` does not. Everything
else (the start-up fix, the consider update until the innovations are consistent, the
re-initialisation after a lock-out) is that of :mod:`quadobs.estimators.bias_states`, the
extra states being ``(b, e)`` together.
"""

from __future__ import annotations

import numpy as np

from quadobs.core.measurements import RangeModel
from quadobs.core.system import QuadraticSystem
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.bias_states import (
    BiasedExtendedKalmanFilter,
    BiasedUnscentedKalmanFilter,
    extended_system,
)
from quadobs.estimators.kalman import OutputModel

__all__ = [
    "HeightAugmentedObserver",
    "HeightBiasedExtendedKalmanFilter",
    "HeightBiasedUnscentedKalmanFilter",
    "HeightRangeOutputModel",
    "height_quadratic_system",
    "height_system",
]


def height_system(system: QuadraticSystem) -> QuadraticSystem:
    """``system`` with two constant states per output appended, the biases ``b`` then the
    squared-range offsets ``e`` (:func:`~quadobs.estimators.bias_states.extended_system` twice)."""
    return extended_system(extended_system(system))


class HeightRangeOutputModel(OutputModel):
    """The norm-space range ``sqrt(2 (y_h + o_h + e_h)) + b_h`` (module docstring), ``b`` and ``e``
    the last ``2 q`` entries of the state of :func:`height_system`; ``offsets`` the anchors'
    ``|a_h|^2 / 2``."""

    def predict(self, x: np.ndarray) -> np.ndarray:
        q = self.system.q
        y = self.system.output(x)
        inside = 2.0 * (y + self.offsets + x[..., -q:])
        return np.sqrt(np.maximum(inside, 0.0)) + x[..., -2 * q : -q]

    def linearize(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = self.system.q
        g = self.system.C @ x
        y = (0.5 * g + self.system.d) @ x
        s = np.sqrt(np.maximum(2.0 * (y + self.offsets + x[-q:]), 0.0))
        with np.errstate(divide="ignore"):
            scale = np.where(s > 0.0, 1.0 / s, 0.0)
        J = (g + self.system.d) * scale[:, None]
        J[:, -2 * q : -q] += np.eye(q)
        J[:, -q:] = np.diag(scale)
        return s + x[-2 * q : -q], J


class HeightBiasedExtendedKalmanFilter(BiasedExtendedKalmanFilter):
    """The EKF on ``(x, b, e)`` (module docstring); :attr:`biases` is ``b``, :attr:`heights`
    the anchors' heights above the tag ``sqrt(2 max(e, 0))``."""

    name = "ekf-height"

    @property
    def biases(self) -> np.ndarray:
        q = (self._x.shape[0] - self.vehicle_n) // 2
        return self._x[self.vehicle_n : self.vehicle_n + q].copy()

    @property
    def heights(self) -> np.ndarray:
        """``|delta z_h| = sqrt(2 e_h)`` (m), from the estimated offsets (negative ones as 0)."""
        q = (self._x.shape[0] - self.vehicle_n) // 2
        return np.sqrt(2.0 * np.maximum(self._x[-q:], 0.0))


class HeightBiasedUnscentedKalmanFilter(BiasedUnscentedKalmanFilter):
    """The UKF on ``(x, b, e)`` (as :class:`HeightBiasedExtendedKalmanFilter`)."""

    name = "ukf-height"
    biases = HeightBiasedExtendedKalmanFilter.biases
    heights = HeightBiasedExtendedKalmanFilter.heights


def height_quadratic_system(system: QuadraticSystem) -> QuadraticSystem:
    """``system`` with one constant state ``e_h`` per output that enters its quadratic output
    linearly, ``y_h = x^T C_h x / 2 + d_h^T x + e_h`` (module docstring): ``A_e = blockdiag(A, 0)``,
    ``B_e = (B, 0)``, ``C_e,h = blockdiag(C_h, 0)``, ``d_e,h = (d_h, e_h)`` (``e_h`` the unit vector;
    :func:`~quadobs.estimators.bias_states.extended_system` with ``linear``)."""
    return extended_system(system, linear=True)


class HeightAugmentedObserver(AugmentedObserver):
    """The observer of [IFAC2021, Thm. 3] on the immersion of :func:`height_quadratic_system`:
    the squared-range offsets ``e`` are constant states of the linear immersed system, so the
    observer stays linear in ``z = (xi, x, e)`` (its convergence from any guess unchanged).
    :attr:`x_hat` is the vehicle's ``x`` (``vehicle_n`` entries); :attr:`heights` the anchors'
    heights above the tag ``sqrt(2 max(e, 0))``.

    Parameters
    ----------
    vehicle_n : int
        The vehicle's state dimension ``n``; the rest of ``x`` are the offsets ``e``.
    anchors : ndarray (q, d)
        The anchors of the outputs: its ranges' model (:class:`~quadobs.core.measurements.RangeModel`,
        whose quadratic output ``(rho^2 - |a_h|^2) / 2`` is the immersion's output ``h``).
    *args, **kw
        Those of :class:`~quadobs.estimators.augmented.AugmentedObserver`.
    """

    name = "augmented-height"

    def __init__(self, *args, vehicle_n: int, anchors: np.ndarray, **kw) -> None:
        super().__init__(*args, **kw)
        self.vehicle_n = int(vehicle_n)
        self.measurement_models = {"range": RangeModel(np.asarray(anchors, dtype=float), 1.0)}

    @property
    def x_hat(self) -> np.ndarray:
        k = self.immersion.n_aux
        return self._z[k : k + self.vehicle_n].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        k, n = self.immersion.n_aux, self.vehicle_n
        return self._P[k : k + n, k : k + n].copy()

    @property
    def heights(self) -> np.ndarray:
        """``|delta z_h| = sqrt(2 e_h)`` (m), from the estimated offsets (negative ones as 0)."""
        e = self._z[self.immersion.n_aux + self.vehicle_n :]
        return np.sqrt(2.0 * np.maximum(e, 0.0))
