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
            ["--topic", "imu=/uwb/range", "--topic", "ranges=/uwb/range"],
            "sensor_msgs/msg/Range, expected sensor_msgs/Imu",
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
