"""Measurements as events in time, and the models that say what each kind of measurement means.

A world, simulated or replayed, yields a time-ordered stream of :class:`Input` and
:class:`Measurement` events. An estimator that takes measurements at their own times is
advanced by ``predict(t)`` (propagate to ``t`` with the input held since the last call) and
``correct(m)`` (one measurement, ``m.t`` equal to the current time); the fixed-grid
``step(u, y)`` is the special case where every measurement falls on a step.

One class knows each measurement kind; every estimator asks it (the predictor/updater
split of Stone Soup and filterpy):

==================  ===========================================================
kind                model
==================  ===========================================================
``"range"``         :class:`RangeModel`: ``rho = |p - a_i| + b_i + noise``
``"tdoa"``          :class:`TdoaModel`: ``d_ij = |p - a_i| - |p - a_j| + b_ij + noise``
==================  ===========================================================

Each model gives the predicted value :meth:`MeasurementModel.h` and its gradient with
respect to the position :meth:`MeasurementModel.jacobian` (for the EKF, the UKF and the
refined estimator), the extra states it may ask the estimator to carry
(:meth:`MeasurementModel.extra_states`, e.g. one bias per anchor) and, where one exists,
the quadratic-output form that the immersion of [IFAC2021] takes
(:meth:`MeasurementModel.quadratic_form`); a model without one is still usable by the
filters and the peer.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field

import numpy as np

from quadobs.errors import QuadobsError

__all__ = [
    "INPUT_KINDS",
    "MEASUREMENT_KINDS",
    "RANGE_BIAS_PRIOR_STD",
    "ExtraState",
    "Input",
    "Measurement",
    "MeasurementModel",
    "QuadraticForm",
    "RangeModel",
    "TdoaModel",
    "range_model_of",
]

#: The measurement kinds the project knows, each with its model class below.
MEASUREMENT_KINDS = ("range", "tdoa")
#: The input kinds: an accelerometer in the navigation frame (gravity removed), a body-frame
#: IMU (specific force and angular rate), planar wheel odometry (speed, yaw rate), or none.
INPUT_KINDS = ("accel_nav", "imu_body", "odometry", "none")
#: The prior standard deviation (m) of a range bias held as a state, around zero: the upper
#: end of UWB antenna delays (+-0.1 to 0.5 m), where nothing else is stated.
RANGE_BIAS_PRIOR_STD = 0.5


@dataclass(frozen=True, slots=True)
class Measurement:
    """One measurement at its own time.

    Attributes
    ----------
    t : float
        Time (s) on the log's or the world's clock.
    kind : str
        One of :data:`MEASUREMENT_KINDS`.
    value : float
        The measured value (m).
    anchors : tuple of int
        Indices (not ids) of the anchors it involves: ``(i,)`` for a range, ``(i, j)`` for a
        TDOA ``|p - a_i| - |p - a_j|``.
    std : float
        Its standard deviation (m); NaN: the model's default.
    """

    t: float
    kind: str
    value: float
    anchors: tuple[int, ...]
    std: float = math.nan


@dataclass(frozen=True, slots=True)
class Input:
    """One input sample, held from its time ``t`` until the next one.

    ``value`` holds, by ``kind``: ``accel_nav`` ``(d,)`` m/s²; ``imu_body`` ``(6,)`` specific
    force (m/s²) then angular rate (rad/s), body frame; ``odometry`` ``(2,)`` speed (m/s) and
    yaw rate (rad/s); ``none`` ``(0,)``.
    """

    t: float
    kind: str
    value: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True, slots=True)
class ExtraState:
    """A state a measurement model asks an estimator to carry besides the vehicle's.

    Attributes
    ----------
    name : str
        E.g. ``"bias[3]"``.
    prior_std : float
        Standard deviation of its prior around zero.
    random_walk : float
        Its random-walk intensity (unit²/s); 0 for a constant.
    """

    name: str
    prior_std: float
    random_walk: float = 0.0


class MeasurementModel(abc.ABC):
    """What every measurement model provides.

    Parameters
    ----------
    anchors : ndarray, shape (m, d)
        Anchor positions in the navigation frame.
    std : float
        Default standard deviation of one measurement (m).
    bias : {"none", "fixed", "state"}
        ``none``: no bias; ``fixed``: the known biases ``fixed_bias`` are subtracted;
        ``state``: one bias per anchor (or pair) is carried as an extra state.
    """

    kind: str = ""

    def __init__(
        self,
        anchors: np.ndarray,
        std: float,
        bias: str = "none",
        fixed_bias: np.ndarray | None = None,
    ) -> None:
        anchors = np.asarray(anchors, dtype=float)
        if anchors.ndim != 2 or anchors.shape[1] not in (2, 3) or anchors.shape[0] < 1:
            raise QuadobsError(f"anchors: expected shape (m, 2) or (m, 3), got {anchors.shape}")
        if not np.all(np.isfinite(anchors)):
            raise QuadobsError("anchors: positions must be finite")
        if not (math.isfinite(std) and std > 0.0):
            raise QuadobsError(f"std: expected a positive finite number, got {std}")
        if bias not in ("none", "fixed", "state"):
            raise QuadobsError(f"bias: expected 'none', 'fixed' or 'state', got {bias!r}")
        self.anchors = anchors
        self.std = float(std)
        self.bias = bias
        self.fixed_bias = (
            np.zeros(anchors.shape[0])
            if fixed_bias is None
            else np.asarray(fixed_bias, dtype=float).copy()
        )

    @property
    def dimension(self) -> int:
        """The dimension of the position, 2 or 3."""
        return int(self.anchors.shape[1])

    def sigma(self, m: Measurement) -> float:
        """The standard deviation to use for ``m``: its own, or the model's default."""
        return self.std if math.isnan(m.std) else float(m.std)

    @abc.abstractmethod
    def h(self, p: np.ndarray, m: Measurement) -> float:
        """The predicted value of ``m`` at position ``p (d,)``, without bias."""

    @abc.abstractmethod
    def jacobian(self, p: np.ndarray, m: Measurement) -> np.ndarray:
        """The gradient of :meth:`h` with respect to the position, ``(d,)``."""

    def extra_states(self) -> list[ExtraState]:
        """The states this model asks an estimator to carry (none by default)."""
        return []

    def bias_of(self, m: Measurement) -> float:
        """The known bias of ``m`` that :meth:`unbiased` removes (0 unless ``bias="fixed"``)."""
        return 0.0

    def unbiased(self, m: Measurement) -> float:
        """``m.value`` less its known bias (``bias="fixed"``), the value the estimators compare
        with :meth:`h`."""
        return float(m.value) - self.bias_of(m)

    def quadratic_form(self) -> QuadraticForm | None:
        """The quadratic-output form of this kind for the immersion, or ``None`` where the kind
        has none (then the immersion-based observers refuse it by name)."""
        return None

    def quadratic_output(self, m: Measurement) -> tuple[int, float, float]:
        """``(h, y_h, var y_h)``: the output row ``m`` informs, its value in the quadratic-output
        form and that value's variance (:meth:`quadratic_form`; refused where there is none)."""
        raise QuadobsError(f"{self.kind} measurements have no quadratic-output form")

    def check(self, m: Measurement) -> None:
        """Refuse ``m`` when it is not of this kind or names anchors this model lacks."""
        count = 1 if self.kind == "range" else 2
        if m.kind != self.kind or len(m.anchors) != count:
            raise QuadobsError(
                f"{self.kind} model: a {m.kind} measurement with anchors {m.anchors} does not fit"
            )
        if any(not 0 <= i < self.anchors.shape[0] for i in m.anchors):
            raise QuadobsError(
                f"{m.kind} measurement at t = {m.t:.9g} s: anchor index {m.anchors} outside "
                f"0..{self.anchors.shape[0] - 1}"
            )


@dataclass(frozen=True, eq=False)
class QuadraticForm:
    """Outputs ``y_h = x^T C_h x / 2 + d_h^T x`` on the position ``x (d,)``, one per anchor.

    Attributes
    ----------
    C : ndarray (m, d, d)
    d : ndarray (m, d)
    """

    C: np.ndarray
    d: np.ndarray


class RangeModel(MeasurementModel):
    """Two-way range to anchor ``i``: ``rho = |p - a_i| + b_i + noise``.

    Its quadratic form is the one of [IFAC2021, eq. 2]: ``rho^2 / 2 = |p - a_i|^2 / 2`` (no
    bias), the output of :func:`quadobs.core.system.vehicle_system`.
    """

    kind = "range"

    def h(self, p: np.ndarray, m: Measurement) -> float:
        return float(np.linalg.norm(p - self.anchors[m.anchors[0]]))

    def jacobian(self, p: np.ndarray, m: Measurement) -> np.ndarray:
        diff = p - self.anchors[m.anchors[0]]
        r = float(np.linalg.norm(diff))
        return diff / r if r > 0.0 else np.zeros_like(diff)

    def extra_states(self) -> list[ExtraState]:
        if self.bias != "state":
            return []
        return [
            ExtraState(f"bias[{i}]", RANGE_BIAS_PRIOR_STD) for i in range(self.anchors.shape[0])
        ]

    def bias_of(self, m: Measurement) -> float:
        return float(self.fixed_bias[m.anchors[0]]) if self.bias == "fixed" else 0.0

    def quadratic_form(self) -> QuadraticForm:
        """``C_h = I``, ``d_h = -a_h``: ``y_h = |p - a_h|^2 / 2 - |a_h|^2 / 2`` [IFAC2021, eq. 44]."""
        m, d = self.anchors.shape
        return QuadraticForm(np.broadcast_to(np.eye(d), (m, d, d)).copy(), -self.anchors)

    def quadratic_output(self, m: Measurement) -> tuple[int, float, float]:
        """``(i, rho^2 / 2 - |a_i|^2 / 2, rho^2 sigma^2 + sigma^4 / 2)`` for a range ``rho`` to anchor ``i``.

        The variance is the exact one of ``(r + e)^2 / 2`` for ``e ~ N(0, sigma^2)``, with the
        measured ``rho`` for the unknown ``r``.
        """
        i = m.anchors[0]
        rho, s2 = self.unbiased(m), self.sigma(m) ** 2
        a = self.anchors[i]
        return i, 0.5 * rho * rho - 0.5 * float(a @ a), rho * rho * s2 + 0.5 * s2 * s2


class TdoaModel(MeasurementModel):
    """Time difference of arrival between anchors ``i`` and ``j``, as a distance:
    ``d_ij = |p - a_i| - |p - a_j| + noise``."""

    kind = "tdoa"

    def bias_of(self, m: Measurement) -> float:
        if self.bias != "fixed":
            return 0.0
        i, j = m.anchors
        return float(self.fixed_bias[i] - self.fixed_bias[j])

    def h(self, p: np.ndarray, m: Measurement) -> float:
        i, j = m.anchors
        return float(np.linalg.norm(p - self.anchors[i]) - np.linalg.norm(p - self.anchors[j]))

    def jacobian(self, p: np.ndarray, m: Measurement) -> np.ndarray:
        i, j = m.anchors
        di, dj = p - self.anchors[i], p - self.anchors[j]
        ri, rj = float(np.linalg.norm(di)), float(np.linalg.norm(dj))
        gi = di / ri if ri > 0.0 else np.zeros_like(di)
        gj = dj / rj if rj > 0.0 else np.zeros_like(dj)
        return gi - gj


def range_model_of(system, std: float = 1.0) -> RangeModel | None:
    """The :class:`RangeModel` whose anchors are the range outputs of a quadratic-output system.

    Output ``h`` is a range to anchor ``a_h`` when ``C_h = diag(I_d, 0)`` and
    ``d_h = (-a_h, 0)`` (:func:`quadobs.core.system.vehicle_system`); the range outputs must be
    the first rows, anchor ``h`` being output ``h``. ``None`` when the first output is not a range.
    """
    C, dvec, n = system.C, system.d, system.n
    anchors = []
    for dim in (3, 2):
        if n < dim:
            continue
        block = np.zeros((n, n))
        block[:dim, :dim] = np.eye(dim)
        for h in range(C.shape[0]):
            if not (np.array_equal(C[h], block) and not dvec[h, dim:].any()):
                break
            anchors.append(-dvec[h, :dim])
        if anchors:
            return RangeModel(np.array(anchors), std)
    return None
