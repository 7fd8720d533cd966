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
from quadobs.scenario import parse_scenario

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
arrays = hnp.arrays(np.float64, shapes, elements=st.floats(allow_nan=True, allow_infinity=True, width=64))


@FAST
@given(A=st.one_of(arrays, junk), B=st.one_of(arrays, junk), C=st.one_of(arrays, junk), d=st.one_of(st.none(), arrays, junk))
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
#: Top-level fields a scenario may hold that BASE does not (each checked on its own, not "unknown").
OPTIONAL_TOP = ("model", "wind")


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


@FAST
@given(key=st.text(min_size=1, max_size=8).filter(lambda k: k not in BASE and k not in OPTIONAL_TOP), value=junk)
def test_unknown_top_level_fields_are_refused(key, value):
    doc = copy.deepcopy(BASE)
    doc[key] = value
    with pytest.raises(QuadobsError, match="unknown field"):
        parse_scenario(doc)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
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
