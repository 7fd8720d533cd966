"""The replay's defaults on a wheeled robot in a small room: ``rover-room`` exported and replayed.

For each seed, ``quadobs run rover-room --export-log DIR`` (the simulated robot: a figure eight
in a 3.0 x 2.4 m room, four anchors, per-anchor range biases of mean +0.11 m, outliers,
dropouts, wheel odometry with a scale error and a yaw-rate bias) and ``quadobs replay DIR
--burn-in 5`` with every other setting at its default (self-calibration, 50 m initial offset,
the default estimators). Each log is replayed twice: as exported (each range with the radio's
stated ``std``) and with the ``std`` column left out, as a log converted by hand holds it (the
replay then takes the ranges' own noise, docs/error-sources.md).

Beside them, the reference: what a short script does that is *given* what the replay must find
out, the true per-anchor biases, the simulation's true noise and the true start (no initial
offset): the range noise ``std`` of the radio, and for the heading filters the odometry's white
noise as intensities ``q_xy_heading = speed_std^2 / rate`` and ``q_theta = yaw_rate_std^2 / rate`` (a
sample held over ``1 / rate``); the EKF of the odometry model (no heading state) with the
default ``q_xy``, as its heading drift is no white noise. Every figure is the position RMSE (m)
after the 5 s burn-in.

    python sims/replay_rover_room.py [--seeds 0,1,2] [--duration 90]

``--variants`` poses the simulated robot as a real one logs it (:data:`VARIANTS`): the
scenario changed by settings (a rest at the start and a stop mid-log with the heading held,
odometry at 20 Hz with wheel slip in turns, ranges at 16 Hz) and the exported log by
:func:`quadobs.testbed.logs.posed.posed_log` (anchors at other heights than the tag with a
planar ``beacons.csv``, the tag off the tracked point, the odometry's clock apart, a Unix time
base); each log is replayed as exported (with ``std``) only:

    python sims/replay_rover_room.py --seeds 0 --variants today,heights,low,rest,rates,clocks,lever,all

Effects compose (:func:`variant_of`): ``heights+lever`` poses two of them, ``all-rest`` every
effect of ``all`` but one (to see which effects add up). On a posed log the reference also
holds ``ukf-height-lever`` given the posing's lever arm and anchors' heights beside the true
biases (:func:`given_truth`): the floor of the model that knows every posed effect.

    python sims/replay_rover_room.py --seeds 0 --variants all-rest,all-rates,all-heights,all-lever,all-clocks

``--without-std`` replays each posed log with its ranges' ``std`` column left out (the
replay then takes the ranges' own noise, docs/error-sources.md):

    python sims/replay_rover_room.py --seeds 0,1,2 --variants all --without-std

``--heights-stated`` writes the posed anchors' heights into the log (``beacons.csv`` with
``z``) and the tag's (``meta.csv`` ``tag_height``), as a log with a survey states them:

    python sims/replay_rover_room.py --seeds 0,1,2 --variants all,heights --heights-stated

``--room`` poses the robot in another room (:data:`ROOMS`: every anchor at one height, a
6 x 5 m room, anchors on the walls and one outside; default the scenario's own), the posed
effects as before:

    python sims/replay_rover_room.py --seeds 0,1,2,3,4 --variants all --room walls
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from unittest.mock import patch

import numpy as np

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.testbed.episode import run_episode
from quadobs.testbed.logs import read_log
from quadobs.testbed.logs.estimators import REPLAY_ESTIMATORS
from quadobs.testbed.logs.export import LogExportSink
from quadobs.testbed.logs.format import write_log
from quadobs.testbed.logs.posed import posed_log
from quadobs.testbed.logs.replay import default_estimators, run_replay
from quadobs.testbed.uwb import radio_of

BURN_IN = 5.0
REFERENCE = ("ekf-heading", "ukf-heading", "ekf")

#: Anchor heights (m) of the posed room, the tag at :data:`TAG_HEIGHT`: anchors on a table,
#: on walls and near the ceiling, as in a room fitted by hand.
ANCHOR_HEIGHTS = (0.30, 2.30, 1.05, 1.80)
TAG_HEIGHT = 0.25
_STOPS = "trajectory.stops=[{start=0.0,end=5.0,ramp=1.0},{start=40.0,end=46.0,ramp=1.0}]"
_RATES = ("odometry.rate=20", "radio.rate=16", "odometry.turn_slip=0.05")
_HEIGHTS = {"anchor_heights": ANCHOR_HEIGHTS, "tag_height": TAG_HEIGHT}
#: Anchors on stands a little above the tag (0.25 to 0.65 m higher).
_LOW = {"anchor_heights": (0.50, 0.90, 0.70, 0.60), "tag_height": TAG_HEIGHT}
_LEVER = {"lever_arm": (0.10, 0.0)}
_CLOCKS = {"odometry_offset": 0.05, "time_base": 1.7e9}
#: Each variant: the scenario's settings, and the posing of its exported log.
VARIANTS = {
    "today": ((), {}),
    "heights": ((), _HEIGHTS),
    "low": ((), _LOW),
    "rest": ((_STOPS,), {}),
    "rates": (_RATES, {}),
    "clocks": ((), _CLOCKS),
    "lever": ((), _LEVER),
    "all": ((_STOPS, *_RATES), {**_HEIGHTS, **_LEVER, **_CLOCKS}),
}


def _room(beacons, offset, amplitudes, omega, heights, point) -> dict:
    """A room: the scenario's settings (its anchors' plan, the figure eight ``offset +
    (a_x sin(w t), a_y sin(2 w t))`` and the live estimators' start) and the anchors' heights
    that the ``heights`` effect poses in it (the tag at :data:`TAG_HEIGHT`)."""
    anchors = ",".join(f"{{position=[{x},{y}]}}" for x, y in beacons)
    terms = ",".join(
        f'{{axis={axis},amplitude={a},omega={w},function="sin"}}'
        for axis, a, w in ((0, amplitudes[0], omega), (1, amplitudes[1], 2 * omega))
    )
    return {
        "settings": (
            f"beacons=[{anchors}]",
            f"trajectory.offset=[{offset[0]},{offset[1]}]",
            f"trajectory.terms=[{terms}]",
            f"initial.point=[{point[0]},{point[1]},0.0,0.0]",
        ),
        "heights": tuple(heights),
    }


#: The rooms the robot is posed in (``--room``). ``today``: the scenario as it ships (3.0 x 2.4
#: m, anchors near the corners at :data:`ANCHOR_HEIGHTS`). ``level``: the same plan, every
#: anchor at 2.0 m (on tripods or at the ceiling, a common layout: the same height offset for
#: all). ``large``: a 6.0 x 5.0 m room, anchors near its corners, the figure eight scaled by 2
#: in x and 2.08 in y at half the rate (the same speeds, 0.22 to 0.50 m/s, a lap of 39 s).
#: ``walls``: the small room's anchors at the middle of three walls and the fourth 2 m outside
#: the west wall (in the next room, 2.3 m from the path's nearest point).
ROOMS = {
    "today": {"settings": (), "heights": ANCHOR_HEIGHTS},
    "level": {"settings": (), "heights": (2.0, 2.0, 2.0, 2.0)},
    "large": _room(
        beacons=((0.15, 0.12), (5.85, 0.20), (5.80, 4.85), (0.20, 4.88)),
        offset=(3.0, 2.5),
        amplitudes=(2.0, 1.25),
        omega=0.16,
        heights=ANCHOR_HEIGHTS,
        point=(2.0, 2.0),
    ),
    "walls": _room(
        beacons=((1.40, 0.05), (2.95, 1.10), (1.70, 2.35), (-2.0, 1.60)),
        offset=(1.5, 1.2),
        amplitudes=(1.0, 0.6),
        omega=0.32,
        heights=ANCHOR_HEIGHTS,
        point=(1.0, 1.0),
    ),
}
#: The effects that ``all`` composes, in its order: a variant ``a+b`` poses the effects ``a`` and
#: ``b`` together, ``all-a`` every effect of ``all`` but ``a`` (:func:`variant_of`).
EFFECTS = ("rest", "rates", "heights", "lever", "clocks")


def variant_of(name: str) -> tuple[tuple, dict]:
    """The scenario's settings and the log's posing of the variant ``name``: one of
    :data:`VARIANTS`, effects joined by ``+`` (``heights+lever``), or ``all-EFFECT`` (``all``
    without one of :data:`EFFECTS`)."""
    if name in VARIANTS:
        return VARIANTS[name]
    if name.startswith("all-"):
        left = name[4:].split("-")
        parts = [e for e in EFFECTS if e not in left]
    else:
        left = parts = name.split("+")
    unknown = [e for e in left if e not in EFFECTS]
    if unknown or not parts:
        raise SystemExit(
            f"--variants: unknown {name!r} (one of {', '.join(VARIANTS)}; effects joined by '+' "
            f"or taken from 'all-': {', '.join(EFFECTS)})"
        )
    settings: tuple = ()
    pose: dict = {}
    for effect in (e for e in EFFECTS if e in parts):
        settings += VARIANTS[effect][0]
        pose.update(VARIANTS[effect][1])
    return settings, pose


def in_room(pose: dict, room: str) -> dict:
    """The posing ``pose`` in the room ``room`` (:data:`ROOMS`): the ``heights`` effect's
    anchors at the room's heights."""
    if pose.get("anchor_heights") == ANCHOR_HEIGHTS:
        return {**pose, "anchor_heights": ROOMS[room]["heights"]}
    return pose


def _poses(variant: str) -> bool:
    """Whether ``variant`` poses any anchor heights (which ``--heights-stated`` states)."""
    return "anchor_heights" in variant_of(variant)[1]


def _poses_heights(variant: str) -> bool:
    """Whether ``variant`` poses the anchors' heights (the ``heights`` effect), where
    ``--room level`` puts them at one height."""
    return variant_of(variant)[1].get("anchor_heights") == ANCHOR_HEIGHTS


def export(
    seed: int,
    duration: float,
    folder: Path,
    variant: str = "today",
    room: str = "today",
    extra: tuple[str, ...] = (),
    heights_stated: bool = False,
):
    """The seed's ``rover-room`` run in ``room`` written as a log in ``folder`` (posed as
    ``variant``; ``extra``: scenario settings applied after the variant's; ``heights_stated``:
    a variant posing the anchors' heights states them in the log, with the tag's); the scenario."""
    settings, pose = variant_of(variant)
    settings, pose = (*ROOMS[room]["settings"], *settings, *extra), in_room(pose, room)
    if heights_stated and "anchor_heights" in pose:
        pose = {**pose, "heights_stated": True}
    scenario = load_scenario("rover-room", seed=seed, duration=duration)
    if settings:
        scenario = scenario.with_settings(settings)
    run_episode(scenario, estimators=["ekf"], sinks=[LogExportSink(folder)])
    if pose:
        write_log(posed_log(read_log(folder), **pose), folder)
    return scenario


def without_std(folder: Path, into: Path) -> Path:
    """A copy of the log ``folder`` whose ``ranges.csv`` has no ``std`` column."""
    shutil.copytree(folder, into)
    with open(folder / "ranges.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    with open(into / "ranges.csv", "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["time", "beacon", "range"])
        out.writerows((r["time"], r["beacon"], r["range"]) for r in rows)
    return into


def replay_defaults(folder: Path, extra: tuple[str, ...] = ()) -> dict:
    """``quadobs replay FOLDER --burn-in 5``, every other setting its default: RMSE by estimator
    (with ``extra``, the default set and those estimators beside it, calibrated once)."""
    summary = folder.parent / f"{folder.name}-summary.json"
    cmd = [sys.executable, "-m", "quadobs", "replay", str(folder), "--burn-in", str(BURN_IN)]
    if extra:
        names = [*default_estimators(read_log(folder)), *extra]
        cmd += ["--estimators", ",".join(dict.fromkeys(names))]
    done = subprocess.run(
        [*cmd, "--summary", str(summary)], capture_output=True, text=True, check=False
    )
    if done.returncode != 0 and not (done.returncode == 1 and summary.exists()):
        raise SystemExit(f"quadobs replay failed: {done.stderr.strip().splitlines()[-1]}")
    estimators = json.loads(summary.read_text())["estimators"]  # status 1: one named diverged
    return {
        name: "diverged" if figures.get("diverged") else figures["rmse"]
        for name, figures in estimators.items()
    }


def given_truth(pose: dict):
    """A factory of the replay's ``ukf-height-lever`` given what the posing put into the log: the
    lever arm and each anchor's squared-range offset ``(dz_h)^2 / 2`` as states whose prior is
    the truth (standard deviation 1e-4), no range-bias states (the true biases are subtracted)."""
    from functools import partial

    from quadobs.estimators.heading_ekf import HeadingUKF
    from quadobs.testbed.logs.estimators import build_ekf_heading

    heights = pose.get("anchor_heights")
    dz = 0.0 if heights is None else np.asarray(heights) - pose.get("tag_height", 0.0)
    known = 1e-4
    options = {"lever_arm_std": known, "lever_arm": pose.get("lever_arm", (0.0, 0.0))}
    options["offsets"] = (0.5 * np.square(dz), known)

    def build(s, x0, name):
        return build_ekf_heading(s, x0, name, partial(HeadingUKF, **options))

    return build


def reference(folder: Path, scenario, pose: dict | None = None) -> dict:
    """The estimators of :data:`REFERENCE` given the true biases and the true noise (module
    docstring); with ``pose`` (a posed log), also ``ukf-height-lever`` given the lever arm and
    the anchors' heights of the posing (:func:`given_truth`)."""
    log = read_log(folder)
    odo, radio = scenario.odometry, scenario.radio
    truth = radio_of(scenario).biases
    options = {
        "range_sigma": radio.std,
        "q_xy_heading": odo.speed_std**2 / odo.rate,
        "q_theta": odo.yaw_rate_std**2 / odo.rate,
    }
    out = {}
    names = [*REFERENCE, "ukf-height-lever"] if pose is not None else REFERENCE
    for name in names:
        opts = options if "heading" in name or "lever" in name else {"range_sigma": radio.std}
        given = {"ukf-height-lever": given_truth(pose)} if pose is not None else {}
        with patch.dict(REPLAY_ESTIMATORS, given):
            summary = run_replay(
                log, estimators=[name], biases=truth, setup_options=opts, burn_in=BURN_IN,
                batch=False, initial_offset=0.0,
            )  # fmt: skip
        out[f"{name} (truth)"] = summary["estimators"][name]["rmse"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--duration", type=float, default=90.0)
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--variants", help=f"posed logs, comma-separated ({', '.join(VARIANTS)})")
    ap.add_argument(
        "--without-std",
        action="store_true",
        help="replay each posed log with its ranges' std column left out (with --variants)",
    )
    ap.add_argument(
        "--room",
        default="today",
        choices=tuple(ROOMS),
        help="the room's anchors and path (with --variants; default: the scenario's own)",
    )
    ap.add_argument(
        "--extra", default="", help="estimators replayed beside the default set (e.g. ukf-height)"
    )
    ap.add_argument(
        "--heights-stated",
        action="store_true",
        help="the posed anchors' heights and the tag's stated in the log (beacons.csv z, "
        "meta.csv tag_height; with --variants)",
    )
    args = ap.parse_args()
    if args.room == "level":  # its one height is posed by the heights effect alone
        flat = [v for v in (args.variants or "today").split(",") if not _poses_heights(v)]
        if flat:
            ap.error(f"--room level: the variant(s) {', '.join(flat)} pose no anchor heights")
    extra = tuple(x for x in args.extra.split(",") if x)
    rows = []
    with tempfile.TemporaryDirectory(prefix="rover-room-") as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            if args.variants:
                variants = args.variants.split(",")
                rows += posed_rows(
                    seed, args.duration, variants, Path(tmp), extra, args.without_std, args.room,
                    args.heights_stated,
                )  # fmt: skip
                continue
            folder = Path(tmp) / f"seed{seed}"
            scenario = export(seed, args.duration, folder, "today", args.room)
            bare = without_std(folder, Path(tmp) / f"seed{seed}-nostd")
            ref = reference(folder, scenario)
            for label, log in (("std", folder), ("no std", bare)):
                row = {"seed": seed, "log": label, **replay_defaults(log), **ref}
                rows.append(row)
                print(", ".join(f"{k} {_fmt(v)}" for k, v in row.items()), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    columns = [k for k in rows[0] if k not in ("seed", "log")]
    print("| seed | log | " + " | ".join(columns) + " |")
    print("|---|---|" + "---|" * len(columns))
    for r in rows:
        print(f"| {r['seed']} | {r['log']} | " + " | ".join(_fmt(r[c]) for c in columns) + " |")
    print(f"(position RMSE after {BURN_IN:g} s, m)")


def posed_rows(
    seed: int,
    duration: float,
    variants: list[str],
    tmp: Path,
    extra=(),
    bare: bool = False,
    room: str = "today",
    heights_stated: bool = False,
) -> list[dict]:
    """One row per variant of the seed in ``room``: the defaults' RMSE and the reference's
    (``bare``: the defaults on the log with its ranges' ``std`` column left out;
    ``heights_stated``: the anchors' and the tag's heights stated in the log, :func:`export`)."""
    rows = []
    for variant in variants:
        variant_of(variant)  # an unknown name stops here, before the export
        folder = tmp / f"seed{seed}-{variant}"
        scenario = export(seed, duration, folder, variant, room, heights_stated=heights_stated)
        replayed = without_std(folder, tmp / f"seed{seed}-{variant}-nostd") if bare else folder
        label = f"{variant}, no std" if bare else variant
        row = {
            "seed": seed,
            "log": f"{label}, heights stated" if heights_stated and _poses(variant) else label,
            **replay_defaults(replayed, extra),
            **reference(folder, scenario, in_room(variant_of(variant)[1], room)),
        }
        rows.append(row)
        print(", ".join(f"{k} {_fmt(v)}" for k, v in row.items()), flush=True)
    return rows


def _fmt(value) -> str:
    return f"{value:.3f}" if isinstance(value, float) and math.isfinite(value) else str(value)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
