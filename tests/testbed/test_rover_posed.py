"""A wheeled robot posed as a real one: stops with the heading held, wheel slip, 3-D ranges of a
planar log, a lever arm, clocks apart; and the filters with the anchors' heights as states."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.odometry import WheelOdometry, heading_and_yaw_rate
from quadobs.testbed.scenario import OdometrySpec, load_scenario
from quadobs.testbed.trajectory import SinusoidTrajectory

_TERMS = np.array([[0, 1.0, 0.32, -np.pi / 2], [1, 0.6, 0.64, -np.pi / 2]])
_STOPS = "trajectory.stops=[{start=0.0,end=1.5,ramp=0.5},{start=6.0,end=7.0,ramp=1.0}]"


def _stopped() -> SinusoidTrajectory:
    return SinusoidTrajectory(np.array([1.5, 1.2]), _TERMS, stops=[[0.0, 1.5, 0.5], [6, 7, 1]])


def test_a_stop_halts_the_path_and_holds_its_direction():
    tr, plain = _stopped(), SinusoidTrajectory(np.array([1.5, 1.2]), _TERMS)
    t = np.array([0.0, 0.7, 1.5, 6.0, 6.5, 7.0])
    np.testing.assert_array_equal(tr.velocity_at(t), 0.0)
    np.testing.assert_array_equal(tr.position(t[:3]), plain.position(np.zeros(3)))
    # after the first stop the path goes on from where it halted: sigma = t - 1.5 - 0.5 / 2
    np.testing.assert_allclose(tr.warp(np.array([3.0]))[0], [1.25], rtol=1e-14)
    # the direction of travel at rest is the path's own, never zero
    np.testing.assert_allclose(tr.path_velocity(t[:1]), plain.velocity_at(t[:1]))
    # without stops the derivatives are those of the plain path, bit for bit
    s = np.linspace(0.0, 9.0, 91)
    np.testing.assert_array_equal(plain.derivative(s, 2), plain._path(s, 2))


def test_the_stop_s_derivatives_are_those_of_its_position():
    tr, h = _stopped(), 1e-5
    t = np.linspace(0.05, 9.0, 400)  # through both ramps and rests
    for order in (1, 2):
        fd = (tr.derivative(t + h, order - 1) - tr.derivative(t - h, order - 1)) / (2 * h)
        np.testing.assert_allclose(tr.derivative(t, order), fd, atol=1e-7)
    with pytest.raises(QuadobsError, match="order 3"):
        tr.derivative(t, 3)


@pytest.mark.parametrize(
    ("stops", "message"),
    [
        ("[{start=0.5,end=2.0,ramp=1.0}]", r"stops\[0\]: the ramp 1.0 s down"),
        ("[{start=0,end=2},{start=2.5,end=4}]", r"stops\[1\]: its ramp down begins at 1.5 s"),
        ("[{start=3,end=2}]", r"stops\[0\]: expected 0 <= start < end"),
    ],
)
def test_bad_stops_are_refused_naming_the_stop(stops, message):
    with pytest.raises(QuadobsError, match=message):
        load_scenario("rover-room", settings=[f"trajectory.stops={stops}"])


def test_at_rest_the_heading_is_held_and_the_encoders_read_zero():
    v = np.array([[0.0, 0.0], [0.3, 0.4]])
    a = np.array([[0.1, 0.0], [0.0, 0.0]])
    direction = np.array([[0.0, 2.0], [1.0, 0.0]])
    speed, heading, yaw_rate = heading_and_yaw_rate(v, a, direction)
    np.testing.assert_allclose(heading, [math.pi / 2, math.atan2(0.4, 0.3)])
    np.testing.assert_array_equal(yaw_rate, [0.0, 0.0])
    spec = OdometrySpec(speed_std=0.05, yaw_rate_bias=0.01, yaw_rate_std=0.0)
    odo = WheelOdometry(spec, seed=0, dt=1e-3, trajectory=_stopped())
    measured, held, _ = odo.sample(np.zeros((2, 2)), np.zeros((2, 2)), np.array([0.0, 1.0]))
    np.testing.assert_array_equal(measured[:, 0], 0.0)  # no wheel turns, no noise either
    np.testing.assert_array_equal(measured[:, 1], 0.01)  # the gyro's bias stays
    np.testing.assert_allclose(held, math.atan2(0.6 * 0.64, 1.0 * 0.32))


def test_wheel_slip_lengthens_the_speed_in_proportion_to_the_yaw_rate():
    phi = np.linspace(-3.0, 3.0, 50)
    v = 0.4 * np.column_stack([np.cos(phi), np.sin(phi)])
    a = 0.4 * -0.8 * np.column_stack([-np.sin(phi), np.cos(phi)])
    spec = OdometrySpec(scale_error=0.02, turn_slip=0.05)
    measured, _, _ = WheelOdometry(spec, seed=0, dt=1e-3).sample(v, a)
    np.testing.assert_allclose(measured[:, 0], (1.0 + 0.02 + 0.05 * 0.8) * 0.4, rtol=1e-12)
    assert "turn_slip" not in load_scenario("rover-room").to_dict()["odometry"]


def test_a_rover_at_rest_exports_its_held_heading(tmp_path):
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.logs import read_log
    from quadobs.testbed.logs.export import LogExportSink

    sc = load_scenario(
        "rover-room", duration=3.0, settings=[_STOPS.replace("6.0", "16.0").replace("7.0", "17.0")]
    )
    run_episode(sc, estimators=["ekf"], sinks=[LogExportSink(tmp_path / "log")])
    log = read_log(tmp_path / "log")
    rest = log.inputs[:, 0] <= 1.5
    np.testing.assert_array_equal(log.inputs[rest, 1], 0.0)
    assert np.all(log.inputs[log.inputs[:, 0] > 2.2, 1] > 0.1)  # moving once the ramp is done
    v0 = sc.trajectory.path_velocity(np.zeros(1))[0]
    assert log.heading0 == pytest.approx(math.atan2(v0[1], v0[0]), abs=1e-12)
    still = log.truth[:, 0] <= 1.5
    np.testing.assert_allclose(log.truth[still, 3], log.heading0, atol=1e-9)
    np.testing.assert_allclose(log.truth[still, 1], 1.5, atol=1e-9)
    np.testing.assert_allclose(log.truth[still, 2], 1.2, atol=1e-9)


def _planar_log(duration: float = 20.0):
    """A robot on a circle of radius 0.8 m about (1.5, 1.2), heading along it, ranges exact + 0.1 m."""
    from quadobs.testbed.logs.format import RangeLog

    t = np.linspace(0.0, duration, int(round(duration * 100)) + 1)
    phi = 0.4 * t
    p = np.column_stack([1.5 + 0.8 * np.cos(phi), 1.2 + 0.8 * np.sin(phi)])
    truth = np.column_stack([t, p, np.unwrap(phi + np.pi / 2)])
    beacons = np.array([[0.1, 0.1], [2.9, 0.2], [2.8, 2.3], [0.2, 2.3]])
    k = np.arange(5, t.size - 1, 5)
    h = k % 4
    ranges = np.column_stack([t[k], h, np.linalg.norm(p[k] - beacons[h], axis=1) + 0.1])
    inputs = np.column_stack([t, np.full(t.size, 0.32), np.full(t.size, 0.4)])
    return RangeLog("circle", np.arange(4), beacons, ranges, inputs, float(truth[0, 3]), truth)


def test_posing_gives_3d_ranges_from_the_tag_and_moves_the_clocks():
    from quadobs.testbed.logs.posed import posed_log, tag_positions

    log = _planar_log()
    heights = np.array([0.3, 2.3, 1.05, 1.8])
    posed = posed_log(
        log, anchor_heights=heights, tag_height=0.25, lever_arm=(0.1, 0.0),
        odometry_offset=0.05, time_base=1.7e9,
    )  # fmt: skip
    t, h = log.ranges[:, 0], log.ranges[:, 1].astype(int)
    tag = tag_positions(log, t, (0.1, 0.0))
    # the tag 0.1 m ahead of the circle's point, along the tangent
    phi = 0.4 * t
    ahead = np.column_stack([1.5 + 0.8 * np.cos(phi), 1.2 + 0.8 * np.sin(phi)])
    ahead += 0.1 * np.column_stack([-np.sin(phi), np.cos(phi)])
    np.testing.assert_allclose(tag, ahead, atol=1e-3)  # the truth's rows are linear between 10 ms
    expected = np.sqrt(np.sum((tag - log.beacons[h]) ** 2, axis=1) + (heights[h] - 0.25) ** 2)
    np.testing.assert_allclose(posed.ranges[:, 2], expected + 0.1, atol=1e-12)
    assert posed.beacons.shape == (4, 2)  # beacons.csv stays planar
    np.testing.assert_array_equal(posed.ranges[:, 0], t + 1.7e9)
    np.testing.assert_array_equal(posed.inputs[:, 0], log.inputs[:, 0] + 0.05 + 1.7e9)
    np.testing.assert_array_equal(posed.truth[:, 0], log.truth[:, 0] + 1.7e9)
    with pytest.raises(QuadobsError, match="expected 4 heights"):
        posed_log(log, anchor_heights=[1.0, 2.0])


def test_stated_heights_give_the_offsets_moments_and_the_filters_start_there():
    """``e_h = (dz_h + delta_h - delta_t)^2 / 2``, each anchor's survey error ``delta_h`` its
    own, the tag's ``delta_t`` common: the offsets' mean and covariance in closed form, checked
    by sampling; a posed log that states its heights hands them to ``ukf-height-lever`` (the
    other height filters keep the storey's prior), and the summary reports them."""
    import dataclasses

    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        build_replay_estimators,
        log_frame,
    )
    from quadobs.testbed.logs.height_estimators import (
        E_MEAN,
        HEIGHT_SURVEY_STD,
        TAG_HEIGHT_STD,
        known_offsets,
    )
    from quadobs.testbed.logs.posed import posed_log
    from quadobs.testbed.logs.replay import run_replay

    heights = np.array([2.3, 0.3, 1.8, 0.25])
    log = posed_log(_planar_log(), anchor_heights=heights, tag_height=0.25, heights_stated=True)
    assert known_offsets(_planar_log()) is None
    mean, cov = known_offsets(log)
    std = np.sqrt(np.diag(cov))
    rng = np.random.default_rng(7)
    draws = 400_000
    delta = HEIGHT_SURVEY_STD * rng.standard_normal((4, draws))
    delta -= TAG_HEIGHT_STD * rng.standard_normal(draws)
    e = 0.5 * (heights[:, None] - 0.25 + delta) ** 2
    np.testing.assert_allclose(mean, e.mean(axis=1), rtol=3e-3)
    np.testing.assert_allclose(cov, np.cov(e), rtol=2e-2, atol=2e-3 * cov.max())
    names = ["ekf-height", "augmented-height", "ukf-height-lever"]
    part = log.excerpt(0.0, 3.0)
    np.testing.assert_array_equal(part.anchor_heights, heights)
    summary = run_replay(part, estimators=names, batch=False)
    np.testing.assert_allclose(summary["noise"]["offsets"]["mean"], mean, rtol=1e-12)
    np.testing.assert_allclose(summary["noise"]["offsets"]["std"], std, rtol=1e-12)
    setup = ReplaySetup(log.beacons, 0.1, "odometry", log.heading0, 1.5, **log_frame(log))
    for est in build_replay_estimators(setup, names, np.array([1.5, 1.2, log.heading0])):
        start = mean if est.name == "ukf-height-lever" else np.full(4, E_MEAN)  # the storey's
        np.testing.assert_allclose(_offsets_state(est), start, rtol=1e-12, err_msg=est.name)
        if est.name == "ukf-height-lever":  # the offsets are the state's last block
            np.testing.assert_array_equal(est.state_covariance[-4:, -4:], cov)
    from quadobs.testbed.logs.replay import replayable_log

    kept = log.ranges[:, 1] != 2
    quiet = dataclasses.replace(log, ranges=log.ranges[kept], range_std=log.range_std[kept])
    heard, notes = replayable_log(quiet)  # an anchor never heard goes, with its height
    np.testing.assert_array_equal(heard.anchor_heights, heights[[0, 1, 3]])
    assert heard.beacons.shape == (3, 2) and notes


def test_stated_heights_the_ranges_contradict_are_not_used():
    """``ukf-height-lever`` started from the stated heights predicts the held-out ranges no
    worse than from a storey's prior where the statement is right, and is used; with the tag
    stated a metre off it predicts them worse, and every filter falls back to the storey's.
    Checked by step 7 whether or not the calibration chose biases (here none)."""
    import dataclasses

    from quadobs.testbed.logs.calibration import Calibration, estimator_biases
    from quadobs.testbed.logs.estimators import ReplaySetup, log_frame, tuning_fields
    from quadobs.testbed.logs.height_estimators import E_MEAN, known_offsets, offsets_prior
    from quadobs.testbed.logs.posed import posed_log

    heights = np.array([2.3, 0.3, 1.8, 1.1])
    log = posed_log(_planar_log(60.0), anchor_heights=heights, tag_height=0.25, heights_stated=True)
    for tag, used in ((0.25, True), (1.25, False)):
        stated = dataclasses.replace(log, tag_height=tag)
        cal = Calibration(None, {}, {}, "", np.zeros(4))
        estimator_biases(stated, cal, ["ekf", "ukf-height-lever"], dt=0.1, model="odometry")
        assert ("stated_heights" not in cal.options) is used, cal.reason
        assert (": used" if used else ": not used, the ranges contradict them") in cal.reason
        setup = ReplaySetup(
            stated.beacons, 0.1, "odometry", stated.heading0, 1.5, **log_frame(stated),
            **tuning_fields(cal.options),
        )  # fmt: skip
        mean = offsets_prior(setup)[0]
        expected = known_offsets(stated)[0] if used else np.full(4, E_MEAN)
        np.testing.assert_allclose(mean, expected, rtol=1e-12)


def _offsets_state(est) -> np.ndarray:
    """A height filter's squared-range offsets: the heading filter's ``offsets``, else from
    the others' ``heights`` (``|dz| = sqrt(2 e)``)."""
    if hasattr(est, "offsets"):
        return np.asarray(est.offsets)
    return 0.5 * np.asarray(est.heights) ** 2


def test_the_height_model_is_the_3d_range_and_its_jacobian():
    from quadobs.core.system import vehicle_system
    from quadobs.estimators.height_states import HeightRangeOutputModel, height_system

    beacons = np.array([[0.1, 0.1], [2.9, 0.2], [2.8, 2.3]])
    ext = height_system(vehicle_system(2, beacons))
    model = HeightRangeOutputModel(ext, np.eye(3), offsets=0.5 * np.sum(beacons**2, axis=1))
    b, e = np.array([0.1, -0.05, 0.2]), np.array([0.5, 2.0, 0.0])
    x = np.concatenate([[1.2, 0.7, 0.3, -0.1], b, e])
    r2 = np.sum((x[:2] - beacons) ** 2, axis=1)
    np.testing.assert_allclose(model.predict(x), np.sqrt(r2 + 2 * e) + b, rtol=1e-12)
    s, J = model.linearize(x)
    np.testing.assert_allclose(s, model.predict(x), rtol=1e-12)
    fd = np.column_stack(
        [(model.predict(x + d) - model.predict(x - d)) / 2e-6 for d in 1e-6 * np.eye(x.size)]
    )
    np.testing.assert_allclose(J, fd, atol=1e-8)


def test_the_height_states_follow_3d_ranges_that_constant_biases_cannot():
    from quadobs.testbed.logs.posed import posed_log
    from quadobs.testbed.logs.replay import run_replay

    log = posed_log(_planar_log(), anchor_heights=[2.3, 0.3, 1.8, 1.1], tag_height=0.25)
    names = ["augmented", "augmented-height", "ekf-bias", "ekf-height"]
    summary = run_replay(log, estimators=names, initial_offset=2.0, batch=False, burn_in=10.0)
    rmse = {n: summary["estimators"][n]["rmse"] for n in names}
    assert rmse["augmented-height"] < 0.5 * rmse["augmented"], rmse
    assert rmse["ekf-height"] < 0.5 * rmse["ekf-bias"], rmse


def test_the_offsets_enter_the_quadratic_output_linearly():
    from quadobs.core.immersion import immerse
    from quadobs.core.system import odometry_system
    from quadobs.estimators.height_states import height_quadratic_system

    beacons = np.array([[0.1, 0.1], [2.9, 0.2], [2.8, 2.3], [0.2, 2.3]])
    ext = height_quadratic_system(odometry_system(beacons))
    p, e = np.array([1.2, 0.7]), np.array([0.5, 2.0, 0.0, 1.1])
    x = np.concatenate([p, e])
    # y_h + |a_h|^2 / 2 = rho_h^2 / 2 with rho_h^2 = |p - a_h|^2 + 2 e_h
    rho2 = np.sum((p - beacons) ** 2, axis=1) + 2 * e
    np.testing.assert_allclose(ext.output(x) + 0.5 * np.sum(beacons**2, axis=1), rho2 / 2)
    im = immerse(ext)  # still one auxiliary state, |p|^2 / 2: the offsets are linear states
    assert im.n_aux == 1 and im.dim == 1 + 2 + 4


def test_the_height_filters_refuse_what_they_cannot_take_by_name():
    from quadobs.testbed.logs.replay import run_replay

    with pytest.raises(
        QuadobsError, match="'augmented-height' takes the ranges of a planar odometry"
    ):
        run_replay(_planar_log(), estimators=["augmented-height"], model="cv", batch=False)


def test_the_heights_apparent_bias_is_the_closed_form_at_each_anchors_median_range():
    """Anchors of ids 0, 1, 5, 6 (columns by id, not by row): at a median range ``r`` the
    offset's prior mean ``E_MEAN`` adds ``sqrt(r^2 + 2 E_MEAN) - r``, its spread ``E_STD`` that
    over ``sqrt(r^2 + 2 E_MEAN)``; an anchor without ranges the height's whole share."""
    from quadobs.testbed.logs.format import RangeLog
    from quadobs.testbed.logs.height_estimators import E_MEAN, E_STD, apparent_bias_prior

    beacons = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [0.0, 2.0]])
    ids = np.array([0, 1, 5, 6])
    rows = [(0, 1.0), (0, 1.5), (0, 9.0), (5, 20.0), (5, 20.0), (1, 0.4)]
    ranges = np.array([[0.1 * i, b, r] for i, (b, r) in enumerate(rows)])
    inputs = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    log = RangeLog("ids", ids, beacons, ranges, inputs, 0.0, None)
    mean, std = apparent_bias_prior(log)
    r = np.array([1.5, 0.4, 20.0, 0.0])
    s = np.sqrt(r**2 + 2 * E_MEAN)
    np.testing.assert_allclose(mean, s - r, rtol=1e-12)
    np.testing.assert_allclose(std, E_STD / s, rtol=1e-12)
    assert mean[3] == pytest.approx(math.sqrt(2 * E_MEAN)) and mean[2] < 0.08


def test_the_height_lever_filter_takes_the_ranges_as_logged_unless_its_prior_excludes_the_biases():
    """Biases calibrated without heights in a room (each anchor's bias and its height's share)
    lie within the prior of the heading filter that holds both: ``ukf-height-lever`` takes the
    ranges as logged; biases of metres at a room's ranges lie outside it and are subtracted.
    ``ekf-height`` (the heading taken as known) and a filter without bias states are not
    checked; the chi-square is the closed form."""
    from quadobs.testbed.logs.calibration import Calibration, estimator_biases
    from quadobs.testbed.logs.height_estimators import apparent_bias_prior
    from quadobs.testbed.logs.posed import posed_log

    log = posed_log(_planar_log(), anchor_heights=[2.3, 0.3, 1.8, 1.1], tag_height=0.25)
    names = ["ekf", "ekf-height", "ukf-height-lever"]
    mean, std = apparent_bias_prior(log)
    for biases, kept in ((0.1 + mean, False), (np.full(4, 3.0), True)):
        cal = Calibration(biases, {}, {}, "", biases)
        logged = estimator_biases(log, cal, names)
        assert list(cal.per_estimator) == ["ukf-height-lever"], cal.per_estimator
        assert logged == (() if kept else ("ukf-height-lever",))
        chi2 = np.sum((biases - mean) ** 2 / (0.25 + std**2))
        record = cal.per_estimator["ukf-height-lever"]
        assert record["prior_chi2"] == pytest.approx(chi2, rel=1e-12)
        assert (record["prior_chi2"] > record["prior_limit"]) == kept
        what = "the calibrated biases subtracted" if kept else "the ranges as logged"
        assert f"ukf-height-lever (range biases and heights as states): {what}" in cal.reason


def test_the_head_line_says_whether_the_stated_heights_are_used(tmp_path, capsys):
    from dataclasses import replace

    from quadobs.cli import main
    from quadobs.testbed.logs import write_log
    from quadobs.testbed.logs.posed import posed_log

    log = posed_log(_planar_log(), anchor_heights=[2.3, 0.3, 1.8, 1.1], tag_height=0.25)
    folder = write_log(replace(log, anchor_heights=[2.3, 0.3, 1.8, 1.1]), tmp_path / "L")
    base = ["replay", str(folder), "--calibrate", "none", "--no-progress"]
    base += ["--estimators", "ukf-height-lever", "--initial-offset", "0"]
    assert main(base) == 0
    assert (
        "anchors' heights stated without meta.csv tag_height: not used" in capsys.readouterr().out
    )
    write_log(replace(log, anchor_heights=[2.3, 0.3, 1.8, 1.1], tag_height=0.25), folder)
    for tune, word in (
        ((), "used by ukf-height-lever ("),
        (("--tune", "stated_heights=0"), "set aside\n"),
    ):
        assert main([*base, *tune]) == 0
        assert f"the tag at 0.25 m: {word}" in capsys.readouterr().out
