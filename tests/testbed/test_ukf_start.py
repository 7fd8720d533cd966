"""The scenarios' UKF from a prior wider than the anchors' geometry (one range at a time)."""

import numpy as np
import pytest

from quadobs.core.measurements import Measurement
from quadobs.estimators.kalman import UnscentedKalmanFilter
from quadobs.estimators.startup import FixedStartUKF
from quadobs.testbed.factories import (
    _gaussian_filter,
    baseline_settings,
    ukf_starts_from_fix,
    unscented_kalman_filter,
)
from quadobs.testbed.scenario import load_scenario

REALISTIC = "quadrotor-uwb-realistic"


def _hover(est, anchors, p, seconds, seed=0, rate=100.0, std=0.1):
    """Ranges from a vehicle hovering at ``p``, one anchor at a time (round robin at ``rate``),
    with Gaussian noise ``std``; returns the position error after each range."""
    rng = np.random.default_rng(seed)
    est.hold(np.zeros(est._input_dimension()))
    errors = []
    for k in range(int(seconds * rate)):
        t = (k + 1) / rate
        h = k % anchors.shape[0]
        est.predict(t)
        rho = float(np.linalg.norm(p - anchors[h])) + std * rng.standard_normal()
        est.correct(Measurement(t, "range", rho, (h,), std))
        errors.append(float(np.linalg.norm(est.x_hat[:3] - p)))
    return np.array(errors)


@pytest.mark.parametrize(
    "name", ["quadrotor-uwb", "ifac2021", "ifac2021-noisy", "quadrotor-1beacon"]
)
def test_priors_within_reach_keep_the_plain_ukf(name):
    sc = load_scenario(name)
    assert not ukf_starts_from_fix(sc)
    x0 = np.zeros(sc.state_dim)
    assert type(unscented_kalman_filter(sc, x0)) is UnscentedKalmanFilter


def test_unscented_range_is_flat_at_an_anchor():
    """Closed form: the mean on an anchor, ``P = s^2 I``: every sigma point pair ``x +- D_i``
    lies at one range ``|D_i|`` from it, so ``P_xz = 0`` and a correction leaves the mean."""
    sc = load_scenario(REALISTIC)
    a = sc.beacons[0]
    x0 = np.concatenate([a, np.zeros(3)])
    ukf = UnscentedKalmanFilter(
        baseline_settings(sc).dynamics, baseline_settings(sc).outputs, x0=x0, P0=100.0
    )
    ukf.correct(Measurement(0.0, "range", 4.0, (0,), 0.1))
    np.testing.assert_allclose(ukf.x_hat, x0, atol=1e-9)
    assert ukf.corrections == 1


def test_realistic_ukf_converges_from_20_m_off():
    """The realistic scenario's prior (20 m off, ``S0 = 100``): its UKF starts from a fix, and
    over the second second of ranges it is within centimetres with a spread to match; the
    plain UKF of the same settings, after the same 200 ranges, has a position spread wider
    than its prior's (``sqrt(tr P_pp) = sqrt(300)``) and errs by more than half a metre, and
    says so (:meth:`uninformed`)."""
    sc = load_scenario(REALISTIC)
    assert ukf_starts_from_fix(sc)
    p = np.array([0.5, -0.3, 1.5])
    x0 = np.array([12.0, 16.0, 0.0, 0.0, 0.0, 0.0])
    ukf = unscented_kalman_filter(sc, x0)
    assert isinstance(ukf, FixedStartUKF)
    errors = _hover(ukf, sc.beacons, p, 2.0)
    assert ukf.fixes and ukf.fixes[0] <= 0.2  # one round of 8 ranges at 100 Hz
    assert np.sqrt(np.mean(errors[100:] ** 2)) < 0.2
    assert np.sqrt(np.trace(ukf.x_covariance[:3, :3])) < 0.2
    assert ukf.uninformed() is None
    plain = _gaussian_filter(UnscentedKalmanFilter, sc, x0)
    errors = _hover(plain, sc.beacons, p, 2.0)
    assert plain.rejected == 0
    assert np.sqrt(np.trace(plain.x_covariance[:3, :3])) > np.sqrt(300.0)
    assert np.sqrt(np.mean(errors[100:] ** 2)) > 0.5
    record = plain.uninformed()  # what the run's summary says of such a filter
    assert record["corrections"] == 200
    assert record["position_spread"] > record["prior_spread"] == pytest.approx(np.sqrt(300.0))


def test_rover_room_ukf_takes_its_velocity_from_the_fix():
    """``rover-room``'s UKF (a 3 x 2.4 m room, the observer's 10 m/s on the velocity): ranges one
    anchor at a time at 40 Hz from a robot crossing the room at 0.4 m/s, each 0.11 m long (the
    room's mean antenna delay, which this UKF does not model), two of the first round's lost
    (the radio's dropouts). Its fix takes the velocity from the round's ranges; from
    the position alone (its spread 2 m per axis after the 0.2 s round) the position's spread
    grew by the velocity's 10 m/s after the fix, over the anchors, and it never took the
    velocity in."""
    sc = load_scenario("rover-room")
    assert ukf_starts_from_fix(sc)
    ukf = unscented_kalman_filter(sc, np.array([1.0, 1.0, 0.0, 0.0]))
    rng = np.random.default_rng(3)
    ukf.hold(np.zeros(2))
    p0, v = np.array([0.8, 0.9]), np.array([0.3, 0.25])
    errors = []
    for k in range(120):  # 3 s
        t = (k + 1) / 40.0
        h = k % 4
        p = p0 + v * t
        if k in (3, 4):
            continue  # lost
        ukf.predict(t)
        rho = float(np.linalg.norm(p - sc.beacons[h])) + 0.11 + 0.08 * rng.standard_normal()
        ukf.correct(Measurement(t, "range", rho, (h,), 0.08))
        errors.append(float(np.linalg.norm(ukf.x_hat[:2] - p)))
    assert ukf.fixes and ukf.fixes[0] == pytest.approx(0.2)
    assert ukf.uninformed() is None
    assert np.sqrt(np.mean(np.square(errors[40:]))) < 0.2
    assert np.sqrt(np.trace(ukf.x_covariance[:2, :2])) < 0.1
    assert np.linalg.norm(ukf.x_hat[2:] - v) < 0.1
