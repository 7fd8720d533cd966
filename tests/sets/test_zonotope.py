"""Zonotope calculus against independent computations: linear programs, brute-force vertex
enumeration, scipy's convex hulls, and points sampled from the exact sets."""

from itertools import product

import numpy as np
import pytest
from scipy.optimize import linprog
from scipy.spatial import ConvexHull

from quadobs import QuadobsError
from quadobs.estimators.zonotopic import segment_gain, volume_gain, volume_gain_terms
from quadobs.sets.zonotope import (
    REDUCTION_METHODS,
    IntervalMatrix,
    Zonotope,
    interval_image,
    interval_zonotope,
    reduce_generators,
)


def random_zonotope(rng, n, m):
    return Zonotope(rng.standard_normal(n), rng.standard_normal((n, m)))


def sample_points(rng, Z, k=300):
    """Points of Z: random interior points and exact vertices (sign vectors)."""
    z = rng.uniform(-1, 1, (k, Z.order))
    z[: k // 2] = np.sign(z[: k // 2])
    return Z.center + z @ Z.generators.T


def lp_support(Z, d, extra_ub=None):
    """max d^T (p + H z) over z in B^m (plus optional linear constraints on z), by linprog."""
    A_ub, b_ub = (None, None) if extra_ub is None else extra_ub
    res = linprog(
        -(Z.generators.T @ d), A_ub=A_ub, b_ub=b_ub, bounds=[(-1, 1)] * Z.order, method="highs"
    )
    assert res.status == 0
    return d @ Z.center - res.fun


def brute_p_radius(Z, P):
    best = 0.0
    for s in product((-1.0, 1.0), repeat=Z.order):
        v = Z.generators @ np.array(s)
        best = max(best, v @ P @ v)
    return best


@pytest.mark.parametrize("n,m", [(2, 5), (3, 6)])
def test_support_function_against_linear_programs(rng, n, m):
    Z = random_zonotope(rng, n, m)
    for d in rng.standard_normal((20, n)):
        assert Z.support(d) == pytest.approx(lp_support(Z, d), rel=1e-9, abs=1e-9)
    D = rng.standard_normal((7, n))
    np.testing.assert_allclose(Z.support(D), [Z.support(d) for d in D])


@pytest.mark.parametrize("n", [2, 3])
def test_minkowski_sum_and_linear_map(rng, n):
    Z1, Z2 = random_zonotope(rng, n, 4), random_zonotope(rng, n, 3)
    S = Z1 + Z2
    for d in rng.standard_normal((10, n)):
        assert S.support(d) == pytest.approx(lp_support(Z1, d) + lp_support(Z2, d), rel=1e-9)
    K = rng.standard_normal((n, n))
    KZ = K @ Z1
    pts = sample_points(rng, Z1)
    assert KZ.contains(pts @ K.T).all()
    for d in rng.standard_normal((10, n)):
        assert KZ.support(d) == pytest.approx(lp_support(Z1, K.T @ d), rel=1e-9)
    assert (Z1 + np.ones(n)).center == pytest.approx(Z1.center + 1)


@pytest.mark.parametrize("n", [2, 3])
def test_interval_hull_and_f_radius(rng, n):
    Z = random_zonotope(rng, n, 6)
    hull = Z.interval_hull()
    for i in range(n):
        e = np.eye(n)[i]
        assert hull[i, 1] == pytest.approx(lp_support(Z, e))
        assert hull[i, 0] == pytest.approx(-lp_support(Z, -e))
    np.testing.assert_allclose(Z.widths(), hull[:, 1] - hull[:, 0])
    assert Z.f_radius() == pytest.approx(np.sqrt((Z.generators**2).sum()))


@pytest.mark.parametrize("n,m", [(2, 7), (3, 6)])
def test_volume_and_vertices_against_convex_hull(rng, n, m):
    for _ in range(3):
        Z = random_zonotope(rng, n, m)
        # exact points of Z including every vertex: all 2^m sign vectors
        signs = np.array(list(product((-1.0, 1.0), repeat=m)))
        hull = ConvexHull(Z.center + signs @ Z.generators.T)
        assert Z.volume() == pytest.approx(hull.volume, rel=1e-9)
        cand = Z.vertex_candidates()
        assert ConvexHull(cand).volume == pytest.approx(hull.volume, rel=1e-9)
        if n == 2:
            V = Z.vertices()
            assert len(V) == 2 * m
            x, y = V[:, 0], V[:, 1]
            signed_area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
            assert signed_area == pytest.approx(
                hull.volume, rel=1e-9
            )  # counter-clockwise, same area
            assert len(hull.vertices) == 2 * m


@pytest.mark.parametrize("n,m", [(2, 6), (3, 5)])
def test_p_radius_against_sign_enumeration(rng, n, m):
    for _ in range(3):
        Z = random_zonotope(rng, n, m)
        R = rng.standard_normal((n, n))
        P = R @ R.T + 0.1 * np.eye(n)
        assert Z.p_radius(P) == pytest.approx(brute_p_radius(Z, P), rel=1e-10)
    assert Z.p_radius() == pytest.approx(brute_p_radius(Z, np.eye(n)), rel=1e-10)


@pytest.mark.parametrize("n,m", [(2, 6), (3, 7)])
def test_contains_halfspaces_agree_with_linear_programs(rng, n, m):
    Z = random_zonotope(rng, n, m)
    pts = Z.center + 1.5 * rng.standard_normal((200, n)) * np.abs(Z.generators).sum(axis=1) / 2
    a = Z.contains(pts, method="halfspace")
    b = Z.contains(pts, method="lp")
    assert 20 < a.sum() < 190
    np.testing.assert_array_equal(a, b)
    assert Z.contains(sample_points(rng, Z)).all()
    assert not Z.contains(Z.center + 1.01 * (Z.vertex_candidates()[0] - Z.center))


@pytest.mark.parametrize("method", [*REDUCTION_METHODS, "callable"])
@pytest.mark.parametrize("n,m,s", [(2, 12, 5), (3, 14, 7)])
def test_order_reduction_contains_the_original(rng, method, n, m, s):
    def halve(H, s):  # a user reduction: box everything
        return np.diag(np.abs(H).sum(axis=1))

    fn = halve if method == "callable" else method
    for _ in range(3):
        Z = random_zonotope(rng, n, m)
        R = Z.reduce(s, fn)
        assert R.order <= s
        assert R.contains(Z.vertex_candidates()).all()
        D = rng.standard_normal((200, n))
        assert np.all(R.support(D) >= Z.support(D) - 1e-9)
    assert Z.reduce(m) is Z


def test_property3_keeps_the_longest_generators(rng):
    H = rng.standard_normal((2, 10))
    out = reduce_generators(H, 5, "combastel")
    longest = H[:, np.argsort(-np.linalg.norm(H, axis=0))[:3]]
    np.testing.assert_array_equal(out[:, :3], longest)
    rest = H[:, np.argsort(-np.linalg.norm(H, axis=0))[3:]]
    np.testing.assert_allclose(out[:, 3:], np.diag(np.abs(rest).sum(axis=1)))


def test_interval_matrix_vertices_and_property5(rng):
    M = IntervalMatrix.from_mid_rad(
        rng.standard_normal((2, 3)), np.array([[0.1, 0, 0.2], [0, 0.3, 0]])
    )
    V = M.vertices()
    assert V.shape == (8, 2, 3)
    assert all(M.contains(v) for v in V)
    assert len({tuple(v.ravel()) for v in V}) == 8
    N = rng.standard_normal((3, 4))
    MN = M @ N
    for _ in range(200):
        A = M.lower + rng.uniform(0, 1, M.shape) * (M.upper - M.lower)
        assert MN.contains(A @ N, tol=1e-12)
    for A in V:
        assert MN.contains(A @ N, tol=1e-12)


@pytest.mark.parametrize("n", [2, 3])
def test_property4_interval_zonotope_contains_the_family(rng, n):
    M = IntervalMatrix.from_mid_rad(rng.standard_normal((n, 4)), 0.3 * rng.uniform(0, 1, (n, 4)))
    p = rng.standard_normal(n)
    Zo = interval_zonotope(p, M)
    pts = []
    for _ in range(100):
        A = M.lower + rng.uniform(0, 1, M.shape) * (M.upper - M.lower)
        z = np.sign(rng.uniform(-1, 1, 4))
        pts.append(p + A @ z)
    for A in M.vertices()[:: max(1, len(M.vertices()) // 64)]:
        pts.append(p + A @ np.sign(rng.uniform(-1, 1, 4)))
    assert Zo.contains(np.array(pts)).all()


@pytest.mark.parametrize("n", [2, 3])
def test_uncertain_image_contains_every_image(rng, n):
    A = IntervalMatrix.from_mid_rad(
        rng.standard_normal((n, n)),
        0.2 * rng.uniform(0, 1, (n, n)) * (rng.uniform(size=(n, n)) < 0.5),
    )
    Z = random_zonotope(rng, n, 4)
    out = interval_image(A, Z)
    pts = sample_points(rng, Z, 100)
    verts = A.vertices()
    images = [pts @ G.T for G in verts] + [
        pts @ (A.lower + rng.uniform(0, 1, A.shape) * (A.upper - A.lower)).T for _ in range(20)
    ]
    assert out.contains(np.vstack(images)).all()


@pytest.mark.parametrize("n", [2, 3])
def test_property6_family_contains_the_intersection(rng, n):
    Z = random_zonotope(rng, n, 5)
    c = rng.standard_normal(n)
    y = float(c @ Z.center + 0.5 * rng.standard_normal())
    phi = 0.4
    # exact points of Z ∩ S: sampled points of Z that satisfy the strip
    pts = sample_points(rng, Z, 4000)
    pts = pts[np.abs(pts @ c - y) <= phi]
    assert len(pts) > 20
    lams = [rng.standard_normal(n) for _ in range(5)] + [
        segment_gain(Z, c, phi),
        volume_gain(Z, c, phi),
        np.zeros(n),
    ]
    for lam in lams:
        Zl = Z.strip_intersection(c, y, phi, lam)
        assert Zl.contains(pts).all()
        # support of the exact intersection (linear program) is dominated by the family member's
        Hc = Z.generators.T @ c
        ub = (np.vstack([Hc, -Hc]), np.array([y - c @ Z.center + phi, -(y - c @ Z.center - phi)]))
        for d in rng.standard_normal((5, n)):
            assert lp_support(Z, d, ub) <= Zl.support(d) + 1e-9


@pytest.mark.parametrize("n", [2, 3])
def test_volume_gain_formula_and_optimality(rng, n):
    Z = random_zonotope(rng, n, 5)
    c, phi, y = rng.standard_normal(n), 0.3, 0.1
    a, G = volume_gain_terms(Z.generators, c)
    for lam in rng.standard_normal((5, n)):
        direct = Z.strip_intersection(c, y, phi, lam).volume()
        formula = 2.0**n * (a * abs(1 - c @ lam) + phi * np.abs(G @ lam).sum())
        assert formula == pytest.approx(direct, rel=1e-9)
    best = Z.strip_intersection(c, y, phi, volume_gain(Z, c, phi)).volume()
    seg = segment_gain(Z, c, phi)
    for lam in [seg, *(seg + 0.2 * rng.standard_normal((30, n)))]:
        assert best <= Z.strip_intersection(c, y, phi, lam).volume() * (1 + 1e-9)
    # segment gain minimises the F-radius
    f_best = Z.strip_intersection(c, y, phi, seg).f_radius()
    for lam in seg + 0.1 * rng.standard_normal((30, n)):
        assert f_best <= Z.strip_intersection(c, y, phi, lam).f_radius() + 1e-12


def test_bad_input_is_refused():
    with pytest.raises(QuadobsError, match="generators"):
        Zonotope(np.zeros(2), np.zeros((3, 2)))
    with pytest.raises(QuadobsError, match="non-finite"):
        Zonotope(np.array([0.0, np.nan]), np.eye(2))
    with pytest.raises(QuadobsError, match="below the lower"):
        IntervalMatrix(np.ones((2, 2)), np.zeros((2, 2)))
    with pytest.raises(QuadobsError, match="max_generators"):
        Zonotope(np.zeros(3), np.ones((3, 5))).reduce(2)
    with pytest.raises(QuadobsError, match="unknown reduction"):
        Zonotope(np.zeros(2), np.ones((2, 5))).reduce(3, "nope")
    with pytest.raises(QuadobsError, match="phi"):
        Zonotope(np.zeros(2), np.eye(2)).strip_intersection([1, 0], 0.0, -1.0, [0, 0])
    with pytest.raises(QuadobsError, match="plane"):
        Zonotope(np.zeros(3), np.eye(3)).vertices()
    Z = Zonotope(np.zeros(2), np.eye(2))
    assert Z.generators.flags.writeable is False
    assert Zonotope(np.zeros(2), np.zeros((2, 0))).order == 0


@pytest.mark.parametrize("n", [2, 4])
def test_strip_update_is_property6_and_the_segment_gain_by_default(rng, n):
    """strip_update (raw arrays) is Zonotope.strip_intersection bit for bit; lam=None is the segment gain."""
    from quadobs.sets.zonotope import segment_gain as raw_segment_gain
    from quadobs.sets.zonotope import strip_update

    Z = random_zonotope(rng, n, 6)
    c, y, phi = rng.standard_normal(n), 0.2, 0.3
    lam = rng.standard_normal(n)
    p_new, H_new = strip_update(Z.center, Z.generators, c, y, phi, lam)
    Zl = Z.strip_intersection(c, y, phi, lam)
    assert np.array_equal(p_new, Zl.center) and np.array_equal(H_new, Zl.generators)
    # closed form of Property 6
    np.testing.assert_allclose(p_new, Z.center + lam * (y - c @ Z.center), rtol=1e-14)
    np.testing.assert_allclose(
        H_new,
        np.column_stack([(np.eye(n) - np.outer(lam, c)) @ Z.generators, phi * lam]),
        rtol=1e-12,
        atol=1e-14,
    )
    # default gain: H g / (g^T g + phi^2), g = H^T c, the same as the estimators' segment gain
    seg = raw_segment_gain(Z.generators, c, phi)
    g = Z.generators.T @ c
    np.testing.assert_allclose(seg, Z.generators @ g / (g @ g + phi**2), rtol=1e-14)
    np.testing.assert_allclose(segment_gain(Z, c, phi), seg, rtol=0, atol=0)
    p_d, H_d = strip_update(Z.center, Z.generators, c, y, phi)
    p_s, H_s = strip_update(Z.center, Z.generators, c, y, phi, seg)
    assert np.array_equal(p_d, p_s) and np.array_equal(H_d, H_s)
    assert (
        Z.strip_intersection(c, y, phi).f_radius()
        == Z.strip_intersection(c, y, phi, seg).f_radius()
    )
    # a degenerate set with an exact output: zero gain, the set unchanged but for a zero generator
    Zp = Zonotope(np.zeros(n), np.zeros((n, 1)))
    assert np.array_equal(raw_segment_gain(Zp.generators, c, 0.0), np.zeros(n))
