"""Reference trajectories: per-axis sums of sinusoids plus offsets and a constant velocity.

.. math::

    p_i(t) = o_i + w_i t + \\sum_k a_k \\cos(\\omega_k t + \\varphi_k) \\quad (\\text{terms on axis } i),

with analytic derivatives of every order, so the commanded acceleration, the jerk and
higher derivatives (needed by the PE conditions of ``000_f34cd1199256bdad.txt``
section 5) are exact. A ``sin`` term is stored as ``cos`` with its phase lowered by
``pi/2``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import QuadobsError, as_array

__all__ = ["SinusoidTrajectory"]


@dataclass(frozen=True, eq=False)
class SinusoidTrajectory:
    """A smooth reference ``p(t)`` in ``R^dim``.

    Parameters
    ----------
    offset : array_like (dim,)
        Constant offsets ``o``.
    terms : array_like (K, 4)
        Rows ``(axis, amplitude, omega, phase)`` of the cosine terms; ``omega`` in rad/s.
    velocity : array_like (dim,), optional
        Constant-velocity part ``w`` (zero by default).
    """

    offset: np.ndarray
    terms: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    velocity: np.ndarray | None = None

    def __post_init__(self) -> None:
        offset = as_array("trajectory.offset", self.offset, (None,))
        dim = offset.shape[0]
        if dim not in (2, 3):
            raise QuadobsError(f"trajectory.offset: expected 2 or 3 entries (the dimension), got {dim}")
        terms = as_array("trajectory.terms", self.terms).reshape(-1, 4)
        axes = terms[:, 0]
        if np.any((axes != np.round(axes)) | (axes < 0) | (axes >= dim)):
            raise QuadobsError(f"trajectory.terms: axis must be an integer in [0, {dim - 1}]")
        vel = np.zeros(dim) if self.velocity is None else as_array("trajectory.velocity", self.velocity, (dim,))
        for name, arr in (("offset", offset), ("terms", terms), ("velocity", vel)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def dim(self) -> int:
        return self.offset.shape[0]

    def derivative(self, t, order: int = 0) -> np.ndarray:
        """``d^order p / dt^order`` at times ``t`` (scalar or ``(T,)``); returns ``(dim,)`` or ``(T, dim)``."""
        t = np.asarray(t, dtype=float)
        scalar = t.ndim == 0
        tt = np.atleast_1d(t)
        out = np.zeros((tt.size, self.dim))
        if order == 0:
            out += self.offset + np.outer(tt, self.velocity)
        elif order == 1:
            out += self.velocity
        if self.terms.size:
            axis = self.terms[:, 0].astype(int)
            amp, om, ph = self.terms[:, 1], self.terms[:, 2], self.terms[:, 3]
            vals = amp * om**order * np.cos(np.outer(tt, om) + ph + order * np.pi / 2)  # (T, K)
            np.add.at(out.T, axis, vals.T)
        return out[0] if scalar else out

    def position(self, t) -> np.ndarray:
        return self.derivative(t, 0)

    def velocity_at(self, t) -> np.ndarray:
        return self.derivative(t, 1)

    def acceleration(self, t) -> np.ndarray:
        return self.derivative(t, 2)

    def step_accelerations(self, t0: float, dt: float, steps: int) -> np.ndarray:
        """The acceleration to hold over each step ``[t_k, t_k + dt)``, ``t_k = t0 + k dt``.

        It is the mean acceleration over the step, ``(v(t_{k+1}) - v(t_k)) / dt``, so that a
        double integrator driven by it (exactly, as MuJoCo's RK4 does) has the reference
        velocity at every step boundary. Returns ``(steps, dim)``.
        """
        v = self.derivative(t0 + dt * np.arange(steps + 1), 1)
        return np.diff(v, axis=0) / dt
