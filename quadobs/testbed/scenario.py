"""Scenarios: what to simulate, described by TOML files.

The built-in scenarios are TOML files shipped in ``quadobs/scenarios/``; a user's file
has the same format (see the README, "Scenario files"). Every field is validated on
load, and an error names the field by its dotted path (``noise.range_rate``,
``trajectory.terms[2].omega``). Unknown fields are refused, so a typo does not pass
silently.

This module needs neither MuJoCo nor rerun: the excitation report and the analytic
parts of a scenario (trajectory, system, beacons) work without the simulator.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.core.system import QuadraticSystem, vehicle_system, wind_system
from quadobs.testbed.trajectory import SinusoidTrajectory

__all__ = [
    "Scenario",
    "NoiseSpec",
    "ObserverSpec",
    "InitialGuess",
    "ExcitationSpec",
    "ZonotopeSpec",
    "load_scenario",
    "list_scenarios",
    "parse_scenario",
]


@dataclass(frozen=True)
class NoiseSpec:
    """Sensor noise and rates. Standard deviations in m, m/s^2, m/s; rates in Hz.

    ``range_rate`` and ``airspeed_rate`` default to the physics rate and must divide it.
    ``dropout`` is the probability that a sample is lost; ``outlier_probability`` the
    probability that a range sample gets an extra error of standard deviation
    ``outlier_std`` (m).

    Bounded noise: ``range_bound``, ``accel_bound``, ``airspeed_bound`` (m, m/s^2, m/s) draw
    the sensor's error uniformly in ``[-bound, bound]`` instead of a Gaussian; a sensor has a
    standard deviation or a bound, not both. Guaranteed (set-membership) estimators need them.
    """

    range_std: float = 0.0
    accel_std: float = 0.0
    airspeed_std: float = 0.0
    range_rate: float | None = None
    airspeed_rate: float | None = None
    dropout: float = 0.0
    outlier_probability: float = 0.0
    outlier_std: float = 0.0
    range_bound: float = 0.0
    accel_bound: float = 0.0
    airspeed_bound: float = 0.0

    def sigma(self, sensor: str) -> float:
        """Standard deviation of a sensor's error (``"range"``, ``"accel"``, ``"airspeed"``):
        the ``*_std`` field, or ``bound / sqrt(3)`` for uniform noise in ``[-bound, bound]``."""
        return getattr(self, f"{sensor}_std") or getattr(self, f"{sensor}_bound") / np.sqrt(3.0)


@dataclass(frozen=True)
class ObserverSpec:
    """Settings of the augmented observer (Theorem 3 of [IFAC2021]).

    ``S0``, ``V`` are scalars times the identity of the augmented state, or lists (a
    diagonal); ``W`` a scalar times ``I_q`` or a list (diagonal). ``gate`` is an optional
    NIS threshold for outlier rejection. ``variants`` are extra observers with the same
    settings that use only some outputs: ``(name, output indices)``, run side by side
    (``[[observer.variants]]`` tables with ``name`` and ``outputs``).
    """

    immersion: str = "minimal"
    S0: Any = 100.0
    V: Any = 1e-4
    W: Any = 1.0
    theta: float = 0.0
    gate: float | None = None
    variants: tuple[tuple[str, tuple[int, ...]], ...] = ()


@dataclass(frozen=True)
class ExcitationSpec:
    """The live excitation monitor (``[excitation]`` table; see :mod:`quadobs.observability.excitation`).

    ``window`` (s) is the length ``delta`` of the sliding window of the Gramian
    ``W(t - delta, t)``, ``threshold`` the value of ``mu = lambda_min(W)`` below which the
    window counts as not exciting, ``update_period`` (s) how often the measure is
    recomputed and ``step`` (s) the hold step over which the measured input is averaged
    (default: the multiple of the physics step nearest 0.01 s). ``window`` and
    ``update_period`` must be multiples of ``step``, and ``step`` of the physics step.
    """

    monitor: bool = True
    window: float = 5.0
    threshold: float = 1e-6
    update_period: float = 0.1
    step: float | None = None

    def grid(self, dt: float) -> tuple[int, int, int]:
        """``(block, window_blocks, update_blocks)``: physics steps per hold step, hold steps per window and per update."""

        def multiple(value: float, unit: float, name: str, unit_name: str) -> int:
            k = int(round(value / unit))
            if k < 1 or abs(value - k * unit) > 1e-9 * max(value, unit):
                raise QuadobsError(f"excitation.{name}: {value} s must be a positive multiple of {unit_name} ({unit:g} s)")
            return k

        block = max(1, int(round(0.01 / dt))) if self.step is None else multiple(self.step, dt, "step", "the physics step")
        h = block * dt
        window = multiple(self.window, h, "window", "excitation.step")
        if window < 2:
            raise QuadobsError(f"excitation.window: {self.window} s must span at least two hold steps of {h:g} s")
        update = multiple(self.update_period, h, "update_period", "excitation.step")
        return block, window, update


@dataclass(frozen=True)
class ZonotopeSpec:
    """Settings of the guaranteed estimator ``"zonotope"`` (:mod:`quadobs.estimators.zonotopic_vehicle`).

    The true initial state must lie in the box centred at the initial guess with half-widths
    ``position_bound`` (m) on positions and ``velocity_bound`` (m/s) on velocities (and wind);
    ``max_generators`` bounds the zonotope's order (0: ten times the augmented dimension);
    ``reduction`` is the order-reduction method (:data:`quadobs.sets.zonotope.REDUCTION_METHODS`).
    """

    position_bound: float = 50.0
    velocity_bound: float = 30.0
    max_generators: int = 0
    reduction: str = "parallelotope"


@dataclass(frozen=True)
class InitialGuess:
    """The initial estimate shared by all estimators.

    ``kind``: ``"zero"``, ``"point"`` (``point``, the full state), or ``"random"``
    (truth plus Gaussian errors of standard deviation ``position_spread`` on positions,
    ``velocity_spread`` on velocities and wind, drawn from the scenario's seed).
    """

    kind: str = "zero"
    point: tuple[float, ...] | None = None
    position_spread: float = 0.0
    velocity_spread: float = 0.0


@dataclass(frozen=True)
class Scenario:
    """A complete, validated description of one episode.

    Attributes
    ----------
    name, description : str
    kind : str
        ``"vehicle"``: the MuJoCo vehicle.
    dimension : int
        2 or 3.
    duration : float
        Seconds of simulated time.
    physics_rate : float
        Physics steps per second.
    seed : int
        Seed of every random draw of the episode.
    beacons : ndarray (q_b, dimension)
    wind : ndarray (dimension,) or None
        Constant wind; when given, the state includes air velocity and wind, and the
        vehicle measures its airspeed.
    trajectory : SinusoidTrajectory
    noise : NoiseSpec
    observer : ObserverSpec
    initial : InitialGuess
    excitation : ExcitationSpec
        The live excitation monitor's settings.
    model : str or None
        Path of an MJCF model to use instead of the built-in vehicle.
    record_every : int
        Record one physics step in ``record_every`` (1: every step).
    source : str
        Where the scenario came from (a built-in name or a file path).
    """

    name: str
    dimension: int
    duration: float
    physics_rate: float
    beacons: np.ndarray
    trajectory: SinusoidTrajectory
    description: str = ""
    kind: str = "vehicle"
    seed: int = 0
    wind: np.ndarray | None = None
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    observer: ObserverSpec = field(default_factory=ObserverSpec)
    initial: InitialGuess = field(default_factory=InitialGuess)
    excitation: ExcitationSpec = field(default_factory=ExcitationSpec)
    zonotope: ZonotopeSpec = field(default_factory=ZonotopeSpec)
    model: str | None = None
    record_every: int = 1
    source: str = ""

    # -- derived quantities ------------------------------------------------------------

    @property
    def dt(self) -> float:
        return 1.0 / self.physics_rate

    @property
    def steps(self) -> int:
        return int(round(self.duration * self.physics_rate))

    @property
    def has_wind(self) -> bool:
        return self.wind is not None

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
        if not self.has_wind:
            return np.concatenate([p, v], axis=-1)
        w = np.broadcast_to(self.wind, p.shape)
        return np.concatenate([p, v - w, w], axis=-1)

    def sample_interval(self, rate: float | None, name: str) -> int:
        """Physics steps between samples of a sensor at ``rate`` Hz."""
        if rate is None:
            return 1
        ratio = self.physics_rate / rate
        k = int(round(ratio))
        if k < 1 or abs(ratio - k) > 1e-9 * ratio:
            raise QuadobsError(
                f"noise.{name}: {rate} Hz must divide the physics rate {self.physics_rate} Hz (and not exceed it)"
            )
        return k

    def with_overrides(self, **changes) -> "Scenario":
        """A copy with top-level fields replaced (``duration``, ``seed``, ...), revalidated."""
        data = self.to_dict()
        for key, value in changes.items():
            if value is not None:
                data[key] = value
        return parse_scenario(data, source=self.source)

    def to_dict(self) -> dict:
        """The scenario as plain data (the TOML structure), for summaries and reloading."""
        traj = self.trajectory
        terms = [
            {"axis": int(a), "amplitude": float(am), "omega": float(om), "phase": float(ph), "function": "cos"}
            for a, am, om, ph in traj.terms
        ]
        out: dict[str, Any] = {
            "name": self.name,
            "description": self.description,
            "kind": self.kind,
            "dimension": self.dimension,
            "duration": self.duration,
            "physics_rate": self.physics_rate,
            "seed": self.seed,
            "record_every": self.record_every,
            "beacons": [{"position": [float(v) for v in b]} for b in self.beacons],
            "trajectory": {
                "offset": traj.offset.tolist(),
                "velocity": traj.velocity.tolist(),
                "terms": terms,
            },
            "noise": {k: v for k, v in vars(self.noise).items() if v is not None},
            "observer": {
                k: (list(v) if isinstance(v, tuple) else v)
                for k, v in vars(self.observer).items()
                if v is not None and k != "variants"
            },
            "initial": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self.initial).items() if v is not None},
            "zonotope": dict(vars(self.zonotope)),
        }
        out["excitation"] = {k: v for k, v in vars(self.excitation).items() if v is not None}
        if traj.coast.size:
            out["trajectory"]["coast"] = [{"start": float(a), "end": float(b)} for a, b in traj.coast]
        if self.observer.variants:
            out["observer"]["variants"] = [{"name": n, "outputs": list(o)} for n, o in self.observer.variants]
        if self.wind is not None:
            out["wind"] = {"velocity": self.wind.tolist()}
        if self.model is not None:
            out["model"] = self.model
        return out


# --------------------------------------------------------------------------------------
# Parsing and validation
# --------------------------------------------------------------------------------------


class _Fields:
    """Pops validated fields from a TOML table and refuses leftovers."""

    def __init__(self, data: Any, path: str) -> None:
        if not isinstance(data, dict):
            raise QuadobsError(f"{path or 'scenario'}: expected a table, got {type(data).__name__}")
        self.data = dict(data)
        self.path = path

    def _name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any = None) -> Any:
        return self.data.pop(key, default)

    def number(self, key: str, default: Any = ..., *, positive=False, nonnegative=False, maximum=None, optional=False):
        name = self._name(key)
        if key not in self.data:
            if default is ...:
                raise QuadobsError(f"{name}: required field is missing")
            return default
        value = self.data.pop(key)
        if value is None and optional:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise QuadobsError(f"{name}: expected a number, got {value!r}")
        value = float(value)
        if not np.isfinite(value):
            raise QuadobsError(f"{name}: must be finite, got {value}")
        if positive and value <= 0:
            raise QuadobsError(f"{name}: must be positive, got {value}")
        if nonnegative and value < 0:
            raise QuadobsError(f"{name}: must be non-negative, got {value}")
        if maximum is not None and value > maximum:
            raise QuadobsError(f"{name}: must be at most {maximum}, got {value}")
        return value

    def integer(self, key: str, default: Any = ..., *, minimum: int | None = None) -> int:
        name = self._name(key)
        if key not in self.data:
            if default is ...:
                raise QuadobsError(f"{name}: required field is missing")
            return default
        value = self.data.pop(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise QuadobsError(f"{name}: expected an integer, got {value!r}")
        if minimum is not None and value < minimum:
            raise QuadobsError(f"{name}: must be at least {minimum}, got {value}")
        return value

    def string(self, key: str, default: Any = ..., choices: tuple[str, ...] | None = None) -> str:
        name = self._name(key)
        if key not in self.data:
            if default is ...:
                raise QuadobsError(f"{name}: required field is missing")
            return default
        value = self.data.pop(key)
        if not isinstance(value, str):
            raise QuadobsError(f"{name}: expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise QuadobsError(f"{name}: must be one of {', '.join(map(repr, choices))}, got {value!r}")
        return value

    def vector(self, key: str, length: int | None, default: Any = ...) -> np.ndarray:
        name = self._name(key)
        if key not in self.data:
            if default is ...:
                raise QuadobsError(f"{name}: required field is missing")
            return default
        value = self.data.pop(key)
        if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
            raise QuadobsError(f"{name}: expected a list of numbers, got {value!r}")
        arr = np.array(value, dtype=float)
        if length is not None and arr.shape != (length,):
            raise QuadobsError(f"{name}: expected {length} numbers, got {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise QuadobsError(f"{name}: holds a non-finite value")
        return arr

    def scalar_or_list(self, key: str, default: Any, *, positive=False, nonnegative=False):
        name = self._name(key)
        if key not in self.data:
            return default
        value = self.data[key]
        if isinstance(value, list):
            arr = self.vector(key, None)
            if positive and np.any(arr <= 0):
                raise QuadobsError(f"{name}: entries must be positive")
            if nonnegative and np.any(arr < 0):
                raise QuadobsError(f"{name}: entries must be non-negative")
            return tuple(float(v) for v in arr)
        return self.number(key, positive=positive, nonnegative=nonnegative)

    def table(self, key: str) -> "_Fields":
        return _Fields(self.data.pop(key, {}), self._name(key))

    def done(self) -> None:
        if self.data:
            keys = ", ".join(sorted(self.data))
            where = self.path or "scenario"
            raise QuadobsError(f"{where}: unknown field(s) {keys}")


def _parse_variants(raw: Any, q: int) -> tuple[tuple[str, tuple[int, ...]], ...]:
    if not isinstance(raw, list):
        raise QuadobsError("observer.variants: expected a list of tables")
    out, seen = [], {"augmented"}
    for i, v in enumerate(raw):
        f = _Fields(v, f"observer.variants[{i}]")
        name = f.string("name")
        if not name.replace("_", "").isalnum() or not name.isascii() or name in seen:
            raise QuadobsError(f"observer.variants[{i}].name: {name!r} must be a new identifier (letters, digits, _)")
        seen.add(name)
        outputs = f.raw("outputs", None)
        if (
            not isinstance(outputs, list)
            or not outputs
            or any(isinstance(o, bool) or not isinstance(o, int) or not 0 <= o < q for o in outputs)
            or len(set(outputs)) != len(outputs)
        ):
            raise QuadobsError(
                f"observer.variants[{i}].outputs: expected distinct output indices in [0, {q - 1}], got {outputs!r}"
            )
        f.done()
        out.append((name, tuple(outputs)))
    return tuple(out)


def parse_scenario(data: dict, source: str = "") -> Scenario:
    """Validate plain data (a parsed TOML document) into a :class:`Scenario`."""
    top = _Fields(data, "")
    name = top.string("name")
    description = top.string("description", "")
    kind = top.string("kind", "vehicle", choices=("vehicle",))
    dim = top.integer("dimension")
    if dim not in (2, 3):
        raise QuadobsError(f"dimension: must be 2 or 3, got {dim}")
    duration = top.number("duration", positive=True)
    rate = top.number("physics_rate", 1000.0, positive=True)
    seed = top.integer("seed", 0, minimum=0)
    record_every = top.integer("record_every", 1, minimum=1)
    model = top.string("model", None) if top.has("model") else None

    beacons_raw = top.raw("beacons", None)
    if not isinstance(beacons_raw, list) or not beacons_raw:
        raise QuadobsError("beacons: at least one [[beacons]] entry with a position is required")
    beacons = []
    for i, b in enumerate(beacons_raw):
        bf = _Fields(b, f"beacons[{i}]")
        beacons.append(bf.vector("position", dim))
        bf.done()
    beacons = np.array(beacons)

    wind = None
    if top.has("wind"):
        wf = top.table("wind")
        wind = wf.vector("velocity", dim)
        wf.done()

    tf = top.table("trajectory")
    offset = tf.vector("offset", dim, np.zeros(dim))
    velocity = tf.vector("velocity", dim, np.zeros(dim))
    terms_raw = tf.raw("terms", [])
    if not isinstance(terms_raw, list):
        raise QuadobsError("trajectory.terms: expected a list of tables")
    terms = []
    for i, term in enumerate(terms_raw):
        f = _Fields(term, f"trajectory.terms[{i}]")
        axis = f.integer("axis", minimum=0)
        if axis >= dim:
            raise QuadobsError(f"trajectory.terms[{i}].axis: must be below the dimension {dim}, got {axis}")
        amp = f.number("amplitude")
        omega = f.number("omega", nonnegative=True)
        phase = f.number("phase", 0.0)
        func = f.string("function", "cos", choices=("cos", "sin"))
        f.done()
        terms.append((axis, amp, omega, phase - (np.pi / 2 if func == "sin" else 0.0)))
    coast_raw = tf.raw("coast", [])
    if not isinstance(coast_raw, list):
        raise QuadobsError("trajectory.coast: expected a list of tables ([[trajectory.coast]] with start and end)")
    coast = []
    for i, seg in enumerate(coast_raw):
        f = _Fields(seg, f"trajectory.coast[{i}]")
        coast.append((f.number("start", nonnegative=True), f.number("end", positive=True)))
        f.done()
    tf.done()
    trajectory = SinusoidTrajectory(
        offset, np.array(terms, dtype=float).reshape(-1, 4), velocity, np.array(coast, dtype=float).reshape(-1, 2)
    )

    nf = top.table("noise")
    noise = NoiseSpec(
        range_std=nf.number("range_std", 0.0, nonnegative=True),
        accel_std=nf.number("accel_std", 0.0, nonnegative=True),
        airspeed_std=nf.number("airspeed_std", 0.0, nonnegative=True),
        range_rate=nf.number("range_rate", None, positive=True, optional=True),
        airspeed_rate=nf.number("airspeed_rate", None, positive=True, optional=True),
        dropout=nf.number("dropout", 0.0, nonnegative=True, maximum=1.0),
        outlier_probability=nf.number("outlier_probability", 0.0, nonnegative=True, maximum=1.0),
        outlier_std=nf.number("outlier_std", 0.0, nonnegative=True),
        range_bound=nf.number("range_bound", 0.0, nonnegative=True),
        accel_bound=nf.number("accel_bound", 0.0, nonnegative=True),
        airspeed_bound=nf.number("airspeed_bound", 0.0, nonnegative=True),
    )
    nf.done()
    for sensor in ("range", "accel", "airspeed"):
        if getattr(noise, f"{sensor}_std") and getattr(noise, f"{sensor}_bound"):
            raise QuadobsError(
                f"noise.{sensor}_bound: cannot be combined with noise.{sensor}_std "
                "(a sensor's noise is Gaussian or bounded, not both)"
            )

    of = top.table("observer")
    observer = ObserverSpec(
        immersion=of.string("immersion", "minimal", choices=("minimal", "chain")),
        S0=of.scalar_or_list("S0", 100.0, positive=True),
        V=of.scalar_or_list("V", 1e-4, nonnegative=True),
        W=of.scalar_or_list("W", 1.0, positive=True),
        theta=of.number("theta", 0.0, nonnegative=True),
        gate=of.number("gate", None, positive=True, optional=True),
        variants=_parse_variants(of.raw("variants", []), beacons.shape[0] + (1 if wind is not None else 0)),
    )
    of.done()

    inf = top.table("initial")
    kind_i = inf.string("kind", "zero", choices=("zero", "point", "random"))
    state_dim = dim * (3 if wind is not None else 2)
    point = None
    if kind_i == "point":
        point = tuple(float(v) for v in inf.vector("point", state_dim))
    initial = InitialGuess(
        kind=kind_i,
        point=point,
        position_spread=inf.number("position_spread", 0.0, nonnegative=True),
        velocity_spread=inf.number("velocity_spread", 0.0, nonnegative=True),
    )
    inf.done()

    xf = top.table("excitation")
    monitor = xf.raw("monitor", True)
    if not isinstance(monitor, bool):
        raise QuadobsError(f"excitation.monitor: expected true or false, got {monitor!r}")
    excitation = ExcitationSpec(
        monitor=monitor,
        window=xf.number("window", 5.0, positive=True),
        threshold=xf.number("threshold", 1e-6, nonnegative=True),
        update_period=xf.number("update_period", 0.1, positive=True),
        step=xf.number("step", None, positive=True, optional=True),
    )
    xf.done()
    zf = top.table("zonotope")
    zonotope = ZonotopeSpec(
        position_bound=zf.number("position_bound", 50.0, positive=True),
        velocity_bound=zf.number("velocity_bound", 30.0, positive=True),
        max_generators=zf.integer("max_generators", 0, minimum=0),
        reduction=zf.string("reduction", "parallelotope", choices=("combastel", "girard", "pca", "parallelotope")),
    )
    zf.done()
    top.done()

    scenario = Scenario(
        name=name,
        description=description,
        kind=kind,
        dimension=dim,
        duration=duration,
        physics_rate=rate,
        seed=seed,
        beacons=beacons,
        wind=wind,
        trajectory=trajectory,
        noise=noise,
        observer=observer,
        initial=initial,
        excitation=excitation,
        zonotope=zonotope,
        model=model,
        record_every=record_every,
        source=source,
    )
    if scenario.steps < 1:
        raise QuadobsError(f"duration: {duration} s is shorter than one physics step ({scenario.dt} s)")
    scenario.sample_interval(noise.range_rate, "range_rate")
    scenario.sample_interval(noise.airspeed_rate, "airspeed_rate")
    excitation.grid(scenario.dt)
    return scenario


def _builtin_dir():
    return resources.files("quadobs.testbed") / "scenarios"


def list_scenarios() -> dict[str, str]:
    """Built-in scenario names and their one-line descriptions."""
    out = {}
    for entry in sorted(_builtin_dir().iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name[:-5]] = str(data.get("description", "")).strip().splitlines()[0] if data.get("description") else ""
    return out


def load_scenario(name_or_path: str | Path, **overrides) -> Scenario:
    """Load a built-in scenario by name, or a scenario file by path.

    Keyword overrides replace top-level fields (``duration=5.0``, ``seed=3``).

    Raises
    ------
    QuadobsError
        Unknown name, unreadable file, TOML syntax error, or an invalid field.
    """
    text_source = str(name_or_path)
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        try:
            text = path.read_text()
        except OSError as exc:
            raise QuadobsError(f"scenario file {text_source}: cannot be read ({exc.strerror})") from None
    else:
        entry = _builtin_dir() / f"{text_source}.toml"
        if not entry.is_file():
            names = ", ".join(list_scenarios())
            raise QuadobsError(f"scenario: unknown name {text_source!r}; built-in scenarios are {names}, or give a .toml path")
        text = entry.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise QuadobsError(f"scenario file {text_source}: invalid TOML ({exc})") from None
    scenario = parse_scenario(data, source=text_source)
    if scenario.model is not None and path.suffix == ".toml" and not Path(scenario.model).is_absolute():
        scenario = replace(scenario, model=str((path.parent / scenario.model).resolve()))
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return scenario.with_overrides(**overrides) if overrides else scenario
