"""Statistics of a campaign: the ensembles of its completed runs, the NEES over their converged parts, the bounds.

The reductions themselves are :mod:`quadobs.evaluation.ensemble`'s; this module gathers the
per-run series of :func:`quadobs.studies.campaign.run_one` into them, in run order.
"""

from __future__ import annotations

import functools

import numpy as np

from quadobs.evaluation.ensemble import Ensemble, converged_nees, ensemble
from quadobs.testbed.flight import crash_counts
from quadobs.testbed.scenario import Scenario

__all__ = ["add_converged_nees", "bound_summary", "ensembles_of", "flight_summary", "sqrt_traces"]


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


def _converged_part(ens: Ensemble, per: list[dict], times: np.ndarray) -> np.ndarray:
    """``(R, T)``: each run's converged part, from its convergence time on and, for a switching estimator, in a later mode."""
    mask = times[None, :] >= ens.convergence_time[:, None]
    if per and all("switched" in p for p in per):
        mask &= np.stack([p["switched"] for p in per])
    return mask


def _stack_key(per: list[dict], key: str):
    """The runs' values of ``key``, stacked along a first axis (``None`` without runs)."""
    return np.stack([p[key] for p in per]) if per else None


def ensembles_of(scenario, names, ok, times, sqrt_bound, threshold, confidence) -> dict:
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


def add_converged_nees(summaries, scenario, names, ok, ensembles, times, confidence) -> None:
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


def _velocity_selector(scenario: Scenario) -> np.ndarray:
    """``(dim, n)``: the ground velocity ``v`` (or ``v_a + v_w``) from the state."""
    dim, n = scenario.dimension, scenario.state_dim
    T = np.zeros((dim, n))
    T[:, dim : 2 * dim] = np.eye(dim)
    if scenario.has_wind:
        T[:, 2 * dim :] = np.eye(dim)
    return T


def sqrt_traces(scenario: Scenario, B: np.ndarray) -> np.ndarray:
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


def bound_summary(bound, sqrt_bound, sqrt_linear) -> dict:
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
