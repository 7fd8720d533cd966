"""Failure behaviour of a run: interrupts, errors inside the loop, unwritable outputs, determinism."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from quadobs import QuadobsError, load_scenario
from quadobs.cli import main
from quadobs.recording import list_entities, read_series, read_text_log
from quadobs.testbed.episode import WALL_CLOCK_KEYS, run_episode

RERUN = str(Path(sys.executable).parent / "rerun")
ROOT = Path(__file__).resolve().parents[2]


def _verify(rrd: Path) -> None:
    proc = subprocess.run([RERUN, "rrd", "verify", str(rrd)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_mid_run_leaves_a_verified_recording_of_every_step(tmp_path, cli_process, sig):
    """SIGINT (Ctrl-C) or SIGTERM during an hour-long run: exit 130, a valid .rrd with steps 0..k-1, the summary of k steps."""
    rrd, js = tmp_path / "run.rrd", tmp_path / "run.json"
    proc = cli_process(
        "run",
        "ifac2021",
        "--duration",
        "3600",
        "--no-progress",
        "--out",
        str(rrd),
        "--summary",
        str(js),
    )
    deadline = time.monotonic() + 120
    # wait until the loop has sent a few blocks of rows to the file
    while not any(
        p.stat().st_size > 200_000 for p in tmp_path.glob(".run.rrd.*.partial")
    ):  # the staging file
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the run did not start writing"
        time.sleep(0.05)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "[INTERRUPTED]" in out
    summary = json.loads(js.read_text())
    k = summary["physics_steps"]
    assert summary["interrupted"] is True and 0 < k < 3_600_000
    assert summary["duration"] == pytest.approx(k * 1e-3)
    _verify(rrd)
    steps = read_series(rrd, "errors/augmented/position/norm")["step"]
    np.testing.assert_array_equal(steps, np.arange(k))
    events = read_text_log(rrd, "events")
    assert any(s == k and "interrupted" in text for s, _, _, text in events)


def test_error_inside_the_loop_closes_the_recording_and_propagates(tmp_path, monkeypatch):
    """An estimator failing at step N (past a block boundary): the error reaches the caller, the previous
    .rrd and summary are untouched, and the run's staging file (``.err.rrd.<pid>-<hex>.partial``) verifies
    and holds steps 0..N-1, with the error in its event log; no summary is written."""
    from quadobs.estimators.augmented import AugmentedObserver

    N = 10_000
    calls = [0]
    original = AugmentedObserver.step_and_record

    def failing(self, u, y, out):
        if calls[0] == N:
            raise FloatingPointError("injected failure")
        calls[0] += 1
        return original(self, u, y, out)

    monkeypatch.setattr(AugmentedObserver, "step_and_record", failing)
    rrd, js = tmp_path / "err.rrd", tmp_path / "err.json"
    rrd.write_bytes(b"previous recording")
    with pytest.raises(FloatingPointError, match="injected failure"):
        run_episode(load_scenario("ifac2021", duration=15.0), out=rrd, summary_path=js)
    assert not js.exists() and rrd.read_bytes() == b"previous recording"
    (rrd,) = tmp_path.glob(".err.rrd.*.partial")
    _verify(rrd)
    for entity in (
        "errors/augmented/position/norm",
        "observer/augmented/nis",
        "measurements/accelerometer",
    ):
        steps = read_series(rrd, entity)["step"]
        np.testing.assert_array_equal(steps, np.arange(N))
    events = read_text_log(rrd, "events")
    assert any(
        s == N and level == "ERROR" and "injected failure" in text for s, _, level, text in events
    )


@pytest.mark.parametrize("seam", ["commit", "after_flush", "next_block"])
def test_interrupt_at_a_block_boundary_records_each_step_once(tmp_path, monkeypatch, seam):
    """Ctrl-C landing in the end-of-block work (counting the sensor events, after the block's
    rows were sent, as the next block starts): steps 0..1023 (the first block) are each recorded exactly once."""
    import tqdm

    from quadobs.testbed.worlds import BlockStepper

    class Stop:
        def __init__(self, *args, **kwargs):
            pass

        def update(self, n):
            if seam == "after_flush":
                raise KeyboardInterrupt

        def close(self):
            pass

    calls = {"commit": 0, "begin": 0}
    commit, begin, begin_ahead = BlockStepper.commit, BlockStepper.begin, BlockStepper.begin_ahead

    def stop_commit(self, rows):
        calls["commit"] += 1
        if seam == "commit" and calls["commit"] == 1:
            raise KeyboardInterrupt
        return commit(self, rows)

    def stopping(
        start,
    ):  # a block starts with begin, or with begin_ahead where its physics ran ahead
        def stop_begin(self, *args, **kwargs):
            calls["begin"] += 1
            if seam == "next_block" and calls["begin"] == 2:
                raise KeyboardInterrupt
            return start(self, *args, **kwargs)

        return stop_begin

    monkeypatch.setattr(tqdm, "tqdm", Stop)
    monkeypatch.setattr(BlockStepper, "commit", stop_commit)
    monkeypatch.setattr(BlockStepper, "begin", stopping(begin))
    monkeypatch.setattr(BlockStepper, "begin_ahead", stopping(begin_ahead))
    rrd = tmp_path / "seam.rrd"
    result = run_episode(load_scenario("ifac2021-outliers", duration=12.0), out=rrd, progress=True)
    summary = result.summary
    assert (
        summary["interrupted"] is True and summary["physics_steps"] == 1024
    )  # the first block (block_count)
    _verify(rrd)
    for entity in ("errors/augmented/position/norm", "measurements/dropped"):
        np.testing.assert_array_equal(read_series(rrd, entity)["step"], np.arange(1024))
    dropped = read_series(rrd, "measurements/dropped")["values"]
    assert summary["measurements"]["dropped"] == int(np.ravel(dropped)[-1]) > 0


@pytest.mark.parametrize("where", ["before", "after"])
def test_interrupt_inside_the_excitation_monitor_counts_each_step_once(monkeypatch, where):
    """Ctrl-C while the monitor processes a chunk (at t = 28 s, inside the second coast of
    `degenerate`, where the measure is low): the open low segment ends at the stop, not a
    chunk later, and nothing is fed twice."""
    from quadobs.observability.excitation import ExcitationMonitor

    chunk_done = ExcitationMonitor._chunk_done

    def stop_at_28s(self):
        if self.steps == 28_000 and where == "before":
            raise KeyboardInterrupt
        out = chunk_done(self)
        if self.steps == 28_000:
            raise KeyboardInterrupt
        return out

    monkeypatch.setattr(ExcitationMonitor, "_chunk_done", stop_at_28s)
    summary = run_episode(load_scenario("degenerate")).summary
    assert summary["interrupted"] is True and summary["physics_steps"] == 28_000
    segments = summary["excitation"]["low_segments"]
    assert segments[-1][0] < 28.0 and segments[-1][1] == pytest.approx(28.0)


def test_deferred_interrupts_hold_a_signal_until_the_section_ends():
    from quadobs.errors import deferred_interrupts

    reached = []
    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupts():
            with deferred_interrupts():  # nested sections: delivered once, at the outer end
                signal.raise_signal(signal.SIGINT)
                reached.append("inner")
            reached.append("outer")
    assert reached == ["inner", "outer"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    got = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        with deferred_interrupts():
            signal.raise_signal(signal.SIGTERM)
            assert got == []
        assert got == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_stop_during_a_send_leaves_every_series_with_each_row_once(tmp_path):
    """Ctrl-C arriving while the recorder sends a block's series: all of them get the block, once."""
    from quadobs.recording import Recorder

    rrd = tmp_path / "send.rrd"
    rec = Recorder(rrd, recording_id="send", capacity=100)
    series = [rec.series(f"s/{i}", 1) for i in range(4)]
    send = rec.rec.send_columns
    calls = [0]

    def interrupted_send(*args, **kwargs):
        calls[0] += 1
        if calls[0] == 2:
            signal.raise_signal(signal.SIGINT)
        return send(*args, **kwargs)

    rec.rec.send_columns = interrupted_send
    rows = rec.rows(np.arange(100), np.arange(100) * 1e-3)
    for i, s in enumerate(series):
        s.buf[rows, 0] = i
    with pytest.raises(KeyboardInterrupt):
        rec.flush()
    assert rec.n == 0 and calls[0] == 4
    rec.close()
    _verify(rrd)
    for i in range(4):
        got = read_series(rrd, f"s/{i}")
        np.testing.assert_array_equal(got["step"], np.arange(100))


@pytest.mark.parametrize("which", ["out", "summary"])
def test_unwritable_output_fails_before_the_simulation(tmp_path, monkeypatch, which):
    """An output under a regular file cannot be written: a QuadobsError naming the path, raised before
    MuJoCo is even set up, and no file is created."""
    import quadobs.testbed.worlds

    def no_simulation(*a, **k):
        raise AssertionError("the simulation started")

    monkeypatch.setattr(quadobs.testbed.worlds, "VehicleSim", no_simulation)
    blocker = tmp_path / "file"
    blocker.write_text("")
    paths = {"out": tmp_path / "ok.rrd", "summary": tmp_path / "ok.json"}
    paths[which] = blocker / "sub" / ("x.rrd" if which == "out" else "x.json")
    with pytest.raises(QuadobsError, match=r"output path .*x\.(rrd|json).*cannot be written"):
        run_episode(
            load_scenario("ifac2021", duration=1.0), out=paths["out"], summary_path=paths["summary"]
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_cli_unwritable_output_exits_2_and_creates_nothing(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    bad = tmp_path / "file" / "x.rrd"
    code = main(
        [
            "run",
            "ifac2021",
            "--no-progress",
            "--out",
            str(bad),
            "--summary",
            str(tmp_path / "s.json"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "x.rrd" in err and "cannot be written" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    code = main(["run", "ifac2021", "--no-progress", "--out", str(tmp_path)])
    assert code == 2 and "is a directory" in capsys.readouterr().err


def test_json_writes_are_atomic(tmp_path, monkeypatch):
    """A failure while writing a summary leaves the previous file intact and no temporary file behind."""
    import quadobs.testbed.episode as runner

    path = tmp_path / "s.json"
    runner.write_json_atomic(path, {"a": 1})
    with pytest.raises(ValueError):
        runner.write_json_atomic(path, {"a": float("nan")})  # refused mid-write (allow_nan=False)
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["s.json"]


def test_same_scenario_and_seed_are_bit_identical_across_processes(tmp_path):
    """Two processes (different hash seeds), the same scenario and seed: identical summaries apart from
    the wall-clock fields and the file name, and identical recorded values, entity by entity.

    The .rrd files themselves differ in bytes: rerun stamps each chunk and row with ids
    generated at write time. Their contents are compared instead.
    """
    runs = []
    for i, hashseed in enumerate(["1", "2"]):
        d = tmp_path / f"p{i}"
        args = [
            "run",
            "ifac2021-outliers",
            "--duration",
            "3",
            "--seed",
            "5",
            "--estimators",
            "augmented,ekf",
            "--no-progress",
            "--out",
            str(d / "run.rrd"),
            "--summary",
            str(d / "run.json"),
        ]
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONHASHSEED=hashseed)
        subprocess.run(
            [sys.executable, "-m", "quadobs.cli", *args],
            cwd=ROOT,
            env=env,
            check=True,
            capture_output=True,
        )
        runs.append(d)
    summaries = []
    for d in runs:
        s = json.loads((d / "run.json").read_text())
        for key in (*WALL_CLOCK_KEYS, "recording"):
            s.pop(key)
        summaries.append(s)
    assert summaries[0] == summaries[1]
    assert (
        summaries[0]["measurements"]["outliers_injected"] > 0
        and summaries[0]["measurements"]["dropped"] > 0
    )
    a, b = runs[0] / "run.rrd", runs[1] / "run.rrd"
    entities = list_entities(a)
    assert entities == list_entities(b) and len(entities) > 20
    compared = 0
    for entity in entities:
        try:
            sa = read_series(a, entity)
        except QuadobsError:  # no numeric series there (text log, boxes)
            continue
        sb = read_series(b, entity)
        for key in ("step", "sim_time", "values"):
            np.testing.assert_array_equal(sa[key], sb[key], err_msg=f"{entity} {key}")
        compared += 1
    assert compared > 20
    assert read_text_log(a, "events") == read_text_log(b, "events")
