"""Range biases and process noise, calibrated from the log itself: never from the ground truth.

Both rest on the prediction residuals of a replay: with ``p_hat_k`` the estimate at the
step of a range, *before* the estimator corrects with it (the record row of step ``k``),

.. math:: r = \\rho - b_h - |\\hat p_k - a_h| ,

over the ranges of the second half of the log (the first half is left to the transient).
Only the ranges, the inputs and the estimator's own output enter: the truth is not read
(the world is built from the log with its truth column, but the residuals read only the
estimate columns).

Range biases. Radio ranges carry a bias per beacon (about +2 to +5 m on the Plaza logs),
which the quadratic output model cannot hold as a state (``(rho - b)^2`` is not quadratic
in ``(p, b)``). :func:`calibrate_biases`, a fixed-point iteration: replay the log with
``b^(0) = 0`` through one estimator (the EKF by default) from the beacons' centroid (or a
given initial guess); ``b_h^(i+1) = b_h^(i) + median_h(r)``, the median resisting the
outliers; ``iterations`` times (3 by default). The residual is biased towards zero where
the estimate itself absorbed part of the bias, so the calibration is a lower bound on the
biases' size.

Process noise. The estimators' defaults (:class:`~quadobs.testbed.logs.estimators.ReplaySetup`)
are round priors chosen without any log; how much the model's input can be trusted
differs from log to log (Plaza1's odometry integrates to within a few metres over half an
hour, Plaza2's heading drifts), and a fixed intensity tuned on one log fails on the other
(``docs/replay.md``). :func:`calibrate_noise` picks the intensity of the model's process
noise (``q_xy``, ``q_acc`` or ``q_imu``) on the grid ``prior 4^j``, ``j = -4 .. 3``, that
minimises the median absolute prediction residual ``median |r - median_h(r)|``: a
prequential score (each range predicted before it is used), which never reads the truth.
Scores within 1 % of the best are ties, won by the smallest intensity (the model trusted
as far as the ranges allow).
:func:`self_calibrate` chains the two: biases at the prior, the noise, then the biases
again at the chosen noise.
"""

from __future__ import annotations

import numpy as np

from quadobs.testbed.logs.estimators import ReplaySetup, build_replay_estimators, replay_setup
from quadobs.testbed.sinks import Rows, Sink
from quadobs.testbed.worlds.replay import ReplayWorld, default_model, state_size

__all__ = [
    "NOISE_FACTORS",
    "calibrate_biases",
    "calibrate_noise",
    "process_noise_key",
    "self_calibrate",
]

#: The factors of the prior process-noise intensity that :func:`calibrate_noise` tries.
NOISE_FACTORS = tuple(4.0**j for j in range(-4, 4))
#: Scores within this fraction of the best are ties, won by the smallest intensity.
TIE = 0.01


class _Estimates(Sink):
    """The first estimator's position at every step."""

    def __init__(self, steps: int, dim: int = 2) -> None:
        self.P = np.full((steps + 1, dim), np.nan)

    def block(self, rows: Rows) -> None:
        name = self.ctx.names[0]
        self.P[rows.ks] = rows.estimates[name][:, : self.P.shape[1]]


def process_noise_key(model: str) -> str:
    """The :class:`ReplaySetup` field of a model's process-noise intensity."""
    return {"odometry": "q_xy", "cv": "q_acc", "imu": "q_imu"}[model]


def _initial(log, model: str, x0) -> np.ndarray:
    """``x0``, or the beacons' centroid with a zero velocity."""
    if x0 is not None:
        return np.asarray(x0, dtype=float)
    x = np.zeros(state_size(log, model))
    x[: log.dimension] = log.beacons.mean(axis=0)
    return x


def _residuals(
    log, dt, model, biases, x0, estimator, setup_options
) -> tuple[np.ndarray, np.ndarray]:
    """One replay with ``biases``: the prediction residuals ``r`` of the second half's ranges and their beacons ``h``."""
    P, steps = _replayed_positions(log, dt, model, biases, x0, estimator, setup_options)
    k = np.floor((log.ranges[:, 0] - log.start) / dt + 1e-9).astype(np.int64)
    h = log.beacon_index(log.ranges[:, 1])
    late = (k >= steps // 2) & (k < steps)
    r = (
        log.ranges[late, 2]
        - biases[h[late]]
        - np.linalg.norm(P[k[late]] - log.beacons[h[late]], axis=1)
    )
    ok = np.isfinite(r)
    return r[ok], h[late][ok]


def calibrate_biases(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    x0=None,
    estimator: str = "ekf",
    iterations: int = 3,
    setup_options: dict | None = None,
) -> np.ndarray:
    """Per-beacon range biases ``(q,)`` (m) by the fixed-point iteration of the module docstring.

    ``model``: default :func:`~quadobs.testbed.worlds.replay.default_model`; ``x0``: the
    initial guess (default: the beacons' centroid, velocity zero).
    """
    model = model or default_model(log)
    x0 = _initial(log, model, x0)
    b = np.zeros(log.beacons.shape[0])
    for _ in range(int(iterations)):
        r, h = _residuals(log, dt, model, b, x0, estimator, setup_options)
        for j in range(b.size):
            if np.any(h == j):
                b[j] += float(np.median(r[h == j]))
    return b


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
    """The model's process-noise intensity with the smallest prediction score (module docstring).

    Returns the intensity and the score (m) of every one tried, ``{intensity: score}``.
    """
    model = model or default_model(log)
    key, x0 = process_noise_key(model), _initial(log, model, x0)
    prior = (setup_options or {}).get(key, getattr(ReplaySetup, key))
    b = np.asarray(biases, dtype=float)
    scores = {}
    for factor in NOISE_FACTORS:
        q = prior * factor
        r, h = _residuals(log, dt, model, b, x0, estimator, {**(setup_options or {}), key: q})
        centred = (
            r
            - np.array([np.median(r[h == j]) if np.any(h == j) else 0.0 for j in range(b.size)])[h]
        )
        scores[q] = float(np.median(np.abs(centred)))
    best = min(scores.values())
    return min(q for q, score in scores.items() if score <= (1.0 + TIE) * best), scores


def self_calibrate(
    log,
    *,
    dt: float = 0.1,
    model: str | None = None,
    setup_options: dict | None = None,
    noise: bool = True,
) -> tuple[np.ndarray, dict, dict]:
    """Biases and (with ``noise``) the process noise from the log (module docstring).

    Returns the biases, the setup options (``setup_options`` with the chosen intensity)
    and the scores of :func:`calibrate_noise` (empty without ``noise``).
    """
    options = dict(setup_options or {})
    b = calibrate_biases(log, dt=dt, model=model, setup_options=options)
    if not noise:
        return b, options, {}
    q, scores = calibrate_noise(log, b, dt=dt, model=model, setup_options=options)
    options[process_noise_key(model or default_model(log))] = q
    return calibrate_biases(log, dt=dt, model=model, setup_options=options), options, scores


def _replayed_positions(
    log, dt, model, biases, x0, estimator, setup_options
) -> tuple[np.ndarray, int]:
    """One replay of ``log`` with ``biases`` through ``estimator``: its position at every step ``(K + 1, dim)``, and ``K``."""
    from quadobs.testbed.episode import run_loop

    world = ReplayWorld(log, dt, model, 8192, biases, peer_batch=False)
    ests = build_replay_estimators(replay_setup(log, world, setup_options), [estimator], x0)
    sink = _Estimates(world.steps, log.dimension)
    done, _ = run_loop(
        lambda merged, completed, wall, interrupted: {"interrupted": interrupted},
        frame=world.frame(),
        world=world,
        estimators=ests,
        sinks=[sink],
    )
    if done["interrupted"]:  # Ctrl-C, SIGTERM: no calibration from part of a replay
        raise KeyboardInterrupt
    return sink.P, world.steps
