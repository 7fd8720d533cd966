"""The ranges' own noise as the default ``range_sigma`` of a log that states none: found where the
ranges are dense enough to show it, the prior kept where the motion dominates them."""

import dataclasses
import math

import numpy as np
import pytest

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.estimators import log_defaults
from quadobs.testbed.logs.range_noise import (
    MIN_ANCHOR_RESIDUALS,
    anchor_noise,
    range_noise,
    smooth_range_noise,
    stated_range_noise,
    with_anchor_noise,
)

ANCHORS = np.array([[-3.0, -3.0, 0.2], [3.0, -3.0, 2.8], [3.0, 3.0, 0.2], [-3.0, 3.0, 2.8]])


def _log(rate, speed, sigma, seconds=20.0, nlos=0.0, radius=2.0):
    """Ranges round-robin over four anchors at ``rate`` Hz, a circle of ``radius`` at ``speed`` m/s,
    Gaussian noise ``sigma`` (one figure, or one per anchor) and a fraction ``nlos`` longer by
    an exponential 0.5 m; no std."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, seconds, 1.0 / rate) + rng.uniform(0.0, 2e-4, int(round(seconds * rate)))
    w = speed / radius
    p = np.column_stack([radius * np.cos(w * t), radius * np.sin(w * t), 1.5 + 0 * t])
    h = np.arange(t.size) % 4
    noise = np.broadcast_to(np.asarray(sigma, dtype=float), (4,))[h]
    r = np.linalg.norm(p - ANCHORS[h], axis=1) + noise * rng.standard_normal(t.size)
    r += (rng.random(t.size) < nlos) * rng.exponential(0.5, t.size)
    imu = np.column_stack([t, np.zeros((t.size, 2)), np.full(t.size, 9.81), np.zeros((t.size, 3))])
    return RangeLog(
        "room", np.arange(4), ANCHORS, np.column_stack([t, h, r]), imu, math.nan,
        input_kind="imu_body",
    )  # fmt: skip


@pytest.mark.parametrize("nlos", [0.0, 0.1])
def test_a_tag_s_dense_ranges_give_their_noise(nlos):
    log = _log(rate=100.0, speed=1.0, sigma=0.1, nlos=nlos)
    sigma, sigma_2, n = range_noise(log)
    # a tenth of the ranges longer spoils three residuals each: the median moves by 30 %, not
    # by the excess's 0.5 m
    assert 0.09 < sigma < 0.11 + 0.3 * nlos and sigma_2 == pytest.approx(sigma, rel=0.1)
    assert n == log.ranges.shape[0] - 8  # every range but each anchor's first and last
    assert log_defaults(log)["range_sigma"] == sigma


def test_sparse_ranges_of_a_fast_vehicle_keep_the_prior():
    """Each anchor ranged every 2 s by a vehicle circling at 3 m/s (radius 10 m): the
    interpolation residual is the motion's curvature, larger over the doubled span, and no
    noise figure."""
    log = _log(rate=2.0, speed=3.0, sigma=0.1, seconds=600.0, radius=10.0)
    sigma, sigma_2, n = range_noise(log)
    assert n >= 400 and sigma_2 > 1.25 * sigma and sigma > 0.2
    assert stated_range_noise(log) is None and "range_sigma" not in log_defaults(log)


def test_sparser_ranges_of_a_flight_show_their_noise_against_a_cubic():
    """Each anchor ranged every 0.5 s on a circle of 2 m at 1 m/s: the linear interpolation's
    residual is the motion's (the doubled span's figure 1.8 times the native one), the cubic's
    the noise. A body-IMU log takes it; a wheel-odometry log keeps the linear test alone; where
    the cubic's residual is the motion's too (2 m/s, every 0.5 s), the prior stands."""
    log = _log(rate=8.0, speed=1.0, sigma=0.1, seconds=80.0)
    sigma, sigma_2, _ = range_noise(log)
    assert sigma_2 > 1.5 * sigma
    smooth, smooth_2, n = smooth_range_noise(log)
    assert 0.09 < smooth < 0.11 and smooth_2 < 1.1 * smooth and n >= 400
    assert stated_range_noise(log) == smooth
    t = log.ranges[:, 0]
    odometry = dataclasses.replace(
        log,
        beacons=ANCHORS[:, :2],
        inputs=np.column_stack([t, np.full(t.size, 1.0), np.full(t.size, 0.5)]),
        input_kind="odometry",
        heading0=0.0,
    )
    assert stated_range_noise(odometry) is None
    fast = _log(rate=8.0, speed=2.0, sigma=0.1, seconds=80.0, radius=3.0)
    assert stated_range_noise(fast) is None


def test_the_cubic_s_residual_is_zero_on_a_cubic_and_skips_repeated_times():
    from quadobs.testbed.logs.range_noise import _cubic_residuals

    t = np.array([0.0, 0.3, 0.35, 1.0, 1.6, 1.7, 2.9, 3.0])
    r = 2.0 - t + 0.5 * t**2 - 0.1 * t**3
    e = _cubic_residuals(t, np.zeros(t.size), r, 1)
    assert e.shape == (t.size - 4,) and np.max(np.abs(e)) < 1e-12
    r4 = r + 0.01 * t**4  # a quartic does not cancel
    assert np.max(np.abs(_cubic_residuals(t, np.zeros(t.size), r4, 1))) > 1e-4
    twice = np.array([0.0, 1.0, 2.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # a stamp repeated
    with np.errstate(all="raise"):
        kept = _cubic_residuals(twice, np.zeros(8), twice**2, 1)
    assert kept.shape == (1,) and abs(kept[0]) < 1e-12  # the window 2, 3, 4, 5, 6 alone


def test_a_log_that_states_its_noise_or_ranges_too_few_keeps_it():
    log = _log(rate=100.0, speed=1.0, sigma=0.1)
    stated = dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], 0.3))
    assert stated_range_noise(stated) is None
    short = _log(rate=100.0, speed=1.0, sigma=0.1, seconds=3.0)  # 292 residuals
    assert stated_range_noise(short) is None


def test_the_plaza_logs_keep_the_prior():
    from quadobs.testbed.logs.plaza import load_builtin

    for name in ("plaza1", "plaza2"):
        sigma, sigma_2, _ = range_noise(load_builtin(name))
        assert sigma_2 > 1.25 * sigma, name
        assert not {"range_sigma", "range_sigma_heading"} & set(log_defaults(load_builtin(name)))
        assert with_anchor_noise(load_builtin(name), {})[2] is None  # nor each anchor's figure


def test_an_odometry_log_gives_its_noise_to_every_filter():
    """A planar odometry log stating no ``std`` takes the ranges' own noise, as a body-IMU log
    does; a ``range_sigma`` the user sets stands."""
    from quadobs.testbed.logs.estimators import build_ukf_heading, replay_setup
    from quadobs.testbed.worlds.replay import ReplayWorld

    body = _log(rate=100.0, speed=1.0, sigma=0.1)
    t = body.ranges[:, 0]
    odometry = np.column_stack([t, np.full(t.size, 1.0), np.full(t.size, 0.5)])
    log = dataclasses.replace(
        body, beacons=ANCHORS[:, :2], inputs=odometry, input_kind="odometry", heading0=0.0
    )
    sigma = stated_range_noise(log)
    assert 0.09 < sigma < 0.12 and log_defaults(log)["range_sigma"] == sigma
    world = ReplayWorld(log, dt=0.1)
    setup = replay_setup(log, world, initial_offset=1.0)
    assert setup.range_sigma == sigma
    assert build_ukf_heading(setup, np.zeros(setup.n)).range_sigma == sigma
    assert replay_setup(log, world, {"range_sigma": 0.3}, initial_offset=1.0).range_sigma == 0.3


def test_each_anchor_s_noise_read_from_its_own_ranges():
    """Anchor 1 three times as noisy as the others: each figure within 10 % of its anchor's
    noise, the pooled one between; each range takes its anchor's figure, the setup the pooled."""
    truth = np.array([0.08, 0.24, 0.08, 0.08])
    log = _log(rate=100.0, speed=1.0, sigma=truth)
    sigma = anchor_noise(log)
    np.testing.assert_allclose(sigma, truth, rtol=0.1)
    pooled = stated_range_noise(log)
    assert truth[0] < pooled < truth[1]
    out, options, note = with_anchor_noise(log, {"q_imu": 0.02})
    assert options == {"q_imu": 0.02, "range_sigma": pooled}
    h = out.beacon_index(out.ranges[:, 1])
    np.testing.assert_array_equal(out.range_std, sigma[h])
    assert note is not None and f"1: {sigma[1]:.3f}" in note and f"{pooled:.3f}" in note
    np.testing.assert_array_equal(out.ranges, log.ranges)  # the ranges themselves untouched
    # what reads a log's stated noise reads the figures as a std column stating them
    from quadobs.testbed.logs.estimators import log_range_std
    from quadobs.testbed.logs.excess_model import known_noise

    assert log_range_std(out) == known_noise(out) == float(np.median(sigma[h]))


def test_the_pooled_figure_where_asked_or_where_an_anchor_shows_too_little():
    log = _log(rate=100.0, speed=1.0, sigma=[0.08, 0.24, 0.08, 0.08])
    for options in ({"range_sigma": 0.3}, {"anchor_sigma": 0.0}):  # the user's say stands
        out, same, note = with_anchor_noise(log, options)
        assert out is log and same == options and note is None
    # anchor 3 heard for its first 99 residuals only: the pooled figure
    h = log.ranges[:, 1]
    keep = (h != 3) | (np.cumsum(h == 3) <= MIN_ANCHOR_RESIDUALS + 1)
    short = dataclasses.replace(log, ranges=log.ranges[keep], range_std=log.range_std[keep])
    sigma = anchor_noise(short)
    assert sigma[3] == stated_range_noise(short) and sigma[1] > 0.2


def test_no_anchor_figures_where_the_log_states_its_noise_or_has_no_imu_or_odometry():
    log = _log(rate=100.0, speed=1.0, sigma=0.1)
    stated = dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], 0.3))
    assert anchor_noise(stated) is None and with_anchor_noise(stated, {})[:2] == (stated, {})
    ranges_only = dataclasses.replace(log, inputs=np.empty((0, 7)), input_kind="none")
    assert with_anchor_noise(ranges_only, {})[2] is None


def test_a_stated_std_far_from_an_anchors_own_noise_gives_way_to_it():
    """Anchors' noise 0.1 m; the std stated ten times too small on anchor 2 alone (a
    firmware's per-anchor figure), or on every anchor (another unit): those anchors' ranges
    take their own figures, with a note naming them; the radio's one figure stated alike on
    every anchor stays where one anchor reads noisier (a path blocked: its excess's changes),
    as does any std the user keeps (``stated_std=1``)."""
    log = _log(rate=100.0, speed=1.0, sigma=0.1)
    h = log.beacon_index(log.ranges[:, 1])
    own = anchor_noise(log)
    firmware = dataclasses.replace(log, range_std=np.where(h == 2, 0.01, 0.1))
    out, options, note = with_anchor_noise(firmware, {"q_imu": 0.02})
    assert options == {"q_imu": 0.02}
    np.testing.assert_array_equal(out.range_std, np.where(h == 2, own[2], 0.1))
    assert note == (
        f"ranges.csv's std of anchor 2 (0.01 m, median) lies more than 5 times from the "
        f"ranges' own noise ({own[2]:.3g} m): those ranges weighed by their own noise (--tune "
        "stated_std=1 keeps the std stated; is it in metres, and the radio's?)"
    )
    unit = dataclasses.replace(log, range_std=np.full(h.size, 0.01))
    out, _, note = with_anchor_noise(unit, {})
    np.testing.assert_array_equal(out.range_std, own[h])
    assert note.startswith("ranges.csv's std of anchors 0, 1, 2, 3 (0.01, 0.01, 0.01, 0.01 m")
    for kept in ({"stated_std": 1.0}, {"anchor_sigma": 0.0}, {"range_sigma": 0.2}):
        same, _, note = with_anchor_noise(unit, kept)
        assert same is unit and "every filter corrects with the stated std" in note
    blocked = _log(rate=100.0, speed=1.0, sigma=[0.1, 0.1, 0.6, 0.1])
    radio = dataclasses.replace(blocked, range_std=np.full(h.size, 0.1))
    assert with_anchor_noise(radio, {})[0] is radio and anchor_noise(blocked)[2] > 0.5
    right = dataclasses.replace(log, range_std=np.full(h.size, 0.1))
    assert with_anchor_noise(right, {}) == (right, {}, None)


def test_anchor_sigma_is_a_switch_the_setup_does_not_take():
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.estimators import parse_tuning, tuning_fields

    assert parse_tuning(["anchor_sigma=0"]) == {"anchor_sigma": 0.0}
    assert tuning_fields({"stated_std": 1.0}) == {}
    with pytest.raises(QuadobsError, match="anchor_sigma: expected 0"):
        parse_tuning(["anchor_sigma=2"])
    assert tuning_fields({"anchor_sigma": 1.0, "q_imu": 0.1}) == {"q_imu": 0.1}


def test_the_replay_says_each_anchor_s_figure_and_keeps_it_in_the_summary(tmp_path, capsys):
    import json

    from quadobs.cli import main
    from quadobs.testbed.logs import write_log

    log = _log(rate=100.0, speed=1.0, sigma=[0.08, 0.24, 0.08, 0.08], seconds=10.0)
    write_log(log, tmp_path / "log")
    base = ["replay", str(tmp_path / "log"), "--calibrate", "none", "--estimators", "ekf"]
    summaries = {}
    runs = (("own", []), ("pooled", ["--tune", "anchor_sigma=0"]))
    runs += (("grid", ["--set", "noise.dropout=0"]),)  # on the grid: one figure for all
    for name, extra in runs:
        path = tmp_path / f"{name}.json"
        assert main([*base, "--no-progress", "--summary", str(path), *extra]) == 0
        summaries[name] = json.loads(path.read_text())["noise"]
    said = capsys.readouterr().out
    assert said.count("ranges' noise by anchor") == 1
    sigma = anchor_noise(log)
    assert summaries["own"]["range_std_by_anchor"] == pytest.approx(list(sigma))
    assert summaries["pooled"]["range_std_by_anchor"] is None
    assert summaries["grid"]["range_std_by_anchor"] is None
    assert summaries["own"]["range_sigma"] == summaries["pooled"]["range_sigma"]


def test_a_stated_std_far_off_is_said_by_the_import_and_on_the_grid():
    """Where the replay's check per anchor does not run (``--set noise.*``), or before it runs
    (an import's notes of what the replay will do), the stated std is still judged."""
    import argparse

    from quadobs.cli import _check_imported, _replay_noise

    log = _log(rate=100.0, speed=1.0, sigma=0.1)
    unit = dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], 0.01))
    grid = argparse.Namespace(tune=[], set=["noise.range_std=0.1"])
    _, _, note = _replay_noise(grid, unit)
    assert note.startswith("ranges.csv states a std of 0.01 m (median), where the ranges' own")
    notes = _check_imported(unit, "map.toml")
    assert any(n.startswith("(replay) ranges.csv's std of anchors 0, 1, 2, 3") for n in notes)
