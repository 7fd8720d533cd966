"""The interface in time: hold(u), predict(t), correct(m) against step(u, y) on a grid, closed forms
and irregular intervals, for every estimator that takes measurements at their own times."""

import math

import numpy as np
import pytest

from quadobs import QuadobsError, vehicle_system
from quadobs.core.immersion import immerse
from quadobs.core.measurements import Measurement, RangeModel, TdoaModel
from quadobs.core.system import range_outputs
from quadobs.estimators.augmented import AugmentedObserver, default_backend
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.zonotopic_vehicle import ZonotopicAugmentedEstimator

BEACONS = np.array([[0.0, 0.0], [20.0, 0.0], [5.0, 15.0]])
DT = 0.05
BACKENDS = ["numpy"] + (["numba"] if default_backend() == "numba" else [])


def _trajectory(steps, beacons=BEACONS, seed=3):
    """Truth of a planar double integrator, its inputs, and one range a step (round-robin)."""
    rng = np.random.default_rng(seed)
    system = vehicle_system(2, beacons)
    model = HeldInputModel(system, DT)
    x = np.array([3.0, 4.0, 1.0, -0.5])
    U, Y, M = [], [], []
    for k in range(steps):
        u = np.array([math.cos(0.3 * k * DT), math.sin(0.2 * k * DT)])
        i = k % len(beacons)
        rho = float(np.linalg.norm(x[:2] - beacons[i])) + 0.1 * rng.standard_normal()
        y = np.full(len(beacons), np.nan)
        y[i] = range_outputs(np.array([rho]), beacons[i : i + 1])[0]
        U.append(u)
        Y.append(y)
        M.append(Measurement(k * DT, "range", rho, (i,)))
        x = model.F @ x + model.G @ u
    return system, np.array(U), np.array(Y), M


def _augmented(system, backend, **kw):
    im = immerse(system)
    x0 = np.array([1.0, 1.0, 0.0, 0.0])
    return AugmentedObserver(
        im, DT, V=1e-3, W=0.05, P0=10.0, z0=im.lift(x0), theta=0.1, backend=backend, **kw
    )


def _filter(cls, system, **kw):
    dyn = HeldInputModel(system, DT, V=np.diag([0.0, 0.0, 0.2, 0.2]), input_covariance=0.01)
    out = OutputModel(system, 0.01, offsets=0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS))
    return cls(dyn, out, x0=[1.0, 1.0, 0.0, 0.0], P0=np.diag([25.0, 25.0, 1.0, 1.0]), **kw)


def _run_in_time(est, U, M):
    for k, m in enumerate(M):
        est.correct(m)
        est.hold(U[k])
        est.predict((k + 1) * DT)


ESTIMATORS = [
    *[pytest.param(lambda s, b=b: _augmented(s, b), id=f"augmented-{b}") for b in BACKENDS],
    pytest.param(lambda s: _filter(ExtendedKalmanFilter, s), id="ekf"),
    pytest.param(lambda s: _filter(UnscentedKalmanFilter, s), id="ukf"),
]


@pytest.mark.parametrize("make", ESTIMATORS)
def test_in_time_on_the_grid_equals_step(make):
    system, U, Y, M = _trajectory(120)
    grid, timed = make(system), make(system)
    for k in range(len(U)):
        grid.step(U[k], Y[k])
    _run_in_time(timed, U, M)
    np.testing.assert_array_equal(timed.x_hat, grid.x_hat)
    np.testing.assert_array_equal(timed.x_covariance, grid.x_covariance)
    assert timed.time == pytest.approx(grid.time, rel=1e-12)
    assert grid.time == pytest.approx(len(U) * DT, rel=1e-12)


def test_zonotope_in_time_on_the_grid_equals_step():
    system, U, Y, M = _trajectory(60)
    im = immerse(system)
    offsets = 0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS)

    def make():
        return ZonotopicAugmentedEstimator(
            im, DT, x0=[3.0, 4.0, 1.0, -0.5], radius=[2.0, 2.0, 1.0, 1.0],
            output_offsets=offsets, output_bounds=np.full(3, 0.5),
        )  # fmt: skip

    grid, timed = make(), make()
    for k in range(len(U)):
        grid.step(U[k], Y[k])
    _run_in_time(timed, U, M)
    np.testing.assert_array_equal(timed.zonotope.center, grid.zonotope.center)
    np.testing.assert_array_equal(timed.bounds, grid.bounds)


@pytest.mark.parametrize("backend", BACKENDS)
def test_augmented_constant_acceleration_closed_form_over_irregular_intervals(backend):
    """No noise, exact start: z(t) = lift(x(t)) with x(t) = (p0 + v0 t + a t^2 / 2, v0 + a t)."""
    system = vehicle_system(2, BEACONS)
    im = immerse(system)
    p0, v0, a = np.array([2.0, -1.0]), np.array([0.5, 0.25]), np.array([0.3, -0.2])
    obs = AugmentedObserver(im, DT, V=0.0, z0=im.lift(np.r_[p0, v0]), backend=backend)
    obs.hold(a)
    for t in np.cumsum([0.013, 0.2, 0.05, 1.7, 0.0004, 0.9]):
        obs.predict(t)
        x = np.r_[p0 + v0 * t + 0.5 * a * t * t, v0 + a * t]
        np.testing.assert_allclose(obs.x_hat, x, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(obs.z, im.lift(x), rtol=1e-10, atol=1e-10)
        assert obs.time == t


@pytest.mark.parametrize("backend", BACKENDS)
def test_augmented_intervals_compose(backend):
    """Predicting over [0, t1] then [t1, t2] is predicting over [0, t2] (mean and covariance)."""
    system = vehicle_system(2, BEACONS)
    one, two = _augmented(system, backend), _augmented(system, backend)
    for est in (one, two):
        est.hold([0.4, -0.7])
    one.predict(0.37)
    one.predict(1.21)
    two.predict(1.21)
    np.testing.assert_allclose(one.z, two.z, rtol=1e-10)
    np.testing.assert_allclose(one.P, two.P, rtol=1e-9)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_filter_prediction_closed_form_constant_velocity(cls):
    """``P(t) = F P F^T + q [[t^3/3, t^2/2], [t^2/2, t]] + s^2 G G^T`` per axis, for a white
    acceleration ``q`` and the accelerometer's error ``s`` held over the interval."""
    system = vehicle_system(2, BEACONS)
    q = 0.2
    f = _filter(cls, system)
    x0, P0 = f.x_hat, f.x_covariance
    f.predict(0.83)
    t = 0.83
    I, Z = np.eye(2), np.zeros((2, 2))
    F = np.block([[I, t * I], [Z, I]])
    Q = q * np.block([[t**3 / 3 * I, t**2 / 2 * I], [t**2 / 2 * I, t * I]])
    G = np.vstack([t**2 / 2 * I, t * I])
    Q += 0.01 * G @ G.T
    np.testing.assert_allclose(f.x_hat, F @ x0, rtol=1e-12)
    np.testing.assert_allclose(f.x_covariance, F @ P0 @ F.T + Q, rtol=1e-10)


def _grid_reference(system, rho: float, r: float) -> AugmentedObserver:
    """The grid observer from ``(1, 1)`` after one correction by a range ``rho`` to anchor 1 whose
    output has the variance ``r``."""
    im = immerse(system)
    ref = AugmentedObserver(
        im, DT, V=1e-3, W=np.diag([1.0, r * DT, 1.0]), P0=10.0,
        z0=im.lift(np.array([1.0, 1.0, 0.0, 0.0])), theta=0.1, backend="numpy",
    )  # fmt: skip
    y = np.full(3, np.nan)
    y[1] = range_outputs(np.array([rho]), BEACONS[1:2])[0]
    ref.correct(y)
    return ref


def test_measurement_std_enters_as_the_squared_range_variance():
    """A range with its own std: the observer's correction with ``R_hh = rho^2 s^2 + s^4 / 2``."""
    system = vehicle_system(2, BEACONS)
    rho, s = 12.0, 0.3
    timed = _augmented(system, "numpy")
    timed.correct(Measurement(0.0, "range", rho, (1,), std=s))
    r = rho**2 * s**2 + s**4 / 2
    ref = _grid_reference(system, rho, r)
    np.testing.assert_allclose(timed.z, ref.z, rtol=1e-12)
    np.testing.assert_allclose(timed.P, ref.P, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("rho", [5.0, 30.0])
def test_a_range_read_short_takes_the_variance_at_the_predicted_range(rho):
    """``range_variance = "larger"``: ``R_hh`` is the larger of ``rho^2 s^2 + s^4 / 2`` at the
    measured range and at the predicted one, ``|p0 - a_1| = sqrt(362)`` from ``p0 = (1, 1)``: a
    range read short (5 m) takes the prediction's, a range read long (30 m) its own."""
    system = vehicle_system(2, BEACONS)
    s = 0.3
    timed = _augmented(system, "numpy")
    timed.range_variance = "larger"
    timed.correct(Measurement(0.0, "range", rho, (1,), std=s))
    r2 = max(rho**2, float(np.sum((np.array([1.0, 1.0]) - BEACONS[1]) ** 2)))
    r = r2 * s**2 + s**4 / 2
    ref = _grid_reference(system, rho, r)
    np.testing.assert_allclose(timed.z, ref.z, rtol=1e-12)
    measured = _augmented(system, "numpy")
    measured.correct(Measurement(0.0, "range", rho, (1,), std=s))
    assert np.allclose(measured.z, timed.z) == (rho > 20.0)  # the default: the measured range


def test_fixed_bias_is_removed_before_the_correction():
    system = vehicle_system(2, BEACONS)
    biased = _filter(
        ExtendedKalmanFilter, system, measurements=RangeModel(BEACONS, 0.1, "fixed", [0, 0.5, 0])
    )
    plain = _filter(ExtendedKalmanFilter, system)
    biased.correct(Measurement(0.0, "range", 10.5, (1,)))
    plain.correct(Measurement(0.0, "range", 10.0, (1,)))
    np.testing.assert_allclose(biased.x_hat, plain.x_hat, rtol=1e-12)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_filters_converge_on_tdoa_measurements(cls):
    """TDOA through the model's h and Jacobian: noise-free pairs at 20 Hz bring a 1 m error down."""
    system = vehicle_system(2, BEACONS)
    models = [RangeModel(BEACONS, 0.1), TdoaModel(BEACONS, 0.05)]
    f = _filter(cls, system, measurements=models)
    f._x[:] = [4.0, 3.5, 1.0, -0.5]  # 1 m off the truth below
    f._P[...] = np.diag([1.0, 1.0, 0.01, 0.01])
    p, v = np.array([3.0, 4.0]), np.array([1.0, -0.5])
    pairs = [(1, 0), (2, 0), (2, 1)]
    for k in range(200):
        t = k * 0.05
        f.predict(t)
        i, j = pairs[k % 3]
        q = p + v * t
        d = np.linalg.norm(q - BEACONS[i]) - np.linalg.norm(q - BEACONS[j])
        f.correct(Measurement(t, "tdoa", float(d), (i, j)))
    assert np.linalg.norm(f.x_hat[:2] - (p + v * t)) < 0.05


def test_refused_with_one_line():
    system = vehicle_system(2, BEACONS)
    obs = _augmented(system, "numpy")
    obs.predict(1.0)
    with pytest.raises(QuadobsError, match="before its current time"):
        obs.predict(0.5)
    with pytest.raises(QuadobsError, match="predict to its time first"):
        obs.correct(Measurement(0.9, "range", 3.0, (0,)))
    with pytest.raises(QuadobsError, match="no model of tdoa"):
        obs.correct(Measurement(1.0, "tdoa", 3.0, (0, 1)))
    with pytest.raises(QuadobsError, match="anchor index"):
        obs.correct(Measurement(1.0, "range", 3.0, (7,)))
    with pytest.raises(QuadobsError, match="no quadratic-output form"):
        _augmented(system, "numpy", measurements=TdoaModel(BEACONS, 0.1))
    with pytest.raises(QuadobsError, match="anchors differ"):
        _filter(ExtendedKalmanFilter, system, measurements=RangeModel(BEACONS + 1.0, 0.1))
    with pytest.raises(QuadobsError, match="u: expected shape"):
        obs.hold([1.0, 2.0, 3.0])


def test_refined_in_time_hands_over_and_ends_near_the_truth():
    """From 3 m off, ranges in time: the observer is reported first, then an EKF at its estimate."""
    from quadobs.estimators.refined import RefinedObserver

    steps = 600
    system, U, Y, M = _trajectory(steps)
    im = immerse(system)
    x0 = np.array([1.0, 1.0, 0.0, 0.0])
    obs = AugmentedObserver(im, DT, V=1e-3, W=0.05, P0=10.0, z0=im.lift(x0), backend="numpy")
    dyn = HeldInputModel(system, DT, V=np.diag([0.0, 0.0, 1e-4, 1e-4]))
    out = OutputModel(system, 0.01, offsets=0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS))
    ref = RefinedObserver(obs, dyn, out, x0=x0, P0=np.diag([25.0, 25.0, 1.0, 1.0]))
    before = []
    for k, m in enumerate(M):
        ref.correct(m)
        if ref.mode == "augmented":
            before.append(np.array_equal(ref.x_hat, obs.x_hat))
        ref.hold(U[k])
        ref.predict((k + 1) * DT)
    assert all(before)
    assert ref.mode == "ekf" and ref.switches[0][1:3] == ("augmented", "ekf")
    model = HeldInputModel(system, DT)
    x = np.array([3.0, 4.0, 1.0, -0.5])
    for u in U:
        x = model.F @ x + model.G @ u
    assert np.linalg.norm(ref.x_hat[:2] - x[:2]) < 0.1
    assert ref.time == pytest.approx(steps * DT)


def test_exact_exponential_of_nilpotent_and_general_matrices():
    from scipy.linalg import expm

    from quadobs.core.held_input import expm_exact

    system = vehicle_system(3, np.array([[1.0, 2.0, 3.0], [4.0, -1.0, 0.5]]))
    im = immerse(system)
    for M in (im.state_matrix(np.array([0.3, -1.0, 2.0])) * 0.7, np.array([[0.1, 1.0], [0, 0]])):
        np.testing.assert_allclose(expm_exact(M), expm(M), rtol=1e-13, atol=1e-14)
