"""Linear dynamics with quadratic outputs.

The class of systems of [ACC2024] (slides, "class of systems
considered") and, with ``q = 1`` and ``d = 0``, of [IFAC2021] eq. (4):

.. math::

    \\dot x = A x + B u, \\qquad
    y_h = \\tfrac12 x^\\top C_h x + d_h^\\top x, \\quad h = 1, \\dots, q.

Also the two families of systems the testbed simulates: a vehicle (double integrator
in ``R^dim``) ranging to beacons, and the same vehicle flying through a constant wind
while measuring its airspeed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from quadobs.errors import QuadobsError, as_array

__all__ = [
    "SYMMETRY_RTOL",
    "QuadraticSystem",
    "constant_velocity_system",
    "odometry_system",
    "range_outputs",
    "vehicle_system",
    "wind_system",
]

#: Relative tolerance on ``|C_h - C_h^T|`` below which an output matrix counts as symmetric.
SYMMETRY_RTOL = 1e-10


@dataclass(frozen=True, eq=False)
class QuadraticSystem:
    """``x' = A x + B u``, ``y_h = 1/2 x^T C_h x + d_h^T x`` (slides, system class).

    Parameters
    ----------
    A : array_like, shape (n, n)
    B : array_like, shape (n, p)
    C : array_like, shape (q, n, n)
        Symmetric output matrices, one per output. A 2-D ``(n, n)`` array is read as
        ``q = 1``.
    d : array_like, shape (q, n), optional
        Linear output terms; zero when omitted.
    symmetrize : bool, keyword-only
        Output matrices must be symmetric (the papers assume it "without loss of
        generality"). A non-symmetric ``C_h`` is refused unless ``symmetrize=True``, in
        which case it is replaced by ``(C_h + C_h^T) / 2``, which defines the same
        quadratic form and hence the same output.

    Raises
    ------
    QuadobsError
        On wrong shapes, non-finite entries, a non-symmetric ``C_h`` (without
        ``symmetrize``), no outputs, or an output that is identically zero.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    d: np.ndarray | None = None
    symmetrize: bool = field(default=False, kw_only=True, repr=False)

    def __post_init__(self) -> None:
        A = as_array("A", self.A, ndim=2)
        n = A.shape[0]
        if n == 0 or A.shape != (n, n):
            raise QuadobsError(f"A: expected a non-empty square matrix, got shape {A.shape}")
        B = as_array("B", self.B)
        if B.ndim == 1:
            B = B.reshape(-1, 1)
        if B.ndim != 2 or B.shape[0] != n:
            raise QuadobsError(f"B: expected shape ({n}, p), got {np.shape(self.B)}")
        C = as_array("C", self.C)
        if C.ndim == 2:
            C = C[None]
        if C.ndim != 3 or C.shape[1:] != (n, n):
            raise QuadobsError(f"C: expected shape (q, {n}, {n}), got {np.shape(self.C)}")
        q = C.shape[0]
        if q == 0:
            raise QuadobsError("C: the system has no outputs (q = 0)")
        asym = np.abs(C - C.transpose(0, 2, 1)).max(axis=(1, 2))
        scale = np.maximum(np.abs(C).max(axis=(1, 2)), np.finfo(float).tiny)
        bad = np.flatnonzero(asym > SYMMETRY_RTOL * scale)
        if bad.size:
            if not self.symmetrize:
                h = int(bad[0])
                raise QuadobsError(
                    f"C[{h}]: output matrix is not symmetric (max |C - C^T| = {asym[h]:.3g}); "
                    "pass (C + C^T)/2, which defines the same output, or symmetrize=True"
                )
        C = 0.5 * (C + C.transpose(0, 2, 1))
        if self.d is None:
            d = np.zeros((q, n))
        else:
            d = as_array("d", self.d)
            if d.ndim == 1 and q == 1:
                d = d[None]
            if d.shape != (q, n):
                raise QuadobsError(f"d: expected shape ({q}, {n}), got {np.shape(self.d)}")
        for h in range(q):
            if not C[h].any() and not d[h].any():
                raise QuadobsError(
                    f"C[{h}], d[{h}]: output {h} is identically zero (both terms vanish)"
                )
        for name, arr in (("A", A), ("B", B), ("C", C), ("d", d)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def p(self) -> int:
        """Input dimension."""
        return self.B.shape[1]

    @property
    def q(self) -> int:
        """Number of outputs."""
        return self.C.shape[0]

    def output(self, x: np.ndarray) -> np.ndarray:
        """``y_h = 1/2 x^T C_h x + d_h^T x`` for ``x`` of shape ``(..., n)``; returns ``(..., q)``."""
        x = np.asarray(x, dtype=float)
        return 0.5 * np.einsum("...a,hab,...b->...h", x, self.C, x) + x @ self.d.T

    def vector_field(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``A x + B u`` for batched ``x (..., n)`` and ``u (..., p)``."""
        return np.asarray(x) @ self.A.T + np.asarray(u) @ self.B.T


def _double_integrator(dim: int) -> tuple[np.ndarray, np.ndarray]:
    eye, zero = np.eye(dim), np.zeros((dim, dim))
    A = np.block([[zero, eye], [zero, zero]])
    B = np.vstack([zero, eye])
    return A, B


def vehicle_system(dim: int, beacons: np.ndarray) -> QuadraticSystem:
    """A double integrator in ``R^dim`` ranging to beacons ([IFAC2021] eqs. 42-44).

    State ``x = (p, v)``, input the acceleration. Output ``h`` is the half squared range to
    beacon ``a_h`` minus the beacon's known constant ``|a_h|^2 / 2``:

    .. math:: y_h = \\tfrac12 |p - a_h|^2 - \\tfrac12 |a_h|^2 = \\tfrac12 |p|^2 - a_h^\\top p,

    so ``C_h = diag(I, 0)`` and ``d_h = (-a_h, 0)``. With one beacon at the origin this is
    exactly eq. (44). Use :func:`range_outputs` to turn measured ranges into ``y``.
    """
    beacons = as_array("beacons", beacons, (None, dim))
    if beacons.shape[0] == 0:
        raise QuadobsError("beacons: at least one beacon is needed")
    A, B = _double_integrator(dim)
    q = beacons.shape[0]
    C = np.zeros((q, 2 * dim, 2 * dim))
    C[:, :dim, :dim] = np.eye(dim)
    d = np.zeros((q, 2 * dim))
    d[:, :dim] = -beacons
    return QuadraticSystem(A, B, C, d)


def wind_system(dim: int, beacons: np.ndarray) -> QuadraticSystem:
    """Vehicle in a constant unknown wind (slides, multiple-output example).

    State ``x = (p, v_a, v_w)``: position, air velocity, wind. ``p' = v_a + v_w``,
    ``v_a' = u``, ``v_w' = 0``. Outputs: one per beacon, ``1/2 |p - a_h|^2 - 1/2 |a_h|^2``
    (as in :func:`vehicle_system`), then the half squared airspeed ``1/2 |v_a|^2``.
    """
    beacons = as_array("beacons", beacons, (None, dim))
    eye, zero = np.eye(dim), np.zeros((dim, dim))
    A = np.block([[zero, eye, eye], [zero, zero, zero], [zero, zero, zero]])
    B = np.vstack([zero, eye, zero])
    nb = beacons.shape[0]
    C = np.zeros((nb + 1, 3 * dim, 3 * dim))
    d = np.zeros((nb + 1, 3 * dim))
    C[:nb, :dim, :dim] = eye
    d[:nb, :dim] = -beacons
    C[nb, dim : 2 * dim, dim : 2 * dim] = eye
    return QuadraticSystem(A, B, C, d)


def range_outputs(ranges: np.ndarray, beacons: np.ndarray) -> np.ndarray:
    """Map measured ranges ``rho_h (..., q)`` to the outputs ``y_h = rho_h^2/2 - |a_h|^2/2``.

    NaN ranges (missing samples) stay NaN.
    """
    ranges = np.asarray(ranges, dtype=float)
    return 0.5 * ranges**2 - 0.5 * np.einsum("hi,hi->h", beacons, beacons)


def _planar_ranges(beacons: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``C_h = diag(I_2, 0)`` and ``d_h = (-a_h, 0)`` of planar range outputs on a state of size ``n``."""
    q = beacons.shape[0]
    C = np.zeros((q, n, n))
    C[:, :2, :2] = np.eye(2)
    d = np.zeros((q, n))
    d[:, :2] = -beacons
    return C, d


def odometry_system(beacons: np.ndarray) -> QuadraticSystem:
    """A ground vehicle in the plane driven by its odometry: a single integrator with known input.

    State ``x = p`` (position, m); input ``u = (v_x, v_y, omega)``: the odometry's forward
    speed rotated by the odometry heading (world frame, m/s) and the yaw rate (rad/s),
    which does not enter the position (the last column of ``B`` is zero; it is carried so
    that estimators of the heading read the same input):

    .. math:: \\dot p = (v_x, v_y), \\qquad
              y_h = \\tfrac12 |p - a_h|^2 - \\tfrac12 |a_h|^2 = \\tfrac12 |p|^2 - a_h^\\top p .

    Assumptions: the odometry's heading is right (its origin known, its drift small over
    the log) and its speed unbiased; what they miss is the process noise. The immersion
    has one auxiliary state ``xi = |p|^2 / 2`` with ``xi' = u^T p`` [ACC2024, Alg. 1].
    """
    beacons = as_array("beacons", beacons, (None, 2))
    if beacons.shape[0] == 0:
        raise QuadobsError("beacons: at least one beacon is needed")
    B = np.zeros((2, 3))
    B[:, :2] = np.eye(2)
    C, d = _planar_ranges(beacons, 2)
    return QuadraticSystem(np.zeros((2, 2)), B, C, d)


def constant_velocity_system(beacons: np.ndarray, inputs: int = 3) -> QuadraticSystem:
    """A vehicle with a constant velocity, driven by process noise only, in the plane or in space.

    State ``x = (p, v)``; ``p' = v``, ``v' = w`` (the process noise of the estimator);
    an input of ``inputs`` components (the ``u = (v_x, v_y, omega)`` of :func:`odometry_system`
    by default, or an acceleration) is accepted and ignored (``B = 0``), so the models
    replay the same rows. Outputs as in :func:`odometry_system` (:func:`vehicle_system` for
    beacons in space: ``beacons (q, 3)``).
    Assumption: the velocity changes slowly against the range rate (its changes are white
    noise of the intensity the estimator is given). Three auxiliary states
    ``|p|^2/2, p^T v, |v|^2/2`` (as for :func:`vehicle_system`).
    """
    beacons = np.asarray(beacons, dtype=float)
    dim = beacons.shape[1] if beacons.ndim == 2 and beacons.shape[1] == 3 else 2
    beacons = as_array("beacons", beacons, (None, dim))
    if beacons.shape[0] == 0:
        raise QuadobsError("beacons: at least one beacon is needed")
    if dim == 3:
        system = vehicle_system(3, beacons)
        return QuadraticSystem(system.A, np.zeros((6, int(inputs))), system.C, system.d)
    A, _ = _double_integrator(2)
    C, d = _planar_ranges(beacons, 4)
    return QuadraticSystem(A, np.zeros((4, int(inputs))), C, d)
