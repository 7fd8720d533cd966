"""The quadrotor's reference and controller: a flight plan over the scenario's trajectory, and a cascaded geometric tracking controller.

* :class:`FlightPlan`: the reference ``r(t)`` and its first two derivatives. The
  scenario's trajectory ``c(tau)`` is followed on its own clock ``tau(t)``, which stands
  still before the take-off ends, in each hover and after the landing starts, and
  slows down and speeds up with cosine ramps in between, so ``r`` is twice
  differentiable; the height is blended from the floor to ``c_z`` during the take-off
  and back during the landing.
* :class:`GeometricController`: the controller of [LEE2010] on SE(3): a PD law on
  position and velocity with the reference acceleration fed forward gives the desired
  thrust vector ``F = m (k_x e_p + k_v e_v + r'' + g e_3)``; its direction and the
  reference yaw give the desired attitude ``R_d``; the attitude error
  ``e_R = vee(R_d^T R - R^T R_d) / 2`` and the body-rate error ``e_W = W`` give the
  torque ``M = J (-k_R e_R - k_W e_W) + W x J W`` [LEE2010, eqs. 15-16], and the mixer
  inverts the map from the four rotor thrusts to the collective thrust ``f = F . R e_3``
  and ``M`` (thrusts clamped to the rotors' limits). The gains come from natural
  frequencies and a damping ratio (``k_x = w_p^2``, ``k_v = 2 zeta w_p``, ``k_R = w_a^2``,
  ``k_W = 2 zeta w_a``), per unit mass and per unit inertia.

The rotor lag. The rotors follow their commands with time constants of 0.136 s spinning
up and 0.108 s spinning down (:mod:`quadobs.testbed.rotors`): a lag the attitude loop
cannot ignore. Linearised about hover, one horizontal axis with a rotor of time constant
``tau`` has the closed-loop characteristic polynomial (:func:`closed_loop_poles`)

.. math::

    s^2 (\tau s^3 + s^2 + (1 + \tau_c s)(k_W s + k_R)) + k_R (1 + \tau_c s)(k_v s + k_x) ,

with ``tau_c = 0`` for commands sent as they are: the attitude part alone is then stable
only while ``k_W > tau k_R``, i.e. ``w_a < 2 zeta / tau`` (13 rad/s at 0.136 s), and the
whole loop with ``w_p`` = 2, ``w_a`` = 12 rad/s is unstable from ``tau`` = 0.128 s.
Lowering ``w_a`` buys little: the best ``w_a`` for rotor time constants from 0.06 to
0.2 s (5 rad/s) leaves a smallest damping ratio of 0.097 and is too slow for the
manoeuvres of ``quadrotor-1beacon``. So the commands invert the identified lag instead
(:func:`lead`, ``control.rotor_lead``): ``T_c = T_d + tau_c dT_d/dt`` with ``tau_c`` the
identified spin-up or spin-down time constant as ``T_d`` rises or falls, the derivative a
difference over the control period low-passed with ``tau_f`` = 0.02 s (so that the jumps
of an estimate, amplified by ``tau_c / tau_f`` rather than ``tau_c rate``, stay small).
With it the gains ``w_p`` = 2 rad/s, ``w_a`` = 12 rad/s, ``zeta`` = 0.9 keep a smallest
damping ratio of 0.54 over true rotor time constants from 0.06 to 0.2 s
(:func:`smallest_damping`; the filter adds a factor ``1 / (1 + tau_f s)`` to the rotor's lag),
and so does the integral action on the position error that takes out a mass or thrust
mismatch (``control.integral_bandwidth`` = 0.5 rad/s, ``k_i = 0.5 k_x``; 1 rad/s would
leave 0.42).

This module needs no MuJoCo: everything is NumPy on the state the world hands over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "CRAZYFLIE",
    "FlightPlan",
    "GeometricController",
    "QuadrotorParameters",
    "closed_loop_poles",
    "smallest_damping",
]

_G = 9.81

#: Time constant (s) of the low-pass on the derivative of the desired thrusts in :func:`lead`.
LEAD_FILTER = 0.02


@dataclass(frozen=True)
class QuadrotorParameters:
    """Rigid-body and rotor figures of a quadrotor in the X configuration.

    Attributes
    ----------
    mass : float
        kg.
    inertia : tuple of float
        Diagonal of the inertia matrix (kg m^2).
    arm : float
        Offset of each rotor along both body axes (m).
    torque_ratio : float
        Drag torque per unit thrust of a rotor (m).
    thrust_max : float
        Largest thrust of one rotor (N).
    spins : tuple of int
        Sign of each rotor's drag torque about the body z axis.
    """

    mass: float
    inertia: tuple[float, float, float]
    arm: float
    torque_ratio: float
    thrust_max: float
    spins: tuple[int, int, int, int] = (-1, 1, -1, 1)

    def mixer(self) -> np.ndarray:
        """``A (4, 4)`` with ``[f, M_x, M_y, M_z] = A T`` for rotor thrusts ``T`` at ``(+-L, +-L)``."""
        L, k = self.arm, self.torque_ratio
        x = np.array([1.0, -1.0, -1.0, 1.0]) * L  # rotor positions, as in models/quadrotor.xml
        y = np.array([-1.0, -1.0, 1.0, 1.0]) * L
        return np.array([np.ones(4), y, -x, k * np.array(self.spins, dtype=float)])


#: The Crazyflie 2.x of ``models/quadrotor.xml`` (figures of drone-models, "cf2x_L250").
CRAZYFLIE = QuadrotorParameters(
    mass=0.0319,
    inertia=(16.8e-6, 16.8e-6, 29.8e-6),
    arm=0.0325,
    torque_ratio=0.00735,
    thrust_max=0.12,
)


def _ramp_integral(
    t: np.ndarray, start: float, r: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A cosine step ``d`` from 0 to 1 over ``[start, start + r]``: its integral, value and derivative at ``t``."""
    x = np.clip(t - start, 0.0, None)
    inside = x < r
    xi = np.minimum(x, r)
    w = math.pi / r
    integral = np.where(inside, 0.5 * (xi - np.sin(w * xi) / w), x - 0.5 * r)
    value = np.where(inside, 0.5 * (1.0 - np.cos(w * xi)), 1.0)
    slope = np.where(inside & (x > 0.0), 0.5 * w * np.sin(w * xi), 0.0)
    return integral, value, slope


def _smoothstep(
    t: np.ndarray, start: float, length: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The quintic step from 0 to 1 over ``[start, start + length]`` and its two derivatives."""
    x = np.clip((t - start) / length, 0.0, 1.0)
    s = x**3 * (10.0 - 15.0 * x + 6.0 * x * x)
    ds = 30.0 * x * x * (1.0 - x) ** 2 / length
    dds = 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x) / length**2
    return s, ds, dds


class FlightPlan:
    """The reference of a flight: take-off, the trajectory on its own clock with hovers, landing.

    Parameters
    ----------
    trajectory : SinusoidTrajectory
        ``c(tau)``, three axes.
    duration : float
        End of the episode; the landing ends there.
    takeoff, landing : float
        Durations (s) of the vertical take-off from and landing on the floor.
    hovers : sequence of (float, float)
        ``(start, end)``: the clock slows to a stop over ``[start, start + ramp]`` and is back
        to full speed at ``end``.
    ramp : float
        Length of the clock's ramps (s).
    floor : float
        Height of the vehicle's centre resting on the floor (m).
    """

    def __init__(
        self, trajectory, duration, *, takeoff, landing, hovers=(), ramp=1.0, floor=0.0
    ) -> None:
        self.trajectory, self.floor, self.ramp = trajectory, float(floor), float(ramp)
        self.takeoff, self.land_start, self.duration = (
            float(takeoff),
            float(duration) - float(landing),
            float(duration),
        )
        # clock events: (start of a cosine step, +1 speeds up, -1 slows down)
        events = [(self.takeoff, 1.0)]
        for a, b in hovers:
            events += [(float(a), -1.0), (float(b) - self.ramp, 1.0)]
        events.append((self.land_start - self.ramp, -1.0))
        self.events = events

    def clock(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``tau(t)``, its rate ``sigma`` in ``[0, 1]`` and ``sigma'``."""
        t = np.asarray(t, dtype=float)
        tau, rate, slope = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        for start, sign in self.events:
            i, v, s = _ramp_integral(t, start, self.ramp)
            tau += sign * i
            rate += sign * v
            slope += sign * s
        return tau, np.clip(rate, 0.0, 1.0), slope

    def moving(self, t) -> np.ndarray:
        """Whether the reference's clock runs at full speed at ``t``."""
        return self.clock(t)[1] >= 1.0 - 1e-12

    def reference(self, t) -> np.ndarray:
        """``r, r', r''`` at ``t`` (scalar or ``(T,)``), shape ``(3, 3)`` or ``(T, 3, 3)``."""
        t = np.asarray(t, dtype=float)
        tau, sig, dsig = self.clock(t)
        tr = self.trajectory
        c0, c1, c2 = tr.derivative(tau, 0), tr.derivative(tau, 1), tr.derivative(tau, 2)
        sig, dsig = sig[..., None], dsig[..., None]
        v = c1 * sig
        a = c2 * sig * sig + c1 * dsig
        up, dup, ddup = _smoothstep(t, 0.0, self.takeoff)
        down, ddown, dddown = _smoothstep(t, self.land_start, self.duration - self.land_start)
        s, ds, dds = up - down, dup - ddown, ddup - dddown
        h = c0[..., 2] - self.floor
        r = np.array(c0, dtype=float)
        r[..., 2] = self.floor + s * h
        rv, ra = np.array(v), np.array(a)
        rv[..., 2] = ds * h + s * v[..., 2]
        ra[..., 2] = dds * h + 2.0 * ds * v[..., 2] + s * a[..., 2]
        return np.stack([r, rv, ra], axis=-2)


class GeometricController:
    """The cascaded geometric tracking controller of [LEE2010] with a rotor mixer (see the module docstring).

    Parameters
    ----------
    params : QuadrotorParameters
    position_bandwidth, attitude_bandwidth : float
        Natural frequencies ``w_p``, ``w_a`` (rad/s) of the position and attitude loops.
    damping : float
        Damping ratio ``zeta`` of both loops.
    max_tilt : float
        Largest tilt of the desired thrust vector (rad).
    """

    def __init__(
        self,
        params: QuadrotorParameters,
        position_bandwidth=2.0,
        attitude_bandwidth=12.0,
        damping=0.9,
        max_tilt=0.6,
    ) -> None:
        self.p = params
        self.kx, self.kv = position_bandwidth**2, 2.0 * damping * position_bandwidth
        self.kR, self.kW = attitude_bandwidth**2, 2.0 * damping * attitude_bandwidth
        self.J = np.array(params.inertia, dtype=float)
        self.mix_inv = np.linalg.inv(params.mixer())
        self.tan_tilt = math.tan(max_tilt)
        self.thrusts = np.zeros(4)

    def thrust_vector(self, p, v, ref) -> np.ndarray:
        """Desired force ``F`` (N), world frame, its tilt limited and pointing up."""
        acc = self.kx * (ref[0] - p) + self.kv * (ref[1] - v) + ref[2]
        acc[2] = max(acc[2] + _G, 0.2 * _G)
        horiz = math.hypot(acc[0], acc[1])
        limit = self.tan_tilt * acc[2]
        if horiz > limit:
            acc[:2] *= limit / horiz
        return self.p.mass * acc

    def __call__(self, p, v, R, W, ref, yaw: float = 0.0) -> np.ndarray:
        """Rotor thrusts ``(4,)`` (N) from position, velocity, attitude ``R`` (world from body), body rates ``W``."""
        F = self.thrust_vector(p, v, ref)
        b3 = F / np.linalg.norm(F)
        b1c = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        b2 = np.cross(b3, b1c)
        b2 /= np.linalg.norm(b2)
        Rd = np.column_stack([np.cross(b2, b3), b2, b3])
        E = Rd.T @ R
        E = E - E.T
        eR = 0.5 * np.array([E[2, 1], E[0, 2], E[1, 0]])
        J = self.J
        M = J * (-self.kR * eR - self.kW * W) + np.cross(W, J * W)
        f = float(F @ R[:, 2])
        wrench = np.array([f, M[0], M[1], M[2]])
        np.clip(self.mix_inv @ wrench, 0.0, self.p.thrust_max, out=self.thrusts)
        return self.thrusts


def closed_loop_poles(
    position_bandwidth: float,
    attitude_bandwidth: float,
    damping: float,
    tau: float,
    tau_c: float = 0.0,
    tau_f: float = 0.0,
    integral: float = 0.0,
) -> np.ndarray:
    """Roots of the hover-linearised closed loop of one horizontal axis, rotor time constant ``tau``, lead ``tau_c`` filtered by ``tau_f``.

    ``x'' = g theta``, ``J theta'' = M`` delayed by ``(1 + tau_c s) / ((1 + tau s)(1 + tau_f s))``,
    ``M = J (-k_R (theta - theta_d) - k_W theta')``, ``g theta_d = -(k_x x + k_v x')``: the
    roots of ``s^2 (s^2 (1 + tau s)(1 + tau_f s) + (1 + tau_c s)(k_W s + k_R)) + k_R (1 + tau_c s)(k_v s + k_x)``;
    with the integral action ``k_i = integral k_x`` on the position error, of that polynomial
    times ``s`` plus ``k_R (1 + tau_c s) k_i``.
    """
    P = np.polynomial.polynomial
    kx, kv = position_bandwidth**2, 2.0 * damping * position_bandwidth
    kR, kW = attitude_bandwidth**2, 2.0 * damping * attitude_bandwidth
    lead = [1.0, tau_c]
    lag = P.polymul([0.0, 0.0, 1.0], P.polymul([1.0, tau], [1.0, tau_f]))
    inner = P.polyadd(lag, P.polymul(lead, [kR, kW]))
    if integral:
        ki = integral * kx
        full = P.polyadd(
            P.polymul([0.0, 0.0, 0.0, 1.0], inner), P.polymul(lead, [kR * ki, kR * kx, kR * kv])
        )
    else:
        full = P.polyadd(P.polymul([0.0, 0.0, 1.0], inner), P.polymul(lead, [kR * kx, kR * kv]))
    return np.roots(full[::-1])


def smallest_damping(
    position_bandwidth: float,
    attitude_bandwidth: float,
    damping: float,
    taus,
    tau_c: float = 0.0,
    tau_f: float = 0.0,
    integral: float = 0.0,
) -> float:
    """The smallest damping ratio ``-Re(s) / |s|`` of :func:`closed_loop_poles` over the rotor time constants ``taus`` (negative: unstable)."""
    worst = math.inf
    for tau in taus:
        r = closed_loop_poles(
            position_bandwidth, attitude_bandwidth, damping, tau, tau_c, tau_f, integral
        )
        worst = min(worst, float(np.min(-r.real / np.abs(r))))
    return worst


def lead(desired, state, tau_up: float, tau_down: float, rate: float, alpha: float, out) -> None:
    """Thrust commands ``out = T_d + tau s`` that invert a first-order rotor lag; ``state = (T_prev (4), s (4))`` is renewed.

    ``s`` is the derivative of ``T_d`` low-passed, ``s <- s + alpha ((T_d - T_prev) rate - s)``
    (``alpha = 1 / (1 + tau_f rate)``, ``rate`` the control rate in Hz); ``tau`` is ``tau_up``
    where ``s > 0``, ``tau_down`` otherwise. The NumPy reference of
    :func:`quadobs._kernels.quadrotor.lead`.
    """
    desired = np.asarray(desired, dtype=float)
    s = state[4:] + alpha * ((desired - state[:4]) * rate - state[4:])
    out[:] = desired + np.where(s > 0.0, tau_up, tau_down) * s
    state[:4], state[4:] = desired, s
