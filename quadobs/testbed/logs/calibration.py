"""Range biases per beacon, calibrated from the log itself: never from the ground truth.

Radio ranges carry a bias per beacon (about +2 to +3 m on the Plaza logs), which the
quadratic output model cannot hold as a state (``(rho - b)^2`` is not quadratic in
``(p, b)``). The procedure, a fixed-point iteration on the replayed estimate:

1. replay the log with the biases ``b^(0) = 0`` through one estimator (the EKF by
   default), from the beacons' centroid (or a given initial guess);
2. over the ranges of the second half of the log (the first half is left to the
   transient), the residuals ``r_h = rho - b_h^(i) - |p_hat(t) - a_h|`` with ``p_hat`` the
   replayed estimate at the range's step; ``b_h^(i+1) = b_h^(i) + median_h(r)``, the median
   resisting the outliers;
3. repeat ``iterations`` times (3 by default; the update is then below a few centimetres
   on both Plaza logs).

Only the ranges, the odometry and the estimator's own output enter: the truth is not read
(the world is built from the log with its truth column, but :func:`calibrate_biases`
reads only the estimate columns). The residual is biased towards zero where the estimate
itself absorbed part of the bias, so the calibration is a lower bound on the biases'
size; the documentation reports what it gives.
"""

from __future__ import annotations

import numpy as np

from quadobs.testbed.logs.estimators import build_replay_estimators, replay_setup
from quadobs.testbed.sinks import Rows, Sink
from quadobs.testbed.worlds.replay import ReplayWorld, default_model, state_size

__all__ = ["calibrate_biases"]


class _Estimates(Sink):
    """The first estimator's position at every step."""

    def __init__(self, steps: int, dim: int = 2) -> None:
        self.P = np.full((steps + 1, dim), np.nan)

    def block(self, rows: Rows) -> None:
        name = self.ctx.names[0]
        self.P[rows.ks] = rows.estimates[name][:, : self.P.shape[1]]


def calibrate_biases(log, *, dt: float = 0.1, model: str | None = None, x0=None, estimator: str = "ekf",
                     iterations: int = 3, setup_options: dict | None = None) -> np.ndarray:
    """Per-beacon range biases ``(q,)`` (m) by the procedure of the module docstring.

    ``model``: default :func:`~quadobs.testbed.worlds.replay.default_model`; ``x0``: the
    initial guess (default: the beacons' centroid, velocity zero).
    """
    model = model or default_model(log)
    q, dim = log.beacons.shape[0], log.dimension
    b = np.zeros(q)
    if x0 is None:
        x0 = np.zeros(state_size(log, model))
        x0[:dim] = log.beacons.mean(axis=0)
    for _ in range(int(iterations)):
        P, steps = _replayed_positions(log, dt, model, b, np.asarray(x0, dtype=float), estimator, setup_options)
        k = np.floor((log.ranges[:, 0] - log.start) / dt + 1e-9).astype(np.int64)
        h = log.beacon_index(log.ranges[:, 1])
        late = (k >= steps // 2) & (k < steps)
        p_hat = P[k[late]]
        r = log.ranges[late, 2] - b[h[late]] - np.linalg.norm(p_hat - log.beacons[h[late]], axis=1)
        for j in range(q):
            rj = r[(h[late] == j) & np.isfinite(r)]
            if rj.size:
                b[j] += float(np.median(rj))
    return b


def _replayed_positions(log, dt, model, biases, x0, estimator, setup_options) -> tuple[np.ndarray, int]:
    """One replay of ``log`` with ``biases`` through ``estimator``: its position at every step ``(K + 1, dim)``, and ``K``."""
    from quadobs.testbed.episode import run_loop

    world = ReplayWorld(log, dt, model, 8192, biases, peer_batch=False)
    ests = build_replay_estimators(replay_setup(log, world, setup_options), [estimator], x0)
    sink = _Estimates(world.steps, log.dimension)
    run_loop(lambda *args: {}, frame=world.frame(), world=world, estimators=ests, sinks=[sink])
    return sink.P, world.steps
