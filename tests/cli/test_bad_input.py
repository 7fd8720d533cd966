"""Property-based tests: malformed input gives the project's own error, never a deep traceback."""

import copy
import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from quadobs import QuadobsError, QuadraticSystem, load_scenario
from quadobs.cli import main
from quadobs.testbed.scenario import Scenario, parse_scenario

FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

junk = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-5, 5),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=4),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)
shapes = hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4)
arrays = hnp.arrays(
    np.float64, shapes, elements=st.floats(allow_nan=True, allow_infinity=True, width=64)
)


@FAST
@given(
    A=st.one_of(arrays, junk),
    B=st.one_of(arrays, junk),
    C=st.one_of(arrays, junk),
    d=st.one_of(st.none(), arrays, junk),
)
def test_quadratic_system_accepts_or_names_the_problem(A, B, C, d):
    try:
        s = QuadraticSystem(A, B, C, d)
    except QuadobsError as exc:
        assert str(exc).split(":")[0].strip() != ""
        return
    # whatever was accepted is a valid system
    assert s.A.shape == (s.n, s.n) and s.C.shape == (s.q, s.n, s.n) and np.isfinite(s.C).all()
    np.testing.assert_array_equal(s.C, s.C.transpose(0, 2, 1))


def _leaves(data, prefix=()):
    if isinstance(data, dict):
        for k, v in data.items():
            yield from _leaves(v, prefix + (k,))
    elif isinstance(data, list) and data and isinstance(data[0], dict):
        for i, v in enumerate(data):
            yield from _leaves(v, prefix + (i,))
    else:
        yield prefix


BASE = load_scenario("beacons").to_dict()
FIELD = re.compile(r"scenario|[a-z_0-9]+(\[\d+\])?(\.[A-Za-z_0-9]+(\[\d+\])?)*")
LEAVES = list(_leaves(BASE))


@FAST
@given(st.data())
def test_scenario_mutations_accept_or_name_the_field(data):
    doc = copy.deepcopy(BASE)
    path = data.draw(st.sampled_from(LEAVES))
    node = doc
    for key in path[:-1]:
        node = node[key]
    value = data.draw(junk)
    node[path[-1]] = value
    try:
        sc = parse_scenario(doc)
    except QuadobsError as exc:
        # the message starts with a field's dotted path (list indices as [i]); a field can make
        # another one invalid (a new dimension invalidates the beacons), so any field may be named
        head = str(exc).split(":")[0]
        assert FIELD.fullmatch(head), (str(exc), path)
        return
    assert sc.steps >= 1 and np.isfinite(sc.beacons).all()


# every top-level field a scenario may have (those the base omits: optional ones left at their default)
KNOWN = (
    set(BASE)
    | set(Scenario.model_fields)
    | {f.alias for f in Scenario.model_fields.values() if f.alias}
    | {"tdoa"}  # the deprecated [tdoa] table, still read (as [radio]) with a warning
)  # every field a scenario file may hold, from the model itself


def test_the_deprecated_tdoa_table_must_be_a_table():
    doc = {**copy.deepcopy(BASE), "tdoa": False}
    with pytest.raises(QuadobsError) as exc:
        parse_scenario(doc)
    assert str(exc.value) == "tdoa: expected a table, got bool"


@FAST
@given(key=st.text(min_size=1, max_size=8).filter(lambda k: k not in KNOWN), value=junk)
def test_unknown_top_level_fields_are_refused(key, value):
    doc = copy.deepcopy(BASE)
    doc[key] = value
    with pytest.raises(QuadobsError, match="unknown field"):
        parse_scenario(doc)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    duration=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.just(-1.0), st.just(0.0)),
    seed=st.integers(-3, -1),
)
def test_cli_options_are_checked(duration, seed, capsys):
    if not (math.isfinite(duration) and duration > 0):
        assert main(["run", "ifac2021", f"--duration={duration!r}", "--no-progress"]) == 2
        assert "duration" in capsys.readouterr().err
    assert main(["run", "ifac2021", f"--seed={seed}", "--no-progress"]) == 2
    assert "seed: must be at least 0" in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# MJCF models, scenario TOML text, observer settings, the P-radius design, zonotopes
# --------------------------------------------------------------------------------------

SOME = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def _vehicle_xml() -> str:
    from quadobs.testbed.worlds import default_model_path

    return default_model_path().read_text()


@SOME
@given(data=st.data())
def test_mjcf_mutations_load_or_name_the_problem(tmp_path_factory, data):
    """Renamed required elements are named in the error; deleted lines, truncations and junk
    attribute values give a QuadobsError or a model that passes every check."""
    from quadobs.testbed.worlds import load_vehicle_model
    from quadobs.testbed.worlds.model import REQUIRED_ELEMENTS

    xml = _vehicle_xml()
    kind = data.draw(st.sampled_from(["rename", "delete_line", "truncate", "attribute"]))
    expect = None
    if kind == "rename":
        elem_kind, name = data.draw(st.sampled_from(REQUIRED_ELEMENTS))
        xml = xml.replace(f'name="{name}"', f'name="{name}_x"', 1)
        expect = f"missing {elem_kind} named {name!r}"
    elif kind == "delete_line":
        lines = xml.splitlines()
        i = data.draw(st.integers(0, len(lines) - 1))
        xml = "\n".join(lines[:i] + lines[i + 1 :])
    elif kind == "truncate":
        xml = xml[: data.draw(st.integers(0, len(xml) - 1))]
    else:
        attrs = list(re.finditer(r'(\w+)="([^"]*)"', xml.split("-->", 1)[1]))
        offset = xml.index("-->") + 3
        m = data.draw(st.sampled_from(attrs))
        value = data.draw(
            st.sampled_from(["", "-1", "nan", "inf", "0", "1 2", "x", "euler", "1 1 1 1 1 1"])
        )
        start, end = offset + m.start(2), offset + m.end(2)
        xml = xml[:start] + value + xml[end:]
    path = tmp_path_factory.mktemp("mjcf") / "model.xml"
    path.write_text(xml)
    try:
        vm = load_vehicle_model(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), path=path)
    except QuadobsError as exc:
        assert str(exc).startswith("model")
        if expect is not None:
            assert expect in str(exc)
        return
    assert expect is None
    assert (
        vm.mass > 0 and vm.offset_adr.shape == (2,) and np.allclose(vm.beacons[1], [10.0, 0.0, 0.0])
    )


@SOME
@given(beacons=st.one_of(arrays, junk), timestep=junk, wind=st.one_of(st.none(), arrays, junk))
def test_model_arguments_are_checked(beacons, timestep, wind):
    from quadobs.testbed.worlds import load_vehicle_model

    try:
        vm = load_vehicle_model(beacons, timestep=timestep, wind=wind)
    except QuadobsError as exc:
        assert str(exc).split(":")[0] in ("beacons", "timestep", "wind")
        return
    assert vm.model.opt.timestep > 0 and np.isfinite(vm.beacons).all()


TOML = (
    __import__("quadobs.testbed.scenario", fromlist=["_builtin_dir"])._builtin_dir()
    / "beacons.toml"
).read_text()
TOML_VALUES = st.sampled_from(
    [
        '"x"',
        "[]",
        "[1, 2]",
        "nan",
        "inf",
        "-inf",
        "-1",
        "0",
        "1e400",
        "true",
        "{}",
        "{ a = 1 }",
        '"1.0"',
        "[[1], [2]]",
        "",
        "=",
        "[",
        "1979-05-27",
    ]
)


@FAST
@given(data=st.data())
def test_scenario_toml_text_loads_or_names_the_problem(tmp_path_factory, data):
    """A built-in file with one value replaced by junk, one line dropped, or random text."""
    kind = data.draw(st.sampled_from(["value", "drop", "text"]))
    lines = TOML.splitlines()
    if kind == "value":
        idx = [i for i, l in enumerate(lines) if re.match(r"\s*\w+\s*=", l)]
        i = data.draw(st.sampled_from(idx))
        key = lines[i].split("=", 1)[0]
        lines[i] = f"{key}= {data.draw(TOML_VALUES)}"
        text = "\n".join(lines)
    elif kind == "drop":
        i = data.draw(st.integers(0, len(lines) - 1))
        text = "\n".join(lines[:i] + lines[i + 1 :])
    else:
        text = data.draw(st.text(max_size=60))
    path = tmp_path_factory.mktemp("toml") / "sc.toml"
    path.write_bytes(text.encode("utf-8", "replace"))
    try:
        sc = load_scenario(str(path))
    except QuadobsError as exc:
        head = str(exc).split(":")[0]
        assert head.startswith("scenario file") or FIELD.fullmatch(head), str(exc)
        return
    assert sc.steps >= 1 and np.isfinite(sc.beacons).all() and sc.beacons.shape[1] == sc.dimension


def test_unknown_scenario_name_lists_the_built_ins(capsys):
    with pytest.raises(QuadobsError, match="unknown name 'ifac2012'.*ifac2021-outliers"):
        load_scenario("ifac2012")
    assert main(["run", "no-such-scenario", "--no-progress"]) == 2
    assert "unknown name 'no-such-scenario'" in capsys.readouterr().err


OBSERVER_FIELDS = ("dt", "V", "W", "S0", "theta", "x0", "sample_period", "gate", "backend")


def test_an_initial_state_whose_lift_overflows_is_named():
    """A finite ``x0`` whose squares overflow float64 (a fresh clone's hypothesis drew it)."""
    from quadobs import AugmentedObserver, immerse, vehicle_system

    im = immerse(vehicle_system(2, np.array([[0.0, 0.0], [5.0, 0.0]])))
    with pytest.raises(QuadobsError, match=r"^x0: its augmented state lift\(x0\) overflows"):
        AugmentedObserver(im, 0.01, x0=[0.0, 0.0, 0.0, 9.480751908109177e153])
    assert np.isfinite(AugmentedObserver(im, 0.01, x0=[0.0, 0.0, 0.0, 1e150]).z).all()


@SOME
@given(
    field=st.sampled_from(OBSERVER_FIELDS),
    value=st.one_of(
        arrays, junk, st.floats(-10, 10), st.sampled_from(["auto", "numpy", "numba", "gpu"])
    ),
)
def test_observer_settings_accept_or_name_the_field(field, value):
    from quadobs import AugmentedObserver, immerse, vehicle_system

    im = immerse(vehicle_system(2, np.array([[0.0, 0.0], [5.0, 0.0]])))
    kwargs = {"dt": 0.01}
    kwargs[field] = value
    dt = kwargs.pop("dt")
    try:
        obs = AugmentedObserver(im, dt, **kwargs)
    except QuadobsError as exc:
        head = str(exc).split(":")[0]
        # a huge theta makes the model over dt overflow: reported on dt (the product matters)
        assert head == field or (field == "theta" and head == "dt"), str(exc)
        return
    P = obs.P
    assert np.isfinite(P).all() and np.array_equal(P, P.T) and np.linalg.eigvalsh(P).min() > 0
    assert np.isfinite(obs.z).all()
    obs.step(np.zeros(2), np.array([1.0, np.nan]))
    assert np.isfinite(obs.z).all()


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    A=st.one_of(arrays, junk),
    F=st.one_of(arrays, junk),
    C=st.one_of(arrays, junk),
    bounds=st.one_of(arrays, junk),
    approach=st.one_of(st.sampled_from([1, 2]), junk),
)
def test_pradius_design_arguments_are_checked(A, F, C, bounds, approach):
    from quadobs import pradius_gains

    try:
        design = pradius_gains(A, F, C, bounds, approach, betas=[0.5], refine=False)
    except QuadobsError as exc:
        assert str(exc).split(":")[0].strip() != "", str(exc)
        return
    assert all(np.isfinite(np.asarray(g)).all() for g in design.gains)


@FAST
@given(center=st.one_of(arrays, junk), generators=st.one_of(arrays, junk))
def test_zonotope_arguments_are_checked(center, generators):
    from quadobs.sets.zonotope import Zonotope

    try:
        z = Zonotope(center, generators)
    except QuadobsError as exc:
        assert str(exc).split(":")[0] in ("center", "generators"), str(exc)
        return
    assert z.center.ndim == 1 and z.generators.shape[0] == z.center.shape[0]
    assert np.isfinite(z.center).all() and np.isfinite(z.generators).all()


@FAST
@given(lower=st.one_of(arrays, junk), upper=st.one_of(arrays, junk))
def test_zonotope_boxes_are_checked(lower, upper):
    from quadobs.sets.zonotope import Zonotope

    try:
        z = Zonotope.from_box(lower, upper)
    except QuadobsError as exc:
        assert str(exc).split(":")[0] in ("lower", "upper"), str(exc)
        return
    assert np.isfinite(z.center).all()


@pytest.mark.parametrize(
    "field, value",
    [
        ("W", -8.99e307),
        ("W", 8.99e307),
        ("V", 8.99e307),
        ("V", -8.99e307),
        ("P0", 1e101),
        ("V", 1e101),
    ],
)
def test_covariances_beyond_double_precision_are_refused(field, value):
    """Entries whose products would overflow (the Riccati update squares them) are named, not run into NaN."""
    from quadobs import AugmentedObserver, immerse, vehicle_system

    im = immerse(vehicle_system(2, np.array([[0.0, 0.0], [5.0, 0.0]])))
    with pytest.raises(
        QuadobsError, match=rf"^{field}: covariance entries must be finite and at most 1e\+100"
    ):
        AugmentedObserver(im, 0.01, **{field: value})
