"""Monte Carlo campaigns: many seeded episodes, in local processes or on a Dask cluster, and their statistics.

A campaign runs ``runs`` episodes of one scenario (:func:`quadobs.testbed.episode.run_episode`,
MuJoCo truth, no recording per run), each with its own seed, and reduces them to the
statistics of :mod:`quadobs.evaluation.ensemble`: RMSE over time and at the end, convergence,
NEES and NIS against their chi-square intervals, and the ratio of the RMSE to the
posterior Cramér-Rao bound of the scenario.

The package is split by role: this module runs one seeded episode (:func:`run_one`) and the
campaign (:func:`run_campaign`); :mod:`~quadobs.studies.campaign.scheduling` hands the runs to
workers, :mod:`~quadobs.studies.campaign.storage` writes the folder and the journal of
finished runs, :mod:`~quadobs.studies.campaign.statistics` reduces the runs and
:mod:`~quadobs.studies.campaign.report` prints the table.

Seeds
    Run ``i`` uses ``seed_i = run_seed(scenario.seed, i)``, derived from the scenario's
    seed and the run index by :class:`numpy.random.SeedSequence` (``spawn_key=(i,)``), so
    the runs are independent, the same campaign gives the same runs wherever they are
    executed, and ``quadobs run SCENARIO --seed seed_i`` replays run ``i`` alone.

Execution
    By default the runs go to local worker processes: a small pool of
    :mod:`~quadobs.studies.campaign.scheduling` (with the platform's default start method,
    or ``start_method``), which replaces a worker that dies holding a run and starts the run
    again (``retries``); its module docstring says why it is not
    :class:`concurrent.futures.ProcessPoolExecutor`. ``workers=0`` runs them one after the
    other in the calling process. With ``scheduler=ADDRESS`` the same function is
    submitted to a Dask distributed cluster (``pip install 'quadobs[cluster]'``; the
    workers must have quadobs installed). Workers find estimators by name through the
    entry points of the group ``quadobs.estimators`` (:mod:`quadobs.testbed.registry`), so
    an estimator from another installed package runs everywhere; one registered at run
    time with :func:`~quadobs.testbed.registry.register_estimator` reaches forked workers
    only, and is refused up front for ``spawn``, ``forkserver`` and Dask. A run that raises is
    recorded as failed with its seed and error and the others go on; Ctrl-C stops the
    campaign and writes the statistics of the runs already finished.

Resume
    With ``out_dir``, every finished run is kept as it arrives in a journal beside the
    folder (:class:`~quadobs.studies.campaign.storage.Journal`). A campaign killed at any
    moment (``SIGKILL``, a power cut) keeps them, and the same campaign with ``resume=True``
    (``quadobs campaign ... --resume``) runs only the others; the runs are sorted by index
    before any statistic, so the result is the one an uninterrupted campaign gives, bit for
    bit (the wall-clock fields aside).

Results (in ``out_dir``)
    ``summary.json`` (aggregates per estimator under ``estimators.<name>``, see
    :meth:`quadobs.evaluation.ensemble.Ensemble.summary`; the failed runs; for a quadrotor
    scenario the flight figures under ``flight``, see
    :func:`~quadobs.studies.campaign.statistics.flight_summary`), ``runs.parquet`` (one
    row per run and estimator, and one per failed run), ``series.parquet`` (per run,
    estimator and sample time: error norms, NEES, NIS), ``statistics.rrd`` (the
    statistics over time). Parquet (via pyarrow, which the recording layer already
    needs) keeps the column types and is read by pandas, polars or DuckDB in one call.
    The folder is written as a whole: its files go to a staging folder that replaces the
    previous folder once complete, so a failure (a full disk) leaves the previous one as it
    was.
"""

from __future__ import annotations

import logging
import time as _time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError, as_finite_scalar, caused_by_interrupt
from quadobs.evaluation.ensemble import Ensemble, nees, set_containment
from quadobs.staging import check_replaceable_folder
from quadobs.studies.campaign.report import print_campaign
from quadobs.studies.campaign.scheduling import execute
from quadobs.studies.campaign.statistics import (
    add_converged_nees,
    bound_summary,
    ensembles_of,
    flight_summary,
    sqrt_traces,
)
from quadobs.studies.campaign.storage import CAMPAIGN_FILES, Journal, write_campaign_folder
from quadobs.testbed.bounds import immersion_bound, scenario_crb
from quadobs.testbed.flight import crash_record
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

log = logging.getLogger("quadobs.studies")

#: Most runs in one campaign, and most local worker processes.
MAX_RUNS = 1_000_000
MAX_WORKERS = 1024


def run_seed(base_seed: int, index: int) -> int:
    """The seed of run ``index`` of a campaign on a scenario of seed ``base_seed`` (63-bit)."""
    ss = np.random.SeedSequence(int(base_seed), spawn_key=(int(index),))
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


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
    resume: bool = False,
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
    resume : bool
        With ``out_dir``: keep the runs that a campaign stopped before its end (killed, Ctrl-C)
        finished, and run only the others (module docstring, "Resume"); the same
        campaign is needed (scenario, seed, runs' settings, estimators, sampling), though
        ``runs`` may differ (a stopped campaign resumed with more runs is extended).
    """
    names, threshold, confidence = _checked_settings(
        scenario, runs, retries, estimators, scheduler, workers, start_method, threshold, confidence
    )
    k_every = _collect_every(scenario, every)
    data = scenario.to_dict()
    tasks = [_task(scenario, data, i, names, k_every) for i in range(runs)]
    kept, journal = _kept_runs(out_dir, resume, data, names, k_every)
    results = [r for r in kept if r["index"] < runs]  # a resume may ask for fewer runs
    finished = {r["index"] for r in results}
    todo = [t for t in tasks if t["index"] not in finished]
    bound = scenario_crb(scenario, every=k_every)
    linear = immersion_bound(scenario, every=k_every)
    log.info("campaign %s: %d runs to do, %d kept", scenario.name, len(todo), len(results))

    wall0 = _time.perf_counter()
    interrupted, backend = _run_tasks(
        todo, results, journal, scheduler, workers, progress, scenario.name, start_method, retries
    )
    wall = _time.perf_counter() - wall0

    ok = sorted((r for r in results if r["status"] == "ok"), key=lambda r: r["index"])
    failed = sorted((r for r in results if r["status"] != "ok"), key=lambda r: r["index"])
    times = (
        ok[0]["time"] if ok else np.arange(scenario.steps // k_every + 1) * k_every * scenario.dt
    )
    curves = tuple(None if b is None else sqrt_traces(scenario, b[1]) for b in (bound, linear))
    ensembles = ensembles_of(scenario, names, ok, times, curves[0], threshold, confidence)
    summary = _summary(scenario, runs, k_every, results, ok, failed, names, threshold, confidence)
    summary.update(interrupted=interrupted, backend=backend, wall_time=wall)
    _add_statistics(summary, scenario, names, ok, ensembles, times, bound, curves, confidence)
    result = CampaignResult(summary, ensembles, ok + failed, bound)
    if journal is not None:
        write_campaign_folder(journal.folder, result, scenario, times, curves, k_every, record)
        if not interrupted:
            journal.remove()
    return result


def _task(scenario: Scenario, data: dict, i: int, names: list[str], k_every: int) -> dict:
    """Run ``i``'s task for :func:`run_one`."""
    return {
        "index": i,
        "seed": run_seed(scenario.seed, i),
        "scenario": data,
        "source": scenario.source,
        "estimators": names,
        "collect_every": k_every,
    }


def _add_statistics(summary, scenario, names, ok, ensembles, times, bound, curves, confidence):
    """The summary's statistics: per estimator, the bounds, the flight figures of a quadrotor."""
    summaries = {nm: ensembles[nm].summary() for nm in names}
    add_converged_nees(summaries, scenario, names, ok, ensembles, times, confidence)
    summary.update(
        run_wall_time_mean=float(np.mean([r["wall_time"] for r in ok])) if ok else None,
        seed_rule="seed_i = run_seed(base_seed, i): SeedSequence(base_seed, spawn_key=(i,)), 63 bits",
        pcrb=bound_summary(bound, *curves),
        estimators=summaries,
    )
    if ok and all("flight" in r for r in ok):
        summary["flight"] = flight_summary([r["flight"] for r in ok], names)


def _kept_runs(out_dir, resume: bool, data: dict, names: list[str], k_every: int):
    """The runs kept by the journal of ``out_dir`` (with ``resume``), and the journal (``None`` without a folder)."""
    if out_dir is None:
        if resume:
            raise QuadobsError("resume: needs out_dir, the folder whose journal holds the runs")
        return [], None
    from quadobs.errors import check_writable

    out = Path(out_dir)
    check_replaceable_folder(out, CAMPAIGN_FILES, "out_dir")
    check_writable(out / "summary.json")
    journal = Journal(out, {"scenario": data, "estimators": names, "collect_every": k_every})
    return journal.start(resume), journal


def _run_tasks(todo, results, journal, scheduler, workers, progress, label, start_method, retries):
    """Run ``todo``, each result appended to ``results`` and kept by the journal as it arrives."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="run", desc=label, leave=False)

    def done(res: dict) -> None:
        if journal is not None:
            journal.keep(res)
        results.append(res)
        if res["status"] != "ok":
            log.warning(
                "campaign: run %d (seed %d) failed: %s", res["index"], res["seed"], res["error"]
            )
        if bar is not None:
            bar.update(1)
            nf = sum(r["status"] != "ok" for r in results)
            if nf:
                bar.set_postfix(failed=nf)

    try:
        return execute(
            todo,
            run_one,
            done,
            scheduler=scheduler,
            workers=workers,
            start_method=start_method,
            retries=retries,
        )
    finally:
        if bar is not None:
            bar.close()


def _summary(scenario, runs, k_every, results, ok, failed, names, threshold, confidence) -> dict:
    """The summary's fields that describe the campaign and its runs (the statistics are added after)."""
    return {
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
        "interrupted": False,
        "duration": scenario.duration,
        "physics_rate": scenario.physics_rate,
        "sample_every": k_every * scenario.dt,
        "estimator_names": names,
        "convergence_threshold": threshold,
        "confidence": confidence,
    }
