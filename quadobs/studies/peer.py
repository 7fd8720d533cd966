"""The GTSAM peer on synthetic logs whose truth is known in closed form: the figures of ``docs/peer.md``.

The vehicle flies a circle of radius 2 m at 0.5 rad/s (1 m/s) with a vertical wave of
0.3 m, yawing at 0.2 rad/s, among six anchors of a room 8 m by 7 m by 3 m
(:data:`ANCHORS`); 2-D cases use its horizontal part and the four corners of a
10 m by 8 m room. Measurements come one at a time, the anchors in turn (as a two-way
ranging tag polls them) at ``rate`` Hz, with Gaussian noise of ``sigma``; the body IMU
is its exact specific force and angular rate at ``imu_rate`` Hz, with white noise. Each
case starts the peer ``offset`` metres off (every axis) and reports the online RMSE after
``burn_in`` seconds, the batch optimum's RMSE over the same nodes, and the wall time.

.. code-block:: python

    from quadobs.studies.peer import peer_study
    peer_study(duration=20.0)     # the table of docs/peer.md
"""

from __future__ import annotations

import math
import time

import numpy as np

from quadobs.core.measurements import Measurement

__all__ = ["ANCHORS", "CASES", "peer_study", "run_case"]

ANCHORS = np.array(
    [[0, 0, 0.2], [8, 0, 2.5], [8, 6, 0.3], [0, 6, 2.8], [4, -1, 1.5], [4, 7, 0.5]], float
)
ANCHORS_2D = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0]])
_W, _YAW0, _YAW_RATE = 0.5, 0.3, 0.2

#: name: (input kind, dimension, measurement kind, outlier probability, bias, loss)
CASES = {
    "ranges, constant velocity, 2-D": ("none", 2, "range", 0.0, False, "huber"),
    "ranges, constant velocity, 3-D": ("none", 3, "range", 0.0, False, "huber"),
    "ranges, accelerometer (navigation frame), 3-D": ("accel_nav", 3, "range", 0.0, False, "huber"),
    "ranges, body IMU (preintegration), 3-D": ("imu_body", 3, "range", 0.0, False, "huber"),
    "TDOA, constant velocity, 3-D": ("none", 3, "tdoa", 0.0, False, "huber"),
    "ranges with 10 % outliers, no robust loss": ("none", 3, "range", 0.1, False, "none"),
    "ranges with 10 % outliers, Huber": ("none", 3, "range", 0.1, False, "huber"),
    "ranges with 10 % outliers, Cauchy": ("none", 3, "range", 0.1, False, "cauchy"),
    "biased ranges, no bias state": ("none", 3, "biased", 0.0, False, "huber"),
    "biased ranges, bias as a state": ("none", 3, "biased", 0.0, True, "huber"),
}
#: The range biases of the ``biased`` cases (m), per anchor.
BIASES = np.array([0.3, -0.2, 0.1, 0.25, -0.3, 0.0])


def _truth(t: float):
    c, s = math.cos(_W * t), math.sin(_W * t)
    p = np.array([4 + 2 * c, 3 + 2 * s, 1.5 + 0.3 * math.sin(2 * _W * t)])
    a = np.array([-2 * _W**2 * c, -2 * _W**2 * s, -1.2 * _W**2 * math.sin(2 * _W * t)])
    return p, a


def _imu(t: float, a: np.ndarray) -> np.ndarray:
    psi = _YAW0 + _YAW_RATE * t
    c, s = math.cos(psi), math.sin(psi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.concatenate([R.T @ (a + [0.0, 0.0, 9.80665]), [0.0, 0.0, _YAW_RATE]])


def _measure(case, t: float, k: int, p: np.ndarray, anchors, sigma: float, rng):
    kind, outliers = case[2], case[3]
    m = len(anchors)
    if kind == "tdoa":
        i, j = k % m, (k + 1 + (k // m) % (m - 1)) % m
        d = np.linalg.norm(p - anchors[i]) - np.linalg.norm(p - anchors[j])
        return Measurement(t, "tdoa", float(d + sigma * rng.standard_normal()), (i, j))
    h = k % m
    rho = np.linalg.norm(p - anchors[h]) + sigma * rng.standard_normal()
    if kind == "biased":
        rho += BIASES[h]
    if outliers and rng.uniform() < outliers:
        rho += rng.uniform(1.0, 5.0)  # non-line-of-sight: metres longer
    return Measurement(t, "range", float(rho), (h,))


def run_case(
    name: str,
    *,
    duration: float = 20.0,
    rate: int = 50,
    imu_rate: int = 500,
    sigma: float = 0.05,
    offset: float = 2.0,
    burn_in: float = 5.0,
    seed: int = 0,
) -> dict:
    """One case of :data:`CASES`: online and batch RMSE after ``burn_in`` (m), wall time (s)."""
    from quadobs.estimators.gtsam_peer import Isam2Peer, PeerNoise

    case = CASES[name]
    input_kind, dim = case[0], case[1]
    rng = np.random.default_rng(seed)
    anchors = ANCHORS if dim == 3 else ANCHORS_2D
    noise = PeerNoise(
        range_sigma=sigma, q_imu=1e-3, loss=case[5], bias="state" if case[4] else "none"
    )
    x0 = np.concatenate([_truth(0.0)[0][:dim] + offset, np.zeros(dim)])
    est = Isam2Peer(anchors, input_kind, x0=x0, P0=4 * offset**2 * dim, noise=noise)
    sub = imu_rate // rate if input_kind in ("imu_body", "accel_nav") else 1
    dt = 1.0 / (rate * sub)
    err_list: list[float] = []
    time_list: list[float] = []
    start = time.perf_counter()
    for k in range(int(round(duration / dt)) + 1):
        t = k * dt
        est.predict(t)
        p, a = _truth(t)
        if k % sub == 0 and k > 0:
            est.correct(_measure(case, t, k // sub, p[:dim], anchors, sigma, rng))
            err_list.append(float(np.linalg.norm(est.x_hat[:dim] - p[:dim])))
            time_list.append(t)
        if input_kind == "imu_body":
            est.hold(_imu(t, a) + _imu_noise(rng))
        elif input_kind == "accel_nav":
            est.hold(a + 0.03 * rng.standard_normal(3))
    online = time.perf_counter() - start
    T, P = est.batch_trajectory()
    batch_err = np.linalg.norm(P - np.array([_truth(s)[0][:dim] for s in T]), axis=1)
    times, errs = np.array(time_list), np.array(err_list)
    out = {
        "online_rmse": float(np.sqrt(np.mean(errs[times > burn_in] ** 2))),
        "batch_rmse": float(np.sqrt(np.mean(batch_err[T > burn_in] ** 2))),
        "final_error": float(errs[-1]),
        "measurements": int(est.corrections),
        "seconds_online": online,
    }
    if est.biases is not None:
        out["bias_error_max"] = float(np.max(np.abs(est.biases - BIASES)))
    return out


def _imu_noise(rng) -> np.ndarray:
    """White noise of the synthetic IMU: 0.03 m/s^2 on the specific force, 1 mrad/s on the rate."""
    return np.concatenate([0.03 * rng.standard_normal(3), 1e-3 * rng.standard_normal(3)])


def peer_study(cases=None, **options) -> dict:
    """:func:`run_case` for each of ``cases`` (default: all of :data:`CASES`)."""
    return {name: run_case(name, **options) for name in (cases or CASES)}
