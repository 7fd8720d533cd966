"""A replay's figures as the field reports them: burn-in, horizontal/vertical split, divergence, TUM files read by evo."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.testbed.logs import RangeLog, write_log
from quadobs.testbed.logs.replay import run_replay

BEACONS = np.array([[-20.0, -15.0, 0.5], [25.0, -20.0, 6.0], [20.0, 25.0, 0.5], [-15.0, 20.0, 8.0]])
R, W = 10.0, 0.2


def position(t):
    return np.column_stack([R * np.cos(W * t), R * np.sin(W * t), 2.0 + np.sin(0.5 * t)])


def velocity(t):
    return np.column_stack([-R * W * np.sin(W * t), R * W * np.cos(W * t), 0.5 * np.cos(0.5 * t)])


def helix_log(duration=20.0, rate=100.0, spike=None) -> RangeLog:
    """A helix in space: an exact accelerometer (navigation frame) at ``rate``, exact ranges
    round-robin at 20 Hz; ``spike``: the accelerometer's row at the ``spike``-th range's time
    read 1e150 m/s^2 (a corrupt sample, which drives every filter to overflow)."""
    t = np.arange(0.0, duration, 1.0 / rate)
    acc = np.column_stack(
        [-R * W**2 * np.cos(W * t), -R * W**2 * np.sin(W * t), -0.25 * np.sin(0.5 * t)]
    )
    t_r = np.arange(0.02, duration - 0.1, 0.05)
    h = np.arange(t_r.size) % 4
    ranges = np.column_stack([t_r, h, np.linalg.norm(position(t_r) - BEACONS[h], axis=1)])
    if spike is not None:
        acc[int(np.searchsorted(t, ranges[spike, 0] - 1e-9))] = 1e150
    truth = np.column_stack([t, position(t), velocity(t)])
    return RangeLog(
        "helix",
        np.arange(4),
        BEACONS,
        ranges,
        np.column_stack([t, acc]),
        math.nan,
        truth,
        input_kind="imu",
        truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"),
    )


SETUP = {"range_sigma": 0.05, "q_imu": 1e-3}


def test_the_burn_in_drops_the_transient_and_the_tum_files_give_evos_rmse(tmp_path):
    pytest.importorskip("evo")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    log = helix_log()
    whole = run_replay(log, dt=0.01, initial_offset=5.0, setup_options=SETUP, progress=False)
    s = run_replay(
        log,
        dt=0.01,
        initial_offset=5.0,
        setup_options=SETUP,
        burn_in=5.0,
        export_tum=tmp_path / "tum",
    )
    for name in ("augmented", "ekf"):
        e, w = s["estimators"][name], whole["estimators"][name]
        assert e["diverged"] is None and e["burn_in"] == 5.0
        assert e["rmse"] < w["rmse"] and e["rmse"] < 0.05  # the 5 m start excluded
        assert e["rmse"] ** 2 == pytest.approx(e["rmse_horizontal"] ** 2 + e["rmse_vertical"] ** 2)
        ref = file_interface.read_tum_trajectory_file(str(tmp_path / "tum" / "truth.tum"))
        est = file_interface.read_tum_trajectory_file(str(tmp_path / "tum" / f"{name}.tum"))
        ref, est = sync.associate_trajectories(ref, est, max_diff=1e-6)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(e["rmse"], rel=1e-9)
        assert ref.num_poses == e["samples"]
    assert ref.timestamps[0] == pytest.approx(log.start + 5.0)
    assert s["tum"]["files"] == ["truth.tum", "augmented.tum", "ekf.tum", "ekf-bias.tum"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tum"]  # no staging folder left
    blind = run_replay(  # a log without a truth: each trajectory after the burn-in, no truth
        dataclasses.replace(log, truth=None, truth_columns=()),
        dt=0.01,
        initial_offset=5.0,
        setup_options=SETUP,
        burn_in=5.0,
        export_tum=tmp_path / "blind",
    )
    assert blind["tum"]["files"] == ["augmented.tum", "ekf.tum", "ekf-bias.tum"]
    assert sorted(p.name for p in (tmp_path / "blind").iterdir()) == sorted(blind["tum"]["files"])
    track = file_interface.read_tum_trajectory_file(str(tmp_path / "blind" / "ekf.tum"))
    mine = file_interface.read_tum_trajectory_file(str(tmp_path / "tum" / "ekf.tum"))
    assert track.num_poses == mine.num_poses  # the helix's truth covers every row
    np.testing.assert_array_equal(track.timestamps, mine.timestamps)
    # started at the anchors' centroid (no truth to start from), it ends where the other does
    np.testing.assert_allclose(track.positions_xyz[-100:], mine.positions_xyz[-100:], atol=0.05)


def test_a_diverged_estimator_is_reported_and_has_no_figures(tmp_path, capsys):
    folder = write_log(helix_log(10.0, spike=40), tmp_path / "log")
    code = main(
        ["replay", str(folder), "--dt", "0.01", "--calibrate", "none", "--no-progress"]
        + ["--tune", "range_sigma=0.05", "--tune", "q_imu=1e-3", "--initial-offset", "5"]
        + ["--summary", str(tmp_path / "s.json"), "--export-tum", str(tmp_path / "tum")]
    )
    out = capsys.readouterr().out
    s = json.loads((tmp_path / "s.json").read_text())
    diverged = {n: e for n, e in s["estimators"].items() if e["diverged"] is not None}
    assert code == 0 and diverged, out
    width = max(10, *(len(n) for n in s["estimators"]))  # the printed names' column
    for name, e in diverged.items():
        assert e["rmse"] is None and e["max_error"] is None and e["final_position_error"] is None
        spike = 0.02 + 40 * 0.05  # the time of the sample of 1e150 m/s^2: from its step on
        assert spike <= e["diverged"]["t"] <= spike + 0.02
        assert f"{name}: DIVERGED at step" in out and f"{name:{width}s} rmse invalid" in out
        assert not (tmp_path / "tum" / f"{name}.tum").exists()


def test_the_field_options_are_checked_before_the_replay(tmp_path, capsys):
    folder = write_log(helix_log(2.0), tmp_path / "log")
    base = ["replay", str(folder), "--dt", "0.01", "--calibrate", "none", "--no-progress"]
    assert main(base + ["--burn-in", "-1"]) == 2
    assert "--burn-in: expected a non-negative number of seconds" in capsys.readouterr().err
    (tmp_path / "tum").mkdir()
    (tmp_path / "tum" / "notes.txt").write_text("mine")
    assert main(base + ["--export-tum", str(tmp_path / "tum")]) == 2
    assert "holds 'notes.txt'" in capsys.readouterr().err
    assert (
        main(
            base
            + ["--export-tum", str(tmp_path / "t2"), "--summary", str(tmp_path / "t2" / "s.json")]
        )
        == 2
    )
    assert "holds the output" in capsys.readouterr().err


def test_an_error_beyond_the_anchors_extent_is_marked_and_the_burn_in_printed(tmp_path, capsys):
    """An estimator whose final error exceeds the anchors' extent is marked in the summary and
    its printed row. A truth moved into another frame gives such errors; the command line
    refuses that truth before any work (``check_truth_units``), so the far case is replayed by
    the library and its rows printed by the command line's printer."""
    from quadobs.cli import _print_replay_rows
    from quadobs.testbed.logs.replay import anchor_extent

    log = helix_log(4.0)
    extent = max(np.linalg.norm(a - b) for a in BEACONS for b in BEACONS)
    assert anchor_extent(BEACONS) == pytest.approx(extent, rel=1e-15)
    moved = log.truth.copy()
    moved[:, 1] += 2.0 * extent  # a truth in another frame: every error about twice the extent
    far = dataclasses.replace(log, truth=moved)
    options = {"range_sigma": 0.05, "q_imu": 1e-3}
    kwargs = dict(dt=0.01, burn_in=2.0, estimators=["augmented", "ekf"], setup_options=options)
    s = run_replay(far, **kwargs)
    _print_replay_rows(s, far)
    assert "final error larger than the anchors' extent, 56.6 m" in capsys.readouterr().out
    for name in ("augmented", "ekf"):
        assert s["estimators"][name]["within_extent"] is False
    assert main(["replay", str(write_log(far, tmp_path / "far")), "--calibrate", "none"]) == 2
    assert "truth.csv: each range differs from the truth's distance" in capsys.readouterr().err
    base = ["--dt", "0.01", "--calibrate", "none", "--no-progress", "--burn-in", "2"]
    base += ["--tune", "range_sigma=0.05", "--tune", "q_imu=1e-3", "--estimators", "augmented,ekf"]
    near, summary = write_log(log, tmp_path / "near"), tmp_path / "near.json"
    assert main(["replay", str(near), *base, "--summary", str(summary)]) == 0
    out = capsys.readouterr().out
    s = json.loads(summary.read_text())
    assert s["anchor_extent"] == pytest.approx(extent, rel=1e-12)
    for name in ("augmented", "ekf"):
        assert s["estimators"][name]["within_extent"] is True
        assert f"{name:10s} rmse after 2 s " in out
    assert "final error larger than the anchors' extent" not in out


def test_an_estimators_own_record_is_reported_on_the_logs_time_from_its_start(tmp_path, capsys):
    """A replayed filter keeps the log's own clock (here unix seconds): its record of having
    given up (a lock-out, a guard) and of a start-up without a fix are reported from the log's
    start, the step the row at that time, as the sink's own divergence is, never ``t =
    1.7e+09 s`` at step 17000000075."""
    from types import SimpleNamespace

    from quadobs.testbed.divergence import given_up, startup_record

    t0 = 1.7e9
    lock = SimpleNamespace(
        diverged={"time": t0 + 7.5, "step": int(round((t0 + 7.5) / 0.1)), "reason": "guard"},
        locked_at_end=None,
    )
    entry = given_up(SimpleNamespace(lockout=lock), t0, 0.1)
    assert entry == {"step": 75, "t": pytest.approx(7.5), "reason": "guard"}
    assert given_up(SimpleNamespace(lockout=lock))["t"] == t0 + 7.5  # a simulated run's clock
    lock.diverged["step"] = -1  # a time without a step stays without one
    assert given_up(SimpleNamespace(lockout=lock), t0, 0.1)["step"] == -1
    start = SimpleNamespace(fix_pending=False, fix_abandoned=t0 + 2.0, dt=0.1, fixes=[])
    record = startup_record(start, t0, 0.1)
    assert record is not None and record["t"] == pytest.approx(2.0) and record["step"] == 20
    shifted = helix_log(10.0, spike=40)
    shifted = dataclasses.replace(
        shifted,
        ranges=shifted.ranges + [t0, 0, 0],
        inputs=shifted.inputs + [t0, 0, 0, 0],
        truth=shifted.truth + np.r_[t0, np.zeros(6)],
    )
    folder = write_log(shifted, tmp_path / "log")
    code = main(
        ["replay", str(folder), "--dt", "0.01", "--calibrate", "none", "--no-progress"]
        + ["--tune", "range_sigma=0.05", "--tune", "q_imu=1e-3", "--initial-offset", "5"]
        + ["--summary", str(tmp_path / "s.json")]
    )
    out = capsys.readouterr().out
    s = json.loads((tmp_path / "s.json").read_text())
    diverged = {n: e["diverged"] for n, e in s["estimators"].items() if e["diverged"]}
    assert code == 0 and diverged, out
    for d in diverged.values():
        assert 0.0 <= d["t"] <= 10.0 and d["step"] == pytest.approx(d["t"] / 0.01, abs=1)
    two = shifted.ranges[shifted.ranges[:, 1] < 2]  # two anchors: no fix in space
    exact = helix_log(10.0).inputs + [t0, 0, 0, 0]  # without the corrupt sample
    folder = write_log(
        dataclasses.replace(shifted, ranges=two, range_std=None, inputs=exact), tmp_path / "two"
    )
    code = main(
        ["replay", str(folder), "--dt", "0.01", "--calibrate", "none", "--no-progress"]
        + ["--estimators", "ekf-bias", "--summary", str(tmp_path / "two.json")]
    )
    out = capsys.readouterr().out
    record = json.loads((tmp_path / "two.json").read_text())["estimators"]["ekf-bias"]["startup"]
    assert code == 0 and 0.0 <= record["t"] <= 10.0, out
    assert record["step"] == pytest.approx(record["t"] / 0.01, abs=1)
    assert "NO START-UP FIX (t = " in out and "t = 1.7e+09" not in out


def test_a_truth_on_another_clock_is_said_before_the_replay():
    """The helix's truth stamped 2 s late: its distances agree with the ranges moved by 2 s,
    and a note says so, as for 1.5 s early and, beyond the fine search, 7 s late and 6.1 s
    early; on its own clock, and stamped 0.1 s late (within the lags not said), nothing is
    said."""
    from quadobs.testbed.logs.replay import replayable_log, truth_lag_note

    log = helix_log(20.0)
    noisy = log.ranges.copy()
    noisy[:, 2] += 0.1 * np.random.default_rng(3).standard_normal(noisy.shape[0])  # a radio's
    log = dataclasses.replace(log, ranges=noisy)
    assert truth_lag_note(log) is None
    cases = [(2.0, "stamped 2.00 s late"), (-1.5, "stamped 1.50 s early"), (0.1, None)]
    for lag, said in [*cases, (7.0, "stamped 7.00 s late"), (-6.1, "stamped 6.10 s early")]:
        moved = dataclasses.replace(log, truth=log.truth + np.r_[lag, np.zeros(6)])
        note = truth_lag_note(moved)
        assert (note is None) if said is None else (said in note and "ranges' clock" in note)
        assert note is None or "a lever arm" in note  # a tag ahead of the truth's point looks so
    late = dataclasses.replace(log, truth=log.truth + np.r_[2.0, np.zeros(6)])
    assert any("stamped 2.00 s late" in n for n in replayable_log(late)[1])


def test_a_lag_is_said_over_anchors_mapped_by_chance_and_a_truth_mostly_off_the_ranges():
    """Where a truth seconds late also fits some anchors' ranges to others' positions, the
    lag is said when no relabelling of ids gives that mapping (two anchors sent to one) or
    when it fits at least as well; a truth covering under half of the ranges' span is said."""
    from quadobs.testbed.logs.replay import _lag_explains, truth_span_note

    lag = (10.0, 0.12, 1.4, False)
    onto_one = [(0, 1, 0.2, 1.0), (4, 1, 0.3, 1.2)]
    swapped = [(0, 1, 0.08, 1.0), (1, 0, 0.1, 1.1)]
    assert _lag_explains(onto_one, lag) and not _lag_explains(swapped, lag)
    assert _lag_explains(swapped, (10.0, 0.08, 1.4, False))  # the lag fits as well
    assert not _lag_explains(swapped, None) and _lag_explains([], lag)
    assert not _lag_explains([], None)
    log = helix_log(20.0)
    assert truth_span_note(log) is None
    late = dataclasses.replace(log, truth=log.truth + np.r_[15.0, np.zeros(6)])
    note = truth_span_note(late)
    assert note.startswith("truth.csv covers 4.87 s") and "of the measurements' 19.9" in note
    assert note.endswith(
        "every estimator is scored there alone; is the truth on the ranges' clock?"
    )


def test_ranges_measured_to_another_anchor_than_their_id_names_are_said():
    """The helix's ranges of anchors 0 and 1 exchanged (their ids swapped in ranges.csv): each
    fits the other's position against the truth, and a note names both; the log as written
    says nothing."""
    from quadobs.testbed.logs.replay import replayable_log, truth_anchor_note

    log = helix_log(20.0)
    ranges = log.ranges.copy()
    ranges[:, 2] += 0.1 * np.random.default_rng(4).standard_normal(ranges.shape[0])  # a radio's
    log = dataclasses.replace(log, ranges=ranges.copy())
    assert truth_anchor_note(log) is None
    ranges[:, 1] = np.choose(ranges[:, 1].astype(int), [1, 0, 2, 3])
    note = truth_anchor_note(dataclasses.replace(log, ranges=ranges))
    assert note is not None and "anchor 0 fit anchor 1's position" in note
    assert "of anchor 1 fit anchor 0's position" in note and "ids name the anchors" in note
    swapped = dataclasses.replace(log, ranges=ranges)
    assert any("fit anchor 1's position" in n for n in replayable_log(swapped)[1])
