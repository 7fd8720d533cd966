"""Every registered estimator through the one interface: shapes, missing outputs, copies, refusals, determinism."""

import numpy as np
import pytest

from quadobs import QuadobsError, load_scenario
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.base import Estimator, Gated, Immersed, SetValued, Subset
from quadobs.estimators.kalman import ExtendedKalmanFilter, UnscentedKalmanFilter
from quadobs.estimators.zonotopic import ZonotopicEstimator
from quadobs.estimators.zonotopic_vehicle import ZonotopicAugmentedEstimator
from quadobs.sets.zonotope import Zonotope
from quadobs.testbed.registry import available_estimators, build_estimators

STEPS = 400  # 0.4 s at 1 kHz: four range samples at 10 Hz


def _scenario(name):
    # bounded noise, so that the guaranteed estimator runs too; the variants come from 'beacons'
    return load_scenario("beacons" if name in _variants() else "ifac2021-bounded", duration=1.0)


def _variants():
    return [n for n, _ in load_scenario("beacons").observer.variants]


def _data(scenario, steps=STEPS):
    """Noise-free ``u (steps, p)``, ``y (steps, q)`` (sampled at the range rate, NaN between) and ``x_0``."""
    dt = scenario.dt
    t = np.arange(steps) * dt
    u = scenario.trajectory.step_accelerations(0.0, dt, steps)
    x = np.concatenate(
        [scenario.trajectory.position(t), scenario.trajectory.velocity_at(t)], axis=1
    )
    y = scenario.system().output(x)
    every = scenario.sample_interval(scenario.noise.range_rate, "range_rate")
    y[np.arange(steps) % every != 0] = np.nan
    return np.ascontiguousarray(u), np.ascontiguousarray(y), x[0]


def _build(name):
    scenario = _scenario(name)
    u, y, x0 = _data(scenario)
    return build_estimators(scenario, [name], x0)[0], scenario, u, y, x0


#: Driven by a body IMU (``u = (f_body, omega_body)``), not the vehicle's acceleration: its
#: interface, refusals and fixed-grid step are tested on a quadrotor in test_onboard_ekf.py.
BODY_IMU = {"onboard-ekf"}
#: Take TDOA, which a range scenario does not measure: their episodes, determinism and export
#: are tested on the TDOA scenarios in tests/testbed/test_tdoa_episode.py.
TDOA = {"tdoa-handover", "tdoa-observer"}
NAMES = [n for n in available_estimators() if n not in BODY_IMU | TDOA] + _variants()


def test_the_built_in_estimators_are_registered():
    assert {"augmented", "ekf", "ukf", "zonotope"} <= set(available_estimators())
    assert available_estimators() == sorted(available_estimators())


@pytest.mark.parametrize("name", NAMES)
def test_every_registered_estimator_keeps_the_interface(name):
    est, scenario, u, y, x0 = _build(name)
    n = scenario.state_dim
    assert isinstance(est, Estimator) and est.name == name
    seen = []
    for k in range(STEPS):
        est.step(u[k], y[k])
        x = est.x_hat
        assert x.shape == (n,) and np.isfinite(x).all()
        seen.append(x)
    P = est.x_covariance
    assert P is None or (P.shape == (n, n) and np.allclose(P, P.T))
    # not a live view: what was read at different steps differs, and writing into it changes nothing
    assert not np.array_equal(seen[0], seen[-1])
    before = est.x_hat.copy()
    try:
        seen[-1][:] = 1e6
    except ValueError:  # a read-only array is fine too
        pass
    np.testing.assert_array_equal(est.x_hat, before)
    if P is not None:
        P[...] = 0.0
        assert np.trace(est.x_covariance) > 0
    # a step where every output is missing is a prediction
    est.step(u[0], np.full(y.shape[1], np.nan))
    assert np.isfinite(est.x_hat).all() and not np.array_equal(est.x_hat, before)


@pytest.mark.parametrize("name", NAMES)
def test_every_registered_estimator_is_deterministic(name):
    runs = []
    for _ in range(2):
        est, scenario, u, y, _ = _build(name)
        rows = []
        for k in range(STEPS):
            est.step(u[k], y[k])
            rows.append(est.x_hat)
        cov = est.x_covariance
        runs.append((np.array(rows), None if cov is None else cov))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    if runs[0][1] is not None:
        np.testing.assert_array_equal(runs[0][1], runs[1][1])


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(
    "bad,match",
    [
        (lambda u, y: (np.array([np.nan, 0.0, 0.0]), y), "u: holds a non-finite value"),
        (lambda u, y: (np.array([np.inf, 0.0, 0.0]), y), "u: holds a non-finite value"),
        (lambda u, y: (u[:2], y), r"u: expected shape \(3,\)"),
        (lambda u, y: (u, y[:-1]), r"y: expected shape"),
        (
            lambda u, y: (u, np.where(np.arange(y.size) == 0, np.inf, y)),
            "y: holds a non-finite value",
        ),
        (lambda u, y: (u, "ranges"), "y: expected"),
    ],
    ids=["u-nan", "u-inf", "u-shape", "y-shape", "y-inf", "y-text"],
)
def test_a_bad_step_is_refused_and_changes_nothing(name, bad, match):
    est, scenario, u, y, _ = _build(name)
    for k in range(5):
        est.step(u[k], y[k])
    x, P = est.x_hat.copy(), est.x_covariance
    bu, by = bad(u[5], y[1])
    with pytest.raises(QuadobsError, match=match):
        est.step(bu, by)
    np.testing.assert_array_equal(est.x_hat, x)
    if P is not None:
        np.testing.assert_array_equal(est.x_covariance, P)
    est.step(u[5], y[5])  # and it goes on
    assert np.isfinite(est.x_hat).all()


def test_abilities_are_declared_by_inheritance():
    scenario = load_scenario("beacons", duration=1.0)
    _, _, x0 = _data(scenario, 1)
    variant = _variants()[0]
    aug, ekf, ukf, sub = build_estimators(scenario, ["augmented", "ekf", "ukf", variant], x0)
    bounded = load_scenario("ifac2021-bounded", duration=1.0)
    (zon,) = build_estimators(bounded, ["zonotope"], _data(bounded, 1)[2])
    assert isinstance(aug, (AugmentedObserver, Gated, Immersed)) and not isinstance(
        aug, (SetValued, Subset)
    )
    for f, cls in ((ekf, ExtendedKalmanFilter), (ukf, UnscentedKalmanFilter)):
        assert (
            isinstance(f, cls)
            and isinstance(f, Gated)
            and not isinstance(f, (Immersed, SetValued, Subset))
        )
    assert isinstance(sub, Gated) and isinstance(sub, Immersed) and isinstance(sub, Subset)
    assert sub.outputs.shape[0] < scenario.beacons.shape[0]
    assert (
        isinstance(zon, ZonotopicAugmentedEstimator)
        and isinstance(zon, SetValued)
        and isinstance(zon, Immersed)
    )
    assert not isinstance(zon, Gated) and zon.x_covariance is None
    b = zon.bounds
    assert b.shape == (6, 2) and np.all(b[:, 0] <= zon.x_hat) and np.all(zon.x_hat <= b[:, 1])


def test_the_linear_zonotopic_estimator_is_an_estimator_without_input():
    est = ZonotopicEstimator(
        np.eye(2), 0.1 * np.eye(2), np.eye(2), 0.5, Zonotope(np.zeros(2), np.eye(2))
    )
    assert isinstance(est, Estimator) and isinstance(est, SetValued) and est.x_covariance is None
    est.step(np.empty(0), np.array([0.2, np.nan]))
    old = est.x_hat.copy()
    est.step([0.3, -0.1])  # the system has no input: y alone
    assert not np.array_equal(est.x_hat, old)
    assert not est.x_hat.flags.writeable
    b = est.bounds
    assert b.shape == (2, 2) and np.all(b[:, 0] <= est.x_hat) and np.all(est.x_hat <= b[:, 1])
    with pytest.raises(QuadobsError, match=r"u: the system has no input"):
        est.step(np.zeros(1), np.zeros(2))
