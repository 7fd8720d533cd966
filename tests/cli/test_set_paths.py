"""``--set`` paths: split and applied in time linear in their number of parts, refused in one line beyond a bound."""

import time

import pytest

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed import scenario as scenario_module
from quadobs.testbed.scenario import apply_settings


def _depth(data) -> int:
    """How many tables nest in ``data`` along its only path (counted without recursion)."""
    depth = 0
    while isinstance(data, dict | list) and data:
        data = next(iter(data.values())) if isinstance(data, dict) else data[0]
        depth += 1
    return depth


def test_a_path_of_60000_parts_is_applied_in_linear_time(monkeypatch):
    """With the bound on parts lifted, 60 000 parts are set in well under a second (naming
    every prefix of the path, as before, took 34 s for 16 000 parts: quadratic)."""
    monkeypatch.setattr(scenario_module, "MAX_NESTING", 10**7)
    path = ".".join(["a", "b"] * 30000)
    start = time.perf_counter()
    data = apply_settings({}, [f"{path}=1"])
    elapsed = time.perf_counter() - start
    assert _depth(data) == 60000
    assert elapsed < 1.0, f"{elapsed:.2f} s"


def test_a_path_of_60000_parts_is_refused_in_one_line_at_once(capsys):
    path = ".".join(["a"] * 60000)
    start = time.perf_counter()
    with pytest.raises(QuadobsError, match="parts"):
        apply_settings({}, [f"{path}=1"])
    assert time.perf_counter() - start < 0.1  # one count of the separators (about 1 ms)
    code = main(["show", "ifac2021", "--set", f"{path}=1"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "--set" in err and f"more than {scenario_module.MAX_NESTING} parts" in err
    assert len(err) < 200, err


def test_a_long_malformed_path_is_named_briefly():
    with pytest.raises(QuadobsError, match=r"is not a dotted field path") as info:
        apply_settings({}, ["a" * 50000 + "[x]=1"])
    assert len(str(info.value)) < 200


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("noise.range_std.x=1", "noise.range_std: is not a table"),
        ("trajectory.terms[5].omega=1", "trajectory.terms[5]: no such entry (1 in the list)"),
        ("trajectory.terms[3]=1", "trajectory.terms[3]: no such entry"),
    ],
)
def test_a_wrong_path_is_named_up_to_the_part_that_fails(setting, message):
    data = {"noise": {"range_std": 0.1}, "trajectory": {"terms": [{"omega": 1.0}]}}
    with pytest.raises(QuadobsError) as info:
        apply_settings(data, [setting])
    assert str(info.value).startswith(message), info.value
