"""A quadrotor flight exported as a log, made into what a real flight log holds, replayed with the defaults.

A real UWB flight log differs from ``quadobs run quadrotor-uwb-realistic --export-log DIR`` in
what it lacks: often no attitude (the body IMU alone), no stated IMU noise, a motion-capture
frame whose axes are not the vehicle's initial heading, and IMU biases larger than a
calibrated unit's. This script exports the scenario (one run per seed, its accelerometer's and
gyroscope's biases drawn with ``--accel-bias`` and ``--gyro-bias`` per axis) and writes these
variants of each log:

* ``full``: the export as it is (body IMU, AHRS attitude, stated noise, truth with attitude);
* ``noatt``: no ``attitude.csv``, no ``accel_noise`` / ``gyro_noise`` (nor the IMU's bias and
  attitude figures) in ``meta.csv``, the truth's attitude columns removed (so nothing can read
  them);
* ``yaw``: ``noatt`` with the navigation frame turned by ``--yaw`` radians about the vertical
  (anchors, true positions and velocities rotated; the body IMU unchanged): the vehicle
  starts with a heading the log does not state.

Each variant is replayed with the command's defaults (``quadobs replay DIR --burn-in 5``,
in-process through :func:`quadobs.cli.main`), and the table gives every estimator's position
RMSE after the burn-in and its ``diverged`` flag.

    python sims/replay_flight_variants.py --seeds 0,1,2 --duration 40 --out flights/
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
from pathlib import Path

import numpy as np

from quadobs import cli
from quadobs.testbed.logs import read_log, write_log
from quadobs.testbed.logs.schema import IMU_FIGURES

VARIANTS = ("full", "noatt", "yaw")


def export(seed: int, duration: float, accel_bias: float, gyro_bias: float, folder: Path) -> None:
    """Fly ``quadrotor-uwb-realistic`` with ``seed`` and write its log to ``folder``."""
    argv = ["run", "quadrotor-uwb-realistic", "--seed", str(seed), "--estimators", "ekf"]
    argv += ["--duration", f"{duration:g}", "--no-progress", "--export-log", str(folder)]
    argv += ["--set", f"quadrotor.accel_bias={accel_bias:g}"]
    argv += ["--set", f"quadrotor.gyro_bias={gyro_bias:g}"]
    code = cli.main(argv)
    if code != 0:
        raise SystemExit(f"export of seed {seed} failed ({code})")


def variant(log, kind: str, yaw: float):
    """``log`` as the variant ``kind`` (module docstring)."""
    if kind == "full":
        return log
    keep = [i for i, c in enumerate(log.truth_columns) if c not in ("qw", "qx", "qy", "qz")]
    truth = log.truth[:, keep].copy()
    columns = tuple(log.truth_columns[i] for i in keep)
    beacons = log.beacons.copy()
    if kind == "yaw":
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s], [s, c]])
        beacons[:, :2] = beacons[:, :2] @ rot.T
        for x, y in (("x", "y"), ("vx", "vy")):
            i, j = columns.index(x), columns.index(y)
            truth[:, [i, j]] = truth[:, [i, j]] @ rot.T
    return dataclasses.replace(
        log,
        beacons=beacons,
        truth=truth,
        truth_columns=columns,
        attitude=None,
        accel_noise=math.nan,
        gyro_noise=math.nan,
        **dict.fromkeys(IMU_FIGURES, math.nan),
        source="",
        name=f"{log.name}-{kind}",
    )


def replay(folder: Path, estimators: str | None, burn_in: float) -> dict:
    """``quadobs replay FOLDER --burn-in B`` (defaults otherwise); its summary."""
    summary = folder.parent / f"{folder.name}.json"
    argv = ["replay", str(folder), "--burn-in", f"{burn_in:g}", "--summary", str(summary)]
    argv += ["--no-progress"] + (["--estimators", estimators] if estimators else [])
    code = cli.main(argv)
    if code not in (0, 1):
        raise SystemExit(f"replay of {folder} failed ({code})")
    return json.loads(summary.read_text())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--accel-bias", type=float, default=0.2, help="m/s^2 per axis (std)")
    ap.add_argument("--gyro-bias", type=float, default=0.01, help="rad/s per axis (std)")
    ap.add_argument("--yaw", type=float, default=1.0, help="rad, the variant yaw's frame turn")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--estimators", default=None, help="default: the replay's default set")
    ap.add_argument("--burn-in", type=float, default=5.0)
    ap.add_argument("--out", help="folder for the logs and summaries (default: a temporary one)")
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="flights-"))
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        base = out / f"seed{seed}"
        if not (base / "meta.csv").exists():
            export(seed, args.duration, args.accel_bias, args.gyro_bias, base)
        log = read_log(base)
        for kind in args.variants.split(","):
            folder = out / f"seed{seed}-{kind}"
            if kind != "full":
                write_log(variant(log, kind, args.yaw), folder)
            s = replay(base if kind == "full" else folder, args.estimators, args.burn_in)
            for name, e in s["estimators"].items():
                rows.append((seed, kind, name, e.get("rmse"), e.get("diverged")))
    print(f"position RMSE after {args.burn_in:g} s (m), logs in {out}")
    for seed, kind, name, rmse, diverged in rows:
        flag = "" if diverged is None else f"  DIVERGED {diverged}"
        text = "-" if rmse is None else f"{rmse:.4f}"
        print(f"seed {seed}  {kind:6s} {name:18s} {text}{flag}")


if __name__ == "__main__":
    main()
