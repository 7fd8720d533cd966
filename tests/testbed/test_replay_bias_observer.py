"""``augmented-bias`` in ``quadobs replay``: the observer with the anchors' range biases in its
immersion, built with the settings of the replay's augmented observer."""

import numpy as np
import pytest
from test_calibration import ANCHORS, circle_laps

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.estimators import (
    REPLAY_ESTIMATORS,
    ReplaySetup,
    build_augmented,
    build_augmented_bias,
    replay_estimator_names,
)
from quadobs.testbed.logs.replay import check_replay, run_replay


def _circle_log(biases) -> RangeLog:
    """Two laps of the calibration tests' circle in 40 s (:func:`test_calibration.circle_laps`)."""
    return circle_laps(biases, period=20.0)


def test_augmented_bias_is_registered_and_takes_the_augmented_observers_settings():
    assert REPLAY_ESTIMATORS["augmented-bias"] is build_augmented_bias
    assert "augmented-bias" in replay_estimator_names()
    s = ReplaySetup(ANCHORS, 0.1, "cv", 0.0, 7.5, range_sigma=0.1, q_acc=1e-2, P0=4.0,
                    input_kind="none")  # fmt: skip
    x0 = np.array([5.0, 4.0, 0.0, 0.0])
    plain, biased = build_augmented(s, x0), build_augmented_bias(s, x0)
    N = plain.immersion.dim
    assert biased.name == "augmented-bias" and biased.sigma == 0.1
    np.testing.assert_array_equal(biased.model.V, plain.model.V)
    np.testing.assert_array_equal(biased._P[:N, :N], plain.P)
    # one bias per anchor after the immersion's state, with the filters' prior (0.5 m)
    np.testing.assert_allclose(np.diag(biased._P)[N:], 0.25)
    np.testing.assert_allclose(biased.x_hat, x0)


def test_augmented_bias_replays_a_biased_log_and_refuses_tdoa():
    log = _circle_log([0.4, -0.3, 0.25, 0.0])
    options = {"range_sigma": 0.1, "q_acc": 1e-2}
    s = run_replay(log, estimators=["augmented-bias"], initial_offset=2.0, batch=False,
                   setup_options=options, burn_in=10.0)["estimators"]["augmented-bias"]  # fmt: skip
    assert s["diverged"] is None
    # measured 0.37 m after 10 s, within 1 m from 0.2 s (a 2 m guess; ranges of 0.1 m)
    assert s["rmse"] < 0.6 and s["time_to_1m"] < 1.0, s
    tdoa = RangeLog(
        "tdoa", np.arange(4), ANCHORS, np.empty((0, 3)), np.empty((0, 1)), float("nan"),
        None, input_kind="none", tdoa=np.array([[0.0, 0, 1, 0.5], [0.1, 1, 2, -0.2]]),
    )  # fmt: skip
    with pytest.raises(QuadobsError, match="'augmented-bias' takes ranges only"):
        check_replay(tdoa, ["augmented-bias"])
