"""Monte Carlo campaigns: many seeded episodes, in local processes or on a Dask cluster, and their statistics.

A campaign runs ``runs`` episodes of one scenario (:func:`quadobs.testbed.episode.run_episode`,
MuJoCo truth, no recording per run), each with its own seed, and reduces them to the
statistics of :mod:`quadobs.evaluation.ensemble`: RMSE over time and at the end, convergence,
NEES and NIS against their chi-square intervals, and the ratio of the RMSE to the
posterior Cramér-Rao bound of the scenario.

Seeds
    Run ``i`` uses ``seed_i = run_seed(scenario.seed, i)``, derived from the scenario's
    seed and the run index by :class:`numpy.random.SeedSequence` (``spawn_key=(i,)``), so
    the runs are independent, the same campaign gives the same runs wherever they are
    executed, and ``quadobs run SCENARIO --seed seed_i`` replays run ``i`` alone.

Execution
    By default the runs go to a :class:`concurrent.futures.ProcessPoolExecutor` (with the
    platform's default start method, or ``start_method``); ``workers=0`` runs them one after
    the other in the calling process. With ``scheduler=ADDRESS`` the same function is
    submitted to a Dask distributed cluster (``pip install 'quadobs[cluster]'``; the
    workers must have quadobs installed). Workers find estimators by name through the
    entry points of the group ``quadobs.estimators`` (:mod:`quadobs.testbed.registry`), so
    an estimator from another installed package runs everywhere; one registered at run
    time with :func:`~quadobs.testbed.registry.register_estimator` reaches forked workers
    only, and is refused up front for ``spawn``, ``forkserver`` and Dask. A run that raises is recorded as failed with
    its seed and error and the others go on; Ctrl-C stops the campaign and writes the
    statistics of the runs already finished.

Results (in ``out_dir``)
    ``summary.json`` (aggregates per estimator under ``estimators.<name>``, see
    :meth:`quadobs.evaluation.ensemble.Ensemble.summary`; the failed runs; for a quadrotor
    scenario the flight figures under ``flight``, see :func:`flight_summary`), ``runs.parquet`` (one
    row per run and estimator, and one per failed run), ``series.parquet`` (per run,
    estimator and sample time: error norms, NEES, NIS), ``statistics.rrd`` (the
    statistics over time). Parquet (via pyarrow, which the recording layer already
    needs) keeps the column types and is read by pandas, polars or DuckDB in one call.
    Every file is written to a temporary name and renamed into place.
"""

from __future__ import annotations

import functools
import math
import os
import tempfile
import time as _time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError, as_finite_scalar, caused_by_interrupt
from quadobs.evaluation.ensemble import Ensemble, converged_nees, ensemble, nees, set_containment
from quadobs.testbed.bounds import immersion_bound, scenario_crb
from quadobs.testbed.flight import crash_counts, crash_record
from quadobs.testbed.registry import available_estimators, default_estimators, estimator_factory
from quadobs.testbed.scenario import Scenario, parse_scenario

__all__ = [
    "CampaignResult",
    "flight_summary",
    "print_campaign",
    "run_campaign",
    "run_one",
    "run_seed",
]


#: Most runs in one campaign, and most local worker processes.
MAX_RUNS = 1_000_000
MAX_WORKERS = 1024
#: Seconds a worker gets to end after SIGTERM before it is killed (campaign stopped).
_TERMINATE_GRACE = 2.0


def run_seed(base_seed: int, index: int) -> int:
    """The seed of run ``index`` of a campaign on a scenario of seed ``base_seed`` (63-bit)."""
    ss = np.random.SeedSequence(int(base_seed), spawn_key=(int(index),))
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


# --------------------------------------------------------------------------------------
# One run (executed in a worker)
# --------------------------------------------------------------------------------------


def run_one(task: dict) -> dict:
    """Run one seeded episode and reduce it to the per-run series of each estimator.

    ``task`` holds ``index``, ``seed``, ``scenario`` (the scenario as plain data,
    :meth:`Scenario.to_dict`), ``source``, ``estimators`` and ``collect_every``. Never
    raises: a failure is returned as ``{"status": "failed", "error": ..., "traceback": ...}``.
    """
    t0 = _time.perf_counter()
    base = {"index": int(task["index"]), "seed": int(task["seed"])}
    try:
        from quadobs.testbed.episode import run_episode

        data = dict(task["scenario"])
        data["seed"] = int(task["seed"])
        scenario = parse_scenario(data, source=task.get("source", ""))
        result = run_episode(
            scenario, estimators=list(task["estimators"]), collect_every=int(task["collect_every"])
        )
        if result.summary[
            "interrupted"
        ]:  # Ctrl-C reached the run: stop the campaign, not just this run
            raise KeyboardInterrupt
        tr = result.trace
        dim, wind = scenario.dimension, scenario.has_wind
        per = {}
        truth = tr["truth"]
        for name in task["estimators"]:
            est = tr["estimates"][name]
            e = est - truth
            ev = e[:, dim : 2 * dim] + (
                e[:, 2 * dim :] if wind else 0.0
            )  # ground velocity (metrics.state_errors)
            entry = {
                "position_error": e[:, :dim].copy(),
                "velocity_error": ev,
                "nees": nees(est - truth, tr["covariances"][name]),
                "nis": tr["nis"][name],
                "nis_dof": tr["nis_dof"][name],
            }
            b = tr["bounds"].get(name)
            if b is not None:
                entry["containment"] = set_containment(truth, b)
                width = b[..., 1] - b[..., 0]
                entry["width_position"] = width[:, :dim].mean(axis=1)
                entry["width_velocity"] = width[:, dim : 2 * dim].mean(axis=1)
            s = result.summary["estimators"][name]
            if (
                s.get("modes") is not None
            ):  # a switching estimator: which samples report a later mode
                entry["switched"] = _switched(tr["time"], s["modes"]["switches"], scenario.dt)
                entry["handover_time"] = _first_handover(s["modes"], scenario.dt)
            for key in (
                "final_position_error",
                "final_velocity_error",
                "time_to_1m",
                "time_to_0p1m",
            ):
                entry[key] = np.nan if s.get(key) is None else float(s[key])
            per[name] = entry
        out = {
            **base,
            "status": "ok",
            "time": tr["time"],
            "estimators": per,
            "wall_time": _time.perf_counter() - t0,
        }
        if (
            "flight" in result.summary
        ):  # a quadrotor world: its flight figures (quadobs.testbed.flight)
            out["flight"] = _run_flight(result.summary)
        return out
    except Exception as exc:  # reported, never dropped
        if caused_by_interrupt(
            exc
        ):  # an import or a compiler cut short by Ctrl-C: the interrupt goes on
            raise KeyboardInterrupt from exc
        return {
            **base,
            "status": "failed",
            "error": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(),
            "wall_time": _time.perf_counter() - t0,
        }


def _run_flight(summary: dict) -> dict:
    """The flight figures of one quadrotor run (``summary["flight"]`` of :class:`~quadobs.testbed.flight.FlightSink`)."""
    f = summary["flight"]
    num = lambda v: float("nan") if v is None else float(v)  # noqa: E731
    return {
        "crashed": bool(f["crashed"]),
        "tracking_rms": num(f["tracking_rms"]),
        "tracking_max": num(f["tracking_max"]),
        "time_on_estimate": float(f["time_on_estimate"]),
        "flight_position_rmse": {
            nm: num(s.get("flight_position_rmse")) for nm, s in summary["estimators"].items()
        },
        **crash_record(f),
    }


def flight_summary(flights: list[dict], names: list[str]) -> dict:
    """The flight figures of a quadrotor campaign over its completed runs.

    ``crashed`` (count), the median and largest tracking RMS and the largest tracking
    error (m, reference minus true position over the flight), the mean time flown on the
    estimate (s), and per estimator the median and largest position RMSE after the switch
    to the estimate (``flight_position_rmse`` of :mod:`quadobs.testbed.flight`).
    """
    rms = np.array([f["tracking_rms"] for f in flights])
    stat = lambda a, fn: None if not np.isfinite(a).any() else float(fn(a[np.isfinite(a)]))  # noqa: E731
    return {
        "runs": len(flights),
        "crashed": int(sum(f["crashed"] for f in flights)),
        "tracking_rms_median": stat(rms, np.median),
        "tracking_rms_max": stat(rms, np.max),
        "tracking_max": stat(np.array([f["tracking_max"] for f in flights]), np.max),
        "time_on_estimate_mean": float(np.mean([f["time_on_estimate"] for f in flights])),
        "crashes_by_estimator": crash_counts(flights),
        "flight_position_rmse": {
            nm: {
                "median": stat(a, np.median),
                "max": stat(a, np.max),
            }
            for nm in names
            for a in [np.array([f["flight_position_rmse"].get(nm, np.nan) for f in flights])]
        },
    }


# --------------------------------------------------------------------------------------
# The campaign
# --------------------------------------------------------------------------------------


@dataclass
class CampaignResult:
    """What :func:`run_campaign` returns: the summary (also in ``summary.json``), the statistics, the per-run results."""

    summary: dict
    ensembles: dict[str, Ensemble] = field(default_factory=dict)
    results: list[dict] = field(default_factory=list, repr=False)
    bound: tuple[np.ndarray, np.ndarray, str] | None = field(default=None, repr=False)


def _switched(times: np.ndarray, switches: list[dict], dt: float) -> np.ndarray:
    """Whether each sample (taken before the update at its step) reports a mode other than the first one."""
    k = np.rint(np.asarray(times) / dt).astype(np.int64)
    first = switches[0]["from"] if switches else None
    mode = np.full(k.shape, first, dtype=object)
    for sw in switches:  # in order; a switch at step s applies from step s + 1
        mode[k > sw["step"]] = sw["to"]
    return np.array([m != first for m in mode]) if switches else np.zeros(k.shape, dtype=bool)


def _first_handover(modes: dict, dt: float) -> float:
    step = modes.get("handover_step")
    return np.nan if step is None else float(step) * dt


def _converged_part(ens: Ensemble, per: list[dict], times: np.ndarray) -> np.ndarray:
    """``(R, T)``: each run's converged part, from its convergence time on and, for a switching estimator, in a later mode."""
    mask = times[None, :] >= ens.convergence_time[:, None]
    if per and all("switched" in p for p in per):
        mask &= np.stack([p["switched"] for p in per])
    return mask


def _collect_every(scenario: Scenario, every: float | None) -> int:
    if every is None:
        k = max(1, int(round(scenario.physics_rate * 0.1)))
        while scenario.steps % k:
            k -= 1
        return k
    every = as_finite_scalar("every", every, positive=True)
    k = int(round(every * scenario.physics_rate))
    if k < 1 or abs(k - every * scenario.physics_rate) > 1e-6 * k:
        raise QuadobsError(
            f"every: {every} s is not a whole number of physics steps ({scenario.dt} s)"
        )
    if scenario.steps % k:
        raise QuadobsError(
            f"every: {every} s must divide the duration {scenario.duration} s (so the last sample is the end)"
        )
    return k


def _checked_settings(
    scenario, runs, retries, estimators, scheduler, workers, start_method, threshold, confidence
):
    """The campaign's settings checked (one-line errors naming the setting): ``names, threshold, confidence``."""
    if (
        isinstance(runs, bool)
        or not isinstance(runs, (int, np.integer))
        or not 1 <= runs <= MAX_RUNS
    ):
        raise QuadobsError(f"runs: expected an integer from 1 to {MAX_RUNS}, got {runs!r}")
    if (
        isinstance(retries, bool)
        or not isinstance(retries, (int, np.integer))
        or not 0 <= retries <= 100
    ):
        raise QuadobsError(f"retries: expected an integer from 0 to 100, got {retries!r}")
    names = list(estimators) if estimators else default_estimators(scenario)
    known = available_estimators(scenario)
    for nm in names:
        if nm not in known:
            raise QuadobsError(
                f"estimators: unknown estimator {nm!r}; available: {', '.join(known)}"
            )
    if len(set(names)) != len(names):
        raise QuadobsError(f"estimators: names must be distinct, got {names}")
    _check_reach(scenario, names, scheduler, workers, start_method)
    if scheduler is not None and workers is not None:
        raise QuadobsError(
            "workers: applies to local processes; with a scheduler the cluster's workers run the campaign"
        )
    if workers is not None and (
        isinstance(workers, bool)
        or not isinstance(workers, (int, np.integer))
        or not 0 <= workers <= MAX_WORKERS
    ):
        raise QuadobsError(f"workers: expected an integer from 0 to {MAX_WORKERS}, got {workers!r}")
    threshold = as_finite_scalar("threshold", threshold, positive=True)
    confidence = as_finite_scalar("confidence", confidence, positive=True)
    if not confidence < 1:
        raise QuadobsError(f"confidence: must be below 1, got {confidence}")
    return names, threshold, confidence


def _stack_key(per: list[dict], key: str):
    """The runs' values of ``key``, stacked along a first axis (``None`` without runs)."""
    return np.stack([p[key] for p in per]) if per else None


def _ensembles(scenario, names, ok, times, sqrt_bound, threshold, confidence) -> dict:
    """Per estimator, the :class:`~quadobs.evaluation.ensemble.Ensemble` of the completed runs."""
    ensembles = {}
    for nm in names:
        per = [r["estimators"][nm] for r in ok]
        stack = functools.partial(_stack_key, per)
        has_set = bool(per) and all("containment" in p for p in per)
        T = times.shape[0]
        dim = scenario.dimension
        ensembles[nm] = ensemble(
            times,
            stack("position_error") if per else np.zeros((0, T, dim)),
            stack("velocity_error") if per else np.zeros((0, T, dim)),
            nees=stack("nees") if per else np.zeros((0, T)),
            nis=stack("nis") if per else None,
            nis_dof=stack("nis_dof") if per else None,
            final_position_error=np.array([p["final_position_error"] for p in per]),
            final_velocity_error=np.array([p["final_velocity_error"] for p in per]),
            state_dim=scenario.state_dim,
            threshold=threshold,
            confidence=confidence,
            bound=sqrt_bound,
            containment=stack("containment") if has_set else None,
            width_position=stack("width_position") if has_set else None,
            width_velocity=stack("width_velocity") if has_set else None,
        )

    return ensembles


def _add_converged_nees(summaries, scenario, names, ok, ensembles, times, confidence) -> None:
    """Add each estimator's NEES over each run's converged part (``nees_converged_part``) to ``summaries``."""
    for nm in names:
        per = [r["estimators"][nm] for r in ok]
        if per:
            part = converged_nees(
                np.stack([p["nees"] for p in per]),
                _converged_part(ensembles[nm], per, times),
                scenario.state_dim,
                confidence,
            )
            summaries[nm]["nees_converged_part"] = {
                "time_average": part["time_average"],
                "inside_fraction": part["inside_fraction"],
                "all_runs_from": None
                if part["all_runs_from"] is None
                else float(times[part["all_runs_from"]]),
                "final": None if not np.isfinite(part["mean"][-1]) else float(part["mean"][-1]),
                "final_bounds": [
                    None if not np.isfinite(v) else float(v) for v in part["bounds"][-1]
                ],
            }


def _write_outputs(
    out,
    summary,
    scenario,
    names,
    ok,
    failed,
    ensembles,
    times,
    record,
    sqrt_bound,
    sqrt_linear,
    k_every,
) -> None:
    """``runs.parquet``, ``series.parquet``, ``statistics.rrd`` (with ``record``) and, last, ``summary.json``."""
    files = {
        "summary": str(out / "summary.json"),
        "runs": str(out / "runs.parquet"),
        "series": str(out / "series.parquet"),
    }
    _write_runs(out / "runs.parquet", ok, failed, names, ensembles)
    _write_series(out / "series.parquet", ok, names, times)
    if record:
        _record_statistics(
            out / "statistics.rrd", scenario, names, ensembles, sqrt_bound, sqrt_linear, k_every
        )
        files["recording"] = str(out / "statistics.rrd")
    summary["files"] = files
    from quadobs.testbed.episode import write_json_atomic

    write_json_atomic(out / "summary.json", summary)


def run_campaign(
    scenario: Scenario,
    *,
    runs: int,
    estimators: list[str] | None = None,
    out_dir: str | Path | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    every: float | None = None,
    threshold: float = 1.0,
    confidence: float = 0.95,
    progress: bool = False,
    record: bool = True,
    start_method: str | None = None,
    retries: int = 2,
) -> CampaignResult:
    """Run ``runs`` seeded episodes of ``scenario`` and compute their statistics (see the module docstring).

    Parameters
    ----------
    scenario : Scenario
    runs : int
        Number of runs (at least 1).
    estimators : list of str, optional
        Default: the augmented observer and the scenario's variants.
    out_dir : path, optional
        Folder for ``summary.json``, ``runs.parquet``, ``series.parquet``, ``statistics.rrd``.
    scheduler : str, optional
        Address of a Dask distributed scheduler (``tcp://host:port``); default: local processes.
    workers : int, optional
        Local processes (default: the number of CPUs; 0: in the calling process). Not
        with ``scheduler``.
    every : float, optional
        Sampling period (s) of the statistics over time; must divide the duration
        (default about 0.1 s).
    threshold : float
        Final position error (m) below which a run counts as converged.
    confidence : float
        Of the two-sided chi-square intervals of NEES and NIS.
    progress : bool
        Progress bar on stderr.
    record : bool
        Write ``statistics.rrd`` (needs rerun).
    start_method : {"fork", "spawn", "forkserver"}, optional
        How local worker processes start (default: the platform's).
    retries : int
        Local processes: how many times a run whose worker process was lost (killed, out
        of memory) is started again on a fresh worker before it is reported as failed
        (0 to 100, default 2). A run that raises is not retried: its error is its result.
    """
    names, threshold, confidence = _checked_settings(
        scenario, runs, retries, estimators, scheduler, workers, start_method, threshold, confidence
    )
    k_every = _collect_every(scenario, every)
    out = None
    if out_dir is not None:
        from quadobs.errors import check_writable

        out = Path(out_dir)
        check_writable(out / "summary.json")

    data = scenario.to_dict()
    tasks = [
        {
            "index": i,
            "seed": run_seed(scenario.seed, i),
            "scenario": data,
            "source": scenario.source,
            "estimators": names,
            "collect_every": k_every,
        }
        for i in range(runs)
    ]
    bound = scenario_crb(scenario, every=k_every)
    linear = immersion_bound(scenario, every=k_every)

    wall0 = _time.perf_counter()
    results, interrupted, backend = _execute(
        tasks, scheduler, workers, progress, scenario.name, start_method, retries
    )
    wall = _time.perf_counter() - wall0

    ok = sorted((r for r in results if r["status"] == "ok"), key=lambda r: r["index"])
    failed = sorted((r for r in results if r["status"] != "ok"), key=lambda r: r["index"])
    times = (
        ok[0]["time"] if ok else np.arange(scenario.steps // k_every + 1) * k_every * scenario.dt
    )
    sqrt_bound = None if bound is None else _sqrt_traces(scenario, bound[1])
    sqrt_linear = None if linear is None else _sqrt_traces(scenario, linear[1])
    ensembles = _ensembles(scenario, names, ok, times, sqrt_bound, threshold, confidence)
    summaries = {nm: ensembles[nm].summary() for nm in names}
    _add_converged_nees(summaries, scenario, names, ok, ensembles, times, confidence)
    summary = {
        "scenario": scenario.name,
        "source": scenario.source,
        "base_seed": scenario.seed,
        "runs_requested": runs,
        "runs_completed": len(ok),
        "runs_failed": len(failed),
        "failed": [{"run": r["index"], "seed": r["seed"], "error": r["error"]} for r in failed],
        "retried": [
            {"run": r["index"], "seed": r["seed"], "lost": r["lost"]}
            for r in sorted(results, key=lambda r: r["index"])
            if r.get("lost")
        ],
        "interrupted": interrupted,
        "duration": scenario.duration,
        "physics_rate": scenario.physics_rate,
        "sample_every": k_every * scenario.dt,
        "estimator_names": names,
        "convergence_threshold": threshold,
        "confidence": confidence,
        "backend": backend,
        "wall_time": wall,
        "run_wall_time_mean": float(np.mean([r["wall_time"] for r in ok])) if ok else None,
        "seed_rule": "seed_i = run_seed(base_seed, i): SeedSequence(base_seed, spawn_key=(i,)), 63 bits",
        "pcrb": _bound_summary(bound, sqrt_bound, sqrt_linear),
        "estimators": summaries,
    }
    if ok and all("flight" in r for r in ok):
        summary["flight"] = flight_summary([r["flight"] for r in ok], names)
    result = CampaignResult(summary, ensembles, ok + failed, bound)
    if out is not None:
        _write_outputs(
            out,
            summary,
            scenario,
            names,
            ok,
            failed,
            ensembles,
            times,
            record,
            sqrt_bound,
            sqrt_linear,
            k_every,
        )
    return result


def _velocity_selector(scenario: Scenario) -> np.ndarray:
    """``(dim, n)``: the ground velocity ``v`` (or ``v_a + v_w``) from the state."""
    dim, n = scenario.dimension, scenario.state_dim
    T = np.zeros((dim, n))
    T[:, dim : 2 * dim] = np.eye(dim)
    if scenario.has_wind:
        T[:, 2 * dim :] = np.eye(dim)
    return T


def _sqrt_traces(scenario: Scenario, B: np.ndarray) -> np.ndarray:
    """``(T, 2)``: square roots of the traces of a state covariance's position and ground-velocity blocks."""
    dim = scenario.dimension
    Tv = _velocity_selector(scenario)
    return np.stack(
        [
            np.sqrt(np.trace(B[:, :dim, :dim], axis1=1, axis2=2)),
            np.sqrt(np.einsum("ia,tab,ib->t", Tv, B, Tv)),
        ],
        axis=1,
    )


def _bound_summary(bound, sqrt_bound, sqrt_linear) -> dict:
    if bound is None:
        return {
            "available": False,
            "note": "a sensor is noise-free: the information is infinite and the bound zero",
        }
    out = {
        "available": True,
        "note": bound[2],
        "final_sqrt_trace_position": float(sqrt_bound[-1, 0]),
        "final_sqrt_trace_velocity": float(sqrt_bound[-1, 1]),
    }
    if sqrt_linear is not None:
        out["immersion_bound_final_sqrt_trace_position"] = float(sqrt_linear[-1, 0])
        out["immersion_bound_final_sqrt_trace_velocity"] = float(sqrt_linear[-1, 1])
    return out


def _check_reach(scenario: Scenario, names: list[str], scheduler, workers, start_method) -> None:
    """Refuse estimators registered at run time when the workers cannot see them (not forked)."""
    import multiprocessing

    methods = multiprocessing.get_all_start_methods()
    if start_method is not None and start_method not in methods:
        raise QuadobsError(f"start_method: expected one of {methods}, got {start_method!r}")
    if workers == 0 and scheduler is None:
        return
    method = start_method or multiprocessing.get_start_method(allow_none=False)
    if scheduler is None and method == "fork":
        return
    variants = dict(scenario.observer.variants)
    for nm in names:
        if nm not in variants and estimator_factory(nm, scenario)[1] == "runtime":
            where = "Dask workers" if scheduler is not None else f"{method!r} workers"
            raise QuadobsError(
                f"estimators: {nm!r} is registered at run time, which {where} do not see; "
                "declare it as an entry point of the group 'quadobs.estimators'"
            )


def _execute(
    tasks: list[dict],
    scheduler,
    workers,
    progress: bool,
    label: str,
    start_method: str | None = None,
    retries: int = 2,
) -> tuple[list[dict], bool, dict]:
    """Run the tasks; returns the results (failures included), whether Ctrl-C stopped it, and the backend."""
    bar = None
    results: list[dict] = []
    interrupted = False

    def done(res: dict) -> None:
        results.append(res)
        if bar is not None:
            bar.update(1)
            nf = sum(r["status"] != "ok" for r in results)
            if nf:
                bar.set_postfix(failed=nf)

    def lost(task: dict, exc: BaseException) -> dict:
        return {
            "index": task["index"],
            "seed": task["seed"],
            "status": "failed",
            "error": f"{type(exc).__name__}: {exc}",
            "traceback": "".join(traceback.format_exception(exc)),
            "wall_time": float("nan"),
        }

    if scheduler is not None:
        backend = {"kind": "dask", "scheduler": scheduler}
    elif workers == 0:
        backend = {"kind": "in-process", "workers": 0}
    else:
        backend = {"kind": "processes", "workers": int(workers or os.cpu_count() or 1)}

    def make_bar():
        if not progress:
            return None
        from tqdm import tqdm

        return tqdm(total=len(tasks), unit="run", desc=label, leave=False)

    if backend["kind"] == "in-process":
        bar = make_bar()
        try:
            for task in tasks:
                done(run_one(task))
        except KeyboardInterrupt:
            interrupted = True
        finally:
            if bar is not None:
                bar.close()
        return results, interrupted, backend

    if backend["kind"] == "processes":
        import multiprocessing

        context = (
            multiprocessing.get_context(start_method)
            if start_method
            else multiprocessing.get_context()
        )
        bar = make_bar()
        try:
            interrupted = _run_local(
                tasks, min(backend["workers"], len(tasks)), context, done, lost, retries
            )
        finally:
            if bar is not None:
                bar.close()
        backend["retries"] = retries
        return results, interrupted, backend

    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError:  # pragma: no cover - depends on the environment
        raise QuadobsError(
            "scheduler: running on a Dask cluster needs dask.distributed (pip install 'quadobs[cluster]')"
        ) from None
    try:
        client = Client(scheduler, timeout=30)
    except OSError as exc:
        raise QuadobsError(f"scheduler: cannot connect to {scheduler!r} ({exc})") from None
    try:
        backend["workers"] = len(client.scheduler_info().get("workers", {}))
        token = f"{os.getpid()}-{_time.time_ns()}"
        futures = {
            client.submit(run_one, t, pure=False, key=f"quadobs-run-{t['index']}-{token}"): t
            for t in tasks
        }
        bar = make_bar()
        try:
            for fut in dask_completed(list(futures)):
                if fut.status == "finished":
                    done(fut.result())
                else:
                    try:
                        exc = fut.exception()
                    except BaseException as e:  # cancelled, lost
                        exc = e
                    done(lost(futures[fut], exc))
        except KeyboardInterrupt:
            interrupted = True
            client.cancel(list(futures))
    finally:
        if bar is not None:
            bar.close()
        client.close()
    return results, interrupted, backend


# --------------------------------------------------------------------------------------
# Local worker processes
# --------------------------------------------------------------------------------------


def _die_with_parent(parent: int) -> None:
    """In a worker: end when the campaign's process ends, even by ``SIGKILL``.

    On Linux the kernel sends ``SIGKILL`` when the parent dies (``prctl(PR_SET_PDEATHSIG)``);
    everywhere, a daemon thread checks once a second that the parent is still the same.
    """
    import threading

    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, 9)  # PR_SET_PDEATHSIG, SIGKILL
    except (OSError, AttributeError):  # not Linux
        pass
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)

    def watch() -> None:
        while True:
            _time.sleep(1.0)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="quadobs-parent-watch", daemon=True).start()


def _worker_main(conn, parent: int) -> None:
    """A local worker: run the tasks received on ``conn`` and send back each result, until EOF."""
    import signal

    signal.signal(
        signal.SIGINT, signal.SIG_IGN
    )  # Ctrl-C is the campaign's to handle: it stops the workers
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with_parent(parent)
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        conn.send(run_one(task))


class _Worker:
    """One local worker process and the task it holds (``None``: idle)."""

    def __init__(self, context) -> None:
        self.conn, child = context.Pipe(duplex=True)
        self.proc = context.Process(
            target=_worker_main,
            args=(child, os.getpid()),
            daemon=True,
            name="quadobs-campaign-worker",
        )
        self.proc.start()
        child.close()
        self.task: dict | None = None

    def give(self, task: dict) -> None:
        self.task = task
        self.conn.send(task)

    def stop(self) -> None:
        """End the process: SIGTERM, then SIGKILL after :data:`_TERMINATE_GRACE` seconds."""
        self.conn.close()
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(_TERMINATE_GRACE)
            if self.proc.is_alive():
                self.proc.kill()
        self.proc.join(_TERMINATE_GRACE)


def _run_local(tasks: list[dict], n: int, context, done, lost, retries: int) -> bool:
    """Run ``tasks`` on ``n`` local worker processes; returns whether Ctrl-C stopped it.

    Each worker has its own pipe, and the loop waits on every pipe and every process
    sentinel at once (``multiprocessing.connection.wait``), so no dead worker can block
    it: a worker that dies holding a run (``SIGKILL``, out of memory) is replaced and the
    run started again, at most ``retries`` times, then reported failed with its seed
    (``lost`` counts the losses). Ctrl-C (or SIGTERM mapped to it) ends every worker and
    keeps the finished runs; the workers end with the campaign's process in any case.
    """
    from collections import deque
    from multiprocessing.connection import wait

    queue, losses = deque(tasks), {}
    pool: list[_Worker] = []
    try:
        pool = [_Worker(context) for _ in range(n)]
        while queue or any(w.task is not None for w in pool):
            for i, w in enumerate(pool):
                if w.task is None and queue:
                    if not w.proc.is_alive():  # died while idle: a fresh one takes its place
                        w.stop()
                        pool[i] = w = _Worker(context)
                    try:
                        w.give(queue.popleft())
                    except (
                        OSError
                    ):  # died just now: the sentinel below reports it, the run is retried
                        pass
            busy = [w for w in pool if w.task is not None]
            ready = set(wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout=1.0))
            for i, w in enumerate(pool):
                if w.task is None or not (w.conn in ready or w.proc.sentinel in ready):
                    continue
                result = _receive(w)
                if result is not None:
                    w.task = None
                    result["lost"] = losses.get(result["index"], 0)
                    done(result)
                    continue
                task, w.task = w.task, None
                losses[task["index"]] = count = losses.get(task["index"], 0) + 1
                w.stop()
                pool[i] = _Worker(context)
                if count <= retries:
                    queue.appendleft(task)
                else:
                    code = w.proc.exitcode
                    why = (
                        f"killed by signal {-code}"
                        if code is not None and code < 0
                        else f"exit status {code}"
                    )
                    done(
                        {
                            **lost(
                                task, RuntimeError(f"worker process lost ({why}), {count} times")
                            ),
                            "lost": count,
                        }
                    )
        return False
    except KeyboardInterrupt:
        return True
    finally:
        _stop_all(pool)


def _stop_all(pool: list[_Worker]) -> None:
    """End every worker: SIGTERM to all, then SIGKILL to those still there after the grace period."""
    for w in pool:
        w.conn.close()
        if w.proc.is_alive():
            w.proc.terminate()
    deadline = _time.monotonic() + _TERMINATE_GRACE
    for w in pool:
        w.proc.join(max(deadline - _time.monotonic(), 0.0))
        if w.proc.is_alive():
            w.proc.kill()
            w.proc.join(_TERMINATE_GRACE)


def _receive(w: _Worker) -> dict | None:
    """The result a worker sent, or ``None`` when it died without one."""
    try:
        if w.conn.poll():
            return w.conn.recv()
    except (EOFError, OSError):
        pass
    return None


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


def _publish(tmp: str | Path, path: Path) -> None:
    """Give a temporary file the usual permissions (``mkstemp`` makes it private) and rename it into place."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    os.replace(tmp, path)


def _write_table_atomic(path: Path, columns: dict) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table(columns)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp)
        _publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write_runs(
    path: Path, ok: list[dict], failed: list[dict], names: list[str], ensembles: dict[str, Ensemble]
) -> None:
    import pyarrow as pa

    cols: dict[str, list] = {
        k: []
        for k in (
            "run",
            "seed",
            "status",
            "error",
            "estimator",
            "final_position_error",
            "final_velocity_error",
            "converged",
            "convergence_time",
            "time_to_1m",
            "time_to_0p1m",
            "final_nees",
            "mean_nis",
            "handover_time",
            "final_containment",
            "wall_time",
        )
    }

    def add(**kw):
        for k in cols:
            cols[k].append(kw.get(k))

    def num(v):
        return None if v is None or not np.isfinite(v) else float(v)

    for nm in names:
        ens = ensembles[nm]
        for i, r in enumerate(ok):
            e = r["estimators"][nm]
            nis = e["nis"][np.isfinite(e["nis"])]
            cont = e.get("containment")
            add(
                run=r["index"],
                seed=r["seed"],
                status="ok",
                estimator=nm,
                final_position_error=num(e["final_position_error"]),
                final_velocity_error=num(e["final_velocity_error"]),
                converged=bool(ens.converged[i]),
                convergence_time=num(ens.convergence_time[i]),
                time_to_1m=num(e["time_to_1m"]),
                time_to_0p1m=num(e["time_to_0p1m"]),
                final_nees=num(e["nees"][-1]),
                mean_nis=num(nis.mean()) if nis.size else None,
                handover_time=num(e["handover_time"]) if "handover_time" in e else None,
                final_containment=num(cont[-1]) if cont is not None else None,
                wall_time=num(r["wall_time"]),
            )
    for r in failed:
        add(
            run=r["index"],
            seed=r["seed"],
            status="failed",
            error=r["error"],
            wall_time=num(r["wall_time"]),
        )
    types = {
        "run": pa.int64(),
        "seed": pa.int64(),
        "status": pa.string(),
        "error": pa.string(),
        "estimator": pa.string(),
        "converged": pa.bool_(),
    }
    _write_table_atomic(
        path, {k: pa.array(v, type=types.get(k, pa.float64())) for k, v in cols.items()}
    )


def _write_series(path: Path, ok: list[dict], names: list[str], times: np.ndarray) -> None:
    import pyarrow as pa

    T = times.shape[0]
    parts = {
        k: []
        for k in (
            "run",
            "estimator",
            "time",
            "position_error",
            "velocity_error",
            "nees",
            "nis",
            "nis_dof",
        )
    }
    for nm in names:
        for r in ok:
            e = r["estimators"][nm]
            parts["run"].append(np.full(T, r["index"], dtype=np.int64))
            parts["estimator"].extend([nm] * T)
            parts["time"].append(times)
            parts["position_error"].append(np.linalg.norm(e["position_error"], axis=1))
            parts["velocity_error"].append(np.linalg.norm(e["velocity_error"], axis=1))
            parts["nees"].append(e["nees"])
            parts["nis"].append(e["nis"])
            parts["nis_dof"].append(np.asarray(e["nis_dof"], dtype=np.int64))
    cols = {}
    for k, v in parts.items():
        if k == "estimator":
            cols[k] = pa.array(v, type=pa.string())
        elif v:
            cols[k] = pa.array(np.concatenate(v))
        else:
            cols[k] = pa.array([], type=pa.int64() if k in ("run", "nis_dof") else pa.float64())
    _write_table_atomic(path, cols)


_PALETTE = [(230, 90, 40), (40, 160, 90), (150, 60, 200), (200, 170, 30), (30, 150, 200)]


def _record_statistics(
    path: Path, scenario: Scenario, names, ensembles, sqrt_bound, sqrt_linear, k_every: int
) -> None:
    """The statistics over time as an ``.rrd`` (entity layout in the module docstring of :mod:`quadobs.studies.campaign`)."""
    import rerun.blueprint as rrb

    from quadobs.recording import Recorder

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".rrd", dir=path.parent)
    os.close(fd)
    views = [
        rrb.TimeSeriesView(
            name="Position RMSE, percentiles, sqrt PCRB (m)",
            contents=[f"/stats/{e}/position/**" for e in names]
            + ["/stats/pcrb/position", "/stats/immersion_bound/position"],
        ),
        rrb.TimeSeriesView(
            name="Velocity RMSE, sqrt PCRB (m/s)",
            contents=[f"/stats/{e}/velocity/**" for e in names]
            + ["/stats/pcrb/velocity", "/stats/immersion_bound/velocity"],
        ),
        rrb.TimeSeriesView(
            name="RMSE / sqrt(PCRB)", contents=[f"/stats/{e}/ratio/**" for e in names]
        ),
        rrb.TimeSeriesView(
            name="NEES and chi-square bounds", contents=[f"/stats/{e}/nees/**" for e in names]
        ),
        rrb.TimeSeriesView(
            name="NIS and chi-square bounds", contents=[f"/stats/{e}/nis/**" for e in names]
        ),
        rrb.TimeSeriesView(
            name="Fraction of runs within the threshold",
            contents=[f"/stats/{e}/converged" for e in names],
        ),
    ]
    sets = [e for e in names if np.isfinite(ensembles[e].containment).any()]
    if sets:
        views.append(
            rrb.TimeSeriesView(
                name="Set estimators: containment, width",
                contents=[f"/stats/{e}/set/**" for e in sets],
            )
        )
    blueprint = rrb.Blueprint(rrb.Grid(*views), collapse_panels=False)
    T = next(iter(ensembles.values())).times.shape[0]
    try:
        rec = Recorder(
            tmp,
            recording_id=f"{scenario.name}-campaign-seed{scenario.seed}",
            blueprint=blueprint,
            capacity=max(T, 1),
        )
        series = {}
        if sqrt_bound is not None:
            series["pcrb"] = (
                rec.series(
                    "stats/pcrb/position", 1, names=["sqrt PCRB position"], color=(40, 90, 220)
                ),
                rec.series(
                    "stats/pcrb/velocity", 1, names=["sqrt PCRB velocity"], color=(40, 90, 220)
                ),
            )
        if sqrt_linear is not None:
            series["linear"] = (
                rec.series(
                    "stats/immersion_bound/position",
                    1,
                    names=["best linear filter on the immersion"],
                    color=(120, 120, 120),
                ),
                rec.series(
                    "stats/immersion_bound/velocity",
                    1,
                    names=["best linear filter on the immersion"],
                    color=(120, 120, 120),
                ),
            )
        for i, e in enumerate(names):
            c = _PALETTE[i % len(_PALETTE)]
            s = {
                "rmse_p": rec.series(f"stats/{e}/position/rmse", 1, names=[f"{e} RMSE"], color=c),
                "pct_p": rec.series(
                    f"stats/{e}/position/percentiles",
                    3,
                    names=[f"{e} |e_p| 5%", f"{e} median", f"{e} 95%"],
                ),
                "rmse_v": rec.series(f"stats/{e}/velocity/rmse", 1, names=[f"{e} RMSE"], color=c),
                "ratio": rec.series(
                    f"stats/{e}/ratio", 2, names=[f"{e} position", f"{e} velocity"]
                ),
                "nees": rec.series(f"stats/{e}/nees/mean", 1, names=[f"{e} mean NEES"], color=c),
                "nees_b": rec.series(
                    f"stats/{e}/nees/bounds", 2, names=[f"{e} lower", f"{e} upper"]
                ),
                "nis": rec.series(
                    f"stats/{e}/nis/mean", 1, skip_nan=True, names=[f"{e} mean NIS"], color=c
                ),
                "nis_b": rec.series(
                    f"stats/{e}/nis/bounds", 2, skip_nan=True, names=[f"{e} lower", f"{e} upper"]
                ),
                "conv": rec.series(f"stats/{e}/converged", 1, names=[f"{e}"], color=c),
            }
            if e in sets:
                s["cont"] = rec.series(
                    f"stats/{e}/set/containment", 1, names=[f"{e} containment"], color=c
                )
                s["width"] = rec.series(
                    f"stats/{e}/set/width", 2, names=[f"{e} width position", f"{e} width velocity"]
                )
            series[e] = s
        for j in range(T):
            ens0 = ensembles[names[0]]
            row = rec.row(j * k_every, float(ens0.times[j]))
            if sqrt_bound is not None:
                series["pcrb"][0].buf[row, 0] = sqrt_bound[j, 0]
                series["pcrb"][1].buf[row, 0] = sqrt_bound[j, 1]
            if sqrt_linear is not None:
                series["linear"][0].buf[row, 0] = sqrt_linear[j, 0]
                series["linear"][1].buf[row, 0] = sqrt_linear[j, 1]
            for e in names:
                en, s = ensembles[e], series[e]
                s["rmse_p"].buf[row, 0] = en.rmse_position[j]
                s["pct_p"].buf[row] = en.position_percentiles[j]
                s["rmse_v"].buf[row, 0] = en.rmse_velocity[j]
                s["ratio"].buf[row] = (en.ratio_position[j], en.ratio_velocity[j])
                s["nees"].buf[row, 0] = en.mean_nees[j]
                s["nees_b"].buf[row] = en.nees_bounds[j]
                s["nis"].buf[row, 0] = en.mean_nis[j]
                s["nis_b"].buf[row] = en.nis_bounds[j] if np.isfinite(en.mean_nis[j]) else np.nan
                s["conv"].buf[row, 0] = en.converged_now[j]
                if "cont" in s:
                    s["cont"].buf[row, 0] = en.containment[j]
                    s["width"].buf[row] = (en.width_position[j], en.width_velocity[j])
        rec.close()
        _publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------------------
# The printed table
# --------------------------------------------------------------------------------------


def _f(v, digits=3, unit=""):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}g}{unit}"


def print_campaign(summary: dict, file=None) -> None:
    """A short table of a campaign summary: one row per estimator."""
    import sys

    file = file or sys.stdout
    b = summary["backend"]
    where = (
        b["kind"]
        + (f" ({b['workers']} workers)" if b["kind"] != "in-process" else "")
        + (f" at {b['scheduler']}" if "scheduler" in b else "")
    )
    print(
        f"campaign {summary['scenario']}: {summary['runs_completed']} of {summary['runs_requested']} runs completed"
        f" ({summary['runs_failed']} failed), {summary['duration']:g} s each, {summary['wall_time']:.1f} s wall on {where}"
        + ("  [INTERRUPTED]" if summary.get("interrupted") else ""),
        file=file,
    )
    pc = summary["pcrb"]
    if pc["available"]:
        print(
            f"posterior CRB at the end: sqrt(tr) = {_f(pc['final_sqrt_trace_position'])} m, "
            f"{_f(pc['final_sqrt_trace_velocity'])} m/s ({pc['note']})",
            file=file,
        )
        if "immersion_bound_final_sqrt_trace_position" in pc:
            print(
                f"best linear filter on the immersion at the end: sqrt(tr) = {_f(pc['immersion_bound_final_sqrt_trace_position'])} m, "
                f"{_f(pc['immersion_bound_final_sqrt_trace_velocity'])} m/s",
                file=file,
            )
    else:
        print(f"posterior CRB: not available ({pc['note']})", file=file)
    thr = summary["convergence_threshold"]
    cols = [
        "estimator",
        f"converged (<{thr:g} m)",
        "final RMSE p (m)",
        "final RMSE v (m/s)",
        "RMSE/sqrt(PCRB) p",
        "RMSE p converged",
        "mean NEES end [bounds]",
        "NEES in bounds",
        "median t_conv",
    ]
    rows = []
    for name, e in summary["estimators"].items():
        nb = e["chi2_bounds"]["nees"]
        frac = e["converged_fraction"]
        rows.append(
            [
                name,
                "-" if frac is None else f"{e['converged_runs']}/{e['runs']} ({100 * frac:.0f}%)",
                _f(e["final_rmse_position"]),
                _f(e["final_rmse_velocity"]),
                _f(e["rmse_over_sqrt_pcrb"]),
                _f(e["final_rmse_position_converged"]),
                f"{_f(e['mean_nees'])} [{_f(nb[0])}, {_f(nb[1])}]",
                "-"
                if e["nees_inside_fraction"] is None
                else f"{100 * e['nees_inside_fraction']:.0f}%",
                _f(e["median_convergence_time"], unit=" s"),
            ]
        )
    widths = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)), file=file)
    for r in rows:
        print("  ".join(v.ljust(w) for v, w in zip(r, widths)), file=file)
    fl = summary.get("flight")
    if fl:
        rmse = ", ".join(
            f"{nm} {_f(v['median'])} / {_f(v['max'])}"
            for nm, v in fl["flight_position_rmse"].items()
        )
        print(
            f"flight: {fl['crashed']} of {fl['runs']} crashed; tracking RMS median {_f(fl['tracking_rms_median'])} m,"
            f" largest {_f(fl['tracking_rms_max'])} m; largest tracking error {_f(fl['tracking_max'])} m;"
            f" {_f(fl['time_on_estimate_mean'])} s on the estimate",
            file=file,
        )
        print(f"position RMSE after the switch (m), median / largest: {rmse}", file=file)
    for name, e in summary["estimators"].items():
        part = e.get("nees_converged_part") or {}
        if part.get("time_average") is not None:
            fb = part["final_bounds"]
            print(
                f"{name}: NEES over each run's converged part: time average {_f(part['time_average'])}, "
                f"{100 * part['inside_fraction']:.0f}% of samples inside their bounds, "
                f"at the end {_f(part['final'])} [{_f(fb[0])}, {_f(fb[1])}]",
                file=file,
            )
    for f in summary["failed"][:10]:
        print(f"failed: run {f['run']} (seed {f['seed']}): {f['error']}", file=file)
    if len(summary["failed"]) > 10:
        print(
            f"... and {len(summary['failed']) - 10} more failed runs (see summary.json)", file=file
        )
    if summary.get("files"):
        print(f"results: {summary['files']['summary']}, {summary['files']['runs']}", file=file)
        if "recording" in summary["files"]:
            print(f"statistics over time: rerun {summary['files']['recording']}", file=file)
