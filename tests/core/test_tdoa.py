"""The TDOA relation squared twice, its immersion and its noise, against closed forms."""

import numpy as np
import pytest

from quadobs.core.held_input import HeldInputDiscretization
from quadobs.core.immersion import lift_jacobian, lifted_covariance
from quadobs.core.tdoa import (
    TdoaImmersion,
    relation_residual,
    relation_variance,
    tdoa_system,
)
from quadobs.errors import QuadobsError

ROOM = np.array(
    [[x, y, z] for z in (0.2, 2.8) for x, y in ((-3, -3), (3, -3), (3, 3), (-3, 3))], dtype=float
)


def _ranges(p, anchors=ROOM):
    return np.linalg.norm(p - anchors, axis=1)


@pytest.mark.parametrize("dim, aux", [(2, 9), (3, 18)])
def test_immersion_has_three_blocks_of_sym(dim, aux):
    im = TdoaImmersion(ROOM[:, :dim] if dim == 3 else ROOM[:4, :2]).immersion
    assert im.n_aux == aux
    assert im.dim == aux + 2 * dim
    assert tdoa_system(dim).q == dim * (dim + 1) // 2


def test_row_is_exact_on_the_lift():
    rng = np.random.default_rng(0)
    model = TdoaImmersion(ROOM)
    for _ in range(50):
        x = np.concatenate([rng.uniform(-4, 4, 3), rng.normal(size=3)])
        i, j = rng.choice(8, 2, replace=False)
        r = _ranges(x[:3])
        c, y = model.row(int(i), int(j), r[i] - r[j])
        scale = abs(y) + np.abs(c * model.lift(x)).sum()
        assert abs(c @ model.lift(x) - y) <= 1e-12 * scale


def test_relation_holds_on_both_sheets_only():
    rng = np.random.default_rng(1)
    p = rng.uniform(-2, 2, 3)
    r = _ranges(p)
    d = r[2] - r[5]
    assert abs(relation_residual(ROOM, 2, 5, d, p)) < 1e-9
    assert abs(relation_residual(ROOM, 2, 5, -d, p)) < 1e-9  # the mirrored sheet
    assert abs(relation_residual(ROOM, 2, 5, d + 0.3, p)) > 1e-2


def test_rows_prescribe_the_lift_propagated_exactly():
    """z(t) from the exact held-input map equals lift(x(t)), so rows stay exact along a flight."""
    model = TdoaImmersion(ROOM)
    step = HeldInputDiscretization(model.immersion, 0.05)
    x = np.array([0.5, -1.0, 1.2, 0.3, 0.2, -0.1])
    z = model.lift(x)
    u = np.array([0.4, -0.2, 0.1])
    for _ in range(40):
        z = step.predict(z, u)
        x = np.concatenate([x[:3] + 0.05 * x[3:] + 0.5 * 0.05**2 * u, x[3:] + 0.05 * u])
    np.testing.assert_allclose(z, model.lift(x), rtol=1e-10, atol=1e-10)


def test_relation_variance_matches_monte_carlo():
    rng = np.random.default_rng(2)
    p = np.array([1.0, -0.5, 1.4])
    r = _ranges(p)
    sigma = 0.1
    for i, j in ((0, 6), (3, 4), (1, 2)):
        d = r[i] - r[j]
        noise = sigma * rng.standard_normal(20_000)
        samples = np.array([relation_residual(ROOM, i, j, d + n, p) for n in noise])
        expected = relation_variance(d, r[i], r[j], sigma)
        assert np.var(samples) == pytest.approx(expected, rel=0.05)


def test_lifted_covariance_matches_monte_carlo():
    rng = np.random.default_rng(3)
    model = TdoaImmersion(ROOM[:4, :2])
    x0 = np.array([1.0, -2.0, 0.3, 0.1])
    Px = np.diag([0.5, 0.2, 0.1, 0.05])
    X = rng.multivariate_normal(x0, Px, size=400_000)
    Z = model.lift(X)
    P = lifted_covariance(model.immersion.aux_forms, x0, Px)
    np.testing.assert_allclose(P, np.cov(Z.T), rtol=0.03, atol=0.01 * np.abs(P).max())


def test_bad_anchors_and_pairs_are_refused():
    with pytest.raises(QuadobsError, match="coincide"):
        TdoaImmersion(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]))
    with pytest.raises(QuadobsError, match="m >= 2"):
        TdoaImmersion(np.zeros((1, 3)))
    model = TdoaImmersion(ROOM)
    with pytest.raises(QuadobsError, match="distinct"):
        model.row(3, 3, 0.0)
    with pytest.raises(QuadobsError, match="finite"):
        model.row(0, 1, float("nan"))


def test_lift_jacobian_is_the_derivative_of_the_lift():
    model = TdoaImmersion(ROOM)
    x = np.array([0.4, -1.1, 1.3, 0.2, -0.3, 0.5])
    J = lift_jacobian(model.immersion.aux_forms, x)
    h = 1e-6
    numeric = np.stack(
        [(model.lift(x + h * e) - model.lift(x - h * e)) / (2 * h) for e in np.eye(6)], axis=1
    )
    np.testing.assert_allclose(J, numeric, rtol=1e-7, atol=1e-8)
