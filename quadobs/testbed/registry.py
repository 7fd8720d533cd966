"""Building the estimators a scenario runs, by name.

``"augmented"`` is Theorem 3's observer on the scenario's immersion; each
``[[observer.variants]]`` of the scenario adds the same observer restricted to some
outputs. Other estimator families register a factory with :func:`register_estimator`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.base import Estimator
from quadobs.testbed import factories
from quadobs.testbed.factories import OutputSubset, augmented_observer
from quadobs.testbed.scenario import Scenario

__all__ = [
    "build_estimators",
    "default_estimators",
    "register_estimator",
    "available_estimators",
]

#: factory(scenario, x0_guess, name) -> Estimator
Factory = Callable[[Scenario, np.ndarray, str], Estimator]
_REGISTRY: dict[str, Factory] = {
    "augmented": lambda scenario, x0, name: factories.augmented_observer(scenario, x0),
    "ekf": lambda scenario, x0, name: factories.extended_kalman_filter(scenario, x0),
    "ukf": lambda scenario, x0, name: factories.unscented_kalman_filter(scenario, x0),
    "zonotope": lambda scenario, x0, name: factories.zonotope_estimator(scenario, x0),
    "augmented-refined": lambda scenario, x0, name: factories.refined_observer(scenario, x0),
}


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
