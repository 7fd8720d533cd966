"""Metrics against closed forms: chi-square intervals, the posterior Cramér-Rao bound, and a linear Gaussian
Monte Carlo where the Kalman filter attains the bound and its NEES and NIS are chi-square."""

import numpy as np
import pytest
from scipy import stats

from quadobs import QuadobsError, QuadraticSystem, load_scenario
from quadobs.estimators.kalman import ExtendedKalmanFilter, HeldInputModel, OutputModel
from quadobs.evaluation.ensemble import (
    chi2_interval,
    convergence_times,
    ensemble,
    lifted_covariance,
    nees,
    posterior_crb,
    range_factor,
    rmse,
    set_containment,
)
from quadobs.testbed.bounds import immersion_bound, scenario_crb
from quadobs.testbed.scenario import parse_scenario


def test_chi2_interval_closed_form():
    lo, hi = chi2_interval(6, 1, 0.95)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, 6)) and hi == pytest.approx(
        stats.chi2.ppf(0.975, 6)
    )
    # N runs of an n-dim NEES: N * mean ~ chi2(N n); for large N about n +- 1.96 sqrt(2 n / N)
    lo, hi = chi2_interval(6 * 2000, 2000, 0.95)
    assert lo == pytest.approx(6 - 1.96 * np.sqrt(12 / 2000), abs=0.01)
    assert hi == pytest.approx(6 + 1.96 * np.sqrt(12 / 2000), abs=0.01)
    b = chi2_interval(np.array([0, 4]), np.array([0, 2]))
    assert np.isnan(b[0]).all() and np.isfinite(b[1]).all()
    with pytest.raises(QuadobsError, match="confidence"):
        chi2_interval(3, 1, 1.5)


def test_nees_rmse_convergence_and_containment_by_hand():
    e = np.array([[1.0, 2.0], [0.0, 3.0]])
    P = np.array([np.diag([1.0, 4.0]), np.full((2, 2), np.nan)])
    out = nees(e, P)
    assert out[0] == pytest.approx(2.0) and np.isnan(out[1])
    errs = np.array([[[3.0, 4.0]], [[0.0, 0.0]]])  # (R=2, T=1, 2)
    assert rmse(errs)[0] == pytest.approx(np.sqrt(12.5))
    t = np.array([0.0, 1.0, 2.0, 3.0])
    err = np.array(
        [[5, 0.5, 2, 0.1], [0.1, 0.2, 0.3, 0.4], [0.1, 0.2, 0.3, 3.0], [np.nan, 0.5, 0.5, 0.5]]
    )
    np.testing.assert_array_equal(convergence_times(t, err, 1.0), [3.0, 0.0, np.nan, 1.0])
    truth = np.array([[0.0, 1.0], [0.0, 5.0], [0.0, 0.0]])
    bounds = np.array([[[-1, 1], [0, 2]], [[-1, 1], [0, 2]], [[np.nan, 1], [0, 1]]])
    np.testing.assert_array_equal(set_containment(truth, bounds), [1.0, 0.0, np.nan])


def test_range_factor_is_the_fisher_information_of_a_range():
    p, a, s = (
        np.array([3.0, -4.0, 12.0]),
        np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),
        np.array([0.5, 2.0]),
    )
    L = range_factor(p, a, s)
    for h in range(2):
        grad = (p - a[h]) / np.linalg.norm(p - a[h])
        np.testing.assert_allclose(L[:, h] @ L[:, h].T, grad @ grad / s[h] ** 2)
        np.testing.assert_allclose(
            np.outer(L[:, h], L[:, h]), np.outer(grad, grad) / s[h] ** 2, rtol=1e-12
        )


def _random_spd(rng, n, scale=1.0):
    M = rng.standard_normal((n, n))
    return scale * (M @ M.T + n * np.eye(n))


def test_pcrb_equals_the_tichavsky_recursion(rng):
    """Covariance form == J_{k+1} = D22 - D21 (J_k + D11)^-1 D12 with nonsingular Q (Tichavsky et al. 1998, eq. 21)."""
    n, K = 4, 30
    F = np.eye(n) + 0.1 * rng.standard_normal((n, n))
    Q = _random_spd(rng, n, 0.01)
    P0 = _random_spd(rng, n)
    Ls = {k: rng.standard_normal((n, 2)) for k in range(K) if k % 3 != 2}
    out = posterior_crb(F, Q, P0, K, Ls.get, every=1)
    Qi = np.linalg.inv(Q)
    D11, D12 = F.T @ Qi @ F, -F.T @ Qi
    J = np.linalg.inv(P0)
    for k in range(K):
        np.testing.assert_allclose(out[k], np.linalg.inv(J), rtol=1e-8)
        J = J + (
            Ls[k] @ Ls[k].T if k in Ls else 0.0
        )  # the measurement at t_k enters before the step
        J = Qi - D12.T @ np.linalg.solve(J + D11, D12)
    np.testing.assert_allclose(out[K], np.linalg.inv(J), rtol=1e-8)


def test_pcrb_without_process_noise_is_the_information_form(rng):
    """Q = 0: J_{k+1} = F^-T (J_k + H^T R^-1 H) F^-1; sampling every 5 steps returns those rows."""
    n, K = 3, 40
    F = np.eye(n) + 0.05 * rng.standard_normal((n, n))
    P0 = _random_spd(rng, n)
    L = rng.standard_normal((n, 1))
    out = posterior_crb(F, np.zeros((n, n)), P0, K, lambda k: L if k % 4 == 0 else None, every=5)
    assert out.shape == (K // 5 + 1, n, n)
    Fi = np.linalg.inv(F)
    J = np.linalg.inv(P0)
    for k in range(K + 1):
        if k % 5 == 0:
            np.testing.assert_allclose(out[k // 5], np.linalg.inv(J), rtol=1e-8)
        if k % 4 == 0:
            J = J + L @ L.T
        J = Fi.T @ J @ Fi


def test_pcrb_of_a_static_position_from_ranges():
    """F = I, Q = 0, two beacons: after K samples the bound is (J0 + K sum u u^T / sigma^2)^-1."""
    p = np.array([3.0, 4.0])
    beacons = np.array([[0.0, 0.0], [10.0, 0.0]])
    s, K = 0.2, 25
    L = range_factor(p, beacons, s)
    out = posterior_crb(np.eye(2), np.zeros((2, 2)), 9.0 * np.eye(2), K, lambda k: L)
    u = (p - beacons) / np.linalg.norm(p - beacons, axis=1)[:, None]
    J = np.eye(2) / 9.0 + K * (u.T @ u) / s**2
    np.testing.assert_allclose(out[K], np.linalg.inv(J), rtol=1e-10)


def test_pcrb_refuses_bad_input():
    with pytest.raises(QuadobsError, match="Q"):
        posterior_crb(np.eye(2), -np.eye(2), np.eye(2), 3, lambda k: None)
    with pytest.raises(QuadobsError, match="every"):
        posterior_crb(np.eye(2), np.eye(2), np.eye(2), 3, lambda k: None, every=0)


def test_linear_gaussian_kalman_filter_attains_the_bound_and_is_consistent():
    """1-D double integrator, noisy accelerometer, position measured every 2 steps; x0 drawn from the prior.

    The Kalman filter (the EKF of a linear output) is then the MMSE estimator: its covariance equals the
    PCRB at every step, the RMSE over runs matches sqrt(tr PCRB), and NEES and NIS are chi-square.
    """
    rng = np.random.default_rng(123)
    dt, sa, sr, steps, runs = 0.1, 0.5, 0.4, 60, 1000
    system = QuadraticSystem([[0, 1], [0, 0]], [[0], [1]], np.zeros((1, 2, 2)), [[1.0, 0.0]])
    dyn = HeldInputModel(system, dt, input_covariance=sa**2)
    out = OutputModel(system, sr**2)
    m0, P0 = np.array([1.0, -0.5]), np.diag([4.0, 1.0])
    Lmeas = np.array([[1.0 / sr], [0.0]])
    bound = posterior_crb(dyn.F, dyn.Q, P0, steps, lambda k: Lmeas if k % 2 == 0 else None)
    T = steps + 1
    err = np.zeros((runs, T, 2))
    cov = np.zeros((runs, T, 2, 2))
    nis = np.full((runs, T), np.nan)
    dof = np.zeros((runs, T))
    for r in range(runs):
        x = m0 + np.linalg.cholesky(P0) @ rng.standard_normal(2)
        f = ExtendedKalmanFilter(dyn, out, x0=m0, P0=P0)
        for k in range(steps):
            err[r, k], cov[r, k] = f.x_hat - x, f.x_covariance
            y = np.array([x[0] + sr * rng.standard_normal()]) if k % 2 == 0 else np.array([np.nan])
            u_true = np.array([np.sin(0.3 * k)])
            f.step(u_true + sa * rng.standard_normal(1), y)
            nis[r, k], dof[r, k] = f.nis, f.nis_dof
            x = dyn.F @ x + dyn.G @ u_true
        err[r, steps], cov[r, steps] = f.x_hat - x, f.x_covariance
    # the filter's covariance is the bound (same for every run)
    np.testing.assert_allclose(cov[0], bound, rtol=1e-9)
    ne = nees(err, cov)
    ens = ensemble(
        np.arange(T) * dt,
        err[..., :1],
        err[..., 1:],
        nees=ne,
        nis=nis,
        nis_dof=dof,
        state_dim=2,
        bound=np.sqrt(np.stack([bound[:, 0, 0], bound[:, 1, 1]], axis=1)),
    )
    # RMSE over 1000 runs matches the bound: 3 standard errors of an MSE estimate (sqrt(2/N) relative) at the end
    assert ens.ratio_position[-1] ** 2 == pytest.approx(1.0, abs=3 * np.sqrt(2 / runs))
    assert ens.ratio_velocity[-1] ** 2 == pytest.approx(1.0, abs=3 * np.sqrt(2 / runs))
    assert np.mean(ens.ratio_position**2) == pytest.approx(1.0, abs=0.05)
    # NEES: N * mean ~ chi2(2N); the time-averaged mean is about n, and the mean at each time is inside the
    # 95 % interval at about 95 % of the times
    s = ens.summary()
    assert s["nees_time_average"] == pytest.approx(2.0, abs=0.1)
    assert 0.88 <= s["nees_inside_fraction"] <= 1.0
    assert s["chi2_bounds"]["nees"] == pytest.approx(list(chi2_interval(2 * runs, runs)), rel=1e-12)
    # NIS of the scalar output: mean about 1, inside its interval at about 95 % of the update times
    assert s["mean_nis"] == pytest.approx(1.0, abs=0.05)
    assert 0.88 <= s["nis_inside_fraction"] <= 1.0
    assert s["chi2_bounds"]["nis_dof_per_run"] == 1
    # an overconfident filter (covariance / 4) fails the test
    bad = ensemble(
        np.arange(T) * dt, err[..., :1], err[..., 1:], nees=nees(err, cov / 4), state_dim=2
    )
    assert bad.summary()["nees_inside_fraction"] < 0.05


def test_ensemble_summary_of_synthetic_runs():
    t = np.linspace(0, 1, 5)
    R = 4
    ep = np.zeros((R, 5, 2))
    ep[:, :, 0] = np.array(
        [[5, 4, 3, 0.5, 0.2], [5, 2, 0.5, 0.4, 0.3], [5, 5, 5, 5, 5], [1, 0.5, 2, 0.5, 0.1]]
    )[:, :]
    ev = np.zeros((R, 5, 2))
    s = ensemble(
        t, ep, ev, nees=np.full((R, 5), 2.0), state_dim=2, threshold=1.0, bound=np.full((5, 2), 0.5)
    ).summary()
    assert s["runs"] == 4 and s["converged_runs"] == 3 and s["converged_fraction"] == 0.75
    assert s["final_rmse_position"] == pytest.approx(np.sqrt((0.04 + 0.09 + 25 + 0.01) / 4))
    assert s["final_rmse_position_converged"] == pytest.approx(np.sqrt((0.04 + 0.09 + 0.01) / 3))
    assert s["rmse_over_sqrt_pcrb"] == pytest.approx(s["final_rmse_position"] / 0.5)
    assert s["median_convergence_time"] == pytest.approx(
        0.75
    )  # runs converge from 0.75, 0.5, never, 0.75
    assert s["mean_nees"] == 2.0 and "containment_rate" not in s


def test_scenario_crb():
    assert (
        scenario_crb(load_scenario("ifac2021")) is None
    )  # noise-free ranges: infinite information
    sc = load_scenario("ifac2021-noisy", duration=2.0)
    times, B, note = scenario_crb(sc, every=100)
    assert times.shape == (21,) and times[-1] == pytest.approx(2.0)
    np.testing.assert_allclose(np.diag(B[0]), [400.0] * 3 + [25.0] * 3)
    assert "prior from initial" in note
    assert np.trace(B[-1][:3, :3]) < 0.1 * np.trace(B[0][:3, :3])
    # dropouts remove information: a looser bound
    data = sc.to_dict()
    data["noise"]["dropout"] = 0.5
    _, Bd, _ = scenario_crb(parse_scenario(data), every=100)
    assert np.trace(Bd[-1]) > np.trace(B[-1])


def test_ekf_near_the_truth_has_the_pcrb_as_covariance():
    """In the MuJoCo testbed, an EKF started close to the truth linearises about it: its covariance is the bound."""
    from quadobs.testbed.episode import run_episode

    data = load_scenario("ifac2021-noisy", duration=3.0).to_dict()
    data["initial"] = {"kind": "random", "position_spread": 0.05, "velocity_spread": 0.01}
    sc = parse_scenario(data)
    res = run_episode(sc, estimators=["ekf"], collect_every=500)
    _, B, _ = scenario_crb(sc, every=500)
    cov = res.trace["covariances"]["ekf"]
    np.testing.assert_allclose(
        np.trace(cov[:, :3, :3], axis1=1, axis2=2),
        np.trace(B[:, :3, :3], axis1=1, axis2=2),
        rtol=0.02,
    )
    np.testing.assert_allclose(
        np.trace(cov[:, 3:, 3:], axis1=1, axis2=2),
        np.trace(B[:, 3:, 3:], axis1=1, axis2=2),
        rtol=0.02,
    )


def test_lifted_covariance_matches_sampling():
    rng = np.random.default_rng(5)
    from quadobs import immerse, vehicle_system

    im = immerse(vehicle_system(3, [[0.0, 0.0, 0.0]]))
    m = np.array([3.0, -2.0, 1.0, 0.5, 1.0, -1.0])
    A = rng.standard_normal((6, 6))
    P = A @ A.T / 6 + 0.2 * np.eye(6)
    x = m + rng.standard_normal((400_000, 6)) @ np.linalg.cholesky(P).T
    z = np.concatenate([0.5 * np.einsum("ra,iab,rb->ri", x, im.aux_forms, x), x], axis=1)
    want = np.cov(z.T)
    got = lifted_covariance(im.aux_forms, m, P)
    np.testing.assert_allclose(got, want, atol=0.02 * np.abs(want).max())
    assert np.linalg.eigvalsh(got).min() > 0


def test_immersion_bound_lies_between_the_pcrb_and_the_prior():
    assert immersion_bound(load_scenario("ifac2021")) is None
    sc = load_scenario("ifac2021-noisy", duration=3.0)
    times, Bi = immersion_bound(sc, every=100)
    _, Bp, _ = scenario_crb(sc, every=100)
    np.testing.assert_allclose(Bi[0], Bp[0])
    for a, b in zip(Bi[1:], Bp[1:]):
        gap = np.linalg.eigvalsh(a - b)
        assert (
            gap.min() > -1e-9 * np.abs(b).max()
        )  # the best linear filter on the immersion is no better than the bound
    assert np.trace(Bi[-1][:3, :3]) > 1.05 * np.trace(
        Bp[-1][:3, :3]
    )  # and it loses information here
    data = sc.to_dict()
    data["noise"]["accel_std"] = 0.1
    assert immersion_bound(parse_scenario(data)) is None


def test_one_convergence_convention_streamed_and_batched(rng):
    """ConvergenceTracker (one episode) and convergence_times (runs) agree; NaN means not converged."""
    from quadobs.evaluation.convergence import ConvergenceTracker, json_time

    t = np.arange(30) * 0.1
    err = rng.uniform(0, 2, (40, 30)) * np.linspace(1, 0, 30) ** rng.integers(0, 3, (40, 1))
    err[rng.random(err.shape) < 0.03] = np.nan
    batch = convergence_times(t, err, 0.5)
    for r in range(err.shape[0]):
        tr = ConvergenceTracker((0.5,))
        for i in range(t.size):
            tr.update(t[i], err[r, i])
        (streamed,) = tr.times()
        np.testing.assert_array_equal(streamed, batch[r])
        # the rule by hand
        bad = np.flatnonzero(~(err[r] < 0.5))
        expected = (
            np.nan
            if bad.size and bad[-1] == t.size - 1
            else (t[0] if not bad.size else t[bad[-1] + 1])
        )
        np.testing.assert_array_equal(batch[r], expected)
    assert np.isnan(batch).any() and np.isfinite(batch).any()
    assert np.isnan(ConvergenceTracker((1.0,)).times()[0])  # nothing seen: not converged
    assert json_time(np.nan) is None and json_time(0.1 + 0.2) == 0.3 and json_time(2.0) == 2.0
