"""The one held-input discretisation: closed forms of the double integrator, Phi(u) against
the matrix exponential of the augmented system, and the in-place and batched forms."""

import math

import numpy as np
import pytest
import scipy.linalg as sla
from conftest import random_system

from quadobs import HeldInputDiscretization, immerse, vehicle_system
from quadobs.core.held_input import held_input_step, van_loan
from quadobs.estimators.kalman import HeldInputModel


def double_integrator(dim):
    A = np.zeros((2 * dim, 2 * dim))
    A[:dim, dim:] = np.eye(dim)
    B = np.vstack([np.zeros((dim, dim)), np.eye(dim)])
    return A, B


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("dt", [1e-3, 0.05, 2.0])
def test_double_integrator_closed_form(dim, dt):
    """F = [[I, dt I], [0, I]], G = [dt^2/2 I; dt I], Q_V = s2 [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I."""
    A, B = double_integrator(dim)
    s2 = 0.7
    I = np.eye(dim)
    F_cf = np.kron(np.array([[1.0, dt], [0.0, 1.0]]), I)
    G_cf = np.kron(np.array([[dt**2 / 2], [dt]]), I)
    Q_cf = s2 * np.kron(np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), I)
    F, G = held_input_step(A, B, dt)
    np.testing.assert_allclose(F, F_cf, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(G, G_cf, rtol=1e-13, atol=1e-15)
    V = np.zeros_like(A)
    V[dim:, dim:] = s2 * I
    Phi, Q = van_loan(A, V, dt)
    np.testing.assert_allclose(Phi, F_cf, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(Q, Q_cf, rtol=1e-11, atol=1e-15 * dt**3)


@pytest.mark.parametrize("dim", [2, 3])
def test_kalman_model_is_the_core_step_plus_input_noise(rng, dim):
    """HeldInputModel: (F, G) of held_input_step, Q = Q_V + G Sigma_u G^T, with the closed forms."""
    system = vehicle_system(dim, rng.uniform(-5, 5, (2, dim)))
    dt, s2, su = 0.02, 0.3, 0.05
    V = np.zeros((2 * dim, 2 * dim))
    V[dim:, dim:] = s2 * np.eye(dim)
    m = HeldInputModel(system, dt, V=V, input_covariance=su)
    F, G = held_input_step(system.A, system.B, dt)
    assert np.array_equal(m.F, F) and np.array_equal(m.G, G)
    I = np.eye(dim)
    Q_cf = s2 * np.kron(np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), I)
    Q_cf += su * np.kron(np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]]), I)
    np.testing.assert_allclose(m.Q, Q_cf, rtol=1e-11, atol=1e-18)


def test_augmented_x_block_is_the_original_step(rng):
    """The x block of Phi(u) and the x part of g(u) are the original system's (F, G u), for every u."""
    system = vehicle_system(3, rng.uniform(-5, 5, (3, 3)))
    disc = HeldInputDiscretization(immerse(system), 0.05)
    F, G = held_input_step(system.A, system.B, 0.05)
    k = disc.immersion.n_aux
    for u in rng.standard_normal((5, 3)):
        np.testing.assert_allclose(disc.transition(u)[k:, k:], F, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(disc.input_term(u)[k:], G @ u, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("which", ["vehicle", "random"])
def test_transition_against_expm_of_the_augmented_matrix(rng, which):
    """Phi(u) = expm(A(u) dt), g(u) = the input block of expm([[A(u), B_z u], [0, 0]] dt), Q_d(u) = Van Loan at u."""
    im = immerse(
        vehicle_system(2, rng.uniform(-5, 5, (2, 2)))
        if which == "vehicle"
        else random_system(rng, 4, 2, 2)
    )
    dt, theta = 0.1, 0.4
    N, p = im.dim, im.system.p
    V = np.diag(rng.uniform(0, 1, N))
    disc = HeldInputDiscretization(im, dt, V, theta)
    U = 2.0 * rng.standard_normal((6, p))
    for u in U:
        A_u = im.state_matrix(u)
        np.testing.assert_allclose(disc.transition(u), sla.expm(A_u * dt), rtol=1e-10, atol=1e-12)
        big = np.zeros((N + 1, N + 1))
        big[:N, :N] = A_u
        big[:N, N] = im.input_matrix @ u
        np.testing.assert_allclose(
            disc.input_term(u), sla.expm(big * dt)[:N, N], rtol=1e-10, atol=1e-12
        )
        Q_u = van_loan(A_u + 0.5 * theta * np.eye(N), V, dt)[1]
        np.testing.assert_allclose(disc.process_noise(u), Q_u, rtol=1e-9, atol=1e-13)
    # batched calls agree with single ones; the in-place form is the allocating one, bit for bit
    batched = disc.transition(U)
    buf = np.array(disc.transition_constant)
    for i, u in enumerate(U):
        single = disc.transition(u)
        assert disc.transition(u, out=buf) is buf
        assert np.array_equal(buf, single)
        np.testing.assert_allclose(batched[i], single, rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(
            disc.input_term(U)[i], disc.input_term(u), rtol=1e-13, atol=1e-15
        )
        np.testing.assert_allclose(
            disc.process_noise(U)[i], disc.process_noise(u), rtol=1e-13, atol=1e-18
        )
    assert disc.transition(U.reshape(2, 3, p)).shape == (2, 3, N, N)


def test_transition_is_affine_in_u(rng):
    im = immerse(vehicle_system(3, rng.uniform(-5, 5, (2, 3))))
    disc = HeldInputDiscretization(im, 0.05)
    u, v = rng.standard_normal((2, 3))
    a = 0.3
    lhs = disc.transition(a * u + (1 - a) * v)
    rhs = a * disc.transition(u) + (1 - a) * disc.transition(v)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12, atol=1e-14)
    assert not np.allclose(disc.transition(u), disc.transition(v))  # the input does enter


def _nilpotent_blocks():
    """The blocks the interface in time exponentiates: ``[[A(u), B u], [0, 0]] dt`` and Van Loan's
    ``[[-A(u), V], [0, A(u)^T]] dt`` of an immersed vehicle, and a general (non-nilpotent) matrix."""
    im = immerse(vehicle_system(3, np.array([[1.0, 2.0, 3.0], [4.0, -1.0, 0.5], [0.0, 1.0, -2.0]])))
    rng = np.random.default_rng(3)
    u, dt, N = rng.standard_normal(3), 0.013, im.dim
    A = im.state_matrix(u)
    held = np.zeros((N + 1, N + 1))
    held[:N, :N], held[:N, N] = A, im.input_matrix @ u
    V = np.diag(rng.uniform(0.1, 2.0, N))
    loan = np.block([[-A, V], [np.zeros((N, N)), A.T]])
    return [held * dt, loan * dt, rng.standard_normal((5, 5))]


def test_compiled_series_is_the_numpy_reference_bit_for_bit():
    """The compiled series performs the reference's operations in the same order: the same bits;
    a matrix that is not nilpotent is refused by both (then ``expm`` takes over)."""
    pytest.importorskip("numba")
    from quadobs._kernels.held_input import expm_series
    from quadobs.core.held_input import expm_exact, expm_series_numpy

    nilpotent, general = _nilpotent_blocks()[:2], _nilpotent_blocks()[2]
    for M in nilpotent:
        n = M.shape[0]
        out, term, work = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
        assert expm_series(M, out, term, work)
        ref = expm_series_numpy(M)
        assert ref is not None and np.array_equal(out, ref)
        np.testing.assert_allclose(out, sla.expm(M), rtol=1e-12, atol=1e-14)
        assert np.array_equal(expm_exact(M), ref)
    n = general.shape[0]
    assert not expm_series(general, np.empty((n, n)), np.empty((n, n)), np.empty((n, n)))
    assert expm_series_numpy(general) is None
    np.testing.assert_array_equal(expm_exact(general), sla.expm(general))


def test_series_of_a_nilpotent_closed_form():
    """``e^M`` of the shift ``M = c J`` (``J`` ones above the diagonal): ``(e^M)_ab = c^(b-a) / (b-a)!``."""
    from quadobs.core.held_input import expm_exact, expm_series_numpy

    c, n = 0.5, 5
    M = c * np.eye(n, k=1)
    cf = np.array(
        [
            [c ** (b - a) / math.factorial(b - a) if b >= a else 0.0 for b in range(n)]
            for a in range(n)
        ]
    )
    np.testing.assert_allclose(expm_exact(M), cf, rtol=1e-15, atol=0)
    np.testing.assert_allclose(expm_series_numpy(M), cf, rtol=1e-15, atol=0)
