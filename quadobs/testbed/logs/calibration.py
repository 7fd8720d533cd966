"""Range biases and process noise, calibrated from the log itself (never from the ground truth),
with a fallback to no correction wherever the data do not support one.

Prequential residuals. One replay of the log *in time* through one estimator (the EKF by
default) from the anchors' centroid: at each range, at its own time and before the estimator
corrects with it,

.. math:: r = \\rho - b_h - |\\hat p^- - a_h| ,

kept over the second half of the log (the first half is left to the transient). Only the
ranges, the inputs and the estimator's own prediction enter: the truth is not read.

Held-out ranges. Every :data:`HOLD_OUT`-th range of the log (by its index among the ranges)
is predicted but never corrected with, in every replay of the calibration: its residual is
an honest test of a setting, since the estimator never fitted it.

Range biases. Radio ranges carry a bias per anchor (an antenna delay; +2 to +5 m on the
Plaza logs), which the quadratic output model cannot hold as a state (``(rho - b)^2`` is not
quadratic in ``(p, b)``). :func:`calibrate_biases`, a fixed-point iteration on the fitted
ranges' residuals: ``b^(0) = 0``, ``b_h^(i+1) = b_h^(i) + median_h(r)`` (the median resists
outliers), :data:`ITERATIONS` times. A bias trades against the position, so the estimate is
only as good as the geometry separates them.

Process noise. The model's process-noise intensity (``q_xy``, ``q_acc`` or ``q_imu``) on the
grid ``prior 4^j``, ``j = -4 .. 3`` (:data:`NOISE_FACTORS`), that minimises the prequential
score over every range of the second half (each predicted before it is used, so none is
fitted), in replays that correct with every range: the root mean square of
``r - median_h(r)`` (the biases' offsets aside) without its largest 5 % (:data:`TRIM`,
outliers). The mean square is ``sigma^2 + E e^2`` for a range noise ``sigma`` and a
prediction error ``e``, so it ranks the settings by the prediction's accuracy, where a
median of ``|r|`` is flattened by the noise. The smallest score wins (ties to rounding,
:data:`TIE`, go to the smallest intensity).

Cannot make things worse. :func:`calibrate` keeps the calibrated biases only when

1. they are identified: some ``|b_h|`` exceeds three standard errors of its median
   (``1.253 * 1.4826 MAD_h / sqrt(n_h)``), and
2. they predict the held-out ranges better than no correction: the held-out score
   ``median |r|`` with them is below :data:`MARGIN` times the score without;

otherwise it applies none, and says which test failed (:attr:`Calibration.reason`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from quadobs.testbed.logs.estimators import ReplaySetup, build_replay_estimators, replay_setup
from quadobs.testbed.logs.events import LogEvents
from quadobs.testbed.worlds.replay import ReplayWorld, default_model, state_size

__all__ = [
    "HOLD_OUT",
    "MARGIN",
    "NOISE_FACTORS",
    "Calibration",
    "calibrate",
    "calibrate_biases",
    "calibrate_noise",
    "prediction_residuals",
    "process_noise_key",
    "self_calibrate",
]

#: The factors of the prior process-noise intensity that :func:`calibrate_noise` tries.
NOISE_FACTORS = tuple(4.0**j for j in range(-4, 4))
#: Scores within this fraction of the best are ties, won by the smallest intensity (rounding only).
TIE = 1e-6
#: The fraction of the largest squared residuals the noise score leaves out (outliers).
TRIM = 0.05
#: Every HOLD_OUT-th range is held out of the corrections (module docstring).
HOLD_OUT = 5
#: The fixed-point iterations of the bias calibration.
ITERATIONS = 3
#: The calibrated biases are kept when their held-out score is below MARGIN times no correction's.
MARGIN = 0.95
#: A bias counts as identified beyond this many standard errors of its median.
IDENTIFIED = 3.0


def process_noise_key(model: str) -> str:
    """The :class:`ReplaySetup` field of a model's process-noise intensity."""
    return {"odometry": "q_xy", "cv": "q_acc", "imu": "q_imu"}[model]


def _initial(log, model: str, x0) -> np.ndarray:
    """``x0``, or the anchors' centroid with a zero velocity."""
    if x0 is not None:
        return np.asarray(x0, dtype=float)
    x = np.zeros(state_size(log, model))
    x[: log.dimension] = log.beacons.mean(axis=0)
    return x


@dataclass
class Residuals:
    """The second half's prequential range residuals of one replay: ``r``, anchor ``h``, and
    whether each was ``held`` out of the corrections."""

    r: np.ndarray
    h: np.ndarray
    held: np.ndarray

    def fitted(self) -> tuple[np.ndarray, np.ndarray]:
        keep = ~self.held
        return self.r[keep], self.h[keep]


def prediction_residuals(
    log,
    *,
    dt=0.1,
    model=None,
    biases=None,
    x0=None,
    estimator="ekf",
    setup_options=None,
    hold_out: bool = True,
) -> Residuals:
    """One replay in time with ``biases`` (module docstring): the residuals of the second half's
    ranges; with ``hold_out``, every :data:`HOLD_OUT`-th range is not corrected with."""
    model = model or default_model(log)
    q = log.beacons.shape[0]
    b = np.zeros(q) if biases is None else np.asarray(biases, dtype=float)
    world = ReplayWorld(log, dt, model, 8, b, peer_batch=False)
    setup = replay_setup(log, world, setup_options)
    est = build_replay_estimators(setup, [estimator], _initial(log, model, x0))[0]
    events = LogEvents(log, b, start=world.times[0], end=world.times[-1])
    t_in, U = events.inputs()
    est.time = world.times[0]
    i = int(np.searchsorted(t_in, world.times[0], side="right"))
    if i:
        est.hold(U[i - 1])
    half = world.times[0] + 0.5 * (world.times[-1] - world.times[0])
    dim, index = log.dimension, _range_index(log, events)
    out_r, out_h, out_held = [], [], []
    for j, m in enumerate(events.measurements):
        while i < t_in.size and t_in[i] <= m.t:
            est.predict(t_in[i])
            est.hold(U[i])
            i += 1
        est.predict(m.t)
        held = hold_out and m.kind == "range" and index[j] % HOLD_OUT == HOLD_OUT // 2
        if m.kind == "range" and m.t >= half:
            p = est.x_hat[:dim]
            out_r.append(m.value - float(np.linalg.norm(p - log.beacons[m.anchors[0]])))
            out_h.append(m.anchors[0])
            out_held.append(held)
        if not held:
            est.correct(m)
    r = np.array(out_r)
    ok = np.isfinite(r)
    return Residuals(r[ok], np.array(out_h, dtype=np.int64)[ok], np.array(out_held, bool)[ok])


def _range_index(log, events: LogEvents) -> np.ndarray:
    """For each event, its index among the log's ranges (``-1`` for other kinds)."""
    out = np.full(events.count, -1, dtype=np.int64)
    k = 0
    for j, m in enumerate(events.measurements):
        if m.kind == "range":
            out[j] = k
            k += 1
    return out


def _trimmed_rms(r: np.ndarray) -> float:
    """The root mean square of ``r`` without its largest :data:`TRIM` fraction (inf when empty)."""
    if r.size == 0:
        return math.inf
    r2 = np.sort(r * r)
    return float(np.sqrt(np.mean(r2[: max(int(math.ceil((1.0 - TRIM) * r2.size)), 1)])))


def _median_by_anchor(r: np.ndarray, h: np.ndarray, q: int) -> np.ndarray:
    return np.array([np.median(r[h == j]) if np.any(h == j) else 0.0 for j in range(q)])


def calibrate_biases(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    x0=None,
    estimator: str = "ekf",
    iterations: int = ITERATIONS,
    setup_options: dict | None = None,
) -> np.ndarray:
    """Per-anchor range biases ``(q,)`` (m) by the fixed-point iteration of the module docstring."""
    return _fixed_point(log, dt, model, x0, estimator, iterations, setup_options)[0]


def _fixed_point(log, dt, model, x0, estimator, iterations, setup_options):
    """The biases and the residuals of the replay with them (the last one run)."""
    q = log.beacons.shape[0]
    b = np.zeros(q)
    res = None
    for _ in range(int(iterations)):
        res = prediction_residuals(
            log, dt=dt, model=model, biases=b, x0=x0, estimator=estimator,
            setup_options=setup_options,
        )  # fmt: skip
        b = b + _median_by_anchor(*res.fitted(), q)
    res = prediction_residuals(
        log, dt=dt, model=model, biases=b, x0=x0, estimator=estimator, setup_options=setup_options
    )
    return b, res


def calibrate_noise(
    log,
    biases,
    *,
    dt: float = 0.1,
    model: str | None = None,
    x0=None,
    estimator: str = "ekf",
    setup_options: dict | None = None,
) -> tuple[float, dict]:
    """The model's process-noise intensity with the smallest prequential score (module docstring).

    Returns the intensity and the score (m) of every one tried, ``{intensity: score}``.
    """
    model = model or default_model(log)
    key = process_noise_key(model)
    prior = (setup_options or {}).get(key, getattr(ReplaySetup, key))
    b = np.asarray(biases, dtype=float)
    scores = {}
    for factor in NOISE_FACTORS:
        q = prior * factor
        res = prediction_residuals(
            log, dt=dt, model=model, biases=b, x0=x0, estimator=estimator,
            setup_options={**(setup_options or {}), key: q}, hold_out=False,
        )  # fmt: skip
        r, h = res.r, res.h
        scores[q] = _trimmed_rms(r - _median_by_anchor(r, h, b.size)[h])
    best = min(scores.values())
    return min(q for q, score in scores.items() if score <= (1.0 + TIE) * best), scores


@dataclass
class Calibration:
    """What :func:`calibrate` chose and why.

    Attributes
    ----------
    biases : ndarray (q,) or None
        The biases applied (None: no correction).
    options : dict
        The setup options, with the chosen process-noise intensity.
    scores : dict
        The prequential score of every intensity tried (empty when the noise was not calibrated).
    reason : str
        Why the biases were kept or not (module docstring).
    candidate : ndarray (q,)
        The calibrated biases, applied or not.
    held_out : dict
        ``{"with_biases": m, "without": m}``: the held-out scores ``median |r|``.
    """

    biases: np.ndarray | None
    options: dict
    scores: dict
    reason: str
    candidate: np.ndarray
    held_out: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """As plain data, for the replay's summary."""
        return {
            "biases": None if self.biases is None else [float(v) for v in self.biases],
            "candidate_biases": [float(v) for v in self.candidate],
            "reason": self.reason,
            "held_out_score": self.held_out,
            "process_noise": {
                k: v for k, v in self.options.items() if k in ("q_xy", "q_acc", "q_imu")
            },
        }


def calibrate(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    setup_options: dict | None = None,
    noise: bool = True,
    estimator: str = "ekf",
) -> Calibration:
    """Biases and (with ``noise``) the process noise from the log, kept only where they help (module docstring)."""
    model = model or default_model(log)
    options = dict(setup_options or {})
    q = log.beacons.shape[0]
    if log.ranges.shape[0] == 0:
        return Calibration(None, options, {}, "the log holds no ranges", np.zeros(q))
    b, res = _fixed_point(log, dt, model, None, estimator, ITERATIONS, options)
    scores = {}
    if noise:
        key = process_noise_key(model)
        options[key], scores = calibrate_noise(
            log, b, dt=dt, model=model, estimator=estimator, setup_options=options
        )
        b, res = _fixed_point(log, dt, model, None, estimator, ITERATIONS, options)
    plain = prediction_residuals(
        log, dt=dt, model=model, biases=None, estimator=estimator, setup_options=options
    )
    with_b = float(np.median(np.abs(res.r[res.held]))) if res.held.any() else math.inf
    without = float(np.median(np.abs(plain.r[plain.held]))) if plain.held.any() else math.inf
    held = {"with_biases": with_b, "without": without}
    r, h = res.fitted()
    se = np.array(
        [
            1.2533 * 1.4826 * np.median(np.abs(r[h == j] - np.median(r[h == j])))
            / math.sqrt(np.sum(h == j)) if np.any(h == j) else math.inf
            for j in range(q)
        ]
    )  # fmt: skip
    if not np.any(np.abs(b) > IDENTIFIED * se):
        reason = f"not identified: every |b_h| within {IDENTIFIED:g} standard errors of its median"
        return Calibration(None, options, scores, reason, b, held)
    if not with_b < MARGIN * without:
        reason = (
            f"no better on the held-out ranges: {with_b:.3f} m with the biases, "
            f"{without:.3f} m without"
        )
        return Calibration(None, options, scores, reason, b, held)
    reason = (
        f"held-out ranges predicted better: {with_b:.3f} m with the biases, {without:.3f} m without"
    )
    return Calibration(b, options, scores, reason, b, held)


def self_calibrate(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    setup_options: dict | None = None,
    noise: bool = True,
) -> tuple[np.ndarray, dict, dict]:
    """:func:`calibrate` as ``(biases, options, scores)``; the biases zero where none were kept."""
    c = calibrate(log, dt=dt, model=model, setup_options=setup_options, noise=noise)
    b = np.zeros(log.beacons.shape[0]) if c.biases is None else c.biases
    return b, c.options, c.scores
