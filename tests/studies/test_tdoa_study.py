"""The TDOA study: its DOP figure and a one-seed run of its comparison."""

import json

import numpy as np
import pytest

from quadobs.studies.tdoa import dop_figure, main
from quadobs.testbed.scenario import load_scenario


def test_dop_figure_is_written(tmp_path):
    pytest.importorskip("matplotlib")
    out = dop_figure(load_scenario("tdoa-room").beacons, 1.5, tmp_path / "dop.png")
    assert out.stat().st_size > 10_000


def test_one_short_seed_of_the_comparison(tmp_path):
    code = main(
        ["--out", str(tmp_path), "--scenario", "tdoa-room", "--seeds", "1"]
        + ["--duration", "1.0", "--settle", "0.5", "--offset", "1.0", "--no-figure"]
    )
    assert code == 0
    result = json.loads((tmp_path / "tdoa-study.json").read_text())
    names = {"tdoa-observer", "tdoa-handover", "tdoa-ekf", "range-ekf", "range-refined"}
    assert set(result["summary"]) == names
    for rows in result["runs"].values():
        assert np.isfinite(rows[0]["rmse"]) and rows[0]["rmse"] < 1.0


def test_bad_input_is_one_line_with_status_2(tmp_path, capsys, monkeypatch):
    from quadobs.studies import tdoa

    monkeypatch.setattr("sys.argv", ["x", "--out", str(tmp_path), "--scenario", "quadrotor-uwb"])
    assert tdoa._main() == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and '[radio] with protocol = "tdoa"' in err
    assert not (tmp_path / "tdoa-study.json").exists()
