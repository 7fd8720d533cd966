"""Scenario files: built-ins load, every bad field is named."""

import copy
import pickle
from pathlib import Path

import numpy as np
import pytest

from quadobs import QuadobsError, list_scenarios, load_scenario
from quadobs.testbed.scenario import (
    Scenario,
    apply_settings,
    field_reference,
    parse_scenario,
    parse_setting,
)


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
    np.testing.assert_allclose(
        p,
        np.stack([20 * np.cos(t) - 20, 10 * np.sin(2 * t) + 20, -4 * np.cos(4 * t)], 1),
        atol=1e-12,
    )
    a = sc.trajectory.acceleration(t)
    np.testing.assert_allclose(
        a, np.stack([-20 * np.cos(t), -40 * np.sin(2 * t), 64 * np.cos(4 * t)], 1), atol=1e-11
    )


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


# --------------------------------------------------------------------------------------
# The declarative schema: suggestions, cross-field rules, copies, TOML, settings, reference
# --------------------------------------------------------------------------------------


ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "path,value,message",
    [
        ("duratoin", 1.0, "scenario: unknown field 'duratoin' (did you mean 'duration'?)"),
        ("noise.range_sdt", 0.1, "noise: unknown field 'range_sdt' (did you mean 'range_std'?)"),
        (
            "beacons.0.postion",
            [1.0, 2.0],
            "beacons[0]: unknown field 'postion' (did you mean 'position'?)",
        ),
        (
            "trajectory.terms.0.omgea",
            2.0,
            "trajectory.terms[0]: unknown field 'omgea' (did you mean 'omega'?)",
        ),
        (
            "observer.variants",
            [{"name": "a", "outputs": [0], "ouptuts": [0]}],
            "observer.variants[0]: unknown field 'ouptuts' (did you mean 'outputs'?)",
        ),
        ("colour", "red", "scenario: unknown field 'colour'"),
    ],
)
def test_unknown_fields_suggest_the_close_name(path, value, message):
    with pytest.raises(QuadobsError) as info:
        parse_scenario(_with(path, value))
    assert str(info.value) == message


@pytest.mark.parametrize(
    "path,value,match",
    [
        (
            "noise",
            {"range_std": 0.1, "range_bound": 0.2},
            "noise.range_bound: cannot be combined with noise.range_std",
        ),
        (
            "observer.variants",
            [{"name": "a", "outputs": [0]}, {"name": "a", "outputs": [0]}],
            r"observer.variants\[1\].name: 'a' must be a new identifier",
        ),
        (
            "observer.variants",
            [{"name": "augmented", "outputs": [0]}],
            r"observer.variants\[0\].name",
        ),
        (
            "observer.variants",
            [{"name": "a b", "outputs": [0]}],
            r"observer.variants\[0\].name: 'a b' must be an identifier",
        ),
        (
            "observer.variants",
            [{"name": "a", "outputs": [0, 0]}],
            r"observer.variants\[0\].outputs: expected distinct",
        ),
        ("observer.S0", [1.0, -1.0], r"observer.S0\[1\]: must be positive"),
        ("observer.V", [], "observer.V: expected at least 1 entries"),
        (
            "initial",
            {"kind": "zero", "point": [0.0, 0.0, 0.0, 0.0]},
            'initial.point: only used with kind = "point"',
        ),
        (
            "initial",
            {"kind": "point", "point": [0.0, 0.0]},
            "initial.point: expected 4 numbers, got 2",
        ),
        ("trajectory.offset", [1.0, 2.0, 3.0], "trajectory.offset: expected 2 numbers, got 3"),
        (
            "trajectory.coast",
            [{"start": 2.0, "end": 3.0}, {"start": 1.0, "end": 4.0}],
            r"trajectory.coast\[1\]",
        ),
        (
            "excitation.window",
            0.015,
            "excitation.window: 0.015 s must be a positive multiple of excitation.step",
        ),
        ("duration", 1e-5, "duration: 1e-05 s is shorter than one physics step"),
        ("seed", True, "seed: expected an integer, got True"),
        ("excitation.monitor", 1, "excitation.monitor: expected true or false, got 1"),
        ("noise", [1.0], "noise: expected a table, got list"),
        (
            "beacons.0.position",
            [1.0, "x"],
            r"beacons\[0\].position\[1\]: expected a number, got 'x'",
        ),
    ],
)
def test_cross_field_and_nested_rules_name_the_field(path, value, match):
    with pytest.raises(QuadobsError, match=match) as info:
        parse_scenario(_with(path, value))
    assert "\n" not in str(info.value)


def test_schema_gives_the_defaults():
    sc = parse_scenario(copy.deepcopy(BASE))
    assert (
        sc.physics_rate == 1000.0 and sc.seed == 0 and sc.record_every == 1 and sc.kind == "vehicle"
    )
    assert sc.noise.range_rate is None and sc.observer.S0 == 100.0 and sc.observer.gate is None
    assert sc.excitation.monitor is True and sc.zonotope.reduction == "parallelotope"
    assert (
        sc.trajectory.velocity.tolist() == [0.0, 0.0]
        and sc.wind is None
        and sc.observer.variants == ()
    )
    assert sc.to_dict()["trajectory"]["velocity"] == [0.0, 0.0]


def test_sin_terms_are_stored_as_cosines():
    sc = parse_scenario(_with("trajectory.terms.0.function", "sin"))
    assert sc.to_dict()["trajectory"]["terms"][0] == {
        "axis": 0,
        "amplitude": 1.0,
        "omega": 1.0,
        "phase": -np.pi / 2,
        "function": "cos",
    }
    t = np.linspace(0.0, 3.0, 7)
    np.testing.assert_allclose(sc.trajectory.position(t)[:, 0], 1.0 + np.sin(t), atol=1e-12)


def test_scenarios_are_frozen_with_read_only_arrays():
    sc = load_scenario("wind")
    with pytest.raises(Exception):
        sc.duration = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        sc.beacons[0, 0] = 1.0
    with pytest.raises(ValueError):
        sc.wind[0] = 1.0
    assert sc.observer.variants == () and load_scenario("beacons").observer.variants == (
        ("augmented_1beacon", (0,)),
    )


@pytest.mark.parametrize("name", list(list_scenarios()))
def test_builtins_pickle_and_print_as_toml_that_loads_back(tmp_path, name):
    sc = load_scenario(name)
    again = pickle.loads(pickle.dumps(sc))
    assert again == sc and again.source == name
    np.testing.assert_array_equal(again.beacons, sc.beacons)
    np.testing.assert_array_equal(
        again.true_state(np.array([0.5, 1.5])), sc.true_state(np.array([0.5, 1.5]))
    )
    path = tmp_path / f"{name}.toml"
    path.write_text(sc.to_toml())
    back = load_scenario(path)
    assert back == sc and back.to_dict() == sc.to_dict() and back.source == str(path)
    assert back != sc.with_overrides(seed=sc.seed + 1)


def test_settings_override_any_field():
    sc = load_scenario(
        "ifac2021",
        settings=[
            "noise.range_std=0.25",
            "trajectory.terms[1].omega=3",
            "observer.W=[2.0]",
            "wind.velocity=[1, 2, 3]",
            "beacons[1]={ position = [5.0, 0.0, 0.0] }",
            "name=my run",
        ],
        duration=2.0,
    )
    assert (
        sc.noise.range_std == 0.25 and sc.trajectory.terms[1, 2] == 3.0 and sc.observer.W == (2.0,)
    )
    assert sc.wind.tolist() == [1.0, 2.0, 3.0] and sc.state_dim == 9 and sc.beacons.shape == (2, 3)
    assert sc.name == "my run" and sc.steps == 2000 and sc.source == "ifac2021"
    off = sc.with_settings({"excitation.monitor": False})
    assert (
        off.excitation.monitor is False and sc.excitation.monitor is True and off.noise == sc.noise
    )


@pytest.mark.parametrize(
    "setting,match",
    [
        ("noise.range_sdt=0.1", r"noise: unknown field 'range_sdt' \(did you mean 'range_std'\?\)"),
        ("noise.range_std=-1", "noise.range_std: must be non-negative, got -1.0"),
        ("noise.range_std.x=1", "noise.range_std: is not a table"),
        ("beacons[3].position=[0, 0, 0]", r"beacons\[3\]: no such entry \(1 in the list\)"),
        ("observer.W=abc", "observer.W: expected a number, got 'abc'"),
        ("duration", "--set: expected FIELD=VALUE"),
        ("a..b=1", "is not a dotted field path"),
        ("beacons[x]=1", "is not a dotted field path"),
    ],
)
def test_bad_settings_name_the_field(setting, match):
    with pytest.raises(QuadobsError, match=match):
        load_scenario("ifac2021", settings=[setting])


def test_setting_values_are_read_as_toml_else_text():
    assert parse_setting("a=1") == ("a", 1)
    assert parse_setting(" a.b = true ") == ("a.b", True)
    assert parse_setting("a=[1, 2.5]") == ("a", [1, 2.5])
    assert parse_setting("a=x=y") == ("a", "x=y")
    assert parse_setting('a="7"') == ("a", "7")
    data = {"noise": {"range_std": 0.1}}
    assert apply_settings(data, ["noise.range_std=0.2"]) == {"noise": {"range_std": 0.2}}
    assert data == {"noise": {"range_std": 0.1}}  # the input is not changed


def _leaf_paths(data, prefix=""):
    for key, value in data.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            yield from _leaf_paths(value, path + ".")
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            for entry in value:
                yield from _leaf_paths(entry, path + "[].")
        else:
            yield path


def test_field_reference_is_up_to_date_and_complete():
    text = field_reference()
    committed = (ROOT / "docs" / "reference" / "scenario.md").read_text()
    assert committed == text, (
        "docs/reference/scenario.md is out of date; regenerate it with "
        "`python -m quadobs.cli show --reference > docs/reference/scenario.md`"
    )
    rows = {line.split("|")[1].strip(" `") for line in text.splitlines() if line.startswith("| `")}
    for name in ("wind", "ifac2021-bounded", "degenerate", "ifac2021-outliers", "beacons"):
        leaves = set(_leaf_paths(load_scenario(name).to_dict()))
        assert leaves <= rows, leaves - rows
    assert "| `noise.dropout` | number >= 0.0, <= 1.0 | `0.0` |" in text
    assert "| `beacons[].position` | list of number | required |" in text
    assert len(rows) == len(text.splitlines()) - 15 and issubclass(Scenario, object)


def test_to_dict_keeps_its_structure():
    """The plain data of a scenario (summaries and campaign workers read it) is unchanged by the schema."""
    data = load_scenario("ifac2021-outliers").to_dict()
    assert data.pop("description").startswith("ifac2021 with faulty ranges")
    terms = [
        {"axis": 0, "amplitude": 20.0, "omega": 1.0, "phase": 0.0, "function": "cos"},
        {"axis": 1, "amplitude": 10.0, "omega": 2.0, "phase": -np.pi / 2, "function": "cos"},
        {"axis": 2, "amplitude": -4.0, "omega": 4.0, "phase": 0.0, "function": "cos"},
    ]
    assert data == {
        "name": "ifac2021-outliers",
        "kind": "vehicle",
        "dimension": 3,
        "duration": 30.0,
        "physics_rate": 1000.0,
        "seed": 0,
        "record_every": 1,
        "beacons": [{"position": [0.0, 0.0, 0.0]}],
        "trajectory": {"offset": [-20.0, 20.0, 0.0], "velocity": [0.0, 0.0, 0.0], "terms": terms},
        "noise": {
            "range_std": 0.2,
            "accel_std": 0.0,
            "airspeed_std": 0.0,
            "range_rate": 50.0,
            "dropout": 0.1,
            "outlier_probability": 0.02,
            "outlier_std": 20.0,
            "range_bound": 0.0,
            "accel_bound": 0.0,
            "airspeed_bound": 0.0,
        },
        "observer": {
            "immersion": "minimal",
            "S0": 1e4,
            "V": 1e-4,
            "W": 2.0,
            "theta": 0.0,
            "gate": 16.0,
        },
        "initial": {"kind": "random", "position_spread": 10.0, "velocity_spread": 2.0},
        "zonotope": {
            "position_bound": 50.0,
            "velocity_bound": 30.0,
            "max_generators": 0,
            "reduction": "parallelotope",
        },
        "excitation": {"monitor": True, "window": 5.0, "threshold": 1e-6, "update_period": 0.1},
    }
    assert [type(v) for v in (data["dimension"], data["duration"], data["seed"])] == [
        int,
        float,
        int,
    ]
