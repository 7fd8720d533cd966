"""The ``quadobs`` command line.

``quadobs run SCENARIO --out PATH.rrd --summary PATH.json`` runs one episode headless and
prints a summary table (``python -m quadobs`` is the same command); ``quadobs list`` names the
built-in scenarios; ``quadobs show SCENARIO`` prints one as TOML (``--set FIELD=VALUE`` overrides
any field, here and wherever a scenario is loaded); ``quadobs excitation
SCENARIO [--window S]`` prints the persistence-of-excitation report of the scenario's input
(no physics, no MuJoCo); ``quadobs campaign SCENARIO --runs N --out DIR`` runs a Monte
Carlo campaign (:mod:`quadobs.studies.campaign`); ``quadobs bench [--json PATH]`` measures the
estimators' cost beside the physics (:mod:`quadobs.studies.bench`). Errors in the
input (a bad scenario field, an unwritable path) print one line naming the problem and
exit with status 2, leaving no folder it created behind; Ctrl-C or SIGTERM, from start-up
(NumPy, SciPy, MuJoCo loading) to exit, stops the command with status 130 and one line,
keeping what is done (a run closes and publishes its recording first; see :func:`main`). On
a first run, one line on stderr says that the compiled kernels are being built (their cache
is then reused).
"""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING

from quadobs._program import (
    INTERRUPTED,
    INTERRUPTED_LINE,
    Signals,
    give_back_signals,
    stop_if_interrupted,
    take_signals,
)

if TYPE_CHECKING:
    import numpy as np

# Nothing else at module level: :func:`main` takes SIGINT and SIGTERM before anything heavier
# (argparse, pathlib, NumPy, ...) loads, so the functions below import what they use.

__all__ = ["main"]


def _fmt(value, unit: str = "", digits: int = 4) -> str:
    if value is None:
        return "never"
    if isinstance(value, float):
        return f"{value:.{digits}g}{unit}"
    return f"{value}{unit}"


#: Exit status of ``quadobs run --fail-on-crash`` when the quadrotor crashed.
EXIT_CRASHED = 3


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
        if e.get("diverged"):  # no figure of a lost estimate (quadobs.testbed.divergence)
            row[2:] = ["invalid"] * (len(row) - 2)
        rows.append(row)
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)), file=file)
    for r in rows:
        print("  ".join(v.ljust(w) for v, w in zip(r, widths)), file=file)
    _print_crash(summary, file)
    print_diverged(summary, file)
    if summary.get("recording"):
        print(
            f"recording: {summary['recording']}  (open with: rerun {summary['recording']})",
            file=file,
        )


def _print_crash(summary: dict, file) -> None:
    """A quadrotor's crash, in one line beside the table (:func:`quadobs.testbed.flight.crash_line`)."""
    from quadobs.testbed.flight import crash_line

    line = crash_line(summary)
    if line is not None:
        print(line, file=file)


def print_diverged(summary: dict, file=None) -> None:
    """One line per diverged or locked-out estimator (:mod:`quadobs.testbed.divergence`), and
    one per filter whose start-up never got its multilateration fix, on ``file`` (default: the
    standard output at the call)."""
    file = sys.stdout if file is None else file
    for name, d in summary.get("estimators", {}).items():
        if isinstance(d, dict) and d.get("diverged"):
            d = d["diverged"]
            at = f"step {d['step']} " if d["step"] >= 0 else ""  # -1: a time without a step
            print(
                f"{name}: DIVERGED at {at}(t = {d['t']:.6g} s): {d['reason']}; "
                "its figures are invalid",
                file=file,
            )
        elif isinstance(d, dict) and d.get("startup"):
            s = d["startup"]
            print(
                f"{name}: NO START-UP FIX (t = {s['t']:.6g} s): {s['reason']}; "
                "its figures are those of the filter run from its prior",
                file=file,
            )


def diverged_status(summary: dict, requested: list[str] | None) -> int:
    """1 when an estimator named in ``--estimators`` diverged or locked out (a line on stderr), else 0.

    With the default estimators (``requested`` is ``None``) the table flags them and the
    status stays 0.
    """
    bad = [
        name
        for name in requested or ()
        if (summary.get("estimators", {}).get(name) or {}).get("diverged")
    ]
    if bad:
        print(
            f"quadobs: error: {', '.join(bad)} diverged; the figures asked for are invalid",
            file=sys.stderr,
        )
    return 1 if bad else 0


#: The section 5 reproduction, run by ``quadobs run le2013`` beside the built-in scenarios.
LE2013_DESCRIPTION = (
    "[LE2013] section 5: zonotopic estimation of an uncertain 2-state system (no MuJoCo)."
)


def _one_line(text: str, width: int) -> str:
    """The first line of ``text``, cut at a word to at most ``width`` characters ("..." marks a cut)."""
    line = text.strip().splitlines()[0] if text.strip() else ""
    if len(line) <= width:
        return line
    cut = line[: max(width - 3, 1)].rsplit(" ", 1)[0].rstrip(" ,;:")
    return cut + "..."


def _cmd_compile(args) -> int:
    """``quadobs compile``: the kernels into Numba's on-disk cache ahead of the first run, side by side."""
    import time

    from quadobs._kernels import cold_kernels
    from quadobs._kernels.cache import cache_folders, heal, writable
    from quadobs._kernels.precompile import SIGNATURES, compile_side_by_side
    from quadobs.errors import RunFault

    t0 = time.perf_counter()
    folders = cache_folders(SIGNATURES)
    for line in heal(folders):
        print(f"quadobs: note: {line}", file=sys.stderr, flush=True)
    todo = list(SIGNATURES) if args.force else cold_kernels(SIGNATURES)
    for folder in folders if todo else ():
        reason = writable(folder)
        if reason is not None:
            raise RunFault(f"kernel cache {folder}: cannot be written ({reason})")
    done = compile_side_by_side(todo)
    for line in heal(folders):  # what was written is read back before it is counted as cached
        print(f"quadobs: note: {line}", file=sys.stderr, flush=True)
    left = cold_kernels(SIGNATURES)
    print(
        f"quadobs compile: {len(done)} of {len(todo)} kernels compiled in {time.perf_counter() - t0:.1f} s; "
        f"{len(SIGNATURES) - len(left)} of {len(SIGNATURES)} in the cache"
    )
    return 0 if not left else 1


def _cmd_list(args) -> int:
    import shutil

    from quadobs.testbed.scenario import list_scenarios

    entries = dict(list_scenarios())
    entries["le2013"] = LE2013_DESCRIPTION
    width = max(len(name) for name in entries)
    columns = shutil.get_terminal_size((100, 24)).columns
    for name in sorted(entries):
        print(f"{name:{width}s}  {_one_line(entries[name], max(columns - width - 3, 20))}")
    return 0


def _estimator_list(text: str | None) -> list[str] | None:
    from quadobs.errors import QuadobsError

    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise QuadobsError("--estimators: give at least one name")
    return names


#: Options of ``quadobs run`` that ``le2013`` takes: ``--duration`` is its number of samples,
#: ``--runs`` its number of seeded runs (``--no-progress`` is accepted: it shows no progress bar).
LE2013_OPTIONS = ("out", "summary", "duration", "seed", "runs", "no_progress")


def _refuse_other_options(args, allowed, what: str) -> None:
    """Refuse any option of ``quadobs run`` given a value other than its default, unless ``allowed``."""
    from quadobs.errors import QuadobsError

    defaults = build_parser().parse_args(["run", args.scenario])
    for dest, value in vars(args).items():
        if (
            dest not in allowed
            and dest not in ("command", "func", "scenario")
            and value != getattr(defaults, dest, value)
        ):
            raise QuadobsError(f"--{dest.replace('_', '-')}: does not apply to {what}")


def _le2013_settings(args) -> dict:
    """``seed``, ``steps`` and ``runs`` of :func:`run_le2013` from the options (defaults 0, 50, 50)."""
    from quadobs.errors import QuadobsError

    _refuse_other_options(
        args, LE2013_OPTIONS, "le2013 (it takes --out, --summary, --duration, --seed, --runs)"
    )
    steps = 50
    if args.duration is not None:
        if not (args.duration >= 1 and float(args.duration).is_integer()):
            raise QuadobsError(
                f"--duration: le2013 counts samples, expected a whole number at least 1, got {args.duration:g}"
            )
        steps = int(args.duration)
    seed = 0 if args.seed is None else args.seed
    if seed < 0:
        raise QuadobsError(f"seed: must be at least 0, got {seed}")
    runs = 50 if args.runs is None else args.runs
    if runs < 1:
        raise QuadobsError(f"--runs: must be at least 1, got {runs}")
    return {"seed": seed, "steps": steps, "runs": runs}


def _cmd_le2013(args) -> int:
    from quadobs.studies.le2013.study import format_table, run_le2013

    settings = _le2013_settings(args)
    _notice_cold_kernels(LE2013_KERNELS)
    stop_if_interrupted()
    summary = run_le2013(args.out, args.summary, **settings)
    print(format_table(summary))
    if args.out:
        print(f"recording: {args.out}  (open with: rerun {args.out})")
    if args.summary:
        print(f"summary: {args.summary}")
    return 0


def _cmd_run(args) -> int:
    from quadobs.errors import QuadobsError, RunFault
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario

    if args.scenario == "le2013":
        if args.set:
            raise QuadobsError("--set: le2013 is not a scenario file and has no fields to set")
        return _cmd_le2013(args)
    if args.runs is not None:
        raise QuadobsError(
            "--runs: applies to le2013 only; for many seeded runs of a scenario use 'quadobs campaign'"
        )
    scenario = load_scenario(
        args.scenario, duration=args.duration, seed=args.seed, settings=args.set
    )
    estimators = _estimator_list(args.estimators)
    sinks = []
    if args.export_log is not None:
        from quadobs.testbed.logs.export import LogExportSink, check_exportable
        from quadobs.testbed.outputs import check_inside_folders, check_output_folder

        check_exportable(scenario)
        check_output_folder(args.export_log, _log_folder_files(), "--export-log")
        check_inside_folders(
            {"--out": args.out, "--summary": args.summary}, {"--export-log": args.export_log}
        )
        sinks.append(LogExportSink(args.export_log))
    _notice_cost(scenario, estimators, args.out is not None)
    _notice_cold_kernels(_episode_kernels(estimators))
    stop_if_interrupted()
    result = run_episode(
        scenario,
        estimators=estimators,
        out=args.out,
        summary_path=args.summary,
        progress=not args.no_progress,
        sinks=sinks,
    )
    print_summary(result.summary)
    if "output_error" in result.summary:  # the table is out; the summary file could not be written
        raise RunFault(result.summary["output_error"])
    if args.summary:
        print(f"summary: {args.summary}")
    if "export_error" in result.summary:  # the run's results are kept; the log folder is not
        raise RunFault(result.summary["export_error"])
    if args.export_log is not None:
        # an odometry log is replayed in time on the default grid (its inputs held between rows)
        grid = "" if scenario.odometry is not None else f" --dt {scenario.dt:g}"
        print(f"log: {args.export_log}  (replay with: quadobs replay {args.export_log}{grid})")
    if result.summary.get("interrupted"):
        return 130
    crashed = result.summary.get("flight", {}).get("crashed")
    if crashed and args.fail_on_crash:
        return EXIT_CRASHED
    return diverged_status(result.summary, estimators)


def _cmd_excitation(args) -> int:
    from quadobs.testbed.episode import write_json_atomic
    from quadobs.testbed.excitation import scenario_report
    from quadobs.testbed.scenario import load_scenario

    if args.json:
        from quadobs.testbed.outputs import check_outputs

        check_outputs({"--json": args.json}, {"scenario": args.scenario})
    scenario = load_scenario(args.scenario, settings=args.set)
    report = scenario_report(scenario, window=args.window, step=args.step)
    print(report.format())
    if args.json:
        write_json_atomic(args.json, report.to_dict())
        print(f"report: {args.json}")
    return 0


def _cmd_campaign(args) -> int:
    from quadobs.errors import QuadobsError
    from quadobs.studies.campaign import print_campaign, run_campaign
    from quadobs.testbed.scenario import load_scenario

    if args.scenario == "le2013":
        raise QuadobsError(
            "scenario 'le2013': not a vehicle scenario; run it with 'quadobs run le2013 --runs N'"
        )
    scenario = load_scenario(
        args.scenario, duration=args.duration, seed=args.seed, settings=args.set
    )
    estimators = _estimator_list(args.estimators)
    _notice_cost(
        scenario, estimators, False, runs=args.runs, workers=args.workers or os.cpu_count() or 1
    )
    _notice_cold_kernels(_episode_kernels(estimators))
    stop_if_interrupted()
    result = run_campaign(
        scenario,
        runs=args.runs,
        estimators=estimators,
        out_dir=args.out,
        scheduler=args.scheduler,
        workers=args.workers,
        every=args.every,
        threshold=args.threshold,
        confidence=args.confidence,
        progress=not args.no_progress,
        retries=args.retries,
        resume=args.resume,
    )
    print_campaign(result.summary)
    if result.summary["interrupted"]:
        return 130
    return 1 if result.summary["runs_failed"] else 0


def _cmd_show(args) -> int:
    from quadobs.errors import QuadobsError
    from quadobs.testbed.scenario import field_reference, load_scenario

    if args.reference:
        print(field_reference(), end="")
        return 0
    if args.scenario is None:
        raise QuadobsError("show: give a scenario name or path (or --reference)")
    print(load_scenario(args.scenario, settings=args.set).to_toml(), end="")
    return 0


def _add_set(p) -> None:
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a scenario field, e.g. noise.range_std=0.1 (value read as TOML, else text; repeatable)",
    )


def _cmd_bench(args) -> int:
    from quadobs.errors import QuadobsError, check_writable
    from quadobs.studies.bench import print_bench, run_bench
    from quadobs.testbed.episode import write_json_atomic

    if args.json is not None:
        check_writable(args.json)
    for name in ("steps", "repeats", "batch", "batch_steps"):
        if getattr(args, name) < 1:
            raise QuadobsError(
                f"--{name.replace('_', '-')}: must be at least 1, got {getattr(args, name)}"
            )
    if args.threads < 0:
        raise QuadobsError(f"--threads: must be non-negative, got {args.threads}")
    log = None if args.quiet else (lambda msg: print(f"[bench] {msg}", file=sys.stderr, flush=True))
    if not args.quiet:
        _notice_cold_kernels(BENCH_KERNELS)
    stop_if_interrupted()
    result = run_bench(
        steps=args.steps,
        repeats=args.repeats,
        batch=args.batch,
        batch_steps=args.batch_steps,
        threads=args.threads,
        quick=args.quick,
        cold_start=not args.no_cold_start,
        log=log,
    )
    print_bench(result)
    if args.json is not None:
        write_json_atomic(args.json, result)
        print(f"figures: {args.json}")
    return 0


def package_version() -> str:
    """The installed distribution's version (``quadobs.__version__``, from the package metadata)."""
    import quadobs

    return quadobs.__version__


def _registered_estimators() -> list[str]:
    from quadobs.testbed.registry import available_estimators

    return available_estimators()


#: Kernels ("module:function") a first run compiles, per command (see :func:`_notice_cold_kernels`).
EPISODE_KERNELS = (  # the default (block) path: the world's read-out with the sensor layer, the excitation monitor
    "quadobs.testbed.worlds._read:read_block",
    "quadobs._kernels.gramian:held_run_terms",
    "quadobs._kernels.observer:range_outputs",
)
AUGMENTED_KERNELS = (
    "quadobs._kernels.observer:augmented_step_block",
    "quadobs._kernels.held_input:expm_series",  # the prediction over intervals of any length
    "quadobs._kernels.in_time:interval_predict",  # the observer in time (quadobs.estimators.augmented_in_time)
    "quadobs._kernels.in_time:state_noise",
    "quadobs._kernels.in_time:scalar_correct",
)
LE2013_KERNELS = ("quadobs._kernels.zonotope:zonotope_step",)
BENCH_KERNELS = (
    "quadobs._kernels.observer:augmented_step",
    "quadobs._kernels.observer:augmented_step_batch",
    "quadobs._kernels.zonotope:zonotope_step",
)
COMPILING_NOTICE = "quadobs: compiling the estimator kernels (first run only, a few seconds)..."


def _episode_kernels(estimators: list[str] | None) -> tuple[str, ...]:
    """The kernels an episode compiles: the sensors' and the world's, the augmented observer's when it runs."""
    if estimators is None or "augmented" in estimators:
        return EPISODE_KERNELS + AUGMENTED_KERNELS
    return EPISODE_KERNELS


def _notice_cost(scenario, estimators, recording: bool, runs: int = 1, workers: int = 1) -> None:
    """One line on stderr before a run expected to be long or large (:func:`quadobs.testbed.outputs.cost_notice`)."""
    from quadobs.testbed.outputs import cost_notice
    from quadobs.testbed.registry import default_estimators

    line = cost_notice(
        scenario, estimators or default_estimators(scenario), recording, runs=runs, workers=workers
    )
    if line:
        import logging

        logging.getLogger("quadobs.cli").warning(line)


def _notice_cold_kernels(kernels, file=None) -> bool:
    """Print :data:`COMPILING_NOTICE` on stderr when some of ``kernels`` are not in Numba's cache yet,
    then compile those side by side (:func:`quadobs._kernels.precompile.compile_side_by_side`)."""
    from quadobs._kernels import cold_kernels
    from quadobs._kernels.precompile import compile_side_by_side

    if not _heal_kernel_cache(kernels, file):  # the cache is bypassed: nothing to compile ahead
        return False
    cold = cold_kernels(kernels)
    if not cold:
        return False
    print(COMPILING_NOTICE, file=file or sys.stderr, flush=True)
    compile_side_by_side(cold)
    _heal_kernel_cache(kernels, file)  # what was written is read back and its sha256 recorded
    return True


def _heal_kernel_cache(kernels, file=None) -> bool:
    """Remove unreadable entries of the kernels' cache (one line each); bypass a cache that cannot
    be written (one line). False when the cache is bypassed (:mod:`quadobs._kernels.cache`)."""
    from quadobs._kernels import cold_kernels
    from quadobs._kernels.cache import bypass, cache_folders, heal, writable

    file = file or sys.stderr
    folders = cache_folders(kernels)
    for line in heal(folders):
        print(f"quadobs: note: {line}", file=file, flush=True)
    if not cold_kernels(kernels):
        return True
    for folder in folders:
        reason = writable(folder)
        if reason is not None:
            bypass()
            print(
                f"quadobs: note: the kernel cache {folder} cannot be written ({reason}); "
                "the kernels are compiled for this run only, uncached",
                file=file,
                flush=True,
            )
            return False
    return True


def _output_paths(args) -> list:
    """The output files and folders named on the command line (removed again if the command fails and they are empty)."""
    from pathlib import Path

    return [
        value
        for name in ("out", "summary", "json", "export", "export_log")
        if isinstance(value := getattr(args, name, None), Path)
    ]


def _cmd_plot(args) -> int:
    """``quadobs plot INPUT --out FIG``: a figure of a run, a campaign folder or the le2013 recording."""
    from quadobs.errors import QuadobsError
    from quadobs.studies.plot import render

    def numbers(text, kind, name):
        try:
            return [kind(v) for v in text.replace("x", ",").split(",") if v.strip()]
        except ValueError:
            raise QuadobsError(
                f"{name}: expected numbers separated by commas, got {text!r}"
            ) from None

    from quadobs.testbed.outputs import check_outputs

    check_outputs(
        {"--out": args.out}, {"input": args.input}
    )  # as run: read-only, devices, the input
    what = None if args.what is None else [w.strip() for w in args.what.split(",") if w.strip()]
    size = None if args.size is None else numbers(args.size, float, "--size")
    samples = None if args.samples is None else numbers(args.samples, int, "--samples")
    out = render(
        args.input,
        args.out,
        what,
        size=size,
        dpi=args.dpi,
        samples=samples,
        legend=not args.no_legend,
        estimators=None
        if args.estimators is None
        else [e.strip() for e in args.estimators.split(",") if e.strip()],
    )
    print(f"figure: {out}")
    return 0


def _parser_classes() -> tuple[type, type]:
    """The parser's help formatter and ``--estimators`` action, made on first use (argparse loads
    only once :func:`main` has taken the signals)."""
    if _PARSER_CLASSES:
        return _PARSER_CLASSES[0]
    import argparse
    import textwrap

    class HelpFormatter(argparse.HelpFormatter):
        """Help text wrapped at spaces only, so that names such as ``augmented-refined`` stay whole."""

        def _split_lines(self, text, width):
            return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

    class EstimatorsOption(argparse._StoreAction):
        """``--estimators``: its help lists the registered names, looked up only when help is shown."""

        @property
        def help(self) -> str:
            try:
                names = ", ".join(sorted(_registered_estimators()))
            except Exception as exc:  # a broken registration must not break --help
                names = f"unavailable ({type(exc).__name__}: {exc})"
            return f"{self._help}; registered: {names}".replace("%", "%%")

        @help.setter
        def help(self, value: str) -> None:
            self._help = value

    _PARSER_CLASSES.append((HelpFormatter, EstimatorsOption))
    return _PARSER_CLASSES[0]


_PARSER_CLASSES: list[tuple[type, type]] = []


def build_parser():
    """The ``argparse.ArgumentParser`` of the command line."""
    import argparse
    import functools

    help_formatter, estimators_option = _parser_classes()
    parser = argparse.ArgumentParser(
        prog="quadobs",
        description="State estimation for systems with quadratic outputs: a MuJoCo testbed.",
        formatter_class=help_formatter,
    )
    parser.add_argument("--version", action="version", version=f"quadobs {package_version()}")
    parser.add_argument(
        "-v",
        "--verbose",
        dest="log_verbose",
        action="count",
        default=0,
        help="the library's progress messages on stderr (-vv: its debugging messages too)",
    )
    parser.add_argument(
        "-q",
        "--quiet",
        dest="log_quiet",
        action="store_true",
        help="errors only: no notices, no library warnings",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser = functools.partial(sub.add_parser, formatter_class=help_formatter)

    _add_list(sub, estimators_option)
    _add_compile(sub, estimators_option)
    _add_run(sub, estimators_option)
    _add_show(sub, estimators_option)
    _add_excitation(sub, estimators_option)
    _add_campaign(sub, estimators_option)
    _add_bench(sub, estimators_option)
    _add_plot(sub, estimators_option)
    _add_replay(sub)
    _add_import_bag(sub)
    _add_import_csv(sub)
    return parser


def _add_list(sub, estimators_option) -> None:
    """The ``list`` subcommand."""
    p = sub.add_parser("list", help="name the built-in scenarios")
    p.set_defaults(func=_cmd_list)


def _add_compile(sub, estimators_option) -> None:
    """The ``compile`` subcommand."""
    p = sub.add_parser(
        "compile",
        help="compile the kernels into the on-disk cache now (side by side), so a first run starts at once",
    )
    p.add_argument(
        "--force", action="store_true", help="compile every kernel, even those already cached"
    )
    p.set_defaults(func=_cmd_compile)


def _add_run(sub, estimators_option) -> None:
    """The ``run`` subcommand."""
    from pathlib import Path

    p = sub.add_parser("run", help="run one episode headless, record it and print a summary")
    p.add_argument(
        "scenario", help="built-in scenario name (see 'quadobs list') or path to a scenario .toml"
    )
    p.add_argument("--out", type=Path, help="recording to write (.rrd)")
    p.add_argument("--summary", type=Path, help="JSON summary to write")
    p.add_argument("--duration", type=float, help="override the scenario duration (s)")
    p.add_argument("--seed", type=int, help="override the scenario seed")
    p.add_argument(
        "--estimators",
        action=estimators_option,
        help="comma-separated estimator names (default: augmented and the scenario's variants; with a TDOA radio, the TDOA estimators)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--runs",
        type=int,
        help="le2013 only: number of seeded runs (default 50; --duration is the number of samples)",
    )
    p.add_argument(
        "--export-log",
        type=Path,
        metavar="DIR",
        help="also write the run as a log folder in the open format (ranges, accelerometer, truth), for 'quadobs replay'",
    )
    p.add_argument(
        "--fail-on-crash",
        action="store_true",
        help=f"exit with status {EXIT_CRASHED} when the quadrotor crashed (for scripts and CI)",
    )
    _add_set(p)
    p.set_defaults(func=_cmd_run)


def _add_show(sub, estimators_option) -> None:
    """The ``show`` subcommand."""
    p = sub.add_parser(
        "show", help="print a scenario's TOML after any --set overrides (or the field reference)"
    )
    p.add_argument(
        "scenario",
        nargs="?",
        help="built-in scenario name (see 'quadobs list') or path to a scenario .toml",
    )
    p.add_argument(
        "--reference",
        action="store_true",
        help="print the field reference of the scenario schema (Markdown)",
    )
    _add_set(p)
    p.set_defaults(func=_cmd_show)


def _add_excitation(sub, estimators_option) -> None:
    """The ``excitation`` subcommand."""
    from pathlib import Path

    p = sub.add_parser(
        "excitation",
        help="persistence-of-excitation report of a scenario's input (Gramian measure, Propositions 4-8), without the physics",
    )
    p.add_argument("scenario", help="built-in scenario name or path to a scenario .toml")
    p.add_argument(
        "--window",
        type=float,
        help="window length delta (s); default: the scenario's excitation.window",
    )
    p.add_argument(
        "--step", type=float, help="hold step of the input (s); default: the monitor's (0.01 s)"
    )
    p.add_argument("--json", type=Path, help="also write the report as JSON")
    _add_set(p)
    p.set_defaults(func=_cmd_excitation)


def _add_campaign(sub, estimators_option) -> None:
    """The ``campaign`` subcommand."""
    from pathlib import Path

    p = sub.add_parser(
        "campaign",
        help="Monte Carlo: many seeded runs in parallel (local processes or a Dask cluster), statistics and the Cramér-Rao bound",
        description="Exit status: 0 when every run completed, 1 when some failed (they are listed), 2 on bad input, 130 on Ctrl-C.",
    )
    p.add_argument(
        "scenario", help="built-in scenario name (see 'quadobs list') or path to a scenario .toml"
    )
    p.add_argument("--runs", type=int, required=True, help="number of seeded runs")
    p.add_argument(
        "--estimators",
        action=estimators_option,
        help="comma-separated estimator names (e.g. augmented,ekf,ukf)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="folder for summary.json, runs.parquet, series.parquet, statistics.rrd",
    )
    p.add_argument(
        "--scheduler",
        help="Dask distributed scheduler address (tcp://host:port); default: local processes",
    )
    p.add_argument(
        "--workers",
        type=int,
        help="local processes (default: the number of CPUs; 0: in this process)",
    )
    p.add_argument(
        "--every",
        type=float,
        help="sampling period (s) of the statistics over time (default about 0.1 s)",
    )
    p.add_argument(
        "--retries",
        type=int,
        default=2,
        help="local processes: restarts of a run whose worker was lost (default 2)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=1.0,
        help="final position error (m) under which a run has converged (default 1)",
    )
    p.add_argument(
        "--confidence",
        type=float,
        default=0.95,
        help="of the two-sided chi-square NEES/NIS intervals (default 0.95)",
    )
    p.add_argument("--duration", type=float, help="override the scenario duration (s)")
    p.add_argument(
        "--seed", type=int, help="override the scenario seed (the runs' seeds derive from it)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--resume",
        action="store_true",
        help="keep the runs a stopped campaign into the same --out finished, run only the others",
    )
    _add_set(p)
    p.set_defaults(func=_cmd_campaign)


def _add_bench(sub, estimators_option) -> None:
    """The ``bench`` subcommand."""
    from pathlib import Path

    p = sub.add_parser(
        "bench",
        help="measure the estimators' cost beside the physics (single vehicle, batch, scaling)",
    )
    p.add_argument("--json", type=Path, help="write the figures to this JSON file")
    p.add_argument(
        "--steps",
        type=int,
        default=20000,
        help="physics steps per single-vehicle run (default 20000)",
    )
    p.add_argument(
        "--repeats",
        type=int,
        default=5,
        help="repeats of each measurement; medians are reported (default 5)",
    )
    p.add_argument("--batch", type=int, default=1000, help="vehicles in the batch (default 1000)")
    p.add_argument("--batch-steps", type=int, default=200, help="steps per batch run (default 200)")
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="threads for the batch: MuJoCo's rollout and the observers (default 0: calling thread)",
    )
    p.add_argument("--quick", action="store_true", help="a small scaling table")
    p.add_argument(
        "--no-cold-start",
        action="store_true",
        help="skip the first run on a fresh kernel cache (it compiles every kernel twice)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=_cmd_bench)


def _add_plot(sub, estimators_option) -> None:
    """The ``plot`` subcommand."""
    from pathlib import Path

    p = sub.add_parser(
        "plot",
        help="draw a figure (PNG, PDF, SVG) of a run's .rrd, a campaign folder or the le2013 recording (needs quadobs[plot])",
        description="Panels (--what, comma-separated): "
        "run .rrd: paths, paths3d, position, velocity, wind, ranges, covariance, nis, bounds, excitation; "
        "campaign folder: rmse, rmse-velocity, converged, nees, nis, final; "
        "le2013 .rrd: sets, width-x1, width-x2, volume, bounds. "
        "Default size 7.0x4.5 in (two-column paper width; 3.5x2.6 for one column).",
    )
    p.add_argument(
        "input",
        type=Path,
        help="a run's .rrd, a campaign folder (or its statistics.rrd), or the le2013 .rrd",
    )
    p.add_argument("--out", type=Path, required=True, help="figure file: .png, .pdf or .svg")
    p.add_argument(
        "--what", help="comma-separated panels (default: the input's usual figure; names above)"
    )
    p.add_argument("--size", help="WIDTHxHEIGHT in inches (default 7.0x4.5)")
    p.add_argument("--dpi", type=float, help="dots per inch of a PNG (default 150)")
    p.add_argument(
        "--samples",
        help="le2013 sets: comma-separated samples k to draw (default: one early, the last)",
    )
    p.add_argument("--no-legend", action="store_true", help="no legends")
    p.add_argument(
        "--estimators",
        help="comma-separated: only these estimators (a campaign's methods) in every panel, in this order",
    )
    p.set_defaults(func=_cmd_plot)


def _add_replay(sub) -> None:
    """The ``replay`` subcommand (:mod:`quadobs.testbed.logs`)."""
    from pathlib import Path

    p = sub.add_parser(
        "replay",
        help="replay a logged range-only run (a log folder, or plaza1/plaza2) through the estimators",
    )
    p.add_argument(
        "log",
        help="log folder (meta.csv, beacons.csv, ranges.csv or tdoa.csv[, inputs.csv or imu.csv][, attitude.csv][, truth.csv]; docs/replaying-your-data.md) or plaza1, plaza2",
    )
    p.add_argument("--out", type=Path, help="recording to write (.rrd)")
    p.add_argument("--summary", type=Path, help="JSON summary to write")
    p.add_argument(
        "--estimators",
        help="comma-separated names (default: chosen from the log, docs/replay.md; isam2: the GTSAM peer)",
    )
    p.add_argument(
        "--export", type=Path, help="write the log in the open format to this folder and stop"
    )
    p.add_argument(
        "--model",
        choices=("odometry", "cv", "imu"),
        help="vehicle model (default: odometry for an odometry log, imu for an accelerometer log)",
    )
    p.add_argument("--dt", type=float, default=0.1, help="replay grid step in s (default 0.1)")
    p.add_argument(
        "--initial-offset",
        type=float,
        default=50.0,
        help="initial guess this far (m) from the truth at t0 (default 50)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="draws the direction of the initial offset and the sensor layer's noise (default 0)",
    )
    p.add_argument(
        "--calibrate",
        choices=("self", "none"),
        default="self",
        help="range biases and the model's process noise: self-calibrated from the log, never its truth (default), or none",
    )
    p.add_argument(
        "--biases",
        help="comma-separated range bias per beacon (m), in beacons.csv order (overrides --calibrate)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--tune",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="the estimators' noise settings: range_sigma, q_xy, q_theta, q_acc, q_imu, gate (a number or none), P0, range_bias (1: the peer's bias per anchor as a state), q_xy_heading, velocity_std (m/s, or log: the velocity the log's start tells, where it tells one), nlos_prior (the excess mixture's stationary probability of a blocked path, in (0, 1)), steady_test (1: ekf-bias-imu-nlos takes a block of ranges read blocked as steady as the noise for its bias's error, the default; 0: off), bias_prior (m: the range biases' prior in the filters that hold them as states, 0.5 by default; log: the spread of the self-calibration's biases), stated_heights (1: ukf-height-lever starts from the heights an odometry log states, the default; 0: from a storey's prior), anchor_sigma (1: a log stating no std gives each range its anchor's own noise read from its ranges, the default; 0: one figure pooled over the anchors), stated_std (1: the std that ranges.csv states is kept on every anchor; 0, the default: an anchor whose stated std lies more than 5 times from its ranges' own noise takes that noise), tag_pattern (1: ukf-height-lever holds the tag's direction-dependent delay as states; 0: not; by default the self-calibration decides by held-out ranges) (repeatable)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="noise.FIELD=VALUE",
        help="sensor layer on the logged ranges, e.g. noise.dropout=0.3 (noise.* fields only; default: the log as it is)",
    )
    p.add_argument(
        "--burn-in",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="take the RMSE and the maximum error from this many seconds after the start (default 0)",
    )
    p.add_argument(
        "--export-tum",
        type=Path,
        metavar="DIR",
        help="write the truth and each estimator's positions as TUM files (truth.tum, NAME.tum) for evo_ape",
    )
    _add_clock_offset(p)
    p.set_defaults(func=_cmd_replay)


def _add_clock_offset(p) -> None:
    """``replay --clock-offset`` (:func:`_replay_clock_offset`)."""
    p.add_argument(
        "--clock-offset",
        type=_clock_offset_value,
        default=0.0,
        metavar="SECONDS|auto",
        help="the inputs (IMU, odometry) stamped this many seconds late against the ranges: moved onto the ranges' clock for every estimator; auto: searched from the log's held-out ranges (default 0)",
    )


def _clock_offset_value(text: str) -> float | str:
    """``--clock-offset``: ``auto`` or a finite number of seconds."""
    import argparse
    import math

    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds or auto, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds, got {text!r}")
    return value


def _cmd_replay(args) -> int:
    """``quadobs replay LOG``: export the log, or replay it and print one row per estimator."""
    from quadobs.testbed.logs import open_log

    _check_replay_numbers(args)
    log = open_log(args.log)
    if args.export is not None:
        return _replay_export(args, log)
    import time

    from quadobs.testbed.logs.replay import log_scenario, run_replay
    from quadobs.testbed.outputs import check_outputs

    check_outputs(
        {"--out": args.out, "--summary": args.summary}, _log_inputs(log)
    )  # before the calibration's replays
    log_scenario(log, args.dt, args.seed, args.set)  # the --set settings, checked as early
    _check_field_options(args)
    _notice_cold_kernels(EPISODE_KERNELS + AUGMENTED_KERNELS)
    from quadobs.testbed.logs.replay import (
        check_burn_in,
        check_clock_overlap,
        check_replay,
        replayable_log,
    )

    given = args.clock_offset if isinstance(args.clock_offset, float) else 0.0
    check_clock_overlap(log, inputs=not given)  # a file on another clock (given: moved later)
    check_burn_in(log, args.burn_in)  # a burn-in past the log or its truth: nothing to score
    log, notes = replayable_log(  # --biases: one each
        log, keep_anchors=args.biases is not None, clock_offset=given
    )
    log, options, noise_note = _replay_noise(args, log)
    for note in [*notes, noise_note] if noise_note else notes:
        print(note)

    check_replay(  # the model and the estimators against the log, before the calibration
        log, _estimator_list(args.estimators), dt=args.dt, model=args.model, options=options
    )
    started = time.perf_counter()
    log = _replay_clock_offset(args, log, dict(options))
    biases, tuning = _replay_calibration(args, log, dict(options))
    if (
        getattr(args, "calibration_report", None) is not None
    ):  # the summary's wall_time is the replay's
        args.calibration_report["seconds"] = time.perf_counter() - started
    stop_if_interrupted()
    summary = run_replay(
        log,
        estimators=_estimator_list(args.estimators),
        dt=args.dt,
        model=args.model,
        initial_offset=args.initial_offset,
        seed=args.seed,
        biases=biases,
        out=args.out,
        summary_path=args.summary,
        progress=not args.no_progress,
        settings=args.set,
        setup_options=tuning,
        burn_in=args.burn_in,
        export_tum=args.export_tum,
        calibration=getattr(args, "calibration_report", None),
        as_logged=getattr(args, "as_logged", ()),
    )
    _print_replay_rows(summary, log)
    print_diverged(summary)
    if args.summary:
        print(f"summary: {args.summary}")
    if summary["interrupted"]:
        return 130
    return diverged_status(summary, _estimator_list(args.estimators))


def _replay_noise(args, log) -> tuple:
    """``(log, options, note)`` of ``quadobs replay``: the ``--tune`` settings, and each
    anchor's own range noise where the log states none
    (:func:`~quadobs.testbed.logs.range_noise.with_anchor_noise`), but on the grid
    (``--set noise.*``), where every range takes the one figure ``range_sigma``."""
    from quadobs.testbed.logs.estimators import parse_tuning
    from quadobs.testbed.logs.range_noise import (
        OWN_NOISE_KINDS,
        stated_std_note,
        with_anchor_noise,
    )

    options = parse_tuning(args.tune)
    if not args.set:
        return with_anchor_noise(log, options)
    own = log.input_kind in OWN_NOISE_KINDS  # else replayable_log said it
    return log, options, stated_std_note(log) if own else None


def _print_replay_rows(summary: dict, log) -> None:
    """The replay's log line and one row per estimator (its RMSE, or why it has none)."""
    m = summary["measurements"]
    print(
        f"log {summary['log']}: {summary['duration']:.1f} s, {summary['ranges']['placed']} ranges, model {summary['model']}"
        + (
            f", {m['dropped']} dropped, {m['outliers_injected']} outliers injected"
            if m["dropped"] or m["outliers_injected"]
            else ""
        )
        + _outside_inputs(summary["ranges"], log.beacons.shape[0])
        + _heights_note(log, summary["noise"])
        + ("  [INTERRUPTED]" if summary["interrupted"] else "")
    )
    width = max([10, *(len(n) for n in summary["estimators"])])
    burn_in = float(summary.get("burn_in") or 0.0)
    after = f"rmse after {burn_in:g} s" if burn_in > 0.0 else "rmse"
    for name, e in summary["estimators"].items():
        extra = (
            f"  batch LM rmse {_fmt(e['batch_rmse'], ' m')}"
            if e.get("batch_rmse") is not None
            else ""
        )
        if e.get("diverged"):
            print(f"  {name:{width}s} rmse invalid (diverged)")
            continue
        if e.get("startup"):
            extra += "  [no start-up fix: ran from its prior]"
        if e.get("same_as"):
            extra += f"  [the same filter as {e['same_as']['estimator']}: {e['same_as']['reason']}]"
        if not summary["has_truth"]:  # "never" would read as never converged
            us = e["seconds_per_measurement"] * 1e6
            print(
                f"  {name:{width}s} no error measured (the log has no truth.csv)  {us:.0f} us/range"
            )
            continue
        if e.get("within_extent") is False:
            extra += (
                f"  [final error larger than the anchors' extent, {summary['anchor_extent']:.3g} m]"
            )
        print(
            f"  {name:{width}s} {after} {_fmt(e['rmse'], ' m')}  max {_fmt(e['max_error'], ' m')}  "
            f"final {_fmt(e['final_position_error'], ' m')}  {e['seconds_per_measurement'] * 1e6:.0f} us/range{extra}"
            + _field_split(e)
        )


def _replay_export(args, log) -> int:
    """``quadobs replay LOG --export DIR``: the log written in the open format, and stop."""
    from quadobs.testbed.logs import write_log
    from quadobs.testbed.outputs import check_output_folder, write_folder_staged

    _refuse_with_export(args)
    check_output_folder(args.export, _log_folder_files(), "--export")
    write_folder_staged(
        args.export, lambda tmp: write_log(log, tmp), "--export", set(_log_folder_files())
    )
    print(
        f"log {log.name}: {log.ranges.shape[0]} ranges, {log.inputs.shape[0]} inputs written to {args.export}"
    )
    return 0


#: Largest magnitude of a ``--tune`` value (squares and products of it stay finite).
TUNE_MAX = 1e12


def _check_replay_numbers(args) -> None:
    """``--dt`` finite and positive, ``--initial-offset`` finite, ``--biases`` finite numbers, ``--tune``
    values finite and within :data:`TUNE_MAX`: one-line errors before the log is read."""
    import math

    from quadobs.errors import QuadobsError

    if not (math.isfinite(args.dt) and args.dt >= 1e-6):
        raise QuadobsError(
            f"--dt: the replay grid step must be a number of seconds of at least 1e-06, got {args.dt:g}"
        )
    if not math.isfinite(args.initial_offset):
        raise QuadobsError(
            f"--initial-offset: expected a finite distance (m), got {args.initial_offset:g}"
        )
    for text in (args.biases or "").split(",") if args.biases is not None else ():
        try:
            value = float(text)
        except ValueError:
            continue  # the calibration names a value that is not a number
        if not math.isfinite(value):
            raise QuadobsError(f"--biases: {text.strip()!r} is not a finite number (m)")
    for text in args.set:
        path = text.partition("=")[0].strip()
        if not path.startswith("noise.") or path == "noise.":
            raise QuadobsError(
                f"--set: {path}: does not apply to a replay (only noise.* settings do)"
            )
    for text in args.tune:
        key, _, raw = text.partition("=")
        try:
            value = float(raw)
        except ValueError:
            continue  # parse_tuning names it
        if not (math.isfinite(value) and abs(value) <= TUNE_MAX):
            raise QuadobsError(
                f"--tune {key.strip()}: expected a finite number of magnitude at most {TUNE_MAX:g}, got {raw.strip()!r}"
            )
    from quadobs.testbed.logs.estimators import FROM_LOG, parse_tuning

    spread = parse_tuning(args.tune).get("bias_prior") == FROM_LOG  # the last one given
    if spread and (args.biases is not None or args.calibrate == "none"):
        raise QuadobsError(
            "--tune bias_prior=log: the biases' spread comes from the self-calibration, "
            f"which {'--biases' if args.biases is not None else '--calibrate none'} turns off"
        )


def _refuse_with_export(args) -> None:
    """``replay --export`` writes the log and stops: the options of a replay are refused beside it."""
    from quadobs.errors import QuadobsError

    for flag in ("out", "summary", "estimators", "biases", "model"):
        if getattr(args, flag) is not None:
            raise QuadobsError(
                f"--{flag}: does not apply with --export, which writes the log folder and stops"
            )
    if args.tune or args.set:
        raise QuadobsError(
            f"--{'tune' if args.tune else 'set'}: does not apply with --export, which writes the log folder and stops"
        )
    if args.clock_offset != 0.0:  # a number or auto: the log is written as it is
        raise QuadobsError(
            "--clock-offset: does not apply with --export, which writes the log folder as it is and stops"
        )


def _log_folder_files() -> tuple[str, ...]:
    """The files of a log folder (:data:`quadobs.testbed.logs.format.LOG_FILES`), ``meta.csv`` included."""
    from quadobs.testbed.logs.format import LOG_FILES

    return tuple(LOG_FILES)


def _log_inputs(log) -> dict:
    """Every file of the log's folder, as inputs no output may name."""
    from pathlib import Path

    from quadobs.testbed.logs.format import LOG_FILES

    return {f"log {f}": Path(log.source) / f for f in LOG_FILES} if log.source else {}


def _outside_inputs(counts: dict, anchors: int) -> str:
    """The measurements a replay left out, before the inputs' first sample or after the grid's
    last step, for its printed head line; after the end, only more than one round of the
    anchors (the grid ends within a step of the log's end, and leaves out that step's ranges)."""
    before, after = counts.get("before_the_first_input", 0), counts.get("after_the_last_step", 0)
    parts = [f"{before} before the first input"] if before else []
    if after > anchors:
        parts.append(f"{after} after the last step")
    return f" ({' and '.join(parts)}: not replayed)" if parts else ""


def _heights_note(log, noise: dict) -> str:
    """For the replay's head line: whether a planar log's stated anchor heights are used
    (``noise``: the summary's, where ``offsets`` is None once set aside)."""
    import math

    if getattr(log, "anchor_heights", None) is None:
        return ""
    if not math.isfinite(log.tag_height):
        return "; anchors' heights stated without meta.csv tag_height: not used"
    if noise.get("offsets") is None:
        return f"; anchors' heights stated, the tag at {log.tag_height:g} m: set aside"
    return (
        f"; anchors' heights stated, the tag at {log.tag_height:g} m: used by ukf-height-lever "
        "(the other filters of the plane take the ranges as planar, or hold the heights as states)"
    )


def _check_field_options(args) -> None:
    """``--burn-in`` and ``--export-tum`` checked before the calibration's replays."""
    import math

    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.figures import check_tum_folder

    if not (math.isfinite(args.burn_in) and args.burn_in >= 0.0):
        raise QuadobsError(
            f"--burn-in: expected a non-negative number of seconds, got {args.burn_in}"
        )
    check_tum_folder(args.export_tum, (args.out, args.summary))


def _field_split(e: dict) -> str:
    """The horizontal and vertical RMSE of a 3-D replay, for its printed row."""
    if e.get("rmse_vertical") is None:
        return ""
    return f"  (horizontal {_fmt(e['rmse_horizontal'], ' m')}, vertical {_fmt(e['rmse_vertical'], ' m')})"


def _add_import_bag(sub) -> None:
    """The ``import-bag`` subcommand (:mod:`quadobs.testbed.logs.rosbag`)."""
    from pathlib import Path

    p = sub.add_parser(
        "import-bag",
        help="import a ROS 1 or ROS 2 bag (IMU or wheel odometry, pose truth, ranges, TDOA) as a log folder for 'quadobs replay'",
    )
    p.add_argument("bag", type=Path, help="a ROS 1 .bag file or a ROS 2 bag folder")
    p.add_argument(
        "--out", type=Path, required=True, help="the log folder to write (written whole)"
    )
    p.add_argument(
        "--map", type=Path, help="TOML topic map: streams, their topics and fields, anchors"
    )
    p.add_argument(
        "--topic",
        action="append",
        default=[],
        metavar="STREAM=TOPIC",
        help="a stream's topic (imu, odometry, truth, ranges, tdoa); repeated for one stream: each of its "
        "topics (e.g. one per anchor); over the --map file's",
    )
    p.add_argument("--anchors", type=Path, help="anchor positions: a CSV file id,x,y[,z]")
    p.add_argument("--name", help="the log's name (default: the map's, else the bag's)")
    p.set_defaults(func=_cmd_import_bag)


def _cmd_import_bag(args) -> int:
    """``quadobs import-bag BAG --out DIR``: a bag as a log folder."""
    from quadobs.testbed.logs import write_log
    from quadobs.testbed.logs.files import check_replaceable_folder
    from quadobs.testbed.logs.format import LOG_FILES
    from quadobs.testbed.logs.rosbag import TopicMap, import_bag, load_topic_map, with_options

    check_replaceable_folder(args.out, set(LOG_FILES), "--out")
    topic_map = load_topic_map(args.map) if args.map is not None else TopicMap()
    topic_map = with_options(topic_map, args.topic, args.anchors, args.name)
    notes: list[str] = []
    log = import_bag(args.bag, topic_map, notes)
    notes += _check_imported(log, str(args.bag))
    write_log(log, args.out)
    _print_imported(log, notes, args.out)
    return 0


def _add_import_csv(sub) -> None:
    """The ``import-csv`` subcommand (:mod:`quadobs.testbed.logs.csv_map`)."""
    from pathlib import Path

    p = sub.add_parser(
        "import-csv",
        help="import CSV files of another layout (columns and units named in a TOML map) as a log folder for 'quadobs replay'",
        description="Import CSV files as a log folder. The TOML map names, per stream (ranges, "
        "tdoa, imu, attitude, odometry, truth), the file, its columns and their units, the "
        "anchors, and meta.csv's keys; docs/replaying-your-data.md has examples.",
    )
    p.add_argument("map", type=Path, help="the TOML column map (its files are found beside it)")
    p.add_argument(
        "--out", type=Path, required=True, help="the log folder to write (written whole)"
    )
    p.add_argument("--name", help="the log's name (default: the map's name, else its file's)")
    p.set_defaults(func=_cmd_import_csv)


def _cmd_import_csv(args) -> int:
    """``quadobs import-csv MAP --out DIR``: CSV files as a log folder."""
    from dataclasses import replace

    from quadobs.testbed.logs import write_log
    from quadobs.testbed.logs.csv_map import import_csv, load_csv_map
    from quadobs.testbed.logs.files import check_replaceable_folder
    from quadobs.testbed.logs.format import LOG_FILES

    check_replaceable_folder(args.out, set(LOG_FILES), "--out")
    csv_map = load_csv_map(args.map)
    if args.name is not None:
        csv_map = replace(csv_map, meta={**csv_map.meta, "name": args.name})
    notes: list[str] = []
    log = import_csv(csv_map, notes)
    notes += _check_imported(log, str(args.map), csv_map.in_its_names)
    write_log(log, args.out)
    _print_imported(log, notes, args.out)
    return 0


def _check_imported(log, source: str, rename=None) -> list[str]:
    """The replay's checks of units, run on an imported log before it is written (a unit the
    map or topic map got wrong is refused at once, naming the source; a body IMU's attitude,
    given or estimated, must keep gravity vertical), and the notes the replay would print
    (ranges of 0 m, the truth against the ranges and the odometry)."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.attitude import check_body_imu, navigation_accelerations
    from quadobs.testbed.logs.range_noise import with_anchor_noise
    from quadobs.testbed.logs.replay import (
        check_odometry_units,
        check_range_units,
        check_truth_units,
        replayable_log,
    )

    try:
        prepared, notes = replayable_log(log)
        noise = with_anchor_noise(prepared, {})[2]  # the stated std as the replay will judge it
        notes += [noise] if noise and noise.startswith("ranges.csv") else []
        check_range_units(prepared)
        check_truth_units(prepared)
        if prepared.input_kind == "odometry":
            check_odometry_units(prepared)
        if prepared.input_kind == "imu_body":
            check_body_imu(prepared)
            navigation_accelerations(prepared)  # gravity held vertical by the attitude
    except QuadobsError as exc:
        said = rename(str(exc)) if rename else str(exc)
        raise QuadobsError(f"{source}: as imported, the replay would refuse it: {said}") from None
    return [f"(replay) {rename(n) if rename else n}" for n in notes]


def _print_imported(log, notes: list[str], out) -> None:
    """The notes of an import and what it wrote."""
    for note in notes:
        print(f"note: {note}")
    print(
        f"log {log.name}: {log.ranges.shape[0]} ranges, {log.tdoa.shape[0]} TDOA, "
        f"{log.inputs.shape[0] if log.input_kind != 'none' else 0} "
        f"{'odometry' if log.input_kind == 'odometry' else 'IMU'} rows, "
        f"{0 if log.truth is None else log.truth.shape[0]} truth rows "
        f"written to {out} (replay with: quadobs replay {out})"
    )


def _replay_calibration(args, log, tuning: dict) -> tuple[list[float] | np.ndarray | None, dict]:
    """The biases and the noise settings: ``--biases`` as given, else self-calibrated (``--calibrate self``) or none.

    The self-calibration also picks the process noise (each intensity of
    :func:`~quadobs.testbed.logs.calibration.noise_keys`), unless ``--tune`` sets it.
    """
    import math

    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.calibration import calibrate, noise_keys

    if args.biases is not None:
        try:
            biases: list[float] | np.ndarray = [float(v) for v in args.biases.split(",")]
        except ValueError:
            raise QuadobsError(
                f"--biases: expected comma-separated numbers, got {args.biases!r}"
            ) from None
        if not all(math.isfinite(b) for b in biases):
            raise QuadobsError(f"--biases: every bias must be a finite number, got {args.biases!r}")
        if len(biases) != log.beacons.shape[0]:
            raise QuadobsError(f"--biases: {len(biases)} values for {log.beacons.shape[0]} beacons")
        return biases, tuning
    if args.calibrate == "none":
        return None, tuning
    keys = noise_keys(log, args.model)  # an intensity fixed by --tune is not calibrated
    if not args.no_progress:  # minutes on a long log, and nothing else printed meanwhile
        print(
            f"calibrating from the log's {log.ranges.shape[0] + log.tdoa.shape[0]} "
            "measurements: replays scored on held-out ones (--calibrate none skips them)",
            file=sys.stderr,
            flush=True,
        )
    cal = calibrate(  # the prior: the log's own defaults (log_defaults) below --tune
        log, dt=args.dt, model=args.model, setup_options=tuning,
        noise=tuple(k for k in keys if k not in tuning),
    )  # fmt: skip
    from quadobs.testbed.logs.calibration import estimator_biases
    from quadobs.testbed.logs.replay import default_estimators

    names = _estimator_list(args.estimators) or default_estimators(log, args.model)
    args.as_logged = estimator_biases(log, cal, names, dt=args.dt, model=args.model)
    from quadobs.testbed.logs.constants_start import estimator_constants

    if not args.set:  # measurements on the grid (noise.*): every filter takes the biases
        estimator_constants(log, cal, names, dt=args.dt, model=args.model)
    chosen = "none" if cal.biases is None else ", ".join(f"{b:.2f}" for b in cal.biases) + " m"
    print(f"calibrated from the log: biases {chosen}" + _reason_lines(cal.reason))
    args.calibration_report = {**cal.summary(), **getattr(args, "clock_report", {})}
    if "clock_offset" in args.calibration_report:  # the offset's reason first, as it came first
        clock = args.calibration_report["clock_offset"]["reason"]
        args.calibration_report["reason"] = f"{clock}; {cal.reason}"
    return None if cal.biases is None else [float(b) for b in cal.biases], cal.options


def _reason_lines(reason: str) -> str:
    """A calibration's reason, its clauses (``; `` apart, outside brackets) one per line."""
    clauses, depth, start = [], 0, 0
    for i, ch in enumerate(reason):
        depth += (ch in "([") - (ch in ")]")
        if depth == 0 and reason.startswith("; ", i):
            clauses.append(reason[start:i])
            start = i + 2
    clauses.append(reason[start:])
    return "".join(f"\n  - {c}" for c in clauses if c)


def _replay_clock_offset(args, log, tuning: dict):
    """The log with its inputs moved onto the ranges' clock by ``--clock-offset``: as given, or
    (``auto``) searched from the log (:mod:`quadobs.testbed.logs.clock_offset`); the choice and
    its reason kept for the summary's ``calibration``."""
    from quadobs.testbed.logs.clock_offset import (
        ClockOffset,
        estimate_clock_offset,
        with_input_offset,
    )

    if args.clock_offset == 0.0:
        return log
    if log.input_kind == "none":
        from quadobs.errors import QuadobsError

        raise QuadobsError(f"--clock-offset: {log.name} holds no inputs to move against its ranges")
    if args.clock_offset == "auto":
        from quadobs.testbed.logs.estimators import log_defaults
        from quadobs.testbed.worlds.replay import default_model

        options = {**log_defaults(log), **tuning}
        found = estimate_clock_offset(
            log, dt=args.dt, model=args.model or default_model(log), setup_options=options
        )
        print(f"calibrated from the log: {found.reason}")
    else:
        tau = float(args.clock_offset)
        found = ClockOffset(
            tau, tau, 0.0, reason=f"clock offset of the inputs {tau * 1e3:+.1f} ms: given"
        )
    args.clock_report = {"clock_offset": found.summary() | {"reason": found.reason}}
    args.calibration_report = {**args.clock_report, "reason": found.reason}
    moved = with_input_offset(log, found.offset)
    if found.offset:
        _check_moved_span(args, moved, found.offset)
    return moved


def _check_moved_span(args, moved, tau: float) -> None:
    """Refuse, before the calibration, an offset ``tau`` (s) whose moved inputs' span holds no
    measurement of the log, or, self-calibrated, fewer held-out ranges than the calibration's
    paired test needs (:data:`~quadobs.testbed.logs.clock_offset.HELD_MIN`)."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.calibration import SCORED_FROM, scored_kind
    from quadobs.testbed.logs.clock_offset import HELD_MIN, held_out_count

    table = moved.ranges if scored_kind(moved) == "range" else moved.tdoa
    t0, t1 = moved.start, moved.end
    t = table[(table[:, 0] >= t0) & (table[:, 0] <= t1), 0]
    span = f"--clock-offset {tau:g}: the inputs moved to {t0:.3f} .. {t1:.3f} s hold {t.size} of the log's {table.shape[0]} {scored_kind(moved)} measurements"
    if t.size == 0:
        raise QuadobsError(f"{span}; none is left to replay")
    held = held_out_count(t, t0 + SCORED_FROM * (t1 - t0))
    if args.biases is None and args.calibrate == "self" and held < HELD_MIN:
        raise QuadobsError(
            f"{span}: too few for the self-calibration ({held} held out and scored, its paired test needs {HELD_MIN}; --calibrate none replays them)"
        )


#: The options whose value may start with a minus sign (a list of numbers such as ``-0.2,0.1``).
NEGATIVE_VALUE_OPTIONS = ("--biases",)


def negative_values(argv: list[str]) -> list[str]:
    """``argv`` with ``--biases -0.2,0.1`` written ``--biases=-0.2,0.1``.

    argparse takes a value that starts with ``-`` for an option unless it is one plain negative
    number, so a list of numbers whose first is negative would leave the option without its
    value; joined to the option with ``=``, it is read as written. Only a value starting with
    ``-`` and a digit or ``.`` is joined (no option is spelled so); nothing after ``--`` is.
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        token = argv[i]
        if token == "--":
            return out + list(argv[i:])
        following = argv[i + 1] if i + 1 < len(argv) else ""
        if token in NEGATIVE_VALUE_OPTIONS and len(following) > 1 and following[0] == "-":
            if following[1].isdigit() or following[1] == ".":
                out.append(f"{token}={following}")
                i += 2
                continue
        out.append(token)
        i += 1
    return out


def _run_command(argv: list[str] | None) -> int:
    """Parse ``argv`` and run its command: the exit status, the error printed on one line.

    A ``KeyboardInterrupt`` propagates (:func:`main` answers it), as does an error made of
    one (:func:`quadobs.errors.caused_by_interrupt`: an import cut short by Ctrl-C, say);
    so does ``SystemExit`` from the parser's usage errors, ``--help`` and ``--version``.
    """
    from quadobs.errors import (
        QuadobsError,
        RunFault,
        caused_by_interrupt,
        new_folders_removed_on_failure,
    )

    args = build_parser().parse_args(negative_values(sys.argv[1:] if argv is None else argv))
    too_little = _address_space_too_small()
    if too_little:  # before NumPy, Numba or rerun load: below the floor they abort the process
        print(f"quadobs: error: {too_little}", file=sys.stderr)
        return 1
    handler = _log_to_stderr(args.log_verbose, args.log_quiet)
    try:
        with new_folders_removed_on_failure(*_output_paths(args)):
            return _without_exit(args.func, args)
    except Exception as exc:
        if caused_by_interrupt(exc):
            raise KeyboardInterrupt from exc
        if isinstance(
            exc, (RunFault, QuadobsError)
        ):  # a run that could not go on (1), bad input (2)
            print(f"quadobs: error: {exc}", file=sys.stderr)
            return 1 if isinstance(exc, RunFault) else 2
        if _out_of_resources(exc):  # ulimit -n, ulimit -v: the system refused, the run stopped (1)
            print(f"quadobs: error: {_out_of_resources(exc)}", file=sys.stderr)
            return 1
        if isinstance(exc, BrokenPipeError):  # output piped into a reader that stopped (e.g. head)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return 141
        if os.environ.get("QUADOBS_TRACEBACK"):
            raise
        # anything else (a plugin's estimator raising mid-run, a fault of quadobs): one line, status 1
        text = str(exc).splitlines()[0] if str(exc) else ""
        print(
            f"quadobs: error: unexpected {type(exc).__name__}: {text[:300]} "
            "(the run stopped; QUADOBS_TRACEBACK=1 shows where)",
            file=sys.stderr,
        )
        return 1

    finally:
        import logging

        logger = logging.getLogger("quadobs")
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)


def _log_to_stderr(verbose: int, quiet: bool):
    """The handler that shows the library's log records on stderr for one command (removed after it).

    Default: warnings and notices; ``-v``: progress (INFO); ``-vv``: DEBUG; ``-q``: errors only.
    Nothing is configured on ``import quadobs``: this is the command line's choice.
    """
    import logging

    class OneLine(logging.Formatter):
        """The command's own notices as they are; the library's records named by their level."""

        def format(self, record: logging.LogRecord) -> str:
            text = " ".join(record.getMessage().splitlines())
            if record.name == "quadobs.cli":
                return text
            return f"quadobs: {record.levelname.lower()}: {text}"

    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO)[min(verbose, 1)]
    if verbose >= 2 and not quiet:
        level = logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(OneLine())
    for name, known in logging.root.manager.loggerDict.items():  # a library's dictConfig (dask's)
        if name.startswith("quadobs") and isinstance(known, logging.Logger):  # may disable them
            known.disabled = False
    logger = logging.getLogger("quadobs")
    logger.addHandler(handler)
    logger.setLevel(level)
    return handler


#: Least address space (``ulimit -v``) a command starts with. Below it NumPy's OpenBLAS, rerun or
#: a thread's stack fail to be mapped inside native code, which ends the process with its own
#: message (status 1, 134 or 255) instead of an error quadobs can report: measured with ``run
#: ifac2021 --duration 0.2`` on a 2-core machine, 0.6 to 1.8 GB aborted so, 2.2 GB ended with
#: the one-line "out of memory", 2.6 GB and more ran.
MIN_ADDRESS_SPACE = 2 << 30


def _address_space_too_small() -> str | None:
    """One line when ``ulimit -v`` is below :data:`MIN_ADDRESS_SPACE`, else ``None``."""
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY or soft >= MIN_ADDRESS_SPACE:
        return None
    return (
        f"the address space is limited to {soft >> 20} MiB (ulimit -v); quadobs needs at least "
        f"{MIN_ADDRESS_SPACE >> 20} MiB (NumPy, Numba and rerun abort below it); nothing was run"
    )


def _out_of_resources(exc: BaseException) -> str | None:
    """One line for an error that says the system ran out of file descriptors or memory, else ``None``.

    ``MemoryError``, an ``OSError`` with ``EMFILE``, ``ENFILE`` or ``ENOMEM``, and an error of a
    library (an ``ImportError`` of a shared object that cannot be mapped, a rerun error)
    whose message says the same are such errors: limits of the process (``ulimit -n``,
    ``ulimit -v``), not faults of the input.
    """
    import errno

    limits = {errno.EMFILE: "ulimit -n", errno.ENFILE: "ulimit -n", errno.ENOMEM: "ulimit -v"}
    text = str(exc).splitlines()[0] if str(exc) else ""
    if isinstance(exc, MemoryError):
        return "out of memory (the address space or the machine's memory; see ulimit -v); the command stopped"
    if isinstance(exc, OSError) and exc.errno in limits:
        return f"{exc.strerror} (see {limits[exc.errno]}); the command stopped"
    for phrase, limit in (
        ("Too many open files", "ulimit -n"),
        ("Cannot allocate memory", "ulimit -v"),
        ("failed to map segment", "ulimit -v"),
        ("Could not find/load shared object", "ulimit -v"),
    ):
        if phrase.lower() in text.lower():
            return f"{type(exc).__name__}: {text[:200]} (see {limit}); the command stopped"
    return None


def _without_exit(func, args) -> int:
    """``func(args)``; a ``SystemExit`` from inside the command (a plugin calling ``sys.exit``) is a
    fault of the run (:class:`~quadobs.errors.RunFault`), not the command's own status."""
    from quadobs.errors import RunFault

    try:
        return func(args)
    except SystemExit as exc:
        raise RunFault(
            f"the command was ended from inside by SystemExit({exc.code!r}) (a plugin calling "
            "sys.exit?); no result was written"
        ) from None


def _exit_status(exc: SystemExit) -> int:
    """The status that Python gives ``SystemExit(exc.code)``: 0 for ``None``, the number, else 1."""
    return 0 if exc.code is None else exc.code if isinstance(exc.code, int) else 1


def main(argv: list[str] | None = None) -> int:
    """The ``quadobs`` command line: run ``argv`` (default ``sys.argv[1:]``); returns the exit status.

    0: done; 1: a run that started and could not go on (a full disk, a physics fault), or an
    estimator named in ``--estimators`` that diverged or locked out (its outputs written,
    :mod:`quadobs.testbed.divergence`); 2: bad input (one line on stderr); 130: stopped by
    SIGINT (Ctrl-C) or SIGTERM, what was done kept.

    Its first act is to take SIGINT and SIGTERM, before anything heavy is imported (this
    module and :mod:`quadobs.errors` load the standard library alone), so a signal at any
    moment of the command, loading NumPy, SciPy or MuJoCo included, ends it with status 130
    and one line, never a traceback. Without ``argv`` it is the program (the ``quadobs``
    script, ``python -m quadobs``): once the command is over, a signal ends the process at
    once with status 130, the outputs being in place, and the process ends with the
    command's status as soon as the exit callbacks have run
    (:func:`quadobs._program.end_program`). With ``argv`` it is a call inside a larger
    program: the caller's handlers are restored on return, and a signal that came while
    returning is delivered to them then. The signal handling is :mod:`quadobs._program`.
    """
    program = argv is None
    previous: dict = {}
    status = None
    try:
        take_signals(previous, program)
        status = _run_command(argv)
    except KeyboardInterrupt:
        status = INTERRUPTED
    except SystemExit as exc:  # the parser's usage errors, --help, --version
        status = _exit_status(exc)
        raise
    finally:
        # No call comes before this store, so no handler runs between the command's end and it.
        Signals.mode = "exit" if program else "hold"
        if status is not None and (Signals.lost or Signals.raised):
            # an interrupt lost in a callback (quadobs._program.keep_lost_interrupts), or swallowed
            # by code that caught what it was turned into: the command was interrupted all the same
            status, Signals.lost = INTERRUPTED, 0
        if status == INTERRUPTED and not Signals.said:
            Signals.said = True
            print(INTERRUPTED_LINE, file=sys.stderr)
        if program:
            Signals.status = status
        else:
            give_back_signals(previous)
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
