"""The printed table of a campaign summary."""

from __future__ import annotations

import math

__all__ = ["print_campaign"]


def _f(v, digits=3, unit=""):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}g}{unit}"


def print_campaign(summary: dict, file=None) -> None:
    """A short table of a campaign summary: one row per estimator."""
    import sys

    file = file or sys.stdout
    _print_head(summary, file)
    _print_table(summary, file)
    _print_tail(summary, file)


def _print_head(summary: dict, file) -> None:
    """The campaign's line and the bounds' lines."""
    b = summary["backend"]
    where = (
        b["kind"]
        + (f" ({b['workers']} workers)" if b["kind"] != "in-process" else "")
        + (f" at {b['scheduler']}" if "scheduler" in b else "")
    )
    print(
        f"campaign {summary['scenario']}: {summary['runs_completed']} of {summary['runs_requested']} runs completed"
        f" ({summary['runs_failed']} failed), {summary['duration']:g} s each, {summary['wall_time']:.1f} s wall on {where}"
        + ("  [INTERRUPTED]" if summary.get("interrupted") else ""),
        file=file,
    )
    pc = summary["pcrb"]
    if pc["available"]:
        print(
            f"posterior CRB at the end: sqrt(tr) = {_f(pc['final_sqrt_trace_position'])} m, "
            f"{_f(pc['final_sqrt_trace_velocity'])} m/s ({pc['note']})",
            file=file,
        )
        if "immersion_bound_final_sqrt_trace_position" in pc:
            print(
                f"best linear filter on the immersion at the end: sqrt(tr) = {_f(pc['immersion_bound_final_sqrt_trace_position'])} m, "
                f"{_f(pc['immersion_bound_final_sqrt_trace_velocity'])} m/s",
                file=file,
            )
    else:
        print(f"posterior CRB: not available ({pc['note']})", file=file)


def _print_table(summary: dict, file) -> None:
    """One row per estimator."""
    thr = summary["convergence_threshold"]
    cols = [
        "estimator",
        f"converged (<{thr:g} m)",
        "final RMSE p (m)",
        "final RMSE v (m/s)",
        "RMSE/sqrt(PCRB) p",
        "RMSE p converged",
        "mean NEES end [bounds]",
        "NEES in bounds",
        "median t_conv",
    ]
    rows = []
    for name, e in summary["estimators"].items():
        nb = e["chi2_bounds"]["nees"]
        frac = e["converged_fraction"]
        rows.append(
            [
                name,
                "-" if frac is None else f"{e['converged_runs']}/{e['runs']} ({100 * frac:.0f}%)",
                _f(e["final_rmse_position"]),
                _f(e["final_rmse_velocity"]),
                _f(e["rmse_over_sqrt_pcrb"]),
                _f(e["final_rmse_position_converged"]),
                f"{_f(e['mean_nees'])} [{_f(nb[0])}, {_f(nb[1])}]",
                "-"
                if e["nees_inside_fraction"] is None
                else f"{100 * e['nees_inside_fraction']:.0f}%",
                _f(e["median_convergence_time"], unit=" s"),
            ]
        )
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)), file=file)
    for r in rows:
        print("  ".join(v.ljust(w) for v, w in zip(r, widths)), file=file)


def _print_tail(summary: dict, file) -> None:
    """The flight figures, the NEES over the converged parts, the failed runs, the files."""
    fl = summary.get("flight")
    if fl:
        rmse = ", ".join(
            f"{nm} {_f(v['median'])} / {_f(v['max'])}"
            for nm, v in fl["flight_position_rmse"].items()
        )
        print(
            f"flight: {fl['crashed']} of {fl['runs']} crashed; tracking RMS median {_f(fl['tracking_rms_median'])} m,"
            f" largest {_f(fl['tracking_rms_max'])} m; largest tracking error {_f(fl['tracking_max'])} m;"
            f" {_f(fl['time_on_estimate_mean'])} s on the estimate",
            file=file,
        )
        print(f"position RMSE after the switch (m), median / largest: {rmse}", file=file)
    for name, e in summary["estimators"].items():
        part = e.get("nees_converged_part") or {}
        if part.get("time_average") is not None:
            fb = part["final_bounds"]
            print(
                f"{name}: NEES over each run's converged part: time average {_f(part['time_average'])}, "
                f"{100 * part['inside_fraction']:.0f}% of samples inside their bounds, "
                f"at the end {_f(part['final'])} [{_f(fb[0])}, {_f(fb[1])}]",
                file=file,
            )
    for f in summary["failed"][:10]:
        print(f"failed: run {f['run']} (seed {f['seed']}): {f['error']}", file=file)
    if len(summary["failed"]) > 10:
        print(
            f"... and {len(summary['failed']) - 10} more failed runs (see summary.json)", file=file
        )
    if summary.get("files"):
        print(f"results: {summary['files']['summary']}, {summary['files']['runs']}", file=file)
        if "recording" in summary["files"]:
            print(f"statistics over time: rerun {summary['files']['recording']}", file=file)
