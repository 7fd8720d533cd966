"""A flight filter's bias states and excess chains traced against the truth of a stressed flight.

The flight's stress logs (``sims/stress_hidden_logs.py flight``) are the stand-in ``real``
with one stress; the simulation knows each anchor's true range bias ``b_h`` (the radio's drawn
bias plus the one ``real`` adds) and which ranges carry an excess (the room blocks the
anchor-to-tag segment at the truth's position, ``mj_ray`` as the radio decides it, or ``real``
lengthened the range). This script rebuilds that truth for one seed and stress, prints per
anchor

* ``b_h``, the share of its ranges with an excess, and the median of ``rho - d - b_h`` over
  its clear ranges (the radio's noise: near 0, a check of the truth), beside the median of
  ``rho - d`` over all its ranges (not the bias where an anchor is mostly blocked);
* the filter's bias state (its estimate plus the calibration's bias where the replay
  subtracted one) and its chain ``P(NLOS)`` averaged over ``--window``;

then the filter's position RMSE after the burn-in (``quadobs replay DIR --burn-in 5`` with
every other setting at its default) on the log as written and, with ``--oracle``, on the log
with each anchor's ``b_h`` subtracted from its ranges (the budget's ``range-bias`` oracle of
``sims/flight_error_budget.py``).

::

    python sims/trace_flight_bias_states.py --seed 0 --stress gap --window 14,18 --oracle
    python sims/trace_flight_bias_states.py --seed 1 --stress moving --window 11,40 --oracle
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np
import replay_flight_variants as flight
import stress_hidden_logs as stress

from quadobs.errors import run_script
from quadobs.testbed.logs import read_log, write_log
from quadobs.testbed.logs import replay as replay_module


def stressed_flight(seed: int, name: str, duration: float, tmp: Path) -> tuple[Path, dict]:
    """:func:`stress_hidden_logs.flight_log`'s folder and the draws of ``real``'s range
    errors: ``bias`` (q,) the added biases, ``nlos`` (M,) the rows it lengthened."""
    flight.RANGE_DRAWS.clear()
    folder = stress.flight_log(seed, name, duration, tmp)
    return folder, dict(flight.RANGE_DRAWS)


def flight_truth(log, seed: int, name: str, record: dict) -> dict:
    """Per range of ``log``: its anchor, true distance and excess flag; per anchor its bias."""
    from quadobs.testbed.scenario import load_scenario
    from quadobs.testbed.uwb import Room, radio_of, room_model_path

    settings = ["quadrotor.accel_bias=0.2", "quadrotor.gyro_bias=0.01", *stress.FLIGHT[name][0]]
    radio = radio_of(load_scenario("quadrotor-uwb-realistic", settings=settings, seed=seed))
    bias = np.asarray(radio.biases, dtype=float) + record["bias"]
    cols, t = log.truth_columns, log.ranges[:, 0]
    tt = log.truth[:, cols.index("time")]
    p = np.column_stack([np.interp(t, tt, log.truth[:, cols.index(c)]) for c in "xyz"])
    anchor = log.beacon_index(log.ranges[:, 1])
    room = Room(room_model_path())
    blocked = np.array([room.blocked(radio.anchors[h], p[k]) for k, h in enumerate(anchor)])
    return {
        "anchor": anchor,
        "distance": np.linalg.norm(p - radio.anchors[anchor], axis=1),
        "excess": blocked | record["nlos"],
        "covered": (t >= tt[0]) & (t <= tt[-1]),
        "bias": bias,
    }


class _Recorder:
    """The bias states, chains and position of the replay's estimator ``name`` after each of
    its corrections (its methods wrapped on the instance the replay builds)."""

    def __init__(self, name: str):
        self.name, self.rows, self.onsets = name, [], None
        self._build = replay_module.build_replay_estimators

    def __enter__(self):
        def build(setup, names, x0):
            built = self._build(setup, names, x0)
            for e in built:
                if e.name == self.name:
                    self.rows = []  # the replay's own build (a calibration's comes before)
                    self.onsets = getattr(e, "onsets", None)
                    self._wrap(e)
            return built

        replay_module.build_replay_estimators = build
        return self

    def __exit__(self, *exc):
        replay_module.build_replay_estimators = self._build

    def _wrap(self, e) -> None:
        for method in ("correct", "correct_many"):
            inner = getattr(e, method)

            def wrapped(m, inner=inner):
                inner(m)
                if getattr(e, "biases_open", False):
                    row = [e._time, *e._x[:3], *e.biases, *e._nlos]
                    self.rows.append(row)

            setattr(e, method, wrapped)


def _replay(folder: Path, name: str) -> tuple[dict, np.ndarray]:
    with _Recorder(name) as rec:
        summary = flight.replay(folder, name, stress.rover.BURN_IN)
    if rec.onsets:  # the Markov onset test's firings, where it is on
        print(f"onset test fired {len(rec.onsets)} times: {np.round(rec.onsets, 1)}")
    return summary, np.array(rec.rows)


def _report(log, truth: dict, summary: dict, rows: np.ndarray, window, name: str) -> None:
    q = truth["bias"].shape[0]
    resid = log.ranges[:, 2] - truth["distance"]
    calibration = summary.get("calibration", {}).get("biases")
    logged = name in summary.get("ranges_as_logged", [])
    offset = np.zeros(q) if calibration is None or logged else np.asarray(calibration)
    cols = log.truth_columns
    t0 = float(log.ranges[0, 0])
    inside = (rows[:, 0] - t0 >= window[0]) & (rows[:, 0] - t0 <= window[1])
    est = rows[inside, 4 : 4 + q].mean(axis=0) + offset
    chain = rows[inside, 4 + q :].mean(axis=0)
    tt = log.truth[:, cols.index("time")]
    p = np.column_stack(
        [np.interp(rows[inside, 0], tt, log.truth[:, cols.index(c)]) for c in "xyz"]
    )
    err = (rows[inside, 1:4] - p).mean(axis=0)
    print(
        f"{name} window {window[0]:g}-{window[1]:g} s of the log (ranges subtracted: "
        f"{'none' if logged or calibration is None else 'the calibration biases'})"
    )
    print("anchor  true b  excess share  clear rho-d-b  all rho-d  filter b  b error  chain")
    for h in range(q):
        a = (truth["anchor"] == h) & truth["covered"]
        clear = a & ~truth["excess"]
        print(
            f"{h:6d} {truth['bias'][h]:+7.3f} {truth['excess'][a].mean():13.2f} "
            f"{np.median(resid[clear] - truth['bias'][h]):+14.3f} {np.median(resid[a]):+10.3f} "
            f"{est[h]:+9.3f} {est[h] - truth['bias'][h]:+8.3f} {chain[h]:6.2f}"
        )  # fmt: skip
    print(f"mean position error over the window (x, y, z): {np.round(err, 3)} m")


def _rmse(summary: dict, name: str) -> float:
    e = summary["estimators"].get(name, {})
    return math.nan if e.get("diverged") else float(e.get("rmse", math.nan))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stress", default="gap", choices=tuple(stress.FLIGHT))
    ap.add_argument("--estimator", default="ekf-bias-imu-nlos")
    ap.add_argument("--window", default="14,18", help="s from the log's first range")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--oracle", action="store_true", help="also the log less the true biases")
    args = ap.parse_args()
    window = tuple(float(v) for v in args.window.split(","))
    with tempfile.TemporaryDirectory(prefix="trace-") as tmp:
        folder, record = stressed_flight(args.seed, args.stress, args.duration, Path(tmp))
        log = read_log(folder)
        truth = flight_truth(log, args.seed, args.stress, record)
        summary, rows = _replay(folder, args.estimator)
        _report(log, truth, summary, rows, window, args.estimator)
        print(f"{args.estimator} RMSE after the burn-in: {_rmse(summary, args.estimator):.3f} m")
        if args.oracle:
            ranges = log.ranges.copy()
            ranges[:, 2] = np.maximum(ranges[:, 2] - truth["bias"][truth["anchor"]], 0.0)
            oracle = folder.parent / f"{folder.name}-range-bias"
            write_log(dataclasses.replace(log, ranges=ranges), oracle)
            summary, rows = _replay(oracle, args.estimator)
            _report(read_log(oracle), {**truth, "bias": 0.0 * truth["bias"]}, summary, rows,
                    window, args.estimator)  # fmt: skip
            rmse = _rmse(summary, args.estimator)
            print(f"{args.estimator} RMSE, true biases subtracted: {rmse:.3f} m")


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
