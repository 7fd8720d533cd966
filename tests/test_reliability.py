"""Hostile use of the command line: fuzzed arguments and scenario files, the issue's cases one by one
(signals at random times: ``tests/cli/test_signals.py``).

Every answer is an exit status of 0, 1 (a run fault, named), 2 (bad input, one line) or 130
(interrupted), never a traceback, and a previous output is never lost.
"""

import io
import os
import random
import tempfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from quadobs.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENARIO_TEXT = (ROOT / "quadobs/testbed/scenarios/ifac2021-noisy.toml").read_text()

HOSTILE_NUMBERS = ["nan", "inf", "-inf", "-1", "0", "1e306", "1e-300", "9223372036854775807", "1e999", "abc", "", "0x10", "1_000"]
FIELDS = [
    "duration", "physics_rate", "seed", "record_every", "noise.range_std", "noise.range_rate", "noise.dropout",
    "initial.position_spread", "initial.point", "initial.kind", "trajectory.offset", "trajectory.terms",
    "excitation.step", "excitation.window", "model", "beacons", "observer.S0", "observer.gate", "name", "nosuch.field",
]
VALUES = HOSTILE_NUMBERS + [
    "[1e300, 0, 0]", "[0.0, 0.0]", "'/dev/zero'", "'/nonexistent/x.xml'", "''", "[[[[[[[[]]]]]]]]", '"zero"', '"point"',
    "[{axis=0, amplitude=1e300, omega=1e300}]", "[{position=[0,0,0]}]", "{a=1}", "true", "'" + "x" * 3000 + "'",
]


def _call(argv):
    """``main(argv)`` in this process: the exit status, stdout and stderr."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's own usage errors
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def _check(code, err):
    assert code in (0, 1, 2, 130), (code, err)
    assert "Traceback" not in err, err
    if code in (1, 2):
        last = err.strip().splitlines()[-1]
        assert last.startswith("quadobs: error: ") or " error: " in last, err


@st.composite
def settings_args(draw):
    n = draw(st.integers(0, 3))
    args = []
    for _ in range(n):
        args += ["--set", f"{draw(st.sampled_from(FIELDS))}={draw(st.sampled_from(VALUES))}"]
    return args


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(command=st.sampled_from(["show", "excitation"]), sets=settings_args(),
       extra=st.lists(st.sampled_from(["--window", "--step", "--json"]).flatmap(
           lambda o: st.tuples(st.just(o), st.sampled_from(HOSTILE_NUMBERS + ["/dev/null", "/tmp"]))), max_size=2))
def test_fuzzed_settings_and_options_answer_cleanly(command, sets, extra):
    argv = [command, "ifac2021", *sets]
    if command == "excitation":
        for opt, value in extra:
            argv += [opt, value]
    here = os.getcwd()
    os.chdir(tempfile.mkdtemp())  # a relative --json lands in a scratch folder
    try:
        code, _, err = _call(argv)
    finally:
        os.chdir(here)
    _check(code, err)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(duration=st.sampled_from(["0.01", "0.02", "nan", "inf", "-1", "1e306", "abc", "0"]), sets=settings_args(),
       seed=st.sampled_from([None, "-1", "3", "99999999999999999999999"]))
def test_fuzzed_runs_answer_cleanly_and_keep_previous_outputs(tmp_path_factory, duration, sets, seed):
    folder = tmp_path_factory.mktemp("fuzz")
    rrd, js = folder / "run.rrd", folder / "run.json"
    rrd.write_bytes(b"previous recording")
    js.write_text('{"previous": true}')
    argv = ["run", "ifac2021", "--no-progress", "--duration", duration, "--out", str(rrd), "--summary", str(js), *sets]
    if seed is not None:
        argv += ["--seed", seed]
    code, _, err = _call(argv)
    _check(code, err)
    if code != 0:
        assert rrd.read_bytes() == b"previous recording"
    if code == 2:
        assert js.read_text() == '{"previous": true}'
    assert not list(folder.glob(".*.partial")) or code == 1


def _mutate(text: str, rnd: random.Random) -> str:
    kind = rnd.randrange(5)
    if kind == 0:  # truncate
        return text[: rnd.randrange(len(text))]
    if kind == 1:  # replace a number by a hostile one
        i = rnd.randrange(len(text))
        while i < len(text) and not text[i].isdigit():
            i += 1
        return text[:i] + rnd.choice(HOSTILE_NUMBERS + ["1e308", "-1e308"]) + text[i + 1 :]
    if kind == 2:  # deep nesting
        return text + "\nx = " + "[" * 3000 + "]" * 3000 + "\n"
    if kind == 3:  # flip a byte
        data = bytearray(text.encode())
        data[rnd.randrange(len(data))] = rnd.randrange(256)
        return data.decode("utf-8", errors="surrogateescape")
    lines = text.splitlines()
    rnd.shuffle(lines)
    return "\n".join(lines)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_mutated_scenario_files_answer_cleanly(tmp_path_factory, seed):
    path = tmp_path_factory.mktemp("toml") / "mutated.toml"
    path.write_bytes(_mutate(SCENARIO_TEXT, random.Random(seed)).encode("utf-8", errors="surrogateescape"))
    code, _, err = _call(["show", str(path)])
    _check(code, err)
    assert code in (0, 2)


# -- the cases, one by one --------------------------------------------------------------


def _hostile_files(folder: Path) -> dict:
    (folder / "nonutf8.toml").write_bytes(b"\xff\xfe name = 1\n")
    (folder / "deep.toml").write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    (folder / "loop1").symlink_to(folder / "loop2")
    (folder / "loop2").symlink_to(folder / "loop1")
    (folder / "adir").mkdir()
    return {"f": str(folder)}


CASES = [
    (["run", "{f}/nonutf8.toml"], "not UTF-8"),
    (["run", "{f}/deep.toml"], "nested too deeply"),
    (["run", "ifac2021", "--set", "duration=1e306"], "duration: must be at most"),
    (["campaign", "ifac2021", "--runs", "2", "--duration", "1e306", "--out", "{f}/c"], "duration: must be at most"),
    (["run", "ifac2021", "--set", "physics_rate=1e300"], "physics_rate: must be at most"),
    (["run", "ifac2021", "--set", "record_every=9223372036854775807", "--out", "{f}/x.rrd"], "record_every: must be at most"),
    (["run", "ifac2021", "--set", "model='{f}/loop1'"], "Too many levels of symbolic links"),
    (["run", "ifac2021", "--set", "model='" + "a" * 5000 + "'"], "model:"),
    (["run", "ifac2021", "--set", 'model="a\\u0000b"'], "NUL"),
    (["run", "ifac2021", "--set", "model='{f}/adir'"], "is a directory"),
    (["run", "ifac2021", "--set", "model=''"], "empty name"),
    (["run", "ifac2021", "--set", "model='/dev/zero'"], "not a regular file"),
    (["run", "x" * 5000], "at most 1024 characters"),
    (["run", "ifac2021", "--out", "/dev/full"], "is a character device"),
    (["run", "le2013", "--duration", "nan"], "--duration"),
    (["run", "le2013", "--duration", "inf"], "--duration"),
    (["run", "le2013", "--seed", "-1"], "seed"),
    (["run", "le2013", "--duration", "0.4"], "--duration"),
    (["excitation", "ifac2021", "--step", "1e-9"], "step:"),
    (["run", "ifac2021", "--set", "noise.range_std=1e300"], "noise.range_std: must be at most"),
    (["run", "ifac2021", "--set", "initial.position_spread=1e300"], "initial.position_spread: must be at most"),
    (["run", "ifac2021", "--set", "initial.point=[0,0,0,0,0,0]"], 'only used with kind = "point"'),
    (["run", "ifac2021", "--seed", str(2**80)], "seed: must be at most"),
    (["campaign", "ifac2021", "--runs", "2", "--retries", "-1", "--out", "{f}/c"], "retries"),
]


@pytest.mark.parametrize("argv, message", CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_each_hostile_case_gets_one_line_and_status_2(tmp_path, argv, message):
    names = _hostile_files(tmp_path)
    code, _, err = _call([a.replace("{f}", names["f"]) for a in argv])
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith(("quadobs: compiling", "quadobs: note:"))]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("quadobs: error: "), err
    assert message in lines[0] and len(lines[0]) < 400 and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "deep.toml", "loop1", "loop2", "nonutf8.toml"]
