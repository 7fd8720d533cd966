"""The replay's filters with one range bias per anchor as a state: ``ekf-bias`` and ``ukf-bias``.

The filters of :mod:`quadobs.estimators.bias_states` (the start-up fix, the biases held in a
consider update until the innovations are consistent, the re-initialisation after a lock-out)
on the replay's model of the log (:class:`~quadobs.testbed.logs.estimators.ReplaySetup`): the
vehicle's state and its process noise are those of the replay's EKF
(:func:`~quadobs.testbed.logs.estimators.build_ekf`), each anchor's bias a constant state of
prior standard deviation the setup's
:meth:`~quadobs.testbed.logs.estimators.ReplaySetup.bias_prior_std`:
:data:`~quadobs.core.measurements.RangeModel`'s extra state (0.5 m, the upper end of UWB
antenna delays) unless ``--tune bias_prior`` sets it (``log``: the spread of the
self-calibration's biases, :func:`~quadobs.testbed.logs.calibration.biases_spread`).

Their gate is a :class:`~quadobs.estimators.robust.SkewedGate`: a range whose standardised
innovation is too *long* for line of sight is left out, since non-line-of-sight excess is
positive and a bias state would take it in. Its two-sided probability is that of the replay's
``gate`` (a threshold on ``chi^2(1)``), else 0.999.
They keep that gate where the self-calibration estimated the ranges' non-line-of-sight excess
(:mod:`~quadobs.testbed.logs.excess_model`), which ``ekf-bias-imu-nlos`` takes through an
:class:`~quadobs.estimators.robust.ExcessMixture` (:func:`range_rule`): under the mixture they
lost on two of four body-IMU flights (their innovations also carry the acceleration's slow
error, which they do not hold as a state; the cause was not examined further). Measured on the flights of
``sims/replay_flight_variants.py`` (seed 0, position RMSE after 5 s), ``ekf-bias`` under the
estimated mixture against the gate: ``full`` 0.116 against 0.175 m, ``nostd`` 0.155 against
0.186 m, but ``bias`` 0.359 against 0.220 m and ``real`` 0.391 against 0.203 m.
A log that states its ranges Gaussian (``meta.csv`` ``range_errors`` ``gaussian``, as an
exported scenario without a radio does) gives them no gate unless ``gate`` is asked for: as the
live filters of such a scenario, which take no robust rule where ``[noise]`` sets none.

The output noise ``R`` (the variance of a range that states none, and of the start-up fix:
:func:`~quadobs.estimators.bias_states.fix_std`) is that of the log's stated ranges, the median
of ``ranges.csv``'s ``std`` where every row states one, as the live filters take the
scenario's stated range noise; else the replay's ``range_sigma``.

These filters run on logs of ranges (any model); a log of TDOA is refused by name (a TDOA
cancels a bias common to both anchors, and the per-pair bias is not a state here).

``augmented-bias``: the observer of [IFAC2021, Thm. 3] with the biases in the immersion
(:class:`~quadobs.estimators.augmented_bias.BiasedAugmentedObserver`,
:mod:`quadobs.core.range_bias`) on the replay's model. Its settings are those of the replay's
augmented observer (:func:`~quadobs.testbed.logs.estimators.build_augmented`), read from an
instance of it so that both follow one rule: the immersion, the fixed process-noise intensity
``V`` (the auxiliary states' noise bounded through the largest anchor distance; the
state-dependent ``V(z)`` the augmented observer uses in time was measured worse here: 0.57 m
against 0.45 m after 10 s on the one-lap circle of ``tests/testbed/test_calibration.py``), the initial
covariance (that of ``lift(x)`` around the guess), ``theta``; each range's own standard
deviation, else ``range_sigma``, gives its output's variance ``rho^2 sigma^2 + sigma^4 / 2``;
the biases' prior is the filters'
(:meth:`~quadobs.testbed.logs.estimators.ReplaySetup.bias_prior_std`). No robust rule: its
covariance is a tuning, and a gate would lock it out of the global convergence it is there
for (as in the simulated scenarios, where only Huber's rule is applied to it).
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["build_augmented_bias", "build_ekf_bias", "build_ukf_bias", "range_rule"]


def _gate_probability(gate: float | None) -> float:
    """The probability of ``chi^2(1)`` below the threshold ``gate`` (``None``: 0.999)."""
    if gate is None:
        return 0.999
    return math.erf(math.sqrt(float(gate) / 2.0))


def range_rule(s, excess: bool = True):
    """The robust rule of the replay's range-bias filters on the setup ``s``: none for a log
    that states its ranges Gaussian (unless ``gate`` is asked for); with ``excess``, an
    :class:`~quadobs.estimators.robust.ExcessMixture` of the excess where the setup knows it
    (``nlos_median``, ``nlos_shape``: estimated from the log by the self-calibration); else
    the :class:`~quadobs.estimators.robust.SkewedGate`. Both at the probability of ``gate``;
    the mixture's chain of sight at the stationary probability ``nlos_prior`` (0.5 unless tuned).

    ``ekf-bias`` and ``ukf-bias`` take it without the excess (the module docstring)."""
    from quadobs.estimators.robust import ExcessMixture, SkewedGate

    if s.gate is None and s.range_errors == "gaussian":
        return None
    probability = _gate_probability(s.gate)
    if excess and s.nlos_median is not None and s.nlos_shape is not None:
        nlos = getattr(s, "nlos_prior", None)  # the chain's stationary probability (tunable)
        if nlos is None:  # a setup that states none: the mixture's own default
            return ExcessMixture(s.nlos_median, s.nlos_shape, probability=probability)
        return ExcessMixture(s.nlos_median, s.nlos_shape, nlos=nlos, probability=probability)
    return SkewedGate(probability)


def _build(s, x0: np.ndarray, name: str, cls, process_noise: np.ndarray):
    from quadobs.estimators.bias_states import BiasedRangeOutputModel, extended_system
    from quadobs.estimators.kalman import HeldInputModel
    from quadobs.testbed.logs.start_prior import set_velocity_prior

    if "tdoa" in s.kinds:
        raise QuadobsError(
            f"estimators: {name!r} estimates range biases and the log holds TDOA (use ekf or ukf)"
        )
    system = s.system
    n, q = system.n, system.q
    ext = extended_system(system)
    V = np.zeros((n + q, n + q))
    V[:n, :n] = process_noise
    dynamics = HeldInputModel(ext, s.dt, V=V)
    offsets = 0.5 * np.einsum("hi,hi->h", system.d, system.d)
    sigma = s.range_sigma if s.range_std_stated is None else s.range_std_stated
    outputs = BiasedRangeOutputModel(ext, sigma**2 * np.eye(q), offsets=offsets)
    P = np.zeros((n + q, n + q))
    P[:n, :n] = np.diag(np.full(n, s.P0))
    P[n:, n:] = s.bias_prior_std() ** 2 * np.eye(q)
    xe = np.concatenate([np.asarray(x0, dtype=float)[:n], np.zeros(q)])
    if n > s.dim:  # the velocity, as the replay's EKF
        set_velocity_prior(s, xe, P, s.dim)
    rule = range_rule(s, excess=False)
    est = cls(dynamics, outputs, x0=xe, P0=P, vehicle_n=n, robust=rule)
    est.name = name
    return est


def build_ekf_bias(s, x0: np.ndarray, name: str, process_noise: np.ndarray):
    """The EKF with the anchors' range biases as states; ``process_noise`` the continuous
    intensity on the vehicle's state (that of the replay's EKF)."""
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter

    return _build(s, x0, name, BiasedExtendedKalmanFilter, process_noise)


def build_ukf_bias(s, x0: np.ndarray, name: str, process_noise: np.ndarray):
    """The UKF with the anchors' range biases as states (as :func:`build_ekf_bias`)."""
    from quadobs.estimators.bias_states import BiasedUnscentedKalmanFilter

    return _build(s, x0, name, BiasedUnscentedKalmanFilter, process_noise)


def build_augmented_bias(s, x0: np.ndarray, name: str, observer):
    """The augmented observer with the anchors' range biases in its immersion (module
    docstring); ``observer`` the replay's augmented observer built for the same log and guess,
    whose immersion, ``V``, initial covariance and ``theta`` it takes."""
    from quadobs.estimators.augmented_bias import BiasedAugmentedObserver

    if "tdoa" in s.kinds:
        raise QuadobsError(
            f"estimators: {name!r} estimates range biases and the log holds TDOA (use ekf or ukf)"
        )
    est = BiasedAugmentedObserver(
        observer.immersion,
        s.dt,
        sigma=s.range_sigma,
        V=np.asarray(observer.model.V, dtype=float),
        P0=observer.P,
        bias_std=s.bias_prior_std(),
        theta=observer.model.theta,
        x0=np.asarray(x0, dtype=float)[: s.n],
    )
    est.name = name
    return est
