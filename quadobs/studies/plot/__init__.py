"""Figures from what the project writes: a run's ``.rrd``, a campaign folder, the le2013 recording.

``quadobs plot INPUT --out FIG.png|.pdf|.svg [--what PANEL,...]`` (:func:`render`) draws one
figure of the chosen panels. The kind of input is told by its content:

========  ==============================================  ========================================
kind      input                                           panels (default first)
========  ==============================================  ========================================
run       ``quadobs run SCENARIO --out RUN.rrd``          ``paths position velocity covariance
                                                          nis`` and ``wind``, ``bounds``,
                                                          ``excitation`` or ``ranges``; also
                                                          ``paths3d``
campaign  ``quadobs campaign ... --out DIR`` (the folder  ``rmse rmse-velocity converged nees nis
          or its ``statistics.rrd``)                      final``
le2013    ``quadobs run le2013 --out LE.rrd``             ``sets width-x1 width-x2``; also
                                                          ``volume bounds``
========  ==============================================  ========================================

Figures are 7.0 x 4.5 in by default (the full text width of a two-column paper; give
``size=(3.5, 2.6)`` for one column), drawn in black and greys with distinct dashes and
markers (readable in greyscale print), with units on every axis, and written without
dates or versions: the same input gives the same file. Matplotlib is optional
(``pip install 'quadobs[plot]'``).

Examples
--------
>>> from quadobs.studies.plot import render                        # doctest: +SKIP
>>> render("run.rrd", "run.pdf", what=["paths", "position"])      # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

from quadobs.errors import QuadobsError
from quadobs.studies.plot import campaign as _campaign
from quadobs.studies.plot import le2013 as _le2013
from quadobs.studies.plot import run as _run
from quadobs.studies.plot._figure import (
    DEFAULT_DPI,
    DEFAULT_SIZE,
    FORMATS,
    drawing,
    new_figure,
    require_matplotlib,
    save_figure,
)
from quadobs.studies.plot._source import open_source

__all__ = ["DEFAULT_DPI", "DEFAULT_SIZE", "FORMATS", "PANELS", "figure", "render"]

_KINDS = {"run": _run, "campaign": _campaign, "le2013": _le2013}
PANELS: dict[str, list[str]] = {kind: list(mod.PANELS) for kind, mod in _KINDS.items()}
"""Panel names of each kind of input."""


def _check_panels(what, kind: str, src) -> list[str]:
    mod = _KINDS[kind]
    if what is None:
        return mod.default_panels(src)
    what = list(what)
    if not what:
        raise QuadobsError("--what: give at least one panel")
    for name in what:
        if name not in mod.PANELS:
            others = [k for k, m in _KINDS.items() if name in m.PANELS and k != kind]
            hint = f" (a panel of a {others[0]} input)" if others else ""
            raise QuadobsError(
                f"--what {name}: not a panel of a {kind} input{hint}; its panels: {', '.join(mod.PANELS)}"
            )
    return list(dict.fromkeys(what))


def _check_size(size, dpi) -> tuple[tuple[float, float], float]:
    size = DEFAULT_SIZE if size is None else tuple(float(v) for v in size)
    dpi = DEFAULT_DPI if dpi is None else float(dpi)
    if len(size) != 2 or not all(0.5 <= v <= 50 for v in size):
        raise QuadobsError(
            f"--size: width and height must be between 0.5 and 50 inches, got {size}"
        )
    if not 10 <= dpi <= 1200:
        raise QuadobsError(f"--dpi: must be between 10 and 1200, got {dpi:g}")
    return size, dpi


def figure(
    input, what=None, *, size=None, dpi=None, samples=None, legend: bool = True, estimators=None
):
    """The matplotlib figure of ``input`` with the panels ``what`` (arguments as :func:`render`).

    Returns
    -------
    fig : matplotlib.figure.Figure
    dpi : float
    """
    size, dpi = _check_size(size, dpi)
    require_matplotlib()  # the missing extra is said before any reading
    src = open_source(input)
    if estimators is not None:
        src.select(estimators)
    panels = _check_panels(what, src.kind, src)
    if samples is not None and (src.kind != "le2013" or "sets" not in panels):
        raise QuadobsError("--samples: applies only to the sets panel of a le2013 recording")
    mod = _KINDS[src.kind]
    with drawing():
        fig, axes = new_figure(panels, size, dpi, three_d=mod.THREE_D)
        for name in panels:
            kw = {"samples": samples} if name == "sets" and samples is not None else {}
            mod.PANELS[name](axes[name], src, **kw)
            ax = axes[name]
            if (
                legend
                and ax in fig.axes
                and ax.get_legend() is None
                and ax.get_legend_handles_labels()[0]
            ):
                ax.legend(loc="best", frameon=False)
    return fig, dpi


def render(
    input,
    out,
    what=None,
    *,
    size=None,
    dpi=None,
    samples=None,
    legend: bool = True,
    estimators=None,
) -> Path:
    """Draw the figure of ``input`` with the panels ``what`` and write it to ``out``.

    Parameters
    ----------
    input : str or Path
        A run's ``.rrd``, a campaign folder (or its ``statistics.rrd``) or the le2013 ``.rrd``.
    out : str or Path
        Figure file; ``.png``, ``.pdf`` or ``.svg``. Written to a temporary name and renamed
        into place: on error nothing is written (not even its folder).
    what : list of str, optional
        Panels (:data:`PANELS` of the input's kind); default: the kind's usual figure.
    size : (float, float), optional
        Width and height in inches (default 7.0 x 4.5, a two-column paper's text width).
    dpi : float, optional
        Dots per inch of a PNG (default 150); a PNG is ``size * dpi`` pixels.
    samples : list of int, optional
        le2013 ``sets``: the samples ``k`` whose zonotopes are drawn.
    legend : bool
        A legend in each panel.
    estimators : list of str, optional
        Only these estimators (methods of a campaign), in this order; default: all of the
        recording's.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    QuadobsError
        Unknown or inapplicable panel, a file that is not a quadobs recording, an output
        format other than PNG, PDF or SVG, matplotlib not installed.
    """
    out = Path(out)
    if out.suffix.lower().lstrip(".") not in FORMATS:
        raise QuadobsError(
            f"--out {str(out)!r}: format {out.suffix or '(none)'!r} not supported (use .png, .pdf or .svg)"
        )
    fig, dpi = figure(
        input, what, size=size, dpi=dpi, samples=samples, legend=legend, estimators=estimators
    )
    return save_figure(fig, out, dpi)
