"""Staged outputs, refused targets, a full disk, killed and concurrent runs, physics faults."""

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from quadobs import QuadobsError, load_scenario
from quadobs.cli import main
from quadobs.errors import RunFault, staging_owner, staging_path
from quadobs.recording import read_series
from quadobs.testbed.episode import run_episode
from quadobs.testbed.outputs import check_outputs, clean_leftovers, write_json_staged

RERUN = str(Path(sys.executable).parent / "rerun")
ROOT = Path(__file__).resolve().parents[2]


def _verify(rrd: Path) -> None:
    proc = subprocess.run([RERUN, "rrd", "verify", str(rrd)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


NOTICES = (
    "quadobs: compiling",
    "quadobs: note:",
)  # a first run's compile notice, a long run's cost notice


def _error_line(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith(NOTICES)]
    assert len(err) == 1 and err[0].startswith("quadobs: error: "), err
    return err[0]


@pytest.fixture
def no_simulation(monkeypatch):
    """Any MuJoCo set-up fails the test: refusals must come before the simulation."""
    import quadobs.testbed.worlds

    def refuse(*a, **k):
        raise AssertionError("the simulation started")

    monkeypatch.setattr(quadobs.testbed.worlds, "PointMassWorld", refuse)


# -- staging ---------------------------------------------------------------------------------


def test_the_previous_recording_stays_whole_until_the_new_one_is_complete(tmp_path):
    from quadobs.recording import Recorder

    rrd = tmp_path / "x.rrd"
    rrd.write_bytes(b"previous")
    rec = Recorder(rrd, recording_id="t", capacity=10)
    s = rec.series("s", 1)
    rows = rec.rows(np.arange(10), np.arange(10) * 1e-3)
    s.buf[rows, 0] = 1.0
    rec.flush(wait=True)
    assert rrd.read_bytes() == b"previous" and rec.staging.exists()
    assert staging_owner(rec.staging) == ("x.rrd", os.getpid())
    rec.close()
    assert not rec.staging.exists()
    _verify(rrd)
    np.testing.assert_array_equal(read_series(rrd, "s")["step"], np.arange(10))


def test_a_symlink_is_written_through(tmp_path):
    real = tmp_path / "real.json"
    real.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(real)
    write_json_staged(link, {"a": 1})
    assert link.is_symlink() and json.loads(real.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "real.json"]


def test_leftovers_of_gone_processes_are_removed_and_live_ones_kept(tmp_path):
    target = tmp_path / "x.rrd"
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / f".x.rrd.{gone.pid}-abcdef.partial"
    live = tmp_path / f".x.rrd.{os.getppid()}-abcdef.partial"
    other = tmp_path / f".y.rrd.{gone.pid}-abcdef.partial"
    for p in (dead, live, other):
        p.write_bytes(b"")
    assert clean_leftovers(target) == [dead]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name])
    assert staging_owner(staging_path(target))[0] == "x.rrd"


# -- refused targets ---------------------------------------------------------------------------


def test_outputs_colliding_with_each_other_or_with_an_input_are_refused(
    tmp_path, capsys, no_simulation
):
    js = tmp_path / "x.json"
    assert main(["run", "ifac2021", "--out", str(js), "--summary", str(js)]) == 2
    assert "same file" in _error_line(capsys)
    link = tmp_path / "link.json"
    link.symlink_to(js)
    assert main(["run", "ifac2021", "--out", str(js), "--summary", str(link)]) == 2
    assert "same file" in _error_line(capsys)
    scenario = tmp_path / "sc.toml"
    text = (ROOT / "quadobs/testbed/scenarios/ifac2021.toml").read_text()
    scenario.write_text(text)
    for option in ("--out", "--summary"):
        assert main(["run", str(scenario), option, str(scenario)]) == 2
        assert "scenario file" in _error_line(capsys)
    assert main(["excitation", str(scenario), "--json", str(scenario)]) == 2
    assert "scenario file" in _error_line(capsys)
    assert scenario.read_text() == text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "sc.toml"]


@pytest.mark.parametrize(
    "kind", ["device", "fifo", "directory", "read-only", "long-name", "nul", "huge", "loop"]
)
def test_non_regular_and_hostile_targets_are_refused_before_the_run(
    tmp_path, capsys, no_simulation, kind
):
    if kind == "device":
        target = "/dev/null"
    elif kind == "fifo":
        target = tmp_path / "pipe"
        os.mkfifo(target)
    elif kind == "directory":
        target = tmp_path
    elif kind == "read-only":
        target = tmp_path / "ro.json"
        target.write_text("old")
        target.chmod(0o444)
    elif kind == "long-name":
        target = tmp_path / ("s" * 248)
    elif kind == "nul":
        target = str(tmp_path / "a\0b.json")
    elif kind == "huge":
        target = str(tmp_path / ("d/" * 2500)) + "x.json"
    else:
        (tmp_path / "a").symlink_to(tmp_path / "b")
        (tmp_path / "b").symlink_to(tmp_path / "a")
        target = tmp_path / "a"
    before = sorted(p.name for p in tmp_path.iterdir())
    for option in ("--summary", "--out"):
        assert main(["run", "ifac2021", "--no-progress", option, str(target)]) == 2
        line = _error_line(capsys)
        assert len(line) < 400
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert Path("/dev/null").is_char_device()


def test_check_outputs_returns_the_files_replaced(tmp_path):
    real = tmp_path / "r.rrd"
    (tmp_path / "l.rrd").symlink_to(real)
    got = check_outputs(
        {"--out": tmp_path / "l.rrd", "--summary": None, "--json": tmp_path / "s.json"}
    )
    assert got == {"--out": real, "--json": tmp_path / "s.json"}
    with pytest.raises(QuadobsError, match="--json: names the same file as --out"):
        check_outputs({"--out": real, "--json": tmp_path / "l.rrd"})


# -- faults while running ----------------------------------------------------------------------


def _limit_file_size(limit: int):
    def apply():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def test_a_full_disk_ends_the_run_with_one_line_and_keeps_the_previous_recording(
    tmp_path, cli_process
):
    """A file size limit (as a full disk): exit 1 within seconds, the error names the path, the
    summary holds the error, the previous recording is untouched and no staging file is left."""
    rrd, js = tmp_path / "run.rrd", tmp_path / "run.json"
    rrd.write_bytes(b"previous")
    t0 = time.monotonic()
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
        preexec_fn=_limit_file_size(2_000_000),
    )
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 1, err
    lines = [
        ln for ln in err.splitlines() if ln.startswith("quadobs:") and not ln.startswith(NOTICES)
    ]
    assert len(lines) == 1 and str(rrd) in lines[0] and "cannot be written" in lines[0], err
    assert "Traceback" not in err and time.monotonic() - t0 < 120
    assert rrd.read_bytes() == b"previous"
    summary = json.loads(js.read_text())
    assert (
        summary["failed"] is True
        and str(rrd) in summary["error"]
        and "final_position_error" not in summary
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json", "run.rrd"]


def test_a_summary_that_cannot_be_written_at_the_end_still_prints_the_table(
    tmp_path, capsys, monkeypatch
):
    import quadobs.cli as cli
    import quadobs.testbed.outputs as outputs

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    printed = []
    monkeypatch.setattr(cli, "print_summary", printed.append)
    js = tmp_path / "s.json"
    monkeypatch.setattr(outputs.os, "fsync", full)
    assert (
        main(["run", "ifac2021", "--duration", "0.5", "--no-progress", "--summary", str(js)]) == 1
    )
    assert "No space left on device" in _error_line(capsys)
    (summary,) = printed
    assert (
        summary["physics_steps"] == 500
        and "final_position_error" in summary
        and str(js) in summary["output_error"]
    )
    assert list(tmp_path.iterdir()) == []


def test_sigkill_mid_run_leaves_the_previous_files_and_the_next_run_cleans_up(
    tmp_path, cli_process
):
    rrd, js = tmp_path / "run.rrd", tmp_path / "run.json"
    rrd.write_bytes(b"previous")
    js.write_text('{"old": true}')
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
    while not any(p.stat().st_size > 100_000 for p in tmp_path.glob(".run.rrd.*.partial")):
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    proc.kill()
    proc.communicate(timeout=60)
    assert rrd.read_bytes() == b"previous" and json.loads(js.read_text()) == {"old": True}
    (left,) = tmp_path.glob(".run.rrd.*.partial")
    assert staging_owner(left)[1] == proc.pid
    assert (
        main(
            [
                "run",
                "ifac2021",
                "--duration",
                "0.2",
                "--no-progress",
                "--out",
                str(rrd),
                "--summary",
                str(js),
            ]
        )
        == 0
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json", "run.rrd"]
    _verify(rrd)


def test_concurrent_writers_each_leave_a_complete_file(tmp_path, cli_process):
    rrd = tmp_path / "same.rrd"
    procs = [
        cli_process(
            "run",
            "ifac2021",
            "--duration",
            "2",
            "--seed",
            str(s),
            "--no-progress",
            "--out",
            str(rrd),
        )
        for s in (1, 2)
    ]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    _verify(rrd)
    np.testing.assert_array_equal(
        read_series(rrd, "errors/augmented/position/norm")["step"], np.arange(2001)
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["same.rrd"]


# -- physics faults ----------------------------------------------------------------------------


def _heavy_model(folder: Path) -> str:
    """The built-in vehicle with a mass of 1e9 kg: the forces it needs exceed MuJoCo's limit."""
    path = folder / "heavy.xml"
    path.write_text(
        (ROOT / "models" / "vehicle.xml").read_text().replace('mass="2.5"', 'mass="1e9"')
    )
    return f"model='{path}'"


@pytest.mark.parametrize(
    "setting", ["trajectory.terms=[{axis=0, amplitude=1e9, omega=1000.0}]", "heavy"]
)
def test_an_unstable_simulation_stops_with_the_step_and_no_figures(
    tmp_path, capfd, monkeypatch, setting
):
    """MuJoCo's warnings (a bad control here) stop the run: exit 1, the block named, no figures, the
    previous recording kept and no converged error reported. The one line is all that is printed
    (captured at the file descriptors: MuJoCo's own printing and its log file are replaced)."""
    monkeypatch.chdir(tmp_path)
    js, rrd = tmp_path / "s.json", tmp_path / "x.rrd"
    rrd.write_bytes(b"previous")
    if setting == "heavy":
        setting = _heavy_model(tmp_path)
    code = main(
        [
            "run",
            "ifac2021",
            "--duration",
            "10",
            "--no-progress",
            "--set",
            setting,
            "--summary",
            str(js),
            "--out",
            str(rrd),
        ]
    )
    assert code == 1
    out, err = capfd.readouterr()
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith(NOTICES)]
    assert len(lines) == 1 and lines[0].startswith("quadobs: error: ") and "WARNING" not in out, (
        out,
        err,
    )
    line = lines[0]
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    # the per-step path sees no jump in the state (the block is named); the block path's rollout
    # leaves one at the first step, which is then named
    assert "physics: MuJoCo reported badctrl" in line
    assert (
        "between step 0 and step 1024 (t = 0 to 1.024 s)" in line
        or "at step 1 (t = 0.001 s)" in line
    ), line
    summary = json.loads(js.read_text())
    assert (
        summary["failed"] is True
        and "final_position_error" not in summary
        and "estimators" not in summary
    )
    assert rrd.read_bytes() == b"previous"


def test_a_fault_in_a_later_block_names_its_step(monkeypatch):
    """MuJoCo's warning raised mid-run (a state made non-finite at step 9000): the error names that step.

    The fault is injected into the per-step stepper; the check after each block is the same for
    the block path (exercised by the unstable-simulation test above)."""
    from quadobs.testbed.worlds import BlockStepper
    from quadobs.testbed.worlds.model import PhysicsFault

    step = BlockStepper.step
    state = {"k0": 0}
    begin = BlockStepper.begin

    def tracking_begin(self, accelerations, k0=0):
        state["k0"] = k0
        return begin(self, accelerations, k0)

    def faulty_step(self, j):
        if state["k0"] + j == 9000:
            self._data.qpos[0] = 1e12  # MuJoCo: bad qpos, reset
        return step(self, j)

    monkeypatch.setattr(BlockStepper, "begin", tracking_begin)
    monkeypatch.setattr(BlockStepper, "step", faulty_step)
    with pytest.raises(PhysicsFault, match=r"at step 900[01] ") as info:
        run_episode(load_scenario("ifac2021", duration=12.0), path="step")
    assert isinstance(info.value, RunFault)


# -- long or large runs say so first -----------------------------------------------------------


def test_the_cost_notice_names_steps_time_and_size_only_for_long_or_large_runs():
    from quadobs.testbed.outputs import cost_notice

    assert cost_notice(load_scenario("ifac2021"), ["augmented"], True) is None
    many = "[" + ", ".join(f"{{position=[{i}.0, 1.0, 2.0]}}" for i in range(2000)) + "]"
    line = cost_notice(
        load_scenario("ifac2021", settings=[f"beacons={many}"]), ["augmented"], False
    )
    assert line.startswith("quadobs: note: 30,000 steps, expected to take about ") and " h;" in line
    line = cost_notice(load_scenario("ifac2021", duration=1e6), ["augmented"], True)
    assert (
        "1,000,000,000 steps" in line
        and "recording of about 330 GB (record_every = 1)" in line
        and "e+" not in line
    )


def test_a_long_run_says_so_on_stderr_before_it_starts_and_does_not_wait(tmp_path, cli_process):
    """``--duration 1e6`` with a recording: the note comes first, the run goes on without waiting for
    anyone, and Ctrl-C then stops it (130) with a valid recording."""
    import select

    rrd = tmp_path / "long.rrd"
    proc = cli_process("run", "ifac2021", "--duration", "1e6", "--no-progress", "--out", str(rrd))
    deadline, note = time.monotonic() + 120, None
    while note is None:
        assert time.monotonic() < deadline and proc.poll() is None, "no notice"
        if select.select([proc.stderr], [], [], 1.0)[0]:
            line = proc.stderr.readline()
            note = line if line.startswith("quadobs: note:") else None
    assert "1,000,000,000 steps, expected to take about" in note and "GB (record_every = 1)" in note
    while not any(
        p.stat().st_size > 100_000 for p in tmp_path.glob(".long.rrd.*.partial")
    ):  # it runs, writing
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "quadobs: interrupted", err
    assert read_series(rrd, "errors/augmented/position/norm")["step"].size > 0
