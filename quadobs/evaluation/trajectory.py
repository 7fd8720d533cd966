"""Trajectory errors as the field reports them: after a burn-in, split horizontal and vertical, divergence named.

For position estimates ``p_hat(t_i)`` against a truth ``p(t_i)`` (rows where the truth is
known), with the error ``e_i = p_hat(t_i) - p(t_i)`` and a burn-in ``t_b`` (seconds from
the first row), the figures are taken over ``I = {i : t_i - t_0 >= t_b}``:

.. math::

    \\mathrm{RMSE} = \\sqrt{\\tfrac{1}{|I|} \\sum_{i \\in I} \\lVert e_i \\rVert^2}, \\quad
    \\mathrm{RMSE}_h = \\sqrt{\\tfrac{1}{|I|} \\sum_{i \\in I} (e_{i,x}^2 + e_{i,y}^2)}, \\quad
    \\mathrm{RMSE}_v = \\sqrt{\\tfrac{1}{|I|} \\sum_{i \\in I} e_{i,z}^2},

so that ``RMSE^2 = RMSE_h^2 + RMSE_v^2`` in 3-D (the split of the absolute trajectory
error that UWB and visual-inertial papers report, e.g. with evo's ``evo_ape``). An
estimator whose estimate stops being finite, or whose error grows beyond
:data:`DIVERGED_ERROR`, has *diverged*: it is reported as such (the row, its time and the
reason) and gets no RMSE at all, never one over its finite rows only.

:func:`tum_text` writes a trajectory in the TUM format (``timestamp tx ty tz qx qy qz
qw``, one pose a line) that ``evo_ape tum`` reads.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.errors import QuadobsError

__all__ = ["DIVERGED_ERROR", "TrajectoryErrors", "tum_text"]

#: An error beyond this (m) is divergence: the largest length a scenario may hold.
DIVERGED_ERROR = 1e9


class TrajectoryErrors:
    """Position errors accumulated row block by row block (a stream), with a burn-in.

    Parameters
    ----------
    dimension : int
        2 or 3 (the vertical split in 3-D only).
    burn_in : float
        Seconds from the first row before the figures start (``>= 0``).
    """

    def __init__(self, dimension: int, burn_in: float = 0.0) -> None:
        if not (math.isfinite(burn_in) and burn_in >= 0.0):
            raise QuadobsError(
                f"--burn-in: expected a non-negative number of seconds, got {burn_in}"
            )
        self.dimension, self.burn_in = int(dimension), float(burn_in)
        self.t0 = math.nan
        self.sum_h = self.sum_v = 0.0
        self.count = 0
        self.max_error = 0.0
        self.final = math.nan
        self.diverged: dict | None = None

    def update(
        self, ks: np.ndarray, t: np.ndarray, estimate: np.ndarray, truth: np.ndarray
    ) -> None:
        """Add rows: steps ``ks (m,)``, times ``t (m,)`` (s), positions ``estimate``, ``truth`` ``(m, dim)``.

        Rows without a truth (NaN) are skipped; a non-finite estimate, or an error beyond
        :data:`DIVERGED_ERROR`, marks the estimator diverged at its first such row.
        """
        if not t.size or self.diverged is not None:
            return
        if math.isnan(self.t0):
            self.t0 = float(t[0])
        d = self.dimension
        est, tru = estimate[:, :d], truth[:, :d]
        known = np.all(np.isfinite(tru), axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            e = est - tru
            norm = np.sqrt(np.einsum("ij,ij->i", e, e))
        bad = ~np.all(np.isfinite(est), axis=1) | (known & ~(norm <= DIVERGED_ERROR))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            reason = (
                "non-finite estimate"
                if not np.all(np.isfinite(est[i]))
                else f"position error beyond {DIVERGED_ERROR:g} m"
            )
            self.diverged = {"step": int(ks[i]), "time": float(t[i]), "reason": reason}
            return
        if known.any():
            self.final = float(norm[known][-1])
        use = known & (t - self.t0 >= self.burn_in)
        if not use.any():
            return
        e = e[use]
        self.sum_h += float(np.sum(e[:, :2] ** 2))
        self.sum_v += float(np.sum(e[:, 2:] ** 2))
        self.count += int(use.sum())
        self.max_error = max(self.max_error, float(norm[use].max()))

    def figures(self) -> dict:
        """``rmse``, ``rmse_horizontal``, ``rmse_vertical`` (3-D; else None), ``max_error``,
        ``final_position_error`` (the last row with a truth), ``burn_in``, ``samples`` and
        ``diverged`` (None, or the step, time and reason); every error figure None when
        diverged or without rows."""
        out = {
            "rmse": None,
            "rmse_horizontal": None,
            "rmse_vertical": None,
            "max_error": None,
            "final_position_error": None,
            "burn_in": self.burn_in,
            "samples": self.count,
            "diverged": self.diverged,
        }
        if self.diverged is not None:
            out["samples"] = 0
            return out
        if math.isfinite(self.final):
            out["final_position_error"] = self.final
        if self.count:
            out["rmse"] = math.sqrt((self.sum_h + self.sum_v) / self.count)
            out["rmse_horizontal"] = math.sqrt(self.sum_h / self.count)
            if self.dimension == 3:
                out["rmse_vertical"] = math.sqrt(self.sum_v / self.count)
            out["max_error"] = self.max_error
        return out


def tum_text(t: np.ndarray, position: np.ndarray, quaternion: np.ndarray | None = None) -> str:
    """A trajectory in the TUM format: ``timestamp tx ty tz qx qy qz qw`` per line.

    Parameters
    ----------
    t : ndarray (m,)
        Times (s).
    position : ndarray (m, 2) or (m, 3)
        Positions (m); a planar one gets ``tz = 0``.
    quaternion : ndarray (m, 4), optional
        Orientations ``(qw, qx, qy, qz)``; default the identity (position-only estimates:
        compare with ``evo_ape``'s default, the translation part).
    """
    m = t.size
    p = np.zeros((m, 3))
    p[:, : position.shape[1]] = position
    q = np.tile([1.0, 0.0, 0.0, 0.0], (m, 1)) if quaternion is None else quaternion
    rows = np.column_stack([t, p, q[:, 1:], q[:, :1]])
    return "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in rows)
