"""The Crazyflie's on-board EKF replaying a body-IMU log: the raw IMU in time, the log's attitude and
frame, its noise from the stated intensities, and a planar log refused in one line."""

import dataclasses
import math

import numpy as np
import pytest
from test_replay_in_time import _imu_body_log, _tdoa_log  # the logs of the replay in time's tests

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.logs import write_log
from quadobs.testbed.logs.estimators import (
    UNKNOWN_YAW_STD,
    ReplaySetup,
    build_onboard_ekf,
    log_frame,
)
from quadobs.testbed.logs.replay import run_replay


def _replay(log):
    s = run_replay(
        log, estimators=["onboard-ekf"], initial_offset=3.0, batch=False,
        setup_options={"range_sigma": 0.05}, burn_in=5.0,
    )  # fmt: skip
    assert s["ranges"]["in_time"] == ["onboard-ekf"]
    return s["estimators"]["onboard-ekf"]


@pytest.mark.parametrize("with_attitude", [True, False])
def test_it_converges_on_a_turning_body_imu_log(with_attitude):
    """3 m off at the start; the body turns at 0.2 rad/s (with no attitude.csv: from heading zero)."""
    e = _replay(_imu_body_log(with_attitude, yaw_rate=0.2))
    assert e["rmse"] < 0.1 and e["final_position_error"] < 0.1, e


def test_a_ned_log_takes_gravity_along_plus_z():
    """The log turned by pi about x (z down) and declared ned converges; declared enu, gravity
    points the wrong way: the attitude given does not keep it vertical, and the log is refused
    saying so (it was replayed, off by metres between ranges)."""
    log = _imu_body_log(True, yaw_rate=0.2)
    M = np.diag([1.0, -1.0, -1.0])
    inputs, truth, attitude = log.inputs.copy(), log.truth.copy(), log.attitude.copy()
    inputs[:, 1:4] @= M
    inputs[:, 4:7] @= M
    truth[:, 1:4] @= M
    truth[:, 4:7] @= M
    attitude[:, 3:5] *= -1.0  # M R M: (qw, qx, -qy, -qz)

    def turned(frame):
        return dataclasses.replace(
            log, beacons=log.beacons @ M, inputs=inputs, truth=truth, attitude=attitude,
            frame=frame,
        )  # fmt: skip

    assert _replay(turned("ned"))["rmse"] < 0.1
    with pytest.raises(QuadobsError, match=r"does not keep gravity vertical .* meta.csv's frame"):
        _replay(turned("enu"))


def test_noise_and_initial_attitude_from_the_setup():
    """Over one IMU interval ``h`` from a zero covariance the velocity gains ``q_imu h``; without
    attitude.csv the attitude starts at the IMU's alignment with the wide yaw prior, with it at
    its first sample."""
    log = _imu_body_log(True, yaw_rate=0.2)
    h = 0.005
    for with_attitude in (True, False):
        fields = log_frame(log if with_attitude else dataclasses.replace(log, attitude=None))
        assert fields["imu_period"] == pytest.approx(h)
        setup = ReplaySetup(
            log.beacons, 0.1, "imu", 0.0, 3.0, q_imu=0.04, input_kind="imu_body", **fields
        )
        est = build_onboard_ekf(setup, np.zeros(6))
        assert est.replay_input == "imu_body"
        yaw_var = est.P[8, 8]
        if with_attitude:
            assert np.allclose(est.attitude, np.eye(3), atol=1e-12)  # the first sample is level
        else:  # the alignment: the circle's centripetal 0.18 m/s^2 read as a pitch of 0.018 rad
            tilt = math.acos(est.attitude[2, 2])
            assert tilt == pytest.approx(0.18 / 9.80665, rel=0.05)
        assert yaw_var == pytest.approx((0.05 if with_attitude else UNKNOWN_YAW_STD) ** 2)
        est.P[:] = 0.0
        est.hold(np.r_[est.attitude.T @ [0.0, 0.0, 9.80665], 0.0, 0.0, 0.0])
        est.predict(h)
        np.testing.assert_allclose(est.P[3:6, 3:6], 0.04 * h * np.eye(3), rtol=1e-12)
        np.testing.assert_allclose(est.x_hat, 0.0, atol=1e-12)  # hovering: f balances gravity
    turned = dataclasses.replace(log, attitude=log.attitude[100:])  # starts at yaw 0.2 * 0.5 s
    fields = log_frame(turned)
    setup = ReplaySetup(log.beacons, 0.1, "imu", 0.0, 3.0, input_kind="imu_body", **fields)
    R = build_onboard_ekf(setup, np.zeros(6)).attitude
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(0.1, abs=1e-12)


def test_a_planar_log_is_refused_in_one_line_before_calibration(tmp_path, capsys):
    folder = write_log(_tdoa_log(), tmp_path / "planar")
    assert main(["replay", str(folder), "--no-progress", "--estimators", "onboard-ekf"]) == 2
    out, err = capsys.readouterr()
    errors = [line for line in err.splitlines() if line.startswith("quadobs: error")]
    assert len(errors) == 1 and "'onboard-ekf' needs a 3-D body-IMU log" in errors[0]
    assert errors[0].endswith("the log has a planar geometry") and "calibrated" not in out
    ranges_alone = ReplaySetup(np.eye(3), 0.1, "cv", 0.0, 1.0, input_kind="none")
    with pytest.raises(QuadobsError, match="inputs of kind 'none'"):
        build_onboard_ekf(ranges_alone, np.zeros(6))


def test_a_forward_right_down_body_starts_the_right_way_up():
    """The body axes forward-right-down (y and z of the IMU negated: ``az = -g`` at rest) and no
    attitude.csv: the initial alignment turns the filter upside down from the start; started
    level it would take gravity for an upward 2 g and fly off."""
    log = _imu_body_log(False, yaw_rate=0.2)
    imu = log.inputs.copy()
    imu[:, [2, 3, 5, 6]] *= -1.0
    frd = dataclasses.replace(log, inputs=imu)
    assert log_frame(frd)["alignment0"] == pytest.approx([0.0, 1.0, 0.0, 0.0], abs=0.02)
    assert _replay(frd)["rmse"] < 0.1
