"""The multilateration start-up of the replay's EKF and UKF (quadobs.estimators.startup)."""

from __future__ import annotations

import numpy as np
import pytest

from quadobs.core.measurements import Measurement
from quadobs.core.system import odometry_system, vehicle_system
from quadobs.estimators.kalman import ExtendedKalmanFilter, HeldInputModel, OutputModel
from quadobs.estimators.startup import FixedStartEKF, FixedStartUKF, start_threshold

ANCHORS = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 30.0], [0.0, 30.0]])
SIGMA = 0.5


def _filter(cls, P0: float, anchors=ANCHORS, q_xy: float = 1.0, x0=(60.0, -40.0)):
    system = odometry_system(anchors)
    dyn = HeldInputModel(system, 0.1, V=q_xy * np.eye(2))
    out = OutputModel(system, SIGMA**2, offsets=0.5 * np.einsum("hi,hi->h", anchors, anchors))
    est = cls(dyn, out, x0=np.array(x0), P0=P0 * np.eye(2))
    if hasattr(est, "start_from_fix"):
        est.start_from_fix(2, start_threshold(anchors, SIGMA))
    return est


def _drive(est, p0, velocity, times, anchors=ANCHORS, first: int = 0):
    """Noise-free ranges one anchor at a time (from anchor ``first`` on), the vehicle at
    ``p0 + velocity t``."""
    est.hold(np.array([*velocity, 0.0]))
    for k, t in enumerate(times, start=first):
        h = k % anchors.shape[0]
        p = p0 + np.asarray(velocity) * t
        est.predict(t)
        est.correct(Measurement(t, "range", float(np.linalg.norm(p - anchors[h])), (h,)))


def test_threshold_is_half_the_extent_at_least_sigma():
    assert start_threshold(ANCHORS, 0.5) == pytest.approx(12.5)  # extent 25 m
    assert start_threshold(ANCHORS, 20.0) == 20.0


@pytest.mark.parametrize("cls", [FixedStartEKF, FixedStartUKF])
def test_moving_vehicle_fixed_exactly_from_ranges_of_different_times(cls):
    """Ranges 0.3 s apart from a vehicle at 3 m/s: the fix, each range moved by the odometry's
    displacement since, is the true position at the fourth range (noise-free: to rounding)."""
    p0, vel = np.array([12.0, 9.0]), np.array([3.0, -1.0])
    est = _filter(cls, 50.0**2)
    assert est.fix_pending
    times = [0.3, 0.6, 0.9]
    _drive(est, p0, vel, times)
    assert est.fix_pending and est.corrections == 3  # waiting: corrected as usual
    _drive(est, p0, vel, [1.2], first=3)  # the fourth anchor's range completes the round
    assert not est.fix_pending and est.fixes == [pytest.approx(1.2)]
    # the completing range is in the fix and is not corrected by again: the fix itself
    assert est.corrections == 3 and np.isnan(est.nis) and est.nis_dof == 0
    np.testing.assert_allclose(est.x_hat, p0 + vel * 1.2, atol=1e-9)


def _least_squares_fix_covariance(p):
    """The weighted least squares' ``(B^T W B)^-1`` of a round of noise-free ranges from ``p``,
    on the position block: ``y_h = c - a_h^T p`` with ``c`` unknown, ``B = [-a_h^T, 1]``, ``W =
    diag(1 / v_h)``, ``v_h = rho_h^2 sigma^2 + sigma^4 / 2`` (closed form of the module
    docstring, written as the joint fit of ``(p, c)``, not the code's centring); it is at most
    the first anchor's differences' ``D^+ Sigma D^+T`` (the fix of before)."""
    rho = np.linalg.norm(p - ANCHORS, axis=1)
    var = rho**2 * SIGMA**2 + 0.5 * SIGMA**4
    B = np.column_stack([-ANCHORS, np.ones(len(ANCHORS))])
    P = np.linalg.inv(B.T @ (B / var[:, None]))[:2, :2]
    pinv = np.linalg.pinv(-(ANCHORS[1:] - ANCHORS[0]))
    before = pinv @ (np.diag(var[1:]) + var[0]) @ pinv.T
    assert np.all(np.linalg.eigvalsh(before - P) > -1e-12)
    return P


def test_fix_covariance_is_the_least_squares_one_plus_the_prediction_since():
    """``P = (D_w^T W D_w)^-1 + q_xy (t - t_0) I`` (closed form) after the range that completes the
    round: the fix's own, that range not corrected by a second time (which would shrink ``P``
    below the covariance of the fix's error: the double count)."""
    p, q_xy = np.array([12.0, 9.0]), 2.0
    est = _filter(FixedStartEKF, 50.0**2, q_xy=q_xy)
    _drive(est, p, (0.0, 0.0), [0.1, 0.2, 0.3, 0.4])
    P_fix = _least_squares_fix_covariance(p) + q_xy * (0.4 - 0.1) * np.eye(2)
    np.testing.assert_allclose(est.x_covariance, P_fix, rtol=1e-9, atol=1e-12)
    # the re-correction by the completing range (anchor 3) the fix is made of, as it was made
    H = ((p - ANCHORS[3]) / np.linalg.norm(p - ANCHORS[3]))[None, :]
    twice = np.linalg.inv(np.linalg.inv(P_fix) + H.T @ H / SIGMA**2)
    assert np.trace(twice) < 0.8 * np.trace(est.x_covariance)


@pytest.mark.parametrize("cls", [FixedStartEKF, FixedStartUKF])
def test_grid_step_fix_is_not_corrected_by_its_own_outputs(cls):
    """One grid step with every range present fixes the position from them: the estimate is the
    truth and its covariance ``(D_w^T W D_w)^-1`` (closed form, no prediction since); before, the
    same outputs corrected it once more, and ``P`` came out near half of it (the double count of
    the linear case, ``(2 H^T R^-1 H)^-1``)."""
    p = np.array([12.0, 9.0])
    est = _filter(cls, 50.0**2)
    y = 0.5 * p @ p - ANCHORS @ p
    est.correct_outputs(y)
    assert est.fixes == [0.0] and est.corrections == 0 and np.isnan(est.nis)
    np.testing.assert_allclose(est.x_hat, p, atol=1e-9)
    P_fix = _least_squares_fix_covariance(p)
    np.testing.assert_allclose(est.x_covariance, P_fix, rtol=1e-9, atol=1e-12)
    # what the second correction by the same four ranges would have made of it: about P_fix / 2
    H = (p - ANCHORS) / np.linalg.norm(p - ANCHORS, axis=1)[:, None]
    twice = np.linalg.inv(np.linalg.inv(P_fix) + H.T @ H / SIGMA**2)
    ratio = np.linalg.eigvals(np.linalg.solve(P_fix, twice)).real
    assert np.all((ratio > 0.45) & (ratio < 0.55))
    # the next step's outputs are new ranges: corrected as usual (one joint correction)
    est.correct_outputs(y)
    assert est.corrections == 1 and est.nis_dof == 4


def test_narrow_prior_is_the_plain_filter():
    """A prior narrower than the threshold: no fix, the plain EKF's estimates to the bit."""
    est, plain = (
        _filter(FixedStartEKF, 4.0, x0=(11.0, 8.0)),
        _filter(ExtendedKalmanFilter, 4.0, x0=(11.0, 8.0)),
    )
    assert not est.fix_pending
    times = np.arange(1, 13) * 0.25
    _drive(est, np.array([12.0, 9.0]), (1.0, 0.5), times)
    _drive(plain, np.array([12.0, 9.0]), (1.0, 0.5), times)
    assert est.fixes == []
    np.testing.assert_array_equal(est.x_hat, plain.x_hat)


def test_collinear_anchors_fix_the_coordinate_they_determine():
    """Anchors on the x axis fix ``x`` alone (differences of the outputs are ``-(a_h - a_0)_x x``):
    after one round ``x`` is the truth's (the guess was 55 m off)."""
    line = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    est = _filter(FixedStartEKF, 50.0**2, anchors=line, q_xy=1.0)
    _drive(est, np.array([5.0, 7.0]), (0.0, 0.0), [0.1, 0.2], anchors=line)
    assert est.fix_pending
    _drive(est, np.array([5.0, 7.0]), (0.0, 0.0), [0.3], anchors=line, first=2)
    assert not est.fix_pending and est.fixes == [pytest.approx(0.3)]
    # (the completing range is then corrected at the estimate's y, which moves x by centimetres)
    assert est.x_hat[0] == pytest.approx(5.0, abs=0.1)


def test_grid_outputs_fix_a_vehicle_with_velocity():
    """The grid's ``step(u, y)`` path: one snapshot of all anchors fixes the position of a
    3-D vehicle (state ``(p, v)``) exactly; its velocity keeps its prior."""
    anchors = np.array(
        [[-3.0, -3.0, 0.2], [3.0, -3.0, 0.2], [3.0, 3.0, 2.8], [-3.0, 3.0, 2.8], [0.0, 0.0, 3.0]]
    )
    system = vehicle_system(3, anchors)
    dyn = HeldInputModel(system, 0.01, V=np.diag([0.0] * 3 + [1e-2] * 3))
    out = OutputModel(system, SIGMA**2, offsets=0.5 * np.einsum("hi,hi->h", anchors, anchors))
    P0 = np.diag([100.0] * 3 + [4.0] * 3)
    est = FixedStartEKF(dyn, out, x0=np.array([9.0, -9.0, 5.0, 0.0, 0.0, 0.0]), P0=P0)
    est.start_from_fix(3, start_threshold(anchors, SIGMA))
    p = np.array([0.5, -1.0, 1.5])
    y = 0.5 * p @ p - anchors @ p
    est.step(np.zeros(3), y)
    assert est.fixes == [0.0]
    np.testing.assert_allclose(est.x_hat[:3], p, atol=1e-9)
    np.testing.assert_allclose(
        est.x_covariance[3:, 3:], 4.0 * np.eye(3) + 1e-2 * 0.01 * np.eye(3), rtol=1e-6
    )


def test_the_replay_builders_arm_the_start_up_from_a_wide_prior_only():
    """``build_ekf``/``build_ukf`` of a replay: armed from 50 m (``P0 = 2500``), not from 2 m."""
    from quadobs.testbed.logs.estimators import ReplaySetup, build_ekf, build_ukf

    x0 = np.array([1.0, 2.0])
    for P0, armed in ((2500.0, True), (4.0, False)):
        s = ReplaySetup(ANCHORS, 0.1, "odometry", 0.0, 20.0, range_sigma=SIGMA, P0=P0)
        ekf, ukf = build_ekf(s, x0), build_ukf(s, x0)
        assert isinstance(ekf, FixedStartEKF) and isinstance(ukf, FixedStartUKF)
        assert ekf.fix_pending is armed and ukf.fix_pending is armed


def test_the_waiting_corrections_weigh_the_second_order_term():
    """``tr((H_2 P)^2) / 2`` in closed form: ``P = s^2 I`` at ``rho`` from the anchor in the
    plane, ``H_2 P = (s^2 / rho) (I - u u^T)`` of rank one: ``s^4 / (2 rho^2)`` (1250 m^2 for a
    50 m prior at 50 m); after the fix the term is gone."""
    est = _filter(FixedStartEKF, 50.0**2, x0=(50.0, 0.0))
    assert est._curvature_variance(0) == pytest.approx(50.0**4 / (2 * 50.0**2))
    p = np.array([12.0, 9.0])
    _drive(est, p, (0.0, 0.0), [0.1, 0.2, 0.3, 0.4])
    assert est.fixes and est._curvature_variance(0) < 1.0


def test_the_ukf_waits_with_the_ranges_own_variance():
    """The UKF's sigma points already follow the range's curvature: its first waiting correction
    is the plain UKF's with the range's variance ``sigma^2`` (to the bit), its ``S`` the closed
    form of the unscented transform (``n + lambda = 2``, ``W^c_0 = 2``, ``W_i = 1/4``) plus
    ``sigma^2`` (1.18 s^2 of spread for a 50 m prior at 50 m), not ``tr((H_2 P)^2) / 2`` more."""
    from quadobs.estimators.kalman import UnscentedKalmanFilter

    est = _filter(FixedStartUKF, 50.0**2, x0=(50.0, 0.0))
    plain = _filter(UnscentedKalmanFilter, 50.0**2, x0=(50.0, 0.0))
    assert est.fix_pending
    rho = 30.0
    for f in (est, plain):
        f.correct(Measurement(0.0, "range", rho, (0,)))
    assert est.fix_pending and est.corrections == 1
    np.testing.assert_array_equal(est.x_hat, plain.x_hat)
    np.testing.assert_array_equal(est.x_covariance, plain.x_covariance)
    x, d = np.array([50.0, 0.0]), 50.0 * np.sqrt(2.0) * np.eye(2)
    Z = np.linalg.norm(np.array([x, x + d[0], x + d[1], x - d[0], x - d[1]]), axis=1)
    z = Z[1:].mean()
    S = 2.0 * (Z[0] - z) ** 2 + np.sum((Z[1:] - z) ** 2) / 4.0 + SIGMA**2
    assert S / 50.0**2 == pytest.approx(1.18, abs=0.005)
    assert est.nis == pytest.approx((rho - z) ** 2 / S, rel=1e-12)


def _moving(cls, velocity_prior, v0=(0.0, 0.0)):
    """A 2-D vehicle state ``(p, v)`` without process noise, 50 m of prior on the position and
    ``velocity_prior`` (m/s) on the velocity about ``v0``, armed."""
    system = vehicle_system(2, ANCHORS)
    dyn = HeldInputModel(system, 0.1, V=np.zeros((4, 4)))
    out = OutputModel(system, SIGMA**2, offsets=0.5 * np.einsum("hi,hi->h", ANCHORS, ANCHORS))
    P0 = np.diag([50.0**2] * 2 + [velocity_prior**2] * 2)
    est = cls(dyn, out, x0=np.array([60.0, -40.0, *v0]), P0=P0)
    est.start_from_fix(2, start_threshold(ANCHORS, SIGMA))
    return est


def _cruise(est, p0, velocity, times, first: int = 0):
    """Noise-free ranges one anchor at a time (from anchor ``first`` on) from
    ``p0 + velocity t``, no input."""
    est.hold(np.zeros(2))
    for k, t in enumerate(times, start=first):
        h = k % ANCHORS.shape[0]
        est.predict(t)
        p = p0 + np.asarray(velocity) * t
        est.correct(Measurement(t, "range", float(np.linalg.norm(p - ANCHORS[h])), (h,)))


@pytest.mark.parametrize("cls", [FixedStartEKF, FixedStartUKF])
def test_the_joint_fix_is_exact_where_the_prior_velocity_is_the_truth(cls):
    """Ranges of a round 0.3 s apart from a vehicle at 3 m/s, the velocity's prior (20 m/s, which
    leaves the position's fix wider than the threshold) about the truth: the joint fix is the
    true position and velocity at the round's last range."""
    p0, vel = np.array([12.0, 9.0]), np.array([3.0, -1.0])
    est = _moving(cls, 20.0, v0=vel)
    _cruise(est, p0, vel, [0.3, 0.6, 0.9, 1.2])
    assert est.fixes == [pytest.approx(1.2)]
    np.testing.assert_allclose(est.x_hat, [*(p0 + 1.2 * vel), *vel], atol=1e-9)


def test_the_joint_fix_takes_the_velocity_from_the_round():
    """From a 20 m/s prior about 0 the round's ranges tell the velocity: the fix minimises
    ``sum (rho_h - |p_h - a_h|)^2 / sigma^2 + v^T v / 400`` (its gradient vanishes) and its
    covariance is the inverse normal matrix (closed form at the estimate, ``p_h = p - v (t - t_h)``;
    ``chi^2`` below its ``dof = 4 - 2``): the velocity's spread falls from 20 m/s."""
    p0, vel, times = np.array([12.0, 9.0]), np.array([3.0, -1.0]), [0.3, 0.6, 0.9, 1.2]
    est = _moving(FixedStartEKF, 20.0)
    _cruise(est, p0, vel, times)
    assert est.fixes == [pytest.approx(1.2)]
    p, v = est.x_hat[:2], est.x_hat[2:]
    J, e = [], []
    for k, t in enumerate(times):
        r = p - v * (1.2 - t) - ANCHORS[k]
        u = r / np.linalg.norm(r)
        J.append(np.r_[u, -(1.2 - t) * u] / SIGMA)
        e.append((np.linalg.norm(p0 + vel * t - ANCHORS[k]) - np.linalg.norm(r)) / SIGMA)
    J, e = np.array(J), np.array(e)
    prior = np.diag([0.0, 0.0, 1.0, 1.0]) / 400.0
    np.testing.assert_allclose(J.T @ e - prior @ est.x_hat, 0.0, atol=1e-8)
    assert e @ e + v @ v / 400.0 < 2.0  # chi^2 within its dof = 4 - 2: the stated variances
    expected = np.linalg.inv(J.T @ J + prior)
    np.testing.assert_allclose(est.x_covariance, expected, rtol=1e-6)
    assert np.all(np.sqrt(np.diag(est.x_covariance)[2:]) < 2.0)
    assert np.linalg.norm(v - vel) < 3.0 * np.sqrt(np.max(np.linalg.eigvalsh(expected[2:, 2:])))


def test_ranges_that_disagree_widen_the_joint_fix():
    """Anchor 3 silent for a round: seven ranges before the round is in, those of anchors 0 to 2
    1.5 m long, then as long short (``chi^2`` far above its ``dof = 7 - 2``). The fix takes the
    ranges' variance ``s = chi^2 / dof`` times the stated one, ``chi^2`` the minimum of the
    stated weights (found here by scipy), and is the minimiser with the new weights, its
    covariance ``(J^T J / (s sigma^2) + prior)^-1`` (closed form at the minimiser)."""
    from scipy.optimize import least_squares

    p0, vel = np.array([12.0, 9.0]), np.array([1.0, 0.5])
    anchor = [0, 1, 2, 0, 1, 2, 3]
    lie = np.array([1.5, 1.5, 1.5, -1.5, -1.5, -1.5, 0.0])
    times = [0.1 * (k + 1) for k in range(7)]
    rho = np.array([np.linalg.norm(p0 + vel * t - ANCHORS[h]) for h, t in zip(anchor, times)])
    rho = rho + lie
    est = _moving(FixedStartEKF, 30.0)
    est.hold(np.zeros(2))
    for h, t, r in zip(anchor, times, rho):
        est.predict(t)
        est.correct(Measurement(t, "range", float(r), (h,)))
    assert est.fixes == [pytest.approx(0.7)]

    def residuals(x, s):
        r = [x[:2] - x[2:] * (0.7 - t) - ANCHORS[h] for h, t in zip(anchor, times)]
        e = (rho - np.linalg.norm(r, axis=1)) / (SIGMA * np.sqrt(s))
        return np.r_[e, x[2:] / 30.0]

    tight = {"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15}
    first = least_squares(residuals, est.x_hat, args=(1.0,), **tight)
    s = 2.0 * first.cost / (7 - 2)
    assert s > 4.0
    again = least_squares(residuals, est.x_hat, args=(s,), **tight)
    # the same minimiser, to the steps' tolerance (1e-4 of its standard deviations)
    assert np.all(np.abs(est.x_hat - again.x) < 1e-3 * np.sqrt(np.diag(est.x_covariance)))
    J = again.jac[:7]
    expected = np.linalg.inv(J.T @ J + np.diag([0.0, 0.0, 1.0, 1.0]) / 900.0)
    np.testing.assert_allclose(est.x_covariance, expected, rtol=1e-4)


def test_a_fix_within_the_threshold_leaves_the_velocity_to_the_filter():
    """The same round from a 2 m/s prior: the position's fix (its growth ``2 m/s x 0.9 s``) is
    within the threshold (12.5 m), so the position alone is fixed and the velocity keeps what
    the waiting corrections made of it, as before (``quadrotor-uwb-realistic``, the replay)."""
    p0, vel = np.array([12.0, 9.0]), np.array([3.0, -1.0])
    est = _moving(FixedStartEKF, 2.0)
    _cruise(est, p0, vel, [0.3, 0.6, 0.9])
    before = est.x_hat[2:].copy()
    _cruise(est, p0, vel, [1.2], first=3)
    assert est.fixes == [pytest.approx(1.2)]
    np.testing.assert_array_equal(est.x_hat[2:], before)
    assert np.sqrt(np.max(np.linalg.eigvalsh(est.x_covariance[:2, :2]))) < 12.5


def test_anchors_at_one_height_fix_the_horizontal_and_leave_the_height_to_its_prior():
    """Anchors all at 2.5 m: the differences of the outputs hold no vertical term, so one grid
    step's round fixes ``x`` and ``y`` (exactly, noise-free) and leaves the height, the velocity
    and their variances at the prior."""
    anchors = np.array([[0.0, 0.0, 2.5], [6.0, 0.0, 2.5], [6.0, 5.0, 2.5], [0.0, 5.0, 2.5]])
    system = vehicle_system(3, anchors)
    dyn = HeldInputModel(system, 0.01, V=np.zeros((6, 6)))
    out = OutputModel(system, SIGMA**2, offsets=0.5 * np.einsum("hi,hi->h", anchors, anchors))
    P0 = np.diag([100.0] * 3 + [4.0] * 3)
    x0 = np.array([9.0, -9.0, 0.5, 0.0, 0.0, 0.0])
    est = FixedStartEKF(dyn, out, x0=x0, P0=P0)
    est.start_from_fix(3, start_threshold(anchors, SIGMA))
    p = np.array([2.0, 3.0, 1.0])
    est.correct_outputs(0.5 * p @ p - anchors @ p)
    assert est.fixes == [0.0]
    np.testing.assert_allclose(est.x_hat[:2], p[:2], atol=1e-9)
    np.testing.assert_array_equal(est.x_hat[2:], x0[2:])
    np.testing.assert_array_equal(np.diag(est.x_covariance)[2:], np.diag(P0)[2:])


def test_the_weighted_fix_is_the_joint_least_squares_and_does_not_depend_on_the_order():
    """``multilateration(..., variances=v)``: the position of the weighted least squares of
    ``y_h = c - a_h^T p`` with ``c`` unknown (closed form, the joint fit of ``(p, c)``), the
    same for the anchors in any order; from the first anchor's output it is not."""
    from quadobs.estimators.robust import multilateration

    rng = np.random.default_rng(4)
    p = np.array([12.0, 9.0])
    C = np.broadcast_to(np.eye(2), (len(ANCHORS), 2, 2))
    rho = np.linalg.norm(p - ANCHORS, axis=1) + 0.3 * rng.standard_normal(len(ANCHORS))
    y, v = 0.5 * rho**2 - 0.5 * np.sum(ANCHORS**2, axis=1), rho**2 * 0.09 + 0.5 * 0.3**4
    B = np.column_stack([-ANCHORS, np.ones(len(ANCHORS))])
    joint = np.linalg.solve(B.T @ (B / v[:, None]), B.T @ (y / v))[:2]
    fixes, plain = [], []
    for order in ([0, 1, 2, 3], [3, 1, 0, 2], [2, 3, 1, 0]):
        fixes.append(multilateration(C, -ANCHORS[order], y[order], variances=v[order])[1])
        plain.append(multilateration(C, -ANCHORS[order], y[order])[1])
    for f in fixes:
        np.testing.assert_allclose(f, joint, atol=1e-9)
    assert max(np.linalg.norm(f - plain[0]) for f in plain[1:]) > 1e-3


@pytest.mark.parametrize("cls", [FixedStartEKF, FixedStartUKF])
def test_a_round_whose_fix_covariance_is_singular_waits_for_the_next(cls, monkeypatch):
    """A round of full rank whose covariance is singular to working precision (anchors nearly
    in line, seen from far off) gives no fix and no error: the filter waits, corrected as
    usual, and fixes from the next round."""
    import quadobs.estimators.startup as startup

    p0, vel = np.array([12.0, 9.0]), np.array([3.0, -1.0])
    est = _filter(cls, 50.0**2)
    real = startup.multilateration_covariance
    calls = []

    def singular_once(D, variances):
        calls.append(1)
        if len(calls) == 1:
            raise np.linalg.LinAlgError("Singular matrix")
        return real(D, variances)

    monkeypatch.setattr(startup, "multilateration_covariance", singular_once)
    _drive(est, p0, vel, [0.3, 0.6, 0.9, 1.2])
    assert est.fix_pending and est.fixes == []  # the first round gave none
    _drive(est, p0, vel, [1.5], first=4)
    assert not est.fix_pending and est.fixes == [pytest.approx(1.5)]
