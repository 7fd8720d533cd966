"""The ranges' own noise as the default ``range_sigma`` of a log that states none: found where the
ranges are dense enough to show it, the prior kept where the motion dominates them."""

import dataclasses
import math

import numpy as np
import pytest

from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.estimators import log_defaults
from quadobs.testbed.logs.range_noise import range_noise, stated_range_noise

ANCHORS = np.array([[-3.0, -3.0, 0.2], [3.0, -3.0, 2.8], [3.0, 3.0, 0.2], [-3.0, 3.0, 2.8]])


def _log(rate, speed, sigma, seconds=20.0, nlos=0.0, radius=2.0):
    """Ranges round-robin over four anchors at ``rate`` Hz, a circle of ``radius`` at ``speed`` m/s,
    Gaussian noise ``sigma`` and a fraction ``nlos`` longer by an exponential 0.5 m; no std."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, seconds, 1.0 / rate) + rng.uniform(0.0, 2e-4, int(round(seconds * rate)))
    w = speed / radius
    p = np.column_stack([radius * np.cos(w * t), radius * np.sin(w * t), 1.5 + 0 * t])
    h = np.arange(t.size) % 4
    r = np.linalg.norm(p - ANCHORS[h], axis=1) + sigma * rng.standard_normal(t.size)
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
