"""Odometry poses as the log's speed and yaw rate: the replay's dead reckoning gives them back."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.convert import odometry_from_poses
from quadobs.testbed.worlds.replay import dead_reckoning


def test_poses_along_their_heading_come_back_from_the_dead_reckoning():
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.01, 0.05, 400))  # uneven intervals
    v = 0.4 * np.sin(0.3 * t)  # forwards and backwards
    w = 0.8 * np.cos(0.2 * t)
    inputs = np.column_stack([t, v, w])
    log = RangeLog("odo", np.arange(2), np.zeros((2, 2)), np.empty((0, 3)), inputs, 2.5)
    p, psi = dead_reckoning(log, t, origin=(3.0, -1.0))  # the odometry's own frame and heading
    wrapped = np.angle(np.exp(1j * psi))
    back = odometry_from_poses(t, p[:, 0], p[:, 1], wrapped)
    np.testing.assert_allclose(back[:-1], inputs[:-1], atol=1e-9)
    np.testing.assert_allclose(back[-1, 1:], back[-2, 1:])
    again = RangeLog("odo", np.arange(2), np.zeros((2, 2)), np.empty((0, 3)), back, psi[0])
    np.testing.assert_allclose(dead_reckoning(again, t, origin=(3.0, -1.0))[0], p, atol=1e-9)


def test_a_sideways_step_is_left_out_and_bad_times_are_refused():
    back = odometry_from_poses([0.0, 1.0], [0.0, 0.3], [0.0, 0.4], [0.0, 0.0])
    np.testing.assert_allclose(back[0, 1:], [0.3, 0.0])  # along the heading only
    assert back[0, 2] == 0.0
    with pytest.raises(QuadobsError, match=r"times must increase \(row 3: 1.0 after 1.0\)"):
        odometry_from_poses([0.0, 1.0, 1.0], [0, 1, 2], [0, 0, 0], [0, 0, 0])
    with pytest.raises(QuadobsError, match="finite"):
        odometry_from_poses([0.0, 1.0], [0, math.nan], [0, 0], [0, 0])


def test_a_differential_drive_turns_left_when_its_right_wheel_is_faster():
    """Wheels at 0.3 and 0.5 m/s on a track of 0.2 m: 0.4 m/s turning left at 1 rad/s, a circle
    of 0.4 m that the replay's dead reckoning closes after 2 pi s; equal wheels go straight."""
    from quadobs.testbed.logs.convert import odometry_from_wheels

    t = np.linspace(0.0, 2.0 * np.pi, 2001)
    rows = odometry_from_wheels(t, 0.3 + 0 * t, 0.5 + 0 * t, 0.2)
    np.testing.assert_allclose(rows[:, 1:], np.tile([0.4, 1.0], (t.size, 1)))
    log = RangeLog("wheels", np.arange(2), np.zeros((2, 2)), np.empty((0, 3)), rows, 0.0)
    p, psi = dead_reckoning(log, t)
    assert p[:, 1].max() == pytest.approx(0.8, abs=1e-6)  # left of the start: y > 0
    np.testing.assert_allclose(p[-1], [0.0, 0.0], atol=1e-6)
    assert odometry_from_wheels([0.0, 1.0], [0.2, 0.2], [0.2, 0.2], 0.3)[0, 2] == 0.0
    with pytest.raises(QuadobsError, match="track: a positive distance"):
        odometry_from_wheels([0.0, 1.0], [0, 0], [0, 0], 0.0)
    with pytest.raises(QuadobsError, match=r"times must increase \(row 2"):
        odometry_from_wheels([1.0, 1.0], [0, 0], [0, 0], 0.2)


def test_the_tags_stated_place_is_read_written_and_starts_the_lever_arm(tmp_path):
    """``meta.csv`` ``tag_x``, ``tag_y``: read and written back; both or neither, odometry logs
    only; the filters that hold the lever arm start from it with the stated prior, and from
    zero with the wide one where the log states none."""
    from quadobs.estimators.heading_ekf import LEVER_ARM_STD, STATED_LEVER_STD
    from quadobs.testbed.logs import read_log, write_log
    from quadobs.testbed.logs.estimators import lever_prior, log_frame

    anchors = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0], [0.0, 3.0]])
    t = np.arange(0.0, 5.0, 0.05)
    ranges = np.column_stack([t, np.arange(t.size) % 4, np.full(t.size, 2.0)])
    inputs = np.column_stack([t, 0.2 + 0 * t, 0 * t])
    log = RangeLog("r", np.arange(4), anchors, ranges, inputs, 0.0, tag_x=0.12, tag_y=-0.03)
    back = read_log(write_log(log, tmp_path / "r"))
    assert back.tag_offset == (0.12, -0.03)
    assert log_frame(back)["lever_arm"] == (0.12, -0.03)
    setup = SimpleNamespace(lever_arm=(0.12, -0.03))
    assert lever_prior(setup) == {"lever_arm_std": STATED_LEVER_STD, "lever_arm": (0.12, -0.03)}
    assert lever_prior(SimpleNamespace(lever_arm=None)) == {"lever_arm_std": LEVER_ARM_STD}
    from quadobs.testbed.logs.estimators import build_replay_estimators, replay_setup
    from quadobs.testbed.worlds.replay import ReplayWorld

    s = replay_setup(back, ReplayWorld(back, 0.1, "odometry"), {"P0": 1.0})
    for est in build_replay_estimators(s, ["ukf-lever", "ukf-height-lever"], np.zeros(2)):
        np.testing.assert_allclose(est.state[4:6], [0.12, -0.03])
        np.testing.assert_allclose(np.diag(est.state_covariance)[4:6], STATED_LEVER_STD**2)
    with pytest.raises(QuadobsError, match="key tag_x: given without tag_y"):
        RangeLog("r", np.arange(4), anchors, ranges, inputs, 0.0, tag_x=0.1)
    with pytest.raises(QuadobsError, match="key tag_z: for a log in space"):
        RangeLog("r", np.arange(4), anchors, ranges, inputs, 0.0, tag_x=0.1, tag_y=0.0, tag_z=0.1)
    with pytest.raises(
        QuadobsError, match=r"key tag_x: for a wheel-odometry log or a log in space \(3-D\)"
    ):
        RangeLog(
            "r", np.arange(4), anchors, ranges, inputs[:, :3], math.nan, input_kind="imu",
            tag_x=0.1, tag_y=0.0,
        )  # fmt: skip
