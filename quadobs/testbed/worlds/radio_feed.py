"""A world's measurements from a simulated UWB radio, each at its own time (``[radio]``).

With a ``[radio]`` table (:func:`quadobs.testbed.uwb.radio_of`) a world measures ranges
(``protocol = "twr"``) or TDOA (``protocol = "tdoa"``) at the radio's event times rather than
ranges on the physics grid: each step ``k`` of length ``dt`` takes the radio's events of
``[t_k, t_k+1)`` from the tag's position and velocity at ``t_k``
(:meth:`~quadobs.testbed.uwb.UwbRadio.take`), and the grid outputs ``y`` stay NaN. The
estimators then run through the interface in time (:meth:`RadioFeed.recorder`):

.. code-block:: text

    hold(u_k); for m in the step's events: predict(m.t); correct(m); predict(t_k+1)

One class for both worlds that carry a radio: the quadrotor and the point mass.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.worlds.point_mass import PointMassWorld

__all__ = ["RadioFeed", "RadioPointMassWorld", "takes_kind"]


def takes_kind(est, kind: str) -> bool:
    """Whether ``est`` has a model of ``kind`` measurements (``measurement_models``; an
    estimator that declares none takes ranges)."""
    models = getattr(est, "measurement_models", None)
    return kind in (models if models is not None else ("range",))


class RadioFeed:
    """The radio of a world (mixed into a :class:`~quadobs.testbed.worlds.base.World`).

    Attributes
    ----------
    radio : UwbRadio or None
        The scenario's radio; ``None`` without a ``[radio]`` table (nothing changes).
    step_events : list of Measurement
        The radio's measurements of the current step.
    step_end : float
        The end of the current step (s).
    event_log : list or None
        When a list, every step's measurements are appended to it (a log export).
    """

    radio = None
    step_events: tuple | list = ()
    step_end = 0.0
    event_log: list | None = None
    dt: float

    def _radio_setup(self, scenario) -> None:
        """The scenario's radio (``None`` without a ``[radio]`` table)."""
        from quadobs.testbed.uwb import radio_of

        self.radio = radio_of(scenario)
        self.step_events = []
        self.step_end = 0.0

    def _radio_take(self, k: int, p: np.ndarray, v: np.ndarray) -> None:
        """The radio's measurements of ``[t_k, t_k+1)``, from the tag at ``p`` moving at ``v`` at ``t_k``."""
        assert self.radio is not None, "called with a radio only"
        t = k * self.dt
        self.step_end = (k + 1) * self.dt
        self.step_events = self.radio.take(t, self.step_end, p, v)
        if self.event_log is not None and self.step_events:
            self.event_log.extend(self.step_events)

    @property
    def radio_kind(self) -> str | None:
        """``"tdoa"`` or ``"range"``: the kind of the radio's measurements (``None`` without one)."""
        if self.radio is None:
            return None
        return "tdoa" if self.radio.config.protocol == "tdoa" else "range"

    def recorder(self, est):
        """What the episode calls for ``est`` each step: :meth:`Estimator.step_and_record`, or,
        with a radio, the interface in time: hold ``u_k``, then for each measurement of the step
        ``predict(m.t)`` and ``correct(m)``, then ``predict(t_k+1)``; the record row as
        :meth:`~quadobs.estimators.base.Estimator.step_and_record` writes it."""
        kind = self.radio_kind
        if kind is None:
            return est.step_and_record
        from quadobs.estimators.base import Gated

        if not takes_kind(est, kind):
            assert self.radio is not None
            raise QuadobsError(
                f"radio.protocol: estimator {est.name!r} takes no {kind} measurements "
                f"(protocol {self.radio.config.protocol!r})"
            )
        gated = isinstance(est, Gated)

        def record(u: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
            n = out.shape[0] - 3
            out[:n] = est.x_hat
            out[n] = est.covariance_trace
            est.hold(u)
            for m in self.step_events:
                est.predict(m.t)
                est.correct(m)
            est.predict(self.step_end)
            out[n + 1] = est.nis
            out[n + 2] = est.rejected if gated else np.nan

        return record


class RadioPointMassWorld(RadioFeed, PointMassWorld):
    """The point-mass world measuring with its radio (:class:`RadioFeed`).

    The point mass flies open loop; the world is still stepped one step at a time
    (``closed_loop``, the estimate unused) so that each step's radio events reach the
    estimators before the next step's. The grid's ranges are drawn as without a radio, and
    left out (``y`` NaN).
    """

    closed_loop = True

    def __init__(self, scenario, sensors, capacity: int, pipelined: bool = False) -> None:
        super().__init__(scenario, sensors, capacity, pipelined=False)
        self._radio_setup(scenario)
        if self.radio is None:
            raise QuadobsError(f"scenario {scenario.name!r}: has no [radio] table")
        self._tag = np.zeros((2, 3))  # a planar tag's position and velocity in the plane z = 0

    def step(self, j: int, estimate: np.ndarray | None = None) -> None:
        self.stepper.step(j)
        row = self.out[j]
        x = row[self.columns.truth]
        dim = x.shape[0] // 2
        if dim == 2:  # the radio's anchors lie in z = 0 (:func:`~quadobs.testbed.uwb.radio_of`)
            self._tag[0, :2], self._tag[1, :2] = x[:2], x[2:]
            self._radio_take(self._k0 + j, self._tag[0], self._tag[1])
        else:
            self._radio_take(self._k0 + j, x[:dim], x[dim:])
        row[self.columns.y] = np.nan
        row[self.columns.measured] = np.nan
