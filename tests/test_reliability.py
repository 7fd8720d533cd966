"""Hostile use of the command line: fuzzed arguments and scenario files, the issue's cases one by one
(signals at random times: ``tests/cli/test_signals.py``).

Every answer is an exit status of 0, 1 (a run fault, named), 2 (bad input, one line) or 130
(interrupted), never a traceback, and a previous output is never lost.
"""

import json
import os
import random
import shutil
import tempfile
from pathlib import Path

import pytest
from conftest import call_main
from hypothesis import HealthCheck, event, given, seed, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
SCENARIO_TEXT = (ROOT / "quadobs/testbed/scenarios/ifac2021-noisy.toml").read_text()

HOSTILE_NUMBERS = [
    "nan",
    "inf",
    "-inf",
    "-1",
    "0",
    "1e306",
    "1e-300",
    "9223372036854775807",
    "1e999",
    "abc",
    "",
    "0x10",
    "1_000",
]
FIELDS = [
    "duration",
    "physics_rate",
    "seed",
    "record_every",
    "noise.range_std",
    "noise.range_rate",
    "noise.dropout",
    "initial.position_spread",
    "initial.point",
    "initial.kind",
    "trajectory.offset",
    "trajectory.terms",
    "excitation.step",
    "excitation.window",
    "model",
    "beacons",
    "observer.S0",
    "observer.gate",
    "name",
    "nosuch.field",
]
VALUES = HOSTILE_NUMBERS + [
    "[1e300, 0, 0]",
    "[0.0, 0.0]",
    "'/dev/zero'",
    "'/nonexistent/x.xml'",
    "''",
    "[[[[[[[[]]]]]]]]",
    '"zero"',
    '"point"',
    "[{axis=0, amplitude=1e300, omega=1e300}]",
    "[{position=[0,0,0]}]",
    "{a=1}",
    "true",
    "'" + "x" * 3000 + "'",
]


_call = call_main


def _check(code, err):
    assert code in (0, 1, 2, 130), (code, err)
    assert "Traceback" not in err, err
    if code in (1, 2):
        last = err.strip().splitlines()[-1]
        assert last.startswith("quadobs: error: ") or " error: " in last, err
        assert "quadobs: error: unexpected " not in last, err  # no fault of quadobs' own


@st.composite
def settings_args(draw):
    n = draw(st.integers(0, 3))
    args = []
    for _ in range(n):
        args += ["--set", f"{draw(st.sampled_from(FIELDS))}={draw(st.sampled_from(VALUES))}"]
    return args


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    command=st.sampled_from(["show", "excitation"]),
    sets=settings_args(),
    extra=st.lists(
        st.sampled_from(["--window", "--step", "--json"]).flatmap(
            lambda o: st.tuples(
                st.just(o), st.sampled_from(HOSTILE_NUMBERS + ["/dev/null", "/tmp"])
            )
        ),
        max_size=2,
    ),
)
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


@settings(
    max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    duration=st.sampled_from(["0.01", "0.02", "nan", "inf", "-1", "1e306", "abc", "0"]),
    sets=settings_args(),
    seed=st.sampled_from([None, "-1", "3", "99999999999999999999999"]),
)
def test_fuzzed_runs_answer_cleanly_and_keep_previous_outputs(
    tmp_path_factory, duration, sets, seed
):
    folder = tmp_path_factory.mktemp("fuzz")
    rrd, js = folder / "run.rrd", folder / "run.json"
    rrd.write_bytes(b"previous recording")
    js.write_text('{"previous": true}')
    argv = [
        "run",
        "ifac2021",
        "--no-progress",
        "--duration",
        duration,
        "--out",
        str(rrd),
        "--summary",
        str(js),
        *sets,
    ]
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
    path.write_bytes(
        _mutate(SCENARIO_TEXT, random.Random(seed)).encode("utf-8", errors="surrogateescape")
    )
    code, _, err = _call(["show", str(path)])
    _check(code, err)
    assert code in (0, 2)


# -- whole command lines and scenario files ------------------------------------------------------

#: Values for the options that take one; --duration and --runs keep a run short (or are refused).
NUMBERS = [v for v in HOSTILE_NUMBERS if v != "1_000"] + ["0.5", "2"]
OPTION_VALUES = {
    "--seed": ["0", "3", "-1", str(2**80), "abc", ""],
    "--estimators": ["augmented", "augmented,ekf", "ukf", "nosuch", ",", "augmented,augmented", ""],
    "--window": NUMBERS,
    "--step": NUMBERS,
    "--every": NUMBERS,
    "--threshold": NUMBERS,
    "--confidence": NUMBERS,
    "--dpi": NUMBERS,
    "--dt": NUMBERS,
    "--initial-offset": NUMBERS,
    "--workers": ["0", "-1", "5000", "abc"],
    "--retries": ["0", "1", "-1", "101", "abc"],
    "--what": ["", "paths", "nosuch", "rmse,,"],
    "--size": ["", "x", "1x", "nan,nan", "1e9x1e9", "0x0"],
    "--samples": ["", "1,2,3", "-1", "abc"],
    "--biases": ["", "1,2", "nan", "abc"],
    "--model": ["odometry", "cv", "bogus"],
    "--calibrate": ["self", "none", "x"],
}
#: Values each option takes without complaint, drawn twice as often as the hostile ones above.
VALID_VALUES = {
    "--seed": ["0", "3"],
    "--estimators": ["augmented", "augmented,ekf", "ukf"],
    "--window": ["0.5", "2"],
    "--step": ["0.01", "0.05"],
    "--every": ["0.1"],
    "--threshold": ["1", "0.5"],
    "--confidence": ["0.9"],
    "--dpi": ["50"],
    "--dt": ["0.1"],
    "--initial-offset": ["5"],
    "--workers": ["0"],
    "--retries": ["0", "1"],
    "--what": ["paths", "position"],
    "--size": ["3x2"],
    "--samples": ["1,2"],
    "--biases": ["1,2"],
    "--model": ["odometry", "cv"],
    "--calibrate": ["self", "none"],
}
#: The options of each command (others are drawn too, less often).
COMMAND_OPTIONS = {
    "run": ["--seed", "--estimators"],
    "show": [],
    "excitation": ["--window", "--step"],
    "list": [],
    "campaign": ["--seed", "--estimators", "--every", "--threshold", "--confidence", "--retries"],
    "plot": ["--what", "--size", "--dpi", "--samples"],
    "replay": [
        "--estimators",
        "--model",
        "--dt",
        "--initial-offset",
        "--seed",
        "--calibrate",
        "--biases",
    ],
}
PATH_OPTIONS = ["--out", "--summary", "--json", "--export"]
COMMAND_PATHS = {
    "run": ["--out", "--summary"],
    "excitation": ["--json"],
    "campaign": ["--out"],
    "plot": ["--out"],
    "replay": ["--out", "--summary", "--export"],
    "show": [],
    "list": [],
}
FLAGS = ["--no-progress", "--reference", "--help", "--version", "--bogus", "-x"]
#: Positional arguments per command; {names} are files made for each example.
POSITIONALS = {
    "run": [
        "ifac2021",
        "ifac2021-outliers",
        "le2013",
        "{scenario}",
        "{mutated}",
        "{nonutf8}",
        "nosuch",
        "",
        "{long}",
        "{dir}",
        "/dev/zero",
    ],
    "show": ["ifac2021", "{scenario}", "{mutated}", "{nonutf8}", "nosuch", "{long}", "{dir}"],
    "excitation": ["ifac2021", "{scenario}", "{mutated}", "le2013", "nosuch", "/dev/zero"],
    "campaign": ["ifac2021", "{scenario}", "{mutated}", "le2013", "nosuch"],
    "plot": ["{prev_rrd}", "{prev_json}", "{dir}", "/dev/null", "nosuch.rrd"],
    "replay": ["{dir}", "{prev_json}", "nosuch", ""],
    "list": [],
}
PATHS = [
    "{prev_rrd}",
    "{prev_json}",
    "{new_rrd}",
    "{new_json}",
    "{scenario}",
    "{dir}",
    "{fifo}",
    "{link}",
    "{long}",
    "/dev/null",
    "/dev/full",
    "{dir}/deep/new/x.json",
    "",
    "{nul}",
]


def _example_files(folder: Path, mutation_seed: int) -> dict:
    """The files an example may name: previous outputs, inputs, and hostile ones."""
    files = {
        "prev_rrd": folder / "prev.rrd",
        "prev_json": folder / "prev.json",
        "new_rrd": folder / "new.rrd",
        "new_json": folder / "new.json",
        "scenario": folder / "sc.toml",
        "mutated": folder / "mutated.toml",
        "nonutf8": folder / "nonutf8.toml",
        "dir": folder / "adir",
        "fifo": folder / "fifo",
        "link": folder / "link.json",
    }
    files["prev_rrd"].write_bytes(b"previous recording")
    files["prev_json"].write_text('{"previous": true}')
    files["scenario"].write_text((ROOT / "quadobs/testbed/scenarios/ifac2021.toml").read_text())
    text = _mutate(SCENARIO_TEXT, random.Random(mutation_seed))
    files["mutated"].write_bytes(text.encode("utf-8", errors="surrogateescape"))
    files["nonutf8"].write_bytes(b"\xff\xfe name = 1\n")
    files["dir"].mkdir()
    os.mkfifo(files["fifo"])
    files["link"].symlink_to(files["prev_json"])
    names = {k: str(v) for k, v in files.items()}
    names.update(long="y" * 5000, nul=str(folder / "a\0b"), campaign=str(folder / "camp"))
    return names


def _weighted(*pairs):
    """A strategy drawing each value with its (integer) weight."""
    return st.sampled_from([value for value, weight in pairs for _ in range(weight)])


@st.composite
def command_lines(draw):
    """A command, its positional argument, options with hostile values and paths, flags, --set overrides.

    Valid choices are drawn more often than hostile ones, so that runs also succeed and replace
    the previous outputs they name (and fail part-way, and get refused)."""
    command = draw(st.sampled_from(sorted(POSITIONALS)))
    argv = [command]
    if POSITIONALS[command]:
        first = POSITIONALS[command][0]
        argv.append(
            draw(
                _weighted(
                    (first, len(POSITIONALS[command])), *[(v, 1) for v in POSITIONALS[command][1:]]
                )
            )
        )
    if command in ("run", "campaign"):  # short runs, or refused
        argv += [
            "--duration",
            draw(
                _weighted(
                    ("0.05", 4), ("0.2", 2), *[(v, 1) for v in ("nan", "inf", "-1", "0", "1e306")]
                )
            ),
        ]
    if command == "campaign":
        argv += [
            "--runs",
            draw(_weighted(("1", 3), ("2", 3), ("0", 1), ("-1", 1), ("10000000", 1))),
            "--workers",
            "0",
            "--out",
            draw(_weighted(("{campaign}", 6), ("{dir}", 2), *[(v, 1) for v in PATHS])),
        ]
    if command == "run" and draw(st.booleans()):
        argv += [
            "--out",
            draw(_weighted(("{prev_rrd}", 3), ("{new_rrd}", 2), *[(v, 1) for v in PATHS])),
            "--summary",
            draw(_weighted(("{prev_json}", 3), ("{new_json}", 2), *[(v, 1) for v in PATHS])),
        ]
    for _ in range(draw(_weighted((0, 3), (1, 3), (2, 2), (3, 1), (4, 1)))):
        kind = draw(st.sampled_from(["value", "path", "flag"]))
        if kind == "value":
            own = COMMAND_OPTIONS[command]
            option = draw(
                _weighted(*[(o, 8) for o in own], *[(o, 1) for o in sorted(OPTION_VALUES)])
            )
            argv += [
                option,
                draw(
                    _weighted(
                        *[(v, 2 * len(OPTION_VALUES[option])) for v in VALID_VALUES[option]],
                        *[(v, len(VALID_VALUES[option])) for v in OPTION_VALUES[option]],
                    )
                ),
            ]
        elif kind == "path":
            argv += [
                draw(
                    _weighted(
                        *[(o, 4) for o in COMMAND_PATHS[command]], *[(o, 1) for o in PATH_OPTIONS]
                    )
                ),
                draw(st.sampled_from(PATHS)),
            ]
        else:
            argv.append(draw(_weighted(("--no-progress", 6), *[(f, 1) for f in FLAGS[1:]])))
    if command in ("run", "show", "excitation", "campaign") and draw(
        _weighted((False, 2), (True, 1))
    ):
        argv += draw(settings_args())
    return argv


def _snapshot(folder: Path) -> dict:
    """The bytes of every regular file in ``folder``, and the folders under it (``None``)."""
    files = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file() and not p.is_symlink()}
    return files | {
        str(p.relative_to(folder)): None
        for p in folder.rglob("*")
        if p.is_dir() and not p.is_symlink()
    }


def _check_complete(path: Path) -> None:
    """``path`` holds one complete JSON document or a readable recording."""
    data = path.read_bytes()
    if data.startswith(b"{"):
        json.loads(data)
    else:
        from quadobs.recording import list_entities

        assert list_entities(path), path


def _check_command_line(argv, folder: Path, before: dict, code: int, err: str) -> None:
    _check(code, err)
    after = _snapshot(folder)
    for name, data in before.items():
        if (
            data is not None and after.get(name) != data
        ):  # only a command that succeeded replaces a file, with a complete one
            assert code == 0 and name in ("prev.rrd", "prev.json"), (argv, name)
            _check_complete(folder / name)
    assert not [n for n in after if n.endswith(".partial")] or code == 1, argv
    if code != 0:  # a failed command leaves no folder it created
        assert {n for n, d in after.items() if d is None} == {
            n for n, d in before.items() if d is None
        }, argv


def _fuzz_command_lines(argv, mutation_seed):
    folder = Path(tempfile.mkdtemp(prefix="quadobs-fuzz-"))
    try:
        names = _example_files(folder, mutation_seed)
        for key, value in names.items():
            argv = [a.replace("{" + key + "}", value) for a in argv]
        before = _snapshot(folder)
        here = os.getcwd()
        os.chdir(folder)  # relative paths land in the example's folder
        try:
            code, _, err = _call(argv)
        finally:
            os.chdir(here)
        event(f"{argv[0]}: exit {code}")
        _check_command_line(argv, folder, before, code, err)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@seed(20211)
@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(argv=command_lines(), mutation_seed=st.integers(0, 2**32 - 1))
def test_fuzzed_command_lines_answer_cleanly_and_keep_previous_outputs(argv, mutation_seed):
    """Any command with hostile arguments, option values, paths (previous outputs, the scenario file,
    a directory, a FIFO, a device, a link, 5000 characters, NUL), flags and --set overrides, on built-in,
    copied and mutated scenario files: exit 0, 1 (a named run fault), 2 or 130, never a traceback, and
    every file there before is untouched unless the command succeeded and replaced it with a complete one."""
    _fuzz_command_lines(argv, mutation_seed)


@pytest.mark.slow
@seed(2021)
@settings(max_examples=1500, deadline=None, suppress_health_check=list(HealthCheck))
@given(argv=command_lines(), mutation_seed=st.integers(0, 2**32 - 1))
def test_fuzzed_command_lines_at_length(argv, mutation_seed):
    """:func:`test_fuzzed_command_lines_answer_cleanly_and_keep_previous_outputs` with many more examples."""
    _fuzz_command_lines(argv, mutation_seed)


# -- the cases, one by one --------------------------------------------------------------


def _hostile_files(folder: Path) -> dict:
    (folder / "prev.rrd").write_bytes(b"previous recording")
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
    (
        ["campaign", "ifac2021", "--runs", "2", "--duration", "1e306", "--out", "{f}/c"],
        "duration: must be at most",
    ),
    (["run", "ifac2021", "--set", "physics_rate=1e300"], "physics_rate: must be at most"),
    (
        ["run", "ifac2021", "--set", "record_every=9223372036854775807", "--out", "{f}/prev.rrd"],
        "record_every: must be at most",
    ),
    (
        ["run", "ifac2021", "--set", "trajectory.offset=[1e11, 0, 0]", "--out", "{f}/prev.rrd"],
        "trajectory.offset[0]: must be at most",
    ),
    (
        ["run", "ifac2021", "--set", "trajectory.terms=[{axis=0, amplitude=2e10, omega=1.0}]"],
        "trajectory.terms[0].amplitude: must be at most",
    ),
    (["run", "ifac2021", "--duration", "1e12"], "duration: must be at most"),
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
    (
        ["run", "le2013", "--duration", "0.4"],
        "--duration: le2013 counts samples, expected a whole number at least 1, got 0.4",
    ),
    (["excitation", "ifac2021", "--step", "1e-9"], "step:"),
    (["run", "ifac2021", "--set", "noise.range_std=1e300"], "noise.range_std: must be at most"),
    (
        ["run", "ifac2021", "--set", "initial.position_spread=1e300"],
        "initial.position_spread: must be at most",
    ),
    (
        ["run", "ifac2021", "--set", "initial.kind='zero'", "--set", "initial.point=[0,0,0,0,0,0]"],
        "initial.point: only used with kind = \"point\", not 'zero'",
    ),
    (["run", "ifac2021", "--seed", str(2**80)], "seed: must be at most"),
    (["campaign", "ifac2021", "--runs", "2", "--retries", "-1", "--out", "{f}/c"], "retries"),
]


@pytest.mark.parametrize("argv, message", CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_each_hostile_case_gets_one_line_and_status_2(tmp_path, argv, message):
    names = _hostile_files(tmp_path)
    code, _, err = _call([a.replace("{f}", names["f"]) for a in argv])
    lines = [
        ln
        for ln in err.strip().splitlines()
        if not ln.startswith(("quadobs: compiling", "quadobs: note:"))
    ]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("quadobs: error: "), err
    assert message in lines[0] and len(lines[0]) < 400 and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "adir",
        "deep.toml",
        "loop1",
        "loop2",
        "nonutf8.toml",
        "prev.rrd",
    ]
    assert (tmp_path / "prev.rrd").read_bytes() == b"previous recording"
