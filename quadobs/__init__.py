"""quadobs: state estimation for linear systems with quadratic outputs.

The estimator core (this package's top level) needs only NumPy and SciPy:

* :class:`QuadraticSystem`: ``x' = A x + B u``, ``y_h = 1/2 x^T C_h x + d_h^T x``;
* :func:`immerse`: the immersion into a state-affine system with linear output
  ([ACC2024] Algorithm 1; the single-output chain of
  [IFAC2021] via ``method="chain"``);
* :class:`AugmentedObserver`: the Kalman-type observer of Theorem 3 of
  [IFAC2021], discretised exactly for a held input;
* :class:`ExtendedKalmanFilter`, :class:`UnscentedKalmanFilter`: the baselines on the
  original state (registered as the estimators ``"ekf"`` and ``"ukf"``).

The MuJoCo testbed (:mod:`quadobs.testbed.worlds`), the rerun recording layer
(:mod:`quadobs.recording`) and the episode runner (:mod:`quadobs.testbed.episode`) sit on top and
are imported only when used.
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
