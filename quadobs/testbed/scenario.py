"""Scenarios: what to simulate, described by TOML files, declared once per field.

The built-in scenarios are TOML files shipped in ``quadobs/testbed/scenarios/``; a
user's file has the same format. The schema is the set of frozen pydantic models below:
each field is declared once, with its type, default, bounds and a one-line description,
and that one declaration gives the validation, the defaults, the serialisation
(:meth:`Scenario.to_dict`, :meth:`Scenario.to_toml`) and the field table of the
documentation (:func:`field_reference`, ``docs/reference/scenario.md``). The rules that
tie several fields together (a beacon has ``dimension`` coordinates, a sensor rate
divides the physics rate, ...) are written out in model validators.

Every error is one line that starts with the field's dotted path (``noise.range_rate``,
``trajectory.terms[2].omega``). Unknown fields are refused, with a suggestion when a
known field is close (``noise: unknown field 'range_sdt' (did you mean 'range_std'?)``).
Any field can be overridden by a setting ``"a.b=value"`` (:func:`apply_settings`; the
command line's ``--set``).

This module needs neither MuJoCo nor rerun: the excitation report and the analytic
parts of a scenario (trajectory, system, beacons) work without the simulator.

Examples
--------
>>> sc = load_scenario("ifac2021", settings=["noise.range_std=0.1", "duration=2"])
>>> sc.noise.range_std, sc.steps, sc.beacons.shape
(0.1, 2000, (1, 3))
"""

from __future__ import annotations

import copy
import difflib
import json
import os
import re
import stat
import sys
import tomllib
from collections.abc import Iterable, Mapping
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Union, get_args, get_origin

import numpy as np
import tomli_w
from annotated_types import Ge, Gt, Le, MaxLen, MinLen
from pydantic import (
    AllowInfNan,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    PrivateAttr,
    Strict,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import ErrorDetails, PydanticCustomError, PydanticUndefined

from quadobs.core.system import QuadraticSystem, vehicle_system, wind_system
from quadobs.errors import QuadobsError, abbreviated
from quadobs.sets.zonotope import REDUCTION_METHODS
from quadobs.testbed.trajectory import SinusoidTrajectory

__all__ = [
    "ControlSpec",
    "ExcitationSpec",
    "InitialGuess",
    "NoiseSpec",
    "ObserverSpec",
    "OdometrySpec",
    "QuadrotorSpec",
    "RadioSpec",
    "Scenario",
    "TdoaSpec",
    "ZonotopeSpec",
    "apply_settings",
    "field_reference",
    "list_scenarios",
    "load_scenario",
    "parse_scenario",
]

# --------------------------------------------------------------------------------------
# Value types: TOML numbers are finite, booleans are not numbers, strings are not parsed
# --------------------------------------------------------------------------------------

Number = Annotated[float, Strict(), AllowInfNan(False)]
Positive = Annotated[Number, Gt(0.0)]
NonNegative = Annotated[Number, Ge(0.0)]
Integer = Annotated[int, Strict()]
String = Annotated[str, Strict()]
Boolean = Annotated[bool, Strict()]
Vector = tuple[Number, ...]

# Bounds of the numbers, checked at parse time so that nothing later overflows or allocates
# without limit (docs/failure-behaviour.md): a duration of 1e306 s, a rate of 1e300 Hz or a
# noise of 1e300 m would otherwise run into an overflow, a huge allocation or a meaningless run.
MAX_DURATION = 1e7  #: s (about 116 days)
MAX_RATE = 1e6  #: Hz, also rad/s
MAX_LENGTH = 1e9  #: m and m/s (MuJoCo calls a position beyond 1e10 unstable)
MAX_NOISE = 1e6  #: m, m/s, m/s^2: noise levels and spreads
MAX_COUNT = 10**9  #: record_every, max_generators
MAX_SEED = 2**63 - 1
MAX_ENTRIES = 10_000  #: beacons, terms, segments, variants
MAX_TEXT = 1024  #: characters of a name or a path

Coordinate = Annotated[Number, Ge(-MAX_LENGTH), Le(MAX_LENGTH)]
BoundedVector = tuple[Coordinate, ...]
Noise = Annotated[NonNegative, Le(MAX_NOISE)]
Rate = Annotated[Positive, Le(MAX_RATE)]
Seconds = Annotated[Positive, Le(MAX_DURATION)]

_TAGS = (
    "scalar",
    "diagonal",
)  # branch names of the scalar-or-diagonal union, left out of error paths


def _diagonal(item: Any) -> Any:
    """A scalar (times the identity) or a non-empty list (a diagonal) of ``item``."""
    return Annotated[
        Annotated[item, Tag("scalar")] | Annotated[tuple[item, ...], MinLen(1), Tag("diagonal")],
        Discriminator(lambda v: "diagonal" if isinstance(v, (list, tuple)) else "scalar"),
    ]


# The types built at import for pydantic, as a type checker sees them.
if TYPE_CHECKING:
    _PositiveDiagonal = float | tuple[float, ...]
    _NonNegativeDiagonal = float | tuple[float, ...]
    _Reduction = str
else:
    _PositiveDiagonal = _diagonal(Positive)
    _NonNegativeDiagonal = _diagonal(NonNegative)
    _Reduction = Literal[tuple(REDUCTION_METHODS)]


def _invalid(message: str, field: str = "") -> PydanticCustomError:
    """A rule broken by ``field`` (a dotted path relative to the model that checks it)."""
    return PydanticCustomError("quadobs", "{message}", {"message": message, "field": field})


class _Table(BaseModel):
    """A TOML table: frozen, unknown keys refused."""

    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------------------
# The tables of a scenario
# --------------------------------------------------------------------------------------


class Beacon(_Table):
    """A ``[[beacons]]`` entry."""

    position: Vector = Field(description="Position of the beacon (m), `dimension` numbers.")


class Wind(_Table):
    """The ``[wind]`` table."""

    velocity: BoundedVector = Field(
        description="Constant wind velocity (m/s), `dimension` numbers."
    )


class Term(_Table):
    """One sinusoid ``amplitude cos(omega t + phase)`` on one axis (``sin``: phase lowered by pi/2)."""

    axis: Annotated[Integer, Ge(0)] = Field(description="Axis of the term, below `dimension`.")
    amplitude: Coordinate = Field(description="Amplitude (m).")
    omega: Annotated[NonNegative, Le(MAX_RATE)] = Field(description="Angular frequency (rad/s).")
    phase: Number = Field(0.0, description="Phase (rad).")
    function: Literal["cos", "sin"] = Field(
        "cos",
        description="`cos` or `sin`; a `sin` term is stored as `cos` with its phase lowered by pi/2.",
    )

    @model_validator(mode="after")
    def _as_cosine(self) -> Term:
        if self.function == "sin":
            return self.model_copy(update={"function": "cos", "phase": self.phase - np.pi / 2})
        return self


class Coast(_Table):
    """A ``[[trajectory.coast]]`` segment: the commanded acceleration is off in ``[start, end)``."""

    start: Annotated[NonNegative, Le(MAX_DURATION)] = Field(description="Start of the segment (s).")
    end: Seconds = Field(description="End of the segment (s); segments are sorted and disjoint.")


class Stop(_Table):
    """A ``[[trajectory.stops]]`` stop: the vehicle halts on its path over ``[start, end]``, its
    heading held (:class:`~quadobs.testbed.trajectory.SinusoidTrajectory`)."""

    start: Annotated[NonNegative, Le(MAX_DURATION)] = Field(
        description="Start of the standstill (s); 0: the vehicle starts at rest."
    )
    end: Seconds = Field(description="End of the standstill (s); stops are sorted and disjoint.")
    ramp: Annotated[Positive, Le(MAX_DURATION)] = Field(
        1.0, description="Length of the cosine ramps down to rest and up again (s)."
    )


class TrajectorySpec(_Table):
    """The ``[trajectory]`` table: offsets, a constant velocity and sinusoids per axis."""

    offset: BoundedVector | None = Field(
        None, description="Constant offset `o` (m), `dimension` numbers (default: zeros)."
    )
    velocity: BoundedVector | None = Field(
        None, description="Constant velocity `w` (m/s), `dimension` numbers (default: zeros)."
    )
    terms: Annotated[tuple[Term, ...], MaxLen(MAX_ENTRIES)] = Field(
        (), description="Sinusoids added to the axes (`[[trajectory.terms]]` or inline tables)."
    )
    coast: Annotated[tuple[Coast, ...], MaxLen(MAX_ENTRIES)] = Field(
        (), description="Segments without commanded acceleration."
    )
    stops: Annotated[tuple[Stop, ...], MaxLen(MAX_ENTRIES)] | None = Field(
        None,
        description="Stops on the path (`[[trajectory.stops]]`: start, end, ramp), the heading held.",
    )


class NoiseSpec(_Table):
    """Sensor noise and rates. Standard deviations in m, m/s^2, m/s; rates in Hz.

    A sensor has a standard deviation (Gaussian noise) or a bound (uniform noise in
    ``[-bound, bound]``), not both; guaranteed (set-membership) estimators need bounds.
    """

    range_std: Noise = Field(0.0, description="Standard deviation of the range error (m).")
    accel_std: Noise = Field(
        0.0, description="Standard deviation of the accelerometer error (m/s^2)."
    )
    airspeed_std: Noise = Field(0.0, description="Standard deviation of the airspeed error (m/s).")
    range_rate: Rate | None = Field(
        None,
        description="Range sample rate (Hz), dividing the physics rate (default: the physics rate).",
    )
    airspeed_rate: Rate | None = Field(
        None,
        description="Airspeed sample rate (Hz), dividing the physics rate (default: the physics rate).",
    )
    dropout: Annotated[NonNegative, Le(1.0)] = Field(
        0.0, description="Probability that a sample is lost."
    )
    outlier_probability: Annotated[NonNegative, Le(1.0)] = Field(
        0.0, description="Probability that a range sample carries an outlier."
    )
    outlier_std: Noise = Field(
        0.0, description="Standard deviation of an outlier's extra error (m)."
    )
    range_bound: Noise = Field(0.0, description="Bound of the uniform range error (m).")
    accel_bound: Noise = Field(0.0, description="Bound of the uniform accelerometer error (m/s^2).")
    airspeed_bound: Noise = Field(0.0, description="Bound of the uniform airspeed error (m/s).")
    gate: Positive | None = Field(
        None,
        description="EKF/UKF/refined: chi-square gate of this probability on each correction's NIS, with one degree of freedom per output corrected (1 for a range at its own time); default: no gate.",
    )
    huber: Positive | None = Field(
        None,
        description="EKF/UKF/refined: Huber M-estimator with this threshold in standard deviations (1.345: 95 % Gaussian efficiency); default: none.",
    )
    lockout: Positive | None = Field(
        None,
        description="EKF/UKF (default: the time 30 corrections take at the scenario's range rate): window over which more than half of the corrections rejected count as a lock-out, after which the filter re-initialises its covariance; after 3 re-initialisations it is reported as diverged.",
    )

    @field_validator("gate")
    @classmethod
    def _a_probability(cls, gate: float | None) -> float | None:
        if gate is not None and not gate < 1.0:
            raise _invalid(
                f"expected the gate's probability in (0, 1), e.g. 0.999: a correction is rejected when its NIS "
                f"exceeds that quantile of chi-square with one degree of freedom per output corrected; got {gate}"
            )
        return gate

    @model_validator(mode="after")
    def _std_or_bound(self) -> NoiseSpec:
        for sensor in ("range", "accel", "airspeed"):
            if getattr(self, f"{sensor}_std") and getattr(self, f"{sensor}_bound"):
                raise _invalid(
                    f"cannot be combined with noise.{sensor}_std (a sensor's noise is Gaussian or bounded, not both)",
                    f"{sensor}_bound",
                )
        return self

    def sigma(self, sensor: str) -> float:
        """Standard deviation of a sensor's error (``"range"``, ``"accel"``, ``"airspeed"``).

        The ``*_std`` field, or ``bound / sqrt(3)`` for uniform noise in ``[-bound, bound]``.
        """
        return getattr(self, f"{sensor}_std") or getattr(self, f"{sensor}_bound") / np.sqrt(3.0)


class Variant(_Table):
    """An ``[[observer.variants]]`` entry: the augmented observer restricted to some outputs."""

    name: String = Field(description="Estimator name: a new identifier (letters, digits, _).")
    outputs: Annotated[tuple[Annotated[Integer, Ge(0)], ...], MinLen(1)] = Field(
        description="Distinct indices of the outputs used (beacons, then airspeed)."
    )

    @model_validator(mode="after")
    def _distinct(self) -> Variant:
        if not self.name.replace("_", "").isalnum() or not self.name.isascii():
            raise _invalid(f"{self.name!r} must be an identifier (letters, digits, _)", "name")
        if len(set(self.outputs)) != len(self.outputs):
            raise _invalid(f"expected distinct output indices, got {list(self.outputs)}", "outputs")
        return self


class ObserverSpec(_Table):
    """Settings of the augmented observer [IFAC2021, Theorem 3].

    ``S0``, ``V`` are scalars times the identity of the augmented state, or lists (a
    diagonal); ``W`` a scalar times ``I_q`` or a list (diagonal). ``variants`` are extra
    observers with the same settings that use only some outputs, run side by side; the
    attribute holds ``(name, output indices)`` pairs. ``tuning = "derived"`` replaces ``S0``,
    ``V`` and ``W`` by the replay's rule on the scenario's stated figures
    (:func:`quadobs.testbed.factories.derived_settings`); they must not be given then.
    """

    immersion: Literal["minimal", "chain"] = Field(
        "minimal", description="Immersion: `minimal` [ACC2024, Alg. 1] or `chain` [IFAC2021]."
    )
    S0: _PositiveDiagonal = Field(
        100.0,
        description="Initial covariance of the augmented state: scalar (times I) or diagonal.",
    )
    V: _NonNegativeDiagonal = Field(
        1e-4, description="Process noise of the augmented state: scalar (times I) or diagonal."
    )
    W: _PositiveDiagonal = Field(1.0, description="Output noise: scalar (times I_q) or diagonal.")
    theta: Annotated[NonNegative, Le(MAX_RATE)] = Field(
        0.0, description="Forgetting rate `theta` of the observer (1/s)."
    )
    gate: Positive | None = Field(
        None, description="NIS threshold above which a correction is rejected (default: no gate)."
    )
    variant_specs: tuple[Variant, ...] = Field(
        (), alias="variants", description="Extra observers restricted to some outputs."
    )
    tuning: Literal["explicit", "derived"] | None = Field(
        None,
        description="`explicit` (default): `S0`, `V`, `W` as given; `derived`: from the stated range noise, "
        "IMU noise, anchors and initial spread, by the rule of the replay (docs/replay.md).",
    )

    @model_validator(mode="after")
    def _derived_alone(self) -> ObserverSpec:
        if self.tuning == "derived":
            for key in ("S0", "V", "W", "theta"):
                if key in self.model_fields_set:
                    raise _invalid(
                        'not used with tuning = "derived" (S0, V and W are then derived from the '
                        'stated noise, anchors and initial spread, theta is 0); set tuning = "explicit" to give it',
                        key,
                    )
        return self

    @model_validator(mode="after")
    def _new_names(self) -> ObserverSpec:
        seen = {"augmented"}
        for i, v in enumerate(self.variant_specs):
            if v.name in seen:
                raise _invalid(
                    f"{v.name!r} must be a new identifier (letters, digits, _)",
                    f"variants[{i}].name",
                )
            seen.add(v.name)
        return self

    @property
    def variants(self) -> tuple[tuple[str, tuple[int, ...]], ...]:
        """``(name, output indices)`` of each variant."""
        return tuple((v.name, v.outputs) for v in self.variant_specs)


class InitialGuess(_Table):
    """The initial estimate shared by all estimators.

    ``kind``: ``"zero"``, ``"point"`` (``point``, the full state), or ``"random"`` (truth
    plus Gaussian errors of standard deviation ``position_spread`` on positions and
    ``velocity_spread`` on velocities and wind, drawn from the scenario's seed).
    """

    kind: Literal["zero", "point", "random"] = Field(
        "zero",
        description="`zero`, `point` (the given state) or `random` (truth plus Gaussian errors).",
    )
    point: BoundedVector | None = Field(
        None, description='The initial state when `kind = "point"` (`state_dim` numbers).'
    )
    position_spread: Noise = Field(
        0.0, description="Standard deviation of the random position error (m)."
    )
    velocity_spread: Noise = Field(
        0.0, description="Standard deviation of the random velocity (and wind) error (m/s)."
    )

    @model_validator(mode="after")
    def _point_with_kind(self) -> InitialGuess:
        if self.kind == "point" and self.point is None:
            raise _invalid("required field is missing", "point")
        if self.kind != "point" and self.point is not None:
            raise _invalid(f'only used with kind = "point", not {self.kind!r}', "point")
        return self


class ExcitationSpec(_Table):
    """The live excitation monitor (``[excitation]``; :mod:`quadobs.observability.excitation`).

    ``window`` and ``update_period`` must be multiples of ``step``, and ``step`` of the
    physics step (:meth:`grid`).
    """

    monitor: Boolean = Field(True, description="Run the live excitation monitor.")
    window: Seconds = Field(
        5.0, description="Length `delta` of the sliding Gramian window `W(t - delta, t)` (s)."
    )
    threshold: NonNegative = Field(
        1e-6, description="`mu = lambda_min(W)` below which a window counts as not exciting."
    )
    update_period: Seconds = Field(0.1, description="Period of the measure's updates (s).")
    step: Annotated[Seconds, Ge(1e-6)] | None = Field(
        None,
        description="Hold step over which the input is averaged (s) (default: the physics-step multiple nearest 0.01 s).",
    )

    def grid(self, dt: float) -> tuple[int, int, int]:
        """``(block, window_blocks, update_blocks)``: physics steps per hold step, hold steps per window and per update."""

        def multiple(value: float, unit: float, name: str, unit_name: str) -> int:
            k = int(round(value / unit))
            if k < 1 or abs(value - k * unit) > 1e-9 * max(value, unit):
                raise QuadobsError(
                    f"excitation.{name}: {value} s must be a positive multiple of {unit_name} ({unit:g} s)"
                )
            return k

        block = (
            max(1, int(round(0.01 / dt)))
            if self.step is None
            else multiple(self.step, dt, "step", "the physics step")
        )
        h = block * dt
        window = multiple(self.window, h, "window", "excitation.step")
        if window < 2:
            raise QuadobsError(
                f"excitation.window: {self.window} s must span at least two hold steps of {h:g} s"
            )
        update = multiple(self.update_period, h, "update_period", "excitation.step")
        return block, window, update


class ZonotopeSpec(_Table):
    """Settings of the guaranteed estimator ``"zonotope"`` (:mod:`quadobs.estimators.zonotopic_vehicle`).

    The true initial state must lie in the box centred at the initial guess with the
    given half-widths.
    """

    position_bound: Annotated[Positive, Le(MAX_LENGTH)] = Field(
        50.0, description="Half-width of the initial box on positions (m)."
    )
    velocity_bound: Annotated[Positive, Le(MAX_LENGTH)] = Field(
        30.0, description="Half-width of the initial box on velocities and wind (m/s)."
    )
    max_generators: Annotated[Integer, Ge(0), Le(MAX_COUNT)] = Field(
        0, description="Largest zonotope order (0: ten times the augmented dimension)."
    )
    reduction: _Reduction = Field(
        "parallelotope",
        description="Order-reduction method (`quadobs.sets.zonotope.REDUCTION_METHODS`).",
    )


class Hover(_Table):
    """A ``[[quadrotor.hovers]]`` pause: the reference stops moving between ``start`` and ``end``."""

    start: NonNegative = Field(description="Time at which the reference starts to slow down (s).")
    end: Positive = Field(description="Time at which the reference is back to full speed (s).")


class ControlSpec(_Table):
    """The quadrotor's cascaded geometric controller (:mod:`quadobs.testbed.controllers`)."""

    feedback: String = Field(
        "truth", description="`truth`, or the name of the estimator whose estimate is flown on."
    )
    switch_time: NonNegative = Field(
        0.0,
        description="Time from which the controller flies on the estimate (s); the truth before.",
    )
    rate: Positive = Field(500.0, description="Controller rate (Hz), dividing the physics rate.")
    position_bandwidth: Positive = Field(
        2.0, description="Natural frequency of the position loop (rad/s)."
    )
    attitude_bandwidth: Positive = Field(
        12.0, description="Natural frequency of the attitude loop (rad/s)."
    )
    damping: Positive = Field(0.9, description="Damping ratio of both loops.")
    crash_distance: Positive = Field(
        1.0,
        description="Tracking error beyond which a flight counts as crashed and the rotors stop (m).",
    )
    integral_bandwidth: NonNegative = Field(
        0.5,
        description="Integral action on the position error, `k_i = integral_bandwidth k_x` (rad/s; 0: none), each axis held within 3 m/s^2.",
    )
    rotor_lead: bool = Field(
        True,
        description="Invert the identified rotor lag in the thrust commands (`T_c = T_d + tau dT_d/dt`).",
    )


class QuadrotorSpec(_Table):
    """Flight plan and on-board sensors of the quadrotor (noise standard deviations, rates in Hz).

    The reference is the scenario's trajectory, entered from the floor by a take-off,
    paused by the hovers and left by a landing at the end of the episode.
    """

    takeoff: Positive = Field(
        3.0, description="Duration of the take-off from the floor below the trajectory's start (s)."
    )
    landing: Positive = Field(3.0, description="Duration of the landing that ends the episode (s).")
    hover_ramp: Positive = Field(
        1.0, description="Time to slow down into and speed up out of a hover (s)."
    )
    hovers: tuple[Hover, ...] = Field(
        (), description="Pauses of the reference (`[[quadrotor.hovers]]`)."
    )
    accel_std: NonNegative = Field(0.0, description="Accelerometer white noise (m/s^2).")
    accel_bias: NonNegative = Field(
        0.0, description="Standard deviation of the accelerometer's constant bias (m/s^2)."
    )
    gyro_std: NonNegative = Field(0.0, description="Gyroscope white noise (rad/s).")
    gyro_bias: NonNegative = Field(
        0.0, description="Standard deviation of the gyroscope's constant bias (rad/s)."
    )
    attitude_std: NonNegative = Field(0.0, description="Attitude (AHRS) error per axis (rad).")
    attitude_rate: Positive | None = Field(
        None,
        description="Attitude sample rate (Hz), dividing the physics rate (default: the physics rate).",
    )
    rotor_tau_up: Positive | None = Field(
        None,
        description="Rotor spin-up time constant at hover (s); default the identified 0.136 s.",
    )
    rotor_tau_down: Positive | None = Field(
        None,
        description="Rotor spin-down time constant at hover (s); default the identified 0.108 s, or scaled with `rotor_tau_up`.",
    )
    mass_scale: Positive = Field(
        1.0,
        description="Factor on the vehicle's mass in the physics (the controller keeps 0.0319 kg).",
    )
    gust_speed: NonNegative = Field(
        0.0,
        description="Amplitude of gusts of wind (m/s) on MuJoCo's fluid model: `w(t) = gust_speed (sin(2 pi t / T), sin(2 pi t / (1.7 T) + 1), 0)`.",
    )
    gust_period: Positive = Field(3.0, description="Period `T` of the gusts (s).")

    @model_validator(mode="after")
    def _sorted_hovers(self) -> QuadrotorSpec:
        last = 0.0
        for i, h in enumerate(self.hovers):
            if h.start < last or h.end - h.start < 2.0 * self.hover_ramp:
                raise _invalid(
                    f"[{h.start}, {h.end}] must be sorted, disjoint and last at least twice hover_ramp",
                    f"hovers[{i}]",
                )
            last = h.end
        return self


class RadioSpec(_Table):
    """The ``[radio]`` table: a simulated UWB radio (:mod:`quadobs.testbed.uwb`) instead of the
    grid ranges of ``[noise]`` (quadrotor scenarios): each range or TDOA at its own time."""

    protocol: Literal["twr", "tdoa"] = Field(
        "twr",
        description="`twr`: two-way ranging, anchors polled in turn; `tdoa`: TDoA3-style differences, random order.",
    )
    rate: Rate = Field(
        100.0, description="Exchanges (twr) or packets (tdoa) per second over all anchors (Hz)."
    )
    rates: tuple[Rate, ...] | None = Field(
        None, description="twr: each anchor's own rate (Hz) instead of the round-robin."
    )
    std: Annotated[Positive, Le(MAX_NOISE)] = Field(
        0.1, description="Line-of-sight noise of one range (m)."
    )
    biases: tuple[Coordinate, ...] | None = Field(
        None, description="Per-anchor biases (m); default: drawn from the seed with `bias_std`."
    )
    bias_std: Noise = Field(
        0.0, description="Standard deviation of the drawn per-anchor biases (m)."
    )
    bias_mean: Annotated[Number, Ge(-MAX_NOISE), Le(MAX_NOISE)] | None = Field(
        None,
        description="Mean of the drawn per-anchor biases (m; default 0): an antenna delay lengthens every range, so real biases are mostly positive.",
    )
    jitter: Noise = Field(
        0.0, description="Standard deviation of each exchange's timing jitter (s)."
    )
    dropout: Annotated[NonNegative, Le(0.99)] = Field(
        0.0, description="Probability that an exchange is lost."
    )
    outlier_probability: Annotated[NonNegative, Le(0.99)] = Field(
        0.0, description="Probability that a range carries an outlier."
    )
    outlier_std: Noise = Field(0.0, description="Standard deviation of an outlier's error (m).")
    nlos_median: Noise = Field(
        0.0,
        description="Median of the non-line-of-sight excess (m, log-normal), where the room blocks the path.",
    )
    nlos_shape: Noise = Field(0.5, description="Log-normal shape of the non-line-of-sight excess.")
    pattern: Noise = Field(
        0.0,
        description="Standard deviation over all directions of each anchor's direction-dependent bias (m; an antenna's delay varies with the signal's direction).",
    )
    level_bias: Annotated[Number, Ge(-MAX_NOISE), Le(MAX_NOISE)] = Field(
        0.0,
        description="Bias `k log10 d` that changes with the distance `d` through the received signal's level (m per decade of distance).",
    )
    room: Annotated[String, MaxLen(MAX_TEXT)] | None = Field(
        None,
        description="MJCF file of the obstacles cast against with `mj_ray` (relative to the scenario file; `builtin` for the package's room).",
    )


class OdometrySpec(_Table):
    """The ``[odometry]`` table: a planar ground robot's wheel odometry (:mod:`quadobs.testbed.odometry`),
    written as the inputs of an exported log (``time,speed,yaw_rate``) instead of the accelerometer.

    The speed is along the direction of travel: ``s~ = (1 + scale_error) |v| + speed_std n``,
    ``omega~ = omega + yaw_rate_bias + yaw_rate_std n'``, each sample held until the next.
    """

    rate: Rate = Field(
        50.0, description="Odometry samples per second (Hz), dividing the physics rate."
    )
    speed_std: Noise = Field(
        0.0, description="Standard deviation of the speed's white noise (m/s)."
    )
    scale_error: Annotated[Number, Gt(-1.0), Le(1.0)] = Field(
        0.0,
        description="Relative error of the wheel scale: the speed reads `(1 + scale_error)` times the true one.",
    )
    yaw_rate_std: Noise = Field(
        0.0, description="Standard deviation of the yaw rate's white noise (rad/s)."
    )
    yaw_rate_bias: Annotated[Number, Ge(-MAX_RATE), Le(MAX_RATE)] = Field(
        0.0, description="Constant bias of the yaw rate (rad/s)."
    )
    turn_slip: Annotated[NonNegative, Le(MAX_RATE)] | None = Field(
        None,
        description="Wheel slip in turns (s/rad): the speed reads `(1 + scale_error + turn_slip |omega|)` times the true one.",
    )


# --------------------------------------------------------------------------------------
# The scenario
# --------------------------------------------------------------------------------------


class TdoaSpec(_Table):
    """The former ``[tdoa]`` table (deprecated): read as ``[radio]`` with ``protocol = "tdoa"``
    and these ``std`` and ``rate`` (:meth:`Scenario._tdoa_table_into_radio`), the one description
    of TDOA (:mod:`quadobs.testbed.uwb`)."""

    std: Noise = Field(0.1, description="Standard deviation of a TDOA (m).")
    rate: Rate = Field(100.0, description="Packets per second (Hz), dividing the physics rate.")


class Scenario(_Table):
    """A complete, validated description of one episode.

    The fields are those of the TOML file (``docs/reference/scenario.md``); the tables
    ``beacons``, ``wind`` and ``trajectory`` are read as arrays and a trajectory:

    Attributes
    ----------
    beacons : ndarray (q_b, dimension)
        Beacon positions (read-only).
    wind : ndarray (dimension,) or None
        Constant wind; when given, the state includes air velocity and wind, and the
        vehicle measures its airspeed.
    trajectory : SinusoidTrajectory
        The reference motion.
    source : str
        Where the scenario came from (a built-in name or a file path); not a field, and
        not compared: two scenarios are equal when their :meth:`to_dict` are.

    Examples
    --------
    >>> sc = load_scenario("wind")
    >>> sc.state_dim, sc.wind.tolist()
    (9, [4.0, -3.0, 0.5])
    """

    name: Annotated[String, MaxLen(MAX_TEXT)] = Field(description="Name of the scenario.")
    description: Annotated[String, MaxLen(100 * MAX_TEXT)] = Field(
        "", description="What the scenario shows (first line: `quadobs list`)."
    )
    kind: Literal["vehicle", "quadrotor"] = Field(
        "vehicle",
        description="`vehicle`: the MuJoCo point-mass vehicle; `quadrotor`: a Crazyflie-sized quadrotor flown by a controller.",
    )
    dimension: Integer = Field(description="Dimension of the motion: 2 or 3.")
    duration: Seconds = Field(description="Simulated time (s).")
    physics_rate: Rate = Field(1000.0, description="Physics steps per second (Hz).")
    seed: Annotated[Integer, Ge(0), Le(MAX_SEED)] = Field(
        0, description="Seed of every random draw of the episode."
    )
    record_every: Annotated[Integer, Ge(1), Le(MAX_COUNT)] = Field(
        1, description="Record one physics step in `record_every`."
    )
    beacon_specs: Annotated[tuple[Beacon, ...], MaxLen(MAX_ENTRIES)] = Field(
        alias="beacons", description="Beacons ranged by the vehicle (`[[beacons]]`, at least one)."
    )
    trajectory_spec: TrajectorySpec = Field(
        default_factory=TrajectorySpec, alias="trajectory", description="The reference motion."
    )
    noise: NoiseSpec = Field(default_factory=NoiseSpec, description="Sensor noise and rates.")
    observer: ObserverSpec = Field(
        default_factory=ObserverSpec, description="Settings of the augmented observer."
    )
    initial: InitialGuess = Field(
        default_factory=InitialGuess, description="The initial estimate of every estimator."
    )
    zonotope: ZonotopeSpec = Field(
        default_factory=ZonotopeSpec, description="Settings of the guaranteed estimator `zonotope`."
    )
    excitation: ExcitationSpec = Field(
        default_factory=ExcitationSpec, description="The live excitation monitor."
    )
    wind_spec: Wind | None = Field(
        None,
        alias="wind",
        description="Constant wind: adds air velocity and wind to the state, and an airspeed output.",
    )
    model: Annotated[String, MaxLen(MAX_TEXT)] | None = Field(
        None,
        description="MJCF model to use instead of the built-in vehicle (relative to the scenario file).",
    )
    control: ControlSpec | None = Field(
        None, description='The flight controller (`kind = "quadrotor"` only).'
    )
    quadrotor: QuadrotorSpec | None = Field(
        None,
        description='Flight plan and on-board sensors of the quadrotor (`kind = "quadrotor"` only).',
    )
    radio: RadioSpec | None = Field(
        None,
        description='A simulated UWB radio feeding each range or TDOA at its own time (a tag in 2-D or 3-D, without wind); `protocol = "tdoa"` is the scenario\'s TDOA (the former `[tdoa]` table, deprecated).',
    )

    odometry: OdometrySpec | None = Field(
        None,
        description="Wheel odometry of a planar ground robot (speed, yaw rate), written as the inputs of an exported log (a 2-D vehicle without wind).",
    )

    _beacons: np.ndarray = PrivateAttr()
    _wind: np.ndarray | None = PrivateAttr(None)
    _trajectory: SinusoidTrajectory = PrivateAttr()
    _source: str = PrivateAttr("")

    @field_validator("model")
    @classmethod
    def _a_path(cls, model: str | None) -> str | None:
        if model is not None and ("\0" in model or not model.strip()):
            raise _invalid(
                "expected the path of an MJCF file, got an empty name or one holding NUL"
            )
        return model

    @field_validator("dimension")
    @classmethod
    def _plane_or_space(cls, dim: int) -> int:
        if dim not in (2, 3):
            raise _invalid(f"must be 2 or 3, got {dim}")
        return dim

    @field_validator("beacon_specs")
    @classmethod
    def _some_beacons(cls, beacons: tuple[Beacon, ...]) -> tuple[Beacon, ...]:
        if not beacons:
            raise _invalid("at least one [[beacons]] entry with a position is required")
        return beacons

    @model_validator(mode="after")
    def _cross_field(self) -> Scenario:
        """The rules between fields, then the arrays and the trajectory built once."""
        dim = self.dimension
        for i, b in enumerate(self.beacon_specs):
            _check_length(f"beacons[{i}].position", b.position, dim)
        if self.wind_spec is not None:
            _check_length("wind.velocity", self.wind_spec.velocity, dim)
        spec = _resolve_trajectory(self.trajectory_spec, dim)
        q = len(self.beacon_specs) + (self.wind_spec is not None)
        for i, v in enumerate(self.observer.variant_specs):
            if any(o >= q for o in v.outputs):
                raise QuadobsError(
                    f"observer.variants[{i}].outputs: expected distinct output indices in [0, {q - 1}], got {list(v.outputs)}"
                )
        if self.initial.point is not None:
            _check_length(
                "initial.point", self.initial.point, dim * (3 if self.wind_spec is not None else 2)
            )
        out = (
            self.model_copy(update={"trajectory_spec": spec})
            if spec is not self.trajectory_spec
            else self
        )
        out._build()
        if out.steps < 1:
            raise QuadobsError(
                f"duration: {self.duration} s is shorter than one physics step ({out.dt} s)"
            )
        out.sample_interval(self.noise.range_rate, "range_rate")
        out.sample_interval(self.noise.airspeed_rate, "airspeed_rate")
        self.excitation.grid(out.dt)
        return out

    @model_validator(mode="before")
    @classmethod
    def _tdoa_table_into_radio(cls, data: Any) -> Any:
        """The deprecated ``[tdoa]`` table (``std``, ``rate``) read as ``[radio]`` with
        ``protocol = "tdoa"``: its keys take the place of the radio's (so that ``--set
        tdoa.std=...`` still works), with a :class:`DeprecationWarning`."""
        if not isinstance(data, dict) or data.get("tdoa") is None:
            return data
        import warnings

        data = dict(data)
        table = data.pop("tdoa")
        if not isinstance(table, dict):
            raise QuadobsError(f"tdoa: expected a table, got {type(table).__name__}")
        try:
            spec = TdoaSpec.model_validate(table)
        except ValidationError as exc:
            raise QuadobsError(f"tdoa.{_first_error(exc)}") from None
        radio = dict(data.get("radio") or {})
        if radio.get("protocol", "tdoa") != "tdoa":
            raise QuadobsError(
                'tdoa: deprecated, and [radio] protocol is not "tdoa" (use [radio] alone)'
            )
        radio.update(protocol="tdoa", **spec.model_dump(exclude_unset=True))
        data["radio"] = radio
        warnings.warn(
            'scenario: the [tdoa] table is deprecated; write [radio] with protocol = "tdoa"',
            DeprecationWarning,
            stacklevel=2,
        )
        return data

    @property
    def tdoa(self) -> RadioSpec | None:
        """The radio when it sends TDOA (``[radio]`` with ``protocol = "tdoa"``), else ``None``."""
        radio = self.radio
        return radio if radio is not None and radio.protocol == "tdoa" else None

    @model_validator(mode="after")
    def _quadrotor_tables(self) -> Scenario:
        """``[control]`` and ``[quadrotor]`` belong to quadrotor scenarios, which move in 3-D."""
        if self.kind != "quadrotor":
            if self.radio is not None and self.wind_spec is not None:
                raise QuadobsError("radio: the radio's tag moves without wind")
            if self.odometry is not None:
                if self.dimension != 2 or self.wind_spec is not None:
                    raise QuadobsError(
                        "odometry: wheel odometry is planar: a 2-D vehicle without wind"
                    )
                self.sample_interval(self.odometry.rate, "rate", table="odometry")
            for table in ("control", "quadrotor"):
                if getattr(self, table) is not None:
                    raise QuadobsError(
                        f'{table}: only used with kind = "quadrotor", not {self.kind!r}'
                    )
            return self
        if self.dimension != 3:
            raise QuadobsError(f"dimension: a quadrotor flies in 3-D, got {self.dimension}")
        if self.odometry is not None:
            raise QuadobsError('odometry: wheel odometry is for kind = "vehicle" in 2-D')
        if self.wind_spec is not None:
            raise QuadobsError('wind: not modelled for kind = "quadrotor"')
        quad, control = self.quadrotor or QuadrotorSpec(), self.control or ControlSpec()
        if quad.takeoff + quad.landing >= self.duration:
            raise QuadobsError(
                f"quadrotor.landing: take-off and landing must fit in the duration {self.duration} s"
            )
        self.sample_interval(control.rate, "rate", table="control")
        self.sample_interval(quad.attitude_rate, "attitude_rate", table="quadrotor")
        return self

    def _build(self) -> None:
        beacons = np.array([b.position for b in self.beacon_specs], dtype=float)
        beacons.setflags(write=False)
        self._beacons = beacons
        if self.wind_spec is not None:
            wind = np.array(self.wind_spec.velocity, dtype=float)
            wind.setflags(write=False)
            self._wind = wind
        t = self.trajectory_spec
        terms = np.array(
            [(x.axis, x.amplitude, x.omega, x.phase) for x in t.terms], dtype=float
        ).reshape(-1, 4)
        coast = np.array([(c.start, c.end) for c in t.coast], dtype=float).reshape(-1, 2)
        stops = np.array([(x.start, x.end, x.ramp) for x in t.stops or ()], dtype=float)
        self._trajectory = SinusoidTrajectory(
            np.array(t.offset), terms, np.array(t.velocity), coast, stops.reshape(-1, 3)
        )
        if self.odometry is not None:
            self._check_moving()

    def _check_moving(self) -> None:
        """A wheeled robot's heading is its direction of travel (:mod:`quadobs.testbed.odometry`):
        refuse, before any step, a reference path whose speed falls to a standstill at one of
        the odometry's sample times (at most a million of them, spread over the duration). A
        stop (``[[trajectory.stops]]``) halts the robot on its path, its heading held: the speed
        checked is the path's own."""
        from quadobs.testbed.odometry import STANDSTILL

        n = int(min(self.duration * self.odometry.rate, 1e6)) + 1  # type: ignore[union-attr]
        t = np.linspace(0.0, self.duration, n)
        speed = np.linalg.norm(self._trajectory.path_velocity(t), axis=1)  # held at a stop
        k = int(np.argmin(speed))
        if speed[k] < STANDSTILL:
            raise QuadobsError(
                f"odometry: the trajectory stops at t = {t[k]:.6g} s (speed {speed[k]:.3g} m/s); "
                "a wheeled robot's heading is its direction of travel: give it a speed that stays positive "
                "(a stop on the path: [[trajectory.stops]])"
            )

    # -- the tables as arrays ----------------------------------------------------------

    @property
    def beacons(self) -> np.ndarray:
        return self._beacons

    @property
    def wind(self) -> np.ndarray | None:
        return self._wind

    @property
    def trajectory(self) -> SinusoidTrajectory:
        return self._trajectory

    @property
    def source(self) -> str:
        return self._source

    # -- derived quantities ------------------------------------------------------------

    @property
    def dt(self) -> float:
        return 1.0 / self.physics_rate

    @property
    def steps(self) -> int:
        return int(round(self.duration * self.physics_rate))

    @property
    def has_wind(self) -> bool:
        return self.wind_spec is not None

    @property
    def state_dim(self) -> int:
        return self.dimension * (3 if self.has_wind else 2)

    def system(self) -> QuadraticSystem:
        """The quadratic-output system the estimators use (outputs: beacons, then airspeed)."""
        if self.has_wind:
            return wind_system(self.dimension, self.beacons)
        return vehicle_system(self.dimension, self.beacons)

    def true_state(self, t) -> np.ndarray:
        """The reference state at ``t``: ``(p, v)``, or ``(p, v_a, v_w)`` with wind."""
        p = self.trajectory.derivative(t, 0)
        v = self.trajectory.derivative(t, 1)
        if self.wind is None:
            return np.concatenate([p, v], axis=-1)
        w = np.broadcast_to(self.wind, p.shape)
        return np.concatenate([p, v - w, w], axis=-1)

    def sample_interval(self, rate: float | None, name: str, table: str = "noise") -> int:
        """Physics steps between samples of a sensor at ``rate`` Hz (``table.name`` in errors)."""
        if rate is None:
            return 1
        ratio = self.physics_rate / rate
        k = int(round(ratio))
        if k < 1 or abs(ratio - k) > 1e-9 * ratio:
            raise QuadobsError(
                f"{table}.{name}: {rate} Hz must divide the physics rate {self.physics_rate} Hz (and not exceed it)"
            )
        return k

    # -- copies and serialisation ------------------------------------------------------

    def with_overrides(self, **changes) -> Scenario:
        """A copy with top-level fields replaced (``duration``, ``seed``, ...), revalidated; ``None`` keeps a field."""
        data = self.to_dict()
        data.update({k: v for k, v in changes.items() if v is not None})
        return parse_scenario(data, source=self.source)

    def with_settings(self, settings: Iterable[str] | Mapping[str, Any]) -> Scenario:
        """A copy with any fields replaced by dotted path (:func:`apply_settings`), revalidated.

        Examples
        --------
        >>> load_scenario("ifac2021").with_settings({"excitation.monitor": False}).excitation.monitor
        False
        """
        base = self.to_dict()
        data = _derived_by_settings(base, apply_settings(copy.deepcopy(base), settings))
        return parse_scenario(data, source=self.source)

    def to_dict(self) -> dict:
        """The scenario as plain data (the TOML structure), for summaries and reloading."""
        out = self.model_dump(mode="json", by_alias=True, exclude_none=True)
        if not out["observer"]["variants"]:
            del out["observer"]["variants"]
        if out["observer"].get("tuning") == "derived":  # derived, not set (a reload refuses them)
            for key in ("S0", "V", "W", "theta"):
                del out["observer"][key]
        if not out["trajectory"]["coast"]:
            del out["trajectory"]["coast"]
        return out

    def to_toml(self) -> str:
        """The scenario as a TOML document that :func:`load_scenario` reads back to an equal scenario.

        Lists of numbers are written on one line.
        """
        text = tomli_w.dumps(self.to_dict(), multiline_strings=True)
        compact = _NUMBER_LIST.sub(
            lambda m: "[" + ", ".join(m.group(0)[1:-1].replace(",", " ").split()) + "]", text
        )
        return compact if tomllib.loads(compact) == tomllib.loads(text) else text

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Scenario):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(json.dumps(self.to_dict(), sort_keys=True))


_NUMBER_LIST = re.compile(r"\[\n(?:[ ]+[-+0-9.eE]+,\n)+[ ]*\]")


def _check_length(path: str, values: tuple, length: int) -> None:
    if len(values) != length:
        raise QuadobsError(f"{path}: expected {length} numbers, got {len(values)}")


def _resolve_trajectory(spec: TrajectorySpec, dim: int) -> TrajectorySpec:
    """The trajectory with its vectors checked against the dimension and defaults filled."""
    update = {}
    for name in ("offset", "velocity"):
        value = getattr(spec, name)
        if value is None:
            update[name] = (0.0,) * dim
        else:
            _check_length(f"trajectory.{name}", value, dim)
    for i, term in enumerate(spec.terms):
        if term.axis >= dim:
            raise QuadobsError(
                f"trajectory.terms[{i}].axis: must be below the dimension {dim}, got {term.axis}"
            )
    return spec.model_copy(update=update) if update else spec


# --------------------------------------------------------------------------------------
# Errors: one line naming the dotted field
# --------------------------------------------------------------------------------------


def _path(loc: Iterable[str | int]) -> str:
    out = ""
    for part in loc:
        if part in _TAGS:
            continue
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _model_at(loc: Iterable[str | int]) -> type[BaseModel] | None:
    """The model class of the table at ``loc`` (keys are aliases), or None."""
    model: Any = Scenario
    for part in loc:
        if isinstance(part, int) or part in _TAGS:
            continue
        fields = {(f.alias or n): f for n, f in model.model_fields.items()}
        if part not in fields:
            return None
        model = _table_class(fields[part].annotation)
        if model is None:
            return None
    return model


def _is_table_list(loc: tuple) -> bool:
    """Whether the field at ``loc`` is a list of tables (``[[name]]``)."""
    model = _model_at(loc[:-1])
    fields = {(f.alias or n): f for n, f in model.model_fields.items()} if model else {}
    info = fields.get(loc[-1]) if loc else None
    return (
        info is not None
        and get_origin(info.annotation) is tuple
        and _table_class(info.annotation) is not None
    )


def _table_class(annotation: Any) -> type[BaseModel] | None:
    """The table model inside ``annotation`` (``Model``, ``Model | None``, ``tuple[Model, ...]``)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _table_class(arg)
        if found is not None:
            return found
    return None


def _unknown(errors: list[ErrorDetails]) -> str:
    """The message for the unknown keys of one table, with a suggestion for each close one."""
    parent = errors[0]["loc"][:-1]
    keys = [e["loc"][-1] for e in errors if e["loc"][:-1] == parent]
    model = _model_at(parent)
    known = [(f.alias or n) for n, f in model.model_fields.items()] if model else []
    hints = []
    for key in keys:
        close = difflib.get_close_matches(str(key), known, n=1)
        hints.append(f"{key!r} (did you mean {close[0]!r}?)" if close else repr(key))
    word = "field" if len(keys) == 1 else "fields"
    return f"{_path(parent) or 'scenario'}: unknown {word} {', '.join(hints)}"


_KINDS = {
    "float_type": "a number",
    "int_type": "an integer",
    "string_type": "a string",
    "bool_type": "true or false",
    "tuple_type": "a list",
    "list_type": "a list",
}


def _bound_message(kind: str, ctx: dict, value: Any) -> str:
    bound = ctx.get("gt", ctx.get("ge", ctx.get("le")))
    value = float(value) if isinstance(bound, float) else value
    if kind == "greater_than":
        return (
            f"must be positive, got {value}"
            if ctx["gt"] == 0
            else f"must be greater than {ctx['gt']}, got {value}"
        )
    if kind == "greater_than_equal":
        if isinstance(ctx["ge"], float) and ctx["ge"] == 0:
            return f"must be non-negative, got {value}"
        return f"must be at least {ctx['ge']}, got {value}"
    return f"must be at most {ctx['le']}, got {value}"


def _message(error: ErrorDetails) -> str:
    """One error of a validation as ``dotted.path: what is wrong``."""
    kind, ctx, value = error["type"], error.get("ctx") or {}, error.get("input")
    path = _path(error["loc"])
    if kind == "quadobs":
        path = ".".join(p for p in (path, ctx["field"]) if p).replace(".[", "[")
        text = ctx["message"]
    elif kind == "value_error" and isinstance(ctx.get("error"), QuadobsError):
        return f"{path}: {ctx['error']}" if path else str(ctx["error"])
    elif kind == "missing":
        text = "required field is missing"
    elif kind == "tuple_type" and _is_table_list(error["loc"]):
        text = "expected a list of tables"
    elif kind in _KINDS:
        text = f"expected {_KINDS[kind]}, got {_short(value)}"
    elif kind in ("model_type", "dict_type", "model_attributes_type"):
        text = f"expected a table, got {type(value).__name__}"
    elif kind == "finite_number":
        text = f"must be finite, got {value}"
    elif kind in ("greater_than", "greater_than_equal", "less_than_equal"):
        text = _bound_message(kind, ctx, value)
    elif kind == "literal_error":
        text = f"must be one of {ctx['expected']}, got {_short(value)}"
    elif kind == "too_short":
        text = f"expected at least {ctx['min_length']} entries, got {ctx['actual_length']}"
    else:
        text = error["msg"]
    return f"{path or 'scenario'}: {text}".replace("\n", " ")


def _first_error(exc: ValidationError) -> str:
    """The error to report: unknown fields first (the likely typo), else the first one."""
    errors = exc.errors(include_url=False)
    unknown = [e for e in errors if e["type"] == "extra_forbidden"]
    return _unknown(unknown) if unknown else _message(errors[0])


# --------------------------------------------------------------------------------------
# Parsing, settings, loading
# --------------------------------------------------------------------------------------


def parse_scenario(data: dict, source: str = "") -> Scenario:
    """Validate plain data (a parsed TOML document) into a :class:`Scenario`.

    Raises
    ------
    QuadobsError
        One line naming the first invalid field by its dotted path.
    """
    if not isinstance(data, dict):
        raise QuadobsError(f"scenario: expected a table, got {type(data).__name__}")
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as exc:
        raise QuadobsError(_first_error(exc)) from None
    scenario._source = source
    return scenario


def parse_setting(text: str) -> tuple[str, Any]:
    """``"a.b[1].c=value"`` as ``(path, value)``; the value is read as TOML, else kept as a string.

    Examples
    --------
    >>> parse_setting("noise.range_std=0.5"), parse_setting("name=demo run")
    (('noise.range_std', 0.5), ('name', 'demo run'))
    """
    path, sep, raw = text.partition("=")
    path = path.strip()
    if not sep or not path:
        raise QuadobsError(f"--set: expected FIELD=VALUE (e.g. noise.range_std=0.1), got {text!r}")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    except RecursionError:
        raise QuadobsError(f"--set {path}: the value is nested too deeply") from None
    except ValueError as exc:  # an integer of more digits than Python converts
        raise QuadobsError(f"--set {path}: {_unreadable_number(exc)}") from None
    return path, value


#: Deepest nesting of tables and lists in a scenario, and most parts of a ``--set`` path.
MAX_NESTING = 100


def _unreadable_number(exc: ValueError) -> str:
    """The one-line reason for a number Python refuses to convert (``exc``)."""
    if "digits" in str(exc):
        return f"a number of more than {sys.get_int_max_str_digits()} digits"
    return f"a value that cannot be read ({exc})"


def _nesting(data: Any) -> int:
    """How deeply tables and lists nest in ``data`` (0 for a scalar), counted without recursion."""
    deepest, stack = 0, [(data, 0)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        if depth > MAX_NESTING:
            break
        children = (
            node.values() if isinstance(node, dict) else node if isinstance(node, list) else ()
        )
        stack.extend((child, depth + 1) for child in children)
    return deepest


def _split_path(path: str) -> list[str | int]:
    """``"a.b[1].c"`` as ``["a", "b", 1, "c"]``, in time linear in the length of ``path``.

    A path of :data:`MAX_NESTING` parts or more is refused before it is split (no field of a
    scenario lies that deep), so the cost of a hostile path is one count of its separators.
    """
    parts: list[str | int] = []
    if path.count(".") + path.count("[") >= MAX_NESTING:
        raise QuadobsError(f"--set: {path[:60]!r}...: more than {MAX_NESTING} parts")
    for name in path.split("."):
        head, *indices = name.split("[")
        if not head or any(not i.endswith("]") or not i[:-1].isdigit() for i in indices):
            shown = path if len(path) <= 80 else path[:77] + "..."
            raise QuadobsError(
                f"--set: {shown!r} is not a dotted field path (e.g. trajectory.terms[0].omega)"
            )
        parts.append(head)
        parts.extend(int(i[:-1]) for i in indices)
    return parts


def _derived_by_settings(base: dict, data: dict) -> dict:
    """``data`` (``base`` with settings applied) without the observer's ``S0``, ``V``, ``W``
    and ``theta`` that ``base`` gave, where the settings made its tuning ``"derived"``: a
    setting cannot remove a field, and a derived tuning refuses them."""
    was, now = base.get("observer") or {}, data.get("observer") or {}
    if now.get("tuning") == "derived" and was.get("tuning") != "derived":
        for key in ("S0", "V", "W", "theta"):
            if key in now and key in was and now[key] == was[key]:
                del now[key]
    return data


def apply_settings(data: dict, settings: Iterable[str] | Mapping[str, Any]) -> dict:
    """A copy of scenario data with fields set by dotted path (missing tables are created).

    Parameters
    ----------
    data : dict
        Scenario data (a parsed TOML document or :meth:`Scenario.to_dict`).
    settings : iterable of str, or mapping
        ``"path=value"`` texts (:func:`parse_setting`), or ``{path: value}``.

    Returns
    -------
    dict
        The new data, to be validated by :func:`parse_scenario` (unknown fields are refused there).
    """
    out = copy.deepcopy(data)
    pairs = settings.items() if isinstance(settings, Mapping) else map(parse_setting, settings)
    for path, value in pairs:
        parts = _split_path(path)
        node: Any = out
        for depth in range(len(parts) - 1):
            node = _child(node, parts, depth)
        _assign(node, parts, value)
    return out


def _child(node: Any, parts: list[str | int], depth: int) -> Any:
    """The entry ``parts[depth]`` of ``node``, created when missing (the path is named on error only).

    Naming the path only when it is wrong keeps :func:`apply_settings` linear in the number
    of parts (naming the prefix at every step made it quadratic).
    """
    part, following = parts[depth], parts[depth + 1]
    if isinstance(part, int):
        if not isinstance(node, list) or not 0 <= part < len(node):
            size = len(node) if isinstance(node, list) else 0
            raise QuadobsError(f"{_path(parts[: depth + 1])}: no such entry ({size} in the list)")
        return node[part]
    if not isinstance(node, dict):
        raise QuadobsError(f"{_path(parts[: depth + 1])}: is not a table")
    return node.setdefault(part, [] if isinstance(following, int) else {})


def _assign(node: Any, parts: list[str | int], value: Any) -> None:
    part = parts[-1]
    if isinstance(part, int):
        if not isinstance(node, list) or not 0 <= part <= len(node):
            raise QuadobsError(
                f"{_path(parts)}: no such entry (a list grows by one entry at a time)"
            )
        node[part : part + 1] = [value]
    elif isinstance(node, dict):
        node[part] = value
    else:
        raise QuadobsError(f"{_path(parts[:-1])}: is not a table")


def _builtin_dir():
    return resources.files("quadobs.testbed") / "scenarios"


def list_scenarios() -> dict[str, str]:
    """Built-in scenario names and their one-line descriptions."""
    out = {}
    for entry in sorted(_builtin_dir().iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name[:-5]] = (
                str(data.get("description", "")).strip().splitlines()[0]
                if data.get("description")
                else ""
            )
    return out


#: Largest scenario file read (bytes).
MAX_FILE_BYTES = 1 << 20


def _read_text(path: Path, shown: str) -> str:
    """The UTF-8 text of a scenario file: a regular file of at most :data:`MAX_FILE_BYTES`."""
    try:  # opened without blocking: a FIFO with no writer would wait for one for ever
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise QuadobsError(f"scenario file {shown}: not a regular file")
            raw = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise QuadobsError(f"scenario file {shown}: cannot be read ({exc.strerror})") from None
    if len(raw) > MAX_FILE_BYTES:
        raise QuadobsError(f"scenario file {shown}: larger than {MAX_FILE_BYTES} bytes")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise QuadobsError(f"scenario file {shown}: not UTF-8 text (byte {exc.start})") from None


def _read(name_or_path: str | Path) -> dict:
    """The TOML document of a built-in name or a file, with a relative model path made absolute."""
    text_source = str(name_or_path)
    shown = abbreviated(text_source)
    if len(text_source) > MAX_TEXT or "\0" in text_source:
        raise QuadobsError(
            f"scenario {shown!r}: expected a name or a path of at most {MAX_TEXT} characters without NUL"
        )
    path = Path(name_or_path)
    try:
        is_file = path.suffix == ".toml" or path.exists()
    except OSError as exc:  # a name too long for the file system
        raise QuadobsError(f"scenario file {shown}: cannot be read ({exc.strerror})") from None
    if is_file:
        text = _read_text(path, shown)
    else:
        entry = _builtin_dir() / f"{text_source}.toml"
        if not entry.is_file():
            names = ", ".join(list_scenarios())
            raise QuadobsError(
                f"scenario: unknown name {shown!r}; built-in scenarios are {names}, or give a .toml path"
            )
        text = entry.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise QuadobsError(f"scenario file {shown}: invalid TOML ({exc})") from None
    except RecursionError:
        raise QuadobsError(f"scenario file {shown}: invalid TOML (nested too deeply)") from None
    except ValueError as exc:  # an integer of more digits than Python converts
        raise QuadobsError(f"scenario file {shown}: {_unreadable_number(exc)}") from None
    if _nesting(data) > MAX_NESTING:  # a table header 5000 names deep parses, then overflows
        raise QuadobsError(
            f"scenario file {shown}: invalid TOML (nested too deeply: more than {MAX_NESTING} levels)"
        )
    model = data.get("model")
    if path.suffix == ".toml" and isinstance(model, str) and not Path(model).is_absolute():
        data["model"] = str((path.parent / model).resolve())
    return data


def load_scenario(
    name_or_path: str | Path, *, settings: Iterable[str] | Mapping[str, Any] = (), **overrides
) -> Scenario:
    """Load a built-in scenario by name, or a scenario file by path.

    Parameters
    ----------
    name_or_path : str or Path
        A built-in name (:func:`list_scenarios`) or the path of a ``.toml`` file.
    settings : iterable of str, or mapping
        Fields set by dotted path, ``"noise.range_std=0.1"`` (:func:`apply_settings`).
    **overrides
        Top-level fields replaced (``duration=5.0``, ``seed=3``); ``None`` keeps a field.

    Raises
    ------
    QuadobsError
        Unknown name, unreadable file, TOML syntax error, or an invalid field.
    """
    base = _read(name_or_path)
    data = _derived_by_settings(base, apply_settings(copy.deepcopy(base), settings))
    data.update({k: v for k, v in overrides.items() if v is not None})
    return parse_scenario(data, source=str(name_or_path))


# --------------------------------------------------------------------------------------
# The field reference of the documentation
# --------------------------------------------------------------------------------------


def _type_label(annotation: Any, metadata: Iterable[Any] = ()) -> str:
    """A reader's name of a field's type, with its bounds (``number > 0``, ``list of number``)."""
    metadata = list(metadata)
    while get_origin(annotation) is Annotated:
        annotation, *more = get_args(annotation)
        metadata += more
    args = get_args(annotation)
    if get_origin(annotation) is Literal:
        label = "one of " + ", ".join(f"`{json.dumps(a)}`" for a in args)
    elif get_origin(annotation) is tuple:
        inner = _table_class(args[0])
        label = "list of tables" if inner else f"list of {_type_label(args[0])}"
    elif args and type(None) in args:
        return _type_label(next(a for a in args if a is not type(None)), metadata) + " (optional)"
    elif get_origin(annotation) is Union:
        label = " or ".join(_type_label(a) for a in args)
    elif _table_class(annotation):
        label = "table"
    else:
        label = {float: "number", int: "integer", str: "string", bool: "boolean"}.get(
            annotation, str(annotation)
        )
    bounds = [
        f"{sign} {getattr(m, attr)}"
        for m in metadata
        for cls, attr, sign in ((Gt, "gt", ">"), (Ge, "ge", ">="), (Le, "le", "<="))
        if isinstance(m, cls)
    ]
    return " ".join([label, ", ".join(bounds)]) if bounds else label


def _default_label(info: Any) -> str:
    if info.default is PydanticUndefined:
        return "required" if info.default_factory is None else ""
    if info.default is None:
        return ""
    if isinstance(info.default, tuple) and not info.default:
        return "`[]`"
    return f"`{json.dumps(info.default)}`"


def _rows(model: type[BaseModel], prefix: str) -> Iterable[tuple[str, str, str, str]]:
    for name, info in model.model_fields.items():
        dotted = prefix + (info.alias or name)
        yield (
            dotted,
            _type_label(info.annotation, info.metadata),
            _default_label(info),
            info.description or "",
        )
        inner = _table_class(info.annotation)
        if inner is not None:
            many = get_origin(info.annotation) is tuple
            yield from _rows(inner, dotted + ("[]." if many else "."))


def field_reference() -> str:
    """The scenario reference of the documentation: one row per field of the schema.

    Returns
    -------
    str
        Markdown, the content of ``docs/reference/scenario.md``
        (regenerate: ``python -m quadobs.cli show --reference > docs/reference/scenario.md``).
    """
    lines = [
        "# Scenario reference",
        "",
        "<!-- Generated from the schema in quadobs/testbed/scenario.py: do not edit. -->",
        "<!-- Regenerate: python -m quadobs.cli show --reference > docs/reference/scenario.md -->",
        "",
        "A scenario is a TOML file; `quadobs show NAME` prints a built-in one, and `--set FIELD=VALUE`",
        "overrides any field below on `quadobs run`, `campaign`, `excitation` and `show`",
        "(`name[]` is a list of tables, e.g. `[[beacons]]`; set an entry with `beacons[0].position=[1, 2, 3]`).",
        "Cross-field rules: vectors have `dimension` entries (`initial.point`: the state's, with wind 3 per axis);",
        "`noise.*_rate` divide `physics_rate`; `excitation.window` and `update_period` are multiples of",
        "`excitation.step`, itself a multiple of the physics step; a sensor has `*_std` or `*_bound`, not both;",
        "`observer.variants[].outputs` index the outputs (beacons, then airspeed).",
        "",
        "| field | type | default | description |",
        "|---|---|---|---|",
    ]
    for dotted, label, default, text in _rows(Scenario, ""):
        lines.append(f"| `{dotted}` | {label} | {default} | {text.replace('|', '/')} |")
    return "\n".join(lines) + "\n"
