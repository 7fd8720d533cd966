"""The on-board EKF peer: rotations, the attitude reset, the time interface, convergence at rest, registration."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from quadobs.core.measurements import Measurement, RangeModel, TdoaModel
from quadobs.errors import QuadobsError
from quadobs.estimators.onboard_ekf import OnboardEKF, rotation_exp, skew

_ANCHORS = np.array(
    [[-3, -3, 0.2], [3, -3, 0.2], [3, 3, 0.2], [-3, 3, 0.2], [-3, -3, 2.8], [3, 3, 2.8]], float
)
_AT_REST = np.array([0.0, 0.0, 9.81, 0.0, 0.0, 0.0])


def _filter(model=None, p0=(0.5, -0.4, 1.2), std=0.5):
    return OnboardEKF(
        model or RangeModel(_ANCHORS, std=0.05),
        1e-3,
        accel_std=0.05,
        gyro_std=0.005,
        x0=np.r_[p0, 0.0, 0.0, 0.0],
        P0=np.eye(6) * std**2,
    )


def test_the_rotation_exponential_is_the_matrix_exponential():
    rng = np.random.default_rng(0)
    for phi in (rng.normal(size=3), np.array([1e-12, 0.0, 0.0])):
        R = rotation_exp(phi)
        assert np.allclose(R, expm(skew(phi)), atol=1e-12)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_at_rest_the_ranges_pull_the_position_to_the_truth():
    truth = np.array([0.3, 0.2, 1.0])
    model = RangeModel(_ANCHORS, std=0.05)
    ekf = _filter(model)
    for k in range(200):
        ekf.hold(_AT_REST)
        for i in range(len(_ANCHORS)):
            ekf.correct(
                Measurement(ekf.time, "range", float(np.linalg.norm(truth - _ANCHORS[i])), (i,))
            )
        ekf.predict((k + 1) * 1e-2)
    assert np.linalg.norm(ekf.x_hat[:3] - truth) < 1e-3
    assert np.linalg.norm(ekf.x_hat[3:]) < 1e-2 and ekf.corrections == 200 * len(_ANCHORS)
    assert np.all(np.linalg.eigvalsh(ekf.x_covariance) > 0.0)


def test_the_fixed_grid_step_is_the_time_interface():
    truth = np.array([0.3, 0.2, 1.0])
    rho = np.linalg.norm(truth - _ANCHORS, axis=1)
    y = 0.5 * rho**2 - 0.5 * np.einsum("hi,hi->h", _ANCHORS, _ANCHORS)  # the testbed's outputs
    a, b = _filter(), _filter()
    for k in range(50):
        a.step(_AT_REST, y if k % 10 == 0 else np.full(len(rho), np.nan))
        if k % 10 == 0:
            for i in range(len(rho)):
                b.correct(Measurement(b.time, "range", float(rho[i]), (i,)))
        b.hold(_AT_REST)
        b.predict((k + 1) * 1e-3)
    assert np.allclose(a.x_hat, b.x_hat, atol=1e-12) and np.allclose(a.P, b.P, atol=1e-12)
    assert a.time == pytest.approx(b.time)


def test_the_attitude_reset_carries_the_covariance_into_the_new_frame():
    """After a correction the attitude error is folded into R and P becomes G P G^T, G = diag(I, I, I - [delta/2]x)."""
    ekf = _filter()
    ekf.P[6:, :3] = ekf.P[:3, 6:] = 0.01 * np.eye(3)  # attitude correlated with position
    ekf.P[6:, 6:] = np.eye(3) * 0.04
    P, R0 = ekf.P.copy(), ekf.R.copy()
    m = Measurement(0.0, "range", 3.0, (0,))
    g = ekf.model.jacobian(ekf.p, m)
    S = g @ P[:3, :3] @ g + 0.05**2
    K = P[:, :3] @ g / S
    r = 3.0 - ekf.model.h(ekf.p, m)
    IKH = np.eye(9)
    IKH[:, :3] -= np.outer(K, g)
    Pu = IKH @ P @ IKH.T + 0.05**2 * np.outer(K, K)
    delta = K[6:] * r
    G = np.eye(9)
    G[6:, 6:] = np.eye(3) - 0.5 * skew(delta)
    ekf.correct(m)
    assert np.linalg.norm(delta) > 1e-3  # the correction did move the attitude
    assert np.allclose(ekf.R, R0 @ expm(skew(delta)), atol=1e-12)
    assert np.allclose(ekf.P, G @ Pu @ G.T, atol=1e-15)


def test_tdoa_corrections_go_through_the_tdoa_model():
    truth = np.array([0.3, 0.2, 1.0])
    model = TdoaModel(_ANCHORS, std=0.05)
    ekf = _filter(model, std=0.3)
    pairs = [(i, 0) for i in range(1, len(_ANCHORS))]
    for k in range(100):
        ekf.hold(_AT_REST)
        for i, j in pairs:
            d = np.linalg.norm(truth - _ANCHORS[i]) - np.linalg.norm(truth - _ANCHORS[j])
            ekf.correct(Measurement(ekf.time, "tdoa", float(d), (i, j)))
        ekf.predict((k + 1) * 1e-2)
    assert np.linalg.norm(ekf.x_hat[:3] - truth) < 1e-2
    with pytest.raises(QuadobsError, match="tdoa"):
        ekf.correct(Measurement(ekf.time, "range", 1.0, (0,)))


def test_bad_input_is_refused_in_one_line():
    ekf = _filter()
    with pytest.raises(QuadobsError, match="6 finite"):
        ekf.hold(np.zeros(3))
    ekf.predict(1.0)
    with pytest.raises(QuadobsError, match="back in time"):
        ekf.predict(0.5)
    assert math.isnan(ekf.nis)


def test_it_is_registered_for_quadrotor_scenarios_only():
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario

    with pytest.raises(QuadobsError, match="body IMU"):
        run_episode(
            load_scenario("ifac2021", settings=["duration=1.0"]), estimators=["onboard-ekf"]
        )
    sc = load_scenario("quadrotor-uwb", settings=["duration=8.0"])
    e = run_episode(sc, estimators=["onboard-ekf"]).summary["estimators"]["onboard-ekf"]
    assert e["final_position_error"] < 0.1
