"""Panels of the le2013 recording (``quadobs run le2013 --out LE.rrd``): the figures of [LE2013, sec. 5].

The zonotopes ``X_k`` of the first run at chosen samples beside the true state, and the
widths of the interval hull of ``X_k`` over the samples, per method (layout:
:mod:`quadobs.studies.le2013.recording`).
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.studies.plot._figure import TRUTH_STYLE, style

__all__ = ["PANELS", "default_panels", "default_samples"]

_ORDER = ("segment", "volume", "pradius1", "pradius2", "pradius2_paper")


def _methods(src) -> list[str]:
    names = src.estimators
    return [m for m in _ORDER if m in names] + [m for m in names if m not in _ORDER]


def default_samples(last: int) -> list[int]:
    """Two samples, early and last (the initial box at ``k = 0`` would dwarf every later set)."""
    return sorted({max(1, int(round(0.2 * last))), last})


def sets(ax, src, samples=None) -> None:
    """The zonotopes of each method at the chosen samples (one small axes each), with the true state (first run)."""
    truth = src.strips("le2013/sets/truth")
    last = max(truth)
    samples = default_samples(last) if samples is None else list(samples)
    bad = [k for k in samples if k not in truth]
    if bad:
        raise QuadobsError(f"--samples: {bad[0]} is not a sample of the recording (0..{last})")
    if not samples:
        raise QuadobsError("--samples: give at least one sample")
    grid = ax.get_subplotspec().subgridspec(len(samples), 1) if len(samples) > 1 else None
    fig = ax.figure
    methods = [(m, src.strips(f"le2013/sets/{m}")) for m in _methods(src)]
    for j, k in enumerate(samples):
        sub = ax if grid is None else fig.add_subplot(grid[j])
        for i, (m, strips) in enumerate(methods):
            for v in strips[k]:
                sub.plot(v[:, 0], v[:, 1], label=m, **style(i + 1))
        p = truth[k][0].reshape(-1, 2)[0]
        sub.plot(
            p[0], p[1], linestyle="none", marker="*", color="0.0", markersize=7, label="true state"
        )
        sub.set_xlabel("x1 (-)")
        sub.set_ylabel("x2 (-)")
        sub.set_title(f"Sets X_k, k = {k}")
        if j == 0 and sub is not ax:
            sub.legend(loc="best", frameon=False, fontsize=5)
    if grid is not None:
        ax.remove()


def _log_plain(ax) -> None:
    """Log scale with plain tick labels (0.3, 0.4, 6 rather than 3 x 10^-1)."""
    from matplotlib.ticker import FuncFormatter

    def label(v, _pos, minor=False):
        lead = int(round(v / 10 ** np.floor(np.log10(v)))) if v > 0 else 0
        return "" if minor and lead not in (2, 3, 5) else f"{v:g}"

    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(label))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, p: label(v, p, minor=True)))


def _width(ax, src, column: int) -> None:
    for i, m in enumerate(_methods(src)):
        s = src.series(f"le2013/width/{m}")
        ax.plot(s["step"], s["values"][:, column], label=m, **style(i + 1, len(s["step"])))
    _log_plain(ax)
    ax.set_xlabel("sample k (-)")
    ax.set_ylabel(f"width of x{column + 1} bounds (-)")
    ax.set_title(f"Width of the x{column + 1} bounds (first run)")


def width_x1(ax, src) -> None:
    """Width of the interval hull of ``X_k`` along ``x1`` over the samples."""
    _width(ax, src, 0)


def width_x2(ax, src) -> None:
    """Width of the interval hull of ``X_k`` along ``x2`` over the samples."""
    _width(ax, src, 1)


def volume(ax, src) -> None:
    """Volume (area) of ``X_k``, averaged over all runs."""
    for i, m in enumerate(_methods(src)):
        s = src.series(f"le2013/mean_volume/{m}")
        ax.plot(s["step"], s["values"][:, 0], label=m, **style(i + 1, len(s["step"])))
    _log_plain(ax)
    ax.set_xlabel("sample k (-)")
    ax.set_ylabel("mean area of X_k (-)")
    ax.set_title("Volume (mean over runs)")


def bounds(ax, src) -> None:
    """Bounds of ``x1`` of each method around the true ``x1`` (first run)."""
    truth = src.series("le2013/truth")
    ax.plot(truth["step"], truth["values"][:, 0], label="true x1", **TRUTH_STYLE)
    for i, m in enumerate(_methods(src)):
        s = src.series(f"le2013/bounds/{m}/x1")
        st = style(i + 1)
        ax.plot(s["step"], s["values"][:, 0], label=m, **st)
        ax.plot(s["step"], s["values"][:, 1], **st)
    ax.set_xlabel("sample k (-)")
    ax.set_ylabel("x1 (-)")
    ax.set_title("Bounds of x1 (first run)")


PANELS = {
    "sets": sets,
    "width-x1": width_x1,
    "width-x2": width_x2,
    "volume": volume,
    "bounds": bounds,
}
THREE_D = ()


def default_panels(src) -> list[str]:
    """The sets and the widths of ``x1`` and ``x2``, as in [LE2013, sec. 5]."""
    return ["sets", "width-x1", "width-x2"]
