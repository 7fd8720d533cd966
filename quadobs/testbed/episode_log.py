"""The layout of an episode's recording: entity paths, their series and the default blueprint.

The same layout for a simulated episode and a replayed log (its frame,
:class:`~quadobs.testbed.sinks.EpisodeFrame`, says what differs). Entity paths
(timelines ``step`` and ``sim_time``; ``<est>`` is an estimator name such as
``augmented``):

=====================================  =========================================================
``world/beacons``                      beacon positions (static points, labelled)
``world/truth/path``                   true position, a point per recorded 3-D frame (trail)
``world/truth/vehicle``                true vehicle: a box moved by its ``Transform3D``
``world/estimates/<est>/path``         estimated position trail
``world/estimates/<est>/vehicle``      estimated vehicle (box)
``errors/<est>/position/norm``         ``|p_hat - p|`` (m)
``errors/<est>/position/axes``         ``p_hat - p`` per axis (m)
``errors/<est>/velocity/norm``, /axes  ground-velocity error (m/s), where the state has a velocity
``errors/<est>/wind/norm``, /axes      wind error (wind scenarios)
``wind/truth``, ``wind/<est>``         true and estimated wind (wind scenarios)
``measurements/range/<h>``             measured range to beacon ``h`` (m), at its sample times
``measurements/airspeed``              measured airspeed (m/s), wind scenarios
``measurements/accelerometer``         measured acceleration (m/s^2); a replayed odometry log:
                                       ``measurements/odometry`` (v_x, v_y in m/s, omega in rad/s)
``observer/<est>/covariance_trace``    trace of the estimator covariance
``observer/<est>/nis``                 normalised innovation squared (at corrections)
``observer/<est>/rejected``            corrections rejected by the NIS gate so far (gated estimators)
``measurements/outliers``              range samples delivered with an injected outlier, so far
``measurements/dropped``               samples lost to dropouts, so far
``excitation/...``                     live excitation monitor (see ``quadobs.recording.excitation``)
``world/estimates/<est>/bounds``       guaranteed box of the position (estimators with ``bounds``)
``errors/<est>/position/bounds``       lower and upper bound minus the true position, per axis (m)
``errors/<est>/position/box_width``    width of the guaranteed box per axis (m)
``events``                             text log (warnings, interruption)
=====================================  =========================================================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from quadobs.errors import QuadobsError
from quadobs.recording.recorder import Recorder

__all__ = ["EpisodeLog", "LoggedRows", "default_blueprint", "scene_size"]

_PALETTE = [(230, 90, 40), (40, 160, 90), (150, 60, 200), (200, 170, 30), (30, 150, 200)]
_TRUTH = (40, 90, 220)


def scene_size(frame) -> float:
    """The length (m) the recording's 3-D sizes follow: the beacons' extent (at least 1 m), or 30 m with a single beacon (whose scene the frame does not tell)."""
    b = np.asarray(frame.beacons, dtype=float)
    if b.shape[0] < 2:
        return 30.0
    return float(max(np.ptp(b, axis=0).max(), 1.0))


def _eye(frame) -> rrb.EyeControls3D | None:
    """The 3-D view's eye: looking at the beacons' centre from a corner, a scene size away (None: rerun's own, with a single beacon)."""
    if frame.beacons.shape[0] < 2:
        return None
    b = np.zeros((frame.beacons.shape[0], 3))
    b[:, : frame.dimension] = frame.beacons
    centre, size = b.mean(axis=0), scene_size(frame)
    return rrb.EyeControls3D(
        position=centre + size * np.array([1.0, -1.2, 0.8]), look_target=centre, eye_up=[0, 0, 1]
    )


def default_blueprint(frame, estimators: list[str]) -> rrb.Blueprint:
    """3-D view of the vehicle, beacons and trails beside time series of errors, measurements and covariance.

    ``frame``: the run's :class:`~quadobs.testbed.sinks.EpisodeFrame`. The 3-D view looks at
    the beacons from a scene size away (:func:`scene_size`); every time series shows the
    whole run, whatever the time cursor.
    """
    history = [  # on both timelines: the viewer may open on either
        rrb.VisibleTimeRange(
            timeline,
            start=rrb.TimeRangeBoundary.infinite(),
            end=rrb.TimeRangeBoundary.cursor_relative(),
        )
        for timeline in ("sim_time", "step")
    ]
    whole = [
        rrb.VisibleTimeRange(
            timeline,
            start=rrb.TimeRangeBoundary.infinite(),
            end=rrb.TimeRangeBoundary.infinite(),
        )
        for timeline in ("sim_time", "step")
    ]
    run = rrb.TimeAxis(  # the x axis opens on the whole run, not on the cursor's neighbourhood
        view_range=rrb.TimeRange(
            start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()
        )
    )
    plots = [
        rrb.TimeSeriesView(
            name="Position error (m)",
            contents=[f"/errors/{e}/position/**" for e in estimators],
            time_ranges=whole,
            axis_x=run,
        ),
        rrb.TimeSeriesView(
            name="Velocity error (m/s)",
            contents=[f"/errors/{e}/velocity/**" for e in estimators],
            time_ranges=whole,
            axis_x=run,
        ),
    ]
    if frame.has_wind:
        plots.append(
            rrb.TimeSeriesView(name="Wind (m/s)", origin="/wind", time_ranges=whole, axis_x=run)
        )
    plots += [
        rrb.TimeSeriesView(
            name="Measurements", origin="/measurements", time_ranges=whole, axis_x=run
        ),
        rrb.TimeSeriesView(
            name="Covariance trace, NIS", origin="/observer", time_ranges=whole, axis_x=run
        ),
    ]
    if frame.excitation:  # see quadobs.recording.excitation
        plots += [
            rrb.TimeSeriesView(
                name="Excitation: log10 mu vs threshold",
                contents=["/excitation/log10"],
                time_ranges=whole,
                axis_x=run,
            ),
            rrb.TimeSeriesView(
                name="Variance in the unexcited directions",
                contents=["/excitation/unexcited_variance/**"],
                time_ranges=whole,
                axis_x=run,
            ),
        ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    name="Vehicle, beacons, trajectories",
                    origin="/world",
                    time_ranges=history,
                    eye_controls=_eye(frame),
                ),
                rrb.TextLogView(name="Events", origin="/events"),
                row_shares=[4, 1],
            ),
            rrb.Vertical(*plots),
            column_shares=[3, 2],
        ),
        collapse_panels=False,
    )


@dataclass(frozen=True)
class LoggedRows:
    """The ``m`` rows of a block that the recording keeps (rows first, ``(m, ...)``).

    Attributes
    ----------
    steps, times : ndarray (m,)
        Physics steps and their times.
    truth_p : ndarray (m, dim)
        True position.
    truth_wind : ndarray (m, dim) or None
        True wind (wind scenarios).
    errors : dict of str to dict of str to ndarray
        Per estimator, :func:`~quadobs.evaluation.convergence.state_errors` of its rows.
    estimates : dict of str to ndarray (m, n)
    traces, nis : dict of str to ndarray (m,)
        Covariance trace and NIS per estimator.
    ranges : ndarray (m, q_b)
        Measured ranges (NaN where not sampled).
    airspeed : ndarray (m,) or None
        Measured airspeed (wind scenarios).
    inputs : ndarray (m, p)
        The measured input (the acceleration; a replayed odometry log's velocity and yaw rate).
    bounds : dict of str to ndarray (m, n, 2)
        Interval bounds of the set-valued estimators.
    rejected : dict of str to ndarray (m,)
        Running count of corrections rejected by the NIS gate (gated estimators).
    events : ndarray (m, 2)
        Running counts of injected outliers and dropped samples.
    """

    steps: np.ndarray
    times: np.ndarray
    truth_p: np.ndarray
    truth_wind: np.ndarray | None
    errors: dict
    estimates: dict
    traces: dict
    nis: dict
    ranges: np.ndarray
    airspeed: np.ndarray | None
    inputs: np.ndarray
    bounds: dict
    rejected: dict
    events: np.ndarray

    def __post_init__(self) -> None:
        m = len(self.steps)
        for name in ("times", "truth_p", "ranges", "inputs", "events"):
            if len(getattr(self, name)) != m:
                raise QuadobsError(
                    f"rows.{name}: expected {m} rows, got {len(getattr(self, name))}"
                )


class EpisodeLog:
    """Declares an episode's series on a :class:`Recorder` and writes one row per recorded step.

    Parameters
    ----------
    recorder : Recorder
    frame : EpisodeFrame
        Its ``trail_every`` steps between 3-D samples (trails and vehicle boxes), and
        ``sensor_events``: record the running counts of injected outliers and dropped samples.
    estimators : list of str
    bounded : list of str
        Estimators exposing guaranteed ``bounds (n, 2)`` of the state: their position box is
        recorded too (see the module docstring).
    gated : list of str
        Estimators with an NIS gate: their running count of rejected corrections is recorded.
    velocity : bool
        The state has a velocity: its errors are recorded.
    """

    def __init__(
        self,
        recorder: Recorder,
        frame,
        estimators: list[str],
        *,
        bounded=(),
        gated=(),
        velocity: bool = True,
    ) -> None:
        self.rec = recorder
        self.sc = frame
        self.names = list(estimators)
        dim, every, r = frame.dimension, frame.trail_every, recorder
        size = min(scene_size(frame) / 30.0, 1.0)  # the sizes below fit a 30 m scene
        axes = ["x", "y", "z"][:dim]
        beacons3 = np.zeros((frame.beacons.shape[0], 3))
        beacons3[:, :dim] = frame.beacons
        r.static(
            "world/beacons",
            rr.Points3D(
                beacons3,
                radii=0.6 * size,
                colors=[(255, 140, 0)],
                labels=list(frame.beacon_labels),
            ),
        )
        r.static("description", rr.TextDocument(f"{frame.name}: {frame.description}"))
        self.truth_path = r.series(
            "world/truth/path", 3, "points3d", every=every, color=_TRUTH, radius=0.15 * size
        )
        self.truth_box = r.series(
            "world/truth/vehicle",
            3,
            "translation",
            every=every,
            color=_TRUTH,
            half_size=(0.6 * size, 0.4 * size, 0.15 * size),
        )
        self.est = {
            name: self._estimator(
                name, _PALETTE[i % len(_PALETTE)], axes, velocity, name in gated, name in bounded
            )
            for i, name in enumerate(self.names)
        }
        if frame.has_wind:
            self.wind_truth = r.series(
                "wind/truth", dim, names=[f"true w_{a}" for a in axes], color=_TRUTH
            )
            self.airspeed = r.series("measurements/airspeed", 1, skip_nan=True, names=["airspeed"])
        self.ranges = [  # by the beacons' ids: a log's, as its files name them
            r.series(f"measurements/range/{h}", 1, skip_nan=True, names=[f"range {h}"])
            for h in (frame.beacon_ids or range(frame.beacons.shape[0]))
        ]
        self.inputs = r.series(
            f"measurements/{frame.input_name}",
            len(frame.input_labels),
            names=list(frame.input_labels),
        )
        self.events = None
        if frame.sensor_events:
            self.events = (
                r.series("measurements/outliers", 1, names=["outliers injected"]),
                r.series("measurements/dropped", 1, names=["samples dropped"]),
            )

    def _estimator(
        self, name: str, color, axes: list[str], velocity: bool, gated: bool, bounded: bool
    ) -> dict:
        """The series of one estimator (module docstring), by short key."""
        r, dim, every = self.rec, len(axes), self.sc.trail_every
        size = min(scene_size(self.sc) / 30.0, 1.0)
        s = {
            "path": r.series(
                f"world/estimates/{name}/path",
                3,
                "points3d",
                every=every,
                color=color,
                radius=0.12 * size,
            ),
            "box": r.series(
                f"world/estimates/{name}/vehicle",
                3,
                "translation",
                every=every,
                color=color,
                half_size=(0.5 * size, 0.35 * size, 0.12 * size),
            ),
            "pos_norm": r.series(
                f"errors/{name}/position/norm", 1, names=[f"{name} |e_p|"], color=color
            ),
            "pos_axes": r.series(
                f"errors/{name}/position/axes", dim, names=[f"{name} e_{a}" for a in axes]
            ),
        }
        if velocity:
            s["vel_norm"] = r.series(
                f"errors/{name}/velocity/norm", 1, names=[f"{name} |e_v|"], color=color
            )
            s["vel_axes"] = r.series(
                f"errors/{name}/velocity/axes", dim, names=[f"{name} e_v{a}" for a in axes]
            )
        s["trace"] = r.series(
            f"observer/{name}/covariance_trace", 1, names=[f"{name} tr P"], color=color
        )
        s["nis"] = r.series(f"observer/{name}/nis", 1, skip_nan=True, names=[f"{name} NIS"])
        if gated:
            s["rejected"] = r.series(
                f"observer/{name}/rejected", 1, names=[f"{name} rejected"], color=color
            )
        if self.sc.has_wind:
            s["wind_norm"] = r.series(
                f"errors/{name}/wind/norm", 1, names=[f"{name} |e_w|"], color=color
            )
            s["wind_axes"] = r.series(
                f"errors/{name}/wind/axes", dim, names=[f"{name} e_w{a}" for a in axes]
            )
            s["wind"] = r.series(
                f"wind/{name}", dim, names=[f"{name} w_{a}" for a in axes], color=color
            )
        if bounded:
            s["bounds_box"] = r.series(
                f"world/estimates/{name}/bounds", 6, "boxes3d", every=every, color=color
            )
            s["bounds_err"] = r.series(
                f"errors/{name}/position/bounds",
                2 * dim,
                names=[f"{name} {a} {side} - true" for side in ("low", "high") for a in axes],
            )
            s["box_width"] = r.series(
                f"errors/{name}/position/box_width",
                dim,
                names=[f"{name} box width {a}" for a in axes],
            )
        return s

    def write_block(self, rows: LoggedRows, extra=None) -> None:
        """Write the ``m`` recorded rows of ``rows`` at once (see the module docstring for what goes where).

        ``extra(rows, steps)``, if given, fills further series for the recorder rows
        ``rows`` (a slice) of the physics ``steps``.
        """
        steps, times, truth_p = np.asarray(rows.steps), rows.times, rows.truth_p
        done, m = 0, len(steps)
        dim = self.sc.dimension
        while done < m:
            i = self.rec.rows(steps[done:], times[done:])
            src = slice(done, done + (i.stop - i.start))
            self.truth_path.buf[i, :dim] = truth_p[src]
            self.truth_box.buf[i, :dim] = truth_p[src]
            for name, s in self.est.items():
                self._write_estimator(s, name, rows, i, src)
            if self.sc.has_wind:
                assert rows.truth_wind is not None and rows.airspeed is not None, "with wind"
                self.wind_truth.buf[i] = rows.truth_wind[src]
                self.airspeed.buf[i, 0] = rows.airspeed[src]
            for h, series in enumerate(self.ranges):
                series.buf[i, 0] = rows.ranges[src, h]
            self.inputs.buf[i] = rows.inputs[src]
            if self.events is not None:
                self.events[0].buf[i, 0] = rows.events[src, 0]
                self.events[1].buf[i, 0] = rows.events[src, 1]
            if extra is not None:
                extra(i, steps[src])
            done = src.stop

    def _write_estimator(self, s: dict, name: str, rows: LoggedRows, i: slice, src: slice) -> None:
        """One estimator's series of the recorder rows ``i`` (rows ``src`` of ``rows``)."""
        dim = self.sc.dimension
        e, xh = rows.errors[name], rows.estimates[name][src]
        s["path"].buf[i, :dim] = xh[:, :dim]
        s["box"].buf[i, :dim] = xh[:, :dim]
        if "bounds_box" in s:
            b, tp = rows.bounds[name][src, :dim], rows.truth_p[src]
            s["bounds_box"].buf[i, :dim] = 0.5 * (b[..., 0] + b[..., 1])
            s["bounds_box"].buf[i, 3 : 3 + dim] = 0.5 * (b[..., 1] - b[..., 0])
            if dim == 2:
                s["bounds_box"].buf[i, 5] = 0.05
            s["bounds_err"].buf[i, :dim] = b[..., 0] - tp
            s["bounds_err"].buf[i, dim:] = b[..., 1] - tp
            s["box_width"].buf[i] = b[..., 1] - b[..., 0]
        ep = e["position"][src]
        s["pos_axes"].buf[i] = ep
        s["pos_norm"].buf[i, 0] = np.sqrt(np.einsum("ij,ij->i", ep, ep))
        if "vel_norm" in s:
            ev = e["velocity"][src]
            s["vel_axes"].buf[i] = ev
            s["vel_norm"].buf[i, 0] = np.sqrt(np.einsum("ij,ij->i", ev, ev))
        s["trace"].buf[i, 0] = rows.traces[name][src]
        s["nis"].buf[i, 0] = rows.nis[name][src]
        if "rejected" in s:
            s["rejected"].buf[i, 0] = rows.rejected[name][src]
        if "wind" in s:
            ew = e["wind"][src]
            s["wind_axes"].buf[i] = ew
            s["wind_norm"].buf[i, 0] = np.sqrt(np.einsum("ij,ij->i", ew, ew))
            s["wind"].buf[i] = xh[:, 2 * dim :]
