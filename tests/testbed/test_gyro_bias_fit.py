"""The AHRS's gyroscope bias from the ranges (:func:`quadobs.testbed.attitude.gyro_bias_from_ranges`):
a log begun while the body turns gives the initial alignment a rate that is not the bias; the
ranges' accelerations tell the bias the AHRS should start from."""

import numpy as np
from scipy.spatial.transform import Rotation

from quadobs.testbed.attitude import (
    _navigation,
    gyro_bias_from_ranges,
    initial_alignment,
)
from quadobs.testbed.logs import RangeLog

G = 9.80665
ANCHORS = np.array(
    [[-4, -4, 0.2], [4, -4, 2.8], [4, 4, 0.2], [-4, 4, 2.8], [0, -5, 1.5], [5, 0, 0.5], [0, 5, 2.5], [-5, 0, 1.0]],
    dtype=float,
)  # fmt: skip
BIAS = np.array([0.015, -0.01, 0.0])  # the gyroscope's (rad/s)


def _hover_log(seconds=30.0, rate=100.0, seed=0, turn=0.03):
    """A body hovering at (0, 0, 1.5) m whose first 0.5 s rolls at ``turn`` rad/s (and rolls back
    at once): its IMU (noise 0.05 m/s^2, 0.005 rad/s; the gyroscope's bias :data:`BIAS`) and
    ranges of 0.05 m to eight anchors in turn at 100 Hz. The alignment's median rate is then
    the bias plus the roll's 0.03 rad/s."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate)
    roll_rate = np.where(t < 0.5, turn, 0.0)
    roll_rate[(t >= 0.5) & (t < 0.55)] = -10.0 * turn  # back to level
    roll = np.cumsum(roll_rate) / rate
    R = Rotation.from_euler("x", roll[:, None])
    f = R.inv().apply(np.tile([0.0, 0.0, G], (t.size, 1))) + 0.05 * rng.standard_normal((t.size, 3))
    w = np.column_stack([roll_rate, 0 * t, 0 * t]) + BIAS + 0.005 * rng.standard_normal((t.size, 3))
    k = np.arange(t.size) % ANCHORS.shape[0]
    r = np.linalg.norm([0.0, 0.0, 1.5] - ANCHORS[k], axis=1) + 0.05 * rng.standard_normal(t.size)
    truth = np.column_stack([t, 0 * t, 0 * t, 0 * t + 1.5])
    return RangeLog(
        "hover", np.arange(8), ANCHORS, np.column_stack([t, k, r]), np.column_stack([t, f, w]),
        float("nan"), input_kind="imu_body", truth=truth, truth_columns=("time", "x", "y", "z"),
    )  # fmt: skip


def test_the_ranges_tell_the_bias_that_the_alignment_missed():
    log = _hover_log(seconds=20.0)
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    b0 = initial_alignment(t, f, w, G)[1]
    assert abs(b0[0] - BIAS[0] - 0.03) < 0.005  # the roll taken for a bias
    fitted = gyro_bias_from_ranges(log, _navigation(log, b0))
    assert fitted is not None
    np.testing.assert_allclose(fitted[:2], BIAS[:2], atol=0.004)
    # the acceleration (a hover: zero) from the alignment's bias and from the fitted one
    late = t > 10.0
    before = np.abs(_navigation(log, b0)[late, 1:3]).mean()
    after = np.abs(_navigation(log, fitted)[late, 1:3]).mean()
    assert before > 0.5 and after < before / 5  # 1.0 and 0.045 m/s^2


def test_an_alignment_at_rest_is_kept_where_the_ranges_say_no_better():
    """The body stands still from the start: the alignment's rate is the bias, and the ranges
    keep it or move it by no more than their noise allows."""
    log = _hover_log(seconds=20.0, seed=1, turn=0.0)
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    b0 = initial_alignment(t, f, w, G)[1]
    fitted = gyro_bias_from_ranges(log, _navigation(log, b0))
    chosen = b0 if fitted is None else fitted
    np.testing.assert_allclose(chosen[:2], BIAS[:2], atol=0.004)


def test_the_fit_is_tried_only_where_the_start_is_not_a_rest(monkeypatch):
    """``navigation_accelerations`` keeps the alignment's bias where the log's start is a rest
    (the start prior's ``at_rest``) and asks the ranges otherwise."""
    from quadobs.testbed import attitude

    asked = []
    monkeypatch.setattr(attitude, "gyro_bias_from_ranges", lambda log, nav: asked.append(1))
    for at_rest, expected in ((True, []), (False, [1])):
        asked.clear()
        log = _hover_log(seconds=3.0)
        monkeypatch.setattr(RangeLog, "starts_at_rest", lambda self, v=at_rest: v)
        attitude.navigation_accelerations(log)
        assert asked == expected


def test_an_ahrs_rate_that_is_not_positive_is_refused():
    import pytest

    from quadobs.errors import QuadobsError
    from quadobs.testbed.attitude import estimate_attitude

    log = _hover_log(seconds=1.0)
    t, f, w = log.inputs[:, 0], log.inputs[:, 1:4], log.inputs[:, 4:7]
    for rate in (0.0, -5.0, float("nan")):
        with pytest.raises(QuadobsError, match="AHRS rate"):
            estimate_attitude(t, f, w, G, rate=rate)
