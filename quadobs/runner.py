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
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import QuadobsError
from .estimators import build_estimators, default_estimators
from .metrics import ConvergenceTracker, state_errors
from .scenario import Scenario
from .sensors import SensorModel, initial_guess, spawn_streams

__all__ = ["EpisodeResult", "run_episode", "write_json_atomic"]

_BLOCK = 8192


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


def _trace_of(est) -> float:
    P = getattr(est, "P", None)
    if P is None:
        cov = est.x_covariance
        return float(np.trace(cov)) if cov is not None else float("nan")
    return float(np.trace(P))


def run_episode(
    scenario: Scenario,
    *,
    estimators: list[str] | None = None,
    out: str | Path | None = None,
    summary_path: str | Path | None = None,
    progress: bool = False,
    collect_every: int = 0,
    flush_rows: int = 4096,
) -> EpisodeResult:
    """Simulate ``scenario`` in MuJoCo, run the estimators every physics step, record and summarise.

    Parameters
    ----------
    scenario : Scenario
    estimators : list of str, optional
        Names (see :func:`quadobs.estimators.available_estimators`); default: the augmented
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
    """
    from .testbed import VehicleSim  # the MuJoCo layer, imported only to run episodes

    if scenario.kind != "vehicle":
        raise QuadobsError(f"scenario {scenario.name!r}: kind {scenario.kind!r} is not a MuJoCo vehicle scenario")
    names = list(estimators) if estimators else default_estimators(scenario)
    if summary_path is not None:
        from .recording import check_writable

        check_writable(summary_path)
    recorder = None
    if out is not None:
        from .recording import Recorder, check_writable

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
    from .excitation import scenario_monitor

    monitor = scenario_monitor(scenario)  # sliding-window Gramian of the applied input (None: disabled)
    xlog = None

    log = None
    if out is not None:
        from .recording import EpisodeLog, default_blueprint

        trail = max(1, int(round(scenario.physics_rate / 100.0)))
        trail = math.lcm(trail, scenario.record_every)
        recorder = Recorder(
            out,
            recording_id=f"{scenario.name}-seed{scenario.seed}",
            blueprint=default_blueprint(scenario, names),
            capacity=flush_rows,
        )
        bounded = [e.name for e in ests if hasattr(e, "bounds")]
        log = EpisodeLog(recorder, scenario, names, trail_every=trail, bounded=bounded)
        if monitor is not None:
            from .recording.excitation import ExcitationLog

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

    last_errors: dict[str, dict[str, np.ndarray]] = {}
    interrupted = False
    completed = 0
    wall0 = _time.perf_counter()

    def observe(k: int, x: np.ndarray, y, u, ranges, airspeed) -> int | None:
        """Errors and trackers for row ``k``; write it to the recording; return its row index."""
        t = k * dt
        errs, xhs, traces, nis = {}, {}, {}, {}
        for est in ests:
            xh = est.x_hat
            e = state_errors(dim, has_wind, xh, x)
            errs[est.name] = e
            xhs[est.name] = xh
            trackers[est.name].update(t, float(np.sqrt(e["position"] @ e["position"])))
        last_errors.update(errs)
        bounds = {}
        for est in ests:
            if est.name in contained:
                b = bounds[est.name] = est.bounds
                c = contained[est.name]
                c[0] += bool(np.all((b[:, 0] <= x) & (x <= b[:, 1])))
                c[1] += 1
                c[2] = b
        if collect and k % collect_every == 0:
            j = k // collect_every
            trace["time"][j] = t
            trace["truth"][j] = x
            for est in ests:
                trace["estimates"][est.name][j] = est.x_hat
                cov = est.x_covariance
                if cov is not None:
                    trace["covariances"][est.name][j] = cov
                b = getattr(est, "bounds", None)
                if b is not None:
                    trace["bounds"].setdefault(est.name, np.full((n_rec, x.shape[0], 2), np.nan))[j] = b
        if log is None or k % record_every:
            return None
        for est in ests:
            traces[est.name] = _trace_of(est)
            nis[est.name] = float("nan")
        log.write(k, t, x[:dim], x[2 * dim :] if has_wind else None, errs, xhs, traces, nis, ranges, airspeed, u, bounds)
        if xlog is not None:
            xlog.write(recorder.n - 1, k)
        return recorder.n - 1

    try:
        for block0 in range(0, steps, _BLOCK):
            nblk = min(_BLOCK, steps - block0)
            u_cmd = traj.step_accelerations(block0 * dt, dt, nblk)
            for j in range(nblk):
                k = block0 + j
                x_true = sim.state()
                sim.step(u_cmd[j])
                y = sensors.outputs(k, sim.ranges(), sim.airspeed() if has_wind else None)
                u = sensors.input(sim.accelerometer())
                row = observe(k, x_true, y, u, sensors.measured_ranges, None if not has_wind else _airspeed_of(y, sensors))
                if monitor is not None and monitor.push(u) and monitor.warning is not None:
                    message = monitor.pop_warning()
                    if xlog is not None:
                        xlog.warn(message, k + 1, (k + 1) * dt)
                for est in ests:
                    est.step(u, y)
                if collect and k % collect_every == 0:
                    _collect_nis(trace, k // collect_every, ests, y)
                if row is not None:
                    for est in ests:
                        log.est[est.name]["nis"].buf[row, 0] = getattr(est, "nis", float("nan"))
                completed = k + 1
            if bar is not None:
                bar.update(nblk)
        observe(steps, sim.state(), None, None, None, None)
    except KeyboardInterrupt:
        interrupted = True
        if log is not None:
            recorder.text("events", f"interrupted at t = {completed * dt:.3f} s (step {completed})", level="WARN", step=completed, time=completed * dt)
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


def _collect_nis(trace: dict, j: int, ests, y: np.ndarray) -> None:
    """NIS of each estimator's update with ``y`` and its degrees of freedom (``nis_dof``, else the outputs it saw)."""
    for est in ests:
        nis = float(getattr(est, "nis", float("nan")))
        trace["nis"][est.name][j] = nis
        dof = getattr(est, "nis_dof", None)
        if dof is None:
            seen = getattr(est, "outputs", None)
            yy = y[seen] if isinstance(seen, np.ndarray) else y
            dof = int(np.count_nonzero(~np.isnan(yy))) if np.isfinite(nis) else 0
        trace["nis_dof"][est.name][j] = dof


def _airspeed_of(y: np.ndarray, sensors: SensorModel) -> float | None:
    v = y[sensors.q_b]
    return None if np.isnan(v) else float(np.sqrt(2.0 * v))


def _summarise(scenario, ests, names, trackers, last_errors, completed, wall, sensors, out, interrupted) -> dict:
    per = {}
    for est in ests:
        e = last_errors.get(est.name)
        t1, t01 = (None if t is None else round(t, 9) for t in trackers[est.name].times())
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
