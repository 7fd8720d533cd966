"""Hostile input to ``run``, ``show`` and ``replay``: one line and status 2 (bad input) or 1 (a fault)."""

import sys
import time
from pathlib import Path

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.estimators.base import Estimator
from quadobs.testbed import registry
from quadobs.testbed.logs import estimators as replay_estimators


@pytest.fixture(scope="module")
def log_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("logs") / "L"
    assert (
        main(["run", "ifac2021", "--duration", "0.3", "--no-progress", "--export-log", str(folder)])
        == 0
    )
    return folder


def _one_line(capsys, code, expected_code, *words):
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("quadobs: error:")]
    assert code == expected_code, err
    assert len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], err
    return lines[0]


@pytest.mark.parametrize(
    ("content", "word"),
    [(b"key,value\nname,\xff\xfe\n", "not UTF-8 text"), (None, "not a regular file")],
)
def test_a_meta_file_that_cannot_be_read_is_named(log_folder, tmp_path, capsys, content, word):
    import shutil

    folder = tmp_path / "M"
    shutil.copytree(log_folder, folder)
    (folder / "meta.csv").unlink()
    if content is None:
        (folder / "meta.csv").mkdir()
    else:
        (folder / "meta.csv").write_bytes(content)
    code = main(["replay", str(folder), "--calibrate", "none", "--dt", "0.001"])
    _one_line(capsys, code, 2, "meta.csv", word)


@pytest.mark.parametrize(
    ("options", "word"),
    [
        (["--dt", "nan"], "--dt"),
        (["--dt", "0"], "--dt"),
        (["--dt", "1e-9"], "--dt"),
        (["--set", "noise=5"], "--set: noise:"),
        (["--set", "trajectory.x=1"], "--set: trajectory.x:"),
        (["--tune", "P0=1e300"], "--tune P0"),
        (["--tune", "q_xy=inf"], "--tune q_xy"),
        (["--biases", "nan"], "--biases"),
        (["--initial-offset", "inf"], "--initial-offset"),
        (["--tune", "bias_prior=log"], "--tune bias_prior=log"),  # no calibration to ask
        (["--tune", "bias_prior=-1"], "bias_prior"),
        (["--biases", "0,0,0", "--tune", "bias_prior=log"], "which --biases turns off"),
    ],
)
def test_replay_refuses_bad_numbers_and_settings_by_their_option(log_folder, capsys, options, word):
    code = main(["replay", str(log_folder), "--calibrate", "none", *options])
    _one_line(capsys, code, 2, word)


def test_a_replay_grid_coarser_than_the_excitation_window_runs(log_folder, capsys):
    """``--dt 0.07`` (5 s is no multiple of it) once failed naming ``excitation.window``."""
    code = main(["replay", str(log_folder), "--calibrate", "none", "--dt", "0.07", "--no-progress"])
    assert code == 0, capsys.readouterr().err


def test_a_long_path_is_shown_with_its_file_name(tmp_path, capsys):
    from quadobs.errors import abbreviated

    deep = tmp_path.joinpath(*["a-long-folder-name"] * 6)
    deep.mkdir(parents=True)
    bad = deep / "broken.toml"
    bad.write_text("[[[\n")
    _one_line(capsys, main(["show", str(bad)]), 2, "broken.toml", "invalid TOML")
    shown = abbreviated(str(bad))
    assert len(shown) == 80 and "..." in shown and shown.endswith("/broken.toml")
    assert abbreviated("short.toml") == "short.toml"


def test_huge_integers_and_deep_tables_are_refused_in_one_line(tmp_path, capsys):
    digits = "9" * 5000
    _one_line(
        capsys, main(["show", "ifac2021", "--set", f"seed={digits}"]), 2, "--set seed", "digits"
    )
    big = tmp_path / "big.toml"
    big.write_text(f"seed = {digits}\n")
    _one_line(capsys, main(["show", str(big)]), 2, "big.toml", "digits")
    deep = tmp_path / "deep.toml"
    deep.write_text("[" + ".".join(["a"] * 5000) + "]\nx = 1\n")
    _one_line(capsys, main(["show", str(deep)]), 2, "deep.toml", "nested too deeply")


def test_a_set_path_of_many_parts_is_refused_at_once(capsys):
    t0 = time.perf_counter()
    code = main(["show", "ifac2021", "--set", ".".join(["a"] * 60000) + "=1"])
    assert time.perf_counter() - t0 < 2.0
    _one_line(capsys, code, 2, "--set", "parts")


class _Exiting(Estimator):
    def __init__(self, x0):
        self._x, self.k = np.array(x0, dtype=float), 0

    def step(self, u, y):
        self.k += 1
        if self.k == 5:
            sys.exit(0)

    @property
    def x_hat(self):
        return self._x.copy()

    @property
    def x_covariance(self):
        return np.eye(self._x.size)


def _raising(*args):
    raise RuntimeError("plugin bug\nsecond line")


@pytest.fixture
def plugins(monkeypatch):
    registry.register_estimator("raising", _raising)
    registry.register_estimator("exiting", lambda sc, x0, nm: _Exiting(x0))
    monkeypatch.setitem(replay_estimators.REPLAY_ESTIMATORS, "raising", _raising)
    monkeypatch.setitem(replay_estimators.REPLAY_ESTIMATORS, "uncallable", 42)
    yield
    for name in ("raising", "exiting"):
        registry._RUNTIME.pop(name, None)
    registry.refresh()


def test_a_plugin_factory_that_raises_is_a_fault_in_one_line(plugins, log_folder, tmp_path, capsys):
    code = main(
        ["run", "ifac2021", "--duration", "0.1", "--estimators", "raising", "--no-progress"]
    )
    _one_line(capsys, code, 1, "'raising'", "RuntimeError: plugin bug")
    code = main(["replay", str(log_folder), "--calibrate", "none", "--estimators", "raising"])
    _one_line(capsys, code, 1, "'raising'", "RuntimeError: plugin bug")
    code = main(["replay", str(log_folder), "--calibrate", "none", "--estimators", "uncallable"])
    _one_line(capsys, code, 2, "'uncallable'", "not callable")


def test_a_plugin_calling_sys_exit_mid_run_is_reported(plugins, tmp_path, capsys):
    out, js = tmp_path / "r.rrd", tmp_path / "r.json"
    code = main(
        ["run", "ifac2021", "--duration", "0.1", "--estimators", "augmented,exiting", "--no-progress",
         "--out", str(out), "--summary", str(js)]
    )  # fmt: skip
    _one_line(capsys, code, 1, "SystemExit(0)")
    assert not js.exists()


@pytest.mark.parametrize(
    ("fname", "content", "words"),
    [
        (
            "beacons.csv",
            "id,x,y\n1e19,0,0\n2e19,1,1\n",
            ("beacons.csv", "1e19", "not an integer id"),
        ),
        ("meta.csv", "key,value\nname,\x1b[31mred\x1b[0m\n", ("meta.csv", "control character")),
    ],
)
def test_huge_ids_and_escape_sequences_in_a_log_are_refused(
    log_folder, tmp_path, capsys, fname, content, words
):
    import shutil

    folder = tmp_path / "L"
    shutil.copytree(log_folder, folder)
    (folder / fname).write_text(content)
    code = main(["replay", str(folder), "--calibrate", "none"])
    line = _one_line(capsys, code, 2, *words)
    assert "\x1b" not in line


@pytest.mark.parametrize(
    ("fname", "columns", "word", "scale"),
    [
        ("ranges.csv", ("range", "std"), "ranges.csv, column range: the median range is", 1000.0),
        ("beacons.csv", ("x", "y"), "beacons.csv: the anchors ranged to span", 1000.0),
        ("ranges.csv", ("range", "std"), "ranges.csv, column range: the ranges' own noise", 100.0),
        ("ranges.csv", ("range", "std"), "within 1 s sum to a median", 0.1),
        ("ranges.csv", ("range", "std"), "the truth lies a median", 10.0),
    ],
)
def test_replay_refuses_ranges_and_anchors_in_different_units(
    tmp_path, capsys, fname, columns, word, scale
):
    """Ranges in mm against anchors in m, or the other way, or ranges in cm (their noise beyond
    half the anchors' extent), or ranges a tenth or ten times the anchors' scale (their pairs
    breaking the triangle inequality): one line before any calibration."""
    import csv

    folder = tmp_path / "R"
    assert (
        main(["run", "rover-room", "--duration", "1", "--no-progress", "--export-log", str(folder)])
        == 0
    )
    capsys.readouterr()
    assert main(["replay", str(folder), "--calibrate", "none", "--estimators", "ekf"]) == 0
    capsys.readouterr()
    rows = list(csv.reader((folder / fname).open()))
    index = [rows[0].index(c) for c in columns]
    for row in rows[1:]:
        for i in index:
            row[i] = repr(scale * float(row[i]))
    with (folder / fname).open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    code = main(["replay", str(folder)])
    _one_line(capsys, code, 2, word, "must both be in metres")
