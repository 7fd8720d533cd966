"""CSV files of other layouts, with their columns and units named in a TOML map, imported
into the open log format: each unit and order stated is undone exactly."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.logs import read_log
from quadobs.testbed.logs.convert import odometry_from_wheels
from quadobs.testbed.logs.csv_map import import_csv, load_csv_map, parse_csv_map

ANCHORS = {3: (0.0, 0.0, 0.2), 7: (6.0, 0.0, 2.5), 11: (6.0, 5.0, 0.3), 12: (0.0, 5.0, 2.4)}
T0 = 1_700_000_000.0


def _position(t):
    return np.column_stack([3.0 + np.cos(t), 2.0 + np.sin(t), 1.0 + 0.1 * t])


def _euler_quaternion(roll, pitch, yaw):
    """``Rz(yaw) Ry(pitch) Rx(roll)`` as ``w, x, y, z``, composed from the axis rotations."""

    def mul(a, b):
        w1, x1, y1, z1 = a
        w2, x2, y2, z2 = b
        return np.array(
            [
                w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            ]
        )

    qz = [math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
    qy = [math.cos(pitch / 2), 0, math.sin(pitch / 2), 0]
    qx = [math.cos(roll / 2), math.sin(roll / 2), 0, 0]
    return mul(mul(qz, qy), qx)


def _anchors_file(folder):
    (folder / "anchors.csv").write_text(
        "id,x,y,z\n" + "".join(f"{i},{x},{y},{z}\n" for i, (x, y, z) in ANCHORS.items())
    )


FLIGHT_MAP = """
name = "csv-flight"
anchors = "anchors.csv"
accel_noise = 0.02
range_errors = "nlos"
[ranges]
file = "uwb.csv"
delimiter = ";"
time = "stamp_ms"
time_unit = "ms"
anchor = "node"
value = "dist_cm"
unit = "cm"
std = 5.0
[imu]
file = "imu.csv"
time = "t"
accel = ["ax_g", "ay_g", "az_g"]
accel_unit = "g"
gyro = ["gx", "gy", "gz"]
gyro_unit = "deg/s"
[attitude]
file = "ahrs.csv"
time = "t"
euler = {roll = "r", pitch = "p", yaw = "y"}
angle_unit = "deg"
[truth]
file = "mocap.txt"
delimiter = " "
names = ["time", "px", "py", "pz", "qx", "qy", "qz", "qw"]
time = "time"
time_offset = -0.5
position = ["px", "py", "pz"]
unit = "mm"
quaternion = {x = "qx", y = "qy", z = "qz", w = "qw"}
"""


def _flight_files(folder) -> dict:
    """A 2-s flight's files in four layouts and its values in SI, for the comparison."""
    _anchors_file(folder)
    ids = sorted(ANCHORS)
    t_r = T0 + 0.003 + 0.01 * np.arange(200)
    a = np.array([ANCHORS[ids[k % 4]] for k in range(200)])
    rho = np.linalg.norm(_position(t_r - T0) - a, axis=1)
    lines = ["stamp_ms;node;dist_cm"]
    lines += [
        f"{t * 1e3:.17g};anchor_{ids[k % 4]};{r * 100:.17g}"
        for k, (t, r) in enumerate(zip(t_r, rho))
    ]
    (folder / "uwb.csv").write_text("\n".join(lines) + "\n")
    t_i = T0 + 0.002 * np.arange(1000)
    acc, gyro = (
        np.column_stack([0.1 * np.ones(1000), np.zeros(1000), np.ones(1000)]),
        np.ones((1000, 3)),
    )
    cells = [
        f"{t:.17g},{x:.17g},{y:.17g},{z:.17g},{p:.17g},{q:.17g},{r:.17g}"
        for t, (x, y, z), (p, q, r) in zip(t_i, acc, gyro * 30)
    ]
    cells[10] = f"{t_i[10]:.17g},,0,1,30,30,30"  # an empty cell: that row left out
    (folder / "imu.csv").write_text("t,ax_g,ay_g,az_g,gx,gy,gz\n" + "\n".join(cells) + "\n")
    euler = [(10.0, -5.0, 120.0), (20.0, 5.0, -60.0)]
    (folder / "ahrs.csv").write_text(
        "t,r,p,y\n" + "".join(f"{T0 + k:.17g},{r},{p},{y}\n" for k, (r, p, y) in enumerate(euler))
    )
    t_m = T0 + 0.5 + 0.01 * np.arange(200)  # the truth's clock 0.5 s ahead
    p = _position(t_m - 0.5 - T0) * 1e3
    q = np.array([0.0, 0.0, math.sin(0.2), math.cos(0.2)])  # x, y, z, w
    (folder / "mocap.txt").write_text(
        "".join(
            f"{t:.17g} {x:.17g} {y:.17g} {z:.17g} 0.0 0.0 {q[2]:.17g} {q[3]:.17g}\n"
            for t, (x, y, z) in zip(t_m, p)
        )
    )
    (folder / "map.toml").write_text(FLIGHT_MAP)
    return {"rho": rho, "t_r": t_r, "euler": euler}


def test_a_flight_in_other_units_and_orders_imports_exactly(tmp_path):
    want = _flight_files(tmp_path)
    notes: list[str] = []
    log = import_csv(load_csv_map(tmp_path / "map.toml"), notes)
    assert (log.name, log.input_kind, log.dimension, log.range_errors) == (
        "csv-flight",
        "imu_body",
        3,
        "nlos",
    )
    assert log.accel_noise == 0.02
    np.testing.assert_allclose(log.ranges[:, 0], want["t_r"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(log.ranges[:, 2], want["rho"], rtol=1e-12)
    assert list(log.ranges[:5, 1]) == [3, 7, 11, 12, 3]
    np.testing.assert_allclose(log.range_std, 0.05)
    assert log.inputs.shape == (999, 7) and notes == [
        "[imu] 1 rows left out: a cell empty or not finite"
    ]
    np.testing.assert_allclose(log.inputs[0, 1:4], [0.980665, 0.0, 9.80665])
    np.testing.assert_allclose(log.inputs[0, 4:], math.radians(30.0))
    for row, angles in zip(log.attitude, want["euler"]):
        q = _euler_quaternion(*np.radians(angles))
        np.testing.assert_allclose(row[1:] * np.sign(row[1] * q[0]), q, atol=1e-12)
    np.testing.assert_allclose(log.truth[:, 0], T0 + 0.01 * np.arange(200), atol=1e-6)
    np.testing.assert_allclose(log.truth[:, 1:4], _position(0.01 * np.arange(200)), atol=1e-9)
    np.testing.assert_allclose(log.truth[0, 4:], [math.cos(0.2), 0.0, 0.0, math.sin(0.2)])


ROBOT_MAP = """
anchors = "anchors.csv"
heading0 = 1.5
tag_height = 0.3
[ranges]
file = "uwb_wide.csv"
time = "t"
columns = {3 = "d3", 7 = "d7", 11 = "d11", 12 = "d12"}
[odometry]
file = "wheels.csv"
time = "t"
left = "vl"
right = "vr"
speed_unit = "mm/s"
track = 0.25
[truth]
file = "truth.csv"
time = "t"
position = ["x", "y"]
heading = "yaw_deg"
angle_unit = "deg"
"""


def _robot_files(folder) -> int:
    """A robot's wheels in mm/s, ranges one column per anchor (two of four a row), a truth
    with its heading in degrees; the number of ranges."""
    _anchors_file(folder)
    t = 0.1 * np.arange(50)
    rows = []
    for k, tk in enumerate(t):
        cells = ["", "", "", ""]
        for c in (k % 4, (k + 1) % 4):
            cells[c] = repr(2.0 + 0.01 * k + c)
        rows.append(f"{tk:.17g}," + ",".join(cells))
    (folder / "uwb_wide.csv").write_text("t,d3,d7,d11,d12\n" + "\n".join(rows) + "\n")
    (folder / "wheels.csv").write_text(
        "t,vl,vr\n" + "".join(f"{tk:.17g},{200.0 + k},{300.0}\n" for k, tk in enumerate(t))
    )
    (folder / "truth.csv").write_text(
        "t,x,y,yaw_deg\n" + "".join(f"{tk:.17g},{tk},1.0,{90.0 + 10 * tk}\n" for tk in t)
    )
    (folder / "map.toml").write_text(ROBOT_MAP)
    return 2 * t.size


def test_a_robot_with_wheels_and_one_range_column_per_anchor_imports_exactly(tmp_path):
    count = _robot_files(tmp_path)
    log = import_csv(load_csv_map(tmp_path / "map.toml"))
    assert (log.input_kind, log.dimension, log.heading0, log.tag_height) == (
        "odometry",
        2,
        1.5,
        0.3,
    )
    np.testing.assert_allclose(log.anchor_heights, [0.2, 2.5, 0.3, 2.4])
    assert log.ranges.shape == (count, 3)
    assert list(log.ranges[:4, 1]) == [3, 7, 7, 11]  # by time, then column
    np.testing.assert_allclose(log.ranges[:4, 2], [2.0, 3.0, 3.01, 4.01])
    t = 0.1 * np.arange(50)
    want = odometry_from_wheels(t, 0.2 + 1e-3 * np.arange(50), np.full(50, 0.3), 0.25)
    np.testing.assert_allclose(log.inputs, want, rtol=1e-12)
    assert log.truth_columns == ("time", "x", "y", "heading")
    np.testing.assert_allclose(log.truth[:, 3], np.radians(90.0 + 10 * t), atol=1e-12)


def test_the_command_line_writes_a_log_that_reads_back(tmp_path, capsys):
    count = _robot_files(tmp_path)
    assert main(["import-csv", str(tmp_path / "map.toml"), "--out", str(tmp_path / "log")]) == 0
    assert f"{count} ranges" in capsys.readouterr().out
    log = read_log(tmp_path / "log")
    assert log.name == "map" and log.ranges.shape == (count, 3)
    assert (
        main(
            [
                "import-csv",
                str(tmp_path / "map.toml"),
                "--out",
                str(tmp_path / "log"),
                "--name",
                "r",
            ]
        )
        == 0
    )
    assert read_log(tmp_path / "log").name == "r"


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            ('value = "dist_cm"', 'value = "dist"'),
            "no column 'dist' ([ranges] value; its columns: stamp_ms, node, dist_cm)",
        ),
        (('unit = "cm"', 'unit = "inch"'), "[ranges] unit: expected one of m, cm, mm, got 'inch'"),
        (('gyro_unit = "deg/s"', 'gyro_rate = "deg/s"'), "[imu] unknown key 'gyro_rate'"),
        (('w = "qw"', 'W = "qw"'), '[truth] quaternion: expected a table {w = "column"'),
        (
            ("time_offset = -0.5", "time_offset = 1000.0"),
            "not one clock (time_offset = SECONDS in [truth]",
        ),
        (("anchors.csv", "nowhere.csv"), "anchors file"),
        (("std = 5.0", "std = 0.05"), "[ranges] std: a median of 0.0005 m"),
        (
            ('unit = "cm"', 'unit = "mm"'),
            "[ranges] uwb.csv, column range: ranges to two anchors within 1 s sum to a median",
        ),
        (
            ('accel = ["ax_g", "ay_g", "az_g"]', 'accel = ["ax_g", "ay_g", "-az_g"]'),
            "does not keep gravity",
        ),
        (
            ('unit = "mm"', 'unit = "m"'),
            "as imported, the replay would refuse it: csv-flight: [truth] mocap.txt: the truth lies a median",
        ),
        (
            ('quaternion = {x = "qx"', 'tag_z = 0.1\nquaternion = {x = "qx"'),
            "[truth] unknown key 'tag_z' (a key of the map's top level: write it before the first [table])",
        ),
        (('file = "imu.csv"', 'file = ["imu.csv"]'), "[imu] file: expected text (a file's name"),
        (
            ('accel_unit = "g"', 'accel_unit = "m/s^2"'),
            "map.toml: as imported, the replay would refuse it: csv-flight: [imu] imu.csv, columns ax,ay,az",
        ),
        (('file = "imu.csv"', 'file = "imu2.csv"'), "[imu] file 'imu2.csv': not found"),
        (
            ('gyro = ["gx", "gy", "gz"]', 'gyro = ["gx", "gy"]'),
            "[imu] gyro: expected a list of 3 column names",
        ),
        (
            ("accel_noise = 0.02", "accel_noise = -1"),
            "key accel_noise: '-1' is not a positive finite number",
        ),
        (("accel_noise = 0.02", "heading0 = 1.0"), "heading0 is for wheel odometry"),
        (
            ('anchor = "node"', 'columns = {3 = "x"}'),
            "[ranges] value is not of (columns): leave it out",
        ),
    ],
)
def test_a_bad_map_is_one_line_with_status_2(tmp_path, capsys, edit, message):
    _flight_files(tmp_path)
    text = (tmp_path / "map.toml").read_text()
    assert edit[0] in text
    (tmp_path / "map.toml").write_text(text.replace(edit[0], edit[1], 1))
    assert main(["import-csv", str(tmp_path / "map.toml"), "--out", str(tmp_path / "log")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "log").exists()


def test_a_cell_that_is_not_a_number_is_named_by_file_line_and_column(tmp_path):
    _flight_files(tmp_path)
    text = (tmp_path / "imu.csv").read_text().splitlines()
    text[7] = "1700000000.012,0.1,0,one,30,30,30"
    (tmp_path / "imu.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(QuadobsError, match=r"imu.csv, line 8, column az_g: 'one' is not a number"):
        import_csv(load_csv_map(tmp_path / "map.toml"))


def test_a_map_refuses_what_it_cannot_import(tmp_path):
    anchors = {"anchors": {"1": [0.0, 0.0], "2": [5.0, 0.0]}}
    ranges = {"file": "r.csv", "time": "t", "anchor": "a", "value": "r"}
    with pytest.raises(QuadobsError, match=r"no \[ranges\] or \[tdoa\] table"):
        parse_csv_map(anchors)
    with pytest.raises(QuadobsError, match=r"unknown key 'ranegs'"):
        parse_csv_map({**anchors, "ranegs": ranges})
    with pytest.raises(QuadobsError, match=r"\[odometry\] needs heading0"):
        parse_csv_map(
            {
                **anchors,
                "ranges": ranges,
                "odometry": {"file": "o.csv", "time": "t", "speed": "v", "yaw_rate": "w"},
            }
        )
    with pytest.raises(
        QuadobsError, match=r"\[odometry\] left, right, track together: track missing"
    ):
        parse_csv_map(
            {
                **anchors,
                "heading0": 0.0,
                "ranges": ranges,
                "odometry": {"file": "o.csv", "time": "t", "left": "l", "right": "r"},
            }
        )
    with pytest.raises(QuadobsError, match=r"anchors missing"):
        parse_csv_map({"ranges": ranges})
    with pytest.raises(QuadobsError, match=r"\[ranges\] time missing"):
        parse_csv_map({**anchors, "ranges": {k: v for k, v in ranges.items() if k != "time"}})
    (tmp_path / "r.csv").write_text("t,a,r\n0.0,1,2.0\n0.1,9,2.0\n")
    with pytest.raises(QuadobsError, match=r"anchor id 9 not among the anchors \(1, 2\)"):
        import_csv(parse_csv_map({**anchors, "ranges": ranges}, base=tmp_path))


def test_the_docs_maps_parse(tmp_path):
    import re
    import tomllib
    from pathlib import Path

    page = (Path(__file__).parents[2] / "docs" / "replaying-your-data.md").read_text()
    section = page.split("## From CSV files of another layout")[1].split("\n## ")[0]
    blocks = [tomllib.loads(b) for b in re.findall(r"```toml\n(.*?)```", section, re.S)]
    assert len(blocks) == 3
    _anchors_file(tmp_path)
    robot = parse_csv_map(blocks[0], base=tmp_path)
    assert set(robot.streams) == {"ranges", "odometry", "truth"}
    assert (
        robot.streams["truth"]["time_unit"] == "s" and robot.streams["ranges"]["time_unit"] == "ms"
    )
    ranges = {"file": "r.csv", "time": "t", "anchor": "a", "value": "r"}
    flight = parse_csv_map({**blocks[1], "anchors": "anchors.csv", "ranges": ranges}, base=tmp_path)
    assert flight.streams["imu"]["accel_unit"] == "g"
    _kinematic_robot(tmp_path)  # its survey.txt is the docs' layout
    surveyed = parse_csv_map({**blocks[2], "ranges": ranges}, base=tmp_path)
    np.testing.assert_allclose(surveyed.anchors[7], ANCHORS[7])


def test_one_file_of_every_sensor_each_row_filled_for_one(tmp_path):
    """A dataset that writes every sensor into one file, each row filling one sensor's
    columns (its own time column among them): each stream reads its rows, the others' skipped
    and said."""
    _anchors_file(tmp_path)
    header = "t_tdoa,idA,idB,tdoa_meas,t_imu,acc_x,acc_y,acc_z,gyro_x,gyro_y,gyro_z,t_pose,x,y,z\n"
    rows = []
    for k in range(300):
        t = 0.01 * k
        if k % 3 == 0:
            rows.append(f"{t},3,{(7, 11, 12)[k % 9 // 3]},{0.01 * k},,,,,,,,,,,")
        elif k % 3 == 1:
            rows.append(f",,,,{t},0.0,0.0,1.0,0.0,0.0,{k},,,,")
        else:
            rows.append(f",,,,,,,,,,,{t},{k},2.0,1.0")
    (tmp_path / "all.csv").write_text(header + "\n".join(rows) + "\n")
    (tmp_path / "map.toml").write_text(
        'anchors = "anchors.csv"\n'
        '[tdoa]\nfile = "all.csv"\ntime = "t_tdoa"\nanchor_i = "idA"\nanchor_j = "idB"\n'
        'value = "tdoa_meas"\n'
        '[imu]\nfile = "all.csv"\ntime = "t_imu"\naccel = ["acc_x", "acc_y", "acc_z"]\n'
        'accel_unit = "g"\ngyro = ["gyro_x", "gyro_y", "gyro_z"]\ngyro_unit = "deg/s"\n'
        '[truth]\nfile = "all.csv"\ntime = "t_pose"\nposition = ["x", "y", "z"]\nunit = "cm"\n'
    )
    notes: list[str] = []
    log = import_csv(load_csv_map(tmp_path / "map.toml"), notes)
    assert (
        log.tdoa.shape == (100, 4) and log.inputs.shape == (100, 7) and log.truth.shape == (100, 4)
    )
    assert list(log.tdoa[:3, 2]) == [7, 11, 12] and np.all(log.tdoa[:, 1] == 3)
    np.testing.assert_allclose(log.inputs[:2, 6], np.radians([1.0, 4.0]))
    np.testing.assert_allclose(log.truth[:2, 1], [0.02, 0.05])
    assert notes == [
        f"[{s}] 200 rows with none of its cells filled skipped (other streams' rows, where one "
        "file holds several)"
        for s in ("imu", "tdoa", "truth")
    ]


KINEMATIC_MAP = """
anchors = {file = "survey.txt", delimiter = "whitespace", id = "name", x = "X", y = "Y", z = "Z", unit = "mm"}
heading0 = 1.5
[ranges]
file = "uwb.csv"
time = "t"
anchor = "anchor"
value = "range"
[odometry]
file = "wheels.csv"
time = "t"
left = "left_degps"
right = "right_degps"
rate_unit = "deg/s"
wheel_radius = 0.05
left_sign = -1
track = 0.25
[truth]
file = "mocap.txt"
delimiter = "whitespace"
time = "when"
time_unit = "iso8601"
position = ["x", "y"]
heading = "yaw"
"""


def _kinematic_robot(folder) -> dict:
    """A robot's truth integrated from its speed and yaw rate (held over each 0.05 s), its
    wheels' rates in deg/s with the left motor mirrored (counting backwards), ranges to
    anchors surveyed in mm with names, a motion capture aligned by spaces with ISO 8601 times."""
    import datetime

    dt, n = 0.05, 400
    t = dt * np.arange(n)
    v, w = 0.3 + 0.1 * np.sin(t), 0.6 * np.cos(0.4 * t)
    psi = 1.5 + np.concatenate([[0.0], np.cumsum(w[:-1] * dt)])
    mid = psi + 0.5 * w * dt
    step = np.column_stack([v * dt * np.cos(mid), v * dt * np.sin(mid)])
    xy = np.vstack([[1.0, 1.0], np.cumsum(step, axis=0)[:-1] + 1.0])
    left, right = (v - w * 0.125) / 0.05, (v + w * 0.125) / 0.05
    (folder / "wheels.csv").write_text(
        "t,left_degps,right_degps\n"
        + "".join(
            f"{a:.17g},{-math.degrees(b):.17g},{math.degrees(c):.17g}\n"
            for a, b, c in zip(t, left, right)
        )
    )
    (folder / "survey.txt").write_text(
        "name      X        Y       Z\n"
        + "".join(
            f"  anchor_{i}\t{x * 1e3:g}   {y * 1e3:g}  {z * 1e3:g}  \n"
            for i, (x, y, z) in ANCHORS.items()
        )
    )
    epoch = datetime.datetime(2026, 11, 28, 10, 0, tzinfo=datetime.UTC)
    stamps = [(epoch + datetime.timedelta(seconds=float(s))).isoformat() for s in t]
    (folder / "mocap.txt").write_text(
        "when   x   y   yaw\n"
        + "".join(f"{s}   {p[0]:.17g} {p[1]:.17g}   {h:.17g}\n" for s, p, h in zip(stamps, xy, psi))
    )
    ids = sorted(ANCHORS)
    anchors = np.array([ANCHORS[i][:2] for i in ids])
    h = np.arange(n) % 4
    heights = np.array([ANCHORS[i][2] for i in ids])[h]
    rho = np.hypot(np.linalg.norm(xy - anchors[h], axis=1), heights)
    t0 = epoch.timestamp()
    (folder / "uwb.csv").write_text(
        "t,anchor,range\n"
        + "".join(f"{t0 + a:.17g},anchor_{ids[k]},{r:.17g}\n" for a, k, r in zip(t, h, rho))
    )
    (folder / "map.toml").write_text(
        KINEMATIC_MAP.replace(
            'file = "wheels.csv"\ntime = "t"',
            'file = "wheels.csv"\ntime = "t"\ntime_offset = ' + repr(t0),
        )
    )
    return {"v": v, "w": w, "t": t0 + t}


def test_wheel_rates_a_mirrored_motor_a_survey_file_and_iso_times(tmp_path):
    want = _kinematic_robot(tmp_path)
    log = import_csv(load_csv_map(tmp_path / "map.toml"))
    np.testing.assert_allclose(log.inputs[:, 1], want["v"], rtol=1e-12)
    np.testing.assert_allclose(log.inputs[:, 2], want["w"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(log.anchor_heights, [0.2, 2.5, 0.3, 2.4])
    np.testing.assert_allclose(log.beacons[1], [6.0, 0.0])
    np.testing.assert_allclose(log.truth[:, 0], want["t"], atol=1e-6)


@pytest.mark.parametrize(
    "edits, note",
    [
        ((), None),
        (
            (("left_sign = -1", "left_sign = 1"),),
            "the odometry's distances (speed) are 0.00949 times",
        ),
        (
            (
                ('left = "left_degps"', 'left = "right_degps"\nright_sign = -1'),
                ('right = "right_degps"', 'right = "left_degps"'),
                ("left_sign = -1", "left_sign = 1"),
            ),
            "the odometry's turns (yaw_rate) are -1 times the truth's",
        ),
        ((("track = 0.25", "track = 0.5"),), "turns (yaw_rate) are 0.5 times the truth's"),
        ((("heading0 = 1.5", "heading0 = 85.9"),), "heading0 85.9 lies beyond 2 pi"),
    ],
)
def test_the_import_says_where_the_odometry_disagrees_with_the_truth(tmp_path, capsys, edits, note):
    _kinematic_robot(tmp_path)
    text = (tmp_path / "map.toml").read_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new)
    (tmp_path / "map.toml").write_text(text)
    assert main(["import-csv", str(tmp_path / "map.toml"), "--out", str(tmp_path / "log")]) == 0
    out = capsys.readouterr().out
    if note is None:
        assert "note:" not in out, out
    else:
        assert "note: (replay) against the truth, " in out and note in out, out


def test_zero_ranges_repeated_rows_and_a_byte_order_mark(tmp_path, capsys):
    """A file of one column per anchor that writes 0 for "not ranged" imports, the replay's
    note saying it leaves them out; a repeated odometry row is left out and said, two rows of
    one time with other values refused naming the file; a map saved with a BOM reads."""
    _robot_files(tmp_path)
    rows = (tmp_path / "uwb_wide.csv").read_text().splitlines()
    filled = [rows[0]] + [",".join(c or "0" for c in r.split(",")) for r in rows[1:]]
    (tmp_path / "uwb_wide.csv").write_text("\n".join(filled) + "\n")
    wheels = (tmp_path / "wheels.csv").read_text().splitlines()
    (tmp_path / "wheels.csv").write_text("\n".join(wheels[:5] + [wheels[4]] + wheels[5:]) + "\n")
    map_text = (tmp_path / "map.toml").read_text()
    (tmp_path / "map.toml").write_text("\ufeff" + map_text, encoding="utf-8")
    assert main(["import-csv", str(tmp_path / "map.toml"), "--out", str(tmp_path / "log")]) == 0
    out = capsys.readouterr().out
    assert "note: [odometry] 1 rows repeated, left out" in out
    assert "note: (replay) ranges of 0 m (a radio's failed exchange), left out: 100" in out
    (tmp_path / "wheels.csv").write_text(
        "\n".join(wheels[:5] + [wheels[4].replace(",300.0", ",301.0")] + wheels[5:]) + "\n"
    )
    assert main(["import-csv", str(tmp_path / "map.toml"), "--out", str(tmp_path / "log2")]) == 0
    out = capsys.readouterr().out
    assert "note: [odometry] 1 rows share their time with the next and hold other values" in out
    assert read_log(tmp_path / "log2").inputs.shape[0] == 50


def test_anchor_ids_in_text():
    from quadobs.testbed.logs.importing import anchor_id

    assert [anchor_id(v, "", "x") for v in ("anchor_12", "A3", "0x1a", " 0XFF ", 7.0)] == [
        12,
        3,
        26,
        255,
        7,
    ]
    assert anchor_id("tag_2/anchor_0x1f", r"anchor_(0x[0-9a-f]+)", "x") == 31
    with pytest.raises(QuadobsError, match="holds 2 numbers"):
        anchor_id("tag_2/anchor_5", "", "x")


def test_a_row_of_another_width_a_repeated_column_name_and_coarse_stamps(tmp_path):
    _flight_files(tmp_path)
    text = (tmp_path / "imu.csv").read_text().splitlines()
    bad = text[:12] + [text[12] + ",9"] + text[13:]
    (tmp_path / "imu.csv").write_text("\n".join(bad) + "\n")
    with pytest.raises(QuadobsError, match=r"imu.csv, line 13: 8 cells, where the header names 7"):
        import_csv(load_csv_map(tmp_path / "map.toml"))
    (tmp_path / "imu.csv").write_text("\n".join([text[0].replace("gz", "gy")] + text[1:]) + "\n")
    with pytest.raises(QuadobsError, match=r"imu.csv: 2 columns named 'gy' \(\[imu\] gyro\[1\]"):
        import_csv(load_csv_map(tmp_path / "map.toml"))
    coarse = [text[0]]
    for k, row in enumerate(text[1:]):
        cells = row.split(",")
        coarse.append(",".join([f"{float(cells[0]):.1f}", *cells[1:6], str(30 + k)]))
    (tmp_path / "imu.csv").write_text("\n".join(coarse) + "\n")
    with pytest.raises(
        QuadobsError,
        match=r"978 of 999 rows share their time with the row before and hold other values",
    ):
        import_csv(load_csv_map(tmp_path / "map.toml"))


@pytest.mark.parametrize("scale, words", [(0.1, "sum to a median"), (10.0, "differ by a median")])
def test_ranges_whose_pairs_break_the_triangle_inequality_are_refused(scale, words):
    """Exact ranges of a tag circling among four anchors, scaled: a point's two distances sum
    to at least the anchors' separation and differ by at most it."""
    from quadobs.testbed.logs import RangeLog
    from quadobs.testbed.logs.replay import check_range_units

    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    t = 0.1 * np.arange(200)
    p = np.column_stack([5 + 3 * np.cos(0.3 * t), 5 + 3 * np.sin(0.3 * t)])
    h = np.arange(t.size) % 4
    rho = np.linalg.norm(p - anchors[h], axis=1)
    log = RangeLog(
        "r",
        np.arange(4),
        anchors,
        np.column_stack([t, h, rho]),
        np.empty((0, 1)),
        math.nan,
        input_kind="none",
    )
    check_range_units(log)
    scaled = RangeLog(
        "r",
        np.arange(4),
        anchors,
        np.column_stack([t, h, scale * rho]),
        np.empty((0, 1)),
        math.nan,
        input_kind="none",
    )
    with pytest.raises(QuadobsError, match=words):
        check_range_units(scaled)


def test_a_truth_with_its_velocity(tmp_path):
    _robot_files(tmp_path)
    rows = (tmp_path / "truth.csv").read_text().splitlines()
    with_v = [rows[0] + ",vx_mm,vy_mm"] + [r + ",1000.0,-20.0" for r in rows[1:]]
    (tmp_path / "truth.csv").write_text("\n".join(with_v) + "\n")
    text = (tmp_path / "map.toml").read_text()
    (tmp_path / "map.toml").write_text(text + 'velocity = ["vx_mm", "-vy_mm"]\nunit = "m"\n')
    m = load_csv_map(tmp_path / "map.toml")
    log = import_csv(m)
    assert log.truth_columns == ("time", "x", "y", "heading", "vx", "vy")
    np.testing.assert_allclose(log.truth[:, 4:], [[1000.0, 20.0]] * 50)
    back = read_log(
        __import__("quadobs.testbed.logs", fromlist=["write_log"]).write_log(log, tmp_path / "log")
    )
    assert back.truth_columns == log.truth_columns


def test_one_range_file_per_anchor(tmp_path):
    count = _robot_files(tmp_path)
    wide = import_csv(load_csv_map(tmp_path / "map.toml"))
    for i in sorted(ANCHORS):
        own = wide.ranges[wide.ranges[:, 1] == i]
        (tmp_path / f"a{i}.csv").write_text(
            "t,d\n" + "".join(f"{t:.17g},{r:.17g}\n" for t, _, r in own)
        )
    text = (tmp_path / "map.toml").read_text()
    start = text.index("[ranges]")
    end = text.index("[odometry]")
    files = ", ".join(f'{i} = "a{i}.csv"' for i in sorted(ANCHORS))
    text = text[:start] + f'[ranges]\nfiles = {{{files}}}\ntime = "t"\nvalue = "d"\n' + text[end:]
    (tmp_path / "map.toml").write_text(text)
    log = import_csv(load_csv_map(tmp_path / "map.toml"))
    assert log.ranges.shape == (count, 3)
    np.testing.assert_array_equal(np.sort(log.ranges, axis=0), np.sort(wide.ranges, axis=0))


def _wrote_map(folder, edits) -> Path:
    text = (folder / "map.toml").read_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new)
    (folder / "map.toml").write_text(text)
    return folder / "map.toml"


def test_what_a_second_review_found_is_read_or_refused_in_one_line(tmp_path):
    """ISO times with empty cells (other sensors' rows) and blanks around; a std column whose
    0 states none; a range row written twice; ids beyond 2^53; a truth of a header alone; a
    unit key the odometry's layout does not read; a file that is not UTF-8 text."""
    import datetime

    _anchors_file(tmp_path)
    t0 = datetime.datetime(2026, 11, 28, tzinfo=datetime.UTC)
    lines = ["stamp,anchor,range,sd,x,y,z"]
    for k in range(60):
        stamp = (t0 + datetime.timedelta(seconds=0.1 * k)).isoformat()
        lines.append(
            f" {stamp} ,anchor_{(3, 7, 11, 12)[k % 4]},{4.0 + 0.01 * k},{0 if k % 2 else 0.1},,,"
        )
        lines.append(f" {stamp} ,,,,3.0,2.0,1.0")
    lines.append(lines[1])  # a range written twice
    (tmp_path / "all.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "map.toml").write_text(
        'anchors = "anchors.csv"\n[ranges]\nfile = "all.csv"\ntime = "stamp"\ntime_unit = "iso8601"\n'
        'anchor = "anchor"\nvalue = "range"\nstd = "sd"\n'
        '[truth]\nfile = "all.csv"\ntime = "stamp"\ntime_unit = "iso8601"\nposition = ["x", "y", "z"]\n'
    )
    notes: list[str] = []
    log = import_csv(load_csv_map(tmp_path / "map.toml"), notes)
    assert log.ranges.shape == (60, 3) and log.truth.shape == (60, 4)
    assert np.isnan(log.range_std[1::2]).all() and np.all(log.range_std[::2] == 0.1)
    assert "[ranges] 1 rows repeated, left out" in notes

    def ranges_of(name: str):
        ranges = {"file": name, "time": "t", "anchor": "anchor", "value": "range"}
        return parse_csv_map({"anchors": "anchors.csv", "ranges": ranges}, base=tmp_path)

    (tmp_path / "big.csv").write_text("t,anchor,range\n0.0,0xDECA000000000A01,4.0\n")
    with pytest.raises(QuadobsError, match=r"is beyond 2\^53"):
        import_csv(ranges_of("big.csv"))
    (tmp_path / "t.csv").write_text("t,x,y,z\n")
    text = (tmp_path / "map.toml").read_text()
    (tmp_path / "map.toml").write_text(
        text.replace('[truth]\nfile = "all.csv"', '[truth]\nfile = "t.csv"').replace(
            'time = "stamp"\ntime_unit = "iso8601"\nposition', 'time = "t"\nposition'
        )
    )
    with pytest.raises(QuadobsError, match=r"\[truth\] t.csv: no row read"):
        import_csv(load_csv_map(tmp_path / "map.toml"))
    (tmp_path / "u16.csv").write_bytes("t,anchor,range\n".encode("utf-16"))
    with pytest.raises(QuadobsError, match=r"u16.csv: UTF-16 text: save it as UTF-8"):
        import_csv(ranges_of("u16.csv"))


def test_a_unit_key_the_odometry_does_not_read_is_refused(tmp_path):
    _robot_files(tmp_path)
    with pytest.raises(
        QuadobsError, match=r"\[odometry\] angle_unit is not read with \(left, right, track\)"
    ):
        load_csv_map(
            _wrote_map(
                tmp_path, [('speed_unit = "mm/s"', 'speed_unit = "mm/s"\nangle_unit = "deg"')]
            )
        )


def test_a_range_row_written_twice_without_a_std_is_left_out_once(tmp_path):
    _robot_files(tmp_path)
    rows = (tmp_path / "uwb_wide.csv").read_text().splitlines()
    (tmp_path / "uwb_wide.csv").write_text("\n".join(rows[:4] + [rows[3]] + rows[4:]) + "\n")
    notes: list[str] = []
    log = import_csv(load_csv_map(tmp_path / "map.toml"), notes)
    assert log.ranges.shape == (100, 3) and "[ranges] 2 rows repeated, left out" in notes


def test_one_file_of_several_message_kinds_told_by_a_column(tmp_path):
    """A text log whose lines are messages of several kinds and widths, the first cell naming
    the kind (``range2``, ``odom2diff``, ``gt2``): each stream selects its lines."""
    _anchors_file(tmp_path)
    lines = ["# a robot's log"]
    for k in range(40):
        t = 0.1 * k
        lines.append(f"range2 {t:.1f}  {3.0 + 0.01 * k}  0.1  {(3, 7, 11, 12)[k % 4]}")
        lines.append(f"odom2diff {t:.1f} 0.3 0.05")
        lines.append(f"gt2 {t:.1f} {1.0 + 0.03 * k} 2.0 {0.005 * k}")
    (tmp_path / "robot.log").write_text("\n".join(lines) + "\n")
    (tmp_path / "map.toml").write_text(
        'anchors = "anchors.csv"\nheading0 = 0.0\n'
        '[ranges]\nfile = "robot.log"\ndelimiter = "whitespace"\nskip_rows = 1\n'
        'names = ["kind", "t", "r", "sd", "id"]\nselect = {kind = "range2"}\n'
        'time = "t"\nanchor = "id"\nvalue = "r"\nstd = "sd"\n'
        '[odometry]\nfile = "robot.log"\ndelimiter = "whitespace"\nskip_rows = 1\n'
        'names = ["kind", "t", "v", "w"]\nselect = {kind = "odom2diff"}\n'
        'time = "t"\nspeed = "v"\nyaw_rate = "w"\n'
        '[truth]\nfile = "robot.log"\ndelimiter = "whitespace"\nskip_rows = 1\n'
        'names = ["kind", "t", "x", "y", "yaw"]\nselect = {kind = "gt2"}\n'
        'time = "t"\nposition = ["x", "y"]\nheading = "yaw"\n'
    )
    log = import_csv(load_csv_map(tmp_path / "map.toml"))
    assert (
        log.ranges.shape == (40, 3) and log.inputs.shape == (40, 3) and log.truth.shape == (40, 4)
    )
    assert list(log.ranges[:4, 1]) == [3, 7, 11, 12] and np.allclose(log.range_std, 0.1)
    np.testing.assert_allclose(log.inputs[:, 1:], [[0.3, 0.05]] * 40)
    lines[5] = lines[5].replace("0.3 0.05", "0.3 fast")  # an odom2diff line's cell
    (tmp_path / "robot.log").write_text("\n".join(lines) + "\n")
    with pytest.raises(QuadobsError, match=r"robot.log, line 6, column w: 'fast' is not a number"):
        import_csv(load_csv_map(tmp_path / "map.toml"))


def test_select_reads_quoted_cells_a_byte_order_mark_and_numbers_alike(tmp_path):
    _anchors_file(tmp_path)
    rows = ['"note, first",1.0,0.0,4.0,3'] + [
        f'"n",{1 + k % 2},{0.1 * k:.1f},4.0,{(3, 7, 11, 12)[k % 4]}' for k in range(1, 40)
    ]
    (tmp_path / "mixed.csv").write_text("\ufeff" + "\n".join(rows) + "\n", encoding="utf-8")
    names = '["note", "kind", "t", "r", "id"]'
    (tmp_path / "map.toml").write_text(
        f'anchors = "anchors.csv"\n[ranges]\nfile = "mixed.csv"\nnames = {names}\n'
        'select = {kind = 1}\ntime = "t"\nanchor = "id"\nvalue = "r"\n'
    )
    log = import_csv(load_csv_map(tmp_path / "map.toml"))
    assert log.ranges.shape == (20, 3) and log.ranges[0, 0] == 0.0  # the first line kept


def test_a_survey_names_the_line_of_a_cell_past_blank_lines_and_each_ids_count(tmp_path):
    _anchors_file(tmp_path)
    (tmp_path / "r.csv").write_text("t,anchor,range\n0.0,3,4.0\n")
    ranges = {"file": "r.csv", "time": "t", "anchor": "anchor", "value": "range"}
    survey = {"file": "survey.csv", "id": "name", "x": "X", "y": "Y", "z": "Z"}
    (tmp_path / "survey.csv").write_text(
        "name,X,Y,Z\n\n3,0,0,0.2\n\n7,6,0,2.5\n11,6,5,\n12,0,5,2.4\n"
    )
    with pytest.raises(QuadobsError, match=r"survey.csv, line 6: an anchor's cell empty"):
        parse_csv_map({"anchors": survey, "ranges": ranges}, base=tmp_path)
    (tmp_path / "survey.csv").write_text(
        "name,X,Y,Z\n3,0,0,0\n3,1,0,0\n7,2,0,0\n7,3,0,0\n7,4,0,0\n"
    )
    with pytest.raises(QuadobsError, match=r"anchor id 3 given 2 times"):
        parse_csv_map({"anchors": survey, "ranges": ranges}, base=tmp_path)
