"""A TDOA flight exported as a log (``--export-log``) and replayed: live and replayed RMSE side by side.

Runs the live episode of a TDOA scenario (``quadrotor-tdoa`` by default: the quadrotor flown
on ``tdoa-handover``) with :class:`~quadobs.testbed.logs.export.LogExportSink` (what
``quadobs run SCENARIO --export-log DIR`` does), reads the log back (``tdoa.csv``, the body
IMU, the AHRS attitude, the truth), replays it in time on the physics grid from the live
episode's initial guess with the replay's defaults (those of ``quadobs replay --calibrate
none``; with ``--calibrate``, the self-calibration's choice from the held-out TDOA, as
``quadobs replay`` by default), and prints each estimator's position RMSE after the burn-in, live
and replayed, and their ratio. The GTSAM peer (``isam2``, the TDOA factor) runs in the
replay beside them: its online estimate, iSAM2's smoothed keyframes and the batch optimum.

    python sims/replay_exported_tdoa.py --duration 70 --burn-in 10 --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.testbed.episode import run_episode
from quadobs.testbed.logs import read_log
from quadobs.testbed.logs.calibration import calibrate
from quadobs.testbed.logs.export import LogExportSink
from quadobs.testbed.logs.replay import run_replay

LIVE = "tdoa-handover,tdoa-observer,ekf,ukf"


def live_rmse(result, name: str, burn_in: float) -> float:
    """Position RMSE of ``name`` over ``t >= burn_in`` of a run collected every step."""
    t, X = result.trace["time"], result.trace["truth"]
    e = (result.trace["estimates"][name][:, :3] - X[:, :3])[t >= burn_in]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def one_seed(args, seed: int) -> dict:
    """Live and replayed RMSE of every estimator for one seed (and iSAM2's in the replay)."""
    names = args.estimators.split(",")
    scenario = load_scenario(args.scenario, duration=args.duration, seed=seed)
    folder = args.out or tempfile.mkdtemp(prefix="tdoa-export-")
    live = run_episode(scenario, estimators=names, collect_every=1, sinks=[LogExportSink(folder)])
    log = read_log(folder)
    x0 = live.trace["estimates"][names[0]][0]
    replayed = names + (["isam2"] if args.isam2 else [])
    options, calibration = None, None
    if args.calibrate:
        cal = calibrate(log, dt=scenario.dt)
        options, calibration = cal.options, cal.summary()
        print(f"seed {seed}: calibrated from the log: {cal.reason}")
    s = run_replay(
        log, estimators=replayed, dt=scenario.dt, x0=x0, batch=args.isam2, burn_in=args.burn_in,
        setup_options=options, calibration=calibration,
    )  # fmt: skip
    flight = live.summary.get("flight", {})
    print(
        f"seed {seed}: {log.tdoa.shape[0]} TDOA, {log.inputs.shape[0]} IMU rows; flown on "
        f"{flight.get('feedback')}, crashed: {flight.get('crashed')}"
    )
    out = {}
    for n in names:
        out[n] = (live_rmse(live, n, args.burn_in), s["estimators"][n]["rmse"])
    if args.isam2:
        peer = s["estimators"]["isam2"]
        out["isam2"] = (np.nan, peer["rmse"])
        out["isam2 smoothed"] = (np.nan, peer.get("smoothed_rmse", np.nan))
        out["isam2 batch"] = (np.nan, peer.get("batch_rmse", np.nan))
    count = s["ranges"].get("measurements_in_time", log.tdoa.shape[0])
    cost = {n: s["estimators"][n].get("seconds_per_measurement", np.nan) * count for n in replayed}
    print(
        f"seed {seed}: replay wall time {s['wall_time']:.1f} s; per estimator (s): "
        + ", ".join(f"{n} {c:.1f}" for n, c in cost.items())
        + (
            f"; isam2 smoothed {s['estimators']['isam2'].get('smoothed_seconds', np.nan):.1f},"
            f" batch {s['estimators']['isam2'].get('batch_seconds', np.nan):.1f}"
            if args.isam2
            else ""
        )
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", default="quadrotor-tdoa")
    ap.add_argument("--duration", type=float, default=70.0)
    ap.add_argument("--estimators", default=LIVE)
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--burn-in", type=float, default=10.0)
    ap.add_argument("--no-isam2", dest="isam2", action="store_false")
    ap.add_argument(
        "--calibrate", action="store_true", help="the replay's noise from the self-calibration"
    )
    ap.add_argument("--out", help="the log folder (default: a temporary one per seed)")
    args = ap.parse_args()
    rows: dict[str, list] = {}
    for seed in (int(s) for s in args.seeds.split(",")):
        for name, pair in one_seed(args, seed).items():
            rows.setdefault(name, []).append(pair)
    print(f"position RMSE after {args.burn_in:g} s (m), per seed: live / replayed (ratio)")
    for name, pairs in rows.items():
        cells = [
            f"{rr:.4f}" if np.isnan(rl) else f"{rl:.4f} / {rr:.4f} ({rr / rl:.3f})"
            for rl, rr in pairs
        ]
        print(f"{name:16s} " + "  ".join(cells))


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
