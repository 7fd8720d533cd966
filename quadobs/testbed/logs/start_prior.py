"""What the log's first half second tells of the vehicle's velocity, and the replay's prior on it.

A log states no spread of its start's velocity. Where it holds an IMU, its first samples
tell whether the vehicle is at rest. The first :data:`START_WINDOW` seconds (the initial
alignment's half second, :func:`~quadobs.testbed.attitude.initial_alignment`) are cut into
slices of :data:`SLICE` seconds; the vehicle is at rest over the leading slices (until the
first that shows motion) in which, with ``N`` samples,

* the gyroscope's median is within ``k sqrt(c sigma_w^2 / N + b_w^2)`` of zero on each axis,
* the specific force's median ``f_m`` is within ``delta = k sqrt(c sigma_f^2 / N + b_f^2)``
  of gravity: its norm within ``delta`` of ``g`` (a body IMU), each axis within ``delta`` of
  zero (an accelerometer in the navigation frame, gravity removed),

with ``c = pi / 2`` (the variance of a median of Gaussian samples against their mean's),
``sigma_f = a_d / sqrt(h)`` and ``sigma_w = w_d / sqrt(h)`` the per-sample noise of the log's
stated densities ``a_d``, ``w_d`` (``meta.csv`` ``accel_noise``, ``gyro_noise``) at the
sampling interval ``h``, else the window's own spread (``1.4826`` times the median absolute
deviation per axis; a window that shows no noise is not tested); ``b_f``, ``b_w`` the stated
constant biases (0 where none is stated) and ``k`` = :data:`REST_K` (three standard
deviations). Medians of short slices, not the window's mean and spread: a single corrupt
first sample does not decide, a vibration that averages out within a slice (motors on the
ground) moves no velocity, and a take-off within the window ends the rest at its slice.

Over a rest of ``T`` seconds, the velocity's prior standard deviation per axis is what the
test cannot exclude: a steady acceleration ``a_max`` that no slice shows, acting over ``T``,
so ``sigma_v = a_max T``. In the navigation frame ``a_max = delta`` (without bias
``k a_d sqrt(c T_s) / T_s``, ``T_s`` the slice). A body IMU's norm test is first-order in an
acceleration along gravity only; one across gravity changes the norm by ``a^2 / (2 g)``, so
there ``a_max = sqrt((g + delta)^2 - g^2)``: the acceleration across gravity whose specific
force's norm is ``g + delta``. Where the first slice shows motion, and for a log without an
IMU (odometry, ranges alone), the velocity keeps :data:`UNKNOWN_VELOCITY_STD` (2 m/s, a
walking or hovering vehicle's speed).

An IMU tells accelerations, not velocity: a vehicle gliding at a constant velocity when its
log starts passes the test. The bound is therefore reported (the summary's ``start``:
``at_rest``, ``velocity_std``, ``reason``, ``applied: false``), not applied: the filters take
``UNKNOWN_VELOCITY_STD`` unless the user, who knows the vehicle starts standing, gives
``--tune velocity_std=...`` (:func:`velocity_variance`). Wheel odometry measures the speed itself: the replay's odometry model holds no
velocity state, so this prior does not enter it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "REST_K",
    "SLICE",
    "START_WINDOW",
    "UNKNOWN_VELOCITY_STD",
    "StartPrior",
    "start_prior",
    "velocity_variance",
]

#: The window at the log's start that the rest test reads (s): the initial alignment's.
START_WINDOW = 0.5
#: The test's bound in standard deviations.
REST_K = 3.0
#: The velocity's prior standard deviation per axis where the log does not show rest (m/s).
UNKNOWN_VELOCITY_STD = 2.0
#: The slices the window is tested in (s): shorter than a take-off's first tenths of a second.
SLICE = 0.1
#: The fewest samples a slice must hold for a test.
MIN_SAMPLES = 5
#: The variance of the median of Gaussian samples over that of their mean (large ``N``).
MEDIAN_VARIANCE = math.pi / 2


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
        """The replay summary's ``start`` entry: the test's outcome and bound, reported (the
        filters take 2 m/s unless told otherwise: :func:`velocity_variance`)."""
        return {
            "at_rest": self.at_rest,
            "velocity_std": self.velocity_std,
            "reason": self.reason,
            "applied": False,
        }


def _unknown(reason: str) -> StartPrior:
    return StartPrior(False, UNKNOWN_VELOCITY_STD, reason)


def _stated(value) -> float:
    """A stated figure (NaN or None: 0, not stated)."""
    value = math.nan if value is None else float(value)
    return value if math.isfinite(value) else 0.0


def _sample_noise(samples: np.ndarray, density, h: float) -> np.ndarray:
    """The per-sample standard deviation per axis: the stated density ``/ sqrt(h)``, else the
    samples' own robust spread (1.4826 times the median absolute deviation)."""
    d = _stated(density)
    if d > 0:
        return np.full(samples.shape[1], d / math.sqrt(h))
    centre = np.median(samples, axis=0)
    return 1.4826 * np.median(np.abs(samples - centre), axis=0)


def _still(f: np.ndarray, w: np.ndarray | None, tol_f: float, tol_w, g: float | None) -> str:
    """The motion that one slice's samples show (module docstring), or ``""``."""
    f_m = np.median(f, axis=0)
    if g is None and np.any(np.abs(f_m) > tol_f):
        return "the acceleration differs from zero"
    if g is not None and abs(float(np.linalg.norm(f_m)) - g) > tol_f:
        return "the specific force's norm differs from gravity"
    if w is not None and np.any(np.abs(np.median(w, axis=0)) > tol_w):
        return "the gyroscope's rate differs from zero"
    return ""


def start_prior(
    log, window: float = START_WINDOW, k: float = REST_K, slice_: float = SLICE
) -> StartPrior:
    """The velocity's prior of a replay of ``log`` (module docstring)."""
    kind = log.input_kind
    if kind not in ("imu_body", "imu"):
        return _unknown(f"no IMU (inputs: {kind})")
    t = log.inputs[:, 0]
    inside = t < t[0] + window if t.size else np.zeros(0, dtype=bool)
    if np.count_nonzero(inside) < 2 * MIN_SAMPLES:
        return _unknown(f"{np.count_nonzero(inside)} IMU samples in the first {window:g} s")
    h = float(np.median(np.diff(t[inside])))
    dim = log.beacons.shape[1]
    f = log.inputs[inside, 1:4] if kind == "imu_body" else log.inputs[inside, 1 : 1 + dim]
    w = log.inputs[inside, 4:7] if kind == "imu_body" else None
    sigma_f = float(np.max(_sample_noise(f, getattr(log, "accel_noise", None), h)))
    sigma_w = None if w is None else _sample_noise(w, getattr(log, "gyro_noise", None), h)
    if not sigma_f > 0 or (sigma_w is not None and not np.all(sigma_w > 0)):
        return _unknown("the IMU states no noise and shows none")
    b_f, b_w = _stated(getattr(log, "accel_bias", None)), _stated(getattr(log, "gyro_bias", None))
    g = float(log.gravity) if kind == "imu_body" else None
    which = np.floor((t[inside] - t[0]) / slice_).astype(int)
    rest, why, delta = 0.0, "", math.inf
    for j in range(int(which.max()) + 1):
        m = which == j
        n = int(np.count_nonzero(m))
        if n < MIN_SAMPLES:
            break
        tol_f = k * math.sqrt(MEDIAN_VARIANCE * sigma_f**2 / n + b_f**2)
        tol_w = None if sigma_w is None else k * np.sqrt(MEDIAN_VARIANCE * sigma_w**2 / n + b_w**2)
        why = _still(f[m], None if w is None else w[m], tol_f, tol_w, g)
        if why:
            break
        rest, delta = rest + n * h, min(delta, tol_f)
    if rest == 0.0:
        return _unknown(why + " in the first slice" if why else "no slice to test")
    a_max = delta if g is None else math.sqrt((g + delta) ** 2 - g**2)
    return StartPrior(True, a_max * rest, f"no motion in the first {rest:.2g} s")


def velocity_variance(setup) -> float:
    """The velocity's prior variance per axis (m^2/s^2) of a replay's filter built on ``setup``
    (:class:`~quadobs.testbed.logs.estimators.ReplaySetup`): the square of its ``velocity_std``
    where the user gives one (``--tune velocity_std=...``), else ``UNKNOWN_VELOCITY_STD^2``.

    The rest test's bound (``setup.start``) is reported, not applied: an IMU cannot tell rest
    from a constant velocity, and a log that starts in flight at a steady speed passes the test
    (the exported ``tdoa-room``, moving at 1 m/s: its EKF 0.021 m live, 0.083 m replayed from
    the bound of 0.002 m/s). A default that can make the filters worse than 2 m/s does is
    not taken; a user who knows the vehicle starts standing gives the bound."""
    std = getattr(setup, "velocity_std", None)
    std = UNKNOWN_VELOCITY_STD if std is None else float(std)
    return std * std
