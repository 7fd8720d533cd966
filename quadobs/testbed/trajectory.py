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

Stops ``[s, e]`` with ramps of ``tau`` halt the vehicle on its path (a wheeled robot standing
still, its heading held): the reference follows the path ``p_0`` at a warped time ``sigma(t)``,

.. math::

    p(t) = p_0(\\sigma), \\quad v(t) = p_0'(\\sigma)\\, g, \\quad
    a(t) = p_0''(\\sigma)\\, g^2 + p_0'(\\sigma)\\, \\dot g, \\qquad
    \\sigma(t) = \\int_0^t g ,

with the speed factor ``g = 1`` away from the stops, ``g = 0`` on ``[s, e]``, and cosine ramps
``g = (1 + cos(pi u)) / 2``, ``u = (t - s + tau) / tau``, over ``[s - tau, s]`` (none for a stop
at ``s = 0``: the vehicle starts at rest) and ``g = (1 - cos(pi u)) / 2``, ``u = (t - e) / tau``,
over ``[e, e + tau]``: the velocity and the acceleration stay continuous, and the direction of
travel ``p_0'(sigma)`` is defined at rest (:meth:`SinusoidTrajectory.path_velocity`).
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
    stops : array_like (S, 3), optional
        Stops ``(start, end, ramp)`` in s (module docstring), sorted, ``start = 0`` or
        ``start >= ramp``, each ramp clear of the next stop's; not with ``coast``.
    """

    offset: np.ndarray
    terms: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    velocity: np.ndarray = None  # type: ignore[assignment]  # None: zeros, set by __post_init__
    coast: np.ndarray = None  # type: ignore[assignment]  # None: no segment, set by __post_init__
    stops: np.ndarray = None  # type: ignore[assignment]  # None: no stop, set by __post_init__

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
        stops = _checked_stops(self.stops, coast)
        for name, arr in (
            ("offset", offset),
            ("terms", terms),
            ("velocity", vel),
            ("coast", coast),
            ("stops", stops),
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
        """``d^order p / dt^order`` at times ``t`` (scalar or ``(T,)``); returns ``(dim,)`` or ``(T, dim)``.

        With stops, orders 0 to 2 (module docstring); a higher order is refused."""
        t = np.asarray(t, dtype=float)
        scalar = t.ndim == 0
        tt = np.atleast_1d(t)
        if self.stops.size:
            out = self._warped(tt, order)
        else:
            out = self._path(tt, order)
        return out[0] if scalar else out

    def warp(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The warped time ``sigma``, the speed factor ``g`` and its rate ``g'`` at times
        ``t (T,)`` (module docstring; ``sigma = t``, ``g = 1`` without stops)."""
        tt = np.atleast_1d(np.asarray(t, dtype=float))
        sigma, g, g_dot = tt.copy(), np.ones(tt.shape), np.zeros(tt.shape)
        for start, end, tau in self.stops:
            if start > 0.0:  # the ramp down over [start - tau, start]
                u = np.clip((tt - start + tau) / tau, 0.0, 1.0)
                sigma -= 0.5 * tau * (u - np.sin(np.pi * u) / np.pi)
                down = (tt > start - tau) & (tt < start)
                g[down] -= 0.5 * (1.0 - np.cos(np.pi * u[down]))
                g_dot[down] -= 0.5 * np.pi / tau * np.sin(np.pi * u[down])
            sigma -= np.clip(tt, start, end) - start
            g[(tt >= start) & (tt <= end)] = 0.0
            u = np.clip((tt - end) / tau, 0.0, 1.0)  # the ramp up over [end, end + tau]
            sigma -= 0.5 * tau * (u + np.sin(np.pi * u) / np.pi)
            up = (tt > end) & (tt < end + tau)
            g[up] -= 0.5 * (1.0 + np.cos(np.pi * u[up]))
            g_dot[up] += 0.5 * np.pi / tau * np.sin(np.pi * u[up])
        return sigma, g, g_dot

    def path_velocity(self, t) -> np.ndarray:
        """The velocity along the path at the warped time, ``p_0'(sigma(t))``: the direction of
        travel, defined at rest (``(T, dim)``; the velocity itself without stops)."""
        return self._path(self.warp(t)[0], 1)

    def _warped(self, tt: np.ndarray, order: int) -> np.ndarray:
        """The derivative of order 0 to 2 of ``p_0(sigma(t))`` (module docstring)."""
        if order > 2:
            raise QuadobsError(
                f"trajectory.stops: derivatives of order {order} are not defined with stops (at most 2)"
            )
        sigma, g, g_dot = self.warp(tt)
        if order == 0:
            return self._path(sigma, 0)
        if order == 1:
            return self._path(sigma, 1) * g[:, None]
        return self._path(sigma, 2) * (g**2)[:, None] + self._path(sigma, 1) * g_dot[:, None]

    def _path(self, tt: np.ndarray, order: int) -> np.ndarray:
        """The reference without stops at ``tt (T,)``: the sinusoids with the coasting segments."""
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
        return out

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


def _checked_stops(stops, coast: np.ndarray) -> np.ndarray:
    """The stops as ``(S, 3)`` rows ``(start, end, ramp)``, refused (naming the stop) where
    they overlap, a ramp would begin before ``t = 0``, or coasting segments are also given."""
    if stops is None:
        return np.zeros((0, 3))
    stops = as_array("trajectory.stops", stops).reshape(-1, 3)
    if stops.size and coast.size:
        raise QuadobsError("trajectory.stops: not with coasting segments (trajectory.coast)")
    for i, (start, end, tau) in enumerate(stops):
        if not (0.0 <= start < end and tau > 0.0):
            raise QuadobsError(
                f"trajectory.stops[{i}]: expected 0 <= start < end and ramp > 0, got start = "
                f"{start}, end = {end}, ramp = {tau}"
            )
        if 0.0 < start < tau:
            raise QuadobsError(
                f"trajectory.stops[{i}]: the ramp {tau} s down to the stop would begin before "
                f"t = 0 (start {start} s): start at 0 or at least one ramp later"
            )
        if i and start - tau < stops[i - 1, 1] + stops[i - 1, 2]:
            raise QuadobsError(
                f"trajectory.stops[{i}]: its ramp down begins at {start - tau} s, before the "
                f"ramp up of stop {i - 1} ends ({stops[i - 1, 1] + stops[i - 1, 2]} s)"
            )
    return stops
