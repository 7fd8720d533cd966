"""Monte Carlo evaluation: errors over runs, consistency tests and the posterior Cramér-Rao bound.

All functions take arrays with the run axis first and the time axis next (``(R, T, ...)``),
as a campaign (:mod:`quadobs.studies.campaign`) collects them, and return plain arrays.

Errors
    ``RMSE(t) = sqrt(mean_r |e_r(t)|^2)`` over the runs, for position and (ground)
    velocity; percentiles of ``|e_r(t)|`` for bands; the final error; the convergence time
    of a run (the time from which its position error stays below a threshold, NaN if it
    does not end below it: the convention of :mod:`quadobs.evaluation.convergence`) and
    whether it converged (final error below the threshold).

Consistency (Bar-Shalom, Li and Kirubarajan 2001, section 5.4)
    ``NEES_r(t) = e^T P^-1 e`` with the estimator's own covariance, ``NIS = nu^T S^-1 nu``.
    If the estimator is consistent, ``N`` times the average over ``N`` independent runs
    is chi-square with ``N n`` degrees of freedom (``sum`` of the runs' degrees of freedom
    for the NIS), so the average lies in
    ``[chi2_{(1-c)/2}(N n) / N, chi2_{(1+c)/2}(N n) / N]`` with probability ``c``
    (:func:`chi2_interval`).

Posterior Cramér-Rao bound (Tichavsky, Muravchik and Nehorai 1998)
    For ``x_{k+1} = F x_k + G u_k + w_k``, ``w_k ~ N(0, Q)``, and measurements
    ``z_k = h(x_k) + v_k``, ``v_k ~ N(0, R)``, the information recursion is

    .. math::

        J_{k+1} = D^{22}_k - D^{21}_k (J_k + D^{11}_k)^{-1} D^{12}_k, \\quad
        D^{11} = F^\\top Q^{-1} F,\\; D^{12} = -F^\\top Q^{-1} = (D^{21})^\\top,\\;
        D^{22} = Q^{-1} + E[H^\\top R^{-1} H],

    and, by the matrix inversion lemma, ``J_{k+1} = (F J_k^{-1} F^T + Q)^{-1} + E[H^T R^{-1} H]``:
    a Kalman filter's covariance recursion with the measurement information evaluated
    on the true trajectory. :func:`posterior_crb` runs it in covariance form,
    ``P^- = F P F^T + Q`` and ``P = P^- - P^- L (I + L^T P^- L)^{-1} L^T P^-`` with
    ``L L^T = H^T R^-1 H``, which needs neither ``Q`` nor ``P`` to be invertible (a
    noise-free accelerometer gives ``Q = 0``, where the recursion is
    ``J_{k+1} = F^{-T} J_k F^{-1} + H^T R^-1 H``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from quadobs.core.held_input import as_covariance
from quadobs.core.immersion import lifted_covariance
from quadobs.errors import QuadobsError, as_array, as_finite_scalar
from quadobs.evaluation.convergence import convergence_times

__all__ = [
    "Ensemble",
    "chi2_interval",
    "converged_nees",
    "convergence_times",
    "ensemble",
    "lifted_covariance",
    "nees",
    "posterior_crb",
    "rmse",
    "set_containment",
]


# --------------------------------------------------------------------------------------
# Per-run quantities
# --------------------------------------------------------------------------------------


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """``e^T P^-1 e`` for errors ``(..., n)`` and covariances ``(..., n, n)``.

    NaN where the covariance is missing (NaN) or singular, or the error is not finite.
    """
    e = np.asarray(errors, dtype=float)
    P = np.asarray(covariances, dtype=float)
    if P.shape != e.shape + e.shape[-1:]:
        raise QuadobsError(f"covariances: expected shape {e.shape + e.shape[-1:]}, got {P.shape}")
    out = np.full(e.shape[:-1], np.nan)
    ok = np.isfinite(e).all(axis=-1) & np.isfinite(P).all(axis=(-2, -1))
    if ok.any():
        ee, PP = e[ok], P[ok]
        try:
            sol = np.linalg.solve(PP, ee[..., None])[..., 0]
            out[ok] = np.einsum("...i,...i->...", ee, sol)
        except np.linalg.LinAlgError:
            vals = np.full(ee.shape[0], np.nan)
            for i in range(ee.shape[0]):
                try:
                    vals[i] = ee[i] @ np.linalg.solve(PP[i], ee[i])
                except np.linalg.LinAlgError:
                    pass
            out[ok] = vals
    return out


def set_containment(truth: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Whether the truth ``(..., n)`` lies in the box ``bounds (..., n, 2)`` (lower, upper) in every component.

    Returns a float array (1.0 inside, 0.0 outside, NaN where the bounds are missing).
    """
    x = np.asarray(truth, dtype=float)
    b = np.asarray(bounds, dtype=float)
    if b.shape != x.shape + (2,):
        raise QuadobsError(f"bounds: expected shape {x.shape + (2,)}, got {b.shape}")
    inside = ((b[..., 0] <= x) & (x <= b[..., 1])).all(axis=-1).astype(float)
    inside[~np.isfinite(b).all(axis=(-2, -1))] = np.nan
    return inside


# --------------------------------------------------------------------------------------
# Over runs
# --------------------------------------------------------------------------------------


def rmse(errors: np.ndarray) -> np.ndarray:
    """``sqrt(mean_r |e_r|^2)`` over the first (run) axis of ``errors (R, ..., k)``; returns ``(...)``."""
    e = np.asarray(errors, dtype=float)
    return np.sqrt(np.mean(np.sum(e * e, axis=-1), axis=0))


def chi2_interval(
    dof: np.ndarray | float, runs: np.ndarray | float, confidence: float = 0.95
) -> np.ndarray:
    """Two-sided ``confidence`` interval of the average of ``runs`` chi-square statistics with ``dof`` degrees in all.

    ``runs * mean`` is chi-square with ``dof`` degrees of freedom (for ``N`` runs of an
    ``n``-dimensional NEES, ``dof = N n``). Returns ``(..., 2)`` (lower, upper); NaN where
    ``runs`` or ``dof`` is zero.
    """
    from scipy import stats  # here, not at import: it costs a second (quadobs.core.quantiles)

    c = as_finite_scalar("confidence", confidence, positive=True)
    if not c < 1:
        raise QuadobsError(f"confidence: must be below 1, got {c}")
    dof = np.asarray(dof, dtype=float)
    runs = np.asarray(runs, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = stats.chi2.ppf(0.5 * (1 - c), dof) / runs
        hi = stats.chi2.ppf(0.5 * (1 + c), dof) / runs
    out = np.stack([lo, hi], axis=-1)
    bad = (dof <= 0) | (runs <= 0)
    out[bad] = np.nan
    return out


def converged_nees(
    nees: np.ndarray, converged: np.ndarray, state_dim: int, confidence: float = 0.95
) -> dict:
    """The mean NEES over each run's converged part, with its two-sided chi-square interval.

    At time ``t`` the ``N_t`` runs with ``converged[r, t]`` enter: for a consistent
    estimator ``N_t * mean_t`` is ``chi^2(N_t n)`` (:func:`chi2_interval`). A run enters
    once it has converged and leaves when it stops (e.g. an estimator that hands back to a
    fallback), so runs still converging do not mix into the statistic.

    Parameters
    ----------
    nees : (R, T)
    converged : (R, T) bool
        Whether run ``r`` is in its converged part at time ``t``.
    state_dim : int
        ``n``, the NEES degrees of freedom of one run.
    confidence : float

    Returns
    -------
    dict
        ``mean (T,)``, ``bounds (T, 2)``, ``runs (T,)`` (``N_t``), NaN where ``N_t = 0``,
        and the scalars ``time_average`` (of ``mean_t`` where ``N_t > 0``), ``inside_fraction``
        (of those times with ``mean_t`` inside its interval) and ``all_runs_from`` (first
        time with ``N_t = R``, ``None`` if never). Times are correlated within a run, so
        ``inside_fraction`` is not a binomial count of independent tests.
    """
    ne = np.asarray(nees, dtype=float)
    m = np.asarray(converged, dtype=bool) & np.isfinite(ne)
    cnt = m.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(cnt > 0, np.where(m, ne, 0.0).sum(axis=0) / cnt, np.nan)
    bounds = chi2_interval(cnt * int(state_dim), cnt, confidence)
    ok = cnt > 0
    inside = ok & (mean >= bounds[:, 0]) & (mean <= bounds[:, 1])
    full = np.flatnonzero(cnt == ne.shape[0]) if ne.shape[0] else np.zeros(0, dtype=int)
    return {
        "mean": mean,
        "bounds": bounds,
        "runs": cnt,
        "time_average": float(np.mean(mean[ok])) if ok.any() else None,
        "inside_fraction": float(np.mean(inside[ok])) if ok.any() else None,
        "all_runs_from": int(full[0]) if full.size else None,
    }


@dataclass(frozen=True, eq=False)
class Ensemble:
    """Statistics over ``R`` runs of one estimator, over time and at the end.

    Over time (``(T,)`` unless noted): ``rmse_position``, ``rmse_velocity``,
    ``position_percentiles (T, 3)`` (5 %, 50 %, 95 % of ``|e_p|``), ``converged_now``
    (fraction of runs with ``|e_p|`` below the threshold), ``mean_nees``, ``nees_bounds
    (T, 2)``, ``mean_nis``, ``nis_bounds (T, 2)`` (NaN where no run had an update),
    ``containment`` and ``width_position``, ``width_velocity`` (set estimators, else NaN),
    ``ratio_position``, ``ratio_velocity`` (RMSE over the square root of the trace of the
    bound's block, NaN without a bound), ``nis_dof`` (mean NIS degrees of freedom of a run
    with an update, NaN where none). Per run (``(R,)``): ``final_position_error``,
    ``final_velocity_error``, ``convergence_time``, ``converged``.
    """

    runs: int
    state_dim: int
    threshold: float
    confidence: float
    times: np.ndarray
    rmse_position: np.ndarray
    rmse_velocity: np.ndarray
    position_percentiles: np.ndarray
    converged_now: np.ndarray
    mean_nees: np.ndarray
    nees_bounds: np.ndarray
    mean_nis: np.ndarray
    nis_bounds: np.ndarray
    containment: np.ndarray
    width_position: np.ndarray
    width_velocity: np.ndarray
    ratio_position: np.ndarray
    ratio_velocity: np.ndarray
    final_position_error: np.ndarray
    final_velocity_error: np.ndarray
    convergence_time: np.ndarray
    converged: np.ndarray
    nis_dof: np.ndarray | None = None

    def summary(self) -> dict:
        """Scalars for ``summary.json`` (NaN and infinities become ``None``)."""
        fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        fp, fv = self.final_position_error, self.final_velocity_error
        conv = self.converged
        nees_ok = np.isfinite(self.mean_nees) & np.isfinite(self.nees_bounds).all(axis=1)
        inside = (self.mean_nees >= self.nees_bounds[:, 0]) & (
            self.mean_nees <= self.nees_bounds[:, 1]
        )
        nis_ok = np.isfinite(self.mean_nis) & np.isfinite(self.nis_bounds).all(axis=1)
        nis_in = (self.mean_nis >= self.nis_bounds[:, 0]) & (self.mean_nis <= self.nis_bounds[:, 1])
        ct = self.convergence_time[np.isfinite(self.convergence_time)]
        out = {
            "runs": int(self.runs),
            "converged_fraction": fin(np.mean(conv)) if self.runs else None,
            "converged_runs": int(np.sum(conv)),
            "convergence_threshold": float(self.threshold),
            "final_rmse_position": fin(np.sqrt(np.mean(fp**2))) if self.runs else None,
            "final_rmse_velocity": fin(np.sqrt(np.mean(fv**2))) if self.runs else None,
            "final_rmse_position_converged": fin(np.sqrt(np.mean(fp[conv] ** 2)))
            if conv.any()
            else None,
            "final_median_position_error": fin(np.median(fp)) if self.runs else None,
            "nonfinite_runs": int(np.sum(~np.isfinite(fp))),
            "median_convergence_time": fin(np.median(ct)) if ct.size else None,
            "rmse_over_sqrt_pcrb": fin(self.ratio_position[-1]),
            "rmse_over_sqrt_pcrb_velocity": fin(self.ratio_velocity[-1]),
            "mean_nees": fin(self.mean_nees[-1]),
            "nees_time_average": fin(np.nanmean(self.mean_nees))
            if np.isfinite(self.mean_nees).any()
            else None,
            "nees_inside_fraction": fin(np.mean(inside[nees_ok])) if nees_ok.any() else None,
            "mean_nis": fin(np.nanmean(self.mean_nis))
            if np.isfinite(self.mean_nis).any()
            else None,
            "nis_inside_fraction": fin(np.mean(nis_in[nis_ok])) if nis_ok.any() else None,
            "chi2_bounds": {
                "confidence": float(self.confidence),
                "nees": [fin(v) for v in self.nees_bounds[-1]],
                "nees_dof_per_run": int(self.state_dim),
                "nis": [fin(v) for v in self._typical_nis_bounds()],
                "nis_dof_per_run": self._typical_nis_dof(),
            },
        }
        if np.isfinite(self.containment).any():
            out["containment_rate"] = fin(np.nanmean(self.containment))
            out["final_containment"] = fin(self.containment[-1])
            out["final_width_position"] = fin(self.width_position[-1])
            out["final_width_velocity"] = fin(self.width_velocity[-1])
        return out

    def _typical_nis_bounds(self) -> np.ndarray:
        ok = np.isfinite(self.nis_bounds).all(axis=1)
        if not ok.any():
            return np.array([np.nan, np.nan])
        rows, counts = np.unique(self.nis_bounds[ok], axis=0, return_counts=True)
        return rows[np.argmax(counts)]

    def _typical_nis_dof(self) -> int | None:
        d = self.nis_dof
        if d is None or not np.isfinite(d).any():
            return None
        vals, counts = np.unique(d[np.isfinite(d) & (d > 0)], return_counts=True)
        return int(vals[np.argmax(counts)]) if vals.size else None


def _nis_statistics(nis, nis_dof, T: int, confidence: float):
    """Mean NIS over the runs with an update at each time, its chi-square interval, its mean dof."""
    if nis is None:
        return np.full(T, np.nan), np.full((T, 2), np.nan), None
    s = np.asarray(nis, dtype=float)
    d = (
        np.asarray(nis_dof, dtype=float)
        if nis_dof is not None
        else np.where(np.isfinite(s), 1.0, 0.0)
    )
    have = np.isfinite(s) & (d > 0)
    cnt = have.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_nis = np.where(cnt > 0, np.where(have, s, 0.0).sum(axis=0) / cnt, np.nan)
    nis_bounds = chi2_interval(np.where(have, d, 0.0).sum(axis=0), cnt, confidence)
    with np.errstate(invalid="ignore"):
        dof_rows = np.where(
            cnt > 0, np.where(have, d, 0.0).sum(axis=0) / np.maximum(cnt, 1), np.nan
        )
    return mean_nis, nis_bounds, dof_rows


def _ratio(bound, r: np.ndarray, col: int) -> np.ndarray:
    """``r`` over the bound's column ``col`` (NaN where the bound is zero, or without one)."""
    if bound is None:
        return np.full(r.shape[0], np.nan)
    b = np.asarray(bound, dtype=float)[:, col]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(b > 0, r / b, np.nan)


def _over_runs(a, T: int) -> np.ndarray:
    """The mean over the runs of ``a (R, T)`` at each time where a run has a value (NaN elsewhere)."""
    if a is None:
        return np.full(T, np.nan)
    a = np.asarray(a, dtype=float)
    ok = np.isfinite(a).any(axis=0)
    out = np.full(T, np.nan)
    out[ok] = np.nanmean(a[:, ok], axis=0)
    return out


def ensemble(
    times: np.ndarray,
    position_errors: np.ndarray,
    velocity_errors: np.ndarray,
    *,
    nees: np.ndarray,
    nis: np.ndarray | None = None,
    nis_dof: np.ndarray | None = None,
    final_position_error: np.ndarray | None = None,
    final_velocity_error: np.ndarray | None = None,
    state_dim: int,
    threshold: float = 1.0,
    confidence: float = 0.95,
    bound: np.ndarray | None = None,
    containment: np.ndarray | None = None,
    width_position: np.ndarray | None = None,
    width_velocity: np.ndarray | None = None,
) -> Ensemble:
    """The statistics of one estimator over ``R`` runs (see :class:`Ensemble` and the module docstring).

    Parameters
    ----------
    times : (T,)
    position_errors, velocity_errors : (R, T, d)
        ``x_hat - x`` blocks.
    nees : (R, T)
        Per-run NEES (NaN where the estimator has no covariance).
    nis, nis_dof : (R, T), optional
        NIS of the update at each time and its degrees of freedom (NaN / 0 where none).
    final_position_error, final_velocity_error : (R,), optional
        Norms at the end; default: the last time.
    state_dim : int
        ``n``, the NEES degrees of freedom of one run.
    threshold : float
        Position error (m) below which a run counts as converged.
    confidence : float
        Of the two-sided chi-square intervals.
    bound : (T, 2), optional
        Square roots of the bound's position and velocity traces, ``sqrt(tr PCRB)``.
    containment, width_position, width_velocity : (R, T), optional
        For set estimators: truth in the set (1/0), mean interval widths.
    """
    t = as_array("times", times, (None,))
    ep = np.asarray(position_errors, dtype=float)
    ev = np.asarray(velocity_errors, dtype=float)
    R, T = ep.shape[:2]
    if T != t.shape[0] or ev.shape[:2] != (R, T):
        raise QuadobsError(
            f"position_errors, velocity_errors: expected (runs, {t.shape[0]}, d), got {ep.shape}, {ev.shape}"
        )
    thr = as_finite_scalar("threshold", threshold, positive=True)
    np_ = np.linalg.norm(ep, axis=-1)
    nv = np.linalg.norm(ev, axis=-1)
    rp, rv = (rmse(ep), rmse(ev)) if R else (np.full(T, np.nan), np.full(T, np.nan))
    pct = np.percentile(np_, [5, 50, 95], axis=0).T if R else np.full((T, 3), np.nan)
    fp = (
        np_[:, -1]
        if final_position_error is None
        else np.asarray(final_position_error, dtype=float)
    )
    fv = (
        nv[:, -1] if final_velocity_error is None else np.asarray(final_velocity_error, dtype=float)
    )

    ne = np.asarray(nees, dtype=float)
    n_ok = np.isfinite(ne).sum(axis=0)
    with np.errstate(invalid="ignore"):
        mean_nees = np.where(n_ok == R, np.mean(ne, axis=0), np.nan) if R else np.full(T, np.nan)
    nees_bounds = chi2_interval(np.full(T, R * state_dim), np.full(T, R), confidence)
    mean_nis, nis_bounds, dof_rows = _nis_statistics(nis, nis_dof, T, confidence)
    ratio = functools.partial(_ratio, bound)
    over_runs = functools.partial(_over_runs, T=T)
    ens = Ensemble(
        runs=R,
        state_dim=int(state_dim),
        threshold=thr,
        confidence=float(confidence),
        times=t,
        rmse_position=rp,
        rmse_velocity=rv,
        position_percentiles=pct,
        converged_now=np.mean(np_ < thr, axis=0) if R else np.full(T, np.nan),
        mean_nees=mean_nees,
        nees_bounds=nees_bounds,
        mean_nis=mean_nis,
        nis_bounds=nis_bounds,
        containment=over_runs(containment),
        width_position=over_runs(width_position),
        width_velocity=over_runs(width_velocity),
        ratio_position=ratio(rp, 0),
        ratio_velocity=ratio(rv, 1),
        final_position_error=fp,
        final_velocity_error=fv,
        convergence_time=convergence_times(t, np_, thr) if R else np.zeros(0),
        converged=fp < thr,
        nis_dof=dof_rows,
    )
    return ens


# --------------------------------------------------------------------------------------
# The posterior Cramér-Rao bound
# --------------------------------------------------------------------------------------


def posterior_crb(
    F: np.ndarray,
    Q: np.ndarray,
    P0: np.ndarray,
    steps: int,
    factors: Callable[[int], np.ndarray | None],
    *,
    every: int = 1,
) -> np.ndarray:
    """The posterior Cramér-Rao bound of linear Gaussian dynamics with measurement information ``L_k L_k^T``.

    Parameters
    ----------
    F, Q : (n, n)
        One-step transition and process-noise covariance (``Q`` may be singular or zero).
    P0 : (n, n)
        Prior covariance of ``x_0`` (the inverse of ``J_0``); positive semidefinite.
    steps : int
        Number of steps ``K``.
    factors : callable
        ``factors(k)`` returns ``L_k (n, m)`` with ``L_k L_k^T = E[H_k^T R_k^-1 H_k]``, the
        information of the measurement taken at step ``k`` (at ``t_k``, before the step),
        or ``None`` when there is none.
    every : int
        Return the bound at steps ``0, every, 2 every, ...``, up to ``K``.

    Returns
    -------
    ndarray (K // every + 1, n, n)
        ``J_k^-1`` at those steps: the bound on the error of an estimate of ``x_k`` from
        the measurements at steps ``0 .. k-1`` (the runner's order: ``x_hat_k`` is
        recorded before the update with ``y_k``).
    """
    F = as_array("F", F, ndim=2)
    n = F.shape[0]
    Q = as_covariance("Q", Q, n, definite=False)
    P = as_covariance("P0", P0, n, definite=False).copy()
    if steps < 0 or every < 1:
        raise QuadobsError(f"steps, every: need steps >= 0 and every >= 1, got {steps}, {every}")
    from quadobs.estimators.kalman import step_power

    out = np.empty((steps // every + 1, n, n))
    powers: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def power(m):
        if m not in powers:
            powers[m] = step_power(F, Q, m)
        return powers[m]

    pending = 0
    for k in range(steps + 1):
        if k % every == 0 or k == steps:
            if pending:
                Fm, Qm = power(pending)
                P = Fm @ P @ Fm.T + Qm
                P = 0.5 * (P + P.T)
                pending = 0
            if k % every == 0:
                out[k // every] = P
        if k == steps:
            break
        L = factors(k)
        if L is not None:
            if pending:
                Fm, Qm = power(pending)
                P = Fm @ P @ Fm.T + Qm
                pending = 0
            PL = P @ L
            M = np.eye(L.shape[1]) + L.T @ PL
            P = P - PL @ np.linalg.solve(M, PL.T)
            P = 0.5 * (P + P.T)
        pending += 1
    return out


def range_factor(position: np.ndarray, beacons: np.ndarray, std: np.ndarray | float) -> np.ndarray:
    """``L (dim, q)`` with ``L L^T`` the Fisher information on ``p`` of ranges ``|p - a_h| + N(0, sigma_h^2)``.

    Column ``h`` is ``(p - a_h) / (|p - a_h| sigma_h)``: the gradient of the range over its
    standard deviation (zero at ``p = a_h``, where the range carries no first-order information).
    """
    d = np.asarray(position, dtype=float)[None, :] - np.asarray(beacons, dtype=float)
    r = np.linalg.norm(d, axis=1)
    std = np.broadcast_to(np.asarray(std, dtype=float), r.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        cols = np.where((r > 0)[:, None], d / (r * std)[:, None], 0.0)
    return cols.T
