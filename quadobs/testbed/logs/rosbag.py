"""ROS 1 and ROS 2 bags imported into the open log format, through ``rosbags``.

``rosbags`` (pure Python, the ``data`` extra) reads both bag formats and the message
definitions stored in them, so custom range and TDOA messages need no ROS installation;
this module only says which topic holds what and which fields to read. A *topic map*
(:class:`TopicMap`, from a small TOML file or the command line) names up to four streams:

==========  ======================================  ===========================================
stream      message                                 written as
==========  ======================================  ===========================================
``imu``     ``sensor_msgs/Imu``                     ``imu.csv``: ``linear_acceleration`` (specific
                                                    force) and ``angular_velocity``, body frame;
                                                    with ``attitude = true`` also ``orientation``
                                                    as ``attitude.csv``
``truth``   ``geometry_msgs/PoseStamped`` or        ``truth.csv``: position and attitude
            ``geometry_msgs/TransformStamped``
``ranges``  any message with an anchor id and a     ``ranges.csv``; fields ``anchor`` (default
            range (e.g. ``sensor_msgs/Range``)      ``header.frame_id``, its last integer),
                                                    ``value`` (default ``range``), ``std``
``tdoa``    any message with two anchor ids and a   ``tdoa.csv``; fields ``anchor_i`` (``idA``),
            difference (m)                          ``anchor_j`` (``idB``), ``value`` (``data``),
                                                    ``std``; ``sign = -1`` where the message
                                                    holds ``|p - a_j| - |p - a_i|``
==========  ======================================  ===========================================

The anchors' positions are not in the bags this targets: they come from a CSV file
(``id,x,y[,z]``, as ``beacons.csv``) or a TOML table. Times are each message's header
stamp (``time = "header"``, the default) or its receive time in the bag
(``time = "receive"``), in seconds; each stream is sorted by time (stably). Quaternions
(ROS order ``x, y, z, w``) are normalised; a zero one is refused.

An example map (``quadobs import-bag BAG --out DIR --map map.toml``)::

    name = "flight-3"
    anchors = "anchors.csv"       # or a table: [anchors] 3 = [0.0, 0.0, 0.2] ...
    [imu]
    topic = "/imu/data"
    [truth]
    topic = "/vicon/pose"
    [ranges]
    topic = "/uwb/range"
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog

__all__ = ["STREAMS", "TopicMap", "import_bag", "load_topic_map", "parse_topic_map"]

#: The streams a topic map may name, and the fields each reads (with their defaults).
STREAMS = {
    "imu": {"attitude": False},
    "truth": {},
    "ranges": {"anchor": "header.frame_id", "value": "range", "std": ""},
    "tdoa": {"anchor_i": "idA", "anchor_j": "idB", "value": "data", "std": "", "sign": 1},
}
_TOP_KEYS = ("name", "description", "frame", "gravity", "time", "anchors")
_TRUTH_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped")


@dataclass(frozen=True)
class TopicMap:
    """Which topic holds which stream, and how its messages are read (module docstring).

    Attributes
    ----------
    streams : dict of str to dict
        Per stream of :data:`STREAMS` present: ``topic`` and its fields.
    anchors : dict of int to tuple of float
        Anchor id to position (m).
    name, description, frame : str
    gravity : float
    time : {"header", "receive"}
    """

    streams: dict = field(default_factory=dict)
    anchors: dict = field(default_factory=dict)
    name: str = ""
    description: str = ""
    frame: str = "enu"
    gravity: float = 9.80665
    time: str = "header"


def _anchors(value, where: str, base: Path | None) -> dict:
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


def parse_topic_map(data: dict, where: str = "topic map", base: Path | None = None) -> TopicMap:
    """A :class:`TopicMap` from its TOML document (module docstring); unknown keys refused."""
    streams, top = {}, {}
    for key, value in data.items():
        if key in STREAMS:
            if not isinstance(value, dict) or not isinstance(value.get("topic"), str):
                raise QuadobsError(f'{where}: [{key}]: expected a table with topic = "/name"')
            unknown = set(value) - {"topic", *STREAMS[key]}
            if unknown:
                raise QuadobsError(
                    f"{where}: [{key}]: unknown key {sorted(unknown)[0]!r} "
                    f"(known: topic, {', '.join(STREAMS[key])})"
                )
            streams[key] = {**STREAMS[key], **value}
        elif key in _TOP_KEYS:
            top[key] = value
        else:
            known = ", ".join((*_TOP_KEYS, *(f"[{s}]" for s in STREAMS)))
            raise QuadobsError(f"{where}: unknown key {key!r} (known: {known})")
    if top.get("time", "header") not in ("header", "receive"):
        raise QuadobsError(f"{where}: time: expected 'header' or 'receive', got {top['time']!r}")
    if "tdoa" in streams and streams["tdoa"]["sign"] not in (1, -1):
        raise QuadobsError(f"{where}: [tdoa] sign: expected 1 or -1")
    if "anchors" in top:
        top["anchors"] = _anchors(top["anchors"], where, base)
    for key in ("name", "description", "frame"):
        if key in top and not isinstance(top[key], str):
            raise QuadobsError(f"{where}: {key}: expected text")
    if "gravity" in top and not (
        isinstance(top["gravity"], int | float)
        and math.isfinite(top["gravity"])
        and top["gravity"] > 0
    ):
        raise QuadobsError(f"{where}: gravity: expected a positive number (m/s^2)")
    return TopicMap(streams=streams, **top)


def load_topic_map(path: str | Path) -> TopicMap:
    """:func:`parse_topic_map` of a TOML file (a regular file of at most 1 MiB)."""
    from quadobs.testbed.logs.files import read_limited

    path = Path(path)
    raw = read_limited(path)
    if raw is None:
        raise QuadobsError(f"--map {str(path)!r}: not found")
    if len(raw) > 1 << 20:
        raise QuadobsError(f"--map {str(path)!r}: larger than 1 MiB")
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        raise QuadobsError(f"--map {str(path)!r}: not a TOML file ({exc})") from None
    return parse_topic_map(data, f"--map {str(path)!r}", path.parent)


def with_options(topic_map: TopicMap, topics=(), anchors=None, name=None) -> TopicMap:
    """``topic_map`` with the command line's ``--topic STREAM=TOPIC``, ``--anchors FILE`` and ``--name``."""
    streams = {k: dict(v) for k, v in topic_map.streams.items()}
    for item in topics:
        stream, sep, topic = item.partition("=")
        if not sep or stream not in STREAMS or not topic:
            raise QuadobsError(
                f"--topic {item!r}: expected STREAM=TOPIC with STREAM one of {', '.join(STREAMS)}"
            )
        streams[stream] = {**STREAMS[stream], **streams.get(stream, {}), "topic": topic}
    changes: dict = {"streams": streams}
    if anchors is not None:
        changes["anchors"] = _anchors(str(anchors), "--anchors", None)
    if name is not None:
        changes["name"] = name
    return replace(topic_map, **changes)


def _field(msg, path: str, where: str):
    """The field at the dotted ``path`` of a message."""
    obj = msg
    for part in path.split("."):
        if not hasattr(obj, part):
            raise QuadobsError(f"{where}: the message has no field {path!r}")
        obj = getattr(obj, part)
    return obj


def _anchor_id(value, where: str) -> int:
    """An anchor id: an integer field, or the last integer in a text field (``"anchor_12"``: 12)."""
    if isinstance(value, str):
        digits = re.findall(r"\d+", value)
        if not digits:
            raise QuadobsError(f"{where}: no anchor id in {value!r}")
        return int(digits[-1])
    number = float(value)
    if not (math.isfinite(number) and number == round(number)):
        raise QuadobsError(f"{where}: anchor id {value!r} is not an integer")
    return int(number)


def _quaternion(q, where: str) -> list[float]:
    """``(qw, qx, qy, qz)`` normalised from a ROS quaternion ``(x, y, z, w)``."""
    v = np.array([q.w, q.x, q.y, q.z], dtype=float)
    norm = float(np.linalg.norm(v))
    if not (math.isfinite(norm) and norm > 0.0):
        raise QuadobsError(f"{where}: not a rotation (quaternion of norm {norm:g})")
    return list(v / norm)


def _imu_rows(msg, t: float, opts: dict, out: dict, where: str) -> None:
    a, w = msg.linear_acceleration, msg.angular_velocity
    out["imu"].append([t, a.x, a.y, a.z, w.x, w.y, w.z])
    if opts["attitude"] and msg.orientation_covariance[0] != -1.0:  # -1: no orientation (ROS)
        out["attitude"].append([t, *_quaternion(msg.orientation, where)])


def _truth_rows(msg, t: float, opts: dict, out: dict, where: str) -> None:
    if hasattr(msg, "transform"):
        p, q = msg.transform.translation, msg.transform.rotation
    else:
        p, q = msg.pose.position, msg.pose.orientation
    out["truth"].append([t, p.x, p.y, p.z, *_quaternion(q, where)])


def _std(msg, opts: dict, where: str) -> float:
    if not opts["std"]:
        return math.nan
    s = float(_field(msg, opts["std"], where))
    if not (math.isfinite(s) and s > 0.0):
        raise QuadobsError(f"{where}: std {s!r} is not a positive standard deviation")
    return s


def _range_rows(msg, t: float, opts: dict, out: dict, where: str) -> None:
    anchor = _anchor_id(_field(msg, opts["anchor"], where), where)
    value = float(_field(msg, opts["value"], where))
    out["ranges"].append([t, anchor, value, _std(msg, opts, where)])


def _tdoa_rows(msg, t: float, opts: dict, out: dict, where: str) -> None:
    i = _anchor_id(_field(msg, opts["anchor_i"], where), where)
    j = _anchor_id(_field(msg, opts["anchor_j"], where), where)
    value = opts["sign"] * float(_field(msg, opts["value"], where))
    out["tdoa"].append([t, i, j, value, _std(msg, opts, where)])


_READERS = {"imu": _imu_rows, "truth": _truth_rows, "ranges": _range_rows, "tdoa": _tdoa_rows}


def _check_types(connections: dict, streams: dict, bag: str) -> None:
    """Every stream's topic in the bag, with a message type it can be read as."""
    for stream, opts in streams.items():
        conn = connections.get(opts["topic"])
        if conn is None:
            raise QuadobsError(
                f"{bag}: [{stream}] topic {opts['topic']!r} is not in the bag "
                f"(topics: {', '.join(sorted(connections)) or 'none'})"
            )
        if stream == "imu" and not conn.msgtype.endswith("/Imu"):
            raise QuadobsError(
                f"{bag}: [imu] {opts['topic']}: {conn.msgtype}, expected sensor_msgs/Imu"
            )
        if stream == "truth" and conn.msgtype not in _TRUTH_TYPES:
            raise QuadobsError(
                f"{bag}: [truth] {opts['topic']}: {conn.msgtype}, expected {' or '.join(_TRUTH_TYPES)}"
            )


def _read_bag(bag: Path, topic_map: TopicMap) -> dict[str, list]:
    """The rows of every stream, in the bag's order."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {k: [] for k in ("imu", "attitude", "truth", "ranges", "tdoa")}
    by_topic = {opts["topic"]: (s, opts) for s, opts in topic_map.streams.items()}
    header = topic_map.time == "header"
    try:
        with AnyReader([bag]) as reader:
            conns = {c.topic: c for c in reader.connections}
            _check_types(conns, topic_map.streams, str(bag))
            wanted = [c for c in reader.connections if c.topic in by_topic]
            for n, (conn, t_ns, raw) in enumerate(reader.messages(connections=wanted)):
                stream, opts = by_topic[conn.topic]
                where = f"{bag}: [{stream}] {conn.topic}, message {n + 1}"
                msg = reader.deserialize(raw, conn.msgtype)
                if header:
                    stamp = _field(msg, "header.stamp", where + ' (use time = "receive")')
                    t = stamp.sec + stamp.nanosec * 1e-9
                else:
                    t = t_ns * 1e-9
                _READERS[stream](msg, t, opts, out, where)
    except QuadobsError:
        raise
    except Exception as exc:  # rosbags' errors: not a bag, a broken one, an unknown message type
        raise QuadobsError(
            f"{bag}: cannot be read as a ROS bag ({type(exc).__name__}: {exc})"
        ) from None
    return out


def _table(rows: list, width: int) -> np.ndarray:
    """Rows sorted by time (stably), ``(m, width)``."""
    a = np.array(rows, dtype=float).reshape(-1, width)
    return a[np.argsort(a[:, 0], kind="stable")]


def import_bag(bag: str | Path, topic_map: TopicMap) -> RangeLog:
    """Read a ROS 1 (``.bag``) or ROS 2 (a folder) bag into a :class:`RangeLog` (module docstring).

    Raises
    ------
    QuadobsError
        No anchors, no ranges or TDOA stream, a topic missing or of the wrong type, a
        field missing, or a value the format refuses: one line naming the bag, the stream,
        the topic and the message.
    """
    bag = Path(bag)
    if not bag.exists():
        raise QuadobsError(f"{bag}: no such bag (a ROS 1 .bag file or a ROS 2 bag folder)")
    if not topic_map.anchors:
        raise QuadobsError("anchors: none given (--anchors FILE, or anchors in the --map file)")
    if not {"ranges", "tdoa"} & set(topic_map.streams):
        raise QuadobsError("topic map: no [ranges] or [tdoa] topic (--topic ranges=/TOPIC)")
    dims = {len(p) for p in topic_map.anchors.values()}
    if len(dims) != 1:
        raise QuadobsError("anchors: all with z or all without")
    dim = dims.pop()
    rows = _read_bag(bag, topic_map)
    ids = np.array(sorted(topic_map.anchors), dtype=np.int64)
    ranges, tdoa = _table(rows["ranges"], 4), _table(rows["tdoa"], 5)
    has_imu = "imu" in topic_map.streams
    truth = _table(rows["truth"], 8) if "truth" in topic_map.streams else None
    truth_columns = ("time", *"xyz"[:dim], "qw", "qx", "qy", "qz")
    if truth is not None and dim == 2:
        truth = np.delete(truth, 3, axis=1)  # a planar log: no z
    return RangeLog(
        topic_map.name or bag.stem,
        ids,
        np.array([topic_map.anchors[i] for i in ids]),
        ranges[:, :3],
        _table(rows["imu"], 7) if has_imu else np.empty((0, 1)),
        math.nan,
        truth if truth is not None and truth.shape[0] else None,
        input_kind="imu_body" if has_imu else "none",
        truth_columns=truth_columns,
        range_std=ranges[:, 3],
        tdoa=tdoa[:, :4],
        tdoa_std=tdoa[:, 4],
        attitude=_table(rows["attitude"], 5) if rows["attitude"] else None,
        frame=topic_map.frame,
        gravity=topic_map.gravity,
        description=topic_map.description,
    )
