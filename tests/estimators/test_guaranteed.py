"""Guaranteed localisation of the vehicle: each bound checked on its own, then MuJoCo episodes
in which the true lifted state lies in the zonotope at every step."""

import numpy as np
import pytest

from quadobs import QuadobsError, immerse, load_scenario, vehicle_system
from quadobs.estimators.zonotopic_vehicle import ZonotopicAugmentedEstimator, lift_box, range_strip
from quadobs.testbed.registry import build_estimators
from quadobs.testbed.scenario import parse_scenario
from quadobs.testbed.sensors import SensorModel, initial_guess, spawn_streams


def test_range_strip_contains_every_true_output_and_is_tight(rng):
    for _ in range(200):
        a2 = rng.uniform(0, 50)  # |a|^2 / 2
        rho = rng.uniform(0, 5) if rng.uniform() < 0.3 else rng.uniform(0, 100)
        nbar = rng.uniform(0.001, 1.0)
        n = rng.uniform(-nbar, nbar)
        y = 0.5 * (rho + n) ** 2 - a2
        yc, phi = range_strip(y, a2, nbar)
        assert abs((0.5 * rho**2 - a2) - yc) <= phi
        # tight: the ends are true outputs for some admissible noise
        meas = abs(rho + n)
        lo, hi = max(0.0, meas - nbar), meas + nbar
        assert yc - phi == pytest.approx(0.5 * lo**2 - a2, abs=1e-9 * (1 + abs(y) + a2))
        assert yc + phi == pytest.approx(0.5 * hi**2 - a2, abs=1e-9 * (1 + abs(y) + a2))
    # far from the beacon the half-width is nbar * rho~, the centre y + nbar^2 / 2
    yc, phi = range_strip(0.5 * 30.0**2 - 2.0, 2.0, 0.05)
    assert phi == pytest.approx(0.05 * 30.0) and yc == pytest.approx(
        0.5 * 30.0**2 - 2.0 + 0.05**2 / 2
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_lift_box_contains_the_lift_of_the_box(rng, dim):
    beacons = rng.uniform(-10, 10, (2, dim))
    im = immerse(vehicle_system(dim, beacons))
    n = 2 * dim
    x0, r = rng.uniform(-5, 5, n), rng.uniform(0.5, 3, n)
    Z = lift_box(im, x0, r)
    X = x0 + r * rng.uniform(-1, 1, (60, n))
    X[:20] = x0 + r * np.sign(rng.uniform(-1, 1, (20, n)))
    assert Z.contains(im.lift(X), method="lp").all()
    # the x-part is the box itself (no inflation there)
    np.testing.assert_allclose(Z.interval_hull()[im.n_aux :], np.stack([x0 - r, x0 + r], axis=1))


def test_prediction_contains_the_true_step_under_input_error(rng):
    beacons = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    im = immerse(vehicle_system(3, beacons))
    est = ZonotopicAugmentedEstimator(
        im,
        0.01,
        x0=np.zeros(6),
        radius=np.full(6, 2.0),
        output_offsets=[0.0, 50.0],
        output_bounds=[0.1, 0.1],
        input_bound=0.5,
    )
    Z0 = est.zonotope
    u_meas = rng.uniform(-3, 3, 3)
    est.predict(u_meas)
    pts = []
    for _ in range(200):
        x = rng.uniform(-2, 2, 6)
        if rng.uniform() < 0.5:
            x = 2.0 * np.sign(x)
        du = 0.5 * (
            np.sign(rng.uniform(-1, 1, 3)) if rng.uniform() < 0.7 else rng.uniform(-1, 1, 3)
        )
        u_true = u_meas - du
        z = im.lift(x)
        assert Z0.contains(z, method="lp")
        pts.append(est.model.predict(z, u_true))
    assert est.zonotope.contains(np.array(pts), method="lp").all()
    # without the input-error term the set would miss some of them
    bare = ZonotopicAugmentedEstimator(
        im,
        0.01,
        x0=np.zeros(6),
        radius=np.full(6, 2.0),
        output_offsets=[0.0, 50.0],
        output_bounds=[0.1, 0.1],
        input_bound=0.0,
    )
    bare.predict(u_meas)
    assert not bare.zonotope.contains(np.array(pts), method="lp").all()


def test_mujoco_step_matches_the_exact_discretisation():
    """The margin argument: MuJoCo's RK4 step of the held force equals the exact held-input step to rounding."""
    from quadobs.core.held_input import HeldInputDiscretization
    from quadobs.testbed.worlds import VehicleSim

    sc = load_scenario("ifac2021-bounded", duration=2.0)
    im = immerse(sc.system())
    model = HeldInputDiscretization(im, sc.dt)
    sim = VehicleSim(3, sc.beacons, timestep=sc.dt)
    sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
    u_cmd = sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps)
    worst = 0.0
    for k in range(sc.steps):
        x = sim.state()
        sim.step(u_cmd[k])
        accel = sim.accelerometer()
        pred = model.predict(im.lift(x), accel)
        truth = im.lift(sim.state())
        worst = max(worst, float(np.max(np.abs(pred - truth) / (1.0 + np.abs(truth)))))
    assert worst < 1e-13


def _bounded(duration, seed, **noise):
    data = load_scenario("ifac2021-bounded").to_dict()
    data.update(duration=duration, seed=seed, physics_rate=200.0)
    data["noise"].update(noise)
    data["noise"]["range_rate"] = 20.0
    return parse_scenario(data)


@pytest.mark.parametrize("seed", range(6))
def test_true_state_inside_the_zonotope_at_every_step(seed):
    """Short seeded MuJoCo episodes: lift(x_true) in the zonotope (linear program) at every step."""
    from quadobs.testbed.worlds import VehicleSim

    sc = _bounded(3.0, seed, range_bound=0.2, accel_bound=0.05)
    sim = VehicleSim(3, sc.beacons, timestep=sc.dt)
    sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
    streams = spawn_streams(sc.seed)
    sensors = SensorModel(sc, streams)
    x0 = initial_guess(sc, sim.state(), streams["initial"])
    (est,) = build_estimators(sc, ["zonotope"], x0)
    u_cmd = sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps)
    widths = []
    for k in range(sc.steps):
        x = sim.state()
        assert est.contains(x), f"step {k}"
        b = est.bounds
        assert np.all((b[:, 0] <= x) & (x <= b[:, 1]))
        widths.append(b[:3, 1] - b[:3, 0])
        sim.step(u_cmd[k])
        est.step(sensors.input(sim.accelerometer()), sensors.outputs(k, sim.ranges()))
    assert est.contains(sim.state())
    assert np.max(widths[-1]) < 0.1 * np.max(widths[0])  # the set shrinks from the 60 m box


def test_episode_records_guaranteed_bounds_that_shrink(tmp_path):
    from quadobs.recording import list_entities, read_series
    from quadobs.testbed.episode import run_episode

    sc = load_scenario("ifac2021-bounded", duration=6.0, seed=3)
    rrd = tmp_path / "b.rrd"
    res = run_episode(sc, estimators=["augmented", "zonotope"], out=rrd)
    zb = res.summary["estimators"]["zonotope"]["bounds"]
    assert zb["contained_fraction"] == 1.0
    assert max(zb["final_width"][:3]) < 2.0
    assert "/world/estimates/zonotope/bounds" in set(list_entities(rrd))
    err = read_series(rrd, "errors/zonotope/position/bounds")["values"]
    assert np.all(err[:, :3] <= 0) and np.all(err[:, 3:] >= 0)  # low - true <= 0 <= high - true
    width = read_series(rrd, "errors/zonotope/position/box_width")["values"]
    assert width[0].max() == pytest.approx(60.0) and width[-1].max() < 2.0
    # from the 60 m box to below 2 m within the first second, and the velocity box too
    assert np.all(width[1000:].max(axis=1) < 2.0)
    assert max(zb["final_width"][3:]) < 0.1 * 60.0


def test_zonotope_refuses_unbounded_noise_and_random_guess():
    sc = load_scenario("ifac2021")  # Gaussian-free but the accelerometer has no bound: fine
    data = sc.to_dict()
    data["noise"] = {"range_std": 0.1}
    with pytest.raises(QuadobsError, match="noise.range_std"):
        build_estimators(parse_scenario(data), ["zonotope"], np.zeros(6))
    data["noise"] = {"range_bound": 0.1, "outlier_probability": 0.01, "outlier_std": 1.0}
    with pytest.raises(QuadobsError, match="outlier"):
        build_estimators(parse_scenario(data), ["zonotope"], np.zeros(6))
    data["noise"] = {"range_bound": 0.1}
    data["initial"] = {"kind": "random", "position_spread": 1.0}
    with pytest.raises(QuadobsError, match="initial.kind"):
        build_estimators(parse_scenario(data), ["zonotope"], np.zeros(6))


def test_bounded_noise_fields_are_validated_and_drawn_within_bounds():
    data = load_scenario("ifac2021").to_dict()
    data["noise"] = {"range_std": 0.1, "range_bound": 0.1}
    with pytest.raises(QuadobsError, match="noise.range_bound"):
        parse_scenario(data)
    data["noise"] = {"accel_bound": -1.0}
    with pytest.raises(QuadobsError, match="noise.accel_bound"):
        parse_scenario(data)
    data["zonotope"] = {"reduction": "nope"}
    data["noise"] = {}
    with pytest.raises(QuadobsError, match="zonotope.reduction"):
        parse_scenario(data)
    data["zonotope"] = {"position_bound": 10.0}
    data["noise"] = {"range_bound": 0.3, "accel_bound": 0.2}
    sc = parse_scenario(data)
    assert parse_scenario(sc.to_dict()).zonotope == sc.zonotope
    sensors = SensorModel(sc)
    errs, accel = [], []
    for k in range(3000):
        y = sensors.outputs(k, np.array([10.0]))
        errs.append(np.sqrt(2 * y[0]) - 10.0)
        accel.append(sensors.input(np.zeros(3)))
    errs, accel = np.array(errs), np.array(accel)
    assert np.all(np.abs(errs) <= 0.3 + 1e-12) and np.abs(errs).max() > 0.29
    assert np.all(np.abs(accel) <= 0.2) and np.abs(accel).max() > 0.19
    assert abs(errs.mean()) < 0.02  # uniform, centred


def _plain_correct(est, Z, y):
    """The strips of :meth:`ZonotopicAugmentedEstimator.correct`, written with one new array per strip."""
    p, H = Z.center, Z.generators
    for h in np.flatnonzero(~np.isnan(y)):
        yc, phi = range_strip(float(y[h]), float(est.offsets[h]), float(est.output_bounds[h]))
        c = est.C[h]
        Hc = H.T @ c
        lam = H @ Hc / (float(Hc @ Hc) + phi * phi)
        p = p + lam * (yc - c @ p)
        H = np.hstack([H - np.outer(lam, Hc), (phi * lam)[:, None]])
    return p, H


def _plain_parallelotope(H, s):
    """Property 3 with the parallelotope of :func:`quadobs.sets.zonotope._reduce_parallelotope`, through scipy.linalg.qr."""
    import scipy.linalg as sla

    n = H.shape[0]
    order = np.argsort(-np.einsum("ij,ij->j", H, H), kind="stable")
    keep, rest = H[:, order[: s - n]], H[:, order[s - n :]]
    _, R, piv = sla.qr(rest, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    T = rest[:, piv[: int(np.sum(diag > 1e-9 * diag[0]))]]
    return np.hstack([keep, T * np.abs(np.linalg.solve(T, rest)).sum(axis=1)])


def test_vehicle_zonotope_step_matches_the_plain_formulas_from_each_state():
    """Step by step from the same set, the estimator's in-place arithmetic gives the plain formulas' set.

    The run as a whole is not compared: the set's reduction reacts to perturbations of 1e-13
    (a different pivot), so two runs that differ by rounding drift apart, both containing the truth.
    """
    from quadobs.sets.zonotope import _pivoted_qr_diag, reduce_generators
    from quadobs.studies.bench import _vehicle_data

    sc = load_scenario("ifac2021-bounded")
    U, Y, x0 = _vehicle_data(sc, 120)
    est = build_estimators(sc, ["zonotope"], x0)[0]
    for k in range(120):
        p, H = _plain_correct(est, est.zonotope, Y[k])
        est.correct(Y[k])
        scale = np.abs(H).sum()
        np.testing.assert_allclose(est.zonotope.center, p, rtol=0, atol=1e-13 * scale)
        np.testing.assert_allclose(est.zonotope.generators, H, rtol=0, atol=1e-13 * scale)
        est.predict(U[k])
        assert not est.zonotope.generators.flags.writeable
    rng = np.random.default_rng(4)
    for _ in range(20):
        A = rng.standard_normal((9, int(rng.integers(9, 40))))
        import scipy.linalg as sla

        _, R, piv = sla.qr(A, mode="economic", pivoting=True)
        diag, piv2 = _pivoted_qr_diag(A)
        np.testing.assert_array_equal(piv2, piv)
        np.testing.assert_allclose(diag, np.abs(np.diag(R)), rtol=1e-14)
        Hbig = rng.standard_normal((9, 60))
        np.testing.assert_allclose(
            reduce_generators(Hbig, 40, "parallelotope"),
            _plain_parallelotope(Hbig, 40),
            rtol=1e-12,
            atol=1e-12,
        )


def test_vehicle_zonotope_refuses_non_finite_inputs():
    sc = load_scenario("ifac2021-bounded")
    est = build_estimators(sc, ["zonotope"], np.zeros(sc.state_dim))[0]
    Z = est.zonotope
    with pytest.raises(QuadobsError, match="u"):
        est.step(np.array([np.nan, 0.0, 0.0]), np.full(est.offsets.shape, np.nan))
    with pytest.raises(QuadobsError, match="y"):
        est.step(np.zeros(3), np.full(est.offsets.shape, np.inf))
    assert est.zonotope is Z
