"""A simulated episode written as a log in the open format (``quadobs run SCENARIO --export-log DIR``).

:class:`LogExportSink` runs beside an episode's sinks and keeps, per step ``k`` (time
``t_k = k dt``), what the estimators were given and what was true:

* ``ranges.csv``: each measured range (after the sensor layer: noise, rate, dropouts,
  outliers) at ``t_k``, as the estimators received it: a range the noise or an outlier
  took below zero is written below zero, as a radio's can be;
* ``inputs.csv``: the measured acceleration ``u_k`` (the accelerometer, with its noise),
  held over ``[t_k, t_(k+1))``, in the navigation frame (``time,ax,ay[,az]``); a last row
  at ``t_K`` (zero) closes the last step, as the format's inputs are held to the next row;
* ``truth.csv``: the true position and velocity ``x_k`` (``time,x,y[,z],vx,vy[,vz]``);
* ``beacons.csv``: the scenario's beacons, ids ``0 .. q - 1``;
* with a ``[radio]`` table, the radio's measurements at their own times with its stated
  ``std`` instead of the grid's ranges: ranges in ``ranges.csv``, TDOA in ``tdoa.csv``
  (:func:`radio_rows`).

With an ``[odometry]`` table (a planar ground robot, :mod:`quadobs.testbed.odometry`) the log
is an odometry log of version 2 instead:

* ``inputs.csv``: ``time,speed,yaw_rate``, the wheel odometry's samples (with its noise,
  scale error and yaw-rate bias) at its ``rate``, each held until the next; a last row at
  ``t_K`` repeats the last sample;
* ``meta.csv``: ``heading0``, the true heading (the direction of travel) at the first sample;
* ``truth.csv``: ``time,x,y,heading`` at each step;
* ``ranges.csv``: the radio's ranges at their own times with its stated ``std``, as above.

``quadobs replay DIR`` reads it with its odometry defaults (the model ``odometry``).

Replayed at ``dt`` equal to the physics step (``quadobs replay DIR --dt DT --model imu``)
the log gives the estimators the same outputs and, to rounding, the same inputs as the
episode (tested in ``tests/testbed/test_replay.py``). Vehicle scenarios with wind are not
written: the format holds no airspeed.

A quadrotor scenario (:class:`~quadobs.testbed.worlds.quadrotor.QuadrotorWorld`) is written
as a log of version 2 with a body IMU, what the vehicle's own sensors gave the estimators
(:class:`QuadrotorLogTap` reads them each step):

* ``imu.csv``: the body IMU of each step, ``time,ax,ay,az,gx,gy,gz``: the specific force
  ``f~`` and the angular rate ``w~`` in the body frame, with their noise and biases, held
  over ``[t_k, t_(k+1))``; a last row at ``t_K`` repeats the last sample;
* ``attitude.csv``: the AHRS attitude ``q~`` (with its error) at the samples it was renewed
  (``[quadrotor] attitude_rate``): the rotation the episode built ``u_k = R~ f~ + g`` with;
* ``ranges.csv``: with a ``[radio]`` table, each of the radio's ranges at its own time, with
  the radio's stated standard deviation (``std``); a TDOA radio's differences go to
  ``tdoa.csv``; without one, the sensor layer's ranges on the physics grid as above, with
  its stated noise ``[noise] range_std`` as ``std`` (:func:`stated_range_std`);
* ``truth.csv``: ``time,x,y,z,qw,qx,qy,qz,vx,vy,vz``, the true position, attitude and
  velocity at each step;
* ``meta.csv``: ``frame`` ``enu`` (z up) and the MuJoCo model's ``gravity``; the IMU's
  stated figures from ``[quadrotor]``: the densities ``accel_noise`` and ``gyro_noise``, the
  biases' standard deviations ``accel_bias`` and ``gyro_bias``, and ``attitude_std``.
  ``range_errors`` ``gaussian`` where the scenario has no radio and draws its ranges with
  Gaussian noise and no outliers (:func:`stated_range_errors`).

The replay (``quadobs replay DIR --model imu``) rebuilds the navigation-frame acceleration
``R~ f~ + g`` from ``imu.csv`` and ``attitude.csv`` (:mod:`quadobs.testbed.attitude`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import LOG_FILES, RangeLog, write_log
from quadobs.testbed.logs.schema import IMU_FIGURES
from quadobs.testbed.sinks import EpisodeContext, Rows, Sink

if TYPE_CHECKING:
    from quadobs.testbed.odometry import WheelOdometry

__all__ = [
    "LogExportSink",
    "QuadrotorLogTap",
    "check_export_folder",
    "check_exportable",
    "stated_range_std",
]


def check_exportable(scenario) -> None:
    """A one-line error unless ``scenario`` can be written as a log (a quadrotor, or a vehicle scenario without wind)."""
    if scenario.kind == "quadrotor":
        return
    if scenario.kind != "vehicle" or scenario.has_wind:
        what = f"of kind {scenario.kind!r}" if scenario.kind != "vehicle" else "a wind scenario"
        raise QuadobsError(
            f"--export-log: {scenario.name!r} is {what}; the log format holds ranges, an accelerometer "
            "in the navigation frame and the truth of a vehicle scenario without wind, or a quadrotor's "
            "body IMU"
        )


def check_export_folder(folder, outputs=()) -> None:
    """Before the run: a one-line error unless ``folder`` is new, empty or a log folder, and
    none of the run's other ``outputs`` lies in it (it is replaced whole at the end)."""
    from quadobs.testbed.logs.files import check_replaceable_folder
    from quadobs.testbed.logs.format import LOG_FILES

    check_replaceable_folder(folder, set(LOG_FILES), "--export-log", outputs)


def stated_range_std(world) -> float:
    """The sensor layer's stated range noise (m): ``noise.range_std``, or a bound's uniform
    ``range_bound / sqrt(3)``; NaN (the replay's default) for noiseless ranges."""
    noise = world.scenario.noise
    std = float(noise.range_std) or float(noise.range_bound or 0.0) / math.sqrt(3.0)
    return std if std > 0 else math.nan


def stated_range_errors(world) -> str:
    """The ranges' error model for ``meta.csv``'s ``range_errors``: ``"gaussian"`` where the
    scenario has no radio and its sensor layer draws each range with Gaussian noise of
    ``noise.range_std`` and no outliers (nothing adds a non-line-of-sight excess); else ``""``
    (not stated: the replay takes the ranges as it would a real log's)."""
    scenario = world.scenario
    noise = scenario.noise
    plain = getattr(scenario, "radio", None) is None and float(noise.range_std) > 0.0
    if plain and not float(noise.range_bound) and not float(noise.outlier_probability):
        return "gaussian"
    return ""


def radio_rows(events, grid_ranges: np.ndarray, grid_std: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``ranges.csv`` ``(time, anchor, range, std)`` and ``tdoa.csv`` ``(time,
    anchor_i, anchor_j, difference, std)``: the radio's measurements (``events``) with their
    stated standard deviation, and the grid's ranges ``(time, anchor, range)`` with ``grid_std``,
    in time order."""
    radio = [(m.t, m.anchors[0], m.value, m.std) for m in events if m.kind == "range"]
    tdoa = [(m.t, *m.anchors, m.value, m.std) for m in events if m.kind == "tdoa"]
    grid = np.column_stack([grid_ranges, np.full(grid_ranges.shape[0], grid_std)])
    ranges = np.vstack([grid, np.asarray(radio, dtype=float).reshape(-1, 4)])
    ranges = ranges.reshape(-1, 4)[np.argsort(ranges[:, 0], kind="stable")]
    return ranges, np.asarray(tdoa, dtype=float).reshape(-1, 5)


class QuadrotorLogTap:
    """Per step of a quadrotor world: its body IMU sample, its AHRS attitude and the radio's measurements.

    Set as the world's ``log_tap``, it is called at the end of each step ``k`` (block row
    ``j``), after the IMU and the radio have been read, and keeps them in arrays allocated
    once (the rows of the current block) and, for the radio, a list.

    Parameters
    ----------
    world : QuadrotorWorld
    """

    def __init__(self, world) -> None:
        rows = world.out.shape[0]
        self.world = world
        self.imu = np.full((rows, 6), np.nan)
        self.attitude = np.full((rows, 4), np.nan)
        self.events: list = []

    def __call__(self, j: int, k: int) -> None:
        w = self.world
        self.imu[j] = w.body_imu
        self.attitude[j] = w.attitude_meas
        if w.step_events:
            self.events.extend(w.step_events)


class LogExportSink(Sink):
    """Collects an episode's ranges, inputs and truth, and writes them as a log folder at the end.

    Parameters
    ----------
    folder : path
        The log folder, written as a whole at the end
        (:func:`~quadobs.testbed.outputs.write_folder_staged`); a failure to write it is
        the summary's ``export_error``, the run's other results being kept.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.parts: dict[str, list[np.ndarray]] = {
            "ranges": [],
            "inputs": [],
            "truth": [],
            "attitude": [],
        }
        self.tap: QuadrotorLogTap | None = None
        self.radio_events: list = []
        self.odometry: WheelOdometry | None = None  # a ground robot's wheel odometry ([odometry])
        self.odometry_parts: list[np.ndarray] = []

    def begin(self, ctx: EpisodeContext) -> None:
        super().begin(ctx)
        fr = ctx.frame
        if fr.has_wind or ctx.block.columns.n != 2 * fr.dimension:
            raise QuadobsError(
                f"--export-log: {fr.name!r}: the log format holds a position and velocity state only"
            )
        world = ctx.world
        if world is not None and hasattr(world, "log_tap"):  # a quadrotor: its body IMU
            self.tap = world.log_tap = QuadrotorLogTap(world)
        elif getattr(world, "radio", None) is not None:  # a point mass's radio: its events
            self.radio_events = world.event_log = []
        if self.tap is None:
            from quadobs.testbed.odometry import odometry_of

            self.odometry = odometry_of(getattr(world, "scenario", None))

    def block(self, rows: Rows) -> None:
        fr, c = self.ctx.frame, rows.block.columns
        steps = rows.ks < fr.steps  # the final row has no step: its truth only
        t = rows.t
        measured = rows.block.raw[: rows.count, c.measured][steps]
        k, h = np.nonzero(~np.isnan(measured))  # row-major: by time, then by beacon
        self.parts["ranges"].append(np.column_stack([t[steps][k], h, measured[k, h]]))
        if self.tap is not None:
            self._quadrotor_block(rows, steps)
            return
        if self.odometry is not None:
            self._odometry_block(rows, steps)
            return
        self.parts["truth"].append(np.column_stack([t, rows.truth]))
        self.parts["inputs"].append(np.column_stack([t[steps], rows.block.u[: rows.count][steps]]))

    def _odometry_block(self, rows: Rows, steps: np.ndarray) -> None:
        """A ground robot: the odometry's samples of the block's steps, and the truth with its heading."""
        odo, truth = self.odometry, rows.truth
        assert odo is not None, "an odometry export only"
        sampled = steps & (rows.ks % odo.every == 0)
        accel = rows.block.raw[: rows.count, rows.block.columns.extra["accel"]]
        measured, _, _ = odo.sample(truth[sampled, 2:4], accel[sampled], rows.t[sampled])
        self.parts["inputs"].append(np.column_stack([rows.t[sampled], measured]))
        heading = np.arctan2(truth[:, 3], truth[:, 2])
        direction = odo.direction(rows.t)  # a stop: the heading held (the path's direction)
        if direction is not None:
            from quadobs.testbed.odometry import STANDSTILL

            still = np.hypot(truth[:, 2], truth[:, 3]) < STANDSTILL
            heading[still] = np.arctan2(direction[still, 1], direction[still, 0])
        self.parts["truth"].append(np.column_stack([rows.t, truth[:, :2], heading]))

    def _quadrotor_block(self, rows: Rows, steps: np.ndarray) -> None:
        """The body IMU, the AHRS attitude where renewed, and the truth with its attitude."""
        assert self.tap is not None, "a quadrotor export only"
        world, t, n = self.tap.world, rows.t, rows.count
        self.parts["inputs"].append(np.column_stack([t[steps], self.tap.imu[:n][steps]]))
        renewed = steps & (rows.ks % world.imu.attitude_every == 0)
        self.parts["attitude"].append(np.column_stack([t[renewed], self.tap.attitude[:n][renewed]]))
        q = rows.block.raw[:n, world.spans["attitude"]].copy()
        q[~steps] = world.attitude()  # the final row (no step): MuJoCo's state at t_K
        self.parts["truth"].append(np.column_stack([t, rows.truth[:, :3], q, rows.truth[:, 3:]]))

    def end(self, completed: int, interrupted: bool) -> dict:
        if completed == 0:
            return {}
        ranges = np.vstack(self.parts["ranges"]).reshape(-1, 3)
        if self.tap:
            log = self._quadrotor_log(completed, ranges)
        elif self.odometry is not None:
            log = self._odometry_log(completed, ranges)
        else:
            log = self._log(completed, ranges)
        from quadobs.testbed.outputs import write_folder_staged

        try:  # the folder as a whole (a full disk leaves the previous one complete)
            write_folder_staged(
                self.folder, lambda tmp: write_log(log, tmp), "--export-log", set(LOG_FILES)
            )
        except QuadobsError as exc:  # the run's own results stay; the command reports it (exit 1)
            return {"export_error": str(exc)}
        return {"exported_log": str(self.folder)}

    def _log(self, completed: int, ranges: np.ndarray) -> RangeLog:
        """A vehicle's log: the navigation-frame accelerometer, position and velocity truth."""
        fr = self.ctx.frame
        dim = fr.dimension
        inputs = np.vstack(self.parts["inputs"] + [np.r_[completed * fr.dt, np.zeros(dim)][None]])
        axes = "xyz"[:dim]
        return self._range_log(
            ranges, inputs, math.nan, np.vstack(self.parts["truth"]), input_kind="imu",
            truth_columns=("time", *axes, *(f"v{a}" for a in axes)),
        )  # fmt: skip

    def _range_log(self, ranges, inputs, heading0: float, truth, **fields) -> RangeLog:
        """The log of the episode's anchors, with the radio's ranges and TDOA at their own times
        and their std where it has a radio (the grid's ``ranges`` otherwise), and ``fields``."""
        fr = self.ctx.frame
        if self.radio_events:
            rows, tdoa = radio_rows(self.radio_events, ranges, math.nan)
            fields.update(range_std=rows[:, 3], tdoa=tdoa[:, :4], tdoa_std=tdoa[:, 4])
            ranges = rows[:, :3]
        ids, beacons = np.arange(fr.beacons.shape[0]), np.asarray(fr.beacons, dtype=float)
        return RangeLog(fr.name, ids, beacons, ranges, inputs, float(heading0), truth, **fields)

    def _odometry_log(self, completed: int, ranges: np.ndarray) -> RangeLog:
        """A ground robot's log: wheel odometry, its start heading, ranges, position and heading truth."""
        fr = self.ctx.frame
        odo = np.vstack(self.parts["inputs"])
        inputs = np.vstack([odo, np.r_[completed * fr.dt, odo[-1, 1:]][None]])
        truth = np.vstack(self.parts["truth"])
        return self._range_log(
            ranges, inputs, truth[0, 3], truth, input_kind="odometry",
            truth_columns=("time", "x", "y", "heading"),
            description=(fr.description.splitlines() or [""])[0],
        )  # fmt: skip

    def _quadrotor_log(self, completed: int, grid_ranges: np.ndarray) -> RangeLog:
        """A quadrotor's log: body IMU, AHRS attitude, ranges (the radio's or the grid's), truth."""
        assert self.tap is not None, "a quadrotor export only"
        fr, world = self.ctx.frame, self.tap.world
        imu = np.vstack(self.parts["inputs"])
        inputs = np.vstack([imu, np.r_[completed * fr.dt, imu[-1, 1:]][None]])
        ranges, tdoa_rows = radio_rows(self.tap.events, grid_ranges, stated_range_std(world))
        return RangeLog(
            fr.name,
            np.arange(fr.beacons.shape[0]),
            np.asarray(fr.beacons, dtype=float),
            ranges[:, :3],
            inputs,
            float("nan"),
            np.vstack(self.parts["truth"]),
            input_kind="imu_body",
            truth_columns=("time", "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz"),
            range_std=ranges[:, 3],
            tdoa=tdoa_rows[:, :4],
            tdoa_std=tdoa_rows[:, 4],
            attitude=np.vstack(self.parts["attitude"]),
            frame="enu",
            gravity=float(-world.model.opt.gravity[2]),
            description=(fr.description.splitlines() or [""])[0],
            **_imu_noise(world.spec, fr.dt),
            range_errors=stated_range_errors(world),
        )


def _imu_noise(spec, dt: float) -> dict:
    """The IMU's stated figures (``meta.csv``) from the scenario's ``[quadrotor]`` table
    ``spec``: the white-noise densities (a standard deviation ``s`` per sample at the physics
    step ``dt`` is a density ``s sqrt(dt)``; none where it is zero), and the standard deviations
    of the constant biases and of the attitude's error as the table states them (zero included:
    a sensor stated to have none), from which the replay sizes the input noise as the live
    filters do (:func:`quadobs.testbed.logs.estimators.imu_input_noise`)."""
    densities = {
        key: std * math.sqrt(dt)
        for key, std in (("accel_noise", spec.accel_std), ("gyro_noise", spec.gyro_std))
        if std > 0
    }
    return {**densities, **{key: float(getattr(spec, key)) for key in IMU_FIGURES}}
