"""Lower bounds on a scenario's estimation error along its true trajectory.

The bounds themselves (:func:`quadobs.evaluation.ensemble.posterior_crb`) know nothing
of scenarios; these functions set them up from a scenario's sensors and reference.
"""

from __future__ import annotations

import numpy as np

from quadobs.core.held_input import HeldInputDiscretization
from quadobs.core.immersion import immerse
from quadobs.estimators.kalman import HeldInputModel
from quadobs.evaluation.ensemble import lifted_covariance, posterior_crb, range_factor
from quadobs.testbed.factories import initial_covariance


def scenario_crb(scenario, every: int = 1) -> tuple[np.ndarray, np.ndarray, str] | None:
    """The posterior Cramér-Rao bound of ``scenario``'s estimation problem along its true trajectory.

    Same model as the baselines (:func:`quadobs.testbed.factories.baseline_settings`): exact held-input
    dynamics with the accelerometer's noise ``Q = sigma_a^2 G G^T`` per physics step, ranges
    (and airspeed) with Gaussian noise of the sensors' standard deviations at their sample
    steps, and the prior :func:`quadobs.testbed.factories.initial_covariance`. The expectation
    ``E[H^T R^-1 H]`` is evaluated at the reference state (the MuJoCo truth follows it
    exactly: RK4 integrates the double integrator exactly). Dropouts of probability ``d``
    scale the information by ``1 - d`` (the information-reduction-factor bound, a valid,
    looser, bound); outliers are left out, which over-states the information of a sample
    (the Fisher information of a Gaussian mixture is at most that of its narrowest
    component), so the bound stays a lower bound.

    Returns
    -------
    (times (T,), bound (T, n, n), note) or None
        ``None`` when a sensor is noise-free: the information is then infinite and the bound zero.
    """
    noise = scenario.noise
    if noise.range_std <= 0 or (scenario.has_wind and noise.airspeed_std <= 0):
        return None
    dim, n = scenario.dimension, scenario.state_dim
    steps, dt = scenario.steps, scenario.dt
    system = scenario.system()
    dyn = HeldInputModel(system, dt, input_covariance=noise.accel_std**2)
    P0, prior = initial_covariance(scenario)
    r_every = scenario.sample_interval(noise.range_rate, "range_rate")
    a_every = scenario.sample_interval(noise.airspeed_rate, "airspeed_rate")
    keep = np.sqrt(1.0 - noise.dropout)
    beacons = scenario.beacons
    q_b = beacons.shape[0]

    def factors(k):
        cols = []
        if k % r_every == 0:
            x = scenario.true_state(k * dt)
            L = np.zeros((n, q_b))
            L[:dim] = range_factor(x[:dim], beacons, noise.range_std)
            cols.append(L)
        if scenario.has_wind and k % a_every == 0:
            x = scenario.true_state(k * dt)
            va = x[dim : 2 * dim]
            s = np.linalg.norm(va)
            L = np.zeros((n, 1))
            if s > 0:
                L[dim : 2 * dim, 0] = va / (s * noise.airspeed_std)
            cols.append(L)
        if not cols:
            return None
        return keep * np.concatenate(cols, axis=1)

    bound = posterior_crb(dyn.F, dyn.Q, P0, steps, factors, every=every)
    times = np.arange(bound.shape[0]) * every * dt
    note = (
        f"ranges N(0, {noise.range_std:g}^2) every {r_every} steps, accelerometer N(0, {noise.accel_std:g}^2) per step, "
        f"prior from {prior}"
        + (f", information scaled by 1 - dropout = {1 - noise.dropout:g}" if noise.dropout else "")
    )
    return times, bound, note


def immersion_bound(scenario, every: int = 1) -> tuple[np.ndarray, np.ndarray] | None:
    """The error covariance of the best *linear* filter on the scenario's immersion, along its true trajectory.

    The augmented observer is a linear filter on the immersion ``z = (xi, x)``
    ([IFAC2021] eq. 14; :func:`quadobs.immerse`): its gains depend on
    the inputs only, so its estimate is affine in the outputs. Among such filters the
    Kalman filter with the true second moments has the least error covariance: this
    function runs it on the exact held-input discretisation
    (:class:`~quadobs.core.held_input.HeldInputDiscretization`, ``V = 0``, the true inputs),
    with the true variance of each output sample, ``Var(y_h) = rho_h^2 sigma^2 + sigma^4 / 2``
    for ``y_h = (rho_h + n)^2 / 2 + const`` (``E[n^2/2] = sigma^2/2`` is a known offset),
    and the exact second moments of ``z_0 = (xi(x_0), x_0)`` for
    ``x_0 ~ N(x_true(0), P_0)`` (``P_0``: :func:`quadobs.testbed.factories.initial_covariance`):
    ``Cov(xi_i, x) = P_0 L_i m``, ``Cov(xi_i, xi_j) = m^T L_i P_0 L_j m + tr(L_i P_0 L_j P_0) / 2``.

    Its ``x`` block lies above the posterior Cramér-Rao bound (:func:`scenario_crb`) by the
    information lost in treating the auxiliary states as free, and below the augmented
    observer's error by what its tuning (``V``, ``W``, ``S0``) costs. Dropouts and outliers
    are left out (more information: still a lower bound). Accelerometer noise enters the
    immersion multiplicatively and is not modelled: ``None`` for a noisy accelerometer, as
    for a noise-free range or airspeed sensor.

    Returns
    -------
    (times (T,), covariance of x (T, n, n)) or None
    """
    noise = scenario.noise
    if (
        noise.range_std <= 0
        or noise.accel_std > 0
        or (scenario.has_wind and noise.airspeed_std <= 0)
    ):
        return None
    dim, n, dt, steps = scenario.dimension, scenario.state_dim, scenario.dt, scenario.steps
    im = immerse(scenario.system(), method=scenario.observer.immersion)
    k_aux = im.n_aux
    disc = HeldInputDiscretization(im, dt, 0.0)
    C = im.output_matrix
    P0x, _ = initial_covariance(scenario)
    P = lifted_covariance(im.aux_forms, scenario.true_state(0.0), P0x)
    u_all = scenario.trajectory.step_accelerations(0.0, dt, steps)
    r_every = scenario.sample_interval(noise.range_rate, "range_rate")
    a_every = scenario.sample_interval(noise.airspeed_rate, "airspeed_rate")
    q_b = scenario.beacons.shape[0]
    out = np.empty((steps // every + 1, n, n))
    for k in range(steps + 1):
        if k % every == 0:
            out[k // every] = P[k_aux:, k_aux:]
        if k == steps:
            break
        rows, var = [], []
        if k % r_every == 0 or (scenario.has_wind and k % a_every == 0):
            x = scenario.true_state(k * dt)
            if k % r_every == 0:
                rho = np.linalg.norm(x[:dim] - scenario.beacons, axis=1)
                rows += list(range(q_b))
                var += list(rho**2 * noise.range_std**2 + 0.5 * noise.range_std**4)
            if scenario.has_wind and k % a_every == 0:
                s_ = np.linalg.norm(x[dim : 2 * dim])
                rows.append(q_b)
                var.append(s_**2 * noise.airspeed_std**2 + 0.5 * noise.airspeed_std**4)
        if rows:
            H = C[rows]
            PH = P @ H.T
            S = H @ PH + np.diag(var)
            P = P - PH @ np.linalg.solve(S, PH.T)
        Phi = disc.transition(u_all[k])
        P = Phi @ P @ Phi.T
        P = 0.5 * (P + P.T)
    times = np.arange(out.shape[0]) * every * dt
    return times, out
