"""The MuJoCo testbed: it realises the double integrator exactly, and its sensors are what they claim."""

import numpy as np
import pytest
import scipy.linalg as sla

from quadobs import QuadobsError, vehicle_system
from quadobs.testbed.worlds import VehicleSim, default_model_path, load_vehicle_model

BEACONS = np.array([[0.0, 0.0, 0.0], [30.0, -5.0, 2.0]])


def test_simulator_matches_the_double_integrator(rng):
    """A rollout under random held accelerations equals the exact discretisation of x' = Ax + Bu."""
    dt = 0.002
    sim = VehicleSim(3, BEACONS, timestep=dt)
    s = vehicle_system(3, BEACONS)
    big = np.zeros((9, 9))
    big[:6, :6], big[:6, 6:] = s.A, s.B
    E = sla.expm(big * dt)
    x = np.array([1.0, -2.0, 3.0, 0.5, 0.0, -1.5])
    sim.reset(x[:3], x[3:])
    for _ in range(2000):
        u = 5 * rng.standard_normal(3)
        sim.step(u)
        x = E[:6, :6] @ x + E[:6, 6:] @ u
    np.testing.assert_allclose(sim.state(), x, rtol=0, atol=1e-9 * np.abs(x).max())


def test_sensors_describe_the_start_of_the_step():
    sim = VehicleSim(3, BEACONS, timestep=0.01)
    sim.reset([5.0, 1.0, -2.0], [1.0, 2.0, 3.0])
    p_before = sim.position()
    sim.step([0.5, -1.0, 2.0])
    np.testing.assert_allclose(sim.ranges(), np.linalg.norm(p_before - BEACONS, axis=1), rtol=1e-12)
    np.testing.assert_allclose(sim.accelerometer(), [0.5, -1.0, 2.0], atol=1e-12)
    assert not np.allclose(sim.position(), p_before)


def test_two_dimensional_vehicle_stays_in_the_plane():
    sim = VehicleSim(2, BEACONS[:, :2], timestep=0.01)
    sim.reset([1.0, 2.0], [0.0, 1.0])
    for _ in range(100):
        sim.step([0.3, -0.2])
    assert abs(sim.data.qpos[2]) < 1e-12
    assert sim.state().shape == (4,)


def test_airspeed_uses_mujoco_wind():
    sim = VehicleSim(3, BEACONS, timestep=0.01, wind=np.array([3.0, -1.0, 0.0]))
    assert np.allclose(sim.model.opt.wind, [3.0, -1.0, 0.0])
    sim.reset([0.0, 0.0, 0.0], [10.0, 0.0, 0.0])
    sim.step([0.0, 0.0, 0.0])
    assert sim.airspeed() == pytest.approx(np.hypot(7.0, 1.0))
    np.testing.assert_allclose(sim.state()[3:], [7.0, 1.0, 0.0, 3.0, -1.0, 0.0])


def test_gravity_on_is_compensated(tmp_path, rng):
    xml = default_model_path().read_text().replace('gravity="0 0 0"', 'gravity="0 0 -9.81"')
    path = tmp_path / "grav.xml"
    path.write_text(xml)
    sim = VehicleSim(3, BEACONS, timestep=0.01, model_path=path)
    sim.reset([0.0, 0.0, 10.0], [0.0, 0.0, 0.0])
    sim.step([1.0, 0.0, 0.0])
    np.testing.assert_allclose(sim.accelerometer(), [1.0, 0.0, 0.0], atol=1e-10)
    np.testing.assert_allclose(sim.velocity(), [0.01, 0.0, 0.0], atol=1e-12)


def test_beacons_are_added_and_existing_ones_moved():
    vm = load_vehicle_model(BEACONS)
    np.testing.assert_allclose(vm.beacons, BEACONS)
    assert len(vm.offset_adr) == 2


@pytest.mark.parametrize(
    "edit,match",
    [
        (('<site name="imu" pos="0 0 0" size="0.05"/>', ""), "missing site named 'imu'"),
        (
            ('<motor name="force_y" joint="vehicle_joint" gear="0 1 0 0 0 0"/>', ""),
            "missing actuator named 'force_y'",
        ),
        (
            ('<accelerometer name="accelerometer" site="imu"/>', ""),
            "missing sensor named 'accelerometer'",
        ),
        (('integrator="RK4"', 'integrator="Euler"'), "integrator must be RK4"),
        (('contype="0" conaffinity="0"', ""), "must have contype=0"),
        (('gear="0 0 1 0 0 0"', 'gear="0 0 2 0 0 0"'), "actuator 'force_z' must act"),
        (("<option ", '<option density="1.2" '), "fluid density"),
        (
            ('<freejoint name="vehicle_joint"/>', '<joint name="vehicle_joint" type="ball"/>'),
            "free joint",
        ),
        (('mass="2.5"', 'mass="nan"'), r"bad.xml: MuJoCo warns: XML contains a 'NaN'"),
    ],
)
def test_bad_models_are_named(tmp_path, edit, match):
    xml = default_model_path().read_text()
    assert edit[0] in xml
    path = tmp_path / "bad.xml"
    path.write_text(xml.replace(edit[0], edit[1]))
    with pytest.raises(QuadobsError, match=match):
        load_vehicle_model(BEACONS, path=path)


def test_a_model_warning_leaves_no_log_file_behind(tmp_path, monkeypatch):
    """MuJoCo's parse warning is the error; MuJoCo's own log file is not written in the working directory."""
    path = tmp_path / "bad.xml"
    path.write_text(default_model_path().read_text().replace('mass="2.5"', 'mass="nan"'))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(QuadobsError):
        load_vehicle_model(BEACONS, path=path)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert load_vehicle_model(BEACONS).mass == 2.5  # the handler before it is back


def test_missing_model_file(tmp_path):
    with pytest.raises(QuadobsError, match="does not exist"):
        load_vehicle_model(BEACONS, path=tmp_path / "none.xml")
