"""The simulated UWB radio: schedule, error sources against closed forms, seeds."""

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.uwb import RadioConfig, Room, UwbRadio, radio_of, room_model_path

ANCHORS = np.array(
    [[-3, -3, 0.2], [3, -3, 0.2], [3, 3, 0.2], [-3, 3, 0.2], [-3, -3, 2.8], [3, -3, 2.8]],
    dtype=float,
)


def still(p):
    return lambda t: np.asarray(p, dtype=float)


def figure(t):
    return np.array([2 * np.sin(0.3 * t), 1.2 * np.sin(0.6 * t), 1.5 + 0.4 * np.sin(0.3 * t)])


def test_round_robin_one_anchor_at_a_time_at_the_rate():
    radio = UwbRadio(ANCHORS, RadioConfig(rate=60.0, std=1e-9), seed=0)
    ms = radio.measurements(still([0.5, 0.2, 1.0]), 1.0)
    assert [m.anchors[0] for m in ms] == [k % 6 for k in range(len(ms))]
    assert len(ms) == 59  # events at k / 60 s, k = 1 .. 59, inside [0, 1)
    assert np.allclose(np.diff([m.t for m in ms]), 1 / 60, atol=1e-3)


def test_noise_free_range_is_the_distance_plus_the_bias():
    biases = (0.1, -0.2, 0.3, 0.0, 0.05, -0.4)
    radio = UwbRadio(ANCHORS, RadioConfig(std=1e-12, biases=biases), seed=3)
    for m in radio.measurements(figure, 0.5):
        true = np.linalg.norm(figure(m.t) - ANCHORS[m.anchors[0]])
        # the tag moves linearly inside one physics step: an error of order |a| dt^2
        assert abs(m.value - true - biases[m.anchors[0]]) < 1e-5


def test_drawn_biases_follow_the_seed_and_the_stated_spread():
    a = UwbRadio(ANCHORS, RadioConfig(bias_std=0.3), seed=1).biases
    b = UwbRadio(ANCHORS, RadioConfig(bias_std=0.3), seed=1).biases
    c = UwbRadio(ANCHORS, RadioConfig(bias_std=0.3), seed=2).biases
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.all(np.abs(a) < 5 * 0.3)


def test_same_seed_same_events_and_sources_independent():
    cfg = RadioConfig(jitter=2e-3, dropout=0.1, outlier_probability=0.05, outlier_std=1.0)
    one = UwbRadio(ANCHORS, cfg, seed=7).measurements(figure, 1.0)
    two = UwbRadio(ANCHORS, cfg, seed=7).measurements(figure, 1.0)
    assert one == two
    # without dropouts, the surviving events keep their times and values
    full = UwbRadio(ANCHORS, RadioConfig(**{**cfg.__dict__, "dropout": 0.0}), 7)
    kept = {m.t: m.value for m in full.measurements(figure, 1.0)}
    assert all(kept[m.t] == m.value for m in one)


def test_level_bias_adds_k_log10_of_the_distance_and_leaves_other_draws():
    cfg = RadioConfig(std=1e-12, biases=(0.1, -0.2, 0.3, 0.0, 0.05, -0.4), level_bias=-0.15)
    for m in UwbRadio(ANCHORS, cfg, seed=3).measurements(figure, 0.5):
        d = np.linalg.norm(figure(m.t) - ANCHORS[m.anchors[0]])
        assert abs(m.value - d - cfg.biases[m.anchors[0]] + 0.15 * np.log10(d)) < 1e-5
    # at an anchor: held at its value at NEAR_FIELD, no unbounded term
    near = UwbRadio(ANCHORS, RadioConfig(std=1e-12, level_bias=-0.1), seed=0)
    at = near.measurements(still(ANCHORS[0] + [1e-9, 0.0, 0.0]), 0.2)
    values = [m.value for m in at if m.anchors[0] == 0]
    assert values and np.allclose(values, -0.1 * np.log10(0.1), atol=1e-8)
    plain = RadioConfig(jitter=2e-3, outlier_probability=0.05, outlier_std=1.0, bias_std=0.2)
    level = RadioConfig(**{**plain.__dict__, "level_bias": 0.2})
    one, two = UwbRadio(ANCHORS, plain, 7), UwbRadio(ANCHORS, level, 7)
    for m, n in zip(one.measurements(figure, 1.0), two.measurements(figure, 1.0), strict=True):
        d = np.linalg.norm(figure(m.t) - ANCHORS[m.anchors[0]])
        assert m.t == n.t and n.value == pytest.approx(m.value + 0.2 * np.log10(d), abs=1e-5)


def test_pattern_bias_is_the_second_order_direction_term_of_stated_spread():
    """``u^T S u``: each range less its distance and constant bias is the direction term, with
    ``S`` symmetric and traceless; over the sphere of directions its mean is 0 and its
    standard deviation ``pattern``; a radio without it draws the same events as before."""
    cfg = RadioConfig(std=1e-12, biases=(0.1, -0.2, 0.3, 0.0, 0.05, -0.4), pattern=0.1)
    radio = UwbRadio(ANCHORS, cfg, seed=3)
    S = radio.pattern_forms
    assert np.allclose(S, S.transpose(0, 2, 1)) and np.allclose(np.trace(S, axis1=1, axis2=2), 0)
    for m in radio.measurements(figure, 0.5):
        i, p = m.anchors[0], figure(m.t)
        u = (p - ANCHORS[i]) / np.linalg.norm(p - ANCHORS[i])
        expected = np.linalg.norm(p - ANCHORS[i]) + cfg.biases[i] + u @ S[i] @ u
        assert abs(m.value - expected) < 1e-5
        assert radio.pattern_bias(i, p) == pytest.approx(u @ S[i] @ u)
    # a Fibonacci lattice of directions: nearly uniform on the sphere
    k = np.arange(20000) + 0.5
    z, phi = 1 - 2 * k / k.size, np.pi * (1 + 5**0.5) * k
    dirs = np.column_stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
    values = np.einsum("ni,hij,nj->nh", dirs, S, dirs)  # (directions, anchors)
    assert np.allclose(values.mean(axis=0), 0.0, atol=1e-4)
    assert np.allclose(values.std(axis=0), 0.1, rtol=1e-3)
    # even in u: over the whole sphere apart from a displaced anchor's term, which is odd in u
    assert np.allclose(np.einsum("ni,hij,nj->nh", -dirs, S, -dirs), values)
    plain = RadioConfig(jitter=2e-3, outlier_probability=0.05, outlier_std=1.0, bias_std=0.2)
    with_pattern = RadioConfig(**{**plain.__dict__, "pattern": 0.1})
    a = UwbRadio(ANCHORS, plain, 7)
    b = UwbRadio(ANCHORS, with_pattern, 7)
    assert not a.pattern_forms.any() and np.array_equal(a.biases, b.biases)
    for m, n in zip(a.measurements(figure, 1.0), b.measurements(figure, 1.0), strict=True):
        assert m.t == n.t and m.anchors == n.anchors
        p = figure(m.t)
        assert n.value == pytest.approx(m.value + b.pattern_bias(m.anchors[0], p), abs=1e-5)
    again = UwbRadio(ANCHORS, with_pattern, 7).pattern_forms
    assert np.array_equal(again, b.pattern_forms)
    assert not np.array_equal(UwbRadio(ANCHORS, with_pattern, 8).pattern_forms, b.pattern_forms)


def test_per_anchor_rates():
    rates = (10.0, 20.0, 30.0, 40.0, 50.0, 25.0)
    radio = UwbRadio(ANCHORS, RadioConfig(rates=rates, jitter=1e-3), seed=0)
    ms = radio.measurements(still([0, 0, 1]), 2.0)
    counts = np.bincount([m.anchors[0] for m in ms], minlength=6)
    assert np.all(np.abs(counts - 2.0 * np.array(rates)) <= 1)
    times = [m.t for m in ms]
    assert times == sorted(times)


def test_jitter_moves_times_but_keeps_their_order():
    radio = UwbRadio(ANCHORS, RadioConfig(rate=100.0, jitter=3e-3), seed=4)
    t = np.array([m.t for m in radio.measurements(still([0, 0, 1]), 1.0)])
    assert np.all(np.diff(t) > 0)
    dev = t - 0.01 * np.arange(1, len(t) + 1)
    assert 1e-3 < dev.std() < 4e-3 and np.abs(dev).max() <= 0.45 * 0.01 + 1e-12


def test_dropout_fraction():
    radio = UwbRadio(ANCHORS, RadioConfig(rate=200.0, dropout=0.2), seed=5)
    ms = radio.measurements(still([0, 0, 1]), 10.0)
    total = radio.counts["dropped"] + len(ms)
    frac = radio.counts["dropped"] / total
    assert abs(frac - 0.2) < 4 * np.sqrt(0.2 * 0.8 / total)


def test_room_blocks_the_segment_through_the_pillar_only():
    room = Room(room_model_path())
    # the pillar: a box of half-size 0.25 around (0, 2.2), from the floor to 3 m
    assert room.blocked(np.array([0.0, 3.0, 1.0]), np.array([0.0, 1.0, 1.0]))
    assert not room.blocked(np.array([1.0, 3.0, 1.0]), np.array([1.0, 1.0, 1.0]))
    # a segment that ends before the pillar is not blocked by it
    assert not room.blocked(np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.8, 1.0]))


def test_nlos_excess_is_positive_and_heavy_tailed():
    anchors = np.array([[0.0, 3.0, 1.0], [3.0, 0.0, 1.0]])
    cfg = RadioConfig(std=1e-12, nlos_median=0.3, nlos_shape=0.8, room=str(room_model_path()))
    radio = UwbRadio(anchors, cfg, seed=9)
    p = np.array([0.0, 1.0, 1.0])
    assert radio.line_of_sight(p).tolist() == [False, True]
    ms = radio.measurements(still(p), 20.0)
    excess = np.array([m.value - np.linalg.norm(p - anchors[m.anchors[0]]) for m in ms])
    blocked = np.array([m.anchors[0] == 0 for m in ms])
    assert np.all(excess[blocked] > 0) and np.all(np.abs(excess[~blocked]) < 1e-9)
    e = excess[blocked]
    assert abs(np.median(e) - 0.3) < 0.05
    assert e.mean() > np.median(e)  # right-skewed: the log-normal's mean exceeds its median
    assert radio.counts["nlos"] == blocked.sum()


def test_tdoa_pairs_differences_and_per_pair_bias():
    biases = (0.1, -0.2, 0.3, 0.0, 0.05, -0.4)
    radio = UwbRadio(ANCHORS, RadioConfig(protocol="tdoa", std=1e-12, biases=biases), seed=2)
    p = np.array([0.3, -0.4, 1.2])
    ms = radio.measurements(still(p), 1.0)
    assert all(m.kind == "tdoa" and m.anchors[0] != m.anchors[1] for m in ms)
    for prev, m in zip(ms, ms[1:]):
        assert m.anchors[1] == prev.anchors[0]  # differenced with the previous packet
    for m in ms:
        i, j = m.anchors
        d = np.linalg.norm(p - ANCHORS[i]) - np.linalg.norm(p - ANCHORS[j])
        assert abs(m.value - d - radio.pair_bias(i, j)) < 1e-9
    assert len({m.anchors for m in ms}) > 10  # a random order, not a fixed cycle


@pytest.mark.parametrize(
    "change, field",
    [
        ({"protocol": "uwb"}, "radio.protocol"),
        ({"rate": 0.0}, "radio.rate"),
        ({"dropout": 1.0}, "radio.dropout"),
        ({"biases": (0.1,)}, "radio.biases"),
        ({"rates": (1.0,) * 6, "protocol": "tdoa"}, "radio.rates"),
        ({"room": "/nonexistent/room.xml"}, "radio.room"),
        ({"pattern": -0.1}, "radio.pattern"),
        ({"level_bias": float("nan")}, "radio.level_bias"),
    ],
)
def test_bad_settings_are_named(change, field):
    with pytest.raises(QuadobsError, match=field):
        UwbRadio(ANCHORS, RadioConfig(**change), seed=0)


def test_realistic_quadrotor_feeds_each_range_at_its_own_time():
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario

    scenario = load_scenario("quadrotor-uwb-realistic", duration=6.5)
    result = run_episode(scenario, estimators=["ekf-bias", "augmented"])
    ekf = result.summary["estimators"]["ekf-bias"]
    # 100 exchanges a second for 6.5 s, less the dropped ones, each corrected or rejected
    # (but the first round, taken by the start-up multilateration); the radio states its
    # non-line-of-sight excess, so the bias filters weigh each range by it (ExcessMixture)
    # and reject only outliers (1 % of the ranges, those beyond the gate)
    tried = ekf["corrections"] + ekf["rejected"]
    assert 560 < tried < 650 and ekf["rejected"] < 0.02 * tried
    assert "non-line-of-sight mixture" in ekf["robust"] and ekf.get("diverged") is None
    # started 20 m off: within 1 m in well under the 2 s target, and it stays there
    assert ekf["time_to_1m"] < 2.0 and ekf["final_position_error"] < 0.5


def test_radio_table_needs_a_tag_without_wind():
    from quadobs.testbed.scenario import load_scenario

    with pytest.raises(QuadobsError, match="radio"):
        load_scenario("wind", settings=["radio.rate=50"])
    assert load_scenario("ifac2021", settings=["radio.rate=50"]).radio.rate == 50.0
    # a planar tag: the anchors in the plane z = 0 (rover-room)
    planar = load_scenario("beacons2d", settings=["radio.rate=50"])
    assert planar.radio.rate == 50.0 and radio_of(planar).anchors[:, 2].tolist() == [0.0] * 3


def test_tdoa_radio_is_refused_by_name_by_an_estimator_without_a_tdoa_model():
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario

    scenario = load_scenario(
        "quadrotor-uwb-realistic", duration=7.0, settings=["radio.protocol=tdoa"]
    )
    with pytest.raises(QuadobsError, match="'augmented' takes no tdoa measurements"):
        run_episode(scenario, estimators=["augmented"])
