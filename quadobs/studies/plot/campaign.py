"""Panels of a campaign folder (``quadobs campaign SCENARIO --out DIR``): statistics over the runs.

Drawn from ``statistics.rrd`` and ``runs.parquet`` (layout: :mod:`quadobs.studies.campaign`).
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.studies.plot._figure import TRUTH_STYLE, style, thin

__all__ = ["PANELS", "default_panels"]


def _line(ax, src, entity: str, i: int, label: str, column: int = 0, **kw) -> None:
    s = src.series(entity)
    t, v = thin(s["sim_time"], s["values"][:, column])
    ax.plot(t, v, label=label, **dict(style(i, len(t)), **kw))


def _rmse(ax, src, what: str, unit: str) -> None:
    for i, e in enumerate(src.estimators, start=1):
        _line(ax, src, f"stats/{e}/{what}/rmse", i, e)
    if src.has(f"stats/pcrb/{what}"):
        _line(ax, src, f"stats/pcrb/{what}", 0, "sqrt PCRB", **dict(TRUTH_STYLE, marker=None))
    if src.has(f"stats/immersion_bound/{what}"):
        _line(
            ax,
            src,
            f"stats/immersion_bound/{what}",
            0,
            "linear bound",
            color="0.5",
            linestyle="--",
            marker=None,
        )
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"RMSE ({unit})")


def rmse(ax, src) -> None:
    """Position RMSE over the runs against the square root of the posterior Cramér-Rao bound."""
    _rmse(ax, src, "position", "m")
    ax.set_title("Position RMSE and sqrt PCRB")


def rmse_velocity(ax, src) -> None:
    """Velocity RMSE over the runs against the square root of the posterior Cramér-Rao bound."""
    _rmse(ax, src, "velocity", "m/s")
    ax.set_title("Velocity RMSE and sqrt PCRB")


def converged(ax, src) -> None:
    """Fraction of the runs whose position error is within the convergence threshold."""
    for i, e in enumerate(src.estimators):
        _line(ax, src, f"stats/{e}/converged", i, e)
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("fraction of runs (-)")
    ax.set_title("Converged runs")


def _consistency(ax, src, what: str, title: str) -> None:
    drawn = False
    for i, e in enumerate(src.estimators):
        if not src.has(f"stats/{e}/{what}/mean"):
            continue
        b = src.series(f"stats/{e}/{what}/bounds")
        t, lo, hi = thin(b["sim_time"], b["values"][:, 0], b["values"][:, 1])
        label = "chi-square" if not drawn else None
        ax.fill_between(t, lo, hi, color="0.88", linewidth=0, label=label)
        ax.plot(t, lo, color="0.6", linewidth=0.6)
        ax.plot(t, hi, color="0.6", linewidth=0.6)
        _line(ax, src, f"stats/{e}/{what}/mean", i, e)
        drawn = True
    if not drawn:
        raise QuadobsError(f"--what {what}: the campaign has no {what.upper()} statistics")
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"mean {what.upper()} (-)")
    ax.set_title(title)


def nees(ax, src) -> None:
    """Mean NEES over the runs with its two-sided chi-square interval."""
    _consistency(ax, src, "nees", "NEES")


def nis(ax, src) -> None:
    """Mean NIS over the runs with its two-sided chi-square interval."""
    _consistency(ax, src, "nis", "NIS")


def final(ax, src) -> None:
    """Empirical distribution of the final position error of each estimator's completed runs."""
    table = src.runs_table()
    drawn = False
    for i, e in enumerate(src.estimators):
        v = np.array(
            [
                x
                for x, nm, st in zip(
                    table["final_position_error"], table["estimator"], table["status"]
                )
                if nm == e and st == "ok" and x is not None
            ],
            dtype=float,
        )
        v = np.sort(v[np.isfinite(v) & (v > 0)])
        if v.size == 0:
            continue
        frac = np.arange(1, v.size + 1) / v.size
        ax.step(np.r_[v[0], v], np.r_[0.0, frac], where="post", label=e, **style(i, v.size + 1))
        drawn = True
    if not drawn:
        raise QuadobsError("--what final: the campaign has no completed runs")
    ax.set_xscale("log")
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("final position error (m)")
    ax.set_ylabel("fraction of runs (-)")
    ax.set_title("Final errors (empirical CDF)")


PANELS = {
    "rmse": rmse,
    "rmse-velocity": rmse_velocity,
    "converged": converged,
    "nees": nees,
    "nis": nis,
    "final": final,
}
THREE_D = ()


def default_panels(src) -> list[str]:
    """Every panel."""
    return list(PANELS)
