"""Folder outputs staged as a whole, collisions with a log's own files, diverged estimators at the CLI."""

import json
import resource
import signal
from pathlib import Path

import pytest

from quadobs.cli import main
from quadobs.testbed.outputs import write_folder_staged


def _limit_file_size(limit: int):
    def apply():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def _snapshot(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def log_folder(tmp_path_factory) -> Path:
    """A log exported from a short simulated run."""
    folder = tmp_path_factory.mktemp("logs") / "A"
    assert (
        main(["run", "ifac2021", "--duration", "0.5", "--no-progress", "--export-log", str(folder)])
        == 0
    )
    return folder


def test_the_staged_folder_writer_replaces_a_folder_whole_or_not_at_all(tmp_path):
    target = tmp_path / "out"
    write_folder_staged(target, lambda d: (d / "a.txt").write_text("one"))
    write_folder_staged(
        target, lambda d: (d / "b.txt").write_text("two"), allowed={"a.txt", "b.txt"}
    )
    assert _snapshot(target) == {"b.txt": b"two"}

    def failing(d):
        (d / "c.txt").write_text("three")
        raise OSError(28, "No space left on device")

    with pytest.raises(Exception, match="No space left"):
        write_folder_staged(target, failing)
    assert _snapshot(target) == {"b.txt": b"two"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder left


def test_replay_refuses_outputs_naming_the_logs_own_files(log_folder, tmp_path, capsys):
    before = _snapshot(log_folder)
    for flag in ("--summary", "--out"):
        for name in ("meta.csv", "ranges.csv", "beacons.csv"):
            code = main(
                ["replay", str(log_folder), flag, str(log_folder / name), "--calibrate", "none"]
            )
            assert code == 2
            assert "log " + name in capsys.readouterr().err
    assert _snapshot(log_folder) == before


def test_replay_export_refuses_the_options_it_would_ignore(log_folder, tmp_path, capsys):
    code = main(
        [
            "replay",
            str(log_folder),
            "--export",
            str(tmp_path / "E"),
            "--out",
            str(tmp_path / "x.rrd"),
        ]
    )
    assert code == 2 and "--out: does not apply with --export" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_an_export_onto_a_folder_with_other_files_is_refused(log_folder, tmp_path, capsys):
    target = tmp_path / "E"
    target.mkdir()
    (target / "notes.txt").write_text("mine")
    assert main(["replay", str(log_folder), "--export", str(target)]) == 2
    assert "notes.txt" in capsys.readouterr().err
    assert _snapshot(target) == {"notes.txt": b"mine"}


def test_run_refuses_an_output_inside_the_exported_log_folder(tmp_path, capsys):
    folder = tmp_path / "D"
    code = main(
        [
            "run",
            "ifac2021",
            "--duration",
            "0.1",
            "--export-log",
            str(folder),
            "--out",
            str(folder / "ranges.csv"),
        ]
    )
    assert code == 2 and "--export-log" in capsys.readouterr().err
    assert not folder.exists()


def test_a_full_disk_leaves_the_previous_export_complete(log_folder, tmp_path, cli_process):
    """``replay A --export B`` over an existing log B, a file size limit as a full disk: B unchanged."""
    target = tmp_path / "B"
    assert main(["replay", str(log_folder), "--export", str(target)]) == 0
    (target / "ranges.csv").write_text(
        (target / "ranges.csv").read_text()[:200].rsplit("\n", 1)[0] + "\n"
    )
    before = _snapshot(target)
    proc = cli_process(
        "replay", str(log_folder), "--export", str(target), preexec_fn=_limit_file_size(20_000)
    )
    out, err = proc.communicate(timeout=120)
    assert (
        proc.returncode == 1 and "Traceback" not in err and "previous folder is unchanged" in err
    ), err
    assert _snapshot(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["B"]


def test_export_log_on_a_full_disk_keeps_the_runs_results(log_folder, tmp_path, cli_process):
    """``run --export-log B --summary r.json`` on a full disk: exit 1, r.json written, B as before."""
    target, js = tmp_path / "B", tmp_path / "r.json"
    assert main(["replay", str(log_folder), "--export", str(target)]) == 0
    before = _snapshot(target)
    proc = cli_process(
        "run", "ifac2021", "--duration", "1", "--no-progress", "--export-log", str(target),
        "--summary", str(js), preexec_fn=_limit_file_size(40_000),
    )  # fmt: skip
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 1 and "Traceback" not in err, err
    summary = json.loads(js.read_text())
    assert "cannot be written" in summary["export_error"] and summary["final_position_error"] > 0
    assert _snapshot(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["B", "r.json"]


def test_the_library_replay_also_refuses_the_logs_meta_file(log_folder):
    from quadobs import QuadobsError
    from quadobs.testbed.logs import read_log
    from quadobs.testbed.logs.replay import run_replay

    before = (log_folder / "meta.csv").read_bytes()
    with pytest.raises(QuadobsError, match="meta.csv"):
        run_replay(read_log(log_folder), summary_path=log_folder / "meta.csv")
    assert (log_folder / "meta.csv").read_bytes() == before
