"""Estimators found through package entry points: a tiny package installed in the test runs in
``quadobs run`` and in campaigns on spawn-started processes and on a Dask cluster."""

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from quadobs import QuadobsError, load_scenario
from quadobs.studies.campaign import run_campaign
from quadobs.testbed import registry

ROOT = Path(__file__).resolve().parents[2]

TINY = '''
import numpy as np

from quadobs.estimators.base import Estimator, check_step


class Frozen(Estimator):
    """Keeps its initial estimate, with a covariance that grows by 1e-3 per step."""

    def __init__(self, x0):
        self._x = np.array(x0, dtype=float)
        self._var = 1.0

    def step(self, u, y):
        check_step(u, y, 3, y.shape[0] if hasattr(y, "shape") else len(y))
        self._var += 1e-3

    @property
    def x_hat(self):
        return self._x.copy()

    @property
    def x_covariance(self):
        return self._var * np.eye(self._x.size)


def factory(scenario, x0, name):
    return Frozen(x0)


def not_an_estimator(scenario, x0, name):
    return "frozen"
'''


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """The package ``tinyest`` with entry points ``tiny``, ``tinywrong`` (returns a string) and
    ``tinybroken`` (a module that does not exist), on ``sys.path`` and ``PYTHONPATH``."""
    (tmp_path / "tinyest").mkdir()
    (tmp_path / "tinyest" / "__init__.py").write_text(TINY)
    info = tmp_path / "tinyest-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: tinyest\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[quadobs.estimators]\ntiny = tinyest:factory\ntinywrong = tinyest:not_an_estimator\ntinybroken = nosuchmodule:factory\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(
        "PYTHONPATH",
        os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
    )
    registry.refresh()
    yield tmp_path
    registry.refresh()


def test_the_builtin_table_is_the_one_declared_in_pyproject():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"][
        "quadobs.estimators"
    ]
    assert declared == registry._BUILTIN
    for value in declared.values():  # and each names a factory that exists
        assert callable(registry._load("x", value))


def test_entry_points_are_listed_sorted_without_importing(tiny):
    names = registry.available_estimators()
    assert names == sorted(names)
    assert {"augmented", "ekf", "ukf", "zonotope", "tiny", "tinywrong", "tinybroken"} <= set(names)
    assert "tinyest" not in sys.modules and "nosuchmodule" not in sys.modules
    beacons = load_scenario("beacons")
    assert registry.available_estimators(beacons)[-1] == "augmented_1beacon"


def test_a_plugin_estimator_is_built_by_name(tiny):
    scenario = load_scenario("ifac2021", duration=0.1)
    aug, est = registry.build_estimators(scenario, ["augmented", "tiny"], np.ones(6))
    assert type(est).__name__ == "Frozen" and est.name == "tiny"
    np.testing.assert_array_equal(est.x_hat, np.ones(6))
    assert registry.estimator_factory("tiny")[1] == "tinyest:factory"


def test_plugin_errors_are_one_line_and_name_the_entry_point(tiny):
    scenario = load_scenario("ifac2021", duration=0.1)
    with pytest.raises(
        QuadobsError,
        match=r"^estimators: the factory of 'tinywrong' \(tinyest:not_an_estimator\) returned str, not",
    ):
        registry.build_estimators(scenario, ["tinywrong"], np.zeros(6))
    with pytest.raises(
        QuadobsError,
        match=r"^estimators: entry point 'tinybroken' \(nosuchmodule:factory\) cannot be loaded: ModuleNotFoundError",
    ) as info:
        registry.build_estimators(scenario, ["augmented", "tinybroken"], np.zeros(6))
    assert "\n" not in str(info.value)
    # the broken one does not stop the others
    assert len(registry.build_estimators(scenario, ["augmented", "tiny"], np.zeros(6))) == 2
    with pytest.raises(
        QuadobsError, match=r"unknown estimator 'nope'; available: .*augmented.*tiny"
    ):
        registry.build_estimators(scenario, ["nope"], np.zeros(6))


def test_a_plugin_runs_in_quadobs_run(tiny, tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "quadobs.cli",
            "run",
            "ifac2021",
            "--duration",
            "1",
            "--estimators",
            "augmented,tiny",
            "--out",
            str(out / "run.rrd"),
            "--summary",
            str(out / "summary.json"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["estimators"]) == {"augmented", "tiny"}
    assert summary["estimators"]["tiny"]["final_position_error"] > 0


@pytest.mark.parametrize("where", ["spawn", "dask"])
def test_a_plugin_runs_in_campaign_workers(tiny, where):
    scenario = load_scenario("ifac2021", duration=0.5)
    kw = dict(runs=2, estimators=["augmented", "tiny"], record=False, every=0.1)
    if where == "spawn":
        result = run_campaign(scenario, workers=2, start_method="spawn", **kw)
    else:
        from distributed import LocalCluster

        with LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster:
            result = run_campaign(scenario, scheduler=cluster.scheduler_address, **kw)
    assert result.summary["failed"] == [], result.summary["failed"]
    assert result.summary["estimators"]["tiny"]["runs"] == 2
    assert result.summary["estimators"]["tiny"]["final_rmse_position"] > 0


def test_runtime_registrations_are_refused_where_workers_cannot_see_them(monkeypatch):
    monkeypatch.setitem(registry._RUNTIME, "local", lambda scenario, x0, name: None)
    scenario = load_scenario("ifac2021", duration=0.5)
    with pytest.raises(
        QuadobsError,
        match=r"estimators: 'local' is registered at run time, which 'spawn' workers do not see",
    ):
        run_campaign(
            scenario, runs=1, estimators=["local"], workers=1, start_method="spawn", record=False
        )
    with pytest.raises(QuadobsError, match=r"start_method: expected one of"):
        run_campaign(scenario, runs=1, workers=1, start_method="thread", record=False)
