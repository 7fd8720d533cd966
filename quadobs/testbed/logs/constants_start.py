"""Step 10 of the self-calibration: each filter's constant states started from a first pass.

A filter that holds constant states (:mod:`quadobs.estimators.constants`: each anchor's range
bias, its height's offset, the tag's lever arm) learns them from its prior while it runs, and
its position carries their error until they settle: on the wheeled robot's logs
``ukf-height-lever`` is 0.2 m off over its first 20 s and under 0.1 m after a minute
(docs/error-sources.md). What the log says of a constant is known once the log has been read:
filtered to the log's end, the constant's estimate is its smoothed estimate at every time
(the module docstring of :mod:`quadobs.estimators.constants`).

So, for each filter of the replay that holds constant states and predicts a range by its own
model (each member of an average apart), by its own name ``F``: the bias filters (``ekf-bias``,
``ukf-bias``, ``ekf-bias-imu``, ``ekf-bias-imu-nlos``: ``|p - a_h| + b_h``) and the heading
filters with a lever arm or anchors' states (``ukf-lever``, ``ukf-height-lever``: the tag's
range with its offset and bias). ``ekf-height`` and ``ukf-height`` hold each anchor's bias and
offset too, but the calibration scores them by the planar distance from their position,
which is not their prediction of a range: they keep their own prior. The augmented observers
(``augmented-bias``, ``augmented-height``) do not expose their constants and keep theirs.

1. the first pass: ``F`` replayed through the log as the calibration replays every setting
   (:func:`~quadobs.testbed.logs.calibration.prediction_residuals`: from the anchors'
   centroid, the same ranges held out, the ranges with or without the calibrated biases as
   the replay gives them to it), its constants' estimate ``c_N`` and covariance ``P_N`` read
   at the end. The held-out ranges never enter them;
2. the second pass: ``F`` replayed again, its constants' prior ``N(c_N, P_N)`` in place of its
   own, uncorrelated with the vehicle's state;
3. the start kept where the second pass predicts the held-out ranges of the whole log (the
   other steps score its second half, after the transient; here the transient is what the
   start is for) at least as well as the first, by the capped score of
   :mod:`~quadobs.testbed.logs.calibration`; else ``F`` keeps its own prior. The paired test
   is reported beside the choice, not asked to be significant: a position offset against a
   pattern of constants predicts the ranges almost as well as the right position (step 7's
   docstring), so the held-out ranges tell the two starts apart only weakly (on the robot's
   15 stress logs ``ukf-height-lever``'s second pass was ahead on every log, by 1.35 to 2.31
   standard errors, where its position RMSE was about half the first's:
   docs/error-sources.md). The held-out ranges guard against a start that predicts them
   worse, such as constants that changed during the log
   (tests/testbed/test_constants_start.py). A first pass that gave up (reported diverged), or
   whose constants are not finite, starts nothing.

The tag's pattern (``ukf-height-lever``, :data:`PATTERN_FILTERS`). A tag's delay that turns
with the vehicle, ``c cos 2 phi_h + s sin 2 phi_h`` of the anchor's bearing ``phi_h`` from the
heading (:mod:`quadobs.estimators.heading_ekf`), can be two more constants of the filter.
Where the user has not fixed them (``--tune tag_pattern=0`` or ``1``), the first and second
passes are run both with and without them, and they are kept (the setup's ``tag_pattern``
set to 1, their start that of their own passes) only where the start kept with them predicts
the held-out ranges *significantly* better than the start kept without (the paired test, one
candidate): states that the ranges do not ask for only add to the position's error (measured
on the robot's logs: docs/error-sources.md).

What the second pass counts twice. Its prior ``P_N`` holds the ranges that the second pass
reads again, so at the log's end its constants' covariance is about half what the data
support, and the position's covariance is the smaller for it. The start is for the position's
estimate; its covariance errs small by that share. A wider prior counts the ranges less twice;
measured on the robot's logs and a simulated room it was no better in general
(docs/error-sources.md), so the first pass's own covariance is taken.

Where the calibration is not run (``--calibrate none``, ``--biases``) every filter keeps its
own prior, and the replay is online from its first measurement on; nor where the replay puts
the measurements on its grid (``--set noise.*``: every filter then takes the calibrated
biases, which a start found on the ranges as logged would count twice). With the calibration, as
with its biases (steps 2 to 7), a filter's start is read from the whole log before the replay.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.estimators.constants import constant_filters
from quadobs.testbed.logs.calibration import (
    Calibration,
    _scoring_estimator,
    compare,
    holds_range_biases,
    prediction_residuals,
)
from quadobs.testbed.worlds.replay import default_model

__all__ = ["START_KEY", "estimator_constants"]

#: The setup option that carries the starts (:attr:`~quadobs.testbed.logs.estimators.ReplaySetup.constants_start`).
START_KEY = "constants_start"
#: The setup switch of the tag's pattern as states (:attr:`~quadobs.testbed.logs.estimators.ReplaySetup.tag_pattern`).
PATTERN_KEY = "tag_pattern"
#: The filters that may hold the tag's pattern (the heading filter with the lever arm, the
#: anchors' biases and heights).
PATTERN_FILTERS = ("ukf-height-lever",)


def _constant_filters_and_biases(log, dt, model, names, cal: Calibration) -> dict:
    """``{filter name: the biases its ranges take}`` for each filter of ``names`` that holds
    constant states and predicts a range by its own model (a bias filter's ``|p - a_h| +
    b_h``, a heading filter's ``predicted_range``): the estimator itself or an average's
    members, by their own names, each with the biases the replay subtracts for the estimator
    (:meth:`~quadobs.testbed.logs.calibration.Calibration.biases_for`). A filter met under two
    estimators whose biases differ is left out: one start could not serve both."""
    zero = np.zeros(log.beacons.shape[0])
    out: dict = {}
    clash: set = set()
    for name in names:
        est = _scoring_estimator(log, dt, model, zero, name, cal.options, None)[1]
        biases = cal.biases_for(name)
        for f in constant_filters(est):
            if not (holds_range_biases(f) or hasattr(f, "predicted_range")):
                continue  # scored by a range it does not predict (ekf-height's, planar)
            key = getattr(f, "scored_as", None) or f.name
            if key in out and not _same(out[key], biases):
                clash.add(key)
            out.setdefault(key, biases)
    return {k: v for k, v in out.items() if k not in clash}


def _same(a, b) -> bool:
    """Whether the biases ``a`` and ``b`` (arrays, or None) are the same."""
    return (a is None and b is None) or (
        a is not None and b is not None and np.array_equal(np.asarray(a), np.asarray(b))
    )


def _unusable(start) -> str:
    """Why the constants ``(mean, covariance)`` of a first pass cannot start a filter, or ``""``."""
    mean, cov = start
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        return "its first pass ended with constants that are not finite"
    sym = 0.5 * (cov + cov.T)
    if np.min(np.linalg.eigvalsh(sym)) < -1e-12 * max(1.0, float(np.max(np.abs(sym)))):
        return "its first pass ended with a covariance that is not positive semi-definite"
    return ""


def _first_and_second(log, dt, model, name, biases, options):
    """The first pass's residuals and, where its constants can start the filter, the second
    pass's from them (else ``None`` and why not)."""
    kw = dict(dt=dt, model=model, biases=biases, estimator=name, scored_from=-math.inf)
    first = prediction_residuals(
        log, setup_options=options, own_range=True, read_constants=True, **kw
    )
    start = first.constants.get(name)
    why = "its first pass gave up (reported diverged)" if start is None else _unusable(start)
    if why:
        return first, None, why
    second = prediction_residuals(
        log, setup_options={**options, START_KEY: {name: start}}, own_range=True, **kw
    )
    return first, second, ""


def estimator_constants(
    log, cal: Calibration, names, *, dt: float = 0.1, model: str | None = None
) -> None:
    """Step 10 (module docstring) for each filter of ``names`` that holds constant states: the
    starts kept set in ``cal.options[START_KEY]``, each choice and its test in
    ``cal.constants`` and a clause of ``cal.reason``."""
    model = model or default_model(log)
    options = {k: v for k, v in cal.options.items() if k != START_KEY}
    kept: dict = {}
    for name, biases in _constant_filters_and_biases(log, dt, model, names, cal).items():
        passes = _first_and_second(log, dt, model, name, biases, options)
        if name in PATTERN_FILTERS and PATTERN_KEY not in options:
            passes = _with_or_without_pattern(log, dt, model, name, biases, options, cal, passes)
        first, second, why = passes
        if second is None:
            cal.constants[name] = {**cal.constants.get(name, {}), "start": "prior", "why": why}
            cal.reason += f"; {name}: its own prior, {why}"
            continue
        start = first.constants[name]
        test = compare(second, first)
        better = test.score <= test.reference_score
        if better:
            kept[name] = start
        cal.constants[name] = {
            **cal.constants.get(name, {}),
            "start": "first pass" if better else "prior",
            "states": int(start[0].size),
            **test.as_dict(),
        }
        scores = (
            f"the held-out ranges {test.score:.3f} m from it, {test.reference_score:.3f} m from"
            " its prior"
        )
        cal.reason += f"; {name} ({start[0].size} constant states): " + (
            f"started from a first pass through the log ({scores})"
            if better
            else f"its own prior, a first pass through the log predicting worse ({scores})"
        )
    if kept:
        cal.options[START_KEY] = kept


def _chosen(first, second):
    """The residuals of the start step 10 keeps: the second pass where it predicts the held-out
    ranges at least as well as the first, else the first."""
    if second is None:
        return first
    test = compare(second, first)
    return second if test.score <= test.reference_score else first


def _with_or_without_pattern(log, dt, model, name, biases, options, cal, without):
    """The tag's pattern as states of ``name`` (module docstring) where, each with its own
    start, they predict the held-out ranges significantly better than without; the passes
    of the setting kept, the choice and its test in ``cal.constants[name]["pattern"]``, a
    clause of ``cal.reason``, and ``cal.options[PATTERN_KEY]`` set to 1 where kept."""
    with_ = _first_and_second(log, dt, model, name, biases, {**options, PATTERN_KEY: 1.0})
    test = compare(_chosen(*with_[:2]), _chosen(*without[:2]))
    kept = test.better and not with_[2]
    cal.constants[name] = {"pattern": {"kept": kept, **test.as_dict()}}
    scores = (
        f"the held-out ranges {test.score:.3f} m with them, {test.reference_score:.3f} m without"
    )
    why = f"with them {with_[2]}" if with_[2] else "not significantly better"
    cal.reason += f"; {name}: the tag's pattern as states " + (
        f"kept ({scores})" if kept else f"not kept ({scores}: {why})"
    )
    if kept:
        cal.options[PATTERN_KEY] = 1.0
        options[PATTERN_KEY] = 1.0  # the other filters' passes see the same setup
        return with_
    return without
