"""Dilution of precision of two-way ranges and of TDOA over a room.

One measurement with unit noise at the position ``p`` has the Fisher information ``h h^T`` on
``p``, with ``h`` its gradient: ``u_i = (p - a_i) / |p - a_i|`` for a range to anchor ``i``,
``u_i - u_j`` for a TDOA of the pair ``(i, j)``. Averaged over the schedule (each anchor
equally often for ranges; each ordered pair equally often for TDoA3, whose consecutive
packets come from any two distinct anchors),

.. math::

    J_{\\rm range} = \\frac1m \\sum_i u_i u_i^\\top, \\qquad
    J_{\\rm tdoa} = \\frac{1}{m(m-1)} \\sum_{i \\ne j} (u_i - u_j)(u_i - u_j)^\\top
                 = \\frac{2}{m-1}\\Big(\\sum_i u_i u_i^\\top - m\\, \\bar u \\bar u^\\top\\Big),

``bar u`` the mean of the ``u_i``. The position dilution of precision per measurement is
``PDOP = sqrt(tr J^{-1})``: ``N`` measurements of standard deviation ``sigma`` at a still
point give a position error of about ``sigma PDOP / sqrt(N)`` (m, root of the summed
variances). A TDOA loses the direction ``bar u`` (a common range offset, the tag's clock in
a TDOA system, is not seen): inside the anchors' hull ``bar u`` is short and little is lost,
outside it the TDOA's PDOP grows fast.
"""

from __future__ import annotations

import numpy as np

from quadobs.errors import QuadobsError, as_array

__all__ = ["pdop", "range_information", "tdoa_information"]


def _directions(anchors: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unit vectors ``(..., m, dim)`` from each anchor to each point (zero at an anchor)."""
    d = points[..., None, :] - anchors
    r = np.linalg.norm(d, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > 0.0, d / r, 0.0)


def range_information(anchors, points) -> np.ndarray:
    """``J_range (..., dim, dim)`` at ``points (..., dim)`` (module docstring)."""
    anchors, points = _checked(anchors, points)
    u = _directions(anchors, points)
    return np.einsum("...ia,...ib->...ab", u, u) / anchors.shape[0]


def tdoa_information(anchors, points) -> np.ndarray:
    """``J_tdoa (..., dim, dim)`` at ``points (..., dim)``, all ordered pairs equally often."""
    anchors, points = _checked(anchors, points)
    m = anchors.shape[0]
    u = _directions(anchors, points)
    mean = u.mean(axis=-2)
    S = np.einsum("...ia,...ib->...ab", u, u) - m * mean[..., :, None] * mean[..., None, :]
    return 2.0 / (m - 1) * S


def pdop(information: np.ndarray) -> np.ndarray:
    """``sqrt(tr J^{-1})`` of information matrices ``(..., dim, dim)``; ``inf`` where singular."""
    J = np.asarray(information, dtype=float)
    w = np.linalg.eigvalsh(J)
    scale = np.maximum(np.abs(w).max(axis=-1, keepdims=True), np.finfo(float).tiny)
    bad = (w <= 1e-12 * scale).any(axis=-1)
    with np.errstate(divide="ignore"):
        out = np.sqrt(np.sum(1.0 / np.where(w > 0.0, w, np.inf), axis=-1))
    return np.where(bad, np.inf, out)


def _checked(anchors, points) -> tuple[np.ndarray, np.ndarray]:
    anchors = as_array("anchors", anchors)
    points = as_array("points", points)
    if anchors.ndim != 2 or anchors.shape[0] < 2 or points.shape[-1:] != anchors.shape[1:]:
        raise QuadobsError(
            f"anchors, points: expected (m >= 2, dim) and (..., dim), got {anchors.shape} and {points.shape}"
        )
    return anchors, points
