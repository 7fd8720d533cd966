"""Replay a logged run through the estimators: the episode's loop, sinks and recording over a log.

.. code-block:: text

    world = ReplayWorld(log, dt, model, biases, sensors)   # rows on the replay grid (worlds/replay.py)
    run_loop(frame=world.frame(seed), world=world, estimators=..., timed=True)   # quadobs.testbed.episode

The loop is the simulated episode's (:func:`quadobs.testbed.episode.run_loop`): the same
blocks, record rows, sinks and recording layout (:mod:`quadobs.testbed.episode_log`, so
``quadobs plot`` and :func:`quadobs.recording.read_series` read a replay's recording as
an episode's). What differs is the world (a log on a grid, :class:`ReplayWorld`), the
frame (the log's name and beacons, the odometry as the input), the sensor layer (nothing
added unless ``noise.*`` settings ask for it, :func:`log_scenario`) and the summary's keys:

* per estimator, from the world's sinks: ``rmse`` and ``max_error`` of the position over
  every step with a truth, ``final_position_error``, ``time_to_5m`` and ``time_to_2m``
  (from when the error stays below), ``seconds_per_measurement`` (the estimator's wall
  time over the ranges placed); from the episode's: ``corrections`` and ``rejected`` where
  the estimator counts them, ``time_to_1m``, ``time_to_0p1m``, ``immersion``;
* for the GTSAM peer, also ``smoothed_rmse`` (iSAM2's final estimate of every keyframe)
  and ``batch_rmse`` (the Levenberg-Marquardt optimum of the whole log), at its keyframes;
* ``measurements``: the sensor layer's ``range_period_steps``, ``dropped`` and
  ``outliers_injected``, as in an episode;
* from :class:`~quadobs.testbed.logs.figures.FieldFiguresSink`: ``rmse`` and ``max_error``
  after ``burn_in`` seconds, ``rmse_horizontal``, ``rmse_vertical`` (3-D), ``samples`` and
  ``diverged`` per estimator; ``tum`` (the folder and its files) with ``export_tum``.
* ``start``: whether the log's first half second shows the vehicle at rest, the velocity
  that the ranges of that rest tell, and whether the filters take it as their prior and why
  (:mod:`~quadobs.testbed.logs.start_prior`).
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.estimators import build_replay_estimators, replay_setup
from quadobs.testbed.logs.events import InTimeOnGrid, LogEvents, in_time, takes_time
from quadobs.testbed.logs.format import INPUT_FILES, LOG_FILES

__all__ = [
    "DEFAULT_ESTIMATORS",
    "anchor_extent",
    "check_burn_in",
    "check_clock_overlap",
    "check_range_units",
    "check_replay",
    "default_estimators",
    "gap_notes",
    "heard_anchors",
    "initial_guess",
    "inputs_span_note",
    "log_scenario",
    "repeated_values",
    "replayable_log",
    "run_replay",
    "without_clipped_inputs",
    "without_held_ranges",
    "without_held_truth",
    "without_impossible_ranges",
    "without_lost_truth",
    "without_zero_ranges",
]

DEFAULT_ESTIMATORS = ("augmented", "ekf")


def default_estimators(log, model: str | None = None) -> list[str]:
    """:data:`DEFAULT_ESTIMATORS`; for a log holding TDOA (which the range observer cannot
    take): where its input is an acceleration, the TDOA observer handing over to the EKF and
    the observer alone; then the EKF and the UKF. A log of ranges gets ``ekf-bias`` beside
    them (the anchors' range biases as states: real two-way ranges carry a per-anchor bias and
    positive non-line-of-sight excess, which the calibration's constant biases do not follow);
    a log of wheel odometry replayed with the model ``odometry`` (``model`` ``None``: the log's
    default) also the heading filter ``ukf-heading`` and the observer driven by its heading,
    ``augmented-heading``: the dead-reckoned heading drifts with the yaw rate's bias, which the
    others take as known (measured on both Plaza logs: docs/replay.md), and for a planar log
    ``ekf-height`` and ``augmented-height`` (anchors at other heights than the tag: each
    anchor's squared-range offset as a state) and ``ukf-lever`` (the tag off the point the
    odometry describes: its offset as states) and ``ukf-height-lever`` (the offset, the anchors'
    biases and heights together; all in docs/error-sources.md); a 3-D log of a body IMU
    also ``ekf-bias-imu`` (:mod:`quadobs.testbed.logs.imu_bias`: the accelerometer's bias and the
    estimated attitude's tilt error reach the navigation-frame acceleration as a slow bias) and
    ``ekf-bias-imu-nlos``, the same filter weighing each range by the non-line-of-sight excess
    the self-calibration estimated from the log, where it identified one (no held-out score
    tells which of the two places the vehicle better: docs/error-sources.md), and
    ``ekf-bias-imu-average``, the two averaged with equal weights."""
    if log.tdoa.shape[0]:
        tdoa = ["tdoa-handover", "tdoa-observer"] if log.input_kind in ("imu", "imu_body") else []
        return tdoa + ["ekf", "ukf"]
    names = [*DEFAULT_ESTIMATORS, "ekf-bias"]
    if log.input_kind == "imu_body" and log.dimension == 3 and model in (None, "imu"):
        names += ["ekf-bias-imu", "ekf-bias-imu-nlos"]  # the gate; the excess estimated
        names.append("ekf-bias-imu-average")  # the two averaged: neither scores better
    if log.input_kind == "odometry" and model in (None, "odometry"):
        names += ["ukf-heading", "augmented-heading"]
    if log.input_kind == "odometry" and log.dimension == 2 and model in (None, "odometry"):
        names += ["ekf-height", "augmented-height"]  # anchors above a planar tag: error-sources.md
        names.append("ukf-lever")  # the tag off the odometry's point: error-sources.md
        names.append("ukf-height-lever")  # both, and the anchors' biases: error-sources.md
    return names


_BLOCK = 8192


def initial_guess(log, world, offset: float, seed: int) -> np.ndarray:
    """The estimators' initial state: the truth at ``t_0`` moved by ``offset`` metres in a horizontal direction drawn from ``seed``.

    Where the truth starts after ``t_0``, its first position stands for the truth at ``t_0``.
    Without a truth: the beacons' centroid. Velocities (models ``cv``, ``imu``) start at zero.
    """
    n, dim = world.columns.n, log.dimension
    x0 = np.zeros(n)
    truth = _truth_at_start(log, world)
    if truth is not None:
        phi = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi)
        x0[:dim] = truth[:dim]
        x0[:2] += offset * np.array([math.cos(phi), math.sin(phi)])
    else:
        x0[:dim] = log.beacons.mean(axis=0)
    return x0


def _truth_at_start(log, world) -> np.ndarray | None:
    """The true state at ``t_0`` (its first position where the truth starts later), or None."""
    truth = world.state()
    first = log.truth_part("position")
    if not np.all(np.isfinite(truth[: log.dimension])) and first is not None and first.shape[0]:
        truth = first[0]
    return truth if np.all(np.isfinite(truth[: log.dimension])) else None


def log_scenario(log, dt: float, seed: int = 0, settings=()):
    """The scenario that configures the sensor layer of a replay: the log's beacons, ``1 / dt`` steps per second, ``seed``.

    ``settings`` (``"noise.FIELD=VALUE"``, the command line's ``--set``) may set the
    ``noise`` table only (:class:`~quadobs.testbed.scenario.NoiseSpec`): the noise, rate,
    dropout and outlier settings of the ranges, and the accelerometer's noise of an
    accelerometer log. Nothing else of a scenario applies to a log.
    """
    from quadobs.testbed.scenario import apply_settings, parse_scenario

    data: dict[str, Any] = {"noise": {}}
    data = apply_settings(data, settings)
    if set(data) != {"noise"}:
        raise QuadobsError(
            f"--set: {sorted(set(data) - {'noise'})[0]}: does not apply to a replay (only noise.* settings do)"
        )
    refused = ("airspeed_std", "airspeed_bound", "airspeed_rate") + (
        ("accel_std", "accel_bound") if log.input_kind == "odometry" else ()
    )
    for key in refused:
        if data["noise"].get(key):
            raise QuadobsError(
                f"noise.{key}: does not apply to a log of ranges and {'odometry' if 'accel' in key else log.input_kind} inputs"
            )
    grid_steps = int(math.floor((log.end - log.start) / dt + 1e-9))
    data.update(
        name=log.name,
        dimension=log.dimension,
        duration=max(grid_steps, 1) * dt,
        physics_rate=1.0 / dt,
        seed=int(seed),
        beacons=[{"position": [float(a) for a in b]} for b in log.beacons],
        # no excitation monitor in a replay: its grid made whole multiples of any dt
        excitation={
            "monitor": False,
            "step": dt,
            "window": max(round(5.0 / dt), 2) * dt,
            "update_period": max(round(0.1 / dt), 1) * dt,
        },
    )
    return parse_scenario(data, source=log.source)


def _replay_estimators(log, world, setup, events, names, x0, own=None) -> list:
    """The estimators of a replay, each taking the log's measurements at their own times where it
    can (:func:`~quadobs.testbed.logs.events.in_time`), on the grid where a sensor layer
    (``noise.*`` settings) acts on the grid's rows; sets ``world.in_time_count``. ``own``:
    ``{name: LogEvents}``, the events an estimator takes in time instead of ``events``."""
    timed = world.sensors is None
    if (events.count if timed else world.placed) == 0:
        raise QuadobsError(f"log {log.name!r}: no measurement falls inside the inputs' time span")
    built = build_replay_estimators(setup, names, x0)
    for e in built:  # on the grid, such an estimator reads a bound IMU source, which a log has not
        if hasattr(e, "bind_imu") and not (timed and takes_time(e)):
            raise QuadobsError(
                f"estimators: {e.name!r} reads the raw body IMU in time, not on the grid of a sensor layer (--set noise.*)"
            )
    world.in_time_count = events.count if timed else None
    own = own or {}
    return [
        in_time(e, own.get(e.name, events), world.times) if timed and takes_time(e) else e
        for e in built
    ]


def run_replay(
    log,
    *,
    estimators=None,
    dt: float = 0.1,
    model: str | None = None,
    initial_offset: float = 50.0,
    seed: int = 0,
    biases=None,
    out: str | Path | None = None,
    summary_path: str | Path | None = None,
    progress: bool = False,
    batch: bool = True,
    setup_options: dict | None = None,
    settings=(),
    x0=None,
    burn_in: float = 0.0,
    export_tum: str | Path | None = None,
    calibration: dict | None = None,
    as_logged=(),
) -> dict:
    """Replay ``log`` through the estimators; returns the summary (module docstring), also written to ``summary_path``.

    Parameters
    ----------
    log : RangeLog
    estimators : list of str, optional
        Default :func:`default_estimators`.
    dt : float
        Replay grid step (s), see :mod:`quadobs.testbed.worlds.replay`.
    model : {"odometry", "cv", "imu"}, optional
        Default :func:`~quadobs.testbed.worlds.replay.default_model` (by the log's inputs).
    initial_offset : float
        Distance (m) of the initial guess from the truth at ``t_0`` (:func:`initial_guess`).
    seed : int
        Draws the direction of the initial offset, and seeds the sensor layer's streams.
    biases : array_like (q,), optional
        Range bias per beacon (m), subtracted from the ranges (see
        :mod:`quadobs.testbed.logs.calibration`).
    out, summary_path : path, optional
        ``.rrd`` recording and JSON summary (checked before the replay starts).
    batch : bool
        Also solve the GTSAM peer's whole graph by Levenberg-Marquardt (the offline optimum).
    setup_options : dict, optional
        Noise settings of :class:`~quadobs.testbed.logs.estimators.ReplaySetup`.
    settings : iterable of str
        ``noise.*`` settings of the sensor layer (:func:`log_scenario`); default: none, the
        log's ranges as they are.
    x0 : array_like (n,), optional
        The initial state itself (replaces ``initial_offset``; its variance ``P0``, unless
        ``setup_options`` gives one, from its distance to the anchors,
        :func:`~quadobs.testbed.logs.estimators.initial_variance`).
    burn_in : float
        Seconds from the start before the RMSE and the maximum error are taken.
    export_tum : path, optional
        Folder for the TUM files of the truth and of each estimator (written whole).
    calibration : dict, optional
        What the self-calibration chose and why
        (:meth:`~quadobs.testbed.logs.calibration.Calibration.summary`), kept in the summary.
    as_logged : iterable of str
        Estimators that take the ranges as logged, ``biases`` not subtracted (those holding the
        range biases as states for which the calibration's biases did not predict better:
        :func:`~quadobs.testbed.logs.calibration.estimator_biases`); where measurements reach
        the estimators on the grid (``noise.*`` settings), every one takes ``biases``.
    """
    from quadobs.testbed.episode import run_loop
    from quadobs.testbed.outputs import check_outputs
    from quadobs.testbed.sensors import SensorModel
    from quadobs.testbed.worlds.replay import ReplayWorld, default_model

    names = list(estimators) if estimators else default_estimators(log, model)
    inputs = {f"log {f}": Path(log.source) / f for f in LOG_FILES} if log.source else {}
    check_outputs({"summary": summary_path, "recording": out}, inputs)
    from quadobs.testbed.logs.figures import FieldFiguresSink, check_tum_folder

    check_tum_folder(export_tum, (summary_path, out))
    field = FieldFiguresSink(log.start, burn_in, export_tum, with_truth=log.truth is not None)
    sensors = SensorModel(log_scenario(log, dt, seed, settings))
    world = ReplayWorld(
        log, dt, model or default_model(log), _BLOCK, biases, sensors=sensors, peer_batch=batch
    )
    x0, setup = _initial_state(log, world, x0, float(initial_offset), seed, setup_options)
    events = LogEvents(
        log, biases, start=world.times[0], end=world.times[-1], std=setup.measurement_std()
    )
    timed = world.sensors is None  # as _replay_estimators: the measurements reach them in time
    logged = set(as_logged) & set(names) if biases is not None and timed else set()
    raw = LogEvents(
        log, None, start=world.times[0], end=world.times[-1], std=setup.measurement_std()
    ) if logged else None  # fmt: skip
    ests = _replay_estimators(log, world, setup, events, names, x0, {n: raw for n in logged})

    def summarise(merged, completed, wall, interrupted):
        summary = _summary(
            log, world, names, merged, completed, interrupted, x0, biases, setup, out, sensors
        )
        summary["ranges"].update(_timing(log, world, ests, events))
        if calibration is not None:
            summary["calibration"] = calibration
        if logged:  # the estimators that took the ranges as logged, biases not subtracted
            summary["ranges_as_logged"] = [n for n in names if n in logged]
        summary["wall_time"] = wall
        return summary

    summary, _ = run_loop(
        summarise,
        summary_path=summary_path,
        frame=world.frame(seed),
        world=world,
        estimators=ests,
        sensors=sensors,
        out=out,
        progress=progress,
        timed=True,
        sinks=[field],
    )
    return summary


def _initial_state(log, world, x0, initial_offset: float, seed: int, options) -> tuple:
    """The initial state ``x0`` (given, else :func:`initial_guess`) and the replay's setup, whose
    ``P0`` is the guess's uncertainty: the offset of a guess drawn from the truth, else the
    anchors' extent (:func:`~quadobs.testbed.logs.estimators.initial_variance`)."""
    drawn = x0 is None and _truth_at_start(log, world) is not None
    if x0 is None:
        x0 = initial_guess(log, world, initial_offset, seed)
    x0 = np.array(x0, dtype=float)
    return x0, replay_setup(log, world, options, initial_offset if drawn else None, x0)


def _timing(log, world, ests, events) -> dict:
    """How the measurements reached the estimators: in time (each at its own timestamp, none
    merged) or on the grid (floored onto its steps, a second range to a beacon in a step merged)."""
    timed = [e.name for e in ests if isinstance(e, InTimeOnGrid)]
    grid = [e.name for e in ests if not isinstance(e, InTimeOnGrid)]
    out = {"tdoa_in_log": int(log.tdoa.shape[0]), "in_time": timed, "on_grid": grid}
    if timed:
        out["measurements_in_time"] = events.count
        # the grid ends within dt of the log's end: what lies after its last time is not replayed
        n_log = int(log.ranges.shape[0] + log.tdoa.shape[0])
        out["after_the_last_step"] = sum(
            1 for t in np.concatenate([log.ranges[:, 0], log.tdoa[:, 0]]) if t >= world.times[-1]
        )
        out["before_the_first_input"] = n_log - events.count - out["after_the_last_step"]
    if not grid:
        out["placed"], out["merged"] = events.count, 0
    return out


def without_zero_ranges(log):
    """``log`` without its ranges of exactly 0 m, and how many there were.

    A two-way ranging radio reports 0 where an exchange failed; a tag is never at an
    antenna's phase centre. Taken as a measurement, one such range pulls an estimator without
    a gate by the whole distance to that anchor (docs/replaying-your-data.md: one among 453
    moved the EKF's RMSE from 0.078 to 0.109 m)."""
    import dataclasses

    from quadobs.testbed.logs.schema import RANGE

    keep = log.ranges[:, RANGE.range] != 0.0
    if keep.all():
        return log, 0
    return dataclasses.replace(log, ranges=log.ranges[keep], range_std=log.range_std[keep]), int(
        (~keep).sum()
    )


#: A range no radio measures: at or below the first (m; an error code of -1, where an antenna
#: delay takes a range below zero by tenths of a metre at most), or an exact value beyond the
#: second times the largest distance between the anchors ranged to, repeated at least the
#: third's count of times and making at least the fourth's share of the ranges within the
#: fifth (m) of it: a radio's code of no range (655.35, 65.535, 999, 2^32 - 1 mm), one value
#: over and over, where a tag far from its anchors ranges a spread of distinct values.
IMPOSSIBLE_RANGES = (-1.0, 2.0, 3, 0.5, 0.5)


def _range_codes(rho: np.ndarray, bound: float) -> np.ndarray:
    """The exact values of ``rho`` beyond ``bound`` that :data:`IMPOSSIBLE_RANGES` takes for a
    radio's codes of no range."""
    _, _, repeats, share, near = IMPOSSIBLE_RANGES
    beyond = np.sort(rho[rho > bound])
    values, counts = np.unique(beyond, return_counts=True)
    around = np.searchsorted(beyond, values + near, side="right") - np.searchsorted(
        beyond, values - near, side="left"
    )
    return values[(counts >= repeats) & (counts >= share * around)]


def without_impossible_ranges(log):
    """``log`` without the ranges that no radio measures (:data:`IMPOSSIBLE_RANGES`), and a
    note naming them, or None.

    A radio's firmware writes a code where an exchange failed (0 m is left out by
    :func:`without_zero_ranges`; -1, 655.35 = 2^16 - 1 cm, 65.535, 999, 2^32 - 1 mm are
    others). Taken as ranges they drag every filter by hundreds of metres: 0.7 % of a
    flight's ranges at 655.35 m took its best default from 0.176 to 0.326 m and its EKF to
    47 m (docs/replaying-your-data.md). A code is one exact value repeated far beyond the
    anchors ranged to (:func:`_range_codes`); a tag genuinely far from a cluster of anchors
    ranges distinct values, kept, and so are ranges in another unit (mm), which
    :func:`check_range_units` refuses. A code written once is kept (a gate takes one range)."""
    import dataclasses

    from quadobs.testbed.logs.schema import RANGE

    if log.ranges.shape[0] == 0:
        return log, None
    low, times = IMPOSSIBLE_RANGES[:2]
    ranged = log.beacon_index(np.unique(log.ranges[:, RANGE.beacon]))
    high = times * anchor_extent(log.beacons[ranged]) if ranged.size > 1 else math.inf
    rho = log.ranges[:, RANGE.range]
    bad = (rho <= low) | np.isin(rho, _range_codes(rho, high))
    if not bad.any():
        return log, None
    values, counts = np.unique(rho[bad], return_counts=True)
    top = np.argsort(-counts, kind="stable")[:3]
    listed = ", ".join(f"{values[k]:.6g} m ({counts[k]})" for k in top)
    more = ", ..." if values.size > 3 else ""
    note = (
        f"ranges of {low:g} m or less, or one value repeated beyond {high:.4g} m ({times:g} "
        f"times the anchors' extent), which no radio measures (a code of no range), left out: "
        f"{int(bad.sum())} ({listed}{more})"
    )
    keep = ~bad
    return dataclasses.replace(log, ranges=log.ranges[keep], range_std=log.range_std[keep]), note


#: How far (m) from the origin the truth's rows about a row at exactly the origin must lie for
#: :func:`without_lost_truth` to take it for a motion capture's row of a lost body: farther
#: than a vehicle moves between two rows (0.25 m: 5 m/s at 20 Hz).
LOST_TRUTH_JUMP = 0.25


def without_lost_truth(log):
    """``log`` without the truth's rows at exactly the origin between rows far from it, and a
    note, or None.

    A motion capture that loses the body (occluded markers) writes zeros in some exports;
    scored as the truth, each such row counts the vehicle's whole distance from the origin as
    error (a flight whose truth lost the body eight times for 0.2 to 1 s: the best default
    0.176 -> 0.807 m, docs/replaying-your-data.md). A row whose position is exactly zero and
    whose nearest other rows before and after lie farther than :data:`LOST_TRUTH_JUMP` from
    the origin is left out: the truth has a gap there, interpolated across where it is short
    (:func:`~quadobs.testbed.worlds.replay.wide_gaps`), unscored where it is wide. A truth
    whose quaternion is zeroed with the position is refused on reading (not a unit
    quaternion) before this step. A vehicle that passes through the origin does so between
    rows near it, and keeps them."""
    import dataclasses

    position = log.truth_part("position") if log.truth is not None else None
    if position is None or position.shape[0] < 3:
        return log, None
    raw = log.truth[:, [log.truth_columns.index(c) for c in ("x", "y", "z")[: log.dimension]]]
    zero = np.all(raw == 0.0, axis=1)
    if not zero.any() or zero.all():
        return log, None
    others = np.flatnonzero(~zero)
    away = np.linalg.norm(raw[others], axis=1) > LOST_TRUTH_JUMP
    rows = np.flatnonzero(zero)
    after = np.clip(np.searchsorted(others, rows), 0, others.size - 1)
    before = np.clip(after - 1, 0, others.size - 1)
    lost = rows[away[before] & away[after]]
    if lost.size == 0:
        return log, None
    keep = np.ones(log.truth.shape[0], dtype=bool)
    keep[lost] = False
    note = (
        f"truth: {lost.size} rows at exactly the origin between rows farther than "
        f"{LOST_TRUTH_JUMP:g} m from it (a motion capture that lost the body), left out: the "
        "truth has a gap there (interpolated across where short)"
    )
    return dataclasses.replace(log, truth=log.truth[keep]), note


#: :func:`without_clipped_inputs`'s bounds: the fewest rows of an accelerometer's or a
#: gyroscope's column at exactly its largest (or least) value, and the band below that value
#: (a share of it) that must hold fewer rows than it, for the value to be a full scale.
CLIPPED_INPUTS = (3, 0.01)
#: The full scales of MEMS accelerometers (in g) and gyroscopes (deg/s) that
#: :func:`without_clipped_inputs` knows, and how far (a share) a calibrated output's value at
#: one may lie from it (a scale factor's correction, an int16's 32767 / 32768).
FULL_SCALES = {"accel": (2, 4, 8, 16, 24, 32), "gyro": (125, 250, 500, 1000, 2000, 4000)}
FULL_SCALE_TOLERANCE = 0.03


def _at_full_scale(column: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """The rows (a mask) of one IMU column at a full scale, and the values found: an extreme
    of the column within :data:`FULL_SCALE_TOLERANCE` of one of ``scales`` (in the column's
    unit), held by at least ``CLIPPED_INPUTS[0]`` rows and by more rows than the band of
    ``CLIPPED_INPUTS[1]`` of its size just inside it (a pile at the edge: a sensor read
    beyond its range gives its full scale; a signal that only peaks there does not pile)."""
    fewest, band = CLIPPED_INPUTS
    rows, found = np.zeros(column.size, dtype=bool), []
    for edge in (float(column.max()), float(column.min())):
        if not edge or np.min(np.abs(abs(edge) / scales - 1.0)) > FULL_SCALE_TOLERANCE:
            continue
        at = column == edge
        same_side = np.sign(column) == np.sign(edge)
        inside = same_side & (np.abs(column) >= (1.0 - band) * abs(edge))
        if np.count_nonzero(at) >= fewest and 2 * np.count_nonzero(at) > np.count_nonzero(inside):
            rows |= at
            found.append(edge)
    return rows, found


def without_clipped_inputs(log):
    """``log`` without the IMU rows at a sensor's full scale, and a note, or None.

    An accelerometer or gyroscope driven beyond its range (a vibration's burst, a hard landing)
    reads its full scale, and the burst's mean is lost: three bursts of 0.1 s clipped at 16 g
    and 2000 deg/s put a flight's IMU filters 9.9 m off and the best default went 0.176 ->
    0.909 m (docs/replaying-your-data.md). A row with any column at a full scale
    (:func:`_at_full_scale`, :data:`FULL_SCALES`) that the column reaches at both its edges is
    left out: the row before it is held across, as over any gap
    of the inputs (the same flight: 0.176 m). A column clipped at one edge only (a vibration
    about an offset, cut on one side) keeps its rows, with a note: left out, its other side's
    rows alone would move the mean further (a flight's stand-in 0.182 m with them, 0.220 m
    without). Only a body IMU's rows are read so: a
    navigation-frame acceleration is no sensor's reading, and wheel odometry has no full
    scale."""
    import dataclasses

    if log.input_kind != "imu_body" or log.inputs.shape[0] < 10:
        return log, None
    from quadobs.testbed.logs.format import INPUT_FILES, INPUT_KINDS

    names = INPUT_KINDS[log.input_kind]
    accel = float(log.gravity) * np.array(FULL_SCALES["accel"], dtype=float)
    gyro = np.radians(np.array(FULL_SCALES["gyro"], dtype=float))
    clipped = np.zeros(log.inputs.shape[0], dtype=bool)
    said, one_side = [], []
    for c, name in enumerate(names[: log.inputs.shape[1] - 1]):
        rows, found = _at_full_scale(log.inputs[:, c + 1], gyro if name[0] == "g" else accel)
        if len(found) == 2:  # clipped both ways: the rows' mean says nothing of the motion
            clipped |= rows
            said.append(f"{name} at {found[0]:.6g} and {found[1]:.6g}")
        elif found:
            one_side.append(f"{name} at {found[0]:.6g}")
    if clipped.all() or not (clipped.any() or one_side):
        return log, None
    where = INPUT_FILES[log.input_kind]
    notes = [
        f"{where}: {np.count_nonzero(clipped)} rows at a sensor's full scale ({', '.join(said)}: "
        "readings beyond its range either way), left out: the row before each held across"
    ] * bool(said)
    notes += [
        f"{where}: rows at a sensor's full scale on one side ({', '.join(one_side)}), kept: "
        "left out, the other side's rows would bias the mean further"
    ] * bool(one_side)
    kept = log
    if clipped.any():  # the file's rows of those kept, for the messages that name one
        read = log.file_rows.get(where, np.arange(clipped.size))
        rows = {**log.file_rows, where: np.asarray(read)[~clipped]}
        kept = dataclasses.replace(log, inputs=log.inputs[~clipped], file_rows=rows)
    return kept, "; ".join(notes)


#: :func:`without_held_truth`'s bounds: the fewest copies in a spell of the truth's rows that
#: repeat the position before them exactly, and how many times the truth's fastest speed
#: elsewhere (the 99th percentile of its steps over their intervals) the step that ends the
#: spell must imply. A vehicle at rest that moves off takes a small first step; a motion
#: capture that held the last pose of a lost body jumps to where the body has gone.
HELD_TRUTH = (2, 3.0)


def without_held_truth(log):
    """``log`` without the truth's rows that hold a lost body's last position, and a note, or None.

    A motion capture (or the export of one) that loses the body may repeat its last pose
    until it finds the body again; scored as the truth, the estimators are charged with
    the vehicle's motion over the spell (a flight whose truth was held over eight losses of
    0.2 to 1 s: the best default 0.176 -> 0.210 m, docs/replaying-your-data.md). A spell of
    at least ``HELD_TRUTH[0]`` rows repeating the position before them exactly, ended by a row
    whose step implies a speed more than ``HELD_TRUTH[1]`` times the 99th percentile of the
    truth's speeds between its other rows, loses its copies (the first row, the last pose
    seen, is kept): the truth has a gap there, interpolated across where it is short
    (:func:`~quadobs.testbed.worlds.replay.wide_gaps`), unscored where it is wide. A vehicle at
    rest written to a coarse resolution repeats its position too, but moves off by a small
    step, and keeps its rows; so does a truth written at a multiple of its own rate."""
    import dataclasses

    if log.truth is None or log.truth.shape[0] < 10 or log.truth_part("position") is None:
        return log, None
    t = log.truth[:, 0]
    p = log.truth[:, [log.truth_columns.index(c) for c in ("x", "y", "z")[: log.dimension]]]
    step, dt = np.linalg.norm(np.diff(p, axis=0), axis=1), np.diff(t)
    from quadobs.testbed.logs.schema import true_runs

    begins, ends = true_runs(step == 0.0)  # step i: row i + 1 repeats row i
    first, last = begins + 1, ends  # the copies' rows, inclusive
    ended = (last - first + 1 >= HELD_TRUTH[0]) & (last + 1 < t.size)
    ended[ended] &= dt[last[ended]] > 0.0
    first, last = first[ended], last[ended]
    reference = (step > 0.0) & (dt > 0.0)
    reference[last] = False  # the steps that end a spell
    if np.count_nonzero(reference) < 10 or first.size == 0:
        return log, None
    fastest = float(np.percentile(step[reference] / dt[reference], 99))
    with np.errstate(divide="ignore"):
        speed = step[last] / dt[last]
    held = speed > HELD_TRUTH[1] * fastest
    if not held.any():
        return log, None
    keep = np.ones(t.size, dtype=bool)
    for a, b in zip(first[held], last[held], strict=True):
        keep[a : b + 1] = False
    spans = t[last[held]] - t[first[held] - 1]
    note = (
        f"truth: {t.size - keep.sum()} rows over {held.sum()} spells (the longest "
        f"{spans.max():.3g} s) repeating the position before them exactly, each ended by a "
        f"step faster than {HELD_TRUTH[1]:g} times the truth's speed elsewhere (a motion "
        "capture holding a lost body's last pose), left out: the truth has a gap there "
        "(interpolated across where short)"
    )
    return dataclasses.replace(log, truth=log.truth[keep]), note


#: The least share of a log's measurements that repeat their anchor's previous value exactly,
#: and how many times the repeats a genuine radio would give at the values' resolution, beyond
#: which :func:`without_held_ranges` takes the repeats for a logger's held values.
HELD_RANGES = (0.2, 5.0)


def repeated_values(keys: np.ndarray, times: np.ndarray, values: np.ndarray) -> tuple:
    """The measurements that repeat their key's (anchor's) previous value exactly, and how
    many repeats a genuine radio would give.

    Returns a mask of the repeats, in the order given, and the expected count. Consecutive
    independent ranges of one anchor, written at a resolution ``q`` (the least gap between
    its distinct values), differ by ``d`` with a density ``f`` that is smooth over a few
    ``q`` (the noise, 0.02 m or more for UWB, spans several): the lattice point ``d = 0``
    then holds about as many pairs as each of ``d = +-q``, ``f(0) q``. So the count of pairs
    at ``+-q``, halved, is the expected count of exact repeats (at full precision none).
    """
    repeat = np.zeros(values.size, dtype=bool)
    expected = 0.0
    for key in np.unique(keys):
        idx = np.flatnonzero(keys == key)
        idx = idx[np.argsort(times[idx], kind="stable")]
        v = values[idx]
        if v.size < 2:
            continue
        d = np.diff(v)
        repeat[idx[1:]] = d == 0.0
        gaps = np.diff(np.unique(np.round(v, 9)))
        q = max(float(gaps[gaps > 0].min()) if np.any(gaps > 0) else 0.0, 1e-9)
        expected += 0.5 * np.count_nonzero((d != 0.0) & (np.abs(d) <= 1.5 * q))
    return repeat, expected


def without_held_ranges(log):
    """``log`` without the ranges (and TDOA) that a logger held, and a note for each kind.

    A logger that writes every anchor's latest range at its own rate (a log block of a
    flight controller, a table of one column per anchor) repeats a range until the radio
    measures the next: each is then counted several times, at times up to one period late
    (a flight stand-in logged so at 100 Hz: the best default 0.176 -> 0.272 m; without the
    copies 0.175 m, docs/replaying-your-data.md). Where a kind's exact repeats of an
    anchor's previous value are at least :data:`HELD_RANGES`'s share of its measurements
    and that many times the count a genuine radio gives at the values' resolution
    (:func:`repeated_values`), the repeats are left out, keeping each value at its first
    time; otherwise the log is as given."""
    import dataclasses

    from quadobs.testbed.logs.schema import RANGE, TDOA

    share, ratio = HELD_RANGES
    changes, notes = {}, []
    tables = (
        ("ranges", "range_std", log.ranges, [RANGE.beacon], RANGE.range, "their anchor's"),
        (
            "tdoa",
            "tdoa_std",
            log.tdoa,
            [TDOA.anchor_i, TDOA.anchor_j],
            TDOA.difference,
            "their pair's",
        ),
    )
    for name, std, table, key_cols, value_col, whose in tables:
        if table.shape[0] < 2:
            continue
        keyed = table[:, key_cols[0]] if len(key_cols) == 1 else table[:, key_cols]
        keys = np.unique(keyed, axis=None if len(key_cols) == 1 else 0, return_inverse=True)[1]
        keys = keys.ravel()
        repeat, expected = repeated_values(keys, table[:, 0], table[:, value_col])
        count = int(repeat.sum())
        if count < share * table.shape[0] or count <= ratio * max(expected, 1.0):
            continue
        changes[name], changes[std] = table[~repeat], getattr(log, std)[~repeat]
        notes.append(
            f"{name} that repeat {whose} previous value exactly (a logger writing held values, "
            "or rows written twice), "
            f"left out: {count} of {table.shape[0]} (at the values' resolution a radio repeats "
            f"about {expected:.0f})"
        )
    return (dataclasses.replace(log, **changes) if changes else log), notes


def heard_anchors(log):
    """``log`` without the anchors that no range or TDOA names, and those anchors' ids.

    An anchor never heard carries nothing for the estimators, yet its position would enter
    what the replay derives from the anchors' geometry (the initial guess and its variance
    without a truth, the typical range, a state per anchor): the log replays as if it were
    not listed."""
    import dataclasses

    from quadobs.testbed.logs.schema import RANGE, TDOA

    named = np.concatenate(
        [log.ranges[:, RANGE.beacon], log.tdoa[:, TDOA.anchor_i], log.tdoa[:, TDOA.anchor_j]]
    )
    heard = np.isin(log.beacon_ids, named)
    if heard.all():
        return log, []
    unheard = [int(i) for i in log.beacon_ids[~heard]]
    heights = None if log.anchor_heights is None else log.anchor_heights[heard]
    return dataclasses.replace(
        log, beacon_ids=log.beacon_ids[heard], beacons=log.beacons[heard], anchor_heights=heights
    ), unheard


def replayable_log(log, keep_anchors: bool = False, clock_offset: float = 0.0) -> tuple:
    """``log`` as the replay takes it, and one line for each thing left out: its ranges of 0 m
    (:func:`without_zero_ranges`) and others no radio measures
    (:func:`without_impossible_ranges`), a logger's held copies (:func:`without_held_ranges`),
    a motion capture's lost rows (:func:`without_lost_truth`, :func:`without_held_truth`),
    then, unless ``keep_anchors``
    (biases given per listed anchor), the anchors that no measurement names
    (:func:`heard_anchors`); and the notes on the log. ``clock_offset``: the inputs' offset
    given (``--clock-offset SECONDS``), applied later, by which the inputs' span is judged.
    The reader's lines (rows left out blank, rows sorted: ``log.read_notes``) come first."""
    notes = list(log.read_notes)
    log, zeros = without_zero_ranges(log)
    if zeros:
        notes.append(f"ranges of 0 m (a radio's failed exchange), left out: {zeros}")
    log, impossible = without_impossible_ranges(log)
    notes += [impossible] if impossible else []
    log, held = without_held_ranges(log)
    notes += held
    log, lost = without_lost_truth(log)
    notes += [lost] if lost else []
    log, held_truth = without_held_truth(log)
    notes += [held_truth] if held_truth else []
    log, clipped = without_clipped_inputs(log)
    notes += [clipped] if clipped else []
    if not keep_anchors:
        log, unheard = heard_anchors(log)
        if unheard:
            notes.append(f"anchors never ranged, left out: {', '.join(map(str, unheard))}")
    notes += gap_notes(log)
    from quadobs.testbed.logs.clock_offset import with_input_offset

    span = inputs_span_note(with_input_offset(log, clock_offset))  # as the offset moves them
    notes += [span] if span else []
    mapping, lagged = anchor_mapping(log), truth_lag(log)  # each can look like the other
    explained = _lag_explains(mapping, lagged)
    anchors = None if explained else _anchor_text(log, mapping)
    lag = _lag_text(*lagged) if explained and lagged is not None else None
    heights = None if anchors or lag else truth_heights_note(log)
    offset = None if anchors or lag or heights else truth_offset_note(log)  # they look offset too
    moved = with_input_offset(log, clock_offset)
    found = [truth_span_note(log), lag, anchors, heights, offset]
    found += [truth_odometry_note(moved), truth_attitude_note(moved)]
    from quadobs.testbed.logs.range_noise import OWN_NOISE_KINDS, stated_std_note

    if log.input_kind not in OWN_NOISE_KINDS:  # else checked per anchor with the noise
        found.append(stated_std_note(log))
    notes += [n for n in found if n]
    plane = anchor_plane(log.beacons)
    if plane is not None:
        notes.append(
            f"the anchors lie in one plane (within {plane:.3g} m): a position and its mirror "
            "image through that plane give the same ranges, so an estimate may settle on the "
            "mirror side"
        )
    else:
        heard = heard_plane_note(log)
        notes += [heard] if heard else []
    return log, notes


#: :func:`heard_plane_note`'s window: at least this many seconds, and this many times the
#: median interval between two ranges of one anchor (a round of the tag's round robin); and
#: the least share of the ranges the log's median interval gives such a window for it to be
#: read (fewer: a radio's outage, which the gap note says, not anchors unheard).
HEARD_WINDOW = (2.0, 3.0, 0.25)


def _round_period(log) -> float:
    """The median over the anchors of the median interval between two ranges of one anchor."""
    t, h = log.ranges[:, 0], log.ranges[:, 1]
    periods = [np.median(np.diff(t[h == k])) for k in np.unique(h) if np.count_nonzero(h == k) > 2]
    return float(np.median(periods)) if periods else math.inf


def heard_plane_note(log) -> str | None:
    """A line where, for a span of a 3-D log, the anchors heard lie in one plane (or are fewer
    than four) while the anchors listed do not, else None.

    Each window of :data:`HEARD_WINDOW` (moved by half its length) whose ranges name anchors
    in one plane (:func:`anchor_plane`) leaves a position and its mirror image through that
    plane the same ranges; the longest run of such windows is said. A flight whose ceiling
    anchors were heard only from 20 s (the floor's four at one height before) settled on the
    mirror side below the floor, 2.8 m off over 5 to 20 s (docs/replaying-your-data.md)."""
    if log.dimension != 3 or log.ranges.shape[0] < 20:
        return None
    width = max(HEARD_WINDOW[0], HEARD_WINDOW[1] * _round_period(log))
    t, ids = log.ranges[:, 0], log.beacon_index(log.ranges[:, 1])
    starts = np.arange(t[0], max(t[-1] - width, t[0]) + 1e-9, width / 2)
    steps = np.diff(t)
    expected = width / max(float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0, 1e-9)
    flat = []
    lo, hi = np.searchsorted(t, starts), np.searchsorted(t, starts + width)
    for i, j in zip(lo, hi, strict=True):
        heard = np.unique(ids[i:j])
        quiet = j - i < HEARD_WINDOW[2] * expected  # a radio's outage
        flat.append(not quiet and (heard.size < 4 or anchor_plane(log.beacons[heard]) is not None))
    best, run, first = (0, 0), 0, 0
    for k, f in enumerate(flat):
        run = run + 1 if f else 0
        first = k - run + 1 if f else first
        best = max(best, (run, first))
    if best[0] < 2:
        return None
    a = float(starts[best[1]])
    b = min(float(starts[best[1] + best[0] - 1]) + width, float(t[-1]))
    window = (t >= a) & (t <= b)
    heard = np.unique(log.ranges[window, 1])
    named = ", ".join(str(int(i)) for i in heard)
    where = (
        "which lie in one plane: there a position and its mirror image through it give the "
        "same ranges, so an estimate may settle on the mirror side"
        if heard.size >= 3
        else "too few to place a position in space"
    )
    return (
        f"the ranges from {max(a - log.start, 0.0):.3g} to {b - log.start:.3g} s into the log "
        f"name only anchor{'s' if heard.size > 1 else ''} {named}, {where} (the other "
        "anchors switched on late, out of range or blocked?)"
    )


def gap_notes(log) -> list[str]:
    """One line for each of the measurements (ranges and TDOA together), the inputs and the
    truth with gaps (:func:`~quadobs.testbed.worlds.replay.wide_gaps`): how many, the longest
    and when (from the log's start), and what the replay does across them. A gap of the
    measurements alone is a radio's outage, or the measurements' clock stepped forward (a
    host's clock set by NTP mid-log: every measurement after it late by the gap's excess)."""
    from quadobs.testbed.worlds.replay import wide_gaps

    what = {
        "measurements": "each estimator predicts across it (a radio's outage, or the "
        "measurements' clock stepped forward?)",
        "inputs": "each input held across it",
        "truth": "no error scored there",
    }
    measured = np.sort(np.concatenate([log.ranges[:, 0], log.tdoa[:, 0]]))
    notes = []
    for name, t in (
        ("measurements", measured),
        ("inputs", None if log.input_kind == "none" else log.inputs[:, 0]),
        ("truth", None if log.truth is None else log.truth[:, 0]),
    ):
        if t is None or t.size < 3:
            continue
        wide = wide_gaps(t)
        if wide.size:
            length = np.diff(t)[wide]
            k = int(wide[np.argmax(length)])
            longest = f"{float(length.max()):.3g} s from {t[k] - log.start:.3g} s into the log"
            count = (
                f"a gap of {longest}"
                if wide.size == 1
                else f"{wide.size} gaps, the longest {longest}"
            )
            notes.append(f"{name}: {count}: {what[name]}")
    return notes


#: The lags (s) of the truth against the ranges that :func:`truth_lag_note` tries: -3 to 3 s by
#: 0.05 s (a motion capture on another clock, or stamped on receipt), and beyond them by
#: :data:`TRUTH_LAG_COARSE`.
TRUTH_LAGS = np.round(np.arange(-3.0, 3.0 + 1e-9, 0.05), 2)
#: The step (s) of :func:`truth_lag_note`'s wider search, out to half the shorter of the
#: truth's and the ranges' spans, at most :data:`TRUTH_LAG_REACH` (s): a truth on another
#: clock by seconds (GPS time against UTC: 18 s), not an hour's time zone, which
#: :func:`check_clock_overlap` refuses. A best lag found there is refined by 0.05 s.
TRUTH_LAG_COARSE = 0.25
TRUTH_LAG_REACH = 120.0
#: The most ranges :func:`truth_lag_note` reads (a long log's sampled to these), and the most
#: its wider search reads at each coarse lag (its best lag then refined on the former).
TRUTH_LAG_RANGES = 20000
TRUTH_LAG_COARSE_RANGES = 1000


def truth_lag(log) -> tuple | None:
    """``(lag, spread, spread_at_zero, at_edge)`` where the truth agrees with the ranges much
    better at another time than its own, else None.

    For each lag ``s`` of :data:`TRUTH_LAGS` and of the wider search
    (:data:`TRUTH_LAG_COARSE`), each range's residual against the truth's point
    at its time plus ``s``, ``rho - |p(t + s) - a_h|`` (the horizontal distance in a planar
    log), less its anchor's median residual (a bias, a height), and the median of their
    absolute values: the spread of the ranges about the truth moved by ``s``. Said where the
    least spread lies 0.25 s or more from 0 and is under 0.7 times the spread at 0: a truth
    that scores every estimator from the wrong time (the figures of a truth 2 s late are
    metres, not the estimators' error). Ranges outside the truth's span at a lag are not
    counted at it, and a lag at which fewer than a quarter of them lie inside is not tried;
    a long log's ranges are sampled (a fixed seed) to :data:`TRUTH_LAG_RANGES`, and to
    :data:`TRUTH_LAG_COARSE_RANGES` for the wider search's coarse lags. A tag
    mounted ``l`` ahead of the truth's point on a vehicle driving forwards at ``v`` looks the
    same, a lag of ``l / v``: the note names both."""
    truth = log.truth
    if truth is None or truth.shape[0] < 2 or log.ranges.shape[0] < 20:
        return None
    t_truth, p_truth = truth[:, 0], log.truth_part("position")
    if p_truth is None:
        return None
    full = _lag_spread(log, _sampled(log.ranges, TRUTH_LAG_RANGES), t_truth, p_truth)
    lags, spreads = TRUTH_LAGS, np.array([full(float(s)) for s in TRUTH_LAGS])
    t = log.ranges[:, 0]
    wide = _truth_lags(min(t[-1] - t[0], t_truth[-1] - t_truth[0]))
    wide = wide[np.abs(wide) > TRUTH_LAGS[-1]]
    if wide.size:  # coarsely on fewer ranges, the best refined on all
        few = _lag_spread(log, _sampled(log.ranges, TRUTH_LAG_COARSE_RANGES), t_truth, p_truth)
        coarse = np.array([few(float(s)) for s in wide])
        if np.isfinite(coarse).any():
            near = np.round(wide[np.argmin(coarse)] + np.arange(-0.2, 0.2 + 1e-9, 0.05), 2)
            lags = np.concatenate([lags, near])
            spreads = np.concatenate([spreads, [full(float(s)) for s in near]])
    at_zero = spreads[np.flatnonzero(lags == 0.0)[0]]
    k = int(np.argmin(spreads))
    best = float(lags[k])
    if not (abs(best) >= 0.25 and math.isfinite(at_zero) and spreads[k] < 0.7 * at_zero):
        return None
    reach = float(np.max(np.abs(wide))) if wide.size else float(TRUTH_LAGS[-1])
    return best, float(spreads[k]), float(at_zero), abs(best) >= reach - 0.2 * bool(wide.size)


def _sampled(rows: np.ndarray, most: int) -> np.ndarray:
    """``rows`` (sorted by time), or ``most`` of them drawn with a fixed seed: a sample, not a
    stride (a round robin aliases a stride)."""
    if rows.shape[0] <= most:
        return rows
    keep = np.random.default_rng(0).choice(rows.shape[0], most, replace=False)
    return rows[np.sort(keep)]


def _lag_spread(log, rows: np.ndarray, t_truth: np.ndarray, p_truth: np.ndarray):
    """The spread (m) of ``rows``' ranges about the truth moved by a lag ``s`` (s), as a
    function of ``s`` (:func:`truth_lag`): each range's residual less its anchor's median,
    the median of their absolute values; infinite where fewer than a quarter of the ranges
    (and than 20) lie inside the truth's span at that lag."""
    t, anchor, rho = rows[:, 0], log.beacon_index(rows[:, 1]), rows[:, 2]
    a = np.asarray(log.beacons, dtype=float)[anchor]
    dim = log.dimension

    def spread(s: float) -> float:
        inside = (t + s >= t_truth[0]) & (t + s <= t_truth[-1])
        if np.count_nonzero(inside) < max(20, t.size // 4):
            return math.inf
        p = np.column_stack([np.interp(t[inside] + s, t_truth, p_truth[:, i]) for i in range(dim)])
        e = rho[inside] - np.linalg.norm(p - a[inside], axis=1)
        h = anchor[inside]
        medians = np.zeros(log.beacons.shape[0])
        for k in np.unique(h):
            medians[k] = np.median(e[h == k])
        return float(np.median(np.abs(e - medians[h])))

    return spread


def truth_lag_note(log) -> str | None:
    """:func:`truth_lag`'s finding as a line, else None."""
    found = truth_lag(log)
    return None if found is None else _lag_text(*found)


def _lag_text(best: float, spread: float, at_zero: float, at_edge: bool) -> str:
    """The truth-lag note (:func:`truth_lag`) for the best lag ``best`` (s), the spreads (m)
    at it and at zero, and whether it lies at the search's edge."""
    edge = "or more " if at_edge else ""
    return (
        f"truth.csv agrees with the ranges best as if stamped {abs(best):.2f} s {edge}"
        f"{'late' if best > 0 else 'early'} (the ranges spread {spread:.3g} m about it "
        f"moved so, {at_zero:.3g} m at its own times): is the truth on the ranges' clock, or "
        "its point off the tag's along the path (a lever arm)? Or are the ranges stamped "
        f"{'early (on another clock)' if best > 0 else 'late (on receipt, on another clock)'}, "
        "then against the "
        "inputs as well (--clock-offset)? A truth on another clock scores every estimator "
        "from the wrong time"
    )


def truth_span_note(log) -> str | None:
    """A line where the truth's span covers less than half of the measurements', else None:
    every estimator is scored over that part alone, and a truth on another clock (seconds
    off, short of no overlap at all: :func:`check_clock_overlap`) looks so. A truth 30 s late
    on a 40 s flight was scored over its last 10 s, 2.9 m off, and said nothing of its clock
    (the lag search reaches half the shorter span)."""
    measured = _measured_span(log)
    if log.truth is None or not log.truth.shape[0] or measured is None:
        return None
    a, b = measured
    ta, tb = float(log.truth[0, 0]), float(log.truth[-1, 0])
    covered = max(0.0, min(b, tb) - max(a, ta))
    if b <= a or covered >= 0.5 * (b - a):
        return None
    return (
        f"truth.csv covers {covered:.3g} s of the measurements' {b - a:.3g} s (it spans "
        f"{ta - log.start:.3g} to {tb - log.start:.3g} s into the log): every estimator is "
        "scored there alone; is the truth on the ranges' clock?"
    )


def _truth_lags(span: float) -> np.ndarray:
    """:data:`TRUTH_LAGS`, and the wider search's lags out to half ``span`` (s), at most
    :data:`TRUTH_LAG_REACH`, by :data:`TRUTH_LAG_COARSE`: sorted, without repeats."""
    reach = min(TRUTH_LAG_REACH, 0.5 * span)
    n = int(reach // TRUTH_LAG_COARSE)
    coarse = np.round(TRUTH_LAG_COARSE * np.arange(-n, n + 1), 2)
    return np.union1d(TRUTH_LAGS, coarse[np.abs(coarse) > TRUTH_LAGS[-1]])


#: :func:`truth_offset_note`'s search: the reach (m) of the offsets tried per axis, its coarse
#: and fine steps (m), the heights (m) tried for a planar log's anchors above the tag, the
#: least offset (m) it says, and the most the ranges' spread may keep of its value at the
#: truth's own position. Measured on Plaza1, Plaza2 and 22 stand-ins whose truth is right:
#: offsets up to 0.30 m keeping 0.99 of the spread (Plaza1), 0.27 m keeping 0.95 (a robot's),
#: none past both bounds; a robot's truth moved 0.3 m keeps 0.90, a flight's moved 0.5 m 0.74.
TRUTH_OFFSET_SEARCH = (1.0, 0.2, 0.05, np.arange(0.0, 3.01, 0.2), 0.3, 0.92)
#: The most ranges :func:`truth_offset_note` reads (a long log's sampled to these).
TRUTH_OFFSET_RANGES = 3000


def _offset_spread(p, anchor, rho, beacons, heights, delta) -> float:
    """The ranges' spread about the truth moved by ``delta``: the median over all ranges of
    their absolute deviation from their anchor's median residual (a bias), each anchor's
    residual taken at the height in ``heights`` that spreads it least (a planar log)."""
    dev = np.empty_like(rho)
    for h in np.unique(anchor):
        mine = anchor == h
        d2 = np.sum((p[mine] + delta - beacons[h]) ** 2, axis=1)
        best = None
        for z in heights:
            e = rho[mine] - np.sqrt(d2 + z * z)
            a = np.abs(e - np.median(e))
            if best is None or np.median(a) < np.median(best):
                best = a
        dev[mine] = best
    return float(np.median(dev))


def truth_offset_note(log) -> str | None:
    """A line where the truth fits the ranges much better moved by a constant offset (its
    origin not the anchors'), else None.

    Over offsets within :data:`TRUTH_OFFSET_SEARCH`'s reach (a grid, then a finer one about
    its best), the ranges' spread about the moved truth (:func:`_offset_spread`: each
    anchor's bias, and in a planar log its height above the tag, fitted). Said where the best
    offset is :data:`TRUTH_OFFSET_SEARCH`'s least or longer and leaves at most its share of
    the spread at the truth's own position: a truth 0.3 m off cost a robot's stand-in 3.85
    times its error, 1 m 10.5 times, 0.5 m a flight's 3.6 times, all unsaid before. In space
    the offset is searched across the horizontal only: anchors that see the vehicle from
    nearly one elevation tell a height's offset poorly from their biases (a helix's 8 s fitted
    0.55 m of one that was not there). A tag off the truth's point on the body is no constant
    offset, and is not said."""
    import itertools

    found = _truth_at_ranges(log)
    if found is None:
        return None
    p, anchor, rho = found
    if rho.size > TRUTH_OFFSET_RANGES:  # a seeded draw: a stride could alias the round-robin
        k = np.sort(np.random.default_rng(0).choice(rho.size, TRUTH_OFFSET_RANGES, replace=False))
        p, anchor, rho = p[k], anchor[k], rho[k]
    reach, coarse, fine, heights, least, keeps = TRUTH_OFFSET_SEARCH
    beacons = np.asarray(log.beacons, dtype=float)
    heights = heights if p.shape[1] == 2 else np.zeros(1)  # a planar log: each anchor's, fitted

    def spread(delta) -> float:
        return _offset_spread(p, anchor, rho, beacons, heights, np.asarray(delta))

    dim = p.shape[1]
    grid = np.arange(-reach, reach + 1e-9, coarse)
    level = (0.0,) * (dim - 2)  # in space, the horizontal offsets only
    best = np.array(min((xy + level for xy in itertools.product(grid, repeat=2)), key=spread))
    near = np.arange(-coarse, coarse + 1e-9, fine)
    moves = (np.array(d + level) for d in itertools.product(near, repeat=2))
    best = min((best + d for d in moves), key=spread)
    at_zero, moved = spread(np.zeros(dim)), spread(best)
    if float(np.linalg.norm(best)) < least or not moved <= keeps * at_zero:
        return None
    edge = " or more" if np.max(np.abs(best)) >= reach else ""
    shown = ", ".join(f"{v:+.2f}" for v in best[:2])  # across the horizontal
    return (
        f"against the ranges, truth.csv fits best moved by ({shown}) m{edge} across the "
        f"horizontal (the ranges "
        f"spread {moved:.3g} m about it so, {at_zero:.3g} m as given; each anchor's bias "
        f"{'and height ' if p.shape[1] == 2 else ''}fitted; a component under 0.25 m is within "
        "what a right truth fits): is the truth's origin the anchors'? A truth off the anchors' frame scores "
        "every estimator with its offset (the truth only scores: the replay goes on)"
    )


def truth_attitude_note(log) -> str | None:
    """A note where the truth's attitude (``qw, qx, qy, qz`` of ``truth.csv``) turns about
    other axes than a body IMU's rates, or a fifth as far or less: a quaternion scalar last,
    navigation to body, or in another frame.

    The comparison of :func:`~quadobs.testbed.attitude.check_rates_against_attitude` (median
    cosine of the windows' rotations below :data:`~quadobs.testbed.attitude.RATE_AXES`'s
    bound, or their angles' median ratio beyond
    :data:`~quadobs.testbed.attitude.RATE_RATIO`), made on the truth's attitude; a note, not a
    refusal, since the truth's attitude only moves the truth to a stated tag (``tag_x``,
    ``tag_y``, ``tag_z``) and writes the TUM files' orientation."""
    from quadobs.testbed.attitude import RATE_AXES, RATE_RATIO, rates_against_attitude

    q = log.truth_part("attitude") if log.input_kind == "imu_body" else None
    if q is None:
        return None
    compared = rates_against_attitude(np.column_stack([log.truth[:, 0], q]), log.inputs)
    if compared is None:
        return None
    ratio, windows, cosine = compared
    bound, count = RATE_AXES
    axes = cosine.size >= count and float(np.median(cosine)) < bound
    if not axes and (ratio is None or 1.0 / RATE_RATIO <= ratio <= RATE_RATIO):
        return None
    said = (
        f"turn about other axes (median cosine {float(np.median(cosine)):.2f} over "
        f"{cosine.size} windows)"
        if axes
        else f"turn {ratio:.3g} times as far (median over {windows} windows)"
    )
    uses = "moves the truth to the stated tag and " if log.truth_lever is not None else ""
    return (
        f"{log.file_label('truth.csv')}: the body rates of imu.csv {said} than the truth's "
        f"attitude (qw,qx,qy,qz) does: is it scalar first, body to navigation, and its body's "
        f"axes the IMU's (a motion capture's rigid body may be turned from them)? It {uses}gives "
        "the TUM files' orientation"
    )


def _truth_at_ranges(log) -> tuple | None:
    """``(points, anchor, rho)``: the truth's point at each range's time (the horizontal one in
    a planar log) for the ranges inside the truth's span, their anchors' rows and values; None
    without a truth or with fewer than 20 such ranges."""
    truth = log.truth
    if truth is None or truth.shape[0] < 2 or log.ranges.shape[0] < 20:
        return None
    t = log.ranges[:, 0]
    inside = (t >= truth[0, 0]) & (t <= truth[-1, 0])
    if np.count_nonzero(inside) < 20:
        return None
    position = log.truth_part("position")
    if position is None:
        return None
    p = np.column_stack([np.interp(t[inside], truth[:, 0], c) for c in position.T])
    return p, log.beacon_index(log.ranges[inside, 1]), log.ranges[inside, 2]


#: The window (s) over which :func:`truth_odometry_note` compares the odometry's turn and
#: distance with the truth's, and the least turn (rad) and distance (m) a window must show.
ODOMETRY_WINDOW = 0.5
ODOMETRY_LEAST_TURN = 0.05
ODOMETRY_LEAST_DISTANCE = 0.05
#: How far from 1 the odometry's turns or distances may be, as a share of the truth's, before
#: :func:`truth_odometry_note` names them (wheels slip and tyres wear by a few per cent; the
#: stand-ins and Plaza measure 0.989 to 1.018).
ODOMETRY_SCALE_TOLERANCE = 0.1
#: The most a window may turn (rad) for :func:`truth_odometry_note` to compare its distance
#: (a tag off the axle moves by the turn times its offset, which the odometry does not see).
STRAIGHT_TURN = 0.1
#: How far (rad) ``heading0`` may lie from the truth's heading before the note says so.
HEADING0_TOLERANCE = 0.3


def _odometry_against_truth(log) -> dict:
    """Per window of :data:`ODOMETRY_WINDOW` inside the truth's span: the odometry's turn and
    distance (its rates integrated, each held to the next row) and the truth's (its heading's
    change, and its displacement along its mean heading), ``{"turn": (odo, truth), ...}``."""
    t_in, speed, rate = log.inputs[:, 0], log.inputs[:, 1], log.inputs[:, 2]
    tt = log.truth[:, 0]
    a, b = max(t_in[0], tt[0]), min(t_in[-1], tt[-1])
    if b - a < 5 * ODOMETRY_WINDOW:
        return {}
    edges = np.arange(a, b, ODOMETRY_WINDOW)
    held = np.concatenate([[0.0], np.cumsum(np.diff(t_in) * speed[:-1])])
    turned = np.concatenate([[0.0], np.cumsum(np.diff(t_in) * rate[:-1])])

    def integral(cumulative: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
        k = np.clip(np.searchsorted(t_in, at, side="right") - 1, 0, t_in.size - 1)
        return cumulative[k] + (at - t_in[k]) * values[k]

    heading = np.unwrap(log.truth[:, log.truth_columns.index("heading")])
    psi = np.interp(edges, tt, heading)
    xy = np.column_stack([np.interp(edges, tt, log.truth[:, c]) for c in (1, 2)])
    mid = 0.5 * (psi[:-1] + psi[1:])
    along = np.sum(np.diff(xy, axis=0) * np.column_stack([np.cos(mid), np.sin(mid)]), axis=1)
    return {
        "turn": (np.diff(integral(turned, rate, edges)), np.diff(psi)),
        "distance": (np.diff(integral(held, speed, edges)), along),
        "jitter": (_jitter(heading), max(_jitter(log.truth[:, 1]), _jitter(log.truth[:, 2]))),
        "heading": (float(log.heading0), float(np.interp(t_in[0], tt, heading))),
        "covered": bool(tt[0] <= t_in[0]),
    }


def _jitter(x: np.ndarray) -> float:
    """A sampled signal's white noise, from its second differences (their variance is six
    times the noise's for independent samples): ``1.4826 MAD / sqrt(6)``."""
    second = np.diff(np.asarray(x, dtype=float), 2)
    if second.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / math.sqrt(6.0))


def truth_odometry_note(log) -> str | None:
    """A line where a wheel-odometry log's inputs or ``heading0`` disagree with its truth's
    heading and path, else None.

    Over windows of :data:`ODOMETRY_WINDOW`, the least-squares ratio of the odometry's turns
    to the truth's (windows turning :data:`ODOMETRY_LEAST_TURN` or more) and of its distances
    to the truth's along its heading (windows moving :data:`ODOMETRY_LEAST_DISTANCE` or more),
    each window's change six times the truth's own jitter (:func:`_jitter`) at least, each
    from five windows at least: said where either is negative (the wheels swapped, a
    wheel's sign, a yaw rate of the opposite convention) or beyond
    :data:`ODOMETRY_SCALE_TOLERANCE` of 1 (a wrong track or unit). ``heading0`` is said where
    it lies more than :data:`HEADING0_TOLERANCE` from the truth's heading at the first input,
    or beyond 2 pi (degrees). The replay goes on: the truth only scores."""
    found = []
    if log.input_kind == "odometry" and abs(float(log.heading0)) > 2.0 * math.pi:
        found.append(f"heading0 {float(log.heading0):g} lies beyond 2 pi (degrees? it is in rad)")
    truth = log.truth
    if log.input_kind != "odometry" or truth is None or "heading" not in log.truth_columns:
        return "; ".join(found) or None
    parts = _odometry_against_truth(log)
    for key, least, what, k in (
        ("turn", ODOMETRY_LEAST_TURN, "turns (yaw_rate)", 0),
        ("distance", ODOMETRY_LEAST_DISTANCE, "distances (speed)", 1),
    ):
        if key not in parts:
            break
        odo, true = parts[key]
        # a window's change must stand out of the truth's own jitter (two samples' worth)
        keep = np.abs(true) >= max(least, 6.0 * math.sqrt(2.0) * parts["jitter"][k])
        if key == "distance":  # a tag beside the axle moves as the robot turns in place
            keep &= np.abs(parts["turn"][1]) < STRAIGHT_TURN
        if np.count_nonzero(keep) < 5:
            continue
        ratio = float(odo[keep] @ true[keep] / (true[keep] @ true[keep]))
        if ratio < 0.0 or abs(ratio - 1.0) > ODOMETRY_SCALE_TOLERANCE:
            degrees = ""
            if key == "turn" and abs(ratio * 180.0 / math.pi - 1.0) < 0.15:
                degrees = " (the truth's heading in degrees?)"
            elif key == "turn" and abs(ratio * math.pi / 180.0 - 1.0) < 0.15:
                degrees = " (the yaw rate in deg/s?)"
            found.append(f"the odometry's {what} are {ratio:.3g} times the truth's{degrees}")
    if parts.get("covered"):
        given, true_heading = parts["heading"]
        off = (given - true_heading + math.pi) % (2.0 * math.pi) - math.pi
        if abs(off) > HEADING0_TOLERANCE:
            found.append(
                f"heading0 {given:.4g} rad lies {off:+.3g} rad from the truth's heading at the "
                f"first input ({true_heading % (2 * math.pi):.4g})"
            )
    if not found:
        return None
    return (
        "against the truth, "
        + "; ".join(found)
        + ": check the odometry's units, the wheels' order and signs, the track, its clock "
        "against the truth's (a lag of seconds), heading0, and the truth's heading (rad, "
        "anticlockwise from the anchors' x axis) (the truth only scores: the replay goes on)"
    )


def truth_anchor_note(log) -> str | None:
    """A line naming the anchors whose ranges fit another anchor's position far better than
    their own, against the truth, else None.

    For each anchor ``h`` and each anchor position ``a_k``, the spread of ``rho - |p - a_k|``
    over ``h``'s ranges (the median absolute deviation about its median: a bias, or a height
    above a planar tag, is a constant). Said where some ``k != h`` gives less than a fifth of
    the spread at ``a_h`` and the spread at ``a_h`` exceeds 0.3 m: ``h``'s ranges were
    measured to ``k`` (ids mapped to the wrong anchors). A constellation whose symmetry maps
    the anchors onto each other (a box's corners) fits a wrong mapping from the ranges alone,
    a whole trajectory turned or mirrored; the truth tells it."""
    return _anchor_text(log, anchor_mapping(log))


def anchor_mapping(log) -> list[tuple]:
    """:func:`truth_anchor_note`'s finding: ``(h, k, spread_k, spread_h)`` (anchor indices,
    spreads in m) for each anchor ``h`` whose ranges fit anchor ``k``'s position far better
    than its own, against the truth; empty where none (or no truth)."""
    found = _truth_at_ranges(log)
    if found is None:
        return []
    p, anchor, rho = found
    beacons = np.asarray(log.beacons, dtype=float)
    wrong = []
    for h in np.unique(anchor):
        mine = anchor == h
        if np.count_nonzero(mine) < 10:
            continue
        e = rho[mine, None] - np.linalg.norm(p[mine, None, :] - beacons[None, :, :], axis=2)
        spread = np.median(np.abs(e - np.median(e, axis=0)), axis=0)
        k = int(np.argmin(spread))
        if k != h and spread[h] > 0.3 and spread[k] < 0.2 * spread[h]:
            wrong.append((int(h), k, float(spread[k]), float(spread[h])))
    return wrong


def _anchor_text(log, mapping: list[tuple]) -> str | None:
    """The line of :func:`truth_anchor_note` for ``mapping`` (:func:`anchor_mapping`)."""
    if not mapping:
        return None
    ids = log.beacon_ids
    wrong = [
        f"{int(ids[h])} fit anchor {int(ids[k])}'s position ({sk:.3g} m against {sh:.3g} m at "
        "its own)"
        for h, k, sk, sh in mapping
    ]
    return (
        "against the truth, the ranges of anchor "
        + "; of anchor ".join(wrong)
        + ": do ranges.csv's ids name the anchors of beacons.csv, and are the truth's axes "
        "the anchors'?"
    )


def _lag_explains(mapping: list[tuple], lag: tuple | None) -> bool:
    """Whether a lag of the truth (:func:`truth_lag`) explains the ranges better than the
    anchors mapped to others (:func:`anchor_mapping`): where the mapping sends two anchors
    to one (no relabelling of ids does), or its median spread is no smaller than the lag's.
    A truth seconds late fits some anchors' ranges to others' positions by chance."""
    if lag is None or not mapping:
        return lag is not None
    targets = [k for _, k, _, _ in mapping]
    injective = len(set(targets)) == len(targets)
    return not injective or float(np.median([sk for _, _, sk, _ in mapping])) >= lag[1]


def _spread_about(p, anchor, rho, beacons) -> float:
    """The median over the anchors of the spread (median absolute deviation) of each anchor's
    residuals ``rho - |p - a_h|`` about their median."""
    e = rho - np.linalg.norm(p - beacons[anchor], axis=1)
    spreads = [
        np.median(np.abs(e[anchor == h] - np.median(e[anchor == h]))) for h in np.unique(anchor)
    ]
    return float(np.median(spreads))


def truth_heights_note(log) -> str | None:
    """A line where a 3-D log's ranges fit the truth much better with the anchors' heights
    turned over (``z -> z_min + z_max - z``: heights measured down from a ceiling, or along
    an axis pointing down), else None.

    The spread of the ranges about the truth (:func:`_spread_about`) as the anchors are given
    and turned over; said where the second is under 0.7 times the first. Measured on a
    flight's stand-in whose heights were written ``3.0 - z``: 0.166 m as given, 0.080 m turned
    over (the log as recorded the reverse); the filters followed the ranges to the mirrored
    track (0.176 -> 0.704 m) and the only note blamed the truth's origin."""
    found = _truth_at_ranges(log) if log.dimension == 3 else None
    beacons = np.asarray(log.beacons, dtype=float)
    if found is None or np.ptp(beacons[:, 2]) == 0.0:
        return None
    p, anchor, rho = found
    turned = beacons.copy()
    turned[:, 2] = beacons[:, 2].min() + beacons[:, 2].max() - beacons[:, 2]
    given, over = _spread_about(p, anchor, rho, beacons), _spread_about(p, anchor, rho, turned)
    if not over < 0.7 * given:
        return None
    return (
        f"against the truth, the ranges fit the anchors turned over in height (z -> "
        f"{beacons[:, 2].min():.3g} + {beacons[:, 2].max():.3g} - z: spread {over:.3g} m, "
        f"against {given:.3g} m as given): are beacons.csv's heights measured down from the "
        "ceiling, or the z axis pointing down?"
    )


#: The anchors of a 3-D log lie in one plane where their spread across it is below this
#: fraction of their extent along it (a survey's error, against a room's size).
PLANE_FRACTION = 0.01


def anchor_plane(beacons: np.ndarray) -> float | None:
    """The anchors' spread (m) about their best plane where a 3-D log's anchors lie in one
    (:data:`PLANE_FRACTION`), else None: the smallest singular value of the centred positions
    over ``sqrt(B)``, against the largest."""
    if beacons.shape[1] != 3 or beacons.shape[0] < 3:
        return None
    s = np.linalg.svd(beacons - beacons.mean(axis=0), compute_uv=False) / math.sqrt(
        beacons.shape[0]
    )
    return float(s[-1]) if s[-1] <= PLANE_FRACTION * s[0] else None


def _measured_span(log) -> tuple[float, float] | None:
    """The first and last time of the log's ranges and TDOA (s), or None without any."""
    tables = [t[:, 0] for t in (log.ranges, log.tdoa) if t.shape[0]]
    if not tables:
        return None
    return float(min(t[0] for t in tables)), float(max(t[-1] for t in tables))


def check_clock_overlap(log, inputs: bool = True) -> None:
    """Refuse, before any work, inputs (unless not ``inputs``: an offset given moves them, and
    its own check follows) or a truth whose times do not overlap the measurements' at all: a
    file on another clock (a time zone's hours, GPS time's 18 s on a short log, a device's
    uptime), which nothing in the replay could score or drive."""
    measured = _measured_span(log)
    if measured is None:
        return
    a, b = measured
    files = [("truth.csv", log.truth)]
    if inputs and log.input_kind != "none":
        files.append((INPUT_FILES[log.input_kind], log.inputs))
    from quadobs.testbed.logs.schema import span_apart

    for fname, table in files:
        apart = span_apart(table, a, b)
        if apart is not None:
            c, d = apart
            raise QuadobsError(
                f"{log.file_label(fname)}: its times ({c:.10g} to {d:.10g} s) do not overlap the "
                f"measurements' ({a:.10g} to {b:.10g} s; {c - a:+.4g} s at the start): a file on "
                "another clock (a time zone's hours, GPS time's 18 s)? Every file's times must "
                "be on the ranges' clock"
            )


#: The share of the measurements outside the inputs' span beyond which
#: :func:`inputs_span_note` says so.
OUTSIDE_INPUTS_SHARE = 0.05


def inputs_span_note(log) -> str | None:
    """A line where more than :data:`OUTSIDE_INPUTS_SHARE` of the measurements lie before the
    first input or after the last (not replayed), naming how far the inputs' span is moved:
    inputs on another clock (GPS time runs 18 s ahead of UTC), or a recording cut short."""
    measured = _measured_span(log)
    fname = INPUT_FILES.get(log.input_kind)
    if measured is None or fname is None:
        return None
    t = np.concatenate([log.ranges[:, 0], log.tdoa[:, 0]])
    before, after = int(np.sum(t < log.start)), int(np.sum(t > log.end))
    if before + after <= OUTSIDE_INPUTS_SHARE * t.size:
        return None
    where = [
        f"starts {log.start - measured[0]:.3g} s after the first measurement ({before} before it)"
        if before
        else "",
        f"ends {measured[1] - log.end:.3g} s before the last ({after} after it)" if after else "",
    ]
    return (
        f"{fname} {' and '.join(w for w in where if w)}, not replayed: the inputs on another "
        "clock (GPS time runs 18 s ahead of UTC; --clock-offset SECONDS moves them), or "
        "recorded over less of the log?"
    )


def check_burn_in(log, burn_in: float) -> None:
    """Refuse, before any work, a burn-in after which nothing would be scored: one that reaches
    the end of the log (its last input, or measurement without inputs), or, where the log has a
    truth, the truth's last time. Such a replay would report no error for any estimator."""
    span = log.end - log.start
    if burn_in > 0.0 and burn_in >= span:
        raise QuadobsError(
            f"--burn-in {burn_in:g} s: not shorter than the log ({span:.3g} s from "
            f"t = {log.start:.10g} s), so no error would be measured"
        )
    if burn_in > 0.0 and log.truth is not None and log.truth[-1, 0] < log.start + burn_in:
        raise QuadobsError(
            f"--burn-in {burn_in:g} s: truth.csv ends {log.truth[-1, 0] - log.start:.3g} s "
            "after the log's start, before the burn-in, so no error would be measured"
        )


def check_replay(log, names, *, dt: float = 0.1, model: str | None = None, options=None) -> None:
    """Refuse, before any calibration or replay, a model the log cannot drive or an estimator
    that cannot take the log (each factory's one-line error, naming what the log lacks or holds),
    and ranges or a body IMU in the wrong units (:func:`check_range_units`,
    :func:`~quadobs.testbed.attitude.check_body_imu`)."""
    from quadobs.testbed.logs.estimators import (
        ReplaySetup,
        _typical_range,
        log_frame,
        tuning_fields,
        velocity_from_log,
    )
    from quadobs.testbed.worlds.replay import default_model, state_size

    model = model or default_model(log)
    n = state_size(log, model)
    kinds = tuple(k for k, table in (("range", log.ranges), ("tdoa", log.tdoa)) if table.shape[0])
    setup = ReplaySetup(
        log.beacons, dt, model, 0.0, _typical_range(log), input_kind=log.input_kind, kinds=kinds,
        **log_frame(log, None, velocity_from_log(options)), **tuning_fields(options),
    )  # fmt: skip
    x0 = np.zeros(n)
    x0[: log.dimension] = log.beacons.mean(axis=0)
    build_replay_estimators(setup, list(names) if names else default_estimators(log, model), x0)
    check_range_units(log)
    check_truth_units(log)
    if log.input_kind == "odometry":
        check_odometry_units(log)
    if log.input_kind == "imu_body":  # its units, and the attitude the model imu rotates it by
        from quadobs.testbed.attitude import check_body_imu, navigation_accelerations

        check_body_imu(log)
        if model == "imu":
            navigation_accelerations(log)  # computed once per log: the replay reads it again


#: How far a log's ranges may lie from the anchors' scale before :func:`check_range_units`
#: refuses them: a vehicle among its anchors reads ranges of the order of their extent, and a
#: factor of 100 either way is a unit (mm against m), not a geometry.
RANGE_SCALE_RATIO = 100.0
#: The largest noise of a log's ranges, as a share of the anchors' extent, before
#: :func:`check_range_units` takes them for another unit (its docstring).
RANGE_NOISE_RATIO = 0.5


def check_range_units(log) -> None:
    """Refuse ranges in another unit than the anchors' coordinates, in one line naming the file.

    ``e``: the diagonal of the box that holds the anchors the log has ranges to (at least 1
    m). Refused: the median range beyond :data:`RANGE_SCALE_RATIO` ``e`` (ranges in mm against
    anchors in m), or every ranged anchor's median range below ``e /``
    :data:`RANGE_SCALE_RATIO` (anchors in mm against ranges in m: a point lies at least ``e /
    (2 sqrt(3))`` from one of the two anchors farthest apart), or the ranges' own noise
    (:func:`~quadobs.testbed.logs.range_noise.range_noise`: the spread of each range about the
    line through its anchor's neighbours) beyond :data:`RANGE_NOISE_RATIO` ``e`` (ranges in
    cm: a radio's decimetres read as metres; measured 0.006 to 0.025 ``e`` on the Plaza logs
    and simulated flights and robots, 1.3 to 1.5 ``e`` on those in cm; anchors more than about
    200 times the radio's noise apart, 10 m at 0.05 m, let ranges in cm pass).
    """
    ranges = log.ranges
    if ranges.shape[0] == 0:
        return
    ids, anchor = np.unique(ranges[:, 1].astype(int), return_inverse=True)
    if ids.size < 2:
        return
    ranged = np.asarray(log.beacons, dtype=float)[log.beacon_index(ids)]  # ids, not rows
    extent = max(float(np.linalg.norm(ranged.max(axis=0) - ranged.min(axis=0))), 1.0)
    median = float(np.median(ranges[:, 2]))
    medians = [float(np.median(ranges[anchor == k, 2])) for k in range(ids.size)]
    both = "the ranges and the anchors' coordinates must both be in metres"
    if median > RANGE_SCALE_RATIO * extent:
        raise QuadobsError(
            f"{log.file_label('ranges.csv')}, column range: the median range is {median:.4g}, "
            f"{median / extent:.0f} times the extent of the anchors ranged to ({extent:.4g}, "
            f"beacons.csv): {both}"
        )
    if max(medians) < extent / RANGE_SCALE_RATIO:
        times = f"{extent / max(medians):.0f} times" if max(medians) > 0 else "beyond"
        raise QuadobsError(
            f"{log.file_label('beacons.csv')}: the anchors ranged to span {extent:.4g}, "
            f"{times} the largest median range of one anchor ({max(medians):.4g}, "
            f"ranges.csv): {both}"
        )
    noise = _own_noise(log)
    if math.isfinite(noise) and noise > RANGE_NOISE_RATIO * extent:
        raise QuadobsError(
            f"{log.file_label('ranges.csv')}, column range: the ranges' own noise is "
            f"{noise:.4g}, {noise / extent:.2g} times the extent of the anchors ranged to "
            f"({extent:.4g}, beacons.csv), where a radio's is a few hundredths of it (ranges "
            f"in cm?): {both}"
        )
    _check_range_triangles(log, both)


#: Consecutive ranges to two anchors at most this far apart in time (s) are taken as one
#: point's by :func:`_check_range_triangles`, and the medians beyond which it refuses them:
#: a point's two distances sum to at least the anchors' separation and differ by at most it
#: (measured: sums 1.29 to 1.90 times it, differences 0.19 to 0.56 times it, on Plaza and the
#: stand-ins).
TRIANGLE_WINDOW = 1.0
TRIANGLE_SHORT = 0.5
TRIANGLE_LONG = 2.0


def _own_noise(log) -> float:
    """The ranges' own noise where a figure is one (:func:`~quadobs.testbed.logs.range_noise.
    is_noise`: against the line through each range's neighbours, else the cubic through four),
    else NaN: sparse ranges of a fast vehicle spread by its motion, not their noise."""
    from quadobs.testbed.logs.range_noise import is_noise, range_noise, smooth_range_noise

    for figures in (range_noise(log), smooth_range_noise(log)):
        if is_noise(figures, fewest=10):  # a short log's few residuals still tell a unit
            return float(figures[0])
    return math.nan


def _check_range_triangles(log, both: str) -> None:
    """Refuse ranges whose pairs break the triangle inequality by a factor: the median of
    ``(r_i + r_j) / |a_i - a_j|`` below :data:`TRIANGLE_SHORT` (ranges in a smaller unit, cm
    read as mm) or of ``|r_i - r_j| / |a_i - a_j|`` beyond :data:`TRIANGLE_LONG` (a larger
    one), over consecutive ranges to two anchors within :data:`TRIANGLE_WINDOW` (20 pairs at
    least). A robot's anchors with heights apart count them in the separation."""
    order = np.argsort(log.ranges[:, 0], kind="stable")
    r = log.ranges[order]
    anchors = np.asarray(log.beacons, dtype=float)
    if log.anchor_heights is not None:
        anchors = np.column_stack([anchors, log.anchor_heights])
    h = log.beacon_index(r[:, 1])
    pair = np.flatnonzero((np.diff(r[:, 0]) <= TRIANGLE_WINDOW) & (h[1:] != h[:-1]))
    if pair.size < 20:
        return
    d = np.linalg.norm(anchors[h[pair]] - anchors[h[pair + 1]], axis=1)
    keep = d > 0
    if np.count_nonzero(keep) < 20:  # anchors at one spot tell no triangle
        return
    ri, rj, d = r[pair, 2][keep], r[pair + 1, 2][keep], d[keep]
    short = float(np.median((ri + rj) / d))
    long = float(np.median(np.abs(ri - rj) / d))
    where = f"{log.file_label('ranges.csv')}, column range"
    if short < TRIANGLE_SHORT:
        raise QuadobsError(
            f"{where}: ranges to two anchors within {TRIANGLE_WINDOW:g} s sum to a median "
            f"{short:.3g} times the anchors' separation, where a point's two distances sum to "
            f"at least it (ranges in a smaller unit?): {both}"
        )
    if long > TRIANGLE_LONG:
        raise QuadobsError(
            f"{where}: ranges to two anchors within {TRIANGLE_WINDOW:g} s differ by a median "
            f"{long:.3g} times the anchors' separation, where a point's two distances differ "
            f"by at most it (ranges in a larger unit?): {both}"
        )


#: How far (a factor either way) the truth's distances to the anchors may lie from the ranges
#: before :func:`check_truth_units` takes the truth for another unit.
TRUTH_SCALE_RATIO = 10.0
#: The share of the median range by which the ranges may differ, in median, from the truth's
#: distances before :func:`check_truth_units` takes the truth for another unit or frame (a bias,
#: an excess, a lever arm or a clock apart give centimetres to decimetres).
TRUTH_APART = 0.5


def check_truth_units(log) -> None:
    """Refuse a truth in another unit than the anchors', in one line naming ``truth.csv``.

    The median over ranges of ``|p(t) - a_h|``, the truth's distance to the anchor ranged to
    at each range's time (with a planar vehicle's anchors' heights above the tag), against the
    median range: a truth of the tag (or near it) gives a
    ratio near 1 (a bias, an excess, a lever arm of centimetres), a truth in mm against
    anchors in m about 1000. Refused beyond :data:`TRUTH_SCALE_RATIO` either way, or where the
    ranges differ from those distances by a median beyond :data:`TRUTH_APART` of the median
    range (a truth in m read as mm, shrunk onto the origin; another frame), where the ranges
    and the distances are both slant (a log in space, or anchors with heights); logs of TDOA
    alone are not checked."""
    found = _truth_at_ranges(log)
    if found is None:
        return
    p, anchor, rho = found
    dim = p.shape[1]
    offset = p - np.asarray(log.beacons)[anchor, :dim]
    if log.anchor_heights is not None:  # a planar vehicle under anchors: their heights count
        tag = float(log.tag_height) if math.isfinite(log.tag_height) else 0.0
        offset = np.column_stack([offset, np.asarray(log.anchor_heights)[anchor] - tag])
    distances = np.linalg.norm(offset, axis=1)
    distance = float(np.median(distances))
    measured = float(np.median(rho))
    if measured <= 0.0:
        return
    ratio = distance / measured
    both = "the truth's positions and the anchors' coordinates must both be in metres, in one frame"
    if not 1.0 / TRUTH_SCALE_RATIO <= ratio <= TRUTH_SCALE_RATIO:
        raise QuadobsError(
            f"{log.file_label('truth.csv')}: the truth lies a median {distance:.4g} from the "
            f"anchors ranged to, where the ranges say {measured:.4g} ({ratio:.3g} times): {both}"
        )
    slant = dim == 3 or log.anchor_heights is not None  # a planar log's ranges may be slant
    apart = float(np.median(np.abs(rho - distances)))
    if slant and apart > TRUTH_APART * measured:
        raise QuadobsError(
            f"{log.file_label('truth.csv')}: each range differs from the truth's distance to its "
            f"anchor by a median {apart:.4g}, {apart / measured:.2g} of the median range: {both} "
            "(and on the ranges' clock)"
        )


#: How much wider than the region its ranges allow a log's dead-reckoned path may be before
#: :func:`check_odometry_units` refuses it: wheel odometry drifts by a few per cent of the
#: distance travelled, and a factor of 10 is a unit (mm/s or cm/s against m/s, times in ms).
ODOMETRY_SPAN_RATIO = 10.0


def check_odometry_units(log) -> None:
    """Refuse wheel odometry in other units than m/s and rad/s (with times in seconds), in one
    line naming the file and the column.

    * the yaw rate: no rate beyond
      :data:`~quadobs.testbed.attitude.GYRO_FULL_SCALE` (a rate in deg/s of a vehicle
      turning faster than 0.6 rad/s reads beyond it; a yaw in degrees differenced into a rate
      jumps by 360 where it wraps);
    * the speed: the path dead-reckoned from it (:func:`~quadobs.testbed.worlds.replay.dead_reckoning`,
      standing still across the inputs' gaps, :func:`~quadobs.testbed.worlds.replay.wide_gaps`,
      where the replay holds the last input; its extent, the diagonal of the box that holds
      it, does not depend on the start or the heading's error but for drift) within
      :data:`ODOMETRY_SPAN_RATIO` times ``e + 2 r``, ``e`` the extent of the anchors ranged to
      and ``r`` the anchors' reach, the median over the anchors of each one's 99th percentile
      range (every position lies within ``r`` of some anchor, so the true path spans at most
      about ``e + 2 r``: a corridor's anchors every 30 m hold a route of kilometres; a sentinel
      range of 9999 moves no median). A speed in mm/s, or times in ms, dead-reckon a path a
      thousand times wider; one in cm/s a hundred times, caught where the path covers more
      than a tenth of that region. Not run on a log of TDOA alone (no range).
    """
    from quadobs.testbed.attitude import GYRO_FULL_SCALE
    from quadobs.testbed.worlds.replay import dead_reckoning, wide_gaps

    rates = np.abs(log.inputs[:, 2])
    if rates.size and float(rates.max()) > GYRO_FULL_SCALE:
        row = int(np.argmax(rates))
        raise QuadobsError(
            f"{log.file_label('inputs.csv')}, row {log.file_row('inputs.csv', row)}, column "
            "yaw_rate: "
            f"{float(log.inputs[row, 2]):.4g} is beyond any gyroscope's range "
            f"({GYRO_FULL_SCALE:.1f} rad/s = 2000 deg/s): the yaw rate must be in rad/s"
        )
    received = log.ranges[log.ranges[:, 2] > 0.0] if log.ranges.shape[0] else log.ranges
    if received.shape[0] == 0 or log.inputs.shape[0] < 2:
        return
    ids = np.unique(received[:, 1])
    ranged = np.asarray(log.beacons, dtype=float)[log.beacon_index(ids)]
    extent = float(np.linalg.norm(ranged.max(axis=0) - ranged.min(axis=0)))
    reach = np.median([np.quantile(received[received[:, 1] == i, 2], 0.99) for i in ids])
    bound = extent + 2.0 * float(reach)
    inputs = log.inputs.copy()
    inputs[wide_gaps(inputs[:, 0]), 1] = 0.0  # no distance across a gap
    odometry = SimpleNamespace(inputs=inputs, heading0=log.heading0)  # not a whole log again
    path = dead_reckoning(odometry, inputs[:, 0])[0]
    span = float(np.linalg.norm(path.max(axis=0) - path.min(axis=0)))
    if span > ODOMETRY_SPAN_RATIO * bound:
        raise QuadobsError(
            f"{log.file_label('inputs.csv')}, column speed: the path dead-reckoned from it spans "
            f"{span:.4g} m, {span / bound:.0f} times the {bound:.4g} m within which the ranges "
            "place the vehicle (the anchors' extent and twice their reach): the speed must be in "
            "m/s and the times in seconds"
        )


def _offsets_summary(offsets) -> dict | None:
    """The anchors' squared-range offsets' prior from the log's stated heights (m^2), or None
    (the storey's prior of the filters that hold them)."""
    if offsets is None:
        return None
    std = np.sqrt(np.diag(offsets[1]))
    return {"mean": [float(v) for v in offsets[0]], "std": [float(v) for v in std]}


def _std_by_anchor(log) -> list | None:
    """The median ``std`` of each anchor's ranges as replayed (the log's, or its anchor's own
    figure, :func:`~quadobs.testbed.logs.range_noise.with_anchor_noise`), None for an anchor
    whose ranges state none; None where no range states one."""
    from quadobs.testbed.logs.schema import RANGE

    if not np.isfinite(log.range_std).any():
        return None
    index = log.beacon_index(log.ranges[:, RANGE.beacon])
    out = []
    for h in range(log.beacons.shape[0]):
        std = log.range_std[(index == h) & np.isfinite(log.range_std)]
        out.append(float(np.median(std)) if std.size else None)
    return out


def _summary(
    log, world, names, merged, completed, interrupted, x0, biases, setup, out, sensors
) -> dict:
    """The replay's summary: the log, the grid, the settings, the sensor layer's counts, the sinks' figures."""
    return {
        "log": log.name,
        "model": world.model,
        "dt": world.dt,
        "duration": completed * world.dt,
        "steps": completed,
        "interrupted": interrupted,
        "has_truth": log.truth is not None,
        "ranges": {
            "in_log": int(log.ranges.shape[0]),
            "placed": world.placed,
            "merged": world.merged,
        },
        "biases": None if biases is None else [float(b) for b in np.asarray(biases).ravel()],
        "initial_guess": [float(v) for v in x0],
        "start": None if setup.start is None else setup.start.summary(),
        "noise": {
            "range_sigma": setup.range_sigma,
            "q_xy": setup.q_xy,
            "q_acc": setup.q_acc,
            "q_imu": setup.q_imu,
            "gate": setup.gate,
            "range_bias": setup.range_bias,
            "steady_test": setup.steady_test,
            "bias_prior": setup.bias_prior_std(),
            "P0": setup.P0,
            "offsets": _offsets_summary(setup.offsets if setup.stated_heights else None),
            "stated_heights": setup.stated_heights,
            "tag_pattern": setup.tag_pattern if "ukf-height-lever" in names else None,
            "lever_arm": None if setup.lever_arm is None else list(setup.lever_arm),
            "range_std_by_anchor": _std_by_anchor(log),
        },
        "measurements": {
            "range_period_steps": sensors.range_every,
            "dropped": sensors.dropped,
            "outliers_injected": sensors.outliers_injected,
        },
        "recording": None if out is None else str(out),
        "primary_estimator": names[0],
        "burn_in": merged.get("burn_in", 0.0),
        "tum": merged.get("tum"),
        "anchor_extent": anchor_extent(log.beacons),
        "estimators": _within_extent(merged.get("estimators", {}), anchor_extent(log.beacons)),
    }


def anchor_extent(beacons: np.ndarray) -> float:
    """The largest distance between two anchors (m): the scale of the field they cover."""
    b = np.asarray(beacons, dtype=float)
    return float(np.max(np.linalg.norm(b[:, None, :] - b[None, :, :], axis=2)))


def _within_extent(estimators: dict, extent: float) -> dict:
    """Each estimator's figures with ``within_extent``: whether its error at the log's end
    (``final_position_error``) is at most the anchors' extent (:func:`anchor_extent`). An error
    larger than the field the anchors cover, at the end of the log, says the ranges do not
    hold the estimate (a filter run away short of the divergence watch's 1e9 m, ranges in the
    wrong unit, a vehicle far outside its anchors); the end, not the RMSE, so that a start far
    off, which the RMSE without a burn-in carries, does not count. None where no final error
    was measured or the anchors are one point."""
    for e in estimators.values():
        final = e.get("final_position_error")
        ok = final is not None and math.isfinite(final) and not e.get("diverged") and extent > 0.0
        e["within_extent"] = bool(final <= extent) if ok else None
    return estimators
