"""Regression tests of the built-in multi-output scenarios, run through the command line."""

import json

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.recording import read_series


def _run(tmp_path, target, *extra):
    rrd, js = tmp_path / "run.rrd", tmp_path / "run.json"
    assert (
        main(["run", str(target), "--out", str(rrd), "--summary", str(js), "--no-progress", *extra])
        == 0
    )
    return rrd, json.loads(js.read_text())


@pytest.mark.parametrize("name", ["beacons", "beacons2d"])
def test_beacons_converge_faster_with_the_same_auxiliary_count(tmp_path, name):
    rrd, s = _run(tmp_path, name)
    many, one = s["estimators"]["augmented"], s["estimators"]["augmented_1beacon"]
    assert many["outputs"] > 1 and one["outputs"] == 1
    assert many["immersion"]["n_aux"] == one["immersion"]["n_aux"] == 3
    final = read_series(rrd, "errors/augmented/position/norm")["values"][-1, 0]
    assert final < 0.05 and final == pytest.approx(s["final_position_error"], rel=1e-12)
    assert s["final_velocity_error"] < 0.05
    assert one["final_position_error"] < 0.05
    assert many["time_to_1m"] < one["time_to_1m"]
    assert many["time_to_0p1m"] < one["time_to_0p1m"]


def test_wind_scenario_estimates_the_wind(tmp_path):
    rrd, s = _run(tmp_path, "wind")
    assert s["immersion"]["n_aux"] == 4 and s["immersion"]["naive_aux"] == 45
    assert s["final_position_error"] < 0.05 and s["final_velocity_error"] < 0.05
    assert s["final_wind_error"] < 0.05
    truth = read_series(rrd, "wind/truth")["values"]
    est = read_series(rrd, "wind/augmented")["values"]
    np.testing.assert_allclose(truth[-1], [4.0, -3.0, 0.5])
    assert np.linalg.norm(est[-1] - truth[-1]) == pytest.approx(s["final_wind_error"], rel=1e-9)
    assert np.linalg.norm(est[0] - truth[0]) > 4.0  # started at zero wind
    airspeed = read_series(rrd, "measurements/airspeed")["values"][:, 0]
    assert np.all(airspeed > 0)


def test_user_scenario_file_with_noise_and_slow_ranges(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text(
        """
name = "mine"
dimension = 2
duration = 3.0
physics_rate = 500.0
seed = 11
[[beacons]]
position = [0.0, 0.0]
[[beacons]]
position = [10.0, 0.0]
[trajectory]
offset = [5.0, 5.0]
terms = [{ axis = 0, amplitude = 3.0, omega = 1.5 }, { axis = 1, amplitude = 2.0, omega = 2.5, function = "sin" }]
[noise]
range_std = 0.05
range_rate = 50.0
[initial]
kind = "point"
point = [4.0, 4.0, 0.0, 0.0]
"""
    )
    rrd, s = _run(tmp_path, path)
    assert s["scenario"] == "mine" and s["physics_steps"] == 1500
    assert s["measurements"]["range_period_steps"] == 10
    ranges = read_series(rrd, "measurements/range/1")
    assert np.all(ranges["step"] % 10 == 0) and len(ranges["step"]) == 150
    assert s["estimators"]["augmented"]["corrections"] == 150


def test_cli_reports_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\ndimension = 3\nduration = 1.0\n[[beacons]]\nposition = [0, 0]\n')
    assert main(["run", str(bad), "--no-progress"]) == 2
    assert "beacons[0].position: expected 3 numbers" in capsys.readouterr().err
    assert main(["run", "nope"]) == 2
    assert "unknown name 'nope'" in capsys.readouterr().err
    assert main(["run", "ifac2021", "--estimators", "kalman"]) == 2
    assert "unknown estimator 'kalman'" in capsys.readouterr().err
    (tmp_path / "dir.rrd").mkdir()
    assert main(["run", "ifac2021", "--out", str(tmp_path / "dir.rrd")]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_list_names_the_scenarios(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ("ifac2021", "beacons", "beacons2d", "wind"):
        assert name in out


@pytest.mark.parametrize("name", ["ifac2021", "wind", "degenerate", "beacons", "ifac2021-bounded"])
def test_show_prints_toml_that_loads_back(tmp_path, capsys, name):
    from quadobs import load_scenario

    assert main(["show", name]) == 0
    path = tmp_path / "shown.toml"
    path.write_text(capsys.readouterr().out)
    assert load_scenario(path) == load_scenario(name)


def test_show_applies_settings_and_prints_the_reference(tmp_path, capsys):
    from quadobs import load_scenario
    from quadobs.testbed.scenario import field_reference

    assert (
        main(["show", "ifac2021", "--set", "noise.range_std=0.2", "--set", "initial.kind=random"])
        == 0
    )
    path = tmp_path / "shown.toml"
    path.write_text(capsys.readouterr().out)
    sc = load_scenario(path)
    assert sc.noise.range_std == 0.2 and sc.initial.kind == "random" and sc.name == "ifac2021"
    assert main(["show", "--reference"]) == 0
    assert capsys.readouterr().out == field_reference()
    assert main(["show"]) == 2
    assert "show: give a scenario" in capsys.readouterr().err


def test_run_and_excitation_take_settings(tmp_path, capsys):
    _, s = _run(
        tmp_path,
        "ifac2021",
        "--set",
        "duration=0.5",
        "--set",
        "physics_rate=500",
        "--set",
        "noise.range_rate=50",
    )
    assert s["physics_steps"] == 250 and s["measurements"]["range_period_steps"] == 10
    capsys.readouterr()
    assert (
        main(["excitation", "ifac2021", "--set", "duration=4", "--set", "excitation.window=2.0"])
        == 0
    )
    assert "windows: delta = 2 s, starts every 0.05 s over [0, 4] s" in capsys.readouterr().out
    out = tmp_path / "campaign"
    args = [
        "campaign",
        "ifac2021-noisy",
        "--runs",
        "1",
        "--workers",
        "0",
        "--no-progress",
        "--out",
        str(out),
    ]
    assert main([*args, "--set", "duration=0.2", "--set", "noise.range_std=0.05"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["duration"] == 0.2 and "N(0, 0.05^2)" in capsys.readouterr().out


def test_bad_settings_exit_2_naming_the_field(capsys):
    assert main(["run", "ifac2021", "--no-progress", "--set", "noise.range_sdt=0.1"]) == 2
    assert "noise: unknown field 'range_sdt' (did you mean 'range_std'?)" in capsys.readouterr().err
    assert (
        main(
            ["campaign", "ifac2021", "--runs", "1", "--out", "unused", "--set", "observer.gate=-1"]
        )
        == 2
    )
    assert "observer.gate: must be positive, got -1.0" in capsys.readouterr().err
    assert main(["excitation", "ifac2021", "--set", "excitation"]) == 2
    assert "--set: expected FIELD=VALUE" in capsys.readouterr().err
    assert main(["run", "le2013", "--set", "duration=3"]) == 2
    assert "--set: le2013" in capsys.readouterr().err
