"""ROS 1 and ROS 2 bags, written here with rosbags itself, imported into the open log format."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.logs import read_log, write_log
from quadobs.testbed.logs.rosbag import import_bag, load_topic_map, parse_topic_map, with_options
from quadobs.testbed.logs.schema import IMU

pytest.importorskip("rosbags")

TDOA_MSG = "std_msgs/Header header\nint32 idA\nint32 idB\nfloat32 data\nfloat32 sigma\n"
ANCHORS = {3: (0.0, 0.0, 0.2), 7: (6.0, 0.0, 2.5), 11: (6.0, 5.0, 0.3), 12: (0.0, 5.0, 2.4)}
T0 = 1_700_000_000.0  # an epoch-like clock, as bags hold


def _position(t):
    return np.array([3.0 + math.cos(t), 2.0 + math.sin(t), 1.0])


def write_bag(path, ros1: bool) -> dict:
    """A 1-s flight: IMU at 200 Hz, pose at 100 Hz, ranges round-robin at 50 Hz (sensor_msgs/Range,
    the anchor in frame_id), TDOA at 25 Hz (a custom message); messages in receive order."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(TDOA_MSG, "cf_msgs/msg/Tdoa"))
    T = ts.types
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr

    def header(t, frame=""):
        stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        extra = {"seq": 0} if ros1 else {}
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame, **extra)

    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    events = []
    for k in range(200):
        t = T0 + k * 0.005
        imu = T["sensor_msgs/msg/Imu"](
            header=header(t),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=2.0),  # not unit: normalised on import
            orientation_covariance=np.zeros(9),
            angular_velocity=V3(x=0.1, y=0.2, z=1.0 + k * 1e-3),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V3(x=-1.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9),
        )
        events.append(("/imu", "sensor_msgs/msg/Imu", t, imu))
    for k in range(100):
        t = T0 + k * 0.01
        p = _position(t - T0)
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
            orientation=Q(x=0.0, y=0.0, z=math.sin(0.1), w=math.cos(0.1)),
        )
        msg = T["geometry_msgs/msg/PoseStamped"](header=header(t), pose=pose)
        events.append(("/vicon/pose", "geometry_msgs/msg/PoseStamped", t, msg))
    ids = sorted(ANCHORS)
    for k in range(50):
        t = T0 + 0.003 + k * 0.02
        a = ids[k % 4]
        rho = float(np.linalg.norm(_position(t - T0) - ANCHORS[a]))
        msg = T["sensor_msgs/msg/Range"](
            header=header(t, f"anchor_{a}"),
            radiation_type=0,
            field_of_view=0.0,
            min_range=0.0,
            max_range=50.0,
            range=rho,
        )
        events.append(("/uwb/range", "sensor_msgs/msg/Range", t + 0.002, msg))  # received later
    for k in range(25):
        t = T0 + 0.007 + k * 0.04
        msg = T["cf_msgs/msg/Tdoa"](header=header(t), idA=7, idB=3, data=0.5 + k, sigma=0.1)
        events.append(("/tdoa", "cf_msgs/msg/Tdoa", t, msg))
    events.sort(key=lambda e: e[2])
    Writer = Writer1 if ros1 else Writer2
    with Writer(path, **({} if ros1 else {"version": 9})) as w:
        conns = {}
        for topic, msgtype, t, msg in events:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], int(round(t * 1e9)), serialize(msg, msgtype))
    return {"events": events}


MAP = """
name = "bag-flight"
anchors = "anchors.csv"
[imu]
topic = "/imu"
attitude = true
[truth]
topic = "/vicon/pose"
[ranges]
topic = "/uwb/range"
[tdoa]
topic = "/tdoa"
std = "sigma"
sign = -1
"""


def _files(tmp_path):
    (tmp_path / "anchors.csv").write_text(
        "id,x,y,z\n" + "".join(f"{i},{x},{y},{z}\n" for i, (x, y, z) in ANCHORS.items())
    )
    (tmp_path / "map.toml").write_text(MAP)


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_a_bag_imports_with_every_stream(tmp_path, ros1):
    _files(tmp_path)
    bag = tmp_path / ("flight.bag" if ros1 else "flight")
    write_bag(bag, ros1)
    log = import_bag(bag, load_topic_map(tmp_path / "map.toml"))
    assert (log.name, log.input_kind, log.dimension) == ("bag-flight", "imu_body", 3)
    assert (
        log.inputs.shape == (200, 7) and log.ranges.shape == (50, 3) and log.tdoa.shape == (25, 4)
    )
    np.testing.assert_allclose(log.inputs[:, IMU.az], 9.81)
    np.testing.assert_allclose(log.inputs[5, IMU.gz], 1.005)
    assert log.ranges[0, 0] == pytest.approx(T0 + 0.003, abs=1e-6)  # the header stamp, not receive
    assert list(log.ranges[:4, 1]) == [3, 7, 11, 12]
    p = np.array([_position(t - T0) for t in log.ranges[:, 0]])
    a = np.array([ANCHORS[int(i)] for i in log.ranges[:, 1]])
    np.testing.assert_allclose(log.ranges[:, 2], np.linalg.norm(p - a, axis=1), atol=1e-5)
    np.testing.assert_allclose(log.tdoa[:3, 3], [-0.5, -1.5, -2.5])  # sign = -1
    np.testing.assert_allclose(log.tdoa_std, 0.1, rtol=1e-6)
    assert np.all(np.isnan(log.range_std))
    np.testing.assert_allclose(log.attitude[0, 1:], [1.0, 0.0, 0.0, 0.0])
    assert log.truth_columns == ("time", "x", "y", "z", "qw", "qx", "qy", "qz")
    np.testing.assert_allclose(log.truth[0, 4:], [math.cos(0.1), 0.0, 0.0, math.sin(0.1)])
    back = read_log(write_log(log, tmp_path / "log"))
    np.testing.assert_array_equal(back.tdoa, log.tdoa)


def test_the_command_line_imports_a_bag_and_the_log_replays(tmp_path, capsys):
    _files(tmp_path)
    write_bag(tmp_path / "flight.bag", ros1=True)
    code = main(
        ["import-bag", str(tmp_path / "flight.bag"), "--out", str(tmp_path / "log")]
        + ["--topic", "ranges=/uwb/range", "--topic", "truth=/vicon/pose"]
        + ["--anchors", str(tmp_path / "anchors.csv")]
    )
    out = capsys.readouterr().out
    assert code == 0 and "50 ranges" in out
    log = read_log(tmp_path / "log")
    assert log.input_kind == "none" and log.name == "flight" and log.truth.shape == (100, 8)


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--topic", "ranges=/nope"],
            "[ranges] topic '/nope' is not in the bag (topics: /imu, /tdoa",
        ),
        (
            ["--topic", "imu=/vicon/pose", "--topic", "ranges=/uwb/range"],
            "geometry_msgs/msg/PoseStamped, expected sensor_msgs/Imu",
        ),
        (
            ["--topic", "imu=/uwb/range", "--topic", "ranges=/uwb/range"],
            "/uwb/range is mapped to [imu] and [ranges]",
        ),
        (["--topic", "speed=/imu"], "--topic 'speed=/imu': expected STREAM=TOPIC"),
        (["--topic", "truth=/vicon/pose"], "no [ranges] or [tdoa] topic"),
    ],
)
def test_a_bad_mapping_is_one_line_with_status_2(tmp_path, capsys, argv, message):
    _files(tmp_path)
    write_bag(tmp_path / "flight.bag", ros1=True)
    base = ["import-bag", str(tmp_path / "flight.bag"), "--out", str(tmp_path / "log")]
    assert main(base + ["--anchors", str(tmp_path / "anchors.csv"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "log").exists()


def test_a_topic_map_refuses_unknown_keys_and_missing_fields(tmp_path):
    with pytest.raises(QuadobsError, match=r"unknown key 'ranegs'"):
        parse_topic_map({"ranegs": {"topic": "/r"}})
    with pytest.raises(QuadobsError, match=r"\[ranges\]: unknown key 'field'"):
        parse_topic_map({"ranges": {"topic": "/r", "field": "x"}})
    with pytest.raises(QuadobsError, match=r"anchors.a: the id must be an integer"):
        parse_topic_map({"anchors": {"a": [0, 0]}})
    _files(tmp_path)
    write_bag(tmp_path / "flight", ros1=False)
    m = with_options(
        parse_topic_map({"anchors": {str(k): list(v) for k, v in ANCHORS.items()}}),
        ["ranges=/uwb/range"],
    )
    bad = with_options(m, ["tdoa=/tdoa"])
    bad.streams["tdoa"]["value"] = "difference"
    with pytest.raises(
        QuadobsError, match=r"\[tdoa\] /tdoa, message \d+: the message has no field 'difference'"
    ):
        import_bag(tmp_path / "flight", bad)
    with pytest.raises(QuadobsError, match=r"cannot be read as a ROS bag"):
        import_bag(tmp_path / "anchors.csv", m)


def test_transform_truth_and_receive_times(tmp_path):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    bag = tmp_path / "tf"
    with Writer(bag, version=9) as w:
        tf = w.add_connection("/mocap", "geometry_msgs/msg/TransformStamped", typestore=ts)
        r = w.add_connection("/r", "sensor_msgs/msg/Range", typestore=ts)
        for k in range(10):
            t = T0 + 0.1 * k
            header = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="a7"
            )
            msg = T["geometry_msgs/msg/TransformStamped"](
                header=header,
                child_frame_id="body",
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=float(k), y=1.0, z=2.0),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                ),
            )
            w.write(tf, int(t * 1e9), ts.serialize_cdr(msg, "geometry_msgs/msg/TransformStamped"))
            rng = T["sensor_msgs/msg/Range"](
                header=header,
                radiation_type=0,
                field_of_view=0.0,
                min_range=0.0,
                max_range=9.0,
                range=1.5,
            )
            w.write(r, int((t + 0.05) * 1e9), ts.serialize_cdr(rng, "sensor_msgs/msg/Range"))
    topic_map = parse_topic_map(
        {
            "time": "receive",  # the stamps are zero: the bag's receive times instead
            "anchors": {"7": [0.0, 0.0, 1.0]},
            "truth": {"topic": "/mocap"},
            "ranges": {"topic": "/r"},
        }
    )
    log = import_bag(bag, topic_map)
    np.testing.assert_allclose(log.truth[:, 0], T0 + 0.1 * np.arange(10), atol=1e-6)
    np.testing.assert_allclose(log.truth[:, 1], np.arange(10.0))
    np.testing.assert_allclose(log.ranges[:, 0], T0 + 0.05 + 0.1 * np.arange(10), atol=1e-6)
    assert set(log.ranges[:, 1]) == {7}


def _ros2_bag(path, build, empty=()):
    """A ROS 2 bag of the events ``build(T, header)`` returns: ``(topic, type, receive, msg)``,
    and a connection without a message for each ``(topic, type)`` of ``empty``."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def header(t, frame=""):
        stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    events = sorted(build(T, header), key=lambda e: e[2])
    with Writer(path, version=9) as w:
        conns = {topic: w.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in empty}
        for topic, msgtype, t, msg in events:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], int(round(t * 1e9)), ts.serialize_cdr(msg, msgtype))
    return path


def _range(T, header, t, frame, value, top=10.0):
    return T["sensor_msgs/msg/Range"](
        header=header(t, frame), radiation_type=0, field_of_view=0.0, min_range=0.0,
        max_range=top, range=value,
    )  # fmt: skip


def _per_anchor(T, header, frame="tag_1", bad=True):
    """Ranges on one topic per anchor (the tag's frame in frame_id), 10 each; with ``bad`` some
    marked as none: +inf, -inf, NaN, and one beyond max_range."""
    marks = {2: math.inf, 4: -math.inf, 6: math.nan, 8: 25.0} if bad else {}
    for a in sorted(ANCHORS):
        for k in range(10):
            t = T0 + 0.1 * k + 0.01 * a
            value = marks.get(k, 1.0 + 0.01 * k) if a == 3 else 1.0 + 0.01 * k
            msg = _range(T, header, t, frame, value)
            yield (f"/uwb/anchor_{a}/range", "sensor_msgs/msg/Range", t, msg)


def _imu(T, header, yaw_rate: float, az: float, orientation: bool = True):
    """A ``sensor_msgs/Imu`` at rest but for ``yaw_rate`` (rad/s) and ``az`` (m/s^2), its
    orientation the identity or (``orientation=False``) marked as none."""
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    return T["sensor_msgs/msg/Imu"](
        header=header, orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([0.0 if orientation else -1.0] + [0.0] * 8),
        angular_velocity=V3(x=0.0, y=0.0, z=yaw_rate), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=V3(x=0.0, y=0.0, z=az), linear_acceleration_covariance=np.zeros(9),
    )  # fmt: skip


def _map(**streams):
    return parse_topic_map({"anchors": {str(k): list(v) for k, v in ANCHORS.items()}, **streams})


def test_ranges_marked_as_none_are_left_out_and_counted_and_topics_name_anchors(tmp_path):
    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(_per_anchor(T, h)))
    topics = [f"/uwb/anchor_{a}/range" for a in sorted(ANCHORS)]
    notes: list[str] = []
    by_topic = _map(ranges={"topic": topics, "anchor": "topic", "anchor_pattern": r"anchor_(\d+)"})
    log = import_bag(bag, by_topic, notes)
    assert log.ranges.shape[0] == 36  # 40 less the four readings of anchor 3 marked as none
    assert sorted(set(log.ranges[:, 1].astype(int))) == sorted(ANCHORS)
    assert np.all(np.isfinite(log.ranges[:, 2])) and log.ranges[:, 2].max() < 2.0
    assert "[ranges] 3 left out: not finite (no reading)" in notes
    assert "[ranges] 1 left out: outside min_range..max_range" in notes
    # the same topics, the id from frame_id 'tag_1': every range would be anchor 1, not one of them
    with pytest.raises(QuadobsError, match=r"anchor id 1 not among the anchors \(3, 7, 11, 12\)"):
        import_bag(bag, _map(ranges={"topic": topics}))
    # a topic's name holding one number needs no pattern
    log2 = import_bag(bag, _map(ranges={"topic": topics, "anchor": "topic"}))
    np.testing.assert_array_equal(log2.ranges, log.ranges)


def test_a_frame_id_with_two_numbers_needs_a_pattern_and_the_command_line_takes_each_topic(
    tmp_path, capsys
):
    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(_per_anchor(T, h, "anchor_3/antenna_1")))
    _files(tmp_path)
    base = ["import-bag", str(bag), "--out", str(tmp_path / "log")]
    base += ["--anchors", str(tmp_path / "anchors.csv")]
    topics = [arg for a in (3, 7) for arg in ("--topic", f"ranges=/uwb/anchor_{a}/range")]
    assert main(base + topics) == 2
    err = capsys.readouterr().err
    assert "'anchor_3/antenna_1' holds 2 numbers" in err and err.count("\n") == 1
    (tmp_path / "map.toml").write_text(
        'anchors = "anchors.csv"\n[ranges]\ntopic = "/x"\nanchor_pattern = "anchor_(\\\\d+)"\n'
    )
    assert main(base + topics + ["--map", str(tmp_path / "map.toml")]) == 0
    out = capsys.readouterr().out
    assert "note: [ranges] 3 left out: not finite (no reading)" in out
    assert "note: anchors that no range or TDOA names: 7, 11, 12" in out
    log = read_log(tmp_path / "log")
    assert log.ranges.shape[0] == 16 and set(log.ranges[:, 1]) == {3}  # both topics: anchor 3


def test_stamps_unset_or_on_another_clock_are_refused_unless_received_times_are_taken(tmp_path):
    def build(T, h, boot=False, unset=False):
        yield from _per_anchor(T, h, bad=False)
        for k in range(20):
            t = T0 + 0.05 * k
            stamp = (100.0 + 0.05 * k) if boot else 0.0 if (unset and k == 3) else t
            imu = _imu(T, h(stamp), 0.1, math.nan if k == 5 else 9.81, orientation=False)
            yield ("/imu", "sensor_msgs/msg/Imu", t + 0.001, imu)

    topics = [f"/uwb/anchor_{a}/range" for a in sorted(ANCHORS)]
    ranges = {"topic": topics, "anchor": "topic", "anchor_pattern": r"anchor_(\d+)"}
    boot = _ros2_bag(tmp_path / "boot", lambda T, h: list(build(T, h, boot=True)))
    with pytest.raises(QuadobsError, match=r"\[imu\] stamps 100 to 100.95 s, .* not one clock"):
        import_bag(boot, _map(ranges=ranges, imu={"topic": "/imu"}))
    notes: list[str] = []
    log = import_bag(boot, _map(ranges=ranges, imu={"topic": "/imu", "time": "receive",
                                                    "attitude": True}), notes)  # fmt: skip
    assert log.inputs.shape[0] == 19 and log.inputs[0, 0] == pytest.approx(T0 + 0.001, abs=1e-6)
    assert "[imu] 1 left out: not finite" in notes and log.attitude is None
    assert any("19 messages hold no orientation" in n for n in notes)
    unset = _ros2_bag(tmp_path / "unset", lambda T, h: list(build(T, h, unset=True)))
    with pytest.raises(QuadobsError, match=r"\[imu\] /imu, message 4: header stamp unset"):
        import_bag(unset, _map(ranges=ranges, imu={"topic": "/imu"}))


def test_truth_from_tf_odometry_and_points(tmp_path):
    def build(T, h):
        yield from _per_anchor(T, h, bad=False)
        V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        P = T["geometry_msgs/msg/Point"]
        for k in range(10):
            t = T0 + 0.1 * k
            q = Q(x=0.0, y=0.0, z=math.sin(0.2), w=math.cos(0.2))

            def tf(child, x, t=t, q=q):
                return T["geometry_msgs/msg/TransformStamped"](
                    header=h(t, "world"), child_frame_id=child,
                    transform=T["geometry_msgs/msg/Transform"](translation=V3(x=x, y=1.0, z=2.0), rotation=q),
                )  # fmt: skip

            other = T["geometry_msgs/msg/TransformStamped"](
                header=h(t, "odom"), child_frame_id="cf",
                transform=T["geometry_msgs/msg/Transform"](translation=V3(x=-5.0, y=1.0, z=2.0), rotation=q),
            )  # fmt: skip
            msg = T["tf2_msgs/msg/TFMessage"](
                transforms=[tf("other", -1.0), tf("cf", float(k)), other]
            )
            yield ("/tf", "tf2_msgs/msg/TFMessage", t, msg)
            pose = T["geometry_msgs/msg/Pose"](position=P(x=float(k), y=2.0, z=1.0), orientation=q)
            cov = T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
            twist = T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=V3(x=0.0, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36),
            )  # fmt: skip
            odom = T["nav_msgs/msg/Odometry"](
                header=h(t, "world"), child_frame_id="cf", pose=cov, twist=twist
            )
            yield ("/odom", "nav_msgs/msg/Odometry", t, odom)
            point = T["geometry_msgs/msg/PointStamped"](
                header=h(t, "world"), point=P(x=float(k), y=3.0, z=0.5)
            )
            yield ("/point", "geometry_msgs/msg/PointStamped", t, point)

    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(build(T, h)))
    topics = [f"/uwb/anchor_{a}/range" for a in sorted(ANCHORS)]
    ranges = {"topic": topics, "anchor": "topic", "anchor_pattern": r"anchor_(\d+)"}
    with pytest.raises(QuadobsError, match=r"TFMessage needs child_frame"):
        import_bag(bag, _map(ranges=ranges, truth={"topic": "/tf"}))
    with pytest.raises(
        QuadobsError,
        match=r"\[truth\] /tf: no pose read \(no transform \* -> body; transforms seen: odom -> cf, world -> cf, world -> other\)",
    ):
        import_bag(bag, _map(ranges=ranges, truth={"topic": "/tf", "child_frame": "body"}))
    both = import_bag(bag, _map(ranges=ranges, truth={"topic": "/tf", "child_frame": "cf"}))
    assert both.truth.shape[0] == 20  # the body in two parents' frames: parent_frame picks one
    tf_map = {"topic": "/tf", "child_frame": "cf", "parent_frame": "world"}
    tf = import_bag(bag, _map(ranges=ranges, truth=tf_map))
    np.testing.assert_allclose(tf.truth[:, 1], np.arange(10.0))
    np.testing.assert_allclose(tf.truth[0, 4:], [math.cos(0.2), 0.0, 0.0, math.sin(0.2)])
    odom = import_bag(bag, _map(ranges=ranges, truth={"topic": "/odom"}))
    np.testing.assert_allclose(
        odom.truth[:, 1:4], np.column_stack([np.arange(10.0), np.full(10, 2.0), np.ones(10)])
    )
    point = import_bag(bag, _map(ranges=ranges, truth={"topic": "/point"}))
    assert point.truth_columns == ("time", "x", "y", "z") and point.truth.shape == (10, 4)
    with pytest.raises(
        QuadobsError, match=r"10 of 20 poses hold no attitude \(points beside poses\)"
    ):
        import_bag(bag, _map(ranges=ranges, truth={"topic": ["/point", "/odom"]}))
    with pytest.raises(QuadobsError, match=r"heading0 is for wheel odometry"):
        import_bag(
            bag,
            parse_topic_map({"anchors": {"3": [0.0, 0.0, 0.0]}, "heading0": 0.1, "ranges": ranges}),
        )


@pytest.mark.parametrize(
    "data, message",
    [
        ({"frame": "frd"}, "frame: expected 'enu' or 'ned'"),
        ({"imu": {"topic": "/i", "attitude": "yes"}}, r"\[imu\]: attitude: expected true or false"),
        ({"ranges": {"topic": "/r", "anchor_pattern": "anchor_"}}, "needs a group around the id"),
        ({"ranges": {"topic": "/r", "anchor_pattern": "("}}, r"anchor_pattern '\(':"),
        ({"ranges": {"topic": ["/r", "/r"]}}, "a list of distinct names"),
        ({"ranges": {"topic": "/r", "time": "bag"}}, r"\[ranges\]: time: expected"),
        ({"tdoa": {"topic": "/t", "sign": True}}, "sign: expected 1 or -1"),
    ],
)
def test_a_topic_map_checks_the_type_of_each_key(data, message):
    with pytest.raises(QuadobsError, match=message):
        parse_topic_map(data)


def test_a_bag_whose_every_range_is_marked_as_none_is_refused_saying_so(tmp_path):
    def build(T, h):
        for topic, msgtype, t, msg in _per_anchor(T, h, bad=False):
            msg.range = math.inf
            yield topic, msgtype, t, msg

    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(build(T, h)))
    topics = [f"/uwb/anchor_{a}/range" for a in sorted(ANCHORS)]
    with pytest.raises(
        QuadobsError, match=r"no range or TDOA left to replay \(\[ranges\] 40 not finite"
    ):
        import_bag(bag, _map(ranges={"topic": topics, "anchor": "topic"}))


def test_an_empty_topic_and_a_std_of_zero(tmp_path):
    def build(T, h):
        for k, (topic, msgtype, t, msg) in enumerate(_per_anchor(T, h, bad=False)):
            msg.field_of_view = 0.0 if k % 2 else 0.05  # a std field: 0 is "none stated"
            yield topic, msgtype, t, msg

    empty = [("/vicon/pose", "geometry_msgs/msg/PoseStamped")]
    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(build(T, h)), empty)
    topics = [f"/uwb/anchor_{a}/range" for a in sorted(ANCHORS)]
    ranges = {"topic": topics, "anchor": "topic", "std": "field_of_view"}
    with pytest.raises(QuadobsError, match=r"no message on \[truth\] /vicon/pose"):
        import_bag(bag, _map(ranges=ranges, truth={"topic": "/vicon/pose"}))
    notes: list[str] = []
    log = import_bag(bag, _map(ranges=ranges), notes)
    assert log.ranges.shape[0] == 40 and np.isnan(log.range_std).sum() == 20
    np.testing.assert_allclose(log.range_std[np.isfinite(log.range_std)], 0.05, rtol=1e-6)
    assert "[ranges] 20 kept with no std stated (the field 0 or NaN)" in notes


def test_wheel_odometry_from_odometry_messages_makes_a_planar_log(tmp_path):
    planar = {3: (0.0, 0.0), 7: (6.0, 0.0), 11: (6.0, 5.0), 12: (0.0, 5.0)}

    def build(T, h):
        V3, Q, P = (T[f"geometry_msgs/msg/{n}"] for n in ("Vector3", "Quaternion", "Point"))
        for k in range(40):
            t = T0 + 0.05 * k
            yaw = 0.3 + 0.2 * (t - T0)
            q = Q(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
            pose = T["geometry_msgs/msg/Pose"](
                position=P(x=1.0 + 0.1 * k, y=2.0, z=0.0), orientation=q
            )
            twist = T["geometry_msgs/msg/Twist"](
                linear=V3(x=0.4, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.2)
            )
            odom = T["nav_msgs/msg/Odometry"](
                header=h(t, "odom"), child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
            )  # fmt: skip
            yield ("/odom", "nav_msgs/msg/Odometry", t, odom)
            truth = T["geometry_msgs/msg/PoseStamped"](header=h(t, "world"), pose=pose)
            yield ("/vicon/pose", "geometry_msgs/msg/PoseStamped", t, truth)
            a = sorted(planar)[k % 4]
            yield (
                "/uwb/range",
                "sensor_msgs/msg/Range",
                t + 0.01,
                _range(T, h, t + 0.01, f"anchor_{a}", 2.0),
            )

    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(build(T, h)))
    streams = {"ranges": {"topic": "/uwb/range"}, "odometry": {"topic": "/odom"}}
    streams["truth"] = {"topic": "/vicon/pose"}
    anchors = {str(k): list(v) for k, v in planar.items()}
    with pytest.raises(QuadobsError, match=r"\[odometry\] needs heading0"):
        import_bag(bag, parse_topic_map({"anchors": anchors, **streams}))
    both = {**streams, "imu": {"topic": "/odom"}}
    with pytest.raises(QuadobsError, match=r"\[imu\] and \[odometry\]: a log holds one kind"):
        import_bag(bag, parse_topic_map({"anchors": anchors, "heading0": 0.3, **both}))
    log = import_bag(bag, parse_topic_map({"anchors": anchors, "heading0": 0.3, **streams}))
    assert (log.input_kind, log.dimension, log.heading0) == ("odometry", 2, 0.3)
    np.testing.assert_allclose(log.inputs[:, 1:], [[0.4, 0.2]] * 40)
    assert log.truth_columns == ("time", "x", "y", "heading")
    np.testing.assert_allclose(log.truth[:, 3], 0.3 + 0.2 * (log.truth[:, 0] - T0), atol=1e-9)
    back = read_log(write_log(log, tmp_path / "log"))
    assert back.input_kind == "odometry" and back.inputs.shape == (40, 3)


def test_inputs_or_a_truth_whose_every_reading_is_marked_as_none_are_refused_saying_so(tmp_path):
    def build(T, h):
        yield from _per_anchor(T, h, bad=False)
        P = T["geometry_msgs/msg/Point"]
        for k in range(20):
            t = T0 + 0.05 * k
            yield ("/imu", "sensor_msgs/msg/Imu", t, _imu(T, h(t), math.nan, 9.8))
            point = T["geometry_msgs/msg/PointStamped"](
                header=h(t, "world"), point=P(x=math.nan, y=0.0, z=0.0)
            )
            yield ("/point", "geometry_msgs/msg/PointStamped", t, point)

    bag = _ros2_bag(tmp_path / "b", lambda T, h: list(build(T, h)))
    ranges = {"topic": [f"/uwb/anchor_{a}/range" for a in sorted(ANCHORS)], "anchor": "topic"}
    with pytest.raises(
        QuadobsError, match=r"\[imu\] fewer than two readings left \(20 left out: not finite\)"
    ):
        import_bag(bag, _map(ranges=ranges, imu={"topic": "/imu"}))
    with pytest.raises(
        QuadobsError, match=r"\[truth\] /point: no pose read \(20 left out: not finite\)"
    ):
        import_bag(bag, _map(ranges=ranges, truth={"topic": "/point"}))


def test_a_topic_map_states_meta_keys_as_meta_csv_would(tmp_path):
    _files(tmp_path)
    write_bag(tmp_path / "flight.bag", ros1=True)
    anchors = {str(k): list(v) for k, v in ANCHORS.items()}
    stated = {"tag_x": -0.012, "tag_y": 0.001, "tag_z": 0.091, "range_errors": "nlos"}
    m = parse_topic_map(
        {
            "anchors": anchors,
            **stated,
            "ranges": {"topic": "/uwb/range"},
            "truth": {"topic": "/vicon/pose"},
        }
    )
    log = import_bag(tmp_path / "flight.bag", m)
    np.testing.assert_array_equal(log.truth_lever, [-0.012, 0.001, 0.091])
    assert log.range_errors == "nlos"
    with pytest.raises(
        QuadobsError, match=r"key accel_noise: '-1' is not a positive finite number"
    ):
        parse_topic_map({"anchors": anchors, "accel_noise": -1})
