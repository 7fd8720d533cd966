"""The minimal immersion against exact arithmetic (issue 15).

The exact minimal count is the dimension of the smallest space of symmetric matrices that
contains every ``C_h`` and is invariant under ``X -> A^T X + X A`` (the linear terms
``d_h`` need no auxiliary state), computed over GF(p) for two large primes on integer
data. The rank over GF(p) never exceeds the rank over the rationals and equals it unless
``p`` divides some minor; the larger of the two is taken. Each integer system is then
immersed in floating point at several scales of ``A`` (the exact space does not depend on
the scale): the count must be the exact one, the immersion must be exact to rounding,
and :func:`observability_rank` must agree.
"""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from quadobs import (
    QuadobsError,
    QuadraticSystem,
    immerse,
    immerse_chain,
    vehicle_system,
    wind_system,
)
from quadobs.core.immersion import (
    ImmersionError,
    lifted_state_matrix,
    lyapunov_krylov,
    observability_rank,
    stacked_output_matrix,
)

PRIMES = (2**61 - 1, 2**31 - 1)
SCALES = (0.1, 1.0, 10.0, 100.0)


# -- exact count -------------------------------------------------------------------------------


def _exact_count_mod(A, C, p):
    """dim span{L_A^k(C_h)} over GF(p), by incremental row reduction of the vech vectors."""
    n = len(A)
    A = [[int(v) % p for v in row] for row in A]
    pairs = [(i, j) for i in range(n) for j in range(i, n)]
    basis = {}  # pivot column -> reduced row with a 1 at the pivot

    def op(X):
        return [
            [sum(A[k][i] * X[k][j] + X[i][k] * A[k][j] for k in range(n)) % p for j in range(n)]
            for i in range(n)
        ]

    def add(X):
        v = [X[i][j] for i, j in pairs]
        for piv, row in basis.items():
            if v[piv]:
                f = v[piv]
                v = [(a - f * b) % p for a, b in zip(v, row)]
        nz = next((k for k, a in enumerate(v) if a), None)
        if nz is None:
            return False
        inv = pow(v[nz], p - 2, p)
        basis[nz] = [(a * inv) % p for a in v]
        return True

    frontier = []
    for Ch in C:
        X = [[int(v) % p for v in row] for row in Ch]
        if add(X):
            frontier.append(X)
    while frontier:
        Y = op(frontier.pop())
        if add(Y):
            frontier.append(Y)
    return len(basis)


def exact_count(A, C):
    A = np.asarray(A).astype(np.int64).tolist()
    C = np.asarray(C).astype(np.int64).reshape(-1, len(A), len(A)).tolist()
    return max(_exact_count_mod(A, C, p) for p in PRIMES)


def test_exact_count_reference_values():
    """The reference itself: the double integrator (3), the issue's diagonal families (15, 21)."""
    di = vehicle_system(1, np.zeros((1, 1)))
    assert exact_count(di.A, di.C) == 3
    assert exact_count(np.diag([1, 2, 4, 8, 16]), np.ones((5, 5))) == 15
    assert exact_count(np.diag([1, 2, 4, 8, 16, 32]), np.ones((6, 6))) == 21
    assert exact_count(np.diag([1, 1, 2]), np.ones((3, 3))) == 3  # sums 2, 3, 4 (repeated)


# -- checks on a floating-point immersion ------------------------------------------------------------


def assert_exact_immersion(im, s, rng, rtol=1e-9):
    """d/dt lift(x) = A(u) lift(x) + B u and C lift(x) = y at random points, relative to the data."""
    for _ in range(4):
        x, u = rng.standard_normal(s.n), rng.standard_normal(s.p)
        xdot = s.A @ x + s.B @ u
        zdot = np.concatenate([np.einsum("a,iab,b->i", x, im.aux_forms, xdot), xdot])
        z = im.lift(x)
        Au = im.state_matrix(u)
        scale = np.abs(Au).max() * np.abs(z).max() + np.abs(im.input_matrix).max() * np.abs(u).max()
        assert np.abs(Au @ z + im.input_matrix @ u - zdot).max() <= rtol * scale
        y = s.output(x)
        yscale = np.abs(im.output_matrix).max() * np.abs(z).max()
        assert np.abs(im.output(z) - y).max() <= rtol * yscale
    # the auxiliary coordinates are well scaled: a power basis is kept only when well
    # conditioned, the Arnoldi basis has ||L_i||_F = 1
    norms = np.linalg.norm(im.aux_forms.reshape(im.n_aux, -1), axis=1)
    if im.n_aux:
        assert norms.max() / norms.min() <= 1e6 * (1 + 0 * norms.max())


def check_system(A, B, C, d, rng, scales=SCALES):
    expected = exact_count(A, C)
    for scale in scales:
        s = QuadraticSystem(scale * np.asarray(A, dtype=float), B, C, d)
        im = immerse(s)
        assert im.n_aux == expected, (scale, im.n_aux, expected)
        assert sum(im.block_sizes) == expected
        assert observability_rank(lifted_state_matrix(s.A), stacked_output_matrix(s)) == expected
        assert_exact_immersion(im, s, rng)
    return expected


# -- integer systems ------------------------------------------------------------------------------


def _symmetric(draw, n, lo=-3, hi=3):
    M = np.array(draw(st.lists(st.integers(lo, hi), min_size=n * n, max_size=n * n))).reshape(n, n)
    return M + M.T


@st.composite
def integer_systems(draw):
    kind = draw(
        st.sampled_from(["random", "nilpotent", "diagonal-spread", "diagonal-repeated", "sparse"])
    )
    n = draw(st.integers(2, 6))
    if kind == "random":
        A = np.array(draw(st.lists(st.integers(-3, 3), min_size=n * n, max_size=n * n))).reshape(
            n, n
        )
    elif kind == "nilpotent":
        # T N T^-1 with N strictly upper triangular and T unimodular (integer inverse),
        # conjugated by a permutation
        N = np.triu(
            np.array(draw(st.lists(st.integers(-2, 2), min_size=n * n, max_size=n * n))).reshape(
                n, n
            ),
            1,
        )
        U = np.triu(
            np.array(draw(st.lists(st.integers(-1, 1), min_size=n * n, max_size=n * n))).reshape(
                n, n
            ),
            1,
        )
        T = np.eye(n, dtype=np.int64) + U
        Ti = np.rint(np.linalg.inv(T)).astype(np.int64)
        perm = np.array(draw(st.permutations(range(n))))
        A = (T @ N @ Ti)[np.ix_(perm, perm)]
    elif kind == "diagonal-spread":
        A = np.diag(
            np.array(
                draw(
                    st.lists(
                        st.sampled_from([-8, -3, 0, 1, 2, 4, 8, 16, 32]), min_size=n, max_size=n
                    )
                )
            )
        )
    elif kind == "diagonal-repeated":
        A = np.diag(np.array(draw(st.lists(st.integers(-2, 2), min_size=n, max_size=n))))
        # a similarity with a unimodular matrix keeps the spectrum and makes A dense
        U = np.triu(
            np.array(draw(st.lists(st.integers(-1, 1), min_size=n * n, max_size=n * n))).reshape(
                n, n
            ),
            1,
        )
        T = np.eye(n, dtype=np.int64) + U
        A = T @ A @ np.rint(np.linalg.inv(T)).astype(np.int64)
    else:
        A = np.array(
            draw(
                st.lists(
                    st.sampled_from([0, 0, 0, 0, -5, -1, 1, 3, 7]), min_size=n * n, max_size=n * n
                )
            )
        ).reshape(n, n)
    q = draw(st.integers(1, 3))
    C = [_symmetric(draw, n) for _ in range(q)]
    if q >= 2 and draw(st.booleans()):  # a dependent output
        a, b = draw(st.integers(-2, 2)), draw(st.integers(-2, 2))
        C.append(a * C[0] + b * C[1])
    C = np.array(C)
    for h in range(C.shape[0]):
        if not C[h].any():
            C[h, 0, 0] = 1
    d = np.array(
        draw(st.lists(st.integers(-2, 2), min_size=C.shape[0] * n, max_size=C.shape[0] * n))
    ).reshape(-1, n)
    B = np.array(draw(st.lists(st.integers(-2, 2), min_size=n, max_size=n)), dtype=float).reshape(
        n, 1
    ) + np.eye(n, 1)
    return kind, A.astype(np.int64), B, C.astype(np.int64), d.astype(float)


@settings(
    max_examples=60, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(integer_systems())
def test_minimal_count_is_exact_at_every_scale(case):
    kind, A, B, C, d = case
    check_system(A, B, C, d, np.random.default_rng(0))


@settings(
    max_examples=25, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(integer_systems(), st.sampled_from([1e-3, 1e-6, 1e-12]), st.sampled_from(SCALES))
def test_other_tolerances_give_the_exact_count_or_refuse(case, rtol, scale):
    """No rtol produces a wrong count: immerse either certifies the exact one or refuses."""
    kind, A, B, C, d = case
    s = QuadraticSystem(scale * A.astype(float), B, C, d)
    try:
        im = immerse(s, rtol=rtol)
    except ImmersionError as exc:
        assert "\n" not in str(exc) and "try" not in str(exc)
        return
    assert im.n_aux == exact_count(A, C)


@pytest.mark.parametrize("diag,expected", [([1, 2, 4, 8, 16], 15), ([1, 2, 4, 8, 16, 32], 21)])
def test_issue_diagonal_families(diag, expected):
    """A = diag(1, 2, 4, ...), B = 1, C = ones: every sum lambda_i + lambda_j is distinct."""
    n = len(diag)
    got = check_system(
        np.diag(diag),
        np.ones((n, 1)),
        np.ones((1, n, n), dtype=np.int64),
        None,
        np.random.default_rng(1),
    )
    assert got == expected


def test_issue_generic_system_does_not_depend_on_the_scale_of_A():
    """A generic 6-state system: 21 at ||A|| = 1.3 and at ||A|| = 13 (L_{sA} = s L_A), whatever the scale of C."""
    rng = np.random.default_rng(7)
    A = rng.standard_normal((6, 6))
    A *= 1.3 / np.linalg.norm(A, 2)
    C = rng.standard_normal((6, 6))
    C = C + C.T
    for a in (1.0, 10.0, 1e3):
        for c in (1e-6, 1.0, 1e6):
            s = QuadraticSystem(a * A, rng.standard_normal((6, 1)), c * C)
            im = immerse(s)
            assert im.n_aux == 21
            assert_exact_immersion(im, s, rng)


@pytest.mark.parametrize(
    "system,expected",
    [
        (vehicle_system(3, np.array([[0.0, 0.0, 0.0]])), 3),
        (wind_system(3, np.zeros((1, 3))), 4),
        (
            vehicle_system(
                3, np.array([[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0], [5.0, 5.0, 5.0]])
            ),
            3,
        ),
        (QuadraticSystem([[0.0, 1.0], [1.0, 2.0]], [[0.0], [1.0]], np.eye(2)), 2),
    ],
    ids=["vehicle", "wind", "beacons", "slide"],
)
def test_examples_keep_their_counts(system, expected):
    assert exact_count(system.A.astype(int), system.C.astype(int)) == expected
    for scale in SCALES:
        s = QuadraticSystem(scale * system.A, system.B, system.C, system.d)
        assert immerse(s).n_aux == expected
        assert observability_rank(lifted_state_matrix(s.A), stacked_output_matrix(s)) == expected


def test_near_degenerate_system_is_refused():
    """Eigenvalue sums 1e-8 apart: the count cannot be certified, and the error says why in one line."""
    s = QuadraticSystem(np.diag([0.0, 1.0, 1.0 + 1e-8]), np.ones((3, 1)), np.ones((3, 3)))
    with pytest.raises(
        ImmersionError, match=r"^system: the minimal auxiliary count cannot be certified"
    ) as info:
        immerse(s)
    msg = str(info.value)
    assert "\n" not in msg and "try" not in msg
    assert isinstance(info.value, QuadobsError)
    # the same system with the sums well apart is certified
    assert (
        immerse(QuadraticSystem(np.diag([0.0, 1.0, 1.5]), np.ones((3, 1)), np.ones((3, 3)))).n_aux
        == 6
    )


def test_ill_conditioned_power_basis_switches_to_orthonormal():
    """diag(1..16): the power basis spans many orders of magnitude; the returned forms are orthonormal."""
    s = QuadraticSystem(np.diag([1.0, 2.0, 4.0, 8.0, 16.0]), np.ones((5, 1)), np.ones((5, 5)))
    im = immerse(s)
    G = im.aux_forms.reshape(im.n_aux, -1)
    np.testing.assert_allclose(G @ G.T, np.eye(im.n_aux), atol=1e-12)
    assert np.abs(im.lift(np.ones(5) / np.sqrt(5))[: im.n_aux]).max() <= 0.5 + 1e-12
    assert im.block_sizes == lyapunov_krylov(s.A, s.C).sizes[::-1]


def test_chain_is_certified():
    """A 3x3 shift with A[2, 0] = eps: the chain (m = 5) where eps = 0, refused where eps is near the tolerance."""

    def system(eps):
        A = np.diag([1.0, 1.0], 1)
        A[2, 0] = eps
        return QuadraticSystem(A, [[0.0], [0.0], [1.0]], np.diag([1.0, 0.0, 0.0]))

    assert immerse_chain(system(0.0)).n_aux == immerse(system(0.0)).n_aux == 5
    for eps in (1e-8, 1e-7):  # the sixth direction has relative size ~1.15 eps: ambiguous
        with pytest.raises(ImmersionError, match="cannot be certified"):
            immerse(system(eps))
        with pytest.raises(QuadobsError):
            immerse_chain(system(eps))
    # 1e-12: within the tolerance of the nilpotent system, whose count (5) is certified
    assert immerse(system(1e-12)).n_aux == 5
    assert immerse(system(1e-3)).n_aux == 6
