"""The Crazyflie's rotors as identified: rotor speed with asymmetric spin-up and spin-down, thrust from speed.

The rotor model of [DRONEMODELS] (entry ``cf2x_L250``, ``rotor_dyn_coef`` and
``rpm2thrust``), in revolutions per minute ``w`` for a commanded speed ``w_c``:

.. math::

    \\dot w = \\begin{cases} k_u (w_c - w) & w_c > w \\text{ (spinning up)} \\\\
                             k_d (w_c^2 - w^2) & w_c \\le w \\text{ (spinning down)}
              \\end{cases}, \\qquad T(w) = a_1 w + a_2 w^2 .

Linearised at the hover speed ``w_h`` (``T(w_h) = m g / 4``, about 18 970 rpm for the
Crazyflie) the time constants are ``tau_u = 1 / k_u`` = 0.136 s spinning up and
``tau_d = 1 / (2 k_d w_h)`` = 0.108 s spinning down; the thrust follows the speed with the
same time constants (``dT = T'(w_h) dw``). The commanded thrust is clamped to
``[T_min, T_max]`` = [0.0128, 0.12] N (the motors' smallest and largest PWM) while the
motors run, and the command is 0 once they are stopped.

Both laws are integrated exactly over a physics step of length ``h`` with the command
held: ``w(h) = w_c + (w_0 - w_c) exp(-k_u h)`` spinning up and
``w(h) = w_c (w_0 + w_c s) / (w_c + w_0 s)``, ``s = tanh(k_d w_c h)``, spinning down
(``w_0 / (1 + k_d w_0 h)`` when ``w_c = 0``). The compiled step is
:func:`quadobs._kernels.quadrotor.rotor_step`; :meth:`RotorModel.step` is its NumPy
reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = ["IDENTIFIED", "RotorModel"]

_G = 9.81


@dataclass(frozen=True)
class RotorModel:
    """Rotor-speed dynamics and thrust map of one rotor (see the module docstring).

    Attributes
    ----------
    k_up : float
        Spin-up rate ``k_u`` (1/s).
    k_down : float
        Spin-down coefficient ``k_d`` (1/(s rpm)).
    thrust_coef : tuple of float
        ``(a_1, a_2)`` of ``T(w) = a_1 w + a_2 w^2`` (N per rpm, N per rpm^2).
    thrust_min, thrust_max : float
        Limits of the commanded thrust while the motors run (N).
    """

    k_up: float
    k_down: float
    thrust_coef: tuple[float, float]
    thrust_min: float
    thrust_max: float

    def thrust(self, w):
        """``T(w)`` (N), never below 0."""
        a1, a2 = self.thrust_coef
        w = np.asarray(w, dtype=float)
        return np.maximum(a1 * w + a2 * w * w, 0.0)

    def speed(self, thrust):
        """The speed ``w`` (rpm) at which the rotor gives ``thrust`` (N >= 0): the positive root of ``T(w)``."""
        a1, a2 = self.thrust_coef
        thrust = np.asarray(thrust, dtype=float)
        return (-a1 + np.sqrt(a1 * a1 + 4.0 * a2 * thrust)) / (2.0 * a2)

    def hover_speed(self, mass: float) -> float:
        """``w_h`` (rpm): each of four rotors carries a quarter of ``m g``."""
        return float(self.speed(mass * _G / 4.0))

    def time_constants(self, mass: float) -> tuple[float, float]:
        """``(tau_u, tau_d)`` (s): the dynamics linearised at the hover speed."""
        return 1.0 / self.k_up, 1.0 / (2.0 * self.k_down * self.hover_speed(mass))

    def with_time_constants(self, mass: float, tau_up: float, tau_down: float) -> RotorModel:
        """The same rotor with the time constants at hover ``tau_up``, ``tau_down`` (s)."""
        return replace(
            self, k_up=1.0 / tau_up, k_down=1.0 / (2.0 * tau_down * self.hover_speed(mass))
        )

    def packed(self) -> np.ndarray:
        """``(k_u, k_d, a_1, a_2, T_min, T_max)``: the operand of the compiled step."""
        a1, a2 = self.thrust_coef
        return np.array([self.k_up, self.k_down, a1, a2, self.thrust_min, self.thrust_max])

    def step(self, w0, command, h: float, running: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Speeds after ``h`` seconds from ``w0`` (rpm) with the thrust ``command`` (N) held, and their thrusts.

        The NumPy reference of :func:`quadobs._kernels.quadrotor.rotor_step`.
        """
        w0 = np.asarray(w0, dtype=float)
        if running:
            c = self.speed(np.clip(command, self.thrust_min, self.thrust_max))
        else:
            c = np.zeros_like(w0)
        up = c + (w0 - c) * np.exp(-self.k_up * h)
        s = np.tanh(self.k_down * c * h)
        with np.errstate(invalid="ignore", divide="ignore"):
            down = np.where(
                c > 0.0, c * (w0 + c * s) / (c + w0 * s), w0 / (1.0 + self.k_down * w0 * h)
            )
        w = np.where(c > w0, up, down)
        return w, self.thrust(w)


#: The identified rotor of the Crazyflie 2.x with its standard propellers ([DRONEMODELS],
#: ``cf2x_L250``: ``rotor_dyn_coef = [k_u, 0, 0, k_d]``, ``rpm2thrust = [0, a_1, a_2]``,
#: ``thrust_min``, ``thrust_max``).
IDENTIFIED = RotorModel(
    k_up=7.355623702172756,
    k_down=0.00024443862952110715,
    thrust_coef=(-5.382196214637237e-7, 2.4582929831265485e-10),
    thrust_min=0.012817578393224994,
    thrust_max=0.12,
)


def settled_time(model: RotorModel, w0: float, thrust: float, fraction: float, h: float) -> float:
    """Time (s) for the thrust to cover ``fraction`` of a step from ``T(w0)`` to ``thrust``, stepped by ``h``."""
    start, w, t = float(model.thrust(w0)), np.array([w0]), 0.0
    goal = start + fraction * (thrust - start)
    rising = thrust > start
    while True:
        w, T = model.step(w, thrust, h)
        t += h
        if (T[0] >= goal) if rising else (T[0] <= goal):
            return t
        if t > 10.0:  # pragma: no cover - a stalled rotor
            return math.inf
