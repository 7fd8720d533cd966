"""The TDOA estimators of a replay: the TDOA observer, and the observer handing over to the EKF.

Entry points ``tdoa-observer`` and ``tdoa-handover`` of the group
``quadobs.replay_estimators`` (``factory(setup, x0, name)``, ``setup`` a
:class:`~quadobs.testbed.logs.estimators.ReplaySetup`), the logged-data counterparts of the
scenario's estimators of the same names (:mod:`quadobs.testbed.tdoa`). They need a log holding
TDOA (``tdoa.csv``) and an acceleration input (model ``imu``: the state ``(p, v)`` of the
observer's immersion, :mod:`quadobs.core.tdoa`).

Noise, from the setup as for the replay's other estimators (no value read from the truth):

* each TDOA its own logged standard deviation, else ``sqrt(2) range_sigma``
  (:meth:`~quadobs.testbed.logs.estimators.ReplaySetup.measurement_std`);
* the acceleration white noise of intensity ``q_imu`` (m^2/s^3), the EKF's
  (:func:`~quadobs.testbed.logs.estimators.build_ekf`), lifted into the observer's auxiliary
  states at its estimate (:class:`~quadobs.estimators.tdoa_observer.TdoaObserver`); where the
  log states its IMU's figures, ``q_imu`` is sized from them as the live filters size it
  (:func:`~quadobs.testbed.logs.estimators.imu_input_noise`; a density alone: its square
  floored at :data:`~quadobs.testbed.logs.estimators.ACCEL_NOISE`), and the self-calibration
  scores held-out TDOA (:func:`~quadobs.testbed.logs.calibration.calibrate_tdoa`);
* the initial position with variance ``P0`` per axis, the velocity 4 m^2/s^2 per axis.

The handover's EKF is the replay's ``ekf`` (the same models and noise) started from the
observer's estimate and covariance.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.kalman import ExtendedKalmanFilter, HeldInputModel, OutputModel
from quadobs.estimators.tdoa_observer import TdoaHandover, TdoaObserver

__all__ = ["build_tdoa_handover", "build_tdoa_observer", "replay_tdoa_ekf"]


def _check(s, name: str) -> None:
    if "tdoa" not in s.kinds:
        raise QuadobsError(f"estimators: {name!r} takes TDOA, and the log holds no tdoa.csv")
    if s.model != "imu":
        raise QuadobsError(
            f"estimators: {name!r} needs an acceleration input (model imu), not model {s.model!r}"
        )


def _P0(s) -> np.ndarray:
    return np.diag([s.P0] * s.dim + [4.0] * s.dim)


def replay_tdoa_ekf(s, x0: np.ndarray, P0: np.ndarray, time: float = 0.0):
    """The replay's EKF on TDOA (the models and noise of ``ekf`` for model ``imu``: the white
    acceleration ``q_imu`` on ``v' = u``) from ``x0, P0`` at ``time``; ``s`` a
    :class:`~quadobs.testbed.logs.estimators.ReplaySetup`."""
    V = np.diag([0.0] * s.dim + [s.q_imu] * s.dim)
    dyn = HeldInputModel(s.system, s.dt, V=V)
    out = OutputModel(
        s.system, s.range_sigma**2, offsets=0.5 * np.einsum("hi,hi->h", s.beacons, s.beacons)
    )
    ekf = ExtendedKalmanFilter(
        dyn, out, x0=x0, P0=P0, gate=s.gate, measurements=s.measurement_models()
    )
    ekf.time = time
    return ekf


def _observer(s, x0: np.ndarray) -> TdoaObserver:
    return TdoaObserver(
        s.beacons,
        s.dt,
        np.asarray(x0, dtype=float)[: 2 * s.dim],
        P0=_P0(s),
        std=s.measurement_std()["tdoa"],
        accel_psd=s.q_imu,
        gate=s.gate,
    )


def build_tdoa_observer(s, x0: np.ndarray, name: str = "tdoa-observer"):
    """Entry point ``tdoa-observer``: the TDOA observer on the log (module docstring)."""
    _check(s, name)
    est = _observer(s, x0)
    est.name = name
    return est


def build_tdoa_handover(s, x0: np.ndarray, name: str = "tdoa-handover"):
    """Entry point ``tdoa-handover``: the TDOA observer handing over to the replay's EKF."""
    _check(s, name)

    def filter_from(x, P, t):
        return replay_tdoa_ekf(s, x, P, t)

    est = TdoaHandover(_observer(s, x0), filter_from)
    est.name = name
    return est
