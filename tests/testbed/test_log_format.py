"""The open log format, version 2: the data model, the schema, the limits on log files, the staged folder."""

from __future__ import annotations

import math
import os
import threading

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog, read_log, write_log
from quadobs.testbed.logs import files as log_files
from quadobs.testbed.logs.schema import IMU, RANGE, TDOA

BEACONS3 = np.array([[0.0, 0.0, 0.2], [6.0, 0.0, 2.5], [6.0, 5.0, 0.3], [0.0, 5.0, 2.4]])
IDS = np.array([3, 7, 11, 12])


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def flight_log(with_truth: bool = True) -> RangeLog:
    """A 3-D log with every part of version 2: ranges with some std, TDOA, body IMU, attitude, truth with attitude."""
    rng = np.random.default_rng(4)
    t_imu = np.arange(0.0, 2.0, 0.01)
    imu = np.column_stack([t_imu, rng.normal(size=(t_imu.size, 6))])
    imu[:, IMU.az] += 9.80665
    t_r = np.arange(0.005, 1.99, 0.03)
    pos = np.column_stack([3 + np.cos(t_r), 2 + np.sin(t_r), np.full_like(t_r, 1.0)])
    h = np.arange(t_r.size) % 4
    ranges = np.column_stack([t_r, IDS[h], np.linalg.norm(pos - BEACONS3[h], axis=1)])
    std = np.where(h == 2, np.nan, 0.1 + 0.01 * h)
    t_d = t_r[::2] + 0.001
    tdoa = np.column_stack([t_d, IDS[1 + h[::2] % 3], np.full_like(t_d, IDS[0]), 0.5 * h[::2]])
    q = _unit(rng.normal(size=(t_imu.size, 4)))
    attitude = np.column_stack([t_imu, q])
    truth = None
    if with_truth:
        truth = np.column_stack(
            [t_imu, 3 + np.cos(t_imu), 2 + np.sin(t_imu), np.ones_like(t_imu), q, -np.sin(t_imu)]
            + [np.cos(t_imu), np.zeros_like(t_imu)]
        )
    return RangeLog(
        "flight",
        IDS,
        BEACONS3,
        ranges,
        imu,
        math.nan,
        truth,
        input_kind="imu_body",
        truth_columns=("time", "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz"),
        range_std=std,
        tdoa=tdoa,
        attitude=attitude,
        frame="ned",
        gravity=9.81,
        description="a short flight",
    )


def test_a_version_2_log_reads_back_exactly(tmp_path):
    log = flight_log()
    back = read_log(write_log(log, tmp_path / "log"))
    for key in ("beacon_ids", "beacons", "ranges", "inputs", "truth", "range_std", "tdoa"):
        np.testing.assert_array_equal(getattr(back, key), getattr(log, key))
    np.testing.assert_array_equal(back.attitude, log.attitude)
    assert np.all(np.isnan(back.tdoa_std)) and back.tdoa.shape == (34, 4)
    assert (back.version, back.input_kind, back.frame, back.gravity) == (2, "imu_body", "ned", 9.81)
    assert back.description == "a short flight" and back.truth_columns == log.truth_columns
    np.testing.assert_array_equal(back.gravity_vector, [0.0, 0.0, 9.81])
    assert back.truth_part("attitude").shape == (200, 4)
    text = (tmp_path / "log" / "ranges.csv").read_text().splitlines()
    assert text[0] == "time,beacon,range,std" and text[3].endswith(",")  # NaN: an empty cell
    assert "version,2" in (tmp_path / "log" / "meta.csv").read_text()


def test_columns_may_come_in_any_order_and_a_bom_is_skipped(tmp_path):
    folder = write_log(flight_log(), tmp_path / "log")
    lines = (folder / "ranges.csv").read_text().splitlines()
    swapped = [",".join([c[2], c[0], c[3], c[1]]) for c in (row.split(",") for row in lines)]
    (folder / "ranges.csv").write_text("\ufeff" + "\n".join(swapped) + "\n", encoding="utf-8")
    (folder / "meta.csv").write_text("\ufeff" + (folder / "meta.csv").read_text())
    back = read_log(folder)
    np.testing.assert_array_equal(back.ranges, flight_log().ranges)


def test_a_log_of_ranges_alone_is_valid(tmp_path):
    log = flight_log(with_truth=False)
    alone = RangeLog(
        "alone",
        log.beacon_ids,
        log.beacons,
        log.ranges,
        np.empty((0, 1)),
        math.nan,
        input_kind="none",
    )
    back = read_log(write_log(alone, tmp_path / "alone"))
    assert back.input_kind == "none" and back.inputs.shape == (0, 1)
    assert not (tmp_path / "alone" / "inputs.csv").exists()
    assert back.start == log.ranges[0, RANGE.time] and back.end == log.ranges[-1, RANGE.time]
    part = back.excerpt(0.5, 1.0)
    assert part.ranges[0, 0] >= back.start + 0.5 and part.ranges[-1, 0] < back.start + 1.0


def test_the_measurements_come_as_events_in_time_order():
    log = flight_log()
    events = log.measurements()
    assert len(events) == log.ranges.shape[0] + log.tdoa.shape[0]
    assert all(a.t <= b.t for a, b in zip(events, events[1:]))
    first_tdoa = next(m for m in events if m.kind == "tdoa")
    row = log.tdoa[0]
    assert first_tdoa.anchors == (
        int(np.flatnonzero(IDS == row[TDOA.anchor_i])[0]),
        int(np.flatnonzero(IDS == row[TDOA.anchor_j])[0]),
    )
    ranges = [m for m in events if m.kind == "range"]
    np.testing.assert_array_equal([m.std for m in ranges], log.range_std)
    assert ranges[1].anchors == (1,)


def test_a_range_below_zero_is_read_as_measured(tmp_path):
    """A radio's range is a distance plus its error: an antenna delay can take a short one
    below zero. It is a measurement like any other, kept with its sign."""
    folder = _write_v1(tmp_path / "log")
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,-0.04\n0.7,1,7.5\n")
    log = read_log(folder)
    np.testing.assert_array_equal(log.ranges[:, RANGE.range], [-0.04, 7.5])
    assert next(m.value for m in log.measurements() if m.kind == "range") == -0.04


def test_wheel_odometry_with_anchors_in_space_keeps_their_heights_apart(tmp_path):
    """A planar vehicle among anchors in space: ``z`` is each anchor's height, the vehicle's
    model stays planar; ``tag_height`` states the tag's, and both are written back."""
    folder = _write_v1(tmp_path / "log")
    (folder / "beacons.csv").write_text("id,x,y,z\n0,0,0,0.3\n1,10,0,2.3\n")
    (folder / "meta.csv").write_text("key,value\nversion,2\nheading0,0.5\ntag_height,0.25\n")
    log = read_log(folder)
    assert log.dimension == 2 and log.tag_height == 0.25
    np.testing.assert_array_equal(log.beacons, [[0, 0], [10, 0]])
    np.testing.assert_array_equal(log.anchor_heights, [0.3, 2.3])
    back = read_log(write_log(log, tmp_path / "back"))
    np.testing.assert_array_equal(back.anchor_heights, log.anchor_heights)
    assert back.tag_height == 0.25
    assert (tmp_path / "back" / "beacons.csv").read_text().startswith("id,x,y,z\n")
    (folder / "truth.csv").write_text("time,x,y,z\n0,1,1,0.25\n")
    with pytest.raises(QuadobsError, match=r"column z given for a planar vehicle"):
        read_log(folder)
    (folder / "truth.csv").unlink()
    (folder / "beacons.csv").write_text("id,x,y\n0,0,0\n1,10,0\n")
    with pytest.raises(QuadobsError, match=r"key tag_height: only for an odometry log whose"):
        read_log(folder)


def _write_v1(folder, ranges_header="time,beacon,range"):
    folder.mkdir()
    (folder / "beacons.csv").write_text("id,x,y\n0,0,0\n1,10,0\n")
    (folder / "ranges.csv").write_text(f"{ranges_header}\n0.5,0,3.0\n0.7,1,7.5\n")
    (folder / "inputs.csv").write_text("time,speed,yaw_rate\n0,1,0\n1,1,0\n")
    (folder / "meta.csv").write_text("key,value\nname,old\nheading0,0.5\n")
    return folder


def test_a_version_1_log_still_reads_and_version_2_parts_ask_for_the_version(tmp_path):
    log = read_log(_write_v1(tmp_path / "v1"))
    assert log.version == 1 and log.input_kind == "odometry" and log.heading0 == 0.5
    folder = _write_v1(tmp_path / "v1std", "time,beacon,range,std")
    with pytest.raises(
        QuadobsError, match=r"ranges.csv, row 1: .*add the row version,2 to meta.csv"
    ):
        read_log(folder)
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,3.0\n")
    (folder / "tdoa.csv").write_text("time,anchor_i,anchor_j,difference\n0.5,0,1,3.0\n")
    with pytest.raises(QuadobsError, match=r"tdoa.csv: a version-2 file; add the row version,2"):
        read_log(folder)
    (folder / "tdoa.csv").unlink()
    (folder / "inputs.csv").unlink()
    with pytest.raises(QuadobsError, match=r"inputs.csv: missing"):
        read_log(folder)


@pytest.mark.parametrize(
    "fname, text, expect",
    [
        (
            "ranges.csv",
            "time,beacon,range\n0.5,0.7,3\n",
            "row 2, column beacon: '0.7' is not an integer",
        ),
        (
            "ranges.csv",
            "time,beacon,range,std\n0.5,0,3,0\n",
            "row 2, column std: '0' is not a positive",
        ),
        (
            "ranges.csv",
            "time,beacon,range,std\n0.5,0,3,inf\n",
            "row 2, column std: 'inf' is not a finite",
        ),
        (
            "ranges.csv",
            "time,beacon,range\n0.5,0,1e400\n",
            "column range: '1e400' is not a finite number",
        ),
        ("ranges.csv", "time,beacon,time\n0.5,0,3\n", "row 1: header 'time,beacon,time'"),
        (
            "ranges.csv",
            "time,beacon,range,speed\n0.5,0,3,1\n",
            "row 1: header 'time,beacon,range,speed'",
        ),
        ("beacons.csv", "id,x,y\n0,0,0\n2e19,1,1\n", "row 3, column id: '2e19' is not an integer"),
        (
            "meta.csv",
            "key,value\nversion,2\nheading0,0\nheading0,1\n",
            "row 4, key heading0: given twice",
        ),
        ("meta.csv", "key,value\nversion,2\nheadng0,0\n", "row 3: unknown key 'headng0'"),
        ("meta.csv", "key,value\nversion,3\n", "key version: '3'; expected 1 or 2"),
        (
            "meta.csv",
            "key,value\nversion,2\nname,a\x1b[31mb\nheading0,0\n",
            "key name: control character",
        ),
        ("meta.csv", "key,value\nframe,ned\nheading0,0\n", "key frame: a version-2 key"),
        (
            "tdoa.csv",
            "time,anchor_i,anchor_j,difference\n0.5,1,1,0.3\n",
            "tdoa.csv, row 2, column anchor_j: the same anchor as anchor_i",
        ),
        (
            "tdoa.csv",
            "time,anchor_i,anchor_j,difference\n0.5,1,4,0.3\n",
            "tdoa.csv, row 2, column anchor_j: unknown beacon id 4",
        ),
        (
            "truth.csv",
            "time,x,y,qw,qx,qy,qz\n0,1,1,1,0,0,0.1\n",
            "truth.csv, row 2, columns qw,qx,qy,qz: not a unit quaternion",
        ),
        ("truth.csv", "time,x,y,qw\n0,1,1,1\n", "truth.csv, row 1: the attitude needs all of"),
        ("beacons.csv", "id,x,y\nA1,0,0\n1,10,0\n", "column id: 'A1' is not an integer anchor id"),
        (
            "ranges.csv",
            "time,beacon,range,rssi\n0.5,0,3,-80\n",
            "'rssi' not a column of the format (leave it out)",
        ),
        (
            "ranges.csv",
            "t_twr,beacon,range\n0.5,0,3\n",
            "'t_twr' not a column of the format (rename it to a column expected, or leave it out)",
        ),
        (
            "imu.csv",
            "time,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n",
            "imu.csv: a log holds inputs.csv or imu.csv, not both",
        ),
        (
            "inputs.csv",
            "time,speed,yaw_rate\n0,1,0\n1e8,1,0\n",
            "inputs.csv spans 1e+08 s, more than 1e+07 s: times must be seconds",
        ),
    ],
)
def test_the_schema_refuses_each_bad_field_in_one_line(tmp_path, fname, text, expect):
    folder = _write_v1(tmp_path / "log")
    (folder / "meta.csv").write_text("key,value\nversion,2\nheading0,0.5\n")
    (folder / fname).write_text(text)
    with pytest.raises(QuadobsError) as err:
        read_log(folder)
    assert expect in str(err.value) and "\n" not in str(err.value)
    assert str(folder / fname) in str(err.value)


def test_files_on_two_clocks_are_named_with_their_times(tmp_path):
    folder = _write_v1(tmp_path / "log")
    (folder / "meta.csv").write_text("key,value\nversion,2\nheading0,0.5\n")
    (folder / "inputs.csv").write_text("time,speed,yaw_rate\n1.7e9,1,0\n1.7e9,1,0\n")
    with pytest.raises(QuadobsError) as err:
        read_log(folder)
    message = str(err.value)
    assert message.startswith(f"{folder}: the files' times lie more than 1e+07 s apart (")
    assert "inputs.csv from 1.7e+09 s" in message and "ranges.csv from 0" in message


def test_a_std_cell_may_be_empty_and_a_row_without_its_value_is_left_out(tmp_path):
    folder = _write_v1(tmp_path / "log")
    (folder / "meta.csv").write_text("key,value\nversion,2\nheading0,0.5\n")
    (folder / "ranges.csv").write_text("time,beacon,range,std\n0.5,0,3,\n0.6,1,4,0.2\n")
    log = read_log(folder)
    np.testing.assert_array_equal(log.range_std, [np.nan, 0.2])
    assert log.read_notes == ()
    (folder / "ranges.csv").write_text("time,beacon,range,std\n0.5,0,,0.1\n0.6,1,nan,\n0.7,1,4,\n")
    log = read_log(folder)
    np.testing.assert_array_equal(log.ranges, [[0.7, 1, 4.0]])
    assert log.read_notes == (
        "ranges.csv: 2 rows with an empty or NaN value left out (no measurement)",
    )
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,\n0.6,1,nan\n")
    with pytest.raises(QuadobsError, match=r"ranges.csv: each of its 2 rows has an empty or NaN"):
        read_log(folder)
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,,3\n")  # an id is never blank
    with pytest.raises(QuadobsError, match=r"row 2, column beacon: '' is not a finite number"):
        read_log(folder)
    (folder / "ranges.csv").write_text("time,beacon,range\n,0,3\n")  # nor a time
    with pytest.raises(QuadobsError, match=r"row 2, column time: '' is not a finite number"):
        read_log(folder)


def test_rows_left_out_keep_the_files_row_numbers_in_later_errors(tmp_path):
    folder = _write_v1(tmp_path / "log")
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,\n0.6,1,4\n0.7,1,-inf\n")
    with pytest.raises(QuadobsError, match=r"ranges.csv, row 4, column range: '-inf' is not a"):
        read_log(folder)
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,\n0.6,1,4\n0.3,1,5\n")
    with pytest.raises(QuadobsError, match=r"ranges.csv, row 4, column time: earlier than a row "):
        read_log(folder)


def test_rows_a_little_out_of_time_order_are_sorted_and_a_clock_set_back_is_refused(tmp_path):
    folder = _write_v1(tmp_path / "log")
    rows = "time,beacon,range\n0.50,0,3\n0.52,1,4\n0.51,0,3.1\n0.60,1,4.1\n0.55,1,4.2\n"
    (folder / "ranges.csv").write_text(rows)
    log = read_log(folder)
    np.testing.assert_array_equal(log.ranges[:, 0], [0.5, 0.51, 0.52, 0.55, 0.6])
    np.testing.assert_array_equal(log.ranges[:, 2], [3, 3.1, 4, 4.2, 4.1])
    assert log.read_notes == (
        "ranges.csv: 2 rows stamped before an earlier row (by up to 0.05 s) sorted by time",
    )
    late = rows.replace("0.55,1", "0.35,1")  # one row 0.25 s late (delayed in a buffer)
    (folder / "ranges.csv").write_text(late + "".join(f"{0.6 + k / 100},1,4\n" for k in range(99)))
    assert read_log(folder).read_notes == (
        "ranges.csv: 2 rows stamped before an earlier row (by up to 0.25 s) sorted by time",
    )
    late += "".join(f"{0.6 + k / 100},1,4\n" for k in range(20))
    set_back = late + "".join(f"{0.6 + k / 100},1,4\n" for k in range(5))  # a clock set back
    (folder / "ranges.csv").write_text(set_back)
    with pytest.raises(QuadobsError) as err:
        read_log(folder)
    assert str(err.value).endswith(  # not the single late row 6: the first row set back
        "ranges.csv, row 27, column time: earlier than a row before it by 0.19 s (rows must be "
        "sorted by time; a step back of up to 0.1 s, or a few rows written late, is sorted, "
        "more is a clock set back)"
    )


def test_log_files_are_regular_files_within_bounds(tmp_path, monkeypatch):
    folder = _write_v1(tmp_path / "log")
    (folder / "truth.csv").symlink_to(tmp_path / "nowhere.csv")
    with pytest.raises(QuadobsError, match=r"truth.csv: a dangling symbolic link"):
        read_log(folder)
    (folder / "truth.csv").unlink()
    (folder / "truth.csv").symlink_to(folder / "truth.csv")
    with pytest.raises(QuadobsError, match=r"truth.csv: a symbolic link loop"):
        read_log(folder)
    (folder / "truth.csv").unlink()
    (folder / "truth.csv").symlink_to("/dev/zero")
    with pytest.raises(QuadobsError, match=r"truth.csv: not a regular file"):
        read_log(folder)
    (folder / "truth.csv").unlink()
    os.mkfifo(folder / "truth.csv")  # refused at once, not waited on
    done: list = []
    reader = threading.Thread(target=lambda: done.append(_error(folder)), daemon=True)
    reader.start()
    reader.join(10.0)
    assert done and "truth.csv: not a regular file" in done[0]
    (folder / "truth.csv").unlink()
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0," + "1" * 5000 + "\n")
    with pytest.raises(
        QuadobsError, match=r"ranges.csv, row 2: a line of 5006 bytes, more than 4096"
    ):
        read_log(folder)
    monkeypatch.setattr(log_files, "MAX_FILE_BYTES", 35)
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,3.0\n0.7,1,7.5\n")
    with pytest.raises(QuadobsError, match=r"ranges.csv: larger than 35 bytes"):
        read_log(folder)


def _error(folder) -> str:
    try:
        read_log(folder)
    except QuadobsError as exc:
        return str(exc)
    return ""


def test_a_log_folder_is_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    folder = write_log(flight_log(), tmp_path / "log")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}

    def fail(stage, target):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(log_files, "_swap_in", fail)
    alone = RangeLog(
        "other",
        IDS,
        BEACONS3,
        flight_log().ranges[:5],
        np.empty((0, 1)),
        math.nan,
        input_kind="none",
    )
    with pytest.raises(
        QuadobsError, match=r"log folder .*: cannot be written \(No space left on device\)"
    ):
        write_log(alone, folder)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log"]  # no staging folder left
    monkeypatch.undo()
    write_log(alone, folder)
    assert sorted(p.name for p in folder.iterdir()) == ["beacons.csv", "meta.csv", "ranges.csv"]
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(QuadobsError, match=r"holds 'notes.txt'"):
        write_log(alone, folder)
    assert (folder / "notes.txt").read_text() == "mine"


def test_a_log_built_in_memory_is_held_to_the_schema_too():
    log = flight_log(with_truth=False)
    bad = log.ranges.copy()
    bad[4, RANGE.range] = math.inf
    with pytest.raises(
        QuadobsError, match=r"flight: ranges.csv, row 6, column range: 'inf' is not a finite"
    ):
        RangeLog("flight", IDS, BEACONS3, bad, log.inputs, math.nan, input_kind="imu_body")
    with pytest.raises(QuadobsError, match=r"a log without inputs needs ranges or TDOA"):
        RangeLog(
            "empty", IDS, BEACONS3, np.empty((0, 3)), np.empty((0, 1)), math.nan, input_kind="none"
        )
    with pytest.raises(QuadobsError, match=r"imu.csv, row 1: a body IMU needs a log in space"):
        RangeLog(
            "flat", IDS, BEACONS3[:, :2], log.ranges, log.inputs, math.nan, input_kind="imu_body"
        )


_FUZZ_FILES = (
    "meta.csv",
    "beacons.csv",
    "ranges.csv",
    "tdoa.csv",
    "imu.csv",
    "attitude.csv",
    "truth.csv",
)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    fname=st.sampled_from(_FUZZ_FILES),
    position=st.floats(0.0, 1.0),
    cut=st.integers(0, 40),
    junk=st.binary(max_size=24)
    | st.sampled_from([b"nan", b"-1e400", b"\n\n", b",,,", b"\xef\xbb\xbf", b'"', b"1e19", b"\r"]),
)
def test_a_mutated_log_reads_or_is_refused_in_one_line(
    tmp_path_factory, fname, position, cut, junk
):
    folder = tmp_path_factory.mktemp("fuzz") / "log"
    write_log(flight_log(), folder)
    path = folder / fname
    raw = path.read_bytes()
    at = int(position * len(raw))
    path.write_bytes(raw[:at] + junk + raw[at + cut :])
    try:
        read_log(folder)
    except QuadobsError as exc:
        assert "\n" not in str(exc) and str(exc)


def test_an_excerpt_keeps_every_part_of_its_span():
    log = flight_log()
    part = log.excerpt(0.5, 1.0)
    a, b = log.start + 0.5, log.start + 1.0
    for table, std in ((part.ranges, part.range_std), (part.tdoa, part.tdoa_std)):
        assert table.shape[0] == std.shape[0] > 0
        assert a <= table[0, 0] and table[-1, 0] < b
    np.testing.assert_array_equal(
        part.range_std, log.range_std[(log.ranges[:, 0] >= a) & (log.ranges[:, 0] < b)]
    )
    assert part.attitude[0, 0] <= a and part.attitude[-1, 0] >= b  # one sample either side
    assert part.inputs[0, 0] == a and part.input_kind == "imu_body" and part.frame == "ned"


def test_arrow_and_the_row_by_row_reader_give_the_same_values(tmp_path):
    from quadobs.studies.bench import log_read_figure
    from quadobs.testbed.logs.schema import FILES

    folder = write_log(flight_log(), tmp_path / "log")
    for fname in ("ranges.csv", "tdoa.csv", "imu.csv", "attitude.csv", "truth.csv"):
        path = folder / fname
        raw = log_files.read_limited(path)
        header = [h.strip() for h in log_files._line(raw, log_files._line_starts(path, raw), 0)]
        columns = FILES[fname].columns_of(header, 2)
        fast = log_files._arrow_values(raw, header, columns)
        slow = log_files._python_values(
            path, raw, log_files._line_starts(path, raw), header, columns
        )
        np.testing.assert_array_equal(fast, slow)
    figure = log_read_figure(rows=2000, repeats=1)
    assert figure["rows"] == 2000 and figure["arrow_s"] > 0 and figure["log_read_speedup"] > 0


def test_arrow_columns_are_read_from_their_buffers_nulls_as_nan(tmp_path):
    """Several chunks (a small block size), nulls among them, and a slice (chunks with an
    offset): the values and the NaNs where the cells were empty, without pandas."""
    import subprocess
    import sys

    import pyarrow as pa
    import pyarrow.csv as pacsv

    rng = np.random.default_rng(3)
    values, empty = rng.normal(size=(3000, 2)), rng.random((3000, 2)) < 0.1
    cells = [
        ["" if e else repr(float(v)) for v, e in zip(row, gap)] for row, gap in zip(values, empty)
    ]
    raw = ("a,b\n" + "".join(",".join(c) + "\n" for c in cells)).encode()
    table = pacsv.read_csv(
        pa.BufferReader(raw),
        read_options=pacsv.ReadOptions(block_size=4096),
        convert_options=pacsv.ConvertOptions(column_types={"a": pa.float64(), "b": pa.float64()}),
    )
    expected = np.where(empty, np.nan, values)
    assert table.column("a").num_chunks > 10
    for part, rows in ((table, slice(None)), (table.slice(7, 2900), slice(7, 2907))):
        for c, name in enumerate("ab"):
            out = np.empty(part.num_rows)
            log_files._fill_float_column(out, part.column(name).chunks)
            np.testing.assert_array_equal(out, expected[rows, c])
    folder = write_log(flight_log(), tmp_path / "log")
    code = (
        f"import sys; from quadobs.testbed.logs import read_log; read_log({str(folder)!r}); "
        "print(sorted(m for m in ('pandas', 'scipy.stats') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_log_needs_ranges_or_tdoa_and_inputs_only_in_version_1(tmp_path):
    folder = _write_v1(tmp_path / "log")
    (folder / "meta.csv").write_text("key,value\nversion,2\nheading0,0.5\n")
    (folder / "inputs.csv").unlink()
    with pytest.raises(QuadobsError, match=r"meta.csv, key heading0: only for an odometry log"):
        read_log(folder)
    (folder / "meta.csv").write_text("key,value\nversion,2\n")
    assert read_log(folder).input_kind == "none"
    (folder / "ranges.csv").unlink()
    with pytest.raises(
        QuadobsError, match=r"ranges.csv: missing \(a log holds ranges.csv, tdoa.csv or both\)"
    ):
        read_log(folder)


def test_a_stated_tag_on_the_truths_body_moves_the_truth_to_the_tag(tmp_path):
    import dataclasses

    from quadobs.testbed.worlds.replay import _truth_rows

    log = flight_log()
    lever = np.array([-0.012, 0.001, 0.091])
    stated = dataclasses.replace(log, tag_x=lever[0], tag_y=lever[1], tag_z=lever[2])
    q = stated.truth[:, 4:8]
    w, v = q[:, 0], q[:, 1:]  # R(q) from its closed form, row by row
    R = np.stack(
        [
            np.eye(3) * (w[k] ** 2 - v[k] @ v[k]) + 2 * np.outer(v[k], v[k])
            + 2 * w[k] * np.array([[0, -v[k, 2], v[k, 1]], [v[k, 2], 0, -v[k, 0]], [-v[k, 1], v[k, 0], 0]])
            for k in range(q.shape[0])
        ]
    )  # fmt: skip
    want = log.truth[:, 1:4] + R @ lever
    np.testing.assert_allclose(stated.truth_part("position"), want, atol=1e-12)
    np.testing.assert_array_equal(stated.truth_part("velocity"), log.truth_part("velocity"))
    T = log.truth[::7, 0]
    np.testing.assert_allclose(_truth_rows(stated, T, 3), want[::7], atol=1e-12)  # scored so
    back = read_log(write_log(stated, tmp_path / "log"))
    np.testing.assert_array_equal(back.truth, log.truth)  # the file keeps the truth's own point
    np.testing.assert_array_equal(back.truth_lever, lever)
    assert back.tag_offset is None


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"tag_x": 0.1, "tag_y": 0.0}, "key tag_x: given without tag_z"),
        ({"tag_z": 0.1}, "key tag_z: given without tag_x, tag_y"),
        ({"tag_x": 0.1, "tag_y": 0.0, "tag_z": math.inf}, "keys tag_x, tag_y, tag_z: not finite"),
    ],
)
def test_a_tag_on_the_truths_body_is_stated_whole(fields, message):
    import dataclasses

    with pytest.raises(QuadobsError, match=message):
        dataclasses.replace(flight_log(), **fields)


def test_a_tag_on_the_truths_body_needs_the_truths_attitude():
    import dataclasses

    log = flight_log()
    point = dataclasses.replace(log, truth=log.truth[:, :4], truth_columns=("time", "x", "y", "z"))
    with pytest.raises(QuadobsError, match=r"truth.csv holds none \(qw,qx,qy,qz\)"):
        dataclasses.replace(point, tag_x=0.0, tag_y=0.0, tag_z=0.09)


def test_rows_named_in_errors_are_the_files_after_rows_left_out_or_sorted(tmp_path):
    """A row left out (an empty value, an empty line) or sorted before a faulty one: the
    error names the faulty row's number in the file, whichever check finds it."""
    folder = _write_v1(tmp_path / "log")
    ranges = ["time,beacon,range", "0.5,0,", "", "0.7,1,7.5", "0.65,0,3", "0.8,9,3"]
    (folder / "ranges.csv").write_text("\n".join(ranges) + "\n")
    with pytest.raises(
        QuadobsError, match=r"ranges.csv, row 6, column beacon: unknown beacon id 9"
    ):
        read_log(folder)
    (folder / "ranges.csv").write_text("\n".join(ranges[:5] + ["0.8,abc,3"]) + "\n")
    with pytest.raises(QuadobsError, match=r"ranges.csv, row 6, column beacon: 'abc' is not"):
        read_log(folder)
    (folder / "ranges.csv").write_text("time,beacon,range\n0.5,0,3.0\n0.7,1,7.5\n")
    (folder / "meta.csv").write_text("key,value\nversion,2\nheading0,0.5\n")
    truth = ["time,x,y,qw,qx,qy,qz", "0.1,,0,1,0,0,0", "0.2,1,0,1,0,0,0", "0.3,1,0,2,0,0,0"]
    (folder / "truth.csv").write_text("\n".join(truth) + "\n")
    with pytest.raises(QuadobsError, match=r"truth.csv, row 4, columns qw,qx,qy,qz: not a unit"):
        read_log(folder)
