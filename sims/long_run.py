"""One simulated hour at 1 kHz (3.6 million steps): the observer's numerics over a long run.

    python sims/long_run.py [--scenario ifac2021-noisy] [--duration 3600] [--json runs/long_run.json]

Two runs of the same length:

* ``testbed``: the episode loop itself (MuJoCo truth, sensor layer, observer; no recording),
  the trajectories sampled every ``--every`` steps; the covariance checked is the state
  block ``x_covariance`` of the augmented ``P``;
* ``direct``: the observer alone on the exactly integrated vehicle (ranges with 0.5 m noise
  at 100 Hz, as ``ifac2021-noisy``), its full augmented ``P`` checked every ``--every`` steps.

Each reports: NaN anywhere, the largest asymmetry ``max |P - P^T|`` and the smallest
eigenvalue of the covariance, the final position error, and the drift once converged:
the RMS position error over consecutive windows (``--window`` s) after ``--settle`` s,
their largest and smallest value and their ratio, and the least-squares slope of the
error (m per hour); also the wall time.
"""

import argparse
import time
from pathlib import Path

import numpy as np

from quadobs import AugmentedObserver, immerse, load_scenario, vehicle_system
from quadobs.errors import run_script
from quadobs.testbed.episode import run_episode, write_json_atomic


def drift(t: np.ndarray, err: np.ndarray, settle: float, window: float) -> dict:
    """Windowed RMS of ``err`` after ``settle`` s and the slope of a straight-line fit (per hour)."""
    keep = t >= settle
    t, err = t[keep], err[keep]
    idx = ((t - settle) // window).astype(int)
    full = idx < max(int((t[-1] - settle + 1e-9) // window), 1)  # whole windows only
    rms = np.sqrt(np.bincount(idx[full], err[full] ** 2) / np.bincount(idx[full]))
    slope = np.polyfit(t, err, 1)[0] * 3600.0
    return {
        "window_s": window,
        "windows": int(rms.size),
        "rms_min": float(rms.min()),
        "rms_max": float(rms.max()),
        "rms_ratio": float(rms.max() / rms.min()),
        "rms_first": float(rms[0]),
        "rms_last": float(rms[-1]),
        "slope_m_per_hour": float(slope),
    }


def testbed(scenario: str, duration: float, every: int, settle: float, window: float) -> dict:
    sc = load_scenario(scenario, duration=duration)
    t0 = time.perf_counter()
    res = run_episode(sc, estimators=["augmented"], collect_every=every)
    wall = time.perf_counter() - t0
    tr = res.trace
    ok = np.isfinite(tr["time"])
    t, X, Xh, P = (
        tr["time"][ok],
        tr["truth"][ok],
        tr["estimates"]["augmented"][ok],
        tr["covariances"]["augmented"][ok],
    )
    err = np.linalg.norm(Xh[:, :3] - X[:, :3], axis=1)
    return {
        "scenario": scenario,
        "steps": res.summary["physics_steps"],
        "wall_s": wall,
        "steps_per_s": res.summary["physics_steps"] / wall,
        "nan": bool(~np.isfinite(Xh).all() or ~np.isfinite(P).all()),
        "covariance": "x block of P, sampled",
        "max_asymmetry": float(np.abs(P - P.transpose(0, 2, 1)).max()),
        "min_eigenvalue": float(np.linalg.eigvalsh(P).min()),
        "final_position_error": res.summary["final_position_error"],
        "drift": drift(t, err, settle, window),
    }


def direct(duration: float, every: int, settle: float, window: float, seed: int = 7) -> dict:
    dt = 1e-3
    steps = int(round(duration / dt))
    traj = load_scenario("ifac2021").trajectory
    rng = np.random.default_rng(seed)
    im = immerse(vehicle_system(3, np.zeros((1, 3))))
    p, v = traj.position(0.0).astype(float), traj.velocity_at(0.0).astype(float)
    x0 = np.concatenate([p + 20.0 * rng.standard_normal(3), v + 5.0 * rng.standard_normal(3)])
    obs = AugmentedObserver(im, dt, V=1e-4, W=1.0, P0=100.0, x0=x0, sample_period=10 * dt)
    n_rec = steps // every
    t_rec, err_rec, eig_min, asym = np.empty(n_rec), np.empty(n_rec), np.inf, 0.0
    nan = False
    y = np.full(1, np.nan)
    t0 = time.perf_counter()
    r = 0
    for b0 in range(0, steps, 100_000):
        m = min(100_000, steps - b0)
        U = traj.step_accelerations(0.0, dt, m, start=b0)
        noise = 0.5 * rng.standard_normal(m)
        for j in range(m):
            k = b0 + j
            u = U[j]
            if k % 10 == 0:
                rho = np.sqrt(p @ p) + noise[j]
                y[0] = 0.5 * rho * rho
            else:
                y[0] = np.nan
            obs.step(u, y)
            p = p + dt * v + 0.5 * dt * dt * u
            v = v + dt * u
            if (k + 1) % every == 0:
                P = obs.P
                asym = max(asym, float(np.abs(P - P.T).max()))
                eig_min = min(eig_min, float(np.linalg.eigvalsh(P).min()))
                nan |= not (np.isfinite(P).all() and np.isfinite(obs.z).all())
                t_rec[r] = (k + 1) * dt
                err_rec[r] = np.linalg.norm(obs.x_hat[:3] - p)
                r += 1
    wall = time.perf_counter() - t0
    return {
        "steps": steps,
        "wall_s": wall,
        "steps_per_s": steps / wall,
        "nan": nan,
        "covariance": "full augmented P",
        "max_asymmetry": asym,
        "min_eigenvalue": eig_min,
        "final_position_error": float(err_rec[-1]),
        "drift": drift(t_rec[:r], err_rec[:r], settle, window),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="ifac2021-noisy")
    parser.add_argument("--duration", type=float, default=3600.0)
    parser.add_argument(
        "--every", type=int, default=100, help="physics steps between samples (default 100)"
    )
    parser.add_argument(
        "--settle", type=float, default=60.0, help="seconds before the estimate counts as converged"
    )
    parser.add_argument(
        "--window", type=float, default=300.0, help="seconds per RMS window (default 300)"
    )
    parser.add_argument("--skip-direct", action="store_true")
    parser.add_argument("--json", help="write the figures to this JSON file")
    args = parser.parse_args()

    out = {"testbed": testbed(args.scenario, args.duration, args.every, args.settle, args.window)}
    if not args.skip_direct:
        out["direct"] = direct(args.duration, args.every, args.settle, args.window)
    for name, r in out.items():
        d = r["drift"]
        print(
            f"{name:8s} {r['steps']} steps in {r['wall_s']:.1f} s ({r['steps_per_s']:.0f} steps/s); NaN: {r['nan']}; "
            f"{r['covariance']}: max |P - P^T| = {r['max_asymmetry']:.3g}, min eigenvalue = {r['min_eigenvalue']:.3g}\n"
            f"         final |e_p| = {r['final_position_error']:.4g} m; RMS |e_p| over {d['windows']} windows of "
            f"{d['window_s']:g} s after {args.settle:g} s: {d['rms_min']:.4g} .. {d['rms_max']:.4g} m "
            f"(ratio {d['rms_ratio']:.3g}; first {d['rms_first']:.4g}, last {d['rms_last']:.4g}); "
            f"slope {d['slope_m_per_hour']:.3g} m/h"
        )
    if args.json:
        write_json_atomic(args.json, out)
        print(f"figures: {args.json}")


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
