"""ROS 1 and ROS 2 bags imported into the open log format, through ``rosbags``.

``rosbags`` (pure Python, the ``data`` extra) reads both bag formats and the message
definitions stored in them, so custom range and TDOA messages need no ROS installation;
this module only says which topic holds what and which fields to read. A *topic map*
(:class:`TopicMap`, from a small TOML file or the command line) names up to five streams,
each from one topic or several (``topic = ["/uwb/anchor_1", "/uwb/anchor_2"]``):

============  ======================================  ===========================================
stream        message                                 written as
============  ======================================  ===========================================
``imu``       ``sensor_msgs/Imu``                     ``imu.csv``: ``linear_acceleration`` (specific
                                                      force) and ``angular_velocity``, body frame;
                                                      with ``attitude = true`` also ``orientation``
                                                      as ``attitude.csv``
``odometry``  ``nav_msgs/Odometry`` or                ``inputs.csv``: ``twist.linear.x`` (speed) and
              ``geometry_msgs/TwistStamped``          ``twist.angular.z`` (yaw rate), a wheeled
                                                      robot's (with ``heading0``, the heading at
                                                      the first message in the anchors' frame)
``truth``     ``geometry_msgs/PoseStamped``,          ``truth.csv``: position and attitude (a
              ``PoseWithCovarianceStamped``,          point: position only); ``/tf``: the
              ``TransformStamped``,                   transforms whose ``child_frame_id`` is
              ``PointStamped``,                       ``child_frame`` (and whose
              ``nav_msgs/Odometry`` or                ``header.frame_id`` is ``parent_frame``,
              ``tf2_msgs/TFMessage``                  where given)
``ranges``    any message with an anchor id and a     ``ranges.csv``; fields ``anchor`` (default
              range (e.g. ``sensor_msgs/Range``)      ``header.frame_id``; ``"topic"``: the
                                                      topic's name), ``value`` (default
                                                      ``range``), ``std``
``tdoa``      any message with two anchor ids and a   ``tdoa.csv``; fields ``anchor_i`` (``idA``),
              difference (m)                          ``anchor_j`` (``idB``), ``value`` (``data``),
                                                      ``std``; ``sign = -1`` where the message
                                                      holds ``|p - a_j| - |p - a_i|``
============  ======================================  ===========================================

An anchor id is an integer field, or a number in a text field (a frame id, a topic's name):
the one number it holds (``"anchor_12"``: 12), or the first group of ``anchor_pattern``, a
regular expression (``'anchor_(\\d+)'`` for ``"anchor_3/antenna_1"``, which holds two and is
refused without it; a group ``0x...`` is read as hexadecimal).

Beside ``name``, ``description``, ``frame``, ``gravity`` and ``heading0``, the map's top level
may state ``meta.csv``'s other keys (:data:`~quadobs.testbed.logs.importing.STATED_META_KEYS`:
the tag's place, an IMU's figures, the ranges' error model), checked as ``meta.csv`` checks
them.

Readings a message marks as none are left out and counted (the import's notes), not
refused: a range, TDOA, IMU or truth value that is not finite (``sensor_msgs/Range`` gives
``+inf`` or ``-inf`` for nothing in reach, NaN for a failed reading), and a
``sensor_msgs/Range`` outside its ``[min_range, max_range]`` (where ``max_range >
min_range``). A ``std`` field of 0 or NaN states no standard deviation (the estimator's
default; a covariance of 0 is ROS's "unknown").

The anchors' positions are not in the bags this targets: they come from a CSV file
(``id,x,y[,z]``, as ``beacons.csv``) or a TOML table. Times are each message's header
stamp (``time = "header"``, the default) or its receive time in the bag
(``time = "receive"``), in seconds, for the whole map or per stream (a ``time`` key in the
stream's table: an IMU stamped on its own boot clock); each stream is sorted by time
(stably). A header stamp of zero (unset), a stream whose stamps do not overlap the ranges'
(another clock), a mapped topic with no message and an anchor id not among the anchors are
refused in one line. Quaternions (ROS order ``x, y, z, w``) are normalised; a zero one is
refused.

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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog
from quadobs.testbed.logs.importing import (
    STATED_META_KEYS,
    anchor_id,
    assemble_log,
    check_anchor_ids,
    check_anchor_pattern,
    check_clocks,
    read_anchors,
    read_map,
    stated_meta,
)

__all__ = ["STREAMS", "TopicMap", "import_bag", "load_topic_map", "parse_topic_map"]

#: The streams a topic map may name, and the fields each reads (with their defaults).
#: The streams a topic map may name, and the keys of each beside ``topic`` (with their
#: defaults; ``time`` None: the map's).
STREAMS: dict[str, dict[str, Any]] = {
    "imu": {"attitude": False, "time": None},
    "odometry": {"time": None},
    "truth": {"child_frame": "", "parent_frame": "", "time": None},
    "ranges": {
        "anchor": "header.frame_id",
        "anchor_pattern": "",
        "value": "range",
        "std": "",
        "time": None,
    },
    "tdoa": {
        "anchor_i": "idA",
        "anchor_j": "idB",
        "anchor_pattern": "",
        "value": "data",
        "std": "",
        "sign": 1,
        "time": None,
    },
}
_TOP_KEYS = (
    "name",
    "description",
    "frame",
    "gravity",
    "time",
    "anchors",
    "heading0",
    *STATED_META_KEYS,
)
_ODOMETRY_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/TwistStamped")
_TRUTH_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/PointStamped",
    "nav_msgs/msg/Odometry",
    "tf2_msgs/msg/TFMessage",
)
_TEXT_KEYS = ("anchor", "anchor_i", "anchor_j", "value", "std", "child_frame", "parent_frame")


@dataclass(frozen=True)
class TopicMap:
    """Which topic holds which stream, and how its messages are read (module docstring).

    Attributes
    ----------
    streams : dict of str to dict
        Per stream of :data:`STREAMS` present: ``topic`` (a tuple of topic names), ``time``
        and its fields.
    anchors : dict of int to tuple of float
        Anchor id to position (m).
    name, description, frame : str
    gravity : float
    time : {"header", "receive"}
        The times of the streams whose table sets none.
    heading0 : float
        With wheel odometry: the heading (rad) at its first row, in the anchors' frame.
    meta : dict
        The other ``meta.csv`` keys the map states
        (:data:`~quadobs.testbed.logs.importing.STATED_META_KEYS`: the tag's place, an IMU's
        figures, the ranges' error model).
    """

    streams: dict = field(default_factory=dict)
    anchors: dict = field(default_factory=dict)
    name: str = ""
    description: str = ""
    frame: str = "enu"
    gravity: float = 9.80665
    time: str = "header"
    heading0: float = math.nan
    meta: dict = field(default_factory=dict)


def _topics(value, where: str) -> tuple[str, ...]:
    """A stream's ``topic``: one name or a non-empty list of distinct names."""
    names = [value] if isinstance(value, str) else value
    if (
        not isinstance(names, list)
        or not names
        or not all(isinstance(n, str) and n for n in names)
        or len(set(names)) != len(names)
    ):
        raise QuadobsError(f'{where}: expected topic = "/name" or a list of distinct names')
    return tuple(names)


def _check_stream(key: str, opts: dict, where: str) -> None:
    """The types of a stream's keys (module docstring), each refused in one line."""
    for name in _TEXT_KEYS:
        if name in opts and not isinstance(opts[name], str):
            raise QuadobsError(f"{where}: {name}: expected text (a field name)")
    if not isinstance(opts.get("attitude", False), bool):
        raise QuadobsError(f"{where}: attitude: expected true or false")
    if opts.get("sign", 1) not in (1, -1) or isinstance(opts.get("sign"), bool):
        raise QuadobsError(f"{where}: sign: expected 1 or -1")
    if opts.get("time") not in (None, "header", "receive"):
        raise QuadobsError(f"{where}: time: expected 'header' or 'receive', got {opts['time']!r}")
    check_anchor_pattern(opts.get("anchor_pattern", ""), where)


def _stream(key: str, value, where: str) -> dict:
    """A stream's table, checked, with its defaults."""
    where = f"{where}: [{key}]"
    if not isinstance(value, dict) or "topic" not in value:
        raise QuadobsError(f'{where}: expected a table with topic = "/name"')
    unknown = set(value) - {"topic", *STREAMS[key]}
    if unknown:
        raise QuadobsError(
            f"{where}: unknown key {sorted(unknown)[0]!r} (known: topic, {', '.join(STREAMS[key])})"
        )
    opts = {**STREAMS[key], **value, "topic": _topics(value["topic"], where)}
    _check_stream(key, opts, where)
    return opts


def parse_topic_map(data: dict, where: str = "topic map", base: Path | None = None) -> TopicMap:
    """A :class:`TopicMap` from its TOML document (module docstring); unknown keys refused."""
    streams, top = {}, {}
    for key, value in data.items():
        if key in STREAMS:
            streams[key] = _stream(key, value, where)
        elif key in _TOP_KEYS:
            top[key] = value
        else:
            known = ", ".join((*_TOP_KEYS, *(f"[{s}]" for s in STREAMS)))
            raise QuadobsError(f"{where}: unknown key {key!r} (known: {known})")
    if top.get("time", "header") not in ("header", "receive"):
        raise QuadobsError(f"{where}: time: expected 'header' or 'receive', got {top['time']!r}")
    if top.get("frame", "enu") not in ("enu", "ned"):
        raise QuadobsError(
            f"{where}: frame: expected 'enu' or 'ned' (the navigation frame: z up or down; "
            f"a body IMU's axes, FLU or FRD, need no setting), got {top['frame']!r}"
        )
    if "anchors" in top:
        top["anchors"] = read_anchors(top["anchors"], where, base)
    for key in ("name", "description"):
        if key in top and not isinstance(top[key], str):
            raise QuadobsError(f"{where}: {key}: expected text")
    if "gravity" in top and not (
        isinstance(top["gravity"], int | float)
        and not isinstance(top["gravity"], bool)
        and math.isfinite(top["gravity"])
        and top["gravity"] > 0
    ):
        raise QuadobsError(f"{where}: gravity: expected a positive number (m/s^2)")
    if "heading0" in top and not (
        isinstance(top["heading0"], int | float)
        and not isinstance(top["heading0"], bool)
        and math.isfinite(top["heading0"])
    ):
        raise QuadobsError(f"{where}: heading0: expected a number (rad)")
    meta = stated_meta(top, STATED_META_KEYS, where)
    top = {k: v for k, v in top.items() if k not in STATED_META_KEYS}
    return TopicMap(streams=streams, meta=meta, **top)


def load_topic_map(path: str | Path) -> TopicMap:
    """:func:`parse_topic_map` of a TOML file (a regular file of at most 1 MiB)."""
    path = Path(path)
    label = f"--map {str(path)!r}"
    return parse_topic_map(read_map(path, label), label, path.parent)


def with_options(topic_map: TopicMap, topics=(), anchors=None, name=None) -> TopicMap:
    """``topic_map`` with the command line's ``--topic STREAM=TOPIC`` (repeated for a stream:
    its topics, in place of the map's), ``--anchors FILE`` and ``--name``."""
    streams = {k: dict(v) for k, v in topic_map.streams.items()}
    given: dict[str, list[str]] = {}
    for item in topics:
        stream, sep, topic = item.partition("=")
        if not sep or stream not in STREAMS or not topic:
            raise QuadobsError(
                f"--topic {item!r}: expected STREAM=TOPIC with STREAM one of {', '.join(STREAMS)}"
            )
        if topic in given.setdefault(stream, []):
            raise QuadobsError(f"--topic {item!r}: given twice")
        given[stream].append(topic)
    for stream, names in given.items():
        streams[stream] = {**STREAMS[stream], **streams.get(stream, {}), "topic": tuple(names)}
    changes: dict = {"streams": streams}
    if anchors is not None:
        changes["anchors"] = read_anchors(str(anchors), "--anchors", None)
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


def _quaternion(q, where: str) -> list[float] | None:
    """``(qw, qx, qy, qz)`` normalised from a ROS quaternion ``(x, y, z, w)``; None where it is
    not finite (no reading)."""
    v = np.array([q.w, q.x, q.y, q.z], dtype=float)
    norm = float(np.linalg.norm(v))
    if not math.isfinite(norm):
        return None
    if not norm > 0.0:
        raise QuadobsError(f"{where}: not a rotation (quaternion of norm {norm:g})")
    return list(v / norm)


@dataclass
class _Reading:
    """What the messages of one bag give: rows per table, readings left out by reason, and
    the times of each message (:meth:`time_of`)."""

    receive: float = 0.0
    header: bool = True
    rows: dict = field(
        default_factory=lambda: {
            k: [] for k in ("imu", "odometry", "attitude", "truth", "ranges", "tdoa")
        }
    )
    left_out: dict = field(default_factory=dict)
    no_attitude: int = 0
    no_std: dict = field(default_factory=dict)
    frames: set = field(default_factory=set)

    def time_of(self, msg, where: str) -> float:
        """The message's header stamp (s) or its receive time, as the stream's ``time`` says."""
        if not self.header:
            return self.receive
        stamp = _field(msg, "header.stamp", where + ' (use time = "receive")')
        if stamp.sec == 0 and stamp.nanosec == 0:
            raise QuadobsError(f'{where}: header stamp unset (0 s): use time = "receive"')
        return stamp.sec + stamp.nanosec * 1e-9

    def leave_out(self, stream: str, reason: str) -> None:
        key = (stream, reason)
        self.left_out[key] = self.left_out.get(key, 0) + 1


def _finite(values) -> bool:
    return all(math.isfinite(v) for v in values)


def _imu_rows(msg, opts: dict, read: _Reading, where: str) -> None:
    a, w = msg.linear_acceleration, msg.angular_velocity
    row = [float(v) for v in (a.x, a.y, a.z, w.x, w.y, w.z)]
    if not _finite(row):
        read.leave_out("imu", "not finite")
        return
    t = read.time_of(msg, where)
    read.rows["imu"].append([t, *row])
    if opts["attitude"]:
        if msg.orientation_covariance[0] == -1.0:  # -1: no orientation (ROS)
            read.no_attitude += 1
            return
        q = _quaternion(msg.orientation, where)
        if q is None:
            read.leave_out("imu", "orientation not finite (its attitude row)")
            return
        read.rows["attitude"].append([t, *q])


def _odometry_rows(msg, opts: dict, read: _Reading, where: str) -> None:
    twist = msg.twist.twist if hasattr(msg.twist, "twist") else msg.twist  # Odometry, TwistStamped
    row = [float(twist.linear.x), float(twist.angular.z)]
    if not _finite(row):
        read.leave_out("odometry", "not finite")
        return
    read.rows["odometry"].append([read.time_of(msg, where), *row])


def _pose_of(msg, opts: dict, read: _Reading) -> list:
    """``[(header holder, position, orientation or None), ...]`` of a truth message."""
    if hasattr(msg, "transforms"):  # tf2_msgs/TFMessage: the transforms of the child frame
        read.frames.update(f"{tf.header.frame_id} -> {tf.child_frame_id}" for tf in msg.transforms)
        return [
            (tf, tf.transform.translation, tf.transform.rotation)
            for tf in msg.transforms
            if tf.child_frame_id == opts["child_frame"]
            and (not opts["parent_frame"] or tf.header.frame_id == opts["parent_frame"])
        ]
    if hasattr(msg, "transform"):
        return [(msg, msg.transform.translation, msg.transform.rotation)]
    if hasattr(msg, "point"):
        return [(msg, msg.point, None)]
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose  # Odometry, with covariance
    return [(msg, pose.position, pose.orientation)]


def _truth_rows(msg, opts: dict, read: _Reading, where: str) -> None:
    for holder, p, q in _pose_of(msg, opts, read):
        position = [float(p.x), float(p.y), float(p.z)]
        attitude = [math.nan] * 4 if q is None else _quaternion(q, where)
        if attitude is None or not _finite(position):
            read.leave_out("truth", "not finite")
            continue
        read.rows["truth"].append([read.time_of(holder, where), *position, *attitude])


def _std(msg, opts: dict, read: _Reading, stream: str, where: str) -> float:
    """The field ``std`` where given: 0 or NaN states none (NaN, counted)."""
    if not opts["std"]:
        return math.nan
    s = float(_field(msg, opts["std"], where))
    if s == 0.0 or math.isnan(s):
        read.no_std[stream] = read.no_std.get(stream, 0) + 1
        return math.nan
    if not (math.isfinite(s) and s > 0.0):
        raise QuadobsError(f"{where}: std {s!r} is not a positive standard deviation")
    return s


def _out_of_reach(msg, value: float) -> bool:
    """A ``sensor_msgs/Range`` outside its ``[min_range, max_range]`` (where those are set)."""
    lo, hi = (float(getattr(msg, k, math.nan)) for k in ("min_range", "max_range"))
    return math.isfinite(lo) and math.isfinite(hi) and hi > lo and not lo <= value <= hi


def _range_rows(msg, opts: dict, read: _Reading, where: str, topic: str) -> None:
    value = float(_field(msg, opts["value"], where))
    if not math.isfinite(value):
        read.leave_out("ranges", "not finite (no reading)")
        return
    if opts["value"] == "range" and _out_of_reach(msg, value):
        read.leave_out("ranges", "outside min_range..max_range")
        return
    text = topic if opts["anchor"] == "topic" else _field(msg, opts["anchor"], where)
    anchor = anchor_id(text, opts["anchor_pattern"], where)
    std = _std(msg, opts, read, "ranges", where)
    read.rows["ranges"].append([read.time_of(msg, where), anchor, value, std])


def _tdoa_rows(msg, opts: dict, read: _Reading, where: str, topic: str) -> None:
    value = opts["sign"] * float(_field(msg, opts["value"], where))
    if not math.isfinite(value):
        read.leave_out("tdoa", "not finite (no reading)")
        return
    i, j = (
        anchor_id(_field(msg, opts[k], where), opts["anchor_pattern"], where)
        for k in ("anchor_i", "anchor_j")
    )
    std = _std(msg, opts, read, "tdoa", where)
    read.rows["tdoa"].append([read.time_of(msg, where), i, j, value, std])


def _check_types(connections: dict, streams: dict, bag: str) -> None:
    """Every stream's topics in the bag, with a message type it can be read as."""
    for stream, opts in streams.items():
        for topic in opts["topic"]:
            conn = connections.get(topic)
            if conn is None:
                raise QuadobsError(
                    f"{bag}: [{stream}] topic {topic!r} is not in the bag "
                    f"(topics: {', '.join(sorted(connections)) or 'none'})"
                )
            if stream == "imu" and not conn.msgtype.endswith("/Imu"):
                raise QuadobsError(
                    f"{bag}: [imu] {topic}: {conn.msgtype}, expected sensor_msgs/Imu"
                )
            if stream == "odometry" and conn.msgtype not in _ODOMETRY_TYPES:
                raise QuadobsError(
                    f"{bag}: [odometry] {topic}: {conn.msgtype}, expected one of {', '.join(_ODOMETRY_TYPES)}"
                )
            if stream == "truth" and conn.msgtype not in _TRUTH_TYPES:
                raise QuadobsError(
                    f"{bag}: [truth] {topic}: {conn.msgtype}, expected one of {', '.join(_TRUTH_TYPES)}"
                )
            if (
                stream == "truth"
                and conn.msgtype.endswith("/TFMessage")
                and not opts["child_frame"]
            ):
                raise QuadobsError(
                    f'{bag}: [truth] {topic}: a tf2_msgs/TFMessage needs child_frame = "the body\'s frame"'
                )


def _read_bag(bag: Path, topic_map: TopicMap) -> _Reading:
    """The rows of every stream, in the bag's order, each message numbered on its topic."""
    from rosbags.highlevel import AnyReader

    read = _Reading()
    by_topic: dict = {}
    for stream, opts in topic_map.streams.items():
        for topic in opts["topic"]:
            if topic in by_topic:
                raise QuadobsError(
                    f"topic map: {topic} is mapped to [{by_topic[topic][0]}] and [{stream}]"
                )
            by_topic[topic] = (stream, opts)
    counts = dict.fromkeys(by_topic, 0)
    try:
        with AnyReader([bag]) as reader:
            _check_types({c.topic: c for c in reader.connections}, topic_map.streams, str(bag))
            wanted = [c for c in reader.connections if c.topic in by_topic]
            for conn, t_ns, raw in reader.messages(connections=wanted):
                stream, opts = by_topic[conn.topic]
                counts[conn.topic] += 1
                where = f"{bag}: [{stream}] {conn.topic}, message {counts[conn.topic]}"
                msg = reader.deserialize(raw, conn.msgtype)
                read.receive = t_ns * 1e-9
                read.header = (opts["time"] or topic_map.time) == "header"
                if stream in ("ranges", "tdoa"):
                    _READ_MEASUREMENT[stream](msg, opts, read, where, conn.topic)
                else:
                    _READ_STATE[stream](msg, opts, read, where)
    except QuadobsError:
        raise
    except Exception as exc:  # rosbags' errors: not a bag, a broken one, an unknown message type
        raise QuadobsError(
            f"{bag}: cannot be read as a ROS bag ({type(exc).__name__}: {exc})"
        ) from None
    empty = [f"[{by_topic[t][0]}] {t}" for t, n in counts.items() if n == 0]
    if empty:
        raise QuadobsError(f"{bag}: no message on {', '.join(empty)}")
    return read


_READ_STATE = {"imu": _imu_rows, "odometry": _odometry_rows, "truth": _truth_rows}
_READ_MEASUREMENT = {"ranges": _range_rows, "tdoa": _tdoa_rows}


def _table(rows: list, width: int) -> np.ndarray:
    """Rows sorted by time (stably), ``(m, width)``."""
    a = np.array(rows, dtype=float).reshape(-1, width)
    return a[np.argsort(a[:, 0], kind="stable")]


def _notes_of(read: _Reading, topic_map: TopicMap, notes) -> None:
    if notes is None:
        return
    for (stream, reason), n in sorted(read.left_out.items()):
        notes.append(f"[{stream}] {n} left out: {reason}")
    for stream, n in sorted(read.no_std.items()):
        notes.append(f"[{stream}] {n} kept with no std stated (the field 0 or NaN)")
    if read.no_attitude:
        notes.append(
            f"[imu] attitude = true, and {read.no_attitude} messages hold no orientation "
            "(orientation_covariance[0] = -1): no attitude.csv from them"
        )


def import_bag(bag: str | Path, topic_map: TopicMap, notes: list | None = None) -> RangeLog:
    """Read a ROS 1 (``.bag``) or ROS 2 (a folder) bag into a :class:`RangeLog` (module docstring).

    Parameters
    ----------
    bag : str or Path
    topic_map : TopicMap
    notes : list, optional
        Where given, lines are appended saying what was left out and why, and which anchors
        no measurement names.

    Raises
    ------
    QuadobsError
        No anchors, no ranges or TDOA stream, a topic missing, empty or of the wrong type, a
        field missing, a stamp unset, streams on different clocks, an anchor id not among the
        anchors, or a value the format refuses: one line naming the bag, the stream, the topic
        and the message.
    """
    bag = Path(bag)
    _check_map(bag, topic_map)
    read = _read_bag(bag, topic_map)
    rows = read.rows
    ranges, tdoa = _table(rows["ranges"], 4), _table(rows["tdoa"], 5)
    kind = next((k for k in ("imu", "odometry") if k in topic_map.streams), "none")
    inputs = {
        "imu": lambda: _table(rows["imu"], 7),
        "odometry": lambda: _table(rows["odometry"], 3),
        "none": lambda: np.empty((0, 1)),
    }[kind]()
    truth = _table(rows["truth"], 8) if "truth" in topic_map.streams else None
    attitude = _table(rows["attitude"], 5) if rows["attitude"] else None
    _check_rows(bag, topic_map, read, ranges.shape[0] + tdoa.shape[0], truth)
    check_clocks(bag, {"ranges": ranges, "tdoa": tdoa, kind: inputs, "truth": truth})
    check_anchor_ids(bag, topic_map.anchors, ranges, tdoa, notes)
    _notes_of(read, topic_map, notes)
    tables = {"ranges": ranges, "tdoa": tdoa, "inputs": inputs, "truth": truth}
    return assemble_log(
        topic_map.name or bag.stem,
        topic_map.anchors,
        {**tables, "attitude": attitude},
        kind,
        heading0=topic_map.heading0,
        frame=topic_map.frame,
        gravity=topic_map.gravity,
        description=topic_map.description,
        **topic_map.meta,
    )


def _check_rows(bag: Path, topic_map: TopicMap, read: _Reading, measured: int, truth) -> None:
    """Something left to replay, and a truth that is one: refused in one line where no range
    or TDOA is left, where the mapped truth gave no pose (a ``/tf`` without the frame asked
    for), or where some of its poses hold an attitude and some do not."""
    if measured == 0:
        why = "; ".join(
            f"[{k}] {n} {r}"
            for (k, r), n in sorted(read.left_out.items())
            if k in ("ranges", "tdoa")
        )
        raise QuadobsError(f"{bag}: no range or TDOA left to replay ({why or 'none read'})")
    for stream in ("imu", "odometry"):
        if stream in topic_map.streams and len(read.rows[stream]) < 2:
            left = read.left_out.get((stream, "not finite"), 0)
            raise QuadobsError(
                f"{bag}: [{stream}] fewer than two readings left ({left} left out: not finite)"
            )
    if truth is None:
        return
    topics = ", ".join(topic_map.streams["truth"]["topic"])
    if truth.shape[0] == 0:
        left = read.left_out.get(("truth", "not finite"), 0)
        raise QuadobsError(
            f"{bag}: [truth] {topics}: no pose read"
            + (f" ({left} left out: not finite)" if left else _frames_asked(topic_map, read))
        )
    missing = np.isnan(truth[:, 4]).sum()
    if 0 < missing < truth.shape[0]:
        raise QuadobsError(
            f"{bag}: [truth] {topics}: {missing} of {truth.shape[0]} poses hold no attitude "
            "(points beside poses): map topics of one kind"
        )


def _frames_asked(topic_map: TopicMap, read: _Reading) -> str:
    """For a ``/tf`` truth that gave no pose: the transform asked for and those seen."""
    frames = sorted(read.frames)
    if not frames:
        return ""
    opts = topic_map.streams["truth"]
    return (
        f" (no transform {opts['parent_frame'] or '*'} -> {opts['child_frame']}; "
        f"transforms seen: {', '.join(frames[:8])})"
    )


def _check_map(bag: Path, topic_map: TopicMap) -> int:
    """What the map must hold before the bag is read; the anchors' dimension."""
    if not bag.exists():
        raise QuadobsError(f"{bag}: no such bag (a ROS 1 .bag file or a ROS 2 bag folder)")
    if not topic_map.anchors:
        raise QuadobsError("anchors: none given (--anchors FILE, or anchors in the --map file)")
    if not {"ranges", "tdoa"} & set(topic_map.streams):
        raise QuadobsError("topic map: no [ranges] or [tdoa] topic (--topic ranges=/TOPIC)")
    if {"imu", "odometry"} <= set(topic_map.streams):
        raise QuadobsError("topic map: [imu] and [odometry]: a log holds one kind of inputs")
    if "odometry" not in topic_map.streams and math.isfinite(topic_map.heading0):
        raise QuadobsError("topic map: heading0 is for wheel odometry, and no [odometry] is mapped")
    if "odometry" in topic_map.streams and not math.isfinite(topic_map.heading0):
        raise QuadobsError(
            "topic map: [odometry] needs heading0, the heading (rad) at the first odometry "
            "message in the anchors' frame (the odometry's own frame does not tell it): set "
            "heading0 = RAD in the --map file"
        )
    dims = {len(p) for p in topic_map.anchors.values()}
    if len(dims) != 1:
        raise QuadobsError("anchors: all with z or all without")
    return dims.pop()
