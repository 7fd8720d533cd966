"""``rover-room``: a planar ground robot with a UWB radio and wheel odometry, exported as an odometry log."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.odometry import WheelOdometry, heading_and_yaw_rate
from quadobs.testbed.scenario import OdometrySpec, load_scenario
from quadobs.testbed.uwb import RadioConfig, UwbRadio, radio_of


def _circle(speed: float, omega: float, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Velocities and accelerations of a uniform circular motion, and its headings."""
    phi = np.linspace(-3.0, 3.0, count)
    v = speed * np.column_stack([np.cos(phi), np.sin(phi)])
    a = speed * omega * np.column_stack([-np.sin(phi), np.cos(phi)])
    return v, a, phi


def test_the_heading_is_the_direction_of_travel_and_the_yaw_rate_its_rate():
    v, a, phi = _circle(0.4, -0.7, 50)
    speed, heading, yaw_rate = heading_and_yaw_rate(v, a)
    np.testing.assert_allclose(speed, 0.4, rtol=1e-12)
    np.testing.assert_allclose(heading, phi, atol=1e-12)
    np.testing.assert_allclose(yaw_rate, -0.7, rtol=1e-12)  # a right turn: negative
    with pytest.raises(QuadobsError, match="odometry: the vehicle stops"):
        heading_and_yaw_rate(np.zeros((2, 2)), np.ones((2, 2)))


def test_the_odometry_errors_are_those_the_table_states():
    spec = OdometrySpec(
        rate=50.0, speed_std=0.05, scale_error=0.04, yaw_rate_std=0.03, yaw_rate_bias=0.01
    )
    n = 40_000
    v, a, _ = _circle(0.3, 0.5, n)
    measured, _, _ = WheelOdometry(spec, seed=3, dt=1e-3).sample(v, a)
    tol = 4.0 / math.sqrt(n)  # four standard errors of a mean, in units of the noise's std
    speed_error = measured[:, 0] - 1.04 * 0.3
    yaw_error = measured[:, 1] - (0.5 + 0.01)
    assert abs(speed_error.mean()) < tol * 0.05 and abs(yaw_error.mean()) < tol * 0.03
    # the sample standard deviation within four of its standard errors, sigma / sqrt(2 n)
    assert speed_error.std() == pytest.approx(0.05, abs=4 * 0.05 / math.sqrt(2 * n))
    assert yaw_error.std() == pytest.approx(0.03, abs=4 * 0.03 / math.sqrt(2 * n))
    assert WheelOdometry(spec, seed=3, dt=1e-3).every == 20


def test_the_odometry_is_the_same_for_a_seed_however_it_is_cut_into_blocks():
    spec = OdometrySpec(speed_std=0.02, yaw_rate_std=0.02)
    v, a, _ = _circle(0.3, 0.5, 1000)
    whole = WheelOdometry(spec, seed=7, dt=1e-3).sample(v, a)[0]
    cut = WheelOdometry(spec, seed=7, dt=1e-3)
    parts = np.vstack([cut.sample(v[:333], a[:333])[0], cut.sample(v[333:], a[333:])[0]])
    np.testing.assert_array_equal(parts, whole)
    other = WheelOdometry(spec, seed=8, dt=1e-3).sample(v, a)[0]
    assert not np.array_equal(other, whole)


def test_radio_biases_have_the_stated_mean_and_a_zero_mean_draws_as_before():
    anchors = np.zeros((4000, 3))
    radio = UwbRadio(anchors, RadioConfig(bias_std=0.03, bias_mean=0.11), seed=1)
    assert radio.biases.mean() == pytest.approx(0.11, abs=4 * 0.03 / math.sqrt(4000))
    plain = UwbRadio(anchors, RadioConfig(bias_std=0.03), seed=1)
    np.testing.assert_array_equal(radio.biases, 0.11 + plain.biases)  # the same draws, shifted
    # rover-room: positive biases, as an antenna delay lengthens each range
    assert np.all(radio_of(load_scenario("rover-room")).biases > 0.0)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (["odometry.rate=300"], "odometry.rate: 300.0 Hz must divide the physics rate"),
        (["odometry.scale_error=-1"], "odometry.scale_error"),
    ],
)
def test_bad_odometry_settings_are_refused_in_one_line(settings, message):
    with pytest.raises(QuadobsError, match=message):
        load_scenario("rover-room", settings=settings)


@pytest.mark.parametrize("name", ["wind", "beacons", "quadrotor-uwb"])
def test_odometry_is_refused_outside_a_planar_vehicle(name):
    with pytest.raises(QuadobsError, match="odometry: wheel odometry is"):
        load_scenario(name, settings=["odometry.rate=50"])


@pytest.fixture(scope="module")
def rover_log(tmp_path_factory):
    """rover-room, 3 s, with its log export, twice with the same seed."""
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.logs import read_log
    from quadobs.testbed.logs.export import LogExportSink

    folders = []
    for run in range(2):
        folder = tmp_path_factory.mktemp(f"rover{run}") / "log"
        sc = load_scenario("rover-room", duration=3.0)
        run_episode(sc, estimators=["ekf"], sinks=[LogExportSink(folder)])
        folders.append(folder)
    return sc, read_log(folders[0]), folders


def test_the_run_is_written_as_an_odometry_log(rover_log):
    sc, log, (folder, _) = rover_log
    assert sorted(p.name for p in folder.iterdir()) == [
        "beacons.csv", "inputs.csv", "meta.csv", "ranges.csv", "truth.csv",
    ]  # fmt: skip
    assert log.version == 2 and log.input_kind == "odometry" and log.dimension == 2
    assert log.truth_columns == ("time", "x", "y", "heading")
    # the odometry at 50 Hz from t = 0, a last row at t_K
    assert log.inputs.shape == (3 * 50 + 1, 3)
    np.testing.assert_allclose(log.inputs[:-1, 0], np.arange(150) * 0.02, atol=1e-12)
    # heading0 is the direction of travel at the start: the trajectory's velocity there
    v0 = sc.trajectory.derivative(0.0, 1)
    assert log.heading0 == pytest.approx(math.atan2(v0[1], v0[0]), abs=1e-9)
    # the ranges: round-robin at 40 Hz less the dropouts, with the radio's stated std
    assert 0.85 * 120 < log.ranges.shape[0] <= 120
    assert np.all(log.range_std == 0.08)
    # the measured speed is (1 + scale_error) times the true one, plus noise of 0.02 m/s
    truth_v = np.diff(log.truth[:, 1:3], axis=0) / np.diff(log.truth[:, :1], axis=0)
    k = np.searchsorted(log.truth[:, 0], log.inputs[:-1, 0])
    true_speed = np.hypot(*truth_v[np.minimum(k, truth_v.shape[0] - 1)].T)
    residual = log.inputs[:-1, 1] - 1.02 * true_speed
    assert abs(residual.mean()) < 4 * 0.02 / math.sqrt(150)


def test_the_export_is_the_same_for_a_seed(rover_log):
    _, _, (a, b) = rover_log
    for name in ("inputs.csv", "ranges.csv", "truth.csv", "meta.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_the_exported_log_replays_with_the_odometry_defaults(rover_log):
    from quadobs.testbed.logs.replay import default_estimators, run_replay

    _, log, _ = rover_log
    names = default_estimators(log)
    assert "ukf-heading" in names
    summary = run_replay(log, initial_offset=0.5, batch=False)
    assert summary["model"] == "odometry"
    for name in names:
        assert summary["estimators"][name]["rmse"] < 1.0, name


def _odometry_log(times, speeds):
    from quadobs.testbed.logs.format import RangeLog

    inputs = np.column_stack([times, speeds, np.zeros(len(times))])
    beacons = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.4]])
    ranges = np.array([[0.5, 0, 1.0], [0.6, 1, 2.0]])
    return RangeLog("odo", np.arange(3), beacons, ranges, inputs, 0.0)


def test_the_odometry_noise_prior_is_the_mean_square_speed_over_a_second():
    from quadobs.testbed.logs.estimators import (
        HEADING_SPEED_ERROR,
        ODOMETRY_ERROR_TIME,
        log_defaults,
        odometry_noise,
    )

    # 0.3 m/s for 2 s, then 0.6 m/s for 1 s (the last row only closes the span)
    log = _odometry_log([0.0, 2.0, 3.0], [0.3, 0.6, 5.0])
    expected = (2.0 * 0.09 + 1.0 * 0.36) / 3.0 * ODOMETRY_ERROR_TIME
    assert odometry_noise(log) == pytest.approx(expected, rel=1e-12)
    heading = pytest.approx(HEADING_SPEED_ERROR**2 * expected, rel=1e-12)  # a speed error's share
    assert log_defaults(log) == {
        "q_xy": pytest.approx(expected, rel=1e-12),
        "q_xy_heading": heading,
    }
    # a robot that never moves still gets the floor's noise, (0.01 m/s)^2 over a second
    assert odometry_noise(_odometry_log([0.0, 1.0], [0.0, 0.0])) == pytest.approx(1e-4)


def test_the_replay_takes_the_log_s_prior_unless_an_option_sets_it():
    from quadobs.testbed.logs.estimators import odometry_noise, replay_setup
    from quadobs.testbed.worlds.replay import ReplayWorld

    log = _odometry_log([0.0, 2.0, 3.0], [0.3, 0.6, 0.6])
    world = ReplayWorld(log, 0.1, "odometry", 8, None, peer_batch=False)
    assert replay_setup(log, world).q_xy == pytest.approx(odometry_noise(log))
    assert replay_setup(log, world, {"q_xy": 2.0}).q_xy == 2.0
    assert replay_setup(log, world).q_xy_heading == pytest.approx(odometry_noise(log) / 64)
    assert replay_setup(log, world, {"q_xy_heading": 2.0}).q_xy_heading == 2.0


def test_the_command_line_exports_and_replays_the_odometry_log(tmp_path, capsys):
    from quadobs.cli import main

    folder = tmp_path / "rover"
    assert main(["run", "rover-room", "--duration", "2", "--export-log", str(folder)]) == 0
    assert f"replay with: quadobs replay {folder})" in capsys.readouterr().out
    assert main(["replay", str(folder), "--burn-in", "1", "--calibrate", "none"]) == 0
    out = capsys.readouterr().out
    assert "model odometry" in out and "ekf-bias" in out and "ukf-heading" in out


def test_a_path_that_stops_is_refused_when_the_scenario_is_read():
    # a straight line at 0.3 m/s forward and back: the speed falls to zero at t = 5 s
    with pytest.raises(QuadobsError, match=r"odometry: the trajectory stops at t = 5 s"):
        load_scenario(
            "rover-room",
            settings=[
                'trajectory.terms=[{axis = 0, amplitude = 0.3, omega = 0.3141592653589793, function = "sin"}]',
                "trajectory.offset=[1.5, 1.2]",
                "duration=20",
            ],
        )


#: The estimators of an odometry log with the heading as a state (the lever arm, the anchors'
#: heights and biases): each must give the same estimate whatever the order of the anchors.
HEADING_FILTERS = (
    "ekf-heading",
    "ukf-heading",
    "augmented-heading",
    "ukf-lever",
    "ukf-height-lever",
)


def test_the_heading_filters_do_not_depend_on_the_order_of_the_anchors(rover_log, tmp_path):
    """The same log with ``beacons.csv`` listed in two other orders (the ranges name their
    anchor by id, so nothing else changes), replayed from 50 m off: every heading filter starts
    from its multilateration and ends on the same trajectory, to rounding."""
    import dataclasses

    from quadobs.testbed.logs.replay import run_replay

    _, log, _ = rover_log
    tracks = []
    for k, order in enumerate(([0, 1, 2, 3], [3, 2, 1, 0], [1, 3, 0, 2])):
        permuted = dataclasses.replace(
            log, beacon_ids=log.beacon_ids[order], beacons=log.beacons[order]
        )
        s = run_replay(
            permuted, estimators=list(HEADING_FILTERS), initial_offset=50.0, batch=False,
            export_tum=tmp_path / f"tum{k}",
        )  # fmt: skip
        tracks.append({n: np.loadtxt(tmp_path / f"tum{k}" / f"{n}.tum") for n in HEADING_FILTERS})
        assert all(s["estimators"][n]["diverged"] is None for n in HEADING_FILTERS), k
    for name in HEADING_FILTERS:
        for other in tracks[1:]:
            np.testing.assert_allclose(
                other[name], tracks[0][name], rtol=0, atol=1e-8, err_msg=name
            )
