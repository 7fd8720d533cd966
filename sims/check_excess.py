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
* the same residuals fitted with the line-of-sight core held at the ranges' known noise
  (:func:`~quadobs.testbed.logs.excess_model.known_noise`) instead of fitted (``held``), and
  held so with each window of ``--rounds`` rounds of the anchors given a common position
  error ``u_i^T dp_w`` as well (``window``: the prediction's error, shared by the anchors of
  one time, fitted by least squares in each M-step; ``u_i`` the direction from the anchor
  to the truth's position, which the prediction's differs from by its error, a tenth of a
  metre against metres);
* the residuals and the ranges' own errors fitted with a third component, outliers of either
  sign (:func:`outlier_fit`; ``outliers``: its fit to the residuals);
* ``ekf-bias-imu-nlos`` replayed with the calibration's options under each excess of
  ``--given`` (``MEDIAN:SHAPE``, ``fit``: the fitted one, ``held``, ``window``, ``outliers``: those fits,
  ``ebi``: the excess fitted to ``ekf-bias-imu``'s own residuals, :func:`own_fit`,
  ``gate``: none, the one-sided gate): its position RMSE after ``--burn-in`` s.

    python sims/replay_flight_variants.py --seeds 0 --variants real --out flights/
    python sims/check_excess.py flights/seed0-real
    python sims/check_excess.py flights/seed0-real --diagnose --given fit,gate,0.3:0.6
    python sims/check_excess.py flights/seed1-real --diagnose --given fit,window,outliers
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


def window_fit(r, h, q: int, u: np.ndarray, t: np.ndarray, rounds: float, sigma: float):
    """The mixture of :mod:`~quadobs.testbed.logs.excess_model` with its core held at
    ``sigma`` (m) and a common error ``dp_w`` of the position in each window of ``rounds``
    rounds of the ``q`` anchors (the ranges' mean rate from ``t``):
    ``r_i = mu_h + u_i^T dp_w + eps_i + delta_i e_i``. Each M-step takes ``mu_h`` and then
    ``dp_w = (sum u u^T)^{-1} sum u (r - mu_h - E[e | r])`` (a 1e-6 ridge). Returns
    ``(median, shape, fraction)``."""
    import math

    from quadobs.testbed.logs.excess_model import GRID, ITERATIONS, _responsibilities

    keep = np.isfinite(r)
    r, h, u, t = r[keep], h[keep], u[keep], t[keep]
    span = rounds * q * (t[-1] - t[0]) / max(t.size - 1, 1)
    w = np.floor((t - t[0]) / span).astype(int)
    A = np.zeros((w.max() + 1, u.shape[1], u.shape[1]))
    np.add.at(A, w, u[:, :, None] * u[:, None, :])
    A += 1e-6 * np.eye(u.shape[1])
    counts = np.bincount(h, minlength=q).astype(float)
    mu = np.array([np.median(r[h == j]) if counts[j] else 0.0 for j in range(q)])
    dp = np.zeros((A.shape[0], u.shape[1]))
    pi, m, s, e = 0.2, math.log(3.0 * sigma), 0.5, np.exp(GRID)
    for _ in range(ITERATIONS):
        log_w = -0.5 * ((GRID - m) / s) ** 2
        log_w -= np.logaddexp.reduce(log_w)
        common = np.einsum("ij,ij->i", u, dp[w])
        gx = _responsibilities(r - mu[h] - common, sigma, pi, log_w)[:, 1:]
        mass = float(gx.sum())
        pi = min(max(mass / r.size, 1e-6), 1.0 - 1e-6)
        m = float((gx @ GRID).sum() / mass)
        s = max(math.sqrt(float((gx @ (GRID - m) ** 2).sum() / mass)), float(GRID[1] - GRID[0]))
        y = r - gx @ e
        mu = np.bincount(h, weights=y - common, minlength=q) / np.maximum(counts, 1.0)
        b = np.zeros_like(dp)
        np.add.at(b, w, u * (y - mu[h])[:, None])
        dp = np.linalg.solve(A, b[:, :, None])[:, :, 0]
    return math.exp(m), s, pi


def outlier_fit(r, h, q: int):
    """The mixture of :mod:`~quadobs.testbed.logs.excess_model` with a third component, an
    outlier of either sign (probability ``pi_o``, density uniform over the residuals' span
    ``1 / (max r - min r)``): the core's standard deviation then fitted over the line-of-sight
    and excess responsibilities alone. Returns ``(median, shape, fraction, pi_o, sigma)``,
    ``fraction`` the excess's share of the ranges that are not outliers."""
    import math

    from quadobs.testbed.logs.excess_model import GRID, ITERATIONS

    keep = np.isfinite(r)
    r, h = r[keep], h[keep]
    mu = np.array([np.median(r[h == j]) if np.any(h == j) else 0.0 for j in range(q)])
    sigma = 1.4826 * float(np.median(np.abs(r - mu[h])))
    log_c = -math.log(float(r.max() - r.min()))
    pi, po, m, s = 0.2, 0.01, math.log(3.0 * sigma), 0.5
    z = np.concatenate([[0.0], np.exp(GRID)])
    for _ in range(ITERATIONS):
        log_w = -0.5 * ((GRID - m) / s) ** 2
        log_w -= np.logaddexp.reduce(log_w)
        d2 = ((r - mu[h])[:, None] - z[None, :]) ** 2
        ll = np.empty((r.size, z.size + 1))
        ll[:, :-1] = -0.5 * d2 / sigma**2 - math.log(sigma * math.sqrt(2.0 * math.pi))
        ll[:, 0] += math.log((1.0 - pi) * (1.0 - po))
        ll[:, 1:-1] += math.log(pi * (1.0 - po)) + log_w
        ll[:, -1] = math.log(po) + log_c
        g = np.exp(ll - ll.max(axis=1, keepdims=True))
        g /= g.sum(axis=1, keepdims=True)
        gx, gi = g[:, 1:-1], g[:, :-1]
        po = min(max(float(g[:, -1].mean()), 1e-6), 0.5)
        mass = float(gx.sum())
        pi = min(max(mass / float(gi.sum()), 1e-6), 1.0 - 1e-6)
        m = float((gx @ GRID).sum() / mass)
        s = max(math.sqrt(float((gx @ (GRID - m) ** 2).sum() / mass)), float(GRID[1] - GRID[0]))
        w = gi.sum(axis=1)
        mu = np.bincount(h, weights=w * r - gx @ z[1:], minlength=q)
        mu /= np.maximum(np.bincount(h, weights=w, minlength=q), 1e-9)
        sigma = math.sqrt(float((gi * d2).sum() / w.sum()))
    return math.exp(m), s, pi, po, sigma


def _directions(log, t: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The unit vectors from each anchor ``h`` to the truth's position at ``t``."""
    cols = log.truth_columns
    p = np.column_stack(
        [np.interp(t, log.truth[:, 0], log.truth[:, cols.index(c)]) for c in "xyz"[: log.dimension]]
    )
    d = p - log.beacons[h]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def other_fits(log, seen: dict, e: np.ndarray, h: np.ndarray, rounds: float) -> dict:
    """The fits of ``--diagnose`` beside the replay's (module docstring), printed: the core
    held at the ranges' known noise, held with a common error per window, and with outliers
    (to the residuals ``seen`` and to the ranges' own errors ``e`` of the anchors ``h``).
    Returns ``{name: (median, shape)}`` of those fitted to the residuals."""
    from quadobs.testbed.logs import excess_model as em

    q = log.beacons.shape[0]
    noise = em.known_noise(log)
    fits: dict = {}
    if noise is not None:
        held = em.fit_excess(seen["r"], seen["h"], q, sigma=noise)
        u = _directions(log, seen["t"], seen["h"])
        fits["held"] = (held.median, held.shape)
        median, shape, fraction = window_fit(seen["r"], seen["h"], q, u, seen["t"], rounds, noise)
        fits["window"] = (median, shape)
        print(f"  core held at the known noise {noise:.3f} m: {_fit_text(held)}")
        print(
            f"  held, a common error per {rounds:g} rounds: median {median:.3f} m, shape "
            f"{shape:.2f}, fraction {fraction:.3f}"
        )
    for what, (x, k) in {"residuals": (seen["r"], seen["h"]), "own errors": (e, h)}.items():
        median, shape, fraction, po, core = outlier_fit(x, k, q)
        if what == "residuals":
            fits["outliers"] = (median, shape)
        print(
            f"  {what} with outliers of either sign: median {median:.3f} m, shape {shape:.2f}, "
            f"fraction {fraction:.3f}, outliers {po:.3f}, core {core:.3f} m"
        )
    return fits


def own_fit(log, cal, dt: float):
    """``(median, shape)`` of the excess fitted, as step 8 fits it, to ``ekf-bias-imu``'s own
    prequential residuals (its biases as states, the ranges as logged, the calibration's
    options without the excess) in place of the EKF's; None where not identified."""
    from quadobs.testbed.logs import calibration as cm
    from quadobs.testbed.logs import excess_model as em

    gate = {k: v for k, v in cal.options.items() if k not in em.EXCESS_KEYS}
    res = cm.prediction_residuals(log, dt=dt, estimator="ekf-bias-imu", setup_options=gate)
    fit, ok, why = em.excess_model(res.r, res.h, log.beacons.shape[0], em.known_noise(log))
    print(f"  ekf-bias-imu's own residuals: {why}")
    return (fit.median, fit.shape) if ok and fit is not None else None


def diagnose(
    folder: str, given: list[str], dt: float, burn_in: float, bootstrap: int, rounds: float
) -> None:
    """``--diagnose`` (module docstring): printed line by line."""
    from quadobs.testbed.logs import calibration as cm
    from quadobs.testbed.logs import excess_model as em
    from quadobs.testbed.logs.replay import replayable_log, run_replay

    log, _ = replayable_log(open_log(folder))
    seen = {}
    step8 = cm.calibrated_excess

    def keep(log_, res, options):  # the residuals step 8 is given
        seen["r"], seen["h"], seen["t"] = res.r, res.h, res.t
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
    fits = other_fits(log, seen, e[ok], h[ok], rounds)
    if "ebi" in given:
        fits["ebi"] = own_fit(log, cal, dt)
    as_logged = estimator_biases(log, cal, [NLOS], dt=dt)
    biases = None if cal.biases is None else [float(b) for b in cal.biases]
    for g in given:
        options = {k: v for k, v in cal.options.items() if k not in em.EXCESS_KEYS}
        if g == "fit":
            options.update({k: cal.options[k] for k in em.EXCESS_KEYS if k in cal.options})
        elif g in ("held", "window", "outliers", "ebi"):
            if fits.get(g) is None:
                print(f"  {NLOS} given {g}: nothing fitted or identified (the gate)")
            else:
                options["nlos_median"], options["nlos_shape"] = fits[g]
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
    ap.add_argument(
        "--given",
        default="fit,gate",
        help="with --diagnose: MEDIAN:SHAPE, fit, held, window, outliers, ebi, gate",
    )
    ap.add_argument(
        "--rounds", type=float, default=3.0, help="with --diagnose: the window, rounds of anchors"
    )
    ap.add_argument("--burn-in", type=float, default=5.0)
    ap.add_argument("--bootstrap", type=int, default=20, help="with --diagnose: resamples")
    args = ap.parse_args()
    if not args.rounds > 0.0:
        ap.error(f"--rounds: expected a positive number of rounds, got {args.rounds}")
    if args.bootstrap < 2:
        ap.error(f"--bootstrap: at least 2 resamples for a standard error, got {args.bootstrap}")
    for g in args.given.split(","):
        if g not in ("fit", "held", "window", "outliers", "ebi", "gate") and not _excess_text_ok(g):
            ap.error(
                f"--given: expected fit, held, window, outliers, ebi, gate or MEDIAN:SHAPE (positive"
                f" numbers),"
                f" got {g!r}"
            )
    for folder in args.folders:
        if args.diagnose:
            diagnose(
                folder, args.given.split(","), args.dt, args.burn_in, args.bootstrap, args.rounds
            )
        else:
            print(check(folder, args.estimator, args.dt), flush=True)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
