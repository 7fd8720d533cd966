"""The white noise of a log's ranges, read from the ranges themselves where the log states none.

A log converted by hand seldom has a ``std`` column in ``ranges.csv``, and the replay's round
prior for a radio range (``range_sigma`` = 1 m) is ten times a UWB radio's line-of-sight noise
(0.05 to 0.15 m): the filters then weigh every range ten times too little, their gates pass a
non-line-of-sight excess of a metre and more, and the bias states cannot be told from the
noise. A tag that ranges each anchor several times a second measures its own noise: between
three consecutive ranges to one anchor at ``t_(k-1) < t_k < t_(k+1)`` the motion is nearly
linear, so the interpolation residual

.. math::

    e_k = \\rho_k - (w \\rho_{k-1} + (1 - w) \\rho_{k+1}), \\qquad
    w = \\frac{t_{k+1} - t_k}{t_{k+1} - t_{k-1}},

of ranges with independent errors of standard deviation ``sigma`` has the variance
``sigma^2 (1 + w^2 + (1 - w)^2)`` (1.5 ``sigma^2`` for equal intervals), plus the motion's
curvature ``rho'' w (1 - w) (t_(k+1) - t_(k-1))^2 / 2``. The estimate is the normalised
residuals' median absolute value times 1.4826 (the standard deviation of a Gaussian; the
median leaves most of the non-line-of-sight excess and the outliers out: a tenth of the
ranges longer by 0.5 m spoils three residuals each and raises the figure by about 30 %,
``tests/testbed/test_range_noise.py``), pooled over the anchors (:func:`range_noise`).

It is a noise figure only where the motion's term is small against it, which the ranges
also show (the test of an Allan variance): the residuals over every other range (the span
doubled) keep the same spread where the noise dominates, and grow four times the motion's
part where the motion does. The estimate is taken where the doubled span's figure is at most
:data:`SPAN_RATIO` times the native one, that is where the motion's part is at most a fifth of
the noise (``(sigma^2 + 16 m^2) / (sigma^2 + m^2) <= 1.25^2`` gives ``m <= 0.197 sigma``).
Measured: the exported ``quadrotor-uwb-realistic`` flight (ranges at 100 Hz over 8 anchors,
0.1 m noise) gives 0.113 m native, 0.114 m at the doubled span; the Plaza logs (a car at 1 to
3.5 m/s ranged every 0.5 to 1 s per anchor) 0.55 / 0.91 m and 0.61 / 0.81 m: there the motion
dominates, and the prior stands.

The replay takes it for the logs of a body IMU and of wheel odometry
(:func:`~quadobs.testbed.logs.estimators.log_defaults`). On a wheeled robot in a small room
(``sims/replay_rover_room.py``, ranges without ``std``) it makes the replay behave as with the
radio's stated ``std``: the filters that model the heading, the lever arm and the anchors'
heights gain (the best default on the robot posed with every effect, 0.204 to 0.236 m with
the prior, 0.112 to 0.136 m with it), while the EKF and the plain observer, which lump the
heading's drift into the ranges' noise, lose as they do with a stated ``std``
(docs/error-sources.md).

Where the ranges to each anchor are sparser (a flight's tag ranging eight anchors at 10 to
20 Hz: each every 0.4 to 0.8 s), the linear interpolation's residual is the motion's and the
test fails; a body-IMU log then takes the residual against the cubic through each range's two
previous and two next ones (:func:`smooth_range_noise`; Lagrange weights ``w_i`` at ``t_k``,
the residual's variance ``sigma^2 (1 + sum w_i^2)``), in which the motion's curvature cancels,
where it passes the same test. Measured on the flight stand-in at 20 Hz
(``docs/error-sources.md``): seeds 0 and 2 fail the linear test (1.36 and 1.25 times at the
doubled span) and pass the cubic's (0.126 and 0.137 m, 1.13 and 1.02 times); at 10 Hz (seed 0)
both fail.
A wheel-odometry log keeps the linear test alone: Plaza2 passes the cubic's (0.57 m), and
replayed with that figure is mostly worse than with the prior (the best default 1.743 ->
1.798 m; docs/error-sources.md).

Each anchor's own figure (:func:`anchor_noise`) is the same estimate over that anchor's ranges
alone. Anchors differ: one whose path the room blocks most of the time has residuals of the
excess's changes as well as of the radio's noise (on the flight stand-ins,
``sims/stress_hidden_logs.py``, the anchor blocked for 82 % of its ranges shows 0.20 to 0.24 m
at 100 Hz and above, 0.14 to 0.19 m at 50 Hz; the others 0.10 to 0.18 m, pooled 0.13 to 0.14 m). The replay takes the log as if its ``std`` column
stated these figures (:func:`with_anchor_noise`): each range is weighed by its anchor's
figure, and what reads a log's stated noise reads them (the median of the ranges' ``std``:
the self-calibration's margin, the excess's core noise, the robust rules' scale); the pooled
figure stays the setup's ``range_sigma`` (the initial variance, the start's threshold, the
noise of a TDOA that states none). ``--tune anchor_sigma=0`` gives every range the pooled
figure, as before; a ``range_sigma`` the user sets is taken for every range.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from quadobs.testbed.logs.schema import RANGE

__all__ = [
    "MIN_ANCHOR_RESIDUALS",
    "MIN_RESIDUALS",
    "OWN_NOISE_KINDS",
    "SPAN_RATIO",
    "STATED_STD_RATIO",
    "anchor_noise",
    "range_noise",
    "smooth_range_noise",
    "stated_range_noise",
    "stated_std_note",
    "with_anchor_noise",
    "with_checked_std",
]

#: The largest ratio of the doubled span's figure to the native one for the figure to be the
#: ranges' noise (module docstring).
SPAN_RATIO = 1.25

#: The fewest interpolation residuals (over all anchors) for an estimate: the median's relative
#: standard error is ``1.25 / sqrt(n)``, 6 % at 400 (a few seconds of a tag's ranges).
MIN_RESIDUALS = 400

#: The fewest residuals of one anchor for its own figure (:func:`anchor_noise`): the median's
#: relative standard error ``1.25 / sqrt(n)`` is 12.5 % at 100 (a few seconds of one anchor
#: in a tag's round-robin); an anchor with fewer takes the pooled figure.
MIN_ANCHOR_RESIDUALS = 100

#: The logs whose ranges give their own noise where they state none: a body IMU's and wheel
#: odometry's (:func:`~quadobs.testbed.logs.estimators.log_defaults`).
OWN_NOISE_KINDS = ("imu_body", "odometry")


def _by_anchor(times, anchors, ranges, step: int, residual, fewest: int) -> np.ndarray:
    """``residual(t, r)`` over every ``step``-th range to each anchor with at least ``fewest``."""
    out = []
    for h in np.unique(anchors):
        pick = np.flatnonzero(anchors == h)[::step]
        if pick.size >= fewest:
            out.append(residual(times[pick], ranges[pick]))
    return np.concatenate(out) if out else np.empty(0)


def _linear(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The normalised interpolation residuals ``e_k / sqrt(1 + w^2 + (1 - w)^2)`` of one
    anchor's ranges ``r`` at ``t`` (module docstring)."""
    span = t[2:] - t[:-2]
    ok = span > 0.0
    w = (t[2:] - t[1:-1])[ok] / span[ok]
    e = r[1:-1][ok] - (w * r[:-2][ok] + (1.0 - w) * r[2:][ok])
    return e / np.sqrt(1.0 + w * w + (1.0 - w) ** 2)


def _cubic(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The normalised residuals ``e_k / sqrt(1 + sum_i w_i^2)`` of one anchor's ranges against
    the cubic through each one's two previous and two next (Lagrange weights ``w_i`` at
    ``t_k``; windows whose times do not increase strictly are left out)."""
    near = np.stack([t[:-4], t[1:-3], t[3:-1], t[4:]])
    ok = np.all(np.diff(np.vstack([near[:2], t[2:-2], near[2:]]), axis=0) > 0.0, axis=0)
    near, t0 = near[:, ok], t[2:-2][ok]
    w = np.ones_like(near)
    for i in range(4):
        for j in range(4):
            if i != j:
                w[i] *= (t0 - near[j]) / (near[i] - near[j])
    rows = np.stack([r[:-4], r[1:-3], r[3:-1], r[4:]])[:, ok]
    e = r[2:-2][ok] - np.sum(w * rows, axis=0)
    return e / np.sqrt(1.0 + np.sum(w * w, axis=0))


def _residuals(times: np.ndarray, anchors: np.ndarray, ranges: np.ndarray, step: int) -> np.ndarray:
    """:func:`_linear` of every ``step``-th range to each anchor (module docstring)."""
    return _by_anchor(times, anchors, ranges, step, _linear, 3)


def _cubic_residuals(
    times: np.ndarray, anchors: np.ndarray, ranges: np.ndarray, step: int
) -> np.ndarray:
    """:func:`_cubic` of every ``step``-th range to each anchor (:func:`smooth_range_noise`)."""
    return _by_anchor(times, anchors, ranges, step, _cubic, 5)


def _noise(ranges: np.ndarray, residuals=_residuals) -> tuple[float, float, int]:
    """:func:`range_noise` of the rows ``ranges`` (``time, beacon, range``), by ``residuals``."""
    t, h, r = ranges[:, RANGE.time], ranges[:, RANGE.beacon], ranges[:, RANGE.range]
    figures = []
    for step in (1, 2):
        e = residuals(t, h, r, step)
        figures.append(1.4826 * float(np.median(np.abs(e))) if e.size else float("nan"))
        if step == 1:
            n = int(e.size)
    return figures[0], figures[1], n


def range_noise(log) -> tuple[float, float, int]:
    """``(sigma, sigma_2, n)``: the ranges' noise estimated at the native span and at the doubled
    one (m; NaN where fewer than three ranges to any anchor), and the number of native
    residuals (module docstring)."""
    return _noise(log.ranges)


def smooth_range_noise(log) -> tuple[float, float, int]:
    """:func:`range_noise` against the cubic through each range's two previous and two next
    ranges to its anchor (module docstring): the motion's curvature cancels, so that sparser
    ranges show their noise; the variance of the residual is ``sigma^2 (1 + sum w_i^2)``
    (1.94 ``sigma^2`` for equal intervals)."""
    return _noise(log.ranges, _cubic_residuals)


def is_noise(figures: tuple[float, float, int], fewest: int = MIN_RESIDUALS) -> bool:
    """Whether ``(sigma, sigma_2, n)`` is the noise: at least ``fewest`` residuals, the doubled
    span's figure within :data:`SPAN_RATIO` of the native one, positive."""
    sigma, sigma_2, n = figures
    return n >= fewest and 0.0 < sigma and sigma_2 <= SPAN_RATIO * sigma


def _pooled(log) -> tuple | None:
    """``(sigma, residuals)``: :func:`stated_range_noise` and the residuals that gave it
    (linear, or the cubic's), or None."""
    if log.ranges.shape[0] == 0 or not np.all(np.isnan(log.range_std)):
        return None
    kinds = (_residuals, _cubic_residuals) if log.input_kind == "imu_body" else (_residuals,)
    for residuals in kinds:
        figures = _noise(log.ranges, residuals)
        if is_noise(figures):
            return figures[0], residuals
    return None


def stated_range_noise(log) -> float | None:
    """The ranges' standard deviation (m) for a log whose ``ranges.csv`` states none: the
    estimate of :func:`range_noise` where it is the noise (at least :data:`MIN_RESIDUALS`
    residuals, the doubled span's figure within :data:`SPAN_RATIO` of it, positive); else, on a
    body-IMU log, that of :func:`smooth_range_noise` where it is; else None (the setup's prior
    ``range_sigma`` stands). None also where any range states its own."""
    pooled = _pooled(log)
    return None if pooled is None else pooled[0]


def anchor_noise(log) -> np.ndarray | None:
    """Each anchor's own noise (m, in :attr:`~quadobs.testbed.logs.format.RangeLog.beacons`
    order): the estimate of the pooled figure (:func:`stated_range_noise`: the linear
    residuals, or the cubic's) over its ranges alone where they show it (at least
    :data:`MIN_ANCHOR_RESIDUALS` residuals, the doubled span's figure within
    :data:`SPAN_RATIO` of it), else the pooled figure; None where the pooled figure is not
    the noise or the log states its own."""
    pooled = _pooled(log)
    return None if pooled is None else _anchor_figures(log, *pooled)


def _anchor_figures(log, pooled: float, residuals) -> np.ndarray:
    """:func:`anchor_noise` given the pooled figure and the residuals that gave it."""
    index = log.beacon_index(log.ranges[:, RANGE.beacon])
    out = np.full(log.beacons.shape[0], pooled)
    for h in range(out.size):
        figures = _noise(log.ranges[index == h], residuals)
        if is_noise(figures, MIN_ANCHOR_RESIDUALS):
            out[h] = figures[0]
    return out


def with_anchor_noise(log, options: dict) -> tuple:
    """``(log, options, note)``: a log of :data:`OWN_NOISE_KINDS` whose ranges state no ``std``
    with each range given its anchor's own noise (:func:`anchor_noise`), and ``options`` with
    ``range_sigma`` the pooled figure (module docstring); the note names each anchor's figure
    by its id. The log and ``options`` as given, and no note, where the user set
    ``range_sigma`` or ``anchor_sigma=0``, or where the ranges do not show their noise. A
    log of those kinds that states a ``std`` has it checked per anchor
    (:func:`with_checked_std`)."""
    if log.input_kind in OWN_NOISE_KINDS and not np.all(np.isnan(log.range_std)):
        checked, note = with_checked_std(log, options)
        return checked, options, note
    if "range_sigma" in options or not options.get("anchor_sigma", 1.0):
        return log, options, None
    found = _pooled(log) if log.input_kind in OWN_NOISE_KINDS else None
    if found is None:
        return log, options, None
    pooled = found[0]
    sigma = _anchor_figures(log, *found)
    std = sigma[log.beacon_index(log.ranges[:, RANGE.beacon])]
    figures = ", ".join(f"{int(i)}: {s:.3f}" for i, s in zip(log.beacon_ids, sigma, strict=True))
    note = (
        "ranges' noise by anchor, from their own ranges (no std stated; --tune anchor_sigma=0 "
        f"pools them): {figures} m (pooled {pooled:.3f} m)"
    )
    return dataclasses.replace(log, range_std=std), {**options, "range_sigma": pooled}, note


#: How far (a factor either way) the stated range std may lie from the ranges' own noise
#: before :func:`stated_std_note` says so.
STATED_STD_RATIO = 5.0


def stated_std_note(log) -> str | None:
    """A line where the ranges' stated std (``ranges.csv``'s ``std``, its median) lies more
    than :data:`STATED_STD_RATIO` times from the ranges' own noise
    (:func:`~quadobs.testbed.logs.range_noise.range_noise`, where it is the noise), else
    None: every filter corrects with the stated std, so one in another unit, or a datasheet's
    figure far from the radio's, weighs the ranges wrongly."""
    stated = log.range_std[np.isfinite(log.range_std)]
    if stated.size == 0:
        return None
    figures = range_noise(log)
    if not is_noise(figures):
        return None
    median, noise = float(np.median(stated)), float(figures[0])
    if 1.0 / STATED_STD_RATIO <= median / noise <= STATED_STD_RATIO:
        return None
    return (
        f"ranges.csv states a std of {median:.3g} m (median), where the ranges' own noise is "
        f"{noise:.3g} m: every filter corrects with the stated std (is it in metres?)"
    )


def with_checked_std(log, options: dict) -> tuple:
    """``(log, note)``: a log whose ``ranges.csv`` states a ``std``, with the ranges of each
    anchor whose stated std (its median) lies more than :data:`STATED_STD_RATIO` times from
    that anchor's own noise (:func:`anchor_noise`, read as if no std were stated) weighed by
    its own noise instead, and a note naming them.

    An anchor's stated std is taken for wrong where it lies that far from the anchor's own
    noise and either the stated std's median lies that far from the pooled noise (every
    anchor stated in another unit, or a datasheet's figure) or the anchor's stated std lies
    that far from the median of the others' (a per-anchor figure of a firmware): an anchor
    whose path is blocked for most of a log reads a noise of its excess's changes, and the
    radio's one figure, stated on every anchor alike, stays (a robot's anchor blocked
    throughout, its own figure 0.415 m against the 0.08 m stated: 0.090 m as stated, 0.115 m
    weighed by its own figure).

    A stated std ten times too small on three of a flight's eight anchors (a firmware's
    per-anchor precision) made every filter trust those ranges past their noise: the best
    default 0.176 -> 0.675 m, with no note, since the median over all anchors agreed
    (docs/replaying-your-data.md); ten times too small on all, four filters diverged (0.552
    m). The log as given, and :func:`stated_std_note` (a pooled check), where the user keeps
    the stated std (``--tune stated_std=1``, or ``range_sigma``, ``anchor_sigma=0``) or where
    the ranges do not show their noise."""
    kept = "range_sigma" in options or not options.get("anchor_sigma", 1.0)
    found = None
    if not (kept or options.get("stated_std", 0.0)):
        found = _pooled(dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], np.nan)))
    if found is None:
        return log, stated_std_note(log)
    own = _anchor_figures(log, *found)
    index = log.beacon_index(log.ranges[:, RANGE.beacon])
    std = log.range_std.copy()
    stated = float(np.nanmedian(std))
    everywhere = _apart(stated, found[0])  # a unit's or a datasheet's figure for the radio
    off = []
    for h in range(own.size):
        rows = (index == h) & np.isfinite(std)
        if not rows.any():
            continue
        median = float(np.median(std[rows]))
        if _apart(median, own[h]) and (everywhere or _apart(median, stated)):
            off.append((h, median))
            std[index == h] = own[h]
    if not off:
        return log, None
    ids = ", ".join(str(int(log.beacon_ids[h])) for h, _ in off)
    given = ", ".join(f"{s:.3g}" for _, s in off)
    figures = ", ".join(f"{own[h]:.3g}" for h, _ in off)
    note = (
        f"ranges.csv's std of anchor{'s' if len(off) > 1 else ''} {ids} ({given} m, median) "
        f"lies more than {STATED_STD_RATIO:g} times from the ranges' own noise ({figures} m): "
        "those ranges weighed by their own noise (--tune stated_std=1 keeps the std stated; "
        "is it in metres, and the radio's?)"
    )
    return dataclasses.replace(log, range_std=std), note


def _apart(a: float, b: float) -> bool:
    """Whether ``a`` and ``b`` (positive) lie more than :data:`STATED_STD_RATIO` times apart."""
    return not 1.0 / STATED_STD_RATIO <= a / b <= STATED_STD_RATIO
