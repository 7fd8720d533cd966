"""The replay in time: every measurement at its own timestamp, models chosen from the log (2-D, 3-D,
ranges alone, TDOA, body IMU), refusals before any calibration, and the self-calibration's fallback."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from quadobs.cli import main
from quadobs.testbed.attitude import estimate_attitude, navigation_accelerations
from quadobs.testbed.logs import RangeLog, write_log
from quadobs.testbed.logs.calibration import calibrate
from quadobs.testbed.logs.replay import run_replay

ANCHORS_2D = np.array([[0.0, 0.0], [12.0, 0.0], [12.0, 9.0], [0.0, 9.0]])
ANCHORS_3D = np.array(
    [[0.0, 0.0, 0.0], [6.0, 0.0, 3.0], [6.0, 6.0, 0.0], [0.0, 6.0, 3.0], [3.0, 3.0, 3.0]]
)


def _straight(t, dim):
    """A constant-velocity truth: position and velocity at times ``t``."""
    p0 = np.array([2.0, 3.0, 1.0])[:dim]
    v = np.array([0.12, 0.06, 0.01])[:dim]
    return p0 + t[:, None] * v, np.tile(v, (t.size, 1))


def _ranges(t, anchors, positions, rng, sigma=0.0):
    """One range a time, to the anchors in turn (a tag's round robin), at the times ``t``."""
    h = np.arange(t.size) % anchors.shape[0]
    rho = np.linalg.norm(positions - anchors[h], axis=1) + sigma * rng.standard_normal(t.size)
    return np.column_stack([t, h, rho])


def _truth(t, p, v, dim):
    cols = ("time", *"xyz"[:dim], *("vx", "vy", "vz")[:dim])
    return np.column_stack([t, p, v]), cols


def test_odometry_log_in_time_uses_every_range_and_integrates_exactly():
    """Ranges off the grid, two to one anchor within a step: all used; a noise-free log started at
    the truth stays on it (the grid's flooring would read each range up to dt early)."""
    rng = np.random.default_rng(0)
    ti = np.arange(0.0, 30.0, 0.05)
    speed, yaw = 0.8, 0.05
    inputs = np.column_stack([ti, np.full(ti.size, speed), np.full(ti.size, yaw)])
    theta = yaw * ti
    p = np.column_stack([np.sin(theta), 1.0 - np.cos(theta)]) * speed / yaw + [3.0, 2.0]
    tr = np.sort(np.r_[0.51, 0.52, 0.53, rng.uniform(0.6, 29.9, 297)])  # 3 in one 0.1 s step
    pr = np.column_stack([np.interp(tr, ti, p[:, 0]), np.interp(tr, ti, p[:, 1])])
    ranges = _ranges(tr, ANCHORS_2D, pr, rng)
    ranges[2, 1] = ranges[1, 1]  # the same anchor twice in that step
    ranges[2, 2] = np.linalg.norm(pr[2] - ANCHORS_2D[int(ranges[1, 1])])
    log = RangeLog(
        "odo", np.arange(4), ANCHORS_2D, ranges, inputs, 0.0,
        np.column_stack([ti, p]), input_kind="odometry", truth_columns=("time", "x", "y"),
    )  # fmt: skip
    s = run_replay(log, estimators=["augmented", "ekf"], initial_offset=0.0, batch=False)
    r = s["ranges"]
    assert r["in_log"] == r["placed"] == r["measurements_in_time"] == 300 and r["merged"] == 0
    assert s["estimators"]["augmented"]["corrections"] == 300
    # the dead reckoning between samples is linear, the truth a circle: chords 0.04 m apart,
    # an error of v^2 dt^2 / (8 R) ~ 2e-5 m, far below the grid's v dt / 2 = 0.04 m
    assert s["estimators"]["ekf"]["max_error"] < 2e-3
    assert s["estimators"]["augmented"]["max_error"] < 2e-3


@pytest.mark.parametrize("dim", [2, 3])
def test_ranges_alone_replay_with_constant_velocity_in_2d_and_3d(dim):
    rng = np.random.default_rng(1)
    anchors = ANCHORS_2D if dim == 2 else ANCHORS_3D
    t = np.arange(0.0, 40.0, 0.04)
    p, v = _straight(t, dim)
    truth, cols = _truth(t, p, v, dim)
    log = RangeLog(
        f"cv{dim}", np.arange(len(anchors)), anchors, _ranges(t, anchors, p, rng, 0.05),
        np.empty((0, 1)), float("nan"), truth, input_kind="none", truth_columns=cols,
    )  # fmt: skip
    s = run_replay(
        log, estimators=["augmented", "ekf", "ukf"], initial_offset=5.0, batch=False,
        setup_options={"range_sigma": 0.05, "q_acc": 1e-3, "P0": 25.0}, burn_in=10.0,
    )  # fmt: skip
    assert s["model"] == "cv" and s["ranges"]["merged"] == 0
    for name in ("augmented", "ekf", "ukf"):
        assert s["estimators"][name]["rmse"] < 0.1, (name, s["estimators"][name])


def _tdoa_log(tmp_path=None):
    rng = np.random.default_rng(2)
    t = np.arange(0.0, 30.0, 0.05)
    p, v = _straight(t, 2)
    pairs = np.array([(1, 0), (2, 0), (3, 0), (2, 1)])[np.arange(t.size) % 4]
    d = np.linalg.norm(p - ANCHORS_2D[pairs[:, 0]], axis=1) - np.linalg.norm(
        p - ANCHORS_2D[pairs[:, 1]], axis=1
    )
    truth, cols = _truth(t, p, v, 2)
    tdoa = np.column_stack([t, pairs, d + 0.03 * rng.standard_normal(t.size)])
    return RangeLog(
        "tdoa", np.arange(4), ANCHORS_2D, np.empty((0, 3)), np.empty((0, 1)), float("nan"),
        truth, input_kind="none", truth_columns=cols, tdoa=tdoa,
    )  # fmt: skip


def test_tdoa_log_through_the_ekf_and_refused_by_the_observer_before_calibration(tmp_path, capsys):
    log = _tdoa_log()
    s = run_replay(
        log, estimators=["ekf"], initial_offset=2.0, batch=False,
        setup_options={"range_sigma": 0.03, "q_acc": 1e-3}, burn_in=10.0,
    )  # fmt: skip
    r = s["ranges"]  # the grid ends at 29.9 s: the TDOA at 29.9 and 29.95 s lie after it
    assert r["measurements_in_time"] == 598 and r["after_the_last_step"] == 2
    assert s["estimators"]["ekf"]["rmse"] < 0.2
    folder = write_log(log, tmp_path / "tdoa")
    assert main(["replay", str(folder), "--no-progress", "--estimators", "ekf,augmented"]) == 2
    out, err = capsys.readouterr()
    assert (
        "'augmented' takes ranges only, and the log holds TDOA" in err and "\n" not in err.strip()
    )
    assert "calibrated" not in out  # refused before any calibration
    assert run_replay(log, batch=False)["primary_estimator"] == "ekf"  # the defaults take TDOA


def _imu_body_log(with_attitude: bool, yaw_rate: float = 0.0):
    """A body that circles at constant speed, level, turning with the circle (heading along the
    velocity) or not; specific force and gyro in the body frame at 200 Hz, ranges at 50 Hz."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20.0, 0.005)
    w, r = 0.3, 2.0
    p = np.column_stack([3 + r * np.cos(w * t), 3 + r * np.sin(w * t), 1.5 + 0 * t])
    v = np.column_stack([-r * w * np.sin(w * t), r * w * np.cos(w * t), 0 * t])
    a = np.column_stack([-r * w * w * np.cos(w * t), -r * w * w * np.sin(w * t), 0 * t])
    R = Rotation.from_euler("z", (yaw_rate * t)[:, None])
    f = R.inv().apply(a - [0.0, 0.0, -9.80665])
    gyro = np.tile([0.0, 0.0, yaw_rate], (t.size, 1))
    q = R.as_quat()[:, [3, 0, 1, 2]]
    tr = t[::4]
    truth = np.column_stack([t, p, v])
    return RangeLog(
        "imu-body", np.arange(5), ANCHORS_3D, _ranges(tr, ANCHORS_3D, p[::4], rng, 0.05),
        np.column_stack([t, f, gyro]), float("nan"), truth, input_kind="imu_body",
        truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"),
        attitude=np.column_stack([t, q]) if with_attitude else None,
    )  # fmt: skip


def test_body_imu_rotated_by_the_logs_attitude_or_an_estimated_one():
    turning = _imu_body_log(True, yaw_rate=0.2)
    nav = navigation_accelerations(turning)
    t = nav[:, 0]
    expected = np.column_stack([-0.18 * np.cos(0.3 * t), -0.18 * np.sin(0.3 * t), 0 * t])
    np.testing.assert_allclose(nav[:, 1:], expected, atol=1e-9)
    level = _imu_body_log(False)  # no attitude: Mahony from the IMU (heading starts at zero)
    inputs = level.inputs.copy()
    inputs[:, 4:7] += 0.002 * np.random.default_rng(5).standard_normal((t.size, 3))
    level = dataclasses.replace(level, inputs=inputs)
    # the centripetal 0.18 m/s^2, taken for a tilt at first, is averaged out by the slow loop
    err = np.abs(navigation_accelerations(level)[:, 1:] - expected)
    assert err.max() < 0.2 and err[t > 10.0].mean() < 0.05
    Q = estimate_attitude(t, level.inputs[:, 1:4], level.inputs[:, 4:7])
    assert np.allclose(np.abs(Q[:, 0]), 1.0, atol=1e-2)  # stays about level, heading zero


@pytest.mark.parametrize("with_attitude", [True, False])
def test_body_imu_log_replays(with_attitude):
    log = _imu_body_log(with_attitude, yaw_rate=0.2 if with_attitude else 0.0)
    s = run_replay(
        log, estimators=["augmented", "ekf"], initial_offset=3.0, batch=False,
        setup_options={"range_sigma": 0.05}, burn_in=5.0,
    )  # fmt: skip
    assert s["model"] == "imu"
    for name in ("augmented", "ekf"):
        assert s["estimators"][name]["rmse"] < 0.1, (name, s["estimators"][name])


def test_calibration_falls_back_to_no_biases_when_they_do_not_help():
    """Unbiased ranges: no bias is applied, and the reason is given; a common 0.6 m bias is kept."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 60.0, 0.04)
    p, v = _straight(t, 2)
    truth, cols = _truth(t, p, v, 2)

    def log(bias):
        ranges = _ranges(t, ANCHORS_2D, p, rng, 0.1)
        ranges[:, 2] += bias
        return RangeLog(
            "cal", np.arange(4), ANCHORS_2D, ranges, np.empty((0, 1)), float("nan"), truth,
            input_kind="none", truth_columns=cols,
        )  # fmt: skip

    opts = {"range_sigma": 0.1, "q_acc": 1e-3}
    clean = calibrate(log(0.0), setup_options=opts, noise=False)
    assert clean.biases is None and clean.reason
    biased = calibrate(log(0.6), setup_options=opts, noise=False)
    assert biased.biases is not None and np.all(np.abs(biased.biases - 0.6) < 0.15), biased


def test_the_initial_offset_applies_when_the_truth_starts_late():
    rng = np.random.default_rng(6)
    t = np.arange(0.0, 20.0, 0.04)
    p, v = _straight(t, 2)
    truth, cols = _truth(t[t >= 2.0], p[t >= 2.0], v[t >= 2.0], 2)
    log = RangeLog(
        "late", np.arange(4), ANCHORS_2D, _ranges(t, ANCHORS_2D, p, rng, 0.05),
        np.empty((0, 1)), float("nan"), truth, input_kind="none", truth_columns=cols,
    )  # fmt: skip
    s = run_replay(log, estimators=["ekf"], initial_offset=7.0, batch=False)
    guess = np.array(s["initial_guess"][:2])
    assert np.linalg.norm(guess - truth[0, 1:3]) == pytest.approx(7.0)


def test_the_final_error_is_the_last_truths_when_the_truth_ends_early():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 20.0, 0.04)
    p, v = _straight(t, 2)
    truth, cols = _truth(t[t <= 15.0], p[t <= 15.0], v[t <= 15.0], 2)
    log = RangeLog(
        "early", np.arange(4), ANCHORS_2D, _ranges(t, ANCHORS_2D, p, rng, 0.05),
        np.empty((0, 1)), float("nan"), truth, input_kind="none", truth_columns=cols,
    )  # fmt: skip
    s = run_replay(log, estimators=["ekf"], initial_offset=0.0, batch=False)
    e = s["estimators"]["ekf"]
    assert e["final_position_error"] is not None
    assert 0.0 < e["final_position_error"] <= e["max_error"]
