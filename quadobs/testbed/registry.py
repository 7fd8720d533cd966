"""Building the estimators a scenario runs, by name.

Names come from three places, looked up in this order:

1. the scenario's ``[[observer.variants]]``: each is ``"augmented"`` (the observer of
   [IFAC2021, Thm. 3] on the scenario's immersion) restricted to some outputs;
2. :func:`register_estimator`, for a factory defined at run time in one process (it does
   not reach the workers of a campaign started with ``spawn`` or on Dask);
3. the package entry points of the group ``quadobs.estimators`` (:data:`ENTRY_POINT_GROUP`):
   the built-in ``augmented``, ``ekf``, ``ukf`` and ``zonotope`` (declared in quadobs' own
   ``pyproject.toml``) and those of any installed package, so that they run in
   ``quadobs run`` and in campaigns on every kind of worker. An entry point names a factory
   ``factory(scenario, x0, name) -> Estimator``::

       [project.entry-points."quadobs.estimators"]
       tiny = "tinyest:factory"

Entry points are listed from the package metadata without importing anything; a factory
is imported when its name is first requested and kept. A package that cannot be imported
is reported (one line, naming the entry point) only when its name is requested.
"""

from __future__ import annotations

import functools
import importlib.metadata
import sys
from collections.abc import Callable

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.base import Estimator
from quadobs.testbed.factories import OutputSubset, live_observer, output_periods
from quadobs.testbed.scenario import Scenario

__all__ = [
    "ENTRY_POINT_GROUP",
    "available_estimators",
    "build_estimators",
    "call_factory",
    "default_estimators",
    "estimator_factory",
    "refresh",
    "register_estimator",
]

#: The entry-point group estimators are declared in.
ENTRY_POINT_GROUP = "quadobs.estimators"

#: factory(scenario, x0, name) -> Estimator
Factory = Callable[[Scenario, np.ndarray, str], Estimator]

# The built-in entry points as declared in pyproject.toml (a test checks that they agree).
# Used only for names that the installed metadata lacks: a source tree on PYTHONPATH, or an
# installation made before the entry points were declared.
_BUILTIN = {
    "augmented": "quadobs.testbed.factories:build_augmented",
    "ekf": "quadobs.testbed.factories:build_ekf",
    "ukf": "quadobs.testbed.factories:build_ukf",
    "zonotope": "quadobs.testbed.factories:build_zonotope",
    "augmented-refined": "quadobs.testbed.factories:build_refined",
    "onboard-ekf": "quadobs.testbed.factories:build_onboard_ekf",
    "ekf-bias": "quadobs.testbed.factories:build_ekf_bias",
    "ukf-bias": "quadobs.testbed.factories:build_ukf_bias",
    "augmented-bias": "quadobs.testbed.factories:build_augmented_bias",
    "tdoa-observer": "quadobs.testbed.tdoa:build_tdoa_observer",
    "tdoa-handover": "quadobs.testbed.tdoa:build_tdoa_handover",
}
_RUNTIME: dict[str, Factory] = {}
_REGISTRY = (
    _RUNTIME  # the run-time table under its former name (callers remove their entries from it)
)
_LOADED: dict[str, Factory] = {}


def register_estimator(name: str, factory: Factory) -> None:
    """Make ``name`` selectable in this process (``--estimators``, scenarios, in-process campaigns).

    A run-time registration lives in this process and in the processes it forks; workers
    started with ``spawn`` and Dask workers do not see it: declare an entry point of the
    group :data:`ENTRY_POINT_GROUP` for those.
    """
    if not isinstance(name, str) or not name:
        raise QuadobsError(f"name: expected a non-empty string, got {name!r}")
    if not callable(factory):
        raise QuadobsError(
            f"factory: expected a callable factory(scenario, x0, name), got {type(factory).__name__}"
        )
    _RUNTIME[name] = factory


@functools.lru_cache(maxsize=8)
def _declared(path: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    """Entry-point values per name on the import path ``path`` (more than one: declared twice)."""
    found: dict[str, list[str]] = {}
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        values = found.setdefault(ep.name, [])
        if ep.value not in values:
            values.append(ep.value)
    for name, value in _BUILTIN.items():
        found.setdefault(name, [value])
    return {name: tuple(values) for name, values in found.items()}


def refresh() -> None:
    """Forget the entry points listed and the factories loaded (after installing a package in a running process)."""
    _declared.cache_clear()
    _LOADED.clear()


def _entry_points() -> dict[str, tuple[str, ...]]:
    return _declared(tuple(sys.path))


def available_estimators(scenario: Scenario | None = None) -> list[str]:
    """The selectable names: registered ones (entry points and :func:`register_estimator`), sorted,
    then the variants of ``scenario``. Imports nothing."""
    names = sorted(set(_entry_points()) | set(_RUNTIME))
    if scenario is not None:
        names += [n for n, _ in scenario.observer.variants if n not in names]
    return names


def default_estimators(scenario: Scenario) -> list[str]:
    """The augmented observer and the scenario's variants of it; for a scenario whose radio
    sends TDOA (:data:`TDOA_ESTIMATORS`), the estimators that take TDOA."""
    if scenario.tdoa is not None:
        return list(TDOA_ESTIMATORS)
    return ["augmented"] + [n for n, _ in scenario.observer.variants]


#: The default estimators of a scenario whose radio sends TDOA: the TDOA observer handing over
#: to the EKF, the observer alone, the EKF and the UKF (the range observers take no TDOA).
TDOA_ESTIMATORS = ("tdoa-handover", "tdoa-observer", "ekf", "ukf")


def _load(name: str, value: str) -> Factory:
    """The object the entry point ``name = value`` names, imported once."""
    hit = _LOADED.get(value)
    if hit is None:
        try:
            hit = importlib.metadata.EntryPoint(name, value, ENTRY_POINT_GROUP).load()
        except Exception as exc:  # any failure of a plugin's import is reported as its own
            reason = str(exc).splitlines()[0] if str(exc) else ""
            raise QuadobsError(
                f"estimators: entry point {name!r} ({value}) cannot be loaded: {type(exc).__name__}: {reason}"
            ) from None
        if not callable(hit):
            raise QuadobsError(
                f"estimators: entry point {name!r} ({value}) is not callable ({type(hit).__name__})"
            )
        _LOADED[value] = hit
    return hit


def estimator_factory(name: str, scenario: Scenario | None = None) -> tuple[Factory, str]:
    """The factory of a registered name and where it comes from (the entry point's value, or ``"runtime"``).

    Raises
    ------
    QuadobsError
        For an unknown name (listing the available ones), a name declared by two packages,
        or an entry point that cannot be imported.
    """
    if name in _RUNTIME:
        return _RUNTIME[name], "runtime"
    values = _entry_points().get(name)
    if not values:
        raise QuadobsError(
            f"estimators: unknown estimator {name!r}; available: {', '.join(available_estimators(scenario))}"
        )
    if len(values) > 1:
        raise QuadobsError(
            f"estimators: {name!r} is declared by several entry points ({', '.join(values)})"
        )
    return _load(name, values[0]), values[0]


def call_factory(factory, name: str, origin: str, *args) -> Estimator:
    """``factory(*args, name)``, a failure of the plugin's own made one line.

    A :class:`QuadobsError` (a factory refusing its input) goes on as it is; any other
    exception becomes a :class:`~quadobs.errors.RunFault` naming the estimator, where it
    comes from and the error's first line (the command line's status 1); an error made of
    a Ctrl-C keeps its cause, so it still counts as the interrupt.
    """
    from quadobs.errors import RunFault

    if not callable(factory):
        raise QuadobsError(
            f"estimators: the factory of {name!r} ({origin}) is not callable ({type(factory).__name__})"
        )
    try:
        return factory(*args, name)
    except QuadobsError:
        raise
    except Exception as exc:
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise RunFault(
            f"estimators: the factory of {name!r} ({origin}) failed: {type(exc).__name__}: {reason}"
        ) from exc


def build_estimators(scenario: Scenario, names: list[str], x0: np.ndarray) -> list[Estimator]:
    """Instantiate the named estimators, all starting from the initial guess ``x0``.

    Raises
    ------
    QuadobsError
        For an unknown name (the message lists the available ones), a repeated one, or a
        factory that does not return an :class:`~quadobs.estimators.base.Estimator`.
    """
    if len(set(names)) != len(names):
        raise QuadobsError(f"estimators: names must be distinct, got {names}")
    variants = dict(scenario.observer.variants)
    out: list[Estimator] = []
    for name in names:
        if name in variants:
            inner = live_observer(scenario, x0, variants[name])
            est: Estimator = OutputSubset(
                inner, variants[name], name, q=output_periods(scenario).size
            )
        else:
            factory, origin = estimator_factory(name, scenario)
            est = call_factory(factory, name, origin, scenario, np.array(x0, dtype=float))
            if not isinstance(est, Estimator):
                raise QuadobsError(
                    f"estimators: the factory of {name!r} ({origin}) returned {type(est).__name__}, "
                    "not a quadobs.estimators.base.Estimator"
                )
            est.name = name
        out.append(est)
    return out
