"""Theorem 3's observer for a batch of systems stepped together.

:class:`BatchAugmentedObserver` holds ``B`` copies of one
:class:`~quadobs.estimators.augmented.AugmentedObserver` (same immersion, discretisation, noise
intensities and gate) with their own estimates ``Z (B, N)`` and covariances ``P (B, N, N)``,
and advances them all with one call: the compiled kernel
(:func:`quadobs._kernels.observer.augmented_step_batch`) runs the exact arithmetic of the single
observer on each member in turn, sharing the model and the work buffers, so member ``b``
evolves exactly as a single observer fed ``U[b]``, ``Y[b]`` would (the same operations in
the same order). Without Numba each member is advanced by the NumPy reference.

A batch is not an :class:`~quadobs.estimators.base.Estimator` (its operands and estimates
carry a leading batch axis, ``U (B, p)``, ``x_hat (B, n)``); its estimates follow the same
conventions (:attr:`BatchAugmentedObserver.x_hat` is a copy, never a live view).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError, as_array
from quadobs.estimators.augmented import (
    AugmentedObserver,
    KernelModel,
    _float64_operands,
    resolve_backend,
)

__all__ = ["BatchAugmentedObserver"]


class BatchAugmentedObserver:
    """``B`` copies of an :class:`~quadobs.estimators.augmented.AugmentedObserver`, stepped together.

    Parameters
    ----------
    observer : AugmentedObserver
        The template: its model, settings, and current estimate and covariance.
    batch : int
        Number of members ``B``.
    x0 : array_like (B, n) or (n,), optional
        Initial estimates of ``x`` (the augmented estimates start at their lifts);
        default: the template's ``z`` for every member.
    z0 : array_like (B, N) or (N,), optional
        Initial augmented estimates (override ``x0``).
    backend : {"auto", "numba", "numpy"}
        As for :class:`~quadobs.estimators.augmented.AugmentedObserver`.
    threads : int
        With the compiled kernel, split the batch over this many threads (the kernel
        releases the GIL); 0 or 1: the calling thread.

    Attributes
    ----------
    Z : ndarray (B, N)
        Augmented estimates, updated in place (assign into it: ``Z[...] = ...``).
    P : ndarray (B, N, N)
        Their covariances, updated in place.
    """

    def __init__(
        self,
        observer: AugmentedObserver,
        batch: int,
        *,
        x0=None,
        z0=None,
        backend: str = "auto",
        threads: int = 0,
    ) -> None:
        if not isinstance(observer, AugmentedObserver):
            raise QuadobsError(
                f"observer: expected an AugmentedObserver, got {type(observer).__name__}"
            )
        if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1:
            raise QuadobsError(f"batch: expected a positive integer, got {batch!r}")
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
            raise QuadobsError(f"threads: expected a non-negative integer, got {threads!r}")
        B = int(batch)
        im = observer.immersion
        N, n, p, q = im.dim, im.system.n, im.system.p, im.system.q
        self.immersion, self.batch = im, B
        self._k = im.n_aux
        if z0 is not None:
            Z = np.broadcast_to(_rows("z0", z0, B, N), (B, N))
        elif x0 is not None:
            Z = im.lift(np.broadcast_to(_rows("x0", x0, B, n), (B, n)))
        else:
            Z = np.broadcast_to(observer.z, (B, N))
        # One row per member, [z | P | stats], the layout of the compiled kernel;
        # Z, P and the stats are views of it.
        self._SB = np.zeros((B, N + N * N + 4))
        self._views()
        self.Z[...] = Z
        self.P[...] = observer.P
        self._stats[:, 0] = np.nan
        self._stats[:, 3] = np.trace(observer.P)
        self._ushape, self._yshape = (B, p), (B, q)
        self.backend = resolve_backend(backend)
        self._kernel = None
        if self.backend == "numba":
            import quadobs._kernels.observer as _kernels

            km = KernelModel(observer.model, observer._C, observer.R, observer.gate)
            self._kops = (self._SB, km.work(), km.fc, km.ic)
            self._kernel = _kernels.augmented_step_batch
            self._batch_refused = _kernels.batch_refused
            self._threads = min(int(threads), B)
            self._pool: Any = None  # a ThreadPoolExecutor once a step runs on threads
            if self._threads > 1:  # contiguous slices of the batch, each with its own work buffer
                edges = np.linspace(0, B, self._threads + 1).astype(int)
                self._slices = [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
                # each thread its own work buffers: W, and ic (its tail holds integer work)
                self._works = [(km.work(), km.ic.copy()) for _ in self._slices]
                self._batch_refused(
                    np.zeros((1, p)), np.zeros((1, q)), km.ic
                )  # load (or compile) it now
            # load (or compile) the kernel now, on scratch copies
            self._kernel(
                np.zeros((1, p)),
                np.full((1, q), np.nan),
                self._SB[:1].copy(),
                km.work(),
                km.fc,
                km.ic,
            )
        else:
            self._ref = copy.copy(observer)  # the NumPy reference path on the template's model
            self._ref._kernel = None
            self._ref._Phi = observer._Phi.copy()

    def close(self) -> None:
        """Stop the worker threads (``threads > 1``; started again by the next :meth:`step`)."""
        if getattr(self, "_pool", None) is not None:
            self._pool.shutdown()
            self._pool = None

    def _views(self) -> None:
        B, N = self.batch, self.immersion.dim
        SB = self._SB
        self.Z = SB[:, :N]
        self.P = SB[:, N : N + N * N].reshape(B, N, N)
        self._stats = SB[:, N + N * N :]  # nis, corrections, rejected, trace(P)
        if getattr(self, "_kops", None) is not None:
            self._kops = (SB,) + self._kops[1:]

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        for key in ("Z", "P", "_stats", "_pool"):  # views of _SB and threads: rebuilt on unpickling
            state.pop(key, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._pool = None
        self._views()

    # -- estimates -------------------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        """``(B, n)`` estimates of ``x`` (a copy of the last ``n`` columns of :attr:`Z`)."""
        return self.Z[:, self._k :].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        """``(B, n, n)`` covariances of :attr:`x_hat` (a copy of blocks of :attr:`P`)."""
        k = self._k
        return self.P[:, k:, k:].copy()

    @property
    def nis(self) -> np.ndarray:
        """``(B,)`` NIS of each member's last correction (NaN where nothing was present)."""
        return self._stats[:, 0].copy()

    @property
    def corrections(self) -> np.ndarray:
        return self._stats[:, 1].astype(np.int64)

    @property
    def rejected(self) -> np.ndarray:
        return self._stats[:, 2].astype(np.int64)

    @property
    def covariance_trace(self) -> np.ndarray:
        """``(B,)`` traces of the augmented covariances."""
        return self._stats[:, 3].copy()

    # -- stepping --------------------------------------------------------------------

    def step(self, U: np.ndarray, Y: np.ndarray) -> None:
        """Correct member ``b`` with ``Y[b]`` (``(B, q)``, NaN = missing), then predict it with ``U[b]`` (``(B, p)``) held.

        A non-finite value in ``U``, an infinite one in ``Y`` or a wrong shape (an empty ``Y``
        included) raises :class:`QuadobsError` naming the member, and leaves every member
        unchanged. The compiled kernel checks the values itself before it changes anything
        (:func:`quadobs._kernels.observer.batch_refused`), so the good path costs nothing more.
        """
        fast = (
            _float64_operands(U, Y, self._ushape, self._yshape)
            and U.flags.c_contiguous
            and Y.flags.c_contiguous
        )
        if not fast:
            _checked = AugmentedObserver._checked
            U, Y = _checked("U", U, self._ushape), _checked("Y", Y, self._yshape)
        if self._kernel is None:
            self._step_reference(U, Y)
        elif self._threads <= 1:
            if self._kernel(U, Y, *self._kops) < 0:  # nothing changed
                self._refuse(U, Y)
        else:
            self._step_threads(U, Y)

    def _refuse(self, U: np.ndarray, Y: np.ndarray) -> None:
        """Raise the :class:`QuadobsError` naming the first member whose ``U[b]`` or ``Y[b]`` is refused."""
        bad = ~np.isfinite(U).all(axis=1) | np.isinf(Y).any(axis=1)
        b = int(np.argmax(bad))
        as_array(f"U[{b}]", U[b], self._ushape[1:])
        as_array(f"Y[{b}]", Y[b], self._yshape[1:], allow_nan=True)
        raise QuadobsError(f"U, Y: member {b} refused")  # pragma: no cover - as_array raised

    def _step_reference(self, U: np.ndarray, Y: np.ndarray) -> None:
        """Each member by the NumPy reference, once every member's operands are checked."""
        if not np.isfinite(U).all() or np.isinf(Y).any():
            self._refuse(U, Y)
        ref = self._ref
        for b in range(self.batch):
            ref._z, ref._P, ref._stats = self.Z[b], self.P[b], self._stats[b]
            ref.correct_outputs(Y[b])
            ref.predict_step(U[b])

    def _step_threads(self, U: np.ndarray, Y: np.ndarray) -> None:
        """The compiled kernel on contiguous slices of the batch, one thread each, once every member is checked."""
        SB, _, fc, ic = self._kops
        if self._batch_refused(U, Y, ic) >= 0:  # before any slice starts: nothing changed
            self._refuse(U, Y)
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=self._threads)
        jobs = [
            self._pool.submit(self._kernel, U[sl], Y[sl], SB[sl], W, fc, ic)
            for sl, (W, ic) in zip(self._slices, self._works)
        ]
        for job in jobs:
            job.result()


def _rows(name: str, value, B: int, width: int) -> np.ndarray:
    arr = as_array(name, value)
    if arr.shape not in ((width,), (B, width)):
        raise QuadobsError(f"{name}: expected shape ({width},) or ({B}, {width}), got {arr.shape}")
    return arr
