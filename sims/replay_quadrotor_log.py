"""A quadrotor-uwb flight as a log of asynchronous ranges and a body IMU, replayed in time.

Runs the live episode (``quadrotor-uwb``, the estimators given), then writes what a UWB tag
and an IMU on that flight would have logged: each anchor ranged at ``--range-rate`` Hz at its
own times (the anchors staggered evenly, as a tag's round robin), noise ``range_std``; a
body IMU at ``--imu-rate`` Hz (specific force and angular rate, with the scenario's noise
and biases), the attitude at 250 Hz with the scenario's error, and the truth. The body's
attitude is the one a multirotor flies: its z axis along the thrust ``a - g``, heading zero.
Then replays the log in time and prints each estimator's position RMSE live and replayed.

    python sims/replay_quadrotor_log.py --duration 30 --out /tmp/quad-log
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.testbed.episode import run_episode
from quadobs.testbed.logs import RangeLog, write_log
from quadobs.testbed.logs.replay import run_replay

G = 9.80665


def thrust_attitude(a: np.ndarray) -> Rotation:
    """Body-to-navigation rotations with the body z along ``a + g e_z`` and heading zero."""
    z = a + np.array([0.0, 0.0, G])
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, [1.0, 0.0, 0.0])
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    x = np.cross(y, z)
    return Rotation.from_matrix(np.stack([x, y, z], axis=2))


def flight_log(scenario, t, X, rng, range_rate, imu_rate) -> RangeLog:
    anchors = scenario.beacons
    m = anchors.shape[0]
    sigma = scenario.noise.range_std
    p, v = X[:, :3], X[:, 3:]
    a = np.gradient(v, t, axis=0)
    spec = scenario.quadrotor
    accel_std, accel_bias = spec.accel_std, spec.accel_bias
    gyro_std, gyro_bias = spec.gyro_std, spec.gyro_bias
    # ranges: anchor h at h / (m rate) + k / rate
    period = 1.0 / range_rate
    rows = []
    for h in range(m):
        tr = np.arange(h * period / m, t[-1], period)
        ph = np.column_stack([np.interp(tr, t, p[:, i]) for i in range(3)])
        rho = np.linalg.norm(ph - anchors[h], axis=1) + sigma * rng.standard_normal(tr.size)
        rows.append(np.column_stack([tr, np.full(tr.size, h), rho]))
    ranges = np.vstack(rows)
    ranges = ranges[np.argsort(ranges[:, 0], kind="stable")]
    ti = np.arange(0.0, t[-1], 1.0 / imu_rate)
    ai = np.column_stack([np.interp(ti, t, a[:, i]) for i in range(3)])
    R = thrust_attitude(ai)
    f = R.inv().apply(ai + [0.0, 0.0, G])
    f += accel_bias * rng.choice([-1.0, 1.0], 3) + accel_std * rng.standard_normal(f.shape)
    rv = R.as_rotvec()
    dR = (R[2:] * R[:-2].inv()).as_rotvec() / (ti[2:] - ti[:-2])[:, None]  # nav-frame rate
    w = np.vstack([dR[:1], dR, dR[-1:]])
    w = R.inv().apply(w)
    w += gyro_bias * rng.choice([-1.0, 1.0], 3) + gyro_std * rng.standard_normal(w.shape)
    ta = ti[:: max(int(round(imu_rate / 250.0)), 1)]
    err = Rotation.from_rotvec(spec.attitude_std * rng.standard_normal((ta.size, 3)))
    Ra = err * Rotation.from_rotvec(
        np.column_stack([np.interp(ta, ti, rv[:, i]) for i in range(3)])
    )
    q = Ra.as_quat()[:, [3, 0, 1, 2]]
    q *= np.sign(q[:, :1]) + (q[:, :1] == 0)
    return RangeLog(
        "quadrotor-uwb-log", np.arange(m), anchors, ranges, np.column_stack([ti, f, w]),
        float("nan"), np.column_stack([t, p, v]), input_kind="imu_body",
        truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"), attitude=np.column_stack([ta, q]),
        range_std=np.full(ranges.shape[0], sigma),
    )  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=70.0)
    ap.add_argument("--estimators", default="augmented,ekf")
    ap.add_argument("--range-rate", type=float, default=100.0)
    ap.add_argument("--imu-rate", type=float, default=500.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--out")
    ap.add_argument("--tune", action="append", default=[], help="KEY=VALUE of the replay's setup")
    ap.add_argument("--burn-in", type=float, default=0.0)
    ap.add_argument(
        "--calibrate", action="store_true", help="self-calibrate as quadobs replay does"
    )
    args = ap.parse_args()
    names = args.estimators.split(",")
    scenario = load_scenario("quadrotor-uwb", duration=args.duration, seed=args.seed)
    live = run_episode(scenario, estimators=names, collect_every=1)
    t, X = live.trace["time"], live.trace["truth"]
    log = flight_log(
        scenario, t, X, np.random.default_rng(args.seed), args.range_rate, args.imu_rate
    )
    if args.out:
        write_log(log, args.out)
    x0 = live.trace["estimates"][names[0]][0]
    options = {k: float(v) for k, v in (a.split("=") for a in args.tune)}
    biases = None
    if args.calibrate:
        from quadobs.testbed.logs.calibration import calibrate

        cal = calibrate(log, dt=args.dt, setup_options=options)
        biases, options = cal.biases, cal.options
        print("calibration:", cal.summary())
    s = run_replay(
        log, estimators=names, dt=args.dt, x0=x0, batch=False, biases=biases,
        setup_options=options, burn_in=args.burn_in,
    )  # fmt: skip
    print(f"{'estimator':12s} live RMSE  replayed RMSE  ratio   (position, whole flight)")
    for n in names:
        e = (live.trace["estimates"][n][:, :3] - X[:, :3])[t >= args.burn_in]
        rl = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
        rr = s["estimators"][n]["rmse"]
        print(f"{n:12s} {rl:9.4f}  {rr:13.4f}  {rr / rl:5.2f}")
    print("ranges:", s["ranges"])


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
