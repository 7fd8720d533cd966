"""The self-calibration keeps the prior defaults unless a candidate predicts the held-out ranges
significantly better: the paired test itself, a log whose prior is right, a log whose prior is
wrong, a log with per-anchor biases."""

import dataclasses

import numpy as np
import pytest

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.calibration import (
    BLOCKS,
    Residuals,
    calibrate,
    compare,
)
from quadobs.testbed.logs.replay import run_replay

ANCHORS = np.array([[0.0, 0.0], [12.0, 0.0], [12.0, 9.0], [0.0, 9.0]])


def _residuals(r: np.ndarray) -> Residuals:
    """Every residual held out, in time order."""
    return Residuals(r, np.zeros(r.size, dtype=np.int64), np.ones(r.size, bool), np.arange(r.size))


def test_the_paired_test_needs_a_significant_improvement():
    rng = np.random.default_rng(0)
    noise = 0.1 * rng.standard_normal(4000)
    reference = _residuals(noise + 0.05)
    same = compare(_residuals(noise + 0.05), reference)
    assert not same.better and same.difference == 0.0 and same.score == same.reference_score
    # a 5 cm smaller systematic error under 0.1 m of noise: paired, the noise cancels
    better = compare(_residuals(noise), reference)
    assert better.better and better.score < better.reference_score
    # as good on average, differently noisy: not significant
    other = compare(_residuals(0.1 * rng.standard_normal(4000) + 0.05), reference)
    assert not other.better
    # a non-finite prediction counts as the cap, and too few held-out ranges decide nothing
    broken = noise.copy()
    broken[::7] = np.nan
    assert not compare(_residuals(broken), reference).better
    assert not compare(_residuals(noise[:5]), _residuals(noise[:5] + 1)).better  # two blocks
    short = compare(_residuals(noise[:12]), _residuals(noise[:12] + 1))  # six blocks
    assert short.better and BLOCKS == 20


def test_a_margin_asks_for_an_effect_beyond_significance():
    """The 5 cm systematic gain of the test above lowers the mean loss by 0.05^2 = 0.0025 m^2
    (the cross term averages out): significant, and beyond a margin of a tenth of it, but not
    beyond the margin sigma^2 / 3 = 0.0033 m^2 of 0.1 m noise in 3-D (step 7's effect)."""
    rng = np.random.default_rng(0)
    noise = 0.1 * rng.standard_normal(4000)
    candidate, reference = _residuals(noise), _residuals(noise + 0.05)
    plain = compare(candidate, reference)
    assert plain.better and abs(plain.difference + 0.0025) < 0.0005, plain
    assert compare(candidate, reference, margin=0.00025).better
    large = compare(candidate, reference, margin=0.1**2 / 3)
    assert not large.better and large.difference == plain.difference, large
    assert large.as_dict()["margin"] == pytest.approx(0.01 / 3)


def test_the_effect_margin_is_a_noise_sized_position_error_projected_on_a_range():
    from quadobs.testbed.logs.calibration import effect_margin, range_noise_std

    log = _random_acceleration_log(0.1)
    assert effect_margin(log, {"range_sigma": 0.2}) == pytest.approx(0.2**2 / 2)
    stated = dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], 0.3))
    assert range_noise_std(stated, {"range_sigma": 0.2}) == pytest.approx(0.3)  # the log's own
    assert effect_margin(stated) == pytest.approx(0.3**2 / 2)
    partly = stated.range_std.copy()
    partly[::2] = np.nan  # stated on some rows only: the filters take range_sigma, as here
    assert range_noise_std(dataclasses.replace(log, range_std=partly), {"range_sigma": 0.2}) == 0.2


def _random_acceleration_log(q: float, biases=(0.0, 0.0, 0.0, 0.0), seed: int = 3) -> RangeLog:
    """40 s of a vehicle driven by a white acceleration of intensity ``q`` (m^2/s^3), ranged at
    20 Hz to the four anchors in turn with 0.1 m noise and per-anchor ``biases``; no inputs."""
    rng = np.random.default_rng(seed)
    h = 0.01
    t = np.arange(0.0, 40.0, h)
    a = np.sqrt(q / h) * rng.standard_normal((t.size, 2))
    v = np.array([0.1, 0.05]) + np.cumsum(a, axis=0) * h
    p = np.array([5.0, 4.0]) + np.cumsum(v, axis=0) * h
    k = np.arange(0, t.size, 5)
    anchor = np.arange(k.size) % 4
    rho = np.linalg.norm(p[k] - ANCHORS[anchor], axis=1) + np.asarray(biases)[anchor]
    rho += 0.1 * rng.standard_normal(k.size)
    return RangeLog(
        "walk", np.arange(4), ANCHORS, np.column_stack([t[k], anchor, rho]), np.empty((0, 1)),
        float("nan"), np.column_stack([t, p, v]), input_kind="none",
        truth_columns=("time", "x", "y", "vx", "vy"),
    )  # fmt: skip


def test_a_right_prior_is_kept():
    log = _random_acceleration_log(1e-3)
    cal = calibrate(log, setup_options={"range_sigma": 0.1, "q_acc": 1e-3})
    assert cal.biases is None and cal.options["q_acc"] == 1e-3, cal.reason
    assert (
        not cal.tests["noise"]["significantly_better"]
        and not cal.tests["biases"]["significantly_better"]
    )
    assert "the prior" in cal.reason and len(cal.scores) == 8


def test_a_wrong_prior_is_replaced_and_the_replay_is_not_worse():
    log = _random_acceleration_log(1e-3)
    prior = {"range_sigma": 0.1, "q_acc": 1.0}  # a thousand times the truth's
    cal = calibrate(log, setup_options=prior)
    assert cal.options["q_acc"] < 0.1 and cal.tests["noise"]["significantly_better"], cal.reason

    def rmse(options):
        s = run_replay(log, estimators=["ekf"], initial_offset=2.0, batch=False,
                       setup_options=options, burn_in=5.0)  # fmt: skip
        return s["estimators"]["ekf"]["rmse"]

    assert rmse(cal.options) < rmse(prior)


def circle_laps(biases, seed: int = 5, period: float = 40.0) -> RangeLog:
    """Laps of a 3.5 m circle about the room's centre in 40 s (one lap a ``period``), one anchor
    at a time at 20 Hz, with per-anchor ``biases`` and 0.1 m of Gaussian noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 40.0, 0.05)
    w = 2.0 * np.pi / period
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


def test_per_anchor_biases_are_found_and_applied():
    truth = np.array([0.4, -0.3, 0.25, 0.0])
    options = {"range_sigma": 0.1, "q_acc": 1e-2}
    cal = calibrate(circle_laps(truth), setup_options=options, noise=False)
    assert cal.biases is not None, cal.reason
    # a bias trades against the position: the fixed point comes within half the biases' size
    err = np.sqrt(np.mean((cal.biases - truth) ** 2))
    assert err < 0.5 * np.sqrt(np.mean(truth**2)), cal.biases
    assert cal.held_out["with_biases"] < cal.held_out["without"]
    assert cal.summary()["biases"] == pytest.approx(list(cal.biases))


def test_the_replays_bias_filters_beat_the_ekf_on_biased_ranges_and_refuse_tdoa():
    """``ekf-bias`` / ``ukf-bias`` of the replay (the default set holds ``ekf-bias``)."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.replay import check_replay, default_estimators

    log = circle_laps(np.array([0.4, -0.3, 0.25, 0.0]))
    assert "ekf-bias" in default_estimators(log)
    names = ["ekf", "ekf-bias", "ukf-bias"]
    options = {"range_sigma": 0.1, "q_acc": 1e-2}
    s = run_replay(log, estimators=names, initial_offset=2.0, batch=False,
                   setup_options=options, burn_in=10.0)["estimators"]  # fmt: skip
    for name in names[1:]:
        assert s[name]["diverged"] is None
        assert s[name]["rmse"] < 0.6 * s["ekf"]["rmse"], (name, s[name]["rmse"], s["ekf"]["rmse"])
    tdoa = RangeLog(
        "tdoa", np.arange(4), ANCHORS, np.empty((0, 3)), np.empty((0, 1)), float("nan"),
        None, input_kind="none", tdoa=np.array([[0.0, 0, 1, 0.5], [0.1, 1, 2, -0.2]]),
    )  # fmt: skip
    with pytest.raises(
        QuadobsError, match="'ekf-bias' estimates range biases and the log holds TDOA"
    ):
        check_replay(tdoa, ["ekf-bias"])


def test_a_bias_filter_is_scored_with_its_own_bias_estimates():
    """The prequential residual of a filter that holds the biases as states subtracts its own
    estimate: on the ranges as logged its residuals are centred per anchor, the EKF's are not."""
    from quadobs.testbed.logs.calibration import prediction_residuals

    truth = np.array([0.4, -0.3, 0.25, 0.0])
    log = circle_laps(truth)
    options = {"range_sigma": 0.1, "q_acc": 1e-2}
    for name, centred in (("ekf-bias", True), ("ekf", False)):
        res = prediction_residuals(log, estimator=name, setup_options=options)
        r, h = res.fitted()
        medians = np.array([np.median(r[h == j]) for j in range(4)])
        assert (np.max(np.abs(medians)) < 0.1) == centred, (name, medians)


def test_the_biases_chi_square_under_the_bias_states_prior():
    from scipy.stats import chi2

    from quadobs.testbed.logs.calibration import SIGNIFICANCE, bias_prior_std, outside_prior

    sigma = bias_prior_std(circle_laps(np.zeros(4)))
    assert sigma == pytest.approx([0.5] * 4)
    value, limit = outside_prior([0.5, -1.0, 0.0, 0.25], sigma)
    assert value == pytest.approx(1.0 + 4.0 + 0.0 + 0.25)
    assert limit == pytest.approx(chi2.ppf(1.0 - SIGNIFICANCE, 4)) and 11.0 < limit < 11.2


def test_bias_filters_take_the_calibrated_biases_only_where_the_data_contradict_their_prior(
    monkeypatch,
):
    """Biases of one sign, two to three times the bias states' 0.5 m prior: the calibrated
    biases lie outside that prior and predict the held-out ranges significantly better through
    ``ekf-bias``: they are kept for it (and it is far better for them); an estimator without
    bias states is not checked; a filter that takes the ranges as logged gets exactly what it
    gets without biases, while the others get the biases. Biases within the prior: kept only
    on the paired held-out test's verdict (the rule checked for either verdict)."""
    from quadobs.testbed.logs.calibration import estimator_biases

    log = circle_laps(np.array([1.0, 1.3, 1.1, 1.4]))
    options = {"range_sigma": 0.1, "q_acc": 1e-2}
    cal = calibrate(log, setup_options=options, noise=False)
    assert cal.biases is not None, cal.reason
    assert estimator_biases(log, cal, ["ekf", "ekf-bias"]) == ()
    assert list(cal.per_estimator) == ["ekf-bias"], cal.per_estimator
    test = cal.summary()["per_estimator"]["ekf-bias"]
    assert test["biases"] == "calibrated" and test["prior_chi2"] > test["prior_limit"], test
    assert "ekf-bias (range biases as states): the calibrated biases subtracted" in cal.reason

    def replay(biases, as_logged=()):
        s = run_replay(log, estimators=["ekf", "ekf-bias"], initial_offset=2.0, batch=False,
                       setup_options=options, burn_in=10.0, biases=biases, as_logged=as_logged)  # fmt: skip
        return s, {k: e["rmse"] for k, e in s["estimators"].items()}

    s, logged = replay(cal.biases, as_logged=["ekf-bias"])
    _, raw = replay(None)
    _, applied = replay(cal.biases)
    assert s["ranges_as_logged"] == ["ekf-bias"]
    assert logged["ekf-bias"] == raw["ekf-bias"] and logged["ekf"] == applied["ekf"]
    assert applied["ekf-bias"] < 0.5 * logged["ekf-bias"], (applied, logged)

    # biases inside the prior: taken only where the paired held-out test says they predict
    # significantly better through the filter itself. Here the two starts' held-out scores
    # differ by a fraction of a millimetre, so the test's verdict depends on the draw; the rule
    # is checked for both verdicts, the test's own statistics being those of the data
    from quadobs.testbed.logs import calibration as calibration_module

    small = circle_laps(np.array([0.4, -0.3, 0.25, 0.0]))
    cal_small = calibrate(small, setup_options=options, noise=False)
    assert cal_small.biases is not None, cal_small.reason
    real_compare = calibration_module.compare
    for verdict in (True, False):

        def forced(*args, verdict=verdict, **kwargs):
            return dataclasses.replace(real_compare(*args, **kwargs), better=verdict)

        cal = dataclasses.replace(cal_small, per_estimator={}, reason=cal_small.reason)
        monkeypatch.setattr(calibration_module, "compare", forced)
        logged_names = estimator_biases(small, cal, ["ekf-bias"])
        monkeypatch.setattr(calibration_module, "compare", real_compare)
        test = cal.per_estimator["ekf-bias"]
        assert test["prior_chi2"] < test["prior_limit"], test
        assert test["margin"] == pytest.approx(0.1**2 / 2), test  # step 7's effect, in 2-D
        assert test["significantly_better"] is verdict, test
        assert test["biases"] == ("calibrated" if verdict else "as logged"), test
        assert logged_names == (() if verdict else ("ekf-bias",)), test


def test_the_bias_states_prior_from_the_calibrated_biases_spread_where_asked():
    """``--tune bias_prior=log``: at step 5's end the biases' prior of the filters that hold
    them as states is the maximum-likelihood spread ``sqrt(mean c_h^2)`` of the calibrated
    biases, within the ranges' noise and the range model's 0.5 m; by default it is not set
    (0.5 m); the replay's bias filters start from the prior set, and from 0.5 m where none is."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs import calibration as calibration_module
    from quadobs.testbed.logs.bias_estimators import build_ekf_bias
    from quadobs.testbed.logs.calibration import biases_spread
    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        build_ekf_bias_imu,
        build_ekf_bias_imu_nlos,
        parse_tuning,
        tuning_fields,
    )

    assert biases_spread([0.3, -0.4, 0.0, 0.0], 0.1, 0.5) == pytest.approx(0.25)
    assert biases_spread([0.01, -0.02, 0.0, 0.03], 0.1, 0.5) == 0.1
    assert biases_spread([2.0, 3.0, 4.0, 5.0], 0.1, 0.5) == 0.5
    assert biases_spread([0.2, float("nan"), 0.1, 0.0], 0.1, 0.5) == 0.5

    truth = np.array([0.4, -0.3, 0.25, 0.0])
    log = circle_laps(truth)
    options = parse_tuning(["range_sigma=0.1", "q_acc=1e-2", "bias_prior=log"])
    assert options["bias_prior"] == "log" and tuning_fields(options).get("bias_prior") is None
    cal = calibrate(log, setup_options=options, noise=False)
    spread = float(np.sqrt(np.mean(np.square(cal.candidate))))
    assert 0.1 < spread < 0.5, cal.candidate
    assert cal.options["bias_prior"] == pytest.approx(spread)
    assert f"the biases' prior {spread:.3f} m" in cal.reason
    assert calibration_module.bias_prior_std(log, cal.options) == pytest.approx([spread] * 4)
    default = {"range_sigma": 0.1}  # not asked: nothing set, the range model's 0.5 m
    assert calibration_module._set_bias_prior(log, default, cal.candidate) == ""
    assert "bias_prior" not in default
    assert calibration_module.bias_prior_std(log, default) == pytest.approx([0.5] * 4)

    beacons = np.array([[-3, -3, 0.2], [3, -3, 0.2], [3, 3, 2.8], [-3, 3, 2.8]], dtype=float)
    base = {"beacons": beacons, "dt": 0.01, "model": "imu", "heading0": 0.0,
            "input_kind": "imu_body", "range_median": 4.0, "range_sigma": 0.1}  # fmt: skip
    x0 = np.zeros(6)
    for prior, variance in ((None, 0.25), (0.2, 0.04)):
        s = ReplaySetup(**base, bias_prior=prior)
        for est in (
            build_ekf_bias(s, x0, "ekf-bias", np.zeros((6, 6))),
            build_ekf_bias_imu(s, x0),
            build_ekf_bias_imu_nlos(s, x0),
        ):
            assert np.diag(est._P)[-4:] == pytest.approx([variance] * 4), (prior, est.name)
    assert parse_tuning(["bias_prior=0.5"]) == {"bias_prior": 0.5}
    with pytest.raises(QuadobsError, match=r"bias_prior: expected a positive finite number"):
        ReplaySetup(**base, bias_prior=-0.1)
