"""The robot behind a pillar: what the excess rule of ``ukf-height-lever`` leaves, against oracles.

The stress ``pillar`` of ``sims/stress_hidden_logs.py`` lengthens every range whose path crosses
a pillar beside the robot's path by an exponential excess of mean 0.3 m
(:func:`quadobs.testbed.logs.posed.behind_pillar`): bursts on anchors 0 and 1 as the robot
passes. For each seed the stand-in ``all`` is exported with and without the stress (the same
draws otherwise), the stressed log is self-calibrated once as ``quadobs replay`` does, and
``ukf-height-lever`` is replayed on it with that calibration (position RMSE after 5 s, m):

* ``rule``: the default (:func:`quadobs.testbed.logs.height_estimators.excess_rule`);
* ``no excess``: the ranges of the log without the stress (the floor of any rule);
* ``sight known``: each range's excess posterior taken as blocked or clear as the posing drew it
  (prior 1 or 0) under the exponential law of the posing's own mean;
* ``sight known, flat``: the same, the excess's law flat (``mu -> inf``: a blocked range leaves
  the line-of-sight part of its innovation at its prior, :class:`ExcessHuber
  <quadobs.estimators.robust.ExcessHuber>`);
* ``blocked dropped``: the blocked ranges left out of the log;
* ``true fractions``: the rule with each anchor's chain relaxing to the fraction of its ranges
  that are blocked (memory: the mean length of a pass behind the pillar), not to the prior
  at the bound;
* ``prior per range``: the rule whose chain gives every range at least the prior at the
  bound ``pi``, ``pi + (1 - pi) gamma exp(-dt / memory)`` (``gamma`` the anchor's previous
  posterior, ``dt`` the time since it; the default chain's ``pi + (gamma - pi) exp(-dt /
  memory)`` gives a range after a clear one ``pi (1 - exp(-dt / memory))``, 0.0033 at 4 Hz an
  anchor);
* ``first pass``, ``later passes``: the log without the stress but for the ranges of the
  first pass behind the pillar (the blocked ranges up to the first gap longer than a pass),
  or but for those of the passes after it.

The oracles replace the filter's excess step (``_less_excess``); nothing else changes. Also
printed: the chi-square of the start-up's multilateration residual against the variance the
fix assumes (one degree of freedom with four anchors), the noise alone and with the anchors'
heights' and biases' priors.

    python sims/pillar_bounds.py --seeds 2,3
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import replace
from pathlib import Path
from unittest.mock import patch

import numpy as np
import stress_hidden_logs as stress

from quadobs.errors import run_script
from quadobs.estimators.robust import ExcessHuber
from quadobs.testbed.logs import read_log, write_log
from quadobs.testbed.logs.calibration import calibrate, estimator_biases, noise_keys
from quadobs.testbed.logs.estimators import REPLAY_ESTIMATORS, build_ukf_height_lever
from quadobs.testbed.logs.replay import default_estimators, run_replay

NAME = "ukf-height-lever"
#: The posing's excess (m): the mean of :func:`stress_hidden_logs.ROVER`'s ``pillar``.
PILLAR_MEAN = 0.3


def replay(folder: Path, cal, builder=None) -> float:
    """``ukf-height-lever`` on the log ``folder`` with the calibration ``cal`` (biases, noise,
    the estimators that take the ranges as logged) and, where given, its own factory."""
    biases, options, as_logged = cal
    given = {NAME: builder} if builder is not None else {}
    with patch.dict(REPLAY_ESTIMATORS, given):
        summary = run_replay(
            read_log(folder), estimators=[NAME], biases=biases, setup_options=options,
            burn_in=stress.rover.BURN_IN, batch=False, as_logged=as_logged,
        )  # fmt: skip
    e = summary["estimators"][NAME]
    return math.nan if e.get("diverged") else float(e["rmse"])


def with_excess(log, hit: np.ndarray, posterior, seen: list):
    """A factory of ``ukf-height-lever`` whose excess step is ``posterior(rule, nu, S, blocked,
    anchor) -> (E[e | nu], Var[e | nu])``, ``blocked`` whether the posing blocked the range:
    the log's range of that anchor nearest in time (within 1 ms). ``seen`` collects the rows
    of the blocked ranges it met, to check that every one was named."""
    rows = [np.flatnonzero(log.ranges[:, 1] == h) for h in range(log.beacons.shape[0])]

    def build(s, x0, name):
        est = build_ukf_height_lever(s, x0, name)

        def less_excess(nu: float, S: float) -> tuple[float, float]:
            h = est._range_anchor
            mine = rows[h]
            i = mine[np.argmin(np.abs(log.ranges[mine, 0] - est._time))]
            if abs(log.ranges[i, 0] - est._time) > 1e-3:
                raise SystemExit(f"no range of anchor {h} at {est._time} s in the log")
            if hit[i]:
                seen.append(int(i))
            shift, var = posterior(est, nu, S, bool(hit[i]), h)
            return nu - shift, var

        est._less_excess = less_excess
        return est

    return build


def oracle(folder: Path, cal, hit: np.ndarray, posterior) -> float:
    """:func:`replay` with the excess step ``posterior``; every blocked range must be met."""
    seen: list = []
    rmse = replay(folder, cal, with_excess(read_log(folder), hit, posterior, seen))
    if len(set(seen)) != int(hit.sum()):
        raise SystemExit(f"{len(set(seen))} of {int(hit.sum())} blocked ranges named")
    return rmse


def known(mean: float):
    """The excess posterior given the range's sight (prior 1 or 0), the law's mean ``mean``."""

    def posterior(est, nu, S, hit, h):
        rule = ExcessHuber(mean, 0.5, est.robust.c)
        return rule.posterior(nu, S, 1.0 if hit else 0.0)[:2]

    return posterior


def fractions(share: np.ndarray, memory: float):
    """The rule's chain relaxing to each anchor's own blocked share over ``memory`` s."""

    def posterior(est, nu, S, hit, h):
        rule, pi = est.robust, max(float(share[h]), 1e-6)
        dt = est._time - float(est._blocked_at[h])
        prior = pi + (float(est._blocked[h]) - pi) * math.exp(-dt / memory) if dt < 1e9 else pi
        mean, var, gamma = rule.posterior(nu, S, prior)
        est._blocked[h], est._blocked_at[h] = gamma, est._time
        return mean, var

    return posterior


def per_range():
    """The rule's chain with the bound's prior ``pi`` per range: a range's sight persists from
    its anchor's previous range with probability ``exp(-dt / memory)``, else is drawn afresh
    with ``pi``, so that its prior is ``pi + (1 - pi) gamma exp(-dt / memory)`` (``gamma``
    the previous range's posterior, ``dt`` the time since it)."""

    def posterior(est, nu, S, hit, h):
        rule = est.robust
        dt = est._time - float(est._blocked_at[h])
        carried = float(est._blocked[h]) * math.exp(-dt / rule.memory) if dt < math.inf else 0.0
        prior = rule.nlos + (1.0 - rule.nlos) * carried
        mean, var, gamma = rule.posterior(nu, S, prior)
        est._blocked[h], est._blocked_at[h] = gamma, est._time
        return mean, var

    return posterior


def partly(clear, hidden, keep: np.ndarray, folder: Path) -> Path:
    """The log ``clear`` with the ranges ``keep`` as the log ``hidden`` holds them."""
    ranges = clear.ranges.copy()
    ranges[keep] = hidden.ranges[keep]
    write_log(replace(hidden, ranges=ranges), folder)
    return folder


def with_fix_chi2(out: list):
    """A factory of ``ukf-height-lever`` (the default, unchanged) that appends to ``out`` the
    chi-square of its start-up fix's residual against the range noise alone and with the
    anchors' states' priors (:meth:`HeadingUKF._fix_covariance`'s variances ``v``).

    The fix is the least squares ``q = H^+ G y`` (``G`` centres the outputs, ``H = -G A``), so
    its residual ``r = (I - H H^+) G y`` has the covariance ``C = (I - H H^+) G diag(v) G (I -
    H H^+)`` of rank ``q - 3``, and ``r^T C^+ r`` is chi-square with ``q - 3`` degrees of
    freedom."""

    def build(s, x0, name):
        est = build_ukf_height_lever(s, x0, name)
        fix = est._fix_covariance

        def checked() -> None:
            rows = np.flatnonzero(~np.isnan(est._latest))
            A, y = est.anchors[rows], est._latest[rows]
            rho2 = np.maximum(2.0 * y + np.einsum("hi,hi->h", A, A), 0.0)
            var, P0 = est._latest_std[rows] ** 2, np.diag(est._P0)
            noise = rho2 * var + 0.5 * var * var
            full = noise.copy()
            if est._ie >= 0:
                full += P0[est._ie + rows]
            if est._ib >= 0:
                full += rho2 * P0[est._ib + rows]
            G = np.eye(rows.size) - 1.0 / rows.size
            H = -G @ A
            K = np.eye(rows.size) - H @ np.linalg.pinv(H)
            r = K @ G @ y
            for v in (noise, full):
                C = K @ G @ np.diag(v) @ G @ K.T
                out.append(float(r @ np.linalg.pinv(C, rcond=1e-10, hermitian=True) @ r))
            out.append(float(rows.size - 3))
            fix()

        est._fix_covariance = checked
        return est

    return build


def calibrated(folder: Path):
    """The replay's self-calibration of the log ``folder`` (``quadobs replay``'s defaults)."""
    log = read_log(folder)
    cal = calibrate(log, dt=0.1, model=None, setup_options={}, noise=tuple(noise_keys(log, None)))
    as_logged = estimator_biases(log, cal, default_estimators(log, None), dt=0.1, model=None)
    biases = None if cal.biases is None else [float(b) for b in cal.biases]
    return biases, cal.options, tuple(as_logged)


def seed_row(seed: int, room: str, duration: float, tmp: Path) -> dict:
    """Every figure of the module docstring for one seed."""
    clear = stress.rover_log(seed, "none", room, duration, tmp)
    hidden = stress.rover_log(seed, "pillar", room, duration, tmp)
    lp, ln = read_log(hidden), read_log(clear)
    excess = lp.ranges[:, 2] - ln.ranges[:, 2]
    hit = excess > 0.0
    anchors = lp.ranges[:, 1].astype(int)
    share = np.array([hit[anchors == h].mean() for h in range(lp.beacons.shape[0])])
    dropped = tmp / f"{hidden.name}-dropped"
    std = lp.range_std[~hit] if lp.range_std.size else lp.range_std
    write_log(replace(lp, ranges=lp.ranges[~hit], range_std=std), dropped)
    cal = calibrated(hidden)
    period = float(np.median(np.diff(lp.ranges[anchors == 0, 0])))
    runs = np.flatnonzero(np.diff(np.r_[0, hit[anchors == 0].astype(int), 0]))
    memory = float(np.mean(np.diff(runs)[::2]) * period) if runs.size else 1.0
    times = lp.ranges[hit, 0]
    gaps = np.flatnonzero(np.diff(times) > memory)
    end = times[gaps[0]] if gaps.size else math.inf
    first = hit & (lp.ranges[:, 0] <= end)
    chi2: list[float] = []
    row = {
        "rule": replay(hidden, cal, with_fix_chi2(chi2)),
        "no excess": replay(clear, cal),
        "sight known": oracle(hidden, cal, hit, known(PILLAR_MEAN)),
        "sight known, flat": oracle(hidden, cal, hit, known(1e6)),
        "blocked dropped": replay(dropped, cal),
        "true fractions": oracle(hidden, cal, hit, fractions(share, memory)),
        "prior per range": oracle(hidden, cal, hit, per_range()),
        "first pass": replay(partly(ln, lp, first, tmp / f"{hidden.name}-first"), cal),
        "later passes": replay(partly(ln, lp, hit & ~first, tmp / f"{hidden.name}-later"), cal),
    }
    fixed = (
        "no start-up fix"
        if not chi2
        else (
            f"start-up fix chi2 {chi2[0]:.1f} (noise alone), {chi2[1]:.2f} (with the anchors' "
            f"priors), {chi2[2]:.0f} degree(s) of freedom"
        )
    )
    print(
        f"seed {seed}: blocked shares {np.round(share, 3).tolist()}, a pass {memory:.2f} s; {fixed}"
    )
    print(f"seed {seed}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()), flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="2,3")
    ap.add_argument("--room", default="today", choices=tuple(stress.rover.ROOMS))
    ap.add_argument("--duration", type=float, default=90.0, help="s")
    args = ap.parse_args()
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    if not args.duration > stress.rover.BURN_IN:
        ap.error(f"--duration: expected more than the {stress.rover.BURN_IN:g} s burn-in")
    rows = {}
    with tempfile.TemporaryDirectory(prefix="pillar-") as tmp:
        for seed in seeds:
            rows[seed] = seed_row(seed, args.room, args.duration, Path(tmp))
    names = list(next(iter(rows.values())))
    print("| seed | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for seed, row in rows.items():
        print(f"| {seed} | " + " | ".join(f"{row[n]:.3f}" for n in names) + " |")
    print(f"({NAME}, position RMSE after {stress.rover.BURN_IN:g} s, m)")


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
