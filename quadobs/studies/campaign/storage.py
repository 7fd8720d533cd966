"""Storage of a campaign: its folder written as a whole, its tables and recording, and the journal of finished runs.

The folder (``summary.json``, ``runs.parquet``, ``series.parquet``, ``statistics.rrd``) is
written into a staging folder that replaces the previous one once complete
(:func:`quadobs.staging.write_folder_staged`): a failure (a full disk) leaves the previous
folder as it was, never a mixture of old and new files.

The journal (:class:`Journal`) keeps each finished run as it arrives, in a folder beside the
campaign's (``.<name>.runs``), each run in its own file written through
:func:`quadobs.staging.write_staged`: a campaign killed at any moment (``SIGKILL``) loses at
most the runs in progress, and ``resume`` starts only the others. The journal records what
fixes the runs' results (the scenario as data, the estimators, the sampling), and a resume
refuses a journal of another campaign. It is removed once the folder is in place.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.evaluation.ensemble import Ensemble
from quadobs.staging import write_folder_staged, write_staged
from quadobs.testbed.outputs import write_json_staged
from quadobs.testbed.scenario import Scenario

if TYPE_CHECKING:
    from quadobs.studies.campaign import CampaignResult

__all__ = ["Journal", "write_campaign_folder"]

log = logging.getLogger("quadobs.studies")

#: The files of a campaign's folder: an existing folder holding anything else is not replaced.
CAMPAIGN_FILES = {"summary.json", "runs.parquet", "series.parquet", "statistics.rrd"}

#: The journal's format; a journal of another format is not resumed from.
JOURNAL_FORMAT = 1


class Journal:
    """The finished runs of a campaign into ``folder``, kept one file each until the campaign is written.

    Parameters
    ----------
    folder : path
        The campaign's folder; the journal is ``.<name>.runs`` beside it.
    identity : dict
        What fixes the runs' results (plain data); a resume needs the same.
    """

    def __init__(self, folder: Path, identity: dict) -> None:
        self.folder = folder
        self.path = folder.parent / f".{folder.name}.runs"
        text = json.dumps(identity, sort_keys=True, default=str)
        self.key = hashlib.sha256(text.encode()).hexdigest()

    def start(self, resume: bool) -> list[dict]:
        """Open the journal; with ``resume``, the finished runs it holds (else it is emptied)."""
        kept: list[dict] = []
        if resume and self.path.is_dir():
            kept = self._read()
        elif self.path.exists():
            stale = len(list(self.path.glob("run-*.pickle")))
            if stale:
                log.warning(
                    "campaign: %d finished runs of a stopped campaign started over (resume keeps them)",
                    stale,
                )
            shutil.rmtree(self.path)
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            write_staged(self.path / "campaign.json", self._write_key, "campaign journal")
        except OSError as exc:
            raise QuadobsError(
                f"campaign journal {os.fspath(self.path)!r}: cannot be written ({exc.strerror or exc})"
            ) from None
        if resume:
            log.info("campaign: %d finished runs kept from %s", len(kept), self.path)
        return kept

    def _write_key(self, tmp: Path) -> None:
        tmp.write_text(json.dumps({"format": JOURNAL_FORMAT, "key": self.key}) + "\n")

    def _read(self) -> list[dict]:
        try:
            head = json.loads((self.path / "campaign.json").read_text())
        except (OSError, ValueError):
            head = None
        if head != {"format": JOURNAL_FORMAT, "key": self.key}:
            raise QuadobsError(
                f"resume: {os.fspath(self.path)!r} holds the runs of another campaign "
                "(another scenario, seed, estimators or sampling); run without resume to start over"
            )
        kept = []
        for entry in sorted(os.scandir(self.path), key=lambda e: e.name):
            if not (entry.name.startswith("run-") and entry.name.endswith(".pickle")):
                continue
            try:
                with open(entry.path, "rb") as fh:
                    kept.append(pickle.load(fh))
            except Exception:  # a run file cut short cannot be: they are published whole
                log.warning("campaign: %s unreadable, its run is started again", entry.path)
        return kept

    def keep(self, result: dict) -> None:
        """Add one finished run (ok or failed) to the journal, complete or not at all."""

        def write(tmp: Path) -> None:
            with open(tmp, "xb") as fh:
                pickle.dump(result, fh, protocol=pickle.HIGHEST_PROTOCOL)

        write_staged(
            self.path / f"run-{int(result['index']):07d}.pickle", write, "campaign journal"
        )

    def remove(self) -> None:
        """Remove the journal (the campaign's folder is written)."""
        shutil.rmtree(self.path, ignore_errors=True)


def write_campaign_folder(
    out: Path, result: CampaignResult, scenario: Scenario, times, curves, k_every: int, record: bool
) -> None:
    """``runs.parquet``, ``series.parquet``, ``statistics.rrd`` (with ``record``) and ``summary.json``, as one folder.

    ``result`` holds the summary, the ensembles and the runs (completed, then failed, each in
    run order); ``curves`` is ``(sqrt_bound, sqrt_linear)``. The folder replaces ``out`` once
    complete (:func:`quadobs.staging.write_folder_staged`); ``summary["files"]`` names the
    files at their final place.
    """
    summary, ensembles, names = result.summary, result.ensembles, result.summary["estimator_names"]
    ok = [r for r in result.results if r["status"] == "ok"]
    failed = [r for r in result.results if r["status"] != "ok"]
    files = {
        "summary": str(out / "summary.json"),
        "runs": str(out / "runs.parquet"),
        "series": str(out / "series.parquet"),
    }
    if record:
        files["recording"] = str(out / "statistics.rrd")
    summary["files"] = files

    def write(folder: Path) -> None:
        _write_runs(folder / "runs.parquet", ok, failed, names, ensembles)
        _write_series(folder / "series.parquet", ok, names, times)
        if record:
            bound, linear = curves
            _record_statistics(
                folder / "statistics.rrd", scenario, names, ensembles, bound, linear, k_every
            )
        write_json_staged(folder / "summary.json", summary)

    write_folder_staged(out, write, "out_dir", CAMPAIGN_FILES)


def _write_table(path: Path, columns: dict) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table(columns)
    write_staged(path, lambda tmp: pq.write_table(table, tmp), "campaign table")


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
    _write_table(path, {k: pa.array(v, type=types.get(k, pa.float64())) for k, v in cols.items()})


def _write_series(path: Path, ok: list[dict], names: list[str], times: np.ndarray) -> None:
    import pyarrow as pa

    T = times.shape[0]
    parts: dict[str, list] = {
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
    _write_table(path, cols)


_PALETTE = [(230, 90, 40), (40, 160, 90), (150, 60, 200), (200, 170, 30), (30, 150, 200)]


def _statistics_blueprint(names: list[str], sets: list[str]):
    """The rerun layout of ``statistics.rrd``: one time-series view per statistic."""
    import rerun.blueprint as rrb

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
    if sets:
        views.append(
            rrb.TimeSeriesView(
                name="Set estimators: containment, width",
                contents=[f"/stats/{e}/set/**" for e in sets],
            )
        )
    return rrb.Blueprint(rrb.Grid(*views), collapse_panels=False)


def _bound_series(rec, sqrt_bound, sqrt_linear) -> dict[str, Any]:
    """The series of the bounds: the posterior CRB and the best linear filter on the immersion."""
    series: dict[str, Any] = {}
    if sqrt_bound is not None:
        series["pcrb"] = tuple(
            rec.series(f"stats/pcrb/{part}", 1, names=[f"sqrt PCRB {part}"], color=(40, 90, 220))
            for part in ("position", "velocity")
        )
    if sqrt_linear is not None:
        series["linear"] = tuple(
            rec.series(
                f"stats/immersion_bound/{part}",
                1,
                names=["best linear filter on the immersion"],
                color=(120, 120, 120),
            )
            for part in ("position", "velocity")
        )
    return series


def _estimator_series(rec, e: str, c, is_set: bool) -> dict[str, Any]:
    """The series of one estimator's statistics."""
    s = {
        "rmse_p": rec.series(f"stats/{e}/position/rmse", 1, names=[f"{e} RMSE"], color=c),
        "pct_p": rec.series(
            f"stats/{e}/position/percentiles", 3, names=[f"{e} |e_p| 5%", f"{e} median", f"{e} 95%"]
        ),
        "rmse_v": rec.series(f"stats/{e}/velocity/rmse", 1, names=[f"{e} RMSE"], color=c),
        "ratio": rec.series(f"stats/{e}/ratio", 2, names=[f"{e} position", f"{e} velocity"]),
        "nees": rec.series(f"stats/{e}/nees/mean", 1, names=[f"{e} mean NEES"], color=c),
        "nees_b": rec.series(f"stats/{e}/nees/bounds", 2, names=[f"{e} lower", f"{e} upper"]),
        "nis": rec.series(
            f"stats/{e}/nis/mean", 1, skip_nan=True, names=[f"{e} mean NIS"], color=c
        ),
        "nis_b": rec.series(
            f"stats/{e}/nis/bounds", 2, skip_nan=True, names=[f"{e} lower", f"{e} upper"]
        ),
        "conv": rec.series(f"stats/{e}/converged", 1, names=[f"{e}"], color=c),
    }
    if is_set:
        s["cont"] = rec.series(f"stats/{e}/set/containment", 1, names=[f"{e} containment"], color=c)
        s["width"] = rec.series(
            f"stats/{e}/set/width", 2, names=[f"{e} width position", f"{e} width velocity"]
        )
    return s


def _fill_row(series: dict, row: int, j: int, names, ensembles, sqrt_bound, sqrt_linear) -> None:
    """Sample ``j`` of every statistic into recorder row ``row``."""
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


def _record_statistics(
    path: Path, scenario: Scenario, names, ensembles, sqrt_bound, sqrt_linear, k_every: int
) -> None:
    """The statistics over time as an ``.rrd`` (the recorder stages the file and publishes it on close)."""
    from quadobs.recording import Recorder

    sets = [e for e in names if np.isfinite(ensembles[e].containment).any()]
    T = next(iter(ensembles.values())).times.shape[0]
    rec = Recorder(
        path,
        recording_id=f"{scenario.name}-campaign-seed{scenario.seed}",
        blueprint=_statistics_blueprint(names, sets),
        capacity=max(T, 1),
    )
    try:
        series = _bound_series(rec, sqrt_bound, sqrt_linear)
        for i, e in enumerate(names):
            series[e] = _estimator_series(rec, e, _PALETTE[i % len(_PALETTE)], e in sets)
        ens0 = ensembles[names[0]]
        for j in range(T):
            row = rec.row(j * k_every, float(ens0.times[j]))
            _fill_row(series, row, j, names, ensembles, sqrt_bound, sqrt_linear)
        rec.close()
    except BaseException:
        rec.close(publish=False)
        raise
