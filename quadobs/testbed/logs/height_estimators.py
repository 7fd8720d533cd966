"""The replay's filters with each anchor's bias and height above the tag as states: ``ekf-height``
and ``ukf-height``.

The filters of :mod:`quadobs.estimators.height_states` on the replay's model of a planar log
(:class:`~quadobs.testbed.logs.estimators.ReplaySetup`): ``ekf-bias`` / ``ukf-bias``
(:mod:`quadobs.testbed.logs.bias_estimators`: the vehicle's state and process noise of the
replay's EKF, the biases' prior 0.5 m, the one-sided gate) with one more constant state per
anchor, the offset of its squared range ``e_h = delta z_h^2 / 2``.

The offsets' prior. A planar log says nothing of its anchors' heights; indoors they hang
between the floor and the ceiling of one storey, :data:`STOREY` = 3 m. With the height of an
anchor above the tag taken uniform on ``[0, STOREY]`` (``H`` for short), ``e_h = dz_h^2 / 2`` has
the mean and standard deviation

.. math::

    \\mathrm E[e_h] = \\frac{\\mathrm E[\\delta z^2]}{2} = \\frac{H^2}{6}, \\qquad
    \\sqrt{\\operatorname{Var} e_h} = \\frac{\\sqrt{\\mathrm E[\\delta z^4] - \\mathrm E[\\delta z^2]^2}}{2}
    = \\frac{H^2}{\\sqrt{45}},

1.5 m^2 and 1.34 m^2 (:data:`E_MEAN`, :data:`E_STD`): the offsets start there. (A prior at
``e_h = 0``, the anchors in the tag's plane as the log draws them, with the standard deviation
``H^2 / 4``, was measured worse where the anchors are high: docs/error-sources.md.) A log in
space (3-D beacons) has its heights and is refused by name.

A wheel-odometry log that states its anchors' heights ``z_h`` (``beacons.csv`` with ``z``)
and the tag's ``z_t`` (``meta.csv`` ``tag_height``) gives the offsets jointly. Each anchor's
height is surveyed to :data:`HEIGHT_SURVEY_STD` (``sigma_a``, independent errors); the tag's
height in the anchors' frame is stated to :data:`TAG_HEIGHT_STD` (``sigma_t``, one error
common to every anchor: a tag height measured on the vehicle from the floor, against anchors
surveyed in a frame whose floor may sit elsewhere). With ``u_h = dz_h + delta_h - delta_t``,
Gaussian of mean ``dz_h`` and covariance ``C = sigma_t^2 1 1^T + sigma_a^2 I``, the offsets
``e_h = u_h^2 / 2`` have (Isserlis' theorem) the mean and covariance

.. math::

    \\mathrm E[e_h] = \\frac{\\delta z_h^2 + C_{hh}}{2}, \\qquad
    \\operatorname{Cov}(e_h, e_k) = \\delta z_h \\delta z_k C_{hk} + \\frac{C_{hk}^2}{2}

(:func:`known_offsets`): the anchors' heights relative to one another tightly, their common
height above the tag loosely, which the filter then estimates. The heading filter that holds
the offsets starts there instead (:func:`offsets_prior`). Heights without the tag's leave the
storey's prior: the tag's height in the anchors' frame is what ties them to the offsets.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError

__all__ = [
    "EXCESS_MEMORY",
    "E_MEAN",
    "E_STD",
    "HEIGHT_SURVEY_STD",
    "STOREY",
    "apparent_bias_prior",
    "build_augmented_height",
    "build_ekf_height",
    "build_ukf_height",
    "excess_rule",
    "heading_height_options",
    "holds_anchor_offsets",
    "huber_rule",
    "known_offsets",
    "offsets_prior",
]

#: The height of one storey (m): the largest height of an indoor anchor above a ground tag.
STOREY = 3.0
#: Prior mean of each squared-range offset ``e_h = dz_h^2 / 2`` (m^2): ``dz`` uniform on ``[0, STOREY]``.
E_MEAN = STOREY**2 / 6.0
#: Prior standard deviation of each offset (m^2), for the same uniform ``dz``.
E_STD = STOREY**2 / 45.0**0.5
#: The standard deviation (m) of a surveyed anchor's height: a tape or a total station, as the
#: anchors' positions (:func:`known_offsets`).
HEIGHT_SURVEY_STD = 0.05
#: The standard deviation (m) of the tag's stated height in the anchors' frame, common to every
#: anchor's offset (:func:`known_offsets`): the height above the floor is measured on the
#: vehicle to centimetres, the floor's height in the frame of a survey is often not stated,
#: and an error of tenths of a metre is one of convention, which the ranges then tell.
TAG_HEIGHT_STD = 0.3


def known_offsets(log) -> tuple[np.ndarray, np.ndarray] | None:
    """The prior ``(mean (q,), covariance (q, q))`` (m^2, m^4) of the squared-range offsets
    where the log states the anchors' heights and the tag's (module docstring), else None."""
    heights = getattr(log, "anchor_heights", None)
    tag = float(getattr(log, "tag_height", math.nan))
    if heights is None or not math.isfinite(tag):
        return None
    dz = np.asarray(heights, dtype=float) - tag
    C = TAG_HEIGHT_STD**2 + HEIGHT_SURVEY_STD**2 * np.eye(dz.size)
    return 0.5 * (dz * dz + np.diag(C)), np.outer(dz, dz) * C + 0.5 * C * C


def offsets_prior(s) -> tuple[np.ndarray, np.ndarray]:
    """The offsets' prior ``(mean (q,), covariance (q, q))`` of ``ukf-height-lever`` on the
    setup ``s``: the log's (:attr:`~quadobs.testbed.logs.estimators.ReplaySetup.offsets`)
    unless set aside, else the storey's :data:`E_MEAN`, :data:`E_STD` for each anchor,
    independent.

    Only the heading filter that holds the offsets (``ukf-height-lever``) takes the log's:
    started from them, ``ekf-height`` and ``augmented-height`` (the heading taken as known)
    were measured worse than from the storey's prior where the tag's height is stated 0.5 m
    off (``ekf-height`` 0.353 against 0.185 m) and ``augmented-height`` even where it is right
    (0.388 against 0.264 m), ``ukf-height-lever`` better in every case (docs/error-sources.md,
    "Heights stated in the log")."""
    if getattr(s, "offsets", None) is not None and float(getattr(s, "stated_heights", 1.0)):
        return s.offsets
    q = s.beacons.shape[0]
    return np.full(q, E_MEAN), np.eye(q) * E_STD**2


#: The time (s) over which a heading filter remembers that an anchor's path was blocked
#: (:func:`excess_rule`): a vehicle passes an obstacle's shadow in seconds, not between two
#: rounds of the anchors (a quarter of a second at 16 Hz over four). A stated figure, checked
#: by measurement on the wheeled robot's stand-ins (docs/error-sources.md, "Stress").
EXCESS_MEMORY = 1.0


def _build(s, x0: np.ndarray, name: str, cls, process_noise: np.ndarray):
    from quadobs.core.measurements import RangeModel
    from quadobs.estimators.height_states import HeightRangeOutputModel, height_system
    from quadobs.estimators.kalman import HeldInputModel
    from quadobs.estimators.robust import SkewedGate
    from quadobs.testbed.logs.bias_estimators import _gate_probability

    if "tdoa" in s.kinds:
        raise QuadobsError(
            f"estimators: {name!r} estimates range biases and the log holds TDOA (use ekf or ukf)"
        )
    if s.dim != 2:
        raise QuadobsError(
            f"estimators: {name!r} estimates the anchors' heights above a planar tag; the log "
            "is in space (its beacons have z): use ekf-bias"
        )
    system = s.system
    n, q = system.n, system.q
    ext = height_system(system)
    V = np.zeros((n + 2 * q, n + 2 * q))
    V[:n, :n] = process_noise
    dynamics = HeldInputModel(ext, s.dt, V=V)
    offsets = 0.5 * np.einsum("hi,hi->h", system.d, system.d)
    outputs = HeightRangeOutputModel(ext, s.range_sigma**2 * np.eye(q), offsets=offsets)
    P0 = np.full(n, s.P0)
    P0[s.dim :] = 4.0  # the velocity, as the replay's EKF
    extra = RangeModel(s.beacons, s.range_sigma, bias="state").extra_states()
    prior = np.concatenate([P0, [e.prior_std**2 for e in extra], np.full(q, E_STD**2)])
    xe = np.concatenate([np.asarray(x0, dtype=float)[:n], np.zeros(q), np.full(q, E_MEAN)])
    rule = SkewedGate(_gate_probability(s.gate))
    est = cls(dynamics, outputs, x0=xe, P0=np.diag(prior), vehicle_n=n, robust=rule)
    est.name = name
    return est


def build_ekf_height(s, x0: np.ndarray, name: str, process_noise: np.ndarray):
    """The EKF with the anchors' biases and squared-range offsets as states (module docstring)."""
    from quadobs.estimators.height_states import HeightBiasedExtendedKalmanFilter

    return _build(s, x0, name, HeightBiasedExtendedKalmanFilter, process_noise)


def build_ukf_height(s, x0: np.ndarray, name: str, process_noise: np.ndarray):
    """The UKF with the anchors' biases and squared-range offsets as states (module docstring)."""
    from quadobs.estimators.height_states import HeightBiasedUnscentedKalmanFilter

    return _build(s, x0, name, HeightBiasedUnscentedKalmanFilter, process_noise)


def build_augmented_height(s, x0: np.ndarray, name: str, process_noise: np.ndarray):
    """The augmented observer with the anchors' squared-range offsets as constant states of its
    immersion (:class:`~quadobs.estimators.height_states.HeightAugmentedObserver`), on a planar
    odometry log. Its settings are the replay's augmented observer's
    (:func:`~quadobs.testbed.logs.estimators.build_augmented`): the process noise
    ``process_noise`` on ``x'`` mapped into the immersed state at the estimate, the prior of
    ``lift(x)``, the output noise ``(median range * range_sigma)^2``; the offsets' prior
    :data:`E_MEAN`, :data:`E_STD`."""
    from quadobs.core.immersion import immerse
    from quadobs.estimators.height_states import HeightAugmentedObserver, height_quadratic_system

    if "tdoa" in s.kinds or s.dim != 2 or s.model != "odometry":
        raise QuadobsError(
            f"estimators: {name!r} takes the ranges of a planar odometry log (the anchors' "
            "heights above the tag as states)"
        )
    n, q = s.n, s.system.q
    im = immerse(height_quadratic_system(s.system))
    k = im.n_aux
    xe = np.concatenate([np.asarray(x0, dtype=float)[:n], np.full(q, E_MEAN)])
    p0 = xe[: s.dim]
    P = np.eye(im.dim) * s.P0
    P[0, 0] = s.P0 * p0 @ p0 + s.P0**2  # the covariance of xi = |p|^2 / 2 for p ~ N(p0, P0 I)
    P[0, k : k + s.dim] = P[k : k + s.dim, 0] = s.P0 * p0
    P[k + n :, k + n :] = np.eye(q) * E_STD**2
    L, J = im.aux_forms, np.zeros((im.dim, n))
    J[k : k + n] = np.eye(n)

    def noise(z: np.ndarray) -> np.ndarray:  # V(z) = J V_x J^T, J = [x^T L_i; I_n; 0]
        J[:k] = (L @ z[k:])[:, :n]
        V = J @ process_noise @ J.T
        return 0.5 * (V + V.T)

    R = (s.range_median * s.range_sigma) ** 2
    est = HeightAugmentedObserver(
        im, s.dt, V=noise(im.lift(xe)), W=R * s.dt, P0=P, z0=im.lift(xe), gate=s.gate,
        noise_of=noise, vehicle_n=n, anchors=s.beacons,
    )  # fmt: skip
    est.name = name
    return est


def heading_height_options(s, name: str, excess: bool = True) -> dict:
    """The options of a heading filter (:mod:`quadobs.estimators.heading_ekf`) that carries each
    anchor's range bias (prior 0 and the bias states' stated 0.5 m,
    :data:`~quadobs.core.measurements.RANGE_BIAS_PRIOR_STD`, as ``ekf-height``) and its
    squared-range offset (prior :data:`E_MEAN`, :data:`E_STD`): a planar log of ranges only.
    The biases are states as well as the offsets because the self-calibration's constant
    biases, fitted by a model without heights, take up part of them.

    Its robust rule (:func:`excess_rule`; ``excess=False``: :func:`huber_rule`, Huber's
    symmetric M-estimator): Huber's bound on a range's innovation less its expected
    non-line-of-sight excess, as the filters of the same states take the one-sided gate
    (``ekf-height``, ``ekf-bias``): without one, a range's outlier moves the anchor's bias and
    offset states in full, and a burst of long ranges moves them step by step."""
    from quadobs.core.measurements import RANGE_BIAS_PRIOR_STD

    if "tdoa" in s.kinds or s.dim != 2:
        raise QuadobsError(
            f"estimators: {name!r} estimates the anchors' heights above a planar tag from "
            "ranges; the log holds TDOA or is in space (use ukf-heading)"
        )
    rule = excess_rule(s) if excess else huber_rule(s.gate)
    return {"offsets": offsets_prior(s), "bias_std": RANGE_BIAS_PRIOR_STD, "robust": rule}


def excess_rule(s):
    """The heading filters' default robust rule: Huber's bound ``c`` (:func:`huber_rule`) on a
    range's innovation less its expected non-line-of-sight excess
    (:class:`~quadobs.estimators.robust.ExcessHuber`), the excess stated by the range noise
    ``sigma`` (``s.range_sigma``) and ``c`` alone (:meth:`ExcessHuber.at_bound
    <quadobs.estimators.robust.ExcessHuber.at_bound>`; ``sigma`` the median of the standard
    deviations the log states, else ``s.range_sigma``): exponential of mean ``c sigma`` (0.26 m
    at 0.08 m), a range ``c sigma`` long as likely blocked as clear (a prior probability of
    0.015), and each anchor's evidence of a blocked path carried over :data:`EXCESS_MEMORY`.

    Huber's symmetric rule bounds each long range's pull but takes a burst of them (an obstacle
    beside the path lengthens every range to an anchor behind it while the vehicle passes);
    this one shifts a long range by its expected excess, so what a burst's range leaves of its
    innovation is at most 2.29 standard deviations (the prior 0.015), tending to ``lambda S``
    for a range far beyond the noise (:class:`~quadobs.estimators.robust.ExcessHuber`). Where no excess shows it is Huber's rule (a range
    within the noise is shifted by millimetres); nothing is rejected, so it cannot lock the
    filter out. Measured in docs/error-sources.md ("Stress: what the stand-ins had not
    posed", ``pillar``)."""
    from quadobs.estimators.robust import ExcessHuber

    sigma = s.range_sigma if s.range_std_stated is None else s.range_std_stated
    return ExcessHuber.at_bound(huber_rule(s.gate).c, sigma, EXCESS_MEMORY)


def huber_rule(gate: float | None):
    """Huber's M-estimator (:class:`~quadobs.estimators.robust.Huber`) whose bound ``c`` is the
    replay's gate on the standardised innovation: ``c = sqrt(gate)`` for a threshold ``gate`` on
    ``chi^2(1)``, else ``sqrt(chi2_(0.999)(1)) = 3.29``, the two-sided probability of the
    one-sided gate of ``ekf-height`` (:func:`~quadobs.testbed.logs.bias_estimators._gate_probability`).

    A range within ``c`` standard deviations of its prediction (``|nu| <= c sqrt(S)``) corrects
    in full: a line-of-sight range is down-weighted with probability 0.001. Beyond it its
    variance is multiplied by ``|nu| / (c sqrt(S))``, which bounds its correction to ``c
    sqrt(S)``: an outlier of a metre at a radio's 0.08 m moves the states as a range ``3.3``
    standard deviations off would, and never locks the filter out (Huber's rule rejects
    nothing, unlike a gate). Measured on the wheeled robot posed with every effect:
    docs/error-sources.md, "A log with a stated range std"."""
    import math

    from quadobs.estimators.robust import Huber, chi2_threshold
    from quadobs.testbed.logs.bias_estimators import _gate_probability

    return Huber(math.sqrt(chi2_threshold(_gate_probability(gate), 1)))


def holds_anchor_offsets(est) -> bool:
    """Whether ``est`` is a heading filter that holds each anchor's range bias and squared-range
    offset as states (``ukf-height-lever``: the range ``sqrt(|q - a_h|^2 + 2 e_h) + b_h``, the
    heading and the lever arm beside them): a filter that models every error the
    self-calibration's constant biases take up (the heights, the tag's offset, the heading's
    drift).

    Not ``ekf-height``: it takes the dead-reckoned heading as known, as the calibration's EKF
    does, so the calibrated biases also take up the heading's drift, which it does not model;
    taking the ranges as logged was measured no better for it (docs/error-sources.md)."""
    from quadobs.estimators.heading_ekf import HeadingEKF, HeadingUKF

    return isinstance(est, (HeadingEKF, HeadingUKF)) and est._ib >= 0 and est._ie >= 0


def apparent_bias_prior(log, stated: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The constant bias ``(mean, std)`` (m, per anchor) that the offsets' prior gives a range
    read by a model without heights, as the self-calibration's EKF reads it.

    At the anchor's typical range ``r_h`` (the median of its logged ranges) the offset ``e_h``
    adds ``g_h = sqrt(r_h^2 + 2 e_h) - r_h`` to the planar distance; at the prior mean
    :data:`E_MEAN`, to first order in ``e_h`` about it,

    .. math::

        \\bar g_h = \\sqrt{r_h^2 + 2 \\bar e} - r_h, \\qquad
        \\sigma_{g,h} = \\frac{\\sigma_e}{\\sqrt{r_h^2 + 2 \\bar e}} ,

    ``sigma_e`` = :data:`E_STD` (the log's own prior where it states the heights,
    :func:`known_offsets`, unless ``stated`` is False). In a room (``r_h`` about 1.5 m) that is 0.79 +- 0.59 m; on a
    field of tens of metres, centimetres. The self-calibration checks its biases against it
    for the heading filter that holds the offsets (:func:`holds_anchor_offsets`;
    :mod:`quadobs.testbed.logs.calibration`, step 7)."""
    from quadobs.testbed.logs.schema import RANGE

    anchor = log.beacon_index(log.ranges[:, RANGE.beacon])
    r = np.zeros(log.beacons.shape[0])
    for h in range(r.size):
        rows = log.ranges[anchor == h, RANGE.range]
        r[h] = float(np.median(rows)) if rows.size else 0.0  # none: the height's whole share
    stated_prior = known_offsets(log) if stated else None
    e_mean, e_std = np.full(r.size, E_MEAN), np.full(r.size, E_STD)
    if stated_prior is not None:
        e_mean, e_std = stated_prior[0], np.sqrt(np.diag(stated_prior[1]))
    s = np.sqrt(r * r + 2.0 * e_mean)
    return s - r, e_std / s
