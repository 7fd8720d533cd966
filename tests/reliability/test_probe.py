"""The hostile probe of the command line, re-run: each case a ``quadobs`` process under ``timeout -k``.

Every case is checked against what ``docs/failure-behaviour.md`` promises: no data lost (a
previous output, a log read, a folder replaced either untouched or complete and new), no
exit status 0 with a wrong result, no traceback (at most one ``quadobs: error:`` line), and
no hang (each process under ``timeout -k``; status 124 or 137 is a failure). The cases need
no root: a full disk is a file size limit (``RLIMIT_FSIZE``, SIGXFSZ ignored), low limits
are ``RLIMIT_NOFILE`` and ``RLIMIT_AS``.

``pytest -m slow tests/reliability/test_probe.py`` runs them as tests (a few minutes);
``python tests/reliability/test_probe.py`` runs them all and prints the counts per category.
"""

from __future__ import annotations

import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: Seconds a case's process may run before ``timeout`` stops it (then SIGKILL 5 s later).
LIMIT = 240


@dataclass
class Result:
    code: int
    out: str
    err: str
    seconds: float


def quadobs(
    cwd: Path, *args: str, limits=(), env=None, module="quadobs.cli", limit=LIMIT, signal_after=None
) -> Result:
    """``python -m quadobs.cli ARGS`` under ``timeout -k 5 LIMIT``, with ``limits`` set in the child.

    ``limits``: ``(resource, soft_and_hard)`` pairs; SIGXFSZ is ignored so a file size limit
    acts as a full disk. ``signal_after``: ``(signal, seconds)`` sent to the process group.
    """

    def child():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        for which, value in limits:
            resource.setrlimit(which, (value, value))

    cmd = ["timeout", "-k", "5", str(limit), sys.executable, "-m", module, *map(str, args)]
    environ = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    start = time.monotonic()
    proc = subprocess.Popen(
        cmd, cwd=cwd, env=environ, preexec_fn=child, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, errors="replace",
    )  # fmt: skip
    if signal_after is not None:
        sig, after = signal_after
        try:
            proc.communicate(timeout=after)
        except subprocess.TimeoutExpired:
            proc.send_signal(sig)  # to ``timeout``, which passes it on
    out, err = proc.communicate()
    return Result(proc.returncode, out, err, time.monotonic() - start)


def promise(result: Result, codes, *words: str) -> None:
    """The status is one of ``codes``, no hang, no traceback, at most one error line (holding ``words``)."""
    assert result.code not in (124, 137), f"hung: stopped by timeout after {result.seconds:.0f} s"
    assert "Traceback" not in result.err, result.err[-2000:]
    errors = [ln for ln in result.err.splitlines() if ln.startswith("quadobs: error:")]
    assert len(errors) <= 1, result.err[-2000:]
    assert result.code in codes, (result.code, result.err[-2000:])
    for word in words:
        assert errors and word in errors[0], (word, result.err[-2000:])
    assert "\x1b" not in result.err, "an escape sequence reached the terminal"


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def no_staging(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if p.name.endswith(".partial")]
    assert not left, left


# -- the inputs ---------------------------------------------------------------------------------

_LOG: dict[str, Path] = {}


def base_log() -> Path:
    """A small log folder exported from a simulated run (made once per process)."""
    if "log" not in _LOG:
        folder = Path(tempfile.mkdtemp(prefix="quadobs-probe-")) / "L"
        promise(quadobs(folder.parent, "run", "ifac2021", "--duration", "0.5", "--no-progress",
                        "--export-log", folder), (0,))  # fmt: skip
        _LOG["log"] = folder
    return _LOG["log"]


def log_copy(tmp: Path, name: str = "L") -> Path:
    folder = tmp / name
    shutil.copytree(base_log(), folder)
    return folder


def replay(tmp: Path, log: Path, *args: str, **kw) -> Result:
    return quadobs(tmp, "replay", log, "--calibrate", "none", *args, **kw)


def previous_outputs(tmp: Path) -> tuple[Path, Path]:
    rrd, js = tmp / "r.rrd", tmp / "r.json"
    rrd.write_bytes(b"previous recording")
    js.write_text('{"previous": true}')
    return rrd, js


RUN = ("run", "ifac2021", "--no-progress")
FSIZE, NOFILE, AS = resource.RLIMIT_FSIZE, resource.RLIMIT_NOFILE, resource.RLIMIT_AS

# -- the cases ----------------------------------------------------------------------------------

CASES: dict[str, tuple[str, Callable[[Path], None]]] = {}


def case(category: str):
    def register(fn):
        CASES[fn.__name__] = (category, fn)
        return fn

    return register


@case("full disk")
def run_recording_on_a_full_disk(tmp):
    rrd, js = previous_outputs(tmp)
    r = quadobs(tmp, *RUN, "--duration", "60", "--out", rrd, "--summary", js,
                limits=[(FSIZE, 2 << 20)])  # fmt: skip
    promise(r, (1,), "cannot be written")
    assert rrd.read_bytes() == b"previous recording"
    assert json.loads(js.read_text()).get("failed") is True
    no_staging(tmp)


@case("full disk")
def replay_export_onto_a_log_on_a_full_disk(tmp):
    a, b = log_copy(tmp, "A"), log_copy(tmp, "B")
    (b / "beacons.csv").write_text((b / "beacons.csv").read_text().replace(",", ", "))
    before = snapshot(b)
    promise(replay(tmp, a, "--export", b, limits=[(FSIZE, 20_000)]), (1,), "previous folder")
    assert snapshot(b) == before


@case("full disk")
def run_export_log_on_a_full_disk(tmp):
    b = log_copy(tmp, "B")
    before = snapshot(b)
    r = quadobs(tmp, *RUN, "--duration", "2", "--export-log", b, "--summary", tmp / "r.json",
                limits=[(FSIZE, 40_000)])  # fmt: skip
    promise(r, (1,))
    assert snapshot(b) == before and "export_error" in json.loads((tmp / "r.json").read_text())


@case("full disk")
def campaign_folder_on_a_full_disk(tmp):
    out = tmp / "C"
    args = ("campaign", "ifac2021-noisy", "--runs", "2", "--duration", "0.5", "--workers", "0",
            "--no-progress", "--estimators", "augmented", "--out", out)  # fmt: skip
    promise(quadobs(tmp, *args), (0,))
    before = snapshot(out)
    promise(quadobs(tmp, *args[:-1], out, "--seed", "7", limits=[(FSIZE, 20_000)]), (1,))
    assert snapshot(out) == before


@case("full disk")
def plot_on_a_full_disk(tmp):
    promise(quadobs(tmp, *RUN, "--duration", "0.5", "--out", tmp / "r.rrd"), (0,))
    fig = tmp / "f.png"
    fig.write_bytes(b"previous figure")
    promise(quadobs(tmp, "plot", tmp / "r.rrd", "--out", fig, limits=[(FSIZE, 2000)]), (1,))
    assert fig.read_bytes() == b"previous figure"


def _damaged_log_file(name: str, make: Callable[[Path], None], *words: str):
    def check(tmp):
        log = log_copy(tmp)
        target = log / name
        target.unlink()
        make(target)
        promise(replay(tmp, log, limit=120), (2,), *words)

    return check


for _name, _file, _make, _words in [
    ("ranges_from_dev_zero", "ranges.csv", lambda p: p.symlink_to("/dev/zero"), ("ranges.csv",)),
    ("ranges_a_fifo", "ranges.csv", lambda p: os.mkfifo(p), ("ranges.csv",)),
    ("ranges_a_1gb_sparse_file", "ranges.csv", lambda p: os.truncate(p.open("wb").name, 1 << 30),
     ("ranges.csv",)),
    ("ranges_one_endless_line", "ranges.csv", lambda p: p.write_text("t," + "9" * (8 << 20)),
     ("ranges.csv",)),
    ("meta_not_utf8", "meta.csv", lambda p: p.write_bytes(b"key,value\nname,\xff\xfe\n"),
     ("meta.csv",)),
    ("meta_a_folder", "meta.csv", lambda p: p.mkdir(), ("meta.csv",)),
    ("truth_a_dangling_link", "truth.csv", lambda p: p.symlink_to(p.parent / "gone.csv"),
     ("truth.csv",)),
    ("truth_a_link_loop", "truth.csv", lambda p: p.symlink_to(p), ("truth.csv",)),
]:  # fmt: skip
    _case = _damaged_log_file(_file, _make, *_words)
    _case.__name__ = _name
    case("malformed log files")(_case)


def _edited_log_file(name: str, edit: Callable[[str], str], *words: str):
    def check(tmp):
        log = log_copy(tmp)
        (log / name).write_text(edit((log / name).read_text()))
        before = snapshot(log)
        promise(replay(tmp, log, limit=120), (2,), *words)
        assert snapshot(log) == before

    return check


def _cell(text: str, row: int, column: int, value: str) -> str:
    lines = text.splitlines()
    cells = lines[row].split(",")
    cells[column] = value
    lines[row] = ",".join(cells)
    return "\n".join(lines) + "\n"


def _ranges_column(text: str, name: str) -> int:
    return text.splitlines()[0].split(",").index(name)


for _name, _file, _edit, _words in [
    ("beacon_id_0_7", "ranges.csv", lambda t: _cell(t, 1, _ranges_column(t, "beacon"), "0.7"), ()),
    ("range_minus_5", "ranges.csv", lambda t: _cell(t, 1, _ranges_column(t, "range"), "-5"), ()),
    ("ids_1e19_2e19", "beacons.csv", lambda t: "id,x,y\n1e19,0,0\n2e19,1,1\n", ("1e19",)),
    ("ansi_in_the_name", "meta.csv", lambda t: t + "name,\x1b[31mred\x1b[0m\n", ("meta.csv",)),
    ("heading0_twice", "meta.csv", lambda t: t + "heading0,0\nheading0,1\n", ("heading0",)),
    ("misspelt_key", "meta.csv", lambda t: t + "headng0,0\n", ("headng0",)),
    ("a_bom_and_a_bad_row", "beacons.csv", lambda t: "\ufeff" + t + "x\n", ()),
]:  # fmt: skip
    _case = _edited_log_file(_file, _edit, *_words)
    _case.__name__ = _name
    case("malformed log files")(_case)


@case("malformed log files")
def a_bom_alone(tmp):
    log = log_copy(tmp)
    (log / "beacons.csv").write_text("\ufeff" + (log / "beacons.csv").read_text())
    r = replay(tmp, log, limit=120)
    promise(r, (0, 2))
    assert "\ufeff" not in r.err and "\\ufeff" not in r.err, r.err


@case("scenario and option values")
def scenario_from_dev_zero(tmp):
    (tmp / "z.toml").symlink_to("/dev/zero")
    promise(quadobs(tmp, "show", tmp / "z.toml"), (2,), "regular file")


@case("scenario and option values")
def scenario_a_fifo(tmp):
    os.mkfifo(tmp / "f.toml")
    promise(quadobs(tmp, "show", tmp / "f.toml"), (2,), "regular file")


@case("scenario and option values")
def scenario_5000_deep(tmp):
    (tmp / "d.toml").write_text("[" + ".".join(["a"] * 5000) + "]\nx = 1\n")
    promise(quadobs(tmp, "show", tmp / "d.toml"), (2,), "nested too deeply")


@case("scenario and option values")
def integer_of_5000_digits(tmp):
    (tmp / "b.toml").write_text(f"seed = {'9' * 5000}\n")
    promise(quadobs(tmp, "show", tmp / "b.toml"), (2,), "digits")
    promise(quadobs(tmp, "show", "ifac2021", "--set", f"seed={'9' * 5000}"), (2,), "digits")


@case("scenario and option values")
def set_path_of_60000_parts(tmp):
    r = quadobs(tmp, "show", "ifac2021", "--set", ".".join(["a"] * 60000) + "=1")
    promise(r, (2,), "parts")
    assert r.seconds < 10, r.seconds


@case("scenario and option values")
def replay_dt_nan_and_0(tmp):
    log = base_log()
    for value in ("nan", "0", "inf", "-1"):
        promise(replay(tmp, log, "--dt", value), (2,), "--dt")


@case("scenario and option values")
def replay_hostile_options(tmp):
    log = base_log()
    for args in (["--set", "noise=5"], ["--tune", "P0=1e300"], ["--biases", "nan,0,0,0"],
                 ["--initial-offset", "nan"]):  # fmt: skip
        promise(replay(tmp, log, *args), (2,))


@case("scenario and option values")
def run_dt_nan_and_0(tmp):
    for args in (["--set", "physics_rate=nan"], ["--set", "physics_rate=0"],
                 ["--set", "duration=inf"], ["--duration", "nan"]):  # fmt: skip
        promise(quadobs(tmp, *RUN, *args), (2,))


@case("colliding and read-only targets")
def out_and_summary_the_same_file(tmp):
    promise(quadobs(tmp, *RUN, "--duration", "0.2", "--out", "x", "--summary", "x"), (2,))
    assert not (tmp / "x").exists()


@case("colliding and read-only targets")
def export_log_and_out_collide(tmp):
    promise(quadobs(tmp, *RUN, "--duration", "0.2", "--export-log", tmp / "D",
                    "--out", tmp / "D" / "ranges.csv"), (2,))  # fmt: skip
    assert not (tmp / "D").exists()


@case("colliding and read-only targets")
def replay_summary_onto_the_logs_meta(tmp):
    log = log_copy(tmp)
    before = snapshot(log)
    for option in ("--summary", "--out"):
        promise(replay(tmp, log, option, log / "meta.csv"), (2,))
    assert snapshot(log) == before


@case("colliding and read-only targets")
def read_only_targets(tmp):
    rrd, js = previous_outputs(tmp)
    rrd.chmod(0o444)
    promise(quadobs(tmp, *RUN, "--duration", "0.2", "--out", rrd), (2,), "read-only")
    promise(quadobs(tmp, *RUN, "--duration", "0.2", "--out", "/dev/full"), (2,))
    assert rrd.read_bytes() == b"previous recording"


@case("colliding and read-only targets")
def export_onto_a_folder_of_other_files(tmp):
    other = tmp / "O"
    other.mkdir()
    (other / "thesis.tex").write_text("precious")
    promise(replay(tmp, base_log(), "--export", other), (2,))
    assert snapshot(other) == {"thesis.tex": b"precious"}


PLUGIN = """
import sys
import numpy as np
from quadobs.cli import main
from quadobs.estimators.base import Estimator
from quadobs.testbed import registry

KIND = sys.argv.pop(1)


class Hostile(Estimator):
    def __init__(self, x0):
        self._x, self.k = np.array(x0, dtype=float), 0

    def step(self, u, y):
        self.k += 1
        if KIND == "exit" and self.k == 5:
            sys.exit(0)
        if KIND == "nan" and self.k >= 10:
            self._x[:] = np.nan
        if KIND == "huge" and self.k >= 10:
            self._x[:] = 1e300

    @property
    def x_hat(self):
        return self._x.copy()

    @property
    def x_covariance(self):
        return np.eye(self._x.size)


def factory(scenario, x0, name):
    if KIND == "raise":
        raise RuntimeError("plugin bug")
    if KIND == "junk":
        return 42
    return Hostile(x0)


registry.register_estimator("hostile", factory)
sys.exit(main())
"""


def _plugin(kind: str, codes):
    def check(tmp):
        (tmp / "hostile_plugin.py").write_text(PLUGIN)
        js = tmp / "r.json"
        r = quadobs(tmp, kind, *RUN, "--duration", "0.3", "--estimators", "augmented,hostile",
                    "--summary", js, module="hostile_plugin",
                    env={"PYTHONPATH": os.pathsep.join([str(tmp), str(ROOT)])})  # fmt: skip
        promise(r, codes)
        if kind in ("nan", "huge"):  # asked for and diverged: flagged, and the status says so
            assert json.loads(js.read_text())["estimators"]["hostile"]["diverged"], r.err

    return check


for _kind, _codes in [("raise", (1,)), ("junk", (1, 2)), ("exit", (1,)), ("nan", (1,)),
                      ("huge", (1,))]:  # fmt: skip
    _case = _plugin(_kind, _codes)
    _case.__name__ = f"plugin_{_kind}"
    case("hostile plugins")(_case)


@case("signals")
def sigterm_mid_run(tmp):
    rrd, js = previous_outputs(tmp)
    r = quadobs(tmp, *RUN, "--duration", "600", "--out", rrd, "--summary", js,
                signal_after=(signal.SIGTERM, 5.0))  # fmt: skip
    promise(r, (130,))
    assert r.seconds < 7, f"the signal took {r.seconds - 5:.1f} s to end the run"
    replaced = rrd.read_bytes() != b"previous recording"
    assert replaced == (js.read_text() != '{"previous": true}')
    assert not replaced or json.loads(js.read_text())["interrupted"] == (r.code == 130)
    no_staging(tmp)


@case("signals")
def sigint_in_a_self_calibrating_replay(tmp):
    r = quadobs(tmp, "replay", base_log(), "--summary", tmp / "r.json",
                signal_after=(signal.SIGINT, 6.0))  # fmt: skip
    promise(r, (0, 130))
    assert r.code == 0 or "calibrated from the log" not in r.out


@case("low limits")
def few_file_descriptors(tmp):
    for n in (8, 12):
        r = quadobs(tmp, *RUN, "--duration", "0.2", "--out", tmp / "r.rrd", limits=[(NOFILE, n)])
        promise(r, (1,), "ulimit -n")


@case("low limits")
def little_address_space(tmp):
    for size in (600 << 20, 1200 << 20, 1800 << 20, 2200 << 20):
        r = quadobs(tmp, *RUN, "--duration", "0.2", "--out", tmp / "r.rrd", limits=[(AS, size)])
        promise(r, (0, 1) if size > 2 << 30 else (1,))
        assert r.code == 0 or "ulimit -v" in r.err, r.err


def _cache_copy(tmp: Path) -> dict[str, str]:
    """A ``NUMBA_CACHE_DIR`` holding a copy of this checkout's kernel cache (its index and data files)."""
    env = {"NUMBA_CACHE_DIR": str(tmp / "cache")}
    code = ("import json; from quadobs._kernels.cache import cache_folders; "
            "from quadobs._kernels.precompile import SIGNATURES; "
            "print(json.dumps([str(f) for f in cache_folders(SIGNATURES)]))")  # fmt: skip
    folders = {}
    for key, extra in (("package", {}), ("copy", env)):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT), **extra),
                             timeout=LIMIT, check=True)  # fmt: skip
        folders[key] = [Path(f) for f in json.loads(out.stdout)]
    for source, target in zip(folders["package"], folders["copy"], strict=True):
        target.mkdir(parents=True, exist_ok=True)
        for f in source.glob("*.nb[ic]"):
            shutil.copy2(f, target / f.name)
    return env


def _damaged_cache(damage: str):
    def check(tmp):
        env = _cache_copy(tmp)
        args = (*RUN, "--duration", "0.5", "--estimators", "augmented")
        clean = quadobs(tmp, *args, "--summary", tmp / "a.json", env=env)
        promise(clean, (0,))
        (data,) = (tmp / "cache").rglob("observer.range_outputs-*.1.nbc")
        if damage == "random bytes":
            with open(data, "r+b") as fh:
                fh.write(os.urandom(1000))
        elif damage == "empty index":
            next(data.parent.glob("observer.range_outputs-*.nbi")).write_bytes(b"")
        else:  # bytes inverted in the middle of the machine code: it still unpickles
            raw = bytearray(data.read_bytes())
            mid = len(raw) // 2
            raw[mid : mid + 64] = bytes(b ^ 0xFF for b in raw[mid : mid + 64])
            with open(data, "r+b") as fh:
                fh.write(raw)
        healed = quadobs(tmp, *args, "--summary", tmp / "b.json", env=env)
        promise(healed, (0,))
        notes = [ln for ln in healed.err.splitlines() if "kernel cache entry" in ln]
        assert len(notes) == 1 and "range_outputs" in notes[0], healed.err
        a, b = (json.loads((tmp / f).read_text()) for f in ("a.json", "b.json"))
        assert a["estimators"] == b["estimators"]  # same results

    return check


for _damage in ("random bytes", "empty index", "flipped middle"):
    _case = _damaged_cache(_damage)
    _case.__name__ = "kernel_cache_" + _damage.replace(" ", "_")
    case("corrupt kernel cache")(_case)


@case("campaign SIGKILL and --resume")
def campaign_killed_then_resumed(tmp):
    args = ["campaign", "ifac2021-noisy", "--runs", "5", "--duration", "0.5", "--workers", "0",
            "--no-progress", "--estimators", "augmented", "--out"]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-m", "quadobs.cli", *args, tmp / "C"], cwd=tmp,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    journal, deadline = tmp / ".C.runs", time.monotonic() + LIMIT
    while len(list(journal.glob("run-*.pickle"))) < 2 and proc.poll() is None:
        assert time.monotonic() < deadline, "the campaign kept no run"
        time.sleep(0.02)
    proc.kill()
    proc.wait()
    assert len(list(journal.glob("run-*.pickle"))) >= 2
    promise(quadobs(tmp, *args, tmp / "C", "--resume"), (0,))
    promise(quadobs(tmp, *args, tmp / "S"), (0,))
    assert not journal.exists()
    assert _figures(tmp / "C") == _figures(tmp / "S"), "the resumed campaign differs"


def _figures(folder: Path):
    """A campaign folder's summary (no wall-clock fields) and tables, as bits."""
    import numpy as np
    import pyarrow.parquet as pq

    summary = json.loads((folder / "summary.json").read_text())
    for key in ("wall_time", "run_wall_time_mean", "files"):
        summary.pop(key, None)
    tables = {}
    for name in ("runs.parquet", "series.parquet"):
        table = pq.read_table(folder / name)
        for column in table.column_names:
            if column != "wall_time":
                values = table[column].to_numpy(zero_copy_only=False)
                tables[name, column] = (
                    values.view(np.int64).tolist() if values.dtype.kind == "f" else values.tolist()
                )
    return summary, tables


# -- running them -------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_probe_case(name, tmp_path):
    CASES[name][1](tmp_path)


def main() -> int:
    """Run every case (or those named on the command line); print each and the counts per category."""
    names = sys.argv[1:] or list(CASES)
    counts: dict[str, list[int]] = {}
    for name in names:
        category, check = CASES[name]
        tmp = Path(tempfile.mkdtemp(prefix="quadobs-probe-"))
        start = time.monotonic()
        try:
            check(tmp)
            verdict = "kept"
        except AssertionError as exc:
            verdict = "BROKEN " + re.sub(r"\s+", " ", str(exc))[:300]
        except Exception as exc:  # the case itself could not be set up: say so, go on
            verdict = f"BROKEN (the case failed: {type(exc).__name__}: {exc})"[:300]
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        counts.setdefault(category, [0, 0])[verdict != "kept"] += 1
        print(f"{category:32s} {name:40s} {time.monotonic() - start:5.1f} s  {verdict}", flush=True)
    print()
    for category, (kept, broken) in counts.items():
        print(f"{category:32s} {kept} kept the promise, {broken} broke it")
    return 1 if any(broken for _, broken in counts.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
