"""The online (filtering) bound of ranging with a constant bias per anchor, and the information
of a range whose excess delay is known to be there.

Ranges ``z = |p - a_h| + b_h + v`` with ``b_h`` a constant bias of anchor ``h``. With the
biases as states, ``x_e = (x, b)``, the range's gradient is
``dz/dx_e = [(p - a_h)^T / |p - a_h|, 0, e_h^T]`` and the posterior Cramér-Rao bound
(:func:`~quadobs.evaluation.ensemble.posterior_crb`, Tichavsky, Muravchik and Nehorai 1998)
of the extended state is the covariance of a Kalman filter linearised along the true
trajectory. Given the biases, the same recursion runs with their block of the prior at zero:
it stays zero (the biases are then parameters known exactly), and the vehicle's block is the
bound of ranging with known biases. The ratio of the two bounds' position RMSEs is the least
factor by which not knowing the biases must raise an efficient online estimator's error.

Evaluated along the true trajectory (the expectation of the information over the states
replaced by its value there, as :func:`quadobs.testbed.bounds.scenario_crb` does); the biases
enter linearly, so over the biases' prior the bound is exact in them (it is the same for
every draw of the biases: a bound on the error averaged over that prior).

A range behind an obstacle carries an excess delay ``e >= 0``. Told which ranges are blocked
(an oracle no estimator has, which can only add information), a blocked range
``z = |p - a_h| + b_h + v + e`` with ``v ~ N(0, sigma^2)`` and ``e`` log-normal of a known
median and shape carries about the range the Fisher information of the location of the
density ``f = N(0, sigma^2) * p_e`` (:func:`excess_fisher_information`), which lies between
``1 / (sigma^2 + Var e)`` (what a linear estimator gets: the Gaussian has the least Fisher
information of a given variance) and ``1 / sigma^2`` (a convolution cannot add information).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal, stats

from quadobs.errors import QuadobsError, as_array
from quadobs.evaluation.ensemble import posterior_crb

__all__ = ["excess_fisher_information", "range_bias_crb", "rmse_bound"]


def excess_fisher_information(
    sigma: float, median: float, shape: float, resolution: int = 40
) -> float:
    """The Fisher information (1/m^2) about its location of a range with Gaussian noise and a
    log-normal excess.

    For ``z = theta + v + e``, ``v ~ N(0, sigma^2)``, ``e = median * exp(shape * n)``,
    ``n ~ N(0, 1)``, the density of ``z - theta`` is ``f = phi_sigma * p_e`` and

    .. math::

        J = \\int \\frac{f'(y)^2}{f(y)}\\, dy, \\qquad f' = \\phi_\\sigma' * p_e,

    evaluated on a grid of ``sigma / resolution`` (the excess's density to its ``1 - 1e-12``
    quantile, normalised on the grid; both convolutions by FFT).

    Parameters
    ----------
    sigma : float
        The range noise's standard deviation (m), positive.
    median, shape : float
        The excess's median (m, positive) and log-normal shape (positive).
    resolution : int
        Grid points per ``sigma``.

    Returns
    -------
    float
        ``J``, between ``1 / (sigma^2 + Var e)`` and ``1 / sigma^2``.
    """
    if not (sigma > 0 and median > 0 and shape > 0 and resolution >= 4):
        raise QuadobsError(
            "excess_fisher_information: expected sigma, median, shape > 0 and resolution >= 4, "
            f"got {sigma!r}, {median!r}, {shape!r}, {resolution!r}"
        )
    h = sigma / resolution
    top = median * math.exp(shape * stats.norm.isf(1e-12))
    cells = int(math.ceil(top / h))
    if cells > 10_000_000:
        raise QuadobsError(
            f"excess_fisher_information: the excess's tail ({top:.3g} m) needs {cells} grid "
            f"cells of {h:.3g} m; lower the resolution or the shape"
        )
    e = np.arange(1, cells + 1) * h
    p_e = stats.lognorm.pdf(e, shape, scale=median)
    p_e /= p_e.sum()
    y = np.arange(-int(math.ceil(10 * resolution)), int(math.ceil(10 * resolution)) + 1) * h
    phi = stats.norm.pdf(y, scale=sigma) * h
    dphi = -y / sigma**2 * phi
    f = signal.fftconvolve(p_e, phi)
    df = signal.fftconvolve(p_e, dphi)
    ok = f > 1e-300
    return float(np.sum(df[ok] ** 2 / f[ok]))


def range_bias_crb(
    F: np.ndarray,
    Q: np.ndarray,
    P0: np.ndarray,
    steps: int,
    beacons: np.ndarray,
    step: np.ndarray,
    anchor: np.ndarray,
    position: np.ndarray,
    information: np.ndarray,
    *,
    every: int = 1,
) -> np.ndarray:
    """The posterior Cramér-Rao bound of a vehicle ranged to anchors with a bias state each.

    The state is ``x_e = (p, ..., b)``: the position ``p`` first (``dim`` entries, as the
    anchors'), the vehicle's other states, then one bias per anchor (the last ``q`` entries).
    Range ``i``, taken during step ``step[i]`` to anchor ``anchor[i]`` from the true position
    ``position[i]``, adds the information ``w_i g_i g_i^T`` with
    ``g_i = [(p_i - a_h)^T / |p_i - a_h|, 0, e_h^T]`` and ``w_i = information[i]``
    (``1 / sigma^2`` for a Gaussian range; :func:`excess_fisher_information` for one with an
    excess). With the biases' block of ``P0`` zero the bound is that of known biases.

    Parameters
    ----------
    F, Q : ndarray (n + q, n + q)
        One step of the extended dynamics (the biases constant: ``F_bb = I``).
    P0 : ndarray (n + q, n + q)
        The prior covariance.
    steps : int
        Steps ``K``.
    beacons : ndarray (q, dim)
    step, anchor : ndarray (m,) of int
        Each range's step (``0 .. K-1``: read after the step, as a filter's estimate before
        its next update) and anchor.
    position : ndarray (m, dim)
        The true position at each range.
    information : ndarray (m,)
        Each range's Fisher information about its distance (1/m^2), non-negative.
    every : int
        The bound at steps ``0, every, ...`` (:func:`~quadobs.evaluation.ensemble.posterior_crb`).

    Returns
    -------
    ndarray (K // every + 1, n + q, n + q)
    """
    beacons = as_array("beacons", beacons, ndim=2)
    q, dim = beacons.shape
    n_e = np.shape(F)[0]
    step = np.asarray(step, dtype=int)
    anchor = np.asarray(anchor, dtype=int)
    m = step.shape[0]
    position = as_array("position", position, (m, dim))
    information = as_array("information", information, (m,))
    if anchor.shape != (m,) or np.any((anchor < 0) | (anchor >= q)):
        raise QuadobsError(f"anchor: expected {m} indices in 0 .. {q - 1}")
    if np.any((step < 0) | (step >= steps)) or np.any(information < 0):
        raise QuadobsError(f"step, information: expected steps in 0 .. {steps - 1}, w >= 0")
    d = position - beacons[anchor]
    r = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where((r > 0)[:, None], d / r[:, None], 0.0)
    G = np.zeros((n_e, m))
    G[:dim] = (u * np.sqrt(information)[:, None]).T
    G[n_e - q + anchor, np.arange(m)] = np.sqrt(information)
    order = np.argsort(step, kind="stable")
    first = np.searchsorted(step[order], np.arange(steps + 1))

    def factors(k: int) -> np.ndarray | None:
        a, b = first[k], first[k + 1]
        return G[:, order[a:b]] if b > a else None

    return posterior_crb(F, Q, P0, steps, factors, every=every)


def rmse_bound(bound: np.ndarray, dim: int, keep: np.ndarray) -> float:
    """The position RMSE that the bound ``bound (T, n, n)`` allows over the times ``keep``
    ``(T,)`` (booleans): ``sqrt(mean_t tr P_pp(t))``, the least mean of ``|p_hat - p|^2``
    over those times (m)."""
    tr = np.trace(np.asarray(bound)[:, :dim, :dim], axis1=1, axis2=2)
    return float(np.sqrt(np.mean(tr[np.asarray(keep, dtype=bool)])))
