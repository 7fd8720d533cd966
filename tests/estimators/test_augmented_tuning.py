"""The augmented observer's prior (quadobs.estimators.augmented_tuning.lifted_covariance)."""

from __future__ import annotations

import numpy as np
import pytest

from quadobs.core.immersion import immerse
from quadobs.core.system import QuadraticSystem, odometry_system, vehicle_system
from quadobs.errors import QuadobsError
from quadobs.estimators.augmented_tuning import lifted_covariance

ANCHORS_3D = np.array([[0.0, 0.0, 0.2], [6.0, 0.0, 0.4], [0.0, 5.0, 2.6], [5.0, 5.0, 2.8]])


def _position_alone(beacons: np.ndarray):
    """``x = p`` in space, ``p' = u``: one auxiliary state ``xi = |p|^2 / 2``."""
    d = beacons.shape[1]
    C = np.broadcast_to(np.eye(d), (beacons.shape[0], d, d))
    return immerse(QuadraticSystem(np.zeros((d, d)), np.eye(d), C, -beacons))


def _sampled(im, x0: np.ndarray, P0: float, draws: int = 400_000) -> np.ndarray:
    rng = np.random.default_rng(7)
    x = x0 + np.sqrt(P0) * rng.standard_normal((draws, x0.size))
    return np.cov(im.lift(x), rowvar=False)


def test_the_squared_norm_has_the_variance_of_its_closed_form_in_space():
    """``xi = |p|^2 / 2`` for ``p ~ N(m, P0 I_3)``: ``var |p|^2 = 2 d P0^2 + 4 P0 |m|^2``, so
    ``var xi = 1.5 P0^2 + P0 |m|^2`` (the plane's ``P0^2`` was taken in space before), and
    ``cov(xi, p) = P0 m``; a Monte Carlo of 400 000 draws (seed 7) agrees to 1 %."""
    im = _position_alone(ANCHORS_3D)
    assert im.n_aux == 1 and np.allclose(im.aux_forms[0], np.eye(3))
    m, P0 = np.array([2.0, -1.0, 1.5]), 4.0
    P = lifted_covariance(im, m, P0, 3)
    assert P[0, 0] == pytest.approx((2 * 3 * P0**2 + 4 * P0 * m @ m) / 4, rel=1e-12)
    np.testing.assert_allclose(P[0, 1:], P0 * m, rtol=1e-12)
    np.testing.assert_allclose(P[1:, 1:], P0 * np.eye(3))
    np.testing.assert_allclose(P, _sampled(im, m, P0), rtol=0.01, atol=0.01 * P0)


def test_a_vehicle_with_velocity_gets_the_moments_of_each_auxiliary_state():
    """``x = (p, v)`` in space (auxiliary states ``|v|^2``, ``p^T v``, ``|p|^2 / 2``), ``P0`` on
    every entry: ``var |v|^2 = 6 P0^2 + 4 P0 |v0|^2``, ``var p^T v = 3 P0^2 + P0 (|p0|^2 +
    |v0|^2)``, their cross terms with ``x`` and each other; all as sampled (1 %)."""
    im = immerse(vehicle_system(3, ANCHORS_3D))
    x0, P0 = np.array([2.0, -1.0, 1.5, 0.5, 0.0, -0.3]), 0.5
    p0, v0 = x0[:3], x0[3:]
    P = lifted_covariance(im, x0, P0, 3)
    assert P[0, 0] == pytest.approx(6 * P0**2 + 4 * P0 * v0 @ v0)
    assert P[1, 1] == pytest.approx(3 * P0**2 + P0 * (p0 @ p0 + v0 @ v0))
    assert P[2, 2] == pytest.approx(1.5 * P0**2 + P0 * p0 @ p0)
    assert P[1, 2] == pytest.approx(P0 * p0 @ v0)
    np.testing.assert_allclose(P, _sampled(im, x0, P0), rtol=0.01, atol=0.01 * P0)


def test_the_plane_is_as_before():
    """In the plane (``xi = |p|^2 / 2``, ``d = 2``) the closed form is ``P0 |p0|^2 + P0^2``."""
    anchors = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 30.0]])
    im = immerse(odometry_system(anchors))
    p0, P0 = np.array([12.0, 9.0]), 2500.0
    P = lifted_covariance(im, p0, P0, 2)
    assert P[0, 0] == P0 * p0 @ p0 + P0**2
    np.testing.assert_array_equal(P[0, 1:], P0 * p0)


def test_a_position_dimension_beyond_the_state_is_refused():
    im = _position_alone(ANCHORS_3D)
    with pytest.raises(QuadobsError, match="dim"):
        lifted_covariance(im, np.zeros(3), 1.0, 4)
