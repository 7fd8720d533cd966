"""Logged data: the open log format, the Plaza loaders, the replay world, the replay and its peer."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog, read_log, write_log
from quadobs.testbed.logs.calibration import calibrate_biases
from quadobs.testbed.logs.estimators import REPLAY_ESTIMATORS, build_isam2
from quadobs.testbed.logs.replay import run_replay
from quadobs.testbed.worlds.replay import ReplayWorld, dead_reckoning

ROOT = Path(__file__).resolve().parents[2]

try:
    import gtsam  # noqa: F401

    HAVE_GTSAM = True
except ImportError:
    HAVE_GTSAM = False
needs_gtsam = pytest.mark.skipif(
    not HAVE_GTSAM, reason="gtsam is not installed (the data extra): no Plaza logs, no iSAM2 peer"
)

BEACONS = np.array([[-30.0, -20.0], [40.0, -25.0], [35.0, 30.0], [-25.0, 35.0]])


def synthetic_log(duration=120.0, bias=0.0, with_truth=True) -> RangeLog:
    """A vehicle on a circle of radius 15 m at 1.5 m/s: exact odometry at 10 Hz, exact ranges round-robin at 4 Hz."""
    R, v = 15.0, 1.5
    w = v / R
    t_in = np.arange(0.0, duration, 0.1)
    inputs = np.column_stack([t_in + 1000.0, np.full_like(t_in, v), np.full_like(t_in, w)])
    heading0 = math.pi / 2  # at angle 0 on the circle, moving counter-clockwise
    pos = lambda t: np.column_stack([R * np.cos(w * t), R * np.sin(w * t)])  # noqa: E731
    t_r = np.arange(0.05, duration - 0.1, 0.25)
    h = np.arange(t_r.size) % 4
    rho = np.linalg.norm(pos(t_r) - BEACONS[h], axis=1) + bias
    ranges = np.column_stack([t_r + 1000.0, np.array([0, 1, 5, 6])[h], rho])
    truth = None
    if with_truth:
        t_gt = np.arange(0.0, duration, 0.05)
        truth = np.column_stack([t_gt + 1000.0, pos(t_gt), heading0 + w * t_gt])
    return RangeLog("circle", np.array([0, 1, 5, 6]), BEACONS, ranges, inputs, heading0, truth)


# -- the open format ------------------------------------------------------------------


def test_a_log_folder_reads_back_exactly(tmp_path):
    log = synthetic_log(20.0)
    back = read_log(write_log(log, tmp_path / "log"))
    for key in ("beacon_ids", "beacons", "ranges", "inputs", "truth"):
        np.testing.assert_array_equal(getattr(back, key), getattr(log, key))
    assert back.heading0 == log.heading0 and back.name == "circle"
    (tmp_path / "log" / "truth.csv").unlink()  # the truth is optional
    assert read_log(tmp_path / "log").truth is None


@pytest.mark.parametrize(
    "fname, row, column, cell, expect",
    [
        (
            "ranges.csv",
            3,
            2,
            "abc",
            "ranges.csv, row 3, column range: 'abc' is not a finite number",
        ),
        ("ranges.csv", 5, 0, "nan", "ranges.csv, row 5, column time: 'nan' is not a finite number"),
        (
            "inputs.csv",
            4,
            1,
            "inf",
            "inputs.csv, row 4, column speed: 'inf' is not a finite number",
        ),
        ("beacons.csv", 2, 1, "", "beacons.csv, row 2, column x: '' is not a finite number"),
        ("ranges.csv", 7, 1, "3", "ranges.csv, row 7, column beacon: unknown beacon id 3"),
        (
            "ranges.csv",
            9,
            0,
            "0",
            "ranges.csv, row 9, column time: earlier than a row before it by",
        ),
        ("truth.csv", 2, 2, "x", "truth.csv, row 2, column y: 'x' is not a finite number"),
    ],
)
def test_a_malformed_log_names_the_file_row_and_column(tmp_path, fname, row, column, cell, expect):
    folder = write_log(synthetic_log(20.0), tmp_path / "log")
    lines = (folder / fname).read_text().splitlines()
    cells = lines[row - 1].split(",")
    cells[column] = cell
    lines[row - 1] = ",".join(cells)
    (folder / fname).write_text("\n".join(lines) + "\n")
    with pytest.raises(QuadobsError) as err:
        read_log(folder)
    assert expect in str(err.value) and "\n" not in str(err.value)


def test_bad_headers_short_rows_and_missing_files_are_named(tmp_path):
    folder = write_log(synthetic_log(20.0), tmp_path / "log")
    (folder / "inputs.csv").write_text("time,speed\n0,1\n")
    with pytest.raises(
        QuadobsError, match=r"inputs.csv, row 1: header 'time,speed'; expected time,speed,yaw_rate"
    ):
        read_log(folder)
    write_log(synthetic_log(20.0), folder)
    text = (folder / "ranges.csv").read_text().splitlines()
    text[3] = "1000.5,0"
    (folder / "ranges.csv").write_text("\n".join(text))
    with pytest.raises(QuadobsError, match=r"ranges.csv, row 4: 2 columns, expected 3"):
        read_log(folder)
    write_log(synthetic_log(20.0), folder)
    (folder / "meta.csv").unlink()
    with pytest.raises(QuadobsError, match=r"meta.csv: missing"):
        read_log(folder)


def test_the_cli_replays_a_log_folder(tmp_path, capsys):
    folder = write_log(synthetic_log(30.0, bias=1.0), tmp_path / "log")
    code = main(
        [
            "replay",
            str(folder),
            "--summary",
            str(tmp_path / "s.json"),
            "--estimators",
            "augmented,ekf",
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "augmented" in out and "ekf" in out and "us/range" in out
    s = json.loads((tmp_path / "s.json").read_text())
    assert (
        set(s["estimators"]) == {"augmented", "ekf"}
        and len(s["biases"]) == 4
        and s["ranges"]["placed"] > 100
    )
    for key in (
        "rmse",
        "max_error",
        "final_position_error",
        "time_to_5m",
        "time_to_2m",
        "seconds_per_measurement",
    ):
        assert key in s["estimators"]["augmented"]
    assert main(["replay", str(folder), "--biases", "1,2", "--no-progress"]) == 2
    assert "--biases: 2 values for 4 beacons" in capsys.readouterr().err
    assert (
        main(
            [
                "replay",
                str(folder),
                "--estimators",
                "nosuch",
                "--no-progress",
                "--calibrate",
                "none",
            ]
        )
        == 2
    )
    assert "unknown estimator 'nosuch'" in capsys.readouterr().err


def test_the_cli_reports_a_malformed_log_in_one_line_with_status_2(tmp_path, capsys):
    folder = write_log(synthetic_log(20.0), tmp_path / "log")
    (folder / "beacons.csv").write_text("id,x,y\n0,1,2\n1,zz,3\n")
    assert main(["replay", str(folder), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.count("\n") == 0
        and err.startswith("quadobs: error: ")
        and "beacons.csv, row 3, column x" in err
    )


# -- the replay world -----------------------------------------------------------------


def test_the_world_holds_the_odometry_and_places_ranges_in_their_step():
    log = synthetic_log(30.0)
    world = ReplayWorld(log, 0.1, "odometry", 64)
    c = world.columns
    rows = world._rows
    # integrating the held inputs reproduces the dead reckoning at every grid time
    P, theta = dead_reckoning(log, world.times)
    u = rows[:-1, c.u]
    np.testing.assert_allclose(
        P[0] + np.vstack([[0, 0], np.cumsum(u[:, :2] * 0.1, axis=0)]), P, atol=1e-9
    )
    np.testing.assert_allclose(np.cumsum(u[:, 2]) * 0.1, theta[1:] - theta[0], atol=1e-12)
    # exact odometry on the circle: the dead reckoning follows the truth (mid-step heading)
    assert np.max(np.linalg.norm(P + rows[0, c.truth] - rows[:, c.truth], axis=1)) < 0.01
    # every range lands in the step that holds its time, as y_h = rho^2/2 - |a_h|^2/2
    k = np.floor((log.ranges[:, 0] - log.start) / 0.1 + 1e-9).astype(int)
    h = log.beacon_index(log.ranges[:, 1])
    inside = k < world.steps
    np.testing.assert_allclose(rows[k[inside], c.measured.start + h[inside]], log.ranges[inside, 2])
    y = rows[k[inside], c.y.start + h[inside]]
    np.testing.assert_allclose(
        y, 0.5 * log.ranges[inside, 2] ** 2 - 0.5 * np.sum(BEACONS[h[inside]] ** 2, axis=1)
    )
    assert world.placed == inside.sum() and world.merged == 0
    assert (
        np.isnan(rows[:, c.y]).sum() == world.steps * 4 - world.placed + 4
    )  # the rest missing (and the final row)


def test_two_ranges_to_one_beacon_in_one_step_keep_the_first():
    log = synthetic_log(10.0)
    dup = log.ranges.copy()
    dup = np.insert(dup, 3, dup[2] + [0.01, 0.0, 5.0], axis=0)
    world = ReplayWorld(
        RangeLog("dup", log.beacon_ids, log.beacons, dup, log.inputs, log.heading0, log.truth), 0.1
    )
    assert world.merged == 1
    k = int(np.floor((dup[2, 0] - log.start) / 0.1 + 1e-9))
    assert world._rows[k, world.columns.measured][log.beacon_index(dup[2:3, 1])[0]] == dup[2, 2]


# -- replays of a synthetic log -------------------------------------------------------


def test_the_augmented_observer_converges_from_50m_on_exact_data():
    s = run_replay(
        synthetic_log(120.0),
        estimators=["augmented", "ekf"],
        initial_offset=50.0,
        batch=False,
        setup_options={"range_sigma": 0.05, "q_xy": 1e-3},
    )
    aug = s["estimators"]["augmented"]
    # the ranges are read up to dt early: |v| dt = 0.15 m at most
    assert (
        aug["final_position_error"] < 0.15
        and aug["time_to_2m"] is not None
        and aug["time_to_2m"] < 60.0
    )
    assert s["ranges"]["placed"] == s["estimators"]["augmented"]["corrections"]
    assert s["estimators"]["ekf"]["seconds_per_measurement"] > 0


def test_the_cv_model_replays_too():
    s = run_replay(
        synthetic_log(120.0),
        estimators=["augmented", "ekf"],
        model="cv",
        initial_offset=10.0,
        batch=False,
        setup_options={"range_sigma": 0.05, "q_acc": 0.05},
    )
    assert s["estimators"]["augmented"]["final_position_error"] < 0.5


def test_a_replay_is_deterministic_and_writes_its_outputs(tmp_path):
    log = synthetic_log(40.0)
    a = run_replay(
        log, initial_offset=20.0, seed=3, out=tmp_path / "r.rrd", summary_path=tmp_path / "s.json"
    )
    b = run_replay(log, initial_offset=20.0, seed=3)
    for s in (a, b):
        s.pop("wall_time")
        s.pop("recording")
        for e in s["estimators"].values():
            e.pop("seconds_per_measurement")
    assert a == b and (tmp_path / "r.rrd").stat().st_size > 0
    assert json.loads((tmp_path / "s.json").read_text())["log"] == "circle"
    from quadobs.recording import list_entities

    assert "errors/augmented/position/norm" in {
        e.lstrip("/") for e in list_entities(tmp_path / "r.rrd")
    }


def test_a_replay_records_the_layout_of_an_episode(tmp_path):
    from quadobs.recording import list_entities, read_series
    from quadobs.studies.plot._source import open_source
    from quadobs.studies.plot.run import default_panels

    log = synthetic_log(30.0)
    s = run_replay(
        log, estimators=["augmented", "ekf"], initial_offset=20.0, out=tmp_path / "r.rrd"
    )
    entities = {e.lstrip("/") for e in list_entities(tmp_path / "r.rrd")}
    for e in (
        "world/truth/path",
        "world/estimates/ekf/path",
        "errors/augmented/position/norm",
        "errors/ekf/position/axes",
        "observer/augmented/nis",
        "observer/ekf/covariance_trace",
        "measurements/range/6",  # by the log's ids (0, 1, 5, 6), not their indices
        "measurements/odometry",
    ):
        assert e in entities
    assert "measurements/range/3" not in entities
    assert not any("velocity" in e for e in entities)  # the odometry model has no velocity
    err = read_series(tmp_path / "r.rrd", "errors/augmented/position/norm")
    assert err["step"][-1] == s["steps"] and err["values"][-1, 0] == pytest.approx(
        s["estimators"]["augmented"]["final_position_error"]
    )
    assert err["values"][0, 0] == pytest.approx(20.0)  # the initial offset, at step 0
    truth = read_series(tmp_path / "r.rrd", "world/truth/path")["values"]
    np.testing.assert_allclose(truth[0, :2], log.truth[0, 1:3])  # the log's truth, on the grid
    for anchor in (0, 5):
        rng = read_series(tmp_path / "r.rrd", f"measurements/range/{anchor}")
        np.testing.assert_array_equal(
            np.sort(rng["values"][:, 0]), np.sort(log.ranges[log.ranges[:, 1] == anchor, 2])
        )
    assert default_panels(open_source(tmp_path / "r.rrd")) == [
        "paths",
        "position",
        "covariance",
        "nis",
        "ranges",
    ]


def _noisy(log, seed, *settings, **kw):
    return run_replay(
        log,
        estimators=["augmented", "ekf"],
        initial_offset=5.0,
        seed=seed,
        batch=False,
        settings=settings,
        **kw,
    )


def test_the_sensor_layer_adds_nothing_by_default_and_drops_ranges_as_configured(tmp_path):
    log = synthetic_log(120.0)
    clean = _noisy(log, 3)
    assert clean["measurements"] == {"range_period_steps": 1, "dropped": 0, "outliers_injected": 0}
    assert clean["estimators"]["augmented"]["corrections"] == clean["ranges"]["placed"]
    a = _noisy(
        log, 3, "noise.dropout=0.3", "noise.outlier_probability=0.05", "noise.outlier_std=20"
    )
    b = _noisy(
        log, 3, "noise.dropout=0.3", "noise.outlier_probability=0.05", "noise.outlier_std=20"
    )
    c = _noisy(
        log, 4, "noise.dropout=0.3", "noise.outlier_probability=0.05", "noise.outlier_std=20"
    )
    for s in (a, b, c):
        s.pop("wall_time")
        for e in s["estimators"].values():
            e.pop("seconds_per_measurement")
    assert (
        a == b and a["measurements"] != c["measurements"]
    )  # seeded: the same draws, another seed others
    placed, m = a["ranges"]["placed"], a["measurements"]
    # binomial counts within 4 standard deviations
    assert abs(m["dropped"] - 0.3 * placed) < 4 * math.sqrt(placed * 0.3 * 0.7)
    kept = placed - m["dropped"]
    assert (
        abs(m["outliers_injected"] - 0.05 * kept) < 4 * math.sqrt(kept * 0.05) + 1
        and m["outliers_injected"] > 0
    )
    for name in ("augmented", "ekf"):  # every range left is corrected with, none dropped is
        assert a["estimators"][name]["corrections"] == kept
    assert (
        a["estimators"]["ekf"]["rmse"] > clean["estimators"]["ekf"]["rmse"]
    )  # 20 m outliers, no gate


def test_the_sensor_layer_adds_its_noise_and_reads_at_its_rate(tmp_path):
    from quadobs.recording import read_series

    log = synthetic_log(120.0)
    s = _noisy(log, 1, "noise.range_std=0.5", out=tmp_path / "n.rrd")
    r = read_series(tmp_path / "n.rrd", "measurements/range/1")
    exact = dict(
        zip(
            np.floor((log.ranges[:, 0] - log.start) / 0.1 + 1e-9).astype(int)[
                log.ranges[:, 1] == 1
            ],
            log.ranges[log.ranges[:, 1] == 1, 2],
        )
    )
    noise = r["values"][:, 0] - np.array([exact[k] for k in r["step"]])
    assert (
        abs(np.std(noise) - 0.5) < 0.1
        and abs(np.mean(noise)) < 0.15
        and s["measurements"]["dropped"] == 0
    )
    slow = _noisy(log, 1, "noise.range_rate=2")  # one grid step in 5 is read
    k = np.floor((log.ranges[:, 0] - log.start) / 0.1 + 1e-9).astype(int)
    assert slow["measurements"]["range_period_steps"] == 5
    assert slow["estimators"]["augmented"]["corrections"] == int(
        np.sum((k % 5 == 0) & (k < slow["steps"]))
    )


def test_replay_settings_are_noise_settings_only(tmp_path, capsys):
    folder = write_log(synthetic_log(20.0), tmp_path / "log")
    for setting, message in (
        ("duration=3", "--set: duration: does not apply to a replay"),
        ("noise.accel_std=1", "noise.accel_std: does not apply"),
        ("noise.dropout=2", "noise.dropout: must be at most 1.0"),
    ):
        assert (
            main(["replay", str(folder), "--no-progress", "--calibrate", "none", "--set", setting])
            == 2
        )
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err


def test_without_truth_there_are_no_errors_but_a_replay():
    s = run_replay(synthetic_log(30.0, with_truth=False), batch=False)
    assert s["has_truth"] is False and s["estimators"]["augmented"]["rmse"] is None
    assert s["initial_guess"] == pytest.approx(list(BEACONS.mean(axis=0)))


def test_the_bias_calibration_recovers_a_common_bias_without_the_truth():
    biased = synthetic_log(240.0, bias=2.5)
    blind = RangeLog(
        "blind",
        biased.beacon_ids,
        biased.beacons,
        biased.ranges,
        biased.inputs,
        biased.heading0,
        None,
    )
    opts = {"range_sigma": 0.1, "q_xy": 1e-2}
    b = calibrate_biases(blind, setup_options=opts)
    # the common bias is recovered; per beacon it trades against the position (within 0.5 m here)
    assert abs(np.mean(b) - 2.5) < 0.15 and np.all(np.abs(b - 2.5) < 0.5)
    np.testing.assert_array_equal(
        b, calibrate_biases(biased, setup_options=opts)
    )  # the truth is not read


def _drifting(log: RangeLog, yaw_bias: float) -> RangeLog:
    """``log`` with a yaw-rate bias in its odometry: a heading that drifts, as Plaza2's."""
    inputs = log.inputs.copy()
    inputs[:, 2] += yaw_bias
    return RangeLog(
        f"{log.name}-drift",
        log.beacon_ids,
        log.beacons,
        log.ranges,
        inputs,
        log.heading0,
        log.truth,
    )


def _noisy_ranges(log: RangeLog, sigma: float, seed: int) -> RangeLog:
    ranges = log.ranges.copy()
    ranges[:, 2] += sigma * np.random.default_rng(seed).standard_normal(len(ranges))
    return RangeLog(
        log.name, log.beacon_ids, log.beacons, ranges, log.inputs, log.heading0, log.truth
    )


def test_the_noise_calibration_trusts_good_odometry_and_not_a_drifting_one():
    from quadobs.testbed.logs.calibration import EXTEND, NOISE_FACTORS, calibrate_noise

    tried = range(len(NOISE_FACTORS), len(NOISE_FACTORS) + EXTEND + 1)  # the grid, and past it
    good, drift = _good_and_drifting()
    q_good, s_good, _ = calibrate_noise(good, np.zeros(4))
    q_drift, s_drift, _ = calibrate_noise(drift, np.zeros(4))
    assert len(s_good) in tried and q_good <= 1.0 / 16 and q_drift >= 4.0
    # the truth is not read; what the calibration picks is what the truth prefers
    blind = RangeLog(
        "blind", drift.beacon_ids, drift.beacons, drift.ranges, drift.inputs, drift.heading0, None
    )
    assert calibrate_noise(blind, np.zeros(4))[:2] == (q_drift, s_drift)
    rmse = {
        q: run_replay(
            drift, estimators=["ekf"], initial_offset=2.0, batch=False, setup_options={"q_xy": q}
        )["estimators"]["ekf"]["rmse"]
        for q in (q_good, q_drift)
    }
    assert rmse[q_drift] < 0.5 * rmse[q_good]


def _good_and_drifting() -> tuple[RangeLog, RangeLog]:
    """Circle laps with 0.3 m range noise, and the same with a yaw-rate bias of 0.01 rad/s in
    the odometry (0.6 degrees per second: 140 degrees of heading error after 240 s)."""
    good = _noisy_ranges(synthetic_log(240.0), 0.3, 1)
    return good, _drifting(good, 0.01)


def test_the_self_calibration_fits_the_noise_of_a_drifting_odometry_and_its_own_range_noise():
    from quadobs.testbed.logs.calibration import EXTEND, NOISE_FACTORS, self_calibrate
    from quadobs.testbed.logs.estimators import odometry_noise
    from quadobs.testbed.logs.range_noise import stated_range_noise

    tried = range(len(NOISE_FACTORS), len(NOISE_FACTORS) + EXTEND + 1)  # the grid, and past it
    drift = _good_and_drifting()[1]
    b, options, scores = self_calibrate(
        drift
    )  # biases, then the noise with them, then the biases again
    own = {"range_sigma": stated_range_noise(drift)}  # the ranges' own noise (log_defaults)
    assert own["range_sigma"] == pytest.approx(0.3, rel=0.15)
    assert (
        set(options) == {"q_xy", "q_xy_heading", "q_theta", *own}  # the heading filters' own too
        and options["q_xy"] >= 4.0
        and len(scores) in tried
        and b.shape == (4,)
    )
    heading = {"q_xy_heading": odometry_noise(drift) / 64}  # an eighth of the speed (log_defaults)
    assert self_calibrate(drift, setup_options={"q_xy": 0.5}, noise=False)[1:] == (
        {"q_xy": 0.5, **own, **heading},
        {},
    )


def test_the_replay_estimators_are_declared_as_entry_points():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"][
        "quadobs.replay_estimators"
    ]
    assert set(declared) == set(REPLAY_ESTIMATORS)
    for name, value in declared.items():
        assert value.split(":")[1] == REPLAY_ESTIMATORS[name].__name__
    assert (
        "gtsam>=4.3"
        in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"][
            "data"
        ]
    )


def test_the_peer_refuses_a_simulated_scenario():
    from quadobs.testbed.scenario import load_scenario

    with pytest.raises(QuadobsError, match="logged data only"):
        build_isam2(load_scenario("beacons2d"), np.zeros(4), "isam2")


def test_the_estimators_noise_is_tuned_on_the_command_line(tmp_path, capsys):
    folder = write_log(synthetic_log(30.0, bias=1.0), tmp_path / "log")
    args = [
        "replay",
        str(folder),
        "--no-progress",
        "--summary",
        str(tmp_path / "s.json"),
        "--tune",
        "q_xy=0.5",
        "--tune",
        "range_sigma=0.2",
        "--tune",
        "gate=none",
    ]
    assert main(args) == 0
    s = json.loads((tmp_path / "s.json").read_text())
    assert (
        s["noise"]["q_xy"] == 0.5
        and s["noise"]["range_sigma"] == 0.2
        and s["noise"]["gate"] is None
    )
    np.testing.assert_array_equal(
        s["biases"],
        calibrate_biases(read_log(folder), setup_options={"q_xy": 0.5, "range_sigma": 0.2}),
    )
    for bad, message in (
        ("q_xy=abc", "--tune q_xy: expected a number, got 'abc'"),
        ("sigma=1", "--tune: expected KEY=VALUE"),
        ("P0=-1", "P0: expected a positive finite number"),
    ):
        assert main(["replay", str(folder), "--no-progress", "--tune", bad]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err


# -- accelerometer logs and simulated runs written as logs ----------------------------


def imu_circle_log(duration=60.0, rate=100.0) -> RangeLog:
    """The circle of :func:`synthetic_log` read by an accelerometer at ``rate`` Hz (the centripetal acceleration), with truth velocities."""
    R, w = 15.0, 0.1
    t = np.arange(0.0, duration, 1.0 / rate)
    acc = (
        -R * w**2 * np.column_stack([np.cos(w * t), np.sin(w * t)])
    )  # exact at each sample time, held
    t_r = np.arange(0.05, duration - 0.1, 0.25)
    h = np.arange(t_r.size) % 4
    p = lambda t: R * np.column_stack([np.cos(w * t), np.sin(w * t)])  # noqa: E731
    ranges = np.column_stack(
        [t_r, np.array([0, 1, 5, 6])[h], np.linalg.norm(p(t_r) - BEACONS[h], axis=1)]
    )
    truth = np.column_stack([t, p(t), R * w * np.column_stack([-np.sin(w * t), np.cos(w * t)])])
    return RangeLog(
        "imu-circle",
        np.array([0, 1, 5, 6]),
        BEACONS,
        ranges,
        np.column_stack([t, acc]),
        math.nan,
        truth,
        input_kind="imu",
        truth_columns=("time", "x", "y", "vx", "vy"),
    )


def test_an_accelerometer_log_reads_back_and_is_held_as_its_mean_over_each_step(tmp_path):
    log = imu_circle_log(20.0)
    back = read_log(write_log(log, tmp_path / "imu"))
    assert (
        back.input_kind == "imu"
        and back.truth_columns == log.truth_columns
        and math.isnan(back.heading0)
    )
    np.testing.assert_array_equal(back.inputs, log.inputs)
    assert (tmp_path / "imu" / "inputs.csv").read_text().startswith("time,ax,ay\n")
    world = ReplayWorld(
        back, 0.1, "imu"
    )  # 100 Hz samples, a 10 Hz grid: the mean of 10 samples per step
    u = world._rows[: world.steps, world.columns.u]
    np.testing.assert_allclose(u[5], log.inputs[50:60, 1:].mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(
        world._rows[7, world.columns.truth], log.truth[70, 1:], atol=1e-12
    )  # truth velocity read
    s = run_replay(
        back,
        estimators=["augmented", "ekf"],
        initial_offset=10.0,
        setup_options={"range_sigma": 0.05, "q_imu": 1e-4},
    )
    assert s["model"] == "imu" and s["estimators"]["augmented"]["final_position_error"] < 0.2
    assert s["estimators"]["augmented"]["final_velocity_error"] < 0.05


def test_accelerometer_logs_check_their_dimensions_and_models(tmp_path, capsys):
    folder = write_log(imu_circle_log(5.0), tmp_path / "imu")
    text = (folder / "inputs.csv").read_text().splitlines()
    (folder / "inputs.csv").write_text(
        "\n".join(["time,ax,ay,az"] + [r + ",0.0" for r in text[1:]]) + "\n"
    )
    with pytest.raises(
        QuadobsError, match=r"inputs.csv, row 1: 3 acceleration columns for 2-D beacons"
    ):
        read_log(folder)
    folder = write_log(imu_circle_log(5.0), tmp_path / "imu")
    for args, message in (
        (["--model", "odometry"], "model odometry: the log 'imu-circle' lacks wheel odometry"),
        (["--set", "noise.airspeed_std=1"], "noise.airspeed_std: does not apply"),
    ):
        assert main(["replay", str(folder), "--no-progress", "--calibrate", "none", *args]) == 2
        assert message in capsys.readouterr().err
    odometry = write_log(synthetic_log(5.0), tmp_path / "odo")
    assert (
        main(["replay", str(odometry), "--no-progress", "--calibrate", "none", "--model", "imu"])
        == 2
    )
    assert "model imu: the log 'circle' lacks an accelerometer" in capsys.readouterr().err


@needs_gtsam
def test_the_peer_replays_an_accelerometer_log():
    s = run_replay(
        imu_circle_log(20.0),
        estimators=["augmented", "isam2"],
        initial_offset=10.0,
        setup_options={"range_sigma": 0.05, "q_imu": 1e-4},
    )
    e = s["estimators"]["isam2"]
    assert e["final_position_error"] < 0.2 and e["batch_rmse"] < e["rmse"]


def test_the_accelerometer_noise_of_the_sensor_layer_applies_to_an_accelerometer_log(tmp_path):
    log = imu_circle_log(20.0)
    world = ReplayWorld(log, 0.1, "imu")
    from quadobs.testbed.logs.replay import log_scenario
    from quadobs.testbed.sensors import SensorModel

    noisy = ReplayWorld(
        log, 0.1, "imu", sensors=SensorModel(log_scenario(log, 0.1, 2, ["noise.accel_std=0.3"]))
    )
    count = noisy.begin_block(0, world.steps)
    noisy.fill(count)
    diff = noisy.out[:count, noisy.columns.u] - world._rows[:count, world.columns.u]
    assert abs(np.std(diff) - 0.3) < 0.03 and abs(np.mean(diff)) < 0.03
    np.testing.assert_array_equal(
        noisy.out[:count, noisy.columns.y], world._rows[:count, world.columns.y]
    )  # ranges untouched


@pytest.fixture(scope="module")
def exported_episode(tmp_path_factory):
    """ifac2021-noisy (30 s at 1 kHz, 0.5 m ranges at 100 Hz, one beacon in space) run and written as a log."""
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.logs.export import LogExportSink
    from quadobs.testbed.scenario import load_scenario

    folder = tmp_path_factory.mktemp("exported") / "noisy"
    sc = load_scenario("ifac2021-noisy")
    ep = run_episode(
        sc, estimators=["augmented", "ekf"], sinks=[LogExportSink(folder)], collect_every=1000
    )
    return sc, ep, read_log(folder)


def test_a_simulated_run_written_as_a_log_holds_what_the_estimators_were_given(exported_episode):
    sc, ep, log = exported_episode
    assert ep.summary["exported_log"] and log.dimension == 3 and log.input_kind == "imu"
    assert (
        log.inputs.shape == (sc.steps + 1, 4)
        and log.ranges.shape == (3000, 3)
        and log.truth.shape == (sc.steps + 1, 7)
    )
    assert np.all(np.diff(log.ranges[:, 0]) >= 0) and log.ranges[1, 0] == pytest.approx(
        0.01
    )  # 100 Hz
    np.testing.assert_allclose(log.truth[-1, 0], sc.duration)


def test_replaying_an_exported_episode_gives_the_episodes_estimates(exported_episode):
    from quadobs.testbed.episode import run_loop
    from quadobs.testbed.registry import build_estimators

    sc, ep, log = exported_episode
    x0 = ep.trace["estimates"]["ekf"][0]  # the episode's initial guess
    world = ReplayWorld(log, sc.dt, "imu")
    summary, _ = run_loop(
        lambda merged, *rest: merged,
        frame=world.frame(),
        world=world,
        estimators=build_estimators(sc, ["augmented", "ekf"], x0),
    )
    for name in (
        "augmented",
        "ekf",
    ):  # the scenario's own estimators on the log: the episode to rounding
        for key in ("final_position_error", "final_velocity_error"):
            assert summary["estimators"][name][key] == pytest.approx(
                ep.summary["estimators"][name][key], abs=1e-6
            )
    # the replay's own model of an accelerometer log (the double integrator, its default noise, the
    # sensor's 0.5 m), from the same guess: within 5 cm of the episode's observer (0.455 against 0.414 m)
    r = run_replay(log, dt=sc.dt, x0=x0, setup_options={"range_sigma": 0.5}, batch=False)
    final = r["estimators"]["augmented"]["final_position_error"]
    assert (
        r["model"] == "imu"
        and abs(final - ep.summary["estimators"]["augmented"]["final_position_error"]) < 0.05
    )
    assert (
        r["estimators"]["ekf"]["final_position_error"] < 1.0
    )  # the EKF of the replay converges too (the episode's does not)


def test_the_cli_writes_a_run_as_a_log_and_refuses_what_the_format_cannot_hold(tmp_path, capsys):
    assert (
        main(
            [
                "run",
                "beacons2d",
                "--duration",
                "2",
                "--no-progress",
                "--export-log",
                str(tmp_path / "log"),
            ]
        )
        == 0
    )
    assert "quadobs replay" in capsys.readouterr().out
    log = read_log(tmp_path / "log")
    assert log.dimension == 2 and log.inputs.shape == (2001, 3) and log.beacons.shape == (3, 2)
    assert (
        main(
            [
                "replay",
                str(tmp_path / "log"),
                "--dt",
                "0.001",
                "--calibrate",
                "none",
                "--no-progress",
            ]
        )
        == 0
    )
    assert (
        main(
            ["run", "wind", "--duration", "1", "--no-progress", "--export-log", str(tmp_path / "w")]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "--export-log: 'wind' is a wind scenario" in err and not (tmp_path / "w").exists()


# -- the Plaza logs (gtsam) -----------------------------------------------------------


@needs_gtsam
def test_the_plaza_loaders_handle_the_dataset_conventions():
    import scipy.io

    from quadobs.testbed.logs import load_builtin
    from quadobs.testbed.logs.plaza import plaza_file

    expect = {"plaza1": (3529, 1933.4), "plaza2": (1816, 409.5)}
    for name, (count, duration) in expect.items():
        log = load_builtin(name)
        assert log.ranges.shape[0] == count and log.end - log.start == pytest.approx(
            duration, abs=0.1
        )
        assert set(log.beacon_ids.tolist()) == {0, 1, 5, 6}
        assert np.all(np.diff(log.ranges[:, 0]) >= 0)  # Plaza1's TD is not in time order: sorted
        # the truth's heading agrees with the odometry's at the start (Plaza2's offset by pi removed)
        assert abs(math.remainder(log.truth[0, 3] - log.heading0, 2 * math.pi)) < 1e-6
    # mid-step integration reproduces the dataset's own dead reckoning of Plaza2
    m = scipy.io.loadmat(plaza_file("plaza2"))
    log = load_builtin("plaza2")
    P, _ = dead_reckoning(log, m["DRp"][1:, 0], origin=m["DRp"][0, 1:3])
    assert np.max(np.linalg.norm(P - m["DRp"][1:, 1:3], axis=1)) < 0.07


@needs_gtsam
def test_export_writes_the_open_format(tmp_path, capsys):
    assert main(["replay", "plaza2", "--export", str(tmp_path / "p2")]) == 0
    log = read_log(tmp_path / "p2")
    assert log.ranges.shape == (1816, 3) and log.truth.shape[1] == 4


# Regression on short excerpts (measured with the default pipeline of quadobs replay: the
# biases and the process noise self-calibrated on the excerpt, never from its truth;
# initial guess 50 m off, seed 0): the bounds are the measured values plus 25 %.
# name: (excerpt s, augmented RMSE, augmented final error, iSAM2 online RMSE), measured
# Plaza2's excerpt: the calibration keeps q_xy at its prior there (q_xy = 4 predicts the held-out
# ranges no better: 2.151 against 2.154 m), whose final error is 3.17 m (1.38 m at the setting
# the previous score picked)
EXCERPTS = {"plaza1": ((0.0, 300.0), 5.02, 3.74, 5.01), "plaza2": ((0.0, 150.0), 3.10, 3.17, 6.71)}


@needs_gtsam
@pytest.mark.parametrize("name", sorted(EXCERPTS))
def test_regression_on_a_plaza_excerpt(name):
    from quadobs.testbed.logs import load_builtin
    from quadobs.testbed.logs.calibration import self_calibrate

    span, aug_rmse, aug_final, isam_rmse = EXCERPTS[name]
    log = load_builtin(name).excerpt(*span)
    biases, options, _ = self_calibrate(log)
    s = run_replay(
        log,
        estimators=["augmented", "ekf", "isam2"],
        initial_offset=50.0,
        seed=0,
        biases=biases,
        setup_options=options,
    )
    e = s["estimators"]
    assert e["augmented"]["max_error"] >= 49.9  # it starts 50 m off
    assert (
        e["augmented"]["rmse"] < 1.25 * aug_rmse
        and e["augmented"]["final_position_error"] < 1.25 * aug_final
    )
    assert e["isam2"]["rmse"] < 1.25 * isam_rmse
    assert e["augmented"]["rmse"] <= 1.2 * e["isam2"]["rmse"]  # the issue's target, on the excerpt
    assert (
        e["isam2"]["batch_rmse"] <= e["isam2"]["smoothed_rmse"] * 1.05
    )  # the offline optimum is no worse
    assert e["augmented"]["corrections"] == s["ranges"]["placed"] == e["isam2"]["corrections"]
