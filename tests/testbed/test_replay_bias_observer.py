"""``augmented-bias`` in ``quadobs replay``: the observer with the anchors' range biases in its
immersion, built with the settings of the replay's augmented observer."""

import numpy as np
import pytest

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

ANCHORS = np.array([[0.0, 0.0], [12.0, 0.0], [12.0, 9.0], [0.0, 9.0]])


def _circle_log(biases) -> RangeLog:
    """Laps of a 3.5 m circle about the room's centre, one anchor at a time at 20 Hz, with
    per-anchor biases and 0.1 m of Gaussian noise."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 40.0, 0.05)
    w = 2.0 * np.pi / 20.0
    p = np.array([6.0, 4.5]) + 3.5 * np.column_stack([np.cos(w * t), np.sin(w * t)])
    v = 3.5 * w * np.column_stack([-np.sin(w * t), np.cos(w * t)])
    anchor = np.arange(t.size) % 4
    rho = np.linalg.norm(p - ANCHORS[anchor], axis=1) + np.asarray(biases)[anchor]
    rho += 0.1 * rng.standard_normal(t.size)
    return RangeLog(
        "lap", np.arange(4), ANCHORS, np.column_stack([t, anchor, rho]), np.empty((0, 1)),
        float("nan"), np.column_stack([t, p, v]), input_kind="none",
        truth_columns=("time", "x", "y", "vx", "vy"),
    )  # fmt: skip


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
