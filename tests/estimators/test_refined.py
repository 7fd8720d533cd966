"""The refined observer: global convergence of the augmented observer, then an EKF at the bound."""

import numpy as np
import pytest
from scipy import stats

import quadobs.testbed.episode as episode
from quadobs import QuadobsError, load_scenario
from quadobs.estimators.refined import HandoverPolicy, RefinedObserver, _Window, curvature_index
from quadobs.evaluation.ensemble import nees
from quadobs.testbed.factories import baseline_settings, refined_observer
from quadobs.testbed.registry import build_estimators

NAMES = ["augmented", "augmented-refined"]

#: Physics rate of the noisy runs below. Their ranges are sampled at 100 Hz (50 Hz with
#: outliers) with a noise-free accelerometer, so 200 Hz leaves the measurements and the
#: estimates at the sample times as at the scenarios' 1000 Hz (the final NEES of seeds
#: 100-105 after 12 s agree to 1e-4) for a fifth of the steps.
RATE = 200.0


def run(scenario, names=NAMES):
    """``run_episode`` on ``scenario``, returning its result and the estimators it built."""
    built = []
    original = episode.build_estimators

    def capture(*args, **kwargs):
        built.extend(original(*args, **kwargs))
        return built

    episode.build_estimators = capture
    try:
        result = episode.run_episode(scenario, estimators=names, collect_every=100)
    finally:
        episode.build_estimators = original
    return result, {e.name: e for e in built}


@pytest.fixture(scope="module")
def noisy():
    """A 12 s run of ``ifac2021-noisy`` (random guess: 20 m, 5 m/s spread)."""
    return run(load_scenario("ifac2021-noisy", duration=12.0, seed=3, physics_rate=RATE))


def test_converges_from_a_far_guess_and_hands_over(noisy):
    result, ests = noisy
    ref = ests["augmented-refined"]
    s = result.summary["estimators"]
    assert (
        np.linalg.norm(result.trace["estimates"]["augmented-refined"][0] - result.trace["truth"][0])
        > 5.0
    )
    assert s["augmented-refined"]["final_position_error"] < 0.5
    assert s["augmented-refined"]["final_position_error"] < s["augmented"]["final_position_error"]
    assert ref.mode == "ekf"
    step, old, new, reason = ref.switches[0]
    assert (old, new) == ("augmented", "ekf") and 0 < step < 12.0 * RATE and "replay" in reason
    summary = ref.summary()
    assert summary["handover_step"] == step and summary["switches"][0]["to"] == "ekf"


def test_reports_the_observer_before_the_handover_and_its_own_covariance_after(noisy):
    result, ests = noisy
    ref = ests["augmented-refined"]
    step = ref.switches[0][0]
    rows = np.flatnonzero(np.arange(result.trace["time"].size) * 100 <= step)
    before = result.trace["estimates"]
    np.testing.assert_array_equal(before["augmented-refined"][rows], before["augmented"][rows])
    P = ref.x_covariance
    np.testing.assert_allclose(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_handover_covariance_is_consistent():
    """Over the seeds handed over within 12 s, the final NEES lies in the two-sided 99 % chi-square band."""
    scenario = load_scenario("ifac2021-noisy", duration=12.0, physics_rate=RATE)
    values = []
    for seed in range(6):
        result, ests = run(scenario.with_overrides(seed=100 + seed), ["augmented-refined"])
        if ests["augmented-refined"].mode != "ekf":
            continue
        tr = result.trace
        values.append(
            nees(
                tr["estimates"]["augmented-refined"][-1] - tr["truth"][-1],
                tr["covariances"]["augmented-refined"][-1],
            )
        )
    assert len(values) >= 4
    dof = 6 * len(values)
    lo, hi = stats.chi2.ppf([0.005, 0.995], dof) / len(values)
    assert lo <= np.mean(values) <= hi


def test_handover_covariance_matches_the_bound(noisy):
    """After the handover the EKF's covariance is the PCRB to first order: no inflation, no overconfidence.

    Every eigenvalue of ``PCRB^-1 P`` at the end lies within 15 % of 1 (measured: 0.92 to 1.07).
    """
    from quadobs.testbed.bounds import scenario_crb

    result, ests = noisy
    assert ests["augmented-refined"].mode == "ekf"
    scenario = load_scenario("ifac2021-noisy", duration=12.0, seed=3, physics_rate=RATE)
    times, bound, _ = scenario_crb(scenario, every=100)
    assert times[-1] == pytest.approx(result.trace["time"][-1])
    P = result.trace["covariances"]["augmented-refined"][-1]
    ratios = np.linalg.eigvals(np.linalg.solve(bound[-1], P)).real
    assert np.all((ratios > 0.85) & (ratios < 1.0 / 0.85)), ratios


def test_batch_replay_equals_the_sequential_pass(noisy):
    """The information-form replay (no process noise, no gate) gives the sequential Kalman pass's posterior."""
    _, ests = noisy
    ref = ests["augmented-refined"]
    assert ref._batchable
    steps, Y, D = np.array(ref._log_steps), np.array(ref._log_y), np.array(ref._log_d)
    x_ref = ref.observer.x_hat
    xb, Pb, wb = ref._replay(steps, Y, D, x_ref)
    xs, Ps, ws = ref._replay(steps, Y, D, x_ref, batch=False)
    np.testing.assert_allclose(xb, xs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Pb, Ps, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose([i[0] for i in wb.items], [i[0] for i in ws.items], rtol=1e-8)
    assert wb.dof == ws.dof == ref.policy.window


def test_noise_free_no_worse_than_the_plain_observer():
    result, ests = run(load_scenario("ifac2021", duration=10.0))
    s = result.summary["estimators"]
    assert ests["augmented-refined"].mode == "ekf"
    for key in ("final_position_error", "final_velocity_error"):
        assert s["augmented-refined"][key] <= s["augmented"][key]


def test_deterministic():
    scenario = load_scenario("ifac2021-noisy", duration=6.0, seed=5)
    (r1, e1), (r2, e2) = run(scenario, ["augmented-refined"]), run(scenario, ["augmented-refined"])
    np.testing.assert_array_equal(
        r1.trace["estimates"]["augmented-refined"], r2.trace["estimates"]["augmented-refined"]
    )
    assert e1["augmented-refined"].switches == e2["augmented-refined"].switches


# -- switching logic on synthetic innovations ---------------------------------------------


def test_window_chi_square_test():
    rng = np.random.default_rng(0)
    w = _Window(50)
    assert not w.passes(0.99)  # empty: no evidence
    for v in rng.chisquare(1, 50):
        w.push(float(v), 1, False)
    assert w.full and w.passes(0.99)
    for _ in range(50):
        w.push(9.0, 1, False)  # 3 sigma every time
    assert not w.passes(0.99)
    w.push(np.inf, 1, False)
    assert not w.passes(0.99)
    for _ in range(30):
        w.push(1e6, 1, True)
    assert w.rejected_fraction() == pytest.approx(0.6)


def test_guard_hands_back_on_inconsistent_innovations(noisy):
    """In the EKF phase, outputs biased by 5 sigma make the guard hand back to the observer."""
    _, ests = noisy
    scenario = load_scenario("ifac2021-noisy", duration=12.0, seed=3)
    ref = ests["augmented-refined"]
    assert ref.mode == "ekf"
    x = ref.x_hat
    u = np.zeros(3)
    k0, n_sw = ref._k, len(ref.switches)
    for k in range(1000):
        y = np.full(1, np.nan)
        if k % 10 == 0:
            s = np.linalg.norm(x[:3] - scenario.beacons[0]) + 2.5
            y[0] = 0.5 * s**2 - 0.5 * scenario.beacons[0] @ scenario.beacons[0]
        ref.step(u, y)
        x = ref.dynamics.F @ x + ref.dynamics.G @ u
    assert ref.mode == "augmented"
    step, old, new, reason = ref.switches[n_sw]
    assert (old, new) == ("ekf", "augmented") and "guard" in reason and k0 < step <= k0 + 1000


def test_gate_rejections_hand_back():
    scenario = load_scenario("ifac2021-outliers", duration=6.0, seed=1, physics_rate=RATE)
    result, ests = run(scenario, ["augmented-refined"])
    ref = ests["augmented-refined"]
    assert ref.mode == "ekf" and ref.gate == 16.0
    assert result.summary["estimators"]["augmented-refined"]["final_position_error"] < 0.5
    x = ref.x_hat
    for k in range(2000):
        y = np.full(1, np.nan)
        if k % 20 == 0:
            s = np.linalg.norm(x[:3] - scenario.beacons[0]) + 50.0  # every sample an outlier
            y[0] = 0.5 * s**2
        ref.step(np.zeros(3), y)
        x = ref.dynamics.F @ x
    assert ref.mode == "augmented" and "gate" in ref.switches[-1][3]
    assert ref.rejected > 0


# -- construction -------------------------------------------------------------------------


def test_registered_and_interface():
    scenario = load_scenario("ifac2021-noisy", duration=1.0)
    (est,) = build_estimators(scenario, ["augmented-refined"], np.ones(6))
    assert isinstance(est, RefinedObserver) and est.name == "augmented-refined"
    x = est.x_hat
    est.step(np.zeros(3), np.array([100.0]))
    assert not np.shares_memory(x, est.x_hat) and est.x_hat.shape == (6,)
    assert est.x_covariance.shape == (6, 6) and np.isfinite(est.nis)
    assert est.immersion is est.observer.immersion


def test_bad_settings_raise():
    scenario = load_scenario("ifac2021-noisy", duration=1.0)
    s = baseline_settings(scenario)
    obs = refined_observer(scenario, np.zeros(6)).observer
    with pytest.raises(QuadobsError, match="observer"):
        RefinedObserver("no", s.dynamics, s.outputs, x0=np.zeros(6), P0=1.0)
    with pytest.raises(QuadobsError, match="x0"):
        RefinedObserver(obs, s.dynamics, s.outputs, x0=np.zeros(5), P0=1.0)
    with pytest.raises(QuadobsError, match="window"):
        HandoverPolicy(window=0)
    with pytest.raises(QuadobsError, match="guard"):
        HandoverPolicy(guard=1.0)


def test_curvature_index_of_a_range():
    """For a range ``|p|`` at distance ``r`` with ``P = p^2 I``, ``eta = p^2 / (r sigma)``."""
    scenario = load_scenario("ifac2021-noisy", duration=1.0)
    outputs = baseline_settings(scenario).outputs
    x = np.array([20.0, 0, 0, 0, 0, 0])
    P = np.diag([4.0, 4.0, 4.0, 1.0, 1.0, 1.0])
    assert curvature_index(outputs, x, P) == pytest.approx(4.0 / (20.0 * 0.5))


def test_mode_switches_reach_the_summary_and_the_event_log(tmp_path):
    """Each switch of the refined observer is an event of the recording at its step, and in the summary."""
    from quadobs.estimators.base import Switching
    from quadobs.recording import read_text_log
    from quadobs.testbed.episode import run_episode

    path = tmp_path / "refined.rrd"
    scenario = load_scenario("ifac2021-noisy", duration=16.0, physics_rate=RATE)
    res = run_episode(scenario, estimators=["augmented-refined"], out=path)
    modes = res.summary["estimators"]["augmented-refined"]["modes"]
    assert modes["switches"], "no handover within 16 s of ifac2021-noisy (seed 0)"
    logged = [
        (step, text)
        for step, _, _, text in read_text_log(path, "events")
        if text.startswith("augmented-refined:")
    ]
    assert [step for step, _ in logged] == [s["step"] for s in modes["switches"]]
    assert all(
        f"{s['from']} -> {s['to']}" in text for (_, text), s in zip(logged, modes["switches"])
    )
    assert issubclass(RefinedObserver, Switching)


# -- the campaign's statistic over each run's converged part ------------------------------


def test_converged_nees_counts_only_the_converged_part():
    from quadobs.evaluation.ensemble import converged_nees

    rng = np.random.default_rng(0)
    R, T = 400, 4
    ne = rng.chisquare(6, (R, T))
    ne[:, 0] = 1e3  # before convergence: far outside
    mask = np.ones((R, T), dtype=bool)
    mask[:, 0] = False
    mask[: R // 2, 1] = False  # half the runs converge one sample later
    part = converged_nees(ne, mask, 6)
    np.testing.assert_array_equal(part["runs"], [0, R // 2, R, R])
    assert np.isnan(part["mean"][0]) and part["all_runs_from"] == 2
    assert part["inside_fraction"] == 1.0 and 5.5 < part["time_average"] < 6.5
    lo, hi = part["bounds"][1]
    assert (
        lo < 6 < hi and hi - lo > part["bounds"][3, 1] - part["bounds"][3, 0]
    )  # fewer runs, wider band
    assert converged_nees(1.5 * ne, mask, 6)["inside_fraction"] == 0.0


def test_campaign_marks_the_samples_after_a_switch():
    from quadobs.studies.campaign import _switched

    times = np.arange(6) * 0.1  # samples at steps 0, 100, ..., 500 (dt = 1e-3)
    switches = [
        {"step": 100, "from": "augmented", "to": "ekf"},
        {"step": 350, "from": "ekf", "to": "augmented"},
    ]
    np.testing.assert_array_equal(_switched(times, switches, 1e-3), [0, 0, 1, 1, 0, 0])
    np.testing.assert_array_equal(_switched(times, [], 1e-3), np.zeros(6, dtype=bool))
