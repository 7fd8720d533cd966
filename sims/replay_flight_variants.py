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

and, each of them ``noatt`` with one thing a real flight log has (``real``: all of them), made
from the exported files by cheap transforms (their draws seeded by the log's seed and the
variant):

* ``vib``: motor vibration, white noise of ``--accel-vibration`` m/s^2 and ``--gyro-vibration``
  rad/s per sample added to the accelerometer and the gyroscope (at the export's 1 kHz);
* ``vib100``: ``vib`` at 100 Hz, each sample the mean of ten (a flight controller low-passes
  its IMU before it logs it at a lower rate: the per-sample noise falls by ``sqrt(10)``);
* ``alias100``: ``vib`` decimated to 100 Hz without a filter (every tenth sample, its
  per-sample noise kept: ten times the noise intensity of ``vib``);
* ``uneven``: the IMU's intervals uneven (each time moved by up to 0.3 of an interval) and
  :data:`GAPS` gaps of 50 ms (the samples in them removed);
* ``clock``: the IMU stamped 20 ms late against the ranges' clock (its times +0.02 s), and
  every time on a Unix clock (+1.7e9 s);
* ``frd``: the body axes forward-right-down (y and z of the accelerometer and the gyroscope
  negated: ``az = -g`` at rest);
* ``bias``: range biases of both signs (uniform in +-0.3 m, anchor 0 at -0.3 m) and more
  non-line-of-sight (a tenth of the ranges longer by an exponential excess of mean 0.3 m);
* ``truth100``: the truth as a motion capture gives it: positions only (no velocity), at 100
  Hz, from 2 s after the IMU's first sample;
* ``nostd``: no ``std`` column in ``ranges.csv`` (a hand-converted log states none);
* ``real``: every one of the above at once (``vib100`` for the rate);
* ``real-STEP`` (not in the default set): ``real`` without the one transform ``STEP`` (one of
  :data:`REAL_STEPS`), every other drawn as in ``real``: what ``STEP`` costs in ``real``.

Each variant is replayed with the command's defaults (``quadobs replay DIR --burn-in 5``;
``--calibrate none``: without the self-calibration; ``--clock-offset auto``: the inputs' clock
offset searched, :mod:`quadobs.testbed.logs.clock_offset`;
in-process through :func:`quadobs.cli.main`), and the table gives every estimator's position
RMSE after the burn-in and its ``diverged`` flag (diverged or locked out), then the best
estimator's RMSE per variant and seed, then the non-line-of-sight excess the self-calibration
fitted to each log (``calibration.excess`` of the replay's summary) and whether
``ekf-bias-imu-nlos`` took it.

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
from quadobs.errors import run_script
from quadobs.testbed.logs import read_log, write_log
from quadobs.testbed.logs.schema import IMU_FIGURES

VARIANTS = ("full", "noatt", "yaw")
#: The variants of a real flight log, each ``noatt`` with one transform (module docstring).
REAL = ("vib", "vib100", "uneven", "clock", "frd", "bias", "truth100", "nostd", "alias100", "real")
#: The IMU's gaps of 50 ms in the variant ``uneven``.
GAPS = 5
#: The Unix time (s) at which the variant ``clock`` starts.
EPOCH = 1.7e9


def export(
    seed: int,
    duration: float,
    accel_bias: float,
    gyro_bias: float,
    folder: Path,
    settings: tuple[str, ...] = (),
) -> None:
    """Fly ``quadrotor-uwb-realistic`` with ``seed`` and write its log to ``folder`` (with the
    scenario ``settings`` after the IMU's biases).

    ``quadobs run`` needs one live estimator; where it diverges (exit 1, as the live EKF of seed
    7 does at 27 s) the log is written all the same, and only a log not written is a failure."""
    argv = ["run", "quadrotor-uwb-realistic", "--seed", str(seed), "--estimators", "ekf"]
    argv += ["--duration", f"{duration:g}", "--no-progress", "--export-log", str(folder)]
    argv += ["--set", f"quadrotor.accel_bias={accel_bias:g}"]
    argv += ["--set", f"quadrotor.gyro_bias={gyro_bias:g}"]
    for setting in settings:
        argv += ["--set", setting]
    code = cli.main(argv)
    if code not in (0, 1) or not (folder / "meta.csv").exists():
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


def _vibration(log, rng, accel: float, gyro: float):
    imu = log.inputs.copy()
    imu[:, 1:4] += accel * rng.standard_normal((imu.shape[0], 3))
    imu[:, 4:7] += gyro * rng.standard_normal((imu.shape[0], 3))
    return dataclasses.replace(log, inputs=imu)


def _block_mean(imu: np.ndarray, m: int) -> np.ndarray:
    """Each ``m`` consecutive rows as one: their mean, at the first one's time."""
    k = imu.shape[0] // m
    out = imu[: k * m].reshape(k, m, -1).mean(axis=1)
    out[:, 0] = imu[: k * m : m, 0]
    return out


def _uneven(log, rng):
    t = log.inputs[:, 0]
    h = float(np.median(np.diff(t)))
    moved = t + rng.uniform(-0.3 * h, 0.3 * h, t.size)
    moved[0] = t[0]
    keep = np.ones(t.size, dtype=bool)
    for start in rng.uniform(t[0] + 1.0, t[-1] - 1.0, GAPS):
        keep &= ~((moved >= start) & (moved < start + 0.05))
    imu = np.column_stack([moved, log.inputs[:, 1:]])[keep]
    return dataclasses.replace(log, inputs=imu)


def _clock(log):
    imu = log.inputs.copy()
    imu[:, 0] += 0.02 + EPOCH
    ranges, truth = log.ranges.copy(), log.truth.copy()
    ranges[:, 0] += EPOCH
    truth[:, 0] += EPOCH
    return dataclasses.replace(log, inputs=imu, ranges=ranges, truth=truth)


def _frd(log):
    imu = log.inputs.copy()
    imu[:, [2, 3, 5, 6]] *= -1.0  # y and z of the specific force and of the rates
    return dataclasses.replace(log, inputs=imu)


#: The draws of the latest :func:`_range_errors`: ``bias`` (q,) the biases it added and ``nlos``
#: (M,) the rows it lengthened (for the studies that need the truth behind a variant's errors;
#: clear it before making a variant).
RANGE_DRAWS: dict = {}


def _range_errors(log, rng):
    q = log.beacons.shape[0]
    bias = rng.uniform(-0.3, 0.3, q)
    bias[0] = -0.3
    ranges = log.ranges.copy()
    anchor = log.beacon_index(ranges[:, 1])
    ranges[:, 2] += bias[anchor]
    nlos = rng.random(ranges.shape[0]) < 0.1
    ranges[nlos, 2] += rng.exponential(0.3, int(nlos.sum()))
    RANGE_DRAWS.update(bias=bias.copy(), nlos=nlos.copy())
    ranges[:, 2] = np.maximum(ranges[:, 2], 0.0)
    return dataclasses.replace(log, ranges=ranges)


def _mocap(log):
    keep = [i for i, c in enumerate(log.truth_columns) if c in ("time", "x", "y", "z")]
    rows = log.truth[log.truth[:, 0] >= log.inputs[0, 0] + 2.0]
    t = rows[:, 0]
    picked = np.searchsorted(t, np.arange(t[0], t[-1], 0.01))  # 100 Hz
    columns = tuple(log.truth_columns[i] for i in keep)
    return dataclasses.replace(log, truth=rows[picked][:, keep], truth_columns=columns)


#: The transforms of ``real`` in the order they are made (the axes before the noise; the
#: clock's shift last, outside the draws).
REAL_STEPS = ("frd", "vib100", "uneven", "bias", "truth100", "nostd", "clock")
#: ``real`` less one of its transforms: ``real-STEP`` for each step of :data:`REAL_STEPS`.
REAL_LESS = tuple(f"real-{s}" for s in REAL_STEPS)


def _apply(step: str, log, rng, accel: float, gyro: float):
    """``log`` with the one transform ``step`` (module docstring)."""
    if step in ("vib", "vib100", "alias100"):
        log = _vibration(log, rng, accel, gyro)
        if step == "alias100":
            return dataclasses.replace(log, inputs=log.inputs[::10].copy())
        if step == "vib100":
            return dataclasses.replace(log, inputs=_block_mean(log.inputs, 10))
        return log
    if step == "uneven":
        return _uneven(log, rng)
    if step == "frd":
        return _frd(log)
    if step == "bias":
        return _range_errors(log, rng)
    if step == "truth100":
        return _mocap(log)
    if step == "nostd":
        return dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], np.nan))
    if step == "clock":
        return _clock(log)
    raise ValueError(f"unknown transform {step!r}")


def real_variant(log, kind: str, rng, accel: float, gyro: float):
    """``log`` (the variant ``noatt``) with what a real flight log has (module docstring).

    ``real-STEP`` is ``real`` without the transform ``STEP``, every other transform drawn as
    in ``real`` (``rng`` seeded as for ``real``: each step starts from the generator's state at
    which it starts in ``real``), so that ``real`` minus ``real-STEP`` is what ``STEP`` costs
    on the same draws.
    """
    if kind in REAL_LESS:
        left_out = kind.removeprefix("real-")
        start = []  # the generator's state at each step of ``real``
        probe = log
        for step in REAL_STEPS:
            start.append(rng.bit_generator.state)
            probe = _apply(step, probe, rng, accel, gyro)
        for step, state in zip(REAL_STEPS, start, strict=True):
            if step != left_out:
                rng.bit_generator.state = state
                log = _apply(step, log, rng, accel, gyro)
    else:
        for step in REAL_STEPS if kind == "real" else (kind,):
            log = _apply(step, log, rng, accel, gyro)
    return dataclasses.replace(log, name=f"{log.name.removesuffix('-noatt')}-{kind}")


def replay(
    folder: Path,
    estimators: str | None,
    burn_in: float,
    reuse: bool = False,
    calibrate="self",
    clock_offset: str = "0",
) -> dict:
    """``quadobs replay FOLDER --burn-in B --calibrate C --clock-offset O`` (defaults
    otherwise); its summary (with ``reuse``, the summary a previous run left, if any)."""
    tag = "" if calibrate == "self" else f"-{calibrate}"
    tag += "" if clock_offset == "0" else f"-clock{clock_offset}"
    summary = folder.parent / f"{folder.name}{tag}.json"
    if reuse and summary.exists():
        return json.loads(summary.read_text())
    argv = ["replay", str(folder), "--burn-in", f"{burn_in:g}", "--summary", str(summary)]
    argv += ["--calibrate", calibrate, "--clock-offset", clock_offset]
    argv += ["--no-progress"] + (["--estimators", estimators] if estimators else [])
    code = cli.main(argv)
    if code not in (0, 1):
        return {"failed": code, "estimators": {}}
    return json.loads(summary.read_text())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--accel-bias", type=float, default=0.2, help="m/s^2 per axis (std)")
    ap.add_argument("--gyro-bias", type=float, default=0.01, help="rad/s per axis (std)")
    ap.add_argument("--yaw", type=float, default=1.0, help="rad, the variant yaw's frame turn")
    ap.add_argument("--variants", default=",".join(VARIANTS + REAL), help="also real-STEP")
    ap.add_argument("--accel-vibration", type=float, default=1.0, help="m/s^2 per sample")
    ap.add_argument("--gyro-vibration", type=float, default=0.05, help="rad/s per sample")
    ap.add_argument("--estimators", default=None, help="default: the replay's default set")
    ap.add_argument("--burn-in", type=float, default=5.0)
    ap.add_argument("--out", help="folder for the logs and summaries (default: a temporary one)")
    ap.add_argument("--reuse", action="store_true", help="take the summaries a previous run left")
    ap.add_argument("--calibrate", default="self", choices=("self", "none"), help="the replay's")
    ap.add_argument("--clock-offset", default="0", help="the replay's (seconds or auto)")
    args = ap.parse_args()
    unknown = set(args.variants.split(",")) - set(VARIANTS + REAL + REAL_LESS)
    if unknown:
        ap.error(f"--variants: unknown {', '.join(sorted(unknown))}")
    out = Path(args.out or tempfile.mkdtemp(prefix="flights-"))
    rows, fits = [], []
    for seed in (int(s) for s in args.seeds.split(",")):
        base = out / f"seed{seed}"
        if not (base / "meta.csv").exists():
            export(seed, args.duration, args.accel_bias, args.gyro_bias, base)
        log = read_log(base)
        for kind in args.variants.split(","):
            folder = out / f"seed{seed}-{kind}"
            if kind in REAL + REAL_LESS:
                index = REAL.index("real" if kind in REAL_LESS else kind)
                rng = np.random.default_rng([seed, index])
                noatt = variant(log, "noatt", args.yaw)
                vib = (args.accel_vibration, args.gyro_vibration)
                write_log(real_variant(noatt, kind, rng, *vib), folder)
            elif kind != "full":
                write_log(variant(log, kind, args.yaw), folder)
            s = replay(
                base if kind == "full" else folder,
                args.estimators,
                args.burn_in,
                args.reuse,
                args.calibrate,
                args.clock_offset,
            )
            fits.append((seed, kind, s.get("calibration", {}).get("excess")))
            if "failed" in s:
                rows.append((seed, kind, "-", None, f"replay exited {s['failed']}"))
            for name, e in s["estimators"].items():
                rows.append((seed, kind, name, e.get("rmse"), e.get("diverged")))
    print(f"position RMSE after {args.burn_in:g} s (m), logs in {out}")
    for seed, kind, name, rmse, diverged in rows:
        flag = "" if diverged is None else f"  DIVERGED {diverged}"
        text = "-" if rmse is None else f"{rmse:.4f}"
        print(f"seed {seed}  {kind:6s} {name:18s} {text}{flag}")
    print("best after the burn-in, by variant (m):")
    for kind in args.variants.split(","):
        best = [
            min((r[3] for r in rows if r[:2] == (seed, kind) and r[3] is not None), default=None)
            for seed in sorted({r[0] for r in rows})
        ]
        print(f"  {kind:8s} " + "  ".join("-" if b is None else f"{b:.3f}" for b in best))
    print("the excess the self-calibration fitted (median m, shape, fraction, core sd m;")
    print("beyond 3 sd above / below each anchor's median residual; taken or not):")
    for seed, kind, e in fits:
        print(f"seed {seed}  {kind:6s} {_excess_text(e)}")


def _excess_text(e: dict | None) -> str:
    """A summary's ``calibration.excess`` in one line."""
    if not e or "median" not in e:
        return "not fitted"
    return (
        f"{e['median']:.2f}, {e['shape']:.2f}, {e['fraction']:.3f}, {e['sigma']:.3f}; "
        f"{e['upper_tail']} / {e['lower_tail']}; {'taken' if e.get('chosen') else 'not taken'}"
    )


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
