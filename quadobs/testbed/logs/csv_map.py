"""CSV files of another layout imported into the open log format, by a small TOML column map.

Datasets that come as CSV seldom hold the format's columns: a range file may read
``t_twr_ms, anchor, dist_cm``, a gyroscope deg/s, a motion capture's quaternion scalar-last,
and a wheeled robot's file its wheels' speeds. Converting each by hand is where units and
orders go wrong silently. A *column map* (:class:`CsvMap`, a TOML file) states instead, per
stream, the file, the columns by name and their units, and ``quadobs import-csv MAP --out
DIR`` writes the log folder; the replay's checks then run on it as on any log.

============  =========================================================================
stream        keys beside the file's (``file``, ``time``, ``time_unit``, ``time_offset``,
              ``delimiter``, ``skip_rows``, ``names``, ``select``)
============  =========================================================================
``ranges``    ``anchor`` and ``value`` (one range a row; ``anchor_pattern`` as for bags),
              or ``columns = {ID = "column", ...}`` (one column per anchor, an empty cell:
              no range), or ``files = {ID = "file", ...}`` and ``value`` (one file per
              anchor, in place of ``file``); ``std`` (a column, or one number for every range, in ``unit``:
              a median outside :data:`STD_SPAN` is refused); ``unit``
``tdoa``      ``anchor_i``, ``anchor_j``, ``value``, ``std``, ``unit``, ``sign``
``imu``       ``accel = [x, y, z]`` and ``gyro = [x, y, z]`` (column names, body frame);
              ``accel_unit`` (``m/s^2`` or ``g``), ``gyro_unit`` (``rad/s`` or ``deg/s``)
``attitude``  ``quaternion = {w = ..., x = ..., y = ..., z = ...}`` (each component by
              name: no order to get wrong) or ``euler = {roll = ..., pitch = ...,
              yaw = ...}`` with ``angle_unit``; the body-to-navigation rotation
``odometry``  ``speed`` and ``yaw_rate`` (``speed_unit``, ``rate_unit``), or the wheels'
              ground speeds ``left``, ``right`` and ``track`` (m; with ``wheel_radius``
              (m), the wheels' rates in ``rate_unit``; ``left_sign``, ``right_sign`` -1
              for a wheel counting backwards), or the odometry's poses ``x``, ``y``,
              ``yaw`` (``unit``, ``angle_unit``); repeated rows left out
``truth``     ``position = [x, y(, z)]`` (``unit``), and a ``quaternion`` or ``euler`` as
              for ``attitude``, or a planar robot's ``heading`` (``angle_unit``);
              ``velocity = [vx, vy(, vz)]`` (``unit`` per second) where it holds one
============  =========================================================================

A vector's column (in ``accel``, ``gyro``, ``position``, ``velocity``) written ``"-ay"`` is
read negated: an axis of the sensor that points the other way.

Units: times ``s`` (the default), ``ms``, ``us``, ``ns``, ``iso8601`` (text such as
``2023-11-14T22:13:20.062+00:00``; without an offset, UTC); lengths ``m`` (the default),
``cm``, ``mm``; speeds ``m/s``, ``cm/s``, ``mm/s``; angles ``rad`` (the default) or ``deg``;
rates ``rad/s`` or ``deg/s``; ``g`` is standard gravity, 9.80665 m/s^2. ``time_offset``
(s) is added to a stream's times after its unit: a file stamped on another clock. Euler
angles compose as ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (aerospace order).

A file is comma-separated with a header row unless its table says otherwise:
``delimiter`` (one character, ``"\\t"`` for tabs, or ``"whitespace"``: runs of spaces and
tabs, as a column-aligned file has), ``select = {column = "value"}`` (the lines of one kind,
in a file that interleaves several: the others are read as blank lines, so line numbers
hold), ``skip_rows`` (lines before the header)
and ``names`` (the columns of a file without a header). Several streams may read one file.
Files are found beside the map. Each is read by ``pyarrow.csv``; a cell that is not a
number is named by file, line and column. An empty or non-finite cell leaves its row out of
that stream, counted in a note; a row with none of the stream's cells filled (another
sensor's row, where one file holds every sensor with a time column each) is skipped and
counted apart.

The map's top level holds ``anchors`` (a ``beacons.csv``-style file or a table, as for
bags, or a survey file of its own layout: ``{file = ..., id = ..., x = ..., y = ..., z =
..., unit = ...}`` with the file keys above), ``time_unit`` and ``delimiter`` (every stream's default), and the keys of
``meta.csv``: ``name``, ``description``, ``frame``, ``gravity``, ``heading0`` (wheel
odometry: required), ``tag_height``, ``tag_x``, ``tag_y``, ``tag_z``, ``accel_noise``, ``gyro_noise``,
``accel_bias``, ``gyro_bias``, ``attitude_std`` and ``range_errors``
(:data:`~quadobs.testbed.logs.schema.META_KEYS`). An example::

    name = "room-2"
    anchors = "anchors.csv"
    heading0 = 1.571
    [ranges]
    file = "uwb.csv"
    time = "stamp_ms"
    time_unit = "ms"
    anchor = "anchor_id"
    value = "dist_cm"
    unit = "cm"
    [odometry]
    file = "wheels.csv"
    time = "stamp_ms"
    time_unit = "ms"
    left = "v_left"
    right = "v_right"
    track = 0.235
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog
from quadobs.testbed.logs.importing import STATED_META_KEYS, stated_meta
from quadobs.testbed.logs.schema import COARSE_SHARE

__all__ = ["STREAMS", "CsvMap", "import_csv", "load_csv_map", "parse_csv_map"]

#: The keys every stream's table may hold (beside its own, :data:`STREAMS`).
FILE_KEYS = (
    "file",
    "time",
    "time_unit",
    "time_offset",
    "delimiter",
    "skip_rows",
    "names",
    "select",
)
#: Each stream's own keys.
STREAMS: dict[str, tuple[str, ...]] = {
    "ranges": ("anchor", "anchor_pattern", "value", "columns", "files", "std", "unit"),
    "tdoa": ("anchor_i", "anchor_j", "anchor_pattern", "value", "std", "unit", "sign"),
    "imu": ("accel", "gyro", "accel_unit", "gyro_unit"),
    "attitude": ("quaternion", "euler", "angle_unit"),
    "odometry": (
        "speed",
        "yaw_rate",
        "speed_unit",
        "rate_unit",
        "left",
        "right",
        "track",
        "wheel_radius",
        "left_sign",
        "right_sign",
        "x",
        "y",
        "yaw",
        "unit",
        "angle_unit",
    ),
    "truth": ("position", "quaternion", "euler", "heading", "velocity", "unit", "angle_unit"),
}
#: Each unit's factor to SI.
UNITS = {
    "time_unit": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "iso8601": 1.0},
    "unit": {"m": 1.0, "cm": 1e-2, "mm": 1e-3},
    "speed_unit": {"m/s": 1.0, "cm/s": 1e-2, "mm/s": 1e-3},
    "angle_unit": {"rad": 1.0, "deg": math.pi / 180.0},
    "rate_unit": {"rad/s": 1.0, "deg/s": math.pi / 180.0},
    "gyro_unit": {"rad/s": 1.0, "deg/s": math.pi / 180.0},
    "accel_unit": {"m/s^2": 1.0, "g": 9.80665},
}
_TOP_KEYS = ("anchors", "time_unit", "delimiter")
#: The ``meta.csv`` keys a map may set at its top level.
_META_KEYS = ("name", "description", "frame", "gravity", "heading0", *STATED_META_KEYS)


@dataclass(frozen=True)
class CsvMap:
    """Which file and columns hold which stream, in which units (module docstring).

    Attributes
    ----------
    streams : dict of str to dict
        Per stream present: its table, checked, with the top level's defaults filled in.
    anchors : dict of int to tuple of float
        Anchor id to position (m).
    meta : dict
        The ``meta.csv`` keys the map sets (:data:`~quadobs.testbed.logs.schema.META_KEYS`).
    base : Path
        The folder the files are named from (the map's).
    where : str
        How errors name the map.
    """

    streams: dict = field(default_factory=dict)
    anchors: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    base: Path = Path(".")
    where: str = "column map"

    def file_names(self) -> dict:
        """The log format's file names, each with the stream of this map and its file that
        it is written from (``"ranges.csv"``: ``"[ranges] uwb.csv"``), for messages."""
        written = {"odometry": "inputs.csv", "imu": "imu.csv"}
        return {
            written.get(stream, f"{stream}.csv"): f"[{stream}] {opts.get('file', 'files')}"
            for stream, opts in self.streams.items()
        } | {"beacons.csv": "the map's anchors"}

    def in_its_names(self, text: str) -> str:
        """``text`` with the format's file names as this map's streams and files (one pass:
        a file of the map named like one of the format's is left as it is)."""
        names = self.file_names()
        pattern = re.compile("|".join(re.escape(k) for k in sorted(names, key=len, reverse=True)))
        return pattern.sub(lambda m: names[m.group(0)], text)


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _column_list(value, sizes: tuple[int, ...], where: str) -> None:
    if not (
        isinstance(value, list)
        and len(value) in sizes
        and all(isinstance(v, str) and v for v in value)
    ):
        n = " or ".join(map(str, sizes))
        raise QuadobsError(f"{where}: expected a list of {n} column names")


def _column_table(value, keys: tuple[str, ...], where: str) -> None:
    if not (
        isinstance(value, dict)
        and set(value) == set(keys)
        and all(isinstance(v, str) and v for v in value.values())
    ):
        spec = ", ".join(f'{k} = "column"' for k in keys)
        raise QuadobsError(f"{where}: expected a table {{{spec}}}, each component by name")


def _check_key(stream: str, key: str, value, where: str) -> None:
    """One key of a stream's table, by its kind (module docstring)."""
    at = f"{where}: [{stream}] {key}"
    if key in UNITS:
        if value not in UNITS[key]:
            raise QuadobsError(f"{at}: expected one of {', '.join(UNITS[key])}, got {value!r}")
    elif key in ("time_offset", "track", "wheel_radius"):
        positive = key != "time_offset"
        if not _is_number(value) or (positive and value <= 0):
            what = "a positive number (m)" if positive else "a number (s)"
            raise QuadobsError(f"{at}: expected {what}")
    elif key == "skip_rows":
        if not (isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1000):
            raise QuadobsError(f"{at}: expected a whole number of lines")
    elif key == "delimiter":
        one = isinstance(value, str) and len(value) == 1 and value not in '"\r\n'
        if not (one or value == "whitespace"):
            raise QuadobsError(f'{at}: expected one character (",", ";", "\\t") or "whitespace"')
    elif key in ("sign", "left_sign", "right_sign"):
        if value not in (1, -1) or isinstance(value, bool):
            raise QuadobsError(f"{at}: expected 1 or -1")
    elif key in ("accel", "gyro"):
        _column_list(value, (3,), at)
    elif key in ("position", "velocity"):
        _column_list(value, (2, 3), at)
    elif key == "names":
        _column_list(value, tuple(range(1, 1001)), at)
    elif key == "quaternion":
        _column_table(value, ("w", "x", "y", "z"), at)
    elif key == "euler":
        _column_table(value, ("roll", "pitch", "yaw"), at)
    elif key in ("columns", "files"):
        _check_wide(value, at)
    elif key == "select":
        if not (
            isinstance(value, dict)
            and value
            and all(isinstance(v, str | int) and not isinstance(v, bool) for v in value.values())
        ):
            raise QuadobsError(f'{at}: expected a table {{column = "value"}}')
    elif key == "anchor_pattern":
        from quadobs.testbed.logs.importing import check_anchor_pattern

        check_anchor_pattern(value, f"{where}: [{stream}]")
    elif key == "std":
        if not (isinstance(value, str) and value) and not (_is_number(value) and value > 0):
            raise QuadobsError(f"{at}: expected a column name or a positive number")
    elif not (isinstance(value, str) and value):
        what = "a file's name, beside the map" if key == "file" else "a column name"
        raise QuadobsError(f"{at}: expected text ({what})")


def _check_wide(value, at: str) -> None:
    if not isinstance(value, dict) or not value:
        raise QuadobsError(f'{at}: expected a table of anchor id = "column"')
    for key, column in value.items():
        if not re.fullmatch(r"-?[0-9]{1,15}", key):
            raise QuadobsError(f"{at}.{key}: the key must be an anchor's integer id")
        if not (isinstance(column, str) and column):
            raise QuadobsError(f"{at}.{key}: expected a column name")


#: Per stream, the alternatives of columns it needs (one of them, whole), and what each forbids.
_NEEDS = {
    "ranges": (("anchor", "value"), ("columns",), ("files", "value")),
    "tdoa": (("anchor_i", "anchor_j", "value"),),
    "imu": (("accel", "gyro"),),
    "attitude": (("quaternion",), ("euler",)),
    "odometry": (("speed", "yaw_rate"), ("left", "right", "track"), ("x", "y", "yaw")),
    "truth": (("position",),),
}


def _check_needs(stream: str, table: dict, where: str) -> None:
    """Exactly one of the stream's layouts (:data:`_NEEDS`), whole."""
    ways = _NEEDS[stream]
    shared = {k for w in ways for k in w if sum(k in v for v in ways) > 1}
    given = [w for w in ways if any(k in table for k in w if k not in shared)]
    text = " or ".join("(" + ", ".join(w) + ")" for w in ways)
    if len(given) != 1:
        if given:
            raise QuadobsError(f"{where}: [{stream}] expected one of {text}, not several")
        raise QuadobsError(f"{where}: [{stream}] expected one of {text}")
    stray = sorted(k for w in ways for k in w if k in table and k not in given[0])
    if stray:
        raise QuadobsError(
            f"{where}: [{stream}] {stray[0]} is not of ({', '.join(given[0])}): leave it out"
        )
    missing = [k for k in given[0] if k not in table]
    if missing:
        raise QuadobsError(
            f"{where}: [{stream}] {', '.join(given[0])} together: {missing[0]} missing"
        )
    if "wheel_radius" in table and "speed_unit" in table:
        raise QuadobsError(
            f"{where}: [{stream}] wheel_radius makes left and right the wheels' rates "
            "(rate_unit), not speeds (speed_unit)"
        )
    wheel = ("wheel_radius", "left_sign", "right_sign")
    if "left" not in table and any(k in table for k in wheel):
        raise QuadobsError(f"{where}: [{stream}] {', '.join(wheel)}: for left, right and track")
    if stream == "odometry":
        _check_odometry_units(table, given[0], where)
    if sum(k in table for k in ("quaternion", "euler", "heading")) > 1:
        raise QuadobsError(f"{where}: [{stream}] one of quaternion, euler or heading")


def _check_odometry_units(table: dict, layout: tuple, where: str) -> None:
    """The unit keys of the odometry's layout only: a unit the layout does not read would be
    ignored, and the values read in the default one."""
    units = {
        "speed": ("speed_unit", "rate_unit"),
        "left": ("rate_unit",) if "wheel_radius" in table else ("speed_unit",),
        "x": ("unit", "angle_unit"),
    }[layout[0]]
    stray = [k for k in ("speed_unit", "rate_unit", "unit", "angle_unit") if k in table]
    stray = [k for k in stray if k not in units]
    if stray:
        raise QuadobsError(
            f"{where}: [odometry] {stray[0]} is not read with ({', '.join(layout)}"
            f"{', wheel_radius' if 'wheel_radius' in table else ''}): its unit keys are "
            f"{' and '.join(units)}"
        )


def _stream(stream: str, value, top: dict, where: str) -> dict:
    """A stream's table checked, the top level's ``time_unit`` and ``delimiter`` filled in."""
    if not isinstance(value, dict):
        raise QuadobsError(f"{where}: [{stream}]: expected a table")
    known = (*FILE_KEYS, *STREAMS[stream])
    unknown = sorted(set(value) - set(known))
    if unknown:
        upper = unknown[0] in (*_TOP_KEYS, *_META_KEYS)
        hint = " (a key of the map's top level: write it before the first [table])" if upper else ""
        raise QuadobsError(
            f"{where}: [{stream}] unknown key {unknown[0]!r}{hint} (known: {', '.join(known)})"
        )
    for key in ("file", "time"):
        if key not in value and not (key == "file" and "files" in value):
            raise QuadobsError(f'{where}: [{stream}] {key} missing ({key} = "...")')
    if "file" in value and "files" in value:
        raise QuadobsError(f"{where}: [{stream}] file or files, not both")
    for key, item in value.items():
        _check_key(stream, key, item, where)
    _check_needs(stream, value, where)
    table = {"time_unit": top.get("time_unit", "s"), "delimiter": top.get("delimiter", ",")}
    return {**table, **value}


def parse_csv_map(data: dict, where: str = "column map", base: Path | None = None) -> CsvMap:
    """A :class:`CsvMap` from its TOML document (module docstring); unknown keys refused."""
    from quadobs.testbed.logs.importing import read_anchors

    top = {k: v for k, v in data.items() if k not in STREAMS}
    for key in top:
        if key not in (*_TOP_KEYS, *_META_KEYS):
            known = ", ".join((*_TOP_KEYS, *_META_KEYS, *(f"[{s}]" for s in STREAMS)))
            raise QuadobsError(f"{where}: unknown key {key!r} (known: {known})")
    for key in ("time_unit", "delimiter"):
        if key in top:
            _check_key("top level", key, top[key], where)
    streams = {k: _stream(k, v, top, where) for k, v in data.items() if k in STREAMS}
    if not {"ranges", "tdoa"} & set(streams):
        raise QuadobsError(f"{where}: no [ranges] or [tdoa] table")
    if {"imu", "odometry"} <= set(streams):
        raise QuadobsError(f"{where}: [imu] and [odometry]: a log holds one kind of inputs")
    if "anchors" not in top:
        raise QuadobsError(f'{where}: anchors missing (anchors = "anchors.csv", or a table)')
    meta = stated_meta(top, _META_KEYS, where)
    if "odometry" in streams and "heading0" not in meta:
        raise QuadobsError(
            f"{where}: [odometry] needs heading0, the heading (rad) at its first row in the "
            "anchors' frame (the odometry's own frame does not tell it)"
        )
    if "heading0" in meta and "odometry" not in streams:
        raise QuadobsError(f"{where}: heading0 is for wheel odometry, and no [odometry] is mapped")
    spec = top["anchors"]
    if isinstance(spec, dict) and "file" in spec:
        anchors = _anchors_from_columns(spec, where, base or Path("."))
    else:
        anchors = read_anchors(spec, where, base)
    return CsvMap(streams, anchors, meta, base or Path("."), where)


_ANCHOR_KEYS = (
    "file",
    "id",
    "x",
    "y",
    "z",
    "unit",
    "anchor_pattern",
    "delimiter",
    "skip_rows",
    "names",
)


def _anchors_from_columns(spec: dict, where: str, base: Path) -> dict:
    """Anchors from a survey file of any layout: ``anchors = {file = ..., id = ..., x = ...,
    y = ..., z = ..., unit = ...}`` (module docstring); each anchor once, every cell a value."""
    at = f"{where}: anchors"
    unknown = sorted(set(spec) - set(_ANCHOR_KEYS))
    if unknown:
        raise QuadobsError(f"{at}: unknown key {unknown[0]!r} (known: {', '.join(_ANCHOR_KEYS)})")
    for key in ("id", "x", "y"):
        if key not in spec:
            raise QuadobsError(f'{at}: {key} missing ({key} = "column")')
    for key, value in spec.items():
        _check_key("anchors", key, value, where)
    axes = {k: spec[k] for k in ("x", "y", "z") if k in spec}
    v, skip = read_columns(spec, base, "[anchors]", axes, {"id": spec["id"]})
    ids = _anchor_ids(v["id"], spec.get("anchor_pattern", ""), at)
    table = np.column_stack([ids, *(v[k] * UNITS["unit"][spec.get("unit", "m")] for k in axes)])
    bad = np.flatnonzero(~np.isfinite(table).all(axis=1))
    if bad.size:
        from quadobs.testbed.logs.files import read_limited

        line = _line_of(read_limited(base / spec["file"]) or b"", skip, int(bad[0]))
        raise QuadobsError(
            f"{base / spec['file']}, line {line}: an anchor's cell empty or not a finite number"
        )
    found, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        k = int(np.flatnonzero(counts > 1)[0])
        raise QuadobsError(
            f"{base / spec['file']}: anchor id {int(found[k])} given {int(counts[k])} times"
        )
    if not ids.size:
        raise QuadobsError(f"{base / spec['file']}: no anchor")
    return {int(row[0]): tuple(float(c) for c in row[1:]) for row in table}


def load_csv_map(path: str | Path) -> CsvMap:
    """:func:`parse_csv_map` of a TOML file (a regular file of at most 1 MiB)."""
    from quadobs.testbed.logs.importing import read_map

    path = Path(path)
    return parse_csv_map(read_map(path, repr(str(path))), str(path), path.parent)


class _Columns:
    """The map's files read by ``pyarrow.csv``: each stream's columns as arrays (module
    docstring), with the rows it left out counted for the notes."""

    def __init__(self, csv_map: CsvMap) -> None:
        self.map = csv_map
        self.left_out: dict[str, int] = {}
        self.blank: dict[str, int] = {}
        self.repeated: dict[str, int] = {}
        self.shared: dict[str, int] = {}

    def notes(self) -> list[str]:
        """One line per stream and kind of row the reading left out or skipped."""
        said = {
            "left out: a cell empty or not finite": self.left_out,
            "with none of its cells filled skipped (other streams' rows, where one file holds "
            "several)": self.blank,
            "repeated, left out": self.repeated,
            "share their time with the next and hold other values: left out (the later kept; "
            "an input would hold the earlier for no time)": self.shared,
        }
        return [
            f"[{s}] {n} rows {what}"
            for what, counts in said.items()
            for s, n in sorted(counts.items())
        ]

    def read(self, stream: str, numeric: dict, text: dict | None = None) -> tuple[dict, int]:
        """``{key: values}`` of the stream's columns (:func:`read_columns`)."""
        opts = self.map.streams[stream]
        return read_columns(opts, self.map.base, f"[{stream}]", numeric, text)

    def without_repeats(self, stream: str, rows: np.ndarray) -> np.ndarray:
        """Measurement rows without exact repeats of a row (a logger's double write), counted
        for the notes; the order kept."""
        _, first = np.unique(np.nan_to_num(rows, nan=-np.inf), axis=0, return_index=True)
        if first.size == rows.shape[0]:
            return rows
        self.repeated[stream] = self.repeated.get(stream, 0) + rows.shape[0] - first.size
        return rows[np.sort(first)]

    def unique_times(self, stream: str, rows: np.ndarray) -> np.ndarray:
        """Sorted ``rows`` with one row per time, the last (an input held until the next row
        holds an earlier one of its time for no time): repeats of a row (the same values) and
        rows of other values are counted apart for the notes; where the latter are more than
        :data:`COARSE_SHARE` of the rows, the stamps are coarser than the sampling, refused
        naming the file."""
        same = np.flatnonzero(np.diff(rows[:, 0]) == 0.0) + 1
        if same.size == 0:
            return rows
        differ = same[np.any(rows[same] != rows[same - 1], axis=1)]
        if differ.size > COARSE_SHARE * rows.shape[0]:
            opts = self.map.streams[stream]
            raise QuadobsError(
                f"{self.map.base / opts['file']}: [{stream}] {differ.size} of "
                f"{rows.shape[0]} rows share their time with the row before and hold other "
                f"values (the first at {rows[differ[0], 0]:.10g} s, after time_unit and "
                "time_offset): stamps written with fewer digits than the sampling needs?"
            )
        if differ.size:
            self.shared[stream] = self.shared.get(stream, 0) + int(differ.size)
        repeats = same.size - differ.size
        if repeats:
            self.repeated[stream] = self.repeated.get(stream, 0) + repeats
        return np.delete(rows, same - 1, axis=0)  # the last row of each time

    def time(self, stream: str, values: np.ndarray) -> np.ndarray:
        """A stream's times in seconds on the ranges' clock."""
        opts = self.map.streams[stream]
        return values * UNITS["time_unit"][opts["time_unit"]] + float(opts.get("time_offset", 0.0))

    def keep(
        self, stream: str, rows: np.ndarray, std: np.ndarray | None = None, blank=None
    ) -> np.ndarray:
        """The rows whose every value is finite, sorted by time (stably), the rest counted;
        with ``std`` (NaN: not stated) as a last column. ``blank``: the rows of none of the
        stream's cells (default: those whose values are all NaN)."""
        ok = np.isfinite(rows).all(axis=1)
        if blank is None:
            blank = np.isnan(rows[:, 1:]).all(axis=1)  # another stream's row of a shared file
        blank = blank & ~ok
        if blank.any():
            self.blank[stream] = self.blank.get(stream, 0) + int(blank.sum())
        if not (ok | blank).all():
            self.left_out[stream] = self.left_out.get(stream, 0) + int((~(ok | blank)).sum())
        rows = (rows if std is None else np.column_stack([rows, std]))[ok]
        return rows[np.argsort(rows[:, 0], kind="stable")]


def _header(opts: dict, path: Path, raw: bytes, delimiter: str) -> tuple[list, int]:
    """The file's column names and the lines before its first row."""
    skip = opts.get("skip_rows", 0)
    if "names" in opts:
        return list(opts["names"]), skip
    lines = _first_lines(raw, skip + 1)
    if len(lines) <= skip:
        raise QuadobsError(f"{path}: no header row (skip_rows = {skip})")
    try:
        header = next(csv.reader(io.StringIO(lines[skip]), delimiter=delimiter), [])
    except csv.Error as exc:
        raise QuadobsError(f"{path}, line {skip + 1}: not a CSV header ({exc})") from None
    return [h.strip() for h in header], skip + 1


def _first_lines(raw: bytes, count: int) -> list[str]:
    """The first ``count`` lines of a file (a byte-order mark skipped), without reading on."""
    end = -1
    for _ in range(count):
        end = raw.find(b"\n", end + 1)
        if end < 0:
            end = len(raw)
            break
    return raw[:end].decode("utf-8-sig", "replace").splitlines()


#: The map's name of each column key the readers use within a stream.
_KEY_NAMES = {"id": "anchor", "i": "anchor_i", "j": "anchor_j"}
_VECTOR_KEYS = {"p": "position", "v": "velocity", "a": "accel", "w": "gyro"}


def _key_label(key: str) -> str:
    """How the map names the column a reader's ``key`` stands for (``"a1"``: ``accel[1]``)."""
    if key in _KEY_NAMES:
        return _KEY_NAMES[key]
    if len(key) == 2 and key[0] in _VECTOR_KEYS and key[1].isdigit():
        return f"{_VECTOR_KEYS[key[0]]}[{key[1]}]"
    if key[:1] == "q" and key[1:] in ("w", "x", "y", "z"):
        return f"quaternion.{key[1:]}"
    if key[:1] == "e" and key[1:] in ("roll", "pitch", "yaw"):
        return f"euler.{key[1:]}"
    if key[:1] == "r" and key[1:].lstrip("-").isdigit():
        return f"columns.{key[1:]}"
    return key


def _check_columns(path: Path, header: list, wanted: dict, label: str, skip_rows: int) -> None:
    for key, column in wanted.items():
        key = _key_label(key)
        if header.count(column) > 1:
            raise QuadobsError(
                f"{path}: {header.count(column)} columns named {column!r} ({label} {key}): "
                "name each with names = [...] and skip_rows = 1"
            )
        if column not in header:
            hint = ""
            if header and header[0].lstrip().startswith(("#", "%", "//")):
                hint = f"; a comment before the header? skip_rows = {skip_rows + 1}"
            raise QuadobsError(
                f"{path}: no column {column!r} ({label} {key}; its columns: "
                f"{', '.join(header[:20])}{hint})"
            )


def _whitespace_separated(raw: bytes) -> bytes:
    """A file of columns aligned by runs of spaces or tabs, as comma-separated: each line's
    leading and trailing blanks dropped, each run inside it a comma."""
    raw = re.sub(rb"(?m)^[ \t]+|[ \t]+(?=\r?$)", b"", raw)
    return re.sub(rb"[ \t]+", b",", raw)


def _check_text(path: Path, raw: bytes) -> None:
    """Refuse a file that is not UTF-8 text, naming what it looks like."""
    if raw[:2] == b"\x1f\x8b":
        raise QuadobsError(f"{path}: gzip-compressed: decompress it first (gunzip)")
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise QuadobsError(f"{path}: UTF-16 text: save it as UTF-8")
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise QuadobsError(
            f"{path}: not UTF-8 text (byte {exc.start}: {raw[exc.start : exc.start + 1]!r}): "
            "save it as UTF-8"
        ) from None


def _selected(raw: bytes, skip: int, wanted: list, delimiter: str) -> bytes:
    """``raw`` with each data line whose cells do not hold ``wanted`` (``(index, value)``
    pairs, compared without blanks or quotes around, and as numbers where the value is one)
    made blank: a file that interleaves messages of several kinds, told by a column. Blank
    lines are no rows, and lines keep their numbers."""
    lines = raw.split(b"\n")
    for n in range(skip, len(lines)):
        line = lines[n].rstrip(b"\r")
        if n == 0 and line.startswith(b"\xef\xbb\xbf"):  # a byte-order mark
            line = line[3:]
        text = line.decode("utf-8", "replace")
        if '"' in text:
            cells = next(csv.reader([text], delimiter=delimiter), [])
        else:
            cells = text.split(delimiter)
        if not all(i < len(cells) and _same_cell(cells[i], v) for i, v in wanted):
            lines[n] = b""
    return b"\n".join(lines)


def _same_cell(cell: str, value: str) -> bool:
    """Whether a cell holds ``value`` (blanks around ignored; ``1`` and ``1.0`` alike)."""
    cell = cell.strip()
    if cell == value:
        return True
    try:
        return float(cell) == float(value)
    except ValueError:
        return False


def read_columns(
    opts: dict, base: Path, label: str, numeric: dict, text: dict | None = None
) -> tuple[dict, int]:
    """``{key: values}`` of the columns of the file ``opts`` names (``numeric`` as float, NaN
    where empty, times in ISO 8601 as seconds where ``time_unit`` says so; ``text`` as str,
    None where empty), keyed as given, and the lines before the first row."""
    from quadobs.testbed.logs.files import read_limited

    numeric, text = dict(numeric), dict(text or {})
    iso = opts.get("time_unit") == "iso8601" and "time" in numeric
    if iso:
        text["time"] = numeric.pop("time")
    path = base / opts["file"]
    raw = read_limited(path)
    if raw is None:
        raise QuadobsError(f"{label} file {opts['file']!r}: not found beside the map ({base})")
    _check_text(path, raw)
    delimiter = opts.get("delimiter", ",")
    if delimiter == "whitespace":
        raw, delimiter = _whitespace_separated(raw), ","
    header, skip = _header(opts, path, raw, delimiter)
    select = opts.get("select", {})
    chosen = {f"select.{c}": c for c in select}
    _check_columns(path, header, {**numeric, **text, **chosen}, label, opts.get("skip_rows", 0))
    if select:
        wanted = [(header.index(c), str(v)) for c, v in select.items()]
        raw = _selected(raw, skip, wanted, delimiter)
    table = _arrow_table(path, raw, header, skip, delimiter, numeric, text)
    values = _arrays(table, numeric, text)
    if iso:
        values["time"] = _iso_seconds(table.column(text["time"]), path, text["time"], skip, raw)
    return values, skip


def _iso_seconds(column, path: Path, name: str, skip: int, raw: bytes) -> np.ndarray:
    """ISO 8601 times as seconds since 1970 (UTC; times without an offset taken as UTC)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    column = pc.utf8_trim_whitespace(column)
    column = pc.if_else(pc.equal(column, ""), pa.scalar(None, pa.string()), column)  # none
    for kind in (pa.timestamp("ns", tz="UTC"), pa.timestamp("ns")):
        try:
            ns = column.cast(kind).cast(pa.int64())
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
            continue
        return np.array([math.nan if v is None else v * 1e-9 for v in ns.to_pylist()])
    cells = column.to_pylist()
    bad = next((i for i, c in enumerate(cells) if c is not None and not _iso_time(c)), None)
    if bad is not None:
        raise QuadobsError(
            f"{path}, line {_line_of(raw, skip, bad)}, column {name}: {cells[bad]!r} is not an "
            "ISO 8601 time"
        )
    raise QuadobsError(
        f"{path}, column {name}: ISO 8601 times of two kinds, some with an offset and some "
        "without: give each its offset"
    )


def _iso_time(text: str) -> bool:
    """Whether ``text`` reads as one ISO 8601 time (with or without an offset)."""
    import pyarrow as pa

    for kind in (pa.timestamp("ns", tz="UTC"), pa.timestamp("ns")):
        try:
            pa.array([text]).cast(kind)
            return True
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
            continue
    return False


def _arrow_table(path: Path, raw: bytes, header: list, skip: int, delimiter: str, numeric, text):
    """The file's columns asked for, by pyarrow; a cell that is not a number named by line."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    wanted = sorted(set(numeric.values()) | set(text.values()))
    types = {c: pa.float64() for c in numeric.values()} | {c: pa.string() for c in text.values()}

    def read(column_types):
        return pacsv.read_csv(
            pa.BufferReader(raw),
            read_options=pacsv.ReadOptions(skip_rows=skip, column_names=header),
            parse_options=pacsv.ParseOptions(delimiter=delimiter),
            convert_options=pacsv.ConvertOptions(include_columns=wanted, column_types=column_types),
        )

    try:
        return read(types)
    except pa.ArrowInvalid as exc:
        try:
            as_text = read({c: pa.string() for c in wanted})
        except pa.ArrowInvalid:
            raise QuadobsError(_row_fault(path, raw, header, skip, delimiter, exc)) from None
    for column in sorted(set(numeric.values())):
        for i, cell in enumerate(as_text.column(column).to_pylist()):
            try:
                if cell and "_" in cell:  # Python reads 1_000 as a number; the file's reader not
                    raise ValueError
                float(cell or "nan")
            except ValueError:
                raise QuadobsError(
                    f"{path}, line {_line_of(raw, skip, i)}, column {column}: {cell!r} is not "
                    "a number"
                ) from None
    raise QuadobsError(f"{path}: cannot be read as CSV")  # pragma: no cover - arrow's own fault


def _line_of(raw: bytes, skip: int, row: int) -> int:
    """The line number (from 1) of data row ``row`` (from 0) after ``skip`` lines, blank
    lines not counted as rows (as the reader skips them)."""
    seen = -1
    for n, line in enumerate(raw.decode("utf-8-sig", "replace").splitlines(), start=1):
        if n <= skip or not line.strip():
            continue
        seen += 1
        if seen == row:
            return n
    return skip + row + 1


def _row_fault(path: Path, raw: bytes, header: list, skip: int, delimiter: str, exc) -> str:
    """Where Arrow refused a file's rows: the first line whose cells are not the header's
    number, else Arrow's own words."""
    lines = raw.decode("utf-8-sig", "replace").splitlines()
    for n, line in enumerate(lines[skip:], start=skip + 1):
        if not line.strip():
            continue
        try:
            cells = next(csv.reader([line], delimiter=delimiter), [])
        except csv.Error as fault:
            return f"{path}, line {n}: not a CSV row ({fault})"
        if len(cells) != len(header):
            hint = ""
            if header and header[0].lstrip().startswith(("#", "%", "//")):
                hint = "; a comment line for a header? give names = [...] and skip_rows"
            elif n == skip + 1 and len(cells) > len(header):
                hint = "; a column name with a space in it? give names = [...] and skip_rows = 1"
            return (
                f"{path}, line {n}: {len(cells)} cells, where the header names {len(header)} "
                f"({line[:60]!r}){hint}"
            )
    return f"{path}: cannot be read as CSV ({str(exc).splitlines()[0]})"


def _arrays(table, numeric: dict, text: dict) -> dict:
    from quadobs.testbed.logs.files import _fill_float_column

    out: dict = {}
    for key, column in numeric.items():
        values = np.empty(table.num_rows)
        _fill_float_column(values, table.column(column).cast("float64").chunks)
        out[key] = values
    for key, column in text.items():
        out[key] = table.column(column).to_pylist()
    return out


def _anchor_ids(cells: list, pattern: str, where: str) -> np.ndarray:
    """Anchor ids from a text column: an integer, or the number in a name (as for bags); NaN
    for an empty cell. Each distinct cell is read once."""
    from quadobs.testbed.logs.importing import anchor_id

    ids: dict = {None: math.nan, "": math.nan}
    for cell in set(cells) - set(ids):
        text = cell.strip()
        if not text:
            ids[cell] = math.nan
            continue
        try:
            number = float(text)
        except ValueError:
            whole = anchor_id(text, pattern, where)
            number = float(whole) if abs(whole) <= 2**53 else math.inf
        shown = repr(text if len(text) <= 40 else text[:37] + "...")
        if math.isnan(number) or (math.isfinite(number) and number != round(number)):
            raise QuadobsError(f"{where}: anchor id {shown} is not an integer")
        if abs(number) > 2**53:  # the format holds ids beside the values, as floats
            raise QuadobsError(
                f"{where}: anchor id {shown} is beyond 2^53, which the log format cannot hold "
                "exactly: number the anchors (in the anchors' table and the measurements alike)"
            )
        ids[cell] = number
    return np.array([ids[c] for c in cells], dtype=float)


#: The span (m) within which the median of a stream's stated std must lie: a radio's or an
#: acoustic beacon's ranges are good to centimetres or decimetres, never to a micrometre or
#: to tens of metres (a std written in metres beside ranges in mm, or the reverse).
STD_SPAN = (1e-3, 10.0)


def _std(opts: dict, values: dict, n: int, where: str) -> np.ndarray:
    """Each measurement's stated std (m): a column, one number, or NaN (not stated); refused
    where their median lies outside :data:`STD_SPAN` (its unit is the stream's ``unit``)."""
    unit = UNITS["unit"][opts.get("unit", "m")]
    std = opts.get("std")
    if isinstance(std, str):
        out = values["std"] * unit
        out[out == 0.0] = math.nan  # 0: none stated (as a covariance of 0 is in ROS)
    else:
        out = np.full(n, math.nan if std is None else float(std) * unit)
    stated = out[np.isfinite(out)]
    if stated.size:
        median = float(np.median(stated))
        if not STD_SPAN[0] <= median <= STD_SPAN[1]:
            raise QuadobsError(
                f"{where} std: a median of {median:.3g} m, where a range's std is "
                f"{STD_SPAN[0]:g} to {STD_SPAN[1]:g} m: the std is read in the stream's unit "
                f"({opts.get('unit', 'm')!r}), as its values are"
            )
    return out


def _ranges(cols: _Columns) -> np.ndarray:
    """``time, id, range, std`` rows."""
    opts = cols.map.streams["ranges"]
    where = f"{cols.map.where}: [ranges]"
    unit = UNITS["unit"][opts.get("unit", "m")]
    std_col = {"std": opts["std"]} if isinstance(opts.get("std"), str) else {}
    if "columns" in opts:
        wide = {f"r{k}": c for k, c in opts["columns"].items()}
        v, _ = cols.read("ranges", {"time": opts["time"], **wide, **std_col})
        t = cols.time("ranges", v["time"])
        std = _std(opts, v, t.size, where)
        parts = []
        for key in opts["columns"]:
            r = v[f"r{key}"] * unit
            given = ~np.isnan(r)  # an empty cell: that anchor not ranged in the row
            parts.append(np.column_stack([t, np.full(t.size, int(key)), r, std])[given])
        rows = np.concatenate(parts)
        return cols.without_repeats("ranges", cols.keep("ranges", rows[:, :3], rows[:, 3]))
    if "files" in opts:
        return _ranges_per_file(cols, std_col)
    v, _ = cols.read(
        "ranges", {"time": opts["time"], "value": opts["value"], **std_col}, {"id": opts["anchor"]}
    )
    ids = _anchor_ids(v["id"], opts.get("anchor_pattern", ""), where)
    t = cols.time("ranges", v["time"])
    rows = np.column_stack([t, ids, v["value"] * unit])
    return cols.without_repeats("ranges", cols.keep("ranges", rows, _std(opts, v, t.size, where)))


def _ranges_per_file(cols: _Columns, std_col: dict) -> np.ndarray:
    """``time, id, range, std`` rows of one file per anchor (``files = {ID = "file"}``)."""
    opts = cols.map.streams["ranges"]
    where = f"{cols.map.where}: [ranges]"
    unit = UNITS["unit"][opts.get("unit", "m")]
    parts = []
    for key, name in opts["files"].items():
        one = {**opts, "file": name}
        v, _ = read_columns(
            one,
            cols.map.base,
            "[ranges]",
            {"time": opts["time"], "value": opts["value"], **std_col},
        )
        t = cols.time("ranges", v["time"])
        std = _std(opts, v, t.size, where)
        parts.append(np.column_stack([t, np.full(t.size, int(key)), v["value"] * unit, std]))
    rows = np.concatenate(parts)
    return cols.without_repeats("ranges", cols.keep("ranges", rows[:, :3], rows[:, 3]))


def _tdoa(cols: _Columns) -> np.ndarray:
    """``time, i, j, difference, std`` rows."""
    opts = cols.map.streams["tdoa"]
    where = f"{cols.map.where}: [tdoa]"
    unit = UNITS["unit"][opts.get("unit", "m")]
    std_col = {"std": opts["std"]} if isinstance(opts.get("std"), str) else {}
    v, _ = cols.read(
        "tdoa",
        {"time": opts["time"], "value": opts["value"], **std_col},
        {"i": opts["anchor_i"], "j": opts["anchor_j"]},
    )
    pattern = opts.get("anchor_pattern", "")
    rows = np.column_stack(
        [
            cols.time("tdoa", v["time"]),
            _anchor_ids(v["i"], pattern, where),
            _anchor_ids(v["j"], pattern, where),
            v["value"] * unit * opts.get("sign", 1),
        ]
    )
    return cols.without_repeats(
        "tdoa", cols.keep("tdoa", rows, _std(opts, v, rows.shape[0], where))
    )


def _rotation_columns(opts: dict) -> dict:
    """The columns of a stream's rotation, keyed ``q{w,x,y,z}``, ``e{roll,...}`` or ``heading``."""
    if "quaternion" in opts:
        return {f"q{k}": c for k, c in opts["quaternion"].items()}
    if "euler" in opts:
        return {f"e{k}": c for k, c in opts["euler"].items()}
    if "heading" in opts:
        return {"heading": opts["heading"]}
    return {}


def _quaternions(opts: dict, v: dict, n: int) -> np.ndarray:
    """``(n, 4)`` unit quaternions ``w, x, y, z`` from the stream's rotation columns (NaN:
    none, or a quaternion of zero norm); Euler angles as ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    angle = UNITS["angle_unit"][opts.get("angle_unit", "rad")]
    if "quaternion" in opts:
        q = np.column_stack([v[f"q{k}"] for k in "wxyz"])
    elif "euler" in opts or "heading" in opts:
        roll, pitch, yaw = (
            (v["eroll"] * angle, v["epitch"] * angle, v["eyaw"] * angle)
            if "euler" in opts
            else (np.zeros(n), np.zeros(n), v["heading"] * angle)
        )
        cr, sr = np.cos(roll / 2), np.sin(roll / 2)
        cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
        cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
        q = np.column_stack(
            [
                cr * cp * cy + sr * sp * sy,
                sr * cp * cy - cr * sp * sy,
                cr * sp * cy + sr * cp * sy,
                cr * cp * sy - sr * sp * cy,
            ]
        )
    else:
        return np.full((n, 4), math.nan)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, q / norm, math.nan)


def _imu(cols: _Columns) -> np.ndarray:
    """``time, ax, ay, az, wx, wy, wz`` rows, body frame, SI."""
    opts = cols.map.streams["imu"]
    accel_cols, accel_signs = _signed(opts["accel"])
    gyro_cols, gyro_signs = _signed(opts["gyro"])
    names = {"time": opts["time"]}
    names |= {f"a{i}": c for i, c in enumerate(accel_cols)}
    names |= {f"w{i}": c for i, c in enumerate(gyro_cols)}
    v, _ = cols.read("imu", names)
    accel = UNITS["accel_unit"][opts.get("accel_unit", "m/s^2")] * accel_signs
    gyro = UNITS["gyro_unit"][opts.get("gyro_unit", "rad/s")] * gyro_signs
    rows = np.column_stack(
        [cols.time("imu", v["time"])]
        + [v[f"a{i}"] * accel[i] for i in range(3)]
        + [v[f"w{i}"] * gyro[i] for i in range(3)]
    )
    return cols.unique_times("imu", cols.keep("imu", rows))


def _signed(columns: list) -> tuple[list, np.ndarray]:
    """Column names, and a sign per axis: ``"-ay"`` reads the column ``ay`` negated (an axis
    of the sensor's frame that points the other way)."""
    names = [c[1:] if c.startswith("-") else c for c in columns]
    return names, np.array([-1.0 if c.startswith("-") else 1.0 for c in columns])


def _attitude(cols: _Columns) -> np.ndarray:
    """``time, qw, qx, qy, qz`` rows."""
    opts = cols.map.streams["attitude"]
    v, _ = cols.read("attitude", {"time": opts["time"], **_rotation_columns(opts)})
    t = cols.time("attitude", v["time"])
    blank = np.isnan(np.column_stack([v[k] for k in _rotation_columns(opts)])).all(axis=1)
    rows = np.column_stack([t, _quaternions(opts, v, t.size)])
    rows = cols.keep("attitude", rows, blank=blank)
    return cols.unique_times("attitude", rows)


def _odometry(cols: _Columns) -> np.ndarray:
    """``time, speed, yaw_rate`` rows, from either layout (module docstring)."""
    from quadobs.testbed.logs.convert import odometry_from_poses, odometry_from_wheels

    opts = cols.map.streams["odometry"]
    keys = next(w for w in _NEEDS["odometry"] if w[0] in opts)
    names = {k: opts[k] for k in keys if k != "track"}
    v, _ = cols.read("odometry", {"time": opts["time"], **names})
    rows = cols.keep(
        "odometry", np.column_stack([cols.time("odometry", v["time"])] + [v[k] for k in names])
    )
    rows = cols.unique_times("odometry", rows)
    if rows.shape[0] < 2:
        raise QuadobsError(
            f"{cols.map.where}: [odometry] fewer than two rows left "
            f"({cols.left_out.get('odometry', 0)} left out: a cell empty or not finite)"
        )
    t = rows[:, 0]
    if "speed" in opts:
        speed = UNITS["speed_unit"][opts.get("speed_unit", "m/s")]
        rate = UNITS["rate_unit"][opts.get("rate_unit", "rad/s")]
        return np.column_stack([t, rows[:, 1] * speed, rows[:, 2] * rate])
    if "left" in opts:
        if "wheel_radius" in opts:  # the wheels' rates, times their radius
            speed = UNITS["rate_unit"][opts.get("rate_unit", "rad/s")] * opts["wheel_radius"]
        else:
            speed = UNITS["speed_unit"][opts.get("speed_unit", "m/s")]
        left = rows[:, 1] * speed * opts.get("left_sign", 1)
        right = rows[:, 2] * speed * opts.get("right_sign", 1)
        return odometry_from_wheels(t, left, right, opts["track"])
    unit = UNITS["unit"][opts.get("unit", "m")]
    angle = UNITS["angle_unit"][opts.get("angle_unit", "rad")]
    return odometry_from_poses(t, rows[:, 1] * unit, rows[:, 2] * unit, rows[:, 3] * angle)


def _truth(cols: _Columns) -> tuple[np.ndarray, np.ndarray | None]:
    """``time, x, y, z, qw, qx, qy, qz`` rows (z 0 for a planar position; the quaternion NaN
    where the truth holds no rotation), and the velocity's rows where the map names it."""
    opts = cols.map.streams["truth"]
    position_cols, position_signs = _signed(opts["position"])
    velocity_cols, velocity_signs = _signed(opts.get("velocity", []))
    named = {f"p{i}": c for i, c in enumerate(position_cols)}
    named |= {f"v{i}": c for i, c in enumerate(velocity_cols)}
    v, _ = cols.read("truth", {"time": opts["time"], **named, **_rotation_columns(opts)})
    t = cols.time("truth", v["time"])
    unit = UNITS["unit"][opts.get("unit", "m")]
    p = [v[f"p{i}"] * unit * position_signs[i] for i in range(len(position_cols))]
    p += [np.zeros(t.size)] * (3 - len(position_cols))
    rotated = bool(_rotation_columns(opts))
    q = _quaternions(opts, v, t.size) if rotated else np.full((t.size, 4), math.nan)
    speed = [v[f"v{i}"] * unit * velocity_signs[i] for i in range(len(velocity_cols))]
    rows = cols.keep("truth", np.column_stack([t, *p, *(q.T if rotated else []), *speed]))
    rows = cols.unique_times("truth", rows)
    k = 4 + (4 if rotated else 0)
    body = (
        rows[:, :k]
        if rotated
        else np.column_stack([rows[:, :4], np.full((rows.shape[0], 4), math.nan)])
    )
    return body, (rows[:, k:] if velocity_cols else None)


def _inputs(cols: _Columns, kind: str) -> np.ndarray:
    """The inputs' rows (``(0, 1)`` for none), at least two of them where a stream is mapped."""
    if kind == "none":
        return np.empty((0, 1))
    try:
        rows = _imu(cols) if kind == "imu" else _odometry(cols)
    except QuadobsError as exc:
        if str(exc).startswith("odometry_from"):  # the converters name themselves only
            raise QuadobsError(f"{cols.map.where}: [odometry] {exc}") from None
        raise
    if rows.shape[0] < 2:
        raise QuadobsError(
            f"{cols.map.where}: [{kind}] fewer than two rows left "
            f"({cols.left_out.get(kind, 0)} left out: a cell empty or not finite)"
        )
    return rows


def import_csv(csv_map: CsvMap, notes: list | None = None) -> RangeLog:
    """Read the files a column map names into a :class:`RangeLog` (module docstring).

    Parameters
    ----------
    csv_map : CsvMap
    notes : list, optional
        Where given, lines are appended saying how many rows each stream left out (a cell
        empty or not finite), and which anchors no measurement names.

    Raises
    ------
    QuadobsError
        A file or column missing, a cell that is not a number (named by file, line and
        column), streams on different clocks, an anchor id not among the anchors, nothing
        left to replay, or a value the format refuses: one line.
    """
    from quadobs.testbed.logs.importing import assemble_log, check_anchor_ids, check_clocks

    dims = {len(p) for p in csv_map.anchors.values()}
    if len(dims) != 1:
        raise QuadobsError(f"{csv_map.where}: anchors: all with z or all without")
    streams, cols = csv_map.streams, _Columns(csv_map)
    ranges = _ranges(cols) if "ranges" in streams else np.empty((0, 4))
    tdoa = _tdoa(cols) if "tdoa" in streams else np.empty((0, 5))
    if ranges.shape[0] + tdoa.shape[0] == 0:
        raise QuadobsError(f"{csv_map.where}: no range or TDOA left to replay ({_left(cols)})")
    kind = next((k for k in ("imu", "odometry") if k in streams), "none")
    inputs = _inputs(cols, kind)
    attitude = _attitude(cols) if "attitude" in streams else None
    if "truth" in streams and dims == {3} and kind != "odometry":
        if len(streams["truth"]["position"]) == 2:
            raise QuadobsError(
                f"{csv_map.where}: [truth] position: two columns, where the anchors are in "
                "space: give its z (or leave the truth out)"
            )
    truth, velocity = _truth(cols) if "truth" in streams else (None, None)
    for stream, table in (("attitude", attitude), ("truth", truth)):
        if table is not None and table.shape[0] == 0:
            raise QuadobsError(
                f"{csv_map.where}: [{stream}] {streams[stream]['file']}: no row read "
                f"({cols.left_out.get(stream, 0)} left out: a cell empty or not finite)"
            )
    label = Path(csv_map.where)
    tables = {"ranges": ranges, "tdoa": tdoa, kind: inputs, "truth": truth, "attitude": attitude}
    check_clocks(label, tables, "time_offset = SECONDS in [{}] moves its times")
    check_anchor_ids(label, csv_map.anchors, ranges, tdoa, notes)
    if notes is not None:
        notes += cols.notes()
    meta = dict(csv_map.meta)
    name = meta.pop("name", "") or label.stem
    try:
        tables |= {"inputs": inputs, "truth_velocity": velocity}
        return assemble_log(name, csv_map.anchors, tables, kind, **meta)
    except QuadobsError as exc:  # the format names its own files: say which the map's are
        text = str(exc).replace(f"{name}: meta.csv, key", f"{csv_map.where}: key")
        if text == str(exc):
            text = f"{csv_map.where}: as imported: {csv_map.in_its_names(text)}"
        raise QuadobsError(text) from None


def _left(cols: _Columns) -> str:
    counts = [f"[{s}] {n} left out" for s, n in sorted(cols.left_out.items())]
    return "; ".join(counts) or "none read"
