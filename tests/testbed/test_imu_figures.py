"""The IMU's stated error figures in ``meta.csv`` (``accel_bias``, ``gyro_bias``,
``attitude_std``): written and read back, checked, and sized into the replay's ``q_imu`` by the
live filters' rule (:func:`quadobs.testbed.imu.input_noise_std`)."""

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog, read_log, write_log
from quadobs.testbed.logs.estimators import ACCEL_NOISE, imu_input_noise, log_defaults

ANCHORS = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 3.0], [6.0, 6.0, 0.0], [0.0, 6.0, 3.0]])


def _log(h: float = 0.002, attitude_every: int = 5, **extra) -> RangeLog:
    """A hover: a body IMU every ``h`` s, an attitude every ``attitude_every`` IMU samples."""
    t = np.arange(0.0, 2.0, h)
    f = np.tile([0.0, 0.0, 9.8], (t.size, 1))
    p = np.tile([3.0, 3.0, 1.5], (t.size, 1))
    k = np.arange(t.size) % 4
    ranges = np.column_stack([t, k, np.linalg.norm(p - ANCHORS[k], axis=1)])
    ta = t[::attitude_every]
    attitude = np.column_stack([ta, np.ones_like(ta), np.zeros((ta.size, 3))])
    return RangeLog(
        "hover", np.arange(4), ANCHORS, ranges, np.column_stack([t, f, 0 * f]), float("nan"),
        np.column_stack([t, p]), input_kind="imu_body", truth_columns=("time", "x", "y", "z"),
        attitude=attitude, gravity=9.8, **extra,
    )  # fmt: skip


def test_the_imu_figures_round_trip_through_meta_csv(tmp_path):
    stated = _log(accel_noise=1e-3, accel_bias=0.02, gyro_bias=0.0, attitude_std=0.01)
    back = read_log(write_log(stated, tmp_path / "s"))
    assert (back.accel_bias, back.gyro_bias, back.attitude_std) == (0.02, 0.0, 0.01)
    meta = (tmp_path / "s" / "meta.csv").read_text()
    assert "accel_bias,0.02" in meta and "gyro_bias,0.0" in meta  # a stated zero is kept
    plain = read_log(write_log(_log(), tmp_path / "p"))
    assert all(math.isnan(getattr(plain, k)) for k in ("accel_bias", "gyro_bias", "attitude_std"))
    assert "bias" not in (tmp_path / "p" / "meta.csv").read_text()


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("accel_bias,-0.1", "meta.csv, row 3, key accel_bias: '-0.1' is not a non-negative finite"),
        ("attitude_std,nan", "key attitude_std: 'nan' is not a non-negative finite number"),
    ],
)
def test_a_bad_imu_figure_is_named(tmp_path, row, message):
    folder = write_log(_log(), tmp_path / "log")
    meta = folder / "meta.csv"
    lines = meta.read_text().splitlines()
    meta.write_text("\n".join([*lines[:2], row, *lines[2:]]) + "\n")
    with pytest.raises(QuadobsError, match=message):
        read_log(folder)


def test_q_imu_is_the_live_rule_on_the_stated_figures():
    """``q = N_a^2 + m h (g sigma_q)^2 + b^2 tau``: here m h = 0.01 s, g = 9.8, tau = 1 s."""
    stated = _log(accel_noise=1e-3, accel_bias=0.02, attitude_std=0.01)
    expected = 1e-6 + 0.01 * (9.8 * 0.01) ** 2 + 0.02**2
    assert imu_input_noise(stated) == pytest.approx(expected, rel=1e-12)
    assert log_defaults(stated) == {"q_imu": pytest.approx(expected, rel=1e-12)}
    # no attitude error stated (or no attitude.csv): that term is zero; no density: zero
    assert imu_input_noise(_log(accel_noise=1e-3, accel_bias=0.02)) == pytest.approx(4.01e-4)
    assert imu_input_noise(_log(accel_bias=0.0, attitude_std=0.01)) == pytest.approx(9.604e-5)
    # figures that give zero (an IMU stated perfect): not a filter's noise; the default stands
    assert imu_input_noise(_log(accel_bias=0.0, attitude_std=0.0)) is None
    # a density without a bias: its square, floored; nothing stated: no default of the log
    assert imu_input_noise(_log(accel_noise=1e-3, attitude_std=0.01)) == ACCEL_NOISE
    assert imu_input_noise(_log()) is None and log_defaults(_log()) == {}


def test_the_ranges_error_model_round_trips_and_sets_the_bias_filters_gate(tmp_path):
    from quadobs.estimators.robust import SkewedGate
    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        _typical_range,
        build_replay_estimators,
        log_frame,
    )

    stated = read_log(write_log(_log(range_errors="gaussian"), tmp_path / "s"))
    plain = read_log(write_log(_log(), tmp_path / "p"))
    assert (stated.range_errors, plain.range_errors) == ("gaussian", "")
    assert "range_errors" not in (tmp_path / "p" / "meta.csv").read_text()
    x0 = np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0]
    rules = {}
    for key, log, options in (
        ("gaussian", stated, {}),
        ("unknown", plain, {}),
        ("gaussian, gate asked", stated, {"gate": 6.6}),
    ):
        setup = ReplaySetup(
            log.beacons, 0.01, "imu", 0.0, _typical_range(log), input_kind=log.input_kind,
            **log_frame(log), **options,
        )  # fmt: skip
        est = build_replay_estimators(setup, ["ekf-bias", "ukf-bias"], x0)
        rules[key] = [e.robust for e in est]
    assert rules["gaussian"] == [None, None]  # as the live filters of a scenario without a radio
    assert all(isinstance(r, SkewedGate) for r in rules["unknown"] + rules["gaussian, gate asked"])


def test_the_bias_filters_take_the_stated_range_noise():
    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        _typical_range,
        build_replay_estimators,
        log_frame,
    )

    x0 = np.r_[3.0, 3.0, 1.5, 0.0, 0.0, 0.0]
    base = _log()
    std = np.full(base.ranges.shape[0], 0.1)
    std[::3] = 0.2  # median 0.1
    for log, sigma in ((_log(range_std=std), 0.1), (base, 0.7)):
        setup = ReplaySetup(
            log.beacons, 0.01, "imu", 0.0, _typical_range(log), input_kind=log.input_kind,
            range_sigma=0.7, **log_frame(log),
        )  # fmt: skip
        for est in build_replay_estimators(setup, ["ekf-bias", "ukf-bias"], x0):
            np.testing.assert_allclose(est.outputs.R, sigma**2 * np.eye(4), rtol=1e-12)


def test_a_bad_range_error_model_is_named(tmp_path):
    folder = write_log(_log(), tmp_path / "log")
    meta = folder / "meta.csv"
    lines = meta.read_text().splitlines()
    meta.write_text("\n".join([*lines[:2], "range_errors,normal", *lines[2:]]) + "\n")
    with pytest.raises(QuadobsError, match="key range_errors: 'normal'; expected one of gaussian"):
        read_log(folder)


def test_a_log_built_in_memory_states_its_range_errors_as_a_read_one_does():
    assert _log(range_errors="Gaussian").range_errors == "gaussian"  # as read_log lowercases
    with pytest.raises(QuadobsError, match="range_errors: 'normal'; expected one of gaussian"):
        _log(range_errors="normal")
