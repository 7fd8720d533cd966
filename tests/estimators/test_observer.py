"""The held-input discretisation and Theorem 3's observer."""

import numpy as np
import pytest
import scipy.linalg as sla
from conftest import random_system
from scipy.integrate import solve_ivp

from quadobs import (
    AugmentedObserver,
    HeldInputDiscretization,
    QuadobsError,
    immerse,
    vehicle_system,
)
from quadobs.core.held_input import van_loan


@pytest.fixture
def vehicle():
    return immerse(vehicle_system(3, np.zeros((1, 3))))


def test_transition_equals_the_matrix_exponential(rng, vehicle):
    """Phi(u) is affine in u and equals expm(A(u) dt) for any held u; g(u) the exact input term."""
    for im in (vehicle, immerse(random_system(rng, 4, 2, 2))):
        dt = 0.05
        disc = HeldInputDiscretization(im, dt)
        N, p = im.dim, im.system.p
        for _ in range(4):
            u = 3 * rng.standard_normal(p)
            big = np.zeros((N + p, N + p))
            big[:N, :N] = im.state_matrix(u)
            big[:N, N:] = im.input_matrix
            E = sla.expm(big * dt)
            np.testing.assert_allclose(disc.transition(u), E[:N, :N], rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(disc.input_term(u), E[:N, N:] @ u, rtol=1e-10, atol=1e-12)


def test_process_noise_polynomial_equals_van_loan(rng, vehicle):
    N = vehicle.dim
    V = rng.standard_normal((N, N))
    V = V @ V.T
    theta = 0.7
    disc = HeldInputDiscretization(vehicle, 0.02, V, theta)
    for _ in range(3):
        u = 5 * rng.standard_normal(3)
        _, Q = van_loan(vehicle.state_matrix(u) + 0.5 * theta * np.eye(N), V, 0.02)
        np.testing.assert_allclose(
            disc.process_noise(u), Q, rtol=1e-8, atol=1e-12 * np.abs(Q).max()
        )


def test_predict_is_exact_under_held_input(rng, vehicle):
    """The discrete map agrees with an ODE solve of z' = A(u) z + B u over the step."""
    disc = HeldInputDiscretization(vehicle, 0.1)
    z0, u = rng.standard_normal(vehicle.dim), rng.standard_normal(3)
    sol = solve_ivp(
        lambda t, z: vehicle.state_matrix(u) @ z + vehicle.input_matrix @ u,
        (0, 0.1),
        z0,
        rtol=1e-12,
        atol=1e-13,
    )
    np.testing.assert_allclose(disc.predict(z0, u), sol.y[:, -1], rtol=1e-9, atol=1e-11)


def _simulate(im, steps, dt, rng, x0):
    s = im.system
    disc = HeldInputDiscretization(im, dt)
    x = x0.copy()
    xs, us, ys = [], [], []
    Ad, Bd = sla.expm(s.A * dt), disc.input_linear
    for k in range(steps):
        u = np.array(
            [np.sin(0.7 * k * dt + j) + 0.5 * np.cos(2.1 * k * dt * (j + 1)) for j in range(s.p)]
        )
        xs.append(x)
        us.append(u)
        ys.append(s.output(x))
        x = Ad @ x + Bd @ u
    return np.array(xs), np.array(us), np.array(ys), x


def test_observer_stays_exact_from_an_exact_start(rng, vehicle):
    """Noise-free, started at lift(x0): the estimate stays exact to rounding (no discretisation error)."""
    dt = 0.01
    x0 = np.array([3.0, -2.0, 1.0, 0.5, 0.2, -0.1])
    xs, us, ys, x_end = _simulate(vehicle, 2000, dt, rng, x0)
    obs = AugmentedObserver(vehicle, dt, x0=x0)
    worst = 0.0
    for k in range(len(us)):
        worst = max(worst, np.abs(obs.x_hat - xs[k]).max())
        obs.step(us[k], ys[k])
    assert worst < 1e-9
    assert np.abs(obs.x_hat - x_end).max() < 1e-9


def test_covariance_stays_symmetric_positive_definite(rng, vehicle):
    dt = 0.001
    xs, us, ys, _ = _simulate(vehicle, 5000, dt, rng, np.array([10.0, 5.0, -3.0, 1.0, 0.0, 2.0]))
    obs = AugmentedObserver(vehicle, dt, V=1e-4, W=1.0, P0=100.0)
    for k in range(len(us)):
        obs.step(us[k], ys[k] + 0.01 * rng.standard_normal(1))
        if k % 500 == 0:
            P = obs.P
            assert np.array_equal(P, P.T)
            assert np.linalg.eigvalsh(P).min() > 0
    assert np.all(np.isfinite(obs.z))


def test_missing_output_means_predict_only(rng, vehicle):
    obs = AugmentedObserver(vehicle, 0.01)
    ref = AugmentedObserver(vehicle, 0.01)
    u = np.array([1.0, 0.0, -1.0])
    obs.step(u, np.array([np.nan]))
    ref.predict(u)
    np.testing.assert_array_equal(obs.z, ref.z)
    np.testing.assert_array_equal(obs.P, ref.P)
    assert obs.corrections == 0 and np.isnan(obs.nis)


def test_partial_outputs_use_the_present_ones(rng):
    im = immerse(vehicle_system(2, np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])))
    obs = AugmentedObserver(im, 0.01, W=[1.0, 2.0, 3.0])
    y = np.array([np.nan, 4.0, np.nan])
    ref = AugmentedObserver(immerse(vehicle_system(2, np.array([[10.0, 0.0]]))), 0.01, W=2.0)
    ref.z[:] = obs.z
    obs.correct(y)
    ref.correct(y[1:2])
    np.testing.assert_allclose(obs.x_hat, ref.x_hat, rtol=1e-12)


def test_gate_rejects_outliers(vehicle):
    obs = AugmentedObserver(vehicle, 0.01, P0=1e-2, x0=np.ones(6), gate=9.0)
    y = vehicle.system.output(np.ones(6))
    obs.correct(y + 1e3)
    assert obs.rejected == 1 and obs.nis > 9.0
    obs.correct(y)
    assert obs.rejected == 1 and obs.corrections == 1


def test_sample_period_scales_the_output_covariance(vehicle):
    obs = AugmentedObserver(vehicle, 0.001, W=2.0, sample_period=0.01)
    np.testing.assert_allclose(obs.R, [[200.0]])


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"W": -1.0}, "W: covariance must be positive definite"),
        ({"P0": np.ones((9, 9))}, "P0: covariance must be positive definite"),
        ({"S0": np.ones((9, 9))}, "S0: covariance must be positive definite"),
        ({"V": np.ones(4)}, "V: expected a scalar"),
        ({"theta": -0.1}, "theta: must be non-negative"),
        ({"x0": np.zeros(5)}, r"x0: expected shape \(6,\)"),
        ({"x0": [np.nan] * 6}, "x0: holds a non-finite value"),
        ({"sample_period": 0.0}, "sample_period: must be positive"),
    ],
)
@pytest.mark.filterwarnings("ignore:AugmentedObserver\\(S0=:DeprecationWarning")
def test_bad_observer_settings_are_named(vehicle, kwargs, match):
    with pytest.raises(QuadobsError, match=match):
        AugmentedObserver(vehicle, 0.01, **kwargs)
    with pytest.raises(QuadobsError, match="dt: must be positive"):
        AugmentedObserver(vehicle, 0.0)


def test_S0_is_the_deprecated_name_of_P0(vehicle):
    new = AugmentedObserver(vehicle, 0.01, P0=3.0)
    with pytest.warns(DeprecationWarning, match=r"S0=\.\.\.\) is deprecated; use P0"):
        old = AugmentedObserver(vehicle, 0.01, S0=3.0)
    np.testing.assert_array_equal(old.P, new.P)
    np.testing.assert_array_equal(new.P, 3.0 * np.eye(9))
    with pytest.raises(QuadobsError, match="S0: give the initial covariance once"):
        AugmentedObserver(vehicle, 0.01, P0=3.0, S0=3.0)
