"""The calibration of an odometry log: the model's ``q_xy`` scored by the EKF that takes the
dead-reckoned heading as known, the heading filters' ``q_xy_heading`` and ``q_theta`` scored by
the EKF that estimates the heading and the yaw rate's bias."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.testbed.logs import RangeLog, write_log
from quadobs.testbed.logs.calibration import (
    HEADING_KEYS,
    HEADING_SCORER,
    calibrate_noise,
    heading_noise,
    noise_keys,
)
from quadobs.testbed.logs.estimators import ReplaySetup, build_ekf_heading
from quadobs.testbed.logs.replay import run_replay

BEACONS = np.array([[-30.0, -20.0], [40.0, -25.0], [35.0, 30.0], [-25.0, 35.0]])


def circle_log(duration: float, yaw_bias: float, sigma: float = 0.3, seed: int = 2) -> RangeLog:
    """A vehicle on a circle of radius 15 m at 1.5 m/s: odometry at 10 Hz whose yaw rate reads
    ``yaw_bias`` (rad/s) too high (its dead-reckoned heading drifts at that rate), ranges
    round-robin at 4 Hz with ``sigma`` (m) of noise."""
    R, v = 15.0, 1.5
    w = v / R
    t_in = np.arange(0.0, duration, 0.1)
    inputs = np.column_stack([t_in, np.full_like(t_in, v), np.full_like(t_in, w + yaw_bias)])
    heading0 = math.pi / 2

    def pos(t):
        return np.column_stack([R * np.cos(w * t), R * np.sin(w * t)])

    t_r = np.arange(0.05, duration - 0.1, 0.25)
    h = np.arange(t_r.size) % 4
    rng = np.random.default_rng(seed)
    rho = np.linalg.norm(pos(t_r) - BEACONS[h], axis=1) + sigma * rng.standard_normal(t_r.size)
    t_gt = np.arange(0.0, duration, 0.05)
    truth = np.column_stack([t_gt, pos(t_gt), heading0 + w * t_gt])
    ranges = np.column_stack([t_r, h, rho])
    return RangeLog("circle", np.arange(4), BEACONS, ranges, inputs, heading0, truth)


def test_the_noise_keys_of_a_log():
    log = circle_log(10.0, 0.0)
    assert noise_keys(log) == ("q_xy", *HEADING_KEYS) == ("q_xy", "q_xy_heading", "q_theta")
    assert noise_keys(log, "cv") == ("q_acc",)  # the heading filters need the model odometry
    assert HEADING_SCORER == "ekf-heading"


def test_the_heading_filters_take_their_own_position_noise():
    log = circle_log(10.0, 0.0)
    s = ReplaySetup(log.beacons, 0.1, "odometry", 0.0, 30.0, q_xy=16.0, q_xy_heading=0.25)
    est = build_ekf_heading(s, np.zeros(2))
    np.testing.assert_array_equal(np.diag(est.Qc)[:3], [0.25, 0.25, s.q_theta])


def test_a_drifting_heading_is_left_to_the_heading_filter_not_to_its_position_noise():
    """A yaw rate read 0.01 rad/s too high (the dead-reckoned heading 1.2 rad off after 120 s):
    the EKF that takes that heading as known needs a large ``q_xy``; the heading filter, which
    estimates the bias, is scored best with a smaller one, no worse on held-out ranges than its
    prior, and the truth (never read by the calibration) agrees."""
    log = circle_log(120.0, 0.01)
    prior = {"range_sigma": 1.0}  # the replay's prior (this log's own noise, 0.3 m, is found)
    q_xy = calibrate_noise(log, np.zeros(4), setup_options=prior)[0]
    options, scores, tests, reason = heading_noise(log, np.zeros(4), setup_options=prior)
    q = options["q_xy_heading"]
    assert q_xy >= 4.0 and q < q_xy, (q_xy, reason)
    t = tests["q_xy_heading"]
    held = scores["q_xy_heading"][q]
    assert held <= t["reference_score"] and (q == 1.0 or t["significantly_better"]), reason
    assert set(tests) == set(HEADING_KEYS) and "scored by ekf-heading" in reason

    def rmse(q_heading):
        s = run_replay(log, estimators=["ekf-heading"], initial_offset=2.0, batch=False,
                       setup_options={**prior, "q_xy_heading": q_heading,
                                      "q_theta": options["q_theta"]},
                       burn_in=10.0)  # fmt: skip
        return s["estimators"]["ekf-heading"]["rmse"]

    assert rmse(q) <= rmse(q_xy), (q, q_xy)


@pytest.mark.parametrize("fixed", [{}, {"q_xy_heading": 0.5}])
def test_the_command_line_calibrates_what_tune_does_not_fix(tmp_path, fixed):
    folder = write_log(circle_log(30.0, 0.01), tmp_path / "log")
    tune = [arg for k, v in fixed.items() for arg in ("--tune", f"{k}={v}")]
    summary = tmp_path / "s.json"
    args = ["replay", str(folder), "--no-progress", "--estimators", "ekf-heading"]
    assert main([*args, "--summary", str(summary), *tune]) == 0
    written = json.loads(summary.read_text())
    cal = written["calibration"]
    assert 0.0 < cal["seconds"] and written["wall_time"] > 0.0  # the calibration's own time
    fitted = {k for k in HEADING_KEYS if f"{k}_scores" in cal}
    assert fitted == set(HEADING_KEYS) - set(fixed), cal
    assert set(cal["heading_noise"]) == set(HEADING_KEYS)
    for k, v in fixed.items():
        assert cal["heading_noise"][k] == v
