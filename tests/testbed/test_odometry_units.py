"""Wheel odometry converted by hand in the wrong units (speed in mm/s, yaw rate in deg/s, times
in ms) is refused in one line naming the file and the column, before any calibration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_flight_log_units import _refused as refused  # the one error line of a replay

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.plaza import load_builtin
from quadobs.testbed.logs.replay import ODOMETRY_SPAN_RATIO, check_odometry_units
from quadobs.testbed.worlds.replay import dead_reckoning

ANCHORS = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 3.0], [0.0, 3.0]])


def _robot_log() -> RangeLog:
    """A robot on a stadium in a 3 m room (0.8 m/s; half turns of 0.8 rad/s, 0.75 s straight
    between them), 60 s: odometry at 20 Hz, ranges to four anchors round-robin at 10 Hz from
    the path it dead-reckons, no truth."""
    t = np.arange(0.0, 60.0, 0.05)
    turn = np.pi / 0.8
    w = np.where(np.mod(t, turn + 0.75) < turn, 0.8, 0.0)
    log = RangeLog(
        "robot", np.arange(4), ANCHORS, np.empty((0, 3)), np.column_stack([t, 0.8 + 0 * t, w]), 0.0
    )
    t_r = np.arange(0.02, 59.9, 0.1)
    h = np.arange(t_r.size) % 4
    p = dead_reckoning(log, t_r, origin=(1.8, 0.5))[0]
    ranges = np.column_stack([t_r, h, np.linalg.norm(p - ANCHORS[h], axis=1)])
    return dataclasses.replace(log, ranges=ranges)


def _scaled(log: RangeLog, speed=1.0, yaw_rate=1.0, time=1.0) -> RangeLog:
    inputs = log.inputs * [time, speed, yaw_rate]
    return dataclasses.replace(log, inputs=inputs, ranges=log.ranges * [time, 1.0, 1.0])


def _refused(tmp_path, capsys, log) -> str:
    return refused(tmp_path, capsys, log, "inputs.csv")


def test_a_speed_in_mm_per_s_is_refused_by_the_path_it_dead_reckons(tmp_path, capsys):
    error = _refused(tmp_path, capsys, _scaled(_robot_log(), speed=1000.0))
    assert "column speed: the path dead-reckoned from it spans " in error
    assert "the speed must be in m/s and the times in seconds" in error
    check_odometry_units(_robot_log())  # in m/s: accepted


def test_times_in_ms_are_refused_as_the_speed_is(tmp_path, capsys):
    error = _refused(tmp_path, capsys, _scaled(_robot_log(), time=1000.0))
    assert "column speed: the path dead-reckoned" in error


def test_a_yaw_rate_in_deg_per_s_is_beyond_any_gyroscopes_range(tmp_path, capsys):
    error = _refused(tmp_path, capsys, _scaled(_robot_log(), yaw_rate=np.degrees(1.0)))
    assert "row 2, column yaw_rate: 45.84 is beyond any gyroscope's range" in error
    assert "must be in rad/s" in error


def test_the_bound_is_far_from_real_odometry_and_its_drift():
    """The dead-reckoned paths of Plaza1 and Plaza2 (a vehicle's wheel odometry over 32 and 7
    minutes, drift included) span a third to two fifths of the region their ranges allow, 25 to 30 times inside
    the bound; a scale error of 5 % and a yaw rate's bias of 0.01 rad/s on the robot stay
    inside."""
    for name in ("plaza1", "plaza2"):
        check_odometry_units(load_builtin(name))
    log = _robot_log()
    drifting = dataclasses.replace(log, inputs=log.inputs * [1.0, 1.05, 1.0] + [0.0, 0.0, 0.01])
    check_odometry_units(drifting)
    with pytest.raises(QuadobsError, match="column speed"):
        check_odometry_units(_scaled(log, speed=2.0 * ODOMETRY_SPAN_RATIO * 3.0))


def test_a_long_route_among_many_anchors_and_a_gap_in_the_odometry_are_not_refused():
    """A robot driving 1.5 km down a corridor at 1 m/s, anchors every 30 m heard to 40 m: its
    path spans far more than twice a range, within the anchors' extent. The stadium's odometry
    and ranges silent for 200 s while it drives straight on (the replay holds the last input
    across the gap, and says so): no distance is dead-reckoned across it, where 160 m at the
    last speed would be ten times the room."""
    xs = np.arange(0.0, 1501.0, 30.0)
    corridor = np.column_stack([xs, np.where(np.arange(xs.size) % 2 == 0, 2.0, -2.0)])
    t = np.arange(0.0, 1500.0, 0.05)
    inputs = np.column_stack([t, 1.0 + 0 * t, 0 * t])
    t_r = np.arange(0.02, 1499.0, 0.1)
    p = np.column_stack([t_r, 0 * t_r])
    d = np.linalg.norm(p[:, None, :] - corridor[None], axis=2)
    h = np.array([np.flatnonzero(row < 40.0)[k % 2] for k, row in enumerate(d)])
    ranges = np.column_stack([t_r, h, d[np.arange(t_r.size), h]])
    check_odometry_units(RangeLog("corridor", np.arange(xs.size), corridor, ranges, inputs, 0.0))
    log = _robot_log()
    k = int(np.flatnonzero((log.inputs[:, 0] > 30.0) & (log.inputs[:, 2] == 0.0))[0])
    after = log.inputs[:, 0] > log.inputs[k, 0]  # 200 s of silence while driving straight on
    inputs, ranges = log.inputs.copy(), log.ranges.copy()
    inputs[after, 0] += 200.0
    ranges[ranges[:, 0] > log.inputs[k, 0], 0] += 200.0
    check_odometry_units(dataclasses.replace(log, inputs=inputs, ranges=ranges))


def test_a_sentinel_range_leaves_the_bound_where_it_was():
    """One range of 9999 (a radio's sentinel) among the robot's: the reach is a median over the
    anchors, so a speed in mm/s is still refused."""
    log = _robot_log()
    ranges = log.ranges.copy()
    ranges[10, 2] = 9999.0
    with pytest.raises(QuadobsError, match="column speed"):
        check_odometry_units(_scaled(dataclasses.replace(log, ranges=ranges), speed=1000.0))
