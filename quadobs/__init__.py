"""quadobs: state estimation for linear systems with quadratic outputs.

The class of systems ([ACC2024]; [IFAC2021] for one output)::

    x' = A x + B u,        y_h = 1/2 x^T C_h x + d_h^T x,   h = 1..q

This top level re-exports the public API, which needs only NumPy and SciPy:

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

from quadobs.core.held_input import HeldInputDiscretization
from quadobs.errors import QuadobsError
from quadobs.estimators.kalman import ExtendedKalmanFilter, UnscentedKalmanFilter
from quadobs.core.immersion import Immersion, immerse, immerse_chain, immerse_minimal
from quadobs.sets.pradius import PRadiusDesign, pradius_gains
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.base import Estimator
from quadobs.testbed.scenario import Scenario, list_scenarios, load_scenario
from quadobs.core.system import QuadraticSystem, range_outputs, vehicle_system, wind_system
from quadobs.estimators.zonotopic import ZonotopicEstimator
from quadobs.testbed.trajectory import SinusoidTrajectory
from quadobs.sets.zonotope import IntervalMatrix, Zonotope

__version__ = "0.1.0"

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
    "Zonotope",
    "ZonotopicEstimator",
    "UnscentedKalmanFilter",
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
