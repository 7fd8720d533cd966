"""The Kalman-type observer of Theorem 3 [IFAC2021, Thm. 3] on the augmented system.

Theorem 3 (Besançon 2007) for ``z' = A(u) z + B u``, ``y = C z``:

.. math::

    \\dot{\\hat z} = A(u)\\hat z + B u + K (y - C \\hat z), \\quad K = M C^\\top W^{-1}, \\\\
    \\dot M = A(u) M + M A(u)^\\top - M C^\\top W^{-1} C M + V + \\theta M .

It is run here as a continuous-discrete filter, one call of :meth:`AugmentedObserver.step`
per physics step: first the correction with the output sampled at the start of the step
(skipped, output by output, where the sample is missing: NaN), then the exact prediction
over the step with the input held (:class:`~quadobs.core.held_input.HeldInputDiscretization`).
The correction uses the Joseph form ``P = (I - K C) P (I - K C)^T + K R K^T`` with
``R = W / T`` (``T`` the sampling period of the output), and the covariance is
re-symmetrised after every operation, so it stays symmetric positive definite. For a
noise-free system whose initial estimate is exact, the estimate stays exact to rounding.

Two implementations of the same arithmetic: a compiled kernel (Numba, :mod:`quadobs._kernels.observer`)
that fuses the correction and the prediction into one call (about 1.4 µs of arithmetic for
the 9-dimensional vehicle, 2.4 µs a step from Python) and allocates nothing, used by
default when Numba is importable; and the NumPy reference (``backend="numpy"``, about
55 µs a step), kept as the specification the kernel is tested against. Both update ``z``
and ``P`` in place.

Measurements at their own times (:meth:`~quadobs.estimators.base.Estimator.predict` over an
interval, :meth:`~quadobs.estimators.base.Estimator.correct` by one measurement) run compiled
too with the compiled backend (:mod:`quadobs.estimators.augmented_in_time`): the interval's
exponentials and the correction by one scalar output in ``O(N^2)``, without allocation; the
NumPy reference (:attr:`AugmentedObserver.in_time_compiled` ``= False``) agrees to rounding.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from quadobs.core.held_input import (
    HeldInputDiscretization,
    as_covariance,
    held_input_interval,
    van_loan_interval,
)
from quadobs.core.immersion import Immersion, as_immersion
from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError, as_array, as_finite_scalar, as_float_array
from quadobs.estimators.augmented_in_time import InTimeKernels
from quadobs.estimators.base import (
    BlockStep,
    Estimator,
    Gated,
    HalfSteps,
    Immersed,
    check_step,
    measurement_models,
    step_operands,
)

__all__ = ["BACKENDS", "AugmentedObserver", "default_backend"]

#: The implementations of :class:`AugmentedObserver`: ``"auto"`` picks ``"numba"`` when Numba imports.
BACKENDS = ("auto", "numba", "numpy")
_F64 = np.dtype(np.float64)


def default_backend() -> str:
    """``"numba"`` when Numba is importable (compiled kernels), else ``"numpy"``."""
    try:
        import quadobs._kernels.observer  # noqa: F401 - imports numba; compiled lazily on first call
    except ImportError:
        return "numpy"
    return "numba"


def resolve_backend(backend: str) -> str:
    """Validate ``backend`` (one of :data:`BACKENDS`) and resolve ``"auto"``."""
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise QuadobsError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return default_backend()
    if backend == "numba":
        try:
            import quadobs._kernels.observer  # noqa: F401
        except ImportError as exc:
            raise QuadobsError(
                f"backend: 'numba' requested but Numba cannot be imported ({exc})"
            ) from None
    return backend


def _initial_covariance(P0, S0):
    """``P0``, or its deprecated name ``S0`` (with a :class:`DeprecationWarning`); default 100."""
    if S0 is None:
        return 100.0 if P0 is None else P0
    if P0 is not None:
        raise QuadobsError(
            "S0: give the initial covariance once, as P0 (S0 is its deprecated name)"
        )
    warnings.warn(
        "AugmentedObserver(S0=...) is deprecated; use P0=...", DeprecationWarning, stacklevel=3
    )
    return S0


def _csr(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row pointers and column indices of the ``True`` entries of a 2-D mask."""
    rows, cols = np.nonzero(mask)
    ptr = np.zeros(mask.shape[0] + 1, dtype=np.int64)
    np.add.at(ptr, rows + 1, 1)
    return np.cumsum(ptr), cols.astype(np.int64)


def _offsets(arrays: dict[str, np.ndarray], start: int) -> dict[str, int]:
    """Where each of ``arrays`` starts once they are packed one after the other from ``start``."""
    out = {}
    for name, a in arrays.items():
        out[name] = start
        start += a.size
    return out


def _float64_operands(u, y, ushape: tuple[int, ...], yshape: tuple[int, ...]) -> bool:
    """Whether ``u`` and ``y`` are float64 arrays of shapes ``ushape`` and ``yshape`` (anything else:
    ``False``): such operands go straight to a compiled kernel, which checks their values itself."""
    try:
        return u.dtype is _F64 and y.dtype is _F64 and u.shape == ushape and y.shape == yshape
    except AttributeError:
        return False


class KernelModel:
    """The constant operands of the compiled kernels for one observer model (shared by a batch).

    Packs, from a :class:`~quadobs.core.held_input.HeldInputDiscretization`, the output matrix
    ``C (q, N)``, the discrete output covariance ``R (q, q)`` and the gate, the arrays
    ``fc`` (floats) and ``ic`` (integers) described in :mod:`quadobs._kernels.observer`: the
    structural nonzeros of ``Phi(u)`` (CSR) and of ``C`` (CSR), and the nonzero
    upper-triangular coefficients of ``Q_d(u)`` per monomial of ``u`` (COO); for a model on
    the dense path (:func:`quadobs._kernels.observer.dense_path`, attribute ``dense``) also
    those coefficients as dense ``(N, N)`` matrices and the constant x-x block of ``Phi``.
    """

    def __init__(
        self, model: HeldInputDiscretization, C: np.ndarray, R: np.ndarray, gate: float | None
    ) -> None:
        from quadobs._kernels.observer import HEADER, HEADER_FIELDS, dense_path

        im = model.immersion
        k, N, n, p = im.n_aux, im.dim, im.system.n, im.system.p
        C = np.asarray(C, dtype=float)
        q = C.shape[0]
        F0 = np.array(model.transition_constant, dtype=float)
        F1 = np.asarray(model.transition_input, dtype=float)
        pattern = F0 != 0
        if p:
            pattern[:k, k:] |= np.any(F1 != 0, axis=0)
        phi_ptr, phi_col = _csr(pattern)
        # Q_d(u) = sum_r mono_r(u) Qc[r], mono = (1, u_j, u_j u_l for j <= l).
        Q2 = model.noise_quadratic
        coeffs = [model.noise_constant] + [model.noise_linear[j] for j in range(p)]
        coeffs += [
            Q2[j, j] if j == l else Q2[j, l] + Q2[l, j] for j in range(p) for l in range(j, p)
        ]
        Qc = np.array(coeffs).reshape(len(coeffs), N, N)
        r_idx, i_idx, j_idx = np.nonzero((Qc != 0) & np.triu(np.ones((N, N), dtype=bool)))
        c_ptr, c_col = _csr(C != 0)
        ints = {
            "o_phi_ptr": phi_ptr,
            "o_phi_col": phi_col,
            "o_qi": i_idx,
            "o_qj": j_idx,
            "o_qr": r_idx,
            "o_c_ptr": c_ptr,
            "o_c_col": c_col,
            "o_iw": np.zeros(max(q, 1)),
        }
        dense = dense_path(N, phi_col.size)
        floats = {
            "o_fblk": F0[:k, k:].ravel(),
            "o_F1": F1.ravel(),
            "o_G0": np.asarray(model.input_linear, dtype=float).ravel(),
            "o_G2": np.asarray(model.input_quadratic, dtype=float).ravel(),
            "o_qv": Qc[r_idx, i_idx, j_idx],
            "o_cval": C[C != 0],
            "o_R": np.asarray(R, dtype=float).ravel(),
            # the dense path's Q_d coefficients and constant x-x block of Phi
            "o_Qc": Qc.ravel() if dense else np.zeros(0),
            "o_E": F0[k:, k:].ravel() if dense else np.zeros(0),
        }
        head = {"N": N, "k": k, "p": p, "q": q, "nm": len(coeffs), "nq": r_idx.size}
        head.update(_offsets(ints, HEADER), dense=int(dense))
        head.update(_offsets(floats, 2))
        self.ic = np.concatenate(
            [np.array([head[name] for name in HEADER_FIELDS], dtype=np.int64)]
            + [a.astype(np.int64) for a in ints.values()]
        )
        growth = float(np.exp(model.theta * model.dt))
        self.fc = np.concatenate(
            [[growth, np.inf if gate is None else float(gate)]] + list(floats.values())
        )
        self.k, self.N, self.n, self.p, self.q, self.nm = k, N, n, p, q, len(coeffs)
        self.dense = dense  # the prediction's dense path (quadobs._kernels.observer.dense_path)
        self.F0 = F0

    def work(self) -> np.ndarray:
        """A fresh work buffer ``W`` (``Phi`` outside its aux-x block set to ``F0``; stats ``[nan, 0, 0, 0]``)."""
        from quadobs._kernels.observer import work_size

        W = np.zeros(work_size(self.N, self.q, self.nm))
        W[: self.N * self.N] = self.F0.ravel()
        W[-4] = np.nan
        return W


class AugmentedObserver(HalfSteps, Gated, Immersed, BlockStep):
    """Theorem 3's observer on an immersion, advanced one held-input step at a time.

    Parameters
    ----------
    immersion : Immersion
        From :func:`quadobs.immerse`.
    dt : float
        Physics step (s): the estimate advances by ``dt`` per :meth:`step`.
    V : float or array_like
        Continuous process-noise intensity (scalar times ``I_N``, diagonal, or ``(N, N)``).
    W : float or array_like
        Continuous output-noise intensity (scalar times ``I_q``, diagonal, or ``(q, q)``),
        positive definite.
    P0 : float or array_like
        Initial covariance ``M_0`` of the augmented estimate (scalar times ``I_N``, diagonal,
        or ``(N, N)``); default ``100``. The scenario field is ``observer.S0``.
    S0 : float or array_like, optional
        Deprecated name of ``P0``.
    theta : float
        Forgetting factor (``theta >= 0``).
    x0 : array_like (n,), optional
        Initial estimate of ``x``; the augmented estimate starts at ``lift(x0)``. Default zero.
    z0 : array_like (N,), optional
        Initial augmented estimate (overrides ``x0``).
    sample_period : float or array_like (q,), optional
        Period ``T_h`` of the samples of each output (s), default ``dt``; the discrete
        output covariance is ``R_hl = W_hl / sqrt(T_h T_l)`` (``R = W / T`` for one rate).
    gate : float, optional
        Reject a correction whose normalised innovation squared exceeds ``gate``
        (a chi-square quantile for ``q`` degrees of freedom); counted in :attr:`rejected`.
    backend : {"auto", "numba", "numpy"}
        ``"numba"``: the compiled kernels of :mod:`quadobs._kernels.observer`; ``"numpy"``: the
        reference implementation; ``"auto"`` (default): Numba when it imports.
    measurements : MeasurementModel or list, optional
        The models of the measurements :meth:`correct` takes (default: the range model of the
        system's range outputs); each needs a quadratic-output form.
    noise_of : callable, optional
        ``z -> V (N, N)``: a process noise that depends on the state, used by :meth:`predict`
        over each interval (at the interval's start) in place of ``V``; :meth:`step` keeps ``V``.

    Attributes
    ----------
    z : ndarray (N,)
        Augmented estimate, updated in place by :meth:`step` (copy it to keep a value);
        :attr:`x_hat` is a copy of its last ``n`` entries.
    P : ndarray (N, N)
        Its covariance, symmetric, updated in place.
    nis : float
        Normalised innovation squared of the last correction (NaN when nothing was present).
    corrections, rejected : int
        Corrections applied, and rejected by the gate.

    Notes
    -----
    The paper's example (section 6) uses ``S_0 = 100 I``, ``V = 1e-4 I``, ``W = I`` and
    writes ``I_6``; the augmented state there has ``N = 9`` entries and the output is
    scalar, so the scenario ``ifac2021`` reads them as ``S_0 = 100 I_9``,
    ``V = 1e-4 I_9`` and ``W = 1``.
    """

    name = "augmented"

    #: Where a range's output variance ``r^2 sigma^2 + sigma^4 / 2`` takes the unknown true range
    #: ``r`` (:meth:`correct`, a measurement with its own ``std``): ``"measured"``, at the measured
    #: range (:meth:`~quadobs.core.measurements.RangeModel.quadratic_output`); ``"larger"``, the
    #: larger of that and the variance at the range the estimate predicts, so that a range read
    #: short (an outlier of a metre near an anchor) gets no more weight than the prediction gives it:
    #: with the measured range alone, a range read ``0.3`` m where ``2.4`` m was predicted, with
    #: ``sigma = 0.08`` m, is taken with the standard deviation ``0.024`` in ``y`` against ``0.19``.
    range_variance: str = "measured"

    def __init__(
        self,
        immersion: Immersion,
        dt: float,
        *,
        V=1e-4,
        W=1.0,
        P0=None,
        S0=None,
        theta: float = 0.0,
        x0=None,
        z0=None,
        sample_period: float | np.ndarray | None = None,
        gate: float | None = None,
        backend: str = "auto",
        measurements=None,
        noise_of=None,
    ) -> None:
        self.immersion = as_immersion(immersion)
        self.model = HeldInputDiscretization(immersion, dt, V, theta)
        self.measurement_models = measurement_models(immersion.system, measurements)
        self.noise_of = noise_of
        for model in self.measurement_models.values():
            if model.quadratic_form() is None:
                raise QuadobsError(
                    f"measurements: {model.kind} measurements have no quadratic-output form, "
                    "which the augmented observer needs"
                )
        self._time = 0.0
        N, q, n = immersion.dim, immersion.system.q, immersion.system.n
        if sample_period is None:
            period = np.full(q, self.model.dt)
        else:
            period = as_array("sample_period", sample_period)
            if period.ndim == 0:
                period = np.full(q, float(period))
            elif period.shape != (q,):
                raise QuadobsError(
                    f"sample_period: expected a scalar or shape ({q},), got {period.shape}"
                )
            if np.any(period <= 0):
                raise QuadobsError("sample_period: must be positive")
        self.W = as_covariance("W", W, q)
        scale = 1.0 / np.sqrt(period)
        self.R = self.W * np.outer(scale, scale)
        if z0 is not None:
            z = as_array("z0", z0, (N,))
        else:
            x = np.zeros(n) if x0 is None else as_array("x0", x0, (n,))
            with np.errstate(over="ignore", invalid="ignore"):
                z = immersion.lift(x)
            if not np.all(np.isfinite(z)):  # finite x0 whose squares overflow float64
                raise QuadobsError(
                    f"x0: its augmented state lift(x0) overflows (largest |x0| {np.max(np.abs(x)):.3g})"
                )
        self._z = np.array(z, dtype=float)
        self._P = np.array(
            as_covariance("P0" if S0 is None else "S0", _initial_covariance(P0, S0), N), dtype=float
        )
        self.gate = None if gate is None else as_finite_scalar("gate", gate, positive=True)
        self._ushape, self._yshape, self._rshape = (immersion.system.p,), (q,), (n + 3,)
        self._C = immersion.output_matrix
        self._eye = np.eye(N)
        self._k = immersion.n_aux
        m = self.model
        self._growth = float(np.exp(m.theta * m.dt))
        self._F0, self._F1 = m.transition_constant, m.transition_input
        self._G0, self._G2 = m.input_linear, m.input_quadratic
        self._Q0, self._Q1, self._Q2 = m.noise_constant, m.noise_linear, m.noise_quadratic
        self._Phi = self._F0.copy()
        self.backend = resolve_backend(backend)
        self._kernel = None
        if self.backend == "numba":
            km = KernelModel(m, self._C, self.R, self.gate)
            # One buffer S = [z | P | W]: the kernels take five arrays (see quadobs._kernels.observer).
            self._S = np.concatenate([self._z, self._P.ravel(), km.work()])
            self._fc, self._ic = km.fc, km.ic
            self._bind_kernels()  # compiled at their first call, or by prepare()
        else:
            self._stats = np.array([np.nan, 0.0, 0.0, 0.0])  # nis, corrections, rejected, trace(P)
        self._stats[3] = np.trace(self._P)
        self._V = np.asarray(m.V)  # (N, N): the interval's process noise without noise_of
        # the interface in time compiled (quadobs.estimators.augmented_in_time), where it applies
        self.in_time_compiled = True

    def prepare(self, path: str) -> None:
        """Load (or compile) the kernel of ``path`` (see :meth:`Estimator.prepare`) on scratch copies.

        ``"record"`` and ``"block"`` are prepared for the strided row views an episode passes
        (``"block"`` also for a single row, whose views NumPy calls contiguous).
        """
        if self._kernel is None:
            return
        n, q, p = self._rshape[0] - 3, self._yshape[0], self._ushape[0]
        S, fc, ic = self._S.copy(), self._fc, self._ic
        u, y = np.zeros(p), np.full(q, np.nan)
        if path == "step":
            self._kernel(u, y, S, fc, ic)
            return
        rows = np.zeros(
            (2, 2 * q + n)
        )  # row views of a wider array, as an episode's block passes them
        rec = np.zeros((2, n + 3))
        if path == "record":
            self._krecord(rows[0, :p], rows[0, p : p + q], S, fc, ic, rec[0])
        elif path == "block":
            self._kblock(rows[:, :p], rows[:, p : p + q], S, fc, ic, rec)
            self._kblock(
                rows[:1, :p], rows[:1, p : p + q], S, fc, ic, rec[:1]
            )  # one row: contiguous views
        else:
            raise QuadobsError(f"prepare: path must be 'step', 'record' or 'block', got {path!r}")

    def _bind_kernels(self) -> None:
        """Views of ``S = [z | P | W]`` and the compiled kernels (after construction or unpickling)."""
        import quadobs._kernels.observer as _kernels

        N, S = self.immersion.dim, self._S
        self._z = S[:N]
        self._P = S[N : N + N * N].reshape(N, N)
        self._stats = S[-4:]  # nis, corrections, rejected, trace(P) (written by the kernels)
        self._kops = (S, self._fc, self._ic)
        self._kernel = _kernels.augmented_step
        self._kcorrect = _kernels.augmented_correct
        self._kpredict = _kernels.augmented_predict
        self._krecord = _kernels.augmented_step_record
        self._kblock = _kernels.augmented_step_block

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        if self.backend == "numba":  # views and kernels are rebuilt from S on unpickling
            for key in (
                "_z",
                "_P",
                "_stats",
                "_kops",
                "_kernel",
                "_kcorrect",
                "_kpredict",
                "_krecord",
                "_kblock",
            ):
                state.pop(key, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if "_in_time" not in state:  # pickled before the interface in time was compiled
            self._V = np.asarray(self.model.V)
            self.in_time_compiled = True
        if self.backend == "numba":
            self._bind_kernels()

    # -- state ---------------------------------------------------------------------------

    @property
    def z(self) -> np.ndarray:
        return self._z

    @z.setter
    def z(self, value) -> None:
        self._z[...] = as_array("z", value, (self.immersion.dim,))

    @property
    def P(self) -> np.ndarray:
        return self._P

    @P.setter
    def P(self, value) -> None:
        N = self.immersion.dim
        self._P[...] = as_array("P", value, (N, N))
        self._stats[3] = np.trace(self._P)

    @property
    def in_time_compiled(self) -> bool:
        """Whether :meth:`predict` over an interval and :meth:`correct` by one measurement take the
        compiled kernels (:mod:`quadobs.estimators.augmented_in_time`): with the compiled
        backend, no forgetting factor and a nilpotent ``A(u)``. Set it to ``False`` for the NumPy
        reference (the same maths, to rounding); ``True`` restores the kernels where they apply."""
        return self._in_time is not None

    @in_time_compiled.setter
    def in_time_compiled(self, value: bool) -> None:
        compiled = bool(value) and self.backend == "numba"
        self._in_time = (
            InTimeKernels.of(self.immersion, self._V, self.model.theta) if compiled else None
        )

    @property
    def covariance_trace(self) -> float:
        """``trace(P)`` of the augmented covariance, kept up to date by every operation."""
        return float(self._stats[3])

    @property
    def nis(self) -> float:
        return float(self._stats[0])

    @nis.setter
    def nis(self, value: float) -> None:
        self._stats[0] = value

    @property
    def corrections(self) -> int:
        return int(self._stats[1])

    @corrections.setter
    def corrections(self, value: int) -> None:
        self._stats[1] = int(value)

    @property
    def rejected(self) -> int:
        return int(self._stats[2])

    @rejected.setter
    def rejected(self, value: int) -> None:
        self._stats[2] = int(value)

    @staticmethod
    def _checked(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
        """``value`` as a contiguous float64 array of ``shape`` (NaN allowed: a missing output)."""
        arr = as_float_array(name, value, copy=False)
        if arr.shape != shape:
            raise QuadobsError(f"{name}: expected shape {shape}, got {arr.shape}")
        return arr

    # -- estimator interface -----------------------------------------------------------

    @property
    def x_hat(self) -> np.ndarray:
        """The estimate of ``x`` ``(n,)``: a copy of the last ``n`` entries of ``z``."""
        return self._z[self._k :].copy()

    @property
    def x_covariance(self) -> np.ndarray:
        """The ``x`` block of ``P`` ``(n, n)`` (a copy)."""
        k = self._k
        return self._P[k:, k:].copy()

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        """Correct with ``y`` (output at the start of the step), then predict over the step with ``u`` held.

        A non-finite ``u``, an infinite ``y`` or a wrong shape raises :class:`QuadobsError`
        and leaves the observer unchanged.
        """
        kernel = self._kernel
        if kernel is None:
            u, y = step_operands(u, y, *self._ushape, *self._yshape)
            self.correct_outputs(y)
            self.predict_step(u)
            self._time += self.model.dt
            return
        if not _float64_operands(u, y, self._ushape, self._yshape):
            u, y = check_step(u, y, *self._ushape, *self._yshape)
        if kernel(u, y, *self._kops) < 0:  # a non-finite u or an infinite y: nothing changed
            check_step(u, y, *self._ushape, *self._yshape)  # raises, naming it
            raise QuadobsError(
                "u, y: refused by the compiled step"
            )  # pragma: no cover - check_step raised
        self._time += self.model.dt

    def step_and_record(self, u: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
        """:meth:`step`, recording ``[x_hat, covariance_trace]`` before it and ``nis`` after it into ``out`` (one compiled call)."""
        if self._kernel is None:
            return Estimator.step_and_record(self, u, y, out)
        fast = (
            _float64_operands(u, y, self._ushape, self._yshape)
            and getattr(out, "dtype", None) is _F64
            and out.shape == self._rshape
        )
        if not fast:
            u, y = self._checked("u", u, self._ushape), self._checked("y", y, self._yshape)
            if not (
                isinstance(out, np.ndarray) and out.shape == self._rshape and out.dtype == _F64
            ):
                raise QuadobsError(f"out: expected a float64 array of shape {self._rshape}")
        if (
            self._krecord(u, y, *self._kops, out) < 0
        ):  # a non-finite u or an infinite y: nothing changed
            check_step(u, y, *self._ushape, *self._yshape)  # raises, naming it
            raise QuadobsError(
                "u, y: refused by the compiled step"
            )  # pragma: no cover - check_step raised
        self._time += self.model.dt

    @property
    def blockwise(self) -> bool:
        """Whether :meth:`step_block` is one compiled call (the compiled backend, and
        :meth:`step_and_record` not overridden: the block must give what it gives)."""
        return self._kernel is not None and type(self).step_and_record is _STEP_AND_RECORD

    def step_block(self, U: np.ndarray, Y: np.ndarray, out: np.ndarray) -> None:
        """:meth:`step_and_record` for each row of ``U (m, p)``, ``Y (m, q)`` into ``out (m, n + 3)``.

        One compiled call when :attr:`blockwise` (:func:`quadobs._kernels.observer.augmented_step_block`:
        the same arithmetic as ``m`` calls of :meth:`step_and_record`, hence the same bits);
        otherwise :meth:`step_and_record` row by row. Shapes and types are checked as
        :meth:`step_and_record` checks them.
        """
        m = self._checked_rows("U", U, self._ushape[0])
        if self._checked_rows("Y", Y, self._yshape[0]) != m or not (
            isinstance(out, np.ndarray) and out.dtype == _F64 and out.shape == (m,) + self._rshape
        ):
            raise QuadobsError(
                f"out: expected a float64 array of shape {(m,) + self._rshape} (one row per row of U and Y)"
            )
        if not self.blockwise:
            for i in range(m):
                self.step_and_record(U[i], Y[i], out[i])
            return
        code = self._kblock(U, Y, *self._kops, out)
        self._time += (m if code >= 0 else -1 - code) * self.model.dt
        if code < 0:  # row -1 - code was refused: the rows before it are done, nothing after
            j = -1 - code
            check_step(U[j], Y[j], *self._ushape, *self._yshape)  # raises, naming it
            raise QuadobsError(
                f"U, Y: row {j} refused by the compiled step"
            )  # pragma: no cover - check_step raised

    @staticmethod
    def _checked_rows(name: str, value, width: int) -> int:
        """Rows of ``value``, a float64 array ``(m, width)`` (views with strides allowed)."""
        if not (
            isinstance(value, np.ndarray)
            and value.dtype == _F64
            and value.ndim == 2
            and value.shape[1] == width
        ):
            raise QuadobsError(f"{name}: expected a float64 array of shape (m, {width})")
        return value.shape[0]

    # -- the two halves ----------------------------------------------------------------

    def correct_outputs(self, y: np.ndarray) -> None:
        """Kalman correction with the outputs present in ``y`` (NaN marks a missing sample).

        The first half of :meth:`step`; leaves :attr:`time` as it is.
        """
        y = self._checked("y", y, self._yshape)
        if self._kernel is not None:
            self._kcorrect(y, *self._kops)
            return
        present = ~np.isnan(y)
        stats = self._stats
        if not present.any():
            stats[0] = np.nan
            return
        if present.all():
            C, R, yv = self._C, self.R, y
        else:
            C, R, yv = self._C[present], self.R[np.ix_(present, present)], y[present]
        P, z = self._P, self._z
        PCt = P @ C.T
        S = C @ PCt + R
        nu = yv - C @ z
        Sinv_nu = np.linalg.solve(S, nu)
        stats[0] = float(nu @ Sinv_nu)
        if self.gate is not None and stats[0] > self.gate:
            stats[2] += 1
            return
        K = np.linalg.solve(S, PCt.T).T
        z += K @ nu
        IKC = self._eye - K @ C
        P = IKC @ P @ IKC.T + K @ R @ K.T
        self._P[...] = 0.5 * (P + P.T)
        stats[1] += 1
        stats[3] = np.trace(self._P)

    def predict_step(self, u: np.ndarray) -> None:
        """Exact propagation over one step with ``u`` held (``P`` with ``Q_d(u)`` and forgetting).

        The second half of :meth:`step`; leaves :attr:`time` as it is.
        """
        u = self._checked("u", u, self._ushape)
        if self._kernel is not None:
            self._kpredict(u, *self._kops)
            return
        m = self.model
        Phi = m.transition(u, out=self._Phi)
        self._z[...] = Phi @ self._z + m.input_term(u)
        P = self._growth * (Phi @ self._P @ Phi.T) + m.process_noise(u)
        self._P[...] = 0.5 * (P + P.T)
        self._stats[3] = np.trace(self._P)

    # -- the interface in time ------------------------------------------------------

    def _input_dimension(self) -> int:
        return self._ushape[0]

    def hold(self, u) -> None:
        """:meth:`Estimator.hold`, with a fast path for a finite float64 array of the right shape
        (one dot product checks it): a copy of ``u`` is held either way."""
        try:
            if u.dtype is _F64 and u.shape == self._ushape and math.isfinite(u.dot(u)):
                self._held = u.copy()
                return
        except AttributeError:
            pass
        super().hold(u)

    def _propagate(self, dt: float, u: np.ndarray) -> None:
        """Exact propagation over ``dt`` with ``u`` held: the precomputed step when ``dt`` is the
        observer's own (within ``1e-9`` relative), else from the matrix exponentials themselves.
        With ``noise_of`` (a function of ``z`` giving ``V``), the process noise of each interval is
        ``noise_of(z)`` at its start (a noise whose map into the augmented state depends on the
        state, as ``p^T w`` in ``(|p|^2 / 2)' = p^T (v + w)``).

        Over any ``dt``, with ``A(u)`` and ``B`` of the augmented system ([IFAC2021, eq. 14]):

        .. math::

            \\exp\\left(\\begin{bmatrix} A(u) & B u \\\\ 0 & 0 \\end{bmatrix} dt\\right)
            = \\begin{bmatrix} \\Phi & g \\\\ 0 & 1 \\end{bmatrix}, \\qquad
            P^- = e^{\\theta dt} \\Phi P \\Phi^\\top + Q_d(u, dt)

        with ``Q_d`` by Van Loan's exponential of ``A(u) + theta I / 2`` and ``V``
        (:mod:`quadobs.core.held_input`): the same maths as the precomputed step.
        """
        m = self.model
        if self.noise_of is None and abs(dt - m.dt) <= 1e-9 * m.dt:
            self.predict_step(u)
            return
        fast = self._in_time
        if fast is not None and fast.predict(self._z, self._P, u, dt, self.noise_of, self._stats):
            return
        self._propagate_reference(dt, u)

    def _propagate_reference(self, dt: float, u: np.ndarray) -> None:
        """The NumPy reference of :meth:`_propagate` off the grid: the two exponentials of the
        interval (:func:`~quadobs.core.held_input.held_input_interval`,
        :func:`~quadobs.core.held_input.van_loan_interval`), then ``P`` as in its docstring."""
        m, im = self.model, self.immersion
        A = im.state_matrix(u)
        V = self._V if self.noise_of is None else self.noise_of(self._z)
        Phi, g = held_input_interval(A, (im.input_matrix @ u)[:, None], dt)
        Q = van_loan_interval(A + 0.5 * m.theta * self._eye, V, dt)[1]
        z, P = self._z, self._P
        z[...] = Phi @ z + g[:, 0]
        P_new = math.exp(m.theta * dt) * (Phi @ P @ Phi.T) + Q
        P[...] = 0.5 * (P_new + P_new.T)
        self._stats[3] = np.trace(P)  # a non-finite estimate is left for the caller to report

    def _correct_measurement(self, m: Measurement) -> None:
        """One measurement through its model's quadratic-output form: output ``h``, value ``y_h``,
        variance the measurement's own (``m.std``) or, when it has none, the observer's ``R_hh``
        (then the very arithmetic of :meth:`correct_outputs` with only ``y_h`` present)."""
        model = self._model_of(m)
        h, yh, var = model.quadratic_output(m)
        if math.isnan(m.std):
            y = np.full(self._yshape, np.nan)
            y[h] = yh
            self.correct_outputs(y)
            return
        if self.range_variance == "larger" and m.kind == "range":
            var = max(var, self._predicted_variance(model, m, h))
        self._correct_scalar(h, yh, var)

    def _predicted_variance(self, model, m: Measurement, h: int) -> float:
        """``r^2 sigma^2 + sigma^4 / 2`` at the predicted range ``r``: ``r^2 = 2 c_h^T z + |a_h|^2``
        (the output ``y_h = r^2 / 2 - |a_h|^2 / 2`` of the estimate before the correction)."""
        a = model.anchors[m.anchors[0]]
        r2 = max(2.0 * float(self._C[h] @ self._z) + float(a @ a), 0.0)
        s2 = model.sigma(m) ** 2
        return r2 * s2 + 0.5 * s2 * s2

    def _correct_scalar(self, h: int, yh: float, r: float) -> None:
        """Joseph-form correction with the single output ``y_h = c^T z`` of variance ``r``.

        For one scalar output the Joseph form needs no matrix product: with ``k = P c / s``,
        ``s = c^T P c + r`` and ``P`` symmetric, as its two factors

        .. math::

            W = P - (P c) k^\\top, \\qquad
            (I - k c^\\top) P (I - k c^\\top)^\\top + r k k^\\top = W - k (c^\\top W) + r k k^\\top ,

        ``O(N^2)``, positive semi-definite where the expanded sum
        ``P - k (P c)^T - (P c) k^T + s k k^T`` can cancel a variance to zero
        (:mod:`quadobs._kernels.in_time`). Compiled (:func:`quadobs._kernels.in_time.scalar_correct`, no allocation)
        with the compiled backend; the NumPy reference below otherwise.
        """
        fast = self._in_time
        if fast is not None:
            fast.correct(self._z, self._P, h, yh, r, self.gate, self._stats)
            return
        z, P, stats = self._z, self._P, self._stats
        c = self._C[h]
        Pc = P @ c
        s = float(c @ Pc) + r
        nu = yh - float(c @ z)
        stats[0] = nu * nu / s
        if not stats[0] <= (np.inf if self.gate is None else self.gate):  # or not a number
            stats[2] += 1
            return
        k = Pc / s
        z += k * nu
        W = P - np.outer(Pc, k)
        P_new = W - np.outer(k, c @ W) + r * np.outer(k, k)
        P[...] = np.tril(P_new) + np.tril(P_new, -1).T  # the lower triangle, as compiled
        stats[1] += 1
        stats[3] = np.trace(P)


#: The compiled :meth:`AugmentedObserver.step_and_record` that :meth:`~AugmentedObserver.step_block` reproduces.
_STEP_AND_RECORD = AugmentedObserver.step_and_record
