"""Immersions: the IFAC 2021 chain and ACC 2024 Algorithm 1, against closed forms and the papers' examples."""

import numpy as np
import pytest
from conftest import random_nilpotent, random_system
from scipy.integrate import solve_ivp

from quadobs import (
    QuadobsError,
    QuadraticSystem,
    immerse,
    immerse_chain,
    immerse_minimal,
    vehicle_system,
    wind_system,
)
from quadobs.core.immersion import (
    duplication_matrix,
    lifted_input_matrix,
    lifted_state_matrix,
    lyapunov_sequence,
    lyapunov_term,
    observability_rank,
    quadratic_lift,
    stacked_output_matrix,
    vanishing_index,
    vech,
)


def double_integrator(n):
    return vehicle_system(n, np.zeros((1, n)))


# -- [IFAC2021] ------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 3])
def test_paper_sequence_for_the_double_integrator(n):
    """Section 6: C_1 = [[0, I], [I, 0]], C_2 = diag(0, 2I), C_3 = 0."""
    s = double_integrator(n)
    Cs = lyapunov_sequence(s.A, s.C[0], 3)
    I, Z = np.eye(n), np.zeros((n, n))
    np.testing.assert_array_equal(Cs[1], np.block([[Z, I], [I, Z]]))
    np.testing.assert_array_equal(Cs[2], np.block([[Z, Z], [Z, 2 * I]]))
    np.testing.assert_array_equal(Cs[3], np.zeros((2 * n, 2 * n)))
    assert vanishing_index(s.A, s.C[0]) == 3


def test_paper_augmented_matrix_eq15():
    """A(u) of section 6: shift on z, u^T B^T C_i in the last columns, A below."""
    s = double_integrator(3)
    im = immerse_chain(s)
    u = np.array([0.3, -1.2, 2.0])
    Au = im.state_matrix(u)
    expected = np.zeros((9, 9))
    expected[0, 1] = expected[1, 2] = 1.0
    for i, Ci in enumerate(lyapunov_sequence(s.A, s.C[0], 2)):
        expected[i, 3:] = u @ s.B.T @ Ci
    expected[3:, 3:] = s.A
    np.testing.assert_array_equal(Au, expected)
    np.testing.assert_array_equal(im.input_matrix, np.vstack([np.zeros((3, 3)), s.B]))
    np.testing.assert_array_equal(im.output_matrix, [[1, 0, 0, 0, 0, 0, 0, 0, 0]])


@pytest.mark.parametrize("n,index", [(3, 2), (4, 3), (5, 5), (6, 4)])
def test_closed_form_eq7_equals_recursion_eq6(rng, n, index):
    A = random_nilpotent(rng, n, index)
    C = rng.standard_normal((n, n))
    C = C + C.T
    seq = lyapunov_sequence(A, C, 2 * index)
    for i in range(2 * index + 1):
        np.testing.assert_allclose(
            lyapunov_term(A, C, i), seq[i], rtol=1e-9, atol=1e-9 * np.abs(seq[i]).max() + 1e-9
        )


@pytest.mark.parametrize("n,index", [(3, 2), (4, 3), (5, 5)])
def test_vanishing_index_of_nilpotent_matrices(rng, n, index):
    """If A^k = 0 then C_(2k-1) = 0 (section 3); the detected m is the first vanishing index."""
    A = random_nilpotent(rng, n, index)
    C = rng.standard_normal((n, n))
    C = C + C.T
    m = vanishing_index(A, C)
    assert m <= 2 * index - 1
    seq = lyapunov_sequence(A, C, m)
    scale = np.linalg.norm(C, 2) * (2 * np.linalg.norm(A, 2)) ** np.arange(m + 1)
    assert np.linalg.norm(seq[m], 2) <= 1e-9 * scale[m]
    assert np.linalg.norm(seq[m - 1], 2) > 1e-6 * scale[m - 1]


def test_assumption_1_failure_is_a_clear_error():
    A = np.array([[0.0, 1.0], [-1.0, -0.1]])  # damped oscillator: C_k never vanishes
    s = QuadraticSystem(A, [[0.0], [1.0]], np.diag([1.0, 0.0]))
    with pytest.raises(QuadobsError, match=r"Assumption 1 fails.*n\(n\+1\)/2 = 3"):
        immerse_chain(s)
    assert immerse(s).n_aux == 3  # the minimal immersion handles it


def test_chain_refuses_several_outputs():
    s = vehicle_system(2, np.array([[0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(QuadobsError, match="single output"):
        immerse_chain(s)


# -- [ACC2024] ------------------------------------------------------------


def test_duplication_matrix_and_half_vectorisation(rng):
    n = 4
    D = duplication_matrix(n)
    S = rng.standard_normal((n, n))
    S = S + S.T
    np.testing.assert_array_equal(D @ vech(S), S.reshape(-1, order="F"))
    x = rng.standard_normal(n)
    np.testing.assert_allclose(quadratic_lift(x), D.T @ np.kron(x, x))
    # slide example: x^[2] = (x1^2, 2 x1 x2, x2^2)
    np.testing.assert_allclose(quadratic_lift(np.array([2.0, 3.0])), [4.0, 12.0, 9.0])


def test_lifted_dynamics_slide_eq6(rng):
    """d/dt x^[2] = A_bar x^[2] + U_bar(t) x, and y = C_bar x^[2] + D x (slide eqs. 5, 6)."""
    s = random_system(rng, 4, 2, 3)
    x, u = rng.standard_normal(4), rng.standard_normal(2)
    xdot = s.A @ x + s.B @ u
    lhs = 2 * (quadratic_lift(x + 1e-6 * xdot) - quadratic_lift(x - 1e-6 * xdot)) / 4e-6
    # exact derivative of the bilinear lift
    D = duplication_matrix(4)
    exact = D.T @ (np.kron(xdot, x) + np.kron(x, xdot))
    np.testing.assert_allclose(lhs, exact, rtol=1e-6)
    rhs = lifted_state_matrix(s.A) @ quadratic_lift(x) + lifted_input_matrix(s.B @ u) @ x
    np.testing.assert_allclose(exact, rhs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(
        stacked_output_matrix(s) @ quadratic_lift(x) + s.d @ x, s.output(x), rtol=1e-12
    )


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_slide_double_integrator_has_three_auxiliary_states(n):
    im = immerse(double_integrator(n))
    assert im.n_aux == 3
    assert im.naive_aux == n * (2 * n + 1)


def test_slide_alpha_example():
    """x1' = x2, x2' = x1 + 2 x2 + u, y = (x1^2 + x2^2)/2: m = 2 and L^[2] = 4 (L^[0] + L^[1])."""
    s = QuadraticSystem([[0.0, 1.0], [1.0, 2.0]], [[0.0], [1.0]], np.eye(2))
    L = lyapunov_sequence(s.A, s.C[0], 2)
    np.testing.assert_array_equal(L[1], [[0, 2], [2, 4]])
    np.testing.assert_array_equal(L[2], [[4, 8], [8, 20]])
    np.testing.assert_array_equal(L[2], 4 * (L[0] + L[1]))
    im = immerse(s)
    assert im.n_aux == 2 < 3
    # state order (xi_1, xi_0): xi_1' = alpha_1 xi_1 + alpha_0 xi_0 = 4 xi_1 + 4 xi_0; xi_0' = xi_1
    np.testing.assert_allclose(im.aux_dynamics, [[4.0, 4.0], [1.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(im.aux_forms[0], L[1], atol=1e-12)
    np.testing.assert_allclose(im.aux_forms[1], L[0], atol=1e-12)


def test_slide_wind_example():
    """m = 3, xi_2 ~ |v_a + v_w|^2, xi_1 ~ p^T (v_a + v_w), xi_0 ~ (|p|^2, |v_a|^2) up to scaling and basis."""
    s = wind_system(3, np.zeros((1, 3)))
    im = immerse(s)
    assert len(im.block_sizes) == 3
    assert im.block_sizes == (1, 1, 2)  # eq. (12) order: xi_2, xi_1, xi_0
    assert im.n_aux == 4
    I, Z = np.eye(3), np.zeros((3, 3))
    slide = [
        np.block([[Z, Z, Z], [Z, I, I], [Z, I, I]]),  # |v_a + v_w|^2
        np.block([[Z, I, I], [I, Z, Z], [I, Z, Z]]),  # p^T (v_a + v_w)
        np.block([[I, Z, Z], [Z, Z, Z], [Z, Z, Z]]),  # |p|^2
        np.block([[Z, Z, Z], [Z, I, Z], [Z, Z, Z]]),  # |v_a|^2
    ]

    # each block spans the same forms as the slide's (up to scaling and basis)
    def span_equal(ours, theirs):
        a = np.array([vech(L) for L in ours])
        b = np.array([vech(L) for L in theirs])
        r = np.linalg.matrix_rank
        return r(a) == r(b) == r(np.vstack([a, b]))

    assert span_equal(im.aux_forms[0:1], slide[0:1])
    assert span_equal(im.aux_forms[1:2], slide[1:2])
    assert span_equal(im.aux_forms[2:4], slide[2:4])


@pytest.mark.parametrize("n,p,q", [(2, 1, 1), (3, 2, 2), (4, 1, 3), (5, 2, 2), (6, 3, 4)])
def test_minimal_count_equals_observability_rank(rng, n, p, q):
    s = random_system(rng, n, p, q)
    im = immerse_minimal(s)
    rank = observability_rank(lifted_state_matrix(s.A), stacked_output_matrix(s))
    assert im.n_aux == rank <= n * (n + 1) // 2


def test_minimal_count_on_structured_systems(rng):
    """Beacons: the auxiliary count does not grow with the number of beacons."""
    for q in (1, 2, 5, 12):
        im = immerse(vehicle_system(3, rng.standard_normal((q, 3)) * 10))
        assert im.n_aux == 3
        s = im.system
        assert im.n_aux == observability_rank(lifted_state_matrix(s.A), stacked_output_matrix(s))


def test_chain_and_minimal_agree(rng):
    """Single output with C_m = 0: the same auxiliary states in reverse order, similar A(u)."""
    for _ in range(5):
        n = int(rng.integers(2, 6))
        A = random_nilpotent(rng, n, int(rng.integers(2, n + 1)))
        C = rng.standard_normal((n, n))
        s = QuadraticSystem(A, rng.standard_normal((n, 2)), C + C.T)
        ic, im = immerse_chain(s), immerse_minimal(s)
        assert ic.n_aux == im.n_aux
        k = ic.n_aux
        perm = np.r_[np.arange(k)[::-1], np.arange(k, k + n)]
        x, u = rng.standard_normal(n), rng.standard_normal(2)
        np.testing.assert_allclose(ic.lift(x), im.lift(x)[perm], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(
            ic.state_matrix(u), im.state_matrix(u)[np.ix_(perm, perm)], atol=1e-8
        )
        np.testing.assert_allclose(ic.output_matrix, im.output_matrix[:, perm], atol=1e-12)


def test_nothing_to_immerse():
    """All C_h = 0 (linear outputs): no auxiliary state, z = x, C = D."""
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    s = QuadraticSystem(A, [[0.0], [1.0]], np.zeros((1, 2, 2)), [[1.0, 0.0]])
    im = immerse(s)
    assert im.n_aux == 0 and im.block_sizes == ()
    np.testing.assert_array_equal(im.state_matrix([3.0]), A)
    np.testing.assert_array_equal(im.output_matrix, [[1.0, 0.0]])
    np.testing.assert_array_equal(im.lift([1.0, 2.0]), [1.0, 2.0])


# -- the immersion identity ------------------------------------------------------------------


@pytest.mark.parametrize(
    "method,n,p,q",
    [
        ("minimal", 2, 1, 1),
        ("minimal", 3, 2, 1),
        ("minimal", 4, 2, 3),
        ("minimal", 6, 3, 2),
        ("chain", 2, 1, 1),
        ("chain", 3, 2, 1),
        ("chain", 5, 2, 1),
    ],
)
def test_lift_derivative_and_output_identity(rng, method, n, p, q):
    """d/dt lift(x) = A(u) lift(x) + B u and C lift(x) = y, at random states and inputs."""
    if method == "chain":
        A = random_nilpotent(rng, n, n)
        C = rng.standard_normal((n, n))
        s = QuadraticSystem(A, rng.standard_normal((n, p)), C + C.T, rng.standard_normal((1, n)))
    else:
        s = random_system(rng, n, p, q)
    im = immerse(s, method=method)
    for _ in range(10):
        x, u = rng.standard_normal(n), rng.standard_normal(p)
        xdot = s.A @ x + s.B @ u
        zdot = np.concatenate([np.einsum("a,iab,b->i", x, im.aux_forms, xdot), xdot])
        z = im.lift(x)
        scale = np.abs(zdot).max() + np.abs(im.state_matrix(u)).max() * np.abs(z).max()
        np.testing.assert_allclose(
            im.state_matrix(u) @ z + im.input_matrix @ u, zdot, atol=1e-10 * scale
        )
        np.testing.assert_allclose(
            im.output(z), s.output(x), rtol=1e-10, atol=1e-10 * np.abs(s.output(x)).max()
        )
        np.testing.assert_array_equal(im.project(z), x)


def test_lift_follows_the_augmented_system_along_trajectories(rng):
    """Integrate x' = Ax + Bu and z' = A(u) z + B u from lift(x0) with a smooth input: z(t) = lift(x(t))."""
    s = random_system(rng, 4, 2, 3)
    im = immerse(s)
    freq, phase = rng.uniform(0.5, 3.0, 2), rng.uniform(0, 6, 2)

    def u(t):
        return np.sin(freq * t + phase)

    x0 = rng.standard_normal(4)
    sol_x = solve_ivp(
        lambda t, x: s.A @ x + s.B @ u(t), (0, 2), x0, rtol=1e-11, atol=1e-12, dense_output=True
    )
    sol_z = solve_ivp(
        lambda t, z: im.state_matrix(u(t)) @ z + im.input_matrix @ u(t),
        (0, 2),
        im.lift(x0),
        rtol=1e-11,
        atol=1e-12,
        dense_output=True,
    )
    for t in np.linspace(0, 2, 9):
        z_lift = im.lift(sol_x.sol(t))
        np.testing.assert_allclose(
            sol_z.sol(t), z_lift, rtol=1e-7, atol=1e-7 * np.abs(z_lift).max()
        )


def test_lift_and_state_matrix_batch_shapes(rng):
    im = immerse(double_integrator(3))
    x = rng.standard_normal((5, 4, 6))
    assert im.lift(x).shape == (5, 4, 9)
    assert im.project(im.lift(x)).shape == (5, 4, 6)
    u = rng.standard_normal((7, 3))
    A = im.state_matrix(u)
    assert A.shape == (7, 9, 9)
    np.testing.assert_array_equal(A[2], im.state_matrix(u[2]))
    with pytest.raises(QuadobsError, match="expected shape"):
        im.lift(np.zeros(5))


def test_immerse_rejects_unknown_method():
    with pytest.raises(QuadobsError, match="unknown immersion"):
        immerse(double_integrator(2), method="naive")
