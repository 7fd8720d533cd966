"""The augmented observer's noise and prior derived from stated figures, one rule for every source.

The observer of [IFAC2021, Thm. 3] runs on the immersion ``z = (xi, x)`` with
``xi_i = x^T L_i x / 2`` [ACC2024, Alg. 1]. Its tuning follows from what a user states about
the sensors and the geometry, not from a hand-set ``V`` and ``W``:

* **process noise in time.** A white noise ``w`` of intensity ``V_x`` on ``x'`` drives
  ``xi_i' = ... + x^T L_i w``, so the augmented state's noise is

  .. math:: V(z) = J V_x J^\\top, \\qquad J = \\begin{bmatrix} x^\\top L_1 \\\\ \\vdots \\\\
            x^\\top L_k \\\\ I_n \\end{bmatrix}

  at the estimate (:func:`state_noise_map`), with no constant of any scale: used where the
  observer predicts over intervals of its own (:meth:`~quadobs.estimators.augmented.AugmentedObserver.predict`);
* **process noise on a grid.** The compiled step keeps a constant ``V``: the ``x`` block is
  ``V_x`` and each auxiliary state gets ``r^2 \\lambda`` with ``\\lambda`` the largest entry of
  ``diag V_x`` and ``r = max_h |a_h|`` (:func:`grid_process_noise`): ``|p| <= r`` for a
  vehicle inside the anchors' hull (the norm being convex), so ``r^2 \\lambda`` bounds the
  variance ``p^T V_v p`` that the noise puts on ``|p|^2 / 2`` and ``p^T v``;
* **output noise.** A range ``rho`` of standard deviation ``sigma`` gives the output
  ``y = rho^2 / 2 - |a|^2 / 2`` the variance ``rho^2 sigma^2 + sigma^4 / 2``
  (:meth:`~quadobs.core.measurements.RangeModel.quadratic_output`, each range at its own
  value in time); on a grid the observer's discrete ``R = (rho_typ sigma)^2`` at a typical
  range ``rho_typ`` (:func:`grid_output_variance`), that is ``W = R T`` for outputs sampled
  every ``T``;
* **prior.** ``x ~ N(x0, P0 I)`` on the position: the covariance of ``lift(x)``
  (:func:`lifted_covariance`), ``P0`` from the guess's own uncertainty (:func:`guess_variance`).

:func:`derived_observer` builds the observer from these; the replay of a log
(:func:`quadobs.testbed.logs.estimators.build_augmented`) and a simulated scenario with
``[observer] tuning = "derived"`` (:func:`quadobs.testbed.factories.augmented_observer`) both
call it, each with the figures it has (a log's measured median range, a scenario's anchors).
"""

from __future__ import annotations

import numpy as np

from quadobs.core.immersion import Immersion
from quadobs.core.immersion import lifted_covariance as gaussian_lift_covariance
from quadobs.errors import QuadobsError
from quadobs.estimators.augmented import AugmentedObserver
from quadobs.estimators.augmented_in_time import StateNoise

__all__ = [
    "anchor_scale",
    "derived_observer",
    "grid_output_variance",
    "grid_process_noise",
    "guess_variance",
    "lifted_covariance",
    "state_noise_map",
]


def anchor_scale(beacons: np.ndarray) -> float:
    """The geometry's typical range (m): the median distance of the anchors from their centroid,
    the range to each anchor of a vehicle at the centre of the room they span."""
    b = np.asarray(beacons, dtype=float)
    return float(np.median(np.linalg.norm(b - b.mean(axis=0), axis=1)))


def guess_variance(
    beacons: np.ndarray, range_sigma: float, *, offset: float | None = None, x0=None
) -> float:
    """The variance ``P0`` (m^2 per axis) of an initial position guess.

    ``offset``: the guess is the truth moved by about that distance (m), or its error has
    that standard deviation: ``max(offset, sigma)^2``, a guess at the truth itself being as
    uncertain as one range (``range_sigma``). Otherwise the vehicle is taken to be within
    the anchors' hull, every point of which lies within the extent ``e = max_h |a_h - c|`` of
    their centroid ``c`` (the distance being convex): a guess ``x0`` (default ``c``) is then
    within ``|p0 - c| + e`` of it, and ``P0`` is that squared.
    """
    if offset is not None:
        return float(max(float(offset), range_sigma) ** 2)
    b = np.asarray(beacons, dtype=float)
    c = b.mean(axis=0)
    extent = float(np.max(np.linalg.norm(b - c, axis=1)))
    d = 0.0 if x0 is None else float(np.linalg.norm(np.asarray(x0, float)[: c.size] - c))
    return max(d + extent, range_sigma) ** 2


def grid_process_noise(im: Immersion, Vx: np.ndarray, r: float) -> np.ndarray:
    """The constant ``V (N, N)`` of a grid's compiled step: ``diag(r^2 lambda I_k, V_x)`` with
    ``lambda = max diag V_x`` and ``r`` the largest anchor distance from the origin (module
    docstring)."""
    k = im.n_aux
    V = np.zeros((im.dim, im.dim))
    V[k:, k:] = Vx
    V[:k, :k] = r**2 * float(np.max(np.diag(Vx))) * np.eye(k)
    return V


def state_noise_map(im: Immersion, Vx: np.ndarray, extra: np.ndarray | None = None):
    """``z -> V(z) = J V_x J^T`` with ``J = [x^T L_1; ...; x^T L_k; I_n]`` at ``z``'s ``x``
    (module docstring). ``extra (n, n)``, read at each call, is added to ``V_x`` (an input's
    error that its owner updates in place: :class:`~quadobs.estimators.heading_ekf.HeadingCascade`)."""
    return StateNoise(im, Vx, extra)  # a callable whose operands the compiled prediction reads


def grid_output_variance(range_sigma: float, typical_range: float) -> float:
    """The discrete variance ``R = (rho_typ sigma)^2`` of a range's output ``rho^2 / 2`` on a
    grid (module docstring)."""
    return (typical_range * range_sigma) ** 2


def lifted_covariance(im: Immersion, x0: np.ndarray, P0: float, dim: int) -> np.ndarray:
    """The initial covariance of ``lift(x)`` for ``x ~ N(x0, P0 I_n)``: ``P0`` on every entry
    of ``x``, the position's first ``dim`` entries and any others (a velocity) alike.

    Exact Gaussian moments (:func:`quadobs.core.immersion.lifted_covariance`): with
    ``xi_i = x^T L_i x / 2``, ``x = x0 + e``,

    .. math:: \\operatorname{cov}(\\xi_i, \\xi_j) = P_0 x_0^\\top L_i L_j x_0
              + \\tfrac{1}{2} P_0^2 \\operatorname{tr}(L_i L_j), \\qquad
              \\operatorname{cov}(\\xi_i, x) = P_0 L_i x_0,

    the first from the part ``x0^T L_i e`` linear in the error, the second from ``e^T L_i e / 2``
    (Isserlis: ``cov(e^T A e, e^T B e) = 2 tr(A P B P)``). For the state of a position alone,
    ``xi = |p|^2 / 2`` (``L = I_d``): ``var xi = P0 |p0|^2 + d P0^2 / 2``, that is
    ``var |p|^2 = 4 P0 |p0|^2 + 2 d P0^2``; ``P0^2`` in the plane, ``1.5 P0^2`` in space.
    """
    if not 0 < dim <= im.system.n:
        raise QuadobsError(f"dim: expected 1 to {im.system.n} position entries, got {dim}")
    x0 = np.asarray(x0, dtype=float)[: im.system.n]
    return gaussian_lift_covariance(im.aux_forms, x0, P0 * np.eye(im.system.n))


def derived_observer(
    im: Immersion,
    dt: float,
    *,
    Vx: np.ndarray,
    beacons: np.ndarray,
    range_sigma: float,
    typical_range: float,
    x0: np.ndarray,
    P0: float,
    sample_period=None,
    gate: float | None = None,
) -> AugmentedObserver:
    """The observer of [IFAC2021, Thm. 3] on ``im`` tuned by the rule of this module.

    Parameters
    ----------
    im : Immersion
        Of a system whose first outputs are the ranges to ``beacons``.
    dt : float
        The grid step (s).
    Vx : ndarray (n, n)
        The white noise's intensity on ``x'`` (an acceleration's on the velocity, an
        odometry's on the position).
    beacons : ndarray (q, dim)
    range_sigma, typical_range : float
        A range's standard deviation and the typical range (m) of the grid's ``R``.
    x0 : ndarray (n,)
        The initial guess; ``P0`` the variance of its position per axis (m^2).
    sample_period : float or ndarray (q,), optional
        The outputs' sampling period ``T`` on the grid (default ``dt``): ``W = R T``.
    gate : float, optional
        The NIS gate.

    Returns
    -------
    AugmentedObserver
        With the grid's constant ``V`` and ``W`` (:func:`grid_process_noise`,
        :func:`grid_output_variance`) and, for :meth:`~AugmentedObserver.predict` over
        intervals of its own, ``noise_of`` = :func:`state_noise_map`.
    """
    dim = np.asarray(beacons).shape[1]
    r = float(np.max(np.linalg.norm(beacons, axis=1)))
    V = grid_process_noise(im, Vx, r)
    P = lifted_covariance(im, x0, P0, dim)
    R = grid_output_variance(range_sigma, typical_range)
    T = dt if sample_period is None else np.asarray(sample_period, dtype=float)
    return AugmentedObserver(
        im,
        dt,
        V=V,
        W=R * T,
        P0=P,
        z0=im.lift(x0),
        gate=gate,
        noise_of=state_noise_map(im, Vx),
        sample_period=sample_period,
    )
