"""The non-line-of-sight excess estimated from residuals (:mod:`quadobs.testbed.logs.excess_model`)."""

from types import SimpleNamespace

import numpy as np
import pytest

from quadobs.testbed.logs.excess_model import calibrated_excess, excess_model

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
