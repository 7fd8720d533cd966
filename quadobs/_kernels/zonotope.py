"""Compiled (Numba) kernels of :class:`quadobs.estimators.zonotopic.ZonotopicEstimator`: one step of Algorithm 1.

Imported lazily (the estimator core imports with NumPy and SciPy alone). The arithmetic is
that of the NumPy reference (``backend="numpy"``), the set calculus of
:mod:`quadobs.sets.zonotope` written out on a buffer that is rewritten in place:

* prediction (eq. 2, section 4.1): ``mid[A] p (+) [mid[A] H, diag(rad[A] (|p| + |H| 1)), F] B``
  (:func:`~quadobs.sets.zonotope.interval_image`, zero box columns dropped);
* correction (eq. 3, Property 6): per output ``i``, ``p + lambda (y_i - c_i^T p)`` and
  ``[(I - lambda c_i^T) H, phi_i lambda]``, with a fixed gain or the segment-minimising
  gain ``lambda = H H^T c / (c^T H H^T c + phi^2)``;
* order reduction (Property 3, ``"combastel"``): the ``s - n`` longest generators kept in
  decreasing order of length (ties in their original order), the rest boxed by ``rs``.

Only the order of floating-point sums differs from NumPy's (which may pair or fuse them),
so the two agree to rounding. Nothing is allocated per call but the sort's index buffer.

Calling convention (operands packed, as in :mod:`quadobs._kernels.observer`):

``ic`` (int64)
    ``[n, n_w, n_y, s, cap, mode, uncertain]``: dimension, columns of ``F``, outputs, order
    bound, column capacity of the buffer, gain mode (0 fixed, 1 segment, 2 given per call)
    and whether ``[A]`` has a non-zero radius.
``fc`` (float64)
    ``mid[A] (n, n)``, ``rad[A] (n, n)``, ``F (n, n_w)``, ``C (n_y, n)``, ``phi (n_y,)`` and
    the fixed gains ``(n_y, n)``, each row-major, one after the other.
``S`` (float64)
    ``[m, p (n), H (n, cap), work, out]``: the number of generators, the centre, the
    generators (row-major, the first ``m`` columns in use), ``2 n cap + n`` floats of work
    and ``out = [p, H (n, m)]`` written at the end of a step (one contiguous block, so that
    the caller takes the set with one copy; :func:`state_size`, :func:`out_offset`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

__all__ = [
    "out_offset",
    "state_size",
    "zonotope_predict",
    "zonotope_reduce",
    "zonotope_step",
    "zonotope_strip",
]

_OPTS: dict[str, Any] = dict(cache=True, nogil=True, error_model="numpy")


def state_size(n: int, cap: int) -> int:
    """Length of ``S`` for dimension ``n`` and a capacity of ``cap`` generators."""
    return out_offset(n, cap) + n + n * cap


def out_offset(n: int, cap: int) -> int:
    """Offset in ``S`` of the block ``[p, H (n, m)]`` written at the end of a step."""
    return 1 + n + n * cap + 2 * n * cap + n


@njit(**_OPTS)
def _out(S, ic):
    """Copy ``p`` and the ``m`` generators in use, contiguous, to the end of ``S``; returns ``m``."""
    n, cap = ic[0], ic[4]
    m = int(S[0])
    o = 1 + n + 3 * n * cap + n
    for r in range(n):
        S[o + r] = S[1 + r]
    o += n
    for r in range(n):
        for j in range(m):
            S[o + r * m + j] = S[1 + n + r * cap + j]
    return m


@njit(**_OPTS)
def _predict(S, fc, ic):
    n, nw, cap, unc = ic[0], ic[1], ic[4], ic[6]
    m = int(S[0])
    oh = 1 + n
    ow = oh + n * cap
    o_rad = n * n
    o_F = 2 * n * n
    nbox = 0
    if unc:
        # box = rad[A] (|p| + |H| 1), from the set before the map
        for k in range(n):
            acc = 0.0
            for j in range(m):
                acc += abs(S[oh + k * cap + j])
            S[ow + k] = abs(S[1 + k]) + acc
        for i in range(n):
            b = 0.0
            for k in range(n):
                b += fc[o_rad + i * n + k] * S[ow + k]
            S[ow + n + i] = b
            if b > 0.0:
                nbox += 1
    # mid[A] H, column by column, and mid[A] p
    t = ow + 2 * n
    for j in range(m):
        for i in range(n):
            acc = 0.0
            for k in range(n):
                acc += fc[i * n + k] * S[oh + k * cap + j]
            S[t + i] = acc
        for i in range(n):
            S[oh + i * cap + j] = S[t + i]
    for i in range(n):
        acc = 0.0
        for k in range(n):
            acc += fc[i * n + k] * S[1 + k]
        S[t + i] = acc
    for i in range(n):
        S[1 + i] = S[t + i]
    if nbox > 0:
        for i in range(n):
            b = S[ow + n + i]
            if b > 0.0:
                for r in range(n):
                    S[oh + r * cap + m] = 0.0
                S[oh + i * cap + m] = b
                m += 1
    for j in range(nw):
        for r in range(n):
            S[oh + r * cap + m] = fc[o_F + r * nw + j]
        m += 1
    S[0] = m


@njit(**_OPTS)
def _strip(S, fc, ic, i, y, lam, lo):
    """Property 6 with output ``i``, measurement ``y`` and the gain ``lam[lo : lo + n]``."""
    n, nw, cap = ic[0], ic[1], ic[4]
    m = int(S[0])
    oh = 1 + n
    o_C = 2 * n * n + n * nw + i * n
    phi = fc[2 * n * n + n * nw + ic[2] * n + i]
    cp = 0.0
    for k in range(n):
        cp += fc[o_C + k] * S[1 + k]
    e = y - cp
    for r in range(n):
        S[1 + r] += lam[lo + r] * e
    for j in range(m):
        ch = 0.0
        for k in range(n):
            ch += fc[o_C + k] * S[oh + k * cap + j]
        for r in range(n):
            S[oh + r * cap + j] -= lam[lo + r] * ch
    for r in range(n):
        S[oh + r * cap + m] = phi * lam[lo + r]
    S[0] = m + 1


@njit(**_OPTS)
def _segment_gain(S, fc, ic, i, out, lo):
    """``lambda = H H^T c / (c^T H H^T c + phi^2)`` into ``out[lo : lo + n]`` (0 when the denominator is not positive)."""
    n, nw, cap = ic[0], ic[1], ic[4]
    m = int(S[0])
    oh = 1 + n
    o_C = 2 * n * n + n * nw + i * n
    phi = fc[2 * n * n + n * nw + ic[2] * n + i]
    ow = oh + n * cap  # H^T c (m floats of work)
    for j in range(m):
        acc = 0.0
        for k in range(n):
            acc += fc[o_C + k] * S[oh + k * cap + j]
        S[ow + j] = acc
    den = 0.0
    for r in range(n):
        acc = 0.0
        for j in range(m):
            acc += S[oh + r * cap + j] * S[ow + j]
        out[lo + r] = acc
        den += fc[o_C + r] * acc
    den += phi * phi
    if den <= 0.0:
        for r in range(n):
            out[lo + r] = 0.0
    else:
        for r in range(n):
            out[lo + r] = out[lo + r] / den


@njit(**_OPTS)
def _reduce(S, ic):
    """Property 3 (``"combastel"``) when more than ``s`` generators are in use."""
    n, s, cap = ic[0], ic[3], ic[4]
    m = int(S[0])
    if m <= s:
        return
    oh = 1 + n
    ow = oh + n * cap
    onorm = ow + n * cap  # squared lengths (cap floats)
    for j in range(m):
        acc = 0.0
        for r in range(n):
            h = S[oh + r * cap + j]
            acc += h * h
        S[onorm + j] = acc
    # stable sort by decreasing length (insertion sort: m is small)
    order = np.empty(m, dtype=np.int64)
    for j in range(m):
        v = S[onorm + j]
        a = j
        while a > 0 and S[onorm + order[a - 1]] < v:
            order[a] = order[a - 1]
            a -= 1
        order[a] = j
    keep = s - n
    for r in range(n):
        acc = 0.0
        for t in range(keep, m):
            acc += abs(S[oh + r * cap + order[t]])
        S[onorm + cap + r] = acc
    for t in range(keep):
        for r in range(n):
            S[ow + r * cap + t] = S[oh + r * cap + order[t]]
    for r in range(n):
        for t in range(keep):
            S[oh + r * cap + t] = S[ow + r * cap + t]
        for t in range(n):
            S[oh + r * cap + keep + t] = 0.0
        S[oh + r * cap + keep + r] = S[onorm + cap + r]
    S[0] = s


@njit(**_OPTS)
def zonotope_predict(S, fc, ic):
    """Step 1 of Algorithm 1 on ``S``: ``[A] X (+) F B`` (no reduction)."""
    _predict(S, fc, ic)


@njit(**_OPTS)
def zonotope_strip(S, fc, ic, i, y, lam):
    """Property 6 on ``S`` with output ``i``, its measurement ``y`` and the gain ``lam (n,)``."""
    _strip(S, fc, ic, i, y, lam, 0)


@njit(**_OPTS)
def zonotope_reduce(S, ic):
    """Property 3 (``"combastel"``) on ``S`` when it holds more than ``s`` generators, then ``out``; returns ``m``."""
    _reduce(S, ic)
    return _out(S, ic)


@njit(**_OPTS)
def zonotope_step(y, S, fc, ic):
    """Predict, correct with ``y (n_y,)`` (NaN: skipped) with fixed (mode 0) or segment (mode 1) gains, reduce.

    Returns the number of generators ``m`` (``out`` written), or -1 without touching ``S``
    when ``y`` holds an infinity.
    """
    n, ny, mode = ic[0], ic[2], ic[5]
    for i in range(ny):
        if math.isinf(y[i]):
            return -1
    _predict(S, fc, ic)
    o_gain = 2 * n * n + n * ic[1] + ny * n + ny
    ol = 1 + n + 3 * n * ic[4]  # the segment gain (the last n floats of work)
    for i in range(ny):
        if math.isnan(y[i]):
            continue
        if mode == 0:
            _strip(S, fc, ic, i, y[i], fc, o_gain + i * n)
        else:
            _segment_gain(S, fc, ic, i, S, ol)
            _strip(S, fc, ic, i, y[i], S, ol)
    _reduce(S, ic)
    return _out(S, ic)
