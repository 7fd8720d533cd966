"""The estimated non-line-of-sight excess on logs: the held-out check (step 9 of the
self-calibration, :func:`quadobs.testbed.logs.calibration.estimator_excess`), or with
``--diagnose`` where the fit comes from and what the filter does with it.

Default, for each log folder: the replay's self-calibration (:func:`~quadobs.testbed.logs.calibration.calibrate`,
then the biases of each bias filter, :func:`~quadobs.testbed.logs.calibration.estimator_biases`),
then the check, ``ekf-bias-imu`` replayed under the fitted mixture and under the one-sided
gate, the same ranges held out. Prints the fitted excess, the held-out scores of both (the
mean negative log-likelihood under the fitted model, and the root mean capped square) and
whether the mixture was significantly better (kept) or not (dropped).

``--diagnose`` (a log with a truth; the truth is read here, never by the replay): the
self-calibration as the replay runs it, then

* the excess fitted to the calibration's residuals (what the replay gives the filter), its
  standard errors over ``--bootstrap`` resamples of those residuals (seeded), and the
  same model fitted to the ranges' own errors against the truth (each range less the true
  distance, each anchor's median error removed: the radio's noise and excess without any
  prediction's error), with the fraction of those errors beyond 0.3 and 0.6 m;
* ``ekf-bias-imu-nlos`` replayed with the calibration's options under each excess of
  ``--given`` (``MEDIAN:SHAPE``, ``fit``: the fitted one, ``gate``: none, the one-sided gate):
  its position RMSE after ``--burn-in`` s.

    python sims/replay_flight_variants.py --seeds 0 --variants real --out flights/
    python sims/check_excess.py flights/seed0-real
    python sims/check_excess.py flights/seed0-real --diagnose --given fit,gate,0.3:0.6
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from quadobs.errors import run_script
from quadobs.testbed.logs import open_log, read_log
from quadobs.testbed.logs.calibration import calibrate, estimator_biases, estimator_excess

NLOS = "ekf-bias-imu-nlos"


def check(folder: str, estimator: str, dt: float) -> str:
    """One log's row of the table."""
    log = read_log(folder)
    cal = calibrate(log, dt=dt)
    estimator_biases(log, cal, [estimator], dt=dt)
    estimator_excess(log, cal, [estimator], dt=dt)
    e = cal.excess
    if "check" not in e:
        return f"{folder}: not checked ({'no excess chosen' if not e.get('chosen') else estimator + ' takes none'})"
    c = e["check"][estimator]
    sq = c["squared"]
    return (
        f"{folder}: excess {e['median']:.2f} m, shape {e['shape']:.2f}; held-out NLL mixture "
        f"{c['score']:.3f}, gate {c['reference_score']:.3f}; capped square {sq['score']:.3f} m, "
        f"{sq['reference_score']:.3f} m; {'kept' if e['chosen'] else 'dropped'}"
    )


def truth_errors(log) -> tuple[np.ndarray, np.ndarray]:
    """``(e, h)``: each range less its true distance (the truth's position interpolated to
    the range's time; NaN outside the truth's span and for a range of 0 m or less, which the
    replay leaves out), less its anchor's median, and its anchor."""
    t = log.truth[:, 0]
    cols = log.truth_columns
    at = log.ranges[:, 0]
    p = np.column_stack(
        [np.interp(at, t, log.truth[:, cols.index(c)]) for c in "xyz"[: log.dimension]]
    )
    h = log.beacon_index(log.ranges[:, 1])
    e = log.ranges[:, 2] - np.linalg.norm(p - log.beacons[h], axis=1)
    e[(at < t[0]) | (at > t[-1]) | (log.ranges[:, 2] <= 0.0)] = np.nan  # as the replay
    for j in np.unique(h):
        e[h == j] -= np.nanmedian(e[h == j])
    return e, h


def _fit_text(fit) -> str:
    return (
        f"median {fit.median:.3f} m, shape {fit.shape:.2f}, fraction {fit.fraction:.3f}, "
        f"core {fit.sigma:.3f} m; beyond 3 sd {fit.upper} above / {fit.lower} below"
    )


def _bootstrap_text(fit, r, h, q: int, count: int) -> str:
    """The fit's standard errors over ``count`` resamples of the residuals (seeded): of
    ``log e_50``, of the shape, and of the separation ``log(e_50 / sigma)``, and the
    separation in its standard errors."""
    from quadobs.testbed.logs.excess_model import fit_excess

    keep = np.isfinite(r)
    r, h = r[keep], h[keep]
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(count):
        i = rng.integers(0, r.size, r.size)
        f = fit_excess(r[i], h[i], q)
        draws.append((np.log(f.median), f.shape, np.log(f.median / f.sigma)))
    se = np.std(draws, axis=0, ddof=1)
    separation = float(np.log(fit.median / fit.sigma))
    return (
        f"{count} resamples: standard error of log median {se[0]:.2f}, of shape {se[1]:.2f}; "
        f"log(median / core) {separation:.2f} +- {se[2]:.2f} ({separation / se[2]:.1f} of them)"
    )


def diagnose(folder: str, given: list[str], dt: float, burn_in: float, bootstrap: int) -> None:
    """``--diagnose`` (module docstring): printed line by line."""
    from quadobs.testbed.logs import calibration as cm
    from quadobs.testbed.logs import excess_model as em
    from quadobs.testbed.logs.replay import replayable_log, run_replay

    log, _ = replayable_log(open_log(folder))
    seen = {}
    step8 = cm.calibrated_excess

    def keep(log_, res, options):  # the residuals step 8 is given
        seen["r"], seen["h"] = res.r, res.h
        return step8(log_, res, options)

    cm.calibrated_excess = keep
    try:
        cal = calibrate(log, dt=dt, noise=cm.noise_keys(log, None))
    finally:
        cm.calibrated_excess = step8
    q = log.beacons.shape[0]
    fit = em.fit_excess(seen["r"], seen["h"], q)
    print(f"{folder}: residuals' fit {_fit_text(fit)}")
    print(f"  {_bootstrap_text(fit, seen['r'], seen['h'], q, bootstrap)}")
    e, h = truth_errors(log)
    ok = np.isfinite(e)
    print(
        f"  ranges' own errors' fit {_fit_text(em.fit_excess(e[ok], h[ok], q))}; beyond "
        f"0.3 m {np.mean(e[ok] > 0.3):.3f}, beyond 0.6 m {np.mean(e[ok] > 0.6):.3f}"
    )
    as_logged = estimator_biases(log, cal, [NLOS], dt=dt)
    biases = None if cal.biases is None else [float(b) for b in cal.biases]
    for g in given:
        options = {k: v for k, v in cal.options.items() if k not in em.EXCESS_KEYS}
        if g == "fit":
            options.update({k: cal.options[k] for k in em.EXCESS_KEYS if k in cal.options})
        elif g != "gate":
            options["nlos_median"], options["nlos_shape"] = (float(v) for v in g.split(":"))
        s = run_replay(
            log,
            estimators=[NLOS],
            dt=dt,
            biases=biases,
            setup_options=options,
            burn_in=burn_in,
            as_logged=as_logged,
            batch=False,
        )
        r = s["estimators"][NLOS]
        said = (
            "the gate"
            if "nlos_median" not in options
            else (f"{options['nlos_median']:.3f} m, {options['nlos_shape']:.2f}")
        )
        print(
            f"  {NLOS} given {g} ({said}): {r['rmse']:.4f} m"
            + (f"  DIVERGED {r['diverged']}" if r.get("diverged") else ""),
            flush=True,
        )


def _excess_text_ok(text: str) -> bool:
    """Whether ``text`` is ``MEDIAN:SHAPE`` with two positive finite numbers."""
    parts = text.split(":")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        return False
    return len(values) == 2 and all(np.isfinite(v) and v > 0 for v in values)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("folders", nargs="+", help="log folders (quadobs replay's)")
    ap.add_argument("--estimator", default="ekf-bias-imu")
    ap.add_argument("--dt", type=float, default=0.1)
    ap.add_argument("--diagnose", action="store_true", help="the fit against the truth's errors")
    ap.add_argument("--given", default="fit,gate", help="with --diagnose: MEDIAN:SHAPE, fit, gate")
    ap.add_argument("--burn-in", type=float, default=5.0)
    ap.add_argument("--bootstrap", type=int, default=20, help="with --diagnose: resamples")
    args = ap.parse_args()
    if args.bootstrap < 2:
        ap.error(f"--bootstrap: at least 2 resamples for a standard error, got {args.bootstrap}")
    for g in args.given.split(","):
        if g not in ("fit", "gate") and not _excess_text_ok(g):
            ap.error(f"--given: expected fit, gate or MEDIAN:SHAPE (positive numbers), got {g!r}")
    for folder in args.folders:
        if args.diagnose:
            diagnose(folder, args.given.split(","), args.dt, args.burn_in, args.bootstrap)
        else:
            print(check(folder, args.estimator, args.dt), flush=True)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
