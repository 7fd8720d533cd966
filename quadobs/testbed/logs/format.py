"""The open log format: a folder of CSV files holding a planar range-only log.

===============  ==========================  ============================================
file             columns (header row)        meaning
===============  ==========================  ============================================
``beacons.csv``  ``id,x,y``                  surveyed beacon positions (m), one per beacon
``ranges.csv``   ``time,beacon,range``       one range (m) to beacon ``beacon`` at ``time``
``inputs.csv``   ``time,speed,yaw_rate``     wheel odometry: forward speed (m/s) and yaw
                                             rate (rad/s) held from ``time`` to the next row
``truth.csv``    ``time,x,y[,heading]``      optional ground truth (m, rad)
``meta.csv``     ``key,value``               ``name``; ``heading0``, the heading (rad) at
                                             the first input time (the odometry's origin)
===============  ==========================  ============================================

Times are seconds on any common clock, each file sorted by time (ties allowed); the
ranges arrive at their own irregular times. Every value must be finite; a beacon id in
``ranges.csv`` must be listed in ``beacons.csv``. A malformed file raises
:class:`~quadobs.errors.QuadobsError` with one line naming the file, the row (1-based,
the header being row 1) and the column.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["LOG_FILES", "RangeLog", "read_log", "write_log"]

#: The files of a log and their required (then optional) columns.
LOG_FILES = {
    "beacons.csv": (("id", "x", "y"), ()),
    "ranges.csv": (("time", "beacon", "range"), ()),
    "inputs.csv": (("time", "speed", "yaw_rate"), ()),
    "truth.csv": (("time", "x", "y"), ("heading",)),
}
_OPTIONAL_FILES = ("truth.csv",)


@dataclass(frozen=True, eq=False)
class RangeLog:
    """A planar range-only log (see the module docstring for the files).

    Attributes
    ----------
    name : str
    beacon_ids : ndarray (B,) of int
    beacons : ndarray (B, 2)
        Positions, in the order of ``beacon_ids`` (the order of the outputs).
    ranges : ndarray (M, 3)
        ``time, beacon id, range`` rows, sorted by time.
    inputs : ndarray (K, 3)
        ``time, speed, yaw_rate`` rows, sorted by time; each held until the next.
    heading0 : float
        Heading at ``inputs[0, 0]`` (rad).
    truth : ndarray (T, 3 or 4) or None
        ``time, x, y[, heading]`` rows.
    source : str
        The folder it was read from (``""``: none).
    """

    name: str
    beacon_ids: np.ndarray
    beacons: np.ndarray
    ranges: np.ndarray
    inputs: np.ndarray
    heading0: float
    truth: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        known = set(int(i) for i in self.beacon_ids)
        if len(known) != len(self.beacon_ids):
            raise QuadobsError(f"{self.name}: beacons.csv, column id: ids must be distinct")
        for i, b in enumerate(self.ranges[:, 1]):
            if int(b) not in known:
                raise QuadobsError(f"{self.name}: ranges.csv, row {i + 2}, column beacon: unknown beacon id {int(b)}")
        if self.inputs.shape[0] < 2:
            raise QuadobsError(f"{self.name}: inputs.csv: at least two rows are needed")

    @property
    def start(self) -> float:
        """First input time (s): the replay's time origin."""
        return float(self.inputs[0, 0])

    @property
    def end(self) -> float:
        """Last input time (s)."""
        return float(self.inputs[-1, 0])

    def beacon_index(self, ids: np.ndarray) -> np.ndarray:
        """Output indices (positions in :attr:`beacon_ids`) of beacon ids."""
        lookup = {int(b): h for h, b in enumerate(self.beacon_ids)}
        return np.array([lookup[int(b)] for b in ids], dtype=np.int64)

    def excerpt(self, t0: float, t1: float) -> "RangeLog":
        """The part of the log with ``t0 <= time - start < t1`` (s from :attr:`start`); the heading carried over.

        The truth keeps one sample either side of the span (so that it covers the excerpt).
        """
        a, b = self.start + t0, self.start + t1
        inp = self.inputs
        k = np.searchsorted(inp[:, 0], a, side="right") - 1
        k = max(int(k), 0)
        heading = self.heading0 + float(np.sum(np.diff(inp[: k + 1, 0]) * inp[:k, 2]))
        keep = lambda arr: arr[(arr[:, 0] >= a) & (arr[:, 0] < b)]  # noqa: E731
        new_inp = inp[k:][inp[k:, 0] < b].copy()
        new_inp[0, 0] = max(new_inp[0, 0], a)
        truth = None
        if self.truth is not None:  # with the samples either side, so that the truth covers the excerpt
            i0 = max(int(np.searchsorted(self.truth[:, 0], a, side="right")) - 1, 0)
            i1 = int(np.searchsorted(self.truth[:, 0], b, side="left")) + 1
            truth = self.truth[i0:i1].copy()
        return RangeLog(f"{self.name}[{t0:g}:{t1:g}]", self.beacon_ids, self.beacons, keep(self.ranges), new_inp, heading, truth)


def _read_csv(folder: Path, fname: str) -> tuple[list[str], np.ndarray]:
    """The header and the values of one file, each checked: one-line errors naming file, row and column."""
    required, optional = LOG_FILES[fname]
    path = folder / fname
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise QuadobsError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise QuadobsError(f"{path}: not a CSV text file ({exc})") from None
    if not rows:
        raise QuadobsError(f"{path}, row 1: empty file; expected the header {','.join(required)}")
    header = [h.strip() for h in rows[0]]
    allowed = required + optional
    if tuple(header[: len(required)]) != required or any(h not in allowed for h in header[len(required) :]):
        raise QuadobsError(f"{path}, row 1: header {','.join(header)!r}; expected {','.join(required)}"
                           + (f" then optionally {','.join(optional)}" if optional else ""))
    values = np.empty((len(rows) - 1, len(header)))
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise QuadobsError(f"{path}, row {r}: {len(row)} columns, expected {len(header)} ({','.join(header)})")
        for c, cell in enumerate(row):
            try:
                v = float(cell)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise QuadobsError(f"{path}, row {r}, column {header[c]}: {cell.strip()!r} is not a finite number")
            values[r - 2, c] = v
    if values.shape[0] == 0:
        raise QuadobsError(f"{path}, row 2: no data rows")
    if header[0] == "time":
        bad = np.flatnonzero(np.diff(values[:, 0]) < 0)
        if bad.size:
            raise QuadobsError(f"{path}, row {int(bad[0]) + 3}, column time: earlier than the row before (rows must be sorted by time)")
    return header, values


def _read_meta(folder: Path) -> dict[str, str]:
    path = folder / "meta.csv"
    if not path.exists():
        raise QuadobsError(f"{path}: missing (key,value rows: name, heading0)")
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or [h.strip() for h in rows[0]] != ["key", "value"]:
        raise QuadobsError(f"{path}, row 1: expected the header key,value")
    meta = {}
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != 2:
            raise QuadobsError(f"{path}, row {r}: {len(row)} columns, expected 2 (key,value)")
        meta[row[0].strip()] = row[1].strip()
    return meta


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
        raise QuadobsError(f"{folder}: not a log folder (expected beacons.csv, ranges.csv, inputs.csv, meta.csv)")
    tables = {}
    for fname in LOG_FILES:
        if fname in _OPTIONAL_FILES and not (folder / fname).exists():
            continue
        header, values = _read_csv(folder, fname)
        tables[fname] = values
    ids = tables["beacons.csv"][:, 0]
    for r, i in enumerate(ids):
        if i != int(i):
            raise QuadobsError(f"{folder / 'beacons.csv'}, row {r + 2}, column id: {i!r} is not an integer")
    meta = _read_meta(folder)
    try:
        heading0 = float(meta.get("heading0", "nan"))
    except ValueError:
        heading0 = math.nan
    if not math.isfinite(heading0):
        raise QuadobsError(f"{folder / 'meta.csv'}, key heading0: missing or not a finite number (rad)")
    try:
        return RangeLog(
            meta.get("name", folder.name), ids.astype(np.int64), tables["beacons.csv"][:, 1:3], tables["ranges.csv"],
            tables["inputs.csv"], heading0, tables.get("truth.csv"), str(folder),
        )
    except QuadobsError as exc:  # name the folder's file, not the log's name
        raise QuadobsError(str(exc).replace(f"{meta.get('name', folder.name)}: ", f"{folder}/", 1)) from None


def _write_csv(path: Path, header: list[str], values: np.ndarray, ints: tuple[int, ...] = ()) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in values:
            w.writerow([str(int(v)) if c in ints else repr(float(v)) for c, v in enumerate(row)])


def write_log(log: RangeLog, folder: str | Path) -> Path:
    """Write ``log`` as a log folder (created if needed); :func:`read_log` gives it back exactly."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _write_csv(folder / "beacons.csv", ["id", "x", "y"], np.column_stack([log.beacon_ids, log.beacons]), ints=(0,))
    _write_csv(folder / "ranges.csv", ["time", "beacon", "range"], log.ranges, ints=(1,))
    _write_csv(folder / "inputs.csv", ["time", "speed", "yaw_rate"], log.inputs)
    if log.truth is not None:
        cols = ["time", "x", "y", "heading"][: log.truth.shape[1]]
        _write_csv(folder / "truth.csv", cols, log.truth)
    with (folder / "meta.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerows([["key", "value"], ["name", log.name], ["heading0", repr(float(log.heading0))]])
    return folder
