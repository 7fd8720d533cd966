"""Monte Carlo campaigns: local processes, in-process, a Dask LocalCluster on loopback; files, seeds, failures."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from quadobs import load_scenario
from quadobs.cli import main
from quadobs.estimators.base import Estimator, SetValued
from quadobs.studies.campaign import run_campaign, run_seed
from quadobs.testbed.episode import run_episode
from quadobs.testbed.factories import extended_kalman_filter
from quadobs.testbed.registry import register_estimator

NAMES = ["augmented", "ekf", "ukf"]
KEYS = {
    "runs",
    "converged_fraction",
    "final_rmse_position",
    "final_rmse_velocity",
    "rmse_over_sqrt_pcrb",
    "mean_nees",
    "chi2_bounds",
}


def short(duration=2.0):
    return load_scenario("ifac2021-noisy", duration=duration)


class Boxed(Estimator, SetValued):
    """A set estimator for the tests: an EKF's estimate +- ``k`` standard deviations as interval bounds."""

    def __init__(self, inner, k):
        self.inner, self.k = inner, k

    def step(self, u, y):
        self.inner.step(u, y)

    @property
    def x_hat(self):
        return self.inner.x_hat

    @property
    def bounds(self):
        s = self.k * np.sqrt(np.diag(self.inner.x_covariance))
        return np.stack([self.inner.x_hat - s, self.inner.x_hat + s], axis=1)


class Flaky(Estimator):
    """Raises ``exc`` (if any) at its 500th step, as a broken estimator would."""

    def __init__(self, x0, exc):
        self.x, self.k, self.exc = np.array(x0, dtype=float), 0, exc

    def step(self, u, y):
        self.k += 1
        if self.k == 500 and self.exc is not None:
            raise self.exc

    @property
    def x_hat(self):
        return self.x


register_estimator("boxed", lambda sc, x0, name: Boxed(extended_kalman_filter(sc, x0), 3.0))
register_estimator("wide", lambda sc, x0, name: Boxed(extended_kalman_filter(sc, x0), 1e6))
register_estimator(
    "flaky",
    lambda sc, x0, name: (
        Flaky(x0, FloatingPointError("diverged on purpose"))
        if sc.seed % 3 == 0
        else Flaky(x0, None)
    ),
)


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    out = tmp_path_factory.mktemp("campaign")
    res = run_campaign(short(), runs=4, estimators=NAMES, out_dir=out, workers=2)
    return out, res


def _numbers(summary):
    return {n: {k: v for k, v in e.items()} for n, e in summary["estimators"].items()}


def test_local_campaign_files_and_summary(local):
    out, res = local
    s = json.loads((out / "summary.json").read_text())
    assert s["runs_completed"] == 4 and s["runs_failed"] == 0 and s["failed"] == []
    assert s["backend"]["kind"] == "processes" and s["sample_every"] == pytest.approx(0.1)
    assert set(s["estimators"]) == set(NAMES)
    for name, e in s["estimators"].items():
        assert KEYS <= set(e), name
        assert e["runs"] == 4
        lo, hi = e["chi2_bounds"]["nees"]
        assert 0 < lo < 6 < hi and e["chi2_bounds"]["nees_dof_per_run"] == 6
    assert s["pcrb"]["available"] and s["pcrb"]["final_sqrt_trace_position"] > 0
    assert _numbers(s) == json.loads(json.dumps(_numbers(res.summary)))

    import pyarrow.parquet as pq

    runs = pq.read_table(out / "runs.parquet").to_pydict()
    assert len(runs["run"]) == 12 and set(runs["status"]) == {"ok"}
    seeds = {r: sd for r, sd in zip(runs["run"], runs["seed"])}
    assert seeds == {i: run_seed(0, i) for i in range(4)}
    series = pq.read_table(out / "series.parquet")
    assert series.num_rows == 3 * 4 * 21
    ekf = [v for v, n in zip(runs["final_position_error"], runs["estimator"]) if n == "ekf"]
    rms = np.sqrt(np.mean(np.square(ekf)))
    assert s["estimators"]["ekf"]["final_rmse_position"] == pytest.approx(rms, rel=1e-12)


def test_statistics_recording(local):
    from quadobs.recording import list_entities, read_series

    out, res = local
    rrd = out / "statistics.rrd"
    ents = set(list_entities(rrd))
    for e in [
        "/stats/pcrb/position",
        "/stats/ekf/position/rmse",
        "/stats/ukf/nees/mean",
        "/stats/augmented/nees/bounds",
        "/stats/ekf/nis/mean",
    ]:
        assert e in ents
    rm = read_series(rrd, "stats/ekf/position/rmse")
    assert rm["step"][-1] == 2000 and len(rm["step"]) == 21
    np.testing.assert_allclose(rm["values"][:, 0], res.ensembles["ekf"].rmse_position, rtol=1e-12)
    assert rm["values"][-1, 0] == pytest.approx(
        res.summary["estimators"]["ekf"]["final_rmse_position"], rel=1e-9
    )
    b = read_series(rrd, "stats/ekf/nees/bounds")["values"][-1]
    assert list(b) == pytest.approx(res.summary["estimators"]["ekf"]["chi2_bounds"]["nees"])
    rerun = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    proc = subprocess.run([rerun, "rrd", "verify", str(rrd)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_a_run_is_reproduced_alone_from_its_seed(local):
    _, res = local
    r2 = next(r for r in res.results if r["index"] == 2)
    alone = run_episode(short().with_overrides(seed=run_seed(0, 2)), estimators=NAMES)
    for name in NAMES:
        assert (
            alone.summary["estimators"][name]["final_position_error"]
            == r2["estimators"][name]["final_position_error"]
        )


def test_in_process_gives_the_same_numbers(local):
    _, res = local
    again = run_campaign(short(), runs=4, estimators=NAMES, workers=0)
    assert again.summary["backend"]["kind"] == "in-process"
    assert _numbers(again.summary) == _numbers(res.summary)


def test_dask_local_cluster_gives_the_same_numbers(local, tmp_path):
    import distributed

    _, res = local
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        dask = run_campaign(
            short(), runs=4, estimators=NAMES, out_dir=tmp_path, scheduler=cluster.scheduler_address
        )
    assert dask.summary["backend"] == {
        "kind": "dask",
        "scheduler": cluster.scheduler_address,
        "workers": 2,
    }
    assert _numbers(dask.summary) == _numbers(res.summary)
    assert (tmp_path / "summary.json").is_file() and (tmp_path / "statistics.rrd").is_file()


@pytest.mark.parametrize("workers", [0, 2])
def test_a_failed_run_is_reported_and_the_others_kept(tmp_path, workers):
    res = run_campaign(
        short(1.0), runs=6, estimators=["ekf", "flaky"], out_dir=tmp_path, workers=workers
    )
    s = res.summary
    bad = sorted(i for i in range(6) if run_seed(0, i) % 3 == 0)
    assert bad and len(bad) < 6
    assert [f["run"] for f in s["failed"]] == bad
    assert all(
        f["seed"] == run_seed(0, f["run"])
        and "FloatingPointError: diverged on purpose" in f["error"]
        for f in s["failed"]
    )
    assert s["runs_completed"] == 6 - len(bad) and s["estimators"]["ekf"]["runs"] == 6 - len(bad)
    import pyarrow.parquet as pq

    runs = pq.read_table(tmp_path / "runs.parquet").to_pydict()
    failed_rows = [r for r, st in zip(runs["run"], runs["status"]) if st == "failed"]
    assert sorted(failed_rows) == bad


def test_every_run_failing_still_writes_a_summary(tmp_path):
    register_estimator("broken", lambda sc, x0, name: Flaky(x0, ValueError("always")))
    res = run_campaign(short(1.0), runs=2, estimators=["broken"], out_dir=tmp_path, workers=0)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert (
        s["runs_completed"] == 0
        and s["runs_failed"] == 2
        and s["estimators"]["broken"]["runs"] == 0
    )
    assert s["estimators"]["broken"]["converged_fraction"] is None
    assert res.summary["failed"][1]["error"] == "ValueError: always"


def test_set_estimators_containment_and_size():
    res = run_campaign(short(1.0), runs=2, estimators=["boxed", "wide", "ekf"], workers=0)
    wide, boxed = res.summary["estimators"]["wide"], res.summary["estimators"]["boxed"]
    assert wide["containment_rate"] == 1.0 and wide["final_containment"] == 1.0
    assert wide["final_width_position"] == pytest.approx(
        1e6 / 3 * boxed["final_width_position"], rel=1e-9
    )
    assert 0.0 <= boxed["containment_rate"] <= 1.0
    assert "containment_rate" not in res.summary["estimators"]["ekf"]


def test_interrupt_keeps_the_finished_runs():
    register_estimator(
        "stopper",
        lambda sc, x0, name: (
            Flaky(x0, KeyboardInterrupt()) if sc.seed == run_seed(0, 2) else Flaky(x0, None)
        ),
    )
    res = run_campaign(short(1.0), runs=5, estimators=["stopper"], workers=0)
    assert res.summary["interrupted"] and res.summary["runs_completed"] == 2


def test_cli_campaign(tmp_path, capsys):
    rc = main(
        [
            "campaign",
            "ifac2021-noisy",
            "--runs",
            "2",
            "--duration",
            "1",
            "--estimators",
            "augmented,ekf",
            "--out",
            str(tmp_path),
            "--workers",
            "0",
            "--no-progress",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    assert "campaign ifac2021-noisy: 2 of 2 runs completed (0 failed)" in out
    assert "RMSE/sqrt(PCRB) p" in out and "ekf" in out
    assert json.loads((tmp_path / "summary.json").read_text())["runs_requested"] == 2
    rc = main(
        [
            "campaign",
            "ifac2021-noisy",
            "--runs",
            "3",
            "--duration",
            "1",
            "--estimators",
            "ekf,flaky",
            "--out",
            str(tmp_path / "f"),
            "--workers",
            "0",
            "--no-progress",
        ]
    )
    assert rc == 1 and "failed: run" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, message",
    [
        (["--runs", "0"], "runs"),
        (["--runs", "2", "--estimators", "augmented,nope"], "unknown estimator 'nope'"),
        (["--runs", "2", "--every", "0.3"], "every"),
        (["--runs", "2", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "workers"),
        (["--runs", "2", "--threshold", "-1"], "threshold"),
    ],
)
def test_cli_campaign_bad_input(tmp_path, capsys, args, message):
    rc = main(
        [
            "campaign",
            "ifac2021-noisy",
            "--duration",
            "1",
            "--out",
            str(tmp_path),
            "--no-progress",
            *args,
        ]
    )
    assert rc == 2
    assert message in capsys.readouterr().err


def test_wind_scenario_campaign():
    """Wind state (p, v_a, v_w), ranges and airspeed: the baselines, the bound and the immersion bound all run."""
    from quadobs.testbed.scenario import parse_scenario

    data = short(1.0).to_dict()
    data["dimension"] = 2
    data["beacons"] = [{"position": [0.0, 0.0]}, {"position": [30.0, 5.0]}]
    data["wind"] = {"velocity": [2.0, -1.0]}
    data["trajectory"] = {
        "offset": [5.0, 10.0],
        "terms": [
            {"axis": 0, "amplitude": 10.0, "omega": 1.0},
            {"axis": 1, "amplitude": 5.0, "omega": 2.0},
        ],
    }
    data["noise"] = {
        "range_std": 0.3,
        "range_rate": 100.0,
        "airspeed_std": 0.1,
        "airspeed_rate": 50.0,
    }
    data["initial"] = {"kind": "random", "position_spread": 1.0, "velocity_spread": 0.3}
    res = run_campaign(parse_scenario(data), runs=2, estimators=NAMES, workers=0)
    s = res.summary
    assert s["runs_completed"] == 2 and s["pcrb"]["available"]
    assert (
        s["pcrb"]["immersion_bound_final_sqrt_trace_position"]
        >= s["pcrb"]["final_sqrt_trace_position"]
    )
    for name in NAMES:
        e = s["estimators"][name]
        assert e["chi2_bounds"]["nees_dof_per_run"] == 6 and np.isfinite(e["final_rmse_position"])
    # started from the true prior, the baselines stay near the bound (the augmented observer starts from S0 = 100 I)
    assert (
        s["estimators"]["ekf"]["rmse_over_sqrt_pcrb"] < 3
        and s["estimators"]["ukf"]["rmse_over_sqrt_pcrb"] < 3
    )
