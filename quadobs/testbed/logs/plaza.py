"""The CMU Plaza1 and Plaza2 range-only logs [DJUGASH2006], read from the files bundled with ``gtsam``.

A ground vehicle with wheel odometry ranges to 4 surveyed beacons (ids 0, 1, 5, 6) with
radio nodes; the logs ship inside the ``gtsam`` wheel (BSD), so they need no network:
``Plaza1_.mat`` (1933 s, 3529 ranges) and ``Plaza2_.mat`` (410 s, 1816 ranges), found
with ``gtsam.findExampleDataFile``. Install the ``data`` extra (``gtsam>=4.3``).

Conventions of the ``.mat`` files, handled here (tested in ``tests/testbed/test_replay.py``):

* ``TL (4, 3)``: ``id, x, y`` of the beacons, kept in file order (the output order);
* ``TD (M, 4)``: ``time, sensor id, beacon id, range``; the sensor id (always 2) is dropped.
  Plaza1's ``TD`` is not in time order (after rows 1988 and 2866 the clock jumps back by
  64 s and 50 s): the ranges are sorted by time (a stable sort);
* ``DR (K, 3)``: ``time t_i, distance d_i, heading change dtheta_i``, the odometry
  *increments* over ``[t_(i-1), t_i]`` with ``t_(-1)`` the first time of ``DRp``. They
  become the held inputs ``speed = d_i / (t_i - t_(i-1))``, ``yaw_rate = dtheta_i / (t_i -
  t_(i-1))`` from ``t_(i-1)`` (a last row at the final time, speed and yaw rate 0, closes
  the last interval); integrated at the mid-step heading
  ``theta_(i-1) + dtheta_i / 2`` they reproduce the dataset's own dead reckoning ``DRp`` of
  Plaza2 to 7 cm;
* ``DRp (K + 1, 4)``: the dataset's dead reckoning, ``time, x, y, heading``; its first
  heading is the odometry's origin ``heading0`` (the start pose the dataset provides);
* ``GT (K + 1, 4)``: the ground truth ``time, x, y, heading``. In Plaza2 its heading is
  offset by pi from the odometry's (``GT - DRp = -pi`` at the start): the truth's heading is
  rotated by pi and wrapped to ``(-pi, pi]``; the positions are untouched.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.testbed.logs.format import RangeLog, read_log

__all__ = ["BUILTIN_LOGS", "load_builtin", "open_log", "plaza_file"]

#: Built-in log names and their ``.mat`` files in gtsam's example data.
BUILTIN_LOGS = {"plaza1": "Plaza1_.mat", "plaza2": "Plaza2_.mat"}

#: Truth heading minus odometry heading, per log (rotated out by the loader).
_TRUTH_HEADING_OFFSET = {"plaza1": 0.0, "plaza2": -math.pi}


def plaza_file(name: str) -> Path:
    """The bundled ``.mat`` of a built-in log; a one-line error when gtsam is missing."""
    try:
        import gtsam
    except ImportError:
        raise QuadobsError(
            f"log {name!r}: the built-in logs are read from the gtsam package; install the data extra "
            "(pip install 'quadobs[data]')"
        ) from None
    try:
        return Path(gtsam.findExampleDataFile(BUILTIN_LOGS[name]))
    except (RuntimeError, IndexError) as exc:  # pragma: no cover - a gtsam build without its data
        raise QuadobsError(
            f"log {name!r}: {BUILTIN_LOGS[name]} is not in this gtsam installation ({exc})"
        ) from None


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to ``(-pi, pi]``."""
    return math.pi - np.mod(math.pi - a, 2.0 * math.pi)


def load_builtin(name: str) -> RangeLog:
    """``plaza1`` or ``plaza2`` as a :class:`RangeLog` (conventions in the module docstring)."""
    import scipy.io

    if name not in BUILTIN_LOGS:
        raise QuadobsError(
            f"log: unknown built-in log {name!r}; built-in: {', '.join(BUILTIN_LOGS)}"
        )
    m = scipy.io.loadmat(plaza_file(name))
    DR, DRp, GT, TD, TL = (np.asarray(m[k], dtype=float) for k in ("DR", "DRp", "GT", "TD", "TL"))
    t = np.concatenate([[DRp[0, 0]], DR[:, 0]])
    span = np.diff(t)
    inputs = np.column_stack([t[:-1], DR[:, 1] / span, DR[:, 2] / span])
    inputs = np.vstack([inputs, [t[-1], 0.0, 0.0]])
    truth = GT.copy()
    truth[:, 3] = _wrap(truth[:, 3] - _TRUTH_HEADING_OFFSET[name])
    ranges = TD[np.argsort(TD[:, 0], kind="stable")][:, [0, 2, 3]]
    return RangeLog(
        name, TL[:, 0].astype(np.int64), TL[:, 1:3], ranges, inputs, float(DRp[0, 3]), truth
    )


def open_log(source: str | Path) -> RangeLog:
    """A built-in name (``plaza1``, ``plaza2``) or a log folder (:func:`~quadobs.testbed.logs.format.read_log`)."""
    if isinstance(source, str) and source in BUILTIN_LOGS:
        return load_builtin(source)
    return read_log(source)
