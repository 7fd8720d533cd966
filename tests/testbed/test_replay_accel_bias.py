"""The accelerometer's bias as a state of the on-board EKF (``onboard-ekf-bias``) on a body-IMU log."""

import dataclasses

import numpy as np
import pytest
from test_replay_in_time import _imu_body_log  # the body-IMU log of the replay in time's tests

from quadobs.testbed.logs.estimators import ReplaySetup, build_onboard_ekf_bias, log_frame
from quadobs.testbed.logs.events import LogEvents
from quadobs.testbed.logs.replay import run_replay

BIAS = np.array([0.3, -0.2, 0.25])  # m/s^2, body frame


def _biased_log(bias=BIAS):
    log = _imu_body_log(True, yaw_rate=0.2)
    inputs = log.inputs.copy()
    inputs[:, 1:4] += bias
    return dataclasses.replace(log, inputs=inputs)


def test_a_constant_accelerometer_bias_is_recovered():
    """From the true start with the log's attitude: the bias, turning with the body at 0.2 rad/s
    while the ranges fix the path."""
    log = _biased_log()
    setup = ReplaySetup(
        log.beacons, 0.1, "imu", 0.0, 3.0, range_sigma=0.05, P0=0.01, input_kind="imu_body",
        **log_frame(log),
    )  # fmt: skip
    x0 = np.concatenate([log.truth[0, 1:4], log.truth[0, 4:7]])
    est = build_onboard_ekf_bias(setup, x0)
    events = LogEvents(log, start=log.start, end=log.end, std=setup.measurement_std())
    t_in, U = events.inputs(raw=True)
    est.time = t_in[0]
    est.hold(U[0])
    i = 1
    for m in events.measurements:
        while i < t_in.size and t_in[i] <= m.t:
            est.predict(t_in[i])
            est.hold(U[i])
            i += 1
        est.predict(m.t)
        est.correct(m)
    err = est.accel_bias - BIAS
    std = np.sqrt(np.diag(est.P)[9:])
    assert np.all(np.abs(err) < 3.0 * std), (err, std)  # consistent with its own covariance
    assert abs(err[2]) < 0.02  # along the thrust: the height fixes it
    # across: a tilt of the attitude looks the same until the body has turned; 20 s at 0.2 rad/s
    assert np.linalg.norm(err[:2]) < 0.5 * np.linalg.norm(BIAS[:2])


@pytest.mark.parametrize("bias", [BIAS, np.zeros(3)])
def test_the_bias_state_removes_the_error_a_bias_adds(bias):
    s = run_replay(
        _biased_log(bias), estimators=["onboard-ekf", "onboard-ekf-bias"], initial_offset=3.0,
        batch=False, setup_options={"range_sigma": 0.05}, burn_in=5.0,
    )  # fmt: skip
    plain, with_bias = (s["estimators"][n]["rmse"] for n in ("onboard-ekf", "onboard-ekf-bias"))
    if bias.any():  # biased: clearly better; unbiased: no worse than 5 %
        assert with_bias < 0.75 * plain, (plain, with_bias)
    else:
        assert with_bias < 1.05 * plain, (plain, with_bias)
