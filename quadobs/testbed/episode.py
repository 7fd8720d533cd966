"""One episode: a world, the sensor layer, the estimators and the sinks, a block of steps at a time.

.. code-block:: text

    world = PointMassWorld(scenario, sensors)        # MuJoCo point mass, sensor layer fused (or any World)
    for each block of steps:
        world.begin_block(k0, count); world.fill(count)   # truth, readings, y_k, u_k per row
        block path:     for est in estimators: est.step_block(U, Y, rows)   # one call each
        per-step path:  for each step k of the block:    # (closed loop: world.step(j, x_hat))
                            for est in estimators: est.step_and_record(u_k, y_k, row_k)
        for sink in sinks: sink.block(rows)              # errors computed once per block
    summary = merge(sink.end() for sink in sinks)

The data path of physics step ``k`` (time ``t_k = k dt``): the world gives the true state
``x_k`` and, after ``mj_step`` with the commanded acceleration held over
``[t_k, t_{k+1})``, the readings that describe ``t_k`` (ranges, accelerometer, airspeed)
with the sensor layer applied (noise, rates, dropouts, outliers): ``y_k``, ``u_k``. Each
estimator then corrects with ``y_k`` and predicts to ``t_{k+1}`` with ``u_k`` held, and
keeps its record row ``[x_hat_k, tr P_k, NIS_k, rejected_k]``. After the last step the
final row ``K`` (``t_K = duration``) is kept, so the summary's final errors compare
``x_hat_K`` with MuJoCo's ``x_K``.

Cost. The per-step path allocates nothing but row views: the world's compiled read
(:class:`~quadobs.testbed.worlds.BlockStepper`) and, per estimator,
:meth:`~quadobs.estimators.base.Estimator.step_and_record` (one compiled call for the
augmented observer). Every value of step ``k`` lands in row ``k`` of the preallocated
:class:`~quadobs.testbed.sinks.Block`; the sinks (:mod:`quadobs.testbed.sinks`) read them
once per block, vectorised.

Two paths, the same summary bit for bit (tested). The block path, the default where the
world is open loop and every estimator is a compiled
:class:`~quadobs.estimators.base.BlockStep`: the world fills the block in one call
(``mujoco.rollout`` and one compiled read with the sensor layer) and each estimator
consumes the block's rows in one compiled call, split only where a sink is due between
steps (:class:`~quadobs.testbed.sinks.StepSink`). The per-step path (``path="step"``, and
always for closed-loop worlds or other estimators): ``mj_step`` and the compiled read
once per step, then each estimator's ``step_and_record`` once per row.

One loop for every world. :func:`run_episode` builds a scenario's parts
(:func:`scenario_parts`: its :class:`~quadobs.testbed.sinks.EpisodeFrame`, world, sensor
layer and estimators) and hands them to :func:`run_loop`, which runs :class:`_Episode`
over them, writes the summary and publishes the outputs. A replay of a logged run
(:func:`quadobs.testbed.logs.replay.run_replay`) hands it a
:class:`~quadobs.testbed.worlds.replay.ReplayWorld`, the frame of its log and its own
summary: the same loop, sinks and recording layout.

Stops. A block's sensor events are counted and its rows handed to the sinks inside
:func:`~quadobs.errors.deferred_interrupts`; a Ctrl-C (or SIGTERM) anywhere else hands the
sinks the rows of the steps completed so far, so every completed row reaches the
recording and the summary exactly once.
"""

from __future__ import annotations

import functools
import time as _time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from quadobs.errors import QuadobsError, RunFault, deferred_interrupts
from quadobs.estimators.base import BlockStep, Counted, Gated, Immersed, SetValued, Switching
from quadobs.testbed.blocks import block_count
from quadobs.testbed.divergence import DivergenceSink, invalidate_diverged
from quadobs.testbed.outputs import check_outputs, write_fault_summary
from quadobs.testbed.registry import build_estimators, default_estimators
from quadobs.testbed.scenario import Scenario

if TYPE_CHECKING:
    from quadobs.core.immersion import Immersion
from quadobs.testbed.sensors import SensorModel, initial_guess, spawn_streams
from quadobs.testbed.sinks import (
    Block,
    BoundsSink,
    ConvergenceSink,
    EpisodeContext,
    EpisodeFrame,
    ExcitationSink,
    ProgressSink,
    RecordingSink,
    Rows,
    Sink,
    StepSink,
    TraceSink,
    merge,
)

__all__ = [
    "PATHS",
    "WALL_CLOCK_KEYS",
    "EpisodeResult",
    "run_episode",
    "run_loop",
    "scenario_parts",
    "write_json_atomic",
]

#: How :func:`run_episode` advances: ``"auto"`` (the block path where it applies), ``"step"``.
PATHS = ("auto", "step")

_BLOCK = 8192

#: The summary's only fields measured on the wall clock: everything else is a function of
#: the scenario and its seed, bit for bit, in any process.
WALL_CLOCK_KEYS = ("steps_per_second", "wall_time")


@dataclass
class EpisodeResult:
    """What :func:`run_episode` returns.

    Attributes
    ----------
    summary : dict
        The JSON summary (see the README for its keys).
    trace : dict or None
        With ``collect_every > 0``: ``time (T,)``, ``truth (T, n)``, and per estimator
        ``estimates[name] (T, n)`` and ``covariances[name] (T, n, n)`` (NaN when the
        estimator has none), sampled every ``collect_every`` steps; ``nis[name] (T,)`` and
        ``nis_dof[name] (T,)``, the NIS of the update made with the outputs of that step
        and its degrees of freedom (NaN and 0 without one), and ``bounds[name] (T, n, 2)``
        for estimators exposing interval ``bounds``.
    """

    summary: dict
    trace: dict | None = None


def write_json_atomic(path: str | Path, data: dict) -> None:
    """Write JSON to a staging file beside ``path`` and rename it into place (:func:`quadobs.testbed.outputs.write_json_staged`)."""
    from quadobs.testbed.outputs import write_json_staged

    write_json_staged(path, data)


def single_threaded_blas():
    """A context in which BLAS and LAPACK run on the calling thread (``threadpoolctl``; no-op without it).

    The estimators' matrices are tiny: a threaded BLAS gains nothing on them, and its
    worker threads, which spin for a while after each call, take a second core (or the
    other half of a hyperthreaded one) from the simulation loop; on a 2-core machine that
    made every step of the loop up to twice as slow.
    """
    controller = _blas_controller()
    if controller is None:  # pragma: no cover - optional at run time
        from contextlib import nullcontext

        return nullcontext()
    return controller.limit(limits=1, user_api="blas")


@functools.lru_cache(maxsize=1)
def _blas_controller():
    """The process's ``threadpoolctl.ThreadpoolController``, found once (the search of the loaded
    libraries takes milliseconds, which a campaign of short episodes would pay per episode)."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - optional at run time
        return None
    return ThreadpoolController()


def _single_threaded(fn):
    """Run ``fn`` inside :func:`single_threaded_blas`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_threaded_blas():
            return fn(*args, **kwargs)

    return wrapper


@_single_threaded
def run_episode(
    scenario: Scenario,
    *,
    estimators: list[str] | None = None,
    out: str | Path | None = None,
    summary_path: str | Path | None = None,
    progress: bool = False,
    collect_every: int = 0,
    flush_rows: int = 8192,
    world=None,
    path: str = "auto",
    sinks=(),
) -> EpisodeResult:
    """Simulate ``scenario`` in a world, run the estimators every physics step, record and summarise.

    Parameters
    ----------
    scenario : Scenario
    estimators : list of str, optional
        Names (see :func:`quadobs.testbed.registry.available_estimators`); default: the augmented
        observer and the scenario's variants of it.
    out : path, optional
        ``.rrd`` recording to write (checked for writability before the simulation starts).
    summary_path : path, optional
        JSON summary to write (atomically).
    progress : bool
        Show a progress bar on stderr.
    collect_every : int
        Also return the trajectories, sampled every ``collect_every`` steps (0: do not).
    flush_rows : int
        Rows buffered between sends to the recording.
    world : callable, optional
        ``world(scenario, sensors, capacity) -> World`` (:class:`~quadobs.testbed.worlds.base.World`);
        default :class:`~quadobs.testbed.worlds.PointMassWorld`.
    path : {"auto", "step"}
        ``"auto"``: the block path (see the module docstring) where the world is open loop
        and every estimator consumes blocks in one compiled call, else the per-step path;
        ``"step"``: the per-step path. The summaries are the same bits.
    sinks : sequence of Sink
        Further sinks, run after the episode's own (e.g. a log export,
        :class:`quadobs.testbed.logs.export.LogExportSink`).

    Returns
    -------
    EpisodeResult
        The summary (also written to ``summary_path``); ``summary["interrupted"]`` is true
        when the run was stopped by Ctrl-C, in which case the recording and the summary
        cover every step up to the stop.

    Raises
    ------
    QuadobsError
        Bad input, or an output path that cannot be written (checked before the simulation
        starts; nothing is created).
    RunFault
        The run could not go on (a recording that cannot be written, a physics fault): the
        summary written names the error and has no figures (:mod:`quadobs.testbed.outputs`).
    Exception
        An error raised inside the loop (by an estimator, say) propagates after the
        recording is closed holding every step completed before it, with the error in
        ``events``; no summary is written.

    Notes
    -----
    BLAS and LAPACK run single-threaded during the episode (:func:`single_threaded_blas`).
    """
    if scenario.kind not in ("vehicle", "quadrotor"):
        raise QuadobsError(
            f"scenario {scenario.name!r}: kind {scenario.kind!r} is not a MuJoCo vehicle scenario"
        )
    names = list(estimators) if estimators else default_estimators(scenario)
    if path not in PATHS:
        raise QuadobsError(f"path: expected one of {PATHS}, got {path!r}")
    check_outputs(
        {"summary": summary_path, "recording": out},
        {"scenario": scenario.source, "model": scenario.model},
    )
    parts = scenario_parts(scenario, names, world)

    def summarise(merged, completed, wall, interrupted):
        return _summarise(
            scenario, names, merged, completed, wall, parts["sensors"], out, interrupted
        )

    summary, episode = run_loop(
        summarise,
        summary_path=summary_path,
        out=out,
        flush_rows=flush_rows,
        progress=progress,
        collect_every=collect_every,
        path=path,
        sinks=sinks,
        **parts,
    )
    return EpisodeResult(summary, episode.trace.trace if episode.trace is not None else None)


def scenario_parts(scenario: Scenario, names: list[str], world=None) -> dict:
    """A scenario's episode parts: ``frame``, ``world``, ``estimators``, ``sensors``, ``check_physics``, ``monitor``.

    The sensor layer's streams come from the scenario's seed; the estimators start at the
    scenario's initial guess (:func:`~quadobs.testbed.sensors.initial_guess`).
    """
    from quadobs.testbed.excitation import scenario_monitor
    from quadobs.testbed.worlds import (
        PointMassWorld,  # the MuJoCo layer, imported only to run episodes
    )
    from quadobs.testbed.worlds.model import physics_check

    streams = spawn_streams(scenario.seed)
    sensors = SensorModel(scenario, streams)
    if world is None and scenario.kind == "quadrotor":  # the quadrotor flown by its controller
        from quadobs.testbed.worlds.quadrotor import QuadrotorWorld as world
    if world is None and scenario.radio is not None:  # the point mass measuring with its radio
        from quadobs.testbed.worlds.radio_feed import RadioPointMassWorld as world
    w = (world or PointMassWorld)(scenario, sensors, _BLOCK)
    check = physics_check(w, scenario)  # MuJoCo's warnings, after every block
    x0 = initial_guess(scenario, w.state(), streams["initial"])
    ests = build_estimators(scenario, names, x0)
    for est in ests:  # an IMU-driven estimator reads the world's latest body IMU sample
        if hasattr(est, "bind_imu") and hasattr(w, "body_imu"):
            est.bind_imu(w.body_imu)
    return {
        "frame": EpisodeFrame.of(scenario),
        "world": w,
        "estimators": ests,
        "sensors": sensors,
        "check_physics": check,
        "monitor": scenario_monitor(scenario, _scenario_immersion(scenario, ests)),
    }


def _scenario_immersion(scenario: Scenario, estimators) -> Immersion | None:
    """An estimator's immersion of the scenario's whole system by the scenario's method, if one has it (the
    excitation monitor then uses it rather than computing it again); ``None`` otherwise."""
    system, method = scenario.system(), scenario.observer.immersion
    for est in estimators:
        im = est.immersion if isinstance(est, Immersed) else None
        if (
            im is not None
            and im.method == method
            and all(
                np.array_equal(getattr(im.system, k), getattr(system, k))
                for k in ("A", "B", "C", "d")
            )
        ):
            return im
    return None


@_single_threaded
def run_loop(summarise, *, summary_path=None, **parts) -> tuple[dict, _Episode]:
    """The episode loop over any world, then the summary written and the outputs published.

    Parameters
    ----------
    summarise : callable
        ``summarise(merged, completed, wall, interrupted) -> dict``: the summary from the
        sinks' merged fragments, the steps completed, the wall time (s) and whether the run
        was interrupted.
    summary_path : path, optional
        JSON summary to write (atomically); the outputs must have been checked.
    **parts
        :class:`_Episode`'s arguments: ``frame``, ``world``, ``estimators`` and its options.

    Returns
    -------
    summary : dict
    episode : _Episode
        Its sinks (the trace) and sensor layer.

    Raises
    ------
    RunFault
        After a fault summary naming it is written to ``summary_path``.
    KeyboardInterrupt
        A stop before the first step completed (the previous outputs stay).
    """
    episode = _Episode(**parts)
    wall0 = _time.perf_counter()
    try:
        fragments, interrupted = episode.run()
    except (
        RunFault
    ) as exc:  # a full disk, a physics fault: the summary says so, then the error goes on
        write_fault_summary(summary_path, episode.frame, episode.completed, exc)
        raise
    wall = _time.perf_counter() - wall0
    if (
        interrupted and not episode.completed
    ):  # stopped before the first step: the previous files stay
        raise KeyboardInterrupt
    with deferred_interrupts():  # the summary, then the recording, are replaced together
        summary = invalidate_diverged(
            summarise(merge(fragments), episode.completed, wall, interrupted)
        )
        if summary_path is not None:
            try:
                write_json_atomic(summary_path, summary)
            except (
                QuadobsError
            ) as exc:  # a full disk at the end: the run's figures are still returned
                summary["output_error"] = str(exc)
        for sink in episode.sinks:
            sink.publish()
    return summary, episode


def _timed(step, clock: np.ndarray, e: int):
    """``step`` timed into ``clock[e]`` (one ``perf_counter`` pair per call: about 0.1 us)."""
    perf = _time.perf_counter

    def timed(u, y, out):
        t0 = perf()
        step(u, y, out)
        clock[e] += perf() - t0

    return timed


class _Episode:
    """The loop's parts (frame, world, block, estimators, sinks) and the position of its loop.

    Parameters
    ----------
    frame : EpisodeFrame
        Name, steps, step, dimension, beacons, ... of the run (:class:`~quadobs.testbed.sinks.EpisodeFrame`).
    world : World
    estimators : list of Estimator
        Each at its initial state.
    sensors : SensorModel, optional
        The world's sensor layer (its counts end in the summary).
    check_physics : callable, optional
        ``check(k0, count)`` after every block (MuJoCo's warnings).
    monitor : ExcitationMonitor, optional
        The live excitation monitor of the applied input.
    out, flush_rows, progress, collect_every, path
        As in :func:`run_episode`.
    sinks : sequence of Sink
        Further sinks, after the episode's own and the world's.
    timed : bool
        Time each estimator's steps into :attr:`clock` (the sinks' ``ctx.clock``).
    """

    def __init__(
        self,
        frame,
        world,
        estimators,
        *,
        sensors=None,
        check_physics=None,
        monitor=None,
        out=None,
        flush_rows=8192,
        progress=False,
        collect_every=0,
        path="auto",
        sinks=(),
        timed=False,
    ) -> None:
        from quadobs.testbed.worlds.base import World

        self.frame, self.steps, self.world, self.sensors = frame, frame.steps, world, sensors
        self.check_physics = check_physics or (lambda k0, count: None)
        ests = list(estimators)
        self.block = block = Block(self.world, ests, _BLOCK)
        self.clock = np.zeros(len(ests)) if timed else None
        feed = getattr(self.world, "recorder", None)  # a world that feeds measurements in time
        self.slots = [
            (self._clocked(feed(est) if feed else est.step_and_record, e), block.rec[e])
            for e, est in enumerate(ests)
        ]
        self.blockwise = (
            path == "auto"
            and not self.world.closed_loop
            and all(
                isinstance(e, BlockStep) and e.blockwise and not isinstance(e, SetValued)
                for e in ests
            )
        )
        self.block_slots = (
            [(self._clocked(est.step_block, e), block.rec[e]) for e, est in enumerate(ests)]
            if self.blockwise
            else []
        )
        for (
            est
        ) in ests:  # compile (first run) or load the kernels of this path now, not inside the loop
            est.prepare("block" if self.blockwise else "record")
        self.world.prepare("step" if path == "step" or self.world.closed_loop else "block")
        self.step_fill = (
            World.fill if path == "step" else None
        )  # the per-step path: one step at a time
        lead = self.world.controller
        found = next((e for e in ests if e.name == lead), None) if lead else ests[0]
        if found is None:
            raise QuadobsError(f"world.controller: no estimator named {lead!r} in this episode")
        self.lead = found
        self.trace = TraceSink(collect_every, self.steps) if collect_every > 0 else None
        self.sinks = self._sinks(out, flush_rows, progress, monitor, sinks)
        ctx = EpisodeContext(frame, tuple(ests), block, self.clock, self.world)
        try:
            for sink in self.sinks:
                sink.begin(ctx)
        except (
            BaseException
        ):  # the recording is open: close it, a valid file, before the error goes on
            for sink in self.sinks:
                sink.close()
            raise
        self.hooks = [s for s in self.sinks if isinstance(s, StepSink)]
        self.due = [h.first_due() for h in self.hooks]
        self.next_due = min(self.due, default=-1)
        self.completed = 0
        self.committed = self.flushing = False  # where a stop found the end-of-block work

    def _clocked(self, step, e: int):
        """``step`` itself, or timed into ``clock[e]`` when the episode times its estimators."""
        return step if self.clock is None else _timed(step, self.clock, e)

    def _sinks(self, out, flush_rows, progress, monitor, extra) -> list[Sink]:
        """Summary first, then the trace, the recording, the monitor, the world's, ``extra``; the progress bar last."""
        fr = self.frame
        recorder = recording = None
        if out is not None:
            from quadobs.recording import Recorder
            from quadobs.testbed.episode_log import default_blueprint

            names = [e.name for e in self.block.estimators]
            recorder = Recorder(
                out,
                recording_id=f"{fr.name}-seed{fr.seed}",
                blueprint=default_blueprint(fr, names),
                capacity=flush_rows,
            )
            recording = RecordingSink(recorder, send_each_block=self.world.computes_ahead)
        sinks: list[Sink] = [ConvergenceSink(), _EstimatorInfo(), BoundsSink(), DivergenceSink()]
        sinks += [self.trace] if self.trace is not None else []
        if recording is not None:
            sinks.append(recording)
        if monitor is not None:
            excitation = ExcitationSink(monitor, recorder)
            sinks.append(excitation)
            if recording is not None:
                recording.extras.append(excitation.fill)
        sinks += self.world.sinks(recording)  # a world's own (the flight's, the replay's)
        sinks += list(extra)
        return sinks + ([ProgressSink()] if progress else [])

    def run(self) -> tuple[list[dict], bool]:
        """The loop, then the sinks' summary fragments; the sinks are closed whatever happens."""
        interrupted = False
        try:
            try:
                k0 = 0
                while k0 < self.steps:
                    k0 += self._block(k0)
            except (
                KeyboardInterrupt
            ):  # Ctrl-C, or SIGTERM (which the CLI maps to it): keep what is complete
                interrupted = True
                self._close_block()
            return [sink.end(self.completed, interrupted) for sink in self.sinks], interrupted
        except Exception as exc:  # the recording keeps every completed step, then the error goes on
            try:
                self._close_block()
                for sink in self.sinks:
                    sink.fail(self.completed, exc)
            except Exception:  # pragma: no cover - keep the original error
                pass
            raise
        finally:
            self.world.close()  # a block computing ahead in the background
            for sink in self.sinks:
                sink.close()

    def _block(self, k0: int) -> int:
        """One block (:func:`~quadobs.testbed.worlds.base.block_count` steps): the world's rows, the estimators over them, the sinks."""
        self.committed = self.flushing = False
        block, world = self.block, self.world
        block.k0 = k0
        count = world.begin_block(k0, block_count(k0, self.steps, _BLOCK))
        if self.step_fill is not None and not world.closed_loop:
            self.step_fill(world, count)
        elif not world.closed_loop:
            world.fill(count)
        if self.blockwise:
            self._estimate_blocks(count)
        else:
            self._estimate(count)
        self.check_physics(k0, count)
        rows = count
        if k0 + count == self.steps:  # the final row: x_K and the estimates at t_K
            block.record_final(count)
            rows += 1
        with (
            deferred_interrupts()
        ):  # a stop (Ctrl-C, SIGTERM) waits until the block is counted and sent
            world.commit(count)
            self.committed = self.flushing = True  # from here on a stop has nothing to add
            self._flush(rows)
        return count

    def _estimate(self, count: int) -> None:
        """The estimators over rows ``[0, count)``: the hot path (no allocation beyond row views)."""
        block = self.block
        y, u, bnd, bounded, slots = block.y, block.u, block.bounds, block.bounded, self.slots
        closed = self.world.step if self.world.closed_loop else None
        lead, k0, due = self.lead, block.k0, self.next_due
        for j in range(count):
            if closed is not None:
                closed(j, lead.x_hat)
            yj, uj = y[j], u[j]
            for b, est in bounded:
                bnd[b, j] = est.bounds
            for record, rec in slots:
                record(uj, yj, rec[j])  # x_hat_k, trace before; NIS, rejected after
            self.completed = s = k0 + j + 1  # row j is complete: what follows only reads it
            if s == due:
                due = self._after_step(s, j)

    def _estimate_blocks(self, count: int) -> None:
        """The block path: each estimator over rows ``[j, stop)`` in one call, ``stop`` the next row a sink is due after."""
        y, u, k0, j = self.block.y, self.block.u, self.block.k0, 0
        while j < count:
            due = self.next_due - k0
            stop = due if j < due < count else count
            for step_block, rec in self.block_slots:
                step_block(u[j:stop], y[j:stop], rec[j:stop])
            self.completed = s = k0 + stop
            if s == self.next_due:
                self._after_step(s, stop - 1)
            j = stop

    def _after_step(self, s: int, j: int) -> int:
        """Call the sinks due after ``s`` steps; returns when the next one is due."""
        for i, hook in enumerate(self.hooks):
            if self.due[i] == s:
                self.due[i] = hook.after_step(s, j)
        self.next_due = min(self.due)
        return self.next_due

    def _flush(self, rows: int) -> None:
        if rows > 0:
            fr = self.frame
            view = Rows(self.block, rows, self.steps, fr.dt, fr.dimension, fr.has_wind)
            for sink in self.sinks:
                sink.block(view)

    def _close_block(self) -> None:
        """After a stop inside the loop: count and hand on the rows of the block's completed steps."""
        done = self.completed - self.block.k0
        if not self.committed:
            self.world.commit(done)
        if not self.flushing:
            self._flush(done)


class _EstimatorInfo(Sink):
    """Each estimator's declared abilities in the summary: corrections and rejections, gate, immersion."""

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {}
        for est in self.ctx.estimators:
            entry: dict[str, Any] = {}
            if isinstance(est, Gated):
                entry["corrections"], entry["rejected"] = int(est.corrections), int(est.rejected)
                if est.gate is not None:
                    entry["gate"] = _finite_or_none(float(est.gate))
            elif isinstance(est, Counted):  # counts its corrections, has no gate
                entry["corrections"] = int(est.corrections)
            if isinstance(est, Switching):
                entry["modes"] = est.summary()
            entry.update(_robust_info(est))
            uninformed = getattr(est, "uninformed", None)
            record = uninformed() if callable(uninformed) else None
            if record is not None:  # only then: every other summary keeps its keys
                entry["uninformed"] = record
            if isinstance(est, Immersed) and est.immersion is not None:
                entry["immersion"] = est.immersion.summary()
                entry["outputs"] = int(est.immersion.system.q)
            per[est.name] = entry
        return {"estimators": per}


def _robust_info(est) -> dict:
    """The robust rule, lock-out re-initialisations and divergence of a filter that has them
    (:mod:`quadobs.estimators.robust`): a diverged filter is reported as such; a bias filter's
    steady-offset test's firings where it is on (:mod:`quadobs.estimators.bias_states`)."""
    out: dict = {}
    rule = getattr(est, "robust", None)
    if rule is not None:
        out["robust"] = rule.describe()
    lock = getattr(est, "lockout", None)
    if lock is not None and (lock.resets or lock.diverged):
        out.update(lock.summary())
    if getattr(est, "steady_test", False):  # the times its steady-offset test took a bias error
        out["steady_offsets"] = [float(t) for t in est.steady_offsets]
    return out


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _summarise(scenario, names, merged, completed, wall, sensors, out, interrupted) -> dict:
    """The summary: the episode's frame, the primary estimator's figures, the sinks' fragments."""
    per = merged.pop("estimators")
    head = per[names[0]]
    summary = {
        "scenario": scenario.name,
        "source": scenario.source,
        "seed": scenario.seed,
        "dimension": scenario.dimension,
        "beacons": scenario.beacons.shape[0],
        "duration": completed * scenario.dt,
        "physics_rate": scenario.physics_rate,
        "physics_steps": completed,
        "steps_per_second": completed / wall if wall > 0 else None,
        "wall_time": wall,
        "interrupted": interrupted,
        "recording": None if out is None else str(out),
        "primary_estimator": names[0],
    }
    for key in (
        "final_position_error",
        "final_velocity_error",
        "time_to_1m",
        "time_to_0p1m",
        "final_wind_error",
        "immersion",
    ):
        if key in head:
            summary[key] = head[key]
    summary["estimators"] = per
    summary["measurements"] = {
        "range_period_steps": sensors.range_every,
        "dropped": sensors.dropped,
        "outliers_injected": sensors.outliers_injected,
    }
    summary.update(merged)
    return summary
