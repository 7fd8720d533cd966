"""The GTSAM peer in the replay in time: ranges alone, TDOA and body-IMU logs, every measurement
at its own time (on its keyframe's position and velocity), online and batch figures beside the
filters'."""

import numpy as np
import pytest

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.replay import run_replay

pytest.importorskip("gtsam", reason="gtsam is not installed (the data extra)")

from test_replay_in_time import (  # the logs of the replay in time's tests
    ANCHORS_3D,
    _imu_body_log,
    _ranges,
    _straight,
    _tdoa_log,
    _truth,
)


def _figures(s, name="isam2"):
    e = s["estimators"][name]
    assert e["diverged"] is None and e["smoothed_rmse"] is not None
    return e


def test_the_peer_replays_ranges_alone_in_3d_on_keyframes():
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 8.0, 0.04)
    p, v = _straight(t, 3)
    truth, cols = _truth(t, p, v, 3)
    log = RangeLog(
        "cv3", np.arange(5), ANCHORS_3D, _ranges(t, ANCHORS_3D, p, rng, 0.05), np.empty((0, 1)),
        float("nan"), truth, input_kind="none", truth_columns=cols,
    )  # fmt: skip
    s = run_replay(
        log, estimators=["ekf", "isam2"], initial_offset=5.0,
        setup_options={"range_sigma": 0.05, "q_acc": 1e-3, "P0": 25.0}, burn_in=4.0,
    )  # fmt: skip
    e = _figures(s)
    assert e["corrections"] == s["ranges"]["measurements_in_time"]  # all before the grid's end
    assert e["rmse"] < 0.1 and e["batch_rmse"] < 0.1, e


def test_the_peer_replays_a_tdoa_log():
    log = _tdoa_log().excerpt(0.0, 12.0)
    s = run_replay(
        log, estimators=["ekf", "isam2"], initial_offset=2.0,
        setup_options={"range_sigma": 0.03, "q_acc": 1e-3}, burn_in=5.0,
    )  # fmt: skip
    e = _figures(s)
    assert e["rmse"] < 0.2 and e["batch_rmse"] < e["rmse"], e


def test_the_peer_preintegrates_a_body_imu_log():
    log = _imu_body_log(True, yaw_rate=0.2).excerpt(0.0, 4.0)
    s = run_replay(
        log, estimators=["ekf", "isam2"], initial_offset=3.0,
        setup_options={"range_sigma": 0.05}, burn_in=2.0,
    )  # fmt: skip
    e = _figures(s)
    assert e["rmse"] < 0.1 and e["batch_rmse"] < 0.1, e
