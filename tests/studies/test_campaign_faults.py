"""Campaigns under worker loss, Ctrl-C and the death of the campaign's own process."""

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from quadobs import QuadobsError, load_scenario
from quadobs.estimators.base import Estimator
from quadobs.studies.campaign import run_campaign, run_seed
from quadobs.testbed.registry import register_estimator


class Still(Estimator):
    """Keeps its initial guess (the tests only need runs that end)."""

    def __init__(self, x0):
        self.x = np.array(x0, dtype=float)

    def step(self, u, y):
        pass

    @property
    def x_hat(self):
        return self.x.copy()


def _killer(marker_dir: Path, victims: set[int], times: int):
    """A factory whose runs of the seeds ``victims`` SIGKILL their worker the first ``times`` attempts."""

    def make(sc, x0, name):
        if sc.seed in victims:
            marks = marker_dir / f"seed-{sc.seed}"
            count = int(marks.read_text()) if marks.exists() else 0
            if count < times:
                marks.write_text(str(count + 1))
                os.kill(os.getpid(), signal.SIGKILL)
        return Still(x0)

    return make


@pytest.mark.parametrize("retries, times", [(2, 1), (1, 5), (0, 1)])
def test_a_lost_worker_is_replaced_and_its_run_retried_or_reported(tmp_path, retries, times):
    """SIGKILL of the worker holding run 1: retried up to ``retries`` times, then failed with its seed; no deadlock."""
    victim = run_seed(0, 1)
    register_estimator(f"killer{retries}", _killer(tmp_path, {victim}, times))
    t0 = time.monotonic()
    res = run_campaign(
        load_scenario("ifac2021", duration=0.2),
        runs=4,
        estimators=[f"killer{retries}"],
        workers=2,
        retries=retries,
    )
    assert time.monotonic() - t0 < 120
    s = res.summary
    attempts = int((tmp_path / f"seed-{victim}").read_text())
    if times <= retries:
        assert s["runs_completed"] == 4 and s["runs_failed"] == 0 and attempts == times
        assert s["retried"] == [{"run": 1, "seed": victim, "lost": times}]
    else:
        assert s["runs_completed"] == 3 and attempts == retries + 1
        (f,) = s["failed"]
        assert f["run"] == 1 and f["seed"] == victim and "killed by signal 9" in f["error"]
        assert f"{retries + 1} times" in f["error"]


def test_every_worker_dying_ends_the_campaign(tmp_path):
    seeds = {run_seed(0, i) for i in range(3)}
    register_estimator("allkill", _killer(tmp_path, seeds, 100))
    res = run_campaign(
        load_scenario("ifac2021", duration=0.2),
        runs=3,
        estimators=["allkill"],
        workers=2,
        retries=1,
    )
    assert res.summary["runs_completed"] == 0 and [f["run"] for f in res.summary["failed"]] == [
        0,
        1,
        2,
    ]


@pytest.mark.parametrize(
    "bad", [{"retries": -1}, {"retries": 101}, {"runs": 10**7}, {"workers": 5000}]
)
def test_campaign_counts_are_bounded(bad):
    kw = {"runs": 2, "workers": 0, **bad}
    with pytest.raises(QuadobsError, match=next(iter(bad))):
        run_campaign(load_scenario("ifac2021", duration=0.2), **kw)


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        text = (task / "children").read_text() if (task / "children").exists() else ""
        out += [int(c) for c in text.split()]
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(") ")[-1][0] != "Z"
    except FileNotFoundError:
        return False


def _campaign(cli_process, tmp_path, runs="6", duration="60"):
    return cli_process(
        "campaign",
        "ifac2021-noisy",
        "--runs",
        runs,
        "--workers",
        "2",
        "--duration",
        duration,
        "--estimators",
        "ekf",
        "--no-progress",
        "--out",
        str(tmp_path / "c"),
    )


def _wait_for_workers(proc, count=2, timeout=120) -> list[int]:
    deadline = time.monotonic() + timeout
    while len(kids := _children(proc.pid)) < count:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.1)
    return kids


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs /proc")
def test_workers_end_when_the_campaign_process_is_killed(tmp_path, cli_process):
    proc = _campaign(cli_process, tmp_path)
    kids = _wait_for_workers(proc)
    time.sleep(1.0)
    proc.kill()
    proc.communicate(timeout=30)
    deadline = time.monotonic() + 10
    while any(_alive(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(k) for k in kids)


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs /proc")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_ends_a_campaign_and_keeps_the_finished_runs(tmp_path, cli_process, sig):
    """A signal while one worker was SIGKILLed and the others run: exit 130 within seconds, summary written."""
    proc = _campaign(cli_process, tmp_path, runs="400", duration="3")  # far more than 4 s of work
    kids = _wait_for_workers(proc)
    os.kill(kids[0], signal.SIGKILL)
    time.sleep(4.0)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    summary = json.loads((tmp_path / "c" / "summary.json").read_text())
    assert (
        summary["interrupted"] is True and summary["runs_completed"] + summary["runs_failed"] < 400
    )
    assert not any(_alive(k) for k in kids)
