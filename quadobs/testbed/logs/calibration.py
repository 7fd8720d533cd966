"""Range biases and process noise, calibrated from the log itself (never from the ground truth),
each kept only where it predicts held-out ranges significantly better than the prior defaults.

Prequential residuals. One replay of the log *in time* through one estimator (the EKF by
default) from the anchors' centroid, its initial variance the anchors' extent
(:func:`~quadobs.testbed.logs.estimators.initial_variance`): at each range, at its own time and
before the estimator corrects with it,

.. math:: r = \\rho - b_h - |\\hat p^- - a_h| ,

kept from :data:`SCORED_FROM` of the log on (the start is left to the transient). Only the
ranges, the inputs and the estimator's own prediction enter: the truth is not read.

Held-out ranges. Every :data:`HOLD_OUT`-th range of the log (by its index among the ranges)
is predicted but never corrected with, in every replay of the calibration: its residual is
an honest test of a setting, since the estimator never fitted it. The same ranges are held
out in every replay, so two settings are compared range by range.

The score. The held-out loss of a range is ``min(r^2, c^2)``, its cap ``c`` :data:`CAP` times
the prior's median held-out ``|r|`` (an outlier of metres counts as ``c``, a non-finite
prediction too); the score of a setting is the root of its mean loss. A candidate beats the
reference setting only *significantly*: the held-out ranges are cut into ``B`` =
:data:`BLOCKS` consecutive blocks (fewer where fewer than two ranges a block are held out;
no test below three blocks) in time, ``D_k`` is the mean of
``loss_candidate - loss_reference`` over block ``k`` (blocks, not ranges: the prediction errors of neighbouring ranges are correlated,
and the block means are close to independent, the method of batch means), and the candidate
wins only if

.. math:: \\bar D + K \\, s_D / \\sqrt{B} < 0 ,

with ``s_D`` the standard deviation of the ``D_k`` and ``K`` the
one-sided quantile of Student's t with ``B - 1`` degrees of freedom at the level
:data:`SIGNIFICANCE` divided by the number ``m`` of candidates the winner was chosen from
(Bonferroni: the chance that any of them passes by luck stays below the level): ``K = 2.09``
for one candidate (the biases), ``3.01`` for the best of the seven other noise intensities.
Paired differences cancel the range noise that both settings see, so a
real improvement shows where the scores' own spread would hide it.

Order (:func:`calibrate`), on the log with its inputs moved onto the ranges' clock where the
replay is given a clock offset or asked to search one (``--clock-offset``, not by default:
:mod:`~quadobs.testbed.logs.clock_offset`, scored as below):

1. the prior: the setup's defaults, no biases (the reference of everything below);
2. range biases at the prior's noise, a fixed-point iteration on the fitted (not held-out)
   residuals, ``b^(0) = 0``, ``b_h^(i+1) = b_h^(i) + median_h(r)`` (the median resists
   outliers), :data:`ITERATIONS` times; kept only when *identified* (some ``|b_h|`` beyond
   :data:`IDENTIFIED` standard errors of its median, ``1.253 * 1.4826 MAD_h / sqrt(n_h)``)
   *and* significantly better on the held-out ranges than no correction;
3. the model's process-noise intensity (``q_xy``, ``q_acc`` or ``q_imu``) on the grid
   ``prior 4^j``, ``j = -4 .. 3`` (:data:`NOISE_FACTORS`), with the biases of step 2, the grid
   going on by factors of 4 past an edge that scores best (at most :data:`EXTEND` steps, while
   the score falls: a prior may be orders of magnitude off on a log of another scale): the
   candidate of the smallest score is kept only if significantly better than the prior's
   intensity (Bonferroni over every candidate tried);
4. where the intensity changed, the biases again at it (the fixed point from the biases of
   step 2, or from zero): kept if identified, significantly better than the prior and
   predicting the held-out ranges at least as well as the biases before; then step 3 once
   more with them (:data:`PASSES`), as a bias fitted at the prior's intensity also biases
   the choice of the intensity (it stops where the intensity or the biases stay);
5. the setting chosen, as a whole, against the prior (one candidate): where it is not
   significantly better, everything reverts to the prior; then, where asked
   (``--tune bias_prior=log``; not the default), the biases' prior of the filters that hold
   them as states, the spread of the calibrated biases, applied or not, within the ranges'
   noise and the range model's 0.5 m (:func:`biases_spread`);
6. a log of wheel odometry replayed with the model ``odometry``: the heading filters' own
   intensities (:data:`HEADING_KEYS`: ``q_xy_heading`` on their position, ``q_theta`` on their
   heading), in turn on the same grid, scored by :data:`HEADING_SCORER` at the biases chosen:
   each best candidate is kept only if significantly better than the setting before it
   (:func:`heading_noise`).

7. each estimator of the replay that holds the range biases as states (``ekf-bias``,
   ``ekf-bias-imu``; :func:`holds_range_biases`), where biases were chosen: the biases kept
   for it only where, replayed through *that* estimator (its prediction of a range adding its
   own bias estimate), they predict the held-out ranges significantly better than the ranges
   as logged by an effect the size of a position error as long as the ranges' noise standard
   deviation (:func:`effect_margin`), or where they lie outside its bias states' prior; else
   it takes the ranges as logged (:func:`estimator_biases`). ``ekf-bias-imu-average`` is
   ``ekf-bias-imu`` when scored (without the excess) and takes that filter's choice. The
   biases of steps 2 to 5 are fitted and tested through the EKF, which holds neither the
   range biases nor what else a filter may hold as states (an acceleration's bias): its
   biases take up those errors too,
   and a filter that holds them would start its states from the EKF's compromise.
   The heading filter that holds each anchor's height beside its bias (``ukf-height-lever``)
   takes the ranges as logged unless its own prior of bias and height excludes the biases
   (:func:`_offsets_biases`): the EKF's biases hold the heights' share too, which it would
   count twice. Before these, heights that an odometry log states are held against the
   ranges and set aside where the ranges contradict them (:func:`check_stated_heights`).

8. the ranges' non-line-of-sight excess, fitted to the chosen setting's residuals (a
   Gaussian and a Gaussian shifted by a log-normal excess, :mod:`~quadobs.testbed.logs.excess_model`)
   where the log states no Gaussian ranges and their noise is known: set in the options
   (``nlos_median``, ``nlos_shape``; ``ekf-bias-imu-nlos`` then weighs each range by an
   :class:`~quadobs.estimators.robust.ExcessMixture` of it,
   :func:`~quadobs.testbed.logs.bias_estimators.range_rule`) only where the residuals
   identify it, else the filters keep the one-sided gate.

9. each estimator of the replay that takes the excess's mixture, where step 8 chose it: the
   excess kept only where, replayed through that estimator with its biases of step 7, the
   mixture predicts the held-out ranges significantly better than the one-sided gate, scored
   by their negative log-likelihood under the fitted model of the ranges (the paired test
   above, one candidate); else every filter keeps the gate (:func:`estimator_excess`). Not
   run by the replay: on the flights of ``sims/replay_flight_variants.py`` the held-out ranges
   did not tell where the mixture helps (its docstring).

10. each filter of the replay that holds constant states (an anchor's range bias, its
    height's offset, the tag's lever arm): started from the constants a first pass through
    the log ended with, where the second pass from them predicts the held-out ranges at least
    as well (:mod:`~quadobs.testbed.logs.constants_start`; run by the replay after step 7);
    for ``ukf-height-lever`` first the tag's pattern as two more constants, kept where, each
    with its own start, they predict the held-out ranges significantly better than without
    (``--tune tag_pattern=0`` or ``1`` fixes it).

Two scorers on an odometry log. The model ``odometry`` takes the dead-reckoned heading as
right, so its ``q_xy`` must also carry the heading's drift (a yaw rate's bias: Plaza2's
drifts at 0.005 rad/s): scored by the EKF of that model, Plaza2 picks ``q_xy = 16``. The
heading filters (``ekf-heading``, ``ukf-heading``, the cascade ``augmented-heading``) hold the
drift as states, and their position noise is the speed's alone: a separate intensity,
``q_xy_heading``, scored by the EKF of their own model. Scored by the heading filter, the biases
came out further from what the batch optimum needs on Plaza2 (2.04, 2.17, -0.66, 3.01 m,
batch LM 2.46 m, against the EKF's 2.94, 4.13, 2.71, 3.80 m, 1.49 m): the biases stay the
EKF's.

Whatever is not kept stays at the prior; :attr:`Calibration.reason` says what was chosen and
why.

A log of TDOA alone (:func:`calibrate_tdoa`) is scored on its held-out TDOA,
``r = d_ij - (|p^- - a_i| - |p^- - a_j|)``, every :data:`HOLD_OUT`-th TDOA held out, by the
TDOA observer handing over to the EKF (:func:`tdoa_estimator`): step 3 only, the prior's
intensity being the log's own where it states its accelerometer's density
(:func:`~quadobs.testbed.logs.estimators.log_defaults`); no biases (a TDOA holds the
difference of two anchors' delays, which the TDOA estimators do not model). Radio ranges carry a bias per anchor (an antenna delay; +2 to +5 m on the Plaza logs),
which the quadratic output model cannot hold as a state (``(rho - b)^2`` is not quadratic in
``(p, b)``); a bias trades against the position, so its estimate is only as good as the
geometry separates them, which is what the held-out test checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from quadobs.core.quantiles import chi2_ppf, student_t_ppf
from quadobs.estimators.constants import constant_filters
from quadobs.testbed.logs.estimators import (
    FROM_LOG,
    ReplaySetup,
    build_replay_estimators,
    log_defaults,
    log_range_std,
    replay_setup,
)
from quadobs.testbed.logs.events import LogEvents
from quadobs.testbed.logs.excess_model import EXCESS_KEYS, calibrated_excess, excess_nll
from quadobs.testbed.logs.height_estimators import holds_anchor_offsets
from quadobs.testbed.worlds.replay import ReplayWorld, default_model, state_size

__all__ = [
    "BLOCKS",
    "CAP",
    "EXTEND",
    "HEADING_KEYS",
    "HEADING_SCORER",
    "HOLD_OUT",
    "NOISE_FACTORS",
    "SIGNIFICANCE",
    "Calibration",
    "Comparison",
    "bias_prior_std",
    "biases_spread",
    "calibrate",
    "calibrate_biases",
    "calibrate_noise",
    "calibrate_tdoa",
    "compare",
    "effect_margin",
    "estimator_biases",
    "estimator_excess",
    "heading_noise",
    "heading_scored",
    "holds_range_biases",
    "noise_keys",
    "outside_prior",
    "prediction_residuals",
    "process_noise_key",
    "range_noise_std",
    "scored_kind",
    "self_calibrate",
    "tdoa_estimator",
    "threshold",
]

#: The factors of the prior process-noise intensity that :func:`calibrate_noise` tries.
NOISE_FACTORS = tuple(4.0**j for j in range(-4, 4))
#: The most steps (each a factor 4) by which :func:`calibrate_noise`'s grid goes on past its
#: smallest or largest factor while that edge scores best (module docstring).
EXTEND = 4
#: Every HOLD_OUT-th range is held out of the corrections (module docstring).
HOLD_OUT = 5
#: The fixed-point iterations of the bias calibration.
ITERATIONS = 3
#: A bias counts as identified beyond this many standard errors of its median.
IDENTIFIED = 3.0
#: The fraction of the log after which the residuals are scored (before: the transient).
SCORED_FROM = 0.5
#: The most passes of the process noise and the biases refitted at it (module docstring).
PASSES = 2
#: The held-out loss is capped at CAP times the prior's median held-out ``|r|``.
CAP = 5.0
#: The number of consecutive blocks of held-out ranges of the significance test.
BLOCKS = 20
#: The one-sided level of the paired test (over all the candidates of one choice).
SIGNIFICANCE = 0.025


def threshold(candidates: int = 1, blocks: int = BLOCKS) -> float:
    """``K``: the one-sided Student-t quantile (``blocks - 1`` degrees of freedom) at
    :data:`SIGNIFICANCE` / ``candidates`` (module docstring)."""
    return student_t_ppf(1.0 - SIGNIFICANCE / max(int(candidates), 1), int(blocks) - 1)


def process_noise_key(model: str) -> str:
    """The :class:`ReplaySetup` field of a model's process-noise intensity."""
    return {"odometry": "q_xy", "cv": "q_acc", "imu": "q_imu"}[model]


#: The estimator that scores the heading filters' intensities (module docstring).
HEADING_SCORER = "ekf-heading"
#: The heading filters' intensities, in the order :func:`heading_noise` fits them.
HEADING_KEYS = ("q_xy_heading", "q_theta")


def heading_scored(log, model: str | None = None) -> bool:
    """Whether the heading filters' intensities are calibrated: a log of wheel odometry
    replayed with the model ``odometry``."""
    return (model or default_model(log)) == "odometry" and log.input_kind == "odometry"


def noise_keys(log, model: str | None = None) -> tuple[str, ...]:
    """The process-noise intensities :func:`calibrate` fits on ``log``: the model's
    (:func:`process_noise_key`), then :data:`HEADING_KEYS` where :func:`heading_scored`."""
    model = model or default_model(log)
    return (process_noise_key(model),) + (HEADING_KEYS if heading_scored(log, model) else ())


def _initial(log, model: str, x0) -> np.ndarray:
    """``x0``, or the anchors' centroid with a zero velocity."""
    if x0 is not None:
        return np.asarray(x0, dtype=float)
    x = np.zeros(state_size(log, model))
    x[: log.dimension] = log.beacons.mean(axis=0)
    return x


@dataclass
class Residuals:
    """The scored prequential range residuals of one replay: ``r`` (NaN where the prediction
    was not finite), anchor ``h``, time ``t`` and whether each was ``held`` out; ``constants``:
    for each filter of the estimator that holds constant states, by its name, their estimate
    and covariance at the log's end (:mod:`quadobs.estimators.constants`)."""

    r: np.ndarray
    h: np.ndarray
    held: np.ndarray
    t: np.ndarray
    constants: dict = field(default_factory=dict)

    def fitted(self) -> tuple[np.ndarray, np.ndarray]:
        """The finite residuals of the ranges corrected with, and their anchors."""
        keep = ~self.held & np.isfinite(self.r)
        return self.r[keep], self.h[keep]

    def held_out(self) -> np.ndarray:
        """The held-out residuals in time order (NaN kept: the same ranges in every replay)."""
        return self.r[self.held]


def holds_range_biases(est) -> bool:
    """Whether ``est`` holds the anchors' range biases as states and predicts a range as
    ``|p - a_h| + b_h``, ``b`` its ``biases`` (m): the filters of
    :mod:`quadobs.estimators.bias_states` on :class:`~quadobs.estimators.bias_states.BiasedRangeOutputModel`
    (not those whose range also holds other states, such as an anchor's height) and the
    augmented observer with the biases in its immersion."""
    from quadobs.estimators.augmented_bias import BiasedAugmentedObserver
    from quadobs.estimators.bias_states import (
        BiasedExtendedKalmanFilter,
        BiasedRangeOutputModel,
        BiasedUnscentedKalmanFilter,
    )

    if isinstance(est, BiasedAugmentedObserver):
        return True
    filters = (BiasedExtendedKalmanFilter, BiasedUnscentedKalmanFilter)
    return isinstance(est, filters) and isinstance(est.outputs, BiasedRangeOutputModel)


def _scoring_estimator(log, dt, model, b, estimator, setup_options, x0):
    """``(world, estimator)``: the replay's world with the biases ``b`` and ``estimator`` built
    on it from ``x0`` (default the anchors' centroid)."""
    world = ReplayWorld(log, dt, model, 8, b, peer_batch=False)
    setup = replay_setup(log, world, setup_options)
    est = build_replay_estimators(setup, [estimator], _initial(log, model, x0))[0]
    return world, _scored_member(est)


def _scored_member(est):
    """``est``, or the only member of a model average with one member, renamed as the average
    and marked ``scored_as`` its own name. Scored without the excess (:func:`estimator_biases`),
    ``ekf-bias-imu-average`` is such an average of ``ekf-bias-imu``, whose choice of biases
    it then takes."""
    from quadobs.estimators.model_average import ModelAverage

    if isinstance(est, ModelAverage) and len(est.members) == 1:
        member = est.members[0]
        member.scored_as, member.name = member.name, est.name
        return member
    return est


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
    scored_from: float | None = None,
    own_range: bool = False,
    read_constants: bool = False,
) -> Residuals:
    """One replay in time with ``biases`` (module docstring): the residuals of the ranges from
    :data:`SCORED_FROM` of the log on; with ``hold_out``, every :data:`HOLD_OUT`-th range is not
    corrected with. An estimator that holds the range biases as states
    (:func:`holds_range_biases`) predicts a range with its own bias estimate added,
    ``r = rho - b_h - |p^- - a_h| - beta_h^-``. ``scored_from``: the time (s, the log's
    clock) from which the ranges are scored, in place of :data:`SCORED_FROM` of the log (the
    same ranges scored in replays whose spans differ, :mod:`~quadobs.testbed.logs.clock_offset`).
    ``own_range``: a filter that predicts a range by its own model (a heading filter's tag,
    lever arm, bias and offset: ``predicted_range``) is scored by that prediction.
    ``read_constants``: the residuals also hold each filter's constants at the log's end
    (:attr:`Residuals.constants`; none of a filter that gave up)."""
    model = model or default_model(log)
    q = log.beacons.shape[0]
    b = np.zeros(q) if biases is None else np.asarray(biases, dtype=float)
    world, est = _scoring_estimator(log, dt, model, b, estimator, setup_options, x0)
    own = holds_range_biases(est)
    # its own range: the tag, the anchor's offset and bias
    whole = holds_anchor_offsets(est) or (own_range and hasattr(est, "predicted_range"))
    events = LogEvents(log, b, start=world.times[0], end=world.times[-1])
    t_in, U = events.inputs()
    est.time = world.times[0]
    i = int(np.searchsorted(t_in, world.times[0], side="right"))
    if i:
        est.hold(U[i - 1])
    start = world.times[0] + SCORED_FROM * (world.times[-1] - world.times[0])
    start = start if scored_from is None else float(scored_from)
    kind = scored_kind(log)
    dim, index = log.dimension, _range_index(events, kind)
    out_r, out_h, out_held, out_t = [], [], [], []
    for j, m in enumerate(events.measurements):
        while i < t_in.size and t_in[i] <= m.t:
            est.predict(t_in[i])
            est.hold(U[i])
            i += 1
        est.predict(m.t)
        held = hold_out and m.kind == kind and index[j] % HOLD_OUT == HOLD_OUT // 2
        if m.kind == kind and m.t >= start:
            if whole and m.kind == "range":
                out_r.append(m.value - est.predicted_range(m))
            else:
                p = est.x_hat[:dim]
                beta = float(est.biases[m.anchors[0]]) if own and m.kind == "range" else 0.0
                out_r.append(m.value - _predicted(log.beacons, p, m) - beta)
            out_h.append(m.anchors[0])
            out_held.append(held)
            out_t.append(m.t)
        if not held:
            est.correct(m)
    r = np.array(out_r, dtype=float)
    r[~np.isfinite(r)] = np.nan
    constants = (
        {f.name: f.constants_estimate() for f in constant_filters(est) if not _gave_up(f)}
        if read_constants
        else {}
    )
    return Residuals(
        r, np.array(out_h, dtype=np.int64), np.array(out_held, dtype=bool), np.array(out_t),
        constants,
    )  # fmt: skip


def _gave_up(est) -> bool:
    """Whether ``est``'s lock-out reports it diverged."""
    return getattr(getattr(est, "lockout", None), "diverged", None) is not None


def scored_kind(log) -> str:
    """The kind of measurement the calibration scores: the ranges, else (a log of TDOA alone)
    the TDOA (:func:`calibrate_tdoa`)."""
    return "range" if log.ranges.shape[0] else "tdoa"


def _predicted(beacons: np.ndarray, p: np.ndarray, m) -> float:
    """``m`` predicted at the position ``p``: ``|p - a_h|`` (a range), ``|p - a_i| - |p - a_j|``
    (a TDOA)."""
    if m.kind == "range":
        return float(np.linalg.norm(p - beacons[m.anchors[0]]))
    i, j = m.anchors
    return float(np.linalg.norm(p - beacons[i]) - np.linalg.norm(p - beacons[j]))


def _range_index(events: LogEvents, kind: str = "range") -> np.ndarray:
    """For each event, its index among the log's measurements of ``kind`` (``-1`` for other kinds)."""
    out = np.full(events.count, -1, dtype=np.int64)
    k = 0
    for j, m in enumerate(events.measurements):
        if m.kind == kind:
            out[j] = k
            k += 1
    return out


def _median_by_anchor(r: np.ndarray, h: np.ndarray, q: int) -> np.ndarray:
    return np.array([np.median(r[h == j]) if np.any(h == j) else 0.0 for j in range(q)])


def _cap(reference: Residuals) -> float:
    """The loss cap ``c`` (module docstring): :data:`CAP` times the reference's median held-out ``|r|``."""
    r = reference.held_out()
    r = r[np.isfinite(r)]
    return CAP * float(np.median(np.abs(r))) if r.size else math.inf


def _loss(res: Residuals, cap: float) -> np.ndarray:
    """The held-out losses ``min(r^2, c^2)``, a non-finite residual counted as ``c``."""
    r = res.held_out()
    return np.where(np.isfinite(r), np.minimum(r * r, cap * cap), cap * cap)


@dataclass
class Comparison:
    """A candidate against a reference on the same held-out ranges (module docstring).

    Attributes
    ----------
    score, reference_score : float
        The root mean held-out loss (m) of the candidate and of the reference.
    difference : float
        ``D``: the mean of the blocks' mean loss differences (m^2; negative: the candidate better).
    standard_error : float
        ``s_D / sqrt(B)`` (m^2).
    better : bool
        ``D + K s_D / sqrt(B) < -margin``.
    margin : float
        The least gain in mean held-out loss (m^2) asked of the candidate (0: significance
        alone; step 7 asks for an effect, :func:`effect_margin`).
    """

    score: float
    reference_score: float
    difference: float
    standard_error: float
    better: bool
    margin: float = 0.0

    def as_dict(self) -> dict:
        """As plain data (JSON: a figure that is not finite, as where too few ranges were held
        out to test, is None)."""
        return {
            "score": _finite(self.score),
            "reference_score": _finite(self.reference_score),
            "difference": _finite(self.difference),
            "standard_error": _finite(self.standard_error),
            "significantly_better": self.better,
            "margin": _finite(self.margin),
        }


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _metres(v: float | None) -> str:
    return "no figure" if v is None or not math.isfinite(v) else f"{v:.3f} m"


def compare(
    candidate: Residuals,
    reference: Residuals,
    cap: float | None = None,
    candidates: int = 1,
    margin: float = 0.0,
) -> Comparison:
    """The paired test of the module docstring: is ``candidate`` significantly better than
    ``reference`` on their held-out ranges, by more than ``margin`` (m^2 of mean loss)? ``cap``
    defaults to the reference's (:func:`_cap`); ``candidates``: how many the candidate was the
    best of (:func:`threshold`)."""
    cap = _cap(reference) if cap is None else cap
    a, b = _loss(candidate, cap), _loss(reference, cap)
    score, ref = math.sqrt(float(np.mean(a))), math.sqrt(float(np.mean(b)))
    if not math.isfinite(cap):
        return Comparison(score, ref, math.nan, math.nan, False, margin)
    return _paired(a, b, score, ref, candidates, margin)


def _paired(
    a: np.ndarray, b: np.ndarray, score: float, ref: float, candidates: int = 1, margin=0.0
) -> Comparison:
    """The paired block test of the module docstring on the held-out losses ``a`` (candidate)
    and ``b`` (reference), reported with the scores ``score`` and ``ref``: the candidate better
    where ``D + K s_D / sqrt(B) < -margin``."""
    B = min(BLOCKS, a.size // 2)
    if a.size != b.size or B < 3:
        return Comparison(score, ref, math.nan, math.nan, False, margin)
    D = np.array([np.mean(d) for d in np.array_split(a - b, B)])
    mean, se = float(np.mean(D)), float(np.std(D, ddof=1) / math.sqrt(B))
    better = mean + threshold(candidates, B) * se < -margin
    return Comparison(score, ref, mean, se, better, margin)


def _replay(log, dt, model, biases, estimator, options) -> Residuals:
    return prediction_residuals(
        log, dt=dt, model=model, biases=biases, estimator=estimator, setup_options=options
    )


def _fixed_point(log, dt, model, estimator, iterations, options, first=None, start=None):
    """The biases and the residuals of the replay with them, from the biases ``start`` (default
    zero); ``first``: the replay with ``start`` at these options, already run (the first
    iteration's)."""
    q = log.beacons.shape[0]
    b = np.zeros(q) if start is None else np.array(start, dtype=float)
    res = first
    for i in range(int(iterations)):
        if res is None or i > 0:
            res = _replay(log, dt, model, b, estimator, options)
        b = b + _median_by_anchor(*res.fitted(), q)
    return b, _replay(log, dt, model, b, estimator, options)


def calibrate_biases(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    estimator: str = "ekf",
    iterations: int = ITERATIONS,
    setup_options: dict | None = None,
) -> np.ndarray:
    """Per-anchor range biases ``(q,)`` (m) by the fixed-point iteration of the module docstring
    (candidates: :func:`calibrate` decides whether they are applied)."""
    return _fixed_point(log, dt, model, estimator, iterations, dict(setup_options or {}))[0]


def _identified(b: np.ndarray, res: Residuals) -> bool:
    """Some ``|b_h|`` beyond :data:`IDENTIFIED` standard errors of its median."""
    r, h = res.fitted()
    for j, bj in enumerate(b):
        rj = r[h == j]
        if rj.size > 1:
            se = 1.2533 * 1.4826 * np.median(np.abs(rj - np.median(rj))) / math.sqrt(rj.size)
            if abs(bj) > IDENTIFIED * se:
                return True
    return False


def calibrate_noise(
    log,
    biases,
    *,
    dt: float = 0.1,
    model: str | None = None,
    estimator: str = "ekf",
    setup_options: dict | None = None,
    key: str | None = None,
) -> tuple[float, dict, dict]:
    """A process-noise intensity: the candidate ``prior 4^j`` of the smallest held-out
    score if it is significantly better than the prior's, else the prior (module docstring).

    ``key``: the :class:`ReplaySetup` field, default the model's (:func:`process_noise_key`).
    Returns the intensity, the held-out score (m) of every intensity tried ``{intensity: score}``,
    and the comparison of the best candidate with the prior (:meth:`Comparison.as_dict`).
    """
    model = model or default_model(log)
    options = {**log_defaults(log), **dict(setup_options or {})}
    b = np.asarray(biases, dtype=float)
    reference = _replay(log, dt, model, b, estimator, options)
    cap = _cap(reference)
    return _noise_step(log, dt, model, estimator, options, b, reference, cap, key)[:3]


def _noise_step(log, dt, model, estimator, options, b, reference, cap, key=None):
    """Step 3 of the module docstring against ``reference``, the replay at the prior with ``b``:
    ``(intensity, scores, test, runs)``, ``runs`` the replays ``{intensity: Residuals}``;
    ``key`` default the model's (:func:`process_noise_key`)."""
    key = key or process_noise_key(model)
    prior = options.get(key, getattr(ReplaySetup, key))
    scores, runs = {prior: compare(reference, reference, cap).score}, {prior: reference}
    for factor in NOISE_FACTORS:
        if factor != 1.0:
            q = prior * factor
            runs[q] = _replay(log, dt, model, b, estimator, {**options, key: q})
            scores[q] = compare(runs[q], reference, cap).score
    best = min((q for q in runs if q != prior), key=lambda q: (scores[q], q))
    for _ in range(EXTEND):  # the grid goes on past its edge while the edge scores best
        edge = {min(runs): 0.25, max(runs): 4.0}.get(best)
        if edge is None:
            break
        q = best * edge
        runs[q] = _replay(log, dt, model, b, estimator, {**options, key: q})
        scores[q] = compare(runs[q], reference, cap).score
        if not scores[q] < scores[best]:
            break
        best = q
    test = compare(runs[best], reference, cap, candidates=len(runs) - 1)
    scores = {q: scores[q] for q in sorted(scores)}
    chosen = best if test.better else prior
    return chosen, scores, {"candidate": best, **test.as_dict()}, runs


def _refit_biases(log, dt, model, estimator, options, current, current_res, prior_res, cap):
    """Step 4 of the module docstring: the biases again at the chosen intensity, from the
    current ones; ``(biases, residuals, test, kept)``, the current ones where the refit is not
    kept."""
    b, res = _fixed_point(
        log, dt, model, estimator, ITERATIONS, options, first=current_res, start=current
    )
    test = compare(res, prior_res, cap)
    now = compare(current_res, prior_res, cap).score
    if _identified(b, res) and test.better and test.score <= now:
        return b, res, test, True
    return current, current_res, test, False


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
        The held-out score (m) of every intensity tried (empty when the noise was not calibrated).
    reason : str
        What was chosen and why, biases and noise (module docstring).
    candidate : ndarray (q,)
        The calibrated biases, applied or not.
    held_out : dict
        The held-out scores (m): ``prior`` (the defaults, no biases), ``with_biases`` (the
        candidate biases at the prior's noise), ``without`` (no biases, the prior's noise),
        ``chosen`` (the setting applied).
    tests : dict
        The paired tests (:meth:`Comparison.as_dict`) of the candidate biases (``biases``), of
        the best candidate intensity (``noise``) and of each of :data:`HEADING_KEYS` fitted
        (by its key).
    more_scores : dict
        The held-out scores (m) of each of :data:`HEADING_KEYS` fitted, ``{key: {intensity:
        score}}`` (scored by :data:`HEADING_SCORER`).
    per_estimator : dict
        For each estimator that holds the range biases as states and was checked
        (:func:`estimator_biases`): ``{name: {"biases": "calibrated" or "as logged", **test}}``,
        ``test`` the paired test of the calibrated biases against the ranges as logged, scored
        by that estimator (:meth:`Comparison.as_dict`).
    excess : dict
        The non-line-of-sight excess fitted to the chosen replay's residuals (step 8,
        :func:`~quadobs.testbed.logs.excess_model.calibrated_excess`): ``chosen`` and the fit.
    constants : dict
        For each filter that holds constant states (step 10,
        :func:`~quadobs.testbed.logs.constants_start.estimator_constants`): ``{name: {"start":
        "first pass" or "prior", "states": count, **test}}``, ``test`` the paired test of the
        second pass (from the first pass's constants) against the first
        (:meth:`Comparison.as_dict`: ``score`` the second's held-out score, ``reference_score``
        the first's); for ``ukf-height-lever`` also ``"pattern"``: whether the tag's pattern
        was kept as states, and its paired test (with them against without).
    """

    biases: np.ndarray | None
    options: dict
    scores: dict
    reason: str
    candidate: np.ndarray
    held_out: dict = field(default_factory=dict)
    tests: dict = field(default_factory=dict)
    more_scores: dict = field(default_factory=dict)
    per_estimator: dict = field(default_factory=dict)
    excess: dict = field(default_factory=dict)
    constants: dict = field(default_factory=dict)

    @property
    def as_logged(self) -> tuple[str, ...]:
        """The estimators that take the ranges as logged (:func:`estimator_biases`)."""
        return tuple(k for k, v in self.per_estimator.items() if v["biases"] == "as logged")

    def biases_for(self, name: str) -> np.ndarray | None:
        """The biases the replay subtracts from the ranges of the estimator ``name`` where its
        measurements reach it in time: none where no biases were chosen or it takes the ranges
        as logged (:func:`~quadobs.testbed.logs.replay.run_replay`'s ``as_logged``)."""
        return None if self.biases is None or name in self.as_logged else self.biases

    def summary(self) -> dict:
        """As plain data, for the replay's summary."""
        return {
            "biases": None if self.biases is None else [float(v) for v in self.biases],
            "candidate_biases": [float(v) for v in self.candidate],
            "reason": self.reason,
            "held_out_score": {k: _finite(v) for k, v in self.held_out.items()},
            "tests": self.tests,
            "noise_scores": {f"{k:g}": _finite(v) for k, v in self.scores.items()},
            "process_noise": {
                k: v for k, v in self.options.items() if k in ("q_xy", "q_acc", "q_imu")
            },
            "heading_noise": {k: v for k, v in self.options.items() if k in HEADING_KEYS},
            **{
                f"{key}_scores": {f"{k:g}": _finite(v) for k, v in sc.items()}
                for key, sc in self.more_scores.items()
            },
            **({"per_estimator": self.per_estimator} if self.per_estimator else {}),
            **({"excess": self.excess} if self.excess else {}),
            **({"constants": self.constants} if self.constants else {}),
        }


def _set_bias_prior(log, options: dict, candidate) -> str:
    """Step 5's end: where ``options`` ask for it (``bias_prior=log``), the biases' prior of
    the filters that hold them as states set from the calibrated biases
    (:func:`biases_spread`); returns the reason's words."""
    if options.get("bias_prior") != FROM_LOG:
        return ""
    cap = float(bias_prior_std(log)[0])
    floor = range_noise_std(log, options)
    options["bias_prior"] = biases_spread(candidate, floor, cap)
    return (
        f"; the biases' prior {options['bias_prior']:.3f} m (the calibrated biases' spread,"
        f" within the ranges' noise {floor:.3g} m and {cap:g} m)"
    )


def _bias_step(log, dt, model, estimator, options, prior_res, cap):
    """Step 2 of the module docstring: ``(biases or None, candidate, residuals, test, reason)``."""
    b, res = _fixed_point(log, dt, model, estimator, ITERATIONS, options, first=prior_res)
    test = compare(res, prior_res, cap)
    if not _identified(b, res):
        why = f"not identified (every |b_h| within {IDENTIFIED:g} standard errors of its median)"
        return None, b, prior_res, test, why
    if not test.better:
        why = (
            f"not significantly better on the held-out ranges ({test.score:.3f} m with them, "
            f"{test.reference_score:.3f} m without)"
        )
        return None, b, prior_res, test, why
    why = f"held-out ranges {test.score:.3f} m with them, {test.reference_score:.3f} m without"
    return b, b, res, test, why


def calibrate(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    setup_options: dict | None = None,
    noise=True,
    estimator: str = "ekf",
) -> Calibration:
    """Biases and (with ``noise``) the process noise from the log, each kept only where it
    predicts the held-out ranges significantly better than the prior (module docstring).

    ``noise``: True (every intensity of :func:`noise_keys`), False (none), or the keys to fit
    (the others stay as ``setup_options`` set them or at their defaults).
    """
    model = model or default_model(log)
    options = {**log_defaults(log), **dict(setup_options or {})}
    q = log.beacons.shape[0]
    if log.ranges.shape[0] == 0 and log.tdoa.shape[0]:
        fit_tdoa = process_noise_key(model) in _fitted_keys(log, model, noise)
        return calibrate_tdoa(log, dt=dt, model=model, setup_options=options, noise=fit_tdoa)
    fit = _fitted_keys(log, model, noise)
    noise = process_noise_key(model) in fit
    if log.ranges.shape[0] == 0:
        return Calibration(None, options, {}, "the log holds no ranges", np.zeros(q))
    prior_res = _replay(log, dt, model, None, estimator, options)
    cap = _cap(prior_res)
    biases, cand, ref, btest, why = _bias_step(log, dt, model, estimator, options, prior_res, cap)
    held = {"prior": btest.reference_score, "with_biases": btest.score,
            "without": btest.reference_score}  # fmt: skip
    tests = {"biases": btest.as_dict()}
    reason = f"biases {'applied' if biases is not None else 'none'}: {why}"
    scores: dict = {}
    chosen_res = ref
    if noise:
        key = process_noise_key(model)
        prior = options.get(key, getattr(ReplaySetup, key))
        for i in range(PASSES):
            b = np.zeros(q) if biases is None else biases
            if i:  # the prior intensity with the refitted biases: the pass's reference
                ref = _replay(log, dt, model, b, estimator, {**options, key: prior})
            last = options.get(key, prior)
            options[key], scores, tests["noise"], runs = _noise_step(
                log, dt, model, estimator, {**options, key: prior}, b, ref, cap
            )
            t, kept = tests["noise"], options[key] != prior
            if i and not kept:  # the first pass's choice stands
                options[key] = last
                break
            chosen_res = runs[options[key]]
            reason += (
                f"; {key} {options[key]:g} ({'calibrated' if kept else 'the prior'}): the best"
                f" candidate {key} {t['candidate']:g} predicts the held-out ranges to"
                f" {_metres(t['score'])}, the prior {prior:g} to {_metres(t['reference_score'])},"
                f" {'' if t['significantly_better'] else 'not '}significantly better"
            )
            if not kept or (i and options[key] == last):
                break
            biases, chosen_res, rtest, refit = _refit_biases(
                log, dt, model, estimator, options, biases, chosen_res, prior_res, cap
            )
            tests["refit"] = {**rtest.as_dict(), "kept": refit}
            if not refit:
                break
            cand = biases
            reason += f"; biases refitted at {key} {options[key]:g}: {rtest.score:.3f} m held out"
    final = compare(chosen_res, prior_res, cap)
    tests["final"] = final.as_dict()
    changed = biases is not None or (noise and options[key] != prior)
    if changed and not final.better:  # the whole setting against the prior, once more
        biases, chosen_res = None, prior_res
        if noise:
            options[key] = prior
        reason += "; all reverted to the prior: the setting as a whole is not significantly better"
    held["chosen"] = compare(chosen_res, prior_res, cap).score
    reason += _set_bias_prior(log, options, cand)
    heading = tuple(k for k in fit if k in HEADING_KEYS)
    options, more, heading_tests, why = heading_noise(
        log, biases, dt=dt, model=model, setup_options=options, keys=heading
    )
    tests.update(heading_tests)
    excess, excess_why = calibrated_excess(log, chosen_res, options)  # step 8
    reason += f"{why}; non-line-of-sight excess {excess_why}"
    return Calibration(biases, options, scores, reason, cand, held, tests, more, excess=excess)


def bias_prior_std(log, options: dict | None = None) -> np.ndarray:
    """The prior standard deviation (m) of each anchor's bias state in the replay's filters:
    ``options``' ``bias_prior`` where set (``--tune``, or :func:`biases_spread` for
    ``bias_prior=log``), else :class:`~quadobs.core.measurements.RangeModel`'s extra states
    (:data:`~quadobs.core.measurements.RANGE_BIAS_PRIOR_STD`, 0.5 m)."""
    from quadobs.core.measurements import RANGE_BIAS_PRIOR_STD

    given = (options or {}).get("bias_prior")
    if given is None or given == FROM_LOG:  # unset, or not yet resolved (step 5's end)
        given = RANGE_BIAS_PRIOR_STD
    return np.full(log.beacons.shape[0], float(given))


def biases_spread(candidate, floor: float, cap: float) -> float:
    """The biases' prior standard deviation set from a log (step 5's end, module docstring):
    the maximum-likelihood spread of the calibrated biases ``c``,
    ``sigma_b = sqrt(mean_h c_h^2)``, clipped to ``[floor, cap]``.

    The biases are modelled as drawn ``b_h ~ N(0, sigma_b^2)`` (a hierarchical prior) and
    ``sigma_b`` is estimated from the log, as its noise intensity is: a prior much wider than
    the biases leaves a flight's weak direction (a height offset against the pattern of biases
    ``u_h,z dz`` that it moves, docs/error-sources.md) to the data alone. The calibrated biases
    also hold what the calibration's EKF does not model (the position error's share, an
    acceleration's offset), which widens the estimate; ``cap`` (the range model's 0.5 m, the
    upper end of antenna delays) keeps the estimate from loosening the prior (a field of biases
    of metres keeps the 0.5 m and its biases are applied, step 7), ``floor`` (the ranges' noise
    standard deviation) keeps it from holding the biases tighter than one range resolves.
    Non-finite biases give ``cap``."""
    c = np.asarray(candidate, dtype=float)
    if c.size == 0 or not np.all(np.isfinite(c)):
        return float(cap)
    return float(min(cap, max(floor, math.sqrt(float(np.mean(c * c))))))


def outside_prior(biases, prior_std) -> tuple[float, float]:
    """``(chi2, limit)``: ``chi2 = sum_h (b_h / sigma_h)^2`` of ``biases`` under the bias
    states' prior ``N(0, diag(sigma^2))``, and its ``1 -`` :data:`SIGNIFICANCE` quantile of
    ``chi^2(q)``; biases with ``chi2 > limit`` are improbable under that prior."""
    z = np.asarray(biases, dtype=float) / np.asarray(prior_std, dtype=float)
    return float(z @ z), chi2_ppf(1.0 - SIGNIFICANCE, z.size)


def range_noise_std(log, options: dict | None = None) -> float:
    """The ranges' noise standard deviation (m) as the filters take it: the median of the log's
    own per-range ``std`` where every row states one
    (:attr:`~quadobs.testbed.logs.estimators.ReplaySetup.range_std_stated`), else the replay's
    ``range_sigma`` (``options`` over the log's defaults,
    :func:`~quadobs.testbed.logs.estimators.log_defaults`)."""
    stated = log_range_std(log)
    if stated is not None:
        return stated
    merged = {**log_defaults(log), **dict(options or {})}
    return float(merged.get("range_sigma", ReplaySetup.range_sigma))


def effect_margin(log, options: dict | None = None) -> float:
    """Step 7's effect (m^2 of mean held-out loss): ``sigma^2 / d``, the mean square that a
    position error of length ``sigma`` (``sigma / sqrt(d)`` per axis; ``sigma`` the ranges'
    noise, :func:`range_noise_std`), oriented at random, adds to a range in ``d`` dimensions:
    its projection on the range's direction. On a planar log whose anchors stand above the
    tag a range's direction leaves the plane and the projection is smaller by the square of
    the elevation's cosine, which the margin leaves out (a margin slightly too large asks a
    little more of the calibrated biases)."""
    return range_noise_std(log, options) ** 2 / int(log.dimension)


def estimator_biases(
    log, cal: Calibration, names, *, dt: float = 0.1, model: str | None = None
) -> tuple[str, ...]:
    """Step 7 of the module docstring: for each estimator of ``names`` that holds the range
    biases as states (:func:`holds_range_biases`), the calibrated biases ``cal.biases`` kept
    only where the data say its own prior is wrong; else it takes the ranges as logged.

    Subtracting the biases from the ranges is the same as starting the filter's bias states at
    them: the choice is the bias states' prior mean, zero (the filter's own prior, the
    reference) or the calibrated biases, which are kept where

    * replayed through that estimator, they predict the held-out ranges significantly better
      than the ranges as logged *by an effect that matters*: the paired test of the module
      docstring with the margin :func:`effect_margin`, ``D + K s_D / sqrt(B) < -sigma^2 / d``
      (the mean square that a position error of length ``sigma``, the ranges' noise, adds to
      a range), or
    * they are improbable under the bias states' prior (:func:`outside_prior`: ``sum_h
      (b_h / sigma_b)^2`` beyond the ``1 -`` :data:`SIGNIFICANCE` quantile of ``chi^2(q)``):
      a filter started from zero would have to find biases its prior all but excludes.

    Within the prior, the filter finds the biases itself, and the EKF's biases (fitted without
    the filter's states, so also taking up what it holds as states, such as an acceleration's
    bias) would start it from that compromise. The held-out test seldom decides for such a
    filter: a position offset against a pattern of biases predicts the ranges almost as well
    from either start, so a significant gain can be a small one that says nothing of the
    position. Significance alone kept the calibrated biases on 4 of the 30 bias filters of the
    ``real`` flights of ``sims/replay_flight_variants.py`` (seeds 0-9) with gains of 0.0001 to
    0.0003 m^2 against margins of 0.0056-0.0065 m^2, and on the three of the ``bias`` flight of
    seed 3 (0.0013-0.0026 m^2 against 0.0033 m^2); the ranges as logged placed ``ekf-bias-imu``
    better on both seeds 3 (0.187 against 0.219 m, 0.146 against 0.204 m:
    ``python sims/bias_start_study.py``, docs/error-sources.md).

    The filters are scored with the one-sided gate even where step 8 gave them the excess's
    mixture (:data:`EXCESS_KEYS`): under the mixture a filter predicts a range's line-of-sight
    length, and its held-out residuals then carry the excess it does not predict, which tells
    the two starts apart by the excess rather than by the position (on the ``real`` flight of
    ``sims/replay_flight_variants.py``, seed 0, it took the calibrated biases for
    ``ekf-bias-imu``, 0.200 against 0.235 m held out, and reached 0.223 m where the ranges as
    logged reach 0.123 m).
    The heading filter that holds each anchor's height beside its bias (``ukf-height-lever``)
    is decided by its prior alone (:func:`_offsets_biases`).

    Records each choice in ``cal.per_estimator`` and ``cal.reason``; returns the names that take
    the ranges as logged (:attr:`Calibration.as_logged`). Nothing to check where no biases were
    applied, but the heights an odometry log states are checked first in any case
    (:func:`check_stated_heights`, where ``ukf-height-lever`` is among ``names``).
    """
    model = model or default_model(log)
    if "ukf-height-lever" in names and model == "odometry":
        check_stated_heights(log, cal, dt=dt, model=model)
    if cal.biases is None:
        return ()
    zero = np.zeros(log.beacons.shape[0])
    chi2, limit = outside_prior(cal.biases, bias_prior_std(log, cal.options))
    options = {k: v for k, v in cal.options.items() if k not in EXCESS_KEYS}  # the gate's
    margin = effect_margin(log, cal.options)
    for name in names:
        est = _scoring_estimator(log, dt, model, zero, name, options, None)[1]
        if _offsets_biases(log, cal, name, est):
            continue
        alias = getattr(est, "scored_as", None)
        if alias in cal.per_estimator:  # scored as an estimator already decided: its choice
            cal.per_estimator[name] = dict(cal.per_estimator[alias])
            cal.reason += f"; {name}: as {alias}, the same filter when scored"
            continue
        if not holds_range_biases(est):
            continue
        logged = _replay(log, dt, model, None, name, options)
        test = compare(_replay(log, dt, model, cal.biases, name, options), logged, margin=margin)
        scored = (
            f"; scored by {name}, the held-out ranges {_metres(test.score)} with them,"
            f" {_metres(test.reference_score)} as logged,"
            f" {'' if test.better else 'not '}significantly better by the margin"
            f" {margin:.2g} m^2"
        )
        _record_biases(
            cal, name, test.better or chi2 > limit, (chi2, limit), "range biases as states",
            "the biases'", test.as_dict(), scored,
        )  # fmt: skip
    return cal.as_logged


def _record_biases(cal, name, kept, chi2_limit, states, what_chi2, figures, scored="") -> None:
    """Step 7's choice for ``name`` in ``cal.per_estimator`` and a clause of ``cal.reason``."""
    chi2, limit = chi2_limit
    cal.per_estimator[name] = {
        "biases": "calibrated" if kept else "as logged",
        "prior_chi2": chi2,
        "prior_limit": limit,
        **figures,
    }
    what = "the calibrated biases subtracted" if kept else "the ranges as logged"
    cal.reason += (
        f"; {name} ({states}): {what}; {what_chi2} chi-square under its prior {chi2:.1f}"
        f" ({'above' if chi2 > limit else 'within'} {limit:.1f}){scored}"
    )


def check_stated_heights(log, cal: Calibration, *, dt: float = 0.1, model=None) -> None:
    """Step 7's first check: heights a log states (an odometry log's anchor heights and tag
    height, :func:`~quadobs.testbed.logs.height_estimators.known_offsets`) held against the
    ranges, before any filter starts from them.

    ``ukf-height-lever``, the filter that holds each anchor's offset beside the heading and
    the lever arm, is replayed twice on the ranges as logged, its offsets started from the
    statement and from the storey's prior, the same ranges held out. Where the storey's start
    predicts them significantly better (the paired test of the module docstring), the ranges
    contradict the statement (a tag height in another frame than the anchors', a survey error
    of decimetres): the options set ``stated_heights = 0`` and every filter takes the storey's
    prior, as for a planar log. A prior too tight at wrong offsets is what this guards
    against: with each height's error taken independent and of the survey's size alone, a tag
    height stated 0.5 m off took ``ukf-height-lever`` to 0.374 m on the posed robot (``all``,
    seed 0), where the storey's prior gives 0.089 m; the joint prior of
    :func:`~quadobs.testbed.logs.height_estimators.known_offsets` stays at 0.069 m there
    (docs/error-sources.md, "Heights stated in the log"). Run by :func:`estimator_biases`
    where ``ukf-height-lever`` is replayed with the model ``odometry``, whether or not biases
    were chosen; not with ``--calibrate none`` or ``--biases`` (no calibration: the statement
    is taken as given). Nothing to check where the log states no heights or holds TDOA, or
    ``--tune stated_heights=0`` turned them off."""
    from quadobs.testbed.logs.height_estimators import known_offsets

    if (
        known_offsets(log) is None
        or log.tdoa.shape[0]
        or not cal.options.get("stated_heights", 1.0)
    ):
        return
    name = "ukf-height-lever"
    options = {k: v for k, v in cal.options.items() if k not in EXCESS_KEYS}
    stated = _replay(log, dt, model, None, name, {**options, "stated_heights": 1.0})
    storey = _replay(log, dt, model, None, name, {**options, "stated_heights": 0.0})
    test = compare(storey, stated)
    if test.better:
        cal.options["stated_heights"] = 0.0
    cal.tests["stated_heights"] = test.as_dict()
    cal.reason += (
        f"; the stated heights (the tag at {log.tag_height:g} m), scored by {name}: the "
        f"held-out ranges {_metres(test.reference_score)} from them, "
        f"{_metres(test.score)} from a storey's prior: "
        f"{'not used, the ranges contradict them' if test.better else 'used'}"
    )


def _offsets_biases(log, cal: Calibration, name: str, est) -> bool:
    """Step 7 for the heading filter that holds each anchor's height beside its bias
    (:func:`~quadobs.testbed.logs.height_estimators.holds_anchor_offsets`); ``False`` for any
    other estimator.

    The biases fitted here by a model without heights hold each anchor's bias and the apparent
    bias of its height (:func:`~quadobs.testbed.logs.height_estimators.apparent_bias_prior`,
    ``g_h +- sigma_g,h``), which such a filter holds as its offset state, started at its prior
    mean: subtracting them counts the height twice. Under the filter's own prior (the bias
    ``N(0, sigma_b^2)``, the height's share beside it) a calibrated bias is ``N(g_h, sigma_b^2 +
    sigma_g,h^2)``; the biases are kept only where that prior all but excludes them
    (:func:`outside_prior` of ``c - g``: the Plaza field's biases of metres, where ``g`` is
    centimetres), else the filter takes the ranges as logged and finds them itself. Recorded as
    :func:`estimator_biases` records its choices."""
    from quadobs.testbed.logs.height_estimators import apparent_bias_prior, holds_anchor_offsets

    if not holds_anchor_offsets(est):
        return False
    mean, std = apparent_bias_prior(log, bool(cal.options.get("stated_heights", 1.0)))
    spread = np.sqrt(np.square(bias_prior_std(log)) + std * std)  # its own prior: 0.5 m
    chi2, limit = outside_prior(np.asarray(cal.biases, dtype=float) - mean, spread)
    _record_biases(
        cal, name, chi2 > limit, (chi2, limit), "range biases and heights as states",
        "the biases less the heights' apparent bias,", {},
    )  # fmt: skip
    return True


def _excess_loss(res: Residuals, fit: dict, cap: float) -> np.ndarray:
    """The held-out losses of step 9 (:func:`estimator_excess`): the negative log-likelihood of
    each held-out residual, clipped to ``[-c, c]`` (a non-finite one counted at ``-c``), under
    the fitted excess ``fit`` (:meth:`~quadobs.testbed.logs.excess_model.ExcessFit.summary`)."""
    r = res.held_out()
    r = np.clip(np.where(np.isfinite(r), r, -cap), -cap, cap)
    return excess_nll(r, fit["median"], fit["shape"], fit["fraction"], fit["sigma"])


def _takes_excess(log, dt, model, name, options) -> bool:
    """Whether the estimator ``name`` weighs the ranges by the excess's mixture under ``options``."""
    from quadobs.estimators.robust import ExcessMixture

    zero = np.zeros(log.beacons.shape[0])
    est = _scoring_estimator(log, dt, model, zero, name, options, None)[1]
    return isinstance(getattr(est, "robust", None), ExcessMixture)


def estimator_excess(log, cal: Calibration, names, *, dt: float = 0.1, model: str | None = None):
    """Step 9 of the module docstring: the excess fitted in step 8 kept only where each
    estimator of ``names`` that takes it (:func:`~quadobs.testbed.logs.bias_estimators.range_rule`)
    predicts the held-out ranges significantly better with it than with the one-sided gate.

    Each such estimator is replayed twice with the range biases of step 7 (those it takes,
    :func:`estimator_biases`, to be run first), once under the mixture and once under the gate,
    the same ranges held out. The score, the same for both: the mean negative log-likelihood of
    the held-out residuals under the fitted model of the ranges (line-of-sight noise plus the
    excess on a fraction, :func:`~quadobs.testbed.logs.excess_model.excess_nll`; residuals
    clipped to the gate replay's loss cap, :data:`CAP`), tested as any setting is (the paired
    block test, one candidate). Both filters predict a range's line-of-sight length plus their
    bias estimate, and the likelihood weighs a long residual as the model of the ranges does:
    a squared loss would favour a filter whose bias estimates take up part of the excess. Where
    any of them is not significantly better, the options lose the excess (every filter keeps
    the gate). Records ``cal.excess["check"]`` and the reason; nothing to check where no
    excess was chosen or no estimator of ``names`` takes it.

    Not run by the replay (``docs/error-sources.md``, "A held-out check of the excess"): on
    the flights of ``sims/replay_flight_variants.py`` it dropped the losses (seed 2's ``real``
    and ``bias``) and the largest gain alike (seed 0's ``real``, 0.175 -> 0.123 m). The
    held-out ranges score the prediction of a range, not of the position: where an anchor is
    blocked for long, the gate's bias state takes up the excess and predicts that anchor's
    ranges well while the vehicle is placed worse, and the mixture, which holds the anchor as
    blocked, predicts its line-of-sight length (held-out median residual +0.40 m on two
    anchors of seed 0's ``real``, against +0.11 and +0.03 m under the gate).
    """
    if not cal.excess.get("chosen"):
        return
    model = model or default_model(log)
    gate = {k: v for k, v in cal.options.items() if k not in EXCESS_KEYS}
    checks, kept = {}, True
    for name in names:
        if not _takes_excess(log, dt, model, name, cal.options):
            continue
        b = None if name in cal.as_logged else cal.biases
        ref = _replay(log, dt, model, b, name, gate)
        mix = _replay(log, dt, model, b, name, cal.options)
        cap = _cap(ref)
        a, c = _excess_loss(mix, cal.excess, cap), _excess_loss(ref, cal.excess, cap)
        test = _paired(a, c, float(np.mean(a)), float(np.mean(c)))
        squared = compare(mix, ref, cap)
        checks[name] = {**test.as_dict(), "squared": squared.as_dict()}
        kept = kept and test.better
        cal.reason += (
            f"; {name}, the excess checked: the held-out ranges' negative log-likelihood"
            f" {test.score:.3f} under the mixture, {test.reference_score:.3f} under the gate,"
            f" {'' if test.better else 'not '}significantly better (root mean capped square"
            f" {_metres(squared.score)} against {_metres(squared.reference_score)})"
        )
    if not checks:
        return
    cal.excess["check"] = checks
    if not kept:
        for k in EXCESS_KEYS:
            cal.options.pop(k, None)
        cal.excess["chosen"] = False
        cal.reason += "; the excess dropped: the filters keep the one-sided gate"


def _fitted_keys(log, model: str, noise) -> tuple[str, ...]:
    """The intensities of :func:`noise_keys` that ``noise`` (True, False or keys) asks for."""
    keys = noise_keys(log, model)
    return keys if noise is True else tuple(k for k in keys if noise and k in noise)


def heading_noise(
    log,
    biases=None,
    *,
    dt: float = 0.1,
    model: str | None = None,
    setup_options: dict | None = None,
    keys=HEADING_KEYS,
) -> tuple[dict, dict, dict, str]:
    """Step 6 of the module docstring: the heading filters' intensities ``keys``, in turn, each
    the candidate ``prior 4^j`` of the smallest held-out score of :data:`HEADING_SCORER` with
    ``biases``, kept only if significantly better than the setting before it.

    Returns the options with the intensities chosen, the scores ``{key: {intensity: score}}``,
    the tests ``{key: Comparison.as_dict()}`` and the reason's clauses.
    """
    model = model or default_model(log)
    options = dict(setup_options or {})
    if not keys:
        return options, {}, {}, ""
    b = np.zeros(log.beacons.shape[0]) if biases is None else np.asarray(biases, dtype=float)
    current = _replay(log, dt, model, b, HEADING_SCORER, options)
    cap = _cap(current)
    scores, tests, reason = {}, {}, ""
    for key in keys:
        prior = options.get(key, getattr(ReplaySetup, key))
        chosen, scores[key], t, runs = _noise_step(
            log, dt, model, HEADING_SCORER, {**options, key: prior}, b, current, cap, key
        )
        options[key], current, tests[key] = chosen, runs[chosen], t
        reason += (
            f"; {key} {chosen:g} ({'calibrated' if chosen != prior else 'the prior'}, scored by"
            f" {HEADING_SCORER}): the best candidate {key} {t['candidate']:g} predicts the"
            f" held-out ranges to {_metres(t['score'])}, the prior {prior:g} to"
            f" {_metres(t['reference_score'])},"
            f" {'' if t['significantly_better'] else 'not '}significantly better"
        )
    return options, scores, tests, reason


def tdoa_estimator(model: str) -> str:
    """The estimator that scores a log of TDOA: the TDOA observer handing over to the EKF
    (``tdoa-handover``) where the model has an acceleration input (``imu``), else the EKF. From
    the anchors' centroid the EKF alone may linearise a TDOA far from the truth and settle on a
    wrong point (from 10 m off, in 24 of 50 seeds of ``quadrotor-tdoa``); the handover starts
    on the observer, which does not linearise."""
    return "tdoa-handover" if model == "imu" else "ekf"


def calibrate_tdoa(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    setup_options: dict | None = None,
    noise: bool = True,
) -> Calibration:
    """The process noise of a log of TDOA, from its held-out TDOA (module docstring, step 3 with
    the TDOA ``d_ij`` in place of the ranges: ``r = d_ij - (|p^- - a_i| - |p^- - a_j|)``).

    No biases: a TDOA carries the difference of two anchors' delays, which the replay's TDOA
    estimators do not model. The intensity of the smallest held-out score among ``prior 4^j``
    is kept only where it is significantly better than the prior's (Bonferroni over the
    candidates), else the prior stands. The scoring estimator: :func:`tdoa_estimator`.
    """
    model = model or default_model(log)
    options = {**log_defaults(log), **dict(setup_options or {})}
    q = log.beacons.shape[0]
    if not noise:
        return Calibration(None, options, {}, "a log of TDOA: no range biases", np.zeros(q))
    key, estimator = process_noise_key(model), tdoa_estimator(model)
    prior = options.get(key, getattr(ReplaySetup, key))
    options[key] = prior
    prior_res = _replay(log, dt, model, None, estimator, options)
    cap = _cap(prior_res)
    chosen, scores, test, runs = _noise_step(
        log, dt, model, estimator, options, np.zeros(q), prior_res, cap
    )
    options[key] = chosen
    reason = (
        f"a log of TDOA, scored by {estimator}: no range biases; {key} {chosen:g} "
        f"({'calibrated' if chosen != prior else 'the prior'}): the best candidate {key} "
        f"{test['candidate']:g} predicts the held-out TDOA to {_metres(test['score'])}, the "
        f"prior {prior:g} to {_metres(test['reference_score'])}, "
        f"{'' if test['significantly_better'] else 'not '}significantly better"
    )
    held = {"prior": test["reference_score"], "chosen": compare(runs[chosen], prior_res, cap).score}
    return Calibration(None, options, scores, reason, np.zeros(q), held, {"noise": test})


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
