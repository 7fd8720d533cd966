"""Building the estimators a scenario runs, by name.

``"augmented"`` is Theorem 3's observer on the scenario's immersion; each
``[[observer.variants]]`` of the scenario adds the same observer restricted to some
outputs. Other estimator families register a factory with :func:`register_estimator`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.core.immersion import immerse
from quadobs.estimators.augmented import AugmentedObserver, Estimator
from quadobs.testbed.scenario import Scenario
from quadobs.core.system import QuadraticSystem

__all__ = [
    "OutputSubset",
    "build_estimators",
    "default_estimators",
    "register_estimator",
    "available_estimators",
    "output_periods",
]

#: factory(scenario, x0_guess, name) -> Estimator
Factory = Callable[[Scenario, np.ndarray, str], Estimator]
_REGISTRY: dict[str, Factory] = {}


def register_estimator(name: str, factory: Factory) -> None:
    """Make ``name`` selectable in scenarios and on the command line (``--estimators``)."""
    _REGISTRY[name] = factory


def available_estimators(scenario: Scenario | None = None) -> list[str]:
    names = list(_REGISTRY)
    if scenario is not None:
        names += [n for n, _ in scenario.observer.variants]
    return names


def default_estimators(scenario: Scenario) -> list[str]:
    """The augmented observer and the scenario's variants of it."""
    return ["augmented"] + [n for n, _ in scenario.observer.variants]


def output_periods(scenario: Scenario) -> np.ndarray:
    """Sampling period (s) of each output: the ranges, then the airspeed."""
    n = scenario.noise
    periods = [scenario.dt * scenario.sample_interval(n.range_rate, "range_rate")] * scenario.beacons.shape[0]
    if scenario.has_wind:
        periods.append(scenario.dt * scenario.sample_interval(n.airspeed_rate, "airspeed_rate"))
    return np.array(periods)


def _matrix_subset(value, idx: tuple[int, ...]):
    if np.ndim(value) == 0:
        return value
    arr = np.asarray(value, dtype=float)
    return arr[list(idx)] if arr.ndim == 1 else arr[np.ix_(idx, idx)]


class OutputSubset(Estimator):
    """Runs an estimator on some of the outputs only (``y[outputs]``)."""

    def __init__(self, inner: Estimator, outputs: tuple[int, ...], name: str) -> None:
        self.inner = inner
        self.outputs = np.asarray(outputs, dtype=int)
        self.name = name

    def step(self, u, y) -> None:
        self.inner.step(u, np.asarray(y)[self.outputs])

    def step_and_record(self, u, y, out) -> None:
        self.inner.step_and_record(u, np.asarray(y)[self.outputs], out)

    @property
    def x_hat(self) -> np.ndarray:
        return self.inner.x_hat

    @property
    def x_covariance(self):
        return self.inner.x_covariance

    @property
    def covariance_trace(self) -> float:
        return self.inner.covariance_trace

    @property
    def nis(self) -> float:
        return getattr(self.inner, "nis", float("nan"))

    def __getattr__(self, item):
        return getattr(self.inner, item)


def augmented_observer(scenario: Scenario, x0: np.ndarray, outputs: tuple[int, ...] | None = None) -> AugmentedObserver:
    """Theorem 3's observer for ``scenario`` (optionally on a subset of the outputs), starting at ``lift(x0)``."""
    system = scenario.system()
    periods = output_periods(scenario)
    W = scenario.observer.W
    if outputs is not None:
        system = QuadraticSystem(system.A, system.B, system.C[list(outputs)], system.d[list(outputs)])
        periods = periods[list(outputs)]
        W = _matrix_subset(W, outputs)
    im = immerse(system, method=scenario.observer.immersion)
    obs = scenario.observer
    return AugmentedObserver(
        im,
        scenario.dt,
        V=np.asarray(obs.V, dtype=float),
        W=np.asarray(W, dtype=float),
        S0=np.asarray(obs.S0, dtype=float),
        theta=obs.theta,
        x0=x0,
        sample_period=periods,
        gate=obs.gate,
    )


def _augmented_factory(scenario: Scenario, x0: np.ndarray, name: str) -> Estimator:
    return augmented_observer(scenario, x0)


register_estimator("augmented", _augmented_factory)


def _zonotope_factory(scenario: Scenario, x0: np.ndarray, name: str) -> Estimator:
    from quadobs.estimators.zonotopic_vehicle import zonotope_estimator

    return zonotope_estimator(scenario, x0)


register_estimator("zonotope", _zonotope_factory)


def build_estimators(scenario: Scenario, names: list[str], x0: np.ndarray) -> list[Estimator]:
    """Instantiate the named estimators, all starting from the initial guess ``x0``.

    Raises
    ------
    QuadobsError
        For an unknown name (the message lists the available ones) or a repeated one.
    """
    if len(set(names)) != len(names):
        raise QuadobsError(f"estimators: names must be distinct, got {names}")
    variants = dict(scenario.observer.variants)
    out = []
    for name in names:
        if name in variants:
            est = OutputSubset(augmented_observer(scenario, x0, variants[name]), variants[name], name)
        elif name in _REGISTRY:
            est = _REGISTRY[name](scenario, x0, name)
            est.name = name
        else:
            raise QuadobsError(
                f"estimators: unknown estimator {name!r}; available: {', '.join(available_estimators(scenario))}"
            )
        out.append(est)
    return out
