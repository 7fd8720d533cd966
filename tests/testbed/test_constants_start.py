"""Step 10 of the self-calibration: each filter's constant states started from a first pass."""

from __future__ import annotations

import json

import numpy as np
from test_calibration import ANCHORS, circle_laps

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.calibration import calibrate, estimator_biases
from quadobs.testbed.logs.constants_start import START_KEY, estimator_constants
from quadobs.testbed.logs.replay import run_replay

OPTIONS = {"range_sigma": 0.1, "q_acc": 1e-2}
TRUTH = np.array([0.4, -0.3, 0.25, 0.0])


def _heading_tests():
    """tests/estimators/test_heading_ekf.py as a module (its logs of a circling vehicle), loaded
    by its path: that folder is on the import path only where its tests were collected."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "estimators" / "test_heading_ekf.py"
    spec = importlib.util.spec_from_file_location("heading_ekf_tests", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _calibrated(log: RangeLog, names):
    cal = calibrate(log, setup_options=OPTIONS, noise=False)
    estimator_biases(log, cal, names)
    estimator_constants(log, cal, names)
    return cal


def test_a_bias_filter_starts_from_its_first_pass_and_the_replay_places_it_better():
    """``ekf-bias`` on biased ranges: the first pass ends near the biases its ranges hold, the
    start is kept (the EKF holds no constant), and the replay from 2 m off is closer from it
    (measured 0.271 -> 0.174 m over the 40 s)."""
    log = circle_laps(TRUTH, seed=6)
    cal = _calibrated(log, ["ekf", "ekf-bias"])
    assert list(cal.constants) == ["ekf-bias"], cal.reason
    record = cal.constants["ekf-bias"]
    assert record["start"] == "first pass" and record["states"] == 4
    assert record["score"] <= record["reference_score"]
    mean, cov = cal.options[START_KEY]["ekf-bias"]
    subtracted = cal.biases is not None and "ekf-bias" not in cal.as_logged
    seen = TRUTH - cal.biases if subtracted else TRUTH  # the biases left in its ranges
    assert np.max(np.abs(mean - seen)) < 0.1 and np.all(np.diag(cov) < 0.01)
    assert "ekf-bias (4 constant states): started from a first pass" in cal.reason
    json.dumps(cal.summary())  # plain data

    def rmse(options) -> float:
        summary = run_replay(
            log, estimators=["ekf-bias"], initial_offset=2.0, batch=False, setup_options=options,
            biases=cal.biases, as_logged=cal.as_logged,
        )  # fmt: skip
        return summary["estimators"]["ekf-bias"]["rmse"]

    own = {k: v for k, v in cal.options.items() if k != START_KEY}
    assert rmse(cal.options) < 0.8 * rmse(own)


def test_a_start_that_predicts_the_held_out_ranges_worse_is_not_kept():
    """Biases that change sign halfway: the first pass ends at the second half's, which predict
    the first half's ranges worse than the filter's own prior; the filter keeps that prior."""
    log = circle_laps(TRUTH)
    ranges = log.ranges.copy()
    late = ranges[:, 0] >= 20.0
    ranges[late, 2] -= 2.0 * TRUTH[ranges[late, 1].astype(int)]
    changed = RangeLog(
        "lap", np.arange(4), ANCHORS, ranges, log.inputs, log.heading0, log.truth,
        input_kind="none", truth_columns=log.truth_columns,
    )  # fmt: skip
    cal = _calibrated(changed, ["ekf-bias"])
    record = cal.constants["ekf-bias"]
    assert record["start"] == "prior" and record["score"] > record["reference_score"], cal.reason
    assert START_KEY not in cal.options
    assert "its own prior, a first pass through the log predicting worse" in cal.reason


def test_a_first_pass_that_gives_up_starts_nothing():
    """``ukf-lever`` on ranges with 1 m of bias left in one anchor's (the log of
    tests/estimators/test_heading_ekf.py whose lever arm leaves its prior): its first pass is
    reported diverged, so its constants start nothing and the replay still reports it."""
    from quadobs.testbed.logs.calibration import Calibration

    log = _heading_tests().circle_log(bias=0.0, heading_error=0.0, duration=40.0)
    log.ranges[log.ranges[:, 1] == 0, 2] += 1.0
    options = {"range_sigma": 0.05, "q_xy": 1e-3, "q_xy_heading": 1e-3}
    cal = Calibration(None, dict(options), {}, "", np.zeros(4))
    estimator_constants(log, cal, ["ukf-lever"])
    assert cal.constants["ukf-lever"] == {
        "start": "prior",
        "why": "its first pass gave up (reported diverged)",
    }
    assert START_KEY not in cal.options


def test_an_averages_members_take_their_own_starts():
    """The replay builds ``ekf-bias-imu-average`` (an excess known: two members) with each
    member started from the start of its own name."""
    from test_replay_in_time import _imu_body_log

    from quadobs.estimators.constants import constant_filters
    from quadobs.testbed.logs.estimators import build_replay_estimators, replay_setup
    from quadobs.testbed.worlds.replay import ReplayWorld

    log = _imu_body_log(False)
    q = log.beacons.shape[0]
    starts = {
        "ekf-bias-imu": (np.full(q, 0.1), 0.01 * np.eye(q)),
        "ekf-bias-imu-nlos": (np.full(q, -0.1), 0.02 * np.eye(q)),
    }
    options = {"nlos_median": 0.4, "nlos_shape": 0.7, START_KEY: starts}
    setup = replay_setup(log, ReplayWorld(log, 0.1, "imu"), options, 3.0)
    average = build_replay_estimators(setup, ["ekf-bias-imu-average"], np.zeros(6))[0]
    members = constant_filters(average)
    assert [m.name for m in members] == ["ekf-bias-imu", "ekf-bias-imu-nlos"]
    for m in members:
        mean, cov = m.constants_estimate()
        np.testing.assert_allclose(mean, starts[m.name][0])
        np.testing.assert_allclose(cov, starts[m.name][1])


def test_the_replay_command_reports_each_start_and_none_with_the_measurements_on_its_grid(
    tmp_path,
):
    """``quadobs replay``: the summary's ``calibration.constants`` names the start of
    ``ekf-bias``; with ``--set noise.*`` (every filter then takes the calibrated biases) the step
    is not run."""
    from quadobs.cli import main
    from quadobs.testbed.logs import write_log

    folder = tmp_path / "laps"
    write_log(circle_laps(TRUTH, seed=6), folder)
    base = ["replay", str(folder), "--no-progress", "--estimators", "ekf,ekf-bias"]
    runs = {"self": [], "grid": ["--set", "noise.dropout=0.1"]}
    cal = {}
    for key, extra in runs.items():
        path = tmp_path / f"{key}.json"
        assert main([*base, *extra, "--summary", str(path)]) == 0
        cal[key] = json.loads(path.read_text()).get("calibration")
    assert cal["self"]["constants"]["ekf-bias"]["start"] == "first pass"
    assert cal["self"]["constants"]["ekf-bias"]["states"] == 4
    assert "ekf" not in cal["self"]["constants"]
    assert "constants" not in cal["grid"]


def test_the_tags_pattern_is_kept_as_states_only_where_the_held_out_ranges_ask_for_it():
    """``ukf-height-lever`` on the S-curve in a small room: with a tag's pattern of 0.18 m over
    bearings in the ranges the filter that holds it predicts the held-out ranges significantly
    better, and the options the replay is built from take it; without one it does not, and the
    filter stays as it was; given by ``--tune`` (in the options) it is not tried."""
    from quadobs.testbed.logs.calibration import Calibration

    module = _heading_tests()
    options = {"range_sigma": 0.02, "q_xy": 1e-3, "q_xy_heading": 1e-3}
    chosen = {}
    for name, (c, s) in (("pattern", (0.15, -0.20)), ("none", (0.0, 0.0))):
        log = module.pattern_room_log(c, s, noise=0.02, seed=3)
        cal = Calibration(None, dict(options), {}, "", np.zeros(4))
        estimator_constants(log, cal, ["ukf-height-lever"])
        chosen[name] = cal
    kept = chosen["pattern"].constants["ukf-height-lever"]["pattern"]
    assert kept["kept"] and kept["score"] < 0.8 * kept["reference_score"], chosen["pattern"].reason
    assert chosen["pattern"].options["tag_pattern"] == 1.0
    assert chosen["pattern"].constants["ukf-height-lever"]["states"] == 12
    assert "the tag's pattern as states kept" in chosen["pattern"].reason
    left = chosen["none"].constants["ukf-height-lever"]
    assert not left["pattern"]["kept"] and "tag_pattern" not in chosen["none"].options
    assert left["states"] == 10 and "as states not kept" in chosen["none"].reason
    given = Calibration(None, {**options, "tag_pattern": 0.0}, {}, "", np.zeros(4))
    estimator_constants(
        module.pattern_room_log(0.15, -0.2, noise=0.02, seed=3), given, ["ukf-height-lever"]
    )
    assert "pattern" not in given.constants["ukf-height-lever"] and "pattern" not in given.reason
