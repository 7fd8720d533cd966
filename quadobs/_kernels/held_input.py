"""Compiled (Numba) finite exponential series of a nilpotent matrix, for the interface in time.

The observer's prediction over an interval of any length (``AugmentedObserver._propagate``)
takes two exponentials of small block matrices per interval through
:func:`quadobs.core.held_input.expm_exact`; its NumPy reference,
:func:`quadobs.core.held_input.expm_series_numpy`, spends most of its time in the interpreter
(a fresh array per product, ``any``, ``eye``). :func:`expm_series` performs the very same
operations in the same order, in place: each product is ``np.dot`` (the same BLAS ``dgemm`` as
NumPy's ``@``), then the division by ``i``, the test for an exactly zero term and the sum, entry
by entry, so that the two agree bit for bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["expm_series"]


@njit(cache=True, nogil=True, error_model="numpy")
def expm_series(M, out, term, work):
    """``out = sum_{i<k} M^i / i!`` when ``M^k = 0`` exactly for some ``k <= n``; returns whether it is.

    .. math::

        T_0 = I, \\qquad T_i = (T_{i-1} M) / i, \\qquad e^M = \\sum_{i < k} T_i
        \\quad \\text{when } T_k = 0 .

    Parameters
    ----------
    M : ndarray (n, n), C-contiguous
    out : ndarray (n, n), C-contiguous
        Receives the sum (meaningful only when the function returns ``True``).
    term, work : ndarray (n, n), C-contiguous
        Work arrays, distinct from ``M`` and ``out`` and from each other.

    Returns
    -------
    bool
        ``True`` when a term was exactly zero (``M`` nilpotent to rounding): ``out`` is ``e^M``;
        ``False`` after ``n`` non-zero terms: the caller takes another method.
    """
    n = M.shape[0]
    for a in range(n):  # element loops rather than slice assignments (see _kernels.gramian)
        for b in range(n):
            v = 1.0 if a == b else 0.0
            out[a, b] = v
            term[a, b] = v
    for i in range(1, n + 1):
        np.dot(term, M, work)
        nonzero = False
        for a in range(n):
            for b in range(n):
                x = work[a, b] / i
                term[a, b] = x
                if x != 0.0:
                    nonzero = True
        if not nonzero:
            return True
        for a in range(n):
            for b in range(n):
                out[a, b] = out[a, b] + term[a, b]
    return False
