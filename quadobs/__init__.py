"""quadobs: state estimation for linear systems with quadratic outputs.

The class of systems ([ACC2024]; [IFAC2021] for one output)::

    x' = A x + B u,        y_h = 1/2 x^T C_h x + d_h^T x,   h = 1..q

This top level re-exports the public API, which needs only NumPy and SciPy (each name is
imported on first use, so ``import quadobs`` itself loads neither):

* :class:`QuadraticSystem`, :func:`vehicle_system`, :func:`wind_system`, :func:`range_outputs`;
* :func:`immerse`: the immersion into a state-affine system with linear output
  ([ACC2024, Alg. 1]; the single-output chain of [IFAC2021, eqs. 10-17] via
  ``method="chain"``), :class:`Immersion`; :class:`HeldInputDiscretization`;
* :class:`Estimator`, the interface of every estimator; :class:`AugmentedObserver`, the
  Kalman-type observer of [IFAC2021, Theorem 3], discretised exactly for a held input;
  :class:`ExtendedKalmanFilter`, :class:`UnscentedKalmanFilter`, the baselines on the
  original state; :class:`ZonotopicEstimator`, guaranteed bounds [LE2013, Alg. 1];
* :class:`Zonotope`, :class:`IntervalMatrix`, :func:`pradius_gains` ([LE2013, problem 9]);
* :class:`Scenario`, :func:`load_scenario`, :func:`list_scenarios`, :class:`SinusoidTrajectory`;
* :class:`QuadobsError`, the one error type.

The subpackages are the layers (``docs/architecture.md``): :mod:`quadobs.core`,
:mod:`quadobs.sets`, :mod:`quadobs.estimators`, :mod:`quadobs.observability`,
:mod:`quadobs.evaluation` (the maths); :mod:`quadobs.recording` (rerun);
:mod:`quadobs.testbed` (scenarios, the MuJoCo worlds, sensors, the episode:
:func:`quadobs.testbed.episode.run_episode`); :mod:`quadobs.studies` (campaigns, the bench,
the [LE2013] reproduction). MuJoCo and rerun are imported only when used.

Examples
--------
>>> import numpy as np
>>> import quadobs
>>> system = quadobs.vehicle_system(3, beacons=np.zeros((1, 3)))
>>> quadobs.immerse(system).n_aux
3
"""

import importlib

#: Where each name of the public API lives; it is imported on first use (PEP 562), so that
#: ``import quadobs`` and ``import quadobs.cli`` stay cheap (the command line installs its
#: signal handling before NumPy and SciPy are loaded).
_EXPORTS = {
    "AugmentedObserver": "quadobs.estimators.augmented",
    "Estimator": "quadobs.estimators.base",
    "ExtendedKalmanFilter": "quadobs.estimators.kalman",
    "HeldInputDiscretization": "quadobs.core.held_input",
    "Immersion": "quadobs.core.immersion",
    "IntervalMatrix": "quadobs.sets.zonotope",
    "PRadiusDesign": "quadobs.sets.pradius",
    "QuadobsError": "quadobs.errors",
    "QuadraticSystem": "quadobs.core.system",
    "Scenario": "quadobs.testbed.scenario",
    "SinusoidTrajectory": "quadobs.testbed.trajectory",
    "Zonotope": "quadobs.sets.zonotope",
    "ZonotopicEstimator": "quadobs.estimators.zonotopic",
    "UnscentedKalmanFilter": "quadobs.estimators.kalman",
    "immerse": "quadobs.core.immersion",
    "immerse_chain": "quadobs.core.immersion",
    "immerse_minimal": "quadobs.core.immersion",
    "list_scenarios": "quadobs.testbed.scenario",
    "load_scenario": "quadobs.testbed.scenario",
    "pradius_gains": "quadobs.sets.pradius",
    "range_outputs": "quadobs.core.system",
    "vehicle_system": "quadobs.core.system",
    "wind_system": "quadobs.core.system",
}
#: The subpackages and modules reachable as attributes after a bare ``import quadobs``.
_SUBMODULES = (
    "core",
    "errors",
    "estimators",
    "evaluation",
    "observability",
    "recording",
    "sets",
    "studies",
    "testbed",
)


__all__ = [
    "AugmentedObserver",
    "Estimator",
    "ExtendedKalmanFilter",
    "HeldInputDiscretization",
    "Immersion",
    "IntervalMatrix",
    "PRadiusDesign",
    "QuadobsError",
    "QuadraticSystem",
    "Scenario",
    "SinusoidTrajectory",
    "UnscentedKalmanFilter",
    "Zonotope",
    "ZonotopicEstimator",
    "immerse",
    "immerse_chain",
    "immerse_minimal",
    "list_scenarios",
    "load_scenario",
    "pradius_gains",
    "range_outputs",
    "vehicle_system",
    "wind_system",
]


def __getattr__(name: str):
    """The public name ``name``, imported from its module on first use (then a plain attribute)."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"{__name__}.{name}")
    elif name == "__version__":
        value = _distribution_version()
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def _distribution_version() -> str:
    """The installed distribution's version: the one source is ``version`` in pyproject.toml."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("quadobs")
    except PackageNotFoundError:  # a source tree on the path, never installed
        return "0+unknown"


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__) | set(_SUBMODULES))
