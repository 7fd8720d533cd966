"""The replay's defaults on a wheeled robot in a small room: ``rover-room`` exported and replayed.

For each seed, ``quadobs run rover-room --export-log DIR`` (the simulated robot: a figure eight
in a 3.0 x 2.4 m room, four anchors, per-anchor range biases of mean +0.11 m, outliers,
dropouts, wheel odometry with a scale error and a yaw-rate bias) and ``quadobs replay DIR
--burn-in 5`` with every other setting at its default (self-calibration, 50 m initial offset,
the default estimators). Each log is replayed twice: as exported (each range with the radio's
stated ``std``) and with the ``std`` column left out, as a log converted by hand holds it (the
replay's ``range_sigma`` then applies).

Beside them, the reference: what a short script does that is *given* what the replay must find
out, the true per-anchor biases, the simulation's true noise and the true start (no initial
offset): the range noise ``std`` of the radio, and for the heading filters the odometry's white
noise as intensities ``q_xy_heading = speed_std^2 / rate`` and ``q_theta = yaw_rate_std^2 / rate`` (a
sample held over ``1 / rate``); the EKF of the odometry model (no heading state) with the
default ``q_xy``, as its heading drift is no white noise. Every figure is the position RMSE (m)
after the 5 s burn-in.

    python sims/replay_rover_room.py [--seeds 0,1,2] [--duration 90]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from quadobs import load_scenario
from quadobs.testbed.episode import run_episode
from quadobs.testbed.logs import read_log
from quadobs.testbed.logs.export import LogExportSink
from quadobs.testbed.logs.replay import run_replay
from quadobs.testbed.uwb import radio_of

BURN_IN = 5.0
REFERENCE = ("ekf-heading", "ukf-heading", "ekf")


def export(seed: int, duration: float, folder: Path):
    """The seed's ``rover-room`` run written as a log in ``folder``; the scenario."""
    scenario = load_scenario("rover-room", seed=seed, duration=duration)
    run_episode(scenario, estimators=["ekf"], sinks=[LogExportSink(folder)])
    return scenario


def without_std(folder: Path, into: Path) -> Path:
    """A copy of the log ``folder`` whose ``ranges.csv`` has no ``std`` column."""
    shutil.copytree(folder, into)
    with open(folder / "ranges.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    with open(into / "ranges.csv", "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["time", "beacon", "range"])
        out.writerows((r["time"], r["beacon"], r["range"]) for r in rows)
    return into


def replay_defaults(folder: Path) -> dict:
    """``quadobs replay FOLDER --burn-in 5``, every other setting its default: RMSE by estimator."""
    summary = folder.parent / f"{folder.name}-summary.json"
    cmd = [sys.executable, "-m", "quadobs", "replay", str(folder), "--burn-in", str(BURN_IN)]
    done = subprocess.run(
        [*cmd, "--summary", str(summary)], capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise SystemExit(f"quadobs replay failed: {done.stderr.strip().splitlines()[-1]}")
    estimators = json.loads(summary.read_text())["estimators"]
    return {name: figures["rmse"] for name, figures in estimators.items()}


def reference(folder: Path, scenario) -> dict:
    """The estimators of :data:`REFERENCE` given the true biases and the true noise (module docstring)."""
    log = read_log(folder)
    odo, radio = scenario.odometry, scenario.radio
    truth = radio_of(scenario).biases
    options = {
        "range_sigma": radio.std,
        "q_xy_heading": odo.speed_std**2 / odo.rate,
        "q_theta": odo.yaw_rate_std**2 / odo.rate,
    }
    out = {}
    for name in REFERENCE:
        opts = options if name.endswith("-heading") else {"range_sigma": radio.std}
        summary = run_replay(
            log, estimators=[name], biases=truth, setup_options=opts, burn_in=BURN_IN,
            batch=False, initial_offset=0.0,
        )  # fmt: skip
        out[f"{name} (truth)"] = summary["estimators"][name]["rmse"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--duration", type=float, default=90.0)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="rover-room-") as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            folder = Path(tmp) / f"seed{seed}"
            scenario = export(seed, args.duration, folder)
            bare = without_std(folder, Path(tmp) / f"seed{seed}-nostd")
            ref = reference(folder, scenario)
            for label, log in (("std", folder), ("no std", bare)):
                row = {"seed": seed, "log": label, **replay_defaults(log), **ref}
                rows.append(row)
                print(", ".join(f"{k} {_fmt(v)}" for k, v in row.items()), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    columns = [k for k in rows[0] if k not in ("seed", "log")]
    print("| seed | log | " + " | ".join(columns) + " |")
    print("|---|---|" + "---|" * len(columns))
    for r in rows:
        print(f"| {r['seed']} | {r['log']} | " + " | ".join(_fmt(r[c]) for c in columns) + " |")
    print(f"(position RMSE after {BURN_IN:g} s, m)")


def _fmt(value) -> str:
    return f"{value:.3f}" if isinstance(value, float) and math.isfinite(value) else str(value)


if __name__ == "__main__":
    main()
