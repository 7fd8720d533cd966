"""TDOA against two-way ranging on the same flight: accuracy, convergence from a far guess, DOP.

``python -m quadobs.studies.tdoa --out DIR [--seeds N] [--duration S] [--offset M]`` flies the
reference flight of ``quadrotor-tdoa`` (:func:`quadobs.testbed.tdoa.fly_reference`) once per
seed, measures TDOA (TDoA3-like, the radio's ``std`` and ``rate``) and two-way ranges
(``[noise]``: every anchor each ``1 / range_rate`` s) on it, runs the estimators from a guess ``offset`` metres off along
``x`` and writes ``DIR/tdoa-study.json`` (per estimator: the position RMSE after ``settle`` s,
the time the position error last crosses 0.5 m, how many seeds are below 0.5 m at 3 s) and
``DIR/tdoa-dop.png`` (the DOP maps of :mod:`quadobs.evaluation.dop`).

Estimators: ``tdoa-observer`` (:class:`~quadobs.estimators.tdoa_observer.TdoaObserver`),
``tdoa-handover`` (the observer handing over to an EKF), ``tdoa-ekf`` (the EKF alone, through
:class:`~quadobs.core.measurements.TdoaModel`), and on the ranges ``range-ekf`` and
``range-refined`` (the project's ``ekf`` and ``augmented-refined``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path
from typing import cast

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.base import Estimator
from quadobs.estimators.tdoa_observer import TdoaHandover
from quadobs.evaluation.convergence import convergence_times
from quadobs.evaluation.dop import pdop, range_information, tdoa_information
from quadobs.testbed.factories import baseline_settings, extended_kalman_filter, refined_observer
from quadobs.testbed.scenario import Scenario, load_scenario
from quadobs.testbed.tdoa import (
    PairsInTime,
    TdoaFlight,
    fly_reference,
    fly_world,
    ordered_pairs,
    reference_run,
    tdoa_ekf,
    tdoa_handover,
    tdoa_observer,
)

__all__ = [
    "convergence_figure",
    "dop_figure",
    "quadrotor_study",
    "range_outputs_of",
    "reference_errors",
    "study",
    "tdoa_estimators",
]

#: The position error (m) a converged estimate stays below (the issue's target).
CONVERGED = 0.5


def tdoa_estimators(scenario: Scenario, x0: np.ndarray, spread: float) -> dict:
    """The TDOA estimators of the study, started at ``x0`` with a position prior of standard
    deviation ``spread`` per axis (at least the scenario's), each taking pairs as outputs."""
    dim = scenario.dimension
    P0 = np.array(baseline_settings(scenario).P0, dtype=float)
    if scenario.tdoa is None:
        raise QuadobsError(f'scenario {scenario.name!r}: has no [radio] with protocol = "tdoa"')
    std = float(scenario.tdoa.std)
    pairs = ordered_pairs(scenario.beacons.shape[0])
    P0[:dim, :dim] = np.eye(dim) * max(spread**2, P0[0, 0])
    return {
        "tdoa-observer": tdoa_observer(scenario, x0, P0),
        "tdoa-handover": tdoa_handover(scenario, x0, P0),
        "tdoa-ekf": PairsInTime(tdoa_ekf(scenario, x0, P0), pairs, scenario.dt, std),
    }


def range_outputs_of(scenario: Scenario, flight: TdoaFlight, seed: int) -> np.ndarray:
    """Two-way ranges on the flight, as the estimators' outputs ``y_h = rho_h^2/2 - |a_h|^2/2``:
    every anchor each ``1 / range_rate`` s, noise ``noise.range_std``; NaN between."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 27, 1]))
    a = scenario.beacons
    T = flight.t.size
    every = scenario.sample_interval(scenario.noise.range_rate, "range_rate")
    Y = np.full((T, a.shape[0]), np.nan)
    rows = np.arange(0, T, every)
    rho = np.linalg.norm(flight.truth[rows, None, : a.shape[1]] - a, axis=-1)
    rho = rho + scenario.noise.sigma("range") * rng.standard_normal(rho.shape)
    Y[rows] = 0.5 * rho**2 - 0.5 * np.einsum("hi,hi->h", a, a)
    return Y


def _metrics(flight: TdoaFlight, X: np.ndarray, dim: int, settle: float) -> dict:
    err = np.linalg.norm(X[:, :dim] - flight.truth[:, :dim], axis=1)
    t = np.append(flight.t, flight.t[-1] + (flight.t[1] - flight.t[0]))
    late = t >= settle
    k3 = int(np.searchsorted(t, 3.0))
    tc = float(convergence_times(t, err[None, :], CONVERGED)[0])
    return {
        "rmse": float(np.sqrt(np.mean(err[late] ** 2))),
        "final_error": float(err[-1]),
        "error_at_3s": float(err[k3]) if k3 < err.size else math.nan,
        "converged_time": None if math.isnan(tc) else tc,
        "max_error_after_settle": float(err[late].max()),
    }


def _summary(runs: dict[str, list[dict]]) -> dict:
    """Median and worst RMSE, seeds below 0.5 m at 3 s, seeds converged, per estimator."""
    summary = {}
    for est_name, rows in runs.items():
        rmse = np.array([r["rmse"] for r in rows])
        at3 = np.array([r["error_at_3s"] for r in rows])
        summary[est_name] = {
            "rmse_median": float(np.median(rmse)),
            "rmse_max": float(np.max(rmse)),
            "below_0.5m_at_3s": f"{int(np.sum(at3 < CONVERGED))}/{len(rows)}",
            "converged": f"{sum(r['converged_time'] is not None for r in rows)}/{len(rows)}",
        }
    return summary


def study(
    name: str = "quadrotor-tdoa",
    seeds: int = 10,
    duration: float | None = None,
    offset: float = 10.0,
    settle: float = 10.0,
) -> dict:
    """Per seed and estimator, the metrics of :func:`_metrics`; and their summary over seeds."""
    scenario = load_scenario(name)
    if duration is not None:
        scenario = scenario.with_overrides(duration=duration)
    dim = scenario.dimension
    runs: dict[str, list[dict]] = {}
    for seed in range(seeds):
        flight = fly_reference(scenario, seed)
        x0 = flight.truth[0].copy()
        x0[0] += offset
        ests = tdoa_estimators(scenario, x0, offset)
        tdoa = reference_run(flight, ests)
        ranges = range_outputs_of(scenario, flight, seed)
        twr: dict[str, Estimator] = {"range-ekf": extended_kalman_filter(scenario, x0)}
        twr["range-refined"] = refined_observer(scenario, x0)
        ranged = reference_run(dataclasses.replace(flight, outputs=ranges), twr)
        _add_runs(runs, flight, {**tdoa, **ranged}, ests, dim, settle)
    return {
        **_header(name, seeds, scenario, offset, settle),
        "summary": _summary(runs),
        "runs": runs,
    }


def _add_runs(runs: dict, flight, estimates: dict, ests: dict, dim: int, settle: float) -> None:
    """Append each estimate's :func:`_metrics` to ``runs`` (the handover's time with them)."""
    for est_name, X in estimates.items():
        m = _metrics(flight, X, dim, settle)
        if est_name == "tdoa-handover":
            m["handover_time"] = cast(TdoaHandover, ests[est_name]).handover_time
        runs.setdefault(est_name, []).append(m)


def _header(name: str, seeds: int, scenario, offset: float, settle: float) -> dict:
    """The settings a study's result records."""
    return {
        "scenario": name,
        "seeds": seeds,
        "duration": scenario.duration,
        "offset": offset,
        "settle": settle,
    }


def quadrotor_study(
    name: str = "quadrotor-tdoa",
    seeds: int = 10,
    duration: float | None = None,
    offset: float = 10.0,
    settle: float = 10.0,
    flown_on: str = "tdoa-handover",
    names: tuple[str, ...] | None = None,
    first_seed: int = 0,
) -> dict:
    """The MuJoCo quadrotor flown on a TDOA estimator (:func:`~quadobs.testbed.tdoa.fly_world`),
    every TDOA estimator started ``offset`` m off along ``x``: per seed, crash and metrics."""
    scenario = load_scenario(name)
    if duration is not None:
        scenario = scenario.with_overrides(duration=duration)
    runs: dict[str, list[dict]] = {}
    crashes = []
    for seed in range(first_seed, first_seed + seeds):

        def make(x_true, scenario=scenario):
            x0 = x_true.copy()
            x0[0] += offset
            ests = tdoa_estimators(scenario, x0, offset)
            return {k: v for k, v in ests.items() if not names or k in names or k == flown_on}

        flight, ests = fly_world(scenario, make, flown_on, seed)
        crashes.append(flight.crashed_at)
        ref = TdoaFlight(flight.t[:-1], flight.truth, np.zeros(0), np.zeros(0), [], 0.0)
        _add_runs(runs, ref, flight.estimates, ests, 3, settle)
    return {
        **_header(name, seeds, scenario, offset, settle),
        "flown_on": flown_on,
        "crashes": f"{sum(c is not None for c in crashes)}/{seeds}",
        "crashed_at": crashes,
        "summary": _summary(runs),
        "runs": runs,
    }


def reference_errors(
    name: str = "quadrotor-tdoa", seed: int = 0, duration: float = 10.0, offset: float = 10.0
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Position errors ``(T + 1,)`` of every estimator of :func:`study` on one reference flight."""
    scenario = load_scenario(name).with_overrides(duration=duration)
    flight = fly_reference(scenario, seed)
    x0 = flight.truth[0].copy()
    x0[0] += offset
    runs = reference_run(flight, tdoa_estimators(scenario, x0, offset))
    ranges = range_outputs_of(scenario, flight, seed)
    twr: dict[str, Estimator] = {
        "range-ekf": extended_kalman_filter(scenario, x0),
        "range-refined": refined_observer(scenario, x0),
    }
    runs.update(reference_run(dataclasses.replace(flight, outputs=ranges), twr))
    dim = scenario.dimension
    t = np.arange(flight.truth.shape[0]) * scenario.dt
    return t, {
        k: np.linalg.norm(X[:, :dim] - flight.truth[:, :dim], axis=1) for k, X in runs.items()
    }


def convergence_figure(t: np.ndarray, errors: dict[str, np.ndarray], out: Path) -> Path:
    """Position error against time, log scale, one line per estimator."""
    from quadobs.studies.plot._figure import drawing, new_figure, save_figure, style, thin

    with drawing():
        fig, axes = new_figure(["error"], (7.0, 3.2), 150)
        ax = axes["error"]
        for i, (name, e) in enumerate(errors.items()):
            tt, ee = thin(t, np.maximum(e, 1e-4))
            ax.semilogy(tt, ee, label=name, **style(i, tt.size))
        ax.axhline(CONVERGED, color="0.5", lw=0.8)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("position error (m)")
        ax.legend(fontsize=7, ncol=2)
        return save_figure(fig, out, 150)


def dop_figure(anchors: np.ndarray, height: float, out: Path, extent: float = 5.0) -> Path:
    """PDOP per measurement at ``height`` over ``[-extent, extent]^2``: ranges, TDOA, their ratio."""
    from quadobs.studies.plot._figure import drawing, new_figure, save_figure

    g = np.linspace(-extent, extent, 161)
    X, Y = np.meshgrid(g, g)
    P = np.stack([X, Y, np.full_like(X, height)], axis=-1)
    d_range = pdop(range_information(anchors, P))
    d_tdoa = pdop(tdoa_information(anchors, P))
    with drawing():
        fig, axes = new_figure(["range", "tdoa", "ratio"], (10.5, 3.4), 150)
        panels = (
            ("range", d_range, "two-way ranges: PDOP", (1.0, 12.0)),
            ("tdoa", d_tdoa, "TDOA (TDoA3 pairs): PDOP", (1.0, 12.0)),
            ("ratio", d_tdoa / d_range, "TDOA PDOP / range PDOP", (0.3, 3.0)),
        )
        for key, data, title, (lo, hi) in panels:
            ax = axes[key]
            from matplotlib.colors import LogNorm

            im = ax.pcolormesh(g, g, data, norm=LogNorm(lo, hi), cmap="viridis", shading="auto")
            ax.contour(g, g, data, levels=[1.5, 2, 3, 5, 8], colors="w", linewidths=0.6)
            ax.plot(anchors[:, 0], anchors[:, 1], "r^", ms=6)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("x (m)")
            ax.set_aspect("equal")
            ax.grid(False)
            fig.colorbar(im, ax=ax, shrink=0.85)
        axes["range"].set_ylabel(f"y (m), z = {height:g} m")
        return save_figure(fig, out, 150)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m quadobs.studies.tdoa", description=__doc__)
    parser.add_argument("--out", required=True, help="folder for tdoa-study.json and tdoa-dop.png")
    parser.add_argument("--scenario", default="quadrotor-tdoa")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--duration", type=float, default=None)
    parser.add_argument("--offset", type=float, default=10.0)
    parser.add_argument("--settle", type=float, default=10.0)
    parser.add_argument("--no-figure", action="store_true")
    parser.add_argument(
        "--quadrotor", action="store_true", help="fly the MuJoCo quadrotor on the TDOA handover"
    )
    parser.add_argument("--estimators", default="", help="quadrotor: the TDOA estimators to run")
    parser.add_argument("--first-seed", type=int, default=0)
    args = parser.parse_args(argv)
    out = Path(args.out)
    common = (args.scenario, args.seeds, args.duration, args.offset, args.settle)
    if args.quadrotor:
        names = tuple(args.estimators.split(",")) if args.estimators else None
        result = quadrotor_study(*common, names=names, first_seed=args.first_seed)
    else:
        result = study(*common)
    out.mkdir(parents=True, exist_ok=True)
    name = f"tdoa-quadrotor-{args.first_seed}.json" if args.quadrotor else "tdoa-study.json"
    (out / name).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["summary"], indent=1))
    if not args.no_figure:
        anchors = load_scenario(args.scenario).beacons
        dop_figure(anchors, 1.5, out / "tdoa-dop.png")
        if not args.quadrotor:
            t, errors = reference_errors(
                args.scenario, 0, min(10.0, result["duration"]), args.offset
            )
            convergence_figure(t, errors, out / "tdoa-convergence.png")
    return 0


def _main() -> int:
    """:func:`main`, a bad input reported in one line with exit status 2."""
    import sys

    try:
        return main()
    except QuadobsError as exc:
        print(f"python -m quadobs.studies.tdoa: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(_main())
