"""TDOA in the episode loop: `quadobs run` of the TDOA scenarios runs the TDOA estimators on the
radio's differences at their own times, the log export writes them to tdoa.csv, and the replay
of that log gives the estimators the same measurements."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.logs import read_log
from quadobs.testbed.registry import TDOA_ESTIMATORS
from quadobs.testbed.scenario import load_scenario

#: A short quadrotor flight: one second of take-off and of landing around the figure eight,
#: on the estimate from 2.5 s.
SHORT = ["quadrotor.takeoff=1", "quadrotor.landing=1", "control.switch_time=2.5"]


def test_quadrotor_tdoa_runs_the_tdoa_estimators_and_flies_on_one(tmp_path):
    summary = tmp_path / "s.json"
    args = ["run", "quadrotor-tdoa", "--duration", "4", "--no-progress", "--summary", str(summary)]
    for s in SHORT:
        args += ["--set", s]
    assert main(args) == 0
    out = json.loads(summary.read_text())
    assert list(out["estimators"]) == list(TDOA_ESTIMATORS)
    for name, est in out["estimators"].items():
        rmse = est["flight_position_rmse"]
        assert math.isfinite(rmse) and rmse < 0.3, (name, rmse)
    flight = out["flight"]
    assert flight["feedback"] == "tdoa-handover" and not flight["crashed"]
    assert flight["time_on_estimate"] == pytest.approx(1.5)


def test_an_estimator_without_a_tdoa_model_is_refused_by_name():
    with pytest.raises(QuadobsError, match="'augmented' takes no tdoa measurements"):
        from quadobs.testbed.episode import run_episode

        run_episode(load_scenario("tdoa-room", duration=0.5), estimators=["augmented"])
    with pytest.raises(QuadobsError, match="'tdoa-observer' takes TDOA"):
        from quadobs.testbed.episode import run_episode

        run_episode(load_scenario("ifac2021", duration=0.5), estimators=["tdoa-observer"])


@pytest.fixture(scope="module")
def room_run(tmp_path_factory):
    """tdoa-room, 3 s, with its log export (every step's estimates kept), and the log read back."""
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.logs.export import LogExportSink

    folder = tmp_path_factory.mktemp("tdoa") / "log"
    sc = load_scenario("tdoa-room", duration=3.0)
    names = ["ekf", "tdoa-handover"]
    ep = run_episode(sc, estimators=names, collect_every=1, sinks=[LogExportSink(folder)])
    return sc, ep, read_log(folder)


def test_the_point_mass_measures_tdoa_with_its_radio_seeded(room_run):
    from quadobs.testbed.episode import run_episode

    sc, ep, log = room_run
    again = run_episode(sc, estimators=["ekf", "tdoa-handover"], collect_every=1)
    for name in ("ekf", "tdoa-handover"):
        X = ep.trace["estimates"][name]
        assert np.array_equal(X, again.trace["estimates"][name])
        e = np.linalg.norm(X[-1000:, :3] - ep.trace["truth"][-1000:, :3], axis=1)
        assert e.max() < 0.15, name  # the last second, from a guess 1 m off


def test_the_exported_tdoa_are_the_radios_own(room_run):
    """tdoa.csv holds the differences the radio gave: a fresh radio of the same seed, fed the
    logged truth step by step, gives the same times, pairs and values."""
    from quadobs.testbed.uwb import radio_of

    sc, _, log = room_run
    assert (
        log.ranges.shape[0] == 0 and log.tdoa.shape[0] == 298
    )  # 100 Hz from 10 ms, the first undifferenced
    radio, truth = radio_of(sc), log.truth
    events = []
    for k in range(sc.steps):
        p, v = truth[k, 1:4], truth[k, 4:7]
        events += radio.take(k * sc.dt, (k + 1) * sc.dt, p, v)
    expected = np.array([(m.t, *m.anchors, m.value) for m in events])
    np.testing.assert_array_equal(log.tdoa[:, :3], expected[:, :3])
    np.testing.assert_allclose(log.tdoa[:, 3], expected[:, 3], rtol=0, atol=1e-12)
    assert np.all(log.tdoa_std == sc.radio.std)


def test_the_exported_tdoa_log_replays_as_it_ran(room_run):
    from quadobs.testbed.logs.replay import default_estimators, run_replay

    sc, ep, log = room_run
    assert default_estimators(log) == ["tdoa-handover", "tdoa-observer", "ekf", "ukf"]
    from quadobs.testbed.factories import baseline_settings

    # the scenario's EKF noise and prior, so that only the log stands between the two runs
    s = baseline_settings(sc)
    q = float(np.asarray(s.dynamics.input_covariance)[0, 0]) * sc.dt
    options = {"q_imu": q, "P0": float(np.asarray(s.P0)[0, 0]), "range_sigma": 0.1 / math.sqrt(2)}
    x0 = ep.trace["estimates"]["ekf"][0]
    r = run_replay(
        log, estimators=["ekf"], dt=sc.dt, x0=x0, batch=False, burn_in=1.0, setup_options=options
    )
    t = ep.trace["time"]
    e = (ep.trace["estimates"]["ekf"][:, :3] - ep.trace["truth"][:, :3])[t >= 1.0]
    live = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
    assert r["estimators"]["ekf"]["rmse"] == pytest.approx(live, rel=0.1)


def test_the_replays_tdoa_estimators_need_tdoa_and_an_acceleration():
    from quadobs.testbed.logs.estimators import ReplaySetup, build_replay_estimators

    anchors = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 3.0]])
    for kinds, model, reason in (
        (("range",), "imu", "'tdoa-observer' takes TDOA"),
        (("tdoa",), "cv", "'tdoa-observer' needs an acceleration input"),
    ):
        setup = ReplaySetup(anchors, 0.01, model, 0.0, 5.0, input_kind="imu", kinds=kinds)
        with pytest.raises(QuadobsError, match=reason):
            build_replay_estimators(setup, ["tdoa-observer"], np.zeros(6))
    setup = ReplaySetup(anchors, 0.01, "imu", 0.0, 5.0, input_kind="imu", kinds=("tdoa",))
    obs, hand = build_replay_estimators(setup, ["tdoa-observer", "tdoa-handover"], np.ones(6))
    assert obs.name == "tdoa-observer" and hand.name == "tdoa-handover"
    assert np.array_equal(hand.x_hat, np.ones(6)) and "tdoa" in hand.measurement_models
