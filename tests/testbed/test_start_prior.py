"""The replay's velocity prior from the log's start (:mod:`quadobs.testbed.logs.start_prior`):
an IMU at rest gives the bound its window cannot exclude, one in motion or a log without an
IMU the unknown start's 2 m/s; over a rest, the ranges' lines give the velocity, applied
where they identify it; the summary reports it, a given velocity_std stands over it."""

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.estimators import ReplaySetup, build_ekf, log_frame
from quadobs.testbed.logs.start_prior import (
    REST_K,
    SLICE,
    START_WINDOW,
    UNKNOWN_VELOCITY_STD,
    range_velocity,
    start_prior,
)

ANCHORS = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 3.0], [6.0, 6.0, 0.0], [0.0, 6.0, 3.0]])
G = 9.80665
H = 0.01  # the IMU's interval (s)
ACCEL_NOISE, GYRO_NOISE = 0.02, 0.005  # stated densities (per sqrt(Hz))


def _imu_log(
    accel: np.ndarray | None = None,
    rate: float = 0.0,
    seed: int = 0,
    velocity=(0.0, 0.0, 0.0),
    range_std: float | None = None,
    anchors: int = 4,
    beacons: np.ndarray = ANCHORS,
    start=(3.0, 3.0, 1.5),
    **extra,
):
    """A 2 s body-IMU log, level, its specific force ``g e_z + accel`` with white noise of the
    stated densities, its angular rate ``rate`` about z; ranges to ``anchors`` of the anchors in
    turn at 100 Hz from a vehicle moving at ``velocity`` from (3, 3, 1.5), exact where
    ``range_std`` is None, else with that noise, stated."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 2.0, H)
    f = np.tile([0.0, 0.0, G], (t.size, 1)) + (0.0 if accel is None else accel)
    f = f + rng.normal(0.0, ACCEL_NOISE / math.sqrt(H), f.shape)
    w = rng.normal(0.0, GYRO_NOISE / math.sqrt(H), f.shape) + [0.0, 0.0, rate]
    p = np.asarray(start) + t[:, None] * np.asarray(velocity)
    k = np.arange(t.size) % anchors
    r = np.linalg.norm(p - beacons[k], axis=1)
    if range_std is not None:
        r = r + rng.normal(0.0, range_std, t.size)
        extra["range_std"] = np.full(t.size, range_std)
    return RangeLog(
        "start", np.arange(4), beacons, np.column_stack([t, k, r]), np.column_stack([t, f, w]),
        float("nan"), input_kind="imu_body", **extra,
    )  # fmt: skip


def test_an_imu_at_rest_gives_the_bound_its_window_cannot_exclude():
    prior = start_prior(_imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE))
    assert prior.at_rest and prior.reason == "no motion in the first 0.5 s"
    n = round(SLICE / H)  # the samples of a slice
    delta = REST_K * math.sqrt(math.pi / 2) * ACCEL_NOISE / math.sqrt(H * n)  # k sigma_median
    expected = math.sqrt((G + delta) ** 2 - G**2) * START_WINDOW
    assert prior.velocity_std == pytest.approx(expected, rel=0.1)
    assert 0.05 < prior.velocity_std < 2.0 == UNKNOWN_VELOCITY_STD


def test_the_window_s_own_spread_stands_for_unstated_noise():
    prior = start_prior(_imu_log())
    assert prior.at_rest and prior.velocity_std < 2.0


def test_a_corrupt_first_sample_does_not_decide():
    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    log.inputs[0, 1:4] = 0.0  # a first sample before the IMU's filter settled
    assert start_prior(log).at_rest


@pytest.mark.parametrize(
    ("accel", "rate", "why"),
    [
        (np.array([0.0, 0.0, 1.0]), 0.0, "norm"),  # climbing at 1 m/s^2
        (None, 0.3, "gyroscope"),  # turning at 0.3 rad/s
    ],
)
def test_an_imu_in_motion_keeps_the_unknown_start(accel, rate, why):
    prior = start_prior(_imu_log(accel, rate, accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE))
    assert not prior.at_rest and why in prior.reason
    assert prior.velocity_std == UNKNOWN_VELOCITY_STD


def test_a_take_off_ends_the_rest():
    t = np.arange(0.0, 2.0, H)
    climb = np.zeros((t.size, 3))
    climb[t >= 0.2, 2] = 3.0  # on the ground for 0.2 s, then a take-off at 3 m/s^2
    still = start_prior(_imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE))
    prior = start_prior(_imu_log(climb, accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE))
    assert prior.at_rest and prior.reason == "no motion in the first 0.2 s"
    assert prior.velocity_std < still.velocity_std  # a shorter rest, a smaller bound


def test_a_log_without_an_imu_keeps_the_unknown_start():
    t = np.arange(0.0, 2.0, 0.1)
    log = RangeLog(
        "plain", np.arange(4), ANCHORS, np.column_stack([t, t * 0, t * 0 + 4.0]), np.empty((0, 1)),
        float("nan"), input_kind="none",
    )  # fmt: skip
    prior = start_prior(log)
    assert not prior.at_rest and prior.velocity_std == UNKNOWN_VELOCITY_STD


def test_the_builders_report_the_start_and_take_a_given_velocity_std():
    """Ranges too noisy to tell the velocity better than 2 m/s: the rest test's bound is
    reported, not applied (an IMU cannot tell rest from a constant velocity); the filters keep
    2 m/s unless ``velocity_std`` is given."""
    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    frame = log_frame(log)
    s = ReplaySetup(ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", **frame)
    ekf = build_ekf(s, np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0])
    assert np.diag(ekf._P)[3:] == pytest.approx([4.0] * 3)
    std = frame["start"].velocity_std
    given = ReplaySetup(
        ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", velocity_std=std, **frame
    )
    assert np.diag(build_ekf(given, np.zeros(6))._P)[3:] == pytest.approx([std**2] * 3)
    summary = frame["start"].summary()
    assert {k: summary[k] for k in ("at_rest", "velocity_std", "reason", "applied")} == {
        "at_rest": True, "velocity_std": std, "reason": "no motion in the first 0.5 s",
        "applied": False,
    }  # fmt: skip
    # exact ranges that state no noise: the setup's 1 m leaves the velocity unidentified
    assert "no better than 2 m/s" in summary["why"] and max(summary["velocity_prior_std"]) > 1.0
    with pytest.raises(QuadobsError, match="velocity_std"):
        ReplaySetup(ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", velocity_std=-1.0)


def test_the_replay_s_summary_reports_the_start():
    from quadobs.testbed.logs.replay import run_replay

    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    summary = run_replay(log, estimators=["ekf"], batch=False, initial_offset=1.0)
    assert summary["start"] == start_prior(log).summary()
    assert summary["start"]["at_rest"]


RANGE_STD = 0.05  # stated range noise (m)


def _applied(velocity=(0.0, 0.0, 0.0), **kw):
    log = _imu_log(
        velocity=velocity, range_std=RANGE_STD, accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE, **kw
    )
    return log, start_prior(log, apply=True)


def test_the_identified_prior_is_reported_not_applied_unless_asked_for():
    """By default the filters keep the unknown start (the prior brought the replayed bias
    filters nearer the live ones but further from the truth); ``--tune velocity_std=log``
    applies it."""
    from quadobs.testbed.logs.estimators import parse_tuning, tuning_fields, velocity_from_log

    log, _ = _applied((0.6, 0.75, 0.15))
    prior = start_prior(log)
    assert prior.moving and not prior.applied and "not applied" in prior.why
    s = ReplaySetup(ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", **log_frame(log))
    ekf = build_ekf(s, np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0])
    assert np.diag(ekf._P)[3:] == pytest.approx([UNKNOWN_VELOCITY_STD**2] * 3)
    options = parse_tuning(["velocity_std=log", "q_acc=2"])
    assert velocity_from_log(options) and tuning_fields(options) == {"q_acc": 2.0}
    assert not velocity_from_log(parse_tuning(["velocity_std=0.5"]))


@pytest.mark.parametrize("velocity", [(0.0, 0.0, 0.0), (0.6, 0.75, 0.15)])
def test_the_ranges_of_the_rest_tell_the_velocity(velocity):
    """At rest, and gliding at about 1 m/s with no acceleration (the IMU shows rest in both; the
    ranges tell the glide from the rest): the ranges' lines identify the velocity within three
    of the prior's standard deviations, and it is applied."""
    log, prior = _applied(velocity)
    gliding = bool(np.any(velocity))
    assert prior.applied and prior.at_rest != gliding and prior.moving == gliding, prior.why
    error = prior.velocity - np.asarray(velocity)
    z = error @ np.linalg.solve(prior.covariance, error)  # chi^2 with 3 degrees of freedom
    assert z < 14.2  # its 0.997 quantile (three standard deviations)
    lines = range_velocity(log, 0.0, START_WINDOW)  # the ranges' own part: C_v and the fix's
    assert error @ np.linalg.solve(lines.covariance, error) < 14.2
    assert np.all(np.sqrt(np.diag(lines.covariance)) < 0.2)  # 51 ranges of 0.05 m in 0.5 s
    # the fix's term, the drift a_max (t_m - t_0) and C_v: all below the unknown start's
    assert np.max(np.linalg.eigvalsh(prior.covariance)) < UNKNOWN_VELOCITY_STD**2
    bound = _applied()[1].velocity_std  # the same IMU's rest bound
    assert np.min(np.linalg.eigvalsh(prior.covariance)) > (bound / 2) ** 2 * 0.9


def test_the_filters_take_the_applied_prior_and_a_given_std_stands_over_it():
    log, prior = _applied((0.6, 0.75, 0.15))
    frame = log_frame(log, None, apply_start=True)
    s = ReplaySetup(ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", **frame)
    ekf = build_ekf(s, np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(ekf.x_hat[3:], prior.velocity)
    np.testing.assert_allclose(ekf._P[3:, 3:], prior.covariance)
    assert np.all(ekf._P[:3, 3:] == 0.0)
    given = ReplaySetup(
        ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", velocity_std=0.5, **frame
    )
    ekf = build_ekf(given, np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0])
    assert np.all(ekf.x_hat[3:] == 0.0)
    np.testing.assert_allclose(ekf._P[3:, 3:], 0.25 * np.eye(3))


def test_three_anchors_in_space_do_not_tell_the_velocity():
    _, prior = _applied(anchors=3)
    assert prior.at_rest and not prior.applied
    assert prior.why == "the ranges: 3 anchors measured in 0.5 s, fewer than 4"
    assert prior.summary()["velocity"] is None


def test_a_constant_bias_of_one_anchor_keeps_the_prior_true():
    """Each anchor's line has its own intercept, which takes in a constant bias of that anchor;
    the bias moves the velocity through the fix's unit vectors alone, within the prior."""
    import dataclasses

    log, _ = _applied()
    biased = log.ranges.copy()
    biased[biased[:, 1] == 2, 2] += 0.4
    prior = start_prior(dataclasses.replace(log, ranges=biased), apply=True)
    assert prior.applied
    assert prior.velocity @ np.linalg.solve(prior.covariance, prior.velocity) < 14.2


def test_the_tdoa_of_the_rest_tell_a_gliding_velocity():
    """TDOA: each difference is that of two anchors' lines (the intercepts' common shift left
    free); gliding at about 1 m/s, the velocity is found within its prior and applied."""
    import dataclasses

    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    t = log.inputs[:, 0]
    velocity = np.array([0.6, 0.75, 0.15])
    p = np.array([3.0, 3.0, 1.5]) + t[:, None] * velocity
    i = np.arange(t.size) % 4
    j = (i + 1 + np.arange(t.size) // 4 % 3) % 4  # every pair in turn
    rng = np.random.default_rng(1)
    d = np.linalg.norm(p - ANCHORS[i], axis=1) - np.linalg.norm(p - ANCHORS[j], axis=1)
    d = d + rng.normal(0.0, RANGE_STD, t.size)
    tdoa = dataclasses.replace(
        log,
        ranges=np.empty((0, 3)),
        range_std=np.empty(0),
        tdoa=np.column_stack([t, i, j, d]),
        tdoa_std=np.full(t.size, RANGE_STD),
    )
    prior = start_prior(tdoa, apply=True)
    assert prior.applied, prior.why
    error = prior.velocity - velocity
    assert error @ np.linalg.solve(prior.covariance, error) < 14.2


@pytest.mark.parametrize("frame", ["enu", "ned"])
def test_anchors_at_one_height_fix_the_vehicle_below_them(frame):
    """Anchors at one height fix no height linearly, and on their plane the fix's steps have no
    gradient across it: the fix starts from the plane's multilateration, below the anchors by
    the ranges' own distance from it (the stated side), and the velocity is identified."""
    up = -1.0 if frame == "ned" else 1.0
    plane = np.array([[0.0, 0.0, 2.5], [6.0, 0.0, 2.5], [6.0, 6.0, 2.5], [0.0, 6.0, 2.5]])
    plane[:, 2] *= up
    truth = np.array([2.0, 3.5, 1.0 * up])
    log, prior = _applied(beacons=plane, start=truth, frame=frame)
    assert prior.applied, prior.why
    assert prior.velocity @ np.linalg.solve(prior.covariance, prior.velocity) < 14.2
    fix = range_velocity(log, 0.0, START_WINDOW, RANGE_STD)
    error = fix.position - truth
    assert error @ np.linalg.solve(fix.position_covariance, error) < 14.2
    assert abs(error[2]) < 0.1  # not the mirror image, 3 m away across the anchors


def test_anchors_in_one_vertical_plane_state_no_side():
    wall = np.array([[0.0, 0.0, 0.5], [6.0, 0.0, 0.5], [6.0, 0.0, 2.5], [0.0, 0.0, 2.5]])
    _, prior = _applied(beacons=wall, start=(3.0, 2.0, 1.5))
    assert not prior.applied
    assert prior.why == (
        "the ranges: the anchors stand in one vertical plane: the vehicle's side of it is not stated"
    )


@pytest.mark.parametrize("offset", [0.0, 0.2])
def test_the_fix_s_covariance_is_scaled_by_its_residuals(offset):
    """At the centre of the anchors (every one 4.5 m away, the unit vectors summing to zero),
    exact ranges and the same ranges all ``offset`` longer fix the same point; the fix's
    covariance is the inverse normal matrix ``(sum_a n_a u_a u_a^T / sigma^2)^-1`` times
    ``max(1, chi^2 / dof)``, ``chi^2 = N offset^2 / sigma^2`` and ``dof = N - 3``."""
    import dataclasses

    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    ranges = log.ranges.copy()
    ranges[:, 2] += offset
    fix = range_velocity(dataclasses.replace(log, ranges=ranges), 0.0, 0.475, RANGE_STD)
    centre = np.array([3.0, 3.0, 1.5])
    np.testing.assert_allclose(fix.position, centre, atol=1e-9)
    u = (centre - ANCHORS) / 4.5
    N = 48  # 12 ranges of each anchor in [0, 0.475)
    normal = 12 * u.T @ u / RANGE_STD**2
    scale = max(1.0, N * offset**2 / RANGE_STD**2 / (N - 3))
    expected = np.linalg.inv(normal) * scale
    np.testing.assert_allclose(fix.position_covariance, expected, rtol=1e-6, atol=1e-12 * scale)
    assert (scale > 1.0) == (offset > 0.0)


@pytest.mark.parametrize("velocity", [(0.0, 0.0, 0.0), (0.6, -0.3, 0.0)])
def test_a_log_begun_at_a_steady_velocity_is_not_reported_at_rest(velocity):
    """An IMU cannot tell rest from a steady velocity; the ranges can. Ranges of 0.1 m that
    state no noise (weighed by the setup's 1 m, which would hide any velocity): the F test on
    their own residuals tells 0.67 m/s from rest, and a standing vehicle stays at rest."""
    import dataclasses

    log = _imu_log(
        velocity=velocity, range_std=0.1, seed=2, accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE
    )
    log = dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], np.nan))
    prior = start_prior(log)
    moving = bool(np.any(velocity))
    assert prior.moving == moving and prior.at_rest != moving, prior.reason
    assert prior.summary()["moving"] == moving
    if moving:
        assert "the ranges of the first 0.5 s show" in prior.reason
        assert prior.velocity_std == UNKNOWN_VELOCITY_STD
    else:
        assert prior.reason == "no motion in the first 0.5 s"
        assert prior.velocity_std < UNKNOWN_VELOCITY_STD


def test_an_imu_in_motion_still_reports_what_the_ranges_show():
    """The IMU shows motion (turning at 0.3 rad/s): no rest either way, and ``moving`` says
    whether the ranges of the first 0.5 s show a velocity."""
    turning = {"rate": 0.3, "range_std": RANGE_STD, "accel_noise": ACCEL_NOISE}
    still = start_prior(_imu_log(gyro_noise=GYRO_NOISE, **turning))
    gliding = start_prior(_imu_log(velocity=(0.6, -0.3, 0.0), gyro_noise=GYRO_NOISE, **turning))
    assert not still.at_rest and not still.moving
    assert not gliding.at_rest and gliding.moving and "the ranges of the first" in gliding.reason
    assert gliding.velocity_std == UNKNOWN_VELOCITY_STD


def test_an_imu_whose_stamps_repeat_is_read_by_its_positive_intervals():
    """Each IMU row written twice (stamps coarser than the sampling, or a copy): the sampling
    period is the median positive interval, and the rest is found as with each row once."""
    import dataclasses

    from quadobs.testbed.logs.schema import sampling_period

    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    doubled = dataclasses.replace(log, inputs=np.repeat(log.inputs, 2, axis=0))
    assert sampling_period(doubled.inputs[:, 0]) == pytest.approx(H)
    assert math.isnan(sampling_period([1.0, 1.0, 1.0]))
    assert start_prior(doubled).at_rest == start_prior(log).at_rest
