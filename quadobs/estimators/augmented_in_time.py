"""The augmented observer's interface in time, compiled: operands and work arrays allocated once.

:class:`~quadobs.estimators.augmented.AugmentedObserver` fed one measurement at its own time
predicts over each interval and corrects by one scalar output (:meth:`~quadobs.estimators.base.Estimator.predict`,
:meth:`~quadobs.estimators.base.Estimator.correct`). :class:`InTimeKernels` holds what the compiled
kernels of :mod:`quadobs._kernels.in_time` need for that: the structure of ``A(u)``, the input
map and the work arrays, so that a range costs no allocation and the correction ``O(N^2)``.
Its NumPy reference is the observer's own (``backend="numpy"``):
:func:`quadobs.core.held_input.held_input_interval` and
:func:`~quadobs.core.held_input.van_loan_interval` for the prediction, the outer products of
:meth:`~quadobs.estimators.augmented.AugmentedObserver._correct_scalar` for the correction.

:class:`StateNoise` is the state-dependent process noise ``V(z) = J V_x J^T`` of
:func:`quadobs.estimators.augmented_tuning.state_noise_map`: a callable as before, whose
operands the compiled prediction reads to form ``V(z)`` in place.
"""

from __future__ import annotations

import numpy as np

from quadobs.core.immersion import Immersion

__all__ = ["InTimeKernels", "StateNoise", "structurally_nilpotent"]


class StateNoise:
    """``z -> V(z) = J (V_x + E) J^T`` (symmetrised), ``J = [x^T L_1; ...; x^T L_k; I_n]`` at ``z``'s ``x``.

    The noise ``w`` of intensity ``V_x`` on ``x'`` mapped into the augmented state
    (:mod:`quadobs.estimators.augmented_tuning`).

    Parameters
    ----------
    im : Immersion
        Its auxiliary forms ``L_i`` (``xi_i = x^T L_i x / 2``, symmetric).
    Vx : ndarray (n, n)
    extra : ndarray (n, n), optional
        ``E``, read at each call: an input's error that its owner updates in place.
    """

    def __init__(self, im: Immersion, Vx: np.ndarray, extra: np.ndarray | None = None) -> None:
        self.k, self.n = im.n_aux, im.system.n
        self.L = np.array(im.aux_forms, dtype=float).reshape(self.k, self.n, self.n)
        self.Vx = np.array(Vx, dtype=float)
        self.extra = extra
        self._J = np.zeros((im.dim, self.n))
        self._J[self.k :] = np.eye(self.n)
        f64 = np.dtype(np.float64)
        #: Whether the compiled prediction can form ``V(z)`` itself (``E`` a float64 C array).
        self.compiled = extra is None or (
            isinstance(extra, np.ndarray) and extra.dtype == f64 and extra.flags.c_contiguous
        )

    def __call__(self, z: np.ndarray) -> np.ndarray:
        J, k = self._J, self.k
        J[:k] = self.L @ z[k:]  # rows x^T L_i (L_i symmetric)
        V = J @ (self.Vx if self.extra is None else self.Vx + self.extra) @ J.T
        return 0.5 * (V + V.T)


def structurally_nilpotent(pattern: np.ndarray) -> bool:
    """Whether every matrix with the nonzero ``pattern (N, N)`` is nilpotent: the graph with an
    edge ``i -> j`` per structural nonzero ``(i, j)`` has no cycle (its ``N``-th boolean power
    is empty)."""
    reach = pattern.astype(bool)
    power = reach.copy()
    for _ in range(pattern.shape[0]):
        if not power.any():
            return True
        power = (power.astype(np.int64) @ reach.astype(np.int64)) > 0
    return not power.any()


_KERNELS = None


def _kernels():
    """:mod:`quadobs._kernels.in_time`, imported at the first use (it imports Numba)."""
    global _KERNELS
    if _KERNELS is None:
        import quadobs._kernels.in_time as module

        _KERNELS = module
    return _KERNELS


def _f64(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


class InTimeKernels:
    """The operands and work arrays of the compiled prediction over an interval and correction
    by one scalar output (:mod:`quadobs._kernels.in_time`) for one observer.

    Build it with :meth:`of`, which returns ``None`` where the kernels do not apply: a forgetting
    factor ``theta > 0`` (Van Loan's block of ``A + theta I / 2`` is not nilpotent) or an ``A(u)``
    whose structure allows a cycle (a rotation, say); the observer then takes its NumPy path.

    Parameters
    ----------
    im : Immersion
    V : ndarray (N, N)
        The constant process-noise intensity (used where the observer has no ``noise_of``).
    """

    def __init__(self, im: Immersion, V: np.ndarray) -> None:
        N, p = im.dim, im.system.p
        # private writable copies: the kernels see one array type whatever the immersion holds
        self.A0 = np.array(im.state_matrix_constant, dtype=float)
        self.Au = np.array(im.state_matrix_input, dtype=float).reshape(p, N, N)
        self.Bz = np.array(im.input_matrix, dtype=float).reshape(N, p)
        self.C = np.array(im.output_matrix, dtype=float)
        rows, cols = np.nonzero(self.pattern(im))
        self.ptr = np.searchsorted(rows, np.arange(N + 1)).astype(np.int64)
        self.col = cols.astype(np.int64)
        self.V = np.array(V, dtype=float)
        self._noise = np.zeros((N, N))  # V(z) of the interval
        self._W = np.zeros((8, N, N))
        self._w = np.zeros((3, N))
        self._Pc = np.zeros((2, N))  # P c and c^T W of the correction
        self._J = np.zeros((2, N, im.system.n))
        self._zero_extra = np.zeros((im.system.n, im.system.n))

    @staticmethod
    def pattern(im: Immersion) -> np.ndarray:
        """The structural nonzeros of ``A(u)`` over all ``u``: those of ``A_0`` and of each ``A_j``."""
        Au = np.asarray(im.state_matrix_input).reshape(-1, im.dim, im.dim)
        return (np.asarray(im.state_matrix_constant) != 0) | np.any(Au != 0, axis=0)

    @classmethod
    def of(cls, im: Immersion, V: np.ndarray, theta: float) -> InTimeKernels | None:
        """The kernels' operands for ``im``, or ``None`` where they do not apply (class docstring)."""
        if theta != 0.0 or not structurally_nilpotent(cls.pattern(im)):
            return None
        return cls(im, V)

    def noise(self, z: np.ndarray, noise_of) -> np.ndarray:
        """The process noise of an interval starting at ``z``: ``noise_of(z)``, formed in place
        for a :class:`StateNoise`; the constant ``V`` without ``noise_of``."""
        if noise_of is None:
            return self.V
        if type(noise_of) is StateNoise and noise_of.compiled:
            extra = self._zero_extra if noise_of.extra is None else noise_of.extra
            J = self._J
            _kernels().state_noise(z, noise_of.L, noise_of.Vx, extra, self._noise, J[0], J[1])
            return self._noise
        return _f64(noise_of(z))

    def predict(self, z, P, u: np.ndarray, dt: float, noise_of, stats: np.ndarray) -> bool:
        """:func:`quadobs._kernels.in_time.interval_predict` of ``z`` and ``P`` in place over
        ``dt`` with ``u`` held (``stats[3]``: the trace of ``P``); ``False`` (nothing changed)
        where its series did not end."""
        V = self.noise(z, noise_of)
        return bool(
            _kernels().interval_predict(
                z,
                P,
                u,
                dt,
                self.A0,
                self.Au,
                self.Bz,
                self.ptr,
                self.col,
                V,
                self._W,
                self._w,
                stats,
            )
        )

    def correct(self, z, P, h: int, yh: float, r: float, gate: float | None, stats) -> None:
        """:func:`quadobs._kernels.in_time.scalar_correct` of ``z`` and ``P`` by ``y_h = C[h] z``
        (the immersion's output matrix) of variance ``r`` (``stats = [nis, corrections,
        rejected, trace P]`` updated)."""
        g = np.inf if gate is None else float(gate)
        _kernels().scalar_correct(z, P, self.C, int(h), float(yh), float(r), g, stats, self._Pc)
