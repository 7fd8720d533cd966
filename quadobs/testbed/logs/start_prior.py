"""The replay's prior on the vehicle's velocity, read from the log's first half second.

A log states no spread of its start's velocity. Where it holds an IMU, its first samples
tell whether the vehicle is at rest: over the window ``T`` (:data:`START_WINDOW`, the initial
alignment's half second, :func:`~quadobs.testbed.attitude.initial_alignment`) of ``N``
samples at the interval ``h``, at rest means

* the gyroscope's mean within ``k sqrt(sigma_w^2 / N + b_w^2)`` of zero on each axis,
* the specific force's mean ``f_bar`` within ``delta = k sqrt(sigma_f^2 / N + b_f^2)`` of
  gravity: its norm within ``delta`` of ``g`` (a body IMU), each axis within ``delta`` of zero
  (an accelerometer in the navigation frame, gravity removed),
* where the log states its noise, each axis's sample variance below the ``chi^2(N - 1)``
  quantile of that noise (a vibrating or manoeuvring vehicle spreads its samples),

with ``sigma_f = a_d / sqrt(h)`` and ``sigma_w = w_d / sqrt(h)`` the per-sample noise of the
log's stated densities ``a_d``, ``w_d`` (``meta.csv`` ``accel_noise``, ``gyro_noise``), else
the window's own spread per axis (a window without noise, stated or shown, is not
tested); ``b_f``, ``b_w`` the stated constant biases (0 where none
is stated) and ``k`` = :data:`REST_K` (three standard deviations).

At rest, the velocity's prior standard deviation per axis is what the test cannot exclude:
a steady acceleration ``a`` that the window does not see, acting over ``T``, so
``sigma_v = a_max T``. In the navigation frame ``a_max = delta``, so that with no bias
``sigma_v = k sigma_f T / sqrt(N) = k a_d sqrt(T)``. A body IMU's norm test is first-order in an
acceleration along gravity only: one across it changes the norm by ``a^2 / (2 g)``, so there
``a_max = sqrt((g + delta)^2 - g^2)``, the acceleration across gravity whose specific force's
norm is ``g + delta``. Otherwise, and for a log without an IMU (odometry, ranges alone),
the velocity keeps :data:`UNKNOWN_VELOCITY_STD` (2 m/s, a walking or hovering vehicle's speed).

An IMU tells accelerations, not velocity: a vehicle gliding at a constant velocity when its
log starts passes the test. The prior assumes that a log whose first half second shows no
motion starts with the vehicle standing (a power-up on the ground or a hover), and the
summary reports the decision (``start``: ``at_rest``, ``velocity_std``) so that a reader can
see where it was taken. Wheel odometry measures the speed itself: the replay's odometry model
holds no velocity state, so this prior does not enter it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["REST_K", "START_WINDOW", "UNKNOWN_VELOCITY_STD", "StartPrior", "start_prior"]

#: The window at the log's start that the rest test reads (s): the initial alignment's.
START_WINDOW = 0.5
#: The test's bound in standard deviations.
REST_K = 3.0
#: The velocity's prior standard deviation per axis where the log does not show rest (m/s).
UNKNOWN_VELOCITY_STD = 2.0
#: The fewest samples the window must hold for a test (a variance of N - 1 degrees of freedom).
MIN_SAMPLES = 5


@dataclass(frozen=True)
class StartPrior:
    """The velocity's prior of a replay (module docstring).

    Attributes
    ----------
    at_rest : bool
        Whether the log's first window shows the vehicle at rest.
    velocity_std : float
        The velocity's prior standard deviation per axis (m/s).
    reason : str
        Why: the test that failed, or that the log holds no IMU.
    """

    at_rest: bool
    velocity_std: float
    reason: str

    def summary(self) -> dict:
        """The replay summary's ``start`` entry."""
        return {"at_rest": self.at_rest, "velocity_std": self.velocity_std, "reason": self.reason}


def _unknown(reason: str) -> StartPrior:
    return StartPrior(False, UNKNOWN_VELOCITY_STD, reason)


def _stated(value) -> float:
    """A stated figure (NaN or None: 0, not stated)."""
    value = math.nan if value is None else float(value)
    return value if math.isfinite(value) else 0.0


def _sample_noise(samples: np.ndarray, density, h: float) -> tuple[np.ndarray, bool]:
    """The per-sample standard deviation per axis: the stated density ``/ sqrt(h)``, else the
    window's own spread; and whether it was stated."""
    d = _stated(density)
    if d > 0:
        return np.full(samples.shape[1], d / math.sqrt(h)), True
    return np.std(samples, axis=0, ddof=1), False


def _spread_ok(samples: np.ndarray, sigma: np.ndarray, p: float) -> bool:
    """Each axis's sample variance below the ``p`` quantile of ``sigma^2 chi^2(N - 1) / (N - 1)``."""
    from scipy.stats import chi2

    n = samples.shape[0]
    bound = sigma**2 * chi2.ppf(p, n - 1) / (n - 1)
    return bool(np.all(np.var(samples, axis=0, ddof=1) <= bound))


def start_prior(log, window: float = START_WINDOW, k: float = REST_K) -> StartPrior:
    """The velocity's prior of a replay of ``log`` (module docstring)."""
    kind = log.input_kind
    if kind not in ("imu_body", "imu"):
        return _unknown(f"no IMU (inputs: {kind})")
    t = log.inputs[:, 0]
    inside = t <= t[0] + window if t.size else np.zeros(0, dtype=bool)
    n = int(np.count_nonzero(inside))
    if n < MIN_SAMPLES:
        return _unknown(f"{n} IMU samples in the first {window:g} s")
    h = float(np.median(np.diff(t[inside])))
    if not h > 0:
        return _unknown("IMU samples without an interval")
    p = math.erf(k / math.sqrt(2.0))
    dim = log.beacons.shape[1]
    f = log.inputs[inside, 1:4] if kind == "imu_body" else log.inputs[inside, 1 : 1 + dim]
    sigma_f, stated_f = _sample_noise(f, getattr(log, "accel_noise", None), h)
    if not np.all(sigma_f > 0):
        return _unknown("the accelerometer states no noise and shows none")
    b_f = _stated(getattr(log, "accel_bias", None))
    delta = k * math.sqrt(float(np.max(sigma_f)) ** 2 / n + b_f**2)
    f_bar = f.mean(axis=0)
    if stated_f and not _spread_ok(f, sigma_f, p):
        return _unknown("the specific force varies beyond its noise")
    if kind == "imu":
        if np.any(np.abs(f_bar) > delta):
            return _unknown("the acceleration's mean differs from zero")
        return StartPrior(True, delta * n * h, "no acceleration in the first window")
    g = float(log.gravity)
    if abs(float(np.linalg.norm(f_bar)) - g) > delta:
        return _unknown("the specific force's norm differs from gravity")
    w = log.inputs[inside, 4:7]
    sigma_w, stated_w = _sample_noise(w, getattr(log, "gyro_noise", None), h)
    if not np.all(sigma_w > 0):
        return _unknown("the gyroscope states no noise and shows none")
    b_w = _stated(getattr(log, "gyro_bias", None))
    if np.any(np.abs(w.mean(axis=0)) > k * np.sqrt(sigma_w**2 / n + b_w**2)):
        return _unknown("the gyroscope's mean differs from zero")
    if stated_w and not _spread_ok(w, sigma_w, p):
        return _unknown("the angular rate varies beyond its noise")
    a_max = math.sqrt((g + delta) ** 2 - g**2)
    return StartPrior(True, a_max * n * h, "no motion in the first window")
