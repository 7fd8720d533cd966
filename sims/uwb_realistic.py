"""quadrotor-uwb-realistic over many seeds: convergence from 20 m off, and bias states against known biases.

For each seed the scenario is flown once (the flight is on the truth, so it does not depend
on the estimators) with, on the same measurements:

* the scenario's estimators named on the command line (default ``ekf-bias``: the EKF with
  a bias state per anchor, the scenario's gate and lock-out);
* ``ekf-known-bias``: the same EKF, gate and lock-out without bias states, given the radio's
  true biases (its range model subtracts them: ``RangeModel(bias="fixed")``);
* with ``--given``, ``ekf-bias-given``: ``ekf-bias`` itself with its bias states pinned at
  the true biases (its robust rule, the excess mixture of the radio's stated
  non-line-of-sight excess, and its start-up unchanged); and ``ukf-bias-given``, the same
  for ``ukf-bias``, when it is among the estimators;
* with ``--line-of-sight`` (a diagnostic no estimator can have), ``ekf-bias-los`` (and, with
  ``--given``, ``ekf-bias-given-los``): the same filters given only the ranges whose path the
  room left clear (the radio's own ray test when it drew the range), which measures what the
  non-line-of-sight excess costs the bias states;
* with ``--sight-model grid``, every bias-state filter (the ``-given`` ones too) keeps each
  anchor's state of sight jointly with its bias (:class:`~quadobs.estimators.robust.BiasSightGrid`)
  instead of the chain on its own bias estimate;
* with ``--memory SECONDS``, every filter whose rule is an
  :class:`~quadobs.estimators.robust.ExcessMixture` (the ``-given`` ones too) keeps its
  anchors' state of sight over that memory instead of the rule's default;
* with ``--fix-correction on|off``, every bias-state filter (the ``-given`` ones too) starts
  with one joint correction by its fix's round of ranges linearised at the multilateration
  (``on``), or with the fix's covariance (``off``), instead of the filters' default;
* with ``--jacobian-at-truth`` (a diagnostic), ``ekf-bias-truejac``: ``ekf-bias`` whose range
  Jacobian is taken at the tag's true position (its predicted ranges still at its estimate),
  which measures what linearising at its own estimate costs it.

Printed per seed and in total: the time from which each estimator's position error stays
below 1 m (the summary's ``time_to_1m``), the position RMSE over the flight after a 5 s
burn-in, and the ratio of each estimator's RMSE to the known-bias EKF's.

Usage::

    python sims/uwb_realistic.py --seeds 0:50 [--duration 40] [--estimators ekf-bias,ukf-bias]
        [--given] [--line-of-sight] [--jacobian-at-truth] [--sight-model grid]
        [--memory 3] [--fix-correction on|off]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from quadobs.core.measurements import RangeModel
from quadobs.errors import run_script
from quadobs.estimators.kalman import ExtendedKalmanFilter
from quadobs.estimators.robust import ExcessMixture
from quadobs.testbed.episode import _summarise, run_loop, scenario_parts
from quadobs.testbed.factories import baseline_settings, robust_settings
from quadobs.testbed.scenario import load_scenario

BURN_IN = 5.0


def known_bias_ekf(scenario, world, x0: np.ndarray) -> ExtendedKalmanFilter:
    """The scenario's EKF given the radio's true biases."""
    s = baseline_settings(scenario)
    model = RangeModel(
        scenario.beacons, scenario.radio.std, bias="fixed", fixed_bias=world.radio.biases
    )
    est = ExtendedKalmanFilter(
        s.dynamics,
        s.outputs,
        x0=x0,
        P0=s.P0,
        gate=scenario.observer.gate,
        measurements=model,
        **robust_settings(scenario),
    )
    est.name = "ekf-known-bias"
    return est


def given_bias_filter(scenario, world, x0: np.ndarray, kind: str = "ekf"):
    """``ekf-bias`` (``kind="ukf"``: ``ukf-bias``) itself with its bias states pinned at the
    radio's true biases (zero prior covariance, and the biases a re-initialisation returns to):
    the same estimator, rule and start-up, given the true biases."""
    from quadobs.testbed.factories import (
        biased_extended_kalman_filter,
        biased_unscented_kalman_filter,
    )

    make = {"ekf": biased_extended_kalman_filter, "ukf": biased_unscented_kalman_filter}[kind]
    est = make(scenario, x0)
    k, b = est.vehicle_n, np.asarray(world.radio.biases, dtype=float)
    est._x[k:] = b
    est._P[k:, :] = 0.0
    est._P[:, k:] = 0.0
    est._P0 = est._P.copy()
    est._bias_prior = b.copy()
    est.name = f"{kind}-bias-given"
    return est


def drawn_events(radio) -> dict:
    """Each range the radio draws from now on, ``id -> (event, tag position, blocked)``: the
    tag's true position at the event's time and whether the room blocked its path (the radio's
    own ray test), recorded by wrapping the radio's ``room.blocked`` and ``_event`` (the events
    are kept, so that no id is reused)."""
    if hasattr(radio, "drawn_events"):
        return radio.drawn_events
    events: dict = {}
    last = {"blocked": False}
    blocked, event = radio.room.blocked, radio._event

    def blocked_kept(a, p):
        last["blocked"] = out = blocked(a, p)
        return out

    def event_kept(t, lane, p):
        last["blocked"] = False
        m = event(t, lane, p)
        if m is not None:
            events[id(m)] = (m, np.array(p, dtype=float), last["blocked"])
        return m

    radio.room.blocked, radio._event = blocked_kept, event_kept
    radio.drawn_events = events
    return events


def line_of_sight_only(est, world):
    """``est`` given only the ranges whose path the radio's room left clear when it drew them
    (:func:`drawn_events`; its other ranges are dropped before they reach it): a diagnostic."""
    correct, events = est.correct, drawn_events(world.radio)

    def clear_only(m):
        if not events[id(m)][2]:
            correct(m)

    est.correct = clear_only
    est.name += "-los"
    return est


def jacobian_at_truth(est, world):
    """``est`` (a bias-state filter) with its range Jacobian at the tag's true position when
    the radio drew the range (:func:`drawn_events`): a diagnostic."""
    from quadobs.estimators.bias_states import BiasedRangeOutputModel

    truth = np.zeros(3)

    class AtTruth(BiasedRangeOutputModel):
        def linearize(self, x):
            x_true = x.copy()
            x_true[:3] = truth
            return super().linearize(x)[0], super().linearize(x_true)[1]

    correct, events = est.correct, drawn_events(world.radio)

    def correct_at_truth(m):
        truth[:] = events[id(m)][1]
        correct(m)

    out = est.outputs
    est.outputs = AtTruth(out.system, out.R, offsets=out.offsets)
    est.correct = correct_at_truth
    est.name += "-truejac"
    return est


def one_seed(
    seed: int,
    duration: float | None,
    names: list[str],
    given: bool = False,
    los: bool = False,
    truejac: bool = False,
    sight: str = "chain",
    memory: float | None = None,
    fix_correction: bool | None = None,
) -> dict:
    over = {"seed": seed} | ({"duration": duration} if duration else {})
    scenario = load_scenario("quadrotor-uwb-realistic", **over)
    parts = scenario_parts(scenario, names)
    world = parts["world"]
    x0 = parts["estimators"][0].x_hat
    parts["estimators"] = list(parts["estimators"]) + [known_bias_ekf(scenario, world, x0)]
    all_names = names + ["ekf-known-bias"]
    if given:
        parts["estimators"].append(given_bias_filter(scenario, world, x0))
        all_names.append("ekf-bias-given")
        if "ukf-bias" in names:
            parts["estimators"].append(given_bias_filter(scenario, world, x0, "ukf"))
            all_names.append("ukf-bias-given")
    if los:
        from quadobs.testbed.factories import biased_extended_kalman_filter

        extra = [biased_extended_kalman_filter(scenario, x0)]
        extra += [given_bias_filter(scenario, world, x0)] if given else []
        for est in extra:
            parts["estimators"].append(line_of_sight_only(est, world))
            all_names.append(est.name)
    if truejac:
        from quadobs.testbed.factories import biased_extended_kalman_filter

        est = jacobian_at_truth(biased_extended_kalman_filter(scenario, x0), world)
        parts["estimators"].append(est)
        all_names.append(est.name)

    for est in parts["estimators"]:
        if hasattr(est, "sight_model"):
            est.sight_model = sight
        if fix_correction is not None and hasattr(est, "fix_correction"):
            est.fix_correction = fix_correction
        if memory is not None and isinstance(getattr(est, "robust", None), ExcessMixture):
            est.robust = dataclasses.replace(est.robust, memory=memory)

    def summarise(merged, completed, wall, interrupted):
        return _summarise(
            scenario, all_names, merged, completed, wall, parts["sensors"], None, interrupted
        )

    summary, episode = run_loop(summarise, collect_every=10, **parts)
    trace = episode.trace.trace
    t = np.asarray(trace["time"])
    truth = np.asarray(trace["truth"])[:, :3]
    keep = (t >= BURN_IN) & np.isfinite(t)
    out = {"seed": seed, "biases": parts["world"].radio.biases.tolist()}
    for name in all_names:
        est = np.asarray(trace["estimates"][name])[:, :3]
        err = np.linalg.norm(est - truth, axis=1)
        info = summary["estimators"][name]
        out[name] = {
            "time_to_1m": info.get("time_to_1m"),
            "rmse_after_burn_in": float(np.sqrt(np.mean(err[keep] ** 2))),
            "diverged": info.get("diverged"),
            "resets": len(info.get("resets", [])),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0:50", help="first:last (exclusive)")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--estimators", default="ekf-bias")
    ap.add_argument(
        "--given",
        action="store_true",
        help="also ekf-bias with its bias states pinned at the truth",
    )
    ap.add_argument(
        "--line-of-sight",
        action="store_true",
        help="also ekf-bias (and, with --given, ekf-bias-given) given the line-of-sight ranges only",
    )
    ap.add_argument(
        "--jacobian-at-truth",
        action="store_true",
        help="also ekf-bias with its range Jacobian at the true position",
    )
    ap.add_argument(
        "--sight-model",
        choices=("chain", "grid"),
        default="chain",
        help="how the bias filters keep each anchor's state of sight (default: chain)",
    )
    ap.add_argument(
        "--memory",
        type=float,
        default=None,
        help="the excess mixture's memory of each anchor's sight (s; default: the rule's)",
    )
    ap.add_argument(
        "--fix-correction",
        choices=("on", "off"),
        default=None,
        help="every bias-state filter's start-up: one joint correction by the fix's round of "
        "ranges linearised at it (on), or the fix's covariance (off); default: the filters'",
    )
    args = ap.parse_args()
    a, b = (int(v) for v in args.seeds.split(":"))
    names = args.estimators.split(",")
    for seed in range(a, b):
        row = one_seed(
            seed,
            args.duration,
            names,
            args.given,
            args.line_of_sight,
            args.jacobian_at_truth,
            args.sight_model,
            args.memory,
            None if args.fix_correction is None else args.fix_correction == "on",
        )
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
