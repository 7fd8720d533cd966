"""The command line's conveniences: ``python -m quadobs``, ``--version``, the estimators' help,
``quadobs list``, le2013's options, the first-run notice, and no folders left by a failed run."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import quadobs
import quadobs._kernels
import quadobs.cli as cli
from quadobs.cli import main
from quadobs.errors import QuadobsError, check_writable, new_folders_removed_on_failure

ROOT = Path(__file__).resolve().parents[2]


def _python(*args, env=None, cwd=None):
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=120
    )


def _error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    err = [
        line for line in lines if not line.startswith("quadobs: compiling")
    ]  # the first-run notice may precede it
    assert len(err) == 1 and err[0].startswith("quadobs: error: "), err
    return err[0]


# -- python -m quadobs, --version, --estimators ----------------------------------------------


def test_python_m_quadobs_is_the_command_and_prints_its_version(tmp_path):
    done = _python("-m", "quadobs", "--version", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"quadobs {cli.package_version()}"
    assert cli.package_version() == quadobs.__version__
    done = _python("-m", "quadobs", "list", cwd=tmp_path)
    assert done.returncode == 0 and "ifac2021" in done.stdout and "le2013" in done.stdout
    done = _python("-m", "quadobs", "run", "no-such-scenario", cwd=tmp_path)
    assert done.returncode == 2 and "unknown name 'no-such-scenario'" in done.stderr


def test_version_has_one_source_the_package_metadata(monkeypatch):
    import importlib.metadata
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    assert quadobs.__version__ == project["project"]["version"]
    assert "__version__ = " not in Path(quadobs.__file__).read_text()

    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    assert quadobs._distribution_version() == "0+unknown"  # a source tree never installed


@pytest.mark.parametrize("command", ["run", "campaign"])
def test_estimators_help_lists_the_registered_names(command, capsys, monkeypatch):
    from quadobs.testbed.registry import available_estimators

    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in available_estimators():
        assert name in text
    import quadobs.testbed.registry as registry

    monkeypatch.setattr(
        registry, "available_estimators", lambda scenario=None: ["augmented", "my_100%_filter"]
    )
    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert "registered: augmented, my_100%_filter" in " ".join(capsys.readouterr().out.split())


# -- quadobs list ---------------------------------------------------------------------------


def test_list_is_sorted_aligned_one_line_each_and_holds_le2013(capsys, monkeypatch):
    from quadobs.testbed.scenario import list_scenarios

    monkeypatch.setenv("COLUMNS", "90")
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = [line.split()[0] for line in lines]
    assert names == sorted([*list_scenarios(), "le2013"])
    starts = {len(line) - len(line[len(name) :].lstrip()) for line, name in zip(lines, names)}
    assert len(starts) == 1, "descriptions start in one column"
    assert all(len(line) <= 90 for line in lines)
    assert all(line.split(None, 1)[1].strip() for line in lines), "every scenario has a description"
    assert "[LE2013]" in lines[names.index("le2013")]


def test_one_line_cuts_at_a_word():
    assert cli._one_line("short\nsecond line", 40) == "short"
    cut = cli._one_line("alpha beta gamma delta epsilon", 20)
    assert cut.endswith("...") and len(cut) <= 20 and cut[:-3] in "alpha beta gamma delta epsilon"
    assert cli._one_line("", 10) == ""


# -- le2013 takes its options and refuses the others ------------------------------------------


@pytest.fixture
def no_le2013_run(monkeypatch):
    import quadobs.studies.le2013.study as study

    def no_run(*a, **k):
        raise AssertionError("run_le2013 started")

    monkeypatch.setattr(study, "run_le2013", no_run)


@pytest.mark.parametrize(
    "argv, field",
    [
        (["--estimators", "ekf"], "--estimators: does not apply to le2013"),
        (["--duration", "2.5"], "--duration: le2013 counts samples"),
        (["--duration", "0"], "--duration: le2013 counts samples"),
        (["--seed", "-1"], "seed: must be at least 0"),
        (["--runs", "0"], "--runs: must be at least 1"),
    ],
)
def test_le2013_refuses_what_does_not_apply(argv, field, capsys, no_le2013_run, tmp_path):
    assert main(["run", "le2013", "--out", str(tmp_path / "new" / "x.rrd"), *argv]) == 2
    assert field in _error_line(capsys)
    assert list(tmp_path.iterdir()) == []


def test_le2013_settings_map_duration_seed_runs():
    args = cli.build_parser().parse_args(
        ["run", "le2013", "--duration", "20", "--seed", "7", "--runs", "3", "--no-progress"]
    )
    assert cli._le2013_settings(args) == {"seed": 7, "steps": 20, "runs": 3}
    args = cli.build_parser().parse_args(["run", "le2013"])
    assert cli._le2013_settings(args) == {"seed": 0, "steps": 50, "runs": 50}


def test_runs_is_refused_for_a_vehicle_scenario_and_le2013_by_campaign(capsys, tmp_path):
    assert main(["run", "ifac2021", "--runs", "3", "--no-progress"]) == 2
    assert "--runs: applies to le2013 only" in _error_line(capsys)
    assert main(["campaign", "le2013", "--runs", "2", "--out", str(tmp_path / "c")]) == 2
    assert "quadobs run le2013" in _error_line(capsys)
    assert list(tmp_path.iterdir()) == []


# -- the first-run notice --------------------------------------------------------------------


def test_cold_kernels_reads_the_cache_without_compiling(tmp_path):
    """Against an empty NUMBA_CACHE_DIR every kernel is cold; nothing is compiled by asking."""
    code = (
        "import sys, time; from quadobs._kernels import cold_kernels; import quadobs.cli as c;"
        "t = time.perf_counter(); cold = cold_kernels(c.BENCH_KERNELS + c.EPISODE_KERNELS + c.AUGMENTED_KERNELS);"
        "print(len(cold), round(time.perf_counter() - t, 3))"
    )
    done = _python("-c", code, env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
    assert done.returncode == 0, done.stderr
    n, seconds = done.stdout.split()
    assert int(n) == len(cli.BENCH_KERNELS + cli.EPISODE_KERNELS + cli.AUGMENTED_KERNELS)
    assert float(seconds) < 5.0
    assert not list((tmp_path / "numba").rglob("*.nbc")), "asking compiled something"


def test_cold_kernels_sees_a_compiled_kernel(tmp_path):
    """A tiny cached kernel: cold before its first call, warm after, in a fresh process."""
    (tmp_path / "tiny_kernel.py").write_text(
        "from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
    )
    code = "from quadobs._kernels import cold_kernels; import sys; print(cold_kernels(['tiny_kernel:twice']))"
    env = {
        "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
        "PYTHONPATH": f"{ROOT}{os.pathsep}{tmp_path}",
    }
    first = _python("-c", code + "; import tiny_kernel; tiny_kernel.twice(2)", env=env)
    second = _python("-c", code, env=env)
    assert first.stdout.strip() == "['tiny_kernel:twice']", first.stderr
    assert second.stdout.strip() == "[]", second.stderr


def test_cold_kernels_says_nothing_when_it_cannot_tell():
    assert (
        quadobs._kernels.cold_kernels(["quadobs.errors:check_writable"]) == []
    )  # not a Numba dispatcher


@pytest.mark.parametrize("cold", [True, False])
def test_the_notice_is_one_line_on_stderr_when_kernels_are_cold(cold, capsys, monkeypatch):
    import quadobs._kernels.precompile as pre

    compiled = []
    monkeypatch.setattr(
        quadobs._kernels, "cold_kernels", lambda kernels: list(kernels) if cold else []
    )
    monkeypatch.setattr(
        pre, "compile_side_by_side", lambda kernels: compiled.extend(kernels) or list(kernels)
    )
    assert main(["run", "ifac2021", "--estimators", "nosuch", "--no-progress"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count(cli.COMPILING_NOTICE) == (1 if cold else 0)
    assert compiled == (
        list(cli._episode_kernels(["nosuch"])) if cold else []
    )  # the cold ones, side by side
    assert (
        captured.err.strip()
        .splitlines()[-1]
        .startswith("quadobs: error: estimators: unknown estimator 'nosuch'")
    )


def test_the_episode_kernels_follow_the_estimators():
    assert set(cli.AUGMENTED_KERNELS) <= set(cli._episode_kernels(None))
    assert set(cli.AUGMENTED_KERNELS) <= set(cli._episode_kernels(["ekf", "augmented"]))
    assert not set(cli.AUGMENTED_KERNELS) & set(cli._episode_kernels(["ekf"]))


# -- no folders left behind ------------------------------------------------------------------


def test_failed_runs_leave_no_folder(tmp_path, capsys):
    new = tmp_path / "newdir" / "sub"
    # an unknown estimator: found after the outputs were checked (which creates their folders)
    assert (
        main(
            [
                "run",
                "ifac2021",
                "--out",
                str(new / "x.rrd"),
                "--summary",
                str(new / "s.json"),
                "--estimators",
                "nosuch",
            ]
        )
        == 2
    )
    assert "unknown estimator 'nosuch'" in _error_line(capsys)
    assert list(tmp_path.iterdir()) == []
    # an unwritable recording after a summary folder was created for the run
    (tmp_path / "file").write_text("")
    code = main(
        [
            "run",
            "ifac2021",
            "--no-progress",
            "--summary",
            str(new / "s.json"),
            "--out",
            str(tmp_path / "file" / "x.rrd"),
        ]
    )
    assert code == 2 and "cannot be written" in _error_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    # a bad scenario field
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\nduration = -1.0\n')
    assert main(["run", str(bad), "--out", str(new / "x.rrd")]) == 2
    _error_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml", "file"]
    # the excitation report and the campaign
    assert main(["excitation", "nosuch", "--json", str(new / "r.json")]) == 2
    assert (
        main(
            [
                "campaign",
                "ifac2021",
                "--runs",
                "2",
                "--out",
                str(new / "c"),
                "--estimators",
                "nosuch",
            ]
        )
        == 2
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml", "file"]


def test_new_folders_removed_on_failure_keeps_what_it_should(tmp_path):
    (tmp_path / "old").mkdir()
    with pytest.raises(QuadobsError):
        with new_folders_removed_on_failure(
            tmp_path / "old" / "a" / "b" / "x.rrd", None, tmp_path / "c" / "y.json"
        ):
            check_writable(tmp_path / "old" / "a" / "b" / "x.rrd")
            check_writable(tmp_path / "c" / "y.json")
            (tmp_path / "c" / "y.json").write_text("{}")  # a file written before the failure stays
            raise QuadobsError("estimators: no")
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == [
        "c",
        "c/y.json",
        "old",
    ]
    with new_folders_removed_on_failure(tmp_path / "d" / "x.rrd"):  # success keeps them
        check_writable(tmp_path / "d" / "x.rrd")
    assert (tmp_path / "d").is_dir()
    with pytest.raises(KeyboardInterrupt):
        with new_folders_removed_on_failure(tmp_path / "e" / "x.rrd"):
            check_writable(tmp_path / "e" / "x.rrd")
            raise KeyboardInterrupt
    assert not (tmp_path / "e").exists()


def test_output_into_a_closed_pipe_ends_quietly(tmp_path):
    """``quadobs run ... | head -1``: the reader goes away; no traceback, the summary is still written."""
    import subprocess
    import sys

    summary = tmp_path / "s.json"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "quadobs",
            "run",
            "ifac2021",
            "--duration",
            "0.5",
            "--no-progress",
            "--summary",
            str(summary),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=tmp_path,
    )
    proc.stdout.close()  # the reader stops before the table is printed
    err = proc.stderr.read().decode()
    proc.wait(timeout=120)
    assert proc.returncode == 141, err
    assert "Traceback" not in err and summary.is_file()


# -- compiling side by side ------------------------------------------------------------------


_SIGNATURES_CALLED = """
import importlib, json
import numpy as np
import quadobs
from quadobs._kernels.precompile import SIGNATURES, signature, signatures
from quadobs.testbed.episode import run_episode
from quadobs.testbed.factories import augmented_observer
from quadobs.core.measurements import Measurement
from quadobs.estimators.augmented_tuning import state_noise_map

sc = quadobs.load_scenario("ifac2021", duration=0.05)
run_episode(quadobs.load_scenario("ifac2021", duration=10.0))
run_episode(sc, path="step")
obs = augmented_observer(sc, np.zeros(sc.state_dim))
obs.step(np.zeros(sc.dimension), np.zeros(1))
obs.predict(obs.time + 0.37 * sc.dt)  # an interval off the grid: the interface in time
obs.noise_of = state_noise_map(obs.immersion, np.eye(sc.state_dim))  # the state noise, compiled
obs.predict(obs.time + 0.37 * sc.dt)
obs.correct(Measurement(obs.time, "range", 5.0, (0,), 0.1))  # one range at its own time
obs.in_time_compiled = False  # the NumPy reference: the exponentials' series
obs.predict(obs.time + 0.37 * sc.dt)
out = {}
for spec in SIGNATURES:
    module, _, name = spec.partition(":")
    called = set(getattr(importlib.import_module(module), name).signatures)
    listed = {signature(codes) for codes in signatures(spec)}
    out[spec] = [str(s) for s in called ^ listed]
print(json.dumps(out))
"""


def test_the_precompiled_signatures_are_those_the_testbed_calls():
    """Each kernel of SIGNATURES, after episodes on each path and a public step (in a fresh process), has
    exactly the listed signatures: none missing, none compiled besides.

    The 10 s episode has a block that ends one step after the excitation monitor is due
    (steps 7869 to 8401): the observer then gets one row, whose views are contiguous."""
    pytest.importorskip("numba")
    from quadobs._kernels.precompile import EPISODE, SIGNATURES

    done = _python("-c", _SIGNATURES_CALLED)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == {
        spec: [] for spec in SIGNATURES
    }  # spec: listed ^ called
    assert set(EPISODE) <= set(cli._episode_kernels(None))


def test_compile_side_by_side_fills_the_cache(tmp_path):
    """A kernel compiled by a child process is warm for the next process (an empty cache before)."""
    spec = "quadobs.testbed.worlds._read:read_block"
    code = (
        "import sys; from quadobs._kernels import cold_kernels; from quadobs._kernels.precompile import compile_side_by_side;"
        f"before = cold_kernels([{spec!r}]); done = compile_side_by_side([{spec!r}, 'not.a:kernel']);"
        f"print(before, done, cold_kernels([{spec!r}]))"
    )
    done = _python("-c", code, env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [f"[{spec!r}]", f"[{spec!r}]", "[]"]
