"""Valid but awkward log folders: each is replayed as its plain form, or refused in one line.

A log written by hand from a real recording differs from an exported one in ways the format
allows (anchor ids that are not 0..n-1, anchors listed in any order or never heard, Windows
line ends, a header with spaces, trailing empty lines, an epoch clock) and in ways it does
not (times in nanoseconds, a burn-in past the log). The first kind must give the same
figures as the plain log; the second a one-line :class:`~quadobs.errors.QuadobsError` before
any work.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog, read_log, write_log
from quadobs.testbed.logs.replay import check_burn_in, run_replay
from quadobs.testbed.logs.schema import RANGE

ANCHORS = np.array([[-6.0, -5.0, 0.5], [7.0, -6.0, 2.5], [6.0, 7.0, 0.3], [-5.0, 6.0, 2.8]])


def helix(duration: float = 8.0) -> RangeLog:
    """A helix read by a navigation-frame accelerometer, ranged round-robin at 20 Hz, with a truth."""
    t = np.arange(0.0, duration, 0.02)

    def p(s):
        return np.column_stack([3 * np.cos(0.3 * s), 3 * np.sin(0.3 * s), 1.5 + 0.3 * np.sin(s)])

    v = np.column_stack(
        [-0.9 * np.sin(0.3 * t), 0.9 * np.cos(0.3 * t), 0.3 * np.cos(t)]
    )  # fmt: skip
    acc = np.column_stack([-0.27 * np.cos(0.3 * t), -0.27 * np.sin(0.3 * t), -0.3 * np.sin(t)])
    tr = np.arange(0.01, duration - 0.02, 0.05)
    h = np.arange(tr.size) % 4
    rng = np.random.default_rng(7)
    r = np.linalg.norm(p(tr) - ANCHORS[h], axis=1) + rng.normal(0.0, 0.05, tr.size)
    return RangeLog(
        "helix", np.arange(4), ANCHORS, np.column_stack([tr, h, r]), np.column_stack([t, acc]),
        math.nan, np.column_stack([t, p(t), v]), input_kind="imu",
        truth_columns=("time", "x", "y", "z", "vx", "vy", "vz"), range_std=np.full(tr.size, 0.05),
    )  # fmt: skip


def _replay(log: RangeLog) -> dict:
    s = run_replay(
        log, estimators=["ekf"], dt=0.1, initial_offset=2.0, burn_in=2.0, batch=False,
        setup_options={"range_sigma": 0.05, "q_imu": 1e-2},
    )  # fmt: skip
    return s["estimators"]["ekf"]


def _rewrite(path, edit) -> None:
    path.write_bytes(edit(path.read_bytes()))


def _spaced_header(text: bytes) -> bytes:
    """The header's names padded with spaces: ``time , beacon , range``."""
    header, rest = text.split(b"\r\n", 1)
    return b" , ".join(b" " + name + b" " for name in header.split(b",")) + b"\r\n" + rest


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    folder = write_log(helix(), tmp_path_factory.mktemp("plain") / "helix")
    return folder, _replay(read_log(folder))


def test_anchor_ids_out_of_order_and_one_never_heard_replay_as_the_plain_log(tmp_path, plain):
    """Ids 101, 7, 3, 55 listed in reverse, beside an anchor no range names: the same figures."""
    log = helix()
    ids = np.array([101, 7, 3, 55])
    ranges = log.ranges.copy()
    ranges[:, RANGE.beacon] = ids[log.ranges[:, RANGE.beacon].astype(int)]
    order = [4, 3, 2, 1, 0]  # 4: the unheard anchor, first in beacons.csv
    awkward = dataclasses.replace(
        log,
        beacon_ids=np.append(ids, 9)[order],
        beacons=np.vstack([ANCHORS, [[0.0, 0.0, 3.0]]])[order],
        ranges=ranges,
    )
    folder = write_log(awkward, tmp_path / "awkward")
    e = _replay(read_log(folder))
    assert e["diverged"] is None and e["rmse"] == pytest.approx(plain[1]["rmse"], rel=1e-9)


@pytest.mark.parametrize(
    "edit",
    [
        pytest.param(lambda b: b.replace(b"\r\n", b"\n"), id="unix-line-ends"),
        pytest.param(
            lambda b: b.replace(b"\r\n", b"\n").replace(b"\n", b"\r\n"), id="windows-line-ends"
        ),
        pytest.param(lambda b: b"\xef\xbb\xbf" + b, id="byte-order-mark"),
        pytest.param(lambda b: b + b"\n\n  \r\n", id="trailing-empty-lines"),
        pytest.param(_spaced_header, id="header-with-spaces"),
    ],
)
def test_text_conventions_of_other_editors_read_as_the_plain_log(tmp_path, plain, edit):
    """Every file of the folder edited alike; the log reads back exactly."""
    folder = tmp_path / "edited"
    expected = read_log(plain[0])
    write_log(expected, folder)
    for path in folder.iterdir():
        _rewrite(path, edit)
    back = read_log(folder)
    assert np.array_equal(back.ranges, expected.ranges)
    assert np.array_equal(back.inputs, expected.inputs)
    assert np.array_equal(back.truth, expected.truth)
    assert back.name == expected.name


def test_empty_lines_between_rows_are_left_out_and_a_row_of_empty_cells_refused(tmp_path, plain):
    """A writer's doubled line ends (an empty line after every row, ``\\r\\r\\n``): the log
    reads as the plain one, with a note; a line of empty cells (``,,``) has an empty time, and
    is refused with its row."""
    expected = read_log(plain[0])
    folder = write_log(expected, tmp_path / "doubled")
    for name in ("ranges.csv", "inputs.csv"):
        _rewrite(folder / name, lambda b: b.replace(b"\r\n", b"\r\r\n"))
    back = read_log(folder)
    assert np.array_equal(back.ranges, expected.ranges)
    assert np.array_equal(back.inputs, expected.inputs)
    n = expected.ranges.shape[0]
    assert back.read_notes[0] == f"ranges.csv: {n} empty lines between rows left out"
    folder = write_log(expected, tmp_path / "commas")
    _rewrite(folder / "ranges.csv", lambda b: b.replace(b"\r\n", b"\r\n,,,\r\n", 3))
    with pytest.raises(QuadobsError, match=r"ranges.csv, row 2, column time: '' is not a finite"):
        read_log(folder)


def test_an_epoch_clock_in_seconds_replays_as_the_plain_log(tmp_path, plain):
    log = helix()

    def moved(table):
        table = table.copy()
        table[:, 0] += 1.7e9
        return table

    epoch = dataclasses.replace(
        log, ranges=moved(log.ranges), inputs=moved(log.inputs), truth=moved(log.truth)
    )
    e = _replay(read_log(write_log(epoch, tmp_path / "epoch")))
    # 1.7e9 s holds times to 2.4e-7 s: the same figures to far below the range noise
    assert e["diverged"] is None and e["rmse"] == pytest.approx(plain[1]["rmse"], abs=1e-4)


def test_times_in_nanoseconds_are_refused_in_one_line_naming_the_unit(tmp_path):
    log = helix()
    folder = write_log(log, tmp_path / "ns")
    for name in ("ranges.csv", "inputs.csv", "truth.csv"):
        rows = (folder / name).read_text().splitlines()
        out = [rows[0]]
        for row in rows[1:]:
            cells = row.split(",")
            cells[0] = str(int(round(float(cells[0]) * 1e9)) + 1_700_000_000_000_000_000)
            out.append(",".join(cells))
        (folder / name).write_text("\n".join(out) + "\n")
    with pytest.raises(
        QuadobsError, match=r"spans \S+ s, more than 1e\+07 s: .*nanoseconds"
    ) as err:
        read_log(folder)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("truth_end", "burn_in", "expect"),
    [
        (None, 8.0, "not shorter than the log"),
        (None, 20.0, "not shorter than the log"),
        (3.0, 5.0, "truth.csv ends 3"),
    ],
)
def test_a_burn_in_past_the_log_or_its_truth_is_refused(truth_end, burn_in, expect):
    log = helix()
    if truth_end is not None:
        log = dataclasses.replace(log, truth=log.truth[log.truth[:, 0] <= truth_end])
    with pytest.raises(QuadobsError, match=expect):
        check_burn_in(log, burn_in)


def test_a_burn_in_inside_the_log_and_its_truth_is_accepted():
    log = helix()
    check_burn_in(log, 0.0)
    check_burn_in(log, 5.0)
    check_burn_in(dataclasses.replace(log, truth=None), 5.0)  # no truth: nothing to score anyway


def test_no_truth_is_made_up_across_a_gap_of_the_truth():
    """A motion capture losing the body for 3 s: the rows inside the gap get no truth (a straight
    line across it is not where the body went), the rows of a dense truth all get one."""
    from quadobs.testbed.worlds.replay import _in_truth_gap

    tt = np.concatenate([np.arange(0.0, 4.0, 0.01), np.arange(7.0, 10.0, 0.01)])
    T = np.arange(0.0, 10.0, 0.1)
    gap = _in_truth_gap(tt, T)
    assert np.array_equal(T[gap], T[(T > tt[399]) & (T < 7.0)])
    assert not _in_truth_gap(np.arange(0.0, 10.0, 0.01), T).any()
    assert not _in_truth_gap(np.arange(0.0, 10.0, 0.3), T).any()  # sparse but even: no gap


def test_gaps_of_the_inputs_and_the_truth_are_said_before_the_replay():
    from quadobs.testbed.logs.replay import gap_notes, replayable_log

    log = helix()
    t = log.inputs[:, 0]
    keep = (t < 4.0) | (t >= 6.5)  # the inputs silent for 2.5 s
    tt = log.truth[:, 0]
    cut = ((tt < 2.0) | (tt > 2.8)) & ((tt < 5.0) | (tt > 6.2))  # two gaps of the truth
    gapped = dataclasses.replace(log, inputs=log.inputs[keep], truth=log.truth[cut])
    step = float(np.median(np.diff(t)))
    notes = replayable_log(gapped)[1]
    assert (
        f"inputs: a gap of {2.5 + step:.3g} s from {4.0 - step - log.start:.3g} s into the log: each input held across it"
        in notes
    )
    assert any(
        n.startswith("truth: 2 gaps, the longest 1.2") and n.endswith("no error scored there")
        for n in notes
    )
    assert gap_notes(log) == []
    tr = log.ranges[:, 0]
    stepped = tr.copy()
    stepped[tr >= 5.0] += 1.0  # the ranges' host clock set 1 s forward 5 s into the log
    moved = dataclasses.replace(log, ranges=np.column_stack([stepped, log.ranges[:, 1:]]))
    assert gap_notes(moved) == [
        f"measurements: a gap of {1.0 + np.min(tr[tr >= 5.0]) - np.max(tr[tr < 5.0]):.3g} s "
        f"from {np.max(tr[tr < 5.0]) - log.start:.3g} s into the log: each estimator predicts "
        "across it (a radio's outage, or the measurements' clock stepped forward?)"
    ]


def test_an_anchor_never_ranged_is_left_out_of_the_replay():
    """Its position would move the geometry the defaults come from; the rest is the plain log."""
    from quadobs.testbed.logs.replay import heard_anchors

    log = helix()
    listed = dataclasses.replace(
        log,
        beacon_ids=np.array([9, 0, 1, 2, 3]),
        beacons=np.vstack([[[40.0, 40.0, 9.0]], ANCHORS]),
    )
    heard, unheard = heard_anchors(listed)
    assert unheard == [9]
    assert np.array_equal(heard.beacon_ids, log.beacon_ids)
    assert np.array_equal(heard.beacons, log.beacons)
    assert heard_anchors(log) == (log, [])


def test_a_range_of_zero_is_left_out_and_said_so(plain):
    """One failed exchange reported as 0 m: left out, and the replay is the plain log's."""
    from quadobs.testbed.logs.replay import replayable_log

    log = helix()
    ranges, std = log.ranges.copy(), log.range_std.copy()
    k = ranges.shape[0] // 2
    ranges = np.insert(ranges, k, [ranges[k, 0], ranges[k, 1], 0.0], axis=0)
    std = np.insert(std, k, 0.05)
    back, notes = replayable_log(dataclasses.replace(log, ranges=ranges, range_std=std))
    assert notes == ["ranges of 0 m (a radio's failed exchange), left out: 1"]
    assert np.array_equal(back.ranges, log.ranges) and np.array_equal(back.range_std, log.range_std)
    assert _replay(back)["rmse"] == pytest.approx(plain[1]["rmse"], rel=1e-12)
    assert replayable_log(log) == (log, [])


def test_the_ranges_outside_the_inputs_span_are_said_in_the_head_line():
    from quadobs.cli import _outside_inputs

    assert _outside_inputs({"placed": 10}, 4) == ""
    assert _outside_inputs({"before_the_first_input": 0, "after_the_last_step": 4}, 4) == ""
    line = _outside_inputs({"before_the_first_input": 76, "after_the_last_step": 1}, 4)
    assert line == " (76 before the first input: not replayed)"
    line = _outside_inputs({"before_the_first_input": 76, "after_the_last_step": 90}, 4)
    assert line == " (76 before the first input and 90 after the last step: not replayed)"


def test_anchors_in_one_plane_are_said_to_leave_a_mirror_image():
    from quadobs.testbed.logs.replay import anchor_plane, replayable_log

    flat = ANCHORS.copy()
    flat[:, 2] = 0.2
    assert anchor_plane(ANCHORS) is None
    assert anchor_plane(flat) == pytest.approx(0.0, abs=1e-12)
    tilted = flat @ np.array([[1.0, 0.0, 0.0], [0.0, 0.8, 0.6], [0.0, -0.6, 0.8]])  # any plane
    assert anchor_plane(tilted) == pytest.approx(0.0, abs=1e-12)
    assert anchor_plane(flat[:, :2]) is None  # a planar log has no mirror
    _, notes = replayable_log(dataclasses.replace(helix(), beacons=flat, truth=None))
    assert len(notes) == 1 and "mirror" in notes[0]  # (without the truth: the ranges are not
    # of these anchors, which the truth's notes would say)


def test_a_span_whose_anchors_heard_lie_in_one_plane_is_said():
    """The helix's fourth anchor silent for its first 4 s: the three heard then lie in one
    plane (as any three), and a note names the span and the anchors; heard throughout,
    nothing is said."""
    from quadobs.testbed.logs.replay import heard_plane_note, replayable_log

    log = helix()
    assert heard_plane_note(log) is None
    r = log.ranges
    keep = (r[:, RANGE.beacon] != 3) | (r[:, 0] >= 4.0)
    late = dataclasses.replace(log, ranges=r[keep], range_std=log.range_std[keep])
    note = (
        "the ranges from 0.01 to 4.01 s into the log name only anchors 0, 1, 2, which lie in one "
        "plane: there a position and its mirror image through it give the same ranges, so an "
        "estimate may settle on the mirror side (the other anchors switched on late, out of "
        "range or blocked?)"
    )
    assert heard_plane_note(late) == note and note in replayable_log(late)[1]
    quiet = (r[:, 0] < 3.0) | (r[:, 0] > 6.0)  # a radio's outage of 3 s: said as a gap alone
    outage = dataclasses.replace(log, ranges=r[quiet], range_std=log.range_std[quiet])
    assert heard_plane_note(outage) is None


def test_anchor_heights_turned_over_are_said_against_the_truth():
    """The helix's anchors written with their heights measured down from a 3.1 m ceiling:
    against the truth the ranges fit them turned over, and a note says so (and no other note
    on the truth); as given, nothing is said."""
    from quadobs.testbed.logs.replay import replayable_log, truth_heights_note

    log = helix()
    noisy = log.ranges.copy()
    noisy[:, 2] += 0.05 * np.random.default_rng(5).standard_normal(noisy.shape[0])
    log = dataclasses.replace(log, ranges=noisy)
    assert truth_heights_note(log) is None
    ceiling = ANCHORS.copy()
    ceiling[:, 2] = 3.1 - ANCHORS[:, 2]
    note = truth_heights_note(dataclasses.replace(log, beacons=ceiling))
    assert note.startswith(
        "against the truth, the ranges fit the anchors turned over in height (z -> 0.3 + 2.8 - z"
    )
    assert note.endswith("are beacons.csv's heights measured down from the ceiling, or the z "
                         "axis pointing down?")  # fmt: skip
    notes = replayable_log(dataclasses.replace(log, beacons=ceiling))[1]
    assert [n for n in notes if "truth" in n] == [note]  # not the truth moved, nor late


def test_a_loggers_held_ranges_are_left_out_and_each_range_kept_once():
    """Every anchor's latest range written at 100 Hz (each range five times or more): the
    copies go, and each range is kept once, at the logger's first time after its own."""
    from quadobs.testbed.logs.posed import ranges_held
    from quadobs.testbed.logs.replay import replayable_log

    log = helix()
    held = ranges_held(log, 100.0)
    back, notes = replayable_log(held)
    assert len(notes) == 1 and notes[0].startswith(
        "ranges that repeat their anchor's previous value exactly (a logger writing held values, or rows written twice), "
        f"left out: {held.ranges.shape[0] - back.ranges.shape[0]} of {held.ranges.shape[0]}"
    )
    r, b = log.ranges, back.ranges
    for anchor in log.beacon_ids:
        mine, kept = r[r[:, 1] == anchor], b[b[:, 1] == anchor]
        assert np.array_equal(kept[:, 2], mine[: kept.shape[0], 2])  # each once, in order
        late = kept[:, 0] - mine[: kept.shape[0], 0]
        assert np.all((late > -1e-9) & (late < 0.01 + 1e-9))
    assert b.shape[0] >= r.shape[0] - 4  # but the last range of each anchor, after the end


def test_ranges_at_a_coarse_resolution_are_not_taken_for_held_ones():
    """Ranges written to the centimetre, to 5 cm and to 10 cm (where a fifth of them repeat
    their anchor's previous one by chance, past the share alone) repeat as a radio's do:
    kept, no note."""
    from quadobs.testbed.logs.replay import repeated_values, replayable_log

    log = helix(40.0)
    for q in (0.01, 0.05, 0.1):
        r = log.ranges.copy()
        r[:, 2] = np.round(r[:, 2] / q) * q
        coarse = dataclasses.replace(log, ranges=r)
        repeat, expected = repeated_values(r[:, 1], r[:, 0], r[:, 2])
        assert repeat.sum() <= 5.0 * expected
        out, notes = replayable_log(coarse)
        assert out is coarse and notes == []


def test_held_differences_are_left_out_by_their_pair():
    """TDOA rows written three times each (at +0, +0.01 and +0.02 s): two of three go, by
    pair; the ranges beside them, as the radio gave them, are kept."""
    from quadobs.testbed.logs.replay import without_held_ranges

    log = helix()
    r = log.ranges
    pairs = np.column_stack([r[:, 1], (r[:, 1] + 1) % 4])
    tdoa = np.column_stack([r[:, 0], pairs, r[:, 2] - 2.0])
    held = np.vstack([tdoa + [dt, 0, 0, 0] for dt in (0.0, 0.01, 0.02)])
    held = held[np.argsort(held[:, 0], kind="stable")]
    withheld = dataclasses.replace(log, tdoa=held, tdoa_std=np.full(held.shape[0], 0.05))
    back, notes = without_held_ranges(withheld)
    assert len(notes) == 1 and notes[0].startswith(
        f"tdoa that repeat their pair's previous value exactly (a logger writing held values, or rows written twice), "
        f"left out: {2 * tdoa.shape[0]} of {held.shape[0]} (at the values' resolution a radio "
        "repeats about "
    )
    assert np.array_equal(back.tdoa, tdoa) and np.array_equal(back.ranges, log.ranges)


def test_a_truth_of_zeros_where_the_motion_capture_lost_the_body_is_left_out(plain):
    """Three spells of the truth's rows written as zeros (3 m from the origin on the helix):
    left out with a note, the replay scored on the rest as the plain log nearly is; a row at
    the origin between rows near it (a vehicle passing through) is kept."""
    from quadobs.testbed.logs.replay import replayable_log, without_lost_truth

    log = helix()
    truth = log.truth.copy()
    t = truth[:, 0]
    lost = ((t > 2.5) & (t < 3.0)) | ((t > 4.0) & (t < 4.6)) | ((t > 6.0) & (t < 6.3))
    truth[lost, 1:4] = 0.0
    back, notes = replayable_log(dataclasses.replace(log, truth=truth))
    assert notes[0] == (
        f"truth: {lost.sum()} rows at exactly the origin between rows farther than 0.25 m "
        "from it (a motion capture that lost the body), left out: the truth has a gap there "
        "(interpolated across where short)"
    )
    assert len(notes) == 2 and notes[1].startswith("truth: a gap of 0.6")  # the widest spell
    assert np.array_equal(back.truth, log.truth[~lost])
    assert _replay(back)["rmse"] == pytest.approx(plain[1]["rmse"], rel=0.05)
    through = log.truth.copy()
    through[:, 1:4] -= through[100, 1:4]  # the origin moved onto the path at row 100
    passing = dataclasses.replace(log, truth=through)
    assert without_lost_truth(passing) == (passing, None)


def test_blank_rows_and_stamps_a_little_out_of_order_replay_as_the_plain_log(tmp_path, plain):
    """A motion capture's lost frames and a radio's failed exchanges written as empty cells,
    and an input file whose host stamps jitter past one another by up to 15 ms: the rows
    without a value are left out and the rest sorted, each said in a line ahead of the
    replay's notes; the figures are those of the plain log without the rows left out."""
    from quadobs.testbed.logs.replay import replayable_log

    log = helix()
    folder = write_log(log, tmp_path / "awkward")
    lines = (folder / "truth.csv").read_text().splitlines()
    lost = list(range(120, 140)) + list(range(300, 305))  # data rows
    for k in lost:
        cells = lines[k + 1].split(",")
        lines[k + 1] = ",".join(cells[:1] + [""] * (len(cells) - 1))
    (folder / "truth.csv").write_text("\n".join(lines) + "\n")
    lines = (folder / "ranges.csv").read_text().splitlines()
    failed = [10, 11, 50]
    for k in failed:
        lines[k + 1] = lines[k + 1].split(",")[0] + "," + lines[k + 1].split(",")[1] + ",nan,"
    (folder / "ranges.csv").write_text("\n".join(lines) + "\n")
    lines = (folder / "inputs.csv").read_text().splitlines()
    swaps = list(range(20, 300, 25))
    for k in swaps:  # each row written a little before the one above it
        lines[k + 1], lines[k + 2] = lines[k + 2], lines[k + 1]
    (folder / "inputs.csv").write_text("\n".join(lines) + "\n")
    read = read_log(folder)
    assert read.read_notes == (
        "ranges.csv: 3 rows with an empty or NaN value left out (no measurement)",
        f"inputs.csv: {len(swaps)} rows stamped before an earlier row (by up to 0.02 s) "
        "sorted by time",
        "truth.csv: 25 rows with an empty or NaN value left out (no measurement)",
    )
    assert np.array_equal(read.inputs, read_log(plain[0]).inputs)
    plain_log = read_log(plain[0])
    expected = dataclasses.replace(
        plain_log,
        ranges=np.delete(plain_log.ranges, failed, axis=0),
        range_std=np.delete(plain_log.range_std, failed),
        truth=np.delete(plain_log.truth, lost, axis=0),
    )
    _, notes = replayable_log(read)
    assert notes[:3] == list(read.read_notes)
    figures, same = _replay(read), _replay(expected)
    for timed in ("seconds_per_measurement",):
        figures.pop(timed), same.pop(timed)
    assert figures == same
    assert figures["rmse"] == pytest.approx(plain[1]["rmse"], rel=0.05)


def test_a_truth_holding_a_lost_bodys_last_pose_is_left_out(plain):
    """Three spells where the motion capture repeated its last pose: the copies are left out
    with a note (the last pose seen kept), the replay scored on the rest as the plain log
    nearly is. A vehicle at rest that moves off, and a truth written at six times its rate,
    repeat their positions too and keep every row."""
    from quadobs.testbed.logs.replay import replayable_log, without_held_truth

    log = helix()
    truth = log.truth.copy()
    t = truth[:, 0]
    held = np.zeros(t.size, dtype=bool)
    for start, end in ((2.5, 3.0), (4.0, 4.6), (6.0, 6.3)):
        spell = np.flatnonzero((t > start) & (t < end))
        truth[spell, 1:] = truth[spell[0] - 1, 1:]
        held[spell] = True
    back, notes = replayable_log(dataclasses.replace(log, truth=truth))
    assert notes[0] == (
        f"truth: {held.sum()} rows over 3 spells (the longest 0.58 s) repeating the position "
        "before them exactly, each ended by a step faster than 3 times the truth's speed "
        "elsewhere (a motion capture holding a lost body's last pose), left out: the truth has "
        "a gap there (interpolated across where short)"
    )
    assert np.array_equal(back.truth, log.truth[~held])
    assert _replay(back)["rmse"] == pytest.approx(plain[1]["rmse"], rel=0.05)
    assert _replay(dataclasses.replace(log, truth=truth))["rmse"] > 1.1 * plain[1]["rmse"]
    resting = log.truth.copy()
    s = np.clip(t - 2.0, 0.0, None)  # at rest for 2 s, then off at 0.5 m/s^2
    resting[:, 1:4] = np.column_stack([0.25 * s**2, 0 * s, 1.0 + 0 * s])
    moving_off = dataclasses.replace(log, truth=resting)
    assert without_held_truth(moving_off) == (moving_off, None)
    coarse = log.truth.copy()
    coarse[:, 1:] = coarse[(np.arange(t.size) // 6) * 6, 1:]  # each pose written six times
    upsampled = dataclasses.replace(log, truth=coarse)
    assert without_held_truth(upsampled) == (upsampled, None)


def test_a_radios_codes_of_no_range_are_left_out_and_named(plain):
    """655.35 m and 999 m three times each and -1 m once among the helix's ranges (its anchors
    17 m apart at most): left out, the codes named by count, and the replay is the plain
    log's; a short range below zero (an antenna delay), a code written once and distinct
    ranges far beyond the anchors (a tag far from them) are kept."""
    from quadobs.testbed.logs.replay import replayable_log, without_impossible_ranges

    log = helix()
    ranges, std = log.ranges.copy(), log.range_std.copy()
    codes = {10: 655.35, 30: 655.35, 50: 655.35, 70: 999.0, 90: 999.0, 110: 999.0, 130: -1.0}
    for k in sorted(codes, reverse=True):
        ranges = np.insert(ranges, k, [ranges[k, 0], ranges[k, 1], codes[k]], axis=0)
        std = np.insert(std, k, 0.05)
    back, notes = replayable_log(dataclasses.replace(log, ranges=ranges, range_std=std))
    bound = 2.0 * np.max(np.linalg.norm(ANCHORS[:, None] - ANCHORS[None], axis=2))
    assert notes == [
        f"ranges of -1 m or less, or one value repeated beyond {bound:.4g} m (2 times the "
        "anchors' extent), which no radio measures (a code of no range), left out: 7 "
        "(655.35 m (3), 999 m (3), -1 m (1))"
    ]
    assert np.array_equal(back.ranges, log.ranges) and np.array_equal(back.range_std, log.range_std)
    assert _replay(back)["rmse"] == pytest.approx(plain[1]["rmse"], rel=1e-12)
    short = log.ranges.copy()
    short[0, 2], short[5, 2] = -0.4, 655.35
    short[10:40, 2] += 100.0  # a tag 100 m off: distinct values
    kept = dataclasses.replace(log, ranges=short)
    assert without_impossible_ranges(kept) == (kept, None)


def test_stamps_coarser_than_the_sampling_are_refused_naming_the_file(tmp_path):
    """Inputs stamped in bursts of five (80 % of the rows share a time with other values) and
    ranges stamped to whole seconds are refused naming the file (written or read); inputs at 50 Hz stamped to
    30 ms (a third of them share one) and a round of ranges to several anchors at one time
    (a grid) are read."""
    log = helix()
    burst = log.inputs.copy()
    burst[:, 0] = burst[(np.arange(burst.shape[0]) // 5) * 5, 0]
    with pytest.raises(QuadobsError, match=r"inputs.csv: 320 of 400 rows share their time"):
        write_log(dataclasses.replace(log, inputs=burst), tmp_path / "burst")
    ranges = log.ranges.copy()
    ranges[:, 0] = np.floor(ranges[:, 0])
    with pytest.raises(
        QuadobsError,
        match=r"ranges.csv: \d+ of 160 rows share their time with a row of the same id",
    ):
        write_log(dataclasses.replace(log, ranges=ranges), tmp_path / "seconds")
    coarse = log.inputs.copy()
    coarse[:, 0] = np.floor(coarse[:, 0] / 0.03 + 1e-9) * 0.03
    grid = log.ranges.copy()
    grid[:, 0] = grid[(np.arange(grid.shape[0]) // 4) * 4, 0]  # four anchors at one time
    folder = write_log(dataclasses.replace(log, inputs=coarse, ranges=grid), tmp_path / "fine")
    back = read_log(folder)
    assert np.array_equal(back.inputs, coarse) and np.array_equal(back.ranges, grid)


def test_rows_stamped_zero_before_a_clock_was_set_are_named():
    """Three inputs stamped 0 beside a log on unix time (an unset stamp): refused naming the
    rows, not taken for nanoseconds."""
    log = helix()
    t0 = 1.7e9
    inputs = log.inputs + [t0, 0, 0, 0]
    inputs[:3, 0] = 0.0
    with pytest.raises(
        QuadobsError,
        match=r"helix: inputs.csv: 3 rows stamped 0 \(the first at row 2\) beside times from 1700000000.06 s",
    ):
        dataclasses.replace(
            log,
            ranges=log.ranges + [t0, 0, 0],
            inputs=inputs,
            truth=log.truth + np.r_[t0, np.zeros(6)],
        )


def test_a_truth_off_the_anchors_origin_is_said_in_a_note():
    """The helix's truth moved by (0.5, 0, 0) m: the note finds about (-0.5, 0) m back across
    the horizontal (within 0.1 m; the height is not searched); as given, and moved by 0.2 m
    (within what unmoved logs fit), nothing is said."""
    import re

    from quadobs.testbed.logs.replay import truth_offset_note

    log = helix(40.0)
    assert truth_offset_note(log) is None
    for shift, said in ((0.2, False), (0.5, True)):
        truth = log.truth.copy()
        truth[:, 1] += shift
        note = truth_offset_note(dataclasses.replace(log, truth=truth))
        assert (note is not None) == said
    assert note is not None and note.startswith(
        "against the ranges, truth.csv fits best moved by ("
    )
    found = np.array([float(v) for v in re.search(r"moved by \(([^)]*)\)", note)[1].split(",")])
    assert found.size == 2 and abs(found[0] + 0.5) <= 0.1 and abs(found[1]) <= 0.1


def test_inputs_on_another_clock_are_refused_or_said():
    """Inputs an hour late overlap no range: refused naming the file and the hour, unless moved
    back by the offset given; a truth 100 s late likewise; inputs 3 s late (of 8 s) leave 3 s
    of ranges before them: said, with --clock-offset, and not once that offset is given."""
    from quadobs.testbed.logs.clock_offset import with_input_offset
    from quadobs.testbed.logs.replay import check_clock_overlap, replayable_log

    log = helix()
    late = dataclasses.replace(log, inputs=log.inputs + [3600.0, 0, 0, 0])
    with pytest.raises(
        QuadobsError, match=r"helix: inputs.csv: its times .* \+3600 s at the start\)"
    ):
        check_clock_overlap(late)
    check_clock_overlap(with_input_offset(late, 3600.0))  # moved back by --clock-offset 3600
    far = dataclasses.replace(log, truth=log.truth + np.r_[100.0, np.zeros(6)])
    with pytest.raises(QuadobsError, match=r"helix: truth.csv: its times"):
        check_clock_overlap(far)
    late = dataclasses.replace(log, inputs=log.inputs + [3.0, 0, 0, 0])
    notes = replayable_log(late)[1]
    assert any(
        n.startswith("inputs.csv starts 2.99 s after the first measurement (60 before it)")
        and "--clock-offset SECONDS" in n
        for n in notes
    ), notes
    assert not any("starts" in n for n in replayable_log(log)[1])
    assert not any("starts" in n for n in replayable_log(late, clock_offset=3.0)[1])


def test_inputs_an_hour_late_replay_with_the_offset_given(tmp_path, capsys):
    """The CLI: refused without --clock-offset (naming the file), replayed with it."""
    from quadobs.cli import main

    log = helix()
    folder = write_log(
        dataclasses.replace(log, inputs=log.inputs + [3600.0, 0, 0, 0]), tmp_path / "late"
    )
    base = ["replay", str(folder), "--calibrate", "none", "--estimators", "ekf", "--no-progress"]
    assert main(base) == 2
    assert "inputs.csv: its times" in capsys.readouterr().err
    assert main([*base, "--clock-offset", "3600"]) == 0
    assert "starts" not in capsys.readouterr().out
