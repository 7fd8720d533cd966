"""Every public step refuses a non-finite input, an infinite output, a wrong shape or an empty output,
and leaves the estimator as it was; NaN in the outputs still means a missing sample."""

import numpy as np
import pytest

import quadobs
from quadobs import QuadobsError, load_scenario
from quadobs.testbed.registry import build_estimators

GOOD_U, GOOD_Y = np.array([1.0, 0.0, 0.0]), np.array([50.0])
BAD = {
    "nan u": (np.array([np.nan, 0.0, 0.0]), GOOD_Y),
    "inf u": (np.array([0.0, -np.inf, 0.0]), GOOD_Y),
    "inf y": (GOOD_U, np.array([np.inf])),
    "short u": (np.zeros(2), GOOD_Y),
    "empty y": (GOOD_U, np.zeros(0)),
    "2-D y": (GOOD_U, np.zeros((1, 1))),
    "text u": ("abc", GOOD_Y),
}


def _estimators():
    sc = load_scenario("ifac2021-noisy")
    ests = build_estimators(sc, ["augmented", "ekf", "ukf"], np.zeros(sc.state_dim))
    ests.append(quadobs.AugmentedObserver(quadobs.immerse(sc.system()), dt=sc.dt, backend="numpy"))
    return ests


def _state(est):
    P = est.x_covariance
    return np.array(est.x_hat), None if P is None else np.array(P)


@pytest.mark.parametrize("call", ["step", "step_and_record"])
@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_operands_raise_and_change_nothing(call, case):
    u, y = BAD[case]
    for est in _estimators():
        est.step(GOOD_U, GOOD_Y)
        before = _state(est)
        with pytest.raises(QuadobsError, match=r"^(u|y)\b"):
            if call == "step":
                est.step(u, y)
            else:
                est.step_and_record(u, y, np.zeros(est.x_hat.shape[0] + 3))
        after = _state(est)
        np.testing.assert_array_equal(before[0], after[0], err_msg=f"{est.name}: x_hat changed ({case})")
        if before[1] is not None:
            np.testing.assert_array_equal(before[1], after[1], err_msg=f"{est.name}: covariance changed ({case})")
        est.step(GOOD_U, GOOD_Y)  # still usable
        assert np.isfinite(est.x_hat).all()


def test_nan_output_still_means_missing():
    for est in _estimators():
        out = np.zeros(est.x_hat.shape[0] + 3)
        est.step_and_record(GOOD_U, np.array([np.nan]), out)
        assert np.isfinite(est.x_hat).all() and np.isfinite(out[: est.x_hat.shape[0]]).all()
