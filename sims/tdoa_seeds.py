"""``quadrotor-tdoa`` over many seeds as ``quadobs run`` runs it, every estimator from a guess 10 m off.

For each seed ``N`` the scenario is loaded as

    quadobs run quadrotor-tdoa --seed N --set initial.kind=point --set "initial.point=[x0]"

with ``x0`` the vehicle's true initial state (on the ground) moved ``--offset`` metres
along ``x``; with ``kind = "point"`` the filters' position prior is the observer's ``S0``
(100 m^2 per axis: 10 m). The episode runs through :func:`~quadobs.testbed.episode.run_episode`,
the loop of ``quadobs run``: the radio's TDoA3 packets at their own times, the controller on
the truth until ``control.switch_time`` (8 s), then on ``tdoa-handover``. Per seed and
estimator: the position error at 3 s, the time from which it stays below 0.5 m, the RMSE after
``--settle`` seconds, the summary's ``flight_position_rmse``; per seed: the crash. Each seed's
line is appended to ``--jsonl`` as it ends (a long study can be stopped and resumed with
``--resume``); the table of all of them is printed at the end.

    python sims/tdoa_seeds.py --seeds 0-49 --duration 20 --jsonl seeds.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.evaluation.convergence import convergence_times
from quadobs.testbed.episode import run_episode

#: The error (m) below which an estimate counts as converged (the issue's target).
CONVERGED = 0.5


def true_start(name: str, seed: int) -> np.ndarray:
    """The vehicle's true initial state ``(p, v)`` of scenario ``name`` with ``seed``."""
    from quadobs.testbed.sensors import SensorModel, spawn_streams
    from quadobs.testbed.worlds.quadrotor import QuadrotorWorld

    scenario = load_scenario(name, seed=seed)
    world = QuadrotorWorld(scenario, SensorModel(scenario, spawn_streams(seed)), 8)
    return np.asarray(world.state(), dtype=float)


def settings_for(x0: np.ndarray) -> list[str]:
    """The ``--set`` settings that start every estimator at ``x0``."""
    point = ", ".join(f"{v:.9g}" for v in x0)
    return ["initial.kind=point", f"initial.point=[{point}]"]


def seed_metrics(args, seed: int) -> dict:
    """One seed: the episode from a guess ``args.offset`` m off along ``x``, and its figures."""
    x0 = true_start(args.scenario, seed)
    x0[0] += args.offset
    scenario = load_scenario(
        args.scenario, duration=args.duration, seed=seed, settings=settings_for(x0)
    )
    names = args.estimators.split(",")
    run = run_episode(scenario, estimators=names, collect_every=args.every)
    t, X = run.trace["time"], run.trace["truth"]
    flight = run.summary.get("flight", {})
    out = {"seed": seed, "crashed": bool(flight.get("crashed")), "estimators": {}}
    k3 = int(np.searchsorted(t, 3.0))
    for name in names:
        err = np.linalg.norm(run.trace["estimates"][name][:, :3] - X[:, :3], axis=1)
        below = float(convergence_times(t, err[None, :], CONVERGED)[0])
        out["estimators"][name] = {
            "error_at_3s": float(err[k3]),
            "below_from": None if math.isnan(below) else below,
            "rmse_after_settle": float(np.sqrt(np.mean(err[t >= args.settle] ** 2))),
            "flight_position_rmse": run.summary["estimators"][name].get("flight_position_rmse"),
        }
    return out


def table(rows: list[dict]) -> str:
    """The study's figures over the seeds, per estimator."""
    names = list(rows[0]["estimators"])
    lines = [
        f"{len(rows)} seeds; crashed: {sum(r['crashed'] for r in rows)}",
        "estimator | below 0.5 m at 3 s | error at 3 s median / worst | stays below 0.5 m "
        "from (worst) | RMSE after settle median / worst | flight_position_rmse median / worst",
    ]
    for n in names:
        e = [r["estimators"][n] for r in rows]
        at3 = np.array([x["error_at_3s"] for x in e])
        below = [x["below_from"] for x in e]
        n_never = sum(b is None for b in below)
        worst = f"never in {n_never}" if n_never else f"{max(below):.2f} s"
        rmse = np.array([x["rmse_after_settle"] for x in e])
        fl = np.array(
            [x["flight_position_rmse"] for x in e if x["flight_position_rmse"] is not None]
        )
        flown = f"{np.median(fl):.4f} m / {fl.max():.4f} m" if fl.size else "none"
        lines.append(
            f"{n} | {int(np.sum(at3 < CONVERGED))}/{len(e)} | {np.median(at3):.3f} m / "
            f"{at3.max():.3f} m | {worst} | {np.median(rmse):.4f} m / {rmse.max():.4f} m | {flown}"
        )  # fmt: skip
    return "\n".join(lines)


def parse_seeds(text: str) -> list[int]:
    """``"0-49"``, ``"0,3,7"`` or both (``"0-9,25-34"``)."""
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", default="quadrotor-tdoa")
    ap.add_argument("--seeds", default="0-49")
    ap.add_argument("--duration", type=float, help="seconds (default: the scenario's, 70 s)")
    ap.add_argument("--estimators", default="tdoa-handover,tdoa-observer,ekf")
    ap.add_argument("--offset", type=float, default=10.0)
    ap.add_argument("--settle", type=float, default=10.0)
    ap.add_argument("--every", type=int, default=10, help="physics steps between trace rows")
    ap.add_argument("--jsonl", type=Path, help="one line per seed, appended as each ends")
    ap.add_argument("--resume", action="store_true", help="skip the seeds already in --jsonl")
    args = ap.parse_args()
    rows = []
    if args.resume and args.jsonl and args.jsonl.exists():
        rows = [json.loads(line) for line in args.jsonl.read_text().splitlines() if line]
    done = {r["seed"] for r in rows}
    for seed in parse_seeds(args.seeds):
        if seed in done:
            continue
        row = seed_metrics(args, seed)
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.jsonl:
            with args.jsonl.open("a") as f:
                f.write(json.dumps(row) + "\n")
    print(table(rows))


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
