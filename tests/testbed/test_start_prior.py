"""The replay's velocity prior from the log's start (:mod:`quadobs.testbed.logs.start_prior`):
an IMU at rest gives the bound its window cannot exclude, one in motion or a log without an
IMU the unknown start's 2 m/s; the summary reports it, the builders take 2 m/s unless a
velocity_std is given."""

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
    start_prior,
)

ANCHORS = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 3.0], [6.0, 6.0, 0.0], [0.0, 6.0, 3.0]])
G = 9.80665
H = 0.01  # the IMU's interval (s)
ACCEL_NOISE, GYRO_NOISE = 0.02, 0.005  # stated densities (per sqrt(Hz))


def _imu_log(accel: np.ndarray | None = None, rate: float = 0.0, seed: int = 0, **extra):
    """A 2 s body-IMU log, level, its specific force ``g e_z + accel`` with white noise of the
    stated densities, its angular rate ``rate`` about z."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 2.0, H)
    f = np.tile([0.0, 0.0, G], (t.size, 1)) + (0.0 if accel is None else accel)
    f = f + rng.normal(0.0, ACCEL_NOISE / math.sqrt(H), f.shape)
    w = rng.normal(0.0, GYRO_NOISE / math.sqrt(H), f.shape) + [0.0, 0.0, rate]
    p = np.tile([3.0, 3.0, 1.5], (t.size, 1))
    k = np.arange(t.size) % 4
    ranges = np.column_stack([t, k, np.linalg.norm(p - ANCHORS[k], axis=1)])
    return RangeLog(
        "start", np.arange(4), ANCHORS, ranges, np.column_stack([t, f, w]), float("nan"),
        input_kind="imu_body", **extra,
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
    """The rest test's bound is reported, not applied (an IMU cannot tell rest from a constant
    velocity): the filters keep 2 m/s unless ``velocity_std`` is given."""
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
    assert frame["start"].summary() == {
        "at_rest": True, "velocity_std": std, "reason": "no motion in the first 0.5 s",
        "applied": False,
    }  # fmt: skip
    with pytest.raises(QuadobsError, match="velocity_std"):
        ReplaySetup(ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", velocity_std=-1.0)


def test_the_replay_s_summary_reports_the_start():
    from quadobs.testbed.logs.replay import run_replay

    log = _imu_log(accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE)
    summary = run_replay(log, estimators=["ekf"], batch=False, initial_offset=1.0)
    assert summary["start"] == start_prior(log).summary()
    assert summary["start"]["at_rest"]
