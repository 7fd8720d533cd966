"""A planar odometry log posed as a real one: 3-D ranges, a lever arm, clocks apart.

A log exported from a planar scenario (``rover-room``) holds what an ideal robot would log:
ranges in the plane of its anchors, from the point the truth tracks, every clock the same
and starting at zero. A real wheeled robot's log differs in ways that none of its files says:

* its anchors are mounted at other heights than its tag (``beacons.csv`` holds their plane
  survey only): each range is the 3-D distance

  .. math::

      \\rho_h = \\sqrt{|q - a_h|^2 + \\delta z_h^2}, \\qquad \\delta z_h = z_{a,h} - z_t ,

  so a filter of planar ranges sees an apparent bias ``sqrt(r^2 + dz^2) - r`` that shrinks as
  the horizontal distance ``r`` grows, no constant;
* the tag sits off the point the motion capture tracks (a lever arm ``l`` in the body frame,
  its x axis the heading ``theta``): ``q = p + R(theta) l``;
* the odometry's clock runs apart from the radio's (its samples stamped ``t + offset``);
* the time base is the computer's clock (Unix seconds, about 1.7e9 s), not zero.

:func:`posed_log` applies them to a log that holds the truth (``x, y, heading``): each range
keeps its own error (noise, bias, outlier) and has its geometry replaced (a negative result,
an outlier's near an anchor, read as zero, as a radio reports it),

.. math::

    \\tilde\\rho' = \\tilde\\rho - |p - a_h| + \\sqrt{|p + R(\\theta) l - a_h|^2 + \\delta z_h^2},

``p, theta`` the truth at the range's time (linear between the truth's rows). Nothing is
drawn: the same log gives the same posed log.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog

__all__ = [
    "accel_scaled",
    "anchor_gap",
    "behind_pillar",
    "blocked_by_pillar",
    "inputs_late",
    "log_start",
    "posed_log",
    "ranges_held",
    "started_at",
    "surveyed",
    "tag_pattern",
    "tag_positions",
    "truth_from",
]


def tag_positions(log: RangeLog, t: np.ndarray, lever_arm=(0.0, 0.0)) -> np.ndarray:
    """The tag's planar position ``p + R(theta) l`` at times ``t (M,)``, from the log's truth
    (``x, y, heading``, linear between rows, the heading unwrapped first): ``(M, 2)``."""
    if log.truth is None or tuple(log.truth_columns[:4]) != ("time", "x", "y", "heading"):
        raise QuadobsError(
            f"{log.name}: posing needs a planar truth with a heading (time, x, y, heading)"
        )
    tt = log.truth[:, 0]
    x = np.interp(t, tt, log.truth[:, 1])
    y = np.interp(t, tt, log.truth[:, 2])
    theta = np.interp(t, tt, np.unwrap(log.truth[:, 3]))
    lx, ly = (float(v) for v in lever_arm)
    c, s = np.cos(theta), np.sin(theta)
    return np.column_stack([x + c * lx - s * ly, y + s * lx + c * ly])


def posed_log(
    log: RangeLog,
    *,
    anchor_heights=None,
    tag_height: float = 0.0,
    lever_arm=(0.0, 0.0),
    odometry_offset: float = 0.0,
    time_base: float = 0.0,
    heights_stated: bool = False,
) -> RangeLog:
    """``log`` as a real robot would have logged it (module docstring).

    Parameters
    ----------
    log : RangeLog
        A planar odometry log with the truth ``time, x, y, heading`` (an exported ``rover-room``).
    anchor_heights : array_like (B,), optional
        Each anchor's height (m), in the order of ``log.beacons`` (default: ``tag_height``,
        the plane of the tag).
    tag_height : float
        The tag's height (m).
    lever_arm : (2,) array_like
        The tag's offset from the tracked point in the body frame (m, forward and left).
    odometry_offset : float
        Added to the odometry's time stamps (s): its clock ahead of the radio's.
    time_base : float
        Added to every time stamp (s), e.g. a Unix time.
    heights_stated : bool
        Whether the log states the heights it was posed with: ``beacons.csv`` with ``z`` (the
        anchors' heights) and ``meta.csv`` ``tag_height``, as a survey would give them.

    Returns
    -------
    RangeLog
        The posed log; ``beacons.csv`` stays planar unless ``heights_stated``.
    """
    if log.dimension != 2 or log.input_kind != "odometry":
        raise QuadobsError(f"{log.name}: posing takes a planar odometry log")
    heights = (
        np.full(log.beacons.shape[0], float(tag_height))
        if anchor_heights is None
        else np.asarray(anchor_heights, dtype=float)
    )
    if heights.shape != (log.beacons.shape[0],):
        raise QuadobsError(
            f"{log.name}: anchor_heights: expected {log.beacons.shape[0]} heights (one per "
            f"anchor), got {heights.size}"
        )
    ranges = log.ranges.copy()
    h = log.beacon_index(ranges[:, 1])
    truth_p = tag_positions(log, ranges[:, 0])
    tag = tag_positions(log, ranges[:, 0], lever_arm)
    a = log.beacons[h]
    dz = heights[h] - float(tag_height)
    planar = np.linalg.norm(truth_p - a, axis=1)
    ranges[:, 2] += np.sqrt(np.sum((tag - a) ** 2, axis=1) + dz**2) - planar
    np.maximum(ranges[:, 2], 0.0, out=ranges[:, 2])  # this posing's radio clamps at zero
    inputs = log.inputs.copy()
    inputs[:, 0] += float(odometry_offset)
    truth = log.truth.copy()  # type: ignore[union-attr]  # checked by tag_positions
    for table in (ranges, inputs, truth):
        table[:, 0] += float(time_base)
    posed = replace(log, ranges=ranges, inputs=inputs, truth=truth, source="")
    if heights_stated:
        return replace(posed, anchor_heights=heights, tag_height=float(tag_height))
    return posed


# Stresses: what a hidden real log may hold that the posed logs above do not. Each is one
# transform of a log (planar or 3-D), seeded where it draws; ``sims/stress_hidden_logs.py``
# applies them one at a time. Times are taken from the log's start, :func:`log_start`.


def log_start(log: RangeLog) -> float:
    """The log's first time stamp: its first range or input (s)."""
    firsts = [table[0, 0] for table in (log.ranges, log.inputs) if table.shape[0]]
    return float(min(firsts))


def surveyed(log: RangeLog, std: float, seed: int) -> RangeLog:
    """``beacons.csv`` as a tape or total-station survey gives it: each anchor's coordinates
    moved by ``N(0, std^2)`` per axis (drawn from ``seed``; stated heights of an odometry log
    too, drawn after the plane's), the ranges left as measured from the true anchors."""
    rng = np.random.default_rng(seed)
    beacons = log.beacons + std * rng.standard_normal(log.beacons.shape)
    if log.anchor_heights is None:
        return replace(log, beacons=beacons)
    heights = log.anchor_heights + std * rng.standard_normal(log.anchor_heights.shape)
    return replace(log, beacons=beacons, anchor_heights=heights)


def started_at(log: RangeLog, delay: float) -> RangeLog:
    """The log begun ``delay`` seconds after its start (a recording started while the vehicle
    moves): every range, input, attitude and truth row before ``log_start + delay`` removed;
    an odometry log's ``heading0`` is its heading at the new first input (:func:`_heading_at`)."""
    t0 = log_start(log) + float(delay)
    keep = log.ranges[:, 0] >= t0
    first = int(np.searchsorted(log.inputs[:, 0], t0))
    heading0 = _heading_at(log, first) if log.input_kind == "odometry" else log.heading0
    truth = None if log.truth is None else log.truth[log.truth[:, 0] >= t0]
    attitude = None if log.attitude is None else log.attitude[log.attitude[:, 0] >= t0]
    return replace(
        log, ranges=log.ranges[keep], range_std=log.range_std[keep], inputs=log.inputs[first:],
        heading0=heading0, truth=truth, attitude=attitude,
    )  # fmt: skip


def _heading_at(log: RangeLog, k: int) -> float:
    """An odometry log's heading at its ``k``-th input: the truth's (linear between rows,
    unwrapped) where the truth holds one, as the export states ``heading0``; else the heading
    dead-reckoned from ``heading0`` with the yaw rates before it."""
    t = log.inputs[k, 0]
    if log.truth is not None and "heading" in log.truth_columns:
        column = log.truth[:, log.truth_columns.index("heading")]
        return float(np.interp(t, log.truth[:, 0], np.unwrap(column)))
    step = np.diff(log.inputs[: k + 1, 0]) * log.inputs[:k, 2]
    return log.heading0 + float(np.sum(step))


def truth_from(log: RangeLog, delay: float, rate: float) -> RangeLog:
    """The truth as a motion capture started late gives it: from ``log_start + delay`` on, at
    ``rate`` Hz (the row at or after each tick), every column kept."""
    if log.truth is None:
        raise QuadobsError(f"{log.name}: truth_from needs a truth")
    rows = log.truth[log.truth[:, 0] >= log_start(log) + float(delay)]
    ticks = np.arange(rows[0, 0], rows[-1, 0], 1.0 / float(rate))
    picked = np.unique(np.minimum(np.searchsorted(rows[:, 0], ticks), rows.shape[0] - 1))
    return replace(log, truth=rows[picked])


def anchor_gap(log: RangeLog, index: int, start: float, length: float) -> RangeLog:
    """The ``index``-th anchor of ``beacons.csv`` silent over ``[start, start + length)``
    seconds from the log's start (an anchor that drops out: its ranges removed)."""
    t = log.ranges[:, 0] - log_start(log)
    silent = (log.ranges[:, 1] == log.beacon_ids[index]) & (t >= start) & (t < start + length)
    return replace(log, ranges=log.ranges[~silent], range_std=log.range_std[~silent])


def blocked_by_pillar(log: RangeLog, centre, radius: float) -> np.ndarray:
    """Which ranges pass through a vertical pillar of ``radius`` about ``centre`` ``(x, y)``:
    the horizontal segment from the truth's position at the range's time (linear between the
    truth's rows) to the anchor comes within ``radius`` of the pillar's axis, ``(M,)`` bool.

    With ``d = a - p`` and ``s = clip((c - p)^T d / |d|^2, 0, 1)``, the segment's nearest point
    to ``c`` is ``p + s d``."""
    if log.truth is None:
        raise QuadobsError(f"{log.name}: a pillar's shadow needs the truth's positions")
    t, cols = log.ranges[:, 0], log.truth_columns
    p = np.column_stack([np.interp(t, log.truth[:, 0], log.truth[:, cols.index(c)]) for c in "xy"])
    d = log.beacons[log.beacon_index(log.ranges[:, 1]), :2] - p
    c = np.asarray(centre, dtype=float)
    s = np.clip(np.sum((c - p) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p + s[:, None] * d - c, axis=1) < radius


def behind_pillar(log: RangeLog, centre, radius: float, excess: float, seed: int) -> RangeLog:
    """Non-line-of-sight bursts: each range blocked by the pillar (:func:`blocked_by_pillar`)
    longer by an exponential excess of mean ``excess`` m (drawn from ``seed``), so that every
    pass of the vehicle behind it lengthens one anchor's ranges for as long as it lasts."""
    blocked = blocked_by_pillar(log, centre, radius)
    ranges = log.ranges.copy()
    ranges[blocked, 2] += np.random.default_rng(seed).exponential(excess, int(blocked.sum()))
    return replace(log, ranges=ranges)


def accel_scaled(log: RangeLog, scale) -> RangeLog:
    """A body IMU whose accelerometer reads ``(1 + scale_i)`` times the specific force on axis
    ``i`` (a scale-factor error; gravity's reading scaled with it)."""
    if log.input_kind != "imu_body":
        raise QuadobsError(f"{log.name}: an accelerometer's scale needs a body IMU log")
    inputs = log.inputs.copy()
    inputs[:, 1:4] *= 1.0 + np.asarray(scale, dtype=float)
    return replace(log, inputs=inputs)


def inputs_late(log: RangeLog, offset: float, jitter: float, seed: int) -> RangeLog:
    """The inputs stamped ``offset`` seconds late against the ranges, each stamp moved by
    uniform jitter in ``+-jitter`` s (drawn from ``seed``) and the rows kept in time order."""
    inputs = log.inputs.copy()
    moved = offset + np.random.default_rng(seed).uniform(-jitter, jitter, inputs.shape[0])
    inputs[:, 0] += moved
    return replace(log, inputs=inputs[np.argsort(inputs[:, 0], kind="stable")])


def ranges_held(log: RangeLog, rate: float) -> RangeLog:
    """The ranges as a logger writes them that holds each anchor's latest range and writes
    every anchor's at ``rate`` Hz from the first range on (a flight controller's log block, a
    table of one column per anchor): each range repeated until its anchor's next, stamped at
    the logger's times; the stated ``std`` held with it."""
    r, std = log.ranges, log.range_std
    if r.shape[0] == 0:
        return log
    times = np.arange(r[0, 0], r[-1, 0], 1.0 / rate)
    rows, stds = [], []
    for anchor in log.beacon_ids:
        own = np.flatnonzero(r[:, 1] == anchor)
        latest = np.searchsorted(r[own, 0], times, side="right") - 1
        seen = latest >= 0
        rows.append(
            np.column_stack([times[seen], np.full(seen.sum(), anchor), r[own[latest[seen]], 2]])
        )
        stds.append(std[own[latest[seen]]])
    held, held_std = np.vstack(rows), np.concatenate(stds)
    order = np.lexsort((held[:, 1], held[:, 0]))
    return replace(log, ranges=held[order], range_std=held_std[order])


def _body_directions(log: RangeLog) -> np.ndarray:
    """The unit direction from the vehicle to each range's anchor in the body frame, at the
    range's time from the truth: ``(M, 2)`` rotated by the heading (linear between rows,
    unwrapped) in a planar log, ``(M, 3)`` by the attitude (spherical between rows) in space."""
    from scipy.spatial.transform import Rotation, Slerp

    t = log.ranges[:, 0]
    planar = log.dimension == 2
    position = log.truth_part("position")
    turn = "heading" if planar else "attitude"
    rotation = (
        log.truth[:, [log.truth_columns.index("heading")]]
        if planar and log.truth is not None and "heading" in log.truth_columns
        else None
        if planar
        else log.truth_part("attitude")
    )
    if position is None or rotation is None:
        raise QuadobsError(f"{log.name}: a tag's pattern needs the truth's position and {turn}")
    tt = log.truth[:, 0]  # type: ignore[index]  # checked with its parts
    t = np.clip(t, tt[0], tt[-1])
    p = np.column_stack([np.interp(t, tt, column) for column in position.T])
    d = log.beacons[log.beacon_index(log.ranges[:, 1]), : p.shape[1]] - p
    if planar:
        theta = np.interp(t, tt, np.unwrap(rotation[:, 0]))
        c, s = np.cos(theta), np.sin(theta)
        d = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    else:
        q = rotation[:, [1, 2, 3, 0]]  # scalar last, as scipy takes it
        d = Slerp(tt, Rotation.from_quat(q))(t).inv().apply(d)
    return d / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]


def tag_pattern(log: RangeLog, std: float, seed: int) -> RangeLog:
    """Each range longer by the tag's direction-dependent delay, fixed to the vehicle's body.

    A tag's antenna delays the signal by an amount that depends on the direction of the
    anchor seen from it in the body frame (the antenna's radiation pattern; the relative
    orientation of the two antennas in Ledergerber and D'Andrea's calibration of UWB ranges,
    IEEE Access 6, 2018, doi:10.1109/ACCESS.2018.2884720), so that the bias turns with the
    vehicle. The first-order term of that function is a lever arm (already posed); this is the
    second-order term, as the anchors' ``radio.pattern`` of :mod:`quadobs.testbed.uwb`:

    .. math::

        \\tilde\\rho' = \\tilde\\rho + u_b^T S u_b ,

    ``u_b`` the unit direction from the vehicle to the anchor in the body frame
    (:func:`_body_directions`, the truth's point taken for the tag's), ``S`` symmetric and
    traceless, drawn once from ``seed`` (the symmetric part of a standard normal matrix less
    its trace). In space ``S`` is 3 x 3 and scaled so that over directions uniform on the
    sphere the term's standard deviation is ``std`` (variance ``2 tr(S^2) / 15``); in the
    plane (an odometry log's heading) ``S`` is 2 x 2, the term a second harmonic
    ``a cos 2 phi + b sin 2 phi`` of the anchor's bearing ``phi`` from the heading, scaled so
    that over bearings uniform on the circle its standard deviation is ``std`` (variance
    ``tr(S^2) / 4``). Ranges of 0 m (nothing received) are left as they are.
    """
    if not std >= 0.0:
        raise QuadobsError(f"{log.name}: a tag's pattern needs a spread >= 0 m, got {std!r}")
    u = _body_directions(log)
    k = u.shape[1]
    g = np.random.default_rng(seed).standard_normal((k, k))
    form = 0.5 * (g + g.T)
    form -= np.trace(form) / k * np.eye(k)
    spread = np.sqrt(
        (np.trace(form @ form) / 4.0) if k == 2 else 2.0 * np.trace(form @ form) / 15.0
    )
    form *= std / spread
    ranges = log.ranges.copy()
    received = ranges[:, 2] > 0.0
    ranges[received, 2] += np.einsum("ni,ij,nj->n", u, form, u)[received]
    return replace(log, ranges=ranges)
