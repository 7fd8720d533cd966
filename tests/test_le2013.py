"""Section 5 of the Automatica 2013 paper: containment over seeded runs, the paper's ordering of
the methods, and ``quadobs run le2013`` (recording and summary)."""

import json

import numpy as np
import pytest

from quadobs import IntervalMatrix, Zonotope, ZonotopicEstimator
from quadobs.cli import main
from quadobs.le2013 import A_INTERVAL, C, F, NOISE_BOUND, design_gains, reproduce, run_once, simulate, summary_of


@pytest.fixture(scope="module")
def designs():
    return design_gains()


@pytest.fixture(scope="module")
def study(designs):
    return reproduce(seed=100, steps=40, runs=12, designs=designs)


def test_true_state_inside_every_set_at_every_step(study):
    for m, frac in study["containment"].items():
        assert frac == 1.0, m


def test_methods_compare_as_in_the_paper(study):
    w = {m: study["mean_width"][m][1:].mean(axis=0) for m in study["methods"]}
    vol = {m: study["mean_volume"][m][1:].mean() for m in study["methods"]}
    final = {m: study["mean_width"][m][-1] for m in study["methods"]}
    # the second approach is tighter than the first and than segment minimisation, in both bounds and volume
    assert np.all(w["pradius2"] < w["segment"]) and vol["pradius2"] < vol["segment"]
    assert np.all(w["pradius2"] < w["pradius1"]) and vol["pradius2"] < vol["pradius1"]
    # the first approach ends tighter than segment minimisation on x2 (its transient is longer)
    assert final["pradius1"][1] < final["segment"][1]
    # volume minimisation has the smallest volume
    assert vol["volume"] <= min(vol.values()) + 1e-12
    # and the P-radius methods are cheaper online than volume minimisation
    assert study["online_us"]["pradius2"] < study["online_us"]["volume"]


def test_a_set_shrinks_from_the_initial_box(study):
    for m in study["methods"]:
        assert np.all(study["mean_width"][m][-1] < 0.25 * study["mean_width"][m][0])


def test_simulation_is_seeded_and_respects_the_bounds():
    a, b, c = simulate(5, 30), simulate(5, 30), simulate(6, 30)
    np.testing.assert_array_equal(a["x"], b["x"])
    assert not np.array_equal(a["x"], c["x"])
    assert np.all(np.abs(a["x"][0]) <= 3.0) and abs(a["delta"]) <= 1.0
    resid = a["y"][1:] - a["x"][1:] @ C.T
    assert np.all(np.abs(resid) <= NOISE_BOUND)
    assert A_INTERVAL.contains(a["A"])


def test_estimator_with_uncertain_a_handles_missing_outputs(designs):
    sim = simulate(3, 30)
    est = ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, Zonotope(np.zeros(2), 3 * np.eye(2)), designs["second_approach"])
    for k in range(1, 31):
        y = sim["y"][k].copy()
        if k % 3 == 0:
            y[1] = np.nan
        Z = est.step(y)
        assert Z.order <= 20
        assert Z.contains(sim["x"][k])


def test_point_matrix_estimator_is_tighter_than_the_interval_one(designs):
    sim = simulate(4, 30)
    X0 = Zonotope(np.zeros(2), 3 * np.eye(2))
    exact = ZonotopicEstimator(IntervalMatrix.point(sim["A"]), F, C, NOISE_BOUND, X0, "segment")
    robust = ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, X0, "segment")
    we, wr = [], []
    for k in range(1, 31):
        we.append(exact.step(sim["y"][k]).widths())
        wr.append(robust.step(sim["y"][k]).widths())
        assert exact.zonotope.contains(sim["x"][k])
    assert np.mean(we) < np.mean(wr)


def test_cli_run_le2013_writes_recording_and_summary(tmp_path, capsys):
    from quadobs.recording import list_entities, read_series

    rrd, js = tmp_path / "le.rrd", tmp_path / "le.json"
    assert main(["run", "le2013", "--out", str(rrd), "--summary", str(js), "--runs", "3", "--duration", "20", "--seed", "7"]) == 0
    out = capsys.readouterr().out
    assert "second_approach lambda_2" in out and "paper" in out
    data = json.loads(js.read_text())
    assert data["runs"] == 3 and data["steps"] == 20 and data["seed"] == 7
    assert set(data["gains"]) == {"first_approach", "second_approach"}
    assert np.array(data["gains"]["first_approach"]).shape == (2, 2)
    np.testing.assert_allclose(data["gains"]["first_approach"], [[-0.2137, 0.5726], [0.3684, 0.3570]], atol=1e-4)
    for key in ("containment", "mean_width"):
        assert set(data[key]) == {"segment", "volume", "pradius1", "pradius2", "pradius2_paper"}
    assert all(v == 1.0 for v in data["containment"].values())
    assert all(len(v) == 2 for v in data["mean_width"].values())
    entities = set(list_entities(rrd))
    assert {"/le2013/truth", "/le2013/width/segment", "/le2013/bounds/pradius2/x1", "/le2013/sets/volume"} <= entities
    width = read_series(rrd, "le2013/width/pradius2")
    assert width["values"].shape == (21, 2)
    first = run_once(design_gains(), 7, 20, methods=("pradius2",))
    np.testing.assert_allclose(width["values"], first.widths["pradius2"], rtol=1e-12)
    bounds = read_series(rrd, "le2013/bounds/segment/x1")["values"]
    truth = read_series(rrd, "le2013/truth")["values"]
    assert np.all((bounds[:, 0] <= truth[:, 0]) & (truth[:, 0] <= bounds[:, 1]))


def test_summary_is_reproducible(designs):
    a = summary_of(reproduce(seed=1, steps=10, runs=2, designs=designs))
    b = summary_of(reproduce(seed=1, steps=10, runs=2, designs=designs))
    for key in ("gains", "containment", "mean_width", "mean_volume", "per_step_mean"):
        assert a[key] == b[key]
