"""Reference trajectories: per-axis sums of sinusoids plus offsets and a constant velocity.

.. math::

    p_i(t) = o_i + w_i t + \\sum_k a_k \\cos(\\omega_k t + \\varphi_k) \\quad (\\text{terms on axis } i),

with analytic derivatives of every order, so the commanded acceleration, the jerk and
higher derivatives (needed by the PE conditions of [IFAC2021]
section 5) are exact. A ``sin`` term is stored as ``cos`` with its phase lowered by
``pi/2``.

Coasting segments ``[s, e)`` switch the commanded acceleration off: there the vehicle
keeps its velocity, and afterwards the sinusoidal acceleration resumes from the state
reached. With ``p_0, v_0`` the sinusoidal reference without coasting and ``c = clip(t, s, e)``,
each segment changes the reference by

.. math::

    \\Delta v(t) = -\\big(v_0(c) - v_0(s)\\big), \\qquad
    \\Delta p(t) = -\\big(p_0(c) - p_0(s) - v_0(s)(c - s)\\big) - \\big(v_0(c) - v_0(s)\\big)(t - c),

and the derivatives of order 2 and more are zero inside ``[s, e)`` (taken piecewise: the
jumps at the ends are not differentiated). A segment whose length is a common period of
all the terms leaves no lasting velocity change.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from quadobs.errors import QuadobsError, as_array

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
    coast : array_like (S, 2), optional
        Coasting segments ``(start, end)`` in s, sorted and disjoint, ``0 <= start < end``.
    """

    offset: np.ndarray
    terms: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    velocity: np.ndarray = None  # type: ignore[assignment]  # None: zeros, set by __post_init__
    coast: np.ndarray = None  # type: ignore[assignment]  # None: no segment, set by __post_init__

    def __post_init__(self) -> None:
        offset = as_array("trajectory.offset", self.offset, (None,))
        dim = offset.shape[0]
        if dim not in (2, 3):
            raise QuadobsError(
                f"trajectory.offset: expected 2 or 3 entries (the dimension), got {dim}"
            )
        terms = as_array("trajectory.terms", self.terms).reshape(-1, 4)
        axes = terms[:, 0]
        if np.any((axes != np.round(axes)) | (axes < 0) | (axes >= dim)):
            raise QuadobsError(f"trajectory.terms: axis must be an integer in [0, {dim - 1}]")
        vel = (
            np.zeros(dim)
            if self.velocity is None
            else as_array("trajectory.velocity", self.velocity, (dim,))
        )
        coast = (
            np.zeros((0, 2))
            if self.coast is None
            else as_array("trajectory.coast", self.coast).reshape(-1, 2)
        )
        for i, (start, end) in enumerate(coast):
            if not 0.0 <= start < end:
                raise QuadobsError(
                    f"trajectory.coast[{i}]: expected 0 <= start < end, got start = {start}, end = {end}"
                )
            if i and start < coast[i - 1, 1]:
                raise QuadobsError(
                    f"trajectory.coast[{i}]: segments must be sorted and disjoint, start {start} is before the end "
                    f"{coast[i - 1, 1]} of segment {i - 1}"
                )
        for name, arr in (
            ("offset", offset),
            ("terms", terms),
            ("velocity", vel),
            ("coast", coast),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def dim(self) -> int:
        return self.offset.shape[0]

    def coasting(self, t) -> np.ndarray:
        """Whether the acceleration is switched off at times ``t`` (inside a segment ``[s, e)``); bool like ``t``."""
        t = np.asarray(t, dtype=float)
        inside = np.zeros(t.shape, dtype=bool)
        for start, end in self.coast:
            inside |= (t >= start) & (t < end)
        return inside

    def derivative(self, t, order: int = 0) -> np.ndarray:
        """``d^order p / dt^order`` at times ``t`` (scalar or ``(T,)``); returns ``(dim,)`` or ``(T, dim)``."""
        t = np.asarray(t, dtype=float)
        scalar = t.ndim == 0
        tt = np.atleast_1d(t)
        out = self._sinusoid(tt, order)
        if self.coast.size:
            if order >= 2:
                out[self.coasting(tt)] = 0.0
            elif order == 1:
                for start, end in self.coast:
                    c = np.clip(tt, start, end)
                    out -= self._sinusoid(c, 1) - self._sinusoid(np.array([start]), 1)
            else:
                for start, end in self.coast:
                    c = np.clip(tt, start, end)
                    v_s = self._sinusoid(np.array([start]), 1)
                    dv = self._sinusoid(c, 1) - v_s
                    out -= (
                        self._sinusoid(c, 0)
                        - self._sinusoid(np.array([start]), 0)
                        - v_s * (c - start)[:, None]
                    )
                    out -= dv * (tt - c)[:, None]
        return out[0] if scalar else out

    def _sinusoid(self, tt: np.ndarray, order: int) -> np.ndarray:
        """The reference without coasting, at ``tt (T,)``: ``(T, dim)``."""
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
        return out

    def position(self, t) -> np.ndarray:
        return self.derivative(t, 0)

    def velocity_at(self, t) -> np.ndarray:
        return self.derivative(t, 1)

    def acceleration(self, t) -> np.ndarray:
        return self.derivative(t, 2)

    def step_accelerations(self, t0: float, dt: float, steps: int, *, start: int = 0) -> np.ndarray:
        """The acceleration to hold over each step ``[t_k, t_k + dt)``, ``t_k = t0 + k dt``, ``k = start .. start + steps - 1``.

        It is the mean acceleration over the step, ``(v(t_{k+1}) - v(t_k)) / dt``, so that a
        double integrator driven by it (exactly, as MuJoCo's RK4 does) has the reference
        velocity at every step boundary. A step lying inside a coasting segment gets exactly
        zero (not the rounding left by the difference). Returns ``(steps, dim)``. The times
        are formed from the step index, so the rows of a block starting at step ``start``
        are those of the whole grid from ``t0``, bit for bit, wherever blocks begin.
        """
        t = t0 + dt * np.arange(start, start + steps + 1)
        v = self.derivative(t, 1)
        out = np.diff(v, axis=0) / dt
        for start, end in self.coast:
            out[(t[:-1] >= start) & (t[1:] <= end)] = 0.0
        return out
