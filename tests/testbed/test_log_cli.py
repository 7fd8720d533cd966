"""Log folders on the command line: one-line refusals (exit 2) before any work, nothing of a log overwritten."""

from __future__ import annotations

import numpy as np
import pytest

from quadobs.cli import main


def _log(folder, meta="key,value\nversion,2\nname,tiny\nheading0,0.0\n"):
    folder.mkdir()
    (folder / "beacons.csv").write_text("id,x,y\n0,0,0\n1,10,0\n2,10,10\n")
    t = np.arange(0.0, 5.0, 0.1)
    (folder / "inputs.csv").write_text(
        "time,speed,yaw_rate\n" + "".join(f"{float(v)!r},1.0,0.0\n" for v in t)
    )
    rows = [f"{float(v) + 0.05!r},{k % 3},{5.0 + 0.1 * k!r}\n" for k, v in enumerate(t)]
    (folder / "ranges.csv").write_text("time,beacon,range\n" + "".join(rows))
    (folder / "meta.csv").write_bytes(meta.encode() if isinstance(meta, str) else meta)
    return folder


REPLAY = ["--no-progress", "--calibrate", "none"]


@pytest.mark.parametrize(
    "meta, message",
    [
        (b"key,value\nname,\xff\xfe\n", "meta.csv: not UTF-8 text"),
        ("key,value\nversion,2\nheading0,0\nheading0,1\n", "row 4, key heading0: given twice"),
        ("key,value\nversion,2\nheadng0,0\n", "row 3: unknown key 'headng0'"),
        ("\ufeffkey,value\nversion,2\nheading0,x\n", "key heading0: 'x' is not a finite number"),
    ],
)
def test_a_bad_meta_file_is_one_line_with_status_2(tmp_path, capsys, meta, message):
    folder = _log(tmp_path / "log", meta)
    assert main(["replay", str(folder), *REPLAY]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_meta_file_that_is_a_folder_is_refused(tmp_path, capsys):
    folder = _log(tmp_path / "log")
    (folder / "meta.csv").unlink()
    (folder / "meta.csv").mkdir()
    assert main(["replay", str(folder), *REPLAY]) == 2
    assert "meta.csv: not a regular file" in capsys.readouterr().err


def test_no_output_replaces_a_file_of_the_log(tmp_path, capsys):
    folder = _log(tmp_path / "log")
    before = (folder / "meta.csv").read_bytes()
    for flag in ("--summary", "--out"):
        assert main(["replay", str(folder), *REPLAY, flag, str(folder / "meta.csv")]) == 2
        assert "is the run's log meta.csv file" in capsys.readouterr().err
    assert (folder / "meta.csv").read_bytes() == before


def test_export_is_alone_and_its_folder_is_checked_first(tmp_path, capsys):
    folder = _log(tmp_path / "log")
    out = ["replay", str(folder), "--export", str(tmp_path / "copy")]
    assert main([*out, "--summary", str(tmp_path / "s.json")]) == 2
    assert "--summary: does not apply with --export" in capsys.readouterr().err
    (tmp_path / "copy").mkdir()
    (tmp_path / "copy" / "notes.txt").write_text("mine")
    assert main(out) == 2
    assert "holds 'notes.txt'" in capsys.readouterr().err
    (tmp_path / "copy" / "notes.txt").unlink()
    assert main(out) == 0
    assert sorted(p.name for p in (tmp_path / "copy").iterdir()) == [
        "beacons.csv",
        "inputs.csv",
        "meta.csv",
        "ranges.csv",
    ]


def test_a_run_exported_as_a_log_refuses_outputs_inside_the_folder(tmp_path, capsys):
    argv = [
        "run",
        "beacons2d",
        "--duration",
        "1",
        "--no-progress",
        "--export-log",
        str(tmp_path / "D"),
    ]
    assert main([*argv, "--out", str(tmp_path / "D" / "ranges.csv")]) == 2
    assert "--export-log" in capsys.readouterr().err and not (tmp_path / "D").exists()


def test_biases_must_be_finite(tmp_path, capsys):
    folder = _log(tmp_path / "log")
    assert main(["replay", str(folder), "--no-progress", "--biases", "nan,0,0"]) == 2
    assert "--biases: 'nan' is not a finite number" in capsys.readouterr().err


def test_a_run_with_ranges_below_zero_is_exported_and_replays_as_it_ran(tmp_path):
    from quadobs.testbed.episode import run_episode, run_loop
    from quadobs.testbed.logs import read_log
    from quadobs.testbed.logs.export import LogExportSink
    from quadobs.testbed.registry import build_estimators
    from quadobs.testbed.scenario import load_scenario
    from quadobs.testbed.worlds.replay import ReplayWorld

    sc = load_scenario(
        "beacons2d",
        duration=2.0,
        settings=["noise.outlier_probability=0.2", "noise.outlier_std=100"],
    )
    ep = run_episode(
        sc,
        estimators=["augmented", "ekf"],
        sinks=[LogExportSink(tmp_path / "log")],
        collect_every=1,
    )
    log = read_log(tmp_path / "log")
    assert np.any(log.ranges[:, 2] < 0)  # the outliers' negative ranges, kept as received
    world = ReplayWorld(log, sc.dt, "imu")
    x0 = ep.trace["estimates"]["augmented"][0]
    summary, _ = run_loop(
        lambda merged, *rest: merged,
        frame=world.frame(),
        world=world,
        estimators=build_estimators(sc, ["augmented", "ekf"], x0),
    )
    for name in ("augmented", "ekf"):
        assert summary["estimators"][name]["final_position_error"] == pytest.approx(
            ep.summary["estimators"][name]["final_position_error"], abs=1e-6
        )
