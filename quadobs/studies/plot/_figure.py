"""Figure making shared by every kind: matplotlib on demand, greyscale-readable styles, atomic saving.

Matplotlib is an optional dependency (``pip install 'quadobs[plot]'``): it is imported here,
when a figure is made, never when :mod:`quadobs` is imported. Figures are drawn on the Agg
canvas without :mod:`matplotlib.pyplot` (no global figure state, no display needed).

Reproducibility: the files carry no date and no software version (PNG ``Software``, PDF
``CreationDate`` and ``Producer``, SVG ``Date`` are dropped; SVG ids are salted with a fixed
string), so the same input gives the same bytes.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.staging import write_staged

__all__ = [
    "DEFAULT_DPI",
    "DEFAULT_SIZE",
    "FORMATS",
    "drawing",
    "new_figure",
    "require_matplotlib",
    "save_figure",
    "style",
    "thin",
]

FORMATS = ("png", "pdf", "svg")
DEFAULT_SIZE = (7.0, 4.5)  # inches: the full text width of a two-column paper
DEFAULT_DPI = 150

# Black and greys with distinct dashes and markers: each line reads in greyscale print.
_STYLES: list[dict[str, Any]] = [
    {"color": "0.0", "linestyle": "-", "marker": "o"},
    {"color": "0.35", "linestyle": "--", "marker": "s", "markerfacecolor": "white"},
    {"color": "0.55", "linestyle": ":", "marker": "^"},
    {"color": "0.2", "linestyle": "-.", "marker": "D"},
    {
        "color": "0.45",
        "linestyle": (0, (5, 1, 1, 1, 1, 1)),
        "marker": "v",
        "markerfacecolor": "white",
    },
    {"color": "0.65", "linestyle": (0, (1, 1)), "marker": "x"},
]
TRUTH_STYLE: dict[str, Any] = {"color": "0.0", "linestyle": "-", "linewidth": 1.6}

_RC = {
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "legend.fontsize": 7,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "lines.linewidth": 1.0,
    "lines.markersize": 4.0,
    "axes.grid": True,
    "grid.color": "0.85",
    "grid.linewidth": 0.5,
    "svg.hashsalt": "quadobs",
    "svg.fonttype": "path",
    "pdf.fonttype": 42,
    "path.simplify": True,
}
_METADATA = {
    "png": {"Software": None},
    "pdf": {"CreationDate": None, "Producer": None, "Creator": None},
    "svg": {"Date": None, "Creator": None},
}


def require_matplotlib():
    """The matplotlib module with the Agg backend, or a one-line error saying how to install it."""
    try:
        import matplotlib
    except ImportError:
        raise QuadobsError("plotting needs matplotlib: pip install 'quadobs[plot]'") from None
    if "matplotlib.pyplot" not in sys.modules:  # never switch the backend under a caller's pyplot
        matplotlib.use("Agg")
    return matplotlib


def drawing():
    """Context manager holding the figures' rc settings (fonts, line widths, fixed SVG salt)."""
    return require_matplotlib().rc_context(_RC)


def style(i: int, n: int | None = None, markers: int = 8) -> dict:
    """Line style ``i`` of the greyscale cycle: colour, dashes, and about ``markers`` markers on a line of ``n`` points.

    Without ``n`` the line has no markers.
    """
    st = dict(_STYLES[i % len(_STYLES)])
    if n is None:
        st["marker"] = None
    else:
        step = max(1, n // max(markers, 1))
        st["markevery"] = (
            (i * step) // 3 % step,
            step,
        )  # staggered: markers of two lines do not hide each other
    return st


def thin(*arrays: np.ndarray, limit: int = 3000) -> tuple[np.ndarray, ...]:
    """Every ``ceil(T / limit)``-th row of each array (same length ``T``), and always the last row."""
    T = len(arrays[0])
    k = max(1, math.ceil(T / limit))
    if k == 1:
        return arrays
    idx = np.unique(np.r_[np.arange(0, T, k), T - 1])
    return tuple(a[idx] for a in arrays)


def _grid(n: int) -> tuple[int, int]:
    return {1: (1, 1), 2: (1, 2), 3: (1, 3), 4: (2, 2), 5: (2, 3), 6: (2, 3)}.get(
        n, (math.ceil(n / 3), 3)
    )


def new_figure(panels: list[str], size: tuple[float, float], dpi: float, three_d=()):
    """A figure of ``size`` inches with one axes per panel on a grid (call inside :func:`drawing`).

    Returns
    -------
    fig : matplotlib.figure.Figure
    axes : dict
        Panel name -> axes (3-D axes for the names in ``three_d``).
    """
    require_matplotlib()
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    rows, cols = _grid(len(panels))
    axes = {}
    for i, name in enumerate(panels):
        kw = {"projection": "3d"} if name in three_d else {}
        axes[name] = fig.add_subplot(rows, cols, i + 1, **kw)
    return fig, axes


def save_figure(fig, out: str | Path, dpi: float) -> Path:
    """Write ``fig`` to ``out`` (format from the suffix) through :func:`quadobs.staging.write_staged`.

    The parent folder is created only once the figure is drawn; on any error nothing is
    left behind.
    """
    out = Path(out)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise QuadobsError(
            f"--out {str(out)!r}: format {out.suffix or '(none)'!r} not supported (use .png, .pdf or .svg)"
        )
    if out.is_dir():
        raise QuadobsError(f"--out {str(out)!r}: is a directory, expected a file name")
    made = [p for p in reversed(out.parent.parents) if not p.exists()] + (
        [out.parent] if not out.parent.exists() else []
    )
    try:
        with drawing():
            write_staged(
                out,
                lambda tmp: fig.savefig(tmp, format=fmt, dpi=dpi, metadata=_METADATA[fmt]),
                "--out",
            )
    except BaseException as exc:
        _remove_dirs(made)
        if isinstance(exc, OSError):  # a full disk, a file size limit: a fault, in one line
            from quadobs.errors import RunFault

            raise RunFault(
                f"--out {str(out)!r}: cannot be written ({exc.strerror or exc}); the previous file is unchanged"
            ) from None
        raise
    return out


def _remove_dirs(made: list[Path]) -> None:
    for p in reversed(made):
        try:
            p.rmdir()
        except OSError:
            pass
