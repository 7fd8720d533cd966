"""SIGINT and SIGTERM at any moment of the ``quadobs`` program: start-up (the imports of NumPy, SciPy,
Numba and MuJoCo), the run, the interpreter's exit; interrupts Python cannot raise; in-process calls.

The answer is status 130 with the one line ``quadobs: interrupted`` (or 0 when the command was
already done), never a traceback, and the previous outputs are either untouched or both replaced
by complete new ones. The only exception is a signal that arrives before ``quadobs.cli.main`` has
started (the interpreter's own start-up): Python's defaults apply there (killed by the signal, or
a ``KeyboardInterrupt`` traceback with no frame inside a quadobs function), and nothing is open.
"""

import json
import os
import random
import re
import signal
import sys
import time
from pathlib import Path

import pytest

import quadobs.cli as cli
from quadobs.cli import main

NOTICES = (
    "quadobs: compiling",
    "quadobs: note:",
)  # a first run's compile notice, a long run's cost notice
PREVIOUS_RRD, PREVIOUS_JSON = b"previous recording", '{"previous": true}'


def _lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(NOTICES)]


def _before_main(proc, sig, err) -> bool:
    """Whether the answer is Python's default for a signal that came before ``main`` started: killed by
    it, or a ``KeyboardInterrupt`` traceback whose frames lie outside every quadobs function."""
    if proc.returncode == -sig and not err.strip():
        return True
    frames = re.findall(r'File "([^"]+)", line \d+, in (\S+)', err)
    in_quadobs = [
        fn for path, fn in frames if f"{os.sep}quadobs{os.sep}" in path and fn != "<module>"
    ]
    return bool(frames) and not in_quadobs and err.rstrip().endswith("KeyboardInterrupt")


def _check_answer(proc, sig, err) -> str:
    lines = _lines(err)
    if proc.returncode == 0:
        assert lines == [], err
        return "done"
    if proc.returncode == 130:
        assert lines == ["quadobs: interrupted"], err
        return "interrupted"
    assert _before_main(proc, sig, err), (sig, proc.returncode, err)
    return "before main"


def _previous_outputs(folder: Path) -> tuple[Path, Path]:
    rrd, js = folder / "run.rrd", folder / "run.json"
    rrd.write_bytes(PREVIOUS_RRD)
    js.write_text(PREVIOUS_JSON)
    return rrd, js


def _check_outputs(folder: Path, rrd: Path, js: Path, total: int = 0) -> bool:
    """The recording and the summary are both untouched or both complete new ones; no staging file is left.

    ``total``: the run's steps (the recording has the final row once all of them are done)."""
    replaced = rrd.read_bytes() != PREVIOUS_RRD
    assert replaced == (js.read_text() != PREVIOUS_JSON), (
        "the recording and the summary are replaced together"
    )
    if replaced:
        from quadobs.recording import read_series

        steps = read_series(rrd, "errors/augmented/position/norm")["step"]
        summary = json.loads(js.read_text())
        done = summary["physics_steps"]
        # the final row (the truth and estimates after the last step) is there when every step is: a stop
        # that arrives while the last block is sent finds the run complete (and still says it was stopped)
        complete = done == total
        assert complete or summary["interrupted"]
        assert steps.size > 0 and steps.size == done + (1 if complete else 0)
    assert not [p.name for p in folder.iterdir() if p.name.endswith(".partial")]
    return replaced


# -- at random times, start-up included --------------------------------------------------------


@pytest.mark.parametrize("trial", range(8))
def test_signals_at_random_times_never_lose_the_previous_outputs(tmp_path, cli_process, trial):
    """SIGINT or SIGTERM at a seeded random time: half the trials in the first 1.5 s (the interpreter's
    start-up, then the imports of NumPy, SciPy, Numba and MuJoCo), half over the rest of a 3 s run."""
    rnd = random.Random(1000 + trial)
    sig = rnd.choice([signal.SIGINT, signal.SIGTERM])
    delay = rnd.uniform(0.0, 1.5) if trial % 2 == 0 else rnd.uniform(1.5, 5.0)
    rrd, js = _previous_outputs(tmp_path)
    proc = cli_process(
        "run",
        "ifac2021",
        "--duration",
        "3",
        "--no-progress",
        "--out",
        str(rrd),
        "--summary",
        str(js),
    )
    time.sleep(delay)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    answer = _check_answer(proc, sig, err)
    replaced = _check_outputs(tmp_path, rrd, js, 3000)
    assert answer != "before main" or not replaced


SIGNAL_ON_IMPORT = '''
"""Run the quadobs program, sending a signal to itself a moment after MODULE starts to load."""
import importlib.abc, os, sys, threading

MODULE, SIG, DELAY = os.environ["ON_IMPORT"], int(os.environ["SIGNAL"]), float(os.environ["DELAY"])


class Watch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == MODULE:
            sys.meta_path.remove(self)
            threading.Timer(DELAY, os.kill, (os.getpid(), SIG)).start()
        return None


sys.meta_path.insert(0, Watch())
from quadobs.cli import main

sys.exit(main())
'''


@pytest.mark.parametrize("module", ["numpy", "scipy.linalg", "numba", "mujoco"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_a_module_loads_ends_with_130_and_one_line(
    tmp_path, cli_process, module, sig
):
    """The signal comes 0 to 20 ms (seeded) after the import of ``module`` starts, before the run
    opens anything: status 130, exactly one line, the previous outputs untouched."""
    (tmp_path / "signal_on_import.py").write_text(SIGNAL_ON_IMPORT)
    delay = random.Random(f"{module}-{sig}").uniform(0.0, 0.02)
    rrd, js = _previous_outputs(tmp_path)
    proc = cli_process(
        "run",
        "ifac2021",
        "--duration",
        "3",
        "--no-progress",
        "--out",
        str(rrd),
        "--summary",
        str(js),
        module="signal_on_import",
        path=[tmp_path],
        env={"ON_IMPORT": module, "SIGNAL": str(int(sig)), "DELAY": str(delay)},
    )
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130 and _lines(err) == ["quadobs: interrupted"], err
    assert not _check_outputs(tmp_path, rrd, js)


@pytest.mark.parametrize("trial", range(4))
def test_a_signal_as_the_recording_opens_replaces_both_outputs_or_neither(
    tmp_path, cli_process, trial
):
    """The signal comes 0 to 50 ms (seeded) after the recording's staging file appears, around the
    first steps of a 30 s run: status 130 and one line; a run stopped before its first step replaces neither file."""
    sig = random.Random(3000 + trial).choice([signal.SIGINT, signal.SIGTERM])
    rrd, js = _previous_outputs(tmp_path)
    proc = cli_process(
        "run",
        "ifac2021",
        "--duration",
        "30",
        "--no-progress",
        "--out",
        str(rrd),
        "--summary",
        str(js),
    )
    deadline = time.monotonic() + 300
    while not list(tmp_path.glob(".run.rrd.*.partial")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.0005)
    time.sleep(random.Random(3000 + trial).uniform(0.0, 0.05))
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and _lines(err) == ["quadobs: interrupted"], err
    _check_outputs(tmp_path, rrd, js, 30000)


# -- at exit ------------------------------------------------------------------------------------


@pytest.mark.parametrize("trial", range(4))
def test_a_signal_at_exit_keeps_the_complete_outputs(tmp_path, cli_process, trial):
    """The signal comes 0 to 30 ms (seeded) after the summary is in place, as the program ends: status 0
    (it had ended) or 130 with one line, and both outputs complete and new."""
    rnd = random.Random(2000 + trial)
    sig = rnd.choice([signal.SIGINT, signal.SIGTERM])
    rrd, js = _previous_outputs(tmp_path)
    proc = cli_process(
        "run",
        "ifac2021",
        "--duration",
        "0.2",
        "--no-progress",
        "--out",
        str(rrd),
        "--summary",
        str(js),
    )
    deadline = time.monotonic() + 300
    while js.read_text() == PREVIOUS_JSON and proc.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.001)
    time.sleep(rnd.uniform(0.0, 0.03))
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert _check_answer(proc, sig, err) in ("done", "interrupted")
    assert _check_outputs(tmp_path, rrd, js, 200)


# -- interrupts that Python cannot raise --------------------------------------------------------


LOST_INTERRUPT = '''
"""Run quadobs.cli.main with a command whose SIGINT arrives where Python cannot raise it."""
import os, signal, sys, time

import quadobs.cli as cli

WHERE, WORK = os.environ["WHERE"], float(os.environ["WORK"])


class Dropper:
    def __del__(self):  # the handler's KeyboardInterrupt cannot leave a __del__
        signal.raise_signal(signal.SIGINT)


def command(argv):
    if WHERE == "__del__":
        Dropper()
    else:  # inside a string exec, as namedtuple and dataclasses use: CPython notes it as unhandled
        exec("import signal; signal.raise_signal(signal.SIGINT)", {})
    t0 = time.monotonic()
    while time.monotonic() - t0 < WORK:
        time.sleep(0.01)
    print("finished", flush=True)
    return 0


cli._run_command = command
sys.exit(cli.main())
'''


@pytest.mark.parametrize("where, work", [("__del__", 0.0), ("__del__", 60.0), ("exec", 0.0)])
def test_an_interrupt_python_cannot_raise_still_ends_the_command(
    tmp_path, cli_process, where, work
):
    """A KeyboardInterrupt lost in a ``__del__`` is sent again and stops a command that runs on (in well
    under its 60 s); a command that ends at once ends with 130 all the same. One raised inside a string
    ``exec`` (which CPython then notes as unhandled, and under ``python -m`` would end the process by
    SIGINT after ``main`` returned) ends with 130."""
    (tmp_path / "lost_interrupt.py").write_text(LOST_INTERRUPT)
    t0 = time.monotonic()
    proc = cli_process(
        "list", module="lost_interrupt", path=[tmp_path], env={"WHERE": where, "WORK": str(work)}
    )
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and _lines(err) == ["quadobs: interrupted"], (
        proc.returncode,
        err,
    )
    assert ("finished" in out) == (
        where == "__del__" and work == 0.0
    ) and time.monotonic() - t0 < 30


# -- in-process calls ---------------------------------------------------------------------------


def test_an_in_process_call_gives_back_the_handlers_and_a_signal_that_came_while_returning(
    monkeypatch,
):
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM), sys.unraisablehook
    assert main(["list"]) == 0
    assert (
        signal.getsignal(signal.SIGINT),
        signal.getsignal(signal.SIGTERM),
        sys.unraisablehook,
    ) == before

    def interrupted(argv):
        raise KeyboardInterrupt

    class SignalOnWrite:  # stderr that receives a SIGTERM while main writes "interrupted" on it
        def __init__(self):
            self.text = ""

        def write(self, text):
            self.text += text
            signal.raise_signal(signal.SIGTERM)

        def flush(self):
            pass

    got = []
    monkeypatch.setattr(cli, "_run_command", interrupted)
    monkeypatch.setattr(sys, "stderr", SignalOnWrite())
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        assert main(["list"]) == 130
        assert sys.stderr.text.strip() == "quadobs: interrupted"
        assert got == [signal.SIGTERM] * len(got) and got, (
            "held while main returned, then delivered to the caller"
        )
    finally:
        signal.signal(signal.SIGTERM, previous)


def _command_that(action):
    def command(args):
        action()
        return 0

    return command


def test_an_error_made_of_an_interrupt_is_the_interrupt(monkeypatch, capsys):
    """An error raised while a Ctrl-C was handled (a compiled extension whose initialisation it cut
    short raises ``ImportError: initialization failed``) ends the command as the interrupt would."""

    def failed_import():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("initialization failed")  # noqa: B904 (the context is the test)

    monkeypatch.setattr(cli, "_cmd_list", _command_that(failed_import))
    assert main(["list"]) == 130
    assert capsys.readouterr().err.strip() == "quadobs: interrupted"


def test_an_interrupt_swallowed_by_the_command_still_ends_it_with_130(monkeypatch, capsys):
    """A SIGINT taken during the command whose interrupt some code caught and dropped: status 130."""

    def swallow():
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            pass

    monkeypatch.setattr(cli, "_cmd_list", _command_that(swallow))
    assert main(["list"]) == 130
    assert capsys.readouterr().err.strip() == "quadobs: interrupted"
    monkeypatch.setattr(cli, "_cmd_list", _command_that(lambda: None))
    assert main(["list"]) == 0  # the next call starts afresh


def test_an_interrupt_swallowed_while_modules_load_stops_the_run_before_it_starts(
    monkeypatch, capsys, tmp_path
):
    """As MuJoCo does for its optional renderer: the Ctrl-C comes during a module's initialisation,
    turns into an ImportError, and the importing package drops it. The run must not start."""
    import quadobs.testbed.episode

    def loading_with_a_dropped_interrupt(kernels, file=None):
        try:
            try:
                signal.raise_signal(signal.SIGINT)
            except KeyboardInterrupt:
                raise ImportError("initialization failed")  # noqa: B904 (the context is the test)
        except ImportError:  # the package's optional part is left out
            pass
        return False

    def no_run(*args, **kwargs):
        raise AssertionError("the run started")

    monkeypatch.setattr(cli, "_notice_cold_kernels", loading_with_a_dropped_interrupt)
    monkeypatch.setattr(quadobs.testbed.episode, "run_episode", no_run)
    rrd, js = _previous_outputs(tmp_path)
    assert (
        main(["run", "ifac2021", "--no-progress", "--out", str(rrd), "--summary", str(js)]) == 130
    )
    assert capsys.readouterr().err.strip() == "quadobs: interrupted"
    assert not _check_outputs(tmp_path, rrd, js)
