"""The schema of the open log format: its files, columns and metadata keys, and the checks of each.

One table (:data:`FILES`) says, for every file of a log folder, which columns it may hold,
which of them are integers or optional, and from which format version on it
exists; :data:`META_KEYS` does the same for the keys of ``meta.csv``. The reader
(:mod:`quadobs.testbed.logs.format`) and the documentation follow these tables; the
checks below hold every value to them and name, on failure, the file, the row (1-based,
the header being row 1) and the column in one line.

Column names are constants (:data:`RANGE`, :data:`TDOA`, :data:`IMU`, ...): each is a
named tuple whose fields are the column offsets of the in-memory array of that file, so
``log.ranges[:, RANGE.beacon]`` reads the beacon ids, never ``log.ranges[:, 1]``.

The limits a log file is held to (the same spirit as a scenario file's): a regular file
(no FIFO, device, directory, dangling link or link loop), at most :data:`MAX_FILE_BYTES`
bytes, lines of at most :data:`MAX_LINE_BYTES` bytes, and a log spanning at most
:data:`MAX_SPAN` seconds (nothing is allocated per second of span by the format).
"""

from __future__ import annotations

import math
import unicodedata
from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from quadobs.errors import QuadobsError

__all__ = [
    "ATTITUDE",
    "BEACON",
    "FILES",
    "IMU",
    "IMU_FIGURES",
    "LATE_ROWS",
    "MAX_FILE_BYTES",
    "MAX_ID",
    "MAX_LINE_BYTES",
    "MAX_SPAN",
    "META_KEYS",
    "ODOMETRY",
    "QUATERNION",
    "RANGE",
    "RANGE_ERRORS",
    "SORT_REACH",
    "STD",
    "TDOA",
    "TIME",
    "FileSpec",
    "MetaKey",
    "blank_rows",
    "check_values",
    "column_index",
    "parse_meta",
    "sampling_period",
    "true_runs",
]

#: Largest log file read (bytes): 512 MiB, about 5 million rows of a body IMU.
MAX_FILE_BYTES = 512 << 20
#: Longest line of a log file (bytes, the line end excluded).
MAX_LINE_BYTES = 4096
#: Longest span of a log (s, first to last time over all its files): a scenario's longest duration.
MAX_SPAN = 1e7
#: How much longer than another one file's span may be before the log's times are taken for
#: two units (milliseconds against seconds: 1000; microseconds: a million), unless the longer
#: file samples more often than every :data:`SAMPLED_WITHIN` seconds and covers the other's
#: span (a flight controller's IMU logged from power-up beside a short UWB recording).
SPAN_RATIO = 100.0
#: The median interval (s) below which a file that spans far longer than the others is taken
#: to be in the same unit: an IMU, an attitude, an odometry or a motion capture samples at
#: 2 Hz or faster, and in milliseconds even an IMU at 1 kHz reads every 1 "second".
SAMPLED_WITHIN = 0.5
#: Largest beacon id magnitude: ids are read as floats, exact up to 2^53.
MAX_ID = 2**53
#: Largest deviation of a unit quaternion's norm from 1.
QUATERNION_TOLERANCE = 1e-3

TIME = "time"
#: The optional per-measurement standard deviation column (m) of ``ranges.csv`` and ``tdoa.csv``.
STD = "std"


def column_index(name: str, columns: tuple[str, ...]):
    """A named tuple type ``name`` whose fields are ``columns`` and an instance holding their offsets."""
    return namedtuple(name, columns)(*range(len(columns)))


#: ``beacons.csv``: id, then the position (m); ``z`` for a log in space.
BEACON = column_index("Beacon", ("id", "x", "y", "z"))
#: ``ranges.csv`` (in memory, without :data:`STD`): time (s), beacon id, range (m).
RANGE = column_index("Range", (TIME, "beacon", "range"))
#: ``tdoa.csv`` (in memory, without :data:`STD`): time, anchors i and j (ids), ``|p - a_i| - |p - a_j|`` (m).
TDOA = column_index("Tdoa", (TIME, "anchor_i", "anchor_j", "difference"))
#: ``inputs.csv`` of an odometry log: time, forward speed (m/s), yaw rate (rad/s).
ODOMETRY = column_index("Odometry", (TIME, "speed", "yaw_rate"))
#: ``inputs.csv`` of an accelerometer log (navigation frame, gravity removed; ``az`` in 3-D).
ACCEL_NAV = column_index("AccelNav", (TIME, "ax", "ay", "az"))
#: ``imu.csv``: time, specific force (m/s^2) and angular rate (rad/s), body frame.
IMU = column_index("Imu", (TIME, "ax", "ay", "az", "gx", "gy", "gz"))
#: ``attitude.csv``: time, the unit quaternion of the body-to-navigation rotation (scalar first).
ATTITUDE = column_index("Attitude", (TIME, "qw", "qx", "qy", "qz"))
#: The attitude columns, in ``attitude.csv`` and (optional) in ``truth.csv``.
QUATERNION = ("qw", "qx", "qy", "qz")
#: The truth's optional columns, in the order they are written.
TRUTH_OPTIONAL = ("heading", *QUATERNION, "vx", "vy", "vz")


@dataclass(frozen=True)
class FileSpec:
    """What one file of a log folder holds.

    Attributes
    ----------
    name : str
        File name.
    variants : tuple of tuple of str
        The accepted sets of required columns, each in its in-memory order.
    optional : tuple of str
        Columns any variant may add (in the order they are appended in memory).
    integers, std : tuple of str
        Columns holding integers (ids) and a standard deviation
        (``> 0``, or empty/NaN for the model's default).
    since : int
        The first format version holding the file.
    required : bool
        Whether every log has it (else optional, or required by another's absence).
    described : str
        The accepted headers, as errors and the docs show them.
    meaning : str
        One line for the docs.
    """

    name: str
    variants: tuple[tuple[str, ...], ...]
    optional: tuple[str, ...] = ()
    integers: tuple[str, ...] = ()
    std: tuple[str, ...] = ()
    since: int = 1
    required: bool = False
    described: str = ""
    meaning: str = ""

    def columns_of(self, header: list[str], version: int) -> tuple[str, ...] | None:
        """The in-memory column order for ``header`` (names in any order), or None if not accepted."""
        names = set(header)
        if len(names) != len(header):
            return None
        optional = self.optional if version >= 2 else ()
        for variant in self.variants:
            extra = names - set(variant)
            if set(variant) <= names and extra <= set(optional):
                return variant + tuple(c for c in optional if c in extra)
        return None


_TRUTH_2D, _TRUTH_3D = (TIME, "x", "y"), (TIME, "x", "y", "z")

#: Every file of a log folder, in the order they are read.
FILES = {
    "beacons.csv": FileSpec(
        "beacons.csv",
        (BEACON._fields[:3], BEACON._fields),
        integers=("id",),
        required=True,
        described="id,x,y[,z]",
        meaning=(
            "surveyed anchor positions (m), navigation frame; with z the log is in space (3-D), "
            "but for wheel odometry (a planar vehicle): the anchors' heights"
        ),
    ),
    "ranges.csv": FileSpec(
        "ranges.csv",
        (RANGE._fields,),
        optional=(STD,),
        integers=("beacon",),
        std=(STD,),
        described="time,beacon,range[,std]",
        meaning=(
            "one range (m) to anchor beacon at time (s), as measured (noise and a bias can take "
            "it below zero); std (m) optional, per range"
        ),
    ),
    "tdoa.csv": FileSpec(
        "tdoa.csv",
        (TDOA._fields,),
        optional=(STD,),
        integers=("anchor_i", "anchor_j"),
        std=(STD,),
        since=2,
        described="time,anchor_i,anchor_j,difference[,std]",
        meaning="one time difference of arrival as a distance, |p - a_i| - |p - a_j| (m)",
    ),
    "inputs.csv": FileSpec(
        "inputs.csv",
        (ODOMETRY._fields, ACCEL_NAV._fields[:3], ACCEL_NAV._fields),
        described="time,speed,yaw_rate (odometry) or time,ax,ay[,az] (accelerometer)",
        meaning="wheel odometry (m/s, rad/s) or an accelerometer in the navigation frame, "
        "gravity removed (m/s^2); each row held until the next",
    ),
    "imu.csv": FileSpec(
        "imu.csv",
        (IMU._fields,),
        since=2,
        described="time,ax,ay,az,gx,gy,gz",
        meaning="body-frame IMU: specific force (m/s^2) and angular rate (rad/s); held until the next row",
    ),
    "attitude.csv": FileSpec(
        "attitude.csv",
        (ATTITUDE._fields,),
        since=2,
        described="time,qw,qx,qy,qz",
        meaning="attitude: unit quaternion of the body-to-navigation rotation",
    ),
    "truth.csv": FileSpec(
        "truth.csv",
        (_TRUTH_2D, _TRUTH_3D),
        optional=TRUTH_OPTIONAL,
        described="time,x,y[,z][,heading][,qw,qx,qy,qz][,vx,vy[,vz]]",
        meaning="ground truth, for the errors only: position (m), heading (rad), attitude, velocity (m/s)",
    ),
}


@dataclass(frozen=True)
class MetaKey:
    """One key of ``meta.csv``: its meaning, its default and the version it appeared in."""

    name: str
    meaning: str
    default: object
    since: int = 1


#: Every key ``meta.csv`` may hold, each at most once.
META_KEYS = {
    k.name: k
    for k in (
        MetaKey("version", "format version, 1 or 2 (absent: 1)", 1, 2),
        MetaKey("name", "the log's name (printable text; absent: the folder's name)", ""),
        MetaKey("description", "free text (printable)", "", 2),
        MetaKey("heading0", "odometry logs: the heading (rad) at the first input time", math.nan),
        MetaKey(
            "tag_height",
            "odometry logs whose beacons.csv holds z: the tag's height (m) in the anchors' "
            "frame, measured on the vehicle (absent: unknown)",
            math.nan,
            2,
        ),
        MetaKey(
            "tag_x",
            "odometry logs: the tag's position (m) forwards of the point the odometry "
            "describes (its axle's centre), measured on the vehicle (absent: unknown); logs in "
            "space: the tag's x in the body frame of the point the truth describes",
            math.nan,
            2,
        ),
        MetaKey(
            "tag_y",
            "odometry logs: the tag's position (m) to the left of that point, measured on the "
            "vehicle (absent: unknown); logs in space: the tag's y in that body frame",
            math.nan,
            2,
        ),
        MetaKey(
            "tag_z",
            "logs in space whose truth holds its attitude: the tag's z (m) in the body frame "
            "of the point the truth describes (with tag_x, tag_y); the truth is moved to the "
            "tag (absent: the truth is the tag's)",
            math.nan,
            2,
        ),
        MetaKey(
            "frame",
            "navigation frame of a log in space: enu (z up, the default) or ned (z down)",
            "enu",
            2,
        ),
        MetaKey("gravity", "magnitude of gravity (m/s^2; default 9.80665)", 9.80665, 2),
        MetaKey(
            "accel_noise",
            "a body IMU's stated accelerometer white-noise density (m/s^2/sqrt(Hz); absent: unknown)",
            math.nan,
            2,
        ),
        MetaKey(
            "gyro_noise",
            "a body IMU's stated gyroscope white-noise density (rad/s/sqrt(Hz); absent: unknown)",
            math.nan,
            2,
        ),
        MetaKey(
            "accel_bias",
            "the stated standard deviation of the accelerometer's constant bias per axis "
            "(m/s^2, non-negative; absent: unknown)",
            math.nan,
            2,
        ),
        MetaKey(
            "gyro_bias",
            "the stated standard deviation of the gyroscope's constant bias per axis "
            "(rad/s, non-negative; absent: unknown)",
            math.nan,
            2,
        ),
        MetaKey(
            "attitude_std",
            "the stated error of each attitude.csv sample per axis (rad, non-negative; "
            "absent: unknown)",
            math.nan,
            2,
        ),
        MetaKey(
            "range_errors",
            "the stated error model of ranges.csv: gaussian (zero-mean Gaussian about the range "
            "plus any constant bias, of the stated std: no non-line-of-sight excess, no outliers) "
            "or nlos (may carry a positive excess); absent: unknown, taken as nlos",
            "",
            2,
        ),
    )
}
#: The ``meta.csv`` keys of an IMU's stated error figures beyond its densities (non-negative;
#: :func:`quadobs.testbed.logs.estimators.imu_input_noise` sizes the input noise from them).
IMU_FIGURES = ("accel_bias", "gyro_bias", "attitude_std")
FRAMES = ("enu", "ned")
#: The values of ``meta.csv``'s ``range_errors`` (:data:`META_KEYS`).
RANGE_ERRORS = ("gaussian", "nlos")


def _printable(where: str, text: str) -> str:
    bad = [c for c in text if unicodedata.category(c).startswith("C")]
    if bad:
        raise QuadobsError(f"{where}: control character {bad[0]!r} (printable text only)")
    return text


def _float_value(
    where: str, text: str, positive: bool = False, non_negative: bool = False
) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or (positive and value <= 0.0) or (non_negative and value < 0.0):
        sign = "positive " if positive else "non-negative " if non_negative else ""
        raise QuadobsError(f"{where}: {text!r} is not a {sign}finite number")
    return value


def parse_meta(where: str, rows: list[list[str]]) -> dict:
    """The metadata of ``meta.csv``'s data rows ``(key, value)``, each key once and known.

    ``where`` names the file; rows are numbered from 2. Returns every key of
    :data:`META_KEYS`, the defaults where absent.
    """
    seen: dict[str, int] = {}
    meta: dict = {k.name: k.default for k in META_KEYS.values()}
    for r, row in enumerate(rows, start=2):
        if len(row) != 2:
            raise QuadobsError(f"{where}, row {r}: {len(row)} columns, expected 2 (key,value)")
        key, text = row[0].strip(), row[1].strip()
        at = f"{where}, row {r}, key {key}"
        if key not in META_KEYS:
            raise QuadobsError(
                f"{where}, row {r}: unknown key {key!r} (known: {', '.join(META_KEYS)})"
            )
        if key in seen:
            raise QuadobsError(f"{at}: given twice (first in row {seen[key]})")
        seen[key] = r
        if key == "version":
            if text not in ("1", "2"):
                raise QuadobsError(f"{at}: {text!r}; expected 1 or 2")
            meta[key] = int(text)
        elif key in ("name", "description"):
            meta[key] = _printable(at, text)
        elif key in ("heading0", "tag_height", "tag_x", "tag_y", "tag_z"):
            meta[key] = _float_value(at, text)
        elif key in ("gravity", "accel_noise", "gyro_noise"):
            meta[key] = _float_value(at, text, positive=True)
        elif key in IMU_FIGURES:
            meta[key] = _float_value(at, text, non_negative=True)
        elif key == "frame":
            if text.lower() not in FRAMES:
                raise QuadobsError(f"{at}: {text!r}; expected one of {', '.join(FRAMES)}")
            meta[key] = text.lower()
        elif key == "range_errors":
            if text.lower() not in RANGE_ERRORS:
                raise QuadobsError(f"{at}: {text!r}; expected one of {', '.join(RANGE_ERRORS)}")
            meta[key] = text.lower()
    for key, r in seen.items():
        if META_KEYS[key].since > meta["version"]:
            raise QuadobsError(
                f"{where}, row {r}, key {key}: a version-2 key; add the row version,2"
            )
    return meta


def _first(mask: np.ndarray) -> tuple[int, int] | None:
    """``(row, column)`` offsets of the first True of a 2-D mask in row-major order, or None."""
    hits = np.argwhere(mask)
    return None if hits.size == 0 else (int(hits[0, 0]), int(hits[0, 1]))


#: The most (s) a row's time may lie before an earlier row's in a file that is read, for the
#: file's rows to be sorted by time (a host's stamps jittered by its scheduler, a serial
#: link's buffer, two threads writing one file) rather than refused: a step back further is a
#: clock set back or wrapped, whose rows no sort puts in place. A tenth of a second: a
#: scheduler's or a buffer's delay is milliseconds to tens of them.
SORT_REACH = 0.1


def blank_rows(spec: FileSpec, columns: tuple[str, ...], values: np.ndarray) -> np.ndarray:
    """The rows (a mask) of a timed file with a time and an empty or NaN value (neither an id
    nor a standard deviation): a sensor's row without a measurement (a radio's failed
    exchange, a motion capture's lost frame written blank), which a reader leaves out."""
    if not columns or columns[0] != TIME or values.shape[0] == 0:
        return np.zeros(values.shape[0], dtype=bool)
    measured = [c for c, n in enumerate(columns) if c and n not in spec.integers + spec.std]
    return np.isfinite(values[:, 0]) & np.isnan(values[:, measured]).any(axis=1)


def check_values(
    where: str,
    spec: FileSpec,
    columns: tuple[str, ...],
    values: np.ndarray,
    cell=None,
    rows: np.ndarray | None = None,
    reach: float = 0.0,
) -> None:
    """Hold the values of one file (rows in file order, ``columns`` named) to ``spec``.

    Every value finite (a standard deviation may be NaN: the model's default), integer
    columns integers of magnitude at most :data:`MAX_ID`,
    standard deviations ``> 0``, times non-decreasing (or no row more than ``reach`` seconds
    before an earlier row, for a reader that then sorts them: :data:`SORT_REACH`),
    quaternions of unit norm.

    ``cell(row_offset, column_offset)`` gives the text of a cell as written (for the
    message); default: the value itself. ``rows``: the data row of the file each row of
    ``values`` was read from (where a reader left rows out), default ``0, 1, ...``. Raises a
    one-line :class:`QuadobsError` naming ``where``, the row (data row ``i`` is row
    ``i + 2``) and the column.
    """

    def row(i: int) -> int:
        return (i if rows is None else int(rows[i])) + 2

    def fail(i: int, c: int, problem: str) -> None:
        text = cell(i, c) if cell is not None else repr(float(values[i, c]))
        raise QuadobsError(f"{where}, row {row(i)}, column {columns[c]}: {text!r} {problem}")

    if values.shape[0] == 0:
        raise QuadobsError(f"{where}, row 2: no data rows")
    std = np.array([c in spec.std for c in columns])
    finite = np.isfinite(values) | (std & np.isnan(values))
    if (at := _first(~finite)) is not None:
        fail(*at, "is not a finite number")
    for c, name in enumerate(columns):
        col = values[:, c]
        if name in spec.integers:
            bad = np.flatnonzero((col != np.round(col)) | (np.abs(col) > MAX_ID))
            if bad.size:
                fail(int(bad[0]), c, "is not an integer id (|id| <= 2^53)")
        if name in spec.std and (bad := np.flatnonzero(col <= 0.0)).size:
            fail(int(bad[0]), c, "is not a positive standard deviation")
    if columns[0] == TIME:
        _check_order(where, values[:, 0], row, reach)
        unsorted = reach > 0.0 and bool(np.any(np.diff(values[:, 0]) < 0.0))
        order = np.argsort(values[:, 0], kind="stable") if unsorted else None
        if order is None:
            _check_stamps(where, values, columns, spec, row)
        else:
            _check_stamps(where, values[order], columns, spec, lambda i: row(int(order[i])))
    if set(QUATERNION) <= set(columns):
        q = values[:, [columns.index(c) for c in QUATERNION]]
        with np.errstate(over="ignore"):  # a huge component: an infinite norm, refused below
            bad = np.flatnonzero(~(np.abs(np.linalg.norm(q, axis=1) - 1.0) <= QUATERNION_TOLERANCE))
        if bad.size:
            raise QuadobsError(
                f"{where}, row {row(int(bad[0]))}, columns qw,qx,qy,qz: not a unit quaternion "
                f"(norm {float(np.linalg.norm(q[bad[0]])):.6g})"
            )


#: The share of a file's rows that may repeat the time of a row of the same sensor (the same
#: anchor or pair, in a file of ranges or differences) with other values, before its stamps
#: are taken for coarser than its sampling. A row held for no time costs little: an IMU at
#: 1 kHz stamped to the millisecond with its jitter had 14 % of its rows share a time (a
#: flight's stand-in: 0.175 m against 0.176 m), and a flight whose files were all stamped to
#: 10 ms a quarter of its IMU's (0.138 m against 0.176 m); whole seconds, float32 stamps or
#: bursts of a serial link stamped at once share most.
COARSE_SHARE = 0.5


#: The most consecutive rows, the largest share of a file's rows, and the furthest (s) that
#: rows may lie more than :data:`SORT_REACH` behind an earlier row for the file still to be
#: sorted: single rows written late (a message delayed in a buffer by up to seconds), not a
#: clock set back, after which every row lies behind, nor a stamp never set (0).
LATE_ROWS = (3, 0.05, 2.0)


def _check_order(where: str, t: np.ndarray, row, reach: float) -> None:
    """Refuse times that step back, or (``reach > 0``, a reader that sorts) step back more
    than ``reach`` (s) behind an earlier row's other than in single rows written late
    (:data:`LATE_ROWS`), naming the first such row (``row(i)``: its number in the file)."""
    back = np.maximum.accumulate(t) - t
    far = back > reach
    bad = np.flatnonzero(far)
    if not bad.size or (reach > 0.0 and back.max() <= LATE_ROWS[2] and _single_rows(far)):
        return
    i = int(bad[0]) if not reach else _first_set_back(far, back)
    sorted_ = (
        f"; a step back of up to {reach:g} s, or a few rows written late, is sorted, more is a "
        "clock set back"
        if reach
        else ""
    )
    raise QuadobsError(
        f"{where}, row {row(i)}, column time: earlier than a row before it by "
        f"{float(back[i]):.6g} s (rows must be sorted by time{sorted_})"
    )


def true_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first index and the end (one past the last) of each run of ``True`` in ``mask``."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]]))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def _first_set_back(far: np.ndarray, back: np.ndarray) -> int:
    """The first row that single rows written late (:data:`LATE_ROWS`) do not account for:
    the first further back than ``LATE_ROWS[2]`` or beginning a run longer than
    ``LATE_ROWS[0]``, else (too many single rows) the first of ``far``."""
    begins, ends = true_runs(far)
    candidates = list(begins[ends - begins > LATE_ROWS[0]]) + list(
        np.flatnonzero(back > LATE_ROWS[2])[:1]
    )
    return int(min(candidates)) if candidates else int(begins[0])


def _single_rows(far: np.ndarray) -> bool:
    """Whether the rows of ``far`` (a mask) come in runs of at most ``LATE_ROWS[0]`` and make
    at most ``LATE_ROWS[1]`` of the rows."""
    begins, ends = true_runs(far)
    runs = ends - begins
    return int(runs.max()) <= LATE_ROWS[0] and runs.sum() <= LATE_ROWS[1] * far.size


def _check_stamps(where: str, values: np.ndarray, columns, spec: FileSpec, row) -> None:
    """Refuse a file whose stamps are coarser than its sampling, in one line.

    Rows of one sensor (one id, in a file that names anchors) at one time with other values
    cannot both be the sensor's: more than :data:`COARSE_SHARE` of them and the stamps were
    written with fewer digits than the rate needs (seconds in whole numbers, a time in float32,
    a burst of a serial link stamped at once). Rows repeated exactly are a logger's copies,
    left to the replay; rows of several anchors at one time are a round of ranges."""
    if np.count_nonzero(np.diff(values[:, 0]) == 0.0) <= COARSE_SHARE * values.shape[0]:
        return  # too few rows share a time for the count below to pass its bound
    keys = [c for c, name in enumerate(columns) if name in spec.integers]
    order = np.lexsort([values[:, 0], *(values[:, k] for k in keys)])
    v = values[order]
    same = np.diff(v[:, 0]) == 0.0
    if keys:
        same &= np.all(v[1:, keys] == v[:-1, keys], axis=1)
    both_nan = np.isnan(v[1:]) & np.isnan(v[:-1])
    differ = same & np.any((v[1:] != v[:-1]) & ~both_nan, axis=1)
    count = int(differ.sum())
    if count > COARSE_SHARE * values.shape[0]:
        first = int(order[1:][differ].min())
        raise QuadobsError(
            f"{where}: {count} of {values.shape[0]} rows share their time with a row "
            f"{'of the same id ' if keys else ''}before them and hold other values (the first "
            f"at row {row(first)}, time {values[first, 0]:.12g}): stamps written with fewer "
            "digits than the sampling needs (whole seconds, float32, a burst stamped at once)?"
        )


def span_apart(table, lo: float, hi: float) -> tuple[float, float] | None:
    """A table's first and last time (s, its first column) where its span does not overlap
    ``[lo, hi]`` (a file on another clock than the measurements'), else None (an empty or
    missing table too)."""
    if table is None or not table.shape[0]:
        return None
    a, b = float(table[0, 0]), float(table[-1, 0])
    return (a, b) if b < lo or a > hi else None


def sampling_period(t) -> float:
    """The median of the positive intervals between the times ``t`` (s), NaN where none: a
    stream's sampling period, times repeated (stamps coarser than the sampling) left out."""
    steps = np.diff(np.asarray(t, dtype=float))
    steps = steps[steps > 0.0]
    return float(np.median(steps)) if steps.size else math.nan
