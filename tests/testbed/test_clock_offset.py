"""The clock offset between a log's inputs and its ranges: moved onto one clock, searched from the
log's held-out ranges (quadobs.testbed.logs.clock_offset)."""

import json

import numpy as np
import pytest
from test_replay_in_time import ANCHORS_3D, _ranges

from quadobs.testbed.logs import RangeLog, write_log
from quadobs.testbed.logs.clock_offset import (
    HELD_MIN,
    estimate_clock_offset,
    held_out_count,
    offset_step,
    with_input_offset,
)


def _swinging_log(late: float, seconds: float = 16.0, seed: int = 4):
    """A tag swinging on a circle (radius 1 m, 2.5 rad/s: 6.25 m/s^2, a jerk of 15.6 m/s^3), its
    navigation-frame accelerometer at 200 Hz stamped ``late`` seconds late, ranges (0.02 m) at
    25 Hz in turn to five anchors: between two ranges the acceleration carries most of what the
    filter knows, so an offset of the inputs shows in the ranges it predicts."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 0.005)
    p, v, a = _swing(t)
    t_r = np.arange(0.0025, seconds, 0.04)
    ranges = _ranges(t_r, ANCHORS_3D, _swing(t_r)[0], rng, 0.02)
    return RangeLog(
        "swinging", np.arange(ANCHORS_3D.shape[0]), ANCHORS_3D, ranges,
        np.column_stack([t + late, a]), float("nan"), np.column_stack([t, p, v]),
        input_kind="imu", truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"),
        range_std=np.full(ranges.shape[0], 0.02),
    )  # fmt: skip


def _swing(t, w=2.5, r=1.0):
    """Position, velocity and acceleration at ``t`` of :func:`_swinging_log`'s tag."""
    c, s, cz, sz = np.cos(w * t), np.sin(w * t), np.cos(0.5 * w * t), np.sin(0.5 * w * t)
    p = np.column_stack([r * c + 3.0, r * s + 3.0, 0.3 * sz + 1.5])
    v = np.column_stack([-r * w * s, r * w * c, 0.15 * w * cz])
    a = np.column_stack([-r * w * w * c, -r * w * w * s, -0.075 * w * w * sz])
    return p, v, a


def test_with_input_offset_moves_the_inputs_and_the_attitude_only():
    log = _swinging_log(0.05, seconds=2.0)
    att = np.column_stack(
        [log.inputs[:, 0], np.tile([1.0, 0.0, 0.0, 0.0], (log.inputs.shape[0], 1))]
    )
    log = RangeLog(**{**log.__dict__, "attitude": att})
    moved = with_input_offset(log, 0.05)
    np.testing.assert_allclose(moved.inputs[:, 0], log.inputs[:, 0] - 0.05)
    np.testing.assert_allclose(moved.attitude[:, 0], log.attitude[:, 0] - 0.05)
    np.testing.assert_array_equal(moved.inputs[:, 1:], log.inputs[:, 1:])
    np.testing.assert_array_equal(moved.ranges, log.ranges)
    np.testing.assert_array_equal(moved.truth, log.truth)
    assert with_input_offset(log, 0.0) is log
    assert offset_step(log) == pytest.approx(0.04)  # the ranges, coarser than the inputs


@pytest.mark.parametrize(("late", "seed"), [(0.0, 4), (0.1, 4), (0.1, 5)])
def test_a_known_offset_is_found_and_none_is_kept_where_there_is_none(late, seed):
    """Within the finest grid step, ``h / 4`` (two halvings): 10 ms here."""
    log = _swinging_log(late, seed=seed)
    found = estimate_clock_offset(log, setup_options={"q_imu": 0.01, "range_sigma": 0.02})
    assert abs(found.offset - late) <= 0.25 * offset_step(log) + 1e-9, found.reason
    if late:
        assert found.test["significantly_better"], found.reason
        assert found.scores[found.offset] < 0.5 * found.scores[0.0]
    assert f"{found.offset * 1e3:+.1f} ms" in found.reason


def test_the_replay_applies_and_reports_the_clock_offset(tmp_path, capsys):
    from quadobs import cli

    write_log(_swinging_log(0.1, seconds=4.0), tmp_path / "log")
    summaries = {}
    for offset in ("0", "0.1"):
        path = tmp_path / f"s{offset}.json"
        argv = ["replay", str(tmp_path / "log"), "--calibrate", "none", "--no-progress"]
        argv += ["--estimators", "ekf", "--clock-offset", offset, "--summary", str(path)]
        argv += ["--initial-offset", "0.5", "--burn-in", "2"]
        assert cli.main(argv) == 0
        summaries[offset] = json.loads(path.read_text())
    given = summaries["0.1"]["calibration"]["clock_offset"]
    assert given["offset"] == 0.1 and "given" in given["reason"]
    assert summaries["0.1"]["calibration"]["reason"] == given["reason"]  # --calibrate none
    rmse = {k: s["estimators"]["ekf"]["rmse"] for k, s in summaries.items()}
    assert rmse["0.1"] < 0.5 * rmse["0"], rmse


def test_a_clock_offset_that_is_not_a_number_is_refused(tmp_path, capsys):
    from quadobs import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main(["replay", str(tmp_path), "--clock-offset", "soon"])
    assert exit_.value.code == 2
    assert "expected seconds or auto" in capsys.readouterr().err


def test_too_few_held_out_ranges_for_the_paired_test_are_not_searched():
    """3.4 s: 43 ranges at least the search's reach inside the inputs, 4 of them held out and
    scored, fewer than the paired test's three blocks of two: no replay, "too few ranges"."""
    log = _swinging_log(0.1, seconds=3.4)
    found = estimate_clock_offset(log, setup_options={"q_imu": 0.01, "range_sigma": 0.02})
    assert found.offset == 0.0 and found.scores == {}, found.reason
    assert "too few ranges" in found.reason and f"needs {HELD_MIN}" in found.reason
    t = np.arange(20.0)  # held: the 3rd of every 5 (2, 7, 12, 17), scored from 7
    assert held_out_count(t, 7.0) == 3 and held_out_count(t[::-1], 0.0) == 4


@pytest.mark.parametrize(
    ("offset", "says"),
    [("-30", "none is left to replay"), ("1e6", "none is left to replay"), ("3", "too few")],
)
def test_a_clock_offset_that_leaves_too_few_ranges_is_refused_first(
    tmp_path, capsys, monkeypatch, offset, says
):
    from quadobs import cli
    from quadobs.testbed.logs import calibration

    def refused(*args, **kwargs):
        raise AssertionError("the calibration ran before the refusal")

    monkeypatch.setattr(calibration, "calibrate", refused)
    write_log(_swinging_log(0.0, seconds=4.0), tmp_path / "log")
    argv = ["replay", str(tmp_path / "log"), "--no-progress", "--clock-offset", offset]
    assert cli.main([*argv, "--summary", str(tmp_path / "s.json")]) == 2
    err = capsys.readouterr().err
    assert f"--clock-offset {float(offset):g}: the inputs moved to" in err and says in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "s.json").exists()


@pytest.mark.parametrize("offset", ["0.1", "auto"])
def test_a_clock_offset_is_refused_with_export(tmp_path, capsys, offset):
    from quadobs import cli

    write_log(_swinging_log(0.0, seconds=2.0), tmp_path / "log")
    argv = ["replay", str(tmp_path / "log"), "--export", str(tmp_path / "copy")]
    assert cli.main([*argv, "--clock-offset", offset]) == 2
    assert "--clock-offset: does not apply with --export" in capsys.readouterr().err
    assert not (tmp_path / "copy").exists()
