"""Faulty measurements in an episode: dropouts and slow ranges mean predict-only, outliers meet the NIS gate."""

import numpy as np
import pytest

from quadobs import load_scenario
from quadobs.recording import read_series, read_text_log
from quadobs.testbed.episode import run_episode
from quadobs.testbed.scenario import parse_scenario


@pytest.fixture(scope="module")
def outlier_run(tmp_path_factory):
    rrd = tmp_path_factory.mktemp("outliers") / "run.rrd"
    result = run_episode(load_scenario("ifac2021-outliers"), out=rrd, collect_every=20)
    return rrd, result


def test_outliers_are_rejected_counted_and_the_estimate_converges(outlier_run):
    _, result = outlier_run
    s = result.summary
    m, est = s["measurements"], s["estimators"]["augmented"]
    assert m["range_period_steps"] == 20  # 50 Hz ranges at 1 kHz physics
    samples = 30000 // 20
    # 10 % dropouts, 2 % outliers among the delivered samples
    assert 0.07 * samples < m["dropped"] < 0.13 * samples
    assert 0.01 * samples < m["outliers_injected"] < 0.03 * samples
    # every correction attempt is either applied or rejected; the dropped samples are neither
    assert est["corrections"] + est["rejected"] == samples - m["dropped"]
    # nearly every outlier is rejected (a few small ones pass), and nearly nothing else
    assert est["gate"] == 16.0
    assert abs(est["rejected"] - m["outliers_injected"]) <= max(3, 0.15 * m["outliers_injected"])
    assert est["final_position_error"] < 0.5 and est["time_to_1m"] < 20.0


def test_the_recording_holds_the_counts(outlier_run):
    rrd, result = outlier_run
    s = result.summary
    rejected = read_series(rrd, "observer/augmented/rejected")
    outliers = read_series(rrd, "measurements/outliers")
    dropped = read_series(rrd, "measurements/dropped")
    for series in (rejected, outliers, dropped):
        np.testing.assert_array_equal(series["step"], np.arange(30001))
        assert np.all(np.diff(series["values"][:, 0]) >= 0)  # running counts
    assert rejected["values"][-1, 0] == s["estimators"]["augmented"]["rejected"]
    assert outliers["values"][-1, 0] == s["measurements"]["outliers_injected"]
    assert dropped["values"][-1, 0] == s["measurements"]["dropped"]
    # a rejection happens exactly at a step whose recorded NIS exceeds the gate
    nis = read_series(rrd, "observer/augmented/nis")
    jumps = rejected["step"][np.flatnonzero(np.diff(rejected["values"][:, 0], prepend=0.0))]
    np.testing.assert_array_equal(jumps, nis["step"][nis["values"][:, 0] > 16.0])
    # the recorded ranges show the outliers and the gaps
    ranges = read_series(rrd, "measurements/range/0")
    assert len(ranges["step"]) == 30000 // 20 - s["measurements"]["dropped"]
    events = read_text_log(rrd, "events")
    assert any("corrections rejected by the NIS gate 16" in text for _, _, _, text in events)


def test_without_the_gate_the_outliers_spoil_the_estimate(outlier_run):
    """Same seed, same measurements, no gate: the late error is several times larger."""
    _, gated = outlier_run
    data = load_scenario("ifac2021-outliers").to_dict()
    del data["observer"]["gate"]
    plain = run_episode(parse_scenario(data), collect_every=20)
    assert plain.summary["measurements"] == gated.summary["measurements"]
    assert plain.summary["estimators"]["augmented"]["rejected"] == 0

    def late_rms(trace):
        late = trace["time"] >= 20.0
        e = trace["estimates"]["augmented"][late, :3] - trace["truth"][late, :3]
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))

    assert late_rms(plain.trace) > 3.0 * late_rms(gated.trace)


def test_missing_samples_mean_predict_only_in_an_episode():
    """Ranges at 100 Hz and 30 % dropouts on a noise-free run: the observer corrects exactly at the
    delivered samples and still converges."""
    data = load_scenario("ifac2021", duration=20.0).to_dict()
    data["noise"] = {"range_rate": 100.0, "dropout": 0.3}
    res = run_episode(parse_scenario(data), collect_every=1)
    s = res.summary
    est = s["estimators"]["augmented"]
    assert est["corrections"] == 20000 // 10 - s["measurements"]["dropped"]
    nis = res.trace["nis"]["augmented"][:-1]
    assert np.count_nonzero(np.isfinite(nis)) == est["corrections"]
    assert np.all(np.isnan(nis[np.arange(nis.size) % 10 != 0]))  # no sample: no correction
    assert s["final_position_error"] < 0.5


def test_a_gated_ekf_on_the_grid_uses_or_rejects_every_range_of_a_step():
    """Four beacons ranged in the same steps, 2 % outliers, the EKF gated at 10.83 (``chi^2(1)``,
    0.999): each range of a step is judged alone, so every delivered sample is corrected with or
    rejected (before, a step's ranges counted once, and one outlier took its step's others)."""
    data = load_scenario("beacons", duration=3.0, seed=2).to_dict()
    data["noise"] = {
        "range_std": 0.2, "range_rate": 50.0, "dropout": 0.1,
        "outlier_probability": 0.02, "outlier_std": 20.0,
    }  # fmt: skip
    data["observer"]["gate"] = 10.83
    data["initial"] = {"kind": "random", "position_spread": 10.0, "velocity_spread": 2.0}
    s = run_episode(parse_scenario(data), estimators=["ekf"], collect_every=20).summary
    m, est = s["measurements"], s["estimators"]["ekf"]
    assert est["corrections"] + est["rejected"] == 4 * (3000 // 20) - m["dropped"]
    assert m["outliers_injected"] > 0 and est["rejected"] >= m["outliers_injected"] - 2
    assert est["final_position_error"] < 0.5
