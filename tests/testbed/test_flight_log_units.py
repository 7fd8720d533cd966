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


def _refused(tmp_path, capsys, log) -> str:
    folder = write_log(log, tmp_path / "flight")
    assert main(["replay", str(folder), "--no-progress"]) == 2
    out, err = capsys.readouterr()
    errors = [line for line in err.splitlines() if line.startswith("quadobs: error")]
    assert len(errors) == 1 and "calibrated" not in out, (out, err)
    assert f"{folder}/imu.csv" in errors[0]
    return errors[0]


def test_an_accelerometer_in_g_is_refused_naming_the_file_and_columns(tmp_path, capsys):
    error = _refused(tmp_path, capsys, _scaled(_imu_body_log(False), accel=1.0 / G))
    assert "columns ax,ay,az: the median |a| is 1, " in error and "in g" in error
    check_body_imu(_imu_body_log(False))  # in m/s^2: accepted


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
