"""Stresses of a log (quadobs.testbed.logs.posed): a surveyed anchor plan, a late start, a late
truth, an anchor's gap, a pillar's shadow, an accelerometer's scale, inputs
late against the ranges, a tag's direction-dependent delay; each against its closed form."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog
from quadobs.testbed.logs.posed import (
    accel_scaled,
    anchor_gap,
    behind_pillar,
    blocked_by_pillar,
    inputs_late,
    log_start,
    started_at,
    surveyed,
    tag_pattern,
    truth_from,
)

BEACONS = np.array([[0.1, 0.1], [2.9, 0.2], [2.8, 2.3], [0.2, 2.3]])


def _circle(t0: float = 100.0) -> RangeLog:
    """A robot on a circle of radius 0.8 m about (1.5, 1.2) at 0.4 rad/s, heading along it,
    from ``t0`` for 20 s: truth at 100 Hz, odometry at 100 Hz, exact ranges at 20 Hz."""
    t = t0 + np.linspace(0.0, 20.0, 2001)
    phi = 0.4 * (t - t0)
    p = np.column_stack([1.5 + 0.8 * np.cos(phi), 1.2 + 0.8 * np.sin(phi)])
    truth = np.column_stack([t, p, phi + np.pi / 2])
    k = np.arange(5, 2000, 5)
    h = k % 4
    ranges = np.column_stack([t[k], h, np.linalg.norm(p[k] - BEACONS[h], axis=1)])
    inputs = np.column_stack([t, np.full(t.size, 0.32), np.full(t.size, 0.4)])
    return RangeLog("circle", np.arange(4), BEACONS, ranges, inputs, np.pi / 2, truth)


def test_survey_moves_the_plan_not_the_ranges_and_is_seeded():
    log = _circle()
    a, b, c = surveyed(log, 0.05, 7), surveyed(log, 0.05, 7), surveyed(log, 0.05, 8)
    np.testing.assert_array_equal(a.beacons, b.beacons)
    assert not np.array_equal(a.beacons, c.beacons)
    np.testing.assert_array_equal(a.ranges, log.ranges)
    drawn = 0.05 * np.random.default_rng(7).standard_normal((4, 2))
    np.testing.assert_allclose(a.beacons - log.beacons, drawn, atol=1e-15)


def test_a_late_start_cuts_every_table_and_states_the_heading_there():
    log = _circle()
    late = started_at(log, 5.0)
    t0 = log_start(log) + 5.0
    for table in (late.ranges, late.inputs, late.truth):
        assert table[0, 0] >= t0 and table[0, 0] < t0 + 0.06
    assert late.range_std.shape == (late.ranges.shape[0],)
    # heading on the circle: pi/2 + 0.4 (t - t0), at the first input left
    t_first = late.inputs[0, 0] - 100.0
    assert late.heading0 == pytest.approx(np.pi / 2 + 0.4 * t_first, abs=1e-12)
    # without a heading in the truth: dead-reckoned from the yaw rate, the same on this circle
    blind = dataclasses.replace(log, truth=log.truth[:, :3], truth_columns=("time", "x", "y"))
    assert started_at(blind, 5.0).heading0 == pytest.approx(late.heading0, abs=1e-9)


def test_a_late_truth_at_its_own_rate():
    late = truth_from(_circle(), 3.0, 30.0)
    assert late.truth[0, 0] == pytest.approx(103.0, abs=1e-9)
    step = np.diff(late.truth[:, 0])  # the 100 Hz row at or after each 1/30 s tick
    assert np.all((step > 0.029) & (step < 0.041))
    assert np.mean(step) == pytest.approx(1.0 / 30.0, rel=0.01)


def test_the_gap_removes_the_ranges_it_names():
    log = _circle()
    gap = anchor_gap(log, 1, 4.0, 3.0)
    t = log.ranges[:, 0] - 100.0
    gone = (log.ranges[:, 1] == 1) & (t >= 4.0) & (t < 7.0)
    assert gone.sum() == 15  # 20 Hz over four anchors: 5 Hz each, for 3 s
    np.testing.assert_array_equal(gap.ranges, log.ranges[~gone])


def test_a_pillar_blocks_the_segments_that_pass_within_its_radius():
    log = RangeLog(
        "two", np.arange(2), np.array([[2.0, 0.0], [0.0, 2.0]]),
        np.array([[0.0, 0, 2.0], [0.0, 1, 2.0]]), np.array([[0.0, 0, 0], [1.0, 0, 0]]), 0.0,
        np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]),
    )  # fmt: skip
    # the tag at the origin: the pillar at (1, 0.1) crosses the path to anchor 0 only
    np.testing.assert_array_equal(blocked_by_pillar(log, (1.0, 0.1), 0.15), [True, False])
    np.testing.assert_array_equal(blocked_by_pillar(log, (1.0, 0.2), 0.15), [False, False])
    # beyond the anchor, in line with it: the segment ends at the anchor
    np.testing.assert_array_equal(blocked_by_pillar(log, (2.3, 0.0), 0.15), [False, False])
    longer = behind_pillar(log, (1.0, 0.1), 0.15, 0.3, seed=3)
    assert longer.ranges[0, 2] > 2.0 and longer.ranges[1, 2] == 2.0


def test_a_circle_passes_behind_a_pillar_in_one_burst_a_lap():
    log = _circle()
    blocked = blocked_by_pillar(log, (1.0, 0.3), 0.15)  # inside the circle's south-west
    assert set(log.ranges[blocked, 1].astype(int)) == {0}  # only the paths to anchor 0 cross it
    edges = np.flatnonzero(np.diff(blocked[log.ranges[:, 1] == 0].astype(int)))
    assert edges.size == 2  # one lap in the 20 s: one shadow, a single run of its ranges


def test_an_accelerometer_scale_and_late_inputs():
    log = _circle()
    with pytest.raises(QuadobsError, match="body IMU"):
        accel_scaled(log, (0.01, 0.0, 0.0))
    imu = np.column_stack([np.arange(5.0), np.ones((5, 3)), np.zeros((5, 3))])
    space = np.column_stack([BEACONS, np.ones(4)])
    body = dataclasses.replace(log, beacons=space, inputs=imu, input_kind="imu_body", truth=None)
    np.testing.assert_allclose(
        accel_scaled(body, (0.02, -0.01, 0.0)).inputs[:, 1:4], [[1.02, 0.99, 1.0]] * 5
    )
    late = inputs_late(log, 0.1, 0.004, seed=2)
    assert np.all(np.diff(late.inputs[:, 0]) >= 0.0)
    np.testing.assert_allclose(late.inputs[:, 0] - log.inputs[:, 0], 0.1, atol=0.004)
    np.testing.assert_array_equal(
        late.inputs[:, 0], inputs_late(log, 0.1, 0.004, seed=2).inputs[:, 0]
    )


def _traceless_fit(u: np.ndarray, value: np.ndarray) -> np.ndarray:
    """The symmetric traceless ``S`` with ``u^T S u = value`` by least squares (exact when the
    values are such a form): ``S`` spanned by its off-diagonal entries and ``e_i e_i^T - e_k
    e_k^T`` (``k`` the last axis)."""
    k = u.shape[1]
    basis = []
    for i in range(k):
        for j in range(i, k):
            if i == j == k - 1:
                continue
            b = np.zeros((k, k))
            if i == j:
                b[i, i], b[-1, -1] = 1.0, -1.0
            else:
                b[i, j] = b[j, i] = 1.0
            basis.append(b)
    design = np.column_stack([np.einsum("ni,ij,nj->n", u, b, u) for b in basis])
    coef, *_ = np.linalg.lstsq(design, value, rcond=None)
    return sum(c * b for c, b in zip(coef, basis, strict=True))


def test_a_tag_pattern_in_the_plane_is_a_second_harmonic_of_the_body_bearing():
    log = _circle()
    log.ranges[3, 2] = 0.0  # nothing received: left at zero
    posed = tag_pattern(log, 0.1, seed=4)
    added = posed.ranges[:, 2] - log.ranges[:, 2]
    assert added[3] == 0.0
    np.testing.assert_array_equal(posed.ranges, tag_pattern(log, 0.1, seed=4).ranges)
    assert not np.array_equal(posed.ranges, tag_pattern(log, 0.1, seed=5).ranges)
    # the anchor's bearing from the vehicle less the heading, from the truth's own rows
    t = log.ranges[:, 0]
    p = np.column_stack([np.interp(t, log.truth[:, 0], log.truth[:, c]) for c in (1, 2)])
    d = BEACONS[log.ranges[:, 1].astype(int)] - p
    phi = np.arctan2(d[:, 1], d[:, 0]) - np.interp(t, log.truth[:, 0], log.truth[:, 3])
    design = np.column_stack([np.cos(2 * phi), np.sin(2 * phi)])
    keep = log.ranges[:, 2] > 0.0
    (a, b), *_ = np.linalg.lstsq(design[keep], added[keep], rcond=None)
    np.testing.assert_allclose(design[keep] @ [a, b], added[keep], atol=1e-12)
    assert (a * a + b * b) / 2.0 == pytest.approx(0.1**2, rel=1e-9)  # the circle's variance
    with pytest.raises(QuadobsError, match="heading"):
        tag_pattern(
            dataclasses.replace(log, truth=log.truth[:, :3], truth_columns=("time", "x", "y")),
            0.1,
            1,
        )


def test_a_tag_pattern_in_space_turns_with_the_attitude():
    from scipy.spatial.transform import Rotation

    t = np.linspace(0.0, 10.0, 1001)
    p = np.column_stack([1.5 + np.cos(t), 1.2 + np.sin(t), 1.0 + 0.2 * np.sin(3 * t)])
    turn = Rotation.from_euler("zyx", np.column_stack([0.7 * t, 0.2 * np.sin(t), 0.1 * t]))
    q = turn.as_quat()[:, [3, 0, 1, 2]]  # scalar first, as truth.csv holds it
    anchors = np.array([[0, 0, 0.2], [3, 0, 2.5], [3, 2.5, 0.3], [0, 2.5, 2.4], [1.5, 1.2, 3.0]])
    k = np.arange(0, 1001, 3)  # at truth rows: no interpolation between them
    h = k % 5
    ranges = np.column_stack([t[k], h, np.linalg.norm(p[k] - anchors[h], axis=1)])
    log = RangeLog(
        "space", np.arange(5), anchors, ranges, np.empty((0, 1)), np.nan,
        np.column_stack([t, p, q]), input_kind="none",
        truth_columns=("time", "x", "y", "z", "qw", "qx", "qy", "qz"),
    )  # fmt: skip
    added = tag_pattern(log, 0.1, seed=3).ranges[:, 2] - ranges[:, 2]
    u = turn[k].inv().apply(anchors[h] - p[k])
    u /= np.linalg.norm(u, axis=1)[:, None]
    form = _traceless_fit(u, added)
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", u, form, u), added, atol=1e-12)
    assert 2.0 * np.trace(form @ form) / 15.0 == pytest.approx(0.1**2, rel=1e-9)  # the sphere's
