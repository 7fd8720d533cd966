"""One episode: MuJoCo truth, sensors, estimators and the recording, composed step by step.

The data path of physics step ``k`` (time ``t_k = k dt``):

1. read the true state ``x_k`` (MuJoCo's ``qpos``/``qvel``);
2. ``mj_step`` with the commanded acceleration held over ``[t_k, t_{k+1})``; the sensors
   now describe ``t_k``: ranges, accelerometer, airspeed;
3. the sensor layer adds noise, rates, dropouts and outliers: ``y_k``, ``u_k``;
4. record row ``k``: truth, each estimate ``x_hat_k`` and its error, the measurements;
5. each estimator corrects with ``y_k`` and predicts to ``t_{k+1}`` with ``u_k`` held.

After the last step the final row ``K`` (``t_K = duration``) is recorded, so the summary's
final errors compare ``x_hat_K`` with MuJoCo's ``x_K``.

Cost. The per-step path allocates nothing and makes three calls from Python: ``mj_step``;
one compiled call that does steps 1 and 3 (the truth, the readings and the sensor layer,
with the noise of the block drawn beforehand from the same streams in the same order;
:class:`~quadobs.testbed.worlds.BlockStepper`); and, per estimator,
:meth:`~quadobs.estimators.augmented.Estimator.step_and_record`, which does step 5 and keeps what
step 4 records (``x_hat_k`` and the covariance trace before the step, the NIS after it).
Every value of step ``k`` lands in row ``k`` of preallocated arrays of a block of steps;
the errors, convergence times and the recording's rows are computed from them once per
block (vectorised), then sent as columns.
"""

from __future__ import annotations

import functools
import json
import math
import os
import tempfile
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError, check_writable, deferred_interrupts
from quadobs.testbed.registry import build_estimators, default_estimators
from quadobs.evaluation.convergence import ConvergenceTracker, json_time, state_errors
from quadobs.estimators.base import Estimator, covariance_trace as _covariance_trace
from quadobs.testbed.scenario import Scenario
from quadobs.testbed.sensors import SensorModel, initial_guess, spawn_streams

__all__ = ["EpisodeResult", "run_episode", "write_json_atomic", "WALL_CLOCK_KEYS"]

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
    """Write JSON to a temporary file beside ``path`` and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh, indent=2, allow_nan=False, default=_json_default)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def single_threaded_blas():
    """A context in which BLAS and LAPACK run on the calling thread (``threadpoolctl``; no-op without it).

    The estimators' matrices are tiny: a threaded BLAS gains nothing on them, and its
    worker threads, which spin for a while after each call, take a second core (or the
    other half of a hyperthreaded one) from the simulation loop; on a 2-core machine that
    made every step of the loop up to twice as slow.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional at run time
        from contextlib import nullcontext

        return nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _single_threaded(fn):
    """Run ``fn`` inside :func:`single_threaded_blas`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_threaded_blas():
            return fn(*args, **kwargs)

    return wrapper


def _step_and_record(est):
    """``est.step_and_record``, or :meth:`Estimator.step_and_record` for an object that only has ``step``."""
    method = getattr(est, "step_and_record", None)
    if method is not None:
        return method
    from functools import partial

    return partial(Estimator.step_and_record, est)


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
) -> EpisodeResult:
    """Simulate ``scenario`` in MuJoCo, run the estimators every physics step, record and summarise.

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
    Exception
        An error raised inside the loop (by an estimator, say) propagates after the
        recording is closed holding every step completed before it, with the error in
        ``events``; no summary is written.

    Notes
    -----
    BLAS and LAPACK run single-threaded during the episode (:func:`single_threaded_blas`).
    """
    from quadobs.testbed.worlds import BlockStepper, VehicleSim  # the MuJoCo layer, imported only to run episodes

    if scenario.kind != "vehicle":
        raise QuadobsError(f"scenario {scenario.name!r}: kind {scenario.kind!r} is not a MuJoCo vehicle scenario")
    names = list(estimators) if estimators else default_estimators(scenario)
    if summary_path is not None:
        check_writable(summary_path)
    recorder = None
    if out is not None:
        from quadobs.recording import Recorder

        check_writable(out)

    dim, dt, steps = scenario.dimension, scenario.dt, scenario.steps
    traj = scenario.trajectory
    sim = VehicleSim(dim, scenario.beacons, timestep=dt, wind=scenario.wind, model_path=scenario.model)
    sim.reset(traj.position(0.0), traj.velocity_at(0.0))
    streams = spawn_streams(scenario.seed)
    sensors = SensorModel(scenario, streams)
    x_true = sim.state()
    x0 = initial_guess(scenario, x_true, streams["initial"])
    ests = build_estimators(scenario, names, x0)
    has_wind = scenario.has_wind
    from quadobs.testbed.excitation import scenario_monitor

    monitor = scenario_monitor(scenario)  # sliding-window Gramian of the applied input (None: disabled)
    xlog = None

    # estimators with an NIS gate: a correction is rejected exactly when its NIS exceeds the gate
    gates = {est: float(g) for est in ests if (g := getattr(est, "gate", None)) is not None}
    rejected_so_far = {est.name: 0 for est in gates}
    events_so_far = np.zeros(2, dtype=np.int64)  # outliers delivered, samples dropped

    log = None
    if out is not None:
        from quadobs.testbed.episode_log import EpisodeLog, default_blueprint

        trail = max(1, int(round(scenario.physics_rate / 100.0)))
        trail = math.lcm(trail, scenario.record_every)
        recorder = Recorder(
            out,
            recording_id=f"{scenario.name}-seed{scenario.seed}",
            blueprint=default_blueprint(scenario, names),
            capacity=flush_rows,
        )
        bounded = [e.name for e in ests if hasattr(e, "bounds")]
        log = EpisodeLog(
            recorder, scenario, names, trail_every=trail, bounded=bounded, gated=[e.name for e in ests if e in gates],
            events=bool(scenario.noise.outlier_probability or scenario.noise.dropout),
        )
        if monitor is not None:
            from quadobs.recording.excitation import ExcitationLog

            xlog = ExcitationLog(recorder, monitor, ests)

    trackers = {n: ConvergenceTracker((1.0, 0.1)) for n in names}
    # guaranteed estimators (with ``bounds (n, 2)``): rows whose true state lies in the bounds
    contained = {e.name: [0, 0, None] for e in ests if hasattr(e, "bounds")}
    collect = collect_every > 0
    if collect:
        n_rec = steps // collect_every + 1
        n = scenario.state_dim
        trace = {
            "time": np.full(n_rec, np.nan),
            "truth": np.full((n_rec, n), np.nan),
            "estimates": {nm: np.full((n_rec, n), np.nan) for nm in names},
            "covariances": {nm: np.full((n_rec, n, n), np.nan) for nm in names},
            "nis": {nm: np.full(n_rec, np.nan) for nm in names},
            "nis_dof": {nm: np.zeros(n_rec, dtype=int) for nm in names},
            "bounds": {},
        }
    record_every = scenario.record_every
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, unit="step", unit_scale=True, desc=scenario.name, leave=False)

    # Per-step values of a block of steps, in preallocated arrays (row j: step block0 + j);
    # errors, convergence times and the recording are computed from them once per block.
    n, E = scenario.state_dim, len(ests)
    stepper = BlockStepper(sim, _BLOCK, sensors)
    raw = stepper.out  # row j: truth x at step block0 + j; readings, y, u, measured ranges of that step
    raw_y, raw_u = raw[:, stepper.y], raw[:, stepper.u]
    # per estimator and row: x_hat and the covariance trace before the step, the NIS of its correction
    rec = np.full((E, _BLOCK + 1, n + 2), np.nan)
    xh, traces, nis = rec[:, :, :n], rec[:, :, n], rec[:, :, n + 1]
    slots = [(est, _step_and_record(est), rec[e]) for e, est in enumerate(ests)]
    # guaranteed estimators: their interval bounds of x_k (before the step), per row
    bounded_ests = [(b, est) for b, est in enumerate(e for e in ests if hasattr(e, "bounds"))]
    bnd = np.full((len(bounded_ests), _BLOCK + 1, n, 2), np.nan)

    last_errors: dict[str, dict[str, np.ndarray]] = {}
    interrupted = False
    completed = 0
    committed = flushing = False  # where a stop found the end-of-block work (see the handlers)

    def flush(block0: int, rows: int) -> None:
        """Errors, convergence, collected trajectories and recording of rows ``[0, rows)`` of the block."""
        if rows <= 0:
            return
        ks = block0 + np.arange(rows)
        t = ks * dt
        X = raw[:rows, stepper.truth]
        errs, xhs, trs, niss = {}, {}, {}, {}
        for e, est in enumerate(ests):
            err = state_errors(dim, has_wind, xh[e, :rows], X)
            ep = err["position"]
            trackers[est.name].update_many(t, np.sqrt(np.einsum("ij,ij->i", ep, ep)))
            errs[est.name], xhs[est.name] = err, xh[e, :rows]
            trs[est.name], niss[est.name] = traces[e, :rows], nis[e, :rows]
            last_errors[est.name] = {key: val[-1].copy() for key, val in err.items()}
        bounds = {}
        for b, est in bounded_ests:
            B = bnd[b, :rows]
            bounds[est.name] = B
            c = contained[est.name]
            c[0] += int(np.all((B[..., 0] <= X) & (X <= B[..., 1]), axis=1).sum())
            c[1] += rows
            c[2] = B[-1].copy()
        if collect:
            sel = np.flatnonzero(ks % collect_every == 0)
            idx = ks[sel] // collect_every
            trace["time"][idx] = t[sel]
            trace["truth"][idx] = X[sel]
            Y = raw[:rows, stepper.y][sel]
            for e, est in enumerate(ests):
                trace["estimates"][est.name][idx] = xh[e, sel]
                trace["nis"][est.name][idx] = nis[e, sel]
                seen = getattr(est, "outputs", None)
                Ys = Y[:, seen] if isinstance(seen, np.ndarray) else Y
                dof = np.count_nonzero(~np.isnan(Ys), axis=1)
                trace["nis_dof"][est.name][idx] = np.where(np.isfinite(nis[e, sel]), dof, 0)
                if est.name in bounds:
                    trace["bounds"].setdefault(est.name, np.full((n_rec, n, 2), np.nan))[idx] = bounds[est.name][sel]
        rejected = {}
        for e, est in enumerate(ests):
            if est in gates:
                with np.errstate(invalid="ignore"):
                    hits = np.cumsum(nis[e, :rows] > gates[est])
                rejected[est.name] = rejected_so_far[est.name] + hits
                rejected_so_far[est.name] += int(hits[-1])
        ev = stepper.events[:rows].copy()
        ev[max(steps - block0, 0) :] = 0  # the final row has no step, hence no measurement
        ev = events_so_far + np.cumsum(ev, axis=0)
        events_so_far[:] = ev[-1]
        if log is None:
            return
        sel = np.flatnonzero(ks % record_every == 0)
        if not sel.size:
            return
        accel = raw[:rows, stepper.u]
        air = np.sqrt(2.0 * raw[:rows, stepper.y.start + sensors.q_b]) if has_wind else None
        log.write_block(
            ks[sel], t[sel], X[sel, :dim], X[sel, 2 * dim :] if has_wind else None,
            {nm: {key: val[sel] for key, val in err.items()} for nm, err in errs.items()},
            {nm: v[sel] for nm, v in xhs.items()}, {nm: v[sel] for nm, v in trs.items()},
            {nm: v[sel] for nm, v in niss.items()}, raw[:rows, stepper.measured][sel], None if air is None else air[sel], accel[sel],
            bounds={nm: v[sel] for nm, v in bounds.items()},
            extra=None if xlog is None else xlog.fill,
            rejected={nm: v[sel] for nm, v in rejected.items()}, events=ev[sel],
        )

    def log_counts(step: int) -> None:
        """Event-log lines: each gate's rejections beside the outliers injected and samples dropped."""
        if log is None:
            return
        for est, gate in gates.items():
            count = rejected_so_far[est.name]
            recorder.text(
                "events",
                f"{est.name}: {count} corrections rejected by the NIS gate {gate:g} "
                f"({int(events_so_far[0])} outliers injected, {int(events_so_far[1])} samples dropped)",
                level="WARN" if count else "INFO", step=step, time=step * dt,
            )

    # The monitor takes the inputs a chunk at a time, at the step that completes the chunk
    # (mon_left counts down to it; -1 and below: no monitor), and the rest at a block's end.
    # What it has taken is its own count of steps, so a stop anywhere feeds it no step twice.
    mon_left = monitor.room if monitor is not None else -1

    def feed_monitor(stop: int) -> None:
        """Feed the monitor the block's inputs before row ``stop`` that it has not taken (never past its chunk)."""
        if monitor is not None:
            take = min(block0 + stop - monitor.steps, monitor.room)
            if take > 0:
                monitor.push_many(raw_u[stop - take : stop])

    wall0 = _time.perf_counter()
    block0 = 0
    try:
        step = stepper.step
        for block0 in range(0, steps, _BLOCK):
            committed = flushing = False
            nblk = stepper.begin(traj.step_accelerations(block0 * dt, dt, min(_BLOCK, steps - block0)), block0)
            for j in range(nblk):
                k = block0 + j
                step(j)  # mj_step; readings, y_k, u_k of step k into raw[j]; truth x_(k+1) into raw[j + 1]
                if collect and k % collect_every == 0:
                    for est in ests:
                        cov = est.x_covariance
                        if cov is not None:
                            trace["covariances"][est.name][k // collect_every] = cov
                y, u = raw_y[j], raw_u[j]
                for b, est in bounded_ests:
                    bnd[b, j] = est.bounds
                for _, step_and_record, est_rec in slots:
                    step_and_record(u, y, est_rec[j])  # x_hat_k, trace before; NIS after
                completed = k + 1  # row j is complete: what follows only reads it
                mon_left -= 1
                if mon_left == 0:  # the monitor's chunk is complete: feed it (the measure may change here)
                    if monitor.push_many(raw_u[monitor.steps - block0 : j + 1]):  # the window measure was recomputed
                        if xlog is not None:
                            xlog.capture(k + 1)
                        if monitor.warning is not None:
                            message = monitor.pop_warning()
                            if xlog is not None:
                                xlog.warn(message, k + 1, (k + 1) * dt)
                    mon_left = monitor.room
            done = nblk
            feed_monitor(done)
            if block0 + nblk == steps:  # the final row: x_K and the estimates at t_K
                for b, est in bounded_ests:
                    bnd[b, nblk] = est.bounds
                for est, _, est_rec in slots:
                    est_rec[nblk, :n] = est.x_hat
                    est_rec[nblk, n] = _covariance_trace(est)
                    est_rec[nblk, n + 1] = np.nan
                    if collect and steps % collect_every == 0:
                        cov = est.x_covariance
                        if cov is not None:
                            trace["covariances"][est.name][steps // collect_every] = cov
                raw[nblk, stepper.ranges.start :] = np.nan  # no measurement at t_K
                nblk += 1
            with deferred_interrupts():  # a stop (Ctrl-C, SIGTERM) waits until the block is counted and sent
                stepper.commit(done)  # the sensor model counts this block's dropouts and outliers
                committed = True
                flushing = True
                flush(block0, nblk)  # the flags stay set until the next block starts: a stop from here on has nothing to add
            if bar is not None:
                bar.update(min(nblk, steps - block0))
        log_counts(completed)
    except KeyboardInterrupt:
        # Ctrl-C (or SIGTERM, which the CLI maps to it): keep every step completed so far
        # in the recording and the summary, and return normally with ``interrupted``.
        interrupted = True
        feed_monitor(completed - block0)
        _close_block(stepper, flush, block0, completed, committed, flushing)
        if log is not None:
            recorder.text("events", f"interrupted at t = {completed * dt:.3f} s (step {completed})", level="WARN", step=completed, time=completed * dt)
        log_counts(completed)
    except Exception as exc:
        # An error inside the loop: the recording keeps every step completed before it
        # (closed below, so it stays a valid file), then the error goes on to the caller.
        try:
            _close_block(stepper, flush, block0, completed, committed, flushing)
            if log is not None:
                recorder.text(
                    "events", f"stopped by an error at t = {completed * dt:.3f} s (step {completed}): {exc!r}",
                    level="ERROR", step=completed, time=completed * dt,
                )
        except Exception:  # pragma: no cover - keep the original error
            pass
        raise
    finally:
        if bar is not None:
            bar.close()
        if recorder is not None:
            recorder.close()
    wall = _time.perf_counter() - wall0

    summary = _summarise(scenario, ests, names, trackers, last_errors, completed, wall, sensors, out, interrupted)
    if monitor is not None:
        summary["excitation"] = monitor.summary()
    for name, (inside, rows, b) in contained.items():
        summary["estimators"][name]["bounds"] = {
            "contained_fraction": inside / rows if rows else None,
            "final_width": None if b is None else (b[:, 1] - b[:, 0]).tolist(),
        }
    if summary_path is not None:
        write_json_atomic(summary_path, summary)
    if collect:
        return EpisodeResult(summary, trace)
    return EpisodeResult(summary)


def _close_block(stepper, flush, block0: int, completed: int, committed: bool, flushing: bool) -> None:
    """After a stop inside the loop: count and flush the rows of the block's completed steps.

    ``committed``/``flushing`` say whether the stop came after the block's sensor counts
    were committed, or during its flush (whose rows are then already on their way).
    """
    if not committed:
        stepper.commit(completed - block0)
    if not flushing:
        flush(block0, completed - block0)


def _summarise(scenario, ests, names, trackers, last_errors, completed, wall, sensors, out, interrupted) -> dict:
    per = {}
    for est in ests:
        e = last_errors.get(est.name)
        t1, t01 = (json_time(t) for t in trackers[est.name].times())
        entry = {
            "final_position_error": float(np.linalg.norm(e["position"])) if e else None,
            "final_velocity_error": float(np.linalg.norm(e["velocity"])) if e else None,
            "time_to_1m": t1,
            "time_to_0p1m": t01,
        }
        if e and "wind" in e:
            entry["final_wind_error"] = float(np.linalg.norm(e["wind"]))
            entry["final_air_velocity_error"] = float(np.linalg.norm(e["air_velocity"]))
        for attr in ("corrections", "rejected"):
            if hasattr(est, attr):
                entry[attr] = int(getattr(est, attr))
        gate = getattr(est, "gate", None)
        if gate is not None:
            entry["gate"] = float(gate)
        im = getattr(est, "immersion", None)
        if im is not None:
            entry["immersion"] = im.summary()
            entry["outputs"] = int(im.system.q)
        for key, val in list(entry.items()):
            if isinstance(val, float):
                entry[key] = _finite_or_none(val)
        per[est.name] = entry
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
    for key in ("final_position_error", "final_velocity_error", "time_to_1m", "time_to_0p1m", "final_wind_error", "immersion"):
        if key in head:
            summary[key] = head[key]
    summary["estimators"] = per
    summary["measurements"] = {
        "range_period_steps": sensors.range_every,
        "dropped": sensors.dropped,
        "outliers_injected": sensors.outliers_injected,
    }
    return summary
