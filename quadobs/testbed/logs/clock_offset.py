"""The offset between the clock of a log's inputs and the clock of its ranges, from the log itself.

A flight controller stamps its IMU on its own clock and the UWB tag its ranges on another (or
on the time a host received them): an offset ``tau`` between the two moves every input by
``tau`` against the ranges. The replay holds the input sampled at ``t_i`` over ``[t_i,
t_(i+1))``; with the inputs stamped ``tau`` late, the estimator integrates ``a(t - tau)`` where
the vehicle flew ``a(t)``, an error ``tau \\dot a`` in the acceleration that the ranges must
correct (``tau`` times the speed's change, in position, after one correction interval).

The offset is a self-calibration step (:func:`estimate_clock_offset`), scored as the rest of
the calibration is (:mod:`quadobs.testbed.logs.calibration`): each candidate ``tau`` is the log
with its inputs moved by ``-tau`` (:func:`with_input_offset`), replayed in time through the
EKF, every :data:`~quadobs.testbed.logs.calibration.HOLD_OUT`-th range held out; the candidate
of the smallest held-out score is kept only if significantly better than ``tau = 0`` (the
paired test over blocks of held-out ranges, Bonferroni over every candidate tried), else the
offset stays zero.

The grid (:func:`offset_step`) is derived from the log's rates, not from its values: its step
``h`` is the longer of the inputs' median interval and the ranges' median interval (over all
anchors: finer than one range's worth of time, the ranges do not tell two offsets apart). The
search scores ``0`` and ``+-h``; where the better of ``+-h`` predicts the held-out ranges
significantly better than ``0`` (the paired test for one candidate), it goes on along that
side by steps of ``h`` (at most :data:`STEPS`) while each step is significantly better than
the one before, then halves the step :data:`REFINE` times about the best candidate. (A
looser rule, a step lower by more than one standard error, walked 13 steps on a flight along
a trend of 3e-5 m per step that the final test rejected.) Where neither ``+-h`` gains, the
offset stays zero after three replays; with fewer than :data:`HELD_MIN` held-out ranges
scored (:func:`held_out_count`), it stays zero after none. Every candidate replays the same
ranges (those at least the search's reach inside the inputs' span) and scores them from the
same time, so the candidates are compared range by range.

Which logs: those whose inputs drive the motion between ranges and carry their own times: a
body IMU or a navigation-frame accelerometer (models ``imu``). An odometry log could take the
same step; it is not run there (:func:`takes_offset`): the Plaza logs range a car every 0.5 to
1 s, so one range's worth of time is already longer than any offset the odometry's rate could
show, and the step would only add replays. A robot ranging at 16 Hz would show one, but not
to this scorer: on a robot's stand-in whose odometry was made 0.35 s late (its anchors above
the tag), the EKF predicted the held-out ranges to 0.875 m, and neither -63 ms nor +63 ms
differed from none by more than 0.001 m; `ukf-height-lever` replayed with the true lag gave
0.053 m against 0.114 m. A lag known in seconds is given as ``--clock-offset SECONDS``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "REFINE",
    "STEPS",
    "ClockOffset",
    "estimate_clock_offset",
    "held_out_count",
    "offset_step",
    "takes_offset",
    "with_input_offset",
]

#: The most steps the search goes along the better side (module docstring).
STEPS = 20
#: Fewer scored held-out ranges than this and the offset is not searched: the paired test
#: (:func:`~quadobs.testbed.logs.calibration.compare`) needs three blocks of two.
HELD_MIN = 3 * 2
#: The halvings of the step about the best candidate.
REFINE = 2


def takes_offset(log, model: str) -> bool:
    """Whether :func:`estimate_clock_offset` runs on ``log`` replayed with ``model``: a log of
    ranges whose inputs are an acceleration (module docstring)."""
    return (
        model == "imu"
        and log.input_kind in ("imu", "imu_body")
        and log.ranges.shape[0] > 0
        and log.inputs.shape[0] > 1
    )


def with_input_offset(log, tau: float):
    """``log`` with its inputs stamped ``tau`` seconds earlier (and its attitude, which comes
    from the same unit): the inputs of a log whose inputs are stamped ``tau`` late, moved onto
    the ranges' clock. ``tau = 0``: ``log`` itself."""
    if tau == 0.0 or log.input_kind == "none":
        return log
    inputs = log.inputs.copy()
    inputs[:, 0] -= tau
    attitude = log.attitude
    if attitude is not None:
        attitude = attitude.copy()
        attitude[:, 0] -= tau
    return dataclasses.replace(log, inputs=inputs, attitude=attitude)


def _median_interval(times: np.ndarray) -> float:
    d = np.diff(np.sort(np.asarray(times, dtype=float)))
    d = d[d > 0.0]
    return float(np.median(d)) if d.size else math.nan


def offset_step(log) -> float:
    """``h`` (s): the longer of the inputs' and the ranges' median intervals (module docstring)."""
    return float(
        np.nanmax([_median_interval(log.inputs[:, 0]), _median_interval(log.ranges[:, 0])])
    )


@dataclass
class ClockOffset:
    """What :func:`estimate_clock_offset` chose and why.

    Attributes
    ----------
    offset : float
        ``tau`` (s): how late the inputs are stamped against the ranges (0: none applied).
    candidate : float
        The candidate of the smallest held-out score, applied or not.
    step : float
        The grid's step ``h`` (s, :func:`offset_step`).
    scores : dict
        The held-out score (m) of every offset tried, ``{tau: score}``.
    test : dict
        The paired test of ``candidate`` against zero
        (:meth:`~quadobs.testbed.logs.calibration.Comparison.as_dict`).
    reason : str
        What was chosen and why.
    """

    offset: float
    candidate: float
    step: float
    scores: dict = field(default_factory=dict)
    test: dict = field(default_factory=dict)
    reason: str = ""

    def summary(self) -> dict:
        """As plain data, for the replay's summary."""
        return {
            "offset": self.offset,
            "candidate": self.candidate,
            "step": self.step if math.isfinite(self.step) else None,
            "scores": {f"{k:.6g}": v for k, v in sorted(self.scores.items())},
            "test": self.test,
        }


def held_out_count(times: np.ndarray, start: float) -> int:
    """How many of the ranges at ``times`` (s) the calibration holds out and scores: every
    :data:`~quadobs.testbed.logs.calibration.HOLD_OUT`-th range in time (the replay's count),
    of those at ``start`` (s) or later."""
    from quadobs.testbed.logs.calibration import HOLD_OUT

    t = np.sort(np.asarray(times, dtype=float))
    held = np.arange(t.size) % HOLD_OUT == HOLD_OUT // 2
    return int(np.count_nonzero(held & (t >= start)))


def _interior(log, margin: float):
    """``log`` with only the ranges at least ``margin`` seconds inside its inputs' span: every
    candidate offset up to ``margin`` then replays the same ranges."""
    t = log.ranges[:, 0]
    keep = (t >= log.inputs[0, 0] + margin) & (t <= log.inputs[-1, 0] - margin)
    return dataclasses.replace(log, ranges=log.ranges[keep], range_std=log.range_std[keep])


def estimate_clock_offset(
    log, *, dt: float = 0.1, model: str = "imu", estimator: str = "ekf", setup_options=None
) -> ClockOffset:
    """The inputs' clock offset ``tau`` against the ranges (module docstring).

    The candidates replay the ranges at least the largest offset the search may reach inside
    the inputs' span, and score them from the same time, :data:`SCORED_FROM` of the log: every
    candidate predicts the same held-out ranges.
    """
    from quadobs.testbed.logs.calibration import (
        SCORED_FROM,
        _cap,
        _metres,
        compare,
        prediction_residuals,
    )

    if not takes_offset(log, model):
        why = (
            "not searched (a log of ranges with an acceleration input and the model imu only;"
            " a lag known in seconds is given as --clock-offset SECONDS)"
        )
        return ClockOffset(0.0, 0.0, math.nan, reason=f"clock offset of the inputs: {why}")
    h = round(offset_step(log), 9)
    t0, t1 = float(log.inputs[0, 0]), float(log.inputs[-1, 0])
    start = t0 + SCORED_FROM * (t1 - t0)
    inner = _interior(log, (STEPS + 1) * h) if math.isfinite(h) else log
    held = held_out_count(inner.ranges[:, 0], start)
    if held < HELD_MIN or not math.isfinite(h):
        why = f"{held} held-out ranges scored, the paired test needs {HELD_MIN}"
        return ClockOffset(
            0.0, 0.0, h, reason=f"clock offset of the inputs: none (too few ranges: {why})"
        )
    runs: dict = {}

    def score(tau: float) -> float:
        tau = round(tau, 9)
        if tau not in runs:
            runs[tau] = prediction_residuals(
                with_input_offset(inner, tau), dt=dt, model=model, estimator=estimator,
                setup_options=setup_options, scored_from=start,
            )  # fmt: skip
        return compare(runs[tau], runs[0.0], cap).score

    runs[0.0] = prediction_residuals(
        inner, dt=dt, model=model, estimator=estimator, setup_options=setup_options,
        scored_from=start,
    )  # fmt: skip
    cap = _cap(runs[0.0])

    def gains(tau: float, than: float) -> bool:  # significantly better, the paired test
        score(tau)
        return compare(runs[tau], runs[than], cap).better

    best = min((0.0, -h, h), key=lambda t: (score(t), abs(t)))
    if best and gains(best, 0.0):  # on along the better side while the score falls
        sign = math.copysign(1.0, best)
        for k in range(2, STEPS + 1):
            if not gains(round(sign * k * h, 9), best):
                break
            best = round(sign * k * h, 9)
        step = h
        for _ in range(REFINE):
            step /= 2.0
            near = (best, round(best - step, 9), round(best + step, 9))
            best = min(near, key=lambda t: (score(t), abs(t)))
    else:
        best = 0.0
    scores = {t: score(t) for t in sorted(runs)}
    if best == 0.0:
        reason = (
            f"clock offset of the inputs +0.0 ms: neither {h * 1e3:+.3g} ms nor"
            f" {-h * 1e3:+.3g} ms predicts the held-out ranges significantly better than none"
            f" ({scores[h]:.3f} and {scores[-h]:.3f} m, none {scores[0.0]:.3f} m)"
        )
        return ClockOffset(0.0, 0.0, h, scores, {}, reason)
    test = compare(runs[best], runs[0.0], cap, candidates=len(runs) - 1)
    chosen = best if test.better else 0.0
    reason = (
        f"clock offset of the inputs {chosen * 1e3:+.1f} ms: the best candidate"
        f" {best * 1e3:+.1f} ms predicts the held-out ranges to {_metres(test.score)}, none to"
        f" {_metres(test.reference_score)}, {'' if test.better else 'not '}significantly better"
        f" ({len(runs) - 1} candidates, step {h * 1e3:.3g} ms)"
    )
    return ClockOffset(chosen, best, h, scores, test.as_dict(), reason)
