"""Step 7 of the self-calibration, each bias filter's start, against both of its choices.

For each log: the self-calibration as ``quadobs replay LOG`` runs it with its defaults, then
step 7 (:func:`quadobs.testbed.logs.calibration.estimator_biases`: for each estimator that
holds the range biases as states, the calibrated biases or the ranges as logged, decided by
their held-out ranges replayed through that estimator), then the replay twice: every such
estimator started from the calibrated biases, then every one from zero (the ranges as
logged). One calibration serves both replays. The table gives, per log and estimator, step
7's choice, its held-out scores with the biases and as logged, the test's difference of the
mean losses ``D`` and its standard error (m^2), and the position RMSE after the burn-in from
each start; the last line, the RMSE of step 7's choice against the better start's.

A log is a folder, a built-in name (``plaza1``, ``plaza2``) or a stand-in drawn here:
``flight:SEED:STRESS`` (the flight's ``real`` stand-in with a stress of
``sims/stress_hidden_logs.py``, ``none`` for none), ``flightbias:SEED`` (the flight variant
``bias`` of ``sims/replay_flight_variants.py``), ``rover:SEED:STRESS`` (the robot's stand-in in
the ``today`` room). Stand-ins are 40 s (flight) and 90 s (robot) long unless ``--duration``
says, written under ``--out`` and taken from there when they exist (whatever their duration:
give another ``--out`` for another duration). A filter reported diverged counts as NaN.

    python sims/bias_start_study.py flight:3:none flightbias:7 rover:2:none plaza1 --out study/
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import replay_flight_variants as flight
import stress_hidden_logs as stress

from quadobs.errors import QuadobsError, run_script
from quadobs.testbed.logs import open_log, read_log, write_log
from quadobs.testbed.logs.calibration import calibrate, estimator_biases, noise_keys
from quadobs.testbed.logs.replay import default_estimators, replayable_log, run_replay

#: Seconds of the stand-ins drawn here (``--duration`` sets both).
DURATION = {"flight": 40.0, "rover": 90.0}


def stand_in(spec: str, out: Path, duration: float | None = None) -> str | Path:
    """The log of ``spec`` (module docstring): written under ``out`` unless there already."""
    kind, *rest = spec.split(":")
    if kind not in ("flight", "flightbias", "rover"):
        return spec
    try:
        seed = int(rest[0])
    except (IndexError, ValueError):
        raise QuadobsError(
            f"{spec!r}: expected {kind}:SEED{'' if kind == 'flightbias' else ':STRESS'}"
        ) from None
    name = rest[1] if len(rest) > 1 else "none"
    table = stress.FLIGHT if kind == "flight" else stress.ROVER
    if kind != "flightbias" and name not in table:
        raise QuadobsError(f"{spec!r}: unknown stress {name!r} (one of {', '.join(table)})")
    folder = (
        out
        / {
            "rover": f"rover-today-seed{seed}-{name}",
            "flight": f"flight-seed{seed}-{name}",
            "flightbias": f"flight-seed{seed}-variant-bias",
        }[kind]
    )
    if (folder / "meta.csv").exists():
        return folder
    if kind == "rover":
        return stress.rover_log(seed, name, "today", duration or DURATION["rover"], out)
    if kind == "flight":
        return stress.flight_log(seed, name, duration or DURATION["flight"], out)
    base = out / f"flight-seed{seed}-export"
    if not (base / "meta.csv").exists():
        flight.export(seed, duration or DURATION["flight"], 0.2, 0.01, base)
    noatt = flight.variant(read_log(base), "noatt", 1.0)
    rng = np.random.default_rng([seed, flight.REAL.index("bias")])
    write_log(flight.real_variant(noatt, "bias", rng, 1.0, 0.05), folder)
    return folder


def study(source, burn_in: float) -> list[dict]:
    """One row per estimator holding the range biases as states (module docstring)."""
    log, _ = replayable_log(open_log(source))
    cal = calibrate(log, dt=0.1, model=None, setup_options={}, noise=noise_keys(log, None))
    names = default_estimators(log, None)
    chosen = estimator_biases(log, cal, names, dt=0.1, model=None)
    held = [n for n in names if "significantly_better" in cal.per_estimator.get(n, {})]
    if cal.biases is None or not held:
        return [{"log": str(source), "estimator": "-", "choice": "no biases calibrated"}]
    rmse = {}
    others = [n for n in chosen if n not in held]  # decided otherwise (their prior): as step 7
    for start, as_logged in (("calibrated", others), ("zero", [*others, *held])):
        summary = run_replay(
            log, biases=cal.biases, setup_options=cal.options, burn_in=burn_in,
            as_logged=as_logged,
        )  # fmt: skip
        rmse[start] = {
            n: math.nan if e.get("diverged") else e["rmse"]
            for n, e in summary["estimators"].items()
        }
    return [
        {
            "log": str(source),
            "estimator": n,
            "choice": "zero" if n in chosen else "calibrated",
            **cal.per_estimator[n],
            "rmse_calibrated": rmse["calibrated"][n],
            "rmse_zero": rmse["zero"][n],
            "best_other": float(np.nanmin([v for k, v in rmse["zero"].items() if k not in held])),
        }
        for n in held
    ]


def _text(v) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.4f}"


def print_table(rows: list[dict]) -> None:
    """The rows of :func:`study`, then step 7's choice against the better start."""
    print(
        "| log | estimator | choice | held out, biases | as logged | D (m^2) | se | rmse calibrated | rmse zero |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        cells = [r.get(k) for k in ("score", "reference_score", "difference", "standard_error")]
        cells += [r.get("rmse_calibrated"), r.get("rmse_zero")]
        print(
            f"| {r['log']} | {r['estimator']} | {r['choice']} | "
            + " | ".join(map(_text, cells))
            + " |"
        )
    scored = [r for r in rows if "rmse_zero" in r]
    if scored:
        pick = [
            r["rmse_calibrated" if r["choice"] == "calibrated" else "rmse_zero"] for r in scored
        ]
        better = [np.fmin(r["rmse_calibrated"], r["rmse_zero"]) for r in scored]
        zero = [r["rmse_zero"] for r in scored]
        print(
            f"mean RMSE (m) over {len(scored)}: step 7's choice {np.nanmean(pick):.4f},"
            f" always zero {np.nanmean(zero):.4f}, the better start {np.nanmean(better):.4f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "logs",
        nargs="+",
        help="folders, plaza1/plaza2, or flight:SEED:STRESS, flightbias:SEED, rover:SEED:STRESS",
    )
    ap.add_argument("--burn-in", type=float, default=5.0, help="s (default 5)")
    ap.add_argument(
        "--duration", type=float, help="s, of the stand-ins (default 40 flight, 90 robot)"
    )
    ap.add_argument(
        "--out", help="folder for the stand-ins and rows.json (default: a temporary one)"
    )
    args = ap.parse_args()
    if not args.burn_in >= 0.0:
        ap.error(f"--burn-in: expected seconds >= 0, got {args.burn_in}")
    if args.duration is not None and not args.duration > args.burn_in:
        ap.error(f"--duration: expected more seconds than the burn-in, got {args.duration}")
    out = Path(args.out or tempfile.mkdtemp(prefix="bias-start-"))
    out.mkdir(parents=True, exist_ok=True)
    sources = [stand_in(spec, out, args.duration) for spec in args.logs]
    rows = []
    for source in sources:
        rows += study(source, args.burn_in)
        (out / "rows.json").write_text(json.dumps(rows, indent=1))
        print(f"{source}: done", flush=True)
    print_table(rows)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
