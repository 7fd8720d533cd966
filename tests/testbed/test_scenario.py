"""Scenario files: built-ins load, every bad field is named."""

import copy

import numpy as np
import pytest

from quadobs import QuadobsError, list_scenarios, load_scenario
from quadobs.testbed.scenario import parse_scenario


def test_builtins_load_and_round_trip():
    names = list_scenarios()
    assert "ifac2021" in names
    for name in names:
        sc = load_scenario(name)
        again = parse_scenario(sc.to_dict(), source=name)
        assert again.to_dict() == sc.to_dict()


def test_ifac2021_reference_trajectory():
    sc = load_scenario("ifac2021")
    t = np.linspace(0, 5, 11)
    p = sc.trajectory.position(t)
    np.testing.assert_allclose(p, np.stack([20 * np.cos(t) - 20, 10 * np.sin(2 * t) + 20, -4 * np.cos(4 * t)], 1), atol=1e-12)
    a = sc.trajectory.acceleration(t)
    np.testing.assert_allclose(a, np.stack([-20 * np.cos(t), -40 * np.sin(2 * t), 64 * np.cos(4 * t)], 1), atol=1e-11)


def test_step_accelerations_are_mean_accelerations():
    sc = load_scenario("ifac2021")
    dt = 0.01
    u = sc.trajectory.step_accelerations(0.0, dt, 100)
    v = sc.trajectory.velocity_at(np.arange(101) * dt)
    np.testing.assert_allclose(v[0] + np.cumsum(u, 0) * dt, v[1:], atol=1e-10)


def test_overrides():
    sc = load_scenario("ifac2021", duration=2.5, seed=7)
    assert sc.duration == 2.5 and sc.seed == 7 and sc.steps == 2500


BASE = {
    "name": "t",
    "dimension": 2,
    "duration": 1.0,
    "beacons": [{"position": [0.0, 0.0]}],
    "trajectory": {"offset": [1.0, 2.0], "terms": [{"axis": 0, "amplitude": 1.0, "omega": 1.0}]},
}


def _with(path, value):
    data = copy.deepcopy(BASE)
    node = data
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if k.isdigit() else node.setdefault(k, {})
    if value is KeyError:
        del node[keys[-1]]
    else:
        node[int(keys[-1]) if keys[-1].isdigit() else keys[-1]] = value
    return data


@pytest.mark.parametrize(
    "path,value,match",
    [
        ("dimension", 4, "dimension: must be 2 or 3"),
        ("duration", -1.0, "duration: must be positive"),
        ("duration", KeyError, "duration: required field is missing"),
        ("duration", "long", "duration: expected a number"),
        ("physics_rate", 0.0, "physics_rate: must be positive"),
        ("beacons", [], "beacons: at least one"),
        ("beacons.0.position", [1.0], r"beacons\[0\].position: expected 2 numbers"),
        ("trajectory.terms.0.axis", 2, r"trajectory.terms\[0\].axis: must be below the dimension"),
        ("trajectory.terms.0.omega", float("nan"), r"trajectory.terms\[0\].omega: must be finite"),
        ("trajectory.terms.0.function", "tan", r"trajectory.terms\[0\].function: must be one of"),
        ("noise.range_rate", 300.0, "noise.range_rate: 300.0 Hz must divide the physics rate"),
        ("noise.range_std", -0.1, "noise.range_std: must be non-negative"),
        ("noise.dropout", 1.5, "noise.dropout: must be at most 1"),
        ("observer.W", 0.0, "observer.W: must be positive"),
        ("observer.immersion", "naive", "observer.immersion: must be one of"),
        ("observer.variants", [{"name": "a", "outputs": [3]}], r"observer.variants\[0\].outputs"),
        ("initial.kind", "point", "initial.point: required field is missing"),
        ("wind.velocity", [1.0, 2.0, 3.0], "wind.velocity: expected 2 numbers"),
        ("colour", "red", "scenario: unknown field"),
        ("noise.range_sdt", 0.1, "noise: unknown field"),
    ],
)
def test_bad_fields_are_named(path, value, match):
    with pytest.raises(QuadobsError, match=match):
        parse_scenario(_with(path, value))


def test_unknown_name_and_bad_files(tmp_path):
    with pytest.raises(QuadobsError, match="unknown name 'nope'.*ifac2021"):
        load_scenario("nope")
    with pytest.raises(QuadobsError, match="cannot be read"):
        load_scenario(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = \n")
    with pytest.raises(QuadobsError, match="invalid TOML"):
        load_scenario(bad)
