"""Replay a logged run through the estimators: the same blocks, record rows and sinks as an episode.

.. code-block:: text

    world = ReplayWorld(log, dt, model, biases)       # rows on the replay grid (worlds/replay.py)
    for each block:  world.fill(count); est.step_and_record(u_k, y_k, row_k) for every estimator
    sinks: ReplayErrorSink (RMSE, max, final, convergence), ReplayRecordingSink (.rrd), ProgressSink

The loop is the episode's (:class:`~quadobs.testbed.sinks.Block`, :class:`~quadobs.testbed.sinks.Rows`,
``step_and_record``); what differs is the frame (a log, not a scenario), no sensor layer
(the log's ranges are the measurements, less the calibrated biases) and the summary's keys:

* per estimator: ``rmse`` and ``max_error`` of the position over every step with a truth,
  ``final_position_error``, ``time_to_5m`` and ``time_to_2m`` (from when the error stays
  below), ``seconds_per_measurement`` (the estimator's wall time over the ranges placed),
  ``corrections`` and ``rejected`` where the estimator counts them;
* for the GTSAM peer, also ``smoothed_rmse`` (iSAM2's final estimate of every keyframe)
  and ``batch_rmse`` (the Levenberg-Marquardt optimum of the whole log), at its keyframes.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError, check_writable
from quadobs.estimators.base import Counted, Gated
from quadobs.evaluation.convergence import ConvergenceTracker, json_time
from quadobs.testbed.logs.estimators import ReplaySetup, build_replay_estimators
from quadobs.testbed.sinks import Block, EpisodeContext, ProgressSink, Rows, Sink, merge

__all__ = ["initial_guess", "run_replay", "DEFAULT_ESTIMATORS"]

DEFAULT_ESTIMATORS = ("augmented", "ekf")
_BLOCK = 8192


@dataclass(frozen=True)
class _Frame:
    """What the shared sinks read of an episode's scenario (name, steps, dt)."""

    name: str
    steps: int
    dt: float


def initial_guess(log, world, offset: float, seed: int) -> np.ndarray:
    """The estimators' initial state: the truth at ``t_0`` moved by ``offset`` metres in a direction drawn from ``seed``.

    Without a truth: the beacons' centroid. Velocities (model ``cv``) start at zero.
    """
    n = world.columns.n
    x0 = np.zeros(n)
    truth = world.state()
    if np.all(np.isfinite(truth[:2])):
        phi = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi)
        x0[:2] = truth[:2] + offset * np.array([math.cos(phi), math.sin(phi)])
    else:
        x0[:2] = log.beacons.mean(axis=0)
    return x0


class ReplayErrorSink(Sink):
    """Position RMSE, maximum and final error, and convergence times (5 m, 2 m) per estimator."""

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        self.sq = {n: [0.0, 0, 0.0, math.nan] for n in ctx.names}  # sum of squares, count, max, last
        self.trackers = {n: ConvergenceTracker((5.0, 2.0)) for n in ctx.names}

    def block(self, rows: Rows) -> None:
        for name, err in rows.errors.items():
            ep = err["position"]
            e = np.sqrt(np.einsum("ij,ij->i", ep, ep))
            ok = np.isfinite(e)
            acc = self.sq[name]
            acc[0] += float(np.sum(e[ok] ** 2))
            acc[1] += int(ok.sum())
            acc[2] = max(acc[2], float(e[ok].max())) if ok.any() else acc[2]
            acc[3] = float(e[-1])
            if ok.any():
                self.trackers[name].update_many(rows.t[ok], e[ok])

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {}
        for name, (ss, m, mx, last) in self.sq.items():
            t5, t2 = (json_time(t) for t in self.trackers[name].times())
            per[name] = {
                "rmse": math.sqrt(ss / m) if m else None,
                "max_error": mx if m else None,
                "final_position_error": last if math.isfinite(last) else None,
                "time_to_5m": t5,
                "time_to_2m": t2,
            }
        return {"estimators": per}


class ReplayRecordingSink(Sink):
    """The replay's ``.rrd``: beacons, true and estimated paths, position errors, ranges, NIS (every row)."""

    def __init__(self, path, log, names: list[str]) -> None:
        from quadobs.recording import Recorder

        self.recorder = r = Recorder(path, recording_id=f"replay-{log.name}", capacity=4096)
        import rerun as rr

        b3 = np.column_stack([log.beacons, np.zeros(len(log.beacons))])
        r.static("world/beacons", rr.Points3D(b3, radii=0.6, colors=[(255, 140, 0)],
                                              labels=[f"beacon {int(i)}" for i in log.beacon_ids]))
        r.static("description", rr.TextDocument(f"replay of the log {log.name}"))
        self.truth = r.series("world/truth/path", 3, "points3d", color=(40, 90, 220), radius=0.15)
        self.paths = {n: r.series(f"world/estimates/{n}/path", 3, "points3d", radius=0.12) for n in names}
        self.errors = {n: r.series(f"errors/{n}/position/norm", 1, names=[f"{n} |e_p|"]) for n in names}
        self.nis = {n: r.series(f"observer/{n}/nis", 1, skip_nan=True, names=[f"{n} NIS"]) for n in names}
        self.ranges = [r.series(f"measurements/range/{int(i)}", 1, skip_nan=True, names=[f"range {int(i)}"])
                       for i in log.beacon_ids]

    def block(self, rows: Rows) -> None:
        raw, c = rows.block.raw[: rows.count], rows.block.columns
        done, m = 0, rows.count
        while done < m:
            i = self.recorder.rows(rows.ks[done:], rows.t[done:])
            src = slice(done, done + (i.stop - i.start))
            self.truth.buf[i, :2] = rows.truth[src, :2]
            for name in self.paths:
                self.paths[name].buf[i, :2] = rows.estimates[name][src, :2]
                ep = rows.errors[name]["position"][src]
                self.errors[name].buf[i, 0] = np.sqrt(np.einsum("ij,ij->i", ep, ep))
                self.nis[name].buf[i, 0] = rows.nis[name][src]
            for h, series in enumerate(self.ranges):
                series.buf[i, 0] = raw[src, c.measured][:, h]
            done = src.stop

    def close(self) -> None:
        self.recorder.close()


def _timed(record, clock: list, e: int):
    """``record`` timed into ``clock[e]`` (one ``perf_counter`` pair per step: about 0.1 us)."""
    perf = _time.perf_counter

    def timed(u, y, out):
        t0 = perf()
        record(u, y, out)
        clock[e] += perf() - t0

    return timed


def _loop(world, ests, sinks, frame) -> tuple[int, bool, list[float], dict]:
    """The episode's loop over blocks: the steps completed, whether interrupted, the wall time per estimator, the sinks' summary."""
    block = Block(world, ests, _BLOCK)
    clock = [0.0] * len(ests)
    slots = [(_timed(est.step_and_record, clock, e), block.rec[e]) for e, est in enumerate(ests)]
    ctx = EpisodeContext(frame, tuple(ests), block)
    for sink in sinks:
        sink.begin(ctx)
    completed, interrupted = 0, False
    try:
        for k0 in range(0, frame.steps, _BLOCK):
            block.k0 = k0
            count = world.begin_block(k0, min(_BLOCK, frame.steps - k0))
            world.fill(count)
            y, u = block.y, block.u
            done = 0
            try:
                for j in range(count):
                    for record, rec in slots:
                        record(u[j], y[j], rec[j])
                    done = j + 1
            except KeyboardInterrupt:
                interrupted = True
            rows = done
            if k0 + done == frame.steps:
                block.record_final(done)
                rows += 1
            completed = k0 + done
            if rows:
                view = Rows(block, rows, frame.steps, frame.dt, 2, False)
                for sink in sinks:
                    sink.block(view)
            if interrupted:
                break
    finally:
        fragments = [sink.end(completed, interrupted) for sink in sinks]
        for sink in sinks:
            sink.close()
    return completed, interrupted, clock, merge(fragments)


def run_replay(
    log,
    *,
    estimators=None,
    dt: float = 0.1,
    model: str = "odometry",
    initial_offset: float = 50.0,
    seed: int = 0,
    biases=None,
    out: str | Path | None = None,
    summary_path: str | Path | None = None,
    progress: bool = False,
    batch: bool = True,
    setup_options: dict | None = None,
) -> dict:
    """Replay ``log`` through the estimators; returns the summary (module docstring), also written to ``summary_path``.

    Parameters
    ----------
    log : RangeLog
    estimators : list of str, optional
        Default :data:`DEFAULT_ESTIMATORS`.
    dt : float
        Replay grid step (s), see :mod:`quadobs.testbed.worlds.replay`.
    model : {"odometry", "cv"}
    initial_offset : float
        Distance (m) of the initial guess from the truth at ``t_0`` (:func:`initial_guess`).
    seed : int
        Draws the direction of the initial offset.
    biases : array_like (q,), optional
        Range bias per beacon (m), subtracted from the ranges (see
        :mod:`quadobs.testbed.logs.calibration`).
    out, summary_path : path, optional
        ``.rrd`` recording and JSON summary (checked for writability first).
    batch : bool
        Also solve the GTSAM peer's whole graph by Levenberg-Marquardt (the offline optimum).
    setup_options : dict, optional
        Noise settings of :class:`~quadobs.testbed.logs.estimators.ReplaySetup`.
    """
    from quadobs.testbed.episode import single_threaded_blas, write_json_atomic
    from quadobs.testbed.worlds.replay import ReplayWorld, dead_reckoning

    names = list(estimators) if estimators else list(DEFAULT_ESTIMATORS)
    for path in (summary_path, out):
        if path is not None:
            check_writable(path)
    world = ReplayWorld(log, dt, model, _BLOCK, biases)
    if world.placed == 0:
        raise QuadobsError(f"log {log.name!r}: no range falls inside the odometry's time span")
    x0 = initial_guess(log, world, float(initial_offset), seed)
    _, theta = dead_reckoning(log, world.times[:1])
    setup = ReplaySetup(log.beacons, world.dt, model, float(theta[0]), float(np.median(log.ranges[:, 2])), **(setup_options or {}))
    ests = build_replay_estimators(setup, names, x0)
    frame = _Frame(log.name, world.steps, world.dt)
    sinks: list[Sink] = [ReplayErrorSink()]
    if out is not None:
        sinks.append(ReplayRecordingSink(out, log, names))
    if progress:
        sinks.append(ProgressSink())
    wall0 = _time.perf_counter()
    with single_threaded_blas():
        completed, interrupted, clock, merged = _loop(world, ests, sinks, frame)
    summary = _summary(log, world, names, ests, merged, clock, completed, interrupted, x0, biases, setup, out)
    summary["wall_time"] = _time.perf_counter() - wall0
    if batch and not interrupted:
        _peer_figures(world, ests, summary)
    if summary_path is not None:
        write_json_atomic(summary_path, summary)
    return summary


def _summary(log, world, names, ests, merged, clock, completed, interrupted, x0, biases, setup, out) -> dict:
    per = merged.get("estimators", {})
    for e, est in enumerate(ests):
        entry = per.setdefault(est.name, {})
        entry["seconds_per_measurement"] = clock[e] / max(world.placed, 1)
        if isinstance(est, Counted):
            entry["corrections"] = int(est.corrections)
        if isinstance(est, Gated):
            entry["rejected"] = int(est.rejected)
    return {
        "log": log.name,
        "model": world.model,
        "dt": world.dt,
        "duration": completed * world.dt,
        "steps": completed,
        "interrupted": interrupted,
        "has_truth": log.truth is not None,
        "ranges": {"in_log": int(log.ranges.shape[0]), "placed": world.placed, "merged": world.merged},
        "biases": None if biases is None else [float(b) for b in np.asarray(biases).ravel()],
        "initial_guess": [float(v) for v in x0],
        "noise": {"range_sigma": setup.range_sigma, "q_xy": setup.q_xy, "q_acc": setup.q_acc, "gate": setup.gate},
        "recording": None if out is None else str(out),
        "primary_estimator": names[0],
        "estimators": per,
    }


def _peer_figures(world, ests, summary: dict) -> None:
    """The GTSAM peer's smoothed and batch (Levenberg-Marquardt) RMSE at its keyframes."""
    from quadobs.estimators.gtsam_peer import Isam2RangeOnly  # imports gtsam only when built

    for est in ests:
        if not isinstance(est, Isam2RangeOnly):
            continue
        entry = summary["estimators"][est.name]
        for key, (steps, P) in (("smoothed", est.online_positions()), ("batch", est.batch_optimum())):
            e = np.linalg.norm(P - world.truth_at(steps)[:, :2], axis=1)
            e = e[np.isfinite(e)]
            entry[f"{key}_rmse"] = float(np.sqrt(np.mean(e**2))) if e.size else None
            entry[f"{key}_max_error"] = float(e.max()) if e.size else None
