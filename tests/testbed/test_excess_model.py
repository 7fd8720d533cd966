"""The non-line-of-sight excess estimated from residuals (:mod:`quadobs.testbed.logs.excess_model`)."""

from types import SimpleNamespace

import numpy as np
import pytest

from quadobs.testbed.logs.excess_model import (
    MIN_TAIL,
    calibrated_excess,
    excess_model,
    fit_excess,
    tail_signs,
)

Q, SIGMA = 8, 0.1


def _residuals(n, seed, tail="excess"):
    """``(r, h)``: anchors' centres drawn with a 0.2 m spread, noise ``SIGMA``, and a log-normal
    excess (median 0.3 m, shape 0.6) on 30 % of them, a Student-t(3) error of either sign in
    place of both, or the Gaussian alone."""
    rng = np.random.default_rng(seed)
    h = rng.integers(0, Q, n)
    centre = rng.normal(0.0, 0.2, Q)
    if tail == "symmetric":
        return centre[h] + SIGMA * rng.standard_t(3, n), h
    r = centre[h] + SIGMA * rng.standard_normal(n)
    if tail == "excess":
        blocked = rng.random(n) < 0.3
        r += blocked * 0.3 * np.exp(0.6 * rng.standard_normal(n))
    return r, h


def test_the_mixture_recovers_a_stated_excess():
    """Drawn from the model itself: the median, shape, fraction and core come back close to the
    values drawn (2000 residuals), and the data identify it."""
    r, h = _residuals(2000, 0)
    fit, ok, why = excess_model(r, h, Q, SIGMA)
    assert ok and why.startswith("estimated")
    assert fit.median == pytest.approx(0.3, rel=0.15)
    assert fit.shape == pytest.approx(0.6, abs=0.12)
    assert fit.fraction == pytest.approx(0.3, abs=0.06)
    assert fit.sigma == pytest.approx(SIGMA, rel=0.1)
    assert fit.upper > 10 * max(fit.lower, 1)


@pytest.mark.parametrize("tail", ["symmetric", "gaussian"])
def test_tails_of_either_sign_do_not_identify_an_excess(tail):
    """A heavy tail of either sign (Student's t) or none: the tails above and below the centre
    are alike, so no excess is taken (the filters keep the one-sided gate)."""
    r, h = _residuals(1500, 1, tail)
    _, ok, why = excess_model(r, h, Q, SIGMA)
    assert not ok and "not identified" in why


def test_the_tails_are_counted_about_a_centre_the_fit_does_not_move():
    """A Student-t(3) error made exactly symmetric about each anchor's centre (each draw and its
    negative, 4000 residuals): counted about each anchor's median, the tails above and below
    are equal however the mixture is fitted. The fit's own centres ``mu_h`` sit below the
    median where it puts excess on the upper tail (here 48 above against 42 below about
    them), which would make a symmetric tail look one-sided."""
    rng = np.random.default_rng(2)
    half = rng.integers(0, 4, 2000)
    x = SIGMA * rng.standard_t(3, half.size)
    centre = rng.normal(0.0, 0.2, 4)
    h = np.concatenate([half, half])
    r = centre[h] + np.concatenate([x, -x])
    fit, ok, why = excess_model(r, h, 4, SIGMA)
    assert not ok and "not identified" in why
    assert fit.fraction > 0.0 and fit.upper >= MIN_TAIL
    assert fit.upper == fit.lower and fit.p_value > 0.5
    about_fit = tail_signs(r - fit.centres[h], fit.sigma)
    assert about_fit[0] > about_fit[1]  # the bias that counting about the median removes


def test_without_the_ranges_noise_nothing_is_fitted():
    """Where the ranges' own noise is unknown (neither stated nor shown by the ranges), the
    residuals are not read; a log that states its ranges Gaussian is not fitted either."""
    r, h = _residuals(500, 2)
    fit, ok, why = excess_model(r, h, Q, None)
    assert fit is None and not ok and "noise is not known" in why
    log = SimpleNamespace(range_errors="gaussian", beacons=np.zeros((Q, 3)))
    options = {}
    summary, why = calibrated_excess(log, SimpleNamespace(r=r, h=h), options)
    assert summary == {"chosen": False} and "Gaussian" in why and options == {}


def test_the_replays_range_rule_follows_what_the_setup_knows():
    """The range-bias filters' rule: none for ranges stated Gaussian, the excess's mixture where
    the setup knows it (at the probability of ``gate``; ``ekf-bias-imu``), else the one-sided
    gate (and always for ``ekf-bias`` and ``ukf-bias``)."""
    from quadobs.estimators.robust import ExcessMixture, SkewedGate
    from quadobs.testbed.logs.bias_estimators import range_rule

    def setup(**kw):
        base = {"gate": None, "range_errors": "", "nlos_median": None, "nlos_shape": None}
        return SimpleNamespace(**{**base, **kw})

    assert range_rule(setup(range_errors="gaussian")) is None
    assert isinstance(range_rule(setup()), SkewedGate)
    rule = range_rule(setup(nlos_median=0.4, nlos_shape=0.7, gate=10.83))
    assert isinstance(rule, ExcessMixture)
    assert (rule.median, rule.shape) == (0.4, 0.7)
    assert rule.probability == pytest.approx(0.999, abs=1e-5)
    known = setup(nlos_median=0.4, nlos_shape=0.7)
    assert isinstance(range_rule(known, excess=False), SkewedGate)  # ekf-bias, ukf-bias


def test_the_chains_stationary_probability_is_tuned_within_zero_and_one():
    """``--tune nlos_prior=P``: the excess mixture's chain of sight at ``P`` (the setup's
    default the mixture's uninformed 0.5); a value that is not a probability is refused in
    one line, before any replay."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.bias_estimators import range_rule
    from quadobs.testbed.logs.estimators import ReplaySetup, parse_tuning

    assert ReplaySetup.nlos_prior == 0.5
    assert parse_tuning(["nlos_prior=0.1"]) == {"nlos_prior": 0.1}
    for bad in ("0", "1", "1.5", "-0.2"):
        with pytest.raises(QuadobsError, match=r"nlos_prior: expected a probability in \(0, 1\)"):
            parse_tuning([f"nlos_prior={bad}"])
    base = {"gate": None, "range_errors": "", "nlos_median": 0.4, "nlos_shape": 0.7}
    assert range_rule(SimpleNamespace(**base)).nlos == 0.5
    tuned = range_rule(SimpleNamespace(**base, nlos_prior=0.1))
    assert tuned.nlos == 0.1
    # a lower stationary probability: a range two noise sd long is read as less likely blocked
    assert (
        tuned.posterior(0.2, 0.01)[2] < range_rule(SimpleNamespace(**base)).posterior(0.2, 0.01)[2]
    )


def test_the_calibration_step_gives_the_filters_an_identified_excess():
    """A log whose ranges state their noise and whose residuals show an excess: the step sets
    ``nlos_median`` and ``nlos_shape`` for the range-bias filters and says so; options that
    already state them are left as they are."""
    r, h = _residuals(1000, 3)
    log = SimpleNamespace(
        range_errors="", beacons=np.zeros((Q, 3)), range_std=np.full(r.size, SIGMA)
    )
    options = {}
    summary, why = calibrated_excess(log, SimpleNamespace(r=r, h=h), options)
    assert summary["chosen"] and why.startswith("estimated")
    assert options == {"nlos_median": summary["median"], "nlos_shape": summary["shape"]}
    stated = {"nlos_median": 0.3, "nlos_shape": 0.6}
    assert calibrated_excess(log, SimpleNamespace(r=r, h=h), stated)[1] == "as given"
    assert stated == {"nlos_median": 0.3, "nlos_shape": 0.6}


def test_the_likelihood_is_the_mixtures_density():
    """``excess_nll``: a density (it integrates to one over the residual), the Gaussian's own
    negative log-likelihood where no range has an excess, a short residual the line of
    sight's alone, and a long one likelier than a short one of the same size."""
    from scipy import integrate, stats

    from quadobs.testbed.logs.excess_model import excess_nll

    args = (0.5, 0.6, 0.1, 0.15)
    mass = integrate.quad(lambda r: np.exp(-excess_nll(np.array([r]), *args)[0]), -3, 60, limit=400)
    assert mass[0] == pytest.approx(1.0, abs=1e-6)
    r = np.array([-0.2, 0.0, 0.3])
    gauss = -stats.norm(0.0, 0.15).logpdf(r)
    np.testing.assert_allclose(excess_nll(r, 0.5, 0.6, 1e-12, 0.15), gauss, rtol=1e-9)
    long, short = excess_nll(np.array([0.6, -0.6]), *args)
    sight = -np.log(0.9) - stats.norm(0.0, 0.15).logpdf(-0.6)  # the line of sight's alone
    assert short == pytest.approx(sight, rel=1e-3) and short < sight
    assert long < short


def _check(monkeypatch, mixture_noise: float, fit_excess=True):
    """``estimator_excess`` on a stand-in log: one estimator takes the mixture; its held-out
    residuals under the gate have a 0.15 m core and under the mixture ``mixture_noise``, both
    with the same excess on a tenth of the ranges."""
    from quadobs.testbed.logs import calibration as cal_mod
    from quadobs.testbed.logs.calibration import Calibration, Residuals, estimator_excess

    rng = np.random.default_rng(4)
    n = 800
    excess = (rng.random(n) < 0.1) * 0.5 * np.exp(0.6 * rng.standard_normal(n))
    z = rng.standard_normal(n)
    runs = {False: 0.15 * z + excess, True: mixture_noise * z + excess}

    def replay(log, dt, model, b, name, options):
        r = runs["nlos_median" in options]
        return Residuals(r, np.zeros(n, np.int64), np.ones(n, bool), np.arange(n, dtype=float))

    monkeypatch.setattr(cal_mod, "_replay", replay)
    monkeypatch.setattr(cal_mod, "_takes_excess", lambda log, dt, m, name, o: name == "imu")
    fit = {"chosen": fit_excess, "median": 0.5, "shape": 0.6, "fraction": 0.1, "sigma": 0.15}
    options = {"q_imu": 1.0, "nlos_median": 0.5, "nlos_shape": 0.6}
    cal = Calibration(None, options, {}, "", np.zeros(Q), excess=fit)
    estimator_excess(SimpleNamespace(), cal, ["plain", "imu"], model="imu")
    return cal


def test_the_excess_is_kept_only_where_the_held_out_ranges_say_it_helps(monkeypatch):
    """Step 9: where the mixture predicts the held-out ranges better (a tighter core), the
    excess stays in the options and the check is recorded; where it predicts them no better,
    the options lose it and the summary says the gate stays; with no excess chosen, nothing
    is replayed."""
    better = _check(monkeypatch, 0.10)
    check = better.excess["check"]["imu"]
    assert better.excess["chosen"] and better.options["nlos_median"] == 0.5
    assert check["significantly_better"] and check["score"] < check["reference_score"]
    assert "plain" not in better.excess["check"] and "significantly better" in better.reason
    same = _check(monkeypatch, 0.15)
    assert not same.excess["chosen"] and "nlos_median" not in same.options
    assert "nlos_shape" not in same.options and "the excess dropped" in same.reason
    assert same.excess["check"]["imu"]["difference"] == 0.0
    none = _check(monkeypatch, 0.10, fit_excess=False)
    assert "check" not in none.excess and none.reason == ""


def test_a_held_core_stays_where_it_is_held():
    """With the core's standard deviation held (``sigma``), the fit keeps it and recovers the
    drawn excess at the drawn noise; held wider, the core takes the smaller excesses in (a
    smaller fraction, a longer median): what the fitted core does to the prequential
    residuals' excess, whose core holds the prediction's error too."""
    r, h = _residuals(800, 0)
    fit = fit_excess(r, h, Q, 30, sigma=SIGMA)  # 30 iterations: converged here
    assert fit.median == pytest.approx(0.3, rel=0.15)
    assert fit.fraction == pytest.approx(0.3, abs=0.06)
    wide = fit_excess(r, h, Q, 30, sigma=2.0 * SIGMA)
    assert wide.fraction < fit.fraction - 0.05 and wide.median > fit.median


def test_the_steady_offset_test_is_on_for_the_mixtures_filter_and_tuned_off():
    """``ekf-bias-imu-nlos`` takes the steady-offset test where it weighs the ranges by the
    excess mixture (``--tune steady_test=0`` turns it off); under the one-sided gate (no
    excess identified) it has no chain to test; any value but 0 or 1 is refused in one line."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        build_ekf_bias_imu,
        build_ekf_bias_imu_nlos,
        parse_tuning,
    )

    beacons = np.array([[-3, -3, 0.2], [3, -3, 0.2], [3, 3, 2.8], [-3, 3, 2.8]], dtype=float)

    def setup(**kw):
        base = {
            "beacons": beacons,
            "dt": 0.01,
            "model": "imu",
            "heading0": 0.0,
            "input_kind": "imu_body",
        }
        return ReplaySetup(**{**base, "range_median": 4.0, "range_sigma": 0.1, **kw})

    x0 = np.zeros(6)
    excess = {"nlos_median": 0.4, "nlos_shape": 0.7}
    assert build_ekf_bias_imu_nlos(setup(**excess), x0).steady_test
    assert not build_ekf_bias_imu_nlos(setup(**excess, steady_test=0), x0).steady_test
    assert not build_ekf_bias_imu_nlos(setup(), x0).steady_test  # the gate: no chain
    assert not build_ekf_bias_imu(setup(**excess), x0).steady_test
    assert parse_tuning(["steady_test=0"]) == {"steady_test": 0.0}
    with pytest.raises(QuadobsError, match=r"--tune steady_test: expected 0 \(off\) or 1 \(on\)"):
        parse_tuning(["steady_test=2"])
    with pytest.raises(QuadobsError, match=r"steady_test: expected 0 \(off\) or 1 \(on\)"):
        setup(steady_test=0.5)


def test_the_summary_lists_the_steady_offset_tests_firings_only_where_it_is_on():
    """A filter with the test on reports each firing's time (``steady_offsets``, an empty
    list where it never fired); a filter with it off has no such key, so every other
    summary keeps its keys."""
    from quadobs.testbed.episode import _robust_info

    on = SimpleNamespace(steady_test=True, steady_offsets=[12.5, 30.0])
    assert _robust_info(on) == {"steady_offsets": [12.5, 30.0]}
    assert _robust_info(SimpleNamespace(steady_test=True, steady_offsets=[])) == {
        "steady_offsets": []
    }
    assert "steady_offsets" not in _robust_info(SimpleNamespace(steady_test=False))
