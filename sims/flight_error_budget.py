"""What limits ``ekf-bias-imu`` on the stand-in flights: an error budget, one oracle at a time.

The flights of ``sims/replay_flight_variants.py`` (``quadrotor-uwb-realistic`` exported, made
into the variants ``real`` and ``bias``) carry several error sources at once. This script
replays ``ekf-bias-imu`` (the replay's defaults otherwise: ``quadobs replay DIR --burn-in 5``,
the self-calibration on) on each variant's log as it is (``none``), then on the same log with
one source taken away by an oracle that reads the simulation's truth, then with all of them:

* ``attitude``: ``attitude.csv`` written from the truth's attitude (on the IMU's clock and in
  its body axes), instead of the attitude the replay estimates from the IMU; the filter then
  takes its acceleration bias ``c`` as the accelerometer's slow drift
  (:func:`~quadobs.testbed.logs.imu_bias.acceleration_bias_walk`), as for any log with an
  attitude;
* ``attitude-walk``: the same attitude, ``c``'s random walk kept at the intensity the filter
  takes for an estimated attitude (``bias_std^2 k_P``): the attitude's error alone, the
  filter's tuning unchanged;
* ``range-bias``: each anchor's true range bias (the radio's drawn bias, plus the variant's
  added one) subtracted from its ranges;
* ``accel-bias``: the accelerometer's true constant bias (the IMU model's draw for the seed)
  subtracted from the body specific force;
* ``excess``: only line-of-sight ranges kept: a range is dropped where an obstacle of the
  room blocks the anchor-to-tag segment at the truth's position (``mj_ray``, as the radio
  decides it) or where the variant added a non-line-of-sight excess (the radio's own outliers,
  1 %, stay);
* ``excess-room``, ``excess-added``: the ranges that the room blocks dropped, or those the
  variant lengthened (its independent excess on a tenth of the ranges): which excess costs;
* ``clock``: the IMU's 20 ms lag behind the ranges removed (``real`` only: ``bias`` has none);
* ``anchors``, ``survey-varying`` (with ``--stress survey`` only): ``beacons.csv`` written
  from the radio's anchors (the survey's error taken away), or the ranges moved so that the
  surveyed anchors hold them up to a constant per anchor (each range's error from the survey,
  ``|p - a~_h| - |p - a_h|`` at the true position, less its mean over the anchor's ranges,
  added back): what the range-bias states could not take up of the survey's error;
* ``all``: ``attitude``, ``range-bias``, ``accel-bias``, ``excess`` and ``clock`` at once.

``--stress NAME`` first applies one stress of ``sims/stress_hidden_logs.py`` to the log (on
the log without attitude, before the variant's transforms, seeded as that script seeds it:
the same logs); with ``imuclock`` the oracles ``attitude`` and ``clock`` take the IMU's whole
lag (the variant's 20 ms and the stress's 50 ms; the jitter stays).

The table gives the position RMSE after the burn-in of ``ekf-bias-imu`` per flight and
oracle; the oracle that lowers it most names the source that costs most. Each flight's
first line checks the oracles of the ranges: the kept ranges less their true distance and
bias (centred on zero, the radio's noise), the dropped ones (long). ``--line-of-sight P``
replays the filter with its one-sided gate at ``P`` (a probe of the gate, not an oracle).

``--offset-scan`` asks what the ranges themselves say of a position offset: the true
trajectory moved by each horizontal offset of a grid (``OFFSET_STEP`` apart, up to
``OFFSET_SPAN``), its distances taken to the log's anchors (``beacons.csv``: as surveyed under
``--stress survey``, so that even clean ranges need not fit best at offset 0), each anchor's
bias refitted to the moved trajectory (its best value on a grid about the median residual),
the ranges' cost summed under three losses of the log's line-of-sight residuals' spread
``sigma``: Huber at ``1.5 sigma``, Cauchy of scale ``sigma``, the square truncated at
``3 sigma``. Ranges of 0 m are left out. Over all ranges, and over the line-of-sight ones
alone (unblocked, and none of the variant's added excess), it prints each loss's best offset
and its cost against the truth's (offset 0), and each anchor's share of blocked ranges: where
the least cost is away from the truth, the ranges do not pull an estimator that takes the
excess as symmetric noise (a robust loss, a gate) with a free bias per anchor to the truth.

    python sims/flight_error_budget.py --stress survey --real-seeds 0,2,3 --bias-seeds "" \
        --oracles none --offset-scan

    python sims/flight_error_budget.py --real-seeds 0,1,2,3,4 --bias-seeds 3,7,9 --out budget/
    python sims/flight_error_budget.py --stress survey --real-seeds 2,3 --bias-seeds "" \
        --oracles none,anchors,survey-varying,attitude,accel-bias,range-bias,excess
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np
import replay_flight_variants as flight
import stress_hidden_logs as stress

from quadobs.errors import run_script
from quadobs.testbed.logs import read_log, write_log

ORACLES = (
    "none",
    "attitude",
    "attitude-walk",
    "range-bias",
    "accel-bias",
    "excess",
    "excess-room",
    "excess-added",
    "clock",
    "anchors",
    "survey-varying",
    "all",
)
#: The oracles that take the survey's error away: ``--stress survey`` only.
SURVEY_ORACLES = ("anchors", "survey-varying")
#: The estimator whose budget is taken.
ESTIMATOR = "ekf-bias-imu"
#: The IMU's lag behind the ranges in the variant ``clock`` (s), as replay_flight_variants makes it.
CLOCK_LAG = 0.02
#: ``--offset-scan``: the grid's spacing and reach per horizontal axis (m), and the biases'
#: grid about each anchor's median residual (m).
OFFSET_STEP, OFFSET_SPAN = 0.02, 0.3
BIAS_GRID = np.linspace(-0.4, 0.4, 161)


@dataclasses.dataclass
class Flight:
    """One variant's log and what the simulation knew of it."""

    log: object  # the variant's RangeLog
    base: object  # the export's RangeLog (truth with attitude, on the ranges' clock)
    steps: tuple[str, ...]  # the variant's transforms
    range_bias: np.ndarray  # (q,) true bias per anchor (m)
    added_nlos: np.ndarray  # (M,) rows that the variant lengthened by an excess
    accel_bias: np.ndarray  # (3,) the accelerometer's bias, body axes of the export (m/s^2)
    anchors: np.ndarray  # (q, 3) the radio's anchor positions
    lag: float = 0.0  # the IMU's lag behind the ranges (s), the variant's and the stress's


def _variant(base, seed: int, kind: str, args) -> tuple:
    """The variant ``kind`` of the export ``base`` as replay_flight_variants makes it (with the
    stress ``args.stress`` as stress_hidden_logs applies it), and the draws of its range errors
    (``bias``: the added biases and which rows took an excess)."""
    flight.RANGE_DRAWS.clear()
    rng = np.random.default_rng([seed, flight.REAL.index(kind)])
    noatt = flight.variant(base, "noatt", args.yaw)
    name = getattr(args, "stress", "none")
    noatt = stress.FLIGHT[name][1](noatt, stress.stress_seed(seed, name))
    vib = (args.accel_vibration, args.gyro_vibration)
    log = flight.real_variant(noatt, kind, rng, *vib)
    record = dict(flight.RANGE_DRAWS)
    return log, record


def _truth_of_flight(base, seed: int, kind: str, args) -> Flight:
    """The variant's log and the truth behind its errors (the scenario rebuilt for ``seed``)."""
    from quadobs.testbed.imu import ImuModel
    from quadobs.testbed.scenario import load_scenario
    from quadobs.testbed.uwb import radio_of

    log, record = _variant(base, seed, kind, args)
    settings = [
        f"quadrotor.accel_bias={args.accel_bias:g}",
        f"quadrotor.gyro_bias={args.gyro_bias:g}",
    ]
    scenario = load_scenario("quadrotor-uwb-realistic", settings=settings, seed=seed)
    radio = radio_of(scenario)
    q = base.beacons.shape[0]
    added = record.get("bias", np.zeros(q))
    nlos = record.get("nlos", np.zeros(log.ranges.shape[0], dtype=bool))
    steps = flight.REAL_STEPS if kind == "real" else (kind,)
    lag = (CLOCK_LAG if "clock" in steps else 0.0) + (
        stress.IMU_LATE[0] if getattr(args, "stress", "none") == "imuclock" else 0.0
    )
    return Flight(
        log=log,
        base=base,
        steps=steps,
        range_bias=np.asarray(radio.biases, dtype=float) + added,
        added_nlos=nlos,
        accel_bias=ImuModel(scenario.quadrotor, seed).accel_bias.copy(),
        anchors=radio.anchors,
        lag=lag,
    )


def _clock_shifts(f: Flight) -> tuple[float, float]:
    """How far the variant moved the ranges' and the IMU's times from the export's (s): the
    variant ``clock``'s Unix epoch (a stress that cuts the log's start, ``moving``, moves no
    time), and the IMU's lag on top."""
    ranges = flight.EPOCH if "clock" in f.steps else 0.0
    return ranges, ranges + f.lag


def _true_attitude(f: Flight) -> np.ndarray:
    """``time, qw, qx, qy, qz`` from the truth, on the IMU's clock and in its body axes
    (forward-right-down: the body turned by pi about x, ``q (x) (0, 1, 0, 0)``)."""
    cols = f.base.truth_columns
    t = f.base.truth[:, cols.index("time")]
    q = f.base.truth[:, [cols.index(c) for c in ("qw", "qx", "qy", "qz")]]
    if "frd" in f.steps:
        w, x, y, z = q.T
        q = np.column_stack([-x, w, z, -y])
    return np.column_stack([t + _clock_shifts(f)[1], q])


def _truth_position(f: Flight, ranges: np.ndarray) -> np.ndarray:
    """The truth's position ``(M, 3)`` at the times of ``ranges`` (on the export's clock)."""
    cols = f.base.truth_columns
    tt = f.base.truth[:, cols.index("time")]
    t = ranges[:, 0] - _clock_shifts(f)[0]
    return np.column_stack([np.interp(t, tt, f.base.truth[:, cols.index(c)]) for c in "xyz"])


def _line_of_sight(f: Flight, ranges: np.ndarray) -> np.ndarray:
    """Rows of ``ranges`` with no excess: unblocked at the truth's position, none added."""
    return ~_blocked(f, ranges) & ~f.added_nlos


def _blocked(f: Flight, ranges: np.ndarray) -> np.ndarray:
    """Rows of ``ranges`` whose anchor-to-tag segment a geom of the room crosses at the
    truth's position (``mj_ray``, as the radio decides it)."""
    from quadobs.testbed.uwb import Room, room_model_path

    room = Room(room_model_path())
    p = _truth_position(f, ranges)
    anchor = f.log.beacon_index(ranges[:, 1])
    return np.array([room.blocked(f.anchors[h], p[k]) for k, h in enumerate(anchor)], dtype=bool)


def _survey_errors(f: Flight) -> np.ndarray:
    """Each range's error from the survey (m): ``|p - a~_h| - |p - a_h|`` at the truth's
    position, ``a~_h`` the anchor in ``beacons.csv``, ``a_h`` the radio's."""
    p = _truth_position(f, f.log.ranges)
    h = f.log.beacon_index(f.log.ranges[:, 1])
    return np.linalg.norm(p - f.log.beacons[h], axis=1) - np.linalg.norm(p - f.anchors[h], axis=1)


def _survey_varying(f: Flight, ranges: np.ndarray) -> np.ndarray:
    """``ranges`` plus the survey's error less its mean per anchor: the surveyed anchors then
    hold them up to a constant per anchor (oracle ``survey-varying``)."""
    e = _survey_errors(f)
    h = f.log.beacon_index(f.log.ranges[:, 1])
    q = f.anchors.shape[0]
    mean = np.bincount(h, e, q) / np.maximum(np.bincount(h, minlength=q), 1)
    out = ranges.copy()
    held = out[:, 2] > 0.0  # a range of 0 m (a failed exchange) stays out of the replay
    out[held, 2] = np.maximum(out[held, 2] + (e - mean[h])[held], 1e-3)
    return out


def range_residuals(f: Flight) -> tuple[np.ndarray, np.ndarray]:
    """Each range of the variant less its true distance and its anchor's true bias (m), and
    whether :func:`_line_of_sight` keeps it: the check of the oracles ``range-bias`` and
    ``excess`` (the kept ones centred on zero with the radio's noise, the others long)."""
    p = _truth_position(f, f.log.ranges)
    anchor = f.log.beacon_index(f.log.ranges[:, 1])
    distance = np.linalg.norm(p - f.anchors[anchor], axis=1)
    residual = f.log.ranges[:, 2] - distance - f.range_bias[anchor]
    return residual, _line_of_sight(f, f.log.ranges)


def _losses() -> dict:
    """``--offset-scan``'s losses, as functions of a residual over ``sigma``."""
    return {
        "huber": lambda z: np.where(np.abs(z) < 1.5, z * z, 3.0 * np.abs(z) - 2.25),
        "cauchy": lambda z: np.log1p(z * z),
        "truncated": lambda z: np.minimum(z * z, 9.0),
    }


def _fit_cost(r: np.ndarray, masks: list, loss, sigma: float) -> float:
    """The ranges' cost with each anchor's bias at its best (:data:`BIAS_GRID` about the
    anchor's median residual): ``sum_h min_b sum_i loss((r_i - b) / sigma)``, ``masks`` each
    anchor's rows."""
    total = 0.0
    for rows in masks:
        rj = r[rows]
        if rj.size:
            b = np.median(rj) + BIAS_GRID
            total += float(loss((rj[:, None] - b[None, :]) / sigma).sum(axis=0).min())
    return total


def _scan_costs(f: Flight, p: np.ndarray, h: np.ndarray, rows, sigma: float) -> dict:
    """``{loss: {(dx, dy): cost}}``: the ranges ``rows`` against the truth ``p`` moved by each
    offset of the grid (exactly 0 at its centre)."""
    n = round(OFFSET_SPAN / OFFSET_STEP)
    axis = OFFSET_STEP * np.arange(-n, n + 1)
    rho, at, hr = f.log.ranges[rows, 2], p[rows], h[rows]
    anchors = f.log.beacons[hr]
    masks = [hr == j for j in range(f.log.beacons.shape[0])]
    losses = _losses()
    costs: dict = {name: {} for name in losses}
    for dx in axis:
        for dy in axis:
            r = rho - np.linalg.norm(at + [dx, dy, 0.0] - anchors, axis=1)
            for name, loss in losses.items():
                costs[name][dx, dy] = _fit_cost(r, masks, loss, sigma)
    return costs


def offset_scan(f: Flight, sigma: float) -> list[str]:
    """``--offset-scan`` (module docstring): lines of text."""
    p = _truth_position(f, f.log.ranges)
    h, q = f.log.beacon_index(f.log.ranges[:, 1]), f.log.beacons.shape[0]
    held = f.log.ranges[:, 2] > 0.0  # a range of 0 m (a failed exchange) left out
    blocked = _blocked(f, f.log.ranges)
    share = [float(blocked[held & (h == j)].mean()) for j in range(q) if np.any(h == j)]
    lines = ["blocked share per anchor: " + ", ".join(f"{s:.2f}" for s in share)]
    clear = ~blocked & ~f.added_nlos  # as _line_of_sight
    for what, rows in (("all ranges", held), ("line of sight", held & clear)):
        for name, cost in _scan_costs(f, p, h, rows, sigma).items():
            best = min(cost, key=cost.get)
            edge = max(abs(best[0]), abs(best[1])) >= OFFSET_SPAN - 1e-9
            lines.append(
                f"{what}, {name}: least cost at offset ({best[0]:+.2f}, {best[1]:+.2f}) m"
                f"{' (the grid edge)' if edge else ''}, {cost[best]:.1f} against "
                f"{cost[0.0, 0.0]:.1f} at the truth"
            )
    return lines


def with_oracle(f: Flight, oracle: str):
    """The variant's log with the error source ``oracle`` taken away (module docstring)."""
    log = f.log
    wanted = (
        {"attitude", "range-bias", "accel-bias", "excess", "clock"} if oracle == "all" else {oracle}
    )
    if wanted & {"attitude", "attitude-walk"}:
        log = dataclasses.replace(log, attitude=_true_attitude(f))
    if "range-bias" in wanted:
        ranges = log.ranges.copy()
        ranges[:, 2] -= f.range_bias[log.beacon_index(ranges[:, 1])]
        ranges[:, 2] = np.maximum(ranges[:, 2], 0.0)  # a distance (0 m: left out by the replay)
        log = dataclasses.replace(log, ranges=ranges)
    if "accel-bias" in wanted:
        imu = log.inputs.copy()
        sign = np.array([1.0, -1.0, -1.0]) if "frd" in f.steps else np.ones(3)
        imu[:, 1:4] -= sign * f.accel_bias
        log = dataclasses.replace(log, inputs=imu)
    if "clock" in wanted and f.lag:
        imu = log.inputs.copy()
        imu[:, 0] -= f.lag
        log = dataclasses.replace(log, inputs=imu)
    if "anchors" in wanted:
        log = dataclasses.replace(log, beacons=f.anchors.copy())
    if "survey-varying" in wanted:
        log = dataclasses.replace(log, ranges=_survey_varying(f, log.ranges))
    drop = {
        "excess": lambda: ~_line_of_sight(f, log.ranges),
        "excess-room": lambda: _blocked(f, log.ranges),
        "excess-added": lambda: f.added_nlos,
    }
    for name in wanted & set(drop):
        keep = ~drop[name]()
        log = dataclasses.replace(log, ranges=log.ranges[keep], range_std=log.range_std[keep])
    return log


def _replay(
    folder: Path, oracle: str, burn_in: float, reuse: bool, line_of_sight: float | None
) -> float | None:
    """``ekf-bias-imu``'s RMSE after ``burn_in`` on the log in ``folder`` (``attitude-walk``:
    its acceleration bias's walk kept at the estimated attitude's; ``line_of_sight``: its
    one-sided gate's probability, :class:`~quadobs.estimators.robust.SkewedGate`, instead of
    the default)."""
    from bias_filter_options import line_of_sight as gate_at

    from quadobs.testbed.logs import imu_bias

    walk = imu_bias.acceleration_bias_walk
    if oracle == "attitude-walk":

        def as_estimated(bias_std, estimated_attitude, drift_time):
            return walk(bias_std, True, drift_time)

        imu_bias.acceleration_bias_walk = as_estimated
    gate = contextlib.nullcontext() if line_of_sight is None else gate_at(line_of_sight)
    try:
        with gate:
            s = flight.replay(folder, ESTIMATOR, burn_in, reuse)
    finally:
        imu_bias.acceleration_bias_walk = walk
    e = s["estimators"].get(ESTIMATOR, {})
    return e.get("rmse") if not e.get("diverged") else math.nan


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--real-seeds", default="0,1,2,3,4", help="seeds of the variant real")
    ap.add_argument("--bias-seeds", default="3,7,9", help="seeds of the variant bias")
    ap.add_argument("--oracles", default=",".join(ORACLES))
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--accel-bias", type=float, default=0.2, help="m/s^2 per axis (std)")
    ap.add_argument("--gyro-bias", type=float, default=0.01, help="rad/s per axis (std)")
    ap.add_argument("--accel-vibration", type=float, default=1.0, help="m/s^2 per sample")
    ap.add_argument("--gyro-vibration", type=float, default=0.05, help="rad/s per sample")
    ap.add_argument("--burn-in", type=float, default=5.0)
    ap.add_argument(
        "--stress", default="none", choices=tuple(stress.FLIGHT), help="stress_hidden_logs' flight"
    )
    ap.add_argument("--out", help="folder for the logs and summaries (default: a temporary one)")
    ap.add_argument("--reuse", action="store_true", help="take the summaries a previous run left")
    ap.add_argument(
        "--line-of-sight",
        type=float,
        default=None,
        help="the one-sided gate's probability (default: the filter's, 0.95)",
    )
    ap.add_argument(
        "--offset-scan",
        action="store_true",
        help="the ranges' cost of the truth moved by a horizontal offset (module docstring)",
    )
    args = ap.parse_args()
    args.yaw = 1.0  # unused by real and bias
    oracles = args.oracles.split(",")
    unknown = set(oracles) - set(ORACLES)
    if unknown:
        ap.error(f"--oracles: unknown {', '.join(sorted(unknown))}")
    if args.stress != "survey" and set(oracles) & set(SURVEY_ORACLES):
        ap.error(f"--oracles: {', '.join(SURVEY_ORACLES)} need --stress survey")
    out = Path(args.out or tempfile.mkdtemp(prefix="budget-"))
    flights = [("real", int(s)) for s in args.real_seeds.split(",") if s]
    flights += [("bias", int(s)) for s in args.bias_seeds.split(",") if s]
    table: dict[tuple, float | None] = {}
    settings = stress.FLIGHT[args.stress][0]
    for kind, seed in flights:
        base_folder = out / f"seed{seed}{''.join('-' + s for s in settings)}"
        if not (base_folder / "meta.csv").exists():
            vary = (args.accel_bias, args.gyro_bias)
            flight.export(seed, args.duration, *vary, base_folder, settings)
        f = _truth_of_flight(read_log(base_folder), seed, kind, args)
        residual, kept = range_residuals(f)
        inner = residual[kept][np.abs(residual[kept]) < 1.0]  # the radio's outliers aside
        print(
            f"{kind} seed {seed}: ranges less truth and true bias, line of sight "
            f"{kept.sum()}: median {np.median(residual[kept]):+.3f} m, sd {inner.std():.3f} m; "
            f"with an excess {(~kept).sum()}: median {np.median(residual[~kept]):+.3f} m",
            flush=True,
        )
        if args.offset_scan:
            for line in offset_scan(f, float(inner.std())):
                print(f"{kind} seed {seed}: {line}", flush=True)
        for oracle in oracles:
            if oracle == "clock" and not f.lag:
                table[kind, seed, oracle] = None  # no lag to remove
                continue
            tag = "" if args.line_of_sight is None else f"-los{args.line_of_sight:g}"
            tag += "" if args.stress == "none" else f"-{args.stress}"
            folder = out / f"seed{seed}-{kind}-{oracle}{tag}"
            write_log(with_oracle(f, oracle), folder)
            table[kind, seed, oracle] = _replay(
                folder, oracle, args.burn_in, args.reuse, args.line_of_sight
            )
            print(f"{kind} seed {seed} {oracle}: {table[kind, seed, oracle]}", flush=True)
    _print_table(table, flights, oracles, args.burn_in, out)


def _print_table(table: dict, flights, oracles, burn_in: float, out: Path) -> None:
    print(f"{ESTIMATOR}: position RMSE after {burn_in:g} s (m) with one oracle; logs in {out}")
    print(f"{'flight':10s} " + " ".join(f"{o:>13s}" for o in oracles))
    for kind, seed in flights:
        cells = []
        for o in oracles:
            v = table[kind, seed, o]
            cells.append(f"{'-' if v is None else f'{v:.3f}':>13s}")
        print(f"{kind + ' ' + str(seed):10s} " + " ".join(cells))
    for kind in sorted({k for k, _ in flights}):
        rows = [(k, s) for k, s in flights if k == kind]
        means = []
        for o in oracles:
            vals = [table[r + (o,)] for r in rows if table[r + (o,)] is not None]
            means.append(f"{np.mean(vals):13.3f}" if vals else f"{'-':>13s}")
        print(f"{'mean ' + kind:10s} " + " ".join(means))


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
