"""The ``quadobs`` command line.

``quadobs run SCENARIO --out PATH.rrd --summary PATH.json`` runs one episode headless and
prints a summary table; ``quadobs list`` names the built-in scenarios; ``quadobs excitation
SCENARIO [--window S]`` prints the persistence-of-excitation report of the scenario's input
(no physics, no MuJoCo); ``quadobs campaign SCENARIO --runs N --out DIR`` runs a Monte
Carlo campaign (:mod:`quadobs.studies.campaign`); ``quadobs bench [--json PATH]`` measures the
estimators' cost beside the physics (:mod:`quadobs.studies.bench`). Errors in the
input (a bad scenario field, an unwritable path) print one line naming the problem and
exit with status 2; Ctrl-C stops a run after closing its recording (status 130).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from quadobs.errors import QuadobsError

__all__ = ["main"]


def _fmt(value, unit: str = "", digits: int = 4) -> str:
    if value is None:
        return "never"
    if isinstance(value, float):
        return f"{value:.{digits}g}{unit}"
    return f"{value}{unit}"


def print_summary(summary: dict, file=sys.stdout) -> None:
    """A compact table of the summary: one row per estimator."""
    head = (
        f"scenario {summary['scenario']}: {summary['physics_steps']} steps, {summary['duration']:.3g} s simulated, "
        f"{summary['steps_per_second']:.0f} steps/s"
        + ("  [INTERRUPTED]" if summary.get("interrupted") else "")
    )
    print(head, file=file)
    cols = ["estimator", "aux", "|e_p| end (m)", "|e_v| end (m/s)", "t(|e_p|<1m)", "t(|e_p|<0.1m)"]
    wind = any("final_wind_error" in e for e in summary["estimators"].values())
    if wind:
        cols.append("|e_w| end (m/s)")
    rows = []
    for name, e in summary["estimators"].items():
        im = e.get("immersion")
        aux = f"{im['n_aux']}/{im['naive_aux']}" if im else "-"
        row = [
            name,
            aux,
            _fmt(e["final_position_error"]),
            _fmt(e["final_velocity_error"]),
            _fmt(e["time_to_1m"], " s"),
            _fmt(e["time_to_0p1m"], " s"),
        ]
        if wind:
            row.append(_fmt(e.get("final_wind_error")))
        rows.append(row)
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)), file=file)
    for r in rows:
        print("  ".join(v.ljust(w) for v, w in zip(r, widths)), file=file)
    if summary.get("recording"):
        print(f"recording: {summary['recording']}  (open with: rerun {summary['recording']})", file=file)


def _cmd_list(args) -> int:
    from quadobs.testbed.scenario import list_scenarios

    for name, desc in list_scenarios().items():
        print(f"{name:16s} {desc}")
    print(f"{'le2013':16s} Le et al. 2013 section 5: zonotopic estimation of an uncertain 2-state system (no MuJoCo)")
    return 0


def _estimator_list(text: str | None) -> list[str] | None:
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise QuadobsError("--estimators: give at least one name")
    return names


def _cmd_le2013(args) -> int:
    from quadobs.studies.le2013.study import format_table, run_le2013

    steps = 50 if args.duration is None else int(round(args.duration))
    summary = run_le2013(args.out, args.summary, seed=0 if args.seed is None else args.seed, steps=steps, runs=args.runs)
    print(format_table(summary))
    if args.out:
        print(f"recording: {args.out}  (open with: rerun {args.out})")
    if args.summary:
        print(f"summary: {args.summary}")
    return 0


def _cmd_run(args) -> int:
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario

    if args.scenario == "le2013":
        return _cmd_le2013(args)
    scenario = load_scenario(args.scenario, duration=args.duration, seed=args.seed)
    result = run_episode(
        scenario,
        estimators=_estimator_list(args.estimators),
        out=args.out,
        summary_path=args.summary,
        progress=not args.no_progress,
    )
    print_summary(result.summary)
    if args.summary:
        print(f"summary: {args.summary}")
    return 130 if result.summary.get("interrupted") else 0


def _cmd_excitation(args) -> int:
    from quadobs.testbed.excitation import scenario_report
    from quadobs.testbed.episode import write_json_atomic
    from quadobs.testbed.scenario import load_scenario

    if args.json:
        from quadobs.errors import check_writable

        check_writable(args.json)
    scenario = load_scenario(args.scenario)
    report = scenario_report(scenario, window=args.window, step=args.step)
    print(report.format())
    if args.json:
        write_json_atomic(args.json, report.to_dict())
        print(f"report: {args.json}")
    return 0


def _cmd_campaign(args) -> int:
    from quadobs.studies.campaign import print_campaign, run_campaign
    from quadobs.testbed.scenario import load_scenario

    scenario = load_scenario(args.scenario, duration=args.duration, seed=args.seed)
    result = run_campaign(
        scenario,
        runs=args.runs,
        estimators=_estimator_list(args.estimators),
        out_dir=args.out,
        scheduler=args.scheduler,
        workers=args.workers,
        every=args.every,
        threshold=args.threshold,
        confidence=args.confidence,
        progress=not args.no_progress,
    )
    print_campaign(result.summary)
    if result.summary["interrupted"]:
        return 130
    return 1 if result.summary["runs_failed"] else 0


def _cmd_bench(args) -> int:
    from quadobs.studies.bench import print_bench, run_bench
    from quadobs.testbed.episode import write_json_atomic

    if args.json is not None:
        from quadobs.errors import check_writable

        check_writable(args.json)
    for name in ("steps", "repeats", "batch", "batch_steps"):
        if getattr(args, name) < 1:
            raise QuadobsError(f"--{name.replace('_', '-')}: must be at least 1, got {getattr(args, name)}")
    if args.threads < 0:
        raise QuadobsError(f"--threads: must be non-negative, got {args.threads}")
    log = None if args.quiet else (lambda msg: print(f"[bench] {msg}", file=sys.stderr, flush=True))
    result = run_bench(
        steps=args.steps, repeats=args.repeats, batch=args.batch, batch_steps=args.batch_steps,
        threads=args.threads, quick=args.quick, log=log,
    )
    print_bench(result)
    if args.json is not None:
        write_json_atomic(args.json, result)
        print(f"figures: {args.json}")
    return 0


def _cmd_plot(args) -> int:
    """``quadobs plot INPUT --out FIG``: a figure of a run, a campaign folder or the le2013 recording."""
    from quadobs.studies.plot import render

    def numbers(text, kind, name):
        try:
            return [kind(v) for v in text.replace("x", ",").split(",") if v.strip()]
        except ValueError:
            raise QuadobsError(f"{name}: expected numbers separated by commas, got {text!r}") from None

    what = None if args.what is None else [w.strip() for w in args.what.split(",") if w.strip()]
    size = None if args.size is None else numbers(args.size, float, "--size")
    samples = None if args.samples is None else numbers(args.samples, int, "--samples")
    out = render(args.input, args.out, what, size=size, dpi=args.dpi, samples=samples, legend=not args.no_legend)
    print(f"figure: {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="quadobs", description="State estimation for systems with quadratic outputs: a MuJoCo testbed.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("list", help="name the built-in scenarios")
    p.set_defaults(func=_cmd_list)

    p = sub.add_parser("run", help="run one episode headless, record it and print a summary")
    p.add_argument("scenario", help="built-in scenario name (see 'quadobs list') or path to a scenario .toml")
    p.add_argument("--out", type=Path, help="recording to write (.rrd)")
    p.add_argument("--summary", type=Path, help="JSON summary to write")
    p.add_argument("--duration", type=float, help="override the scenario duration (s)")
    p.add_argument("--seed", type=int, help="override the scenario seed")
    p.add_argument("--estimators", help="comma-separated estimator names (default: augmented and the scenario's variants)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--runs", type=int, default=50, help="le2013 only: number of seeded runs (default 50; --duration is the number of samples)")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "excitation",
        help="persistence-of-excitation report of a scenario's input (Gramian measure, Propositions 4-8), without the physics",
    )
    p.add_argument("scenario", help="built-in scenario name or path to a scenario .toml")
    p.add_argument("--window", type=float, help="window length delta (s); default: the scenario's excitation.window")
    p.add_argument("--step", type=float, help="hold step of the input (s); default: the monitor's (0.01 s)")
    p.add_argument("--json", type=Path, help="also write the report as JSON")
    p.set_defaults(func=_cmd_excitation)

    p = sub.add_parser(
        "campaign",
        help="Monte Carlo: many seeded runs in parallel (local processes or a Dask cluster), statistics and the Cramér-Rao bound",
        description="Exit status: 0 when every run completed, 1 when some failed (they are listed), 2 on bad input, 130 on Ctrl-C.",
    )
    p.add_argument("scenario", help="built-in scenario name (see 'quadobs list') or path to a scenario .toml")
    p.add_argument("--runs", type=int, required=True, help="number of seeded runs")
    p.add_argument("--estimators", help="comma-separated estimator names (e.g. augmented,ekf,ukf)")
    p.add_argument("--out", type=Path, required=True, help="folder for summary.json, runs.parquet, series.parquet, statistics.rrd")
    p.add_argument("--scheduler", help="Dask distributed scheduler address (tcp://host:port); default: local processes")
    p.add_argument("--workers", type=int, help="local processes (default: the number of CPUs; 0: in this process)")
    p.add_argument("--every", type=float, help="sampling period (s) of the statistics over time (default about 0.1 s)")
    p.add_argument("--threshold", type=float, default=1.0, help="final position error (m) under which a run has converged (default 1)")
    p.add_argument("--confidence", type=float, default=0.95, help="of the two-sided chi-square NEES/NIS intervals (default 0.95)")
    p.add_argument("--duration", type=float, help="override the scenario duration (s)")
    p.add_argument("--seed", type=int, help="override the scenario seed (the runs' seeds derive from it)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_campaign)

    p = sub.add_parser("bench", help="measure the estimators' cost beside the physics (single vehicle, batch, scaling)")
    p.add_argument("--json", type=Path, help="write the figures to this JSON file")
    p.add_argument("--steps", type=int, default=20000, help="physics steps per single-vehicle run (default 20000)")
    p.add_argument("--repeats", type=int, default=5, help="repeats of each measurement; medians are reported (default 5)")
    p.add_argument("--batch", type=int, default=1000, help="vehicles in the batch (default 1000)")
    p.add_argument("--batch-steps", type=int, default=200, help="steps per batch run (default 200)")
    p.add_argument("--threads", type=int, default=0, help="threads for the batch: MuJoCo's rollout and the observers (default 0: calling thread)")
    p.add_argument("--quick", action="store_true", help="a small scaling table")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser(
        "plot",
        help="draw a figure (PNG, PDF, SVG) of a run's .rrd, a campaign folder or the le2013 recording (needs quadobs[plot])",
        description="Panels (--what, comma-separated): "
        "run .rrd: paths, paths3d, position, velocity, wind, ranges, covariance, nis, bounds, excitation; "
        "campaign folder: rmse, rmse-velocity, converged, nees, nis, final; "
        "le2013 .rrd: sets, width-x1, width-x2, volume, bounds. "
        "Default size 7.0x4.5 in (two-column paper width; 3.5x2.6 for one column).",
    )
    p.add_argument("input", type=Path, help="a run's .rrd, a campaign folder (or its statistics.rrd), or the le2013 .rrd")
    p.add_argument("--out", type=Path, required=True, help="figure file: .png, .pdf or .svg")
    p.add_argument("--what", help="comma-separated panels (default: the input's usual figure; names above)")
    p.add_argument("--size", help="WIDTHxHEIGHT in inches (default 7.0x4.5)")
    p.add_argument("--dpi", type=float, help="dots per inch of a PNG (default 150)")
    p.add_argument("--samples", help="le2013 sets: comma-separated samples k to draw (default: one early, the last)")
    p.add_argument("--no-legend", action="store_true", help="no legends")
    p.set_defaults(func=_cmd_plot)
    return parser


def _sigterm_as_interrupt(signum, frame):  # pragma: no cover - exercised by a subprocess test
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    except ValueError:  # not in the main thread
        pass
    try:
        return args.func(args)
    except QuadobsError as exc:
        print(f"quadobs: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("quadobs: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into a reader that stopped (e.g. head)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
