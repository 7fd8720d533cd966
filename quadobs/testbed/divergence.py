"""Diverged and locked-out estimators: detected while the episode runs, their figures marked invalid.

An estimator has *diverged* at the first step ``k`` where

* its estimate ``x_hat_k`` holds a value that is not finite (``reason = "non-finite
  estimate"``), or its position error ``e_p,k = p_hat_k - p_k`` is not finite while the
  truth is (``"non-finite error"``);
* its position error exceeds the bound (``"error beyond the bound"``)

  .. math::

      \\|e_{p,k}\\| > \\beta = F \\max(D, \\|e_{p,0}\\|, 1\\,\\mathrm{m}),
      \\qquad F = 100,

  with ``D`` the diameter of the beacon set (the largest distance between two beacons) and
  ``e_p,0`` the initial error: a hundred times the size of the scene, which no estimate of a
  vehicle among those beacons reaches unless it is lost (:func:`error_bound`).

An estimator is *locked out* when, over the second half of the run (from the first of
:data:`BINS` equal bins of steps that starts at or after ``K / 2``), it was offered at least
:data:`LOCKOUT_MIN` corrections and rejected at least :data:`LOCKOUT_SHARE` (90 %) of them
(``"locked out"``, the step being the start of that half): its gate refused the
measurements and it ran on its model alone. A filter with a lock-out of its own
(:class:`~quadobs.estimators.robust.LockOut`) is also reported when the run ends while its
window still holds more rejected corrections than accepted ones, inside the grace after a
re-initialisation (:meth:`~quadobs.estimators.robust.LockOut.locked_at_end`; step ``-1``:
its time alone is known). A correction is offered at a step where the
estimator's NIS is finite; it is rejected when its rejected count grows at that step.

Either way the estimator's summary gets ``diverged = {"step", "t", "reason"}`` and every
error figure (``rmse``, ``max_error``, ``final_*_error``, ``time_to_*``, ...) becomes
``None`` (:func:`invalidate_diverged`): no RMSE of the finite part, no final error of a
lost estimate. Counters (``corrections``, ``rejected``) and timings stay.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.estimators.startup import not_started
from quadobs.testbed.sinks import EpisodeContext, Rows, Sink

__all__ = [
    "BINS",
    "BOUND_FACTOR",
    "LOCKOUT_MIN",
    "LOCKOUT_SHARE",
    "DivergenceSink",
    "diverged_estimators",
    "error_bound",
    "given_up",
    "invalidate_diverged",
    "startup_record",
]

#: The divergence bound in sizes of the scene (:func:`error_bound`).
BOUND_FACTOR = 100.0
#: Fewest corrections offered in the run's second half for a lock-out, and the share of them refused.
LOCKOUT_MIN, LOCKOUT_SHARE = 10, 0.9
#: Bins of steps over which the corrections offered and refused are counted.
BINS = 64


def error_bound(beacons: np.ndarray, initial_error: float) -> float:
    """``beta = F max(D, |e_p,0|, 1 m)``: the position error beyond which an estimator has diverged.

    Parameters
    ----------
    beacons : ndarray (q_b, d)
        Beacon positions (m); ``D`` is their diameter (0 for fewer than two).
    initial_error : float
        ``|e_p,0|`` (m); a value that is not finite counts as 0.
    """
    b = np.asarray(beacons, dtype=float).reshape(len(beacons), -1)
    diameter = 0.0
    if b.shape[0] > 1:
        diffs = b[:, None, :] - b[None, :, :]
        diameter = float(np.sqrt(np.max(np.einsum("ijk,ijk->ij", diffs, diffs))))
    e0 = initial_error if math.isfinite(initial_error) else 0.0
    return BOUND_FACTOR * max(diameter, e0, 1.0)


class DivergenceSink(Sink):
    """Per estimator: the first step where it diverged (module docstring), and its lock-out run."""

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        self.bound = math.nan  # set from the first row's error
        self.found: dict[str, dict] = {}
        # per estimator: corrections offered and refused per bin of steps, the rejected count so far
        self.offered = {n: np.zeros(BINS, dtype=np.int64) for n in ctx.names}
        self.refused = {n: np.zeros(BINS, dtype=np.int64) for n in ctx.names}
        self.last_rejected = dict.fromkeys(ctx.names, 0.0)

    def block(self, rows: Rows) -> None:
        if rows.count == 0:
            return
        if math.isnan(self.bound):
            e0 = [float(np.linalg.norm(err["position"][0])) for err in rows.errors.values()]
            self.bound = error_bound(self.ctx.frame.beacons, max(e0, default=0.0))
        steps = rows.ks < self.ctx.frame.steps  # the final row has no correction
        for name, err in rows.errors.items():
            if name not in self.found:
                self._divergence(name, rows, err["position"])
            self._lockout(name, rows.nis[name][steps], rows.rejected[name][steps], rows.ks[steps])

    def _divergence(self, name: str, rows: Rows, ep: np.ndarray) -> None:
        x_bad = ~np.all(np.isfinite(rows.estimates[name]), axis=1)
        truth_ok = np.all(np.isfinite(rows.truth), axis=1)
        e = np.sqrt(np.einsum("ij,ij->i", ep, ep))
        with np.errstate(invalid="ignore"):
            far = e > self.bound
        e_bad = truth_ok & ~np.isfinite(e)
        for reason, hit in (
            ("non-finite estimate", x_bad),
            ("non-finite error", e_bad),
            (f"error beyond the bound {self.bound:.4g} m", far),
        ):
            if hit.any():
                j = int(np.argmax(hit))
                if name not in self.found or rows.ks[j] < self.found[name]["step"]:
                    self.found[name] = {
                        "step": int(rows.ks[j]),
                        "t": float(rows.t[j]),
                        "reason": reason,
                    }

    def _lockout(self, name: str, nis: np.ndarray, rejected: np.ndarray, ks: np.ndarray) -> None:
        """Corrections offered and refused by ``name`` in the rows' steps, counted per bin of steps."""
        offered = np.isfinite(nis)
        if not offered.any() or np.all(np.isnan(rejected)):
            return
        prev = np.concatenate(([self.last_rejected[name]], rejected[:-1]))
        refused = offered & (rejected > prev)
        self.last_rejected[name] = float(rejected[-1])
        bins = ks * BINS // max(self.ctx.frame.steps, 1)
        np.add.at(self.offered[name], bins[offered], 1)
        np.add.at(self.refused[name], bins[refused], 1)

    def _locked_out(self, name: str, completed: int) -> dict | None:
        """The lock-out entry of ``name`` (module docstring), over the bins of the run's second half."""
        steps = max(self.ctx.frame.steps, 1)
        first = -(-BINS * (completed // 2) // steps)  # the first bin starting at or after K/2
        offered = int(self.offered[name][first:].sum())
        refused = int(self.refused[name][first:].sum())
        if offered < LOCKOUT_MIN or refused < LOCKOUT_SHARE * offered:
            return None
        k = -(-first * steps // BINS)
        return {
            "step": k,
            "t": k * self.ctx.frame.dt,
            "reason": f"locked out: rejected {refused} of the {offered} corrections offered from step {k} on",
        }

    def end(self, completed: int, interrupted: bool) -> dict:
        per = {}
        own = {est.name: est for est in getattr(self.ctx, "estimators", ())}
        frame = self.ctx.frame  # the estimators' clock to the rows'
        clock = (getattr(frame, "time_origin", 0.0), frame.dt)
        for name in self.ctx.names:
            est = own.get(name)
            found = (
                self.found.get(name) or given_up(est, *clock) or self._locked_out(name, completed)
            )
            per[name] = {"diverged": found}
            started = startup_record(est, *clock)
            if started is not None:  # only then: every other summary keeps its keys
                per[name]["startup"] = started
        return {"estimators": per}


def _entry(record: dict, origin: float, dt: float | None) -> dict:
    """An estimator's record ``{"time", "step", "reason"}`` as a summary's entry on the run's
    clock: ``t`` from row 0 (the estimator's time less ``origin``, the clock's time of row 0:
    a replayed log's own stamps), ``step`` the row at ``t`` where ``origin`` is not 0 (an
    estimator counting steps from its own clock's zero would give ``t_log / dt``), else the
    record's own (-1: a time without a step)."""
    t = float(record["time"]) - float(origin)
    step = int(record["step"])
    if origin and dt and step >= 0:
        step = int(round(t / dt))
    return {"step": step, "t": t, "reason": record["reason"]}


def given_up(est, origin: float = 0.0, dt: float | None = None) -> dict | None:
    """The estimator's own record of having given up (its lock-out's ``diverged``: out of
    re-initialisations, or a state it judged implausible), as this sink's entry on the run's
    clock (:func:`_entry`)."""
    lock = getattr(est, "lockout", None)
    record = getattr(lock, "diverged", None)
    at_end = getattr(lock, "locked_at_end", None)
    if not record and at_end is not None:  # the run ended inside a re-initialisation's grace
        record = at_end()
    if not record:
        return None
    return _entry(record, origin, dt)


def startup_record(est, origin: float = 0.0, dt: float | None = None) -> dict | None:
    """A start-up from a multilateration that never set the position
    (:func:`~quadobs.estimators.startup.not_started`) as a summary's ``startup`` entry on the
    run's clock (:func:`_entry`), else None. The filter ran from its prior, correcting every
    range with the start-up's grown variance, so its figures stand; the entry says that they
    are those of a filter that never took its position from a fix."""
    record = not_started(est)
    if not record:
        return None
    return _entry(record, origin, dt)


#: Summary keys of an estimator that are figures of its error (made ``None`` once it diverged).
def _is_error_figure(key: str) -> bool:
    return "rmse" in key or "error" in key or key.startswith("time_to_")


def invalidate_diverged(summary: dict) -> dict:
    """Every error figure of a diverged estimator of ``summary`` set to ``None`` (in place); returns it."""
    for entry in summary.get("estimators", {}).values():
        if isinstance(entry, dict) and entry.get("diverged"):
            for key in list(entry):
                if _is_error_figure(key):
                    entry[key] = None
    primary = summary.get("estimators", {}).get(summary.get("primary_estimator"))
    if isinstance(primary, dict) and primary.get("diverged"):  # its figures copied to the top
        for key in list(summary):
            if _is_error_figure(key):
                summary[key] = None
    return summary


def diverged_estimators(summary: dict) -> dict[str, dict]:
    """The estimators of ``summary`` that diverged or locked out, with their ``diverged`` entry."""
    return {
        name: e["diverged"]
        for name, e in summary.get("estimators", {}).items()
        if isinstance(e, dict) and e.get("diverged")
    }
