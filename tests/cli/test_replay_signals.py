"""Signals during a replay's self-calibration: the command stops at once and calibrates nothing."""

import signal
import time
from pathlib import Path

import pytest

from quadobs.cli import main
from quadobs.testbed.logs import calibration


@pytest.fixture(scope="module")
def log_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("logs") / "L"
    assert (
        main(["run", "ifac2021", "--duration", "0.5", "--no-progress", "--export-log", str(folder)])
        == 0
    )
    return folder


def test_an_interrupt_in_a_calibration_replay_stops_the_command(log_folder, monkeypatch, capsys):
    """A Ctrl-C in the second replay of the calibration (as the program's signal handler raises
    it) stops the calibration: status 130, no "calibrated" line, no replay after it."""
    calls = []
    replay = calibration.prediction_residuals

    def interrupted_replay(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return replay(*args, **kwargs)

    monkeypatch.setattr(calibration, "prediction_residuals", interrupted_replay)
    code = main(["replay", str(log_folder), "--dt", "0.00005", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 130 and "calibrated" not in out and "rmse" not in out
    assert len(calls) == 2  # no further replay started


@pytest.mark.slow
def test_sigterm_during_the_calibration_of_plaza1_ends_within_a_second(cli_process):
    pytest.importorskip("gtsam")
    proc = cli_process("replay", "plaza1", "--no-progress")
    time.sleep(12.0)  # imports done, the calibration's replays running (it takes about 30 s)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and time.monotonic() - t0 < 1.0, err
    assert "calibrated" not in out
