"""Robust corrections (chi-square gate, Huber) and the lock-out of the Kalman filters."""

import math

import numpy as np
import pytest
from scipy import stats

from quadobs.core.system import vehicle_system
from quadobs.errors import QuadobsError
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.robust import (
    ChiSquareGate,
    Huber,
    LockOut,
    chi2_threshold,
    reinitialised_covariance,
    reweight,
)

BEACONS = np.array([[-5.0, -5.0], [5.0, -5.0], [5.0, 5.0], [-5.0, 5.0]])
DT = 0.01


def test_gate_threshold_is_the_chi_square_quantile():
    # one degree of freedom: the square of the two-sided normal quantile
    assert chi2_threshold(0.999, 1) == pytest.approx(stats.norm.ppf(0.9995) ** 2)
    assert ChiSquareGate(0.95).threshold(2) == pytest.approx(-2 * np.log(0.05))
    assert "k = outputs per correction" in ChiSquareGate().describe()
    with pytest.raises(QuadobsError, match="noise.gate"):
        ChiSquareGate(5.0)


def test_huber_reweighting_closed_form():
    R, S = np.array([[0.04]]), np.array([[0.09]])
    assert reweight(Huber(1.5), np.array([0.3]), S, R) is R  # |r| = 1 <= c: unchanged
    nu = np.array([3.0])  # r = 10: weight c / r, R divided by it
    assert reweight(Huber(1.5), nu, S, R)[0, 0] == pytest.approx(0.04 * 10 / 1.5)
    assert reweight(ChiSquareGate(0.99), nu, S, R) is None
    assert reweight(None, nu, S, R) is R


def _filter(kind, x0, P0, **kw):
    system = vehicle_system(2, BEACONS)
    dyn = HeldInputModel(system, DT, input_covariance=0.01)
    out = OutputModel(system, 0.01 * np.eye(4), offsets=0.5 * (BEACONS**2).sum(1))
    cls = ExtendedKalmanFilter if kind == "ekf" else UnscentedKalmanFilter
    return cls(dyn, out, x0=x0, P0=P0, **kw)


def _outputs(p, rng, sigma=0.1, outlier=0.0):
    rho = np.linalg.norm(p - BEACONS, axis=1) + sigma * rng.standard_normal(4)
    rho[0] += outlier
    return 0.5 * rho**2 - 0.5 * (BEACONS**2).sum(1)


def _run(est, steps, rng, outlier_every=0, outlier=0.0):
    x = np.array([1.0, -0.5, 0.2, 0.1])
    for k in range(steps):
        y = _outputs(x[:2], rng, outlier=outlier if outlier_every and k % outlier_every == 0 else 0)
        est.step(np.zeros(2), y)
        x = np.concatenate([x[:2] + DT * x[2:], x[2:]])
    return np.linalg.norm(est.x_hat[:2] - x[:2])


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_huber_limits_the_pull_of_outliers(kind):
    x0, P0 = np.array([1.0, -0.5, 0.2, 0.1]), np.diag([0.01, 0.01, 0.01, 0.01])
    plain = _run(_filter(kind, x0, P0), 300, np.random.default_rng(1), 10, 8.0)
    robust = _run(_filter(kind, x0, P0, robust=Huber()), 300, np.random.default_rng(1), 10, 8.0)
    assert robust < 0.5 * plain


def test_locked_out_filter_reinitialises_and_recovers():
    # 20 m off with a prior of 0.1 m: every correction fails the gate
    x0, P0 = np.array([21.0, -0.5, 0.2, 0.1]), 0.01 * np.eye(4)
    est = _filter("ekf", x0, P0, robust=ChiSquareGate(0.999), lockout=LockOut(timeout=0.5))
    err = _run(est, 600, np.random.default_rng(2))
    assert est.lockout.resets and est.lockout.resets[0]["time"] == pytest.approx(0.51, abs=0.02)
    assert est.diverged is None and err < 0.3


def test_the_lockouts_grace_counts_from_a_clock_that_does_not_start_at_zero():
    """A log stamped in Unix seconds: the filter's time set to 1.7e9 s at its start, the grace
    counts from there (the re-initialisation as on a clock from zero, 0.51 s in), not from
    zero (which would declare a lock-out at the first rejected range, over a span of none)."""
    x0, P0 = np.array([21.0, -0.5, 0.2, 0.1]), 0.01 * np.eye(4)
    est = _filter("ekf", x0, P0, robust=ChiSquareGate(0.999), lockout=LockOut(timeout=0.5))
    est.time = 1.7e9
    assert est.lockout.since == 1.7e9
    err = _run(est, 600, np.random.default_rng(2))
    assert est.lockout.resets[0]["time"] - 1.7e9 == pytest.approx(0.51, abs=0.02)
    assert est.diverged is None and err < 0.3
    from quadobs.estimators.robust import SkewedGate

    assert SkewedGate().rejects(np.array([-0.1]), np.array([[-0.02]]))  # S lost: rejected
    assert not SkewedGate().rejects(np.array([-0.1]), np.array([[0.02]]))
    under_way = LockOut(timeout=0.5)
    under_way.observe(3.0, False, 1.0)
    under_way.begin(10.0)  # a watch already under way keeps its start
    assert under_way.since == 0.0


def test_a_lockout_after_a_silence_spans_the_silence():
    """No correction tried for 5 s (every range lost), then ranges rejected: the window reaches
    back to hold five corrections (:data:`LOCKOUT_MIN_TRIED`), so one rejected range is not a
    lock-out, three of the last five are, and the span the re-initialisation divides the
    innovation by runs from the window's start before the silence, not from its first range
    after it (0.02 s). After a re-initialisation and a silence, the span runs from the
    re-initialisation. Without a silence the span is the window's, as before."""
    lock = LockOut(timeout=2.0)
    for k in range(400):
        lock.observe(0.01 * k, True, 0.05)
    assert lock.span(3.99) == pytest.approx(2.0, abs=0.011)  # the window's start
    assert not lock.observe(9.0, False, 0.8) and not lock.observe(9.01, False, 0.8)
    assert lock.observe(9.02, False, 0.8)  # three of the last five rejected
    assert lock.span(9.02) == pytest.approx(9.02 - 3.98)
    P = reinitialised_covariance(np.eye(4) * 1e-4, np.eye(4) * 1e-4, 0.8, 2, lock.span(9.02))
    assert P[2, 2] == pytest.approx((0.8 / 5.04) ** 2)
    lock.reset(9.02, 902, "test")
    assert not any(lock.observe(15.0 + 0.01 * k, False, 0.8) for k in range(4))  # four tried
    assert lock.observe(15.04, False, 0.8)
    assert lock.span(15.04) == pytest.approx(15.04 - 9.02)  # from the re-initialisation
    steady = LockOut(timeout=2.0)
    k = 0
    while not steady.observe(0.01 * k, k < 400, 0.5):  # every range rejected from 4 s on
        k += 1
    assert steady.span(0.01 * k) == pytest.approx(2.0, abs=0.011)  # the window's start


def test_filter_out_of_resets_is_reported_diverged():
    x0, P0 = np.array([21.0, -0.5, 0.2, 0.1]), 0.01 * np.eye(4)
    lock = LockOut(timeout=0.5, max_resets=0)
    est = _filter("ekf", x0, P0, robust=ChiSquareGate(0.999), lockout=lock)
    _run(est, 200, np.random.default_rng(2))
    assert est.diverged is not None and est.diverged["step"] == 50
    assert "rejected" in est.diverged["reason"]
    assert est.corrections == 0 and est.rejected == 4 * 200  # one per range


def test_no_rule_is_bit_identical_to_the_plain_filter():
    x0, P0 = np.array([1.5, -0.5, 0.2, 0.1]), 0.5 * np.eye(4)
    a, b = _filter("ekf", x0, P0), _filter("ekf", x0, P0, lockout=LockOut(0.1))
    _run(a, 100, np.random.default_rng(3))
    _run(b, 100, np.random.default_rng(3))
    assert np.array_equal(a.x_hat, b.x_hat) and np.array_equal(a.x_covariance, b.x_covariance)


def test_multilateration_is_exact_on_noise_free_ranges():
    from quadobs.estimators.robust import multilateration

    system = vehicle_system(2, BEACONS)
    x = np.array([1.3, -2.1, 0.4, 0.2])
    cols, p = multilateration(system.C, system.d, system.output(x))
    assert cols.tolist() == [0, 1] and np.allclose(p, x[:2], atol=1e-10)
    y = system.output(x)
    y[1:] = np.nan  # one range fixes nothing
    assert multilateration(system.C, system.d, y) is None


def test_noise_gate_is_a_probability_and_says_its_degrees_of_freedom():
    from quadobs.testbed.factories import robust_settings
    from quadobs.testbed.scenario import load_scenario

    with pytest.raises(QuadobsError, match="one degree of freedom per output"):
        load_scenario("quadrotor-uwb", settings=["noise.gate=5"])
    rule = robust_settings(load_scenario("quadrotor-uwb", settings=["noise.gate=0.99"]))["robust"]
    assert rule.threshold(1) == pytest.approx(stats.chi2.ppf(0.99, 1))
    with pytest.raises(QuadobsError, match="noise.huber"):
        robust_settings(
            load_scenario("quadrotor-uwb", settings=["noise.gate=0.99", "noise.huber=1.5"])
        )


def test_skewed_gate_rejects_long_ranges_beyond_the_one_sided_quantile():
    from quadobs.estimators.robust import SkewedGate

    gate = SkewedGate(0.999, 0.95)
    assert np.isclose(gate.upper, 1.6448536, atol=1e-6)
    S = np.array([[0.04]])  # sqrt(S) = 0.2
    R = np.array([[0.01]])
    assert reweight(gate, np.array([0.2 * 1.6]), S, R) is R  # long, but within line of sight
    assert reweight(gate, np.array([0.2 * 1.7]), S, R) is None  # too long for line of sight
    assert reweight(gate, np.array([-0.2 * 3.2]), S, R) is R  # short: only the chi-square gate
    assert reweight(gate, np.array([-0.2 * 3.4]), S, R) is None  # beyond sqrt(10.83) = 3.29
    # two outputs at once: the chi-square gate with two degrees of freedom alone
    assert reweight(gate, np.array([0.4, 0.4]), 0.04 * np.eye(2), 0.01 * np.eye(2)) is not None


def test_skewed_gate_refuses_a_probability_outside_its_range():
    from quadobs.errors import QuadobsError
    from quadobs.estimators.robust import SkewedGate

    with pytest.raises(QuadobsError, match="line_of_sight"):
        SkewedGate(0.999, 0.4)
    with pytest.raises(QuadobsError, match="noise.gate"):
        SkewedGate(1.5)


def _continuous_excess_posterior(nu, S, pi, median=0.3, shape=0.6):
    """``E[e | nu]``, ``Var[e | nu]`` and ``P(NLOS | nu)`` of ``e = 0`` (probability ``1 - pi``)
    or log-normal (``pi``), ``nu ~ N(e, S)``, by quadrature of the continuous density."""
    from scipy import integrate

    lik = stats.norm(0.0, np.sqrt(S)).pdf
    f = stats.lognorm(shape, scale=median).pdf
    moments = [
        integrate.quad(lambda e, k=k: e**k * f(e) * lik(nu - e), 0.0, 20.0, points=[nu])[0]
        for k in range(3)
    ]
    evidence = (1.0 - pi) * lik(nu) + pi * moments[0]
    mean = pi * moments[1] / evidence
    return mean, pi * moments[2] / evidence - mean**2, pi * moments[0] / evidence


@pytest.mark.parametrize(
    ("nu", "S", "pi"), [(0.05, 0.012, 0.2), (0.3, 0.015, 0.5), (0.8, 0.02, 0.9)]
)
def test_excess_mixture_posterior_is_the_continuous_mixtures(nu, S, pi):
    """The discretised log-normal's posterior mean, variance and probability of
    non-line-of-sight against quadrature of the continuous density."""
    from quadobs.estimators.robust import ExcessMixture

    mean, var, p = ExcessMixture(0.3, 0.6).posterior(nu, S, pi)
    mean_c, var_c, p_c = _continuous_excess_posterior(nu, S, pi)
    assert mean == pytest.approx(mean_c, abs=1e-4)
    assert var == pytest.approx(var_c, rel=1e-3)
    assert p == pytest.approx(p_c, abs=1e-4)


def test_excess_mixture_separates_line_of_sight_from_excess_and_outliers():
    from quadobs.estimators.robust import ExcessMixture

    rule = ExcessMixture(0.3, 0.6, probability=0.999)
    sd = 0.11
    # in line of sight (the anchor's chain says so): taken nearly as it is
    shift, var, p = rule.posterior(0.0, sd**2, 0.01)
    assert shift < 0.005 and var < 1e-3 and p < 0.02
    # 0.6 m long, six standard deviations of the noise: the excess takes nearly all of it
    shift, var, p = rule.posterior(0.6, sd**2, 0.5)
    assert p > 0.999 and 0.5 < shift < 0.6 and var < sd**2
    # outliers: shorter than the gate allows, or longer than the excess's 0.999 quantile
    z = np.sqrt(chi2_threshold(0.999, 1))
    assert rule.upper == pytest.approx(0.3 * np.exp(0.6 * stats.norm.ppf(0.999)))
    assert rule.posterior(-1.01 * z * sd, sd**2) is None
    assert rule.posterior(-0.99 * z * sd, sd**2) is not None
    assert rule.posterior(rule.upper + 1.01 * z * sd, sd**2) is None
    assert rule.posterior(rule.upper + 0.99 * z * sd, sd**2) is not None
    # the chain: relaxed towards the stationary probability over the memory
    assert rule.prior(0.9, rule.memory) == pytest.approx(0.5 + 0.4 * np.exp(-1.0))
    assert rule.prior(0.9, 0.0) == 0.9
    with pytest.raises(QuadobsError, match="radio.nlos_median"):
        ExcessMixture(0.0, 0.6)
    with pytest.raises(QuadobsError, match="nlos"):
        ExcessMixture(0.3, 0.6, nlos=1.0)
    with pytest.raises(QuadobsError, match="memory"):
        ExcessMixture(0.3, 0.6, memory=0.0)


def test_bias_sight_grid_moves_its_state_of_sight_as_the_mixtures_chain():
    """Between two ranges the grid's probability of a blocked path follows
    :meth:`ExcessMixture.prior` at every bias value, and a range weighs each value of
    ``(b, sight)`` by its likelihood (checked against direct evaluation)."""
    from quadobs.estimators.robust import BiasSightGrid, ExcessMixture

    rule = ExcessMixture(0.3, 0.6)
    grid = BiasSightGrid(rule, np.zeros(2), np.full(2, 0.2), points=21)
    assert grid.predict(0, 0.0) == 0.0  # starts in line of sight
    grid.weights[0, 1] = 0.3 * grid.weights[0, 0]
    grid.weights[0, 0] *= 0.7
    assert grid.predict(0, 4.0) == pytest.approx(rule.prior(0.3, 4.0))
    before = grid.weights[1].copy()
    grid.predict(1, 0.0)
    r, S = 0.25, 0.012
    grid.update(1, r, S, S)  # no position uncertainty: no walk of the bias values
    b = grid.bias[1]
    clear = np.exp(-0.5 * (r - b) ** 2 / S)
    e, w = rule.excess[1:], np.exp(rule.log_prior[1:])
    blocked = np.exp(-0.5 * (r - b[:, None] - e) ** 2 / S) @ w
    expected = before * np.stack([clear, blocked])
    np.testing.assert_allclose(grid.weights[1], expected / expected.sum(), rtol=1e-12)


def test_bias_sight_grid_tells_a_clear_anchor_with_a_bias_from_a_blocked_one():
    """The confounding the grid resolves: ranges in line of sight long by a bias of 0.2 m
    that the filter does not know yet (its estimate 0) look, one by one, like an excess, and
    the chain on the filter's own bias estimate reads the anchor as blocked; the joint
    posterior of ``(b, sight)`` reads it as clear with its bias near 0.2 m, because the
    residuals spread by the noise alone. Ranges behind an obstacle (the log-normal excess
    above an unbiased anchor) are read as blocked, the bias near 0."""
    from quadobs.estimators.robust import BiasSightGrid, ExcessMixture

    rule, sigma, n = ExcessMixture(0.3, 0.6), 0.1, 150
    rng = np.random.default_rng(3)
    clear = 0.2 + sigma * rng.standard_normal(n)
    blocked = 0.3 * np.exp(0.6 * rng.standard_normal(n)) + sigma * rng.standard_normal(n)
    grid = BiasSightGrid(rule, np.zeros(2), np.full(2, 0.2))
    chain, t = 0.0, 0.0
    for k in range(n):
        t += 0.08
        for h, r in ((0, clear[k]), (1, blocked[k])):
            grid.predict(h, t)
            grid.update(h, r, sigma**2, sigma**2)
        chain = rule.posterior(clear[k], sigma**2, rule.prior(chain, 0.08))[2]
    assert chain > 0.9  # the chain on the bias estimate 0: "blocked"
    p_blocked = grid.blocked()
    assert p_blocked[0] < 0.05 and p_blocked[1] > 0.95
    mean = grid.bias_mean()
    assert abs(mean[0] - 0.2) < 0.04 and abs(mean[1]) < 0.06


def test_bias_filters_name_their_model_of_sight():
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter
    from quadobs.testbed.factories import _bias_filter
    from quadobs.testbed.scenario import load_scenario

    scenario = load_scenario("quadrotor-uwb-realistic")
    x0 = np.array([1.0, 2.0, 1.5, 0.0, 0.0, 0.0])
    assert _bias_filter(scenario, x0, BiasedExtendedKalmanFilter).sight_model == "chain"
    with pytest.raises(QuadobsError, match="sight_model: expected 'chain' or 'grid'"):
        est = _bias_filter(scenario, x0, BiasedExtendedKalmanFilter)
        BiasedExtendedKalmanFilter(
            est.dynamics, est.outputs, x0=est._x, P0=est._P, vehicle_n=6, sight_model="joint"
        )


def test_the_grids_bias_walk_adds_the_variance_it_is_given_and_forgets_a_wider_one():
    from quadobs.estimators.robust import BiasSightGrid, ExcessMixture

    grid = BiasSightGrid(ExcessMixture(0.2, 0.3, 0.5), np.zeros(1), np.full(1, 0.2))
    b, step = grid.bias[0], grid.bias[0, 1] - grid.bias[0, 0]
    w = np.zeros((2, b.size))
    w[0, b.size // 2] = 1.0  # the bias known at 0, in line of sight
    grid._diffuse(w, 0.003, step)  # a walk of sd 0.055 m, well inside the span of +-0.8 m
    assert w.sum() == pytest.approx(1.0)
    assert np.sum(w[0] * b * b) == pytest.approx(0.003, rel=1e-9)  # mean 0: the variance
    w[1] = 0.25 * w[0]
    grid._diffuse(w, 0.05, step)  # more than the prior's 0.04 m^2: its shape, weights kept
    np.testing.assert_allclose(w[0] / w[0].sum(), grid._prior)
    assert w[1].sum() / w[0].sum() == pytest.approx(0.25)


@pytest.mark.parametrize("S", [0.0, -1.0, float("nan")])
def test_excess_mixture_rejects_a_range_whose_variance_is_not_positive(S):
    """A covariance that lost its definiteness: the range is refused (the lock-out watch counts
    it and re-initialises the filter), not the run ended."""
    from quadobs.estimators.robust import ExcessMixture

    assert ExcessMixture(0.3, 0.6).posterior(0.1, S) is None
    assert ExcessMixture(0.3, 0.6).posterior(0.1, 0.01) is not None


def test_a_run_that_ends_inside_the_grace_still_locked_out_is_reported():
    """After its re-initialisations a filter gets a doubled grace; a run that ends within it
    while the window holds more rejected corrections than accepted ones (at least
    ``LOCKOUT_END_MIN``) is reported as locked out at the end; one that accepts most, or has
    tried too few in the window, is not."""
    from quadobs.estimators.robust import LOCKOUT_END_MIN, LockOut

    lock = LockOut(timeout=2.0)
    for i in range(3):
        assert lock.reset(10.0 * (i + 1), i, "test")
    t0 = lock.since  # grace 16 s from here: observe() cannot declare a lock-out before t0 + 16
    for k in range(40):
        assert not lock.observe(t0 + 0.05 * k, k % 4 == 0, 3.0)
    record = lock.locked_at_end()
    assert record is not None and record["time"] == pytest.approx(t0 + 0.05 * 39)
    assert "30 of the last 40 corrections rejected" in record["reason"]
    assert lock.diverged is None  # the record is the end's, not a give-up during the run

    fine = LockOut(timeout=2.0)
    for k in range(40):
        fine.observe(0.05 * k, k % 4 != 0, 1.0)
    assert fine.locked_at_end() is None
    few = LockOut(timeout=2.0)
    for k in range(LOCKOUT_END_MIN - 1):
        few.observe(0.05 * k, False, 3.0)
    assert few.locked_at_end() is None


def _exponential_excess_posterior(nu, S, pi, mean):
    """``E[e | nu]``, ``Var[e | nu]`` and ``P(blocked | nu)`` of ``e = 0`` (probability
    ``1 - pi``) or exponential of mean ``mean`` (``pi``), ``nu ~ N(e, S)``, by quadrature."""
    from scipy import integrate

    lik = stats.norm(0.0, np.sqrt(S)).pdf
    f = stats.expon(scale=mean).pdf
    top = max(nu, 0.0) + 12.0 * np.sqrt(S) + 40.0 * mean
    moments = [
        integrate.quad(lambda e, k=k: e**k * f(e) * lik(nu - e), 0.0, top, points=[max(nu, 0)])[0]
        for k in range(3)
    ]
    evidence = (1.0 - pi) * lik(nu) + pi * moments[0]
    m = pi * moments[1] / evidence
    return m, pi * moments[2] / evidence - m**2, pi * moments[0] / evidence


@pytest.mark.parametrize(
    ("nu", "S", "pi"),
    [(-0.1, 0.0064, 0.015), (0.1, 0.0064, 0.015), (0.3, 0.01, 0.2), (1.5, 0.0064, 0.5)],
)
def test_excess_huber_posterior_is_the_exponential_mixtures(nu, S, pi):
    """The closed form (the exponentially modified Gaussian and the truncated normal) against
    quadrature of the mixture's density."""
    from quadobs.estimators.robust import ExcessHuber

    mean, var, gamma = ExcessHuber(0.26, pi).posterior(nu, S)
    mean_c, var_c, gamma_c = _exponential_excess_posterior(nu, S, pi, 0.26)
    assert gamma == pytest.approx(gamma_c, rel=1e-6, abs=1e-12)
    assert mean == pytest.approx(mean_c, rel=1e-6, abs=1e-12)
    assert var == pytest.approx(var_c, rel=1e-5, abs=1e-12)


def test_excess_huber_is_hubers_rule_without_excess_and_bounds_a_long_ranges_pull():
    """``nlos = 0``: no excess, Huber's weights on both sides. With an excess, a range
    ``k`` metres long is left with the innovation ``nu - E[e | nu] -> lambda S`` (bounded, where
    Huber's keeps ``c sqrt(S)``) and adds nothing to the filter's knowledge (``Var[e | nu] ->
    S``); one as short keeps Huber's weight ``c / |r|`` (its excess ``~ 0``)."""
    from quadobs.estimators.robust import ExcessHuber

    S, c = 0.0064, 3.29
    none = ExcessHuber(0.26, 0.0, c)
    for nu in (-1.0, -0.1, 0.0, 0.2, 2.0):
        assert none.posterior(nu, S) == (0.0, 0.0, 0.0)
        np.testing.assert_array_equal(
            none.weights(np.array([nu]), np.array([[S]])),
            Huber(c).weights(np.array([nu]), np.array([[S]])),
        )
    rule = ExcessHuber(0.26, 0.015, c)
    left = [nu - rule.posterior(nu, S)[0] for nu in (0.5, 1.0, 3.0, 10.0)]
    assert max(left) < S / 0.26 * 1.01 < c * math.sqrt(S)
    assert left[-1] == pytest.approx(S / 0.26, rel=1e-3)
    assert rule.posterior(10.0, S)[1] == pytest.approx(S, rel=1e-3)
    shift, var, gamma = rule.posterior(-1.0, S)
    assert 0.0 <= shift < 1e-4  # a tenth of a millimetre
    w = rule.weights(np.array([-1.0 - shift]), np.array([[S]]))
    assert w[0] == pytest.approx(c * math.sqrt(S) / (1.0 + shift), rel=1e-12)
    # a range within the noise is taken as line of sight: its shift is millimetres
    assert rule.posterior(0.08, S)[0] < 0.005


def test_excess_huber_leaves_at_most_its_stated_supremum_of_any_innovation():
    """Over every innovation from 0 to 15 sd, what the shift leaves, ``nu - E[e | nu]``, is
    largest where ``gamma`` turns (2.29 sd at ``nu`` = 2.71 sd for the prior at the bound), below
    Huber's ``c``, and lower where a range is more likely blocked (0.69 sd at a prior of 1/2)."""
    from quadobs.estimators.robust import ExcessHuber

    for sigma in (0.08, 0.3):
        S = sigma * sigma
        rule = ExcessHuber.at_bound(3.29, sigma)
        nus = np.linspace(0.0, 15.0 * sigma, 1501)
        left = np.array([nu - rule.posterior(nu, S)[0] for nu in nus]) / sigma
        assert left.max() == pytest.approx(2.29, abs=0.01)
        assert nus[left.argmax()] / sigma == pytest.approx(2.71, abs=0.02)
        half = np.array([nu - rule.posterior(nu, S, 0.5)[0] for nu in nus]) / sigma
        assert half.max() == pytest.approx(0.69, abs=0.01)
        assert np.all(half <= left + 1e-12)


def test_excess_huber_carries_an_anchors_blocked_path_over_its_memory():
    """The chain of :meth:`ExcessHuber.prior`: ``nlos`` without memory; with it, the previous
    range's ``gamma`` relaxed to ``nlos`` as ``exp(-dt / memory)``."""
    from quadobs.estimators.robust import ExcessHuber

    assert ExcessHuber(0.26, 0.015).prior(0.9, 0.1) == 0.015
    rule = ExcessHuber(0.26, 0.015, memory=2.0)
    assert rule.prior(0.9, 0.0) == pytest.approx(0.9)
    assert rule.prior(0.9, 2.0) == pytest.approx(0.015 + (0.9 - 0.015) * math.exp(-1.0))
    assert rule.prior(0.0, math.inf) == 0.015
    with pytest.raises(QuadobsError, match="excess mean"):
        ExcessHuber(0.0)
    with pytest.raises(QuadobsError, match="nlos"):
        ExcessHuber(0.26, 1.0)
