"""Recording of ``quadobs run le2013`` (section 5 of [LE2013]).

Timelines ``step`` (the sample ``k``) and ``sim_time`` (``k`` seconds, one sample a second).
Entity paths (``<m>`` is a method: ``segment``, ``volume``, ``pradius1``, ``pradius2``,
``pradius2_paper``):

================================  ==================================================================
``le2013/truth``                  true ``x1, x2`` of the first run (seed ``seed``)
``le2013/bounds/<m>/x1``, ``/x2`` lower and upper bound of ``x1``, ``x2`` (first run)
``le2013/width/<m>``              widths of the bounds of ``x1``, ``x2`` (first run)
``le2013/volume/<m>``             volume of the zonotope (first run)
``le2013/mean_width/<m>``         widths averaged over all runs
``le2013/mean_volume/<m>``        volume averaged over all runs
``le2013/sets/<m>``               the zonotope of each step as a closed line strip (first run)
``le2013/sets/truth``             the true state of each step (first run)
``le2013/table``                  the comparison table (static text)
================================  ==================================================================
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from quadobs.recording.recorder import Recorder

__all__ = ["record_le2013"]

_COLORS = {
    "segment": (230, 90, 40),
    "volume": (40, 160, 90),
    "pradius1": (150, 60, 200),
    "pradius2": (30, 150, 200),
    "pradius2_paper": (200, 170, 30),
}
_TRUTH = (40, 40, 40)


def _blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(name="Zonotopes X_k (first run)", origin="/le2013/sets"),
                rrb.TextDocumentView(name="Comparison", origin="/le2013/table"),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    name="Bounds of x1", contents=["/le2013/truth", "/le2013/bounds/**"]
                ),
                rrb.TimeSeriesView(name="Width of the bounds (first run)", origin="/le2013/width"),
                rrb.TimeSeriesView(name="Mean width over runs", origin="/le2013/mean_width"),
                rrb.TimeSeriesView(name="Volume (first run)", origin="/le2013/volume"),
                rrb.TimeSeriesView(name="Mean volume over runs", origin="/le2013/mean_volume"),
            ),
            column_shares=[2, 3],
        ),
        collapse_panels=False,
    )


def record_le2013(path, res: dict, table: str) -> None:
    """Write the result of :func:`quadobs.studies.le2013.study.reproduce` to ``path`` (``.rrd``), with ``table``
    (:func:`~quadobs.studies.le2013.study.format_table`) as a text document."""
    first = res["first"]
    methods = res["methods"]
    steps = res["steps"]
    rec = Recorder(
        path, recording_id=f"le2013-seed{res['seed']}", blueprint=_blueprint(), capacity=steps + 1
    )
    try:
        truth = rec.series("le2013/truth", 2, names=["true x1", "true x2"], color=_TRUTH)
        s = {}
        for m in methods:
            col = _COLORS.get(m, (120, 120, 120))
            s[m] = {
                "x1": rec.series(
                    f"le2013/bounds/{m}/x1", 2, names=[f"{m} x1 low", f"{m} x1 high"], color=col
                ),
                "x2": rec.series(
                    f"le2013/bounds/{m}/x2", 2, names=[f"{m} x2 low", f"{m} x2 high"], color=col
                ),
                "width": rec.series(
                    f"le2013/width/{m}", 2, names=[f"{m} width x1", f"{m} width x2"]
                ),
                "volume": rec.series(f"le2013/volume/{m}", 1, names=[f"{m} volume"], color=col),
                "mean_width": rec.series(
                    f"le2013/mean_width/{m}", 2, names=[f"{m} mean width x1", f"{m} mean width x2"]
                ),
                "mean_volume": rec.series(
                    f"le2013/mean_volume/{m}", 1, names=[f"{m} mean volume"], color=col
                ),
            }
        for k in range(steps + 1):
            i = rec.row(k, float(k))
            truth.buf[i] = first.truth[k]
            for m in methods:
                b = first.bounds[m][k]
                s[m]["x1"].buf[i] = b[0]
                s[m]["x2"].buf[i] = b[1]
                s[m]["width"].buf[i] = first.widths[m][k]
                s[m]["volume"].buf[i, 0] = first.volume[m][k]
                s[m]["mean_width"].buf[i] = res["mean_width"][m][k]
                s[m]["mean_volume"].buf[i, 0] = res["mean_volume"][m][k]
        rec.flush()
        stream = rec.rec
        for k in range(steps + 1):
            stream.set_time("step", sequence=k)
            stream.set_time("sim_time", duration=float(k))
            for m in methods:
                v = first.sets[m][k].vertices()
                stream.log(
                    f"le2013/sets/{m}",
                    rr.LineStrips2D(
                        [np.vstack([v, v[:1]])],
                        colors=[_COLORS.get(m, (120, 120, 120))],
                        labels=[m],
                    ),
                )
            stream.log(
                "le2013/sets/truth", rr.Points2D([first.truth[k]], colors=[_TRUTH], radii=0.02)
            )
        stream.reset_time()
        rec.static(
            "le2013/table", rr.TextDocument("```\n" + table + "\n```", media_type="text/markdown")
        )
    finally:
        rec.close()
