"""The replay's defaults derived from the log: the initial variance from the guess's uncertainty,
the gyroscope's noise from the log's stated density (else the documented fallback)."""

import math
import tempfile

import numpy as np
import pytest

from quadobs.testbed.logs import RangeLog, read_log, write_log
from quadobs.testbed.logs.estimators import (
    GYRO_NOISE,
    build_onboard_ekf,
    initial_variance,
    log_frame,
)
from quadobs.testbed.logs.replay import run_replay

ANCHORS = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 3.0], [6.0, 6.0, 0.0], [0.0, 6.0, 3.0]])


def _log(**extra) -> RangeLog:
    t = np.arange(0.0, 4.0, 0.01)
    f = np.tile([0.0, 0.0, 9.80665], (t.size, 1))
    p = np.tile([3.0, 3.0, 1.5], (t.size, 1))
    h = np.arange(t.size) % 4
    ranges = np.column_stack([t, h, np.linalg.norm(p - ANCHORS[h], axis=1)])
    return RangeLog(
        "hover", np.arange(4), ANCHORS, ranges, np.column_stack([t, f, 0 * f]), float("nan"),
        np.column_stack([t, p, 0 * p]), input_kind="imu_body",
        truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"), **extra,
    )  # fmt: skip


def test_the_initial_variance_is_the_guess_s_uncertainty():
    log = _log()
    c = ANCHORS.mean(axis=0)
    extent = np.max(np.linalg.norm(ANCHORS - c, axis=1))  # sqrt(3^2 + 3^2 + 1.5^2) = 4.5
    assert extent == pytest.approx(4.5)
    assert initial_variance(log, 50.0) == 2500.0
    assert initial_variance(log, 0.0, range_sigma=0.1) == pytest.approx(0.01)
    assert initial_variance(log) == pytest.approx(4.5**2)
    far = c + np.array([12.0, 16.0, 0.0])  # 20 m from the centroid
    assert initial_variance(log, x0=far) == pytest.approx(24.5**2)


def test_a_replay_reports_the_derived_initial_variance():
    log = _log()
    drawn = run_replay(log, estimators=["ekf"], initial_offset=3.0, batch=False)
    assert drawn["noise"]["P0"] == 9.0
    given = run_replay(
        log, estimators=["ekf"], x0=np.r_[ANCHORS.mean(axis=0), 0, 0, 0], batch=False
    )
    assert given["noise"]["P0"] == pytest.approx(4.5**2)
    tuned = run_replay(log, estimators=["ekf"], batch=False, setup_options={"P0": 7.0})
    assert tuned["noise"]["P0"] == 7.0


def test_the_gyro_noise_is_the_log_s_stated_density_above_the_floor(tmp_path):
    from quadobs.testbed.logs.estimators import ReplaySetup

    stated = read_log(write_log(_log(gyro_noise=0.02, accel_noise=1e-3), tmp_path / "s"))
    assert stated.gyro_noise == 0.02 and stated.accel_noise == 1e-3
    assert "gyro_noise,0.02" in (tmp_path / "s" / "meta.csv").read_text()
    quiet = read_log(
        write_log(_log(gyro_noise=2e-3), tmp_path / "q")
    )  # 4e-6 rad^2/s: below the floor
    plain = read_log(write_log(_log(), tempfile.mkdtemp()))
    assert math.isnan(plain.gyro_noise)
    # a stated bias: the live filter's rule N^2 + b^2 (1 s), below the floor too
    biased = read_log(write_log(_log(gyro_noise=2e-3, gyro_bias=2e-3), tmp_path / "b"))
    h = 0.01
    cases = ((stated, 4e-4), (quiet, GYRO_NOISE), (plain, GYRO_NOISE), (biased, 8e-6))
    for log, intensity in cases:
        s = ReplaySetup(ANCHORS, 0.1, "imu", 0.0, 4.0, input_kind="imu_body", **log_frame(log))
        est = build_onboard_ekf(s, np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0])
        assert est.q_a == pytest.approx(intensity / h)  # the per-sample variance at the IMU's rate
