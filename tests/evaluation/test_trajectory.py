"""Trajectory errors after a burn-in, split horizontal/vertical, divergence; TUM text (closed forms)."""

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.evaluation.trajectory import DIVERGED_ERROR, TrajectoryErrors, tum_text


def test_the_rmse_after_the_burn_in_splits_into_horizontal_and_vertical():
    t = np.arange(10.0)
    truth = np.zeros((10, 3))
    est = np.zeros((10, 3))
    est[:3] = 100.0  # the start-up transient, inside the burn-in
    est[3:, 0], est[3:, 2] = 3.0, 4.0
    acc = TrajectoryErrors(3, burn_in=3.0)
    acc.update(np.arange(5), t[:5], est[:5], truth[:5])  # streamed in two blocks
    acc.update(np.arange(5, 10), t[5:], est[5:], truth[5:])
    f = acc.figures()
    assert f["rmse"] == pytest.approx(5.0) and f["max_error"] == pytest.approx(5.0)
    assert f["rmse_horizontal"] == pytest.approx(3.0) and f["rmse_vertical"] == pytest.approx(4.0)
    assert f["samples"] == 7 and f["diverged"] is None and f["final_position_error"] == 5.0
    whole = TrajectoryErrors(3)
    whole.update(np.arange(10), t, est, truth)
    assert whole.figures()["rmse"] == pytest.approx(math.sqrt((3 * 30000 + 7 * 25) / 10))


def test_rows_without_truth_are_skipped_and_planar_runs_have_no_vertical_part():
    t = np.arange(4.0)
    truth = np.array([[np.nan, np.nan], [0.0, 0.0], [0.0, 0.0], [np.nan, np.nan]])
    acc = TrajectoryErrors(2)
    acc.update(np.arange(4), t, np.ones((4, 2)), truth)
    f = acc.figures()
    assert f["samples"] == 2 and f["rmse"] == pytest.approx(math.sqrt(2.0))
    assert f["rmse_vertical"] is None and f["rmse_horizontal"] == f["rmse"]


@pytest.mark.parametrize(
    "bad, reason",
    [
        (np.inf, "non-finite estimate"),
        (np.nan, "non-finite estimate"),
        (2 * DIVERGED_ERROR, "beyond"),
    ],
)
def test_a_diverged_estimator_gets_no_rmse(bad, reason):
    t = np.arange(20.0) * 0.5
    est = np.zeros((20, 2))
    est[10, 0] = bad  # one bad row: the rest finite and good
    acc = TrajectoryErrors(2)
    acc.update(np.arange(20), t, est, np.zeros((20, 2)))
    f = acc.figures()
    assert f["diverged"]["step"] == 10 and f["diverged"]["time"] == 5.0
    assert reason in f["diverged"]["reason"]
    assert f["rmse"] is None and f["max_error"] is None and f["final_position_error"] is None


def test_a_negative_burn_in_is_refused():
    with pytest.raises(QuadobsError, match="--burn-in"):
        TrajectoryErrors(2, burn_in=-1.0)


def test_tum_lines_hold_time_position_and_a_scalar_last_quaternion():
    text = tum_text(np.array([1.5]), np.array([[1.0, 2.0]]))
    assert text == "1.5 1.0 2.0 0.0 0.0 0.0 0.0 1.0\n"
    q = np.array([[0.5, 0.5, 0.5, 0.5]])
    assert tum_text(np.array([0.0]), np.ones((1, 3)), q).split()[4:] == ["0.5"] * 4
