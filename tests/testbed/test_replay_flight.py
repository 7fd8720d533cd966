"""Body-IMU flight logs: the AHRS's initial alignment and ``ekf-bias-imu`` (the acceleration's bias as a state)."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_replay_in_time import _imu_body_log  # the body-IMU log of the replay in time's tests

from quadobs.core.held_input import held_input_step
from quadobs.testbed.attitude import ALIGN_TIME, estimate_attitude, initial_alignment
from quadobs.testbed.logs.imu_bias import acceleration_bias_system, acceleration_bias_walk
from quadobs.testbed.logs.replay import default_estimators, run_replay

G = 9.80665


def _resting_imu(tilt, gyro_bias, seconds=2.0, rate=500.0, seed=0):
    """A body resting at ``tilt`` (roll, pitch; rad) for ``seconds``: its specific force and rates
    with noise, the first sample a transient (the body settling, falling freely)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate)
    R = Rotation.from_euler("xy", tilt)
    f = np.tile(R.inv().apply([0.0, 0.0, G]), (t.size, 1)) + 0.05 * rng.standard_normal((t.size, 3))
    w = np.tile(gyro_bias, (t.size, 1)) + 0.005 * rng.standard_normal((t.size, 3))
    f[0] = [0.2, -0.1, -0.3]
    return t, f, w, R


def test_the_alignment_finds_the_tilt_and_the_gyro_bias_despite_a_first_transient():
    bias = np.array([0.012, -0.008, 0.02])
    t, f, w, R = _resting_imu((0.1, -0.05), bias)
    q, b = initial_alignment(t, f, w, G)
    est = Rotation.from_quat(q[[1, 2, 3, 0]])
    tilt_err = np.degrees(np.linalg.norm((R.inv() * est).as_rotvec()[:2]))
    assert tilt_err < 0.1  # the median over 0.5 s of 500 Hz samples: 0.05 m/s^2 noise
    np.testing.assert_allclose(b, bias, atol=1e-3)
    # from the first sample alone the tilt would be some 150 degrees off
    f_first = f[0] / np.linalg.norm(f[0])
    assert np.degrees(np.arccos(f_first[2])) > 90.0
    # the filter starts with the bias: 2 s later the heading has drifted by a fraction of what
    # the yaw rate's bias alone gives (0.04 rad)
    Q = estimate_attitude(t, f, w, G)
    yaw = Rotation.from_quat(Q[-1, [1, 2, 3, 0]]).as_euler("zyx")[0]
    assert abs(yaw) < 0.25 * bias[2] * t[-1]


def test_the_alignment_takes_no_bias_when_the_body_accelerates():
    t, f, w, _ = _resting_imu((0.0, 0.0), np.array([0.0, 0.0, 0.3]))
    f[:, 2] += 3.0  # climbing at 3 m/s^2: not resting, the rates are not a bias
    _, b = initial_alignment(t, f, w, G)
    assert np.all(b == 0.0)
    assert ALIGN_TIME < t[-1]


def test_acceleration_bias_system_is_the_closed_form_held_input_step():
    h = 0.3
    system = acceleration_bias_system(3, np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 1.0]]))
    F, Gm = held_input_step(system.A, system.B, h)
    eye = np.eye(3)
    expected = np.block(
        [[eye, h * eye, -h * h / 2 * eye], [0 * eye, eye, -h * eye], [0 * eye, 0 * eye, eye]]
    )
    np.testing.assert_allclose(F, expected, atol=1e-12)
    np.testing.assert_allclose(Gm, np.vstack([h * h / 2 * eye, h * eye, 0 * eye]), atol=1e-12)
    p = np.array([1.0, 2.0, 0.5])  # the outputs: half the squared range less |a|^2 / 2
    x = np.concatenate([p, np.zeros(6)])
    a = system.d[1, :3]
    assert np.isclose(0.5 * x @ system.C[1] @ x + system.d[1] @ x, 0.5 * p @ p + a @ p)
    walk = acceleration_bias_walk  # the AHRS's 10 s against an hour's drift
    assert walk(0.2, True, 3600.0) == pytest.approx(360.0 * walk(0.2, False, 3600.0))


def _biased(log, bias):
    inputs = log.inputs.copy()
    inputs[:, 1:4] += bias
    return dataclasses.replace(log, inputs=inputs)


@pytest.mark.parametrize("with_attitude", [True, False])
def test_ekf_bias_imu_removes_an_accelerometer_bias(with_attitude):
    """A level body circling, its accelerometer biased by (0.2, -0.1, 0.3) m/s^2: the acceleration's
    bias as a state beats the range biases alone, with the log's attitude or the AHRS's."""
    log = _biased(_imu_body_log(with_attitude), np.array([0.2, -0.1, 0.3]))
    s = run_replay(
        log, estimators=["ekf-bias", "ekf-bias-imu"], initial_offset=3.0, batch=False,
        setup_options={"range_sigma": 0.05}, burn_in=5.0,
    )  # fmt: skip
    plain, imu = (s["estimators"][n]["rmse"] for n in ("ekf-bias", "ekf-bias-imu"))
    assert s["estimators"]["ekf-bias-imu"]["diverged"] is None
    assert imu < 0.6 * plain, (plain, imu)


def test_the_gate_and_the_estimated_excess_are_two_filters():
    """``ekf-bias-imu`` keeps the one-sided gate where the setup knows an excess;
    ``ekf-bias-imu-nlos`` takes the excess's mixture there, and the gate where none is known."""
    from quadobs.estimators.robust import ExcessMixture, SkewedGate
    from quadobs.testbed.logs.estimators import REPLAY_ESTIMATORS, replay_setup
    from quadobs.testbed.worlds.replay import ReplayWorld

    log = _imu_body_log(False)
    world = ReplayWorld(log, 0.1, "imu")
    known = replay_setup(log, world, {"nlos_median": 0.4, "nlos_shape": 0.7}, 3.0)
    unknown = replay_setup(log, world, {}, 3.0)
    x0 = np.zeros(6)
    rules = {
        (name, bool(s.nlos_median)): type(REPLAY_ESTIMATORS[name](s, x0).robust)
        for name in ("ekf-bias-imu", "ekf-bias-imu-nlos")
        for s in (known, unknown)
    }
    assert rules == {
        ("ekf-bias-imu", True): SkewedGate,
        ("ekf-bias-imu", False): SkewedGate,
        ("ekf-bias-imu-nlos", True): ExcessMixture,
        ("ekf-bias-imu-nlos", False): SkewedGate,
    }
    assert {"ekf-bias-imu", "ekf-bias-imu-nlos"} <= set(default_estimators(log))


def test_body_imu_logs_replay_ekf_bias_imu_by_default():
    assert "ekf-bias-imu" in default_estimators(_imu_body_log(False))
    assert "ekf-bias-imu" not in default_estimators(_imu_body_log(False), "cv")
    body = _imu_body_log(False)
    navigation_frame = dataclasses.replace(body, input_kind="imu", inputs=body.inputs[:, :4])
    assert "ekf-bias-imu" not in default_estimators(navigation_frame)


def test_the_navigation_accelerations_are_computed_once_per_log():
    from quadobs.testbed import attitude

    log = _imu_body_log(False)
    first = attitude.navigation_accelerations(log)
    assert log in attitude._NAVIGATION  # the calibration's replays read it again
    first[:, 1:] = 0.0  # a caller's copy: the cached rows are not changed through it
    again = attitude.navigation_accelerations(log)
    assert np.any(again[:, 1:] != 0.0)


def _circling_log(psi: float, seconds: float = 60.0, anchors=None):
    """A level body circling (radius 2 m, 0.3 rad/s) without turning, its IMU at 100 Hz (gyro
    noise 0.002 rad/s: ahrs skips a sample of exactly zero rate) and no attitude, ranges 0.05 m
    at 50 Hz; the log's frame turned by ``psi`` about the vertical from the IMU's first heading."""
    from test_replay_in_time import ANCHORS_3D, _ranges

    from quadobs.testbed.logs import RangeLog

    rng = np.random.default_rng(3)
    c, s = np.cos(psi), np.sin(psi)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = np.arange(0.0, seconds, 0.01)
    w, r = 0.3, 2.0
    p = np.column_stack([r * np.cos(w * t), r * np.sin(w * t), 0 * t])
    v = np.column_stack([-r * w * np.sin(w * t), r * w * np.cos(w * t), 0 * t])
    a = -w * w * p
    p = p + [3.0, 3.0, 1.5]
    f = a + [0.0, 0.0, G]  # body axes along the IMU's frame
    gyro = 0.002 * rng.standard_normal((t.size, 3))
    placed = ANCHORS_3D if anchors is None else anchors
    anchors = placed @ rot.T
    ranges = _ranges(t[::2], placed, p[::2], rng, 0.05)
    truth = np.column_stack([t, p @ rot.T, v @ rot.T])
    log = RangeLog(
        "circling", np.arange(anchors.shape[0]), anchors, ranges, np.column_stack([t, f, gyro]), float("nan"),
        truth, input_kind="imu_body", truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"),
    )  # fmt: skip
    return log, rot, np.column_stack([t, a @ rot.T])


def _ahrs_accelerations(log):
    """The AHRS's navigation-frame acceleration of ``log``, its heading the IMU's first."""
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    R = Rotation.from_quat(estimate_attitude(t, f, w, G)[:, [1, 2, 3, 0]])
    return np.column_stack([t, R.apply(f) + log.gravity_vector])


@pytest.mark.parametrize("psi", [0.0, 2.0, -2.5])
def test_the_ahrs_heading_is_found_in_the_log_s_frame(psi):
    """The ranges give the turn between the IMU's first heading and the log's frame (the AHRS's
    lag on the slow circle, 0.4 rad uncorrected, is modelled), and the navigation-frame
    accelerations are turned by it."""
    from quadobs.testbed.attitude import heading_offset, navigation_accelerations

    log, _, _ = _circling_log(psi)
    ahrs = _ahrs_accelerations(log)
    found = heading_offset(log, ahrs)
    assert found == pytest.approx(psi, abs=0.1)
    c, s = np.cos(found), np.sin(found)
    turned = ahrs[:, 1:3] @ np.array([[c, s], [-s, c]])
    np.testing.assert_allclose(navigation_accelerations(log)[:, 1:3], turned, atol=1e-12)
    short, _, _ = _circling_log(psi, seconds=12.0)  # three spans of 4 s: not enough to tell
    assert heading_offset(short, _ahrs_accelerations(short)) == 0.0


def test_the_ahrs_heading_is_found_with_the_anchors_in_one_plane():
    """Anchors all at one height fix no height, and the horizontal positions suffice."""
    from quadobs.testbed.attitude import heading_offset

    ceiling = np.array([[0.0, 0.0, 3.0], [6.0, 0.0, 3.0], [6.0, 6.0, 3.0], [0.0, 6.0, 3.0]])
    log, _, _ = _circling_log(1.0, anchors=ceiling)
    assert heading_offset(log, _ahrs_accelerations(log)) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("name", ["ekf-bias-imu", "ekf-bias-imu-average"])
def test_ekf_bias_imu_refuses_what_it_cannot_take_before_any_work(name):
    """Refused by its own name (the average too, whose member is ``ekf-bias-imu``)."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.replay import check_replay

    body = _imu_body_log(False)
    with pytest.raises(QuadobsError, match=f"'{name}' takes the model imu, not 'cv'"):
        check_replay(body, [name], model="cv")
    navigation_frame = dataclasses.replace(body, input_kind="imu", inputs=body.inputs[:, :4])
    with pytest.raises(QuadobsError, match=f"'{name}' needs a 3-D body-IMU log"):
        check_replay(navigation_frame, [name])


def test_the_average_replays_as_the_mean_of_the_gate_and_the_mixture(tmp_path):
    """``ekf-bias-imu-average`` where the setup knows an excess: its track is the mean of the
    tracks of ``ekf-bias-imu`` and ``ekf-bias-imu-nlos`` replayed beside it; where none is known
    it is ``ekf-bias-imu``'s."""
    from quadobs.testbed.logs.estimators import REPLAY_ESTIMATORS, replay_setup
    from quadobs.testbed.worlds.replay import ReplayWorld

    log = _imu_body_log(False)
    names = ["ekf-bias-imu", "ekf-bias-imu-nlos", "ekf-bias-imu-average"]
    tracks, summaries = {}, {}
    for known in (True, False):
        options = {"nlos_median": 0.4, "nlos_shape": 0.7} if known else {}
        summaries[known] = run_replay(
            log, estimators=names, initial_offset=3.0, batch=False, setup_options=options,
            burn_in=2.0, export_tum=tmp_path / str(known),
        )["estimators"]  # fmt: skip
        tracks[known] = {n: np.loadtxt(tmp_path / str(known) / f"{n}.tum") for n in names}
    per = summaries[True]
    assert per["ekf-bias-imu-average"]["diverged"] is None
    for key in ("corrections", "rejected"):  # the members' counts, summed
        assert per["ekf-bias-imu-average"][key] == sum(per[n][key] for n in names[:2]), key
    assert per["ekf-bias-imu-average"]["robust"] == (
        f"ekf-bias-imu: {per['ekf-bias-imu']['robust']}; "
        f"ekf-bias-imu-nlos: {per['ekf-bias-imu-nlos']['robust']}"
    )
    two = tracks[True]
    assert not np.allclose(two["ekf-bias-imu"][:, 1:4], two["ekf-bias-imu-nlos"][:, 1:4])
    mean = (two["ekf-bias-imu"][:, 1:4] + two["ekf-bias-imu-nlos"][:, 1:4]) / 2
    np.testing.assert_allclose(two["ekf-bias-imu-average"][:, 1:4], mean, rtol=0, atol=1e-9)
    one = tracks[False]
    np.testing.assert_array_equal(one["ekf-bias-imu-average"], one["ekf-bias-imu"])
    same = {
        "estimator": "ekf-bias-imu",
        "reason": "no non-line-of-sight excess identified in the log",
    }
    for name in names[1:]:  # the summary says which rows are that filter
        assert summaries[False][name]["same_as"] == same and "same_as" not in per[name]
    assert "same_as" not in summaries[False]["ekf-bias-imu"]
    world = ReplayWorld(log, 0.1, "imu")
    build = REPLAY_ESTIMATORS["ekf-bias-imu-average"]
    counts = [
        len(build(replay_setup(log, world, o, 3.0), np.zeros(6)).members)
        for o in ({"nlos_median": 0.4, "nlos_shape": 0.7}, {})
    ]
    assert counts == [2, 1]
    assert "ekf-bias-imu-average" in default_estimators(log)


def test_the_average_takes_the_choice_of_biases_of_the_filter_it_is_when_scored():
    """Scored without the excess the average is ``ekf-bias-imu``: step 7 of the self-calibration
    gives it that filter's choice without replaying it again, or, asked alone, the same choice."""
    from quadobs.testbed.logs.calibration import Calibration, estimator_biases

    log = _imu_body_log(False)
    q = log.beacons.shape[0]
    biases = np.linspace(-0.3, 0.3, q)

    def decided(names, options):
        cal = Calibration(biases, dict(options), {}, "", biases.copy())
        estimator_biases(log, cal, names, model="imu")
        return cal

    for options in ({}, {"nlos_median": 0.4, "nlos_shape": 0.7}):  # the excess of step 8 or none
        both = decided(["ekf-bias-imu", "ekf-bias-imu-average"], options)
        alone = decided(["ekf-bias-imu-average"], options)
        assert both.per_estimator["ekf-bias-imu-average"] == both.per_estimator["ekf-bias-imu"]
        assert alone.per_estimator["ekf-bias-imu-average"] == both.per_estimator["ekf-bias-imu"]
        assert "ekf-bias-imu-average: as ekf-bias-imu, the same filter when scored" in both.reason
        assert "ekf-bias-imu-average: as" not in alone.reason  # scored itself
