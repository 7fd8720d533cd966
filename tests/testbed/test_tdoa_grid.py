"""TDOA on the fixed grid: the TDoA3-like schedule, pairs as outputs, the reference flight."""

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.scenario import load_scenario
from quadobs.testbed.tdoa import (
    fly_reference,
    measurements,
    ordered_pairs,
    tdoa3_sequence,
    tdoa_outputs,
)


def test_schedule_never_repeats_an_anchor_and_visits_pairs_evenly():
    seq = tdoa3_sequence(np.random.default_rng(0), 8, 56_000)
    assert np.all(seq[1:] != seq[:-1])
    counts = np.zeros((8, 8))
    np.add.at(counts, (seq[1:], seq[:-1]), 1)
    off = counts[~np.eye(8, dtype=bool)]
    assert off.min() > 0.85 * off.mean() and off.max() < 1.15 * off.mean()


def test_outputs_are_the_pair_differences_at_the_packet_steps():
    anchors = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0]])
    positions = np.random.default_rng(1).uniform(0, 3, (50, 2))
    rngs = [np.random.default_rng(s) for s in (2, 3)]
    Y = tdoa_outputs(positions, anchors, 5, 0.0, *rngs)
    pairs = ordered_pairs(3)
    assert Y.shape == (50, 6)
    present = np.isfinite(Y)
    assert np.array_equal(present.sum(axis=1), (np.arange(50) % 5 == 0).astype(int))
    for k, h in zip(*np.nonzero(present)):
        i, j = pairs[h]
        r = np.linalg.norm(positions[k] - anchors, axis=1)
        assert Y[k, h] == pytest.approx(r[i] - r[j], abs=1e-12)
    events = measurements(Y, 0.01, 0.1)
    assert [len(e) for e in events[:6]] == [1, 0, 0, 0, 0, 1]
    assert events[5][0].t == pytest.approx(0.05) and events[5][0].kind == "tdoa"


def test_reference_flight_is_seeded_and_consistent():
    sc = load_scenario("tdoa-room").with_overrides(duration=1.0)
    a, b = fly_reference(sc, 3), fly_reference(sc, 3)
    assert np.array_equal(a.outputs, b.outputs, equal_nan=True)
    assert not np.array_equal(a.outputs, fly_reference(sc, 4).outputs, equal_nan=True)
    np.testing.assert_allclose(a.truth[0], sc.true_state(0.0))
    np.testing.assert_allclose(a.truth[-1], sc.true_state(1.0), atol=1e-6)
    assert np.isfinite(a.outputs).sum() == 100  # 100 Hz for 1 s


def test_scenario_without_tdoa_is_refused():
    with pytest.raises(QuadobsError, match='protocol = "tdoa"'):
        fly_reference(load_scenario("quadrotor-uwb"))
    with pytest.raises(QuadobsError, match="radio.rate"):  # the grid needs a whole interval
        fly_reference(load_scenario("tdoa-room", settings=["radio.rate=300.0"]))


def test_the_former_tdoa_table_is_read_as_the_radio_with_a_warning():
    with pytest.warns(DeprecationWarning, match=r"\[tdoa\] table is deprecated"):
        sc = load_scenario("tdoa-room", settings=["tdoa.std=0.2", "tdoa.rate=50.0"])
    assert sc.radio.protocol == "tdoa" and sc.tdoa.std == 0.2 and sc.tdoa.rate == 50.0
    assert "tdoa" not in sc.to_dict() and sc == load_scenario(sc.to_dict()["name"]).with_settings(
        {"radio.std": 0.2, "radio.rate": 50.0}
    )
    with pytest.raises(QuadobsError, match="tdoa: deprecated"):
        load_scenario("quadrotor-uwb-realistic", settings=["tdoa.std=0.2"])
    with pytest.raises(QuadobsError, match="tdoa.std"):
        load_scenario("tdoa-room", settings=["tdoa.std=-1"])


def test_quadrotor_flies_on_a_tdoa_estimate_seeded():
    """A short MuJoCo flight flown on the TDOA observer from the start: same seed, same flight."""
    from quadobs.estimators.tdoa_observer import TdoaObserver
    from quadobs.testbed.factories import baseline_settings
    from quadobs.testbed.tdoa import fly_world

    sc = load_scenario("quadrotor-tdoa").with_settings(
        {
            "duration": 4.5,
            "quadrotor.takeoff": 2.0,
            "quadrotor.landing": 2.0,
            "control.switch_time": 1.0,
        }
    )

    psd = float(baseline_settings(sc).dynamics.input_covariance[0, 0]) * sc.dt

    def make(x0):
        obs = TdoaObserver(
            sc.beacons, sc.dt, x0, P0=0.01, std=0.1, accel_psd=psd, pairs=ordered_pairs(8)
        )
        return {"obs": obs}

    def run():
        return fly_world(sc, make, "obs", seed=1)[0]

    a, b = run(), run()
    assert a.crashed_at is None
    assert np.array_equal(a.estimates["obs"], b.estimates["obs"])
    assert a.truth.shape == (4501, 6) and np.isfinite(a.truth).all()
    err = np.linalg.norm(a.estimates["obs"][:, :3] - a.truth[:, :3], axis=1)
    assert err.max() < 0.5
    with pytest.raises(QuadobsError, match="flown_on"):
        fly_world(sc, make, "ekf")


def test_point_mass_world_with_tdoa_pairs_end_to_end():
    """tdoa-room in the MuJoCo point-mass world: pairs as outputs, the observer from 10 m off."""
    from quadobs.estimators.tdoa_observer import TdoaObserver
    from quadobs.testbed.tdoa import fly_world

    sc = load_scenario("tdoa-room").with_overrides(duration=3.0)
    psd = sc.noise.sigma("accel") ** 2 * sc.dt

    def make(x0):
        far = x0 + np.array([10.0, 0, 0, 0, 0, 0])
        obs = TdoaObserver(
            sc.beacons,
            sc.dt,
            far,
            P0=[100.0] * 3 + [0.01] * 3,
            accel_psd=psd,
            pairs=ordered_pairs(8),
        )
        return {"obs": obs}

    flight, ests = fly_world(sc, make, seed=2)
    np.testing.assert_allclose(flight.truth[0], sc.true_state(0.0), atol=1e-9)
    err = np.linalg.norm(flight.estimates["obs"][:, :3] - flight.truth[:, :3], axis=1)
    assert err[0] == pytest.approx(10.0)
    assert err[-1] < 0.5
    assert ests["obs"].corrections == 300
