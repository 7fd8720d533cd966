"""The open log format, version 2: a folder of CSV files holding a log of ranges (or TDOA), planar or in space.

=================  ==============================================  ==================================
file               columns (header row; names in any order)        meaning
=================  ==============================================  ==================================
``meta.csv``       ``key,value``                                   ``version`` (2), ``name``, ...
                                                                   (:data:`~quadobs.testbed.logs.schema.META_KEYS`)
``beacons.csv``    ``id,x,y[,z]``                                  surveyed anchor positions (m);
                                                                   with ``z`` the log is in space
                                                                   (wheel odometry: the anchors'
                                                                   heights, the vehicle planar)
``ranges.csv``     ``time,beacon,range[,std]``                     one range (m) to anchor ``beacon``
``tdoa.csv``       ``time,anchor_i,anchor_j,difference[,std]``     ``|p - a_i| - |p - a_j|`` (m)
``inputs.csv``     ``time,speed,yaw_rate``                         planar wheel odometry (m/s, rad/s)
                   or ``time,ax,ay[,az]``                          accelerometer, navigation frame,
                                                                   gravity removed (m/s^2)
``imu.csv``        ``time,ax,ay,az,gx,gy,gz``                      body IMU: specific force (m/s^2),
                                                                   angular rate (rad/s)
``attitude.csv``   ``time,qw,qx,qy,qz``                            body-to-navigation quaternion
``truth.csv``      ``time,x,y[,z][,heading][,qw,qx,qy,qz]``        ground truth, for the errors only
                   ``[,vx,vy[,vz]]``
=================  ==============================================  ==================================

A log holds ``meta.csv``, ``beacons.csv`` and at least one of ``ranges.csv`` and
``tdoa.csv``; at most one of ``inputs.csv`` and ``imu.csv`` (none: a log of measurements
alone); ``attitude.csv`` and ``truth.csv`` are optional. Version 1 (no ``version`` key) is
the earlier format: ``inputs.csv`` required, no ``std``, TDOA, IMU, attitude or truth
attitude; it is still read. Each input row is held from its time to the next row's.

Times are seconds on one clock common to the files, each file sorted by time (ties
allowed; the reader sorts a file whose rows step back by at most
:data:`~quadobs.testbed.logs.schema.SORT_REACH`, 0.1 s, or holds single rows written late,
:data:`~quadobs.testbed.logs.schema.LATE_ROWS`, and says so). Every value must be
finite (a ``std`` cell may be empty: the estimator's default), ids integers, quaternions of
unit norm; a row of a timed file with an empty or ``nan`` value (a failed exchange, a motion
capture's lost frame) is left out by the reader with a note; every id in
``ranges.csv`` or ``tdoa.csv`` must be listed in ``beacons.csv``. The checks and the
limits a log file is held to are in :mod:`quadobs.testbed.logs.schema`; a malformed file
raises :class:`~quadobs.errors.QuadobsError` with one line naming the file, the row
(1-based, the header being row 1) and the column.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.schema import (
    ACCEL_NAV,
    ATTITUDE,
    FILES,
    IMU,
    IMU_FIGURES,
    MAX_SPAN,
    ODOMETRY,
    QUATERNION,
    RANGE,
    RANGE_ERRORS,
    SAMPLED_WITHIN,
    SPAN_RATIO,
    STD,
    TDOA,
    check_values,
    parse_meta,
    sampling_period,
)

__all__ = [
    "EVENT_INPUT_KINDS",
    "INPUT_KINDS",
    "LOG_FILES",
    "RangeLog",
    "read_log",
    "write_log",
]

#: The input columns (after ``time``) of each kind of input: ``imu`` is an accelerometer in
#: the navigation frame (``az`` in 3-D), ``imu_body`` a body-frame IMU, ``none`` no input.
INPUT_KINDS = {
    "odometry": ODOMETRY._fields[1:],
    "imu": ACCEL_NAV._fields[1:],
    "imu_body": IMU._fields[1:],
    "none": (),
}
#: The kind of :class:`quadobs.core.measurements.Input` each log input kind is.
EVENT_INPUT_KINDS = {
    "odometry": "odometry",
    "imu": "accel_nav",
    "imu_body": "imu_body",
    "none": "none",
}
#: The file each input kind is read from and written to.
INPUT_FILES = {"odometry": "inputs.csv", "imu": "inputs.csv", "imu_body": "imu.csv"}

#: The files of a log (every file a log folder may hold, ``meta.csv`` included).
LOG_FILES = ("meta.csv", *FILES)


def rotate_by_quaternions(q: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``R(q_k) d_k`` for each row ``q_k = (w, x, y, z)`` of ``q`` (normalised here), ``(K, 3)``,
    with ``d`` one vector ``(3,)`` or one per row: ``d + w t + v x t``, ``t = 2 v x d``,
    ``v = (x, y, z)``."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    v = q[:, 1:]
    t = 2.0 * np.cross(v, d)
    return d + q[:, :1] * t + np.cross(v, t)


def _empty(columns: int) -> np.ndarray:
    return np.empty((0, columns))


@dataclass(frozen=True, eq=False)
class RangeLog:
    """A log of ranges and/or TDOA (see the module docstring for the files).

    Attributes
    ----------
    name : str
    beacon_ids : ndarray (B,) of int
    beacons : ndarray (B, dim)
        Positions, in the order of ``beacon_ids`` (the order of the outputs); ``dim`` 2 or 3.
    ranges : ndarray (M, 3)
        ``time, beacon id, range`` rows (columns :data:`~quadobs.testbed.logs.schema.RANGE`),
        sorted by time; ``(0, 3)`` for a log of TDOA alone.
    inputs : ndarray (K, 1 + p)
        ``time`` and the columns :data:`INPUT_KINDS` ``[input_kind]`` (``dim`` of them for
        ``imu``), sorted by time, each held until the next; ``(0, 1)`` for ``none``.
    heading0 : float
        Odometry: the heading at ``inputs[0, 0]`` (rad); NaN otherwise.
    truth : ndarray (T, c) or None
        Rows of the columns :attr:`truth_columns`.
    source : str
        The folder it was read from (``""``: none).
    input_kind : {"odometry", "imu", "imu_body", "none"}
        ``imu`` is an accelerometer in the navigation frame, gravity removed (version 1's).
    truth_columns : tuple of str
        Names of the truth's columns (default for a planar log: ``time, x, y[, heading]``).
    version : {1, 2}
        The format version it was read from (2 for a log built in memory).
    range_std : ndarray (M,), optional
        Standard deviation of each range (m); NaN: the estimator's default (all NaN when not given).
    tdoa : ndarray (N, 4), optional
        ``time, anchor_i, anchor_j, difference`` rows (:data:`~quadobs.testbed.logs.schema.TDOA`).
    tdoa_std : ndarray (N,), optional
        As ``range_std``, for ``tdoa``.
    attitude : ndarray (A, 5) or None
        ``time, qw, qx, qy, qz``: the body-to-navigation rotation.
    frame : {"enu", "ned"}
        Navigation frame of a log in space (z up or down): the direction of gravity.
    gravity : float
        Magnitude of gravity (m/s^2).
    description : str
    accel_noise, gyro_noise : float
        A body IMU's stated white-noise densities (m/s^2/sqrt(Hz), rad/s/sqrt(Hz)); NaN: unknown.
    accel_bias, gyro_bias : float
        The stated standard deviation of the accelerometer's and the gyroscope's constant bias
        per axis (m/s^2, rad/s); NaN: unknown.
    attitude_std : float
        The stated error of each attitude sample per axis (rad); NaN: unknown.
    range_errors : str
        The stated error model of ``ranges``: ``"gaussian"`` (no non-line-of-sight excess, no
        outliers), ``"nlos"``, or ``""`` (unknown, taken as ``"nlos"``).
    anchor_heights : ndarray (B,) or None
        A wheel-odometry log whose ``beacons.csv`` holds ``z``: the anchors' heights (m), taken
        out of ``beacons`` (the vehicle moves in the plane; ``beacons`` keeps ``x, y``). None
        otherwise. Given ``beacons`` with three columns and odometry, they are split so.
    tag_height : float
        With ``anchor_heights``: the tag's height (m) in the same frame, as stated in
        ``meta.csv`` (NaN: not stated).
    tag_x, tag_y : float
        A wheel-odometry log: the tag's position (m) in the vehicle's frame, forwards and to
        the left of the point the odometry describes, as measured on the vehicle and stated in
        ``meta.csv`` (NaN: not stated; both or neither).
    tag_z : float
        With ``tag_x``, ``tag_y``, in a log in space whose truth holds its attitude: the tag's
        position (m) in the body frame of the point the truth describes (all three or none;
        :attr:`truth_lever`).
    read_notes : tuple of str
        What the reader did to the files' rows (:func:`read_log`): one line per file whose
        empty lines or rows with an empty or NaN value it left out, or whose rows out of
        time order it sorted; empty for a log built in memory.
    file_rows : dict
        For each file whose rows the reader left out or sorted, the file's data row (0-based)
        of each row in memory (:meth:`file_row`); empty for a log built in memory.
    """

    name: str
    beacon_ids: np.ndarray
    beacons: np.ndarray
    ranges: np.ndarray
    inputs: np.ndarray
    heading0: float
    truth: np.ndarray | None = None
    source: str = ""
    input_kind: str = "odometry"
    truth_columns: tuple = ()
    version: int = 2
    range_std: np.ndarray = field(default_factory=lambda: np.empty(0))
    tdoa: np.ndarray = field(default_factory=lambda: _empty(len(TDOA)))
    tdoa_std: np.ndarray = field(default_factory=lambda: np.empty(0))
    attitude: np.ndarray | None = None
    frame: str = "enu"
    gravity: float = 9.80665
    description: str = ""
    accel_noise: float = math.nan
    gyro_noise: float = math.nan
    accel_bias: float = math.nan
    gyro_bias: float = math.nan
    attitude_std: float = math.nan
    range_errors: str = ""
    anchor_heights: np.ndarray | None = None
    tag_height: float = math.nan
    tag_x: float = math.nan
    tag_y: float = math.nan
    tag_z: float = math.nan
    read_notes: tuple = ()
    file_rows: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        fix = lambda key, value: object.__setattr__(self, key, value)  # noqa: E731
        self._split_heights(fix)
        errors = str(self.range_errors).lower()
        if errors not in ("", *RANGE_ERRORS):
            raise QuadobsError(
                f"{self.name}: range_errors: {self.range_errors!r}; expected one of "
                f"{', '.join(RANGE_ERRORS)} (or none)"
            )
        fix("range_errors", errors)
        fix("ranges", np.asarray(self.ranges, dtype=float).reshape(-1, len(RANGE)))
        tdoa = _empty(len(TDOA)) if self.tdoa is None else self.tdoa
        fix("tdoa", np.asarray(tdoa, dtype=float).reshape(-1, len(TDOA)))
        for key, table in (("range_std", self.ranges), ("tdoa_std", self.tdoa)):
            std = getattr(self, key)
            if std is None or (np.size(std) == 0 and table.shape[0]):  # not given: all NaN
                std = np.full(table.shape[0], np.nan)
            fix(key, np.asarray(std, dtype=float))
            if getattr(self, key).shape != (table.shape[0],):
                raise QuadobsError(f"{self.name}: {key}: one value per row expected")
        if self.truth is not None and not self.truth_columns:
            fix("truth_columns", ("time", "x", "y", "heading")[: self.truth.shape[1]])
        self._check_ids()
        self._check_inputs()
        self._check_truth()
        self._check_values()

    def _split_heights(self, fix) -> None:
        """An odometry log's anchors in space: ``z`` into :attr:`anchor_heights` (the vehicle
        moves in the plane); a tag height only beside them."""
        beacons = np.asarray(self.beacons, dtype=float)
        if self.input_kind == "odometry" and beacons.ndim == 2 and beacons.shape[1] == 3:
            if self.anchor_heights is not None:
                raise QuadobsError(f"{self.name}: beacons.csv: z given twice")
            fix("anchor_heights", beacons[:, 2].copy())
            fix("beacons", beacons[:, :2].copy())
        if self.anchor_heights is not None:
            heights = np.asarray(self.anchor_heights, dtype=float).ravel()
            if self.input_kind != "odometry" or heights.shape != (beacons.shape[0],):
                raise QuadobsError(
                    f"{self.name}: beacons.csv, column z: anchor heights apart from x, y are "
                    "for a wheel-odometry log, one per anchor"
                )
            fix("anchor_heights", heights)
        elif not math.isnan(self.tag_height):
            raise QuadobsError(
                f"{self.name}: meta.csv, key tag_height: only for an odometry log whose "
                "beacons.csv holds z"
            )
        if not (math.isnan(self.tag_height) or math.isfinite(self.tag_height)):
            raise QuadobsError(f"{self.name}: meta.csv, key tag_height: not a finite number")
        self._check_tag_place()

    def _check_tag_place(self) -> None:
        """``tag_x``, ``tag_y`` (a wheel-odometry log), or ``tag_x``, ``tag_y``, ``tag_z`` (a log
        in space whose truth holds its attitude): all of them or none, finite."""
        keys = ("tag_x", "tag_y") if self.input_kind == "odometry" else ("tag_x", "tag_y", "tag_z")
        stated = [k for k in ("tag_x", "tag_y", "tag_z") if not math.isnan(getattr(self, k))]
        if not stated:
            return
        at = f"{self.name}: meta.csv, key {stated[0]}"
        if self.input_kind == "odometry" and "tag_z" in stated:
            raise QuadobsError(
                f"{self.name}: meta.csv, key tag_z: for a log in space (a wheeled robot's tag "
                "height is tag_height)"
            )
        if self.input_kind != "odometry" and self.dimension != 3:
            raise QuadobsError(f"{at}: for a wheel-odometry log or a log in space (3-D)")
        missing = [k for k in keys if k not in stated]
        if missing:
            raise QuadobsError(f"{at}: given without {', '.join(missing)}")
        if any(not math.isfinite(getattr(self, k)) for k in stated):
            raise QuadobsError(f"{self.name}: meta.csv, keys {', '.join(keys)}: not finite numbers")
        if self.input_kind != "odometry" and self.truth_part("attitude") is None:
            raise QuadobsError(
                f"{at}: the tag's place on the body the truth describes, which moves the truth "
                "to the tag by the truth's attitude: truth.csv holds none (qw,qx,qy,qz)"
            )

    @property
    def truth_lever(self) -> np.ndarray | None:
        """A log in space: the tag's stated place in the body frame of the point the truth
        describes, ``(tag_x, tag_y, tag_z)`` (m), or None. :meth:`truth_part` moves the truth's
        position to the tag by it."""
        if self.input_kind == "odometry" or math.isnan(self.tag_z):
            return None
        return np.array([self.tag_x, self.tag_y, self.tag_z], dtype=float)

    @property
    def tag_offset(self) -> tuple[float, float] | None:
        """A wheel-odometry log: the tag's stated place on the vehicle ``(tag_x, tag_y)`` (m),
        or None."""
        if self.input_kind != "odometry" or math.isnan(self.tag_x) or math.isnan(self.tag_y):
            return None
        return float(self.tag_x), float(self.tag_y)

    def _check_ids(self) -> None:
        ids = np.asarray(self.beacon_ids)
        if len(set(int(i) for i in ids)) != len(ids):
            raise QuadobsError(f"{self.name}: beacons.csv, column id: ids must be distinct")
        for fname, table, cols in (
            ("ranges.csv", self.ranges, (RANGE.beacon,)),
            ("tdoa.csv", self.tdoa, (TDOA.anchor_i, TDOA.anchor_j)),
        ):
            for c in cols:
                bad = np.flatnonzero(~np.isin(table[:, c], ids))
                if bad.size:
                    name = (RANGE._fields if fname == "ranges.csv" else TDOA._fields)[c]
                    raise QuadobsError(
                        f"{self.name}: {fname}, row {self.file_row(fname, bad[0])}, column "
                        f"{name}: unknown beacon id {table[bad[0], c]:g}"
                    )
        same = np.flatnonzero(self.tdoa[:, TDOA.anchor_i] == self.tdoa[:, TDOA.anchor_j])
        if same.size:
            raise QuadobsError(
                f"{self.name}: tdoa.csv, row {self.file_row('tdoa.csv', same[0])}, column "
                "anchor_j: the same anchor as anchor_i"
            )

    def _check_inputs(self) -> None:
        """Inputs in the beacons' dimension; odometry in the plane only, a body IMU in space only."""
        dim, kind = self.dimension, self.input_kind
        fname = INPUT_FILES.get(kind, "inputs.csv")
        if kind not in INPUT_KINDS:
            raise QuadobsError(
                f"{self.name}: input kind: expected one of {', '.join(INPUT_KINDS)}, got {kind!r}"
            )
        if kind == "none":
            if self.inputs.shape[0]:
                raise QuadobsError(f"{self.name}: input kind none: the log holds inputs")
            if not (self.ranges.shape[0] or self.tdoa.shape[0]):
                raise QuadobsError(
                    f"{self.name}: ranges.csv: a log without inputs needs ranges or TDOA"
                )
            return
        if self.inputs.shape[0] < 2:
            raise QuadobsError(f"{self.name}: {fname}: at least two rows are needed")
        if kind == "odometry" and self.inputs.shape[1] != len(ODOMETRY):
            raise QuadobsError(
                f"{self.name}: inputs.csv, row 1: odometry needs the columns time,speed,yaw_rate"
            )
        if kind == "imu" and self.inputs.shape[1] != 1 + dim:
            raise QuadobsError(
                f"{self.name}: inputs.csv, row 1: {self.inputs.shape[1] - 1} acceleration columns for "
                f"{dim}-D beacons (beacons.csv {'with' if dim == 3 else 'without'} z)"
            )
        if kind == "imu_body" and (dim != 3 or self.inputs.shape[1] != len(IMU)):
            raise QuadobsError(
                f"{self.name}: imu.csv, row 1: a body IMU needs a log in space (beacons.csv with z)"
            )

    def _check_truth(self) -> None:
        """The truth's columns: z as the beacons, a whole quaternion, a velocity of the dimension."""
        if self.truth is None:
            return
        dim, cols = self.dimension, set(self.truth_columns)
        if ("z" in cols) != (dim == 3):
            what = "a planar vehicle (wheel odometry)" if self.input_kind == "odometry" else ""
            raise QuadobsError(
                f"{self.name}: truth.csv, row 1: column z {'missing' if dim == 3 else 'given'} "
                f"for {what or f'{dim}-D beacons'}"
            )
        if cols & set(QUATERNION) and not set(QUATERNION) <= cols:
            raise QuadobsError(
                f"{self.name}: truth.csv, row 1: the attitude needs all of qw,qx,qy,qz"
            )
        velocity = {"vx", "vy", "vz"} & cols
        if velocity and velocity != set(("vx", "vy", "vz")[:dim]):
            raise QuadobsError(
                f"{self.name}: truth.csv, row 1: the velocity needs {','.join(('vx', 'vy', 'vz')[:dim])} in {dim}-D"
            )

    def _check_values(self) -> None:
        """Every table held to the schema; the span, the frame and gravity."""
        tables = [
            ("beacons.csv", *self._beacon_table()),
            ("ranges.csv", (*RANGE._fields, STD), np.column_stack([self.ranges, self.range_std])),
            ("tdoa.csv", (*TDOA._fields, STD), np.column_stack([self.tdoa, self.tdoa_std])),
        ]
        if self.input_kind != "none":
            cols = ("time", *INPUT_KINDS[self.input_kind][: self.inputs.shape[1] - 1])
            tables.append((INPUT_FILES[self.input_kind], cols, self.inputs))
        if self.attitude is not None:
            tables.append(("attitude.csv", ATTITUDE._fields, self.attitude))
        if self.truth is not None:
            tables.append(("truth.csv", tuple(self.truth_columns), self.truth))
        for fname, columns, values in tables:
            if values.shape[0]:
                check_values(f"{self.name}: {fname}", FILES[fname], columns, values)
        self._check_clocks(tables)
        self._check_time_units(tables)
        if self.frame not in ("enu", "ned") or not (
            math.isfinite(self.gravity) and self.gravity > 0
        ):
            raise QuadobsError(
                f"{self.name}: meta.csv: frame enu or ned and a positive gravity expected"
            )
        if self.version not in (1, 2):
            raise QuadobsError(f"{self.name}: meta.csv, key version: expected 1 or 2")

    def _beacon_table(self) -> tuple[tuple[str, ...], np.ndarray]:
        """``beacons.csv``'s columns and rows: ``id``, the position and, for an odometry log
        with them, the anchors' heights as ``z``."""
        columns = ("id", *"xyz"[: self.dimension])
        table = np.column_stack([self.beacon_ids, self.beacons])
        if self.anchor_heights is None:
            return columns, table
        return (*columns, "z"), np.column_stack([table, self.anchor_heights])

    def _check_clocks(self, tables) -> None:
        """Every file's times seconds on one clock: no file, and not all of them together,
        spanning more than :data:`MAX_SPAN`."""
        spans = {f: v[[0, -1], 0] for f, c, v in tables if f != "beacons.csv" and v.shape[0]}
        if not spans or float(np.ptp(np.concatenate(list(spans.values())))) <= MAX_SPAN:
            return
        for fname, (a, b) in spans.items():
            rows = next(v for f, _, v in tables if f == fname)
            zero = np.flatnonzero(rows[:, 0] == 0.0)
            if b - a > MAX_SPAN and 0 < 2 * zero.size < rows.shape[0] and a == 0.0:
                raise QuadobsError(
                    f"{self.name}: {fname}: {zero.size} rows stamped 0 (the first at row "
                    f"{self.file_row(fname, zero[0])}) beside times from "
                    f"{float(rows[zero.size, 0]):.12g} s: "
                    "stamps not set (before the clock was synchronised?): leave those rows out"
                )
            if b - a > MAX_SPAN:
                raise QuadobsError(
                    f"{self.name}: {fname} spans {b - a:.3g} s, more than {MAX_SPAN:g} s: "
                    "times must be seconds (nanoseconds: divide by 1e9; milliseconds: by 1e3)"
                )
        starts = ", ".join(f"{f} from {a:.6g} s" for f, (a, b) in spans.items())
        raise QuadobsError(
            f"{self.name}: the files' times lie more than {MAX_SPAN:g} s apart ({starts}): "
            "times must be seconds on one clock in every file"
        )

    def _check_time_units(self, tables) -> None:
        """Every file's times in one unit: a file spanning :data:`SPAN_RATIO` times the
        measurements' span (``ranges.csv`` or ``tdoa.csv``, the longer), or measurements
        spanning that many times the inputs' (which cover the log), holds times in another
        unit (milliseconds or microseconds against seconds), unless it samples more often than
        every :data:`SAMPLED_WITHIN` seconds and covers the other's span: a long file in
        seconds (an IMU logged from power-up). A short truth is not judged short."""
        times = {f: v[:, 0] for f, _, v in tables if f != "beacons.csv" and v.shape[0] > 1}
        spans = {f: float(np.ptp(t)) for f, t in times.items()}
        own = [f for f in ("ranges.csv", "tdoa.csv") if spans.get(f, 0.0) > 0.0]
        if not own:
            return
        longest = max(own, key=spans.__getitem__)
        measured = spans[longest]
        inputs = INPUT_FILES.get(self.input_kind)

        def in_seconds(long: str, short: str) -> bool:  # samples often, and covers the other
            t, s = times[long], times[short]
            return sampling_period(t) < SAMPLED_WITHIN and t[0] <= s[0] and s[-1] <= t[-1]

        for fname, span in spans.items():
            if span > SPAN_RATIO * measured and not in_seconds(fname, longest):
                culprit, other, ratio = fname, "the measurements'", span / measured
            elif (
                fname == inputs
                and 0.0 < span
                and measured > SPAN_RATIO * span
                and not in_seconds(longest, fname)
            ):
                culprit, span, other, ratio = longest, measured, f"{inputs}'s", measured / span
            else:
                continue
            raise QuadobsError(
                f"{self.name}: {culprit} spans {span:.4g} s, {ratio:.0f} times {other}: times "
                "must be seconds in every file (milliseconds: divide by 1e3; microseconds: 1e6)"
            )

    @property
    def dimension(self) -> int:
        """2 (planar) or 3."""
        return int(self.beacons.shape[1])

    @property
    def start(self) -> float:
        """The replay's time origin (s): the first input time; without inputs, the first measurement's."""
        if self.input_kind != "none":
            return float(self.inputs[0, 0])
        return float(min(t[0, 0] for t in (self.ranges, self.tdoa) if t.shape[0]))

    @property
    def end(self) -> float:
        """The last input time (s); without inputs, the last measurement's."""
        if self.input_kind != "none":
            return float(self.inputs[-1, 0])
        return float(max(t[-1, 0] for t in (self.ranges, self.tdoa) if t.shape[0]))

    @property
    def gravity_vector(self) -> np.ndarray:
        """Gravity in the navigation frame ``(3,)`` (m/s^2): ``-g e_z`` (enu) or ``+g e_z`` (ned)."""
        return np.array([0.0, 0.0, -self.gravity if self.frame == "enu" else self.gravity])

    def starts_at_rest(self) -> bool:
        """Whether the vehicle stands at the log's start: the IMU's rest test and the ranges of
        its rest (:func:`~quadobs.testbed.logs.start_prior.start_prior`'s ``at_rest``). Where it
        does not, the AHRS's alignment did not measure the gyroscope's bias on a standing body
        (:func:`~quadobs.testbed.attitude.navigation_accelerations`)."""
        from quadobs.testbed.logs.start_prior import start_prior

        return start_prior(self).at_rest

    def truth_part(self, what: str) -> np.ndarray | None:
        """The truth's ``"position"``, ``"velocity"`` or ``"attitude"`` columns, or None (no
        truth, or no such columns).

        Where a log in space states the tag's place on the body (:attr:`truth_lever`, ``d``),
        the position is the tag's, ``p + R(q) d``, with ``R(q)`` the truth's attitude: the point
        the ranges measure and the estimators estimate."""
        names = {
            "position": ("x", "y", "z")[: self.dimension],
            "velocity": ("vx", "vy", "vz")[: self.dimension],
            "attitude": QUATERNION,
        }[what]
        if self.truth is None or not set(names) <= set(self.truth_columns):
            return None
        part = self.truth[:, [self.truth_columns.index(c) for c in names]]
        lever = self.truth_lever if what == "position" else None
        if lever is not None:
            q = self.truth_part("attitude")
            assert q is not None  # checked on construction
            part = part + rotate_by_quaternions(q, lever)
        return part

    def file_row(self, fname: str, i: int) -> int:
        """The row number (1-based, the header being row 1) in the file ``fname`` of the
        in-memory row ``i`` of its table, as messages name it."""
        rows = self.file_rows.get(fname)
        return (int(i) if rows is None else int(rows[int(i)])) + 2

    def file_label(self, fname: str) -> str:
        """How a message names the log's file ``fname``: its path where the log was read from a
        folder, else the log's name and the file's."""
        return f"{self.source}/{fname}" if self.source else f"{self.name}: {fname}"

    def beacon_index(self, ids: np.ndarray) -> np.ndarray:
        """Output indices (positions in :attr:`beacon_ids`) of beacon ids."""
        ids = np.asarray(ids).astype(np.int64)
        order = np.argsort(self.beacon_ids, kind="stable")
        return order[np.searchsorted(np.asarray(self.beacon_ids)[order], ids)].astype(np.int64)

    def measurements(self) -> list:
        """Every range and TDOA as a :class:`~quadobs.core.measurements.Measurement`, in time order.

        Anchors are indices into :attr:`beacons`; at equal times, ranges come first, each
        kind in file order.
        """
        from quadobs.core.measurements import Measurement

        r_anchor = self.beacon_index(self.ranges[:, RANGE.beacon])
        t_i = self.beacon_index(self.tdoa[:, TDOA.anchor_i])
        t_j = self.beacon_index(self.tdoa[:, TDOA.anchor_j])
        events = [
            Measurement(
                float(row[RANGE.time]), "range", float(row[RANGE.range]), (int(a),), float(s)
            )
            for row, a, s in zip(self.ranges, r_anchor, self.range_std)
        ] + [
            Measurement(
                float(row[TDOA.time]),
                "tdoa",
                float(row[TDOA.difference]),
                (int(i), int(j)),
                float(s),
            )
            for row, i, j, s in zip(self.tdoa, t_i, t_j, self.tdoa_std)
        ]
        return sorted(events, key=lambda m: m.t)

    def excerpt(self, t0: float, t1: float) -> RangeLog:
        """The part of the log with ``t0 <= time - start < t1`` (s from :attr:`start`); the odometry's heading carried over.

        The truth and the attitude keep one sample either side of the span (so that they
        cover the excerpt); the inputs, the one held at ``start + t0``.
        """
        a, b = self.start + t0, self.start + t1
        inp, heading = self.inputs, self.heading0
        if self.input_kind != "none":
            k = max(int(np.searchsorted(inp[:, 0], a, side="right") - 1), 0)
            if self.input_kind == "odometry":
                heading = self.heading0 + float(np.sum(np.diff(inp[: k + 1, 0]) * inp[:k, 2]))
            inp = inp[k:][inp[k:, 0] < b].copy()
            inp[0, 0] = max(inp[0, 0], a)
        r = (self.ranges[:, 0] >= a) & (self.ranges[:, 0] < b)
        d = (self.tdoa[:, 0] >= a) & (self.tdoa[:, 0] < b)

        def around(table):
            if table is None:
                return None
            i0 = max(int(np.searchsorted(table[:, 0], a, side="right")) - 1, 0)
            i1 = int(np.searchsorted(table[:, 0], b, side="left")) + 1
            return table[i0:i1].copy()

        return dataclasses.replace(
            self,
            name=f"{self.name}[{t0:g}:{t1:g}]",
            ranges=self.ranges[r],
            range_std=self.range_std[r],
            tdoa=self.tdoa[d],
            tdoa_std=self.tdoa_std[d],
            inputs=inp,
            heading0=heading,
            truth=around(self.truth),
            attitude=around(self.attitude),
        )


def _read_meta(folder: Path) -> dict:
    from quadobs.testbed.logs.files import read_limited, text_rows

    path = folder / "meta.csv"
    raw = read_limited(path)
    if raw is None:
        raise QuadobsError(f"{path}: missing (key,value rows: version, name, ...)")
    rows = text_rows(path, raw)
    if not rows or [h.strip() for h in rows[0]] != ["key", "value"]:
        raise QuadobsError(f"{path}, row 1: expected the header key,value")
    return parse_meta(str(path), rows[1:])


def _read_tables(
    folder: Path, version: int, notes: list | None = None, row_map: dict | None = None
) -> dict:
    """Every file of the folder present (:data:`~quadobs.testbed.logs.schema.FILES`), as
    ``(columns, values)``; a line appended to ``notes`` for each file whose rows were left out
    or sorted (:func:`~quadobs.testbed.logs.files.read_table`)."""
    from quadobs.testbed.logs.files import read_limited, read_table

    tables = {}
    for fname, spec in FILES.items():
        raw = read_limited(folder / fname)
        if raw is None:
            required = spec.required or (fname == "inputs.csv" and version == 1)
            if required:
                raise QuadobsError(f"{folder / fname}: missing ({spec.described})")
            continue
        if spec.since > version:
            raise QuadobsError(
                f"{folder / fname}: a version-2 file; add the row version,2 to meta.csv"
            )
        tables[fname] = read_table(folder / fname, raw, spec, version, notes, row_map)
    if "ranges.csv" not in tables and "tdoa.csv" not in tables:
        raise QuadobsError(
            f"{folder / 'ranges.csv'}: missing (a log holds ranges.csv, tdoa.csv or both)"
        )
    if "inputs.csv" in tables and "imu.csv" in tables:
        raise QuadobsError(f"{folder / 'imu.csv'}: a log holds inputs.csv or imu.csv, not both")
    return tables


def _measurements(tables: dict, fname: str, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows (without ``std``) and the standard deviations of ``ranges.csv`` or ``tdoa.csv``."""
    if fname not in tables:
        return _empty(width), np.empty(0)
    columns, values = tables[fname]
    std = values[:, columns.index(STD)] if STD in columns else np.empty(0)
    return values[:, :width], std


def read_log(folder: str | Path) -> RangeLog:
    """Read a log folder of version 1 or 2 (see the module docstring).

    Raises
    ------
    QuadobsError
        A missing folder or file, a file that is not a regular file or too large, or a
        malformed value: one line naming the file, the row and the column.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise QuadobsError(
            f"{folder}: not a log folder (expected meta.csv, beacons.csv, ranges.csv, ...)"
        )
    meta = _read_meta(folder)
    read_notes: list[str] = []
    file_rows: dict = {}
    tables = _read_tables(folder, meta["version"], read_notes, file_rows)
    ids = tables["beacons.csv"][1][:, 0]
    if "imu.csv" in tables:
        kind = "imu_body"
    elif "inputs.csv" in tables:
        kind = "odometry" if tables["inputs.csv"][0][1] == "speed" else "imu"
    else:
        kind = "none"
    if not math.isnan(meta["heading0"]) and kind != "odometry":
        raise QuadobsError(f"{folder / 'meta.csv'}, key heading0: only for an odometry log")
    if kind == "odometry" and math.isnan(meta["heading0"]):
        raise QuadobsError(
            f"{folder / 'meta.csv'}, key heading0: missing or not a finite number (rad)"
        )
    ranges, range_std = _measurements(tables, "ranges.csv", len(RANGE))
    tdoa, tdoa_std = _measurements(tables, "tdoa.csv", len(TDOA))
    truth_columns, truth = tables.get("truth.csv", ((), None))
    name = meta["name"] or folder.name
    if any(not ch.isprintable() for ch in name):  # an escape sequence would reach the terminal
        raise QuadobsError(f"{folder / 'meta.csv'}, key name: {name!r} holds control characters")
    try:
        return RangeLog(
            name,
            ids.astype(np.int64),
            tables["beacons.csv"][1][:, 1:],
            ranges,
            tables[INPUT_FILES[kind]][1] if kind != "none" else _empty(1),
            meta["heading0"] if kind == "odometry" else math.nan,
            truth,
            str(folder),
            kind,
            tuple(truth_columns),
            version=meta["version"],
            range_std=range_std,
            tdoa=tdoa,
            tdoa_std=tdoa_std,
            attitude=tables.get("attitude.csv", (None, None))[1],
            frame=meta["frame"],
            gravity=meta["gravity"],
            description=meta["description"],
            accel_noise=meta["accel_noise"],
            gyro_noise=meta["gyro_noise"],
            **{key: meta[key] for key in IMU_FIGURES},
            range_errors=meta["range_errors"],
            tag_height=meta["tag_height"],
            tag_x=meta["tag_x"],
            tag_y=meta["tag_y"],
            tag_z=meta["tag_z"],
            read_notes=tuple(read_notes),
            file_rows=file_rows,
        )
    except QuadobsError as exc:  # name the folder's file, not the log's name
        raise QuadobsError(_in_folder(str(exc), name, folder)) from None


def _in_folder(message: str, name: str, folder) -> str:
    """``message`` of the log ``name`` read from ``folder``: ``name: ranges.csv, ...`` as
    ``folder/ranges.csv, ...``, any other ``name: ...`` as ``folder: ...``."""
    head = f"{name}: "
    if not message.startswith(head):
        return message
    rest = message[len(head) :]
    first = re.split(r"[ ,:]", rest, maxsplit=1)[0]
    return f"{folder}/{rest}" if first.endswith(".csv") else f"{folder}: {rest}"


def _csv_text(header: list[str], values, ints: tuple[int, ...] = ()) -> str:
    """``values`` under ``header`` as CSV text; floats as ``repr`` (read back exactly), NaN as an empty cell."""
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(header)
    for row in values:
        w.writerow(
            [
                v
                if isinstance(v, str)
                else str(int(v))
                if c in ints
                else ""
                if math.isnan(v)
                else repr(float(v))
                for c, v in enumerate(row)
            ]
        )
    return text.getvalue()


def _log_texts(log: RangeLog) -> dict[str, str]:
    """Every file of ``log`` in format version 2, as text."""
    dim = log.dimension
    header, rows = log._beacon_table()
    texts = {"beacons.csv": _csv_text(list(header), rows, ints=(0,))}
    for fname, cols, values, std, ints in (
        ("ranges.csv", RANGE._fields, log.ranges, log.range_std, (RANGE.beacon,)),
        ("tdoa.csv", TDOA._fields, log.tdoa, log.tdoa_std, (TDOA.anchor_i, TDOA.anchor_j)),
    ):
        if values.shape[0] == 0:
            continue
        with_std = not np.all(np.isnan(std))
        table = np.column_stack([values, std]) if with_std else values
        texts[fname] = _csv_text([*cols, *((STD,) if with_std else ())], table, ints)
    if log.input_kind != "none":
        columns = ["time", *INPUT_KINDS[log.input_kind][: log.inputs.shape[1] - 1]]
        texts[INPUT_FILES[log.input_kind]] = _csv_text(columns, log.inputs)
    if log.attitude is not None:
        texts["attitude.csv"] = _csv_text(list(ATTITUDE._fields), log.attitude)
    if log.truth is not None:
        texts["truth.csv"] = _csv_text(list(log.truth_columns), log.truth)
    meta = [["version", "2"], ["name", log.name]]
    if log.description:
        meta.append(["description", log.description])
    if log.input_kind == "odometry":
        meta.append(["heading0", repr(float(log.heading0))])
    if math.isfinite(log.tag_height):
        meta.append(["tag_height", repr(float(log.tag_height))])
    if log.tag_offset is not None:
        meta += [["tag_x", repr(log.tag_offset[0])], ["tag_y", repr(log.tag_offset[1])]]
    if log.truth_lever is not None:
        meta += [[k, repr(float(v))] for k, v in zip(("tag_x", "tag_y", "tag_z"), log.truth_lever)]
    if dim == 3:
        meta += [["frame", log.frame], ["gravity", repr(float(log.gravity))]]
    for key in ("accel_noise", "gyro_noise", *IMU_FIGURES):
        if math.isfinite(getattr(log, key)):
            meta.append([key, repr(float(getattr(log, key)))])
    if log.range_errors:
        meta.append(["range_errors", log.range_errors])
    texts["meta.csv"] = _csv_text(["key", "value"], meta)
    return texts


def write_log(log: RangeLog, folder: str | Path) -> Path:
    """Write ``log`` as a log folder of format version 2; :func:`read_log` gives it back exactly.

    The folder is written whole: built beside its target and renamed into place once
    complete (:func:`~quadobs.testbed.logs.files.staged_folder`), so a failure leaves the
    previous folder as it was. An existing folder may hold only log files (it is replaced).
    """
    from quadobs.testbed.logs.files import staged_folder

    texts = _log_texts(log)
    with staged_folder(folder, set(LOG_FILES), "log folder") as stage:
        for fname, text in texts.items():
            with open(stage / fname, "w", newline="", encoding="utf-8") as fh:
                fh.write(text)
    return Path(folder)
