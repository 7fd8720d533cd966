"""Observability Gramian, the PE conditions of eqs. 28-41, Proposition 4, the report and the monitor (no MuJoCo)."""

import copy
import subprocess
import sys

import numpy as np
import pytest
from conftest import random_nilpotent
from scipy.integrate import solve_ivp

from quadobs import (
    QuadobsError,
    QuadraticSystem,
    immerse,
    list_scenarios,
    load_scenario,
    vehicle_system,
    wind_system,
)
from quadobs.observability.conditions import chain_structure, r_sequence
from quadobs.observability.excitation import (
    ExcitationMonitor,
    HeldInput,
    excitation_report,
    proposition4,
)
from quadobs.observability.gramian import (
    GramianModel,
    reduce_window,
    scaled_min_eig,
    sliding_windows,
)
from quadobs.testbed.excitation import scenario_input, scenario_monitor, scenario_report
from quadobs.testbed.scenario import parse_scenario

ORIGIN3 = [[0.0, 0.0, 0.0]]


# --------------------------------------------------------------------------------------
# r_i and Gamma (eqs. 28, 38-40)
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
def test_double_integrator_r_sequence_section6(rng, dim):
    """Section 6: r_1 = 0, r_2 = [u, 0], r_3 = [u', 3u]; Gamma = [[0, 3I], [I, 0], [0, 0]]."""
    chain = chain_structure(vehicle_system(dim, np.zeros((1, dim))))
    assert chain.m == 3 and chain.kappa == 3 + 2 * dim - 1
    D = rng.standard_normal((3, 50, dim))  # u, u', u'' at 50 instants
    r = r_sequence(chain, D, 3)
    u, du = D[0], D[1]
    np.testing.assert_array_equal(r[0], 0.0)
    np.testing.assert_array_equal(r[1], 0.0)
    np.testing.assert_allclose(r[2], np.hstack([u, 0 * u]), atol=1e-14)
    np.testing.assert_allclose(r[3], np.hstack([du, 3 * u]), atol=1e-14)
    eye, zero = np.eye(dim), np.zeros((dim, dim))
    np.testing.assert_array_equal(
        chain.Gamma, np.block([[zero, 3 * eye], [eye, zero], [zero, zero]])
    )
    assert chain.real_eigenvalues() and chain.gamma_observable() and chain.affine_free()


def _poly_derivative(coef):
    """Coefficients (K, ...) of sum_k c_k t^k -> those of its derivative."""
    k = np.arange(1, coef.shape[0]).reshape((-1,) + (1,) * (coef.ndim - 1))
    return np.concatenate([coef[1:] * k, np.zeros_like(coef[:1])])


def _poly_eval(coef, t):
    return np.einsum("k...,tk->t...", coef, np.power.outer(t, np.arange(coef.shape[0])))


@pytest.mark.parametrize("with_d", [False, True])
def test_r_sequence_matches_recursion_eq28(rng, with_d):
    """Eq. 38 (via Gamma, eq. 39) equals the recursion of eq. 28 run on exact polynomial derivatives.

    With a linear output term the recursion starts at r_0 = d^T (module docstring of quadobs.observability.conditions).
    """
    n, p = 4, 2
    A = random_nilpotent(rng, n, 2)
    B = rng.standard_normal((n, p))
    C = rng.standard_normal((n, n))
    C = C + C.T
    d = rng.standard_normal(n) if with_d else None
    system = QuadraticSystem(A, B, C, d)
    chain = chain_structure(system)
    U = rng.standard_normal((7, p))  # u(t) = sum_k U_k t^k
    K = chain.kappa
    R = [np.zeros((7, n))]  # polynomial coefficients of r_i
    R[0][0] = system.d[0]
    for i in range(K):
        nxt = R[i] @ A + _poly_derivative(R[i]) + U @ (B.T @ chain.Cs[i])
        R.append(nxt)
    t = np.linspace(-1.0, 1.0, 9)
    D = [U]
    for _ in range(K - 1):
        D.append(_poly_derivative(D[-1]))
    derivs = np.stack([_poly_eval(c, t) for c in D])
    got = r_sequence(chain, derivs, K)
    for i in range(K + 1):
        want = _poly_eval(R[i], t)
        np.testing.assert_allclose(got[i], want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


def test_chain_conditions_refuse_other_systems():
    with pytest.raises(QuadobsError, match="single output.*q = 3"):
        chain_structure(vehicle_system(2, [[0, 0], [1, 0], [0, 1]]))
    rot = QuadraticSystem([[0.0, 1.0], [-1.0, 0.0]], [[0.0], [1.0]], np.diag([1.0, 2.0]))
    with pytest.raises(QuadobsError, match="Assumption 1"):
        chain_structure(rot)
    with pytest.raises(QuadobsError, match="kappa: must be at least m \\+ 1 = 4"):
        chain_structure(vehicle_system(2, [[0.0, 0.0]]), kappa=3)


# --------------------------------------------------------------------------------------
# The Gramian (eq. 27) from the block formulas against brute force
# --------------------------------------------------------------------------------------


def _brute_force_gramian(im, u, h):
    """Integrate Phi' = A(u) Phi and W' = Phi^T C^T C Phi with solve_ivp, step by step."""
    N = im.dim
    C = im.output_matrix
    Phi, W = np.eye(N), np.zeros((N, N))
    for uk in u:
        Ak = im.state_matrix(uk)

        def f(t, y, Ak=Ak):
            P = y[: N * N].reshape(N, N)
            CP = C @ P
            return np.concatenate([(Ak @ P).ravel(), (CP.T @ CP).ravel()])

        sol = solve_ivp(
            f,
            (0.0, h),
            np.concatenate([np.eye(N).ravel(), np.zeros(N * N)]),
            rtol=1e-12,
            atol=1e-14,
            method="DOP853",
        )
        P_k, G_k = sol.y[: N * N, -1].reshape(N, N), sol.y[N * N :, -1].reshape(N, N)
        W = W + Phi.T @ G_k @ Phi
        Phi = P_k @ Phi
    return Phi, W


@pytest.mark.parametrize(
    "system,method",
    [
        (vehicle_system(3, ORIGIN3), "chain"),
        (vehicle_system(3, ORIGIN3), "minimal"),
        (
            wind_system(2, [[1.0, -2.0], [3.0, 1.0]]),
            "minimal",
        ),  # several outputs, general aux dynamics M
    ],
)
def test_gramian_block_formulas_equal_brute_force(rng, system, method):
    im = immerse(system, method=method)
    h = 0.05
    u = rng.standard_normal((24, system.p)) * 3.0
    gm = GramianModel(im, h)
    Phi, G = gm.step_terms(u)
    P_fast, W_fast = reduce_window(Phi, G)
    P_ref, W_ref = _brute_force_gramian(im, u, h)
    np.testing.assert_allclose(P_fast, P_ref, rtol=1e-8, atol=1e-9 * np.abs(P_ref).max())
    np.testing.assert_allclose(W_fast, W_ref, rtol=1e-8, atol=1e-9 * np.abs(W_ref).max())
    # the doubling table gives every window's Gramian
    L = 7
    W_all = sliding_windows(Phi, G, L)[1]
    for i in (0, 5, 17):
        np.testing.assert_allclose(
            W_all[i],
            reduce_window(Phi[i : i + L], G[i : i + L])[1],
            rtol=1e-11,
            atol=1e-12 * np.abs(W_all[i]).max(),
        )


def test_held_gramian_converges_to_the_smooth_input(rng):
    """For the paper's trajectory the held-input Gramian (mean acceleration per step) tends to the smooth one as O(h^2)."""
    sc = load_scenario("ifac2021")
    im = immerse(sc.system(), method="chain")
    Ws = [
        GramianModel(im, h).gramian(scenario_input(sc, h, duration=2.0).values)
        for h in (0.04, 0.02, 0.01)
    ]
    e1, e2 = np.abs(Ws[0] - Ws[2]).max(), np.abs(Ws[1] - Ws[2]).max()
    assert e1 / e2 > 3.0  # 5 for an exact O(h^2) (errors against the finest, not the limit)
    assert e2 < 1e-3 * np.abs(Ws[2]).max()


def test_scaled_min_eig_is_unit_free(rng):
    X = rng.standard_normal((5, 5))
    W = X @ X.T
    S = np.diag(10.0 ** rng.uniform(-4, 4, 5))
    assert scaled_min_eig(S @ W @ S) == pytest.approx(scaled_min_eig(W), rel=1e-9)
    W[:, 2] = W[2, :] = 0.0
    assert scaled_min_eig(W) == 0.0


# --------------------------------------------------------------------------------------
# Conditions on the paper's trajectory, on degenerate inputs, Proposition 4
# --------------------------------------------------------------------------------------


def test_paper_trajectory_is_persistently_exciting():
    """Section 6: the trajectory satisfies eq. 37 (Prop. 7); eq. 41 fails because u'' = -omega^2 u on each axis."""
    rep = scenario_report(load_scenario("ifac2021"), window=5.0)
    cond = {c.key: c for c in rep.conditions}
    assert rep.persistently_exciting and rep.mu > 1e-4
    assert cond["eq37"].status == "holds" and cond["eq37"].margin.min() > 100.0
    assert cond["eq31"].status == "holds" and cond["eq29"].status == "holds"
    assert cond["eq41"].status == "fails" and cond["eq41"].relative.max() < 1e-14
    assert rep.below_threshold() == 0
    assert "PERSISTENTLY EXCITING" in rep.verdict()


def _vehicle_report(values, h=0.01, window=2.0):
    im = immerse(vehicle_system(3, ORIGIN3), method="chain")
    return excitation_report(im, HeldInput(values, h), window, stride=0.5)


def test_constant_acceleration_fails():
    rep = _vehicle_report(np.tile([1.0, -2.0, 0.5], (600, 1)))
    cond = {c.key: c for c in rep.conditions}
    assert cond["eq37"].status == "fails" and not cond["eq37"].holds.any()
    assert not rep.persistently_exciting and not rep.gramian.holds.any()
    assert "constant input" in rep.explanation and "rank 4 < 9" in rep.explanation


def test_straight_line_fails():
    """Acceleration along one fixed direction: rotations about that axis leave the range unchanged."""
    t = (np.arange(600) + 0.5) * 0.01
    values = np.outer(np.sin(2 * t) + 0.3 * np.cos(5 * t), [1.0, 2.0, -1.0])
    rep = _vehicle_report(values)
    cond = {c.key: c for c in rep.conditions}
    assert cond["eq37"].status == "fails" and cond["eq37"].relative.max() < 1e-12
    assert cond["eq31"].status == "fails"
    assert not rep.gramian.holds.any() and "varying input" in rep.explanation


def test_zero_input_and_proposition4():
    rep = _vehicle_report(np.zeros((600, 3)))
    assert (
        not rep.gramian.holds.any()
        and "zero input (Proposition 4: (A_0, C) has rank 3 < 9)" in rep.explanation
    )
    p4 = rep.prop4
    assert (
        p4.input_enters
        and p4.zero_input_rank == 3
        and p4.excitation_needed
        and not p4.never_observable
    )
    # four beacons in general position: observable without excitation
    p4b = proposition4(immerse(vehicle_system(3, [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])))
    assert p4b.zero_input_observable and "without excitation" in p4b.statement
    # B^T C_r = 0 for all r: the input never enters A(u)
    sys0 = QuadraticSystem(np.zeros((2, 2)), [[0.0], [1.0]], np.diag([1.0, 0.0]))
    p40 = proposition4(immerse(sys0, method="chain"))
    assert not p40.input_enters and p40.never_observable and "whatever the input" in p40.statement


def test_sampled_input_finite_differences():
    """Derivatives of a sampled input by central differences: O(h^2); eq. 29 needs u^(7), so it is not evaluated."""
    sc = load_scenario("ifac2021")
    analytic = scenario_input(sc, 0.01, duration=10.0)
    sampled = HeldInput(analytic.values, 0.01)
    Da, Ds = analytic.derivatives(3), sampled.derivatives(3)
    inner = slice(2, -2)
    h = 0.01
    u2, u3 = np.abs(Da[2]).max(), np.abs(analytic.analytic(analytic.midpoints, 3)).max()
    # a step's mean differs from the midpoint value by at most h^2 max|u''| / 24
    assert np.abs(Ds[0] - Da[0]).max() <= 1.01 * h**2 * u2 / 24
    # central difference of those means: at most h^2 max|u'''| (1/6 + 1/24)
    assert np.abs(Ds[1][inner] - Da[1][inner]).max() <= 1.01 * h**2 * u3 * 5 / 24
    with pytest.raises(QuadobsError, match="order 3"):
        sampled.derivatives(4)
    im = immerse(sc.system())
    rep = excitation_report(im, sampled, 5.0)
    cond = {c.key: c for c in rep.conditions}
    assert cond["eq29"].status == "not evaluated" and "u^(7)" in cond["eq29"].detail
    assert cond["eq37"].status == "holds" and rep.persistently_exciting


# --------------------------------------------------------------------------------------
# Several outputs
# --------------------------------------------------------------------------------------

_BASE = {
    "name": "t",
    "dimension": 2,
    "duration": 12.0,
    "beacons": [{"position": [0.0, 0.0]}],
    "trajectory": {
        "offset": [1.0, 2.0],
        "terms": [
            {"axis": 0, "amplitude": 10.0, "omega": 1.0},
            {"axis": 1, "amplitude": 5.0, "omega": 2.0, "function": "sin"},
        ],
    },
}


def _scenario(**changes):
    data = copy.deepcopy(_BASE)
    data.update(changes)
    return parse_scenario(data)


def test_wind_system_gets_the_gramian_and_not_the_chain_conditions():
    sc = _scenario(
        beacons=[{"position": [0.0, 0.0]}, {"position": [20.0, 5.0]}],
        wind={"velocity": [2.0, -1.0]},
    )
    rep = scenario_report(sc, window=5.0)
    assert rep.immersion.system.q == 3 and rep.chain_m is None
    assert all(c.status == "not applicable" and "single output" in c.detail for c in rep.conditions)
    assert rep.gramian.status == "holds" and rep.mu > 0
    d = rep.to_dict()
    assert (
        d["conditions"]["eq37"]["status"] == "not applicable" and d["gramian"]["status"] == "holds"
    )


def test_several_beacons_observe_a_coasting_vehicle():
    """Three beacons in the plane: with no acceleration at all the state is still observable (Proposition 4 does not bite)."""
    beacons = [{"position": [0.0, 0.0]}, {"position": [30.0, 0.0]}, {"position": [0.0, 30.0]}]
    sc = _scenario(beacons=beacons, trajectory={"offset": [1.0, 2.0], "velocity": [1.0, 0.5]})
    rep = scenario_report(sc, window=5.0)
    assert rep.prop4.zero_input_observable and rep.persistently_exciting


# --------------------------------------------------------------------------------------
# Coasting trajectories
# --------------------------------------------------------------------------------------


def test_coast_keeps_velocity_and_commands_are_consistent():
    sc = load_scenario("degenerate")
    traj = sc.trajectory
    dt = 1e-3
    steps = sc.steps
    u = traj.step_accelerations(0.0, dt, steps)
    t = dt * np.arange(steps + 1)
    v, p = traj.velocity_at(t), traj.position(t)
    # exact double integration of the held commands: the reference velocity at every step
    # boundary, and the reference position to O(dt^2) (the hold within a step)
    v_int = v[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(u, 0) * dt])
    p_int = p[0] + np.concatenate(
        [np.zeros((1, 3)), np.cumsum(v_int[:-1] * dt + 0.5 * u * dt**2, 0)]
    )
    np.testing.assert_allclose(v_int, v, atol=1e-9)
    np.testing.assert_allclose(p_int, p, atol=1e-4)
    for start, end in traj.coast:
        inside = (t[:-1] >= start) & (t[1:] <= end)
        assert np.all(u[inside] == 0.0)
        assert np.all(traj.acceleration(t[:-1][inside]) == 0.0)
        np.testing.assert_allclose(
            traj.velocity_at(end), traj.velocity_at(start), atol=1e-12
        )  # whole periods


@pytest.mark.parametrize(
    "coast,match",
    [
        ([{"start": 3.0, "end": 2.0}], r"trajectory.coast\[0\]: expected 0 <= start < end"),
        (
            [{"start": 1.0, "end": 4.0}, {"start": 3.0, "end": 5.0}],
            r"trajectory.coast\[1\]: segments must be sorted",
        ),
        ([{"start": -1.0, "end": 2.0}], r"trajectory.coast\[0\].start: must be non-negative"),
        ([{"start": 1.0}], r"trajectory.coast\[0\].end: required field is missing"),
        ([{"start": 1.0, "end": 2.0, "stop": 3}], r"trajectory.coast\[0\]: unknown field"),
        ({"start": 1.0}, "trajectory.coast: expected a list of tables"),
    ],
)
def test_bad_coast_segments_are_named(coast, match):
    data = copy.deepcopy(_BASE)
    data["trajectory"]["coast"] = coast
    with pytest.raises(QuadobsError, match=match):
        parse_scenario(data)


@pytest.mark.parametrize(
    "table,match",
    [
        (
            {"window": 5.003},
            r"excitation.window: 5.003 s must be a positive multiple of excitation.step",
        ),
        (
            {"step": 0.0015},
            r"excitation.step: 0.0015 s must be a positive multiple of the physics step",
        ),
        ({"update_period": 0.015}, r"excitation.update_period"),
        ({"threshold": -1.0}, r"excitation.threshold: must be non-negative"),
        ({"monitor": "yes"}, r"excitation.monitor: expected true or false"),
        ({"windw": 3.0}, r"excitation: unknown field"),
        ({"window": 0.01}, r"excitation.window: 0.01 s must span at least two hold steps"),
    ],
)
def test_bad_excitation_fields_are_named(table, match):
    data = copy.deepcopy(_BASE)
    data["excitation"] = table
    with pytest.raises(QuadobsError, match=match):
        parse_scenario(data)


def test_excitation_table_round_trips():
    sc = _scenario(
        excitation={
            "window": 4.0,
            "threshold": 1e-5,
            "update_period": 0.2,
            "step": 0.02,
            "monitor": False,
        }
    )
    assert sc.excitation.window == 4.0 and sc.excitation.step == 0.02 and not sc.excitation.monitor
    assert parse_scenario(sc.to_dict()).to_dict() == sc.to_dict()
    assert scenario_monitor(sc) is None


# --------------------------------------------------------------------------------------
# The monitor
# --------------------------------------------------------------------------------------


def test_monitor_matches_the_offline_gramian():
    sc = load_scenario("ifac2021", duration=8.0)
    mon = scenario_monitor(sc)
    u = sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps)
    values, times = [], []
    for _k, uk in enumerate(u):
        if mon.push(uk):
            values.append(mon.measure)
            times.append(mon.measure_time)
    assert times[0] == pytest.approx(mon.window) and len(times) == int(round((8.0 - 5.0) / 0.1)) + 1
    # offline: the same input averaged over 10 ms, windows of 500 hold steps
    held = u.reshape(-1, 10, 3).mean(axis=1)
    W = GramianModel(mon.immersion, 0.01).sliding(held, 500, 10)
    offline = np.linalg.eigvalsh(W)[:, 0]
    np.testing.assert_allclose(values, offline, rtol=1e-6)


@pytest.mark.parametrize("name", ["ifac2021", "wind"])
def test_compiled_chunk_terms_equal_the_tree_reduction(rng, name):
    pytest.importorskip("numba")
    from quadobs._kernels.gramian import held_run_terms

    model = scenario_monitor(load_scenario(name)).model
    U = rng.normal(size=(17, model.immersion.system.p))
    P_ref, W_ref = reduce_window(*model.step_terms(U))
    N = model.dim
    P, W, work = np.empty((N, N)), np.empty((N, N)), np.empty((3, N, N))
    d = model.discretization
    held_run_terms(
        U,
        d.transition_constant,
        d.transition_input,
        model.gramian_constant,
        model.gramian_linear,
        model.gramian_quadratic,
        P,
        W,
        *work,
    )
    np.testing.assert_allclose(P, P_ref, rtol=1e-12, atol=1e-12 * np.abs(P_ref).max())
    np.testing.assert_allclose(W, W_ref, rtol=1e-10, atol=1e-12 * np.abs(W_ref).max())


def test_monitor_push_many_equals_push(rng):
    """Feeding the inputs in uneven slices (never past a chunk's end) gives the same measures at the same steps."""
    sc = load_scenario("degenerate", duration=12.0)
    u = sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps)
    one, many = scenario_monitor(sc), scenario_monitor(sc)
    seen_one = [(k, one.measure) for k, uk in enumerate(u) if one.push(uk)]
    seen_many, k = [], 0
    while k < len(u):
        n = int(rng.integers(1, many.room + 1))
        if many.push_many(u[k : k + n]):
            seen_many.append((k + n - 1, many.measure))
        k += n
    assert seen_many == seen_one and len(seen_one) > 10
    assert many.summary() == one.summary()
    with pytest.raises(QuadobsError, match="room for"):
        many.push_many(np.zeros((many.room + 1, 3)))
    before = many.summary(), many.steps
    with pytest.raises(QuadobsError, match="U: expected shape"):
        many.push_many(np.zeros(3))  # one step given as a row would broadcast
    with pytest.raises(QuadobsError, match="U"):
        many.push_many(np.full((2, 3), np.nan))
    with pytest.raises(QuadobsError, match="u"):
        many.push(np.zeros(2))
    assert (many.summary(), many.steps) == before  # refused input changes nothing


def test_monitor_flags_exactly_the_coasting_segments():
    """Each coast [c0, c1) gives one low segment [a, b) with c0 < a <= max(c0 + delta, delta) + P and c1 < b <= c1 + delta + P.

    Windows (ending at t, covering [t - delta, t)) that lie inside a coast have zero input
    and are flagged; windows overlapping no coast are rich and are not. Windows that
    straddle a boundary are not constrained. P is the update period; before the first full
    window (t < delta) nothing is evaluated.
    """
    sc = load_scenario("degenerate")
    mon = scenario_monitor(sc)
    for uk in sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps):
        mon.push(uk)
    segs = mon.summary()["low_segments"]
    delta, P = mon.window, mon.update_period
    coasts = sc.trajectory.coast
    assert len(segs) == len(coasts) == 2
    for (a, b), (c0, c1) in zip(segs, coasts):
        assert c0 < a <= max(c0 + delta, delta) + P + 1e-9
        assert c1 < b <= c1 + delta + P + 1e-9
    assert mon.pop_warning() is not None and mon.pop_warning() is None  # once per episode
    assert mon.min_measure < 1e-12 * mon.lambda_max


def test_monitor_on_every_builtin_scenario():
    for name in list_scenarios():
        sc = load_scenario(name)
        rep = scenario_report(sc)
        assert rep.gramian.margin.size and rep.verdict()
        mon = scenario_monitor(sc)
        seconds = min(sc.duration, sc.excitation.window + 1.0)
        for uk in sc.trajectory.step_accelerations(0.0, sc.dt, int(round(seconds / sc.dt))):
            mon.push(uk)
        assert mon.updates >= 1 and np.isfinite(mon.measure)


def test_monitor_argument_checks():
    im = immerse(vehicle_system(2, [[0.0, 0.0]]))
    with pytest.raises(QuadobsError, match="window_blocks >= 2"):
        ExcitationMonitor(im, 1e-3, block=10, window_blocks=1, update_blocks=1, threshold=1e-6)
    with pytest.raises(QuadobsError, match="threshold: must be non-negative"):
        ExcitationMonitor(im, 1e-3, block=10, window_blocks=10, update_blocks=1, threshold=-1.0)


def test_report_argument_checks():
    sc = load_scenario("ifac2021")
    with pytest.raises(QuadobsError, match="window: 40.0 s is longer than the scenario"):
        scenario_report(sc, window=40.0)
    im = immerse(sc.system())
    u = scenario_input(sc, 0.01, duration=3.0)
    with pytest.raises(QuadobsError, match="multiple of the hold step"):
        excitation_report(im, u, 1.234)
    with pytest.raises(QuadobsError, match="stride"):
        excitation_report(im, u, 1.0, stride=0.015)


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def test_cli_excitation_report_without_mujoco(tmp_path):
    js = tmp_path / "rep.json"
    code = (
        "import sys; from quadobs.cli import main; rc = main(['excitation', 'degenerate', '--window', '5', '--json', "
        f"{str(js)!r}]); print('RC', rc, sorted(m for m in ('mujoco', 'rerun') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert "RC 0 []" in out
    assert "eq. 37 (Prop. 7)" in out and "NOT persistently exciting with delta = 5 s" in out
    assert "zero input (Proposition 4" in out
    import json

    data = json.loads(js.read_text())
    assert data["persistently_exciting"] is False and data["gramian"]["failing"]


def test_cli_excitation_bad_window(capsys):
    from quadobs.cli import main

    assert main(["excitation", "ifac2021", "--window", "0.005"]) == 2
    assert "window" in capsys.readouterr().err


def test_held_input_signal_keeps_its_former_name():
    from quadobs.observability.excitation import HeldInputSignal

    assert HeldInput is HeldInputSignal
    u = HeldInputSignal(np.array([[0.0], [1.0], [4.0]]), 0.5, t0=1.0)
    np.testing.assert_allclose(u.midpoints, [1.25, 1.75, 2.25])
    with pytest.raises(QuadobsError, match="HeldInputSignal"):
        excitation_report(immerse(vehicle_system(1, np.zeros((1, 1)))), u.values, 1.0)
