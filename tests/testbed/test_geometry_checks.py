"""The replay's checks of units and its notes hold on correct logs of awkward geometry, and
still catch what they are for: sparse ranges of a fast vehicle among anchors close together,
a robot under high anchors, a robot that drives straight with a jittery truth or turns on the
spot with its tag off the axle, a truth shrunk onto the origin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.replay import check_range_units, check_truth_units, truth_odometry_note

ROBOT_TRUTH = ("time", "x", "y", "heading")


def _log(anchors, t, rho, inputs=None, truth=None, columns=ROBOT_TRUTH) -> RangeLog:
    """A log of ranges to the anchors in turn, with wheel odometry (``heading0`` 0, or the
    truth's first heading) where ``inputs`` is given."""
    ranges = np.column_stack([t, np.arange(t.size) % anchors.shape[0], rho])
    ids = np.arange(anchors.shape[0])
    if inputs is None:
        kind = {"input_kind": "none", "truth_columns": columns}
        return RangeLog("g", ids, anchors, ranges, np.empty((0, 1)), math.nan, truth, **kind)
    heading0 = 0.0 if truth is None else float(truth[0, 3])
    return RangeLog("g", ids, anchors, ranges, inputs, heading0, truth, truth_columns=columns)


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
    check_range_units(
        _log(pad, t, np.linalg.norm(p - pad[h], axis=1) + rng.normal(0.0, 0.05, t.size))
    )


def test_a_robot_under_high_anchors_keeps_the_anchors_heights_in_the_truths_distance():
    anchors = np.array([[-1.0, -1.0, 15.0], [1.0, -1.0, 15.0], [1.0, 1.0, 15.0], [-1.0, 1.0, 15.0]])
    t = 0.05 * np.arange(400)
    p = np.column_stack([0.5 * np.cos(0.3 * t), 0.5 * np.sin(0.3 * t)])
    rho = np.hypot(np.linalg.norm(p - anchors[np.arange(t.size) % 4, :2], axis=1), 15.0)
    inputs = np.column_stack([t, 0.15 + 0 * t, 0.3 + 0 * t])
    check_truth_units(_log(anchors, t, rho, inputs, np.column_stack([t, p, 0.3 * t + math.pi / 2])))


def test_a_robot_driving_straight_with_a_jittery_truth_heading_is_not_noted():
    rng = np.random.default_rng(1)
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 2.0], [0.0, 2.0]])
    t = 0.02 * np.arange(6000)
    x = 1.0 + 4.0 * (1.0 - np.cos(0.2 * t))  # back and forth along the corridor, no turn
    truth = np.column_stack([t, x, 1.0 + 0 * t, rng.normal(0.0, 0.02, t.size)])
    rho = np.linalg.norm(truth[:, 1:3] - anchors[np.arange(t.size) % 4], axis=1)
    inputs = np.column_stack([t, np.gradient(x, t), 0 * t])
    assert truth_odometry_note(_log(anchors, t, rho, inputs, truth)) is None
    flipped = truth_odometry_note(_log(anchors, t, rho, inputs * [1, -1, 1], truth))
    assert "distances (speed) are -1 times" in flipped


def test_a_truth_shrunk_onto_the_origin_is_refused():
    """A truth in metres read as mm lies near the origin: its distances to the anchors are of
    the ranges' size, but each differs from its range by metres."""
    anchors = np.array([[0.0, 0.0, 0.2], [6.0, 0.0, 2.5], [6.0, 5.0, 0.3], [0.0, 5.0, 2.4]])
    t = 0.05 * np.arange(400)
    p = np.column_stack([3 + 2 * np.cos(0.3 * t), 2.5 + 2 * np.sin(0.3 * t), 1.0 + 0 * t])
    rho = np.linalg.norm(p - anchors[np.arange(t.size) % 4], axis=1)
    truth, columns = np.column_stack([t, p]), ("time", "x", "y", "z")
    check_truth_units(_log(anchors, t, rho, truth=truth, columns=columns))
    shrunk = _log(anchors, t, rho, truth=truth * [1, 1e-3, 1e-3, 1e-3], columns=columns)
    with pytest.raises(QuadobsError, match="each range differs from the truth's distance"):
        check_truth_units(shrunk)


def test_a_robot_turning_in_place_with_its_tag_off_the_axle_is_not_noted():
    """The truth of a tag 0.2 m beside the axle moves as the robot spins on the spot, which
    the odometry's speed (zero) does not show: only windows that drive straight are compared."""
    anchors = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    t, dt = 0.02 * np.arange(3000), 0.02
    spinning = (t // 10) % 2 == 0
    rate, speed = np.where(spinning, 0.8, 0.0), np.where(spinning, 0.0, 0.2)
    psi = np.concatenate([[0.0], np.cumsum(rate[:-1] * dt)])
    step = np.column_stack([speed * np.cos(psi), speed * np.sin(psi)]) * dt
    axle = 2.0 + np.vstack([[0.0, 0.0], np.cumsum(step[:-1], axis=0)])
    tag = axle + 0.2 * np.column_stack([-np.sin(psi), np.cos(psi)])
    rho = np.linalg.norm(tag - anchors[np.arange(t.size) % 4], axis=1)
    inputs = np.column_stack([t, speed, rate])
    assert (
        truth_odometry_note(_log(anchors, t, rho, inputs, np.column_stack([t, tag, psi]))) is None
    )
