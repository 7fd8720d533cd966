"""The replay's checks of units and its notes hold on correct logs of awkward geometry: sparse
ranges of a fast vehicle among anchors close together, a robot under high anchors, a robot
that drives straight with a jittery truth."""

from __future__ import annotations

import math

import numpy as np

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.replay import check_range_units, check_truth_units, truth_odometry_note


def test_sparse_ranges_of_a_fast_drone_over_a_landing_pad_are_not_taken_for_cm():
    """Four anchors on a 0.6 m pad, a drone shuttling between 1 and 30 m away (4 m/s on
    average, slowing at each end) while climbing and sinking, ranges at 5 Hz with 0.05 m of
    noise: the spread about each range's neighbours is the motion's (0.67 m, and 2.7 m over
    the doubled span), not a noise in cm; the cubic's figure (0.07 m) is the noise."""
    rng = np.random.default_rng(0)
    pad = np.array([[-0.3, -0.3, 0.05], [0.3, -0.3, 0.05], [0.3, 0.3, 0.05], [-0.3, 0.3, 0.05]])
    t = 0.2 * np.arange(300)
    period = math.hypot(29.0, 0.5) / 4.0
    s = (t % (2 * period)) / period
    s = 0.5 - 0.5 * np.cos(math.pi * np.where(s < 1, s, 2 - s))
    p = np.column_stack([30 - 29 * s, 0.5 * s, 2 + 3 * np.abs(np.sin(t / 10))])
    h = np.arange(t.size) % 4
    rho = np.linalg.norm(p - pad[h], axis=1) + rng.normal(0.0, 0.05, t.size)
    log = RangeLog(
        "pad",
        np.arange(4),
        pad,
        np.column_stack([t, h, rho]),
        np.empty((0, 1)),
        math.nan,
        input_kind="none",
    )
    check_range_units(log)


def test_a_robot_under_high_anchors_keeps_the_anchors_heights_in_the_truths_distance():
    anchors = np.array([[-1.0, -1.0, 15.0], [1.0, -1.0, 15.0], [1.0, 1.0, 15.0], [-1.0, 1.0, 15.0]])
    t = 0.05 * np.arange(400)
    p = np.column_stack([0.5 * np.cos(0.3 * t), 0.5 * np.sin(0.3 * t)])
    h = np.arange(t.size) % 4
    rho = np.hypot(np.linalg.norm(p - anchors[h, :2], axis=1), 15.0)
    inputs = np.column_stack([t, 0.15 + 0 * t, 0.3 + 0 * t])
    truth = np.column_stack([t, p, 0.3 * t + math.pi / 2])
    log = RangeLog(
        "under",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        inputs,
        math.pi / 2,
        truth,
        truth_columns=("time", "x", "y", "heading"),
    )
    check_truth_units(log)


def test_a_robot_driving_straight_with_a_jittery_truth_heading_is_not_noted():
    rng = np.random.default_rng(1)
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 2.0], [0.0, 2.0]])
    t = 0.02 * np.arange(6000)
    x = 1.0 + 4.0 * (1.0 - np.cos(0.2 * t))  # back and forth along the corridor, no turn
    speed = np.gradient(x, t)
    truth = np.column_stack([t, x, 1.0 + 0 * t, rng.normal(0.0, 0.02, t.size)])
    h = np.arange(t.size) % 4
    rho = np.linalg.norm(truth[:, 1:3] - anchors[h], axis=1)
    inputs = np.column_stack([t, speed, 0 * t])
    log = RangeLog(
        "corridor",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        inputs,
        0.0,
        truth,
        truth_columns=("time", "x", "y", "heading"),
    )
    assert truth_odometry_note(log) is None
    flipped = RangeLog(
        "corridor",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        inputs * [1, -1, 1],
        0.0,
        truth,
        truth_columns=("time", "x", "y", "heading"),
    )
    assert "distances (speed) are -1 times" in truth_odometry_note(flipped)


def test_a_truth_shrunk_onto_the_origin_is_refused():
    """A truth in metres read as mm lies near the origin: its distances to the anchors are of
    the ranges' size, but each differs from its range by metres."""
    import pytest

    from quadobs.errors import QuadobsError

    anchors = np.array([[0.0, 0.0, 0.2], [6.0, 0.0, 2.5], [6.0, 5.0, 0.3], [0.0, 5.0, 2.4]])
    t = 0.05 * np.arange(400)
    p = np.column_stack([3 + 2 * np.cos(0.3 * t), 2.5 + 2 * np.sin(0.3 * t), 1.0 + 0 * t])
    h = np.arange(t.size) % 4
    rho = np.linalg.norm(p - anchors[h], axis=1)
    truth = np.column_stack([t, p])
    columns = ("time", "x", "y", "z")
    ok = RangeLog(
        "f",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        np.empty((0, 1)),
        math.nan,
        truth,
        input_kind="none",
        truth_columns=columns,
    )
    check_truth_units(ok)
    shrunk = RangeLog(
        "f",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        np.empty((0, 1)),
        math.nan,
        truth * [1, 1e-3, 1e-3, 1e-3],
        input_kind="none",
        truth_columns=columns,
    )
    with pytest.raises(QuadobsError, match="each range differs from the truth's distance"):
        check_truth_units(shrunk)


def test_a_robot_turning_in_place_with_its_tag_off_the_axle_is_not_noted():
    """The truth of a tag 0.2 m beside the axle moves as the robot spins on the spot, which
    the odometry's speed (zero) does not show: only windows that drive straight are compared."""
    anchors = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    t = 0.02 * np.arange(3000)
    rate = np.where((t // 10) % 2 == 0, 0.8, 0.0)  # spin, then drive
    speed = np.where((t // 10) % 2 == 0, 0.0, 0.2)
    psi = np.concatenate([[0.0], np.cumsum(rate[:-1] * 0.02)])
    axle = np.column_stack(
        [
            2 + np.concatenate([[0.0], np.cumsum(speed[:-1] * np.cos(psi[:-1]) * 0.02)]),
            2 + np.concatenate([[0.0], np.cumsum(speed[:-1] * np.sin(psi[:-1]) * 0.02)]),
        ]
    )
    tag = axle + 0.2 * np.column_stack([-np.sin(psi), np.cos(psi)])
    h = np.arange(t.size) % 4
    rho = np.linalg.norm(tag - anchors[h], axis=1)
    truth = np.column_stack([t, tag, psi])
    inputs = np.column_stack([t, speed, rate])
    log = RangeLog(
        "spin",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        inputs,
        0.0,
        truth,
        truth_columns=("time", "x", "y", "heading"),
    )
    assert truth_odometry_note(log) is None
