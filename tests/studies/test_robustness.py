"""The quadrotor's robustness sweep: the grid, its table, and (slow) no crash on the truth anywhere on it."""

import pytest

from quadobs.studies.robustness import format_sweep, robustness_grid, sweep
from quadobs.testbed.scenario import load_scenario


def test_the_grid_varies_one_thing_at_a_time_and_each_point_loads():
    sc = load_scenario("quadrotor-uwb-augmented")
    grid = robustness_grid(sc)
    labels = [label for label, _ in grid]
    assert len(set(labels)) == len(labels) and grid[0][1] == []
    for label, settings in grid:
        v = load_scenario("quadrotor-uwb-augmented", settings=settings)
        assert v.quadrotor is not None, label
    noisy = load_scenario("quadrotor-uwb-augmented", settings=dict(grid)["IMU noise x3"])
    assert noisy.quadrotor.gyro_std == pytest.approx(3.0 * sc.quadrotor.gyro_std)
    row = {
        "label": "x",
        "flown_on": "truth",
        "crashed": True,
        "crash_time": 6.4,
        "tracking_rms": 0.5,
        "tracking_max": 1.2,
        "position_rmse": None,
    }
    assert "| x | truth | at 6.4 s | 0.500 / 1.200 | - |" in format_sweep([row])


@pytest.mark.slow
def test_no_crash_on_the_truth_anywhere_on_the_grid():
    rows = sweep("quadrotor-uwb-augmented", feedbacks=("augmented",), settings=["duration=30"])
    truth = [r for r in rows if r["flown_on"] == "truth"]
    assert len(truth) == 7 and not any(r["crashed"] for r in truth), format_sweep(rows)
    assert all(r["tracking_rms"] <= 0.10 for r in truth), format_sweep(rows)
