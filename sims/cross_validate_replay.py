"""The replay's defaults across sources: each source's calibrated setting applied to the others.

Sources: two simulated flights exported as logs (``quadrotor-uwb`` and
``quadrotor-uwb-realistic``, what ``quadobs run SCENARIO --export-log DIR`` writes) and the
CMU Plaza1 and Plaza2 logs (``gtsam`` needed). For each source the self-calibration
(:func:`~quadobs.testbed.logs.calibration.calibrate`, never the truth) picks the process noise
and the range biases. The noise is carried to another source as its factor of the model's prior
(``q / prior``: ``q_imu`` on the flights, ``q_xy`` on the Plaza logs, whose models differ; the
prior is the log's own where it sets one, :func:`~quadobs.testbed.logs.estimators.log_defaults`:
an odometry's speed, a stated accelerometer density);
the heading filters' intensities (``q_xy_heading``, ``q_theta``, calibrated on odometry logs)
likewise where both logs have them, else the target's prior; the biases belong to a log's
anchors, so each log keeps its own calibrated ones. Every log is replayed in time with
``--estimators`` (default ``augmented,ekf``) from ``--initial-offset`` metres off, at the prior
(``--calibrate none``), and at each source's factors; the table gives the position RMSE after
each log's burn-in (5 s on the flights, none on the Plaza logs, as in the docs' figures), and,
with ``isam2`` among the estimators, each one's ratio to iSAM2's online RMSE. An estimator the
replay reports diverged has no figure: ``diverged`` stands in its place (and in its ratios).

    python sims/cross_validate_replay.py [--quad-duration 20] [--sources quad,realistic,plaza1,plaza2]
    python sims/cross_validate_replay.py --sources plaza1,plaza2 \
        --estimators augmented,augmented-heading,ekf,ukf-heading,isam2
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.testbed.episode import run_episode
from quadobs.testbed.logs import load_builtin, read_log
from quadobs.testbed.logs.calibration import calibrate, noise_keys, process_noise_key
from quadobs.testbed.logs.estimators import ReplaySetup, log_defaults
from quadobs.testbed.logs.export import LogExportSink
from quadobs.testbed.logs.replay import run_replay
from quadobs.testbed.worlds.replay import default_model

NAMES = ["augmented", "ekf"]
SCENARIOS = {"quad": "quadrotor-uwb", "realistic": "quadrotor-uwb-realistic"}


def source_log(name: str, durations: dict):
    """The log of a source, its replay step and burn-in (s)."""
    if name in SCENARIOS:
        scenario = load_scenario(SCENARIOS[name], duration=durations[name], seed=0)
        folder = tempfile.mkdtemp(prefix=f"{name}-")
        run_episode(scenario, estimators=["ekf"], sinks=[LogExportSink(folder)])
        return read_log(folder), scenario.dt, 5.0
    return load_builtin(name), 0.1, 0.0


def carried(factors: dict, source: str, log, key: str, prior: dict) -> dict:
    """The setup options of ``log`` at ``source``'s factors of its ``prior``: the model's intensity
    ``key`` at the source's model factor, each heading intensity of the log at the source's factor
    (1 where the source has none)."""
    out = {key: prior[key] * factors[source]["model"]}
    for k in noise_keys(log)[1:]:
        out[k] = prior[k] * factors[source].get(k, 1.0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sources", default="quad,realistic,plaza1,plaza2")
    ap.add_argument("--estimators", default=",".join(NAMES))
    ap.add_argument("--quad-duration", type=float, default=20.0)
    ap.add_argument("--realistic-duration", type=float, default=40.0)
    ap.add_argument("--initial-offset", type=float, default=50.0)
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    names, estimators = args.sources.split(","), args.estimators.split(",")
    durations = {"quad": args.quad_duration, "realistic": args.realistic_duration}
    logs, factors, cals = {}, {}, {}
    for name in names:
        log, dt, burn = source_log(name, durations)
        key = process_noise_key(default_model(log))
        prior = {**{k: getattr(ReplaySetup, k) for k in noise_keys(log)}, **log_defaults(log)}
        cal = calibrate(log, dt=dt)  # the log's own prior (log_defaults)
        logs[name], cals[name] = (log, dt, burn, key, prior), cal
        factors[name] = {"model": cal.options[key] / prior[key]}
        factors[name].update({k: cal.options[k] / prior[k] for k in noise_keys(log)[1:]})
        print(f"{name}: {key} {cal.options[key]:g} (factors {factors[name]}); {cal.reason}")
    rows = {}
    for name, (log, dt, burn, key, prior) in logs.items():
        biases = cals[name].biases
        runs = {"prior": {}, **{f"from {s}": carried(factors, s, log, key, prior) for s in factors}}
        done: dict = {}
        for label, options in runs.items():
            tag = tuple(sorted(options.items()))
            if tag not in done:
                s = run_replay(
                    log, estimators=estimators, dt=dt, initial_offset=args.initial_offset,
                    batch=False, burn_in=burn, biases=biases, setup_options=options,
                )  # fmt: skip
                done[tag] = {n: s["estimators"][n]["rmse"] for n in estimators}
                for n in estimators:
                    if s["estimators"][n].get("diverged"):
                        print(f"{name} {label}: {n} diverged: {s['estimators'][n]['diverged']}")
            rows.setdefault(name, {})[label] = done[tag]
        print(
            f"{name}: "
            + "; ".join(
                f"{label} " + ", ".join(f"{n} {_fmt(v, '.4g')}" for n, v in r.items())
                for label, r in rows[name].items()
            ),
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"factors": factors, "rmse": rows}, fh, indent=1)
    header = "evaluated on | " + " | ".join(["prior", *(f"from {s}" for s in names)])
    print(header)
    for name, r in rows.items():
        print(f"{name} | " + " | ".join(" / ".join(_fmt(v) for v in r[c].values()) for c in r))
    print(f"({' / '.join(estimators)} position RMSE, m)")
    if "isam2" in estimators:
        print("ratio to iSAM2's online RMSE:")
        for name, r in rows.items():
            print(
                f"{name} | "
                + " | ".join(
                    " / ".join(
                        _fmt(None if v is None or r[c]["isam2"] is None else v / r[c]["isam2"])
                        for n, v in r[c].items()
                        if n != "isam2"
                    )
                    for c in r
                )
            )


def _fmt(value, spec: str = ".3g") -> str:
    """A figure, or ``diverged`` where the replay gave none (an estimator reported diverged)."""
    return "diverged" if value is None else format(value, spec)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
