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

Over a rest of ``T`` seconds, the velocity that the test cannot exclude for a vehicle that
stands at the start (the summary's ``velocity_std``, per axis) is a steady acceleration
``a_max`` that no slice shows, acting over ``T``: ``sigma_v = a_max T``. In the navigation frame ``a_max = delta`` (without bias
``k a_d sqrt(c T_s) / T_s``, ``T_s`` the slice). A body IMU's norm test is first-order in an
acceleration along gravity only; one across gravity changes the norm by ``a^2 / (2 g)``, so
there ``a_max = sqrt((g + delta)^2 - g^2)``: the acceleration across gravity whose specific
force's norm is ``g + delta``. Where the first slice shows motion, and for a log without an
IMU (odometry, ranges alone), the test reports :data:`UNKNOWN_VELOCITY_STD` (2 m/s, a
walking or hovering vehicle's speed).

An IMU tells accelerations, not velocity: a vehicle gliding at a constant velocity when its
log starts passes the test (the exported ``tdoa-room``, at 1 m/s). What the test does tell is
that the velocity hardly changes over the rest's ``T`` seconds; the ranges (or TDOA) of the
same window then tell the velocity itself (:func:`range_velocity`). Each anchor ``a`` gets a
line ``r_a(t) = rho_a + (u_a . v) (t - t_m)`` (its own intercept ``rho_a``, which takes in a
constant bias of that anchor; ``t_m`` the window's mean measurement time), a TDOA of anchors
``i, j`` the difference of two such lines, with ``u_a = (p - a) / |p - a|`` the unit vector
from the anchor to the position ``p`` at ``t_m``: the fix of the window's measurements (a
least-squares fit of ``p``, each measurement moved by ``v (t - t_m)``, alternated with the lines
twice from ``v = 0``; its covariance the inverse normal matrix scaled by its residuals'
``max(1, chi^2 / dof)``, ``dof`` the measurements less ``dim``: a fix from ranges that disagree
with one another is not reported as certain as one from ranges that agree). The intercepts and ``v`` are one weighted linear least-squares problem
with the measurements' standard deviations (their own, else ``range_sigma``, ``sqrt 2`` that for
a TDOA); ``v``'s covariance is the inverse normal matrix's velocity block, scaled by the
residuals' ``chi^2 / dof`` where that exceeds 1 (ranges noisier than stated). The prior on the
velocity at the log's start ``t_0`` is then

``v_0 ~ N(v_hat, C_v + (|v_hat| sigma_p / r_min)^2 I + (a_max (t_m - t_0))^2 I)``

with ``sigma_p`` the fix's largest position standard deviation over the nearest anchor's
distance ``r_min`` (the unit vectors' error, first order) and ``a_max (t_m - t_0)`` the velocity
that an acceleration no slice shows moves between the start and ``t_m``. It is identified
where the IMU shows rest and the ranges identify ``v``: at least ``dim + 1`` anchors measured,
more measurements than unknowns, and the prior's largest variance below
:data:`UNKNOWN_VELOCITY_STD` squared (it then says more than the unknown start in every
direction). It is reported in the summary's ``start`` and applied (``applied``, ``why``) only
where asked for (``--tune velocity_std=log``): on the exported ``quadrotor-uwb`` flights it
brought the replayed bias filters nearer the live ones (``ukf-bias`` 0.815-1.050 of live to
0.873-1.050) but further from the truth (``ukf-bias`` +4 % summed over the seven flights where
it was identified, ``ekf-bias`` the same): a default must not make the estimate worse. Elsewhere
the filters take ``UNKNOWN_VELOCITY_STD``; a user who knows better gives
``--tune velocity_std=...`` (:func:`velocity_prior`), which stands over both. Wheel odometry measures the speed itself: the replay's odometry model holds no velocity
state, so this prior does not enter it.

Standing or moving. The IMU's rest is a rest of the acceleration; :attr:`StartPrior.at_rest`
claims more, that the vehicle stands, and the ranges may contradict it
(:func:`ranges_moving`). Under a standing vehicle the lines' velocity is zero, and
``F = (v_hat^T N^-1 v_hat / dim) / s^2``, with ``N^-1`` the lines' unscaled velocity block
and ``s^2 = chi^2 / dof`` the noise that their own residuals show, follows Fisher's
``F(dim, dof)`` whatever the ranges' common scale (a log that states no noise is weighed by
the setup's 1 m, which would hide any velocity); a log whose ranges state their noise keeps
it as a floor, ``s^2 >= 1``, one that states none the resolution's ``(1 mm / sigma)^2``. The
vehicle is taken to move where ``F`` is beyond its quantile at the rest test's ``k`` standard
deviations (``erf(k / sqrt 2)``, :func:`rest_probability`, shared by the windows tried,
Bonferroni), over the IMU's rest or, where its ranges tell no velocity, over
:data:`MOTION_WINDOWS` multiples of the start's window (a rest of one slice of 0.1 s holds
eleven ranges at 100 Hz, fewer than eight intercepts and three rates need). It is then not
at rest (``moving``). A vehicle that starts to move within a window longer than the IMU's rest
(a take-off 0.3 s in, an acceleration the IMU's norm test does not see) is reported moving as
well: over that window a constant velocity's line does not tell a steady velocity from one
begun inside it at this noise (a line with an acceleration would, with many times the
variance). The report is the summary's; the filters' velocity prior takes none of it unless
asked (``--tune velocity_std=log``). ``velocity_std``
is :data:`UNKNOWN_VELOCITY_STD`, and the ranges' prior of the rest's window is reported (and
applied where asked) as before. The flight of ``sims/stress_hidden_logs.py`` begun 5 s in
(``moving``, 0.75 m/s) showed "no motion in the first 0.1 s" on three of five seeds; the
ranges of its first second now say 0.56 to 0.67 m/s (``F`` 7.9 to 11.5 against 6.0), and
the stand-in's own start (``none``, at rest 0.29 s before it takes off) stays at rest. Where
the IMU shows motion in its first slice (no rest), ``moving`` still says what the ranges of
those windows show (the ``moving`` flight's seeds 0 and 2: moving; the stand-in's: not).

Anchors in one plane. The fix's Gauss-Newton steps start at the measured anchors' centroid,
unless the anchors stand in one plane (in 3-D: every anchor closer than the ranges' standard
deviation to their best-fitting plane; anchors at one height, common indoors). On that plane
the Jacobian's column across it vanishes and a linear multilateration fixes no distance from
it, so the fix starts from what can be fixed (:func:`start_point`): the position in the plane
from the linear multilateration of each anchor's mean range, and the distance from the plane
from the ranges' own nonlinear solution, on the side of :data:`COPLANAR_SIDE` (below the
anchors, as the frame's ``up`` gives it); the steps then stay on that side, whose mirror
image fits the ranges as well. Anchors in one vertical plane (a wall) leave the side
unstated, and ranges that put the vehicle in the plane fix no distance from it: the ranges
then tell no velocity (the summary's ``why`` says which).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from quadobs.core.quantiles import fisher_ppf

__all__ = [
    "COPLANAR_SIDE",
    "REST_K",
    "SLICE",
    "START_WINDOW",
    "UNKNOWN_VELOCITY_STD",
    "RangeVelocity",
    "StartPrior",
    "range_velocity",
    "ranges_moving",
    "rest_probability",
    "set_velocity_prior",
    "start_point",
    "start_prior",
    "velocity_prior",
]

#: The window at the log's start that the rest test reads (s): the initial alignment's.
START_WINDOW = 0.5
#: The test's bound in standard deviations.
REST_K = 3.0
#: The velocity's prior standard deviation per axis where the log does not tell it (m/s).
UNKNOWN_VELOCITY_STD = 2.0
#: The slices the window is tested in (s): shorter than a take-off's first tenths of a second.
SLICE = 0.1
#: The fewest samples a slice must hold for a test.
MIN_SAMPLES = 5
#: The variance of the median of Gaussian samples over that of their mean (large ``N``).
MEDIAN_VARIANCE = math.pi / 2
#: The alternations of the fix and the lines (:func:`range_velocity`): from ``v = 0``, the
#: second fix moves each measurement by the first lines' velocity.
FIX_ROUNDS = 2
#: The most Gauss-Newton steps of a fix (from the anchors' centroid: a few suffice).
FIX_STEPS = 20
#: The ranges' windows of the test for motion beyond the IMU's rest: ``j`` times the start's
#: window, ``j = 1 ..`` this (:func:`ranges_moving`): ranges of 0.1 m at 100 Hz over eight
#: anchors tell 0.75 m/s from rest over one second, not over half of one.
MOTION_WINDOWS = 2
#: The least noise (m) that :meth:`RangeVelocity.motion` takes of ranges that state none: a
#: UWB range's resolution (a millimetre; exact simulated ranges are not infinitely precise).
RANGE_RESOLUTION = 1e-3
#: The side of a plane of anchors that the vehicle is taken to start on: ``+1`` below them
#: (anchors at one height are mounted high, on a ceiling or walls, to see over what stands
#: on the floor), ``-1`` above (:func:`start_point`).
COPLANAR_SIDE = 1.0


@dataclass(frozen=True, eq=False)
class RangeVelocity:
    """The velocity that the ranges (or TDOA) of a window tell (module docstring).

    Attributes
    ----------
    velocity : ndarray (dim,)
        ``v_hat`` at the window's mean measurement time ``t_m`` (m/s).
    covariance : ndarray (dim, dim)
        ``C_v`` plus the fix's term ``(|v_hat| sigma_p / r_min)^2 I`` (m^2/s^2).
    time : float
        ``t_m`` (s).
    anchors : int
        The anchors the window's measurements involve.
    measurements : int
    position, position_covariance : ndarray (dim,), (dim, dim)
        The fix ``p`` at ``t_m`` and its covariance, scaled by its residuals'
        ``max(1, chi^2 / dof)`` (module docstring).
    lines_covariance : ndarray (dim, dim) or None
        The lines' velocity block of the inverse normal matrix, unscaled (the measurements'
        standard deviations as given).
    chi2 : float
        The lines' weighted squared residuals.
    dof : int
        Their degrees of freedom: the measurements less the lines' unknowns.
    scale_floor : float
        The least noise scale :meth:`motion` takes (``chi^2 / dof`` at least this): 1 where
        every measurement states its standard deviation (the stated noise is a floor), else
        ``(RANGE_RESOLUTION / sigma)^2`` (the residuals' own spread, down to a range's
        resolution).
    """

    velocity: np.ndarray
    covariance: np.ndarray
    time: float
    anchors: int
    measurements: int
    position: np.ndarray | None = None
    position_covariance: np.ndarray | None = None
    lines_covariance: np.ndarray | None = None
    chi2: float = math.nan
    dof: int = 0
    scale_floor: float = 1.0

    def motion(self) -> float:
        """The F statistic of ``v = 0`` (a vehicle standing over the window),
        ``F = (v_hat^T N^-1 v_hat / dim) / (chi^2 / dof)`` with ``N^-1`` the unscaled
        :attr:`lines_covariance`: the velocity against the noise that the lines' own residuals
        show, at least :attr:`scale_floor`; ``F(dim, dof)``-distributed where the vehicle
        stands (module docstring, "Standing or moving"). NaN where not computed."""
        if self.lines_covariance is None or self.dof < 1:
            return math.nan
        v = self.velocity
        z = float(v @ np.linalg.solve(self.lines_covariance, v))
        return (z / v.size) / max(self.chi2 / self.dof, self.scale_floor)


@dataclass(frozen=True, eq=False)
class StartPrior:
    """The velocity's prior of a replay (module docstring).

    Attributes
    ----------
    at_rest : bool
        Whether the vehicle stands at the log's start: its first window shows no acceleration
        (the IMU's rest test) and its ranges no velocity (:func:`ranges_moving`).
    velocity_std : float
        The rest test's bound per axis (m/s): the velocity it cannot exclude for a vehicle
        standing at the start; :data:`UNKNOWN_VELOCITY_STD` where it shows no rest.
    moving : bool
        Whether the ranges of the log's start show a velocity (:func:`ranges_moving`): where
        the IMU shows no acceleration the vehicle moves at a steady velocity (not at rest; the
        ranges' prior of the rest's window still holds); where it shows motion, over its first
        :data:`MOTION_WINDOWS` windows.
    reason : str
        The rest test's outcome: the test that failed, or that the log holds no IMU.
    velocity, covariance : ndarray or None
        The prior's mean (dim,) and covariance (dim, dim) at the log's start, from the ranges
        of the rest's window (:func:`range_velocity`); None where they tell none.
    applied : bool
        Whether the filters take ``velocity`` and ``covariance`` (module docstring).
    why : str
        Why it is applied or not.
    """

    at_rest: bool
    velocity_std: float
    reason: str
    velocity: np.ndarray | None = None
    covariance: np.ndarray | None = None
    applied: bool = False
    why: str = ""
    moving: bool = False

    def summary(self) -> dict:
        """The replay summary's ``start`` entry: the rest test, the ranges' velocity and its
        standard deviation per axis, and whether the filters take it (``applied``, ``why``)."""
        v, C = self.velocity, self.covariance
        return {
            "at_rest": self.at_rest,
            "moving": self.moving,
            "velocity_std": self.velocity_std,
            "reason": self.reason,
            "applied": self.applied,
            "why": self.why,
            "velocity": None if v is None else [float(x) for x in v],
            "velocity_prior_std": None if C is None else [float(x) for x in np.sqrt(np.diag(C))],
        }


def _unknown(reason: str) -> StartPrior:
    return StartPrior(False, UNKNOWN_VELOCITY_STD, reason, why=f"no rest: {reason}")


def _stated(value) -> float:
    """A stated figure (NaN or None: 0, not stated)."""
    value = math.nan if value is None else float(value)
    return value if math.isfinite(value) else 0.0


def _sample_noise(samples: np.ndarray, density, h: float) -> np.ndarray:
    """The per-sample standard deviation per axis: the stated density ``/ sqrt(h)``, else the
    samples' own robust spread (1.4826 times the median absolute deviation)."""
    d = _stated(density)
    if d > 0 and h > 0:  # h NaN: every time repeated
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


def _rest(log, window: float, k: float, slice_: float) -> tuple[float, float, str]:
    """``(T, a_max, reason)``: the rest's length (0: none) and the largest acceleration that its
    slices cannot exclude (module docstring)."""
    kind = log.input_kind
    if kind not in ("imu_body", "imu"):
        return 0.0, math.inf, f"no IMU (inputs: {kind})"
    t = log.inputs[:, 0]
    inside = t < t[0] + window if t.size else np.zeros(0, dtype=bool)
    if np.count_nonzero(inside) < 2 * MIN_SAMPLES:
        return 0.0, math.inf, f"{np.count_nonzero(inside)} IMU samples in the first {window:g} s"
    from quadobs.testbed.logs.schema import sampling_period

    h = sampling_period(t[inside])
    dim = log.beacons.shape[1]
    f = log.inputs[inside, 1:4] if kind == "imu_body" else log.inputs[inside, 1 : 1 + dim]
    w = log.inputs[inside, 4:7] if kind == "imu_body" else None
    sigma_f = float(np.max(_sample_noise(f, getattr(log, "accel_noise", None), h)))
    sigma_w = None if w is None else _sample_noise(w, getattr(log, "gyro_noise", None), h)
    if not sigma_f > 0 or (sigma_w is not None and not np.all(sigma_w > 0)):
        return 0.0, math.inf, "the IMU states no noise and shows none"
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
        return 0.0, math.inf, why + " in the first slice" if why else "no slice to test"
    a_max = delta if g is None else math.sqrt((g + delta) ** 2 - g**2)
    return rest, a_max, f"no motion in the first {rest:.2g} s"


def start_prior(
    log,
    window: float = START_WINDOW,
    k: float = REST_K,
    slice_: float = SLICE,
    range_sigma: float | None = None,
    apply: bool = False,
) -> StartPrior:
    """The velocity's prior of a replay of ``log`` (module docstring); ``range_sigma`` the
    standard deviation of a range that states none (default: the setup's 1 m); ``apply``:
    the filters take the prior where it is identified (``--tune velocity_std=log``)."""
    rest, a_max, reason = _rest(log, window, k, slice_)
    sigma = 1.0 if range_sigma is None else float(range_sigma)
    if rest == 0.0:
        unknown = _unknown(reason)
        if log.input_kind not in ("imu_body", "imu") or not log.inputs.shape[0]:
            return unknown
        t0 = float(log.inputs[0, 0])
        spans = tuple(j * window for j in range(1, MOTION_WINDOWS + 1))
        moving = ranges_moving(log, t0, spans, sigma, None, k)
        return replace(unknown, moving=True, reason=f"{reason}; {moving}") if moving else unknown
    t0 = float(log.inputs[0, 0])
    found = range_velocity(log, t0, t0 + rest, sigma)
    spans = (rest, *(j * window for j in range(1, MOTION_WINDOWS + 1) if j * window > rest))
    moving = ranges_moving(log, t0, spans, sigma, found, k)
    standing = not moving
    bound = a_max * rest if standing else UNKNOWN_VELOCITY_STD
    if moving:
        reason = f"{reason} (the IMU's), but {moving}: moving, or starting to move"
    if isinstance(found, str):
        return StartPrior(standing, bound, reason, why=f"the ranges: {found}", moving=bool(moving))
    drift = a_max * (found.time - t0)  # the velocity's change from t_0 to t_m left open
    cov = found.covariance + drift**2 * np.eye(found.velocity.size)
    largest = float(np.sqrt(np.max(np.linalg.eigvalsh(cov))))
    identified = largest < UNKNOWN_VELOCITY_STD
    applied = identified and apply
    why = (
        f"{found.measurements} measurements of {found.anchors} anchors in the rest's "
        f"{rest:.2g} s: the velocity to {largest:.2g} m/s in its worst direction"
        + ("" if identified else f", no better than {UNKNOWN_VELOCITY_STD:g} m/s")
        + ("" if applied or not identified else "; reported, not applied (--tune velocity_std=log)")
    )
    return StartPrior(
        standing, bound, reason, found.velocity, cov, applied, why, moving=bool(moving)
    )


def rest_probability(k: float = REST_K) -> float:
    """The two-sided probability of ``k`` standard deviations, ``erf(k / sqrt 2)`` (0.9973 for
    :data:`REST_K`): the level of every test of the rest."""
    return math.erf(k / math.sqrt(2.0))


def ranges_moving(log, t0: float, spans, sigma: float, found=None, k: float = REST_K) -> str:
    """Why the ranges say the vehicle does not stand at the log's start, or ``""`` (module
    docstring, "Standing or moving").

    The lines' velocity of ``[t0, t0 + T)`` for each span ``T`` of ``spans`` in turn (``found``:
    that of the first, already fitted by :func:`range_velocity`), until one identifies it: the
    vehicle moves where it is beyond the quantile of ``F(dim, dof)`` at ``1 - (1 - P) / m``
    (:meth:`RangeVelocity.motion`; ``P`` the :func:`rest_probability`, ``m`` the spans: the
    chance that any of the tests rejects a standing vehicle stays below ``1 - P``). ``""``
    where no span's ranges tell a velocity or none rejects: they contradict nothing."""
    spans = sorted(set(float(T) for T in spans))
    level = 1.0 - (1.0 - rest_probability(k)) / len(spans)
    for i, span in enumerate(spans):
        probe = found if i == 0 and found is not None else range_velocity(log, t0, t0 + span, sigma)
        if not isinstance(probe, RangeVelocity) or not math.isfinite(probe.motion()):
            continue
        F = probe.motion()
        limit = fisher_ppf(level, probe.velocity.size, probe.dof)
        if F > limit:
            speed = float(np.linalg.norm(probe.velocity))
            return (
                f"the ranges of the first {span:.2g} s show {speed:.2g} m/s "
                f"(F = {F:.3g}, beyond {limit:.3g})"
            )
    return ""


def _window(log, t0: float, t1: float, sigma: float):
    """The window's measurements: times ``(N,)``, anchor weights ``W (N, B)`` (a range ``e_a``,
    a TDOA ``e_i - e_j``), values ``(N,)``, standard deviations ``(N,)``, and whether each
    states its own."""
    from quadobs.testbed.logs.schema import RANGE, TDOA

    B = log.beacons.shape[0]
    rows, parts, stated = [], [], True
    for table, std, cols, value, fallback in (
        (log.ranges, log.range_std, (RANGE.beacon,), RANGE.range, sigma),
        (
            log.tdoa,
            log.tdoa_std,
            (TDOA.anchor_i, TDOA.anchor_j),
            TDOA.difference,
            math.sqrt(2.0) * sigma,
        ),
    ):
        if not table.shape[0]:
            continue
        t = table[:, RANGE.time if len(cols) == 1 else TDOA.time]
        keep = (t >= t0) & (t < t1)
        if len(cols) == 1:
            keep &= table[:, value] > 0.0  # a failed exchange's 0 (the replay drops those)
        W = np.zeros((int(np.count_nonzero(keep)), B))
        for sign, c in zip((1.0, -1.0), cols, strict=False):
            W[np.arange(W.shape[0]), log.beacon_index(table[keep, c])] += sign
        given = np.asarray(std, dtype=float)[keep] if len(std) else np.full(W.shape[0], np.nan)
        stated = stated and bool(np.all(np.isfinite(given)))
        rows.append(W)
        parts.append(
            np.column_stack(
                [t[keep], table[keep, value], np.where(np.isfinite(given), given, fallback)]
            )
        )
    W = np.vstack(rows) if rows else np.zeros((0, B))
    part = np.vstack(parts) if parts else np.zeros((0, 3))
    return part[:, 0], W, part[:, 1], part[:, 2], stated


def _fix(anchors, t, W, y, std, v, t_m, p):
    """The position at ``t_m`` from the window's measurements, each moved by ``v (t - t_m)``
    (Gauss-Newton from ``p``; the anchors' own intercepts are not used), and its covariance,
    the inverse normal matrix times ``max(1, chi^2 / dof)`` (``dof = N - dim > 0``, else 1);
    None where the normal matrix is singular or the steps do not settle."""
    moved = (t - t_m)[:, None] * v
    w = 1.0 / std
    for _ in range(FIX_STEPS):
        r = p + moved[:, None, :] - anchors[None, :, :]  # (N, B, dim)
        rho = np.linalg.norm(r, axis=2)
        if np.any(rho == 0.0):
            return None
        J = np.einsum("nb,nbd->nd", W, r / rho[:, :, None])
        e = y - np.einsum("nb,nb->n", W, rho)
        step, _, rank, _ = np.linalg.lstsq(J * w[:, None], e * w, rcond=None)
        if rank < p.size:
            return None
        p = p + step
        if not np.all(np.isfinite(p)):
            return None
        if np.linalg.norm(step) < 1e-9:
            break
    else:
        return None  # no convergence in FIX_STEPS steps
    N = (J * (w * w)[:, None]).T @ J
    dof = y.size - p.size
    chi2 = float(np.sum((e * w) ** 2))
    return p, np.linalg.inv(N) * (max(1.0, chi2 / dof) if dof > 0 else 1.0)


def _lines(anchors, t, W, y, std, p, t_m):
    """The lines' velocity and its covariance (intercepts per anchor, module docstring),
    scaled by ``max(1, chi^2 / dof)``, and ``(N^-1 block, chi^2, dof)`` unscaled (the F test
    of :meth:`RangeVelocity.motion`); None where ``v`` is not identified."""
    r = p - anchors
    U = r / np.linalg.norm(r, axis=1)[:, None]
    A = np.column_stack([W, (t - t_m)[:, None] * (W @ U)])
    w = 1.0 / std
    theta, _, rank, _ = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)
    dof = A.shape[0] - rank
    dim = anchors.shape[1]
    if dof < 1 or rank - np.linalg.matrix_rank(W * w[:, None]) < dim:
        return None  # v is not identified where the intercepts alone reach the rank
    N_inv = np.linalg.pinv((A * (w * w)[:, None]).T @ A)
    chi2 = float(np.sum(((y - A @ theta) * w) ** 2))
    block = N_inv[-dim:, -dim:]
    return theta[-dim:], block * max(1.0, chi2 / dof), (block, chi2, int(dof))


def _plane(anchors: np.ndarray, sigma: float) -> np.ndarray | None:
    """The unit normal of the plane that the anchors stand in (in 3-D), or None: the largest
    distance of an anchor from their best-fitting plane (the smallest singular direction of
    the anchors about their centroid) is at least ``sigma``, which a range then tells apart."""
    if anchors.shape[1] != 3 or anchors.shape[0] < 3:
        return None
    centred = anchors - anchors.mean(axis=0)
    n = np.linalg.svd(centred)[2][-1]
    return n if float(np.max(np.abs(centred @ n))) < sigma else None


def start_point(
    anchors: np.ndarray, W: np.ndarray, y: np.ndarray, sigma: float, frame: str = "enu"
) -> np.ndarray | str:
    """Where the fix's Gauss-Newton steps start (module docstring, "Anchors in one plane"), or
    why no fix can be made: the measured anchors' centroid, unless they stand in one plane
    (:func:`_plane`), where the Jacobian's column across the plane vanishes on it.

    Then the position in the plane is the linear multilateration of each anchor's mean range
    ``rbar_h``, ``(a_h - abar)^T p = ((|a_h|^2 - mean |a|^2) - (rbar_h^2 - mean rbar^2)) / 2``
    (least squares of least norm: ``p_s``, moved into the plane, ``p_o = p_s + (abar . n) n``),
    and its distance from the plane the ranges' own nonlinear solution,
    ``h^2 = mean_h (rbar_h^2 - |p_o - a_h|^2)``; the point is ``p_o + s h n`` with the side
    ``s`` of :data:`COPLANAR_SIDE` (below the anchors, ``up`` the frame's: ``+z`` in ``enu``,
    ``-z`` in ``ned``). A window of TDOA alone starts at ``abar`` moved to that side by the
    anchors' extent."""
    used = np.any(W != 0.0, axis=0)
    a = anchors[used]
    centre = a.mean(axis=0)
    n = _plane(a, sigma)
    if n is None:
        return centre
    up = np.array([0.0, 0.0, -1.0 if frame == "ned" else 1.0])
    if abs(float(n @ up)) < 1e-6:
        return "the anchors stand in one vertical plane: the vehicle's side of it is not stated"
    side = -COPLANAR_SIDE * math.copysign(1.0, float(n @ up))  # +1 below: against up
    ranges = (np.count_nonzero(W, axis=1) == 1)[:, None] & (W[:, used] == 1.0)  # (N, anchors)
    count = np.count_nonzero(ranges, axis=0)
    if np.any(count == 0):  # not every anchor ranged (TDOA): off the plane by their extent
        extent = float(np.max(np.linalg.norm(a - centre, axis=1)))
        return centre + side * extent * n
    r = (ranges * y[:, None]).sum(axis=0) / count
    sq = np.sum(a * a, axis=1)
    rhs = 0.5 * ((sq - sq.mean()) - (r * r - np.mean(r * r)))
    p = np.linalg.lstsq(a - centre, rhs, rcond=None)[0]
    p = p + (float(centre @ n) - float(p @ n)) * n
    h2 = float(np.mean(r * r - np.sum((p - a) ** 2, axis=1)))
    if not h2 > 0.0:
        return "the anchors stand in one plane and the ranges put the vehicle in it"
    return p + side * math.sqrt(h2) * n


def range_velocity(log, t0: float, t1: float, sigma: float = 1.0) -> RangeVelocity | str:
    """The velocity that the ranges (or TDOA) of ``[t0, t1)`` tell, taken constant over it
    (module docstring), or why they tell none; ``sigma`` the standard deviation of a range
    that states none."""
    anchors = np.asarray(log.beacons, dtype=float)
    dim = anchors.shape[1]
    t, W, y, std, stated = _window(log, t0, t1, sigma)
    used = int(np.count_nonzero(np.any(W != 0.0, axis=0)))
    if used < dim + 1:
        return f"{used} anchors measured in {t1 - t0:.2g} s, fewer than {dim + 1}"
    t_m = float(np.mean(t))
    p = start_point(anchors, W, y, float(np.median(std)), getattr(log, "frame", "enu"))
    if isinstance(p, str):
        return p
    v = np.zeros(dim)
    for _ in range(FIX_ROUNDS):
        fixed = _fix(anchors, t, W, y, std, v, t_m, p)
        if fixed is None:
            return "the window's measurements fix no position"
        p, C_p = fixed
        lines = _lines(anchors, t, W, y, std, p, t_m)
        if lines is None:
            return f"{t.size} measurements of {used} anchors do not fix a velocity"
        v, C_v, unscaled = lines
    r_min = float(np.min(np.linalg.norm(p - anchors, axis=1)))
    sigma_p = math.sqrt(float(np.max(np.linalg.eigvalsh(C_p))))
    cov = C_v + (float(np.linalg.norm(v)) * sigma_p / r_min) ** 2 * np.eye(dim)
    block, chi2, dof = unscaled
    cov = 0.5 * (cov + cov.T)
    floor = 1.0 if stated else (RANGE_RESOLUTION / sigma) ** 2
    return RangeVelocity(v, cov, t_m, used, int(t.size), p, C_p, block, chi2, dof, floor)


def velocity_prior(setup) -> tuple[np.ndarray | None, np.ndarray]:
    """The velocity's prior ``(mean, covariance)`` of a replay's filter built on ``setup``
    (:class:`~quadobs.testbed.logs.estimators.ReplaySetup`); ``mean`` None: the initial guess's.

    ``--tune velocity_std=...`` (``setup.velocity_std``) stands over the log: ``std^2 I``
    about the guess's velocity. Else the start's prior where it is applied (``setup.start``,
    module docstring), else ``UNKNOWN_VELOCITY_STD^2 I``."""
    dim = int(setup.beacons.shape[1])
    std = getattr(setup, "velocity_std", None)
    start = getattr(setup, "start", None)
    if std is None and start is not None and start.applied:
        return np.array(start.velocity, dtype=float), np.array(start.covariance, dtype=float)
    std = UNKNOWN_VELOCITY_STD if std is None else float(std)
    return None, std * std * np.eye(dim)


def set_velocity_prior(setup, x: np.ndarray, P: np.ndarray, first: int) -> None:
    """Put :func:`velocity_prior` into a filter's initial state ``x`` and covariance ``P`` (in
    place), the velocity at ``x[first : first + dim]``, uncorrelated with the other states."""
    mean, cov = velocity_prior(setup)
    block = slice(first, first + cov.shape[0])
    if mean is not None:
        x[block] = mean
    P[block, :] = 0.0
    P[:, block] = 0.0
    P[block, block] = cov
