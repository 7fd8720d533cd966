"""Stress: what the stand-ins for a real robot's and a real flight's log had not posed yet.

The stand-ins (``sims/replay_rover_room.py --variants all``, ``sims/replay_flight_variants.py
--variants real``) pose what a real log holds that the simulator's export does not. A real log
may differ in more ways; each stress below is one of them, a single switch on top of the
stand-in (seeded where it draws: the seed of the run and the stress's name), replayed with
``quadobs replay DIR --burn-in 5`` and every other setting at its default. The table gives the
best estimator's position RMSE after the burn-in (no estimator reported diverged counts), and
whether it meets the target: 0.15 m for the robot, 0.20 m for the flight.

Robot (``all`` in ``--room``: anchors above the tag, a lever arm, stops, odometry at 20 Hz
with slip, clocks apart; :data:`ROVER`):

* ``survey``: ``beacons.csv`` as surveyed, each coordinate off by ``N(0, 0.05^2)`` m;
* ``rate10``: ranges at 10 Hz over the four anchors (2.5 Hz each);
* ``scale``: the wheel scale 5 % short (``odometry.scale_error = -0.05``);
* ``moving``: the log begun 8 s in, the robot at speed (its rest over 0-5 s cut);
* ``truth``: the motion capture from 3 s after the log's start, at 30 Hz;
* ``pillar``: a pillar of 0.15 m radius at (1.5, 0.5) m, beside the path: a range whose path
  crosses it is longer by an exponential excess of mean 0.3 m (bursts as the robot passes);
* ``gap``: anchor 1 silent for 8 s from 30 s;
* ``odoclock``: the odometry 0.1 s late against the ranges, its stamps jittered by +-10 ms;
* ``pattern``: each anchor's range bias varying with the direction of the tag seen from it,
  0.1 m over all directions (``radio.pattern = 0.1``: the antennas' radiation patterns, their
  second-order term, :mod:`quadobs.testbed.uwb`); over the cone of directions in which an
  anchor sees the vehicle it acts mostly as a bias and a displaced anchor (``--pattern-fit``);
* ``level``: every range's bias changing with the distance through the received signal's
  level, ``0.1 log10 d`` m (``radio.level_bias = 0.1``, :mod:`quadobs.testbed.uwb`);
* ``tagpattern``: the tag's own pattern, a range bias that turns with the vehicle: a second
  harmonic of the anchor's bearing from the heading, 0.1 m over bearings
  (:func:`~quadobs.testbed.logs.posed.tag_pattern`);
* ``held``: the ranges as a logger at 20 Hz writes every anchor's latest one
  (:func:`~quadobs.testbed.logs.posed.ranges_held`: each range repeated until its anchor's
  next, at the logger's times).

Flight (``real``: no attitude, vibration at 100 Hz, uneven IMU, FRD axes, IMU 20 ms late,
range biases of both signs, motion capture at 100 Hz, no ``std``; :data:`FLIGHT`, each applied
to the log without attitude before ``real``'s transforms):

* ``survey``: as the robot's;
* ``rate50``: ranges at 50 Hz over the eight anchors (``radio.rate = 50``: a tag's
  round-robin at half the rate; keeping every other range of the 100 Hz export instead would
  keep half the anchors between two dropouts);
* ``rate400``: ranges at 400 Hz over the eight anchors (``radio.rate = 400``);
* ``rate20``, ``rate10``: ranges at 20 or 10 Hz over the eight anchors (each anchor every 0.4
  or 0.8 s: the noise test's sparse case, docs/error-sources.md; not in the default list);
* ``moving``: the log begun 5 s into the flight;
* ``gap``: anchor 0 silent for 10 s from 15 s;
* ``imuclock``: the IMU a further 50 ms late, its stamps jittered by +-2 ms;
* ``ascale``: the accelerometer's scale off by +2, -1.5 and +1 % on x, y, z;
* ``pattern``, ``level``: as the robot's;
* ``tagpattern``: the tag's pattern as the second-order form of the anchor's direction in the
  body frame (the truth's attitude), 0.1 m over all directions; applied to the export, whose
  truth holds the attitude, before it is removed;
* ``held``: as the robot's, the logger at 100 Hz, on the ranges as ``real`` leaves them.

Both (``mix``): several of them at once, as a real log would hold them, at moderate sizes:
the anchors' and the tag's patterns at :data:`MIX_PATTERN_STD` (0.05 m) each, ``level``,
``survey``, and the robot's ``pillar`` and ``odoclock`` or the flight's ``imuclock`` and
``ascale`` (the flight's applied to the export, as ``tagpattern``).

::

    python sims/stress_hidden_logs.py rover --seeds 0,1,2,3,4
    python sims/stress_hidden_logs.py rover --seeds 0,1,2,3,4 --room walls
    python sims/stress_hidden_logs.py flight --seeds 0,1,2,3,4

``--variants`` picks stresses (``none``: the stand-in itself); ``--json`` writes every
estimator's RMSE. ``--estimators`` and ``--tune`` are handed to each replay (a comparison of
one setting on the same logs); ``--without-std`` leaves the ranges' ``std`` column out of each
log (the robot's logs state one, the flight's none), as a log converted by hand would::

    python sims/stress_hidden_logs.py rover --seeds 0,1 --without-std --tune anchor_sigma=0

``--pattern`` sets the ``pattern`` and ``tagpattern`` stresses' spread (m; default :data:`PATTERN_STD`), ``--level``
the ``level`` stress's bias per decade (m; default :data:`LEVEL_BIAS`); ``--keep DIR`` keeps the
logs (and the replays' summaries) in a new folder ``DIR``.
``--given-biases`` (flight) also replays ``ekf-bias-imu`` given each anchor's constant bias as
the truth supports it (:func:`truth_biases`) and held to it: what the best constant biases
allow, beside what the default estimators reach without them::

    python sims/stress_hidden_logs.py flight --seeds 0,1,2,3,4 --variants none,pattern --given-biases
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import zlib
from pathlib import Path

import numpy as np
import replay_flight_variants as flight
import replay_rover_room as rover

from quadobs.errors import run_script
from quadobs.testbed.logs import read_log, write_log
from quadobs.testbed.logs.posed import (
    accel_scaled,
    anchor_gap,
    behind_pillar,
    inputs_late,
    ranges_held,
    started_at,
    surveyed,
    tag_pattern,
    truth_from,
)

TARGET = {"rover": 0.15, "flight": 0.20}
SURVEY_STD = 0.05
#: The ``pattern`` stress's spread over directions of each anchor's direction-dependent bias (m).
PATTERN_STD = 0.1
#: The ``level`` stress's bias per decade of distance (m).
LEVEL_BIAS = 0.1
#: The flight's ``imuclock``: the IMU's further lag (s) and its stamps' jitter (+- s).
IMU_LATE = (0.05, 0.002)


def _none(log, seed):
    return log


#: The ``mix`` stress's spread of the anchors' and the tag's patterns (m): half the single
#: stresses', since it poses them together with the others.
MIX_PATTERN_STD = 0.05


def _mixed(*steps):
    """The transforms ``steps`` applied in turn, the ``k``-th drawn from ``seed + k``."""

    def transform(log, seed):
        for k, step in enumerate(steps):
            log = step(log, seed + k)
        return log

    return transform


#: The ``mix`` stress's scenario settings (the anchors' pattern, the received level's bias) and
#: its first transforms (the survey, the tag's pattern), for the robot and the flight alike.
MIX_SETTINGS = (f"radio.pattern={MIX_PATTERN_STD}", f"radio.level_bias={LEVEL_BIAS}")
MIX_COMMON = (
    lambda log, seed: surveyed(log, SURVEY_STD, seed),
    lambda log, seed: tag_pattern(log, MIX_PATTERN_STD, seed),
)


#: The robot's stresses: scenario settings and a transform ``(log, seed) -> log``.
ROVER = {
    "none": ((), _none),
    "survey": ((), lambda log, seed: surveyed(log, SURVEY_STD, seed)),
    "rate10": (("radio.rate=10",), _none),
    "scale": (("odometry.scale_error=-0.05",), _none),
    "moving": ((), lambda log, seed: started_at(log, 8.0)),
    "truth": ((), lambda log, seed: truth_from(log, 3.0, 30.0)),
    "pillar": ((), lambda log, seed: behind_pillar(log, (1.5, 0.5), 0.15, 0.3, seed)),
    "gap": ((), lambda log, seed: anchor_gap(log, 1, 30.0, 8.0)),
    "odoclock": ((), lambda log, seed: inputs_late(log, 0.1, 0.01, seed)),
    "pattern": ((f"radio.pattern={PATTERN_STD}",), _none),
    "level": ((f"radio.level_bias={LEVEL_BIAS}",), _none),
    "tagpattern": ((), lambda log, seed: tag_pattern(log, PATTERN_STD, seed)),
    "held": ((), lambda log, seed: ranges_held(log, 20.0)),
    "mix": (
        MIX_SETTINGS,
        _mixed(
            *MIX_COMMON,
            lambda log, seed: behind_pillar(log, (1.5, 0.5), 0.15, 0.3, seed),
            lambda log, seed: inputs_late(log, 0.1, 0.01, seed),
        ),
    ),
}
#: The flight's stresses, as :data:`ROVER`.
FLIGHT = {
    "none": ((), _none),
    "survey": ((), lambda log, seed: surveyed(log, SURVEY_STD, seed)),
    "rate50": (("radio.rate=50",), _none),
    "rate400": (("radio.rate=400",), _none),
    "rate20": (("radio.rate=20",), _none),
    "rate10": (("radio.rate=10",), _none),
    "moving": ((), lambda log, seed: started_at(log, 5.0)),
    "gap": ((), lambda log, seed: anchor_gap(log, 0, 15.0, 10.0)),
    "imuclock": ((), lambda log, seed: inputs_late(log, *IMU_LATE, seed)),
    "ascale": ((), lambda log, seed: accel_scaled(log, (0.02, -0.015, 0.01))),
    "pattern": ((f"radio.pattern={PATTERN_STD}",), _none),
    "level": ((f"radio.level_bias={LEVEL_BIAS}",), _none),
    "tagpattern": ((), lambda log, seed: tag_pattern(log, PATTERN_STD, seed)),
    "held": ((), _none),  # the logger's, after real's transforms: FLIGHT_LOGGER
    "mix": (
        MIX_SETTINGS,
        _mixed(
            *MIX_COMMON,
            lambda log, seed: inputs_late(log, *IMU_LATE, seed),
            lambda log, seed: accel_scaled(log, (0.02, -0.015, 0.01)),
        ),
    ),
}


#: The flight's stresses of its logger, applied after ``real``'s transforms (which draw the
#: radio's errors per range): the ranges held as the radio gave them.
FLIGHT_LOGGER = {"held": lambda log, seed: ranges_held(log, 100.0)}
AFTER_REAL = tuple(FLIGHT_LOGGER)

#: The flight's stresses run only when named (the robot's own ``rate10`` runs by default): at
#: these rates no filter meets the target, and they pose the noise test's sparse case rather
#: than a log's difference from the stand-in.
SPARSE = ("rate20", "rate10")

#: The flight's stresses that take the truth's attitude: applied to the export before its
#: attitude is removed (the tag's pattern reads it; the rest of ``mix`` changes the ranges and
#: the IMU's samples, which removing the attitude leaves as they are).
WITH_ATTITUDE = ("tagpattern", "mix")


def stress_seed(seed: int, name: str) -> int:
    """The draws of the stress ``name`` on the run ``seed``: one seed from both."""
    return seed * 1000 + zlib.crc32(name.encode()) % 1000


def rover_log(seed: int, name: str, room: str, duration: float, tmp: Path, table=None) -> Path:
    """The robot's stand-in ``all`` in ``room`` with the stress ``name``, written in ``tmp``."""
    settings, transform = (table or ROVER)[name]
    folder = tmp / f"rover-{room}-seed{seed}-{name}"
    rover.export(seed, duration, folder, "all", room, settings)
    write_log(transform(read_log(folder), stress_seed(seed, name)), folder)
    return folder


def flight_log(seed: int, name: str, duration: float, tmp: Path, table=None) -> Path:
    """The flight's stand-in ``real`` with the stress ``name``, written in ``tmp``: the stress
    on the log without attitude, then ``real``'s transforms drawn as the flight study does (a
    logger's stress, :data:`FLIGHT_LOGGER`, after them)."""
    settings, transform = (table or FLIGHT)[name]
    base = tmp / f"flight-seed{seed}-export{'-'.join(settings)}"
    if not (base / "meta.csv").exists():
        flight.export(seed, duration, 0.2, 0.01, base, settings)
    if name in WITH_ATTITUDE:  # on the export, whose truth holds the attitude, then without it
        stressed = flight.variant(transform(read_log(base), stress_seed(seed, name)), "noatt", 1.0)
    else:
        stressed = transform(flight.variant(read_log(base), "noatt", 1.0), stress_seed(seed, name))
    rng = np.random.default_rng([seed, flight.REAL.index("real")])
    folder = tmp / f"flight-seed{seed}-{name}"
    real = flight.real_variant(stressed, "real", rng, 1.0, 0.05)
    if name in AFTER_REAL:  # a logger's: on the ranges as the radio gave them, errors and all
        real = FLIGHT_LOGGER[name](real, stress_seed(seed, name))
    write_log(real, folder)
    return folder


def replay(folder: Path, estimators: str | None = None, tune=(), biases=None) -> dict:
    """``quadobs replay FOLDER --burn-in 5``, with ``--estimators``, each ``--tune`` and
    ``--biases`` where given: the RMSE by estimator (``"diverged"`` where the replay reports it
    so; none where the replay failed, which the table shows as ``-``)."""
    from quadobs import cli

    summary = folder.with_name(f"{folder.name}-summary.json")
    argv = ["replay", str(folder), "--burn-in", f"{rover.BURN_IN:g}", "--no-progress"]
    argv += ["--summary", str(summary)] + (["--estimators", estimators] if estimators else [])
    for setting in tune:
        argv += ["--tune", setting]
    if biases is not None:
        argv.append(_biases_text(biases))
    code = cli.main(argv)
    if code not in (0, 1):  # 1: an estimator reported diverged; else none ran: the next log
        print(f"quadobs replay {folder.name} failed (status {code})", flush=True)
        return {}
    return {
        k: "diverged" if e.get("diverged") else e.get("rmse", math.nan)
        for k, e in json.loads(summary.read_text())["estimators"].items()
    }


def _check_replay_options(ap, args) -> None:
    """``--tune`` and ``--estimators`` checked before any log is simulated."""
    from quadobs.errors import QuadobsError
    from quadobs.testbed.logs.estimators import parse_tuning, replay_estimator_names

    try:
        parse_tuning(args.tune)
    except QuadobsError as exc:
        ap.error(str(exc))
    names = [n.strip() for n in (args.estimators or "").split(",") if n.strip()]
    unknown = sorted(set(names) - set(replay_estimator_names()))
    if unknown or (args.estimators is not None and not names):
        ap.error(f"--estimators: unknown {', '.join(unknown) or '(none given)'}")


def truth_biases(folder: Path) -> np.ndarray:
    """Each anchor's constant range bias as the flight's truth supports it: the median of its
    ranges less their true distance (the truth's position at the range's time, linear between
    rows; ranges of 0 m and those outside the truth's span left out), 0 for an anchor with
    none. The noise, the non-line-of-sight excess (a minority of most anchors' ranges) and a
    direction-dependent bias's mean over the flight are in the ranges alike; the median keeps
    the constant part of what a range filter given constant biases can use."""
    log = read_log(folder)
    t, cols = log.ranges[:, 0], log.truth_columns
    keep = (log.ranges[:, 2] > 0.0) & (t >= log.truth[0, 0]) & (t <= log.truth[-1, 0])
    p = np.column_stack([np.interp(t, log.truth[:, 0], log.truth[:, cols.index(c)]) for c in "xyz"])
    h = log.beacon_index(log.ranges[:, 1])
    residual = log.ranges[:, 2] - np.linalg.norm(p - log.beacons[h], axis=1)
    return np.array(
        [np.median(residual[keep & (h == i)]) if np.any(keep & (h == i)) else 0.0
         for i in range(log.beacons.shape[0])]
    )  # fmt: skip


#: ``--given-biases``: the flight's bias filters given :func:`truth_biases` and held to them
#: (their prior 1 mm, the self-calibration skipped as ``--biases`` does).
GIVEN = ("ekf-bias-imu", ("bias_prior=0.001",))


def pattern_spread(base: Path, seed: int, settings) -> tuple[np.ndarray, np.ndarray]:
    """Each anchor's pattern term ``u^T S u`` over the directions the flight ``base`` (its
    export, in the radio's frame) visits, every truth row: its standard deviation, and the RMS
    left of it by a least-squares fit of a constant and a linear term in ``u`` (a bias and a
    displaced phase centre, which is all a limited cone of directions leaves apart)."""
    from quadobs import load_scenario
    from quadobs.testbed.uwb import radio_of

    radio = radio_of(load_scenario("quadrotor-uwb-realistic", seed=seed).with_settings(settings))
    log = read_log(base)
    p = log.truth[:, [log.truth_columns.index(c) for c in "xyz"]]
    spread, left = np.zeros(radio.m), np.zeros(radio.m)
    for i in range(radio.m):
        u = p - radio.anchors[i]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        e = np.einsum("ni,ij,nj->n", u, radio.pattern_forms[i], u)
        X = np.column_stack([np.ones(len(u)), u])
        fit = np.linalg.lstsq(X, e, rcond=None)[0]
        spread[i], left[i] = e.std(), math.sqrt(np.mean((e - X @ fit) ** 2))
    return spread, left


def best(rmse: dict) -> tuple[str, float]:
    """The estimator of least RMSE among those not reported diverged."""
    ran = {k: v for k, v in rmse.items() if isinstance(v, float) and math.isfinite(v)}
    if not ran:
        return "-", math.inf
    name = min(ran, key=ran.get)
    return name, ran[name]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("platform", choices=("rover", "flight"))
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--variants", help="comma-separated stresses (default: all of them)")
    ap.add_argument("--room", default="today", choices=tuple(rover.ROOMS), help="the robot's")
    ap.add_argument("--duration", type=float, help="s (default: 90 robot, 40 flight)")
    ap.add_argument("--json", help="write every estimator's RMSE here")
    ap.add_argument("--estimators", help="comma-separated, for every replay (default: its own)")
    ap.add_argument("--tune", action="append", default=[], metavar="KEY=VALUE", help="repeatable")
    ap.add_argument("--without-std", action="store_true", help="the ranges' std column left out")
    ap.add_argument(
        "--pattern",
        type=float,
        default=PATTERN_STD,
        help=f"m, the pattern and tagpattern stresses' spread over directions (default {PATTERN_STD:g})",
    )
    ap.add_argument(
        "--level",
        type=float,
        default=LEVEL_BIAS,
        help=f"m per decade, the level stress's bias (default {LEVEL_BIAS:g})",
    )
    ap.add_argument("--keep", help="a new folder to keep the logs in (default: none kept)")
    ap.add_argument(
        "--given-biases",
        action="store_true",
        help="flight: also ekf-bias-imu given each anchor's constant bias from the truth",
    )
    ap.add_argument(
        "--pattern-fit",
        action="store_true",
        help="flight: the pattern's spread over each anchor's directions, and what a bias and a displaced anchor leave of it",
    )
    args = ap.parse_args()
    if args.pattern_fit and args.platform != "flight":
        ap.error("--pattern-fit: the flight's logs only")
    if args.given_biases and args.platform != "flight":
        ap.error(
            "--given-biases: the flight's logs only (the robot's anchors' heights are not in its log)"
        )
    table = ROVER if args.platform == "rover" else FLIGHT
    if not (math.isfinite(args.pattern) and args.pattern > 0.0):
        ap.error(f"--pattern: expected a positive number of metres, got {args.pattern}")
    if not math.isfinite(args.level):
        ap.error(f"--level: expected a finite number of metres per decade, got {args.level}")
    table = {**table, "pattern": ((f"radio.pattern={args.pattern!r}",), _none)}
    table["level"] = ((f"radio.level_bias={args.level!r}",), _none)
    spread = args.pattern
    table["tagpattern"] = ((), lambda log, seed: tag_pattern(log, spread, seed))
    if args.keep and Path(args.keep).exists():
        ap.error(f"--keep: {args.keep} exists (a new folder is made, none is replaced)")
    sparse = SPARSE if args.platform == "flight" else ()  # the robot's rate10 is in its list
    names = args.variants.split(",") if args.variants else [n for n in table if n not in sparse]
    unknown = [n for n in names if n not in table]
    if unknown:
        ap.error(f"unknown stress {', '.join(unknown)} (one of {', '.join(table)})")
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    _check_replay_options(ap, args)
    if args.duration is not None and not args.duration > 0.0:
        ap.error(f"--duration: expected a positive number of seconds, got {args.duration}")
    duration = args.duration or (90.0 if args.platform == "rover" else 40.0)
    rows = []
    with _logs_folder(args.keep) as tmp:
        for seed in seeds:
            for name in names:
                if args.platform == "rover":
                    folder = rover_log(seed, name, args.room, duration, Path(tmp), table)
                else:
                    folder = flight_log(seed, name, duration, Path(tmp), table)
                if args.without_std:
                    folder = rover.without_std(folder, folder.with_name(f"{folder.name}-nostd"))
                rmse = replay(folder, args.estimators, args.tune)
                who, value = best(rmse)
                row = {"seed": seed, "stress": name, "best": who, "rmse": value, **rmse}
                if args.given_biases:
                    biases = truth_biases(folder)
                    given = replay(folder, GIVEN[0], [*args.tune, *GIVEN[1]], biases)
                    row["given"] = given.get(GIVEN[0], math.nan)
                    print(f"seed {seed} {name}: given biases {_biases_text(biases)}", flush=True)
                if args.pattern_fit and name == "pattern":
                    _print_pattern(Path(tmp), seed, table["pattern"][0])
                rows.append(row)
                print(f"seed {seed} {name}: best {who} {value:.3f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    _print_table(rows, names, TARGET[args.platform])


def _print_table(rows: list[dict], names: list[str], target: float) -> None:
    """Per stress: the best default's RMSE on each seed, the worst, and the target met."""
    seeds = sorted({r["seed"] for r in rows})
    print("| stress | " + " | ".join(f"seed {s}" for s in seeds) + " | worst | target met |")
    print("|---|" + "---|" * (len(seeds) + 2))
    for name in names:
        cells = {r["seed"]: r for r in rows if r["stress"] == name}
        worst = max(cells[s]["rmse"] for s in seeds)
        text = " | ".join(
            f"{cells[s]['rmse']:.3f} ({cells[s]['best']}{_given(cells[s])})" for s in seeds
        )
        print(f"| {name} | {text} | {worst:.3f} | {'yes' if worst <= target else 'no'} |")
    print(f"(best default's position RMSE after {rover.BURN_IN:g} s, m; target {target:g} m)")
    if any("given" in r for r in rows):
        print(f"(given: {GIVEN[0]} given each anchor's constant bias from the truth)")


def _print_pattern(tmp: Path, seed: int, settings) -> None:
    """``--pattern-fit``: the seed's pattern over its flight (:func:`pattern_spread`)."""
    spread, left = pattern_spread(
        tmp / f"flight-seed{seed}-export{'-'.join(settings)}", seed, settings
    )
    print(
        f"seed {seed} pattern over the flight's directions, per anchor: spread "
        f"{spread.min():.3f}-{spread.max():.3f} m, left by a constant and a linear term in u "
        f"{left.min():.3f}-{left.max():.3f} m",
        flush=True,
    )


def _logs_folder(keep: str | None):
    """The folder the logs are written in: ``keep`` (made, and kept) or a temporary one."""
    import contextlib

    if keep is None:
        return tempfile.TemporaryDirectory(prefix="stress-")
    Path(keep).mkdir(parents=True)
    return contextlib.nullcontext(keep)


def _biases_text(biases) -> str:
    """``--biases=...`` as the replay takes them."""
    return "--biases=" + ",".join(f"{b:.4f}" for b in biases)


def _given(row: dict) -> str:
    """``; given X`` where the row has the filter given the truth's biases."""
    value = row.get("given")
    if value is None:
        return ""
    return f"; given {value:.3f}" if isinstance(value, float) else f"; given {value}"


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
