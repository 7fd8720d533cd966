"""Range biases as states: the quadratic-output form with a measured coefficient, the observer on
it (exact convergence on noise-free data), its observability, and the filters' bias states."""

import numpy as np
import pytest

from quadobs.core.immersion import immerse
from quadobs.core.measurements import Measurement, RangeModel
from quadobs.core.range_bias import BiasedRangeImmersion, excitation_gramian
from quadobs.core.system import vehicle_system
from quadobs.estimators.augmented_bias import BiasedAugmentedObserver
from quadobs.estimators.bias_states import biased_models
from quadobs.estimators.kalman import ExtendedKalmanFilter, UnscentedKalmanFilter

ANCHORS = np.array(
    [
        [-3, -3, 0.2],
        [3, -3, 0.2],
        [3, 3, 0.2],
        [-3, 3, 0.2],
        [-3, -3, 2.8],
        [3, -3, 2.8],
        [3, 3, 2.8],
        [-3, 3, 2.8],
    ],
    dtype=float,
)
BIASES = np.array([0.1, -0.2, 0.3, 0.05, -0.15, 0.2, 0.0, -0.3])
W = 0.314


def acc(t):
    return np.array(
        [-2 * W * W * np.sin(W * t), -4.8 * W * W * np.sin(2 * W * t), -0.4 * W * W * np.sin(W * t)]
    )


def flight(steps, dt, sigma=0.0, seed=0):
    """A figure eight integrated exactly under the held input, and its biased ranges."""
    rng = np.random.default_rng(seed)
    p, v = np.array([0.0, 0.0, 1.5]), np.array([2 * W, 2.4 * W, 0.4 * W])
    for k in range(steps):
        a = acc(k * dt)
        rho = np.linalg.norm(p - ANCHORS, axis=1) + BIASES + sigma * rng.standard_normal(8)
        yield a, rho, p.copy()
        p, v = p + v * dt + 0.5 * a * dt * dt, v + a * dt


def test_output_row_reproduces_the_squared_range_exactly():
    ext = BiasedRangeImmersion(immerse(vehicle_system(3, ANCHORS)), squares=True)
    x = np.array([1.0, -0.7, 1.2, 0.3, 0.1, 0.0])
    zeta = ext.lift(x, BIASES)
    for h in range(8):
        rho = np.linalg.norm(x[:3] - ANCHORS[h]) + BIASES[h]
        row, y = ext.measurement(h, rho, zeta)
        assert row @ zeta == pytest.approx(y, abs=1e-12)
        assert y == pytest.approx(rho**2 / 2 - ANCHORS[h] @ ANCHORS[h] / 2)


def test_squares_as_states_are_not_observable_and_the_tangent_form_is():
    dt, T = 0.05, 400
    ts = np.arange(T) * dt
    P = np.array([p for _, _, p in flight(T, dt)])
    U = np.array([acc(t) for t in ts])
    rhos = np.linalg.norm(P[:, None] - ANCHORS[None], axis=2) + BIASES
    im = immerse(vehicle_system(3, ANCHORS))
    exact = np.linalg.eigvalsh(excitation_gramian(BiasedRangeImmersion(im, True), P, U, rhos, dt))
    tangent = np.linalg.eigvalsh(excitation_gramian(BiasedRangeImmersion(im), P, U, rhos, dt))
    assert exact[1] / exact[-1] < 1e-15  # two directions the outputs never see
    assert tangent[0] / tangent[-1] > 1e-8  # every direction seen over 20 s of flight


def test_observer_converges_exactly_on_noise_free_ranges_from_far():
    dt = 0.01
    im = immerse(vehicle_system(3, ANCHORS))
    est = BiasedAugmentedObserver(im, dt, sigma=1e-6, V=1e-10, P0=100.0, x0=[15.0, 10, 5, 0, 0, 0])
    for a, rho, _ in flight(6000, dt):
        est.step(a, 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
    # x_hat after the last step is the estimate at t + dt: the next truth
    truth_next = [p for _, _, p in flight(6001, dt)][-1]
    final = np.linalg.norm(est.x_hat[:3] - truth_next)
    assert final < 1e-3 and np.abs(est.biases - BIASES).max() < 1e-3


def test_observer_in_time_matches_the_fixed_grid():
    dt = 0.01
    im = immerse(vehicle_system(3, ANCHORS))
    grid = BiasedAugmentedObserver(im, dt, sigma=0.1, V=1e-3, x0=[1.0, 1, 1, 0, 0, 0])
    timed = BiasedAugmentedObserver(im, dt, sigma=0.1, V=1e-3, x0=[1.0, 1, 1, 0, 0, 0])
    for k, (a, rho, _) in enumerate(flight(300, dt, sigma=0.1)):
        grid.step(a, 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
        for h in range(8):
            timed.correct(Measurement(k * dt, "range", float(rho[h]), (h,)))
        timed.hold(a)
        timed.predict((k + 1) * dt)
    assert np.allclose(grid.zeta, timed.zeta, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_filters_estimate_the_biases_as_states(cls):
    dt, sigma = 0.01, 0.05
    system = vehicle_system(3, ANCHORS)
    model = RangeModel(ANCHORS, sigma, bias="state")
    dyn, out, P0 = biased_models(system, dt, sigma, 0.02, np.eye(6), model)
    x0 = np.r_[0.3, -0.2, 1.6, 2 * W, 2.4 * W, 0.4 * W, np.zeros(8)]
    est = cls(dyn, out, x0=x0, P0=P0)
    for a, rho, _ in flight(2000, dt, sigma=sigma, seed=3):
        est.step(a, 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
    assert np.abs(est.x_hat[6:] - BIASES).max() < 0.03


def _bias_filter(cls, sigma, x0, rule=None, p0=100.0, bias_walk=0.0):
    from quadobs.estimators.bias_states import (
        BiasedExtendedKalmanFilter,
        BiasedUnscentedKalmanFilter,
    )

    system = vehicle_system(3, ANCHORS)
    model = RangeModel(ANCHORS, sigma, bias="state")
    dyn, out, P0 = biased_models(system, 0.01, sigma, 0.02, p0 * np.eye(6), model, bias_walk)
    kind = {"ekf": BiasedExtendedKalmanFilter, "ukf": BiasedUnscentedKalmanFilter}[cls]
    return kind(dyn, out, x0=np.r_[x0, np.zeros(8)], P0=P0, vehicle_n=6, robust=rule)


@pytest.mark.parametrize("cls", ["ekf", "ukf"])
def test_bias_filter_recovers_the_biases_from_far_on_noise_free_ranges(cls):
    """From 20 m off: the position fixed by multilateration at the first full round, the biases
    opened once the innovations are consistent, and then recovered."""
    est = _bias_filter(cls, 0.05, np.array([12.0, 16.0, 0.0, 0.0, 0.0, 0.0]))
    assert est.fix_pending  # a 10 m prior is wider than a multilateration's error
    truth = list(flight(2001, 0.01))
    for a, rho, _ in truth[:-1]:
        est.step(a, 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
    p = truth[-1][2]  # the truth at the estimate's time
    assert est.fixes == [0.0] and len(est.opened_at) == 1 and est.opened_at[0] < 1.0
    assert np.abs(est.biases - BIASES).max() < 0.02
    assert np.linalg.norm(est.x_hat[:3] - p) < 0.02


def test_bias_states_do_not_take_in_non_line_of_sight_excess():
    """Anchor 1 hidden 75 % of the time (positive excess, median 0.3 m): with the one-sided
    gate its bias stays near the truth; with the two-sided gate alone it absorbs the excess.

    The fixed points where the accepted innovations of anchor 1 average zero (line-of-sight noise
    0.1 m, ``sqrt(S)`` about 0.1 m, computed by sampling the mixture): 0.06 m above the truth
    with the one-sided gate at ``z_+ = 1.645``, 0.20 m with the two-sided gate at 3.29."""
    from quadobs.estimators.robust import ChiSquareGate, SkewedGate

    sigma, steps, rng = 0.1, 1200, np.random.default_rng(7)
    hidden = rng.random(steps) < 0.75
    excess = 0.3 * np.exp(0.6 * rng.standard_normal(steps))
    errors = {}
    for label, rule in (("skewed", SkewedGate(0.999)), ("chi2", ChiSquareGate(0.999))):
        x0 = np.array([0.3, -0.2, 1.6, 2 * W, 2.4 * W, 0.4 * W])
        est = _bias_filter("ekf", sigma, x0, rule, p0=0.01)  # near the truth: no fix
        for k, (a, rho, _) in enumerate(flight(steps, 0.01, sigma=sigma, seed=5)):
            rho[1] += excess[k] * hidden[k]
            est.step(a, 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
        errors[label] = est.biases[1] - BIASES[1]
    assert abs(errors["skewed"]) < 0.08
    assert errors["chi2"] > 0.13


def test_an_anchor_hidden_in_spells_keeps_its_bias_under_the_excess_mixture():
    """Anchor 1 hidden 3 s of every 4 (a blocked path persists while the vehicle is behind
    the obstacle), excess of median 0.3 m: under the
    :class:`~quadobs.estimators.robust.ExcessMixture` of that excess each range is corrected
    by its expected excess, and every bias, anchor 1's and the seven clear ones' (0.3 m for
    anchor 2: a range long by a positive bias is not taken for excess), ends within 0.05 m of
    the truth; the one-sided gate leaves anchor 1's 0.06 m above it (the test above)."""
    from quadobs.estimators.robust import ExcessMixture

    sigma, steps, rng = 0.1, 1200, np.random.default_rng(7)
    hidden = (np.arange(steps) // 100) % 4 != 0
    excess = 0.3 * np.exp(0.6 * rng.standard_normal(steps))
    x0 = np.array([0.3, -0.2, 1.6, 2 * W, 2.4 * W, 0.4 * W])
    est = _bias_filter("ekf", sigma, x0, ExcessMixture(0.3, 0.6), p0=0.01)
    for k, (a, rho, _) in enumerate(flight(steps, 0.01, sigma=sigma, seed=5)):
        rho[1] += excess[k] * hidden[k]
        est.step(a, 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
    assert np.abs(est.biases - BIASES).max() < 0.05
    assert est.rejected < 0.01 * est.corrections  # outliers only: no long range refused


def test_bias_filter_fixes_its_start_without_a_silent_anchor():
    """An anchor that never answers delays the fix by two rounds of ranges, no more."""
    est = _bias_filter("ekf", 0.05, np.array([12.0, 16.0, 0.0, 0.0, 0.0, 0.0]))
    truth = list(flight(1001, 0.01))
    for a, rho, _ in truth[:-1]:
        y = 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1)
        y[7] = np.nan
        est.step(a, y)
    assert est.fixes == [0.02]  # 7 ranges a step: the 16th range comes with the third step
    assert np.linalg.norm(est.x_hat[:3] - truth[-1][2]) < 0.1


@pytest.mark.parametrize("cls", ["ekf", "ukf"])
@pytest.mark.parametrize("entry", ["outputs", "in_time", "batch"])
def test_the_fix_is_not_corrected_by_its_own_ranges(cls, entry):
    """The round of ranges a fix is made of is not corrected by again: the position covariance
    after the fix is the fix's, ``fix_std^2 I`` with ``fix_std^2 = sigma^2 + sigma_b^2``, not
    about half of it (what a second correction by the same ranges gives in the linear case)."""
    sigma = 0.05
    est = _bias_filter(cls, sigma, np.array([12.0, 16.0, 0.0, 0.0, 0.0, 0.0]))
    assert est.fix_pending
    p = np.array([0.4, -0.3, 1.5])
    rho = np.linalg.norm(p - ANCHORS, axis=1) + BIASES
    ms = [Measurement(0.0, "range", float(r), (h,), sigma) for h, r in enumerate(rho)]
    if entry == "outputs":
        est.correct_outputs(0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
    elif entry == "in_time":
        for m in ms:
            est.correct(m)
    else:
        est.correct_many(ms)
    assert est.fixes == [0.0] and not est.fix_pending
    var = sigma**2 + 0.5**2  # the range noise and the biases' prior (RangeModel's 0.5 m)
    assert est.x_covariance[:3, :3] == pytest.approx(var * np.eye(3), abs=1e-12)
    assert np.isnan(est.nis)  # no correction at the fix
    # the first range after the fix is corrected by, and narrows the position
    est.correct(Measurement(0.0, "range", float(rho[0]), (0,), sigma))
    assert np.trace(est.x_covariance[:3, :3]) < 3 * var


@pytest.mark.parametrize("cls", ["ekf", "ukf"])
def test_the_fix_correction_is_one_joint_update_linearised_at_the_fix(cls):
    """``fix_correction``: the round of ranges corrects the prior once, linearised at the
    multilateration (the closed form of an iterated EKF's first iterate, computed here from
    the unit vectors), the biases' rows of the gain held at zero; the position's covariance
    with the biases is then ``-K_p P_bb``, where the fix's covariance has none."""
    from quadobs.estimators.robust import multilateration

    sigma = 0.05
    x0 = np.array([12.0, 16.0, 0.0, 0.0, 0.0, 0.0])
    est = _bias_filter(cls, sigma, x0)
    est.fix_correction = True
    P0 = est._P.copy()
    p = np.array([0.4, -0.3, 1.5])
    rho = np.linalg.norm(p - ANCHORS, axis=1) + BIASES
    y = 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1)
    est.correct_outputs(y)
    system = vehicle_system(3, ANCHORS)
    v = est._fix_var  # the fix weighs each output by its variance rho^2 v + v^2 / 2
    variances = (2.0 * y + (ANCHORS**2).sum(1)) * v + 0.5 * v * v
    cols, p_fix = multilateration(system.C, system.d, y, variances=variances)
    x_i = np.r_[x0, np.zeros(8)]
    x_i[cols] = p_fix
    diff = p_fix - ANCHORS
    H = np.zeros((8, 14))
    H[:, :3] = diff / np.linalg.norm(diff, axis=1)[:, None]
    H[:, 6:] = np.eye(8)
    R = sigma**2 * np.eye(8)
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + R)
    K[6:] = 0.0  # the biases closed at the start
    nu = rho - np.linalg.norm(diff, axis=1) - H @ (np.r_[x0, np.zeros(8)] - x_i)
    IKH = np.eye(14) - K @ H
    P = IKH @ P0 @ IKH.T + K @ R @ K.T
    assert est.fixes == [0.0]
    assert est.x_hat == pytest.approx(x0 + (K @ nu)[:6], abs=1e-9)
    assert est.x_covariance == pytest.approx(P[:6, :6], abs=1e-12)
    assert est._P[:3, 6:] == pytest.approx(-K[:3] @ P0[6:, 6:], abs=1e-12)
    assert np.abs(est._P[:3, 6:]).max() > 0.01  # the fix's error is the biases' pattern


def test_the_biases_prior_is_the_radios_stated_spread():
    """``ekf-bias``, ``ukf-bias`` and ``augmented-bias`` take the biases' prior from the radio's
    stated spread (``radio.bias_std``) where its biases are drawn with one; given biases or no
    radio leave the range model's 0.5 m."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.factories import (
        bias_prior_std,
        biased_augmented_observer,
        biased_extended_kalman_filter,
        biased_unscented_kalman_filter,
    )
    from quadobs.testbed.scenario import load_scenario

    scenario = load_scenario("quadrotor-uwb-realistic")
    assert bias_prior_std(scenario) == scenario.radio.bias_std == 0.2
    x0 = np.array([1.0, 2.0, 1.5, 0.0, 0.0, 0.0])
    for make in (biased_extended_kalman_filter, biased_unscented_kalman_filter):
        est = make(scenario, x0)
        np.testing.assert_allclose(np.diag(est._P)[6:], 0.04)
    obs = biased_augmented_observer(scenario, x0)
    N = obs.immersion.dim
    np.testing.assert_allclose(np.diag(obs._P)[N:], 0.04)
    given = scenario.model_copy(
        update={"radio": scenario.radio.model_copy(update={"biases": (0.1,) * 8})}
    )
    assert bias_prior_std(given) is None
    assert bias_prior_std(load_scenario("quadrotor-uwb")) is None
    system, model = vehicle_system(3, ANCHORS), RangeModel(ANCHORS, 0.1, bias="state")
    _, _, P = biased_models(system, 0.01, 0.1, 0.02, np.eye(6), model)
    np.testing.assert_allclose(np.diag(P)[6:], 0.25)
    with pytest.raises(QuadobsError, match="bias_std"):
        biased_models(system, 0.01, 0.1, 0.02, np.eye(6), model, bias_std=-0.1)


def test_a_hovering_vehicles_position_is_bounded_by_the_biases_prior():
    """Hovering, a position offset ``d`` and the biases ``-U d`` fit every range alike, so only
    the biases' prior ``s`` separates them: the position's posterior covariance is
    ``(U^T U / (s^2 + sigma^2 / K) + P0^-1)^-1`` after ``K`` rounds (``U`` the unit vectors from
    the anchors). A Kalman filter with the Jacobian at the true position reaches that; the EKF,
    whose Jacobian follows its own estimate, reports less (the linearisation point moves along
    the unobservable direction and lends it information it does not have)."""
    from quadobs.estimators.bias_states import BiasedRangeOutputModel

    p, sigma, s, K = np.array([0.5, -0.4, 1.5]), 0.1, 0.5, 600
    U = (p - ANCHORS) / np.linalg.norm(p - ANCHORS, axis=1)[:, None]
    closed = np.linalg.inv(U.T @ U / (s * s + sigma**2 / K) + np.eye(3) / 0.04)

    class AtTruth(BiasedRangeOutputModel):
        def linearize(self, x):
            z = super().linearize(x)[0]
            return z, super().linearize(np.r_[p, x[3:]])[1]

    system, model = vehicle_system(3, ANCHORS), RangeModel(ANCHORS, sigma, bias="state")
    traces = {}
    for label in ("ekf", "at truth"):
        dyn, out, P0 = biased_models(system, 0.01, sigma, 0.0, 0.04 * np.eye(6), model, bias_std=s)
        if label == "at truth":
            out = AtTruth(out.system, out.R, offsets=out.offsets)
        rng = np.random.default_rng(1)
        x0 = np.r_[p + 0.2 * rng.standard_normal(3), np.zeros(3), np.zeros(8)]
        est = ExtendedKalmanFilter(dyn, out, x0=x0, P0=P0)
        b = s * rng.standard_normal(8)
        for _ in range(K):
            rho = np.linalg.norm(p - ANCHORS, axis=1) + b + sigma * rng.standard_normal(8)
            est.step(np.zeros(3), 0.5 * rho**2 - 0.5 * (ANCHORS**2).sum(1))
        traces[label] = np.trace(est.x_covariance[:3, :3])
    assert traces["at truth"] == pytest.approx(np.trace(closed), rel=0.05)
    assert traces["ekf"] < 0.85 * np.trace(closed), traces


def test_the_excess_mixture_keeps_the_filters_gate():
    """A filter given both a ``gate`` (a NIS threshold) and an
    :class:`~quadobs.estimators.robust.ExcessMixture` rejects a range whose NIS, its innovation
    corrected by the expected excess, exceeds the gate: a range 0.25 m short of line of sight
    with 0.1 m noise (the position and the bias known to 0.01 m) passes the mixture's own bounds
    (3.29 standard deviations) but not a gate of 1; without the gate it is taken."""
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter
    from quadobs.estimators.robust import ExcessMixture

    system = vehicle_system(3, ANCHORS)
    model = RangeModel(ANCHORS, 0.1, bias="state")
    dyn, out, P0 = biased_models(system, 0.01, 0.1, 0.02, 1e-4 * np.eye(6), model, bias_std=0.01)
    p = np.array([0.3, -0.2, 1.6])
    x0 = np.r_[p, np.zeros(3), np.zeros(8)]
    rho = np.linalg.norm(ANCHORS[0] - p) - 0.25
    taken = {}
    for gate in (None, 1.0):
        est = BiasedExtendedKalmanFilter(
            dyn, out, x0=x0, P0=P0, vehicle_n=6, robust=ExcessMixture(0.3, 0.6), gate=gate
        )
        est.correct(Measurement(0.0, "range", rho, (0,), 0.1))
        taken[gate] = (est.corrections, est.rejected, est.nis)
    assert taken[None][:2] == (1, 0)
    assert taken[1.0][:2] == (0, 1) and taken[1.0][2] > 1.0


def test_markov_onset_fires_on_three_clear_chains_turned_in_one_round_not_two():
    from types import SimpleNamespace

    from quadobs.estimators.bias_states import _VehicleBlock
    from quadobs.estimators.robust import ExcessMixture

    rule, q = ExcessMixture(median=0.4, shape=0.7), 8
    f = SimpleNamespace(
        _nlos=np.zeros(q), _nlos_time=np.zeros(q), _onset_at=np.full(q, -np.inf),
        _onset_pre=np.zeros(q), _onset_nu=np.zeros(q), _onset_fire=np.zeros(q, dtype=bool),
        _onset_pending=False, onset_window=0.0, _time=0.0,
    )  # fmt: skip
    for k, h in enumerate((0, 1, 2)):  # three anchors, 0.01 s apart, each heard 0.08 s before
        f._time = 1.0 + 0.01 * k
        f._nlos_time[h] = f._time - 0.08
        prior = rule.prior(0.0, 0.08)
        _VehicleBlock._onset(f, rule, h, prior, 0.99, 0.5)
        f._nlos[h], f._nlos_time[h] = 0.99, f._time
        assert f._onset_pending == (k == 2)
    assert f._onset_fire[:3].all() and not f._onset_fire[3:].any()


def _steady_run(innovations, R=0.01):
    """Feed one anchor's ranges, all read blocked, to the steady-offset test; the count of
    ranges after which it fired (``None``: it never did)."""
    from types import SimpleNamespace

    from quadobs.estimators.bias_states import _VehicleBlock
    from quadobs.estimators.robust import ExcessMixture

    rule = ExcessMixture(median=0.3, shape=0.6)
    f = SimpleNamespace(_block=np.zeros((8, 4)), _steady_pending=None, biases_open=True)
    for i, nu in enumerate(innovations, start=1):
        _VehicleBlock._steady(f, rule, 2, 0.99, float(nu), R)
        if f._steady_pending is not None:
            return i
    return None


def test_steady_offset_passes_a_bias_error_and_not_an_excess():
    """Blocks of 51 ranges (``steady_block`` at ``P = 0.999``) with the noise's 0.1 m: a bias
    state 0.3 m low (innovations ``0.3 + n``) passes a block with probability 1/2 (the median
    of ``chi^2(50)``), an excess as spread as the noise (``0.5 + e + n``, ``e ~ N(0, 0.1^2)``)
    with probability 0.001, and the stand-ins' log-normal excess (median 0.3 m, shape 0.6:
    0.24 m standard deviation) never; a negative mean is no excess. 400 blocks each."""
    from quadobs.estimators.bias_states import steady_block

    n, median, z = steady_block(0.999)
    assert (
        n == 51 and median == pytest.approx(49.33, abs=0.01) and z == pytest.approx(3.29, abs=0.01)
    )
    rng = np.random.default_rng(3)

    def passed(draw):
        return sum(_steady_run(draw()) is not None for _ in range(400))

    bias = passed(lambda: 0.3 + 0.1 * rng.standard_normal(n))
    assert 160 <= bias <= 240, bias  # binomial(400, 1/2): 200 +- 20
    wide = passed(lambda: 0.5 + 0.1 * rng.standard_normal(n) + 0.1 * rng.standard_normal(n))
    assert wide <= 3, wide  # binomial(400, 0.001): 0.4 expected, 4 or more 0.008
    lognormal = passed(
        lambda: 0.3 * np.exp(0.6 * rng.standard_normal(n)) + 0.1 * rng.standard_normal(n)
    )
    assert lognormal == 0
    assert passed(lambda: -0.3 + 0.1 * rng.standard_normal(n)) == 0


def test_steady_offset_the_other_way_passes_a_bias_too_high_and_not_a_right_one():
    """The test on an anchor's clear and short ranges (a bias state too high): blocks of a
    steady -0.5 m offset (beyond one range's gate, 3.29 x 0.1 m) pass with probability 1/2;
    -0.2 m (which the accepted ranges correct), a right bias and a positive mean never (400
    blocks each, the noise 0.1 m)."""
    from quadobs.estimators.bias_states import steady_block, steady_offset

    n = steady_block(0.999)[0]
    rng = np.random.default_rng(5)

    def passed(mean):
        block, count = np.zeros(4), 0
        for _ in range(400):
            for nu in mean + 0.1 * rng.standard_normal(n):
                count += steady_offset(block, 0.999, True, float(nu), 0.01, -1.0, True) is not None
        return count

    assert 160 <= passed(-0.5) <= 240
    assert passed(-0.2) == 0
    assert passed(0.0) == 0
    assert passed(0.3) == 0


def test_steady_offset_restarts_on_a_clear_range_and_releases_into_the_bias():
    """A block restarts on every range read clear, so 200 ranges of a steady 0.6 m offset
    with one clear range in 40 never fill a block. A block taken as a bias error grows that
    anchor's bias variance by its mean squared, reads its chain clear, takes it out of the
    onset test's record and logs the time."""
    from types import SimpleNamespace

    from quadobs.estimators.bias_states import _VehicleBlock
    from quadobs.estimators.robust import ExcessMixture

    rule = ExcessMixture(median=0.3, shape=0.6)
    f = SimpleNamespace(_block=np.zeros((8, 4)), _steady_pending=None, biases_open=True)
    for k in range(200):
        post = 0.2 if k % 40 == 39 else 0.99  # every fortieth range read clear
        _VehicleBlock._steady(f, rule, 0, post, 0.6, 0.01)
    assert f._steady_pending is None and f._block[0, 0] == 0.0
    P = np.eye(14) * 0.01
    g = SimpleNamespace(
        _steady_pending=(2, 0.4), vehicle_n=6, _P=P.copy(), _nlos=np.ones(8),
        _nlos_time=np.zeros(8), _time=12.5, _onset_at=np.full(8, 12.0), steady_offsets=[],
    )  # fmt: skip
    _VehicleBlock._steady_release(g)
    grown = P.copy()
    grown[8, 8] += 0.4 * 0.4
    np.testing.assert_array_equal(g._P, grown)
    assert g._nlos[2] == 0.0 and g._nlos_time[2] == 12.5 and g._onset_at[2] == -np.inf
    assert g._steady_pending is None and g.steady_offsets == [12.5]


@pytest.mark.parametrize("start", [-0.5, 0.5])
def test_steady_offset_frees_a_bias_state_trapped_in_the_filter(start):
    """A vehicle at rest ranged by eight anchors without bias, the filter's bias state of
    anchor 0 started 0.5 m off and sure of itself (0.01 m). Under the excess mixture, low
    (-0.5) every range of anchor 0 reads as blocked and the chain keeps it from correcting the
    bias; high (+0.5) most of its ranges are rejected as shorter than line of sight. Either way
    the bias is still more than 0.3 m off after 200 rounds. With the steady-offset test a block
    is taken as the bias's error and the bias comes back within 0.05 m, the position with it."""
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter
    from quadobs.estimators.robust import ExcessMixture

    system = vehicle_system(3, ANCHORS)
    model = RangeModel(ANCHORS, 0.1, bias="state")
    dyn, out, P0 = biased_models(system, 0.01, 0.1, 0.02, 1e-4 * np.eye(6), model, bias_std=0.01)
    p = np.array([0.3, -0.2, 1.6])
    d = np.linalg.norm(ANCHORS - p, axis=1)
    found = {}
    for on in (False, True):
        rng = np.random.default_rng(0)
        b0 = np.zeros(8)
        b0[0] = start
        est = BiasedExtendedKalmanFilter(
            dyn,
            out,
            x0=np.r_[p, np.zeros(3), b0],
            P0=P0,
            vehicle_n=6,
            robust=ExcessMixture(0.3, 0.6),
        )
        est.steady_test = on
        for _ in range(200):
            for h in range(8):
                rho = d[h] + 0.1 * rng.standard_normal()
                est.correct(Measurement(0.0, "range", rho, (h,), 0.1))
        found[on] = (est.biases[0], len(est.steady_offsets), np.linalg.norm(est.x_hat[:3] - p))
    assert abs(found[False][0]) > 0.3 and found[False][1] == 0, found
    assert abs(found[True][0]) < 0.05 and found[True][1] >= 1, found
    assert found[True][2] < found[False][2], found
