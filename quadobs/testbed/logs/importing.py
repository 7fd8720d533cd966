"""What the importers of other formats share (:mod:`~quadobs.testbed.logs.rosbag`,
:mod:`~quadobs.testbed.logs.csv_map`): the anchors, anchor ids read from text, one clock for
every stream, the truth's table, and the ``meta.csv`` keys a map may state."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError

__all__ = [
    "STATED_META_KEYS",
    "anchor_id",
    "assemble_log",
    "check_anchor_ids",
    "check_anchor_pattern",
    "check_clocks",
    "read_anchors",
    "read_map",
    "stated_meta",
    "truth_table",
]

#: The ``meta.csv`` keys an import's map may state beside its own (name, description, frame,
#: gravity, heading0 are read by each importer).
STATED_META_KEYS = (
    "tag_height",
    "tag_x",
    "tag_y",
    "tag_z",
    "accel_noise",
    "gyro_noise",
    "accel_bias",
    "gyro_bias",
    "attitude_std",
    "range_errors",
)


def stated_meta(top: dict, keys, where: str) -> dict:
    """The ``meta.csv`` keys of ``keys`` that a map's top level ``top`` states, each checked as
    ``meta.csv`` checks it (:func:`~quadobs.testbed.logs.schema.parse_meta`)."""
    from quadobs.testbed.logs.schema import parse_meta

    meta = {}
    for key, value in top.items():
        if key in keys:
            text = str(value).lower() if isinstance(value, bool) else str(value)
            try:
                meta[key] = parse_meta(where, [["version", "2"], [key, text]])[key]
            except QuadobsError as exc:  # one key at a time: no row to name in a TOML file
                raise QuadobsError(str(exc).replace(", row 3", "")) from None
    return meta


def read_anchors(value, where: str, base: Path | None) -> dict:
    """Anchors from a CSV file name (``beacons.csv``'s columns) or a table ``id = [x, y(, z)]``."""
    from quadobs.testbed.logs.files import read_limited, read_table
    from quadobs.testbed.logs.schema import FILES

    if isinstance(value, str):
        path = Path(value) if base is None or Path(value).is_absolute() else base / value
        raw = read_limited(path)
        if raw is None:
            raise QuadobsError(f"{where}: anchors file {str(path)!r} not found")
        _, values = read_table(path, raw, FILES["beacons.csv"], 2)
        return {int(row[0]): tuple(float(v) for v in row[1:]) for row in values}
    if not isinstance(value, dict) or not value:
        raise QuadobsError(f"{where}: anchors: expected a CSV file name or a table id = [x, y, z]")
    out = {}
    for key, pos in value.items():
        if not re.fullmatch(r"-?\d{1,15}", str(key)):
            raise QuadobsError(f"{where}: anchors.{key}: the id must be an integer")
        if (
            not isinstance(pos, list)
            or len(pos) not in (2, 3)
            or not all(isinstance(v, int | float) and math.isfinite(v) for v in pos)
        ):
            raise QuadobsError(f"{where}: anchors.{key}: expected [x, y] or [x, y, z] in metres")
        out[int(key)] = tuple(float(v) for v in pos)
    return out


def check_anchor_pattern(pattern, where: str) -> None:
    """An ``anchor_pattern``: a regular expression with a group around the id, or empty."""
    if not isinstance(pattern, str):
        raise QuadobsError(f"{where}: anchor_pattern: expected a regular expression")
    if pattern:
        try:
            groups = re.compile(pattern).groups
        except re.error as exc:
            raise QuadobsError(f"{where}: anchor_pattern {pattern!r}: {exc}") from None
        if groups < 1:
            raise QuadobsError(
                f"{where}: anchor_pattern {pattern!r}: needs a group around the id, "
                "e.g. 'anchor_(\\d+)'"
            )


def anchor_id(value, pattern: str, where: str) -> int:
    """An anchor id: an integer field, or the number in a text field (the first group of
    ``pattern`` where given; a text that is one hexadecimal number, ``0x1a``, read as one)."""
    if isinstance(value, str):
        if not pattern and re.fullmatch(r"\s*0[xX][0-9a-fA-F]+\s*", value):
            return int(value.strip(), 16)
        if pattern:
            match = re.search(pattern, value)
            if match is None or not match.group(1):
                raise QuadobsError(f"{where}: anchor_pattern {pattern!r} finds no id in {value!r}")
            text = match.group(1)
            try:
                return int(text, 16) if text.lower().startswith("0x") else int(text)
            except ValueError:
                raise QuadobsError(
                    f"{where}: anchor_pattern {pattern!r} gives {text!r} of {value!r}, not an integer"
                ) from None
        numbers = re.findall(r"\d+", value)
        if not numbers:
            raise QuadobsError(f"{where}: no anchor id in {value!r}")
        if len(numbers) > 1:
            raise QuadobsError(
                f"{where}: {value!r} holds {len(numbers)} numbers: say which is the anchor's "
                "with anchor_pattern, e.g. 'anchor_(\\d+)' (a hexadecimal id: '(0x[0-9a-fA-F]+)')"
            )
        return int(numbers[0])
    number = float(value)
    if not (math.isfinite(number) and number == round(number)):
        raise QuadobsError(f"{where}: anchor id {value!r} is not an integer")
    return int(number)


def check_clocks(
    bag: Path, tables: dict, fix: str = 'time = "receive" in [{}] takes the bag\'s'
) -> None:
    """Every stream's times overlap the ranges' and TDOA's: one clock (module docstring)."""
    measured = [t[:, 0] for k, t in tables.items() if k in ("ranges", "tdoa") and t.shape[0]]
    if not measured:
        return
    lo = min(float(t.min()) for t in measured)
    hi = max(float(t.max()) for t in measured)
    from quadobs.testbed.logs.schema import span_apart

    for stream, table in tables.items():
        apart = None if stream in ("ranges", "tdoa") else span_apart(table, lo, hi)
        if apart is not None:
            a, b = apart
            raise QuadobsError(
                f"{bag}: [{stream}] stamps {a:.10g} to {b:.10g} s, the ranges' {lo:.10g} to "
                f"{hi:.10g} s: not one clock ({fix.format(stream)})"
            )


def check_anchor_ids(bag: Path, anchors: dict, ranges, tdoa, notes) -> None:
    """Every id the measurements name among the anchors; anchors that none names noted."""
    named = set(ranges[:, 1].astype(np.int64)) | set(tdoa[:, 1:3].astype(np.int64).ravel())
    unknown = sorted(named - set(anchors))
    if unknown:
        raise QuadobsError(
            f"{bag}: anchor id {', '.join(map(str, unknown[:5]))} not among the anchors "
            f"({', '.join(map(str, sorted(anchors)))}): check the anchors, or the "
            "field the id is read from (anchor, anchor_pattern)"
        )
    silent = sorted(set(anchors) - named)
    if silent and notes is not None:
        notes.append(
            f"anchors that no range or TDOA names: {', '.join(map(str, silent))} "
            "(check the field the id is read from)"
        )


def truth_table(truth, dim: int, planar_vehicle: bool) -> tuple:
    """The truth's rows and columns: position and attitude (a point: position only); for a
    wheeled vehicle the position in the plane and the heading, the attitude's yaw."""
    columns: tuple = ("time", *"xyz"[:dim], "qw", "qx", "qy", "qz")
    if truth is None:
        return None, columns
    if planar_vehicle:
        w, x, y, z = truth[:, 4:8].T
        heading = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        if np.isnan(heading).any():  # points: no attitude
            return truth[:, :3], ("time", "x", "y")
        return np.column_stack([truth[:, :3], heading]), ("time", "x", "y", "heading")
    if np.isnan(truth[:, 4:]).any():  # points: no attitude
        truth, columns = truth[:, :4], columns[: 1 + dim]
    if dim == 2:
        truth = np.delete(truth, 3, axis=1)  # a planar log: no z
    return truth, columns


def read_map(path: Path, label: str) -> dict:
    """The TOML document of an import's map file (a regular file of at most 1 MiB); errors
    name it as ``label``."""
    from quadobs.testbed.logs.files import read_limited

    raw = read_limited(path)
    if raw is None:
        raise QuadobsError(f"{label}: not found")
    if len(raw) > 1 << 20:
        raise QuadobsError(f"{label}: larger than 1 MiB")
    try:
        return tomllib.loads(raw.decode("utf-8-sig"))  # an editor's byte-order mark skipped
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        raise QuadobsError(f"{label}: not a TOML file ({exc})") from None


def assemble_log(name: str, anchors: dict, tables: dict, kind: str, **fields):
    """The :class:`~quadobs.testbed.logs.format.RangeLog` of an import: ``tables`` holds
    ``ranges`` ``(M, 4)`` and ``tdoa`` ``(N, 5)`` (each with its std last), ``inputs``,
    ``truth`` ``(T, 8)`` or None (:func:`truth_table`), optionally ``truth_velocity``
    ``(T, 2 or 3)``, and ``attitude`` or None; ``kind`` is
    ``"imu"``, ``"odometry"`` or ``"none"``; ``fields`` the log's others (``heading0``, meta)."""
    from quadobs.testbed.logs.format import RangeLog

    heading0 = fields.pop("heading0", math.nan) if kind == "odometry" else math.nan
    fields.pop("heading0", None)
    ids = np.array(sorted(anchors), dtype=np.int64)
    dim = len(anchors[int(ids[0])])
    ranges, tdoa = tables["ranges"], tables["tdoa"]
    truth, truth_columns = truth_table(tables["truth"], dim, kind == "odometry")
    velocity = tables.get("truth_velocity")
    if truth is not None and velocity is not None:  # the navigation frame's, in m/s
        truth = np.column_stack([truth, velocity])
        truth_columns = (*truth_columns, *("vx", "vy", "vz")[: velocity.shape[1]])
    return RangeLog(
        name,
        ids,
        np.array([anchors[i] for i in ids]),
        ranges[:, :3],
        tables["inputs"],
        heading0,
        truth if truth is not None and truth.shape[0] else None,
        input_kind={"imu": "imu_body", "odometry": "odometry", "none": "none"}[kind],
        truth_columns=truth_columns,
        range_std=ranges[:, 3],
        tdoa=tdoa[:, :4],
        tdoa_std=tdoa[:, 4],
        attitude=tables["attitude"],
        **fields,
    )
