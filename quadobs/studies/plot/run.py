"""Panels of one run's recording (``quadobs run SCENARIO --out RUN.rrd``): the figures of [IFAC2021, sec. 6].

Each panel function draws on one axes from a :class:`~quadobs.studies.plot._source.Source`
of kind ``run`` (entity layout: :mod:`quadobs.testbed.episode_log`).
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.studies.plot._figure import TRUTH_STYLE, style, thin

__all__ = ["PANELS", "default_panels"]

_AXES = "xyz"


def _time_series(ax, src, entity: str, i: int, label: str, column: int = 0) -> None:
    s = src.series(entity)
    t, v = thin(s["sim_time"], s["values"][:, column])
    ax.plot(t, v, label=label, **style(i, len(t)))


def paths(ax, src, planes=(0, 1)) -> None:
    """True and estimated paths projected on the x-y plane, beacons as crosses."""
    a, b = planes
    truth = src.series("world/truth/path")["values"]
    ax.plot(truth[:, a], truth[:, b], label="truth", zorder=3, **TRUTH_STYLE)
    for i, e in enumerate(src.estimators, start=1):
        p = src.series(f"world/estimates/{e}/path")["values"]
        ax.plot(p[:, a], p[:, b], label=e, **style(i, len(p), markers=12))
    beacons = src.static_points("world/beacons")
    if beacons is not None:
        ax.plot(
            beacons[:, a],
            beacons[:, b],
            linestyle="none",
            marker="x",
            color="0.0",
            markersize=6,
            label="beacons",
        )
    _field_limits(ax, truth[:, [a, b]], None if beacons is None else beacons[:, [a, b]])
    ax.set_xlabel(f"{_AXES[a]} (m)")
    ax.set_ylabel(f"{_AXES[b]} (m)")
    ax.set_title("Paths (x-y projection)")
    ax.set_aspect("equal", adjustable="box")  # the limits kept: the panel's box adjusts


def _field_limits(ax, truth: np.ndarray, beacons: np.ndarray | None) -> None:
    """The axes' limits about the truth and the beacons, a fifth of their extent around (at
    least 0.5 m): an estimate's start from a guess tens of metres off would otherwise shrink a
    room's paths to a dot (it is drawn, and leaves the axes)."""
    points = truth if beacons is None else np.vstack([truth, beacons])
    points = points[np.all(np.isfinite(points), axis=1)]
    if points.shape[0] == 0:
        return
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = max(0.2 * float(np.max(hi - lo)), 0.5)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)


def paths3d(ax, src) -> None:
    """True and estimated paths in 3-D (2-D scenarios are drawn at z = 0)."""
    truth = src.series("world/truth/path")["values"]
    ax.plot(truth[:, 0], truth[:, 1], truth[:, 2], label="truth", **TRUTH_STYLE)
    for i, e in enumerate(src.estimators, start=1):
        p = src.series(f"world/estimates/{e}/path")["values"]
        ax.plot(p[:, 0], p[:, 1], p[:, 2], label=e, **style(i, len(p), markers=12))
    for k, name in enumerate(("x (m)", "y (m)", "z (m)")):
        getattr(ax, f"set_{'xyz'[k]}label")(name)
    ax.set_title("Paths")


def _error_norm(ax, src, what: str, unit: str, title: str) -> None:
    for i, e in enumerate(src.estimators):
        _time_series(ax, src, f"errors/{e}/{what}/norm", i, e)
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"error norm ({unit})")
    ax.set_title(title)


def position(ax, src) -> None:
    """Position error norm ``|p_hat - p|`` over time, log scale."""
    _error_norm(ax, src, "position", "m", "Position error")


def velocity(ax, src) -> None:
    """Velocity error norm ``|v_hat - v|`` over time, log scale (estimators with a velocity)."""
    if not _has_velocity(src):
        raise QuadobsError(
            "--what velocity: the recording has no velocity estimate (a state without a velocity)"
        )
    _error_norm(ax, src, "velocity", "m/s", "Velocity error")


def _has_velocity(src) -> bool:
    return any(src.has(f"errors/{e}/velocity/norm") for e in src.estimators)


def wind(ax, src) -> None:
    """Wind error norm ``|w_hat - w|`` over time, log scale (wind scenarios)."""
    if not any(src.has(f"errors/{e}/wind/norm") for e in src.estimators):
        raise QuadobsError("--what wind: the recording has no wind estimate (not a wind scenario)")
    _error_norm(ax, src, "wind", "m/s", "Wind error")


def ranges(ax, src) -> None:
    """Measured range to each beacon at its sample times."""
    for i, h in enumerate(sorted(src.names("measurements/range/<x>"), key=int)):
        s = src.series(f"measurements/range/{h}")
        t, v = thin(s["sim_time"], s["values"][:, 0])
        ax.plot(t, v, label=f"beacon {h}", **style(i, len(t)))
    ax.set_xlabel("time (s)")
    ax.set_ylabel("range (m)")
    ax.set_title("Range measurements")


def covariance(ax, src) -> None:
    """Trace of each estimator's covariance, log scale."""
    for i, e in enumerate(src.estimators):
        _time_series(ax, src, f"observer/{e}/covariance_trace", i, e)
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tr P (mixed units)")
    ax.set_title("Covariance trace")


def _measurement_counts(src, steps: np.ndarray) -> np.ndarray:
    """How many measurements (ranges, airspeed) were taken at each of ``steps``: the NIS degrees of freedom."""
    dof = np.zeros(len(steps), dtype=int)
    ents = [f"measurements/range/{h}" for h in src.names("measurements/range/<x>")]
    ents += ["measurements/airspeed"] if src.has("measurements/airspeed") else []
    for ent in ents:
        dof += np.isin(steps, src.series(ent)["step"])
    return dof


def nis(ax, src, confidence: float = 0.95) -> None:
    """NIS at each correction with its two-sided chi-square interval (dof: measurements at that step)."""
    from scipy.stats import chi2

    band = False
    for i, e in enumerate(src.estimators):
        if not src.has(f"observer/{e}/nis"):
            continue
        s = src.series(f"observer/{e}/nis")
        t, steps, v = thin(s["sim_time"], s["step"], s["values"][:, 0], limit=600)
        if not band:
            dof = np.maximum(_measurement_counts(src, steps), 1)
            lo, hi = chi2.ppf((1 - confidence) / 2, dof), chi2.ppf((1 + confidence) / 2, dof)
            ax.fill_between(
                t,
                lo,
                hi,
                step="mid",
                color="0.85",
                linewidth=0,
                label=f"chi-square {confidence:.0%}",
            )
            band = True
        ax.plot(t, v, label=e, **dict(style(i, 1, markers=1), linestyle="none", markersize=1.5))
    if not band:
        raise QuadobsError("--what nis: the recording has no NIS series")
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("NIS (-)")
    ax.set_title("Normalised innovation squared")


def bounds(ax, src) -> None:
    """Guaranteed position bounds minus the truth, per axis (the truth is the zero line), symlog scale."""
    bounded = [e for e in src.estimators if src.has(f"errors/{e}/position/bounds")]
    if not bounded:
        raise QuadobsError(
            "--what bounds: the recording has no guaranteed bounds (no set-valued estimator)"
        )
    i = 0
    for e in bounded:
        s = src.series(f"errors/{e}/position/bounds")
        dim = s["values"].shape[1] // 2
        for a in range(dim):
            t, lo, hi = thin(s["sim_time"], s["values"][:, a], s["values"][:, dim + a])
            st = style(i, len(t))
            ax.plot(t, lo, label=f"{e} {_AXES[a]}", **st)
            ax.plot(t, hi, **dict(st, label=None))
            i += 1
    ax.axhline(0.0, **dict(TRUTH_STYLE, linewidth=0.8))
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("bound - true position (m)")
    ax.set_title("Guaranteed bounds - truth")


def excitation(ax, src) -> None:
    """The excitation measure ``log10 mu`` against the threshold; windows below it shaded."""
    if not src.has("excitation/log10"):
        raise QuadobsError(
            "--what excitation: the recording has no excitation monitor (scenario excitation.monitor)"
        )
    s = src.series("excitation/log10")
    t, mu, thr = s["sim_time"], s["values"][:, 0], s["values"][:, 1]
    ax.plot(t, mu, label="log10 mu", **style(0))
    ax.plot(t, thr, label="log10 threshold", **style(1))
    low = np.isfinite(mu) & np.isfinite(thr) & (mu < thr)
    if low.any():
        top = np.nanmax(np.r_[mu, thr])
        bottom = np.nanmin(np.r_[mu, thr])
        ax.fill_between(
            t,
            bottom,
            top,
            where=low,
            step="mid",
            color="0.85",
            hatch="//",
            linewidth=0,
            label="below threshold",
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("log10 of the Gramian's lambda_min (-)")
    ax.set_title("Persistence of excitation")


PANELS = {
    "paths": paths,
    "paths3d": paths3d,
    "position": position,
    "velocity": velocity,
    "wind": wind,
    "ranges": ranges,
    "covariance": covariance,
    "nis": nis,
    "bounds": bounds,
    "excitation": excitation,
}
THREE_D = ("paths3d",)


def default_panels(src) -> list[str]:
    """Paths, errors (the velocity's where the state has one), covariance and NIS, and the wind, the bounds, the excitation or else the ranges."""
    extra = "ranges"
    if any(src.has(f"errors/{e}/wind/norm") for e in src.estimators):
        extra = "wind"
    elif any(src.has(f"errors/{e}/position/bounds") for e in src.estimators):
        extra = "bounds"
    elif src.has("excitation/log10"):
        extra = "excitation"
    panels = ["paths", "position", "velocity", "covariance", "nis", extra]
    if not _has_velocity(src):  # a state without a velocity (a replayed odometry log)
        panels.remove("velocity")
    return panels
