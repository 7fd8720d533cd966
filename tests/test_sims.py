"""The scripts in ``sims/`` run: each in a subprocess with short options, outputs under a tmp folder."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SIMS = ROOT / "sims"

#: script -> (arguments, outputs it must write, text its output must hold); {tmp} is the tmp folder
CASES = {
    "localise_vehicle.py": (
        ["--duration", "1", "--out", "{tmp}/runs/localise.rrd"],
        ["runs/localise.rrd"],
        "ifac2021: final position error",
    ),
    "excitation_degenerate.py": (
        ["--duration", "8", "--every", "2", "--out", "{tmp}/runs/degenerate.rrd"],
        ["runs/degenerate.rrd"],
        "low segments (s): [[5.0,",
    ),
    "excitation_overhead.py": (
        ["--duration", "1", "--repeats", "1"],
        [],
        "throughput ratio on/off:",
    ),
    "long_run.py": (
        [
            "--duration",
            "2",
            "--settle",
            "0.5",
            "--window",
            "0.5",
            "--json",
            "{tmp}/runs/long_run.json",
        ],
        ["runs/long_run.json"],
        "NaN: False",
    ),
    "replay_quadrotor_log.py": (
        ["--duration", "7", "--estimators", "ekf", "--range-rate", "20", "--imu-rate", "200"],
        [],
        "replayed RMSE",
    ),
    "uwb_realistic.py": (
        "--seeds 0:1 --duration 7 --estimators ekf --given --line-of-sight --jacobian-at-truth".split(),
        [],
        '"ekf-bias-truejac": {"time_to_1m"',
    ),
    "uwb_online_bound.py": (
        "--seeds 0:1 --duration 7 --burn-in 3".split(),
        [],
        "bound ratio (imu-oracle): median",
    ),
    "uwb_bias_bound.py": (
        "--seeds 0:1 --duration 7 --burn-in 3 --key-period 0.05 --line-of-sight".split(),
        [],
        '"ratio_ekf_at_batch-los"',
    ),
    "tuned_baselines.py": (
        ["--duration", "1", "--runs", "2", "--workers", "0", "--out", "{tmp}/campaign"],
        ["campaign/summary.json", "campaign/runs.parquet", "campaign/statistics.rrd"],
        "ekf_tuned",
    ),
    "replay_exported_quadrotor.py": (
        ["--duration", "8", "--burn-in", "3", "--out", "{tmp}/log"],
        ["log/imu.csv", "log/attitude.csv"],
        "own tuning",
    ),
    "replay_exported_tdoa.py": (
        ["--duration", "8", "--burn-in", "3", "--no-isam2", "--out", "{tmp}/tdoa-log"],
        ["tdoa-log/tdoa.csv"],
        "live / replayed (ratio)",
    ),
    "cross_validate_replay.py": (
        [
            "--sources",
            "quad",
            "--quad-duration",
            "8",
            "--initial-offset",
            "2",
            "--json",
            "{tmp}/cv.json",
        ],
        ["cv.json"],
        "evaluated on | prior | from quad",
    ),
    "replay_rover_room.py": (
        ["--seeds", "0", "--duration", "8", "--json", "{tmp}/rover.json"],
        ["rover.json"],
        "| seed | log |",
    ),
    "stress_hidden_logs.py": (
        ["rover", "--seeds", "0", "--variants", "pattern,tagpattern", "--duration", "8"]
        + ["--json", "{tmp}/stress.json", "--without-std", "--tune", "anchor_sigma=1"]
        + ["--keep", "{tmp}/logs"],
        ["stress.json", "logs/rover-today-seed0-pattern/meta.csv"],
        "| stress | seed 0 | worst | target met |",
    ),
    "bias_start_study.py": (
        ["flight:0:none", "--duration", "8", "--out", "{tmp}/study"],
        ["study/rows.json"],
        "| log | estimator | choice |",
    ),
    "pillar_bounds.py": (
        ["--seeds", "0", "--duration", "8"],
        [],
        "| seed | rule | no excess | sight known |",
    ),
    "replay_flight_variants.py": (
        ["--seeds", "0", "--duration", "8", "--variants", "noatt", "--estimators", "ekf-bias-imu"]
        + ["--out", "{tmp}/flights"],
        ["flights/seed0/imu.csv", "flights/seed0-noatt/imu.csv"],
        "seed 0  noatt  ekf-bias-imu",
    ),
    "imu_noise_rule.py": (
        ["--duration", "8", "--burn-in", "3", "--estimators", "tdoa-handover", "--seeds", "0"]
        + ["--q", "live"],
        [],
        "tdoa-handover  mean ratio to live: live",
    ),
    "tdoa_seeds.py": (
        ["--seeds", "0", "--duration", "7", "--settle", "3", "--estimators", "tdoa-handover"]
        + ["--jsonl", "{tmp}/seeds.jsonl"],
        ["seeds.jsonl"],
        "tdoa-handover | 1/1",
    ),
    "flight_error_budget.py": (
        ["--real-seeds", "0", "--bias-seeds", "", "--duration", "8", "--stress", "survey"]
        + ["--oracles", "survey-varying,all", "--out", "{tmp}/budget", "--offset-scan"],
        ["budget/seed0-real-all-survey/ranges.csv"],
        "line of sight, truncated: least cost at offset",
    ),
}


#: script -> why it has no short run here, and where it is tested instead
NOT_SHORT = {
    "screenshots.py": "needs chromium and about 30 s a world: tests/test_screenshots.py (slow)",
    "check_excess.py": "needs an exported flight log and a minute of self-calibration: its check"
    " is tested in tests/testbed/test_excess_model.py",
    "excess_fit_oracle.py": "needs a 40 s exported flight and a minute of self-calibration per"
    " flight: its fits are tested in tests/testbed/test_excess_model.py",
    "bias_filter_options.py": "runs another script (the flight's stress or variants: minutes)"
    " with the filters' sight model changed",
    "trace_flight_bias_states.py": "simulates and replays a 40 s flight twice (minutes): a trace"
    " for docs/error-sources.md, its stress logs tested through stress_hidden_logs.py",
}


def test_every_script_has_a_smoke_test():
    assert sorted(p.name for p in SIMS.glob("*.py")) == sorted([*CASES, *NOT_SHORT])
    assert not set(CASES) & set(NOT_SHORT)


#: studies whose short run takes more than the default run's share (about 20 s): marked slow.
#: ``replay_rover_room.py``'s export and posing of the robot run in the short run of
#: ``stress_hidden_logs.py``; the flight's and the quadrotor's replay scripts stay.
SLOW = {
    "uwb_bias_bound.py",
    "pillar_bounds.py",
    "bias_start_study.py",
    "flight_error_budget.py",
    "cross_validate_replay.py",
    "replay_rover_room.py",
}


@pytest.mark.parametrize(
    "script",
    [pytest.param(s, marks=pytest.mark.slow) if s in SLOW else s for s in sorted(CASES)],
)
def test_script_runs_short(script, tmp_path):
    args, outputs, text = CASES[script]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, str(SIMS / script), *(a.format(tmp=tmp_path) for a in args)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert text in done.stdout, done.stdout[-3000:]
    for out in outputs:
        path = tmp_path / out
        assert path.is_file() and path.stat().st_size > 0, out
    if script == "long_run.py":
        figures = json.loads((tmp_path / "runs/long_run.json").read_text())
        assert set(figures) == {"testbed", "direct"}
        assert not figures["testbed"]["nan"] and not figures["direct"]["nan"]
    assert not (tmp_path / "runs").exists() or all(
        p.name in {Path(o).name for o in outputs} for p in (tmp_path / "runs").iterdir()
    )


def test_every_script_answers_bad_input_on_one_line():
    for path in SIMS.glob("*.py"):
        assert path.read_text().rstrip().endswith("run_script(main, Path(__file__).name)"), (
            path.name
        )


def test_a_scripts_bad_scenario_setting_is_one_line_and_status_2(tmp_path):
    done = subprocess.run(
        [sys.executable, str(SIMS / "uwb_realistic.py"), "--seeds", "0:1", "--duration", "4"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        cwd=tmp_path,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "uwb_realistic.py: error: quadrotor.landing: take-off and landing must fit in the duration 4.0 s"
    ]


@pytest.mark.parametrize(
    ("option", "said"),
    [
        ("--tune=anchor_sigma=2", "anchor_sigma: expected 0"),
        ("--estimators=ekf,nope", "unknown nope"),
        ("--given-biases", "--given-biases: the flight's logs only"),
        ("--pattern=-1", "--pattern: expected a positive number"),
        ("--pattern-fit", "--pattern-fit: the flight's logs only"),
        ("--level=nan", "--level: expected a finite number"),
    ],
)
def test_the_stress_script_refuses_bad_replay_options_before_any_log(tmp_path, option, said):
    done = subprocess.run(
        [sys.executable, str(SIMS / "stress_hidden_logs.py"), "rover", "--seeds", "0", option],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        cwd=tmp_path,
        timeout=120,
    )
    assert done.returncode == 2 and said in done.stderr.strip().splitlines()[-1]
    assert "seed 0" not in done.stdout  # no log simulated, none replayed


def test_bias_filter_options_sets_the_gate_and_runs_the_command_line():
    """``--line-of-sight`` reaches every one-sided gate built afterwards (checked in a child, so
    this process keeps the default); ``quadobs`` runs the command line; a bad value is refused."""
    code = (
        "import runpy, sys; from unittest.mock import patch\n"
        "from quadobs.estimators.robust import SkewedGate\n"
        "seen = []\n"
        "def cli_main(argv): seen.append((SkewedGate().line_of_sight, argv)); return 0\n"
        "sys.argv = ['bias_filter_options.py', '--line-of-sight', '0.99', 'quadobs', '--version']\n"
        "with patch('quadobs.cli.main', cli_main):\n"
        f"    try: runpy.run_path({str(SIMS / 'bias_filter_options.py')!r}, run_name='__main__')\n"
        "    except SystemExit as e: print(e.code, seen)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=SIMS
    )
    assert out.stdout.strip() == "0 [(0.99, ['--version'])]", out.stderr
    bad = subprocess.run(
        [sys.executable, str(SIMS / "bias_filter_options.py"), "--line-of-sight", "1.5", "quadobs"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and bad.stderr.strip(), bad.stderr
    assert "line_of_sight" in bad.stderr.strip().splitlines()[-1]


def test_the_stress_scripts_given_biases_are_each_anchors_median_against_the_truth(
    tmp_path, monkeypatch
):
    """``truth_biases``: each anchor's median of its ranges less the true distance, outliers
    of a minority left out by the median, ranges of 0 m and those outside the truth's span
    not counted."""
    monkeypatch.syspath_prepend(str(SIMS))
    import numpy as np
    import stress_hidden_logs

    from quadobs.testbed.logs import write_log
    from quadobs.testbed.logs.format import RangeLog

    anchors = np.array([[-3, -3, 0.2], [3, -3, 0.2], [3, 3, 2.8], [-3, 3, 2.8]], dtype=float)
    t = np.linspace(0.0, 20.0, 2001)
    p = np.column_stack([np.cos(0.3 * t), np.sin(0.3 * t), 1.0 + 0.2 * np.sin(t)])
    k = np.arange(1, 2000, 3)
    h = np.arange(k.size) % 4
    bias = np.array([0.12, -0.3, 0.05, 0.4])
    r = np.linalg.norm(p[k] - anchors[h], axis=1) + bias[h]
    r[::7] += 2.0  # a minority of each anchor's ranges far too long
    r[::11] = 0.0  # failed exchanges
    outside = ((t[k] < 1.0) & (h == 0)) | ((t[k] > 8.0) & (h == 1))
    r[outside] += 5.0  # before the truth starts or after it ends (most of anchor 1's): not counted
    truth_rows = (t >= 1.0) & (t <= 8.0)
    log = RangeLog(
        "given", np.arange(4), anchors, np.column_stack([t[k], h, r]),
        np.column_stack([t, np.zeros((t.size, 3))]), np.nan,
        np.column_stack([t, p])[truth_rows], input_kind="imu", truth_columns=("time", "x", "y", "z"),
    )  # fmt: skip
    folder = write_log(log, tmp_path / "given")
    np.testing.assert_allclose(stress_hidden_logs.truth_biases(folder), bias, atol=1e-9)


def test_the_stress_scripts_pattern_spread_is_the_radios_term_and_its_linear_fit(
    tmp_path, monkeypatch
):
    """``pattern_spread``: each anchor's ``u^T S u`` over the truth's rows, as the scenario's
    radio gives it for the seed, and what a constant and a linear term in ``u`` leave of it
    (never more than its spread; over the anchors, far less on a flight's narrow cones of
    directions)."""
    monkeypatch.syspath_prepend(str(SIMS))
    import numpy as np
    import stress_hidden_logs

    from quadobs import load_scenario
    from quadobs.testbed.logs import write_log
    from quadobs.testbed.logs.format import RangeLog
    from quadobs.testbed.uwb import radio_of

    settings = ("radio.pattern=0.1",)
    radio = radio_of(load_scenario("quadrotor-uwb-realistic", seed=4).with_settings(settings))
    t = np.linspace(0.0, 20.0, 401)
    p = np.column_stack([1.5 * np.cos(0.3 * t), np.sin(0.3 * t), 1.0 + 0.3 * np.sin(t)])
    log = RangeLog(
        "flight", np.arange(radio.m), radio.anchors, np.column_stack([t, np.arange(t.size) % radio.m, 3 + 0 * t]),
        np.column_stack([t, np.zeros((t.size, 3))]), np.nan, np.column_stack([t, p]),
        input_kind="imu", truth_columns=("time", "x", "y", "z"),
    )  # fmt: skip
    folder = write_log(log, tmp_path / "flight")
    spread, left = stress_hidden_logs.pattern_spread(folder, 4, settings)
    direct = np.array([[radio.pattern_bias(i, q) for i in range(radio.m)] for q in p])
    np.testing.assert_allclose(spread, direct.std(axis=0), rtol=1e-9)
    assert np.all(left <= spread)
    assert np.sqrt(np.mean(left**2)) < 0.25 * np.sqrt(np.mean(spread**2))


def test_the_stress_scripts_mix_is_its_transforms_in_turn_each_from_its_own_draw(monkeypatch):
    """``mix``: the transforms one after the other, the ``k``-th from ``seed + k``, so that
    two of them never share a draw (a log stressed twice from one seed would tie the errors
    of a survey to those of a pattern)."""
    monkeypatch.syspath_prepend(str(SIMS))
    import stress_hidden_logs

    seen = []

    def step(name):
        return lambda log, seed: seen.append((name, seed)) or log + [name]

    mixed = stress_hidden_logs._mixed(step("survey"), step("pattern"), step("clock"))
    assert mixed([], 7000) == ["survey", "pattern", "clock"]
    assert seen == [("survey", 7000), ("pattern", 7001), ("clock", 7002)]
    for table in (stress_hidden_logs.ROVER, stress_hidden_logs.FLIGHT):
        settings, _ = table["mix"]
        assert f"radio.pattern={stress_hidden_logs.MIX_PATTERN_STD}" in settings
    assert "mix" in stress_hidden_logs.WITH_ATTITUDE  # its tag pattern takes the attitude
