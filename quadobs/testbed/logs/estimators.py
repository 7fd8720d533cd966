"""The estimators a replay runs, built from a :class:`ReplaySetup` (the log, the model, the noise).

Names: ``augmented`` (the observer of [IFAC2021, Thm. 3] on the immersion of the replay
model), ``ekf`` (the EKF on the original state, in the range ("norm") space), ``isam2``
(the GTSAM peer, :mod:`quadobs.estimators.gtsam_peer`), and any other name registered in
:mod:`quadobs.testbed.registry` whose factory accepts a :class:`ReplaySetup`.

Noise (the defaults of :class:`ReplaySetup`; the same for every estimator):

* ranges: standard deviation ``range_sigma`` (1 m). The augmented observer's output is the
  half squared range, whose standard deviation is about ``rho sigma``: it is given
  ``R = (rho_med range_sigma)^2`` with ``rho_med`` the median measured range of the log;
* odometry (model ``odometry``): a white noise of intensity ``q_xy`` (m^2/s) on ``p'``; on
  the auxiliary state ``xi = |p|^2/2`` (``xi' = u^T p``) the matching intensity
  ``r^2 q_xy``, ``r`` the largest beacon distance from the origin plus 20 m;
* model ``cv``: a white acceleration of intensity ``q_acc`` (m^2/s^3), and ``r^2 q_acc`` on
  each auxiliary state;
* the initial guess ``x0`` with variance ``P0`` per position axis; the augmented
  observer's initial covariance is that of ``lift(x)`` for ``x ~ N(x0, P0 I)`` on the
  position: ``var xi = P0 |p0|^2 + P0^2``, ``cov(xi, p) = P0 p0``;
* a gate on the NIS at ``gate`` (10.83: the 0.999 quantile of chi-square with 1 degree of
  freedom; the outputs of a step are few and mostly single).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from quadobs.core.immersion import immerse
from quadobs.core.system import QuadraticSystem, constant_velocity_system, odometry_system
from quadobs.errors import QuadobsError
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.base import Estimator
from quadobs.estimators.kalman import ExtendedKalmanFilter, HeldInputModel, OutputModel

__all__ = ["ReplaySetup", "build_replay_estimators", "build_isam2", "REPLAY_ESTIMATORS"]


@dataclass(frozen=True, eq=False)
class ReplaySetup:
    """What the replay's estimators are built from.

    Attributes
    ----------
    beacons : ndarray (q, 2)
    dt : float
    model : {"odometry", "cv"}
    heading0 : float
        The odometry's heading at the first step (rad).
    range_median : float
        Median measured range (m).
    range_sigma, q_xy, q_theta, q_acc, gate : float
        Noise settings (module docstring).
    P0 : float
        Variance of the initial position guess per axis (m^2).
    """

    beacons: np.ndarray
    dt: float
    model: str
    heading0: float
    range_median: float
    range_sigma: float = 1.0
    q_xy: float = 0.1
    q_theta: float = 1e-3
    q_acc: float = 0.5
    gate: float | None = 10.83
    P0: float = 2500.0
    system: QuadraticSystem = field(init=False, repr=False)

    def __post_init__(self) -> None:
        make = {"odometry": odometry_system, "cv": constant_velocity_system}.get(self.model)
        if make is None:
            raise QuadobsError(f"model: expected odometry or cv, got {self.model!r}")
        object.__setattr__(self, "system", make(self.beacons))

    @property
    def n(self) -> int:
        return self.system.n


def _process_noise(s: ReplaySetup) -> np.ndarray:
    """Continuous intensity on ``x`` (module docstring)."""
    if s.model == "odometry":
        return s.q_xy * np.eye(2)
    return np.diag([0.0, 0.0, s.q_acc, s.q_acc])


def build_augmented(s: ReplaySetup, x0: np.ndarray, name: str = "augmented") -> AugmentedObserver:
    """The observer of [IFAC2021, Thm. 3] on the immersion of the replay model [ACC2024, Alg. 1]."""
    im = immerse(s.system)
    k, n = im.n_aux, s.n
    r = float(np.max(np.linalg.norm(s.beacons, axis=1))) + 20.0
    V = np.zeros((im.dim, im.dim))
    V[k:, k:] = _process_noise(s)
    if s.model == "odometry":
        V[0, 0] = r**2 * s.q_xy
    else:  # xi spans |p|^2/2, p.v, |v|^2/2: the acceleration noise reaches them through p.w, v.w
        V[:k, :k] = r**2 * s.q_acc * np.eye(k)
    p0 = np.asarray(x0[:2], dtype=float)
    P = np.eye(im.dim) * s.P0
    z0 = im.lift(x0)
    if s.model == "odometry":  # the covariance of lift(x) for x ~ N(x0, P0 I): exact for xi = |p|^2/2
        P[0, 0] = s.P0 * p0 @ p0 + s.P0**2
        P[0, k : k + 2] = P[k : k + 2, 0] = s.P0 * p0
    else:
        P[:k, :k] = np.eye(k) * (s.P0 * (p0 @ p0 + 1.0) + s.P0**2)
    R = (s.range_median * s.range_sigma) ** 2
    est = AugmentedObserver(im, s.dt, V=V, W=R * s.dt, P0=P, z0=z0, gate=s.gate)
    est.name = name
    return est


def build_ekf(s: ReplaySetup, x0: np.ndarray, name: str = "ekf") -> ExtendedKalmanFilter:
    """The EKF on ``x`` in the range space (:class:`~quadobs.estimators.kalman.OutputModel` with offsets)."""
    dyn = HeldInputModel(s.system, s.dt, V=_process_noise(s))
    out = OutputModel(s.system, s.range_sigma**2, offsets=0.5 * np.einsum("hi,hi->h", s.beacons, s.beacons))
    P0 = np.full(s.n, s.P0)
    if s.model == "cv":
        P0[2:] = 4.0
    est = ExtendedKalmanFilter(dyn, out, x0=x0, P0=np.diag(P0), gate=s.gate)
    est.name = name
    return est


def build_isam2(s, x0: np.ndarray, name: str = "isam2") -> Estimator:
    """Entry point ``isam2``: the GTSAM peer (:class:`~quadobs.estimators.gtsam_peer.Isam2RangeOnly`); logged data only."""
    if not isinstance(s, ReplaySetup):
        raise QuadobsError(f"estimators: {name!r} runs on logged data only (quadobs replay), not in a simulated scenario")
    from quadobs.estimators.gtsam_peer import Isam2RangeOnly

    est = Isam2RangeOnly(s.beacons, s.dt, x0=x0, heading0=s.heading0, P0=s.P0, n=s.n, range_sigma=s.range_sigma,
                         q_xy=s.q_xy, q_theta=s.q_theta)
    est.name = name
    return est


#: The replay's own estimators by name.
REPLAY_ESTIMATORS = {"augmented": build_augmented, "ekf": build_ekf, "isam2": build_isam2}


def build_replay_estimators(setup: ReplaySetup, names: list[str], x0: np.ndarray) -> list[Estimator]:
    """The named estimators, all from ``x0``; names beyond :data:`REPLAY_ESTIMATORS` come from the registry."""
    if len(set(names)) != len(names):
        raise QuadobsError(f"estimators: names must be distinct, got {names}")
    out = []
    for name in names:
        factory = REPLAY_ESTIMATORS.get(name)
        if factory is None:
            from quadobs.testbed.registry import estimator_factory

            factory = estimator_factory(name)[0]
        est = factory(setup, np.array(x0, dtype=float), name)
        if not isinstance(est, Estimator):
            raise QuadobsError(f"estimators: the factory of {name!r} returned {type(est).__name__}, not an Estimator")
        est.name = name
        out.append(est)
    return out
