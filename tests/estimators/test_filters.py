"""The EKF and UKF baselines: exact held-input prediction, measurement spaces, and agreement with Stone Soup."""

import numpy as np
import pytest

from quadobs import QuadobsError, QuadraticSystem, load_scenario, vehicle_system, wind_system
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
    step_power,
)
from quadobs.testbed.factories import baseline_settings, initial_covariance
from quadobs.testbed.registry import build_estimators
from quadobs.testbed.scenario import parse_scenario

BEACONS = np.array([[0.0, 0.0, 0.0], [30.0, -5.0, 2.0], [-10.0, 25.0, -3.0]])


def synthesize(rng, steps, dt, beacons, x0, *, accel_std, range_std, every, missing=0.0):
    """Truth of a 3-D double integrator under a smooth acceleration, noisy ranges as outputs, noisy inputs."""
    system = vehicle_system(3, beacons)
    model = HeldInputModel(system, dt)
    half = 0.5 * np.einsum("hi,hi->h", beacons, beacons)
    x = np.array(x0, dtype=float)
    xs, us, ys = [], [], []
    for k in range(steps):
        t = k * dt
        a = np.array([np.cos(t), 2 * np.sin(2 * t), -np.cos(3 * t)])
        y = np.full(len(beacons), np.nan)
        if k % every == 0:
            rho = np.linalg.norm(x[:3] - beacons, axis=1) + range_std * rng.standard_normal(
                len(beacons)
            )
            y = 0.5 * rho**2 - half
            y[rng.random(len(beacons)) < missing] = np.nan
        xs.append(x.copy())
        us.append(a + accel_std * rng.standard_normal(3))
        ys.append(y)
        x = model.F @ x + model.G @ a
    return system, np.array(xs), np.array(us), np.array(ys), x


def test_held_input_model_double_integrator_closed_form():
    dt, q, s = 0.02, 0.3, 0.7
    system = vehicle_system(2, [[0.0, 0.0]])
    I, Z = np.eye(2), np.zeros((2, 2))
    m = HeldInputModel(system, dt, V=np.diag([0, 0, q, q]), input_covariance=s**2)
    np.testing.assert_allclose(m.F, np.block([[I, dt * I], [Z, I]]), atol=1e-15)
    np.testing.assert_allclose(m.G, np.vstack([0.5 * dt**2 * I, dt * I]), rtol=1e-12)
    Q_V = q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])
    np.testing.assert_allclose(m.Q, Q_V + s**2 * m.G @ m.G.T, rtol=1e-10, atol=1e-18)


def test_lazy_covariance_equals_step_by_step(rng):
    system = vehicle_system(3, BEACONS)
    dyn = HeldInputModel(system, 0.01, V=0.05, input_covariance=0.2)
    out = OutputModel(system, 0.25, offsets=0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS))
    P0 = np.diag(rng.uniform(1, 4, 6))
    f = ExtendedKalmanFilter(dyn, out, x0=np.ones(6), P0=P0)
    P = P0.copy()
    for k in range(37):
        u = rng.standard_normal(3)
        f.step(u, np.full(3, np.nan))
        P = dyn.F @ P @ dyn.F.T + dyn.Q
        if k in (0, 5, 36):
            np.testing.assert_allclose(f.x_covariance, P, rtol=1e-11)
    assert np.isnan(f.nis) and f.nis_dof == 0 and f.corrections == 0


def test_step_power_by_doubling_equals_the_loop(rng):
    F = np.eye(4) + 0.01 * rng.standard_normal((4, 4))
    A = rng.standard_normal((4, 4))
    Q = 1e-3 * A @ A.T
    Fm, Qm = np.eye(4), np.zeros((4, 4))
    for m in range(1, 70):
        Fm, Qm = F @ Fm, F @ Qm @ F.T + Q
        got = step_power(F, Q, m)
        np.testing.assert_allclose(got[0], Fm, rtol=1e-11, atol=1e-14)
        np.testing.assert_allclose(got[1], Qm, rtol=1e-10, atol=1e-14)
    # a long gap between measurements: no recursion, the same covariance as step by step
    system = vehicle_system(3, BEACONS[:1])
    dyn = HeldInputModel(system, 0.001, input_covariance=0.01)
    f = ExtendedKalmanFilter(dyn, OutputModel(system, 1.0), x0=np.zeros(6), P0=1.0)
    P = np.eye(6)
    for _ in range(5000):
        f.step(np.zeros(3), np.array([np.nan]))
        P = dyn.F @ P @ dyn.F.T + dyn.Q
    np.testing.assert_allclose(f.x_covariance, P, rtol=1e-9)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_linear_outputs_give_the_kalman_filter(cls, rng):
    """With C = 0 the outputs are linear; EKF and UKF must reproduce the Kalman filter exactly."""
    n, p, q = 4, 2, 2
    A = rng.standard_normal((n, n)) * 0.3
    B = rng.standard_normal((n, p))
    D = rng.standard_normal((q, n))
    system = QuadraticSystem(A, B, np.zeros((q, n, n)), D)
    dyn = HeldInputModel(system, 0.05, V=0.1 * np.eye(n))
    R = np.array([[0.3, 0.05], [0.05, 0.2]])
    f = cls(dyn, OutputModel(system, R), x0=np.zeros(n), P0=2.0)
    x, P = np.zeros(n), 2.0 * np.eye(n)
    for _ in range(40):
        y, u = rng.standard_normal(q), rng.standard_normal(p)
        S = D @ P @ D.T + R
        K = P @ D.T @ np.linalg.inv(S)
        nu = y - D @ x
        nis = nu @ np.linalg.solve(S, nu)
        x, P = x + K @ nu, (np.eye(n) - K @ D) @ P
        x, P = dyn.F @ x + dyn.G @ u, dyn.F @ P @ dyn.F.T + dyn.Q
        f.step(u, y)
        assert f.nis == pytest.approx(nis, rel=1e-9)
    np.testing.assert_allclose(f.x_hat, x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.x_covariance, P, rtol=1e-9, atol=1e-12)
    assert f.nis_dof == q and f.corrections == 40


def test_norm_space_recovers_the_range_and_its_jacobian(rng):
    system = vehicle_system(3, BEACONS)
    half = 0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS)
    out = OutputModel(system, 0.25, offsets=half)
    assert out.space == "norm" and OutputModel(system, 1.0).space == "output"
    x = np.concatenate([rng.normal(5, 10, 3), rng.standard_normal(3)])
    rho = np.linalg.norm(x[:3] - BEACONS, axis=1)
    np.testing.assert_allclose(out.predict(x), rho, rtol=1e-12)
    np.testing.assert_allclose(out.measure(system.output(x)), rho, rtol=1e-10)
    J = out.jacobian(x)
    h = 1e-6
    num = np.stack(
        [(out.predict(x + h * e) - out.predict(x - h * e)) / (2 * h) for e in np.eye(6)], axis=1
    )
    np.testing.assert_allclose(J, num, atol=1e-8)
    # airspeed of the wind system: y = |v_a|^2/2, offset 0
    ws = wind_system(2, [[1.0, 2.0]])
    wo = OutputModel(ws, [0.1, 0.01], offsets=[2.5, 0.0])
    xw = np.array([3.0, 4.0, 0.6, -0.8, 1.0, 2.0])
    np.testing.assert_allclose(wo.predict(xw), [np.hypot(2.0, 2.0), 1.0], rtol=1e-12)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_missing_outputs_use_the_present_ones_only(cls, rng):
    system = vehicle_system(3, BEACONS)
    half = 0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS)
    R = np.diag([0.1, 0.2, 0.3])
    dyn = HeldInputModel(system, 0.01)
    x0 = np.array([3.0, 4.0, 1.0, 0.5, 0.0, 0.0])
    full = cls(dyn, OutputModel(system, R, offsets=half), x0=x0, P0=4.0)
    sub_sys = vehicle_system(3, BEACONS[[0, 2]])
    sub = cls(
        dyn.__class__(sub_sys, 0.01),
        OutputModel(sub_sys, R[np.ix_([0, 2], [0, 2])], offsets=half[[0, 2]]),
        x0=x0,
        P0=4.0,
    )
    y = system.output(x0 + 0.3) + 0.5
    y[1] = np.nan
    full.correct(y)
    sub.correct(y[[0, 2]])
    np.testing.assert_allclose(full.x_hat, sub.x_hat, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(full.x_covariance, sub.x_covariance, rtol=1e-12, atol=1e-14)
    assert full.nis == pytest.approx(sub.nis, rel=1e-12) and full.nis_dof == 2


def test_gate_rejects_an_outlier():
    system = vehicle_system(3, BEACONS[:1])
    f = ExtendedKalmanFilter(
        HeldInputModel(system, 0.01),
        OutputModel(system, 0.01, offsets=[0.0]),
        x0=[10, 0, 0, 0, 0, 0],
        P0=0.01,
        gate=9.0,
    )
    f.correct(np.array([0.5 * 10.05**2]))
    assert f.corrections == 1 and f.rejected == 0
    x = f.x_hat.copy()
    f.correct(np.array([0.5 * 30.0**2]))
    assert f.rejected == 1 and f.nis > 9.0
    np.testing.assert_array_equal(f.x_hat, x)


def test_ekf_noise_free_start_at_the_truth_stays_exact(rng):
    """The EKF's predicted output is h(x_hat): zero innovations at the truth. (Not so for the UKF, whose
    predicted output is the unscented mean of h, h(x_hat) + tr(C_h P)/2 for a quadratic output.)"""
    system, xs, us, ys, x_end = synthesize(
        rng, 300, 0.01, BEACONS, [5, 6, 1, 1, -1, 0.5], accel_std=0, range_std=0, every=1
    )
    f = ExtendedKalmanFilter(
        HeldInputModel(system, 0.01), OutputModel(system, 1.0), x0=xs[0], P0=1.0
    )
    for u, y in zip(us, ys):
        f.step(u, y)
    np.testing.assert_allclose(f.x_hat, x_end, atol=1e-9)


def test_bad_input_is_refused():
    system = vehicle_system(3, BEACONS)
    dyn = HeldInputModel(system, 0.01)
    out = OutputModel(system, 1.0)
    with pytest.raises(QuadobsError, match="x0"):
        ExtendedKalmanFilter(dyn, out, x0=np.zeros(5), P0=1.0)
    with pytest.raises(QuadobsError, match="P0"):
        ExtendedKalmanFilter(dyn, out, x0=np.zeros(6), P0=-1.0)
    with pytest.raises(QuadobsError, match="R"):
        OutputModel(system, 0.0)
    with pytest.raises(QuadobsError, match="offsets"):
        OutputModel(system, 1.0, offsets=[1.0])
    with pytest.raises(QuadobsError, match="dt"):
        HeldInputModel(system, -1.0)
    with pytest.raises(QuadobsError, match="alpha"):
        UnscentedKalmanFilter(dyn, out, x0=np.zeros(6), P0=1.0, alpha=0.5, kappa=-6.0)


# --------------------------------------------------------------------------------------
# Scenario settings
# --------------------------------------------------------------------------------------


def _noisy(**changes):
    data = load_scenario("ifac2021-noisy").to_dict()
    for k, v in changes.items():
        data[k] = {**data.get(k, {}), **v}
    return parse_scenario(data)


def test_baseline_settings_use_the_true_noise_levels():
    sc = _noisy(noise={"accel_std": 0.1})
    s = baseline_settings(sc)
    assert s.noise_source == "sensors" and s.outputs.space == "norm"
    np.testing.assert_allclose(s.outputs.R, [[0.25]])
    np.testing.assert_allclose(s.dynamics.Q, 0.01 * s.dynamics.G @ s.dynamics.G.T)
    assert s.prior_source == "initial"
    np.testing.assert_allclose(np.diag(s.P0), [400.0] * 3 + [25.0] * 3)


def test_baseline_settings_of_a_noise_free_scenario_use_the_observer_tuning():
    sc = load_scenario("ifac2021")
    s = baseline_settings(sc)
    assert s.noise_source == "observer" and s.outputs.space == "output"
    np.testing.assert_allclose(
        s.outputs.R, [[sc.observer.W * sc.physics_rate]]
    )  # W / T with T = dt
    assert not s.dynamics.Q.any()
    P0, src = initial_covariance(sc)
    assert src == "observer"
    np.testing.assert_allclose(P0, 100.0 * np.eye(6))
    data = sc.to_dict()
    data["observer"]["S0"] = list(range(1, 10))  # the augmented state: 3 auxiliary states, then x
    P0, _ = initial_covariance(parse_scenario(data))
    np.testing.assert_allclose(np.diag(P0), [4, 5, 6, 7, 8, 9])


def test_registered_estimators_run_in_a_scenario():
    sc = _noisy()
    ests = build_estimators(sc, ["augmented", "ekf", "ukf"], np.ones(6))
    assert [e.name for e in ests] == ["augmented", "ekf", "ukf"]
    assert isinstance(ests[1], ExtendedKalmanFilter) and isinstance(ests[2], UnscentedKalmanFilter)
    np.testing.assert_array_equal(ests[1].x_hat, np.ones(6))


# --------------------------------------------------------------------------------------
# Against Stone Soup, a maintained tracking library, on the same data
# --------------------------------------------------------------------------------------


def _stonesoup_models(system, dyn, beacons, R):
    from stonesoup.base import Property
    from stonesoup.models.control.linear import LinearControlModel
    from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
    from stonesoup.models.transition.linear import LinearGaussianTransitionModel
    from stonesoup.types.array import CovarianceMatrix, StateVectors

    class HeldInput(LinearGaussianTransitionModel):
        F: np.ndarray = Property(doc="transition")
        Q: np.ndarray = Property(doc="process noise")

        def matrix(self, **kwargs):
            return self.F

        def covar(self, **kwargs):
            return CovarianceMatrix(self.Q)

    class Ranges(NonLinearGaussianMeasurement):
        beacons: np.ndarray = Property(doc="beacon positions (q, 3)")

        @property
        def ndim_meas(self):
            return len(self.beacons)

        def function(self, state, noise=False, **kwargs):
            X = np.asarray(state.state_vector, dtype=float)
            d = X[None, :3, :] - self.beacons[:, :, None]
            return StateVectors(np.sqrt((d * d).sum(axis=1)))

        def jacobian(self, state, **kwargs):
            x = np.asarray(state.state_vector, dtype=float)[:, 0]
            d = x[:3] - self.beacons
            H = np.zeros((len(self.beacons), 6))
            H[:, :3] = d / np.linalg.norm(d, axis=1)[:, None]
            return H

    transition = HeldInput(F=np.array(dyn.F), Q=np.array(dyn.Q))
    control = LinearControlModel(control_matrix=np.array(dyn.G))

    def ranges(idx):
        return Ranges(
            ndim_state=6, mapping=(0, 1, 2), noise_covar=R[np.ix_(idx, idx)], beacons=beacons[idx]
        )

    return transition, control, ranges


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_agrees_with_stonesoup_on_the_same_data(kind):
    """Step by step, mean and covariance equal Stone Soup's EKF / UKF (same model, same data, same UT parameters)."""
    from datetime import datetime, timedelta

    import stonesoup
    from stonesoup.predictor.kalman import ExtendedKalmanPredictor, UnscentedKalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState, State
    from stonesoup.updater.kalman import ExtendedKalmanUpdater, UnscentedKalmanUpdater

    assert stonesoup.__version__
    rng = np.random.default_rng(7)
    dt, sa, sr = 0.01, 0.2, 0.3
    x0 = np.array([5.0, 12.0, -1.0, 2.0, -1.0, 0.5])
    system, xs, us, ys, _ = synthesize(
        rng, 400, dt, BEACONS, x0, accel_std=sa, range_std=sr, every=5, missing=0.2
    )
    dyn = HeldInputModel(system, dt, input_covariance=sa**2)
    R = np.diag([sr**2, 0.5 * sr**2, 2 * sr**2])
    half = 0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS)
    guess = x0 + np.array([3.0, -2.0, 1.0, 0.5, 0.3, -0.2])
    P0 = np.diag([9.0, 9.0, 4.0, 1.0, 1.0, 1.0])
    ours_cls = ExtendedKalmanFilter if kind == "ekf" else UnscentedKalmanFilter
    ours = ours_cls(dyn, OutputModel(system, R, offsets=half), x0=guess, P0=P0)

    transition, control, ranges = _stonesoup_models(system, dyn, BEACONS, R)
    if kind == "ekf":
        predictor = ExtendedKalmanPredictor(transition, control_model=control)
        updater = ExtendedKalmanUpdater(measurement_model=None, use_joseph_cov=True)
    else:
        predictor = UnscentedKalmanPredictor(
            transition, control_model=control, alpha=1.0, beta=2.0, kappa=0.0
        )
        updater = UnscentedKalmanUpdater(measurement_model=None, alpha=1.0, beta=2.0, kappa=0.0)
    t0 = datetime(2024, 1, 1)
    state = GaussianState(guess.reshape(-1, 1), P0, timestamp=t0)
    updates = 0
    for k, (u, y) in enumerate(zip(us, ys)):
        t = t0 + timedelta(seconds=k * dt)
        idx = np.flatnonzero(~np.isnan(y))
        if idx.size:
            rho = np.sqrt(2 * (y[idx] + half[idx]))
            det = Detection(rho.reshape(-1, 1), timestamp=t, measurement_model=ranges(idx))
            state = updater.update(SingleHypothesis(state, det))
            updates += 1
        state = predictor.predict(
            state, timestamp=t + timedelta(seconds=dt), control_input=State(u.reshape(-1, 1))
        )
        ours.step(u, y)
        if k % 50 == 49 or k == len(us) - 1:
            np.testing.assert_allclose(
                ours.x_hat, np.asarray(state.state_vector, dtype=float)[:, 0], rtol=1e-9, atol=1e-9
            )
            np.testing.assert_allclose(
                ours.x_covariance, np.asarray(state.covar, dtype=float), rtol=1e-8, atol=1e-11
            )
    assert updates == ours.corrections > 60
