"""The quadrotor world: model figures, flight plan, controller, IMU input, flight on the estimate."""

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.controllers import CRAZYFLIE, FlightPlan, GeometricController
from quadobs.testbed.imu import quat_to_matrix
from quadobs.testbed.scenario import load_scenario


def _short(name, *settings, duration=12.0):
    return load_scenario(
        name,
        settings=[
            f"duration={duration}",
            "quadrotor.takeoff=2.0",
            "quadrotor.landing=2.0",
            *settings,
        ],
    )


def test_the_model_has_the_crazyflie_figures():
    import mujoco

    from quadobs.testbed.worlds.quadrotor import quadrotor_model_path

    m = mujoco.MjModel.from_xml_path(str(quadrotor_model_path()))
    body = m.body("quadrotor")
    assert body.mass[0] == pytest.approx(0.0319)
    assert np.allclose(body.inertia, [16.8e-6, 16.8e-6, 29.8e-6])
    assert m.nu == 4 and np.allclose(m.actuator_ctrlrange, [0.0, 0.12])
    assert np.all(m.actuator_dyntype == 0) and m.opt.density > 0 and m.opt.gravity[2] < 0
    assert np.allclose(np.abs(m.actuator_gear[:, 5]), CRAZYFLIE.torque_ratio)


def test_the_flight_plan_is_twice_differentiable_and_stands_still_in_hovers():
    sc = load_scenario("quadrotor-1beacon")
    plan = FlightPlan(
        sc.trajectory,
        sc.duration,
        takeoff=3.0,
        landing=3.0,
        hovers=[(13.0, 23.0)],
        ramp=1.0,
        floor=0.02,
    )
    t = np.arange(0.0, sc.duration, 1e-3)
    ref = plan.reference(t)
    assert np.allclose(ref[0, 0], [*sc.trajectory.position(0.0)[:2], 0.02])  # starts on the floor
    assert np.allclose(
        np.gradient(ref[:, 0], t, axis=0), ref[:, 1], atol=2e-3
    )  # r' is the derivative of r
    assert np.allclose(np.gradient(ref[:, 1], t, axis=0), ref[:, 2], atol=5e-3)
    hover = (t > 14.1) & (t < 21.9)
    assert np.abs(ref[hover, 1]).max() < 1e-12 and np.ptp(ref[hover, 0], axis=0).max() < 1e-12
    assert ref[-1, 0, 2] == pytest.approx(0.02, abs=1e-6)  # lands


def test_the_mixer_inverts_collective_thrust_and_torques():
    ctrl = GeometricController(CRAZYFLIE)
    T = np.array([0.07, 0.08, 0.09, 0.075])
    f_m = CRAZYFLIE.mixer() @ T
    assert f_m[0] == pytest.approx(T.sum())
    assert np.allclose(ctrl.mix_inv @ f_m, T)
    hover = ctrl(np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros((3, 3)))
    assert np.allclose(hover, CRAZYFLIE.mass * 9.81 / 4)


def test_quaternion_matrix_is_a_rotation():
    q = np.array([0.9, 0.1, -0.3, 0.2])
    R = quat_to_matrix(q / np.linalg.norm(q))
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)


def test_the_quadrotor_tables_belong_to_quadrotor_scenarios():
    with pytest.raises(QuadobsError, match=r"^control: only used with kind"):
        load_scenario("ifac2021", settings=["control.feedback=truth"])
    with pytest.raises(QuadobsError, match=r"^quadrotor.hovers\[0\]"):
        load_scenario("quadrotor-uwb", settings=["quadrotor.hovers=[{start = 10.0, end = 10.5}]"])
    with pytest.raises(QuadobsError, match=r"^control.rate"):
        load_scenario("quadrotor-uwb", settings=["control.rate=300.0"])


def _rows_world():
    from quadobs.testbed.worlds.quadrotor import QuadrotorWorld

    kept = {}

    class Kept(QuadrotorWorld):
        def commit(self, rows):
            kept.setdefault("rows", []).append(self.out[:rows].copy())
            kept["world"] = self

    return Kept, kept


def test_noise_free_imu_input_is_the_true_acceleration_and_the_observer_converges():
    from quadobs.testbed.episode import run_episode

    sc = _short(
        "quadrotor-uwb",
        "quadrotor.accel_std=0.0",
        "quadrotor.accel_bias=0.0",
        "quadrotor.attitude_std=0.0",
        "quadrotor.gyro_std=0.0",
        "quadrotor.gyro_bias=0.0",
        "noise.range_std=0.0",
        # noise-free ranges state no noise to derive the observer's tuning from: a hand-set one
        'observer.tuning="explicit"',
        "observer.V=3e-2",
        "observer.W=0.2",
    )
    world, kept = _rows_world()
    res = run_episode(sc, estimators=["augmented"], world=world)
    w = kept["world"]
    rows = np.concatenate(kept["rows"])
    v = rows[:, w.columns.truth][:, 3:]
    a = np.diff(v, axis=0) / sc.dt  # mean acceleration over each step
    u = rows[:-1, w.columns.u]
    assert (
        np.abs(u - a)[10:].max() < 0.05
    )  # u = R f + g: the acceleration (after the first contact steps on the floor)
    f = res.summary["flight"]
    assert not f["crashed"] and f["tracking_rms"] < 0.05 and f["time_on_estimate"] == 0.0
    assert res.summary["estimators"]["augmented"]["flight_position_rmse"] < 0.05


def test_the_augmented_observer_flies_the_quadrotor_deterministically():
    from quadobs.testbed.episode import run_episode

    sc = _short("quadrotor-uwb-augmented", "control.switch_time=5.0", duration=15.0)
    a = run_episode(sc, estimators=["augmented", "ekf"]).summary
    b = run_episode(sc, estimators=["augmented", "ekf"]).summary
    f = a["flight"]
    assert not f["crashed"] and f["time_on_estimate"] == pytest.approx(15.0 - 5.0)
    assert f["tracking_rms"] < 0.15 and f["tracking_max"] < 0.3
    assert a["estimators"]["augmented"]["flight_position_rmse"] < 0.1
    assert a["flight"] == b["flight"] and a["estimators"] == b["estimators"]


def test_a_feedback_estimator_must_run_in_the_episode():
    from quadobs.testbed.episode import run_episode

    sc = _short("quadrotor-uwb", "control.feedback=ukf", duration=5.0)
    with pytest.raises(QuadobsError, match="ukf"):
        run_episode(sc, estimators=["augmented"])


def test_the_recording_holds_the_flight(tmp_path):
    from quadobs.recording import list_entities
    from quadobs.testbed.episode import run_episode

    sc = _short("quadrotor-uwb-augmented", "control.switch_time=3.0", duration=6.0)
    out = tmp_path / "q.rrd"
    run_episode(sc, estimators=["augmented"], out=out)
    names = set(list_entities(out))
    for entity in (
        "/world/reference/path",
        "/world/quadrotor",
        "/flight/rotors",
        "/flight/tracking_error",
        "/errors/augmented/position/norm",
    ):
        assert entity in names


def test_the_excitation_monitor_flags_the_hovers_and_not_the_manoeuvres():
    from quadobs.testbed.episode import run_episode

    sc = load_scenario("quadrotor-1beacon")
    spec = sc.excitation
    low = run_episode(sc, estimators=[]).summary["excitation"]["low_segments"]
    landing = sc.duration - sc.quadrotor.landing
    hovers = [(h.start, h.end) for h in sc.quadrotor.hovers]
    for (
        start,
        end,
    ) in hovers:  # one long segment per hover, from once the window has left the manoeuvre
        inside = [(a, b) for a, b in low if a < end + spec.window and b > start]
        assert len(inside) == 1, (start, end, low)
        a, b = inside[0]
        assert (
            # the vehicle settles into the hover within 2 s of the reference (rotor lag, position loop)
            start < a <= start + spec.window + sc.quadrotor.hover_ramp + 2.0
            and end - 1.0 <= b <= end + spec.window
        )
    for a, b in low:  # nothing flagged in the manoeuvres after the take-off
        assert (
            any(a < e + spec.window and b > s for s, e in hovers)
            or a >= landing
            or b <= sc.quadrotor.takeoff + spec.window
        )


def test_the_filters_input_noise_comes_from_the_imu_settings():
    from quadobs.testbed.factories import baseline_settings
    from quadobs.testbed.imu import input_noise_std

    sc = load_scenario("quadrotor-uwb")
    q = sc.quadrotor
    every = int(round(sc.physics_rate / q.attitude_rate))
    expected = np.sqrt(
        q.accel_std**2 + every * (9.81 * q.attitude_std) ** 2 + q.accel_bias**2 * 1.0 / sc.dt
    )
    assert input_noise_std(q, every, sc.dt) == pytest.approx(expected)
    Q = baseline_settings(sc).dynamics.input_covariance
    assert (
        np.allclose(Q, expected**2 * np.eye(3)) and sc.noise.accel_std == 0.0
    )  # not the [noise] table
    louder = load_scenario("quadrotor-uwb", settings=["quadrotor.attitude_std=0.02"])
    assert np.all(np.diag(baseline_settings(louder).dynamics.input_covariance) > np.diag(Q))


def test_every_bias_rule_takes_the_one_horizon(monkeypatch):
    """The live EKF's input, the live on-board EKF and the replay's gyroscope match a constant
    bias over :data:`~quadobs.testbed.imu.BIAS_HORIZON`: at 1 s to the bit as written before, and
    a changed horizon reaches all three (``b^2 tau`` per unit time)."""
    import math

    from quadobs.testbed import factories, imu
    from quadobs.testbed.logs import estimators as replay_estimators
    from quadobs.testbed.logs.estimators import ReplaySetup, gyro_noise

    sc = load_scenario("quadrotor-uwb")
    q, dt = sc.quadrotor, sc.dt
    beacons = np.array(sc.beacons)
    setup = ReplaySetup(beacons, 0.1, "imu", 0.0, 3.0, gyro_noise=1e-4, gyro_bias=q.gyro_bias)

    def rules():
        ekf = factories.onboard_ekf(sc, np.zeros(6))
        return imu.input_noise_std(q, 4, dt) ** 2, ekf.q_v, ekf.q_a, gyro_noise(setup)

    white = q.accel_std**2 + 4 * (9.81 * q.attitude_std) ** 2
    one = rules()
    assert imu.BIAS_HORIZON == 1.0
    assert one[1] == math.sqrt(q.accel_std**2 + q.accel_bias**2 / dt) ** 2
    assert one[2] == math.sqrt(q.gyro_std**2 + q.gyro_bias**2 / dt) ** 2
    assert one[3] == 1e-8 + q.gyro_bias**2
    for module in (imu, replay_estimators):  # factories reads it from imu at the call
        monkeypatch.setattr(module, "BIAS_HORIZON", 3.0)
    three = rules()
    assert three[0] - white == pytest.approx(3.0 * (one[0] - white))
    for k, b2 in ((1, q.accel_bias**2 / dt), (2, q.gyro_bias**2 / dt), (3, q.gyro_bias**2)):
        assert math.isclose(three[k] - one[k], 2.0 * b2, rel_tol=1e-9)


def test_the_campaign_summarises_the_flights():
    from quadobs.studies.campaign import flight_summary

    flights = [
        {
            "crashed": False,
            "tracking_rms": 0.05,
            "tracking_max": 0.1,
            "time_on_estimate": 60.0,
            "flight_position_rmse": {"augmented": 0.02},
            "flown_on": "augmented",
            "crash_time": float("nan"),
        },
        {
            "crashed": True,
            "tracking_rms": 0.2,
            "tracking_max": 1.2,
            "time_on_estimate": 20.0,
            "flight_position_rmse": {"augmented": 0.06},
            "flown_on": "augmented",
            "crash_time": 28.0,
        },
        {
            "crashed": False,
            "tracking_rms": 0.07,
            "tracking_max": 0.2,
            "time_on_estimate": 60.0,
            "flight_position_rmse": {"augmented": float("nan")},
            "flown_on": "augmented",
            "crash_time": float("nan"),
        },
    ]
    s = flight_summary(flights, ["augmented"])
    assert s["runs"] == 3 and s["crashed"] == 1
    assert s["crashes_by_estimator"] == {
        "augmented": {"runs": 3, "crashed": 1, "crash_times": [28.0]}
    }
    assert s["tracking_rms_median"] == pytest.approx(0.07) and s[
        "tracking_rms_max"
    ] == pytest.approx(0.2)
    assert s["tracking_max"] == pytest.approx(1.2) and s["time_on_estimate_mean"] == pytest.approx(
        140.0 / 3
    )
    assert s["flight_position_rmse"]["augmented"] == {
        "median": pytest.approx(0.04),
        "max": pytest.approx(0.06),
    }


@pytest.mark.slow
def test_the_50_flights_on_the_augmented_observer_meet_the_targets():
    from quadobs.studies.campaign import run_campaign

    sc = load_scenario("quadrotor-uwb-augmented")
    s = run_campaign(
        sc, runs=50, estimators=["augmented", "ekf", "ukf"], workers=2, record=False
    ).summary
    f = s["flight"]
    assert s["runs_completed"] == 50 and f["crashed"] == 0
    assert f["tracking_rms_max"] <= 0.10  # with the identified rotor
    for name in ("augmented", "ekf", "ukf"):
        assert f["flight_position_rmse"][name]["max"] <= 0.10, name


def test_the_augmented_observer_reconverges_after_each_hover_on_one_beacon():
    # quadrotor-1beacon's [observer] table: V and W from the IMU's and the range's noise (docs/quadrotor.md).
    from quadobs.testbed.episode import run_episode

    sc = load_scenario("quadrotor-1beacon")
    tr = run_episode(sc, estimators=["augmented"], collect_every=50).trace
    t, err = (
        tr["time"],
        np.linalg.norm(tr["estimates"]["augmented"][:, :3] - tr["truth"][:, :3], axis=1),
    )
    ends = [h.end for h in sc.quadrotor.hovers]
    nexts = [h.start for h in sc.quadrotor.hovers][1:] + [sc.duration - sc.quadrotor.landing]
    for end, nxt in zip(ends, nexts):
        drifted = err[(t >= end - 1.0) & (t < end)].max()
        after = err[(t >= end) & (t < nxt)]
        assert drifted > 2.0 and after.min() < 0.5, (
            end,
            drifted,
            after.min(),
        )  # lost in the hover, found after it


def test_the_compiled_controller_and_imu_agree_with_the_numpy_reference():
    from types import SimpleNamespace

    from quadobs._kernels import quadrotor as kq
    from quadobs.testbed.imu import ImuModel

    rng = np.random.default_rng(3)
    c = GeometricController(CRAZYFLIE, 2.0, 12.0, 0.9)
    gains = np.array(
        [c.kx, c.kv, c.kR, c.kW, CRAZYFLIE.mass, c.tan_tilt, CRAZYFLIE.thrust_max, 0.0]
    )
    out, R = np.zeros(4), np.zeros((3, 3))
    for _ in range(50):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        p, v, W, ref = (
            rng.standard_normal(3),
            rng.standard_normal(3),
            rng.standard_normal(3),
            rng.standard_normal((3, 3)),
        )
        kq.quat_matrix(q, R)
        assert np.allclose(R, quat_to_matrix(q), atol=1e-15)
        kq.control(p, v, R, W, ref, gains, c.J, c.mix_inv, out)
        assert np.allclose(out, c(p, v, quat_to_matrix(q), W, ref), rtol=1e-12, atol=1e-15)
    spec = SimpleNamespace(
        accel_std=0.03, accel_bias=0.02, gyro_std=0.005, gyro_bias=0.002, attitude_std=0.01
    )
    imu = ImuModel(spec, seed=5)
    packed = np.concatenate(
        [imu.accel_bias, imu.gyro_bias, [imu.accel_std, imu.gyro_std, imu.attitude_std]]
    )
    noise = imu.draws(1)
    sd = rng.standard_normal(10)
    sd[6:10] /= np.linalg.norm(sd[6:10])
    att, rates, row, nxt = np.zeros(4), np.zeros(3), np.zeros(7), np.zeros(6)
    upside = kq.post_step(
        sd, 0, 3, 6, noise[0], packed, True, att, rates, R, row, 0, 4, sd[:3], sd[3:6], nxt
    )
    f_m, w_m, q_m = imu.measure(0, 0, noise, sd[:3], sd[3:6], sd[6:10])
    assert np.allclose(att, q_m, atol=1e-15) and np.allclose(rates, w_m, atol=1e-15)
    assert np.allclose(row[4:7], quat_to_matrix(q_m) @ f_m + [0.0, 0.0, -9.81], atol=1e-14)
    assert np.array_equal(row[:4], sd[6:10]) and upside == (quat_to_matrix(sd[6:10])[2, 2] < 0.0)
