"""quadrotor-uwb-realistic: what a flight's data say about the range biases.

The target "the bias filter within 1.2x of the same filter given the true biases" asks how
much worse any estimator must be for not knowing the biases. The flight answers it offline:
for each seed the scenario is flown once (on the truth), every input and range the
estimators receive is recorded, and then

* ``batch-bias``: the GTSAM peer's factor graph of the whole flight
  (:class:`~quadobs.estimators.gtsam_peer.Isam2Peer`, the world-frame acceleration as its
  input, ``accel_nav``) with one constant bias per anchor as a variable
  (``PeerNoise(bias="state")``, prior the radio's stated spread), solved by
  Levenberg-Marquardt over the whole flight (the graph built without iSAM2,
  ``online=False``, and solved from ``ekf-bias``'s own trajectory and final biases);
* ``batch-given``: the same graph given the true biases (``fixed_bias``);
* ``ekf-bias``, ``ekf-bias-given`` (its bias states pinned at the truth), and
  ``ekf-bias-at-batch``: the same filter with its bias states pinned at ``batch-bias``'s
  biases, the best the flight's own data (all of it, the future included) can tell it.
  Each is the recorded flight replayed into the filter (the same calls in the same order as
  in the flight; ``ekf-bias-given`` replayed so matches :mod:`uwb_realistic`'s).

The peer's noise is the filters' own: the stated range noise, the input noise's intensity
``q = sigma_u^2 dt`` (:func:`~quadobs.testbed.imu.input_noise_std`), the biases' prior the
radio's ``bias_std``; its loss is ``--loss`` (Huber at 3 standard deviations by default, the
peer's default). With ``--online`` the batches are left out and the peer runs online
instead: ``isam2-bias`` (iSAM2 with the biases as variables) and ``isam2-given`` (given the
true biases), the recorded flight replayed into each and its estimate read as the filters'
(iSAM2's estimate of the last node propagated by the held input), beside ``ekf-bias-given``.
``--key-period`` lets the ranges within that time after a node share it (each on the
node's position and velocity at its own time, ``p + v tau``: an error of the acceleration's
``a tau^2 / 2``), for fewer nodes: the cost of a solution grows faster than the nodes
(gtsam's elimination, docs/peer.md).

Printed per seed (one JSON line): each estimator's position RMSE after a 5 s burn-in over
the same times as :mod:`uwb_realistic` (every tenth physics step), and the biases' errors.
With ``--line-of-sight`` (a diagnostic no estimator can have) both batches are solved again
(``batch-bias-los``, ``batch-given-los``; ``ekf-bias-at-batch-los``) given only the ranges whose path the room left clear (the radio's own ray test when it drew the range,
:func:`uwb_realistic.drawn_events`): the biases as the line-of-sight ranges of the whole
flight tell them, the excess set aside by an oracle. ``--set radio.nlos_median=0`` flies the same seeds with no non-line-of-sight excess (the
other draws unchanged: the radio's streams are separate; the filters then take the
scenario's one-sided gate).

Usage::

    python sims/uwb_bias_bound.py --seeds 0:10 [--duration 40] [--loss huber|cauchy|none]
        [--set radio.nlos_median=0] [--line-of-sight] [--burn-in 5] [--key-period 0.02]
        [--online]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from uwb_realistic import drawn_events

from quadobs.errors import run_script
from quadobs.estimators.gtsam_peer import Isam2Peer, PeerNoise
from quadobs.testbed.episode import _summarise, run_loop, scenario_parts
from quadobs.testbed.factories import (
    _input_std,
    _range_sigma,
    bias_prior_std,
    biased_extended_kalman_filter,
    initial_covariance,
)
from quadobs.testbed.scenario import load_scenario


def recorded(est, calls: list):
    """``est`` with every ``hold``, ``predict`` and ``correct`` it receives appended to ``calls``."""
    hold, predict, correct = est.hold, est.predict, est.correct

    def hold_kept(u):
        calls.append(("hold", np.array(u, dtype=float)))
        hold(u)

    def predict_kept(t):
        calls.append(("predict", float(t)))
        predict(t)

    def correct_kept(m):
        calls.append(("correct", m))
        correct(m)

    est.hold, est.predict, est.correct = hold_kept, predict_kept, correct_kept
    return est


def replay(est, calls: list, times: np.ndarray) -> np.ndarray:
    """The position estimates ``(len(times), 3)`` of ``est`` given ``calls`` in order, read at
    each step's start (before its ``hold``, as the episode's trace), at ``times``."""
    t_read, x_read = [], []
    for kind, arg in calls:
        if kind == "hold":
            t_read.append(est.time)
            x_read.append(est.x_hat[:3].copy())
        getattr(est, kind)(arg)
    return at_times(np.array(t_read), np.array(x_read), times)


def at_times(t: np.ndarray, x: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``x`` (rows at the increasing ``t``) at ``times``, linearly interpolated."""
    return np.column_stack([np.interp(times, t, x[:, c]) for c in range(x.shape[1])])


def pinned(est, biases: np.ndarray, name: str):
    """``est`` (a bias-state filter) with its bias states pinned at ``biases``."""
    k = est.vehicle_n
    est._x[k:] = biases
    est._P[k:, :] = 0.0
    est._P[:, k:] = 0.0
    est._P0 = est._P.copy()
    est._bias_prior = np.array(biases, dtype=float)
    est.name = name
    return est


def make_peer(scenario, x0, loss: str, fixed_bias=None, key_period: float = 0.0, online=False):
    """The GTSAM peer with the filters' own noise (module docstring): biases as states, or
    given (``fixed_bias``); ``online=False`` builds the graph only."""
    P0, _ = initial_covariance(scenario)
    noise = PeerNoise(
        range_sigma=_range_sigma(scenario),
        loss=loss,
        bias="none" if fixed_bias is not None else "state",
        bias_sigma=bias_prior_std(scenario) or 0.5,
        q_imu=_input_std(scenario) ** 2 * scenario.dt,
        velocity_sigma=math.sqrt(float(np.asarray(P0)[3, 3])),
        key_period=key_period,
    )
    return Isam2Peer(
        scenario.beacons,
        "accel_nav",
        x0=x0,
        P0=float(np.asarray(P0)[0, 0]),
        noise=noise,
        fixed_bias=fixed_bias,
        online=online,
    )


def batch(scenario, calls, x0, loss: str, start, fixed_bias=None, key_period: float = 0.0):
    """The peer's graph of the recorded flight solved by Levenberg-Marquardt: the nodes'
    times and positions and the biases (the variables', or ``fixed_bias``).

    The graph is built without iSAM2 (``online=False``) and solved from ``start``: a
    function of the nodes' times giving the positions and velocities ``(m, 6)``, and the
    biases ``(q,)`` (the online filter's, no truth)."""
    peer = make_peer(scenario, x0, loss, fixed_bias, key_period)
    for kind, arg in calls:
        getattr(peer, kind)(arg)
    peer._flush()
    import gtsam

    states, biases = start(np.array(peer.node_times))
    values, motion = peer.values, peer.motion
    for i, x in enumerate(states):
        values.update(motion.position_key(i), x[:3])
        values.update(motion.velocity_key(i), x[3:6])
    if fixed_bias is None:
        for h, b in enumerate(biases):
            values.update(peer._bias_key(h), np.array([b]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    solved = gtsam.LevenbergMarquardtOptimizer(peer.graph, values, params).optimize()
    times, positions = peer._positions(solved)
    if fixed_bias is not None:
        return times, positions, np.asarray(fixed_bias, dtype=float)
    b = np.array([solved.atVector(peer._bias_key(h))[0] for h in range(len(scenario.beacons))])
    return times, positions, b


def one_seed(
    seed: int,
    duration: float | None,
    loss: str,
    settings: list[str],
    los: bool = False,
    burn_in: float = 5.0,
    key_period: float = 0.0,
    peer_online: bool = False,
) -> dict:
    over = {"seed": seed} | ({"duration": duration} if duration else {})
    scenario = load_scenario("quadrotor-uwb-realistic", settings=settings, **over)
    parts = scenario_parts(scenario, ["ekf-bias"])
    world = parts["world"]
    (est,) = parts["estimators"]
    x0 = est.x_hat[: est.vehicle_n].copy()
    calls: list = []
    recorded(est, calls)
    events = drawn_events(world.radio)

    def summarise(merged, completed, wall, interrupted):
        return _summarise(
            scenario, ["ekf-bias"], merged, completed, wall, parts["sensors"], None, interrupted
        )

    _, episode = run_loop(summarise, collect_every=10, **parts)
    trace = episode.trace.trace
    t = np.asarray(trace["time"])
    truth = np.asarray(trace["truth"])[:, :3]
    keep = (t >= burn_in) & np.isfinite(t)
    b_true = np.asarray(world.radio.biases, dtype=float)
    online = np.asarray(trace["estimates"]["ekf-bias"])[:, :6]
    ok = np.isfinite(t) & np.all(np.isfinite(online), axis=1)
    b_online = np.asarray(est.biases, dtype=float)

    def start(times: np.ndarray):
        return at_times(t[ok], online[ok], times), b_online

    def rmse(est_xyz: np.ndarray) -> float:
        err = np.linalg.norm(est_xyz[keep] - truth[keep], axis=1)
        return float(np.sqrt(np.mean(err**2)))

    out: dict = {"seed": seed, "biases": b_true.round(4).tolist()}
    out["ekf-bias"] = {"rmse": rmse(np.asarray(trace["estimates"]["ekf-bias"])[:, :3])}
    if peer_online:
        out |= online_peers(scenario, calls, x0, loss, b_true, key_period, t, rmse)
        out["ratio_ekf"] = out["ekf-bias"]["rmse"] / out["ekf-bias-given"]["rmse"]
        return out
    sources = {"": calls}
    if los:
        sources["-los"] = [c for c in calls if c[0] != "correct" or not events[id(c[1])][2]]
    filters = {"ekf-bias-given": b_true}
    for suffix, given in sources.items():
        for name, fixed in (("batch-bias", None), ("batch-given", b_true)):
            T, P, b = batch(scenario, given, x0, loss, start, fixed, key_period)
            out[name + suffix] = {"rmse": rmse(at_times(T, P, t))}
            if fixed is None:
                out[name + suffix]["bias_error"] = (b - b_true).round(4).tolist()
                filters["ekf-bias-at-batch" + suffix] = b
        ratio = out["batch-bias" + suffix]["rmse"] / out["batch-given" + suffix]["rmse"]
        out["ratio_batch" + suffix] = ratio
    for name, b in filters.items():
        filt = pinned(biased_extended_kalman_filter(scenario, x0), b, name)
        out[name] = {"rmse": rmse(replay(filt, calls, t))}
    given = out["ekf-bias-given"]["rmse"]
    out["ratio_ekf"] = out["ekf-bias"]["rmse"] / given
    for suffix in sources:
        out["ratio_ekf_at_batch" + suffix] = out["ekf-bias-at-batch" + suffix]["rmse"] / given
    return out


def online_peers(scenario, calls, x0, loss, b_true, key_period, times, rmse) -> dict:
    """``isam2-bias`` (the peer online, biases as states) and ``isam2-given`` (given the true
    biases), each the recorded flight replayed into iSAM2 and its estimate read as the
    filters' are (:func:`replay`); ``ekf-bias-given`` beside them, and the ratios of each to
    itself given the biases. Each has its wall-clock time (s)."""
    import time

    out: dict = {}
    for name, fixed in (("isam2-bias", None), ("isam2-given", b_true)):
        start = time.perf_counter()
        est = make_peer(scenario, x0, loss, fixed, key_period, online=True)
        out[name] = {"rmse": rmse(replay(est, calls, times))}
        out[name]["wall_s"] = round(time.perf_counter() - start, 1)
        out[name]["failure"] = est.failure
        if fixed is None:
            out[name]["bias_error"] = (est.biases - b_true).round(4).tolist()
    filt = pinned(biased_extended_kalman_filter(scenario, x0), b_true, "ekf-bias-given")
    out["ekf-bias-given"] = {"rmse": rmse(replay(filt, calls, times))}
    out["ratio_isam2"] = out["isam2-bias"]["rmse"] / out["isam2-given"]["rmse"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0:10", help="first:last (exclusive)")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--loss", choices=("huber", "cauchy", "none"), default="huber")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        help="a scenario setting by dotted path, e.g. radio.nlos_median=0",
    )
    ap.add_argument(
        "--line-of-sight",
        action="store_true",
        help="the batches given only the ranges the room left clear (a diagnostic)",
    )
    ap.add_argument("--burn-in", type=float, default=5.0, help="s left out of the RMSE")
    ap.add_argument(
        "--key-period",
        type=float,
        default=0.0,
        help="the peer's key_period (s): ranges within it after a node share the node",
    )
    ap.add_argument(
        "--online",
        action="store_true",
        help="instead of the batches, the peer online (iSAM2), biases as states and given",
    )
    args = ap.parse_args()
    a, b = (int(v) for v in args.seeds.split(":"))
    for seed in range(a, b):
        row = one_seed(
            seed,
            args.duration,
            args.loss,
            args.set,
            args.line_of_sight,
            args.burn_in,
            args.key_period,
            args.online,
        )
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
