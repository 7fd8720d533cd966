"""The live excitation monitor in a MuJoCo episode: the degenerate scenario, its recording and summary."""

import json

import numpy as np
import pytest

from quadobs import load_scenario
from quadobs.recording import list_entities, read_series, read_text_log
from quadobs.testbed.episode import run_episode


@pytest.fixture(scope="module")
def degenerate_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("degenerate")
    rrd, js = out / "degenerate.rrd", out / "degenerate.json"
    sc = load_scenario("degenerate")
    result = run_episode(sc, out=rrd, summary_path=js)
    return sc, rrd, js, result.summary


def _at(series, t):
    """The last recorded value at or before ``t``."""
    i = np.searchsorted(series["sim_time"], t + 1e-9) - 1
    return series["values"][i, 0]


def test_monitor_flags_the_coasting_segments_from_the_measured_input(degenerate_run):
    """The monitor fed MuJoCo's (noisy) accelerometer flags each coast once, within the window of its ends.

    A low segment [a, b) for the coast [c0, c1): c0 < a <= max(c0 + delta, delta) + P and
    c1 < b <= c1 + delta + P (delta the window, P the update period; see
    tests/test_excitation.py for the reasoning), and nowhere else.
    """
    sc, _, js, summary = degenerate_run
    ex = json.loads(js.read_text())["excitation"]
    assert ex == summary["excitation"]
    delta, P = ex["window"], ex["update_period"]
    segs = ex["low_segments"]
    assert len(segs) == len(sc.trajectory.coast) == 2
    for (a, b), (c0, c1) in zip(segs, sc.trajectory.coast):
        assert c0 < a <= max(c0 + delta, delta) + P + 1e-9
        assert c1 < b <= c1 + delta + P + 1e-9
    assert ex["min_measure"] < 1e-8 < ex["threshold"]


def test_recording_shows_measure_warning_and_covariance(degenerate_run):
    sc, rrd, _, summary = degenerate_run
    entities = set(list_entities(rrd))
    for e in [
        "/excitation/measure",
        "/excitation/threshold",
        "/excitation/log10",
        "/excitation/unexcited_variance/augmented",
    ]:
        assert e in entities
    mu = read_series(rrd, "excitation/measure")
    assert mu["sim_time"][0] == pytest.approx(sc.excitation.window)  # first full window
    segs = summary["excitation"]["low_segments"]
    # measure below the threshold exactly on the flagged segments
    low = mu["values"][:, 0] < sc.excitation.threshold
    in_seg = np.zeros_like(low)
    for a, b in segs:
        in_seg |= (mu["sim_time"] >= a - 1e-9) & (mu["sim_time"] < b - 1e-9)
    np.testing.assert_array_equal(low, in_seg)
    # one warning, at the start of the first low segment
    events = [e for e in read_text_log(rrd, "events") if e[2] == "WARN"]
    assert (
        len(events) == 1
        and events[0][1] == pytest.approx(segs[0][0])
        and "excitation low" in events[0][3]
    )

    # Second coast [20, 32.57): the variance in the unexcited directions grows, the error drifts,
    # and both recover once the motion resumes.
    a, b = segs[1]
    var = read_series(rrd, "excitation/unexcited_variance/augmented")
    err = read_series(rrd, "errors/augmented/position/norm")
    v_early, v_late = _at(var, a + 2.0), _at(var, 32.5)
    assert v_late > 1.5 * v_early
    e_in = err["values"][(err["sim_time"] > 24.0) & (err["sim_time"] < 25.0), 0].max()
    e_end = err["values"][(err["sim_time"] > 32.0) & (err["sim_time"] < 33.0), 0].max()
    assert e_end > 3.0 * e_in
    assert summary["final_position_error"] < e_end


def test_monitor_reuses_the_observer_immersion_and_reports_the_same():
    """The monitor takes the augmented observer's immersion of the whole system (not computed twice) and gives
    the same excitation summary as a monitor with its own."""
    from quadobs.testbed.episode import scenario_parts
    from quadobs.testbed.excitation import scenario_monitor

    sc = load_scenario("degenerate", duration=8.0)
    parts = scenario_parts(sc, ["augmented"])
    (obs,) = parts["estimators"]
    shared, own = parts["monitor"], scenario_monitor(sc)
    assert shared.immersion is obs.immersion and own.immersion is not obs.immersion
    u = np.random.default_rng(2).normal(size=(8000, sc.system().p))
    for m in (shared, own):
        k = 0
        while k < len(u):
            take = m.room
            m.push_many(u[k : k + take])
            k += take
    assert json.dumps(shared.summary(), sort_keys=True) == json.dumps(own.summary(), sort_keys=True)


def test_an_observer_fed_in_time_keeps_its_covariance_series():
    """``quadrotor-uwb``'s observer takes its ranges one at a time through a wrapper: the
    recording's unexcited-variance series reads the wrapped observer's covariance."""
    from quadobs.recording.excitation import ExcitationLog
    from quadobs.testbed.episode import scenario_parts

    sc = load_scenario("quadrotor-uwb")
    parts = scenario_parts(sc, ["augmented"])
    (est,) = parts["estimators"]
    assert est.inner.P.shape == (est.immersion.dim, est.immersion.dim)  # a wrapper, as stated

    class Recorder:  # what ExcitationLog declares on a recorder: the series' names
        def __init__(self):
            self.names = []

        def series(self, name, *args, **kwargs):
            self.names.append(name)
            return name

    rec = Recorder()
    log = ExcitationLog(rec, parts["monitor"], [est])
    assert "excitation/unexcited_variance/augmented" in rec.names
    assert log.weak["augmented"][0] is est.inner
