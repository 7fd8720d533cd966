"""quadrotor-uwb-realistic: the online bound of estimating the range biases, flight by flight.

The target "the bias filter within 1.2x of the same filter given the true biases" asks how
much not knowing the biases must cost an online estimator. For each seed the scenario is
flown once (on the truth) with ``ekf-bias`` (and the estimators named) and the same filters
given the true biases (``ekf-bias-given``: their bias states pinned at the radio's biases),
and every range the radio draws is kept with the tag's true position and whether the room
blocked its path (the radio's own ray test, :func:`uwb_realistic.drawn_events`). On those
ranges, at their times, the posterior Cramér-Rao bound
(:func:`quadobs.evaluation.range_bias_bound.range_bias_crb`; the prior of ``ekf-bias``, the
biases' prior the radio's stated spread) is run twice along the true trajectory: with the
biases as states (``bound-bias``) and with them known (``bound-given``, the biases' prior
block zero). Two input models:

* ``model``: the filters' own (:func:`extended_model`: the held-input dynamics and input noise
  of ``ekf-bias``, which stands the accelerometer's constant bias in as white noise, and so
  over-states the flight's input errors: not a bound of these flights);
* ``imu``: the flight's own input errors to first order (:func:`imu_model`: the
  accelerometer's bias as states, its noise and the attitude error as white noise).

and two sets of ranges:

* ``los``: the line-of-sight ranges only, each with the stated noise ``1 / sigma^2``;
* ``oracle``: those and the blocked ranges too, each with the Fisher information of a range
  whose log-normal excess (the radio's stated median and shape) is known to be there
  (:func:`~quadobs.evaluation.range_bias_bound.excess_fisher_information`): more than any
  estimator that is not told which paths are blocked can draw from them, so a lower bound.

Both count every range drawn at the stated noise, outliers included (information over-stated:
still a lower bound). The ratio ``bound-bias / bound-given`` of the position RMSEs after the
burn-in is the least factor by which the unknown biases raise an efficient online estimator's
error. The filters given the true biases are not efficient (their error is several times the
bound's): ``floor`` is the RMSE ``ekf-bias-given`` would have if the unknown biases cost it
what they cost the bound, ``sqrt(G^2 + B_bias^2 - B_given^2)`` (for the optimal estimators
the two errors add so: the estimate given the biases is that without them plus an orthogonal
correction), not itself a bound, and with no footing for a filter that is not efficient. The
bound holds for the error averaged over the noise and the biases' draws, not one flight's: the
summary sets it against each filter given the biases as root mean squares over the seeds.

Printed per seed (one JSON line) and, at the end, the medians and means over the seeds.

Usage::

    python sims/uwb_online_bound.py --seeds 0:30 [--duration 40] [--burn-in 5]
        [--estimators ekf-bias,ukf-bias]
    # the summary of lines printed before
    python sims/uwb_online_bound.py --summary rows.jsonl [--estimators ekf-bias]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from uwb_realistic import drawn_events, given_bias_filter

from quadobs.errors import run_script
from quadobs.evaluation.range_bias_bound import (
    excess_fisher_information,
    range_bias_crb,
    rmse_bound,
)
from quadobs.testbed.episode import _summarise, run_loop, scenario_parts
from quadobs.testbed.factories import _range_sigma, bias_filter_models
from quadobs.testbed.scenario import load_scenario

EVERY = 10  # the trace's period in physics steps (collect_every)
#: the bounds: the input's model (the filters' own, or the flight's IMU errors) and the ranges
VARIANTS = ("model-los", "model-oracle", "imu-los", "imu-oracle")


def extended_model(scenario):
    """``(F, Q, P0)`` of the bias filters' extended state, as ``ekf-bias`` builds them."""
    dyn, _, Pe = bias_filter_models(scenario)
    return dyn.F, dyn.Q, Pe


def imu_model(scenario):
    """``(F, Q, P0)`` of the flight's own input errors, to first order: the state
    ``(p, v, b_a, b)`` with the accelerometer's constant bias ``b_a`` (prior ``accel_bias`` per
    axis; the body frame taken as the world's, the flight's tilt being small) and white noise
    of intensity (m^2/s^3) ``sigma_a^2 dt`` along the thrust and ``(sigma_a^2 + m (g sigma_q)^2) dt``
    across it (the attitude error held over ``m`` steps, :func:`~quadobs.testbed.imu.input_noise_std`),
    exact over a step: ``v' = u - b_a + w`` gives ``F = [[I, dt I, -dt^2/2 I], [0, I, -dt I],
    [0, 0, I]]`` and ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis on ``(p, v)``."""
    spec, dt, q_b = scenario.quadrotor, scenario.dt, scenario.beacons.shape[0]
    m = scenario.sample_interval(spec.attitude_rate, "attitude_rate", table="quadrotor")
    across = spec.accel_std**2 + m * (9.81 * spec.attitude_std) ** 2
    white = np.array([across, across, spec.accel_std**2]) * dt
    I3, n = np.eye(3), 9 + q_b
    F = np.eye(n)
    F[0:3, 3:6], F[0:3, 6:9], F[3:6, 6:9] = dt * I3, -0.5 * dt * dt * I3, -dt * I3
    Q = np.zeros((n, n))
    Q[0:3, 0:3] = np.diag(white) * dt**3 / 3.0
    Q[0:3, 3:6] = Q[3:6, 0:3] = np.diag(white) * dt**2 / 2.0
    Q[3:6, 3:6] = np.diag(white) * dt
    _, _, Pe = extended_model(scenario)
    P0 = np.zeros((n, n))
    P0[:6, :6] = Pe[:6, :6]
    P0[6:9, 6:9] = spec.accel_bias**2 * I3
    P0[9:, 9:] = Pe[6:, 6:]
    return F, Q, P0


def ranges_of(events: dict, dt: float):
    """The drawn ranges as arrays: step, anchor, true position, blocked."""
    rows = sorted(events.values(), key=lambda e: e[0].t)
    step = np.array([int(math.floor(m.t / dt + 1e-9)) for m, _, _ in rows])
    anchor = np.array([m.anchors[0] for m, _, _ in rows])
    position = np.array([p for _, p, _ in rows])
    blocked = np.array([b for _, _, b in rows], dtype=bool)
    return step, anchor, position, blocked


def bounds(scenario, events: dict, burn_in: float) -> dict:
    """The two bounds' position RMSEs after ``burn_in`` on each set of ranges (module docstring),
    and the bound's largest bias standard deviation at the end."""
    q = scenario.beacons.shape[0]
    step, anchor, position, blocked = ranges_of(events, scenario.dt)
    keep_steps = step < scenario.steps
    step, anchor, position, blocked = (a[keep_steps] for a in (step, anchor, position, blocked))
    sigma, radio = _range_sigma(scenario), scenario.radio
    w_los = 1.0 / sigma**2
    w_nlos = (
        excess_fisher_information(sigma, radio.nlos_median, radio.nlos_shape)
        if radio.nlos_median > 0
        else w_los
    )
    times = np.arange(scenario.steps // EVERY + 1) * EVERY * scenario.dt
    keep = times >= burn_in
    out: dict = {"nlos_fraction": float(blocked.mean()), "w_nlos": w_nlos}
    for model, (F, Q, Pe) in (("model", extended_model(scenario)), ("imu", imu_model(scenario))):
        known = Pe.copy()
        known[-q:, :] = 0.0
        known[:, -q:] = 0.0
        for ranges, w_blocked in (("los", 0.0), ("oracle", w_nlos)):
            info = np.where(blocked, w_blocked, w_los)
            row = {}
            for label, P0 in (("bound-bias", Pe), ("bound-given", known)):
                B = range_bias_crb(
                    F,
                    Q,
                    P0,
                    scenario.steps,
                    scenario.beacons,
                    step,
                    anchor,
                    position,
                    info,
                    every=EVERY,
                )
                row[label] = rmse_bound(B, scenario.dimension, keep)
                if label == "bound-bias":
                    row["bias_std_end"] = float(np.sqrt(np.max(np.diag(B[-1])[-q:])))
            row["ratio"] = row["bound-bias"] / row["bound-given"]
            out[f"{model}-{ranges}"] = row
    return out


def one_seed(seed: int, duration: float | None, names: list[str], burn_in: float) -> dict:
    over = {"seed": seed} | ({"duration": duration} if duration else {})
    scenario = load_scenario("quadrotor-uwb-realistic", **over)
    parts = scenario_parts(scenario, names)
    world = parts["world"]
    x0 = parts["estimators"][0].x_hat
    all_names = list(names)
    for kind in ("ekf", "ukf"):
        if f"{kind}-bias" in names:
            parts["estimators"] = [
                *parts["estimators"],
                given_bias_filter(scenario, world, x0, kind),
            ]
            all_names.append(f"{kind}-bias-given")
    events = drawn_events(world.radio)

    def summarise(merged, completed, wall, interrupted):
        return _summarise(
            scenario, all_names, merged, completed, wall, parts["sensors"], None, interrupted
        )

    _, episode = run_loop(summarise, collect_every=EVERY, **parts)
    trace = episode.trace.trace
    t = np.asarray(trace["time"])
    truth = np.asarray(trace["truth"])[:, :3]
    keep = (t >= burn_in) & np.isfinite(t)
    out: dict = {"seed": seed}
    for name in all_names:
        err = np.linalg.norm(np.asarray(trace["estimates"][name])[:, :3] - truth, axis=1)
        out[name] = float(np.sqrt(np.mean(err[keep] ** 2)))
    for est in parts["estimators"]:
        if est.name in names and hasattr(est, "biases"):
            bias_error = np.asarray(est.biases) - np.asarray(world.radio.biases)
            out[est.name + "_bias_error_end"] = float(np.max(np.abs(bias_error)))
    out |= bounds(scenario, events, burn_in)
    for name in names:
        given = out.get(f"{name}-given")
        if given:
            out[f"ratio_{name}"] = out[name] / given
            for s in VARIANTS:
                extra = out[s]["bound-bias"] ** 2 - out[s]["bound-given"] ** 2
                out[s][f"floor_{name}"] = math.sqrt(given**2 + extra) / given
    return out


def summary(rows: list[dict], names: list[str]) -> list[str]:
    """Median, mean and the seeds above 1.2 of each ratio over the seeds; the bound with the
    biases against the filter given them, both as root mean squares over the seeds."""

    def line(label: str, values: list[float]) -> str:
        v = np.array(values)
        return (
            f"{label}: median {np.median(v):.3f}, mean {np.mean(v):.3f}, "
            f"range {v.min():.3f} .. {v.max():.3f}, above 1.2 on {int(np.sum(v > 1.2))} / {len(v)}"
        )

    out = []
    for s in VARIANTS:
        out.append(line(f"bound ratio ({s})", [r[s]["ratio"] for r in rows]))
        for label in ("bound-bias", "bound-given"):
            v = np.array([r[s][label] for r in rows])
            out.append(f"{label} ({s}): median {np.median(v):.4f} m, mean {np.mean(v):.4f} m")
    for name in names:
        if f"ratio_{name}" not in rows[0]:
            continue
        out.append(line(f"{name} / {name}-given", [r[f"ratio_{name}"] for r in rows]))
        for s in VARIANTS:
            out.append(line(f"floor of {name} ({s})", [r[s][f"floor_{name}"] for r in rows]))
            # the bound holds for the error averaged over the draws (noise and biases), not on
            # one flight: set against the filter given the biases averaged over the same flights
            bound = math.sqrt(np.mean([r[s]["bound-bias"] ** 2 for r in rows]))
            given = math.sqrt(np.mean([r[f"{name}-given"] ** 2 for r in rows]))
            out.append(
                f"bound-bias ({s}), rms over the seeds: {bound:.4f} m against 1.2 x "
                f"{name}-given's rms {1.2 * given:.4f} m (ratio {bound / given:.3f})"
            )
            for label, of in ((name, "bound-bias"), (f"{name}-given", "bound-given")):
                out.append(line(f"{label} / {of} ({s})", [r[label] / r[s][of] for r in rows]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0:10", help="first:last (exclusive)")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--burn-in", type=float, default=5.0, help="s left out of the RMSE")
    ap.add_argument("--estimators", default="ekf-bias")
    ap.add_argument(
        "--summary",
        default=None,
        help="a file of this script's JSON lines: print their summary only (no flight)",
    )
    args = ap.parse_args()
    names = args.estimators.split(",")
    if args.summary:
        with open(args.summary) as f:
            rows = [json.loads(line) for line in f if line.startswith("{")]
        print("\n".join(summary(rows, names)))
        return
    a, b = (int(v) for v in args.seeds.split(":"))
    rows = []
    for seed in range(a, b):
        rows.append(one_seed(seed, args.duration, names, args.burn_in))
        print(json.dumps(rows[-1]), flush=True)
    for text in summary(rows, names):
        print(text)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
