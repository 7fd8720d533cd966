"""A body IMU converted by hand in the wrong units (accelerometer in g, gyroscope in deg/s) is
refused in one line naming the file and the columns, before any calibration."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_replay_in_time import _imu_body_log  # the body-IMU log of the replay in time's tests

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.attitude import check_body_imu, navigation_accelerations
from quadobs.testbed.logs import write_log

G = 9.80665


def _scaled(log, accel=1.0, gyro=1.0):
    imu = log.inputs.copy()
    imu[:, 1:4] *= accel
    imu[:, 4:7] *= gyro
    return dataclasses.replace(log, inputs=imu)


def _refused(tmp_path, capsys, log, file: str = "imu.csv") -> str:
    """The one error line of ``quadobs replay`` on ``log`` written out, which names ``file``
    (exit status 2, nothing calibrated)."""
    folder = write_log(log, tmp_path / "log")
    assert main(["replay", str(folder), "--no-progress"]) == 2
    out, err = capsys.readouterr()
    errors = [line for line in err.splitlines() if line.startswith("quadobs: error")]
    assert len(errors) == 1 and "calibrated" not in out, (out, err)
    assert f"{folder}/{file}" in errors[0]
    return errors[0]


def test_an_accelerometer_in_g_is_refused_naming_the_file_and_columns(tmp_path, capsys):
    error = _refused(tmp_path, capsys, _scaled(_imu_body_log(False), accel=1.0 / G))
    assert "columns ax,ay,az: the median |a| is 1, " in error and "in g" in error
    check_body_imu(_imu_body_log(False))  # in m/s^2: accepted
    error = _refused(tmp_path / "mg", capsys, _scaled(_imu_body_log(False), accel=1000.0 / G))
    assert "the median |a| is 1000, " in error and "(a log in mg: times g / 1000)" in error


def test_an_accelerometer_with_gravity_taken_out_is_refused_saying_so(tmp_path, capsys):
    log = _rocking_log()
    t = log.inputs[:, 0]
    linear = log.inputs.copy()
    linear[:, 1:4] = np.column_stack([0.6 * np.sin(3 * t), 0.4 * np.cos(2 * t), 0 * t])
    error = _refused(tmp_path, capsys, dataclasses.replace(log, inputs=linear))
    assert "columns ax,ay,az: the median |a| is " in error and "gravity taken out?" in error


def test_a_gyroscope_in_deg_per_s_turning_fast_is_beyond_any_full_scale(tmp_path, capsys):
    log = _scaled(_imu_body_log(True, yaw_rate=0.8), gyro=np.degrees(1.0))  # 45.8 "rad/s"
    error = _refused(tmp_path, capsys, log)
    assert "row 2, column gz: 45.84 is beyond any MEMS gyroscope's range" in error


def _rocking_log():
    """A body hovering in place, at rest for a second, then rolling +-0.1 rad at 1 rad/s (rates
    within 0.1 rad/s); no attitude."""
    log = _imu_body_log(False)
    t = log.inputs[:, 0]
    s = np.maximum(t - 1.0, 0.0)
    roll = 0.1 * np.sin(s)
    f = Rotation.from_euler("x", roll[:, None]).inv().apply([0.0, 0.0, G])
    w = np.column_stack([0.1 * np.cos(s) * (t > 1.0), 0 * t, 0 * t])
    w += 0.002 * np.random.default_rng(1).standard_normal(w.shape)
    return dataclasses.replace(log, inputs=np.column_stack([t, f, w]))


def test_a_slowly_turning_gyroscope_in_deg_per_s_does_not_keep_gravity_vertical():
    """Its rates (at most 5.7 deg/s) lie within any full scale, and the attitude integrated from
    them (every turn 57 times too large) leaves the acceleration's mean far from zero."""
    log = _rocking_log()
    navigation_accelerations(log)  # in rad/s: accepted
    wrong = _scaled(log, gyro=np.degrees(1.0))
    check_body_imu(wrong)
    with pytest.raises(
        QuadobsError, match="columns gx,gy,gz: the attitude integrated from the rat"
    ):
        navigation_accelerations(wrong)


def test_a_given_attitude_that_the_accelerometer_contradicts_is_refused(tmp_path, capsys):
    """An accelerometer whose y and z axes are flipped against the body the attitude turns
    leaves gravity far from vertical: refused naming attitude.csv and the conventions (the
    gyroscope's flipped too turns about other axes than the attitude: refused as well)."""
    log = _imu_body_log(True, yaw_rate=0.2)
    flipped = dataclasses.replace(log, inputs=log.inputs * [1, 1, -1, -1, 1, 1, 1])
    folder = write_log(flipped, tmp_path / "flight")
    assert main(["replay", str(folder), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"{folder}/attitude.csv: the attitude given does not keep gravity vertical" in err
    assert "scalar first (qw,qx,qy,qz)" in err
    both = dataclasses.replace(log, inputs=log.inputs * [1, 1, -1, -1, 1, -1, -1])
    with pytest.raises(QuadobsError, match="turn about other axes than the attitude does"):
        check_body_imu(both)


def test_rates_in_deg_per_s_beside_a_given_attitude_turn_57_times_as_far():
    """A gyroscope in deg/s turning slowly (0.2 rad/s: within any full scale) beside a given
    attitude: its rotations are 57.3 times the attitude's."""
    log = _scaled(_imu_body_log(True, yaw_rate=0.2), gyro=np.degrees(1.0))
    with pytest.raises(
        QuadobsError, match=r"columns gx,gy,gz: the rates integrated turn 57.3 times"
    ):
        check_body_imu(log)
    check_body_imu(_imu_body_log(True, yaw_rate=0.2))  # in rad/s: accepted


def test_an_attitude_given_navigation_to_body_turns_about_the_opposite_axes():
    """The attitude written the other way (its conjugate): the body rates turn about the
    opposite axis of the attitude's own rotations, which no unit explains."""
    log = _imu_body_log(True, yaw_rate=0.2)
    att = log.attitude * [1, 1, -1, -1, -1]
    with pytest.raises(
        QuadobsError,
        match=r"attitude.csv: the body rates of imu.csv turn about other axes than the attitude does \(median cosine -1.00",
    ):
        check_body_imu(dataclasses.replace(log, attitude=att))


def test_one_file_in_milliseconds_is_refused_by_its_span_and_a_short_truth_is_not(tmp_path):
    """The IMU stamped in ms beside ranges in s spans a thousand times the measurements; the
    ranges in ms beside inputs in s, a thousand times the inputs. A truth of one second in a
    20 s log is a short truth, not a unit."""
    from quadobs.testbed.logs import read_log

    log = _imu_body_log(False)
    with pytest.raises(
        QuadobsError, match=r"imu.csv spans 2e\+04 s, 10\d\d times the measurements'"
    ):
        dataclasses.replace(log, inputs=log.inputs * [1000, 1, 1, 1, 1, 1, 1])
    with pytest.raises(QuadobsError, match=r"ranges.csv spans 1.998e\+04 s, 999 times imu.csv's"):
        dataclasses.replace(log, ranges=log.ranges * [1000, 1, 1], range_std=None)
    short = dataclasses.replace(log, truth=log.truth[log.truth[:, 0] < 1.0])
    assert read_log(write_log(short, tmp_path / "short-truth")).truth.shape[0] == 200


def test_an_attitude_that_jumps_where_the_rates_do_not_is_left_as_it_is():
    """A level hover whose attitude.csv jumps by 0.2 rad in yaw twice (an on-board filter's
    resets) and jitters by 2 degrees per axis (a noisy attitude), the rates right but for a
    bias of 0.2 rad/s about z: the attitude turns where the rates do not, and the rates where
    the attitude does not, which says nothing of the rates' unit or axes."""
    log = _imu_body_log(True)
    log = dataclasses.replace(log, inputs=log.inputs + [0, 0, 0, 0, 0, 0, 0.2])
    t = log.attitude[:, 0]
    rng = np.random.default_rng(7)
    yaw = 0.2 * ((t > 5.0).astype(float) + (t > 12.0))
    jitter = np.radians(2.0) * rng.standard_normal((t.size, 3))
    R = Rotation.from_euler("z", yaw[:, None]) * Rotation.from_rotvec(jitter)
    check_body_imu(
        dataclasses.replace(log, attitude=np.column_stack([t, R.as_quat()[:, [3, 0, 1, 2]]]))
    )


def test_a_long_imu_beside_a_short_recording_is_not_taken_for_milliseconds(tmp_path):
    """An IMU logged from power-up, 120 times the ranges' span, in seconds both: accepted (it
    samples every 5 ms and covers the ranges); TDOA in ms beside an IMU in s is named as TDOA;
    a truth of 4 s stamped in ms (200 times the measurements' span, a row every 5 "s") and a
    5 s IMU in microseconds are refused."""
    log = _imu_body_log(False)
    t = np.arange(-2380.0, 20.0, 0.005)
    inputs = np.vstack(
        [
            np.column_stack([t[t < 0.0], np.tile(log.inputs[0, 1:], ((t < 0.0).sum(), 1))]),
            log.inputs,
        ]
    )
    dataclasses.replace(log, inputs=inputs)  # accepted
    tdoa = np.column_stack(
        [
            log.ranges[:, 0] * 1000.0,
            log.ranges[:, 1],
            (log.ranges[:, 1] + 1) % 5,
            0 * log.ranges[:, 0],
        ]
    )
    with pytest.raises(QuadobsError, match=r"tdoa.csv spans 1.998e\+04 s, 999 times imu.csv's"):
        dataclasses.replace(log, ranges=np.empty((0, 3)), range_std=None, tdoa=tdoa)
    truth = log.truth[log.truth[:, 0] < 4.0] * np.r_[1000.0, np.ones(6)]
    with pytest.raises(QuadobsError, match=r"truth.csv spans 3995 s, 200 times the measurements'"):
        dataclasses.replace(log, truth=truth)
    short = dataclasses.replace(
        log, truth=None, ranges=log.ranges[log.ranges[:, 0] < 5.0], range_std=None
    )
    imu = short.inputs[short.inputs[:, 0] < 5.0] * [1e6, 1, 1, 1, 1, 1, 1]
    with pytest.raises(QuadobsError, match=r"imu.csv spans .* microseconds: 1e6"):
        dataclasses.replace(short, inputs=imu)
    fast = np.arange(
        0.0, 20.0, 0.001
    )  # an IMU at 1 kHz in ms from the ranges' zero: a row a "second"
    imu_ms = np.column_stack([1000.0 * fast, np.tile(log.inputs[0, 1:], (fast.size, 1))])
    with pytest.raises(QuadobsError, match=r"imu.csv spans 2e\+04 s"):
        dataclasses.replace(log, inputs=imu_ms)


def _truth_attitude(log, q):
    """``log`` without attitude.csv, its truth holding the attitude ``q`` (rows qw, qx, qy, qz
    at the truth's times, which are the attitude's)."""
    columns = ("time", "x", "y", "z", "qw", "qx", "qy", "qz")
    truth = np.column_stack([log.truth[:, :4], q])
    return dataclasses.replace(log, attitude=None, truth=truth, truth_columns=columns)


def test_a_truth_attitude_that_the_rates_contradict_is_said_in_a_note():
    """The truth's quaternion as the IMU turns: nothing said; its conjugate (navigation to
    body) turns about the opposite axis, scalar last about another: each said, naming
    truth.csv and what it moves."""
    from quadobs.testbed.logs.replay import truth_attitude_note

    log = _imu_body_log(True, yaw_rate=0.2)
    q = log.attitude[:, 1:]
    assert truth_attitude_note(_truth_attitude(log, q)) is None
    note = truth_attitude_note(_truth_attitude(log, q * [1, -1, -1, -1]))
    assert note is not None and "turn about other axes (median cosine -1.00" in note
    assert note.startswith("imu-body: truth.csv: the body rates of imu.csv")
    assert note.endswith("It gives the TUM files' orientation")
    lever = dataclasses.replace(
        _truth_attitude(log, q[:, [1, 2, 3, 0]]), tag_x=0.0, tag_y=0.0, tag_z=0.0
    )
    note = truth_attitude_note(lever)
    assert note is not None and "moves the truth to the stated tag and gives" in note


def test_rows_of_an_imu_at_its_full_scale_are_left_out_and_said():
    """Three bursts of 0.1 s of a vibration beyond 16 g and 2000 deg/s, read at the sensors'
    full scales (an int16's 32767 / 32768 of it, a calibration's 1.005 on the rates): those
    rows are left out with a note, and the rates are then within any gyroscope's range. An
    accelerometer clipped at 1 g (no sensor's full scale), or peaking once at 16 g, keeps its
    rows."""
    from quadobs.testbed.logs.replay import replayable_log, without_clipped_inputs

    log = _imu_body_log(True, yaw_rate=0.2)
    t = log.inputs[:, 0]
    burst = ((t >= 5.0) & (t < 5.1)) | ((t >= 9.0) & (t < 9.1)) | ((t >= 14.0) & (t < 14.1))
    sign = np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)[burst, None]
    imu = log.inputs.copy()
    accel, rate = 16 * G * 32767 / 32768, np.radians(2000.0) * 32767 / 32768
    imu[burst, 1:4] = np.clip(imu[burst, 1:4] + 245.0 * sign, -accel, accel)
    imu[burst, 4:7] = 1.005 * np.clip(imu[burst, 4:7] + 50.0 * sign, -rate, rate)
    clipped = dataclasses.replace(log, inputs=imu)
    with pytest.raises(QuadobsError, match="beyond any MEMS gyroscope's range"):
        check_body_imu(clipped)
    back, notes = replayable_log(clipped)
    assert notes[0] == (
        f"imu.csv: {burst.sum()} rows at a sensor's full scale (ax at 156.902 and -156.902, ay "
        "at 156.902 and -156.902, az at 156.902 and -156.902, gx at 35.08 and -35.08, gy at "
        "35.08 and -35.08, gz at 35.08 and -35.08: readings beyond its range either way), left "
        "out: the row before each held across"
    )
    np.testing.assert_array_equal(back.inputs, log.inputs[~burst])
    check_body_imu(back)
    one_g = log.inputs.copy()
    one_g[:, 3] = np.minimum(one_g[:, 3], G)  # level at rest reads g: a pile at 1 g
    assert (one_g[:, 3] == G).sum() > 1000
    one_g_log = dataclasses.replace(log, inputs=one_g)
    assert without_clipped_inputs(one_g_log) == (one_g_log, None)
    below = log.inputs.copy()  # a vibration about the specific force, cut at -2 g alone
    below[burst, 3] = np.maximum(below[burst, 3] - 40.0 * (sign[:, 0] > 0), -2 * G)
    one_side = dataclasses.replace(log, inputs=below)
    same, note = without_clipped_inputs(one_side)
    assert same is one_side and note == (
        "imu.csv: rows at a sensor's full scale on one side (az at -19.6133), kept: left out, "
        "the other side's rows would bias the mean further"
    )
    peak = log.inputs.copy()
    peak[100, 1] = 16 * G
    peak_log = dataclasses.replace(log, inputs=peak)
    assert without_clipped_inputs(peak_log) == (peak_log, None)
