"""The GTSAM factors of the peer that GTSAM does not ship: ranges with a bias, TDOA, the double integrator.

Each is a ``gtsam.CustomFactor`` (gtsam's Python bindings call the error function and ask
it for the Jacobians when they linearise), with the Jacobians derived here in closed form
and tested against finite differences. The vehicle's position ``p`` is read from one
variable, of one of three types (:data:`POSITION_TYPES`):

==========  ===================================  ==============================================
type        variable                              ``d p / d delta`` (gtsam's tangent ``delta``)
==========  ===================================  ==============================================
``point``   a vector ``p`` (2-D or 3-D)           ``I``
``pose2``   ``Pose2 (R, t)``, ``p = t``           ``[R, 0]`` (``delta = (v_x, v_y, omega)``)
``pose3``   ``Pose3 (R, t)``, ``p = t``           ``[0, R]`` (``delta = (omega, v)``)
==========  ===================================  ==============================================

since gtsam retracts a pose as ``X exp(delta)``, whose translation moves by ``R v`` to first
order.

* Range to anchor ``a`` with an optional bias variable ``b`` (a 1-vector):
  ``e = |p - a| + b - rho``, ``d e / d p = u^T`` with ``u = (p - a) / |p - a|``,
  ``d e / d b = 1``; taken ``tau`` seconds after its node, on ``p_node + v tau`` as a TDOA
  below (``d e / d v = tau u^T``).
* TDOA between anchors ``a_i`` and ``a_j`` (the model of :class:`~quadobs.core.measurements.TdoaModel`):
  ``e = |p - a_i| - |p - a_j| - d_ij``, ``d e / d p = u_i^T - u_j^T``. Taken ``tau`` seconds
  after its node (keyframes), on the node's position and velocity: ``p = p_node + v tau``,
  whose error is the acceleration's ``a tau^2 / 2`` (5 mm for ``a = 1`` m/s^2, ``tau = 0.1``
  s), and ``d e / d v = tau (u_i - u_j)^T``.
* The double integrator between ``(p_i, v_i)`` and ``(p_j, v_j)``, ``T`` seconds apart, with
  a known input contribution ``(Delta p, Delta v)`` (``int int a`` and ``int a`` over the
  interval; zero for the constant-velocity prior):

  .. math:: e = \\begin{bmatrix} p_j - p_i - v_i T - \\Delta p \\\\ v_j - v_i - \\Delta v \\end{bmatrix},
            \\qquad Q = q \\begin{bmatrix} T^3/3\\, I & T^2/2\\, I \\\\ T^2/2\\, I & T\\, I \\end{bmatrix},

  ``Q`` the covariance of a white acceleration of intensity ``q`` integrated over ``T``
  (the exact discretisation of ``p' = v``, ``v' = a + w``).

Position and velocity variables of the ``point`` type are plain vectors (``Values.insert``
of a 1-D float array, read with ``atVector``).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "POSITION_TYPES",
    "double_integrator_covariance",
    "double_integrator_factor",
    "position_of",
    "range_factor",
    "tdoa_factor",
]

#: The variable types a position is read from (module docstring).
POSITION_TYPES = ("point", "pose2", "pose3")


def position_of(values, key: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """The position ``p (d,)`` held by the variable ``key`` and ``d p / d delta (d, dof)``."""
    if kind == "point":
        p = np.asarray(values.atVector(key), dtype=float)
        return p, np.eye(p.size)
    if kind == "pose2":
        X = values.atPose2(key)
        c, s = np.cos(X.theta()), np.sin(X.theta())
        return np.array([X.x(), X.y()]), np.array([[c, -s, 0.0], [s, c, 0.0]])
    X = values.atPose3(key)
    R = X.rotation().matrix()
    return np.asarray(X.translation(), dtype=float), np.hstack([np.zeros((3, 3)), R])


def _unit(diff: np.ndarray) -> tuple[float, np.ndarray]:
    r = float(np.sqrt(diff @ diff))
    return r, (diff / r if r > 0.0 else np.zeros_like(diff))


def range_factor(
    gtsam,
    noise,
    key: int,
    kind: str,
    anchor,
    rho: float,
    bias_key: int | None = None,
    velocity_key: int | None = None,
    offset: float = 0.0,
):
    """``rho = |p - a| + b``: a ``CustomFactor`` on the position variable ``key`` (and the bias
    ``bias_key``; and the velocity ``velocity_key``, the range taken ``offset`` seconds after
    its node: ``p = p_node + v offset``, as :func:`tdoa_factor`'s)."""
    a = np.asarray(anchor, dtype=float)
    rho, tau = float(rho), float(offset)

    def error(this, values, jacobians):
        p, dp = position_of(values, key, kind)
        if velocity_key is not None:
            p = p + tau * np.asarray(values.atVector(velocity_key), dtype=float)
        r, u = _unit(p - a)
        e = r - rho
        if bias_key is not None:
            e += float(values.atVector(bias_key)[0])
        if jacobians is not None:
            jacobians[0] = (u @ dp)[None, :]
            if bias_key is not None:
                jacobians[1] = np.ones((1, 1))
            if velocity_key is not None:
                jacobians[-1] = tau * u[None, :]
        return np.array([e])

    keys = [key] + ([] if bias_key is None else [bias_key])
    keys += [] if velocity_key is None else [velocity_key]
    return gtsam.CustomFactor(noise, keys, error)


def tdoa_factor(
    gtsam,
    noise,
    key: int,
    kind: str,
    anchor_i,
    anchor_j,
    d: float,
    velocity_key: int | None = None,
    offset: float = 0.0,
):
    """``d_ij = |p - a_i| - |p - a_j|``: a ``CustomFactor`` on the position variable ``key``.

    With ``velocity_key`` (a vector variable, the node's velocity ``v`` in the navigation frame)
    the TDOA was taken ``offset`` seconds after the node: ``p`` is then ``p_node + v offset``
    (module docstring), and ``d e / d v = offset (u_i - u_j)^T``.
    """
    ai, aj = np.asarray(anchor_i, dtype=float), np.asarray(anchor_j, dtype=float)
    d, tau = float(d), float(offset)

    def error(this, values, jacobians):
        p, dp = position_of(values, key, kind)
        if velocity_key is not None:
            p = p + tau * np.asarray(values.atVector(velocity_key), dtype=float)
        ri, ui = _unit(p - ai)
        rj, uj = _unit(p - aj)
        if jacobians is not None:
            g = ui - uj
            jacobians[0] = (g @ dp)[None, :]
            if velocity_key is not None:
                jacobians[1] = tau * g[None, :]
        return np.array([ri - rj - d])

    keys = [key] if velocity_key is None else [key, velocity_key]
    return gtsam.CustomFactor(noise, keys, error)


def double_integrator_covariance(q: float, T: float, d: int) -> np.ndarray:
    """``Q (2d, 2d)`` of a white acceleration of intensity ``q`` (m^2/s^3) over ``T`` seconds (module docstring)."""
    eye = np.eye(d)
    return q * np.block([[T**3 / 3.0 * eye, T**2 / 2.0 * eye], [T**2 / 2.0 * eye, T * eye]])


def double_integrator_factor(
    gtsam, keys, T: float, delta_p, delta_v, q: float, min_span: float = 0.0
):
    """The double integrator's factor on ``keys = (p_i, v_i, p_j, v_j)`` (vector variables; module docstring).

    ``Q`` is formed over ``max(T, min_span)``: a floor that keeps its information finite
    for two nodes a few microseconds apart.
    """
    dp, dv = np.asarray(delta_p, dtype=float), np.asarray(delta_v, dtype=float)
    d = dp.size
    T = float(T)
    Q = double_integrator_covariance(q, max(T, float(min_span)), d)
    noise = gtsam.noiseModel.Gaussian.Covariance(Q)
    eye, zero = np.eye(d), np.zeros((d, d))
    J = (
        np.vstack([-eye, zero]),
        np.vstack([-T * eye, -eye]),
        np.vstack([eye, zero]),
        np.vstack([zero, eye]),
    )
    ki, vi, kj, vj = (int(k) for k in keys)

    def error(this, values, jacobians):
        pi, ui = values.atVector(ki), values.atVector(vi)
        pj, uj = values.atVector(kj), values.atVector(vj)
        if jacobians is not None:
            for n in range(4):
                jacobians[n] = J[n]
        return np.concatenate([pj - pi - ui * T - dp, uj - ui - dv])

    return gtsam.CustomFactor(noise, [ki, vi, kj, vj], error)
