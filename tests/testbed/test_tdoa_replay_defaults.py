"""The replay's noise of a TDOA log from the log itself: the accelerometer's stated density sets
``q_imu`` (floored), and the self-calibration scores the held-out TDOA where the log holds no
ranges, keeping the prior unless a candidate is significantly better."""

import json
import math

import numpy as np
import pytest

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.calibration import (
    EXTEND,
    HOLD_OUT,
    calibrate,
    prediction_residuals,
    scored_kind,
)
from quadobs.testbed.logs.estimators import (
    ACCEL_NOISE,
    ReplaySetup,
    accel_noise,
    log_defaults,
)
from quadobs.testbed.logs.replay import run_replay

ANCHORS = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0]])


def _tdoa_log(q: float, seed: int = 4, duration: float = 40.0, **extra) -> RangeLog:
    """A planar vehicle's accelerometer logged at 100 Hz in the navigation frame with a white
    error of intensity ``q`` (m^2/s^3: the replay's ``q_imu``), and a TDoA3-like TDOA every 50 ms
    (anchor ``k mod 4`` against the one before) with 0.1 m of noise."""
    rng = np.random.default_rng(seed)
    h = 0.01
    t = np.arange(0.0, duration, h)
    a = np.sqrt(1e-2 / h) * rng.standard_normal((t.size, 2))
    a -= 0.02 * (np.cumsum(a, axis=0) * h)  # a weak pull keeps the walk inside the room
    v = np.array([0.2, 0.1]) + np.cumsum(a, axis=0) * h
    p = np.array([4.0, 3.0]) + np.cumsum(v, axis=0) * h
    k = np.arange(5, t.size, 5)
    i, j = np.arange(k.size) % 4, (np.arange(k.size) - 1) % 4
    r = np.linalg.norm(p[k, None, :] - ANCHORS, axis=2)
    d = r[np.arange(k.size), i] - r[np.arange(k.size), j] + 0.1 * rng.standard_normal(k.size)
    accel = a + np.sqrt(q / h) * rng.standard_normal(a.shape)
    return RangeLog(
        "tdoa-walk", np.arange(4), ANCHORS, np.empty((0, 3)), np.column_stack([t, accel]),
        float("nan"), np.column_stack([t, p, v]), input_kind="imu",
        truth_columns=("time", "x", "y", "vx", "vy"),
        tdoa=np.column_stack([t[k], i, j, d]), tdoa_std=np.full(k.size, 0.1), **extra,
    )  # fmt: skip


def test_the_stated_accelerometer_density_sets_q_imu_above_the_floor():
    assert accel_noise(None) is None and accel_noise(math.nan) is None
    assert accel_noise(1e-3) == ACCEL_NOISE  # 1e-6 m^2/s^3: below the floor
    assert accel_noise(0.2) == pytest.approx(0.04)  # a noisy part: its own square
    assert log_defaults(_tdoa_log(1e-3, duration=2.0)) == {}
    quiet = _tdoa_log(1e-3, duration=2.0, accel_noise=1e-3)
    assert log_defaults(quiet) == {"q_imu": ACCEL_NOISE}
    # the replay's setup takes it, below a given option; a log stating nothing keeps the default
    s = run_replay(quiet, estimators=["ekf"], batch=False, initial_offset=1.0)
    assert s["noise"]["q_imu"] == ACCEL_NOISE
    s = run_replay(quiet, estimators=["ekf"], batch=False, setup_options={"q_imu": 0.3})
    assert s["noise"]["q_imu"] == 0.3
    plain = run_replay(_tdoa_log(1e-3, duration=2.0), estimators=["ekf"], batch=False)
    assert plain["noise"]["q_imu"] == ReplaySetup.q_imu


def test_the_calibration_scores_held_out_tdoa_of_a_tdoa_log():
    log = _tdoa_log(1e-3, duration=20.0)
    assert scored_kind(log) == "tdoa"
    res = prediction_residuals(log, dt=0.01, estimator="tdoa-handover")
    n_scored = np.sum(log.tdoa[:, 0] >= res.t[0])
    assert res.r.size == n_scored and np.all(np.isfinite(res.r))
    # every HOLD_OUT-th TDOA held out, the rest corrected with
    assert abs(np.mean(res.held) - 1.0 / HOLD_OUT) < 0.01
    # converged: the residuals are the TDOA noise (0.1 m) and what the prediction adds
    assert 0.08 < np.sqrt(np.mean(res.r**2)) < 0.2


def test_a_wrong_tdoa_prior_is_replaced_and_a_right_one_kept():
    log = _tdoa_log(1e-3)
    wrong = calibrate(log, dt=0.01, setup_options={"q_imu": 1.0})  # a thousand times the truth's
    assert "TDOA" in wrong.reason and wrong.biases is None and len(wrong.scores) > 8
    # past the grid's smallest factor (4^-4): the grid goes on while its edge scores best
    assert wrong.options["q_imu"] < 4.0**-4, wrong.reason
    assert len(wrong.scores) <= 8 + EXTEND
    assert wrong.tests["noise"]["significantly_better"]
    right = calibrate(log, dt=0.01, setup_options={"q_imu": 1e-3})
    assert right.options["q_imu"] == 1e-3, right.reason
    assert not right.tests["noise"]["significantly_better"]

    def rmse(options):
        s = run_replay(log, estimators=["tdoa-handover"], dt=0.01, initial_offset=2.0,
                       batch=False, setup_options=options, burn_in=10.0)  # fmt: skip
        return s["estimators"]["tdoa-handover"]["rmse"]

    assert rmse(wrong.options) < rmse({"q_imu": 1.0})


def test_quadobs_replay_of_a_tdoa_log_calibrates_from_its_tdoa_and_its_density(tmp_path):
    from conftest import call_main

    from quadobs.testbed.logs import write_log

    folder = write_log(_tdoa_log(1e-3, duration=12.0, accel_noise=1e-3), tmp_path / "log")
    summary = tmp_path / "s.json"
    code, out, err = call_main(
        ["replay", str(folder), "--dt", "0.01", "--estimators", "tdoa-handover,ekf",
         "--summary", str(summary), "--no-progress"]
    )  # fmt: skip
    assert code == 0, err
    assert "a log of TDOA, scored by tdoa-handover" in out
    s = json.loads(summary.read_text())
    # the candidates are the log's prior (its density, floored) times 4^j, not the default's
    scores = s["calibration"]["noise_scores"]
    assert len(scores) == 8 and "0.0025" in scores and "0.01" in scores and "0.64" not in scores
    assert s["noise"]["q_imu"] == s["calibration"]["process_noise"]["q_imu"]
