"""The IMU input's noise intensity ``q_imu``: which rule tracks a quadrotor best, and whether the
difference is systematic or seed to seed.

For each seed the scenario flies live with the log export (the live filters take the scenario's
rule, :func:`quadobs.testbed.imu.input_noise_std`: white noise, attitude error and the
accelerometer's bias matched over 1 s), and the exported log is replayed in time from the live
episode's initial guess, without calibration, once with each intensity of ``--q``: the same
rows, the same estimators, only ``q_imu`` differs. ``live`` names the scenario's rule
(``sigma_u^2 dt``), ``floor`` the replay's floor for a log stating only a density
(:data:`~quadobs.testbed.logs.estimators.ACCEL_NOISE`), ``log`` what the replay's defaults take
from the log (:func:`~quadobs.testbed.logs.estimators.log_defaults`); any other entry is a
number (m^2/s^3). Prints the position RMSE after the burn-in per estimator and seed, and the
mean over the seeds of the ratio of each column to the live episode's.

    python sims/imu_noise_rule.py --scenario quadrotor-tdoa --duration 30 --burn-in 10 \\
        --estimators tdoa-handover,ekf --seeds 0,1,2,3,4
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
from quadobs.testbed.logs.estimators import ACCEL_NOISE, log_defaults
from quadobs.testbed.logs.export import LogExportSink
from quadobs.testbed.logs.replay import run_replay


def live_rmse(result, name: str, burn_in: float) -> float:
    """Position RMSE of ``name`` over ``t >= burn_in`` of a run collected every step."""
    t, X = result.trace["time"], result.trace["truth"]
    e = (result.trace["estimates"][name][:, :3] - X[:, :3])[t >= burn_in]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def live_q(scenario) -> float:
    """The live filters' input-noise intensity (m^2/s^3): ``sigma_u^2 dt``."""
    from quadobs.testbed.factories import baseline_settings

    variance = np.asarray(baseline_settings(scenario).dynamics.input_covariance, dtype=float)
    return float(variance.flat[0]) * scenario.dt


def intensity(label: str, scenario, log) -> float:
    """The ``q_imu`` a column label names."""
    if label == "live":
        return live_q(scenario)
    if label == "floor":
        return ACCEL_NOISE
    if label == "log":
        return log_defaults(log).get("q_imu", np.nan)
    return float(label)


def one_seed(args, seed: int) -> dict:
    """``{estimator: [live, replayed at each q]}`` for one seed."""
    names = args.estimators.split(",")
    scenario = load_scenario(args.scenario, duration=args.duration, seed=seed)
    folder = tempfile.mkdtemp(prefix="imu-rule-")
    live = run_episode(scenario, estimators=names, collect_every=1, sinks=[LogExportSink(folder)])
    log = read_log(folder)
    x0 = live.trace["estimates"][names[0]][0]
    out = {n: [live_rmse(live, n, args.burn_in)] for n in names}
    qs = [intensity(label, scenario, log) for label in args.q.split(",")]
    for q in qs:
        s = run_replay(
            log, estimators=names, dt=scenario.dt, x0=x0, batch=False, burn_in=args.burn_in,
            setup_options={"q_imu": q},
        )  # fmt: skip
        for n in names:
            out[n].append(s["estimators"][n]["rmse"])
    print(f"seed {seed}: q_imu " + ", ".join(f"{q:.3g}" for q in qs), flush=True)
    for n in names:
        print(f"  {n:14s} " + "  ".join(f"{v:.4f}" for v in out[n]), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", default="quadrotor-tdoa")
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--burn-in", type=float, default=10.0)
    ap.add_argument("--estimators", default="tdoa-handover,ekf")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--q", default="live,floor", help="the replay's q_imu, comma-separated")
    args = ap.parse_args()
    labels = args.q.split(",")
    rows: dict[str, list] = {}
    for seed in (int(s) for s in args.seeds.split(",")):
        for name, values in one_seed(args, seed).items():
            rows.setdefault(name, []).append(values)
    print(f"{args.scenario}, {args.duration:g} s, RMSE after {args.burn_in:g} s (m)")
    print(f"{'estimator':14s} {'seed':>4s} {'live':>8s} " + " ".join(f"{x:>8s}" for x in labels))
    seeds = args.seeds.split(",")
    for name, table in rows.items():
        a = np.array(table)
        for seed, r in zip(seeds, a):
            print(f"{name:14s} {seed:>4s} " + " ".join(f"{v:8.4f}" for v in r))
        ratio = a[:, 1:] / a[:, :1]
        print(
            f"{name:14s} mean ratio to live: "
            + ", ".join(f"{x} {m:.3f} (sd {s:.3f})" for x, m, s in
                        zip(labels, ratio.mean(0), ratio.std(0, ddof=1) if len(a) > 1 else ratio[0] * 0))
        )  # fmt: skip


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
