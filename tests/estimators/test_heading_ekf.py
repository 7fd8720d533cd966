"""The heading and yaw-rate-bias filters of odometry logs: closed forms and noise-free recovery."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.estimators.heading_ekf import HeadingEKF, HeadingUKF, arc_points, arc_step
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.events import held_inputs
from quadobs.testbed.logs.replay import check_replay, run_replay

BEACONS = np.array([[-30.0, -20.0], [40.0, -25.0], [35.0, 30.0], [-25.0, 35.0]])
OMEGA, SPEED, RADIUS = 0.1, 1.5, 15.0


def circle_log(bias: float, heading_error: float, duration: float = 120.0) -> RangeLog:
    """A vehicle on a circle of radius 15 m at 1.5 m/s; its yaw rate read with ``bias``, its start
    heading stated ``heading_error`` off; noise-free ranges to each anchor in turn at 4 Hz."""
    t = np.arange(0.0, duration, 0.1)
    inputs = np.column_stack([t, np.full_like(t, SPEED), np.full_like(t, OMEGA + bias)])
    tr = np.arange(0.05, duration - 0.1, 0.25)
    h = np.arange(tr.size) % 4
    p = RADIUS * np.column_stack([np.cos(OMEGA * tr), np.sin(OMEGA * tr)])
    ranges = np.column_stack([tr, h, np.linalg.norm(p - BEACONS[h], axis=1)])
    truth = np.column_stack([t, RADIUS * np.cos(OMEGA * t), RADIUS * np.sin(OMEGA * t)])
    return RangeLog(
        "circle", np.arange(4), BEACONS, ranges, inputs, math.pi / 2 + heading_error, truth
    )


def pass_through(f, log: RangeLog):
    """The filter ``f`` fed the log's held inputs and its ranges at their own times: yields each
    range after the correction by it."""
    tin, U = held_inputs(log)
    f.time = tin[0]
    f.hold(U[0])
    i = 1
    for m in log.measurements():
        while i < tin.size and tin[i] <= m.t:
            f.predict(tin[i])
            f.hold(U[i])
            i += 1
        f.predict(m.t)
        f.correct(m)
        yield m


def run_in_time(log: RangeLog, cls, P0, x0=(RADIUS, 0.0, 0.0, 0.0), **noise):
    """The filter fed the log's held inputs and its ranges at their own times."""
    f = cls(log.beacons, x0=x0, P0=P0, dt=0.1, heading0=log.heading0, **noise)
    for _ in pass_through(f, log):
        pass
    return f


NOISE = {"q_xy": 1e-6, "q_theta": 1e-8, "q_bias": 1e-10, "range_sigma": 0.05}


def test_arc_step_is_the_chord_of_the_arc_and_its_jacobian_is_exact():
    # a bias b turns the path at -b: a quarter circle of radius s / |b| in pi / (2 |b|) seconds
    x, _ = arc_step(np.array([0.0, 0.0, 0.0, -0.5]), np.array([1.0, 0.0, 0.3]), math.pi)
    np.testing.assert_allclose(x, [2.0, 2.0, math.pi / 2, -0.5], atol=1e-12)
    # no bias: a straight line along the corrected heading
    x, _ = arc_step(np.array([1.0, 2.0, 0.3, 0.0]), np.array([0.0, 2.0, 0.0]), 0.5)
    np.testing.assert_allclose(x[:2], [1.0 - math.sin(0.3), 2.0 + math.cos(0.3)], atol=1e-12)
    # the Jacobian against central differences, with a bias and without
    for b in (0.0, 0.4):
        x0 = np.array([1.0, -2.0, 0.7, b])
        u = np.array([1.2, -0.4, 0.1])
        _, F = arc_step(x0, u, 0.8)
        eps = 1e-6
        num = np.column_stack(
            [
                (arc_step(x0 + e, u, 0.8)[0] - arc_step(x0 - e, u, 0.8)[0]) / (2 * eps)
                for e in eps * np.eye(4)
            ]
        )
        np.testing.assert_allclose(F, num, atol=1e-8)


@pytest.mark.parametrize("cls", [HeadingEKF, HeadingUKF])
def test_a_known_gyro_bias_is_recovered(cls):
    log = circle_log(bias=0.01, heading_error=0.0)
    f = run_in_time(log, cls, [1.0, 1.0, 0.01, 1e-3], **NOISE)
    assert abs(f.gyro_bias - 0.01) < 1e-5
    heading = math.pi / 2 + OMEGA * f.time
    assert abs(math.remainder(f.heading - heading, 2 * math.pi)) < 1e-4
    truth = RADIUS * np.array([math.cos(OMEGA * f.time), math.sin(OMEGA * f.time)])
    assert np.linalg.norm(f.x_hat - truth) < 1e-3
    assert f.corrections == len(log.measurements()) and f.rejected == 0


@pytest.mark.parametrize("cls", [HeadingEKF, HeadingUKF])
def test_the_heading_converges_from_a_wrong_start_heading(cls):
    log = circle_log(bias=-0.02, heading_error=-0.5)  # stated 0.5 rad off, and a bias
    f = run_in_time(log, cls, [1.0, 1.0, 0.5**2, 1e-3], **NOISE)
    heading = math.pi / 2 + OMEGA * f.time
    assert abs(math.remainder(f.heading - heading, 2 * math.pi)) < 1e-4
    assert abs(f.gyro_bias + 0.02) < 1e-5
    # the dead reckoning alone ends far off: the start heading's error turns the whole circle
    assert abs(math.remainder(f.theta_o - heading, 2 * math.pi)) > 0.5


@pytest.mark.parametrize("cls", [HeadingEKF, HeadingUKF])
def test_a_prior_as_wide_as_the_anchors_is_replaced_by_a_multilateration(cls):
    # 50 m off with a 50 m prior: one round of ranges sets the position, then the heading converges
    log = circle_log(bias=0.01, heading_error=-0.3)
    P0 = [2500.0, 2500.0, 0.3**2, 1e-3]
    assert cls(log.beacons, x0=[45.0, 40.0, 0.0, 0.0], P0=P0, dt=0.1, **NOISE).fix_pending
    f = run_in_time(log, cls, P0, x0=(RADIUS + 30.0, 40.0, 0.0, 0.0), **NOISE)
    assert len(f.fixes) == 1 and f.fixes[0] < 1.5  # one round of four ranges at 4 Hz
    truth = RADIUS * np.array([math.cos(OMEGA * f.time), math.sin(OMEGA * f.time)])
    assert np.linalg.norm(f.x_hat - truth) < 1e-2
    assert abs(f.gyro_bias - 0.01) < 1e-3
    # a prior narrower than half the anchors' extent is kept
    g = cls(log.beacons, x0=[RADIUS, 0.0, 0.0, 0.0], P0=[1.0, 1.0, 0.1, 1e-3], dt=0.1, **NOISE)
    assert not g.fix_pending


@pytest.mark.parametrize("cls", [HeadingEKF, HeadingUKF])
@pytest.mark.parametrize("stated", [0.05, math.nan])
def test_the_fix_takes_the_variance_of_the_ranges_it_was_made_of(cls, stated):
    # ranges stating their std (0.05 m) under a setup prior of 1 m: the fix's covariance is made
    # of the stated std, not the prior's; ranges stating none take the prior
    log = circle_log(bias=0.0, heading_error=0.0)
    noise = {**NOISE, "range_sigma": 1.0}
    f = cls(log.beacons, x0=[45.0, 40.0, 0.0, 0.0], P0=[2500.0, 2500.0, 0.1, 1e-3], dt=0.1, **noise)
    f.time = 0.0
    f.hold(np.array([SPEED, 0.0, OMEGA]))
    for m in log.measurements():
        f.predict(m.t)
        f.correct(dataclasses.replace(m, std=stated))
        if f.fixes:
            break
    sigma = 1.0 if math.isnan(stated) else stated
    assert len(f.fixes) == 1
    # the centred least squares of y_h = rho_h^2 / 2 - |a_h|^2 / 2, each of variance
    # rho_h^2 sigma^2 + sigma^4 / 2: M G diag(v) G^T M^T (M G = M, the columns of D centred)
    rho2 = 2.0 * f._latest + np.sum(BEACONS**2, axis=1)
    M = np.linalg.pinv(BEACONS.mean(axis=0) - BEACONS)
    expected = (M * (rho2 * sigma**2 + sigma**4 / 2)) @ M.T
    np.testing.assert_allclose(f.state_covariance[:2, :2], expected, rtol=1e-10)


def test_the_replay_runs_them_on_an_odometry_log_and_refuses_other_logs(tmp_path):
    log = circle_log(bias=0.01, heading_error=0.05, duration=40.0)
    options = {"range_sigma": 0.05, "q_xy": 1e-3, "q_xy_heading": 1e-3}
    names = ["ekf-heading", "ukf-heading", "augmented-heading", "augmented", "ekf"]
    s = run_replay(log, estimators=names, initial_offset=5.0, setup_options=options, batch=False)
    est = s["estimators"]
    for name in names[:3]:  # the heading estimated beats the heading taken as known
        assert est[name]["final_position_error"] < 0.2
        assert est[name]["final_position_error"] < 0.5 * est["augmented"]["final_position_error"]
    # on the grid (a sensor layer acts on the rows) too
    grid = run_replay(
        log, estimators=names[:3], initial_offset=5.0, setup_options=options, batch=False,
        settings=["noise.dropout=0.1"],
    )  # fmt: skip
    assert grid["ranges"]["on_grid"] == names[:3]
    for name in names[:3]:
        assert grid["estimators"][name]["final_position_error"] < 0.3
    with pytest.raises(QuadobsError, match="'ekf-heading' needs a planar log with wheel odometry"):
        check_replay(log, ["ekf-heading"], model="cv")


def test_a_filter_whose_gate_rejects_everything_is_reinitialised_then_reported_diverged():
    log = circle_log(bias=0.0, heading_error=0.0, duration=60.0)
    f = run_in_time(log, HeadingEKF, [1.0, 1.0, 0.01, 1e-4], gate=1e-12, **NOISE)
    assert f.corrections == 0 and f.rejected == len(log.measurements())
    assert len(f.lockout.resets) == f.lockout.max_resets
    assert f.diverged is not None and "rejected" in f.diverged["reason"]


def test_the_cascade_turns_the_odometry_by_the_estimated_heading():
    from quadobs.core.immersion import immerse
    from quadobs.core.system import odometry_system
    from quadobs.estimators.augmented import AugmentedObserver
    from quadobs.estimators.heading_ekf import HeadingCascade

    im = immerse(odometry_system(BEACONS))
    obs = AugmentedObserver(im, 0.1, V=1e-3, W=0.05, z0=im.lift(np.zeros(2)))
    heading = HeadingEKF(BEACONS, x0=[0.0, 0.0, 0.3, 0.0], P0=np.ones(4), dt=0.1, **NOISE)
    cascade = HeadingCascade(obs, heading)
    cascade.hold([2.0, 0.0, 0.1])
    cascade.predict(1.0)  # no bias: the odometry's velocity turned by delta = 0.3 for 1 s
    np.testing.assert_allclose(cascade.x_hat, 2.0 * np.array([math.cos(0.3), math.sin(0.3)]))
    assert heading.theta_o == pytest.approx(0.1) and cascade.time == 1.0


def test_the_cascade_gives_its_observer_the_turned_inputs_error():
    """Over ``h`` with ``b = 0``: ``u' = R(delta) u_xy``, its error ``w e_delta`` with ``w = R(delta) J
    u_xy`` across the track, so the intensity written is ``h P_delta w w^T`` (the displacement's
    variance ``h^2 P_delta w w^T`` over the interval), and the observer's position covariance grows
    by it across the track only."""
    from quadobs.estimators.heading_ekf import HeadingCascade
    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        _noise_map,
        build_augmented,
        build_augmented_heading,
    )

    setup = ReplaySetup(BEACONS, 0.1, "odometry", 0.0, 30.0, q_xy=1e-4, P0=1.0)
    runs = {}
    for extra in (None, np.zeros((2, 2))):
        heading = HeadingEKF(BEACONS, x0=[0.0, 0.0, 0.3, 0.0], P0=[1, 1, 0.01, 0], dt=0.1, **NOISE)
        obs = build_augmented(setup, np.zeros(2))
        obs.noise_of = _noise_map(setup, obs.immersion, extra)
        cascade = HeadingCascade(obs, heading, input_noise=extra)
        cascade.time = 0.0
        cascade.hold([2.0, 0.0, 0.1])
        cascade.predict(0.5)
        runs[extra is None] = (extra, cascade.x_covariance)
    w = 2.0 * np.array([-math.sin(0.3), math.cos(0.3)])
    written, P = runs[False]
    np.testing.assert_allclose(written, 0.5 * 0.01 * np.outer(w, w), rtol=1e-12, atol=1e-15)
    grown = P - runs[True][1]
    np.testing.assert_allclose(w @ grown @ w / (w @ w), 0.5**2 * 0.01 * (w @ w), rtol=1e-6)
    along = np.array([math.cos(0.3), math.sin(0.3)])
    assert abs(along @ grown @ along) < 1e-12
    assert build_augmented_heading(setup, np.zeros(2)).inner.range_variance == "larger"
    assert obs.range_variance == "measured"  # the plain observer keeps the measured range


def test_the_cascade_takes_a_range_read_short_with_the_predicted_ranges_variance(monkeypatch):
    """One range read at a fifth of its 26.7 m (noise-free circle, 0.05 m stated) at 30 s: with its
    variance at the measured range the cascade's observer takes it almost whole and is metres off
    for seconds; at the larger of the measured and the predicted range it stays within 2.5 m."""
    import dataclasses

    import quadobs.testbed.logs.estimators as E

    log = circle_log(bias=0.0, heading_error=0.0, duration=40.0)
    ranges = log.ranges.copy()
    k = int(np.searchsorted(ranges[:, 0], 30.0))
    ranges[k, 2] *= 0.2
    log = dataclasses.replace(log, ranges=ranges)
    figures = {}
    for mode in ("measured", "larger"):

        def build(s, x0, name="augmented-heading", mode=mode):
            est = E.build_augmented_heading(s, x0, name)
            est.inner.range_variance = mode
            return est

        monkeypatch.setitem(E.REPLAY_ESTIMATORS, "augmented-heading", build)
        summary = run_replay(
            log, estimators=["augmented-heading"], initial_offset=0.0, batch=False, burn_in=30.0,
            setup_options={"range_sigma": 0.05, "q_xy_heading": 1e-4, "q_theta": 1e-6},
        )  # fmt: skip
        figures[mode] = summary["estimators"]["augmented-heading"]["max_error"]
    assert figures["measured"] > 5.0
    assert figures["larger"] < 2.5


def test_an_odometry_log_gets_the_heading_filter_by_default_and_a_model_without_it_does_not():
    from quadobs.testbed.logs.replay import default_estimators

    log = circle_log(bias=0.0, heading_error=0.0, duration=5.0)
    names = ["augmented", "ekf", "ekf-bias", "ukf-heading", "augmented-heading"]
    planar = ["ekf-height", "augmented-height", "ukf-lever", "ukf-height-lever"]
    assert default_estimators(log) == [*names, *planar]
    assert not {"ukf-heading", "augmented-heading"} & set(default_estimators(log, "cv"))
    check_replay(log, [])  # the default set builds on the log
    check_replay(log, [], model="cv")  # and the one without the heading filter under cv


def s_curve(t: np.ndarray, lever_arm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vehicle turning left on a circle of radius 15 m for 60 s, then right on another
    (at 1.5 m/s): the yaw rate, the odometry's point ``p`` and the tag's ``p + R(theta) l``."""
    t1 = 60.0
    left = t < t1
    a = np.where(left, OMEGA * t, OMEGA * t1 + math.pi - OMEGA * (t - t1))
    centre = np.where(
        left[:, None], 0.0, 2 * RADIUS * np.array([math.cos(OMEGA * t1), math.sin(OMEGA * t1)])
    )
    p = centre + RADIUS * np.column_stack([np.cos(a), np.sin(a)])
    theta = np.where(left, OMEGA * t, 2 * OMEGA * t1 - OMEGA * t) + math.pi / 2
    lx, ly = lever_arm
    c, s = np.cos(theta), np.sin(theta)
    tag = p + np.column_stack([c * lx - s * ly, s * lx + c * ly])
    return np.where(left, OMEGA, -OMEGA), p, tag


@pytest.mark.parametrize("cls", [HeadingEKF, HeadingUKF])
def test_a_lever_arm_as_states_is_recovered_in_turns_and_the_tracked_point_reported(cls):
    lever = (0.12, -0.07)
    t = np.arange(0.0, 110.0, 0.1)
    omega, _, _ = s_curve(t + 0.05, lever)  # the yaw rate held over each interval
    inputs = np.column_stack([t, np.full_like(t, SPEED), omega])
    tr = np.arange(0.05, 109.9, 0.25)
    h = np.arange(tr.size) % 4
    _, p, tag = s_curve(tr, lever)
    ranges = np.column_stack([tr, h, np.linalg.norm(tag - BEACONS[h], axis=1)])
    log = RangeLog("s-curve", np.arange(4), BEACONS, ranges, inputs, math.pi / 2, None)
    P0 = [1.0, 1.0, 0.01, 1e-4]
    with_lever = run_in_time(log, cls, P0, lever_arm_std=0.2, **NOISE)
    without = run_in_time(log, cls, P0, **NOISE)
    _, p_end, _ = s_curve(np.array([with_lever.time]), lever)
    np.testing.assert_allclose(with_lever.lever_arm, lever, atol=2e-3)
    assert np.linalg.norm(with_lever.x_hat - p_end[0]) < 5e-3
    assert with_lever.state.shape == (6,) and np.all(without.lever_arm == 0.0)
    # without the lever arm's states the ranges place the tag, not the tracked point
    assert np.linalg.norm(without.x_hat - p_end[0]) > 0.05


def test_the_replay_runs_ukf_lever_in_time_and_on_the_grid_and_refuses_other_logs():
    log = circle_log(bias=0.01, heading_error=0.05, duration=40.0)  # no lever arm
    options = {"range_sigma": 0.05, "q_xy": 1e-3, "q_xy_heading": 1e-3}
    names = ["ukf-heading", "ukf-lever"]
    for settings in ((), ("noise.dropout=0.1",)):
        s = run_replay(
            log, estimators=names, initial_offset=5.0, setup_options=options, batch=False,
            settings=list(settings),
        )  # fmt: skip
        assert s["ranges"]["on_grid"] == (names if settings else [])
        err = {name: s["estimators"][name]["final_position_error"] for name in names}
        assert err["ukf-lever"] < 0.3 and err["ukf-lever"] < err["ukf-heading"] + 0.05
    with pytest.raises(QuadobsError, match="'ukf-lever' needs a planar log with wheel odometry"):
        check_replay(log, ["ukf-lever"], model="cv")


def test_a_lever_arm_beyond_its_prior_reports_the_filter_diverged():
    """An anchor's bias left in its ranges (1 m): the offset takes it up and leaves its prior's
    0.999 region; the replay reports ``ukf-lever`` diverged, its error figures withheld."""
    log = circle_log(bias=0.0, heading_error=0.0, duration=40.0)
    log.ranges[log.ranges[:, 1] == 0, 2] += 1.0
    options = {"range_sigma": 0.05, "q_xy": 1e-3, "q_xy_heading": 1e-3}
    s = run_replay(
        log, estimators=["ukf-lever"], initial_offset=0.0, setup_options=options, batch=False
    )
    entry = s["estimators"]["ukf-lever"]
    assert entry["diverged"] is not None and "lever arm" in entry["diverged"]["reason"]
    assert entry["rmse"] is None and entry["final_position_error"] is None


ROOM = np.array([[0.12, 0.10], [2.90, 0.16], [2.86, 2.28], [0.15, 2.31]])


def _numeric_jacobian(f, model, m, x, eps: float = 1e-6) -> list[float]:
    """``d h / d x`` of the filter's range model by central differences."""
    return [
        (f.linearized(model, m, x + eps * e)[0] - f.linearized(model, m, x - eps * e)[0])
        / (2 * eps)
        for e in np.eye(x.size)
    ]


def test_a_range_with_lever_arm_biases_and_offsets_and_its_jacobian_are_the_closed_forms():
    """``rho_h = sqrt(|p + R(theta_o + delta) l - a_h|^2 + 2 e_h) + b_h`` and its derivative by
    central differences, at a state off every prior mean."""
    from quadobs.core.measurements import Measurement, RangeModel

    f = HeadingEKF(
        ROOM, x0=[1.0, 1.0, 0.0, 0.0], P0=[1.0, 1.0, 0.01, 1e-4], dt=0.1, q_xy=1e-3,
        q_theta=1e-4, q_bias=1e-8, heading0=0.7, lever_arm_std=0.2, offsets=(1.5, 1.34),
        bias_std=0.5,
    )  # fmt: skip
    assert f.state.shape == (14,)
    assert np.all(f.offsets == 1.5) and np.all(f.range_biases == 0.0)
    x = np.array([1.3, 0.8, 0.2, 0.01, 0.1, -0.04, 0.1, 0.2, -0.1, 0.05, 0.02, 2.1, 0.3, 1.2])
    model = RangeModel(ROOM, 0.05)
    theta = 0.7 + x[2]
    tag = (
        x[:2]
        + np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
        @ x[4:6]
    )
    for h in range(4):
        m = Measurement(0.0, "range", 1.0, (h,), 0.05)
        z, H = f.linearized(model, m, x)
        expected = math.sqrt(np.sum((tag - ROOM[h]) ** 2) + 2 * x[10 + h]) + x[6 + h]
        assert z == pytest.approx(expected, rel=1e-12)
        np.testing.assert_allclose(H, _numeric_jacobian(f, model, m, x), atol=1e-8)
        assert H[6 + h] == 1.0 and H[10 + h] == pytest.approx(1.0 / (expected - x[6 + h]))


def room_s_curve(t: np.ndarray, lever_arm, radius: float = 0.6, omega: float = 0.5):
    """A robot in a 3.0 x 2.4 m room turning left on a circle of radius 0.6 m for one lap, then
    right on the next circle for one lap, and again (0.3 m/s): the yaw rate, ``p`` and the tag."""
    lap = 2 * math.pi / omega
    k = np.floor(t / lap).astype(int)
    left = k % 2 == 0
    tau = t - k * lap
    centres = np.array([[0.9, 1.2], [2.1, 1.2]])
    c = centres[np.where(left, 0, 1)]
    a = np.where(left, omega * tau, math.pi - omega * tau)  # both circles meet at (1.5, 1.2)
    p = c + radius * np.column_stack([np.cos(a), np.sin(a)])
    theta = np.where(left, a + math.pi / 2, a - math.pi / 2)
    cs, sn = np.cos(theta), np.sin(theta)
    lx, ly = lever_arm
    tag = p + np.column_stack([cs * lx - sn * ly, sn * lx + cs * ly])
    return np.where(left, omega, -omega), p, tag, theta


def test_a_lever_arm_and_the_anchors_biases_and_heights_are_recovered_together():
    """Noise-free 3-D ranges in a small room from a tag 0.1 m ahead of the tracked point, anchors
    0.05 to 2.05 m above it with biases of 0.05 to 0.15 m: the UKF with all three as states finds
    them and the tracked point; with the lever arm alone it cannot place the point."""
    lever, dz = (0.10, 0.03), np.array([0.05, 2.05, 0.80, 1.55])
    bias = np.array([0.10, 0.05, 0.15, 0.08])
    t = np.arange(0.0, 38.0, 0.1)
    omega = room_s_curve(t + 0.05, lever)[0]  # the yaw rate held over each interval
    inputs = np.column_stack([t, np.full_like(t, 0.3), omega])
    tr = np.arange(0.05, 37.9, 0.25)
    h = np.arange(tr.size) % 4
    tag = room_s_curve(tr, lever)[2]
    rho = np.sqrt(np.sum((tag - ROOM[h]) ** 2, axis=1) + dz[h] ** 2) + bias[h]
    log = RangeLog(
        "room", np.arange(4), ROOM, np.column_stack([tr, h, rho]), inputs, math.pi / 2, None
    )
    noise = {**NOISE, "range_sigma": 0.02}
    start = {"x0": (1.5, 1.2, 0.0, 0.0), "lever_arm_std": 0.2}
    P0 = [0.01, 0.01, 0.01, 1e-4]
    f = run_in_time(log, HeadingUKF, P0, offsets=(1.5, 1.34), bias_std=0.5, **start, **noise)
    lever_only = run_in_time(log, HeadingUKF, P0, **start, **noise)
    p_end = room_s_curve(np.array([f.time]), lever)[1][0]
    np.testing.assert_allclose(f.lever_arm, lever, atol=5e-3)
    np.testing.assert_allclose(f.offsets, dz**2 / 2, atol=0.03)
    np.testing.assert_allclose(f.range_biases, bias, atol=0.015)
    assert np.linalg.norm(f.x_hat - p_end) < 0.02
    assert np.linalg.norm(lever_only.x_hat - p_end) > 0.1


def test_the_points_map_is_the_arc_step_on_every_row():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(9, 8))
    X[0, 3] = 1e-6  # the series near b = 0
    u = np.array([0.4, 0.1, 0.3])
    expected = [np.r_[arc_step(x[:4], u, 0.05)[0], x[4:]] for x in X]
    np.testing.assert_allclose(arc_points(X, u, 0.05), expected, rtol=1e-13, atol=1e-15)


def test_the_filter_with_the_anchors_states_bounds_an_outliers_correction_by_hubers_rule():
    """``ukf-height-lever``'s rule: Huber's bound at the replay's gate (3.29 standard deviations of
    the innovation for the default 0.999); a range 1 m long at a stated 0.05 m corrects as with
    its variance multiplied by ``|r| / c`` (the closed form of the re-weighting), a range within
    the bound in full."""
    from types import SimpleNamespace

    from quadobs.core.measurements import Measurement, RangeModel
    from quadobs.testbed.logs.height_estimators import heading_height_options, huber_rule

    anchors = np.array([[0.12, 0.10], [2.90, 0.16], [2.86, 2.28], [0.15, 2.31]])
    setup = SimpleNamespace(kinds=("range",), dim=2, beacons=anchors, range_sigma=1.0, gate=None)
    rule = heading_height_options(setup, "ukf-height-lever", excess=False)["robust"]
    assert rule.c == pytest.approx(math.sqrt(10.828), abs=1e-3) == huber_rule(None).c
    assert huber_rule(13.8).c == pytest.approx(math.sqrt(13.8))

    def corrected(error: float, robust):
        f = HeadingEKF(anchors, x0=[1.5, 1.2, 0, 0], P0=[0.01, 0.01, 0.01, 1e-4], dt=0.1,
                       q_xy=1e-3, q_theta=1e-4, q_bias=1e-8, lever_arm_std=0.2,
                       offsets=(1.5, 0.01), bias_std=0.01, robust=robust)  # fmt: skip
        rho = RangeModel(anchors, 0.05)
        m0 = Measurement(0.0, "range", 0.0, (1,), 0.05)
        m = Measurement(0.0, "range", f.linearized(rho, m0, f.state)[0] + error, (1,), 0.05)
        x = f.state.copy()
        f.correct(m)
        return f.state - x, f.nis

    seen = []
    for error in (1.0, 0.1):
        dx0, nis0 = corrected(error, None)
        seen.append(math.sqrt(nis0) > rule.c)
        dx, _ = corrected(error, rule)
        r = math.sqrt(nis0)  # |nu| / sqrt(S), the same prediction for both
        S = error**2 / nis0
        inflated = S + 0.05**2 * (max(r / rule.c, 1.0) - 1.0)
        assert np.allclose(dx, dx0 * S / inflated, rtol=1e-9, atol=1e-12)
        assert (r > rule.c) == (np.linalg.norm(dx) < 0.999 * np.linalg.norm(dx0))
    assert seen == [True, False]  # the outlier beyond the bound, the 0.1 m within it


def _height_lever_ekf(anchors, robust):
    """A filter settled to centimetres (its position, lever arm and anchors' states)."""
    return HeadingEKF(anchors, x0=[1.5, 1.2, 0, 0], P0=[1e-4, 1e-4, 1e-4, 1e-6], dt=0.1,
                      q_xy=1e-4, q_theta=1e-5, q_bias=1e-8, lever_arm_std=0.01,
                      offsets=(1.5, 0.01), bias_std=0.01, robust=robust)  # fmt: skip


def test_the_excess_rule_corrects_by_the_innovation_less_its_expected_excess():
    """``ukf-height-lever``'s default rule (:func:`excess_rule`: ``mu = c sigma``, the prior at
    which a range ``c sigma`` long is as likely blocked as clear): a range ``k`` long corrects
    the state by ``K (nu - E[e | nu])`` and the covariance by ``-(S - Var[e | nu]) K K^T``, the
    closed form of the two-component posterior; a burst of ranges 0.3 m long on one anchor
    moves its bias state by less than a fifth of what Huber's rule lets it (0.009 against
    0.052 m), and nothing is
    rejected."""
    from types import SimpleNamespace

    from quadobs.core.measurements import Measurement, RangeModel
    from quadobs.estimators.robust import ExcessHuber, Huber
    from quadobs.testbed.logs.height_estimators import EXCESS_MEMORY, excess_rule

    anchors = np.array([[0.12, 0.10], [2.90, 0.16], [2.86, 2.28], [0.15, 2.31]])
    setup = SimpleNamespace(
        kinds=("range",), dim=2, beacons=anchors, range_sigma=1.0, range_std_stated=0.08, gate=None
    )
    rule = excess_rule(setup)
    assert excess_rule(SimpleNamespace(**{**vars(setup), "range_std_stated": None})).mean == rule.c
    assert isinstance(rule, ExcessHuber) and rule.memory == EXCESS_MEMORY
    assert rule.mean == pytest.approx(rule.c * 0.08) and rule.nlos == pytest.approx(
        0.0150, abs=1e-4
    )
    rho = RangeModel(anchors, 0.08)
    m0 = Measurement(0.0, "range", 0.0, (1,), 0.08)
    for error in (0.05, 0.3, 2.0):
        f = _height_lever_ekf(anchors, rule)
        z, H = f.linearized(rho, m0, f.state)
        P, x = f.state_covariance.copy(), f.state.copy()
        S = float(H @ P @ H) + 0.08**2
        K = P @ H / S
        shift, var, _ = rule.posterior(error, S)
        f.correct(Measurement(0.0, "range", z + error, (1,), 0.08))
        np.testing.assert_allclose(f.state - x, K * (error - shift), rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(
            f.state_covariance, P - (S - var) * np.outer(K, K), rtol=1e-9, atol=1e-14
        )
    moved = {}
    for name, robust in (("excess", rule), ("huber", Huber(rule.c))):
        f = _height_lever_ekf(anchors, robust)
        b0, z = f.range_biases[1], f.linearized(rho, m0, f.state)[0]
        for k in range(20):  # 20 ranges 0.3 m long on anchor 1, 0.1 s apart, the robot at rest
            f.predict(0.1 * (k + 1))
            f.correct(Measurement(0.1 * (k + 1), "range", z + 0.3, (1,), 0.08))
        assert f.rejected == 0
        moved[name] = f.range_biases[1] - b0
    assert 0.0 < moved["excess"] < 0.2 * moved["huber"]


def test_the_excess_rule_on_the_grid_weighs_each_range_by_its_own_anchors_chain():
    """:meth:`step` (the grid's outputs) corrects as :meth:`correct` does, each range's excess
    read against its own anchor's chain: a range 0.5 m long on anchor 2 alone leaves anchor 2
    as blocked and the others clear."""
    from quadobs.core.measurements import Measurement, RangeModel
    from quadobs.estimators.robust import ExcessHuber

    anchors = np.array([[0.12, 0.10], [2.90, 0.16], [2.86, 2.28], [0.15, 2.31]])
    rule = ExcessHuber.at_bound(3.29, 0.08, memory=1.0)
    rho = RangeModel(anchors, 0.08)
    grid, timed = _height_lever_ekf(anchors, rule), _height_lever_ekf(anchors, rule)
    for f in (grid, timed):
        f.range_sigma = 0.08
    r = [
        grid.linearized(rho, Measurement(0.0, "range", 0.0, (h,), 0.08), grid.state)[0]
        for h in range(4)
    ]
    r[2] += 0.5
    y = 0.5 * np.square(r) - 0.5 * np.einsum("hi,hi->h", anchors, anchors)
    grid.step(np.zeros(3), y)
    for h in np.lexsort(anchors.T[::-1]):
        timed.correct(Measurement(0.0, "range", r[h], (int(h),), 0.08))
    np.testing.assert_allclose(grid.state, timed.state, rtol=1e-9, atol=1e-12)
    assert grid._blocked[2] > 0.9 and np.all(grid._blocked[[0, 1, 3]] < 0.05)


def test_a_lock_out_reinitialisation_restarts_the_excess_chains_in_line_of_sight():
    """A re-initialisation by the lock-out forgets each anchor's evidence of a blocked path:
    the chains restart as at the filter's start (clear, no previous range)."""
    from quadobs.core.measurements import Measurement
    from quadobs.estimators.robust import ExcessHuber, LockOut

    anchors = np.array([[0.12, 0.10], [2.90, 0.16], [2.86, 2.28], [0.15, 2.31]])
    f = _height_lever_ekf(anchors, ExcessHuber.at_bound(3.29, 0.08, memory=1.0))
    f.range_sigma, f.gate, f.lockout = 0.08, 1e-6, LockOut(timeout=0.3)  # every range rejected
    f.hold(np.zeros(3))
    f.correct(Measurement(0.0, "range", 5.0, (2,), 0.08))
    assert f._blocked[2] > 0.9 and f._blocked_at[2] == 0.0
    for k in range(1, 9):
        f.predict(0.05 * k)
        f.correct(Measurement(0.05 * k, "range", 5.0, (0,), 0.08))
    assert f.lockout.resets and f.diverged is None
    assert f._blocked[2] == 0.0 and f._blocked_at[2] == -np.inf
    # the position's variance at least the largest innovation squared; heading and gyroscope
    # bias (no velocity in this state) as they were
    assert np.all(np.diag(f._P)[:2] > 4.0 * np.diag(f._P0)[:2])
    assert np.all(np.diag(f._P)[2:4] < 2.0 * np.diag(f._P0)[2:4])


def test_the_filter_with_the_anchors_states_is_the_same_whatever_the_anchors_order():
    """The same noisy ranges with the anchors listed in reverse: the UKF with the anchors'
    biases and offsets as states starts from a centred multilateration and spreads its sigma
    points by the symmetric root, so it ends where it ends with the anchors in order (to
    rounding), its anchor states reversed."""
    lever, dz = (0.10, 0.0), np.array([0.05, 2.05, 0.80, 1.55])
    t = np.arange(0.0, 6.0, 0.1)
    omega = room_s_curve(t + 0.05, lever)[0]
    inputs = np.column_stack([t, np.full_like(t, 0.3), omega])
    tr = np.arange(0.05, 5.9, 0.25)
    h = np.arange(tr.size) % 4
    tag = room_s_curve(tr, lever)[2]
    rho = np.sqrt(np.sum((tag - ROOM[h]) ** 2, axis=1) + dz[h] ** 2) + 0.1
    rho += 0.05 * np.random.default_rng(0).standard_normal(tr.size)
    ends = []
    for order in (np.arange(4), np.arange(4)[::-1]):
        index = np.argsort(order)  # anchor h is listed at index[h]
        ranges = np.column_stack([tr, index[h], rho])
        log = RangeLog("room", np.arange(4), ROOM[order], ranges, inputs, math.pi / 2, None)
        f = run_in_time(
            log, HeadingUKF, [100.0, 100.0, 0.01, 1e-4], x0=(8.0, -5.0, 0.0, 0.0),
            lever_arm_std=0.2, offsets=(1.5, 1.34), bias_std=0.5, **{**NOISE, "q_xy": 1e-3},
        )  # fmt: skip
        assert f.fixes  # the start-up's multilateration was taken
        ends.append((f.x_hat, f.lever_arm, f.range_biases[index], f.offsets[index]))
    for a, b in zip(*ends, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_the_centred_multilateration_is_exact_and_does_not_depend_on_the_outputs_order():
    """Noise-free outputs: both differences give the position; noisy ones: the centred fix of
    the outputs in any order is the same, the fix from the first output is not."""
    from quadobs.estimators.robust import multilateration

    p = np.array([1.1, 0.7])
    y = 0.5 * np.sum((p - ROOM) ** 2, axis=1) - 0.5 * np.sum(ROOM**2, axis=1)
    C = np.broadcast_to(np.eye(2), (4, 2, 2))
    for centred in (False, True):
        np.testing.assert_allclose(multilateration(C, -ROOM, y, centred)[1], p, atol=1e-12)
    y_noisy = y + np.array([0.05, -0.03, 0.02, 0.04])
    fixes = {
        centred: [multilateration(C, -ROOM[o], y_noisy[o], centred)[1] for o in ([0, 1, 2, 3], [2, 3, 0, 1])]
        for centred in (False, True)
    }  # fmt: skip
    np.testing.assert_allclose(fixes[True][0], fixes[True][1], atol=1e-12)
    assert np.linalg.norm(fixes[False][0] - fixes[False][1]) > 1e-3


def _one_round(f, anchors, rho, sigma):
    """Every anchor's range at t = 0 corrected in turn (the fix follows the last)."""
    from quadobs.core.measurements import Measurement

    f.time = 0.0
    f.hold(np.zeros(3))
    for h in range(anchors.shape[0]):
        f.correct(Measurement(0.0, "range", float(rho[h]), (h,), sigma))


@pytest.mark.parametrize("states", ["none", "lever, offsets, biases", "the pattern"])
def test_the_fix_s_normalised_error_is_chi_square_with_two_degrees_of_freedom(states):
    """Ranges drawn from the filter's model (the lever arm, the anchors' offsets and biases from
    their priors where states): the error of the fix's position (the tag's fix less the lever
    arm's prior mean 0, so off the point by the tag's error plus ``R l``), normalised by the
    position covariance the filter gives it, is chi-square with 2 degrees of freedom (mean 2):
    the centred estimator's covariance, the range noise counted once, plus ``R P_l R^T``. The position variance
    ``sigma^2`` per axis of before gives a mean of 1.0 at this point, the room's centre. The
    states the fix leaves at their prior keep their prior covariance, independent of it. The
    tag's pattern alone, 0.1 m against a range noise of 0.01 m: one ``(c, s)`` for every anchor
    correlates the outputs' errors. Measured on these draws, the mean is 3.0 without the
    pattern's term, and 0.03 with each anchor's share on the diagonal alone (the correlation
    left out: the common pattern mostly cancels in the centred differences)."""
    rng = np.random.default_rng(11)
    p, theta, sigma, e_prior, b_std, l_std = np.array([1.5, 1.2]), 0.7, 0.08, (1.5, 0.4), 0.1, 0.2
    c, sn = math.cos(theta), math.sin(theta)
    kw = dict(x0=(8.0, -5.0, 0.0, 0.0), P0=[100.0, 100.0, 0.01, 1e-4], dt=0.1, heading0=theta,
              **NOISE)  # fmt: skip
    if states == "lever, offsets, biases":
        kw.update(lever_arm_std=l_std, offsets=e_prior, bias_std=b_std)
    if states == "the pattern":  # the pattern's share of the fix's error above the noise's
        kw.update(tag_pattern_std=0.1)
        sigma = 0.01
    nees = []
    for _ in range(400):
        l, b, e, cs = np.zeros(2), np.zeros(4), np.zeros(4), np.zeros(2)
        if states == "lever, offsets, biases":
            l, b = l_std * rng.standard_normal(2), b_std * rng.standard_normal(4)
            e = e_prior[0] + e_prior[1] * rng.standard_normal(4)
        if states == "the pattern":
            cs = 0.1 * rng.standard_normal(2)
        tag = p + np.array([[c, -sn], [sn, c]]) @ l
        d = ROOM - tag
        phi = 2.0 * (np.arctan2(d[:, 1], d[:, 0]) - theta)
        s = np.sqrt(np.sum(d**2, axis=1) + 2.0 * e) + cs[0] * np.cos(phi) + cs[1] * np.sin(phi)
        f = HeadingEKF(ROOM, **kw)
        _one_round(f, ROOM, s + b + sigma * rng.standard_normal(4), sigma)
        assert len(f.fixes) == 1
        err = f.state[:2] - p  # the state's point: the tag less R l (the fix is the tag's)
        nees.append(err @ np.linalg.solve(f.state_covariance[:2, :2], err))
        np.testing.assert_array_equal(f.state_covariance[2:, 2:], f._P0[2:, 2:])
        np.testing.assert_array_equal(f.state_covariance[:2, 2:], 0.0)
    assert abs(np.mean(nees) - 2.0) < 0.3  # the mean of 400 draws: standard error 0.1


@pytest.mark.parametrize("cls", [HeadingEKF, HeadingUKF])
def test_the_grid_and_the_lock_out_s_re_fix_do_not_depend_on_the_order_of_the_anchors(cls):
    """On the grid (several ranges in one step), from 50 m off, with a gate that rejects most
    corrections so that the lock-out re-fixes the position: the anchors listed in three orders
    give the same states at every step, to rounding."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 8.0, 0.1)
    omega = room_s_curve(t + 0.05, (0.1, 0.0))[0]
    tag = room_s_curve(t, (0.1, 0.0))[2]
    Y = 0.5 * np.sum((tag[:, None] - ROOM) ** 2, axis=2) - 0.5 * np.sum(ROOM**2, axis=1)
    Y += 0.05 * rng.standard_normal(Y.shape)
    Y[rng.random(Y.shape) < 0.3] = np.nan  # dropouts
    runs = []
    for order in ([0, 1, 2, 3], [3, 1, 0, 2], [2, 3, 1, 0]):
        f = cls(ROOM[order], x0=(40.0, 30.0, 0.0, 0.0), P0=[2500.0, 2500.0, 0.01, 1e-4], dt=0.1,
                lever_arm_std=0.2, gate=0.5, **{**NOISE, "q_xy": 1e-3})  # fmt: skip
        states = []
        for k in range(t.size):
            f.step(np.array([0.3, 0.0, omega[k]]), Y[k, order])
            states.append(f.state)
        assert f.fixes and f.lockout.resets  # the start-up's fix and at least one re-fix
        runs.append(np.array(states))
    for other in runs[1:]:
        np.testing.assert_allclose(other, runs[0], rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("spread", "message"),
    [
        ([1.0, 2.0], "one standard deviation, or 4"),
        (np.ones((4, 4)), "not positive definite"),
        (np.eye(3), r"symmetric \(4, 4\) prior covariance"),
        ([1.0, 1.0, -1.0, 1.0], "positive finite prior standard deviation"),
    ],
)
def test_the_offsets_prior_is_refused_in_one_line_when_malformed(spread, message):
    anchors = np.array([[0.12, 0.10], [2.90, 0.16], [2.86, 2.28], [0.15, 2.31]])
    with pytest.raises(QuadobsError, match=message):
        HeadingEKF(
            anchors, x0=[1.5, 1.2, 0, 0], P0=[1, 1, 0.01, 1e-4], dt=0.1, q_xy=1e-3,
            q_theta=1e-4, q_bias=1e-8, offsets=(1.5, spread),
        )  # fmt: skip


def test_a_range_with_the_tags_pattern_and_its_jacobian_are_the_closed_forms():
    """``rho_h = sqrt(|q - a_h|^2 + 2 e_h) + b_h + c cos 2 phi_h + s sin 2 phi_h``, ``phi_h`` the
    anchor's bearing from the tag less the heading; its derivative by central differences, and
    the UKF's points map the same range."""
    from quadobs.core.measurements import Measurement, RangeModel

    kw = dict(
        x0=[1.0, 1.0, 0.0, 0.0], P0=[1.0, 1.0, 0.01, 1e-4], dt=0.1, q_xy=1e-3, q_theta=1e-4,
        q_bias=1e-8, heading0=0.7, lever_arm_std=0.2, offsets=(1.5, 1.34), bias_std=0.5,
        tag_pattern_std=0.1,
    )  # fmt: skip
    f, u = HeadingEKF(ROOM, **kw), HeadingUKF(ROOM, **kw)
    assert f.state.shape == (16,) and np.all(f.tag_pattern == 0.0)
    assert list(f.constant_states) == [4, 5, *range(6, 16)]
    x = np.array([1.3, 0.8, 0.2, 0.01, 0.1, -0.04, 0.1, 0.2, -0.1, 0.05, 0.02, 2.1, 0.3, 1.2])
    x = np.concatenate([x, [0.07, -0.04]])
    model = RangeModel(ROOM, 0.05)
    theta = 0.7 + x[2]
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    tag = x[:2] + rot @ x[4:6]
    X = x + 0.01 * np.random.default_rng(1).standard_normal((5, 16))
    for h in range(4):
        m = Measurement(0.0, "range", 1.0, (h,), 0.05)
        z, H = f.linearized(model, m, x)
        d = ROOM[h] - tag
        phi = math.atan2(d[1], d[0]) - theta
        pattern = 0.07 * math.cos(2 * phi) - 0.04 * math.sin(2 * phi)
        expected = math.sqrt(d @ d + 2 * x[10 + h]) + x[6 + h] + pattern
        assert z == pytest.approx(expected, rel=1e-12)
        np.testing.assert_allclose(H, _numeric_jacobian(f, model, m, x), atol=1e-8)
        points = u._points_ranges(model, m, X)
        np.testing.assert_allclose(points, [u._range(model, m, xi)[0] for xi in X], rtol=1e-12)


PATTERN_LEVER = (0.10, 0.03)


def pattern_room_log(c: float, s: float, noise: float = 0.0, seed: int = 0) -> RangeLog:
    """76 s of the S-curve in the small room (:func:`room_s_curve`), 3-D ranges at 4 Hz from a
    tag :data:`PATTERN_LEVER` ahead of the tracked point to anchors 0.05 to 2.05 m above it
    with biases of 0.05 to 0.15 m, each range longer by the tag's pattern ``c cos 2 phi + s sin
    2 phi`` (``phi`` the anchor's bearing from the tag less the heading) and by Gaussian noise
    of ``noise`` m (drawn from ``seed``)."""
    dz, bias = np.array([0.05, 2.05, 0.80, 1.55]), np.array([0.10, 0.05, 0.15, 0.08])
    t = np.arange(0.0, 76.0, 0.1)
    omega = room_s_curve(t + 0.05, PATTERN_LEVER)[0]
    inputs = np.column_stack([t, np.full_like(t, 0.3), omega])
    tr = np.arange(0.05, 75.9, 0.25)
    h = np.arange(tr.size) % 4
    _, _, tag, theta = room_s_curve(tr, PATTERN_LEVER)
    d = ROOM[h] - tag
    phi = np.arctan2(d[:, 1], d[:, 0]) - theta
    rho = np.sqrt(np.sum(d**2, axis=1) + dz[h] ** 2) + bias[h]
    rho += c * np.cos(2 * phi) + s * np.sin(2 * phi)
    rho += noise * np.random.default_rng(seed).standard_normal(rho.size)
    return RangeLog(
        "room", np.arange(4), ROOM, np.column_stack([tr, h, rho]), inputs, math.pi / 2, None
    )


def test_the_tags_pattern_as_states_is_recovered_in_turns_and_keeps_the_tracked_point():
    """Noise-free 3-D ranges in a small room (:func:`pattern_room_log`), the tag's delay ``c cos 2 phi + s sin 2 phi`` of
    0.18 m over bearings turning with the robot, anchors above it with biases: the UKF that
    holds the pattern finds it and tracks the point as well as without a pattern in the
    ranges; without those states the biases and the lever arm take it up, and the point is
    off by half a metre."""
    lever, (c, s) = PATTERN_LEVER, (0.15, -0.20)
    log = pattern_room_log(c, s)
    noise = {**NOISE, "range_sigma": 0.02}
    start = {"x0": (1.5, 1.2, 0.0, 0.0), "lever_arm_std": 0.2}
    P0 = [0.01, 0.01, 0.01, 1e-4]
    states = {"offsets": (1.5, 1.34), "bias_std": 0.5}
    errors = {}
    for name, extra in (("pattern", {"tag_pattern_std": 0.1}), ("without", {})):
        f = HeadingUKF(
            ROOM, P0=P0, dt=0.1, heading0=log.heading0, **extra, **states, **start, **noise
        )
        late = [
            np.linalg.norm(f.x_hat - room_s_curve(np.array([m.t]), lever)[1][0])
            for m in pass_through(f, log)
            if m.t > 38.0
        ]
        errors[name] = math.sqrt(np.mean(np.square(late)))
        if name == "pattern":
            np.testing.assert_allclose(f.tag_pattern, (c, s), atol=0.01)
            np.testing.assert_allclose(f.lever_arm, lever, atol=0.01)
    # 0.022 m with no pattern in the ranges either way (the arc's model on the S-curve's turns)
    assert errors["pattern"] < 0.03 and errors["without"] > 0.2, errors
