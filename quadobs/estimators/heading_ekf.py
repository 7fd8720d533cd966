"""Kalman filters of a wheeled vehicle whose heading and gyroscope bias are states (odometry logs).

The replay's ``odometry`` model (:func:`~quadobs.core.system.odometry_system`) takes the
odometry's dead-reckoned heading as right: its input is the forward speed ``s`` rotated by
that heading, ``u = (s cos theta_o, s sin theta_o, omega_m)``, with ``theta_o`` the integral
of the measured yaw rate ``omega_m`` from the log's start heading. A yaw rate read with a
constant bias ``b`` (a gyroscope's, or an odometry's unequal wheel radii) makes
``theta_o`` drift linearly, and a wrong start heading turns the whole path. These filters
estimate both. The state is

.. math:: x = (p_x,\\ p_y,\\ \\delta,\\ b), \\qquad \\theta = \\theta_o + \\delta ,

``delta`` the heading's correction to the dead reckoning (rad) and ``b`` the yaw rate's
bias (rad/s). With ``omega_m = theta' + b + n_theta`` and ``theta_o' = omega_m``,

.. math::

    \\dot p = s \\begin{bmatrix} \\cos\\theta \\\\ \\sin\\theta \\end{bmatrix}
            = R(\\delta)\\, u_{xy} + w_p, \\qquad
    \\dot\\delta = -b - n_\\theta, \\qquad \\dot b = w_b,

``R(delta)`` the rotation by ``delta``: the replay's own held input drives it, on the grid and
in time alike, and ``theta_o`` is needed only to report the heading. The white noises have
intensities ``q_xy`` (m^2/s per axis: the speed's noise), ``q_theta`` (rad^2/s: the yaw
rate's) and ``q_bias`` (rad^2/s^3: the bias's random walk).

Prediction over an interval ``h`` with ``u`` held is exact for the mean: ``delta`` falls
linearly, ``delta(tau) = delta_0 - b tau``, and

.. math::

    p(h) = p_0 + \\int_0^h R(\\delta_0 - b\\tau)\\, d\\tau\\ u_{xy}
         = p_0 + h\\, \\operatorname{sinc}(b h / 2)\\, R(\\delta_0 - b h / 2)\\, u_{xy},

``sinc x = sin x / x`` (the chord of an arc). :class:`HeadingEKF` propagates the covariance
with the Jacobian ``F`` of that map and the noise ``Q_d`` of Van Loan's integral
(:func:`~quadobs.core.held_input.van_loan_interval`) for the model linearised at the
interval's middle heading; :class:`HeadingUKF` sends sigma points through the same map.
A range ``rho = |p - a_h| + e`` (or a TDOA) corrects through its
:class:`~quadobs.core.measurements.MeasurementModel` (``h`` and its Jacobian on the
position), with the robust rules, the gate and the lock-out of the other Kalman filters
(:mod:`quadobs.estimators.robust`).

The heading is observable only while the vehicle moves (``u_xy != 0``): at rest the
filters keep its prior, and its bias follows from the heading's change over time. The
estimate the testbed reads (:attr:`HeadingEKF.x_hat`) is the position, the state of the
replay's odometry model; :attr:`~HeadingEKF.state`, :attr:`~HeadingEKF.heading` and
:attr:`~HeadingEKF.gyro_bias` give the rest.

A lever arm. On a real robot the tag sits off the point the odometry describes (the axle's
centre): at ``q = p + R(theta) l``, ``l`` a constant offset in the body frame (x forward).
With ``lever_arm_std`` given, the filters append ``l`` to the state as two constants (prior
mean 0 and that standard deviation, no process noise),

.. math:: x = (p_x,\\ p_y,\\ \\delta,\\ b,\\ l_x,\\ l_y), \\qquad
          \\rho_h = |p + R(\\theta_o + \\delta)\\, l - a_h| + e ,

the measurement models taking the tag's position ``q`` where they took ``p`` (the EKF's
Jacobian ``dh/dx = dh/dq [I,\\ R(\\theta) J l,\\ 0,\\ R(\\theta)]``). The estimate read stays
``p``, the odometry's point. ``l`` is observable in turns: the tag's velocity is
``R(delta) u_xy + omega R(theta) J l``, so a yaw rate that changes separates ``l`` from ``p``
and the heading (on a circle of constant turn rate its forward component trades against
``delta``).

Anchors above or below the tag. A planar log draws its anchors in the tag's plane, while each
range is the 3-D distance. With ``offsets`` given (the prior mean and standard deviation of
``e_h``), the filters append one constant per anchor, the offset of its squared range
``e_h = delta z_h^2 / 2`` (:mod:`quadobs.estimators.height_states`), and with ``bias_std`` one
more, its range bias ``b_h`` (prior mean 0); the state is ``(p, delta, b, [l], [b_1..q],
[e_1..q])`` and a range

.. math:: \\rho_h = s_h + b_h, \\qquad s_h = \\sqrt{|q - a_h|^2 + 2 e_h},

``q`` the tag's position (``p`` without a lever arm). Its derivatives: ``d rho_h / d q =
(q - a_h)^T / s_h`` (carried to ``p``, ``delta`` and ``l`` as above), ``d rho_h / d e_h = 1 /
s_h``, ``d rho_h / d b_h = 1``. ``e_h`` and ``b_h`` are told apart by the distance (``e_h / s_h``
falls as the tag moves away, ``b_h`` does not), ``e_h`` and ``l`` by the heading (the tag's
offset turns with the robot, ``e_h`` does not). Such filters take ranges only (no TDOA).

The tag's pattern. A tag's antenna delays the signal by an amount that depends on the
direction of the anchor in the body frame, so that the range's bias turns with the vehicle
(Ledergerber and D'Andrea, IEEE Access 6, 2018, doi:10.1109/ACCESS.2018.2884720, calibrate it
against the two antennas' relative orientation). Expanded in the anchor's bearing ``phi_h``
from the tag less the heading, its constant is in each ``b_h`` and its first harmonic is a
lever arm (``l``, above); with ``tag_pattern_std`` given the filters append the second,

.. math:: \\rho_h \\mathrel{+}= c \\cos 2\\phi_h + s \\sin 2\\phi_h, \\qquad
          \\phi_h = \\operatorname{atan2}(a_h - q) - (\\theta_o + \\delta),

``(c, s)`` two constants (prior 0 and ``tag_pattern_std`` each), one for the tag, not per
anchor. Its derivatives: ``cos 2 phi_h`` and ``sin 2 phi_h`` at ``(c, s)``, ``d phi_h / d q =
(d_y, -d_x) / |d|^2`` (``d = a_h - q``), ``d phi_h / d delta = -1``. It turns at twice the
heading's rate where ``l``'s term turns once and ``b_h`` not at all, so a robot that turns
tells the three apart.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.core.held_input import van_loan_interval
from quadobs.core.measurements import Measurement, RangeModel
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.estimators.base import Estimator, Gated, Immersed, InnerClock, step_operands
from quadobs.estimators.constants import ConstantStates
from quadobs.estimators.robust import (
    ExcessHuber,
    LockOut,
    multilateration,
    reinitialised_covariance,
    reweight,
)

__all__ = [
    "GYRO_BIAS_STD",
    "GYRO_BIAS_TIME",
    "HEADING_STD",
    "LEVER_ARM_STD",
    "TAG_PATTERN_STD",
    "HeadingCascade",
    "HeadingEKF",
    "HeadingUKF",
    "arc_step",
]

#: The prior standard deviation of the yaw rate's bias (rad/s): 1 deg/s, the turn-on bias a
#: consumer MEMS gyroscope's data sheet states (and beyond what a wheel odometry's unequal
#: wheel radii give at walking speeds: 1 % of 1 m/s over a 0.5 m track is 0.02 rad/s).
GYRO_BIAS_STD = math.radians(1.0)

#: The time (s) over which the bias may wander by :data:`GYRO_BIAS_STD`: an hour, the scale of a
#: gyroscope's thermal drift; the random walk's intensity is ``GYRO_BIAS_STD^2 / GYRO_BIAS_TIME``.
GYRO_BIAS_TIME = 3600.0

#: The prior standard deviation of the start heading a log states (rad): 0.1 rad (6 deg), a
#: heading read off a survey or a compass at the start; the heading becomes observable as soon
#: as the vehicle moves among the anchors.
HEADING_STD = 0.1

#: The prior standard deviation of the tag's lever arm per body axis (m): 0.2 m, half the size of
#: a small wheeled robot (a 0.4 m base), as far as a tag mounted on it can sit from its axle's
#: centre when nobody measured where.
LEVER_ARM_STD = 0.2

#: The prior standard deviation of the lever arm per body axis where the log states the tag's
#: place on the vehicle (m): 0.02 m, a place measured with a rule to the antenna's mark, whose
#: phase centre lies within a centimetre or two of it.
STATED_LEVER_STD = 0.02

#: The prior standard deviation (m) of each coefficient of the tag's pattern, ``c`` and ``s``:
#: 0.1 m, the size of the range errors that the relative orientation of two UWB antennas gives
#: (Ledergerber and D'Andrea, IEEE Access 6, 2018, doi:10.1109/ACCESS.2018.2884720), so that
#: the term's standard deviation over bearings, ``sqrt((c^2 + s^2) / 2)``, is 0.1 m a priori.
TAG_PATTERN_STD = 0.1

#: The 0.999 quantile of ``chi^2(2)`` (``-2 ln 0.001``): a lever arm whose squared distance to
#: its prior's mean exceeds this many prior variances is implausible (:meth:`_check_lever`).
LEVER_CHI2 = -2.0 * math.log(1e-3)

_J = np.array([[0.0, -1.0], [1.0, 0.0]])  # d R(phi) / d phi = R(phi) J


def _rotation(phi: float) -> np.ndarray:
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s], [s, c]])


def _sinc(x: float) -> tuple[float, float]:
    """``(sin x / x, d/dx (sin x / x))``, by their series near 0."""
    if abs(x) < 1e-4:
        return 1.0 - x * x / 6.0, -x / 3.0
    s, c = math.sin(x), math.cos(x)
    return s / x, (x * c - s) / (x * x)


def arc_step(x: np.ndarray, u: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """The exact mean map over ``h`` seconds with ``u`` held, and its Jacobian (module docstring).

    Parameters
    ----------
    x : ndarray (4,)
        ``(p_x, p_y, delta, b)``.
    u : ndarray (3,)
        ``(v_x, v_y, omega)``: the odometry's velocity along its own heading and its yaw rate.
    h : float
        The interval (s).

    Returns
    -------
    x_next : ndarray (4,)
    F : ndarray (4, 4)
        ``d x_next / d x``.

    Examples
    --------
    A bias ``b`` turns the path at ``-b``: a quarter circle of radius 1 in ``pi / 2`` s.

    >>> x, F = arc_step(np.zeros(4) + [0, 0, 0, -1.0], np.array([1.0, 0.0, 0.0]), np.pi / 2)
    >>> np.round(x, 12).tolist()
    [1.0, 1.0, 1.570796326795, -1.0]
    """
    delta, b = float(x[2]), float(x[3])
    xh = 0.5 * b * h
    sig, dsig = _sinc(xh)
    Rm = _rotation(delta - xh)
    v = Rm @ u[:2]
    w = Rm @ (_J @ u[:2])
    out = np.array([x[0] + h * sig * v[0], x[1] + h * sig * v[1], delta - b * h, b])
    F = np.eye(4)
    F[:2, 2] = h * sig * w
    F[:2, 3] = 0.5 * h * h * (dsig * v - sig * w)
    F[2, 3] = -h
    return out, F


def arc_points(X: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
    """The mean map of :func:`arc_step` on every row of ``X`` (``(p, delta, b, ...)``, the
    entries after ``b`` constant) at once, without the Jacobian."""
    b = X[:, 3]
    xh = 0.5 * b * h
    small = np.abs(xh) < 1e-4
    safe = np.where(small, 1.0, xh)
    sig = np.where(small, 1.0 - xh * xh / 6.0, np.sin(safe) / safe)
    phi = X[:, 2] - xh
    c, s = np.cos(phi), np.sin(phi)
    out = X.copy()
    out[:, 0] += h * sig * (c * u[0] - s * u[1])
    out[:, 1] += h * sig * (s * u[0] + c * u[1])
    out[:, 2] = X[:, 2] - b * h
    return out


class _HeadingFilter(ConstantStates, Estimator, Gated):
    """The shared state, prediction noise, measurement models, robust rules and lock-out."""

    def __init__(
        self,
        anchors,
        *,
        x0,
        P0,
        dt: float,
        q_xy: float,
        q_theta: float,
        q_bias: float,
        range_sigma: float = 1.0,
        heading0: float = 0.0,
        gate: float | None = None,
        robust=None,
        lockout: LockOut | None = None,
        measurements=None,
        lever_arm_std: float | None = None,
        lever_arm=(0.0, 0.0),
        offsets: tuple[float, float] | None = None,
        bias_std: float | None = None,
        tag_pattern_std: float | None = None,
    ) -> None:
        self.anchors = as_array("anchors", anchors, (None, 2))
        self._x = as_array("x0", x0, (4,)).copy()
        P = np.diag(as_array("P0", P0, (4,))) if np.ndim(P0) == 1 else as_array("P0", P0, (4, 4))
        self._P = 0.5 * (P + P.T)
        self.dt = as_finite_scalar("dt", dt, positive=True)
        self.Qc = np.diag([q_xy, q_xy, q_theta, q_bias]).astype(float)
        if not np.all(np.isfinite(self.Qc)) or np.any(np.diag(self.Qc) < 0.0):
            raise QuadobsError("q_xy, q_theta, q_bias: expected non-negative finite intensities")
        self.lever = lever_arm_std is not None
        if self.lever:
            var = as_finite_scalar("lever_arm_std", lever_arm_std, positive=True) ** 2
            self._lever_var = var
            self._lever_mean = as_array("lever_arm", lever_arm, (2,))  # the guard's centre
            self._x = np.concatenate([self._x, self._lever_mean])
            self._P = np.block([[self._P, np.zeros((4, 2))], [np.zeros((2, 4)), var * np.eye(2)]])
        self._append_anchor_states(offsets, bias_std)
        self._append_pattern_states(tag_pattern_std)
        self.range_sigma = as_finite_scalar("range_sigma", range_sigma, positive=True)
        self.theta_o = as_finite_scalar("heading0", heading0)
        self.gate = None if gate is None else as_finite_scalar("gate", gate, positive=True)
        models = (
            [RangeModel(self.anchors, self.range_sigma)] if measurements is None else measurements
        )
        self.measurement_models = {m.kind: m for m in models}
        if self._ip >= 0 and set(self.measurement_models) != {"range"}:
            raise QuadobsError("tag_pattern_std: the tag's pattern is a state of ranges only")
        self.robust = robust
        self.lockout = lockout if lockout is not None else LockOut()
        self._P0, self._x0 = self._P.copy(), self._x.copy()
        self._grid_order = np.lexsort(self.anchors.T[::-1])  # by x, then y (step)
        self._latest = np.full(self.anchors.shape[0], np.nan)  # y_h = rho^2/2 - |a_h|^2/2
        self._latest_std = np.full(self.anchors.shape[0], self.range_sigma)  # each one's sigma
        # each anchor's probability of a blocked path at its last range, and when (ExcessHuber)
        self._blocked = np.zeros(self.anchors.shape[0])
        self._blocked_at = np.full(self.anchors.shape[0], -math.inf)
        self._range_anchor = -1
        self.nis, self.corrections, self.rejected = math.nan, 0, 0
        self._time = 0.0
        # start-up (_starting): a prior position as wide as the anchors' geometry
        c = self.anchors.mean(axis=0)
        scale = max(0.5 * float(np.max(np.linalg.norm(self.anchors - c, axis=1))), self.range_sigma)
        prior_std = math.sqrt(float(np.max(np.diag(self._P)[:2])))
        self.fix_pending = "range" in self.measurement_models and prior_std > scale
        self.fixes: list[float] = []
        self.fix_abandoned: float | None = None
        self._waited = 0

    # -- what the testbed reads ---------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        """The position ``(2,)`` (the replay odometry model's state; a copy)."""
        return self._x[:2].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        return self._P[:2, :2].copy()

    @property
    def state(self) -> np.ndarray:
        """``(p_x, p_y, delta, b)``, then ``(l_x, l_y)`` with a lever arm, the anchors' biases
        and offsets, and the tag's pattern ``(c, s)``, each where held (a copy)."""
        return self._x.copy()

    @property
    def state_covariance(self) -> np.ndarray:
        return self._P.copy()

    @property
    def heading(self) -> float:
        """``theta = theta_o + delta`` (rad): the dead-reckoned heading corrected."""
        return self.theta_o + float(self._x[2])

    @property
    def gyro_bias(self) -> float:
        """The yaw rate's bias ``b`` (rad/s): measured minus true."""
        return float(self._x[3])

    @property
    def lever_arm(self) -> np.ndarray:
        """The tag's offset ``l`` (m) in the body frame: its estimate, or zero without those states."""
        return self._x[4:6].copy() if self.lever else np.zeros(2)

    @property
    def _anchor_states(self) -> bool:
        """Whether the state holds entries per anchor (biases, offsets): its order is then the
        log's order of the anchors."""
        return self._ie >= 0 or self._ib >= 0

    def _append_anchor_states(self, offsets, bias_std) -> None:
        """The anchors' range biases (prior 0, ``bias_std``) and squared-range offsets (prior
        ``offsets = (mean, spread)``) appended to the state where given (module docstring)."""
        q = self.anchors.shape[0]
        mean, cov = [], []
        self._ib = self._ie = -1  # the first index of b, of e (-1: not states)
        if bias_std is not None:
            std = as_finite_scalar("bias_std", bias_std, positive=True)
            self._ib = self._x.size
            mean.append(np.zeros(q))
            cov.append(np.eye(q) * std * std)
        if offsets is not None:
            e_mean = np.broadcast_to(np.asarray(offsets[0], dtype=float), (q,))
            if not np.all(np.isfinite(e_mean)):
                raise QuadobsError("offsets: expected a finite prior mean (one, or one per anchor)")
            self._ie = self._x.size + q * len(mean)
            mean.append(e_mean.copy())
            cov.append(_offsets_covariance(offsets[1], q))
        if not mean:
            return
        n = self._x.size
        self._x = np.concatenate([self._x, *mean])
        P = np.zeros((self._x.size, self._x.size))
        P[:n, :n] = self._P
        for k, block in enumerate(cov):
            i = n + k * q
            P[i : i + q, i : i + q] = block
        self._P = P

    def _append_pattern_states(self, std) -> None:
        """The tag's pattern ``(c, s)`` appended to the state where ``std`` is given (prior 0 and
        ``std`` each; module docstring)."""
        self._ip = -1
        if std is None:
            return
        var = as_finite_scalar("tag_pattern_std", std, positive=True) ** 2
        n = self._x.size
        self._ip = n
        self._x = np.concatenate([self._x, np.zeros(2)])
        P = np.zeros((n + 2, n + 2))
        P[:n, :n] = self._P
        P[n:, n:] = var * np.eye(2)
        self._P = P

    @property
    def tag_pattern(self) -> np.ndarray:
        """The tag's pattern ``(c, s)`` (m): its estimate, or zero without those states."""
        return self._x[self._ip : self._ip + 2].copy() if self._ip >= 0 else np.zeros(2)

    @property
    def constant_states(self) -> np.ndarray:
        """The indices of the states no process noise moves: the lever arm, each anchor's bias
        and offset, the tag's pattern, where held (:mod:`quadobs.estimators.constants`; the yaw
        rate's bias walks)."""
        q = self.anchors.shape[0]
        parts = [np.arange(4, 6)] if self.lever else []
        parts += [np.arange(i, i + q) for i in (self._ib, self._ie) if i >= 0]
        parts += [np.arange(self._ip, self._ip + 2)] if self._ip >= 0 else []
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)

    @property
    def offsets(self) -> np.ndarray:
        """The anchors' squared-range offsets ``e_h = delta z_h^2 / 2`` (m^2): their estimate, or
        zero without those states."""
        q = self.anchors.shape[0]
        return self._x[self._ie : self._ie + q].copy() if self._ie >= 0 else np.zeros(q)

    @property
    def range_biases(self) -> np.ndarray:
        """The anchors' range biases ``b_h`` (m): their estimate, or zero without those states."""
        q = self.anchors.shape[0]
        return self._x[self._ib : self._ib + q].copy() if self._ib >= 0 else np.zeros(q)

    def predicted_range(self, m: Measurement) -> float:
        """The range ``m`` predicted at the current estimate: from the tag's position, with the
        anchor's offset and bias and the tag's pattern where they are states (:meth:`_range`)."""
        return self._range(self.measurement_models["range"], m, self._x)[0]

    def _range(self, model, m: Measurement, x: np.ndarray) -> tuple[float, float, float]:
        """The range ``rho_h`` predicted at the state ``x``, ``|q - a_h| / s_h`` (the factor of
        ``d rho / d q``) and ``1 / s_h`` (``d rho / d e_h``; 0 where ``s_h = 0``) (module
        docstring). Without offsets ``s_h = |q - a_h|`` and the factor is 1."""
        r = model.h(self._tag(x), m)
        pattern = self._pattern(x, m) if self._ip >= 0 else 0.0
        if self._ie < 0 and self._ib < 0:
            return r + pattern, 1.0, 0.0
        h = m.anchors[0]
        s = math.sqrt(max(r * r + 2.0 * float(x[self._ie + h]), 0.0)) if self._ie >= 0 else r
        b = float(x[self._ib + h]) + pattern if self._ib >= 0 else pattern
        if s <= 0.0:
            return b, 0.0, 0.0
        return s + b, r / s, 1.0 / s

    def _bearing(self, x: np.ndarray, m: Measurement) -> float:
        """The anchor's bearing seen from the tag, from the heading: ``phi_h`` (rad)."""
        d = self.anchors[m.anchors[0]] - self._tag(x)
        return math.atan2(float(d[1]), float(d[0])) - self.theta_o - float(x[2])

    def _pattern(self, x: np.ndarray, m: Measurement) -> float:
        """The tag's pattern's term of a range ``c cos 2 phi_h + s sin 2 phi_h`` (m)."""
        phi = 2.0 * self._bearing(x, m)
        return float(x[self._ip]) * math.cos(phi) + float(x[self._ip + 1]) * math.sin(phi)

    def _tag(self, x: np.ndarray) -> np.ndarray:
        """The tag's position ``q = p + R(theta_o + delta) l`` of the state ``x`` (``p`` without
        a lever arm)."""
        if not self.lever:
            return x[:2]
        return x[:2] + _rotation(self.theta_o + float(x[2])) @ x[4:6]

    def _arc(self, x: np.ndarray, u: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """:func:`arc_step` on the whole state: the lever arm (where a state) is constant."""
        if x.size == 4:
            return arc_step(x, u, h)
        out, F4 = arc_step(x[:4], u, h)
        F = np.eye(x.size)
        F[:4, :4] = F4
        return np.concatenate([out, x[4:]]), F

    @property
    def diverged(self) -> dict | None:
        """``None``, or when and why the filter was given up (:class:`~quadobs.estimators.robust.LockOut`)."""
        return self.lockout.diverged

    # -- the grid and time -------------------------------------------------------------

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Correct with the outputs ``y_h = rho_h^2 / 2 - |a_h|^2 / 2`` present in ``y`` (NaN:
        missing), one range at a time, then predict over ``dt`` with ``u`` held. The ranges of
        a step are taken in the order of their anchors' positions (by ``x``, then ``y``): the
        corrections of a nonlinear model do not commute, and the log's listing of its anchors
        must not change the estimate."""
        q = self.anchors.shape[0]
        u, y = step_operands(u, y, 3, q)
        model = self.measurement_models.get("range")
        if model is None and not np.all(np.isnan(y)):
            raise QuadobsError(f"{self.name}: has no model of range outputs")
        for i in self._grid_order:  # the anchors by position, not by the log's listing
            if math.isnan(y[i]):
                continue
            rho = math.sqrt(max(2.0 * y[i] + float(self.anchors[i] @ self.anchors[i]), 0.0))
            self._latest[i], self._latest_std[i] = y[i], self.range_sigma
            m = Measurement(self._time, "range", rho, (int(i),), self.range_sigma)
            self._range_anchor = int(i)
            self._correct_range(model, m)
            self._starting()
        self._range_anchor = -1
        self._propagate(self.dt, u)
        self._time += self.dt

    def _input_dimension(self) -> int:
        return 3

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        self.theta_o += float(u[2]) * dt
        self._predict(dt, u)

    def _noise(self, dt: float, u: np.ndarray) -> np.ndarray:
        """Van Loan's ``Q_d`` of the model linearised at the interval's middle heading."""
        A = np.zeros((4, 4))
        A[:2, 2] = _rotation(float(self._x[2]) - 0.5 * float(self._x[3]) * dt) @ (_J @ u[:2])
        A[2, 3] = -1.0
        Q = van_loan_interval(A, self.Qc, dt)[1]
        if self._x.size == 4:
            return Q
        out = np.zeros((self._x.size, self._x.size))
        out[:4, :4] = Q
        return out

    def _correct_measurement(self, m: Measurement) -> None:
        model = self.measurement_models.get(m.kind)
        if model is None:
            raise QuadobsError(f"{self.name}: has no model of {m.kind} measurements")
        model.check(m)
        self._range_anchor = m.anchors[0] if m.kind == "range" else -1  # the excess's (_gain)
        if m.kind == "range":
            h = m.anchors[0]
            rho = model.unbiased(m)
            self._latest[h] = 0.5 * rho * rho - 0.5 * float(self.anchors[h] @ self.anchors[h])
            self._latest_std[h] = model.sigma(m)
        self._correct_range(model, m)
        if m.kind == "range":
            self._starting()

    def _starting(self) -> None:
        """Start-up (as the bias filters', :mod:`quadobs.estimators.bias_states`): where the
        prior position's standard deviation exceeds half the anchors' extent ``e = max_h |a_h -
        c|`` (``c`` their centroid; at least ``range_sigma``), the scale on which a range bends
        over the prior and a UKF's sigma points no longer see its slope, once every anchor has a
        range (or two rounds' worth have come, an anchor silent) the position is set by their
        least-squares multilateration with the covariance of that estimator
        (:meth:`_fix_covariance`), and the heading's correction and its bias go back to their
        prior: what the corrections made of them from a prior of tens of metres (a UKF's sigma
        points spread over it) is not kept. After four rounds without a multilateration
        (anchors in too few directions) the prior is kept. The multilateration takes the
        differences of the outputs from their mean
        (:func:`~quadobs.estimators.robust.multilateration`, ``centred``): its fix, like the
        filter, is the same whatever the order of the anchors (from the first anchor's output
        it was not)."""
        if not self.fix_pending:
            return
        q = self.anchors.shape[0]
        self._waited += 1
        if np.isnan(self._latest).any() and self._waited < 2 * q:
            return
        C = np.broadcast_to(np.eye(2), (q, 2, 2))
        fixed = multilateration(C, -self.anchors, self._latest, centred=True)
        if fixed is None and self._waited < 4 * q:
            return
        self.fix_pending = False
        if fixed is not None and fixed[0].shape[0] == 2:
            self._x[:2] = fixed[1]
            self._x[2:] = self._x0[2:]
            self._P = self._P0.copy()
            self._fix_covariance()
            self.fixes.append(self._time)
        else:  # reported without a fix (quadobs.estimators.startup.not_started)
            self.fix_abandoned = self._time

    def _fix_covariance(self) -> None:
        """The fix's position covariance, that of the centred multilateration, written into
        :attr:`_P` (the rest of the state at its prior, :meth:`_starting`).

        Each output ``y_h = rho_h^2 / 2 - |a_h|^2 / 2`` of a measured range ``rho_h = s_h + b_h +
        n_h`` (``s_h^2 = |q - a_h|^2 + 2 e_h``, ``q`` the tag, module docstring; ``e_h = b_h =
        0`` without the anchors' states) is ``-a_h^T q + |q|^2 / 2 + eps_h`` with the error

        .. math:: \\varepsilon_h = \\delta e_h + \\rho_h \\nu_h - \\nu_h^2 / 2, \\qquad
                  \\nu_h = \\delta b_h + n_h

        (``delta e_h``, ``delta b_h``: the offset's and the bias's deviations from their prior
        means; ``n_h`` of variance ``sigma_h^2``, the range's own, else ``range_sigma``). The fix
        is linear in the outputs' differences from their mean, ``q_hat = M G y`` with ``G = I - 1
        1^T / q`` and ``M`` the pseudo-inverse of ``-(a_h - abar)^T``
        (:func:`~quadobs.estimators.robust.multilateration`), so its error is ``M G eps``, of
        covariance

        .. math:: P_{qq} = M G\\, (\\mathrm{diag}(v) + W)\\, G^\\top M^\\top, \\qquad
                  v_h = \\rho_h^2 \\sigma_h^2 + \\sigma_h^4 / 2
                        + \\operatorname{var} e_h + \\rho_h^2 \\operatorname{var} b_h

        and, with the tag's pattern as states, ``W_hk = rho_h rho_k g_h^T P_cs g_k`` (``g_h =
        (cos 2 phi_h, sin 2 phi_h)`` at the fix and the prior heading, ``P_cs`` the pattern's
        prior: one pattern for every anchor, so the outputs' errors are correlated), else ``W =
        0``, to first order in the anchors' states (common means cancel in the differences; ``n_h^2
        / 2`` has the variance ``sigma_h^4 / 2``): the range noise enters once, in ``v``, and its
        normalised error ``(q_hat - q)^T P_qq^-1 (q_hat - q)`` is chi-square with 2 degrees of
        freedom (tests/estimators/test_heading_ekf.py). With a lever arm the position is the
        tag's less its prior mean, ``p_hat = q_hat - R(theta) l_0``, whose error ``(q_hat - q) +
        R (l - l_0)`` has the marginal covariance ``P_qq + R P_l R^T``: that is the position's.
        The fix's error is correlated with the anchors' states (``-M G diag(var e)``, ``-M G
        diag(rho var b)``), with the tag's pattern (``-M G diag(rho) g P_cs``) and with the lever
        arm (``-R P_l``); the filter keeps those states
        independent of it, at their prior (the tag's covariance then errs wide, by ``R P_l
        R^T``): with the cross-covariances ``ukf-height-lever`` was measured worse on the
        wheeled robot (docs/error-sources.md, the order of the anchors). The fix takes the
        ranges as measured: where the constants were started away from zero (a first pass,
        :mod:`quadobs.testbed.logs.constants_start`), their means are not taken off them, and
        the fix is off by what they add, its covariance the started constants'."""
        rows = np.flatnonzero(~np.isnan(self._latest))
        A = self.anchors[rows]
        rho2 = np.maximum(2.0 * self._latest[rows] + np.einsum("hi,hi->h", A, A), 0.0)
        var = self._latest_std[rows] ** 2
        v = rho2 * var + 0.5 * var * var
        P0 = np.diag(self._P0)
        if self._ie >= 0:
            v = v + P0[self._ie + rows]
        if self._ib >= 0:
            v = v + rho2 * P0[self._ib + rows]
        MG = np.linalg.pinv(A.mean(axis=0) - A)
        MG = MG - MG.mean(axis=1, keepdims=True)  # M G: the columns' mean taken out
        V = np.diag(v)
        if self._ip >= 0:  # the tag's pattern: one (c, s) for every anchor, so correlated
            d = A - self._x[:2]
            phi = 2.0 * (np.arctan2(d[:, 1], d[:, 0]) - self.theta_o - float(self._x[2]))
            G = np.column_stack([np.cos(phi), np.sin(phi)])
            rho = np.sqrt(rho2)
            i = self._ip
            V += np.outer(rho, rho) * (G @ self._P0[i : i + 2, i : i + 2] @ G.T)
        self._P[:2, :2] = MG @ V @ MG.T
        if self.lever:
            R = _rotation(self.theta_o + float(self._x[2]))
            self._x[:2] -= R @ self._x0[4:6]
            self._P[:2, :2] += R @ self._P0[4:6, 4:6] @ R.T  # p = q - R l: the lever's share

    def _gain(self, nu: float, S: float, Pxz: np.ndarray, R: float) -> None:
        """Robust rule, gate and lock-out on the innovation ``nu`` (variance ``S``), then the
        update ``x += K nu``, ``P -= K S K^T`` with ``K = P_xz / S`` (``P_xz``: the state's
        cross-covariance with the measurement). Under :class:`~quadobs.estimators.robust.ExcessHuber`
        a range's ``nu`` is first less its expected excess and ``P -= K (S - Var[e | nu]) K^T``."""
        excess = 0.0
        if isinstance(self.robust, ExcessHuber) and self._range_anchor >= 0:
            nu, excess = self._less_excess(nu, S)
        R_w = reweight(self.robust, np.array([nu]), np.array([[S]]), np.array([[R]]))
        if R_w is not None:
            S = S + float(R_w[0, 0]) - R
        self.nis = nu * nu / S
        if R_w is None or (self.gate is not None and self.nis > self.gate):
            self.rejected += 1
            self._watch(False, nu)
            return
        self.corrections += 1
        self._watch(True, nu)
        K = Pxz / S
        self._x = self._x + K * nu
        P = self._P - (S - excess) * np.outer(K, K)
        self._P = 0.5 * (P + P.T)
        if self.lever:
            self._check_lever()

    def _less_excess(self, nu: float, S: float) -> tuple[float, float]:
        """The innovation less its expected non-line-of-sight excess and the excess's variance
        (:class:`~quadobs.estimators.robust.ExcessHuber`), the range's anchor's prior of a
        blocked path carried from its previous range (:meth:`ExcessHuber.prior
        <quadobs.estimators.robust.ExcessHuber.prior>`)."""
        rule, h = self.robust, self._range_anchor
        prior = rule.prior(float(self._blocked[h]), self._time - float(self._blocked_at[h]))
        shift, var, gamma = rule.posterior(nu, S, prior)
        self._blocked[h], self._blocked_at[h] = gamma, self._time
        return nu - shift, var

    def _check_lever(self) -> None:
        """The lever arm's plausibility: where its estimate lies beyond the :data:`LEVER_CHI2`
        quantile of its own prior (``(l - l_0)^T P_l0^-1 (l - l_0)``, 2 degrees of freedom,
        ``l_0`` the filter's own prior mean, which a start of its constants leaves as the
        guard's centre), the offset has taken up what the ranges carry and the filter
        does not model (an anchor's bias left in them, a height), and the filter is reported
        as diverged (its lock-out's record), never summarised as if it had run."""
        lock = self.lockout
        if lock.diverged is not None:
            return
        l = self._x[4:6]
        d = l - self._lever_mean
        if float(d @ d) > LEVER_CHI2 * self._lever_var:
            lock.diverged = {
                "time": self._time,
                "step": int(round(self._time / self.dt)),
                "reason": f"lever arm ({l[0]:.3g}, {l[1]:.3g}) m beyond its prior's 0.999 "
                "quantile: the ranges carry an error the filter does not model (a heading0 or "
                "odometry the ranges contradict, an anchor's bias or height, a stated tag_x, "
                "tag_y off the tag)",
            }

    def _watch(self, accepted: bool, nu: float) -> None:
        """Lock-out: re-initialise the covariance and the position, or give the filter up. A
        re-initialisation also restarts each anchor's chain of a blocked path in line of sight
        (:meth:`_less_excess`): what the ranges said of the sight, read against the estimate
        given up, is not kept."""
        lock, t = self.lockout, self._time
        if not lock.observe(t, accepted, abs(nu)):
            return
        reason, largest = lock.reason(t), lock.largest  # read before the reset clears it
        if lock.reset(t, int(round(t / self.dt)), reason):
            # the position's floor nu^2 alone: the state holds no velocity (an infinite span)
            self._P = reinitialised_covariance(self._P, self._P0, largest, 2, math.inf)
            self._blocked[:] = 0.0
            self._blocked_at[:] = -math.inf
            q = self.anchors.shape[0]
            C = np.broadcast_to(np.eye(2), (q, 2, 2))
            fixed = multilateration(C, -self.anchors, self._latest, centred=True)
            if fixed is not None and fixed[0].size == 2:  # the tag's fix: p = q - R l
                self._x[:2] = fixed[1] - (self._tag(self._x) - self._x[:2])
            elif fixed is not None:
                self._x[fixed[0]] = fixed[1]

    def _predict(self, dt: float, u: np.ndarray) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _correct_range(self, model, m: Measurement) -> None:  # pragma: no cover - interface
        raise NotImplementedError


def _offsets_covariance(spread, q: int) -> np.ndarray:
    """The offsets' prior covariance from ``spread``: a standard deviation (one, or one per
    anchor), or a ``(q, q)`` covariance (symmetric, finite, positive diagonal)."""
    spread = np.asarray(spread, dtype=float)
    if spread.ndim == 2:
        ok = spread.shape == (q, q) and np.all(np.isfinite(spread))
        if not (ok and np.allclose(spread, spread.T) and np.all(np.diag(spread) > 0.0)):
            raise QuadobsError(
                f"offsets: expected a symmetric ({q}, {q}) prior covariance with a positive diagonal"
            )
        try:
            np.linalg.cholesky(spread)
        except np.linalg.LinAlgError:
            raise QuadobsError("offsets: the prior covariance is not positive definite") from None
        return spread.copy()
    if spread.ndim > 1 or spread.size not in (1, q):
        raise QuadobsError(f"offsets: expected one standard deviation, or {q} (one per anchor)")
    std = np.broadcast_to(spread, (q,))
    if not np.all(np.isfinite(std) & (std > 0.0)):
        raise QuadobsError(
            "offsets: expected a positive finite prior standard deviation (one, or one per anchor)"
        )
    return np.diag(std * std)


class HeadingEKF(_HeadingFilter):
    """EKF on ``(p, delta, b)``: exact mean prediction, covariance through its Jacobian.

    Parameters
    ----------
    anchors : array_like (q, 2)
    x0 : array_like (4,)
        ``(p_x, p_y, delta, b)``.
    P0 : array_like (4,) or (4, 4)
        Initial covariance (its diagonal, or whole).
    dt : float
        The grid's step (s) of :meth:`step`.
    q_xy, q_theta, q_bias : float
        White-noise intensities on ``p'`` (m^2/s), ``delta'`` (rad^2/s), ``b'`` (rad^2/s^3).
    range_sigma : float
        Standard deviation of a range without its own (m).
    heading0 : float
        The dead-reckoned heading at the start (rad), for :attr:`heading`.
    gate : float, optional
        Reject a correction whose NIS exceeds it (one degree of freedom per measurement).
    robust : ChiSquareGate, Huber or ExcessHuber, optional
        :class:`~quadobs.estimators.robust.ExcessHuber`: a range's innovation less its expected
        non-line-of-sight excess, each anchor's chain of a blocked path kept by the filter
        (:meth:`_less_excess`), then Huber's weight; the update ``x += K nu'``, ``P -= (S -
        Var[e | nu]) K K^T``. A TDOA takes Huber's weight alone.
    lockout : LockOut, optional
    measurements : list of MeasurementModel, optional
        Default: ranges to ``anchors``.
    lever_arm_std : float, optional
        With it, the tag's lever arm ``(l_x, l_y)`` (m, body frame) as two more states, prior
        mean ``lever_arm`` and this standard deviation each (e.g. :data:`LEVER_ARM_STD`);
        without, the tag is at ``p``.
    lever_arm : array_like (2,)
        The lever arm's prior mean (m; default 0: nobody measured where the tag sits).
    offsets : (float or array_like, float or array_like), optional
        With it, each anchor's squared-range offset ``e_h`` as a state: its prior mean (m^2, one,
        or one per anchor) and either its standard deviation (m^2, one, or one per anchor) or
        its ``(q, q)`` covariance (m^4; module docstring). Ranges only.
    bias_std : float, optional
        With it, each anchor's range bias ``b_h`` as a state, prior mean 0 and this standard
        deviation (m).
    tag_pattern_std : float, optional
        With it, the tag's pattern ``(c, s)`` as two more states, prior mean 0 and this
        standard deviation each (m; e.g. :data:`TAG_PATTERN_STD`; module docstring). Ranges
        only.

    Notes
    -----
    ``P = F P F^T + Q_d`` over an interval (module docstring); a measurement ``z`` with
    ``H = [dh/dp, 0, 0]``: ``S = H P H^T + sigma^2``, ``K = P H^T / S``, ``x += K (z - h(p))``,
    ``P -= K S K^T``. With a lever arm (``lever_arm_std``), ``H = dh/dq [I, R(theta) J l, 0,
    R(theta)]`` at the tag's position ``q``; with offsets and biases, ``dh/dq`` is scaled by
    ``|q - a_h| / s_h`` and ``H`` gains ``1`` at ``b_h`` and ``1 / s_h`` at ``e_h`` (module
    docstring; :meth:`linearized`).
    """

    name = "ekf-heading"

    def _predict(self, dt: float, u: np.ndarray) -> None:
        Q = self._noise(dt, u)
        self._x, F = self._arc(self._x, u, dt)
        P = F @ self._P @ F.T + Q
        self._P = 0.5 * (P + P.T)

    def linearized(self, model, m: Measurement, x: np.ndarray) -> tuple[float, np.ndarray]:
        """The measurement ``m`` predicted at the state ``x`` and its Jacobian ``d h / d x``
        (class docstring; the model's own Jacobian on the tag's position, carried to the state)."""
        q = self._tag(x)
        z, scale, de = self._range(model, m, x)
        H = np.zeros(x.size)
        H[:2] = scale * model.jacobian(q, m)
        if self._ie >= 0:
            H[self._ie + m.anchors[0]] = de
        if self._ib >= 0:
            H[self._ib + m.anchors[0]] = 1.0
        if self.lever:
            Rt = _rotation(self.theta_o + float(x[2]))
            H[2] = H[:2] @ Rt @ _J @ x[4:6]
            H[4:6] = H[:2] @ Rt
        if self._ip >= 0:
            self._pattern_jacobian(x, m, H)
        return z, H

    def _pattern_jacobian(self, x: np.ndarray, m: Measurement, H: np.ndarray) -> None:
        """The pattern's term's derivatives added to ``H``: ``cos 2 phi`` and ``sin 2 phi`` at
        ``(c, s)``, and through ``phi = atan2(a - q) - theta``, ``d phi / d q = (d_y, -d_x) /
        |d|^2`` (``d = a - q``) carried to ``p``, ``delta`` and ``l`` as the range's, and ``d phi
        / d delta = -1``."""
        phi = 2.0 * self._bearing(x, m)
        c, s = float(x[self._ip]), float(x[self._ip + 1])
        dterm = 2.0 * (s * math.cos(phi) - c * math.sin(phi))  # d term / d phi
        H[self._ip], H[self._ip + 1] = math.cos(phi), math.sin(phi)
        d = self.anchors[m.anchors[0]] - self._tag(x)
        dq = dterm * np.array([d[1], -d[0]]) / max(float(d @ d), 1e-12)  # d term / d q
        H[:2] += dq
        H[2] -= dterm
        if self.lever:
            Rt = _rotation(self.theta_o + float(x[2]))
            H[2] += dq @ Rt @ _J @ x[4:6]
            H[4:6] += dq @ Rt

    def _correct_range(self, model, m: Measurement) -> None:
        z, H = self.linearized(model, m, self._x)
        PHt = self._P @ H
        s = model.sigma(m)
        R = s * s
        self._gain(model.unbiased(m) - z, float(H @ PHt) + R, PHt, R)


class HeadingUKF(_HeadingFilter):
    """UKF on ``(p, delta, b)``: sigma points through the exact mean map and the measurement.

    Parameters as :class:`HeadingEKF`, and the scaled unscented transform's ``alpha``,
    ``beta``, ``kappa`` (defaults 1, 2, 0, as :class:`~quadobs.estimators.kalman.UnscentedKalmanFilter`).

    Notes
    -----
    Sigma points ``X_0 = x``, ``X_i, X_(n+i) = x +- sqrt(n + lambda) L_i`` (``L`` the Cholesky
    factor of ``P``, its anchors' states taken in the order of the anchors' positions);
    prediction ``x = sum W^m_i f(X_i)``, ``P = sum W^c_i (f(X_i) - x)(.)^T + Q_d``;
    a measurement ``Z_i = h(X_i)``, ``S = sum W^c_i (Z_i - z)^2 + sigma^2``,
    ``P_xz = sum W^c_i (X_i - x)(Z_i - z)``, ``K = P_xz / S``.

    The Cholesky factor is triangular: its columns, so the sigma points, and so (the
    measurement being nonlinear) the transform's mean and covariance depend on the order of
    the state's entries. With the anchors' biases or offsets as states that order would be
    the log's listing of its anchors; the factor takes them instead in the order of the
    anchors' positions (by ``x``, then ``y``; :meth:`_canonical_order`), which no listing
    changes, so that (with the centred start-up fix) the filter is the same whatever the order
    of the anchors, to rounding. The symmetric root ``P^(1/2)``, equivariant under any
    permutation, would do as well, and was measured worse on four logs of five of the wheeled robot
    (docs/error-sources.md).
    """

    name = "ukf-heading"

    def __init__(self, anchors, *, alpha=1.0, beta=2.0, kappa=0.0, **kwargs) -> None:
        super().__init__(anchors, **kwargs)
        n = self._x.size
        lam = alpha**2 * (n + kappa) - n
        if not n + lam > 0:
            raise QuadobsError(f"alpha, kappa: need alpha^2 (n + kappa) > 0, got {n + lam:.3g}")
        self._scale = math.sqrt(n + lam)
        self._wm = np.full(2 * n + 1, 0.5 / (n + lam))
        self._wm[0] = lam / (n + lam)
        self._wc = self._wm.copy()
        self._wc[0] += 1.0 - alpha**2 + beta
        self._root_order = self._canonical_order()

    def _sigma(self) -> np.ndarray:
        o = self._root_order  # the anchors' states in the order of their positions (docstring)
        P = self._P if o is None else self._P[np.ix_(o, o)]
        try:
            L = np.linalg.cholesky(P)
        except np.linalg.LinAlgError:
            w, U = np.linalg.eigh(P)
            L = U * np.sqrt(np.maximum(w, 0.0))
        if o is None:
            D = self._scale * L.T
        else:
            D = np.empty_like(L)
            D[:, o] = self._scale * L.T  # column k of the factor, back in the state's order
        return np.concatenate([self._x[None], self._x + D, self._x - D])

    def _canonical_order(self) -> np.ndarray | None:
        """The state's indices with each block of anchors' states (biases, offsets) in the
        order of the anchors' positions (by ``x``, then ``y``), not the log's: the order of
        the Cholesky factor of :meth:`_sigma`; None without anchors' states (the state's own)."""
        if not self._anchor_states:
            return None
        order = np.arange(self._x.size)
        rank = np.lexsort(self.anchors.T[::-1])  # by x, then y
        for first in (self._ib, self._ie):
            if first >= 0:
                order[first : first + rank.size] = first + rank
        return order

    def _predict(self, dt: float, u: np.ndarray) -> None:
        Q = self._noise(dt, u)
        if self._ie >= 0 or self._ib >= 0:  # the anchors' states: every point at once
            X = arc_points(self._sigma(), u, dt)
        else:
            X = np.array([self._arc(xi, u, dt)[0] for xi in self._sigma()])
        x = self._wm @ X
        dX = X - x
        P = (dX.T * self._wc) @ dX + Q
        self._x, self._P = x, 0.5 * (P + P.T)

    def _points_ranges(self, model, m: Measurement, X: np.ndarray) -> np.ndarray:
        """:meth:`_range` of every sigma point (rows of ``X``) at once, for a range with the
        anchors' states; one at a time otherwise."""
        if m.kind != "range" or not isinstance(model, RangeModel) or self._ie < 0:
            return np.array([self._range(model, m, xi)[0] for xi in X])
        h = m.anchors[0]
        q = X[:, :2]
        theta = self.theta_o + X[:, 2]
        if self.lever:
            c, s = np.cos(theta), np.sin(theta)
            q = q + np.column_stack([c * X[:, 4] - s * X[:, 5], s * X[:, 4] + c * X[:, 5]])
        d = q - model.anchors[h]
        out = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) + 2.0 * X[:, self._ie + h], 0.0))
        if self._ip >= 0:  # the tag's pattern: the anchor's bearing from the tag, less theta
            phi = 2.0 * (np.arctan2(-d[:, 1], -d[:, 0]) - theta)
            out = out + X[:, self._ip] * np.cos(phi) + X[:, self._ip + 1] * np.sin(phi)
        return out + X[:, self._ib + h] if self._ib >= 0 else out

    def _correct_range(self, model, m: Measurement) -> None:
        X = self._sigma()
        Z = self._points_ranges(model, m, X)
        z = float(self._wm @ Z)
        dZ = Z - z
        s = model.sigma(m)
        R = s * s
        S = float(self._wc @ (dZ * dZ)) + R
        Pxz = ((X - self._x).T * self._wc) @ dZ
        self._gain(model.unbiased(m) - z, S, Pxz, R)


class HeadingCascade(InnerClock, Gated, Immersed):
    """A cascade: an observer driven by the odometry turned by a heading filter's estimate.

    The observer (``inner``, e.g. the augmented observer of the replay's odometry model) takes
    the held input ``u = (v_x, v_y, omega)`` of the dead reckoning; the cascade gives it instead,
    over each interval ``[t, t + h)``, the mean velocity of the heading filter's model over that
    interval at its current estimate (the chord of :func:`arc_step`),

    .. math:: u' = \\big(\\operatorname{sinc}(\\hat b h / 2)\\, R(\\hat\\delta - \\hat b h / 2)\\,
              u_{xy},\\ \\omega\\big),

    so the observer integrates the odometry along the estimated heading, not the drifting dead
    reckoning. Both correct with every measurement; the estimate read is the observer's: a
    cascade, not a joint estimator.

    The turned input carries the heading filter's error: with ``G = d u' / d(delta, b)`` (the
    last two columns of :func:`arc_step`'s Jacobian over ``h``, divided by ``h``; ``G = [w, .]``
    with ``w = R(delta) J u_xy`` across the track where ``b = 0``) and ``P_(delta b)`` the filter's
    covariance of ``(delta, b)``, the velocity's error has the covariance ``G P_(delta b) G^T``
    (``v^2 P_delta`` across the track). Where ``input_noise`` is given, before each interval the
    cascade writes there the intensity

    .. math:: Q_u = h\\, G P_{\\delta b} G^\\top \\quad (\\mathrm{m^2/s}),

    whose integral over the interval is the variance ``h^2 G P G^T`` of the displacement the
    turned input makes over it; the observer's noise map adds it to its own white noise on
    ``x'``. The intervals' errors are taken as independent, a lower bound: the heading's error
    persists over many of them.

    Parameters
    ----------
    observer : Estimator
        Takes the interface in time with the input ``(v_x, v_y, omega)``.
    heading : HeadingEKF or HeadingUKF
    input_noise : ndarray (2, 2), optional
        Where the cascade writes ``Q_u`` (in place) for the observer's noise map to add; the
        grid's :meth:`step` leaves it as it is (the observer's fixed ``V`` there).
    """

    def __init__(
        self,
        observer: Estimator,
        heading: _HeadingFilter,
        input_noise: np.ndarray | None = None,
    ) -> None:
        self.inner, self.heading_filter = observer, heading
        self.name = f"{observer.name}-heading"
        self._u = np.zeros(3)
        self.input_noise = input_noise
        self.immersion = observer.immersion if isinstance(observer, Immersed) else None  # type: ignore[assignment]

    gate = property(lambda self: getattr(self.inner, "gate", None))
    corrections = property(lambda self: getattr(self.inner, "corrections", 0))
    rejected = property(lambda self: getattr(self.inner, "rejected", 0))

    def _set_time(self, value: float) -> None:
        self.inner.time = value
        self.heading_filter.time = value

    def _turned(self, u: np.ndarray, h: float) -> np.ndarray:
        """The input ``u'`` of the observer over the next ``h`` seconds (class docstring), and
        the intensity of its error written into :attr:`input_noise`."""
        f = self.heading_filter
        x = f._x
        out = np.array(u, dtype=float)
        if h > 0.0:
            x_next, F = arc_step(x, out, h)
            out[:2] = (x_next[:2] - x[:2]) / h
            if self.input_noise is not None:
                G = F[:2, 2:] / h  # d u' / d (delta, b)
                Q = h * (G @ f._P[2:4, 2:4] @ G.T)
                self.input_noise[...] = 0.5 * (Q + Q.T)
        return out

    def hold(self, u) -> None:
        self.heading_filter.hold(u)
        self._u = self.heading_filter.held_input()

    def predict(self, t) -> None:
        h = self.heading_filter._interval(t)
        self.inner.hold(self._turned(self._u, h))
        self.inner.predict(t)
        self.heading_filter.predict(t)

    def correct(self, m: Measurement) -> None:
        self.heading_filter.correct(m)
        self.inner.correct(m)
        self.nis = self.inner.nis

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """The grid's step: the observer with the turned input, then the heading filter."""
        self.inner.step(self._turned(np.asarray(u, dtype=float), self.heading_filter.dt), y)
        self.heading_filter.step(u, y)
        self.nis = self.inner.nis
