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
