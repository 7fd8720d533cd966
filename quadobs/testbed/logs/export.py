"""A simulated episode written as a log in the open format (``quadobs run SCENARIO --export-log DIR``).

:class:`LogExportSink` runs beside an episode's sinks and keeps, per step ``k`` (time
``t_k = k dt``), what the estimators were given and what was true:

* ``ranges.csv``: each measured range (after the sensor layer: noise, rate, dropouts,
  outliers) at ``t_k``. A range the noise or an outlier took below zero is written as its
  magnitude ``|rho|``: the format holds distances (non-negative), and the estimators'
  output ``y = rho^2 / 2 - |a|^2 / 2`` is the same for both signs, so the replay still
  gives the episode's outputs; the summary counts them (``exported_log_ranges_negated``);
* ``inputs.csv``: the measured acceleration ``u_k`` (the accelerometer, with its noise),
  held over ``[t_k, t_(k+1))``, in the navigation frame (``time,ax,ay[,az]``); a last row
  at ``t_K`` (zero) closes the last step, as the format's inputs are held to the next row;
* ``truth.csv``: the true position and velocity ``x_k`` (``time,x,y[,z],vx,vy[,vz]``);
* ``beacons.csv``: the scenario's beacons, ids ``0 .. q - 1``.

Replayed at ``dt`` equal to the physics step (``quadobs replay DIR --dt DT --model imu``)
the log gives the estimators the same outputs and, to rounding, the same inputs as the
episode (tested in ``tests/testbed/test_replay.py``). Only vehicle scenarios without wind
are written: the format holds neither an airspeed nor a quadrotor's attitude.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog, write_log
from quadobs.testbed.sinks import EpisodeContext, Rows, Sink

__all__ = ["LogExportSink", "check_export_folder", "check_exportable"]


def check_exportable(scenario) -> None:
    """A one-line error unless ``scenario`` can be written as a log (a vehicle scenario without wind)."""
    if scenario.kind != "vehicle" or scenario.has_wind:
        what = "a quadrotor" if scenario.kind != "vehicle" else "a wind scenario"
        raise QuadobsError(
            f"--export-log: {scenario.name!r} is {what}; the log format holds ranges, an accelerometer "
            "in the navigation frame and the truth of a vehicle scenario without wind"
        )


def check_export_folder(folder, outputs=()) -> None:
    """Before the run: a one-line error unless ``folder`` is new, empty or a log folder, and
    none of the run's other ``outputs`` lies in it (it is replaced whole at the end)."""
    from quadobs.testbed.logs.files import check_replaceable_folder
    from quadobs.testbed.logs.format import LOG_FILES

    check_replaceable_folder(folder, set(LOG_FILES), "--export-log", outputs)


class LogExportSink(Sink):
    """Collects an episode's ranges, inputs and truth, and writes them as a log folder at the end.

    Parameters
    ----------
    folder : path
        The log folder (created; its files are replaced each complete, see
        :func:`~quadobs.testbed.logs.format.write_log`).
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.parts: dict[str, list[np.ndarray]] = {"ranges": [], "inputs": [], "truth": []}

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        fr = ctx.frame
        if fr.has_wind or ctx.block.columns.n != 2 * fr.dimension:
            raise QuadobsError(
                f"--export-log: {fr.name!r}: the log format holds a position and velocity state only"
            )

    def block(self, rows: Rows) -> None:
        fr, c = self.ctx.frame, rows.block.columns
        steps = rows.ks < fr.steps  # the final row has no step: its truth only
        t = rows.t
        self.parts["truth"].append(np.column_stack([t, rows.truth]))
        self.parts["inputs"].append(np.column_stack([t[steps], rows.block.u[: rows.count][steps]]))
        measured = rows.block.raw[: rows.count, c.measured][steps]
        k, h = np.nonzero(~np.isnan(measured))  # row-major: by time, then by beacon
        self.parts["ranges"].append(np.column_stack([t[steps][k], h, measured[k, h]]))

    def end(self, completed: int, interrupted: bool) -> dict:
        if completed == 0:
            return {}
        fr = self.ctx.frame
        dim = fr.dimension
        inputs = np.vstack(self.parts["inputs"] + [np.r_[completed * fr.dt, np.zeros(dim)][None]])
        axes = "xyz"[:dim]
        ranges = np.vstack(self.parts["ranges"]).reshape(-1, 3)
        negated = int(np.count_nonzero(ranges[:, 2] < 0.0))
        ranges[:, 2] = np.abs(ranges[:, 2])
        log = RangeLog(
            fr.name,
            np.arange(fr.beacons.shape[0]),
            np.asarray(fr.beacons, dtype=float),
            ranges,
            inputs,
            float("nan"),
            np.vstack(self.parts["truth"]),
            input_kind="imu",
            truth_columns=("time", *axes, *(f"v{a}" for a in axes)),
        )
        write_log(log, self.folder)
        return {"exported_log": str(self.folder), "exported_log_ranges_negated": negated}
