"""Diverged and locked-out estimators: flagged with the step and the reason, figures invalid."""

import numpy as np
import pytest

from quadobs.estimators.base import Estimator
from quadobs.testbed import registry
from quadobs.testbed.divergence import error_bound, invalidate_diverged
from quadobs.testbed.episode import run_episode
from quadobs.testbed.scenario import load_scenario


class Runaway(Estimator):
    """Keeps its initial estimate, then jumps to ``value`` at step ``at``."""

    def __init__(self, x0, at, value):
        self._x = np.array(x0, dtype=float)
        self.k, self.at, self.value = 0, at, value

    def step(self, u, y):
        self.k += 1
        if self.k == self.at:
            self._x[:] = self.value

    @property
    def x_hat(self):
        return self._x.copy()

    @property
    def x_covariance(self):
        return np.eye(self._x.size)


@pytest.fixture
def runaway():
    names = []

    def register(name, at, value):
        registry.register_estimator(name, lambda sc, x0, nm: Runaway(x0, at, value))
        names.append(name)

    yield register
    for name in names:
        registry._RUNTIME.pop(name, None)
        registry.refresh()


def test_error_bound_is_a_hundred_scene_sizes():
    beacons = np.array([[0.0, 0.0], [3.0, 4.0], [1.0, 1.0]])
    assert error_bound(beacons, 2.0) == pytest.approx(500.0)
    assert error_bound(beacons, 20.0) == pytest.approx(2000.0)
    assert error_bound(beacons[:1], float("nan")) == pytest.approx(100.0)


@pytest.mark.parametrize(
    ("value", "reason"), [(np.inf, "non-finite estimate"), (1e7, "error beyond the bound")]
)
def test_a_runaway_estimator_is_flagged_and_has_no_figures(runaway, value, reason):
    runaway("runaway", 10, value)
    scenario = load_scenario("ifac2021", duration=0.2)
    summary = run_episode(scenario, estimators=["augmented", "runaway"]).summary
    bad = summary["estimators"]["runaway"]
    assert bad["diverged"]["step"] == 10
    assert bad["diverged"]["reason"].startswith(reason)
    assert bad["final_position_error"] is None and bad["time_to_1m"] is None
    good = summary["estimators"]["augmented"]
    assert good["diverged"] is None and np.isfinite(good["final_position_error"])


def test_invalidate_keeps_counters():
    s = {
        "estimators": {"a": {"diverged": {"step": 3}, "rmse": 1.0, "rejected": 4, "time_to_5m": 2}}
    }
    assert invalidate_diverged(s)["estimators"]["a"] == {
        "diverged": {"step": 3},
        "rmse": None,
        "rejected": 4,
        "time_to_5m": None,
    }


def _lockout_sink(names=("a",)):
    from types import SimpleNamespace

    from quadobs.testbed.divergence import DivergenceSink

    sink = DivergenceSink()
    sink.begin(SimpleNamespace(names=list(names), frame=SimpleNamespace(dt=0.1, steps=1000)))
    return sink


def test_a_gate_that_rejects_nearly_everything_in_the_second_half_is_a_lockout():
    sink = _lockout_sink()  # 1000 steps, 64 bins: the second half starts at step 500
    ks = np.arange(1000)
    nis = np.where(ks % 2 == 0, 1.0, np.nan)  # a correction every other step
    refused = (ks >= 400) & (ks % 2 == 0) & (ks % 50 != 0)  # all but one in 25 from step 400
    rejected = np.cumsum(refused).astype(float)
    sink._lockout("a", nis[:600], rejected[:600], ks[:600])  # across two blocks
    sink._lockout("a", nis[600:], rejected[600:], ks[600:])
    found = sink.end(1000, False)["estimators"]["a"]["diverged"]
    assert found["step"] == 500 and "rejected 240 of the 250 corrections" in found["reason"]


def test_a_filter_that_gave_up_is_reported_diverged_by_its_own_record():
    """A lock-out out of re-initialisations (or a state the filter judged implausible) is the
    filter's own record; the sink reports it, where the rows alone show nothing wrong."""
    from types import SimpleNamespace

    from quadobs.estimators.robust import LockOut
    from quadobs.testbed.divergence import DivergenceSink

    gave_up, fine = LockOut(), LockOut()
    gave_up.diverged = {"time": 4.5, "step": 45, "reason": "out of re-initialisations"}
    estimators = [
        SimpleNamespace(name="a", lockout=gave_up),
        SimpleNamespace(name="b", lockout=fine),
    ]
    sink = DivergenceSink()
    frame = SimpleNamespace(dt=0.1, steps=1000)
    sink.begin(SimpleNamespace(names=["a", "b"], frame=frame, estimators=estimators))
    per = sink.end(1000, False)["estimators"]
    assert per["a"]["diverged"] == {"step": 45, "t": 4.5, "reason": "out of re-initialisations"}
    assert per["b"]["diverged"] is None


def test_scattered_rejections_and_a_short_final_run_are_no_lockout():
    sink = _lockout_sink(["scattered", "short", "none"])
    ks = np.arange(1000)
    nis = np.ones(1000)
    sink._lockout("scattered", nis, np.cumsum(ks % 3 == 0).astype(float), ks)
    sink._lockout("short", nis, np.cumsum(ks >= 800).astype(float), ks)  # the last 200 of 500
    sink._lockout("none", np.full(1000, np.nan), np.zeros(1000), ks)
    per = sink.end(1000, False)["estimators"]
    assert all(per[n]["diverged"] is None for n in ("scattered", "short", "none"))


def test_a_diverged_replay_estimator_named_on_the_command_line_exits_1(
    tmp_path, capsys, monkeypatch
):
    from quadobs.cli import main
    from quadobs.testbed.logs import estimators as replay_estimators

    folder = tmp_path / "log"
    assert (
        main(["run", "ifac2021", "--duration", "0.3", "--no-progress", "--export-log", str(folder)])
        == 0
    )
    monkeypatch.setitem(
        replay_estimators.REPLAY_ESTIMATORS, "runaway", lambda s, x0, nm: Runaway(x0, 2, np.nan)
    )
    js = tmp_path / "r.json"
    argv = ["replay", str(folder), "--calibrate", "none", "--dt", "0.01", "--no-progress"]
    assert main([*argv, "--estimators", "augmented,runaway", "--summary", str(js)]) == 1
    captured = capsys.readouterr()
    assert "runaway: DIVERGED at step" in captured.out and "rmse invalid" in captured.out
    assert "runaway diverged" in captured.err
    import json

    entry = json.loads(js.read_text())["estimators"]["runaway"]
    assert entry["rmse"] is None and entry["diverged"]["reason"] == "non-finite estimate"
