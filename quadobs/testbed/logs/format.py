"""The open log format: a folder of CSV files holding a range-only log, planar or in space.

===============  =================================  =====================================
file             columns (header row)               meaning
===============  =================================  =====================================
``beacons.csv``  ``id,x,y[,z]``                     surveyed beacon positions (m); with
                                                    ``z`` the log is in space (3-D)
``ranges.csv``   ``time,beacon,range``              one range (m) to beacon ``beacon`` at
                                                    ``time``
``inputs.csv``   ``time,speed,yaw_rate``            wheel odometry (planar logs): forward
                                                    speed (m/s), yaw rate (rad/s)
                 or ``time,ax,ay[,az]``             accelerometer: the acceleration (m/s^2)
                                                    in the navigation frame, gravity
                                                    removed (``az`` in 3-D logs)
``truth.csv``    ``time,x,y[,z][,heading]``         optional ground truth: position (m),
                 ``[,vx,vy[,vz]]``                  heading (rad), velocity (m/s)
``meta.csv``     ``key,value``                      ``name``; odometry logs: ``heading0``,
                                                    the heading (rad) at the first input
===============  =================================  =====================================

Each input row is held from its time to the next row's. An accelerometer log assumes a
vehicle whose attitude the accelerometer's axes already follow (a strapdown unit with its
rotation and gravity removed, as the simulated point mass reads it): the replay's models
take the acceleration as the known input of a double integrator.

Times are seconds on any common clock, each file sorted by time (ties allowed); the
ranges arrive at their own irregular times. Every value must be finite; a beacon id in
``ranges.csv`` must be listed in ``beacons.csv``. A malformed file raises
:class:`~quadobs.errors.QuadobsError` with one line naming the file, the row (1-based,
the header being row 1) and the column.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["INPUT_KINDS", "LOG_FILES", "RangeLog", "read_log", "write_log"]

#: The input columns (after ``time``) of each kind of input.
INPUT_KINDS = {"odometry": ("speed", "yaw_rate"), "imu": ("ax", "ay", "az")}


def _truth_headers() -> tuple[tuple[str, ...], ...]:
    out = []
    for dim, heading, velocity in itertools.product((2, 3), (False, True), (False, True)):
        out.append(
            ("time", *"xyz"[:dim])
            + (("heading",) if heading else ())
            + (("vx", "vy", "vz")[:dim] if velocity else ())
        )
    return tuple(out)


#: The files of a log: their accepted headers, and how the headers are described in errors.
LOG_FILES = {
    "beacons.csv": ((("id", "x", "y"), ("id", "x", "y", "z")), "id,x,y[,z]"),
    "ranges.csv": ((("time", "beacon", "range"),), "time,beacon,range"),
    "inputs.csv": (
        (("time", "speed", "yaw_rate"), ("time", "ax", "ay"), ("time", "ax", "ay", "az")),
        "time,speed,yaw_rate (odometry) or time,ax,ay[,az] (accelerometer)",
    ),
    "truth.csv": (_truth_headers(), "time,x,y[,z][,heading][,vx,vy[,vz]]"),
}
_OPTIONAL_FILES = ("truth.csv",)


@dataclass(frozen=True, eq=False)
class RangeLog:
    """A range-only log (see the module docstring for the files).

    Attributes
    ----------
    name : str
    beacon_ids : ndarray (B,) of int
    beacons : ndarray (B, dim)
        Positions, in the order of ``beacon_ids`` (the order of the outputs); ``dim`` 2 or 3.
    ranges : ndarray (M, 3)
        ``time, beacon id, range`` rows, sorted by time.
    inputs : ndarray (K, 1 + p)
        ``time, speed, yaw_rate`` (odometry) or ``time, ax, ay[, az]`` (accelerometer) rows,
        sorted by time; each held until the next.
    heading0 : float
        Odometry: the heading at ``inputs[0, 0]`` (rad); NaN for an accelerometer log.
    truth : ndarray (T, c) or None
        Rows of the columns :attr:`truth_columns`.
    source : str
        The folder it was read from (``""``: none).
    input_kind : {"odometry", "imu"}
    truth_columns : tuple of str
        Names of the truth's columns (default for a planar log: ``time, x, y[, heading]``).
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

    def __post_init__(self) -> None:
        known = set(int(i) for i in self.beacon_ids)
        if len(known) != len(self.beacon_ids):
            raise QuadobsError(f"{self.name}: beacons.csv, column id: ids must be distinct")
        for i, b in enumerate(self.ranges[:, 1]):
            if int(b) not in known:
                raise QuadobsError(
                    f"{self.name}: ranges.csv, row {i + 2}, column beacon: unknown beacon id {int(b)}"
                )
        if self.inputs.shape[0] < 2:
            raise QuadobsError(f"{self.name}: inputs.csv: at least two rows are needed")
        if self.truth is not None and not self.truth_columns:
            object.__setattr__(
                self, "truth_columns", ("time", "x", "y", "heading")[: self.truth.shape[1]]
            )
        self._check_dimensions()

    def _check_dimensions(self) -> None:
        """Inputs and truth in the beacons' dimension; odometry in the plane only."""
        dim = self.dimension
        if self.input_kind not in INPUT_KINDS:
            raise QuadobsError(
                f"{self.name}: input kind: expected one of {', '.join(INPUT_KINDS)}, got {self.input_kind!r}"
            )
        if self.input_kind == "odometry" and (dim != 2 or self.inputs.shape[1] != 3):
            raise QuadobsError(
                f"{self.name}: inputs.csv, row 1: odometry (speed, yaw_rate) needs a planar log (beacons.csv without z)"
            )
        if self.input_kind == "imu" and self.inputs.shape[1] != 1 + dim:
            raise QuadobsError(
                f"{self.name}: inputs.csv, row 1: {self.inputs.shape[1] - 1} acceleration columns for "
                f"{dim}-D beacons (beacons.csv {'with' if dim == 3 else 'without'} z)"
            )
        if self.truth is not None and ("z" in self.truth_columns) != (dim == 3):
            raise QuadobsError(
                f"{self.name}: truth.csv, row 1: column z {'missing' if dim == 3 else 'given'} for {dim}-D beacons"
            )

    @property
    def dimension(self) -> int:
        """2 (planar) or 3."""
        return int(self.beacons.shape[1])

    @property
    def start(self) -> float:
        """First input time (s): the replay's time origin."""
        return float(self.inputs[0, 0])

    @property
    def end(self) -> float:
        """Last input time (s)."""
        return float(self.inputs[-1, 0])

    def truth_part(self, what: str) -> np.ndarray | None:
        """The truth's ``"position"`` or ``"velocity"`` columns ``(T, dim)``, or None (no truth, or no such columns)."""
        names = {"position": ("x", "y", "z"), "velocity": ("vx", "vy", "vz")}[what][
            : self.dimension
        ]
        if self.truth is None or not set(names) <= set(self.truth_columns):
            return None
        return self.truth[:, [self.truth_columns.index(c) for c in names]]

    def beacon_index(self, ids: np.ndarray) -> np.ndarray:
        """Output indices (positions in :attr:`beacon_ids`) of beacon ids."""
        lookup = {int(b): h for h, b in enumerate(self.beacon_ids)}
        return np.array([lookup[int(b)] for b in ids], dtype=np.int64)

    def excerpt(self, t0: float, t1: float) -> RangeLog:
        """The part of the log with ``t0 <= time - start < t1`` (s from :attr:`start`); the odometry's heading carried over.

        The truth keeps one sample either side of the span (so that it covers the excerpt).
        """
        a, b = self.start + t0, self.start + t1
        inp = self.inputs
        k = max(int(np.searchsorted(inp[:, 0], a, side="right") - 1), 0)
        heading = self.heading0
        if self.input_kind == "odometry":
            heading = self.heading0 + float(np.sum(np.diff(inp[: k + 1, 0]) * inp[:k, 2]))
        keep = lambda arr: arr[(arr[:, 0] >= a) & (arr[:, 0] < b)]  # noqa: E731
        new_inp = inp[k:][inp[k:, 0] < b].copy()
        new_inp[0, 0] = max(new_inp[0, 0], a)
        truth = None
        if (
            self.truth is not None
        ):  # with the samples either side, so that the truth covers the excerpt
            i0 = max(int(np.searchsorted(self.truth[:, 0], a, side="right")) - 1, 0)
            i1 = int(np.searchsorted(self.truth[:, 0], b, side="left")) + 1
            truth = self.truth[i0:i1].copy()
        return RangeLog(
            f"{self.name}[{t0:g}:{t1:g}]",
            self.beacon_ids,
            self.beacons,
            keep(self.ranges),
            new_inp,
            heading,
            truth,
            self.source,
            self.input_kind,
            self.truth_columns,
        )


def _read_rows(path: Path, headers: tuple, described: str) -> tuple[list[str], list[list[str]]]:
    """The header (one of ``headers``) and the data rows of a CSV file."""
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise QuadobsError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise QuadobsError(f"{path}: not a CSV text file ({exc})") from None
    if not rows:
        raise QuadobsError(f"{path}, row 1: empty file; expected the header {described}")
    header = [h.strip() for h in rows[0]]
    if tuple(header) not in headers:
        raise QuadobsError(f"{path}, row 1: header {','.join(header)!r}; expected {described}")
    return header, rows[1:]


def _read_csv(folder: Path, fname: str) -> tuple[list[str], np.ndarray]:
    """The header and the values of one file, each checked: one-line errors naming file, row and column."""
    path = folder / fname
    header, rows = _read_rows(path, *LOG_FILES[fname])
    values = np.empty((len(rows), len(header)))
    for r, row in enumerate(rows, start=2):
        if len(row) != len(header):
            raise QuadobsError(
                f"{path}, row {r}: {len(row)} columns, expected {len(header)} ({','.join(header)})"
            )
        for c, cell in enumerate(row):
            try:
                v = float(cell)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise QuadobsError(
                    f"{path}, row {r}, column {header[c]}: {cell.strip()!r} is not a finite number"
                )
            values[r - 2, c] = v
    if values.shape[0] == 0:
        raise QuadobsError(f"{path}, row 2: no data rows")
    if header[0] == "time":
        bad = np.flatnonzero(np.diff(values[:, 0]) < 0)
        if bad.size:
            raise QuadobsError(
                f"{path}, row {int(bad[0]) + 3}, column time: earlier than the row before (rows must be sorted by time)"
            )
    return header, values


def _read_meta(folder: Path) -> dict[str, str]:
    path = folder / "meta.csv"
    if not path.exists():
        raise QuadobsError(f"{path}: missing (key,value rows: name; heading0 for an odometry log)")
    try:  # not UTF-8, a folder, unreadable: one line naming the file
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise QuadobsError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise QuadobsError(f"{path}: not a CSV text file ({exc})") from None
    if not rows or [h.strip() for h in rows[0]] != ["key", "value"]:
        raise QuadobsError(f"{path}, row 1: expected the header key,value")
    meta = {}
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != 2:
            raise QuadobsError(f"{path}, row {r}: {len(row)} columns, expected 2 (key,value)")
        meta[row[0].strip()] = row[1].strip()
    return meta


def _heading0(folder: Path, meta: dict, kind: str) -> float:
    """``heading0`` of an odometry log (required); NaN for an accelerometer log."""
    if kind != "odometry":
        return math.nan
    try:
        heading0 = float(meta.get("heading0", "nan"))
    except ValueError:
        heading0 = math.nan
    if not math.isfinite(heading0):
        raise QuadobsError(
            f"{folder / 'meta.csv'}, key heading0: missing or not a finite number (rad)"
        )
    return heading0


def read_log(folder: str | Path) -> RangeLog:
    """Read a log folder (see the module docstring).

    Raises
    ------
    QuadobsError
        A missing folder or file, or a malformed value: one line naming the file, the row
        and the column.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise QuadobsError(
            f"{folder}: not a log folder (expected beacons.csv, ranges.csv, inputs.csv, meta.csv)"
        )
    tables = {}
    for fname in LOG_FILES:
        if fname in _OPTIONAL_FILES and not (folder / fname).exists():
            continue
        tables[fname] = _read_csv(folder, fname)
    ids = tables["beacons.csv"][1][:, 0]
    for r, i in enumerate(ids):
        if i != int(i) or not -(2**63) <= i < 2**63:  # 1e19 would wrap in int64
            raise QuadobsError(
                f"{folder / 'beacons.csv'}, row {r + 2}, column id: {float(i)!r} is not an integer below 2^63 in size"
            )
    meta = _read_meta(folder)
    kind = "odometry" if tables["inputs.csv"][0][1] == "speed" else "imu"
    truth_header, truth = tables.get("truth.csv", ((), None))
    name = meta.get("name", folder.name)
    if any(not ch.isprintable() for ch in name):  # an escape sequence would reach the terminal
        raise QuadobsError(f"{folder / 'meta.csv'}, key name: {name!r} holds control characters")
    try:
        return RangeLog(
            name,
            ids.astype(np.int64),
            tables["beacons.csv"][1][:, 1:],
            tables["ranges.csv"][1],
            tables["inputs.csv"][1],
            _heading0(folder, meta, kind),
            truth,
            str(folder),
            kind,
            tuple(truth_header),
        )
    except QuadobsError as exc:  # name the folder's file, not the log's name
        raise QuadobsError(str(exc).replace(f"{name}: ", f"{folder}/", 1)) from None


def _write_csv(path: Path, header: list[str], values, ints: tuple[int, ...] = ()) -> None:
    """``values`` under ``header``, written to a staging file renamed onto ``path`` once complete."""
    from quadobs.testbed.outputs import write_text_staged

    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(header)
    for row in values:
        w.writerow(
            [
                v if isinstance(v, str) else str(int(v)) if c in ints else repr(float(v))
                for c, v in enumerate(row)
            ]
        )
    write_text_staged(path, text.getvalue(), "log file")


def write_log(log: RangeLog, folder: str | Path) -> Path:
    """Write ``log`` as a log folder (created if needed), each file complete or not at all; :func:`read_log` gives it back exactly."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise QuadobsError(f"{folder}: cannot be created ({exc.strerror or exc})") from None
    dim = log.dimension
    _write_csv(
        folder / "beacons.csv",
        ["id", *"xyz"[:dim]],
        np.column_stack([log.beacon_ids, log.beacons]),
        ints=(0,),
    )
    _write_csv(folder / "ranges.csv", ["time", "beacon", "range"], log.ranges, ints=(1,))
    _write_csv(
        folder / "inputs.csv",
        ["time", *INPUT_KINDS[log.input_kind][: log.inputs.shape[1] - 1]],
        log.inputs,
    )
    if log.truth is not None:
        _write_csv(folder / "truth.csv", list(log.truth_columns), log.truth)
    meta = [["name", log.name]] + (
        [["heading0", repr(float(log.heading0))]] if log.input_kind == "odometry" else []
    )
    _write_csv(folder / "meta.csv", ["key", "value"], meta)
    return folder
