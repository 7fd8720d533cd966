"""A grid world's ranges handed to an estimator one at a time, as a replay hands a log's.

On the physics grid a world samples its ranges as the outputs ``y_h = rho_h^2 / 2 - |a_h|^2 / 2``
of the step (NaN where none). :class:`RangesInTime` turns each sample back into its range
``rho_h = sqrt(2 y_h + |a_h|^2)`` (exact: the square is what the output holds), corrects the
wrapped estimator with it as a :class:`~quadobs.core.measurements.Measurement` of the stated
standard deviation, then holds ``u`` and predicts to the end of the step:

.. code-block:: text

    for each range h sampled at t_k: correct(Measurement(t_k, "range", rho_h, (h,), sigma))
    hold(u_k); predict(t_k + dt)

which is what the replay in time does with the same samples read from a log
(:class:`~quadobs.testbed.logs.events.InTimeOnGrid`). The augmented observer then takes each
range with its own output variance ``rho^2 sigma^2 + sigma^4 / 2`` and the state-dependent
process noise ``V(z)`` (:mod:`quadobs.estimators.augmented_tuning`) rather than the grid's
constant ``R`` and ``V``. A step costs the interval's prediction and each range's correction,
both compiled and free of allocation (:mod:`quadobs.estimators.augmented_in_time`), and the
interface's Python around them: on ``quadrotor-uwb`` 24 us of CPU per 1 ms step without a
range and 32 us with one (62 us and 94 us with only the exponentials' series compiled; a
2-core machine under load), some 5 to 12 times the compiled grid step (``quadobs bench``:
``observer_in_time_step_us`` beside ``grid_step_us`` and ``in_time_numpy_step_us``).
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.core.measurements import Measurement
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.base import Gated, Immersed, InnerClock, step_operands

__all__ = ["RangesInTime"]


class RangesInTime(InnerClock, Gated, Immersed):
    """``inner`` stepped on the grid through its interface in time (module docstring).

    Parameters
    ----------
    inner : AugmentedObserver
        Its first ``q`` outputs are the ranges to the anchors of its range model.
    dt : float
        The grid step (s).
    range_sigma : float
        The stated standard deviation of a range (m).
    name : str, optional
        Default: the inner estimator's.

    Attributes
    ----------
    q : int
        The outputs ``y`` holds (the inner observer's ranges).
    nis : float
        The sum of the scalar corrections' NIS over the step: for independent outputs, the
        NIS of their joint correction (NaN where no range was sampled).
    """

    inner: AugmentedObserver

    def __init__(
        self, inner: AugmentedObserver, dt: float, range_sigma: float, name: str | None = None
    ) -> None:
        self.inner = inner
        self.name = name or inner.name
        self.dt = float(dt)
        self.range_sigma = float(range_sigma)
        anchors = inner.measurement_models["range"].anchors
        self._a2 = np.einsum("hi,hi->h", anchors, anchors)
        self._p, self.q = inner.immersion.system.p, inner.immersion.system.q
        self.nis = math.nan

    gate = property(lambda self: self.inner.gate)
    corrections = property(lambda self: self.inner.corrections)
    rejected = property(lambda self: self.inner.rejected)
    immersion = property(lambda self: self.inner.immersion)

    def step(self, u, y) -> None:
        """Correct with each range sampled in ``y``, then hold ``u`` and predict over the step."""
        u, y = step_operands(u, y, self._p, self.q)
        est, t = self.inner, self.inner.time
        nis = math.nan
        for h in range(self._a2.size):
            yh = y[h]
            if yh != yh:  # NaN: no sample
                continue
            rho = math.sqrt(max(2.0 * yh + self._a2[h], 0.0))
            est.correct(Measurement(t, "range", rho, (h,), self.range_sigma))
            nis = est.nis if nis != nis else nis + est.nis
        est.hold(u)
        est.predict(t + self.dt)
        self.nis = nis
