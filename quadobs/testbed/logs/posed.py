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

__all__ = ["posed_log", "tag_positions"]


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

    Returns
    -------
    RangeLog
        The posed log; ``beacons.csv`` stays planar.
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
    np.maximum(ranges[:, 2], 0.0, out=ranges[:, 2])  # a radio reports no negative range
    inputs = log.inputs.copy()
    inputs[:, 0] += float(odometry_offset)
    truth = log.truth.copy()  # type: ignore[union-attr]  # checked by tag_positions
    for table in (ranges, inputs, truth):
        table[:, 0] += float(time_base)
    return replace(log, ranges=ranges, inputs=inputs, truth=truth, source="")
