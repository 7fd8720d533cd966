"""What every online estimator provides, and the optional abilities it may declare.

An estimator is advanced one physics step at a time by :meth:`Estimator.step` and read
through :attr:`Estimator.x_hat` and :attr:`Estimator.x_covariance`. Abilities beyond that
are declared by inheriting the ability classes below, never discovered by probing
attributes, so the testbed can ask ``isinstance(est, Gated)``:

===================  ===============================================================
ability              what the estimator then provides
===================  ===============================================================
:class:`Counted`     ``corrections``: the corrections applied so far
:class:`Gated`       ``gate`` (NIS threshold or ``None``), ``rejected``, and ``corrections`` (a :class:`Counted`)
:class:`Switching`   ``mode``, ``switches`` (``(step, from, to, reason)``) and ``summary()``
:class:`SetValued`   ``bounds (n, 2)``: interval bounds guaranteed to hold the state
:class:`Immersed`    ``immersion``: the :class:`~quadobs.core.immersion.Immersion` it runs on
:class:`Subset`      ``outputs (q_used,)``: the indices of the outputs it reads
:class:`BlockStep`   ``step_block(U, Y, out)``: the records of a block of steps in one call
===================  ===============================================================

Conventions: ``u (p,)`` is the input held over the step, ``y (q,)`` the outputs sampled
at its start with NaN where a sample is missing; vectors are ``(n,)``. A step with a
non-finite ``u``, an infinite ``y`` or a wrong shape is refused with
:class:`~quadobs.errors.QuadobsError` before anything changes (:func:`check_step`).

Constructors share one vocabulary, each keyword where the concept applies: ``x0`` (the
initial estimate of the state, ``(n,)``), ``P0`` (the initial covariance of the estimator's
own state: the augmented one for immersion-based observers), ``gate`` (NIS threshold),
``dt`` (the physics step) and ``backend`` (``"auto"``, ``"numba"`` or ``"numpy"``).

Estimators are made selectable by name through the package entry points of the group
``quadobs.estimators`` (see :mod:`quadobs.testbed.registry`).
"""

from __future__ import annotations

import abc
import math
from typing import TYPE_CHECKING

import numpy as np

from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError, as_array

if TYPE_CHECKING:
    from quadobs.core.immersion import Immersion

__all__ = [
    "BlockStep",
    "Counted",
    "Estimator",
    "Gated",
    "HalfSteps",
    "Immersed",
    "InnerClock",
    "SetValued",
    "Subset",
    "Switching",
    "Wrapper",
    "check_step",
    "covariance_trace",
    "measurement_models",
    "step_operands",
]


class Estimator(abc.ABC):
    """The interface every online estimator implements.

    Subclasses implement :meth:`step` and :attr:`x_hat`; the rest has defaults.

    Attributes
    ----------
    name : str
        The name it is registered and recorded under.
    nis : float
        Normalised innovation squared of the last correction (NaN without one).
    same_as : (str, str) or None
        Where the data made it another estimator of the same set: that estimator's name and
        why (a replay's summary says so); None otherwise.
    """

    name: str = "estimator"
    nis: float = float("nan")
    same_as: tuple[str, str] | None = None

    @abc.abstractmethod
    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Consume the output ``y (q,)`` sampled at the start of a physics step (NaN: missing)
        and the input ``u (p,)`` held over it; afterwards :attr:`x_hat` estimates the state at
        the end of the step."""

    # -- the interface in time ----------------------------------------------------------

    @property
    def time(self) -> float:
        """The time (s) the estimate refers to: advanced by :meth:`predict`, by ``dt`` per
        :meth:`step`; 0 at construction unless set."""
        return self.__dict__.get("_time", 0.0)

    @time.setter
    def time(self, value: float) -> None:
        t = float(value)
        if not math.isfinite(t):
            raise QuadobsError(f"time: expected a finite number of seconds, got {value!r}")
        self._time = t
        lockout = self.__dict__.get("lockout")
        if lockout is not None:  # the lock-out's grace counts from the time set (a log's start)
            lockout.begin(t)

    def hold(self, u) -> None:
        """Hold the input ``u (p,)`` from the current time on, until the next call.

        :meth:`predict` propagates with it (zero until a first call). :meth:`step` uses its own
        ``u`` and leaves the held input as it is.
        """
        p = self._input_dimension()
        self._held = as_array("u", u, (p,)).copy()

    def held_input(self) -> np.ndarray:
        """The input held now, ``(p,)`` (zeros before any :meth:`hold`)."""
        held = self.__dict__.get("_held")
        return np.zeros(self._input_dimension()) if held is None else held

    def predict(self, t: float) -> None:
        """Propagate the estimate from :attr:`time` to ``t`` (s) with the input held since the last
        :meth:`hold`, exactly over any interval where the model allows it.

        With :meth:`correct`, the interface in time: measurements at their own times
        (:class:`~quadobs.core.measurements.Measurement`), the predictor/updater split of Stone
        Soup and filterpy. ``t`` before :attr:`time` is refused; ``t`` equal to it changes nothing.
        """
        dt = self._interval(t)
        if dt > 0.0:
            self._propagate(dt, self.held_input())
        self._time = float(t)

    def correct(self, m: Measurement) -> None:
        """Correct the estimate with one measurement ``m`` taken at the current time
        (``m.t`` equal to :attr:`time` within a nanosecond)."""
        self._check_measurement(m)
        self._correct_measurement(m)

    def correct_many(self, measurements) -> None:
        """Correct the estimate with measurements all taken at the current time.

        Measurements of one time are one measurement vector ``y = (y_1, ..., y_m)``: an
        estimator that can takes them in one joint correction (the batch update, e.g. the
        Kalman filter's ``S = H P H^T + R``, ``K = P H^T S^-1`` with ``H``, ``R`` stacked), as
        :meth:`step` takes a grid step's outputs. The default corrects by them one after the
        other (:meth:`correct`), which for a model linear in the state and uncorrelated noise
        gives the same posterior. Every measurement is checked (its type, its time, a finite
        value) before any is applied.

        Parameters
        ----------
        measurements : sequence of Measurement
            Each at :attr:`time` (as for :meth:`correct`).
        """
        measurements = list(measurements)
        for m in measurements:
            self._check_measurement(m)
        for m in measurements:
            self.correct(m)

    # hooks of the interface in time (estimators that take measurements at their own times)

    def _input_dimension(self) -> int:
        raise QuadobsError(f"{self.name}: does not take measurements at their own times")

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        """Propagate over ``dt > 0`` seconds with ``u`` held."""
        raise QuadobsError(f"{self.name}: does not take measurements at their own times")

    def _correct_measurement(self, m: Measurement) -> None:
        raise QuadobsError(f"{self.name}: does not take measurements at their own times")

    def _interval(self, t) -> float:
        """``t - time``, checked: ``t`` a finite number not before :attr:`time`."""
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise QuadobsError(f"predict: t must be a time in seconds, got {t!r}") from None
        if not math.isfinite(t):
            raise QuadobsError(f"predict: t must be finite, got {t}")
        dt = t - self.time
        if dt < 0.0:
            raise QuadobsError(
                f"{self.name}: predict to t = {t:.9g} s, before its current time {self.time:.9g} s"
            )
        return dt

    def _model_of(self, m: Measurement):
        """The measurement model of ``m``'s kind (``self.measurement_models``), ``m`` checked against it."""
        model = self.__dict__.get("measurement_models", {}).get(m.kind)
        if model is None:
            raise QuadobsError(f"{self.name}: has no model of {m.kind} measurements")
        model.check(m)
        return model

    def _check_measurement(self, m) -> None:
        if not isinstance(m, Measurement):
            raise QuadobsError(f"correct: expected a Measurement, got {type(m).__name__}")
        if abs(m.t - self.time) > 1e-9 * max(1.0, abs(self.time)):
            raise QuadobsError(
                f"{self.name}: a {m.kind} measurement at t = {m.t:.9g} s, but the estimate is at "
                f"{self.time:.9g} s (predict to its time first)"
            )
        if not math.isfinite(m.value):
            raise QuadobsError(
                f"{self.name}: a {m.kind} measurement at t = {m.t:.9g} s is not finite"
            )

    @property
    @abc.abstractmethod
    def x_hat(self) -> np.ndarray:
        """The estimate of the state ``(n,)``: a copy or a read-only array, never a live view
        that a later :meth:`step` changes."""

    @property
    def x_covariance(self) -> np.ndarray | None:
        """The error covariance of :attr:`x_hat` ``(n, n)``, or ``None`` for estimators without one."""
        return None

    @property
    def covariance_trace(self) -> float:
        """The trace the testbed records: of the estimator's own covariance (the augmented one
        for immersion-based observers), NaN without one. Subclasses may keep it cheaper."""
        P = self.x_covariance
        return float(np.trace(P)) if P is not None else float("nan")

    def prepare(self, path: str) -> None:
        """Load (or compile) now what the calls of ``path`` need, rather than in the first of them.

        ``path`` is ``"step"`` (:meth:`step`), ``"record"`` (:meth:`step_and_record`) or
        ``"block"`` (:meth:`BlockStep.step_block`). An episode calls it before its loop, so
        a first run compiles only the kernels its path uses and its timings hold no
        compilation. The default: nothing to prepare.
        """

    def step_and_record(self, u: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
        """:meth:`step`, writing what the testbed records of it into the row ``out (n + 3,)``.

        The record row of a step is

        .. math:: [\\hat x_k,\\ \\operatorname{tr} P_k,\\ \\mathrm{NIS}_k,\\ r_k]

        with ``out[:n]`` :attr:`x_hat` and ``out[n]`` :attr:`covariance_trace` before the
        step, ``out[n + 1]`` :attr:`nis` after it and ``out[n + 2]`` the running count of
        corrections rejected by the gate after it (:attr:`Gated.rejected`; NaN for
        estimators without the ability). Compiled estimators do it in one call.

        Examples
        --------
        >>> import numpy as np
        >>> class Still(Estimator):
        ...     def step(self, u, y):
        ...         pass
        ...     @property
        ...     def x_hat(self):
        ...         return np.zeros(2)
        >>> row = np.empty(5)
        >>> Still().step_and_record(np.zeros(1), np.zeros(1), row)
        >>> row
        array([ 0.,  0., nan, nan, nan])
        """
        n = out.shape[0] - 3
        out[:n] = self.x_hat
        out[n] = self.covariance_trace
        self.step(u, y)
        out[n + 1] = self.nis
        out[n + 2] = self.rejected if isinstance(self, Gated) else np.nan


def check_step(u, y, p: int, q: int) -> tuple[np.ndarray, np.ndarray]:
    """The operands of :meth:`Estimator.step` as float64 arrays, checked before any state changes.

    Parameters
    ----------
    u : array_like (p,)
        The input held over the step; every entry finite.
    y : array_like (q,)
        The outputs; NaN marks a missing sample, infinities are refused.
    p, q : int
        Input and output dimensions.

    Returns
    -------
    u, y : ndarray (p,), ndarray (q,)
        New arrays (the caller's are never kept).

    Raises
    ------
    QuadobsError
        Naming ``u`` or ``y`` and what is wrong with it.

    Examples
    --------
    >>> u, y = check_step([0.0, 1.0], [float("nan")], 2, 1)
    >>> u.shape, bool(np.isnan(y[0]))
    ((2,), True)
    """
    return as_array("u", u, (p,)), as_array("y", y, (q,), allow_nan=True)


def step_operands(u, y, p: int, q: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`check_step` with a fast path: float64 arrays of the right shapes, ``u`` finite and
    ``y`` free of infinities, are returned as they are (one dot product each when all is finite).

    The caller must not keep them beyond the step.
    """
    try:
        if (
            u.dtype == np.float64
            and y.dtype == np.float64
            and u.shape == (p,)
            and y.shape == (q,)
            and math.isfinite(u.dot(u))
            and (math.isfinite(y.dot(y)) or not np.isinf(y).any())
        ):
            return u, y
    except AttributeError:
        pass
    return check_step(u, y, p, q)


def measurement_models(system, models=None, std: float = 1.0) -> dict:
    """The measurement models of an estimator on ``system``, by kind.

    ``models``: a :class:`~quadobs.core.measurements.MeasurementModel` or a list of them (one per
    kind); by default the range model of the system's range outputs
    (:func:`~quadobs.core.measurements.range_model_of`, standard deviation ``std``). A range
    model must name the system's anchors, anchor ``h`` being output ``h``; models that ask for
    extra states are refused (these estimators carry none).
    """
    from quadobs.core.measurements import MeasurementModel, range_model_of

    if models is None:
        default = range_model_of(system, std)
        return {} if default is None else {"range": default}
    models = [models] if isinstance(models, MeasurementModel) else list(models)
    out = {}
    for model in models:
        if not isinstance(model, MeasurementModel):
            raise QuadobsError(
                f"measurement_models: expected MeasurementModel objects, got {type(model).__name__}"
            )
        if model.kind in out:
            raise QuadobsError(f"measurement_models: two models of kind {model.kind!r}")
        if model.extra_states():
            raise QuadobsError(
                f"measurement_models: the {model.kind} model asks for extra states "
                f"(bias={model.bias!r}), which this estimator does not carry"
            )
        if model.kind == "range":
            own = range_model_of(system)
            if own is None or not np.allclose(own.anchors, model.anchors, rtol=0, atol=1e-9):
                raise QuadobsError(
                    "measurement_models: the range model's anchors differ from the system's range outputs"
                )
        out[model.kind] = model
    return out


def covariance_trace(est: Estimator) -> float:
    """``est.covariance_trace`` (kept for callers holding any :class:`Estimator`)."""
    return est.covariance_trace


class Wrapper(Estimator):
    """An estimator that wraps another, ``inner``, and reads the estimate from it.

    Subclasses implement :meth:`step`; :attr:`x_hat`, :attr:`x_covariance` and
    :attr:`covariance_trace` are the wrapped estimator's.
    """

    inner: Estimator

    @property
    def x_hat(self) -> np.ndarray:
        return self.inner.x_hat

    @property
    def x_covariance(self) -> np.ndarray | None:
        return self.inner.x_covariance

    @property
    def covariance_trace(self) -> float:
        return self.inner.covariance_trace


class InnerClock(Wrapper):
    """A :class:`Wrapper` whose :attr:`time` is the wrapped estimator's: reading it reads
    ``inner.time``, setting it sets that (and whatever :meth:`_set_time` adds)."""

    @property
    def time(self) -> float:
        return self.inner.time

    @time.setter
    def time(self, value: float) -> None:
        self._set_time(value)

    def _set_time(self, value: float) -> None:
        self.inner.time = value


class HalfSteps(Estimator):
    """An estimator whose :meth:`step` is two halves that may also be called on their own.

    :meth:`correct_outputs` takes the outputs ``y (q,)`` sampled at the start of a step (NaN:
    missing) and :meth:`predict_step` predicts over the step with ``u (p,)`` held; neither moves
    :attr:`time`. :meth:`predict` and :meth:`correct` take either the operands of the interface in
    time (a time in seconds, a :class:`~quadobs.core.measurements.Measurement`) or those of the
    grid's half steps (an array ``u``, an array ``y``).
    """

    @abc.abstractmethod
    def correct_outputs(self, y: np.ndarray) -> None:
        """Correct with the outputs present in ``y (q,)``, the first half of :meth:`step`."""

    @abc.abstractmethod
    def predict_step(self, u: np.ndarray) -> None:
        """Predict over one step with ``u (p,)`` held, the second half of :meth:`step`."""

    def predict(self, t) -> None:
        """Propagate to the time ``t`` (:meth:`Estimator.predict`, exact over any interval); an
        array ``u (p,)`` is :meth:`predict_step` (the grid's half step)."""
        if np.ndim(t) == 0:
            super().predict(t)
        else:
            self.predict_step(t)

    def correct(self, m) -> None:
        """Correct with one :class:`~quadobs.core.measurements.Measurement` at the current time
        (:meth:`Estimator.correct`); an array ``y (q,)`` is :meth:`correct_outputs` (the grid's half step)."""
        if isinstance(m, Measurement):
            super().correct(m)
        else:
            self.correct_outputs(m)


class Counted(abc.ABC):
    """Ability: counts the corrections it applies (:attr:`corrections`)."""

    corrections: int = 0


class Gated(Counted):
    """Ability: corrections whose NIS exceeds :attr:`gate` are rejected and counted.

    Attributes
    ----------
    gate : float or None
        The threshold (``None``: no gate), stated for a correction of one output; the Kalman
        filters judge each output of one time alone against it
        (:meth:`~quadobs.estimators.kalman.ExtendedKalmanFilter.gate_threshold`).
    corrections : int
        Corrections applied so far.
    rejected : int
        Corrections rejected by the gate so far.
    """

    name: str  # the estimator's, which this ability is mixed into
    gate: float | None = None
    rejected: int = 0


class Switching(abc.ABC):
    """Ability: switches between modes during a run (the testbed logs each switch as an event).

    Attributes
    ----------
    mode : str
        The current mode.
    switches : list of tuple
        ``(step, from, to, reason)`` for every switch so far, ``step`` counting the calls of
        :meth:`Estimator.step` before it.
    """

    name: str  # the estimator's, which this ability is mixed into
    mode: str = ""
    switches: list

    @abc.abstractmethod
    def summary(self) -> dict:
        """The switches as plain data for the episode summary (JSON-serialisable)."""


class SetValued(abc.ABC):
    """Ability: guaranteed interval bounds of the state."""

    @property
    @abc.abstractmethod
    def bounds(self) -> np.ndarray:
        """``(n, 2)``: lower and upper bounds of each state entry at the current step."""


class Immersed(abc.ABC):
    """Ability: runs on an immersion (:attr:`immersion`, a :class:`~quadobs.core.immersion.Immersion`)."""

    immersion: Immersion


class Subset(abc.ABC):
    """Ability: reads only some of the outputs (:attr:`outputs`, their indices in ``y``)."""

    outputs: np.ndarray


class BlockStep(abc.ABC):
    """Ability: consumes a block of steps in one call, as many calls of :meth:`Estimator.step_and_record` would.

    For an open-loop episode (the truth does not depend on the estimates) every ``u_k``,
    ``y_k`` of a block is known before the estimators run, so an estimator with this
    ability advances over rows ``[j, m)`` at once: for each row ``i``,

    .. math:: \\text{out}_i = [\\hat x_i,\\ \\operatorname{tr} P_i,\\ \\mathrm{NIS}_i,\\ r_i]

    bit for bit what ``step_and_record(U[i], Y[i], out[i])`` would write, and the same
    state afterwards.

    Attributes
    ----------
    blockwise : bool
        Whether :meth:`step_block` is one call that cannot stop between rows (a compiled
        kernel); ``False`` where it would loop over the rows from Python, in which case the
        testbed calls :meth:`Estimator.step_and_record` row by row itself.
    """

    @property
    def blockwise(self) -> bool:
        return False

    @abc.abstractmethod
    def step_block(self, U: np.ndarray, Y: np.ndarray, out: np.ndarray) -> None:
        """Steps with the rows of ``U (m, p)`` and ``Y (m, q)``, their records into ``out (m, n + 3)``."""
