"""A body-frame IMU as the navigation-frame acceleration the replay models take.

A body IMU (``imu.csv``) reads the specific force ``f`` and the angular rate ``omega`` in the
body frame. With the body-to-navigation rotation ``R`` and gravity ``g`` (the log's
:attr:`~quadobs.testbed.logs.format.RangeLog.gravity_vector`, ``-g e_z`` in an ``enu``
frame), the acceleration in the navigation frame is

.. math:: a = R f + g ,

the known input of the double integrator (model ``imu``). The rotation comes from the log's
``attitude.csv`` where it has one (interpolated to the IMU's times by spherical linear
interpolation, held before its first and after its last sample), else it is estimated from
the IMU alone by the Mahony complementary filter of the maintained ``ahrs`` package
(:class:`ahrs.filters.Mahony`, chosen over a hand-written filter: tested, and it estimates
the gyroscope's bias through its integral gain ``k_I``; :data:`MAHONY_GAINS`). Without a
magnetometer the heading
is not observable: it starts at zero and follows the bias-corrected gyroscope, so an
estimated attitude suits logs that start with the body axes along the navigation axes
(as the simulated quadrotor's) or whose horizontal accelerations are small.

The filter starts from an initial alignment (:func:`initial_alignment`), as an inertial
system is aligned before it moves: over the first :data:`ALIGN_TIME` seconds, the median
specific force gives the tilt (the median, not the first sample: a log's first rows may
hold a transient, such as a vehicle settling on its legs), and, where the vehicle rests
there, the median angular rate is the gyroscope's bias, the filter's initial ``b``. A
Mahony filter started from one bad sample with ``k_P = 0.1`` takes tens of seconds to find
the tilt, and every second of a tilt error ``delta`` puts ``g delta`` into the acceleration.

The estimated heading starts at zero, the IMU's first heading, which need not be the log's x
axis: :func:`heading_offset` finds the turn between the two from the ranges, and the
acceleration is turned by it where the ranges show it.

The gyroscope's bias. The alignment's test of rest (the specific force's norm near ``g``)
cannot tell a standing body from a flying multirotor, whose thrust balances its weight: a log
begun in flight has the alignment take the body's turning rates for the gyroscope's bias. The
Mahony filter's integral unlearns it slowly (its loop's time constant ``1 / sqrt(k_I) =
20`` s): a bias error ``db`` tilts the attitude by up to ``db / (sqrt(k_I) e)``, and each
0.01 rad/s of it puts up to 0.7 m/s^2 into the acceleration for tens of seconds. On the flight
of ``sims/stress_hidden_logs.py`` begun 5 s in (``moving``, seed 1) the alignment's rates
were off by 0.016 and 0.010 rad/s and the acceleration by 1.0 to 1.4 m/s^2 over 5 to 35 s
(against the same flight's log begun at rest). The ranges see it:
:func:`gyro_bias_from_ranges` fits the bias whose AHRS acceleration best matches the ranges'
accelerations (the filter's response to a bias step is linear), and the AHRS is run again
from it where the fit is significant and the log's start is not a rest: where the IMU's rest
test and the ranges of its rest say the vehicle stands (the log's ``starts_at_rest``, the start
prior's ``at_rest``), the alignment measured the bias on a standing body and is kept (a fit at three standard
deviations whose residuals are serially correlated would otherwise act on any systematic misfit
of a long log). On that flight it found the bias within 0.003 rad/s of
the rest's alignment, the acceleration then within 0.07 to 0.24 m/s^2 (5 s means) of the log
begun at rest. Like :func:`heading_offset`, it reads the whole log's ranges (the replay's attitude is
prepared from the log before the filters run).
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from quadobs.core.quantiles import fisher_ppf
from quadobs.errors import QuadobsError

__all__ = [
    "AHRS_RATE",
    "ALIGN_TIME",
    "GYRO_FULL_SCALE",
    "MAHONY_GAINS",
    "REST_TOLERANCE",
    "attitude_at",
    "check_body_imu",
    "estimate_attitude",
    "gyro_bias_from_ranges",
    "heading_offset",
    "initial_alignment",
    "navigation_accelerations",
]

#: The Mahony filter's gains (``k_P`` 1/s, ``k_I`` 1/s^2). The filter takes the specific force
#: for gravity, which a moving vehicle's own accelerations (and a multirotor's thrust, always
#: along its body z) contradict; they average out over a few seconds of manoeuvres, so the tilt
#: is pulled towards the accelerometer's with a time constant of ``1 / k_P = 10`` s and follows
#: the gyroscope in between; ``k_I = k_P^2 / 4`` makes the loop critically damped (natural
#: frequency ``sqrt(k_I)``, damping ``k_P / (2 sqrt(k_I)) = 1``). ``ahrs``' defaults (1, 0.3)
#: trust the accelerometer ten times faster.
MAHONY_GAINS = (0.1, 0.0025)


#: The initial alignment's window (s) from the log's first IMU sample: long enough for a median
#: over hundreds of samples at an IMU's 100 Hz to 1 kHz (its tilt error then a small fraction of
#: the accelerometer's per-sample noise over ``g``), short against the seconds a vehicle rests
#: before it moves.
ALIGN_TIME = 0.5

#: How far (a fraction of ``g``) the median specific force's magnitude may be from gravity for
#: the vehicle to be taken as resting during the alignment: 5 % (0.49 m/s^2), above a MEMS
#: accelerometer's bias and scale error (up to 0.3 m/s^2 and 1 %; 2.5 times the 0.2 m/s^2
#: prior of the replay's bias states), below the thrust excess of a take-off (a fifth of ``g``
#: and more).
REST_TOLERANCE = 0.05


def initial_alignment(
    times: np.ndarray, accel: np.ndarray, gyro: np.ndarray, gravity: float
) -> tuple[np.ndarray, np.ndarray]:
    """The attitude ``(qw, qx, qy, qz)`` (tilt only, heading zero) and the gyroscope's bias (rad/s)
    from the first :data:`ALIGN_TIME` seconds of a body IMU (module docstring).

    With ``f`` the median specific force over the window, the rotation takes ``f / |f|`` to
    ``+z``: roll ``atan2(f_y, f_z)``, pitch ``atan2(-f_x, sqrt(f_y^2 + f_z^2))``. The bias is the
    median angular rate when ``| |f| - g | <= REST_TOLERANCE g`` (resting), else zero.
    """
    window = times <= times[0] + ALIGN_TIME
    f = np.median(accel[window], axis=0)
    norm = float(np.linalg.norm(f))
    f0 = f / max(norm, 1e-12)
    roll, pitch = np.arctan2(f0[1], f0[2]), np.arctan2(-f0[0], np.hypot(f0[1], f0[2]))
    cr, sr, cp, sp = np.cos(roll / 2), np.sin(roll / 2), np.cos(pitch / 2), np.sin(pitch / 2)
    q = np.array([cr * cp, sr * cp, cr * sp, -sr * sp])
    resting = abs(norm - gravity) <= REST_TOLERANCE * gravity
    bias = np.median(gyro[window], axis=0) if resting else np.zeros(3)
    return q, bias


def _rotation(quaternions: np.ndarray):
    from scipy.spatial.transform import Rotation

    q = np.asarray(quaternions, dtype=float)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])  # scipy: scalar last


def attitude_at(attitude: np.ndarray, times: np.ndarray):
    """The rotations of ``attitude (A, 5)`` (``time, qw, qx, qy, qz``) at ``times``, by slerp."""
    from scipy.spatial.transform import Slerp

    t = attitude[:, 0]
    if t.size == 1:
        return _rotation(np.repeat(attitude[:, 1:], times.size, axis=0))
    keep = np.concatenate([[True], np.diff(t) > 0])
    slerp = Slerp(t[keep], _rotation(attitude[keep, 1:]))
    return slerp(np.clip(times, t[0], t[-1]))


#: The rate (Hz) at which the Mahony filter is updated: an IMU sampled faster is averaged over
#: blocks of ``m = round(1 / (AHRS_RATE h_s))`` samples (interval ``h_s``). The filter's loop
#: (``1 / k_P = 10`` s) and a multirotor's attitude motion (a bandwidth of about 10 rad/s) are
#: far slower than 100 Hz; the block's mean rate integrates a rotation about a fixed axis
#: exactly, and a coning motion of rate ``omega`` with an error of the order of
#: ``(omega h)^2``, 1e-4 rad at 1 rad/s. Between the blocks' starts the attitude is
#: interpolated (:func:`attitude_at`). It makes the Python loop ``m`` times shorter.
AHRS_RATE = 100.0


def estimate_attitude(
    times: np.ndarray,
    accel: np.ndarray,
    gyro: np.ndarray,
    gravity: float = 9.80665,
    bias: np.ndarray | None = None,
    rate: float = AHRS_RATE,
) -> np.ndarray:
    """Body-to-navigation quaternions ``(K, 4)`` (``qw, qx, qy, qz``) from the IMU alone (Mahony).

    The first from the initial alignment (:func:`initial_alignment`: tilt, heading zero, the
    gyroscope's bias where the vehicle rests), then one ``ahrs`` update per block of samples
    (:data:`AHRS_RATE`) with the block's mean specific force and rate over the block's span;
    the samples' attitudes interpolated between the blocks' starts. ``bias``: the gyroscope's
    bias the filter starts from, in place of the alignment's (:func:`gyro_bias_from_ranges`).
    ``rate``: the filter's update rate (Hz), :data:`AHRS_RATE` unless a cheaper pass is asked.
    """
    from ahrs.filters import Mahony

    if not (math.isfinite(rate) and rate > 0.0):
        raise QuadobsError(f"AHRS rate: expected a positive number (Hz), got {rate}")
    k_p, k_i = MAHONY_GAINS
    dts = np.diff(times)
    h = float(np.median(dts)) if dts.size and np.median(dts) > 0 else 1.0 / AHRS_RATE
    m = max(int(round(1.0 / (rate * h))), 1)
    starts = np.arange(0, times.size, m)
    t_block = times[starts]
    f_block = np.add.reduceat(accel, starts, axis=0) / np.diff(np.r_[starts, times.size])[:, None]
    w_block = np.add.reduceat(gyro, starts, axis=0) / np.diff(np.r_[starts, times.size])[:, None]
    q, aligned = initial_alignment(times, accel, gyro, gravity)
    bias = aligned if bias is None else np.asarray(bias, dtype=float)
    filt = Mahony(frequency=1.0 / (m * h), k_P=k_p, k_I=k_i, b0=bias)
    Q = np.empty((t_block.size, 4))
    Q[0] = q
    for k in range(1, t_block.size):
        dt = float(t_block[k] - t_block[k - 1])
        if dt > 0:
            q = filt.updateIMU(q, w_block[k - 1], f_block[k - 1], dt=dt)
        Q[k] = q
    if m == 1:
        return Q
    R = attitude_at(np.column_stack([t_block, Q]), times)
    return R.as_quat()[:, [3, 0, 1, 2]]


#: The heading offset's windows (s): each window's median range per anchor is multilaterated
#: into one position (a tag's round robin over 8 anchors at 100 Hz gives each anchor about 6
#: ranges in 0.5 s; the median leaves its outliers out).
HEADING_WINDOW = 0.5

#: The half-span ``T`` (s) of the second differences that turn those positions into
#: accelerations: their noise falls as ``1 / T^2`` (0.2 m over ``T = 2`` s: 0.05 m/s^2), while
#: a vehicle's manoeuvres of periods of seconds and more are kept.
HEADING_SPAN = 2.0


def heading_offset(log, nav: np.ndarray) -> float:
    """The heading (rad) of the AHRS's frame in the log's navigation frame, from the ranges; 0 when
    the ranges do not show it.

    An attitude estimated from the IMU alone has its heading zero at the start (no
    magnetometer), so its navigation-frame acceleration ``u`` (``nav``, ``time, ax, ay, az``)
    is the log's ``a`` turned by an unknown ``psi`` about the vertical: ``a_h = R_z(psi) u_h``.
    The ranges give ``a`` without the IMU: positions ``p_j`` multilaterated every
    :data:`HEADING_WINDOW` seconds, their second differences over ``T =`` :data:`HEADING_SPAN`
    equal ``int (T - |s|) a(t_j + s) ds / T^2``, and the same of ``u`` is the second difference
    of its double integral (initial conditions cancel). ``psi`` is the least-squares rotation
    between the two sets of horizontal vectors, ``arg sum conj(u_j) a_j`` (as complex numbers).
    It is applied when their coherence ``|sum conj(u_j) a_j| / sum |u_j| |a_j|`` exceeds
    ``3 / sqrt(N)``, three times what ``N`` independent spans (``N = duration / (2 T)``) of
    unrelated vectors give.
    """
    if log.ranges.shape[0] == 0 or log.dimension != 3:
        return 0.0
    mid, T, a, ok = _range_accelerations(log)
    b = _imu_second_differences(nav, mid, T)
    ok = ok & (mid - T >= nav[0, 0]) & (mid + T <= nav[-1, 0])
    if np.count_nonzero(ok) < 2:
        return 0.0
    a = _as_the_ahrs_sees(mid, a, ok)
    za = a[ok, 0] + 1j * a[ok, 1]
    zu = b[ok, 0] + 1j * b[ok, 1]
    cross = complex(np.sum(np.conj(zu) * za))
    scale = float(np.sum(np.abs(zu) * np.abs(za)))
    spans = max((nav[-1, 0] - nav[0, 0]) / (2.0 * T), 1.0)
    if scale <= 0.0 or abs(cross) / scale <= 3.0 / np.sqrt(spans):
        return 0.0
    return float(np.angle(cross))


def _range_accelerations(log):
    """``(mid, T, a, ok)``: the horizontal accelerations ``a (J, 2)`` that the ranges give
    (:func:`heading_offset`: positions multilaterated every :data:`HEADING_WINDOW` seconds,
    their second differences over ``T =`` :data:`HEADING_SPAN`) at the times ``mid``, and
    where they are finite (``ok``); computed once per log."""
    if log in _RANGES:
        return _RANGES[log]
    _RANGES[log] = found = _range_accelerations_of(log)
    return found


def _range_accelerations_of(log):
    """:func:`_range_accelerations`, computed."""
    from quadobs.core.system import vehicle_system
    from quadobs.estimators.robust import multilateration

    ranges = [m for m in log.measurements() if m.kind == "range"]  # in time order
    t_r = np.array([m.t for m in ranges])
    anchor = np.array([m.anchors[0] for m in ranges], dtype=int)
    rho = np.array([m.value for m in ranges])
    edges = np.arange(log.start, log.end, HEADING_WINDOW)
    system = vehicle_system(3, log.beacons)
    q = log.beacons.shape[0]
    P = np.full((edges.size, 2), np.nan)  # horizontal positions (anchors in one plane give no z)
    bounds = np.searchsorted(t_r, np.r_[edges, np.inf]).astype(int)  # ranges in time order
    for j in range(edges.size):
        a_j, r_j = anchor[bounds[j] : bounds[j + 1]], rho[bounds[j] : bounds[j + 1]]
        y = np.full(q, np.nan)
        for h in np.unique(a_j):
            r = float(np.median(r_j[a_j == h]))
            y[h] = 0.5 * r * r - 0.5 * float(log.beacons[h] @ log.beacons[h])
        if np.count_nonzero(~np.isnan(y)) >= 4:
            fixed = multilateration(system.C, system.d, y)
            if fixed is not None and list(fixed[0][:2]) == [0, 1]:
                P[j] = fixed[1][:2]
    k = max(int(round(HEADING_SPAN / HEADING_WINDOW)), 1)
    T = k * HEADING_WINDOW
    tc = edges + 0.5 * HEADING_WINDOW
    a = (P[2 * k :] - 2.0 * P[k:-k] + P[: -2 * k]) / (T * T)
    return tc[k:-k], T, a, np.all(np.isfinite(a), axis=1)


def _imu_second_differences(nav: np.ndarray, mid: np.ndarray, T: float) -> np.ndarray:
    """The second differences over ``T`` at ``mid`` of the double integral of the horizontal
    accelerations ``nav`` (``time, ax, ay, ...``): :func:`_range_accelerations`' of the IMU."""
    t, u = nav[:, 0], nav[:, 1:3]
    dt = np.diff(t)[:, None]
    U1 = np.vstack([np.zeros((1, 2)), np.cumsum(0.5 * (u[1:] + u[:-1]) * dt, axis=0)])
    U2 = np.vstack([np.zeros((1, 2)), np.cumsum(0.5 * (U1[1:] + U1[:-1]) * dt, axis=0)])
    at = lambda times: np.column_stack([np.interp(times, t, U2[:, i]) for i in range(2)])  # noqa: E731
    return (at(mid + T) - 2.0 * at(mid) + at(mid - T)) / (T * T)


#: The step (rad/s) of the gyroscope's bias by which :func:`gyro_bias_from_ranges` finds the
#: AHRS's response to it (its response is linear over hundredths of a rad/s).
BIAS_STEP = 1e-3


#: The update rate (Hz) of the AHRS passes that find its response to the gyroscope's bias
#: (:func:`gyro_bias_from_ranges`): the response lives on the loop's scale of ten seconds
#: (``1 / k_P``), and four passes at a tenth of :data:`AHRS_RATE` cost less than half of one at
#: it (the fitted biases of the ``moving`` flights equal those of passes at 100 Hz to 1e-4
#: rad/s).
RESPONSE_RATE = 10.0


def _navigation(log, bias: np.ndarray, rate: float = AHRS_RATE) -> np.ndarray:
    """``time, ax, ay, az`` of the AHRS started from the gyroscope's ``bias``."""
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    R = _rotation(estimate_attitude(t, f, w, float(log.gravity), bias, rate))
    return np.column_stack([t, R.apply(f) + log.gravity_vector])


def gyro_bias_from_ranges(log, nav: np.ndarray) -> np.ndarray | None:
    """The gyroscope's bias that the ranges say the AHRS should start from, or None where they
    do not say it better than the initial alignment (module docstring, "The gyroscope's bias").

    ``nav`` is the AHRS's acceleration from the alignment's bias ``b_0``. A bias error
    ``db`` reaches it through the filter's loop, linearly: ``u(b_0 + db) = u(b_0) + S db``,
    ``S`` found by stepping each axis by :data:`BIAS_STEP` (passes at :data:`RESPONSE_RATE`;
    the yaw rate's bias turns the horizontal acceleration more and more with time, which the
    constant turn of :func:`heading_offset` does not take up: measured on the flights of
    ``sims/stress_hidden_logs.py``, leaving it out moved seed 3's ``none`` from 0.186 to 0.216 m). The ranges' horizontal
    accelerations ``a`` (:func:`_range_accelerations`, as the AHRS sees them,
    :func:`_as_the_ahrs_sees`, turned into its heading by :func:`heading_offset`) and the
    second differences ``D`` of the IMU's (:func:`_imu_second_differences`) give the least
    squares ``db = argmin |R_z(-psi) a - D u(b_0) - D S db|^2``. It is taken where its ``F``
    statistic, ``(db^T J^T J db / 3) / s^2`` with ``s^2`` the residuals' variance times
    ``2 T / HEADING_WINDOW`` (the overlap of neighbouring spans), exceeds the ``F(3, N - 3)``
    quantile at three standard deviations (0.9973), ``N`` the spans' ``2 J`` components over
    that overlap.
    """
    if log.ranges.shape[0] == 0 or log.dimension != 3 or log.input_kind != "imu_body":
        return None
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    b0 = initial_alignment(t, f, w, float(log.gravity))[1]
    mid, T, a, ok = _range_accelerations(log)
    ok = ok & (mid - T >= t[0]) & (mid + T <= t[-1])
    overlap = 2.0 * T / HEADING_WINDOW
    n = 2.0 * np.count_nonzero(ok) / overlap
    if n < 8:
        return None
    a = _as_the_ahrs_sees(mid, a, ok)
    psi = heading_offset(log, nav)
    c, s = math.cos(psi), math.sin(psi)
    a = a @ np.array([[c, -s], [s, c]])  # R_z(-psi) a, rows
    D0 = _imu_second_differences(nav, mid, T)
    D_r = _imu_second_differences(_navigation(log, b0, RESPONSE_RATE), mid, T)
    S = []
    for i in range(3):
        step = np.zeros(3)
        step[i] = BIAS_STEP
        D = _imu_second_differences(_navigation(log, b0 + step, RESPONSE_RATE), mid, T)
        S.append(((D - D_r) / BIAS_STEP)[ok].ravel())
    J = np.column_stack(S)
    r = (a - D0)[ok].ravel()
    db, *_ = np.linalg.lstsq(J, r, rcond=None)
    e = r - J @ db
    s2 = float(e @ e) / max(e.size - 3, 1) * overlap
    F = float(db @ (J.T @ J) @ db) / 3.0 / s2 if s2 > 0 else 0.0
    if not F > fisher_ppf(math.erf(3.0 / math.sqrt(2.0)), 3, n - 3):
        return None
    return b0 + db


def _as_the_ahrs_sees(times: np.ndarray, a: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The horizontal accelerations ``a (J, 2)`` at ``times`` (equally spaced) as the Mahony
    filter's acceleration shows them: high-passed by ``s^2 / (s^2 + k_P s + k_I)``.

    The filter takes the specific force's horizontal part for a tilt (a multirotor's thrust
    along its body z says "level", a level body's horizontal acceleration says "tilted"), and
    its proportional-integral loop follows that reading with the transfer
    ``(k_P s + k_I) / (s^2 + k_P s + k_I)``; the acceleration it leaves, ``R~ f + g``, is the
    rest, so slow manoeuvres reach it attenuated and advanced in phase (at 0.3 rad/s by a
    third, 0.4 rad). The ranges' accelerations pass through the same filter (bilinear
    transform; gaps ``~ok`` filled linearly) before they are compared.
    """
    from scipy.signal import bilinear, lfilter

    k_p, k_i = MAHONY_GAINS
    fs = 1.0 / float(times[1] - times[0])
    b, den = bilinear([1.0, 0.0, 0.0], [1.0, k_p, k_i], fs=fs)
    out = np.empty_like(a)
    idx = np.flatnonzero(ok)
    for i in range(2):
        filled = np.interp(np.arange(a.shape[0]), idx, a[idx, i])
        out[:, i] = lfilter(b, den, filled)
    return out


#: The largest full scale of a MEMS rate gyroscope (rad/s): +-2000 deg/s (the Crazyflie's BMI088
#: and most flight controllers' parts at their widest range). A rate beyond it cannot have been
#: read by such a sensor: :func:`check_body_imu` takes it for a gyroscope logged in deg/s.
GYRO_FULL_SCALE = math.radians(2000.0)


def check_body_imu(log) -> None:
    """Refuse a body IMU logged in other units than m/s^2 and rad/s, in one line naming the file
    and the columns (:class:`~quadobs.errors.QuadobsError`).

    * the accelerometer: the median of ``|f|`` over the log must lie within a factor 2 of the
      log's gravity ``g``. A vehicle resting, hovering or flying reads ``|f| = |a - g|``, whose
      median is ``g`` to within its typical acceleration (a multirotor's thrust stays within
      a few tenths of ``g`` of its weight for most of a flight); a log in ``g`` reads about 1,
      one in ``mg`` about 1000;
    * the gyroscope: no rate beyond :data:`GYRO_FULL_SCALE` (a log in deg/s of a vehicle
      turning faster than 0.6 rad/s reads beyond it).

    The rates of a gyroscope in deg/s that turns slowly stay within the full scale; where the
    log has no attitude, :func:`navigation_accelerations` then finds the attitude integrated
    from them not keeping gravity vertical (:func:`_check_gravity_held`).
    """
    g = float(log.gravity)
    f = np.linalg.norm(log.inputs[:, 1:4], axis=1)
    median = float(np.median(f)) if f.size else g
    if not 0.5 * g <= median <= 2.0 * g:
        hint = _accelerometer_hint(f, median, g)
        raise QuadobsError(
            f"{log.file_label('imu.csv')}, columns ax,ay,az: the median |a| is {median:.4g}, and a body's "
            f"specific force in m/s^2 has a median near gravity {g:g}{hint}"
        )
    w = np.abs(log.inputs[:, 4:7])
    if w.size and float(w.max()) > GYRO_FULL_SCALE:
        row, col = np.unravel_index(int(np.argmax(w)), w.shape)
        raise QuadobsError(
            f"{log.file_label('imu.csv')}, row {log.file_row('imu.csv', row)}, column "
            f"g{'xyz'[int(col)]}: "
            f"{float(log.inputs[row, 4 + col]):.4g} is beyond any MEMS gyroscope's range "
            f"({GYRO_FULL_SCALE:.1f} rad/s = 2000 deg/s): the rates must be in rad/s"
        )
    check_rates_against_attitude(log)


def _accelerometer_hint(f: np.ndarray, median: float, g: float) -> str:
    """What an accelerometer's norms ``|f|`` of median ``median`` outside ``[g/2, 2g]`` were
    likely logged in. A specific force in ``g`` keeps its norm near 1 (a vehicle never falls
    freely for long: its 5th percentile at least half its median); one with gravity taken
    out (a linear acceleration) comes near 0 whenever the vehicle does not accelerate; one in
    ``mg`` reads about 1000."""
    if median < 0.5 * g:
        if float(np.percentile(f, 5)) >= 0.5 * median:
            return " (a log in g: times g)"
        return (
            " (gravity taken out? the accelerometer must read the specific force, gravity "
            "included: g upwards at rest)"
        )
    return " (a log in mg: times g / 1000)" if 500.0 <= median <= 2000.0 else ""


def _check_gravity_held(log, nav: np.ndarray, given: bool = False) -> None:
    """Refuse an attitude estimated from the IMU (or, ``given``, the log's ``attitude.csv``)
    that does not keep gravity vertical.

    The mean of the navigation-frame acceleration ``a = R f + g`` over a log of span ``T`` is
    ``(v(T) - v(0)) / T``: for any vehicle (a few m/s over tens of seconds) a small fraction of
    ``g``. An attitude integrated from rates in the wrong unit (deg/s read as rad/s: every turn
    57 times too large) leaves ``R f`` pointing anywhere, and its mean far from ``-g``: refused
    where ``|mean a| > g / 2`` (a change of velocity of ``g T / 2``, 200 m/s over 40 s). A
    given attitude in another convention (navigation to body, the scalar last) or an
    accelerometer whose axes are not the body's (an axis's sign flipped) does the same.
    """
    t = nav[:, 0]
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    if span <= 0.0:
        return
    dt = np.diff(t)[:, None]
    mean = np.sum(nav[:-1, 1:] * dt, axis=0) / span
    g = float(log.gravity)
    if float(np.linalg.norm(mean)) > 0.5 * g:
        where, what, fix = (
            (
                "attitude.csv",
                "the attitude given",
                f"{GIVEN_ATTITUDE_HINT}, and meta.csv's frame the navigation frame's (enu: z up; ned: z down)",
            )
            if given
            else (
                "imu.csv, columns gx,gy,gz",
                "the attitude integrated from the rates",
                "the rates must be in rad/s",
            )
        )
        raise QuadobsError(
            f"{log.file_label(where)}: {what} does not keep gravity vertical (mean acceleration "
            f"{np.linalg.norm(mean):.3g} m/s^2 over {span:.4g} s, at most g / 2 for any "
            f"vehicle): {fix}"
        )


#: What a given attitude that the IMU or the ranges contradict may have got wrong.
GIVEN_ATTITUDE_HINT = (
    "the quaternion must be scalar first (qw,qx,qy,qz) and turn the body frame into the "
    "navigation frame, and imu.csv's axes be the body's, its accelerometer reading the specific "
    "force (+g along the up axis of a level body at rest)"
)

#: The window (s) over which :func:`check_rates_against_attitude` compares the gyroscope's
#: integrated rotation with the given attitude's, and the least rotation (rad) of a window it
#: counts: over half a second a multirotor's attitude moves by tenths of a radian, a bias of
#: 0.01 rad/s by 0.005 rad.
RATE_WINDOW = (0.5, 0.05)

#: The ratio of the gyroscope's rotation to the attitude's beyond which
#: :func:`check_rates_against_attitude` refuses the rates (a unit: deg/s read as rad/s is 57).
RATE_RATIO = 5.0

#: The least median cosine between the gyroscope's rotations and the attitude's, over at least
#: the given number of windows, below which :func:`check_rates_against_attitude` refuses the
#: attitude: a body-to-navigation attitude read the other way turns about the opposite axes
#: (cosine -1), one read scalar last about permuted ones.
RATE_AXES = (0.5, 5)


def check_rates_against_attitude(log) -> None:
    """Refuse a gyroscope whose rates do not turn as the log's given attitude does, in one line.

    Over windows of :data:`RATE_WINDOW` seconds, the rotation the attitude makes in the body
    frame (``log(R(t_0)^T R(t_1))``) against the rates integrated (``int omega dt``, exact for a
    rotation about a fixed axis, within the coning error otherwise), less the gyroscope's bias
    where the attitude holds still in that many windows (the median of the rates' rotation over
    the windows where the attitude turns by less than :data:`RATE_WINDOW`'s angle), each test
    over at least :data:`RATE_AXES`'s count of windows:

    * over the windows where the attitude turns by at least :data:`RATE_WINDOW`'s angle, the
      median ratio of the rates' angle to the attitude's at most :data:`RATE_RATIO` (rates in
      deg/s give 57). Not the other way: an attitude that jumps where the rates do not (an
      on-board filter's reset, a motion capture's glitch, a noisy attitude of a hovering
      vehicle) gives ratios near 0 and says nothing of the rates' unit;
    * over the windows where both turn by that angle, and by angles within :data:`RATE_RATIO`
      of each other (a gyroscope's bias against a jittering attitude turns both, by unrelated
      amounts), the median cosine between the two rotation vectors at least
      :data:`RATE_AXES`'s bound (an attitude given navigation to
      body turns about the opposite axes, one read scalar last about other axes: measured
      -0.98 and -0.26 on a simulated flight whose own gives 0.94).

    A log whose attitude and rates turn that much in fewer windows has too little to compare
    and is left as it is.
    """
    compared = rates_against_attitude(log.attitude, log.inputs)
    if compared is None:
        return
    window = RATE_WINDOW[0]
    ratio, windows, cosine = compared
    if ratio is not None and ratio > RATE_RATIO:
        raise QuadobsError(
            f"{log.file_label('imu.csv')}, columns gx,gy,gz: the rates integrated turn "
            f"{ratio:.3g} times as far as attitude.csv does (median over {windows} windows of "
            f"{window:g} s; deg/s read as rad/s: 57): the rates must be in rad/s, and "
            f"{GIVEN_ATTITUDE_HINT}"
        )
    bound, count = RATE_AXES
    if cosine.size >= count and float(np.median(cosine)) < bound:
        raise QuadobsError(
            f"{log.file_label('attitude.csv')}: the body rates of imu.csv turn about other axes "
            f"than the attitude does (median cosine {float(np.median(cosine)):.2f} over "
            f"{cosine.size} windows of {window:g} s, {bound:g} at least): the rates must be in "
            f"rad/s, on the attitude's clock, and {GIVEN_ATTITUDE_HINT}"
        )


def rates_against_attitude(att, inputs) -> tuple | None:
    """A body IMU's rates against an attitude ``att`` (rows ``time, qw, qx, qy, qz``), over
    windows of :data:`RATE_WINDOW` seconds (:func:`check_rates_against_attitude`).

    Returns None where they share no window, else the median ratio of the rates' angle to the
    attitude's over the windows where the attitude turns (None in fewer than
    :data:`RATE_AXES`'s count), that count of windows, and the cosines between the two
    rotation vectors over the windows where both turn by angles of one size.
    """
    if att is None or att.shape[0] < 2 or inputs.shape[0] < 2:
        return None
    window, least = RATE_WINDOW
    t, w = inputs[:, 0], inputs[:, 4:7]
    edges = np.arange(max(t[0], att[0, 0]), min(t[-1], att[-1, 0]) - window, window)
    if edges.size == 0:
        return None
    times = np.r_[edges, edges[-1] + window]
    R = attitude_at(att, times)
    rotation = (R[:-1].inv() * R[1:]).as_rotvec()
    dt = np.diff(t)[:, None]
    W = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (w[1:] + w[:-1]) * dt, axis=0)])
    rates = np.diff(np.column_stack([np.interp(times, t, W[:, i]) for i in range(3)]), axis=0)
    turned = np.linalg.norm(rotation, axis=1)
    count = RATE_AXES[1]
    moving = turned >= least
    if np.count_nonzero(~moving) >= count:  # the gyroscope's bias, where the attitude is still
        rates = rates - np.median(rates[~moving], axis=0)
    integrated = np.linalg.norm(rates, axis=1)
    windows = int(np.count_nonzero(moving))
    ratio = float(np.median(integrated[moving] / turned[moving])) if windows >= count else None
    both = moving & (integrated >= least)  # and by angles of one size (not a bias against jitter)
    both &= (integrated <= RATE_RATIO * turned) & (turned <= RATE_RATIO * integrated)
    cosine = np.sum(rotation * rates, axis=1)[both] / (turned * integrated)[both]
    return ratio, windows, cosine


_NAVIGATION: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_RANGES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def navigation_accelerations(log) -> np.ndarray:
    """The body IMU of ``log`` as ``time, ax, ay, az`` rows in the navigation frame (module
    docstring): rotated by the log's attitude, else by the AHRS's turned by
    :func:`heading_offset`; computed once per log."""
    if log.input_kind != "imu_body":
        raise QuadobsError(f"{log.name}: navigation accelerations need a body IMU (imu.csv)")
    if log in _NAVIGATION:  # a log is replayed several times (the calibration's candidates)
        return _NAVIGATION[log].copy()
    check_body_imu(log)
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    if log.attitude is not None and log.attitude.shape[0]:
        R = attitude_at(log.attitude, t)
    else:
        if log.frame != "enu":
            raise QuadobsError(
                f"{log.name}: a body IMU in a {log.frame} frame needs attitude.csv "
                "(the attitude is estimated in enu frames only)"
            )
        R = _rotation(estimate_attitude(t, f, w, float(log.gravity)))
    out = np.column_stack([t, R.apply(f) + log.gravity_vector])
    if log.attitude is not None and log.attitude.shape[0]:
        _check_gravity_held(log, out, given=True)
    if log.attitude is None or not log.attitude.shape[0]:
        _check_gravity_held(log, out)
        bias = None if log.starts_at_rest() else gyro_bias_from_ranges(log, out)
        if bias is not None:  # the alignment's rate was not the gyroscope's bias
            R = _rotation(estimate_attitude(t, f, w, float(log.gravity), bias))
            out = np.column_stack([t, R.apply(f) + log.gravity_vector])
            _check_gravity_held(log, out)
    if log.attitude is None or not log.attitude.shape[0]:  # the AHRS's heading is not the log's
        psi = heading_offset(log, out)
        c, s = np.cos(psi), np.sin(psi)
        out[:, 1:3] = out[:, 1:3] @ np.array([[c, s], [-s, c]])
    _NAVIGATION[log] = out
    return out.copy()
