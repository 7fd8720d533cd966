"""Campaign folders: finished runs kept through SIGKILL and resumed bit for bit; a folder replaced as a whole."""

import errno
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import quadobs.studies.campaign as campaign
from quadobs import QuadobsError, load_scenario
from quadobs.studies.campaign import run_campaign

#: Fields measured on the wall clock or naming the folder: everything else is fixed by the seeds.
WALL = {"wall_time", "run_wall_time_mean", "files"}
RUNS = 5


def small():
    return load_scenario("ifac2021-noisy", duration=0.5)


def figures(folder: Path) -> tuple[dict, dict]:
    """The summary without its wall-clock fields, and every table column as bits."""
    summary = json.loads((folder / "summary.json").read_text())
    for key in WALL:
        summary.pop(key)
    tables = {}
    for name in ("runs.parquet", "series.parquet"):
        table = pq.read_table(folder / name)
        for column in table.column_names:
            if column == "wall_time":
                continue
            values = table[column].to_numpy(zero_copy_only=False)
            tables[name, column] = (
                values.view(np.int64).tolist() if values.dtype.kind == "f" else values.tolist()
            )
    return summary, tables


def test_a_killed_campaign_resumes_bit_identical_to_a_straight_one(tmp_path, monkeypatch):
    out = tmp_path / "camp"
    child = (
        "from quadobs import load_scenario\n"
        "from quadobs.studies.campaign import run_campaign\n"
        f"run_campaign(load_scenario('ifac2021-noisy', duration=0.5), runs={RUNS}, "
        f"estimators=['augmented'], out_dir={str(out)!r}, workers=0, record=False)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", child])
    journal = tmp_path / ".camp.runs"
    deadline = time.monotonic() + 120
    while len(list(journal.glob("run-*.pickle"))) < 2 and proc.poll() is None:
        assert time.monotonic() < deadline, "the campaign kept no run"
        time.sleep(0.02)
    proc.kill()  # SIGKILL: no handler, no clean-up
    proc.wait()
    kept = sorted(p.name for p in journal.glob("run-*.pickle"))
    assert 2 <= len(kept) < RUNS and not (out / "summary.json").exists()

    started = []
    run_one = campaign.run_one
    monkeypatch.setattr(
        campaign, "run_one", lambda task: started.append(task["index"]) or run_one(task)
    )
    resumed = run_campaign(
        small(),
        runs=RUNS,
        estimators=["augmented"],
        out_dir=out,
        workers=0,
        record=False,
        resume=True,
    )
    assert sorted(started) == [i for i in range(RUNS) if f"run-{i:07d}.pickle" not in kept]
    assert resumed.summary["runs_completed"] == RUNS and not journal.exists()

    monkeypatch.setattr(campaign, "run_one", run_one)
    run_campaign(
        small(),
        runs=RUNS,
        estimators=["augmented"],
        out_dir=tmp_path / "straight",
        workers=0,
        record=False,
    )
    assert figures(out) == figures(tmp_path / "straight")


def test_resume_refuses_the_journal_of_another_campaign(tmp_path):
    out = tmp_path / "camp"
    journal = campaign.storage.Journal(out, {"scenario": small().to_dict(), "other": 1})
    journal.start(resume=False)
    with pytest.raises(QuadobsError, match="another campaign"):
        run_campaign(small(), runs=2, estimators=["augmented"], out_dir=out, workers=0, resume=True)
    with pytest.raises(QuadobsError, match="resume: needs out_dir"):
        run_campaign(small(), runs=2, estimators=["augmented"], workers=0, resume=True)


def test_a_failed_write_leaves_the_previous_folder_complete(tmp_path, monkeypatch):
    out = tmp_path / "camp"
    run_campaign(small(), runs=2, estimators=["augmented"], out_dir=out, workers=0, record=False)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def full_disk(path, *args):
        path.write_bytes(b"part of a table")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(campaign.storage, "_write_series", full_disk)
    with pytest.raises(QuadobsError, match="No space left on device"):
        run_campaign(
            small(), runs=3, estimators=["augmented"], out_dir=out, workers=0, record=False
        )
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [".camp.runs", "camp"]  # runs kept


def test_a_folder_holding_other_files_is_refused_before_any_run(tmp_path, monkeypatch):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "thesis.tex").write_text("kept")
    monkeypatch.setattr(campaign, "run_one", lambda task: pytest.fail("a run started"))
    with pytest.raises(QuadobsError, match=r"holds 'thesis.tex', not written here"):
        run_campaign(small(), runs=2, estimators=["augmented"], out_dir=out, workers=0)
    assert (out / "thesis.tex").read_text() == "kept"
