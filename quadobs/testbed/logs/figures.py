"""A replay's figures as the field reports them, and its trajectories as TUM files for evo.

:class:`FieldFiguresSink` runs beside a replay's other sinks (after them: its figures are
the summary's) and gives, per estimator, the figures of
:class:`~quadobs.evaluation.trajectory.TrajectoryErrors` over the rows with a truth: the
position RMSE after the burn-in (``--burn-in SECONDS``, from the replay's first row), its
horizontal and vertical parts in 3-D, the maximum error after the burn-in and ``diverged``
(None, or the row, the time and the reason; then no error figure at all: RMSE, maximum,
final error and convergence times all None).

With a folder (``--export-tum DIR``) it also writes, once the replay is complete, the
truth and each estimator's position at the same rows (after the burn-in, with a truth,
timestamps on the log's clock) as ``DIR/truth.tum`` and ``DIR/<estimator>.tum``: ``evo_ape
tum DIR/truth.tum DIR/ekf.tum`` then gives the RMSE of the summary (translation part, no
alignment). A log without a truth gives each estimator's position at every row after the
burn-in, and no ``truth.tum``. The folder is built beside its target and renamed into place whole
(:func:`~quadobs.testbed.logs.files.staged_folder`); a diverged estimator has no file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError, RunFault
from quadobs.evaluation.trajectory import TrajectoryErrors, tum_text
from quadobs.testbed.divergence import given_up, startup_record
from quadobs.testbed.logs.files import check_replaceable_folder, staged_folder
from quadobs.testbed.sinks import EpisodeContext, Rows, Sink

__all__ = ["FieldFiguresSink", "check_tum_folder", "tum_name"]


def tum_name(estimator: str) -> str:
    """The TUM file name of an estimator (characters other than letters, digits, ``._-`` as ``_``)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", estimator) + ".tum"


def _is_tum(name: str) -> bool:
    return name.endswith(".tum")


def check_tum_folder(folder: str | Path | None, outputs=()) -> None:
    """Before a replay: a one-line error unless ``folder`` is new, empty or holds only ``.tum``
    files, and none of the run's other ``outputs`` (paths or None) lies in it."""
    if folder is not None:
        check_replaceable_folder(folder, _is_tum, "--export-tum", outputs)


class FieldFiguresSink(Sink):
    """Per estimator, the figures of the module docstring; the TUM files when given a folder.

    Parameters
    ----------
    start : float
        The log's time of the replay's first row (s): added to the rows' times in the TUM files.
    burn_in : float
        Seconds from the first row before the figures (and the TUM rows) start.
    tum_folder : path, optional
    with_truth : bool
        Whether the log holds a truth. Without one, each estimator's TUM file holds its
        estimate at every row after the burn-in and no ``truth.tum`` is written (the
        trajectory of a log that nothing scores, for evo's other tools or a plot).
    """

    def __init__(
        self, start: float, burn_in: float = 0.0, tum_folder=None, with_truth: bool = True
    ) -> None:
        self.start, self.burn_in = float(start), float(burn_in)
        self.tum_folder = None if tum_folder is None else Path(tum_folder)
        self.with_truth = bool(with_truth)
        TrajectoryErrors(2, self.burn_in)  # the burn-in checked before the run

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        dim = ctx.frame.dimension
        self.errors = {n: TrajectoryErrors(dim, self.burn_in) for n in ctx.names}
        self.tracks: dict[str, list[np.ndarray]] = {n: [] for n in ["truth", *ctx.names]}
        self.t0: float | None = None

    def block(self, rows: Rows) -> None:
        if not rows.t.size:
            return
        dim = self.ctx.frame.dimension
        if self.t0 is None:
            self.t0 = float(rows.t[0])
        truth = rows.truth[:, :dim]
        for name, err in self.errors.items():
            err.update(rows.ks, rows.t, rows.estimates[name], truth)
        if self.tum_folder is None:
            return
        keep = rows.t - self.t0 >= self.burn_in
        if self.with_truth:
            keep &= np.all(np.isfinite(truth), axis=1)
        t = self.start + rows.t[keep]
        self.tracks["truth"].append(np.column_stack([t, truth[keep]]))
        for name in self.errors:
            self.tracks[name].append(np.column_stack([t, rows.estimates[name][keep, :dim]]))

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {}
        own = {est.name: est for est in getattr(self.ctx, "estimators", ())}
        for name, err in self.errors.items():
            per[name] = figures = err.figures()
            clock = (self.start, self.ctx.frame.dt)  # the filters' time is the log's
            if figures["diverged"] is None:  # the filter's own record of having given up
                figures["diverged"] = given_up(own.get(name), *clock)
            started = startup_record(own.get(name), *clock)
            if started is not None:  # ran from its prior: its figures stand, the entry says so
                figures["startup"] = started
            same_as = _same_as(own.get(name))
            if same_as is not None:  # built as another estimator of the set (the log decided)
                figures["same_as"] = {"estimator": same_as[0], "reason": same_as[1]}
            if figures["diverged"] is None:  # the final error as the replay's own sink gives it
                del figures["final_position_error"]
            else:  # nothing of a diverged estimator is summarised as if it ran
                figures.update(time_to_5m=None, time_to_2m=None)
        out: dict = {"burn_in": self.burn_in, "estimators": per}
        if self.tum_folder is not None:
            written = [n for n in self.errors if per[n]["diverged"] is None]
            out["tum"] = {
                "folder": str(self.tum_folder),
                "files": ["truth.tum"] * self.with_truth + [tum_name(n) for n in written],
            }
            self._written = written
        return out

    def publish(self) -> None:
        """The TUM folder, whole (after the summary, beside the recording)."""
        if self.tum_folder is None or not hasattr(self, "_written"):
            return
        texts = {"truth.tum": self._text("truth")} if self.with_truth else {}
        texts.update({tum_name(n): self._text(n) for n in self._written})
        try:
            with staged_folder(self.tum_folder, _is_tum, "--export-tum") as stage:
                for fname, text in texts.items():
                    (stage / fname).write_text(text)
        except QuadobsError as exc:
            raise RunFault(str(exc)) from None

    def _text(self, name: str) -> str:
        parts = self.tracks[name]
        rows = np.vstack(parts) if parts else np.empty((0, 1 + self.ctx.frame.dimension))
        return tum_text(rows[:, 0], rows[:, 1:])


def _same_as(est) -> tuple | None:
    """The ``same_as`` (another estimator's name, and why) of an estimator or of the one it
    wraps (``inner``), None where none says it."""
    while est is not None:
        same_as = getattr(est, "same_as", None)
        if same_as is not None:
            return same_as
        est = getattr(est, "inner", None)
    return None
