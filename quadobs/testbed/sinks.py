"""What an episode does with its rows: the block of preallocated arrays and the sinks that consume it.

The episode (:func:`quadobs.testbed.episode.run_episode`) fills one :class:`Block` per
block of steps: the world's rows (truth, readings, ``y``, ``u``), each estimator's record
rows (:meth:`~quadobs.estimators.base.Estimator.step_and_record`:
``[x_hat, tr P, NIS, rejected]``) and the bounds of set-valued estimators. Once per block
it hands the completed rows, as :class:`Rows` (errors computed once, vectorised), to every
sink:

=========================  ==========================================================
sink                       what it keeps, and its summary fragment
=========================  ==========================================================
:class:`ConvergenceSink`   final errors, ``time_to_1m``, ``time_to_0p1m`` per estimator
:class:`TraceSink`         the trajectories sampled every ``collect_every`` steps
:class:`BoundsSink`        how often the true state lies in the guaranteed bounds
:class:`ExcitationSink`    the live excitation monitor (``excitation``), its series
:class:`RecordingSink`     the ``.rrd`` recording (:class:`~.episode_log.EpisodeLog`)
:class:`ProgressSink`      the progress bar
=========================  ==========================================================

A sink has ``begin(context)``, ``block(rows)``, ``end(completed, interrupted) -> dict``
(merged into the summary by :func:`merge`), ``fail(completed, error)`` and ``close()``;
a :class:`StepSink` also acts between steps: ``first_due()`` and ``after_step(s, j)``
(called when ``s`` steps are complete, the last one being row ``j`` of the block; returns
the next ``s`` at which to call it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from quadobs.estimators.base import Estimator, Gated, SetValued, Subset, Switching
from quadobs.evaluation.convergence import ConvergenceTracker, json_time, state_errors
from quadobs.testbed.blocks import LEAD

if TYPE_CHECKING:
    from quadobs.recording.excitation import ExcitationLog

#: Steps before the end of an episode from which the recording sends its rows only when it closes.
SEND_AHEAD = 2 * LEAD

__all__ = [
    "Block",
    "BoundsSink",
    "ConvergenceSink",
    "EpisodeContext",
    "EpisodeFrame",
    "ExcitationSink",
    "ProgressSink",
    "RecordingSink",
    "Rows",
    "Sink",
    "StepSink",
    "TraceSink",
    "merge",
]

_NEVER = np.iinfo(np.int64).max


class Block:
    """The preallocated arrays of a block of steps (row ``j``: step ``k0 + j``).

    Parameters
    ----------
    world : World
        Its rows ``out`` and per-step ``events`` are the block's ``raw`` and ``events``.
    estimators : list of Estimator
    capacity : int
        Most steps per block.

    Attributes
    ----------
    raw : ndarray (capacity + 1, width)
        The world's rows (see :class:`~quadobs.testbed.worlds.base.Columns`).
    y, u : ndarray
        Views of the outputs ``(capacity + 1, q)`` and inputs ``(capacity + 1, p)``.
    rec : ndarray (E, capacity + 1, n + 3)
        Per estimator: the record rows ``[x_hat, tr P]`` before the step, ``[NIS, rejected]`` after it.
    bounded : list of (int, Estimator)
        The set-valued estimators and their index in ``bounds``.
    bounds : ndarray (B, capacity + 1, n, 2)
        Their interval bounds of ``x_k`` (before the step).
    k0 : int
        First step of the current block.
    """

    def __init__(self, world, estimators: list[Estimator], capacity: int) -> None:
        c = world.columns
        self.columns, self.raw, self.events = c, world.out, world.events
        self.y, self.u = self.raw[:, c.y], self.raw[:, c.u]
        self.estimators = list(estimators)
        n = c.n
        self.rec = np.full((len(self.estimators), capacity + 1, n + 3), np.nan)
        self.bounded = list(enumerate(e for e in self.estimators if isinstance(e, SetValued)))
        self.bounds = np.full((len(self.bounded), capacity + 1, n, 2), np.nan)
        self.k0 = 0

    def record_final(self, j: int) -> None:
        """Row ``j`` holds ``t_K``: the estimates and bounds there, no step, no measurement."""
        n = self.columns.n
        for b, bounded in self.bounded:
            self.bounds[b, j] = bounded.bounds
        for e, est in enumerate(self.estimators):
            row = self.rec[e, j]
            row[:n] = est.x_hat
            row[n] = est.covariance_trace
            row[n + 1] = np.nan
            row[n + 2] = est.rejected if isinstance(est, Gated) else np.nan
        truth = self.raw[j, self.columns.truth].copy()
        self.raw[j] = np.nan
        self.raw[j, self.columns.truth] = truth


class Rows:
    """The completed rows ``[0, count)`` of a block, as the sinks read them.

    Attributes
    ----------
    ks, t : ndarray (m,)
        Physics steps and their times.
    truth : ndarray (m, n)
    estimates, traces, nis, rejected : dict of str to ndarray
        Per estimator name: ``x_hat (m, n)``, ``tr P (m,)``, NIS ``(m,)``, rejected so far ``(m,)``.
    errors : dict of str to dict of str to ndarray
        Per estimator: :func:`~quadobs.evaluation.convergence.state_errors` of its rows.
    bounds : dict of str to ndarray (m, n, 2)
    events : ndarray (m, 2)
        Per step: outliers delivered, samples dropped (0 on the final row, which has no step).
    """

    def __init__(
        self, block: Block, count: int, steps: int, dt: float, dim: int, has_wind: bool
    ) -> None:
        n = block.columns.n
        self.block, self.count = block, count
        self.ks = block.k0 + np.arange(count)
        self.t = self.ks * dt
        self.truth = X = block.raw[:count, block.columns.truth]
        self.estimates, self.traces, self.nis, self.rejected, self.errors = {}, {}, {}, {}, {}
        for e, est in enumerate(block.estimators):
            r = block.rec[e, :count]
            self.estimates[est.name], self.traces[est.name] = r[:, :n], r[:, n]
            self.nis[est.name], self.rejected[est.name] = r[:, n + 1], r[:, n + 2]
            self.errors[est.name] = state_errors(dim, has_wind, r[:, :n], X)
        self.bounds = {est.name: block.bounds[b, :count] for b, est in block.bounded}
        self.events = block.events[:count].copy()
        self.events[max(steps - block.k0, 0) :] = 0


@dataclass(frozen=True, eq=False)
class EpisodeFrame:
    """What the episode loop and its sinks know of a run besides its world and estimators.

    A simulated episode's frame comes from its scenario (:meth:`of`); a replay's from its
    log (:func:`quadobs.testbed.logs.replay.run_replay`).

    Attributes
    ----------
    name : str
    steps : int
        Steps ``K`` of the loop (rows ``0 .. K``, the last one the final row).
    dt : float
        Step (s); row ``k`` is at ``t_k = k dt``.
    dimension : int
        Dimension of the motion (2 or 3).
    beacons : ndarray (q_b, dimension)
    physics_rate : float
        Steps per second (``1 / dt``).
    seed : int
    description, source : str
        One line for the recording; the file the run was read from (``""``: none).
    has_wind : bool
        The state holds an air velocity and a wind, the outputs an airspeed.
    record_every, trail_every : int
        Steps between recorded rows, and between 3-D samples (trails and vehicle boxes).
    sensor_events : bool
        The sensor layer injects outliers or drops samples: their counts are recorded.
    excitation : bool
        The recording's blueprint shows the excitation monitor's views.
    input_name : str
        The measured input's series, ``measurements/<input_name>``.
    input_labels : tuple of str
        Its columns (as many as the world's ``u``).
    beacon_labels : tuple of str
        Labels of the beacons in the recording.
    beacon_ids : tuple of int
        The beacons' ids, which name their range series (``measurements/range/<id>``); empty:
        their indices (a simulated scenario's ids).
    time_origin : float
        The estimators' clock at row 0 (s): a replayed log's first grid time, its own stamps;
        0 for a simulated episode, whose estimators count from the row times. Their records
        (a divergence, a start-up) are reported on the rows' clock, less it.
    """

    name: str
    steps: int
    dt: float
    dimension: int
    beacons: np.ndarray
    physics_rate: float
    seed: int = 0
    description: str = ""
    source: str = ""
    has_wind: bool = False
    record_every: int = 1
    trail_every: int = 1
    sensor_events: bool = False
    excitation: bool = False
    input_name: str = "accelerometer"
    input_labels: tuple = ()
    beacon_labels: tuple = ()
    beacon_ids: tuple = ()
    time_origin: float = 0.0

    @classmethod
    def of(cls, scenario) -> EpisodeFrame:
        """The frame of a scenario's episode: 3-D samples at most every 10 ms of simulated time."""
        axes = "xyz"[: scenario.dimension]
        noise = scenario.noise
        return cls(
            name=scenario.name,
            steps=scenario.steps,
            dt=scenario.dt,
            dimension=scenario.dimension,
            beacons=scenario.beacons,
            physics_rate=scenario.physics_rate,
            seed=scenario.seed,
            description=scenario.description,
            source=scenario.source,
            has_wind=scenario.has_wind,
            record_every=scenario.record_every,
            trail_every=math.lcm(
                max(1, int(round(scenario.physics_rate / 100.0))), scenario.record_every
            ),
            sensor_events=bool(noise.outlier_probability or noise.dropout),
            excitation=scenario.excitation.monitor,
            input_labels=tuple(f"a_{a}" for a in axes),
            beacon_labels=tuple(f"beacon {h}" for h in range(scenario.beacons.shape[0])),
        )


@dataclass(frozen=True)
class EpisodeContext:
    """What the sinks learn at ``begin``: the frame, the estimators, the block and the estimators' clock.

    ``clock`` (``(E,)``, seconds) accumulates the wall time of each estimator's steps when
    the episode times them (``None`` otherwise). ``world`` is the episode's world (``None``
    where the caller gives none), for a sink that reads what the world's rows do not hold
    (:class:`~quadobs.testbed.logs.export.LogExportSink`: a quadrotor's body IMU).
    """

    frame: EpisodeFrame
    estimators: tuple
    block: Block
    clock: np.ndarray | None = None
    world: Any = None

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.estimators]


class Sink:
    """A consumer of an episode's rows (see the module docstring); every method defaults to nothing."""

    def begin(self, ctx: EpisodeContext) -> None:
        self.ctx = ctx

    def block(self, rows: Rows) -> None:
        pass

    def end(self, completed: int, interrupted: bool) -> dict:
        return {}

    def fail(self, completed: int, error: BaseException) -> None:
        pass

    def close(self) -> None:
        pass

    def publish(self) -> None:
        """After the summary is written: move the sink's files into place (default: nothing)."""


class StepSink(Sink):
    """A sink that also acts between steps, at the step counts it asks for."""

    def first_due(self) -> int:
        """The first count of completed steps at which to call :meth:`after_step`."""
        raise NotImplementedError

    def after_step(self, s: int, j: int) -> int:
        """Called when ``s`` steps are complete (the last one row ``j`` of the block); returns the next ``s``."""
        raise NotImplementedError


def merge(fragments) -> dict:
    """Merge summary fragments: nested dictionaries are merged key by key, later values win.

    Examples
    --------
    >>> merge([{"estimators": {"a": {"x": 1}}}, {"estimators": {"a": {"y": 2}}, "z": 3}])
    {'estimators': {'a': {'x': 1, 'y': 2}}, 'z': 3}
    """
    out: dict = {}
    for frag in fragments:
        for key, val in frag.items():
            if isinstance(val, dict) and isinstance(out.get(key), dict):
                out[key] = merge([out[key], val])
            else:
                out[key] = val
    return out


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


class ConvergenceSink(Sink):
    """Final errors and the times after which the position error stays below 1 m and 0.1 m."""

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        self.trackers = {n: ConvergenceTracker((1.0, 0.1)) for n in ctx.names}
        self.last: dict[str, dict[str, np.ndarray]] = {}

    def block(self, rows: Rows) -> None:
        for name, err in rows.errors.items():
            ep = err["position"]
            self.trackers[name].update_many(rows.t, np.sqrt(np.einsum("ij,ij->i", ep, ep)))
            self.last[name] = {key: val[-1].copy() for key, val in err.items()}

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {}
        for name in self.ctx.names:
            e = self.last.get(name)
            t1, t01 = (json_time(t) for t in self.trackers[name].times())
            entry = {
                "final_position_error": _norm(e, "position"),
                "final_velocity_error": _norm(e, "velocity"),
                "time_to_1m": t1,
                "time_to_0p1m": t01,
            }
            if e and "wind" in e:
                entry["final_wind_error"] = _norm(e, "wind")
                entry["final_air_velocity_error"] = _norm(e, "air_velocity")
            per[name] = entry
        return {"estimators": per}


def _norm(errors, key) -> float | None:
    """The norm of the error ``key`` (None without the error, or where the state has no such part)."""
    return _finite_or_none(float(np.linalg.norm(errors[key]))) if errors and key in errors else None


class TraceSink(StepSink):
    """The trajectories sampled every ``every`` steps (:attr:`EpisodeResult.trace <quadobs.testbed.episode.EpisodeResult>`)."""

    def __init__(self, every: int, steps: int) -> None:
        self.every, self.steps = int(every), int(steps)

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        T, n = self.steps // self.every + 1, ctx.block.columns.n
        names = ctx.names
        self.trace: dict[str, Any] = {
            "time": np.full(T, np.nan),
            "truth": np.full((T, n), np.nan),
            "estimates": {nm: np.full((T, n), np.nan) for nm in names},
            "covariances": {nm: np.full((T, n, n), np.nan) for nm in names},
            "nis": {nm: np.full(T, np.nan) for nm in names},
            "nis_dof": {nm: np.zeros(T, dtype=int) for nm in names},
            "bounds": {},
        }
        self._covariances(0)

    def _covariances(self, s: int) -> None:
        for est in self.ctx.estimators:
            cov = est.x_covariance
            if cov is not None:
                self.trace["covariances"][est.name][s // self.every] = cov

    def first_due(self) -> int:
        return self.every

    def after_step(self, s: int, j: int) -> int:
        """The covariances at ``t_s`` (after ``s`` steps), sampled rows only."""
        self._covariances(s)
        return s + self.every

    def block(self, rows: Rows) -> None:
        sel = np.flatnonzero(rows.ks % self.every == 0)
        idx = rows.ks[sel] // self.every
        tr = self.trace
        tr["time"][idx] = rows.t[sel]
        tr["truth"][idx] = rows.truth[sel]
        Y = rows.block.y[: rows.count][sel]
        for est in self.ctx.estimators:
            name = est.name
            tr["estimates"][name][idx] = rows.estimates[name][sel]
            nis = rows.nis[name][sel]
            tr["nis"][name][idx] = nis
            Ys = Y[:, est.outputs] if isinstance(est, Subset) else Y
            dof = np.count_nonzero(~np.isnan(Ys), axis=1)
            tr["nis_dof"][name][idx] = np.where(np.isfinite(nis), dof, 0)
            if name in rows.bounds:
                T, n = tr["time"].shape[0], rows.truth.shape[1]
                tr["bounds"].setdefault(name, np.full((T, n, 2), np.nan))[idx] = rows.bounds[name][
                    sel
                ]


class BoundsSink(Sink):
    """Set-valued estimators: the fraction of rows whose true state lies in the bounds, the final width."""

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        self.contained: dict[str, list[Any]] = {
            est.name: [0, 0, None] for _, est in ctx.block.bounded
        }

    def block(self, rows: Rows) -> None:
        X = rows.truth
        for name, B in rows.bounds.items():
            c = self.contained[name]
            c[0] += int(np.all((B[..., 0] <= X) & (X <= B[..., 1]), axis=1).sum())
            c[1] += rows.count
            c[2] = B[-1].copy()

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {
            name: {
                "bounds": {
                    "contained_fraction": inside / n if n else None,
                    "final_width": None if b is None else (b[:, 1] - b[:, 0]).tolist(),
                }
            }
            for name, (inside, n, b) in self.contained.items()
        }
        return {"estimators": per} if per else {}


class ExcitationSink(StepSink):
    """The live excitation monitor: fed the applied inputs a chunk at a time, its series recorded.

    The monitor takes the inputs at the step that completes its chunk (:meth:`after_step`),
    and the rest of a block's inputs at the block's end (:meth:`block`). What it has taken
    is its own count of steps, so a stop anywhere feeds it no step twice.

    Parameters
    ----------
    monitor : ExcitationMonitor
    recorder : Recorder, optional
        Records the monitor's series (:class:`~quadobs.recording.excitation.ExcitationLog`).
    """

    def __init__(self, monitor, recorder=None) -> None:
        self.monitor, self.recorder = monitor, recorder
        self.log: ExcitationLog | None = None

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        if self.recorder is not None:
            from quadobs.recording.excitation import ExcitationLog

            self.log = ExcitationLog(self.recorder, self.monitor, list(ctx.estimators))

    def first_due(self) -> int:
        return self.monitor.steps + self.monitor.room

    def fill(self, rows: slice, steps: np.ndarray) -> None:
        """The monitor's series of the recorded rows (see :meth:`ExcitationLog.fill`)."""
        if self.log is not None:
            self.log.fill(rows, steps)

    def after_step(self, s: int, j: int) -> int:
        m, block = self.monitor, self.ctx.block
        if m.push_many(block.u[m.steps - block.k0 : j + 1]):  # the window measure was recomputed
            if self.log is not None:
                self.log.capture(s)
            if m.warning is not None:
                message = m.pop_warning()
                if self.log is not None:
                    self.log.warn(message, s, s * self.ctx.frame.dt)
        return s + m.room

    def feed(self, stop: int) -> None:
        """Feed the block's inputs before row ``stop`` that the monitor has not taken (never past its chunk)."""
        m, k0 = self.monitor, self.ctx.block.k0
        take = min(k0 + stop - m.steps, m.room)
        if take > 0:
            m.push_many(self.ctx.block.u[stop - take : stop])

    def block(self, rows: Rows) -> None:
        self.feed(min(rows.count, self.ctx.frame.steps - rows.block.k0))

    def end(self, completed: int, interrupted: bool) -> dict:
        return {"excitation": self.monitor.summary()}


class ProgressSink(Sink):
    """A progress bar on stderr (``tqdm``)."""

    def begin(self, ctx: EpisodeContext) -> None:
        from tqdm import tqdm

        super().begin(ctx)
        sc = ctx.frame
        self.bar = tqdm(total=sc.steps, unit="step", unit_scale=True, desc=sc.name, leave=False)

    def block(self, rows: Rows) -> None:
        self.bar.update(min(rows.count, self.ctx.frame.steps - rows.block.k0))

    def __init__(self) -> None:
        self.bar = None

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class RecordingSink(Sink):
    """The episode's ``.rrd`` recording: every ``record_every``-th row, its event log, closed at the end.

    Parameters
    ----------
    recorder : Recorder
    extras : list of callable
        ``fill(rows, steps)`` of further series written with each recorded row (the
        excitation monitor's); may be appended to before :meth:`begin`.
    send_each_block : bool
        At the end of a block, with half the recorder's buffers filled or more and more
        than :data:`SEND_AHEAD` steps to go, send the rows and wait for rerun to encode them
        (for a world computing the physics ahead,
        :attr:`~quadobs.testbed.worlds.base.World.computes_ahead`); otherwise the recorder
        sends when its buffers are full.
    """

    def __init__(self, recorder, extras=None, *, send_each_block: bool = False) -> None:
        self.recorder, self.extras, self.send_each_block = (
            recorder,
            list(extras or []),
            send_each_block,
        )

    def begin(self, ctx: EpisodeContext) -> None:
        from quadobs.testbed.episode_log import EpisodeLog

        super().begin(ctx)
        self.gated = [e for e in ctx.estimators if isinstance(e, Gated) and e.gate is not None]
        self.log = EpisodeLog(
            self.recorder,
            ctx.frame,
            ctx.names,
            bounded=[e.name for _, e in ctx.block.bounded],
            gated=[e.name for e in self.gated],
            velocity=ctx.block.columns.n >= 2 * ctx.frame.dimension,
        )
        self.events = np.zeros(2, dtype=np.int64)  # outliers delivered, samples dropped, so far
        self.rejected = {
            e.name: 0 for e in self.gated
        }  # rejected corrections so far (recorded rows)
        self.switching = {
            e.name: (e, 0) for e in ctx.estimators if isinstance(e, Switching)
        }  # switches logged

    def block(self, rows: Rows) -> None:
        from quadobs.testbed.episode_log import LoggedRows

        self._log_switches()
        ev = self.events + np.cumsum(rows.events, axis=0)
        self.events[:] = ev[-1]
        for e in self.gated:
            self.rejected[e.name] = int(rows.rejected[e.name][-1])
        sel = np.flatnonzero(rows.ks % self.ctx.frame.record_every == 0)
        if not sel.size:
            return
        sc, c, raw = self.ctx.frame, rows.block.columns, rows.block.raw[: rows.count]
        dim = sc.dimension
        X = rows.truth[sel]
        air = (
            np.sqrt(2.0 * rows.block.y[: rows.count, sc.beacons.shape[0]][sel])
            if sc.has_wind
            else None
        )
        self.log.write_block(
            LoggedRows(
                steps=rows.ks[sel],
                times=rows.t[sel],
                truth_p=X[:, :dim],
                truth_wind=X[:, 2 * dim :] if sc.has_wind else None,
                errors={
                    nm: {key: val[sel] for key, val in err.items()}
                    for nm, err in rows.errors.items()
                },
                estimates={nm: v[sel] for nm, v in rows.estimates.items()},
                traces={nm: v[sel] for nm, v in rows.traces.items()},
                nis={nm: v[sel] for nm, v in rows.nis.items()},
                ranges=raw[sel, c.measured],
                airspeed=air,
                inputs=rows.block.u[: rows.count][sel],
                bounds={nm: v[sel] for nm, v in rows.bounds.items()},
                rejected={e.name: rows.rejected[e.name][sel] for e in self.gated},
                events=ev[sel],
            ),
            extra=self._extra,
        )
        rec = self.recorder
        if (
            self.send_each_block
            and rec.n >= rec.capacity // 2
            and self.ctx.frame.steps - int(rows.ks[-1]) > SEND_AHEAD
        ):
            # Sent now, and rerun's encoding waited for, while the physics of the blocks ahead
            # is still computing beside it (the reader would wait for it anyway): the encoding
            # then never competes with the physics for a core. Half a buffer at least, so that
            # the file holds few, long chunks; the last blocks' rows go together when the
            # recording closes. Without physics ahead, the recorder sends when its buffers
            # are full, without waiting.
            rec.flush(wait=True)

    def _extra(self, rows: slice, steps: np.ndarray) -> None:
        for fill in self.extras:
            fill(rows, steps)

    def _log_switches(self) -> None:
        """One event-log line per mode switch not logged yet, at the step it happened."""
        for name, (est, done) in self.switching.items():
            for step, old, new, reason in est.switches[done:]:
                self._text(f"{name}: {old} -> {new} ({reason})", "INFO", step)
            self.switching[name] = (est, len(est.switches))

    def _text(self, message: str, level: str, step: int) -> None:
        self.recorder.text("events", message, level=level, step=step, time=step * self.ctx.frame.dt)

    def end(self, completed: int, interrupted: bool) -> dict:
        """The event log's last lines: the interruption, and each gate's rejections beside the injected events."""
        self._log_switches()
        if interrupted:
            self._text(
                f"interrupted at t = {completed * self.ctx.frame.dt:.3f} s (step {completed})",
                "WARN",
                completed,
            )
        for e in self.gated:
            count = self.rejected[e.name]
            self._text(
                f"{e.name}: {count} corrections rejected by the NIS gate {e.gate:g} "
                f"({int(self.events[0])} outliers injected, {int(self.events[1])} samples dropped)",
                "WARN" if count else "INFO",
                completed,
            )
        return {}

    def fail(self, completed: int, error: BaseException) -> None:
        self.recorder.fail()  # the target keeps the previous recording; the staging file keeps this one
        dt = self.ctx.frame.dt
        self._text(
            f"stopped by an error at t = {completed * dt:.3f} s (step {completed}): {error!r}",
            "ERROR",
            completed,
        )

    def close(self) -> None:
        self.recorder.close(publish=False)  # renamed into place by publish(), after the summary

    def publish(self) -> None:
        self.recorder.publish()
