"""The augmented observer's compiled interface in time against its NumPy reference and closed forms:
the O(N^2) Joseph correction, the prediction over an interval, and that neither allocates."""

import pickle

import numpy as np
import pytest

from quadobs import vehicle_system
from quadobs.core.immersion import immerse
from quadobs.estimators.augmented import AugmentedObserver, default_backend
from quadobs.estimators.augmented_in_time import StateNoise, structurally_nilpotent
from quadobs.estimators.augmented_tuning import state_noise_map

pytestmark = pytest.mark.skipif(default_backend() != "numba", reason="the kernels need Numba")

BEACONS = np.array([[0.0, 0.0, 0.5], [8.0, 0.0, 2.5], [8.0, 6.0, 0.4], [0.0, 6.0, 2.8]])


def _observer(**kw) -> AugmentedObserver:
    """The 3-D double integrator's observer (N = 9) at a moving state, with a full covariance."""
    im = immerse(vehicle_system(3, BEACONS))
    x0 = np.array([2.0, 3.0, 1.2, 0.4, -0.3, 0.1])
    rng = np.random.default_rng(5)
    G = rng.standard_normal((im.dim, im.dim))
    P0 = G @ G.T + 0.5 * np.eye(im.dim)
    return AugmentedObserver(im, 0.01, V=1e-3, W=1.0, P0=P0, x0=x0, **kw)


def _joseph(P, c, r):
    """The textbook Joseph form ``(I - k c^T) P (I - k c^T)^T + r k k^T``, matrix products and all."""
    k = P @ c / (c @ P @ c + r)
    IKC = np.eye(P.shape[0]) - np.outer(k, c)
    return IKC @ P @ IKC.T + r * np.outer(k, k), k


def test_the_scalar_correction_is_the_joseph_form():
    """O(N^2) in place, as the full Joseph form to 1e-12 relative, P exactly symmetric; the NumPy
    reference the same."""
    for compiled in (True, False):
        obs = _observer()
        obs.in_time_compiled = compiled
        assert obs.in_time_compiled is compiled
        z, P, c = obs.z.copy(), obs.P.copy(), obs._C[2]
        yh, r = float(c @ z) + 0.7, 0.3
        P_ref, k = _joseph(P, c, r)
        obs._correct_scalar(2, yh, r)
        scale = np.max(np.abs(P_ref))
        np.testing.assert_allclose(obs.P, P_ref, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(obs.z, z + k * 0.7, rtol=1e-12)
        assert np.array_equal(obs.P, obs.P.T)
        s = c @ P @ c + r
        assert obs.nis == pytest.approx(0.7**2 / s, rel=1e-12)
        assert obs.corrections == 1 and obs.covariance_trace == pytest.approx(np.trace(P_ref))


@pytest.mark.parametrize("compiled", [True, False])
def test_an_ill_conditioned_correction_keeps_the_variance_it_is_given(compiled):
    """A covariance of 1e8 m^2 along a ridge corrected by an output of variance 1e-9: the
    posterior variance of the output is ``r c^T P c / s``, about 1e-9 (the closed form), where
    the expanded sum ``P - k (Pc)^T - (Pc) k^T + s k k^T`` cancels it to 0; likewise for 200
    covariances with eigenvalues from 1e-6 to 1e8 in random axes, each corrected once by one
    of their coordinates (the expanded sum misses it on about a quarter of them), none with
    an eigenvalue below rounding."""
    from quadobs._kernels import in_time

    def correct(z, P, C, h, yh, r):
        if compiled:
            in_time.scalar_correct(z, P, C, h, yh, r, np.inf, np.zeros(4), np.zeros((2, z.size)))
            return
        obs = _observer()
        obs.in_time_compiled = False
        obs._z, obs._P, obs._C, obs._stats = z, P, C, np.zeros(4)
        obs._correct_scalar(h, yh, r)

    P = np.array([[1e8, 1e8 - 1e-2], [1e8 - 1e-2, 1e8]])
    correct(np.zeros(2), P, np.array([[1.0, 0.0]]), 0, 0.0, 1e-9)
    assert P[0, 0] == pytest.approx(1e-9, rel=1e-3)
    rng = np.random.default_rng(1)
    for _ in range(200):
        Q = np.linalg.qr(rng.standard_normal((9, 9)))[0]
        P = Q @ np.diag(np.logspace(-6, 8, 9)) @ Q.T
        P = 0.5 * (P + P.T)
        h = int(rng.integers(9))
        prior = P[h, h]
        correct(np.zeros(9), P, np.eye(9), h, 0.0, 1e-9)
        assert P[h, h] == pytest.approx(1e-9 * prior / (prior + 1e-9), rel=0.5)
        eig = np.linalg.eigvalsh(P)
        assert eig[0] >= -1e-15 * eig[-1]


def test_a_nan_innovation_variance_is_rejected_not_spread():
    """A NIS that is not a number (a range variance of NaN) counts as rejected; z and P stay."""
    from quadobs._kernels import in_time

    z, P = np.ones(3), np.eye(3)
    stats = np.zeros(4)
    in_time.scalar_correct(z, P, np.eye(3), 0, 2.0, np.nan, np.inf, stats, np.zeros((2, 3)))
    assert stats[2] == 1.0 and np.array_equal(z, np.ones(3)) and np.array_equal(P, np.eye(3))


def test_a_gated_scalar_correction_changes_nothing_but_the_count():
    obs = _observer(gate=1.0)
    z, P = obs.z.copy(), obs.P.copy()
    c = obs._C[0]
    obs._correct_scalar(0, float(c @ z) + 1e3, 0.01)
    assert obs.rejected == 1 and obs.corrections == 0 and obs.nis > 1.0
    assert np.array_equal(obs.z, z) and np.array_equal(obs.P, P)


@pytest.mark.parametrize("noise", ["constant", "state"])
def test_the_compiled_prediction_is_the_reference_to_rounding(noise):
    """One interval off the grid, compiled against the two exponentials of the NumPy reference."""
    fast, ref = _observer(), _observer()
    ref.in_time_compiled = False
    if noise == "state":
        Vx = np.diag([0.0, 0.0, 0.0, 0.4, 0.4, 0.9])
        fast.noise_of = state_noise_map(fast.immersion, Vx)
        ref.noise_of = state_noise_map(ref.immersion, Vx)
    u = np.array([0.3, -1.1, 0.6])
    for est in (fast, ref):
        est.hold(u)
        est.predict(0.0237)
    scale = np.max(np.abs(ref.P))
    np.testing.assert_allclose(fast.z, ref.z, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref.z)))
    np.testing.assert_allclose(fast.P, ref.P, rtol=0, atol=1e-12 * scale)
    assert np.array_equal(fast.P, fast.P.T)
    assert fast.covariance_trace == pytest.approx(np.trace(ref.P), rel=1e-12)


def test_two_half_intervals_are_the_grid_step():
    """The held-input map is a semigroup: predicting over dt / 2 twice (compiled, the constant V)
    is the grid's precomputed step over dt (scipy's exponential) to rounding."""
    grid, halves = _observer(), _observer()
    u = np.array([0.8, 0.2, -0.5])
    grid.predict_step(u)
    halves.hold(u)
    halves.predict(0.005)
    halves.predict(0.01)
    np.testing.assert_allclose(halves.z, grid.z, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(halves.P, grid.P, rtol=0, atol=1e-11 * np.max(np.abs(grid.P)))


def test_state_noise_compiled_is_its_call():
    obs = _observer()
    Vx = np.diag([0.0, 0.0, 0.0, 0.4, 0.5, 0.9])
    extra = np.zeros((6, 6))
    extra[3, 4] = extra[4, 3] = 0.05
    noise = state_noise_map(obs.immersion, Vx, extra)
    assert isinstance(noise, StateNoise) and noise.compiled
    V = obs._in_time.noise(obs.z, noise)
    np.testing.assert_allclose(V, noise(obs.z), rtol=1e-14, atol=1e-15)
    extra[3, 4] = extra[4, 3] = -0.02  # read at each call
    np.testing.assert_allclose(
        obs._in_time.noise(obs.z, noise), noise(obs.z), rtol=1e-14, atol=1e-15
    )


def test_neither_kernel_allocates():
    """Numba's runtime counts no allocation in the kernels' bodies over a prediction with the state
    noise and a correction: one per array argument (its unboxing), none besides."""
    from numba.core.runtime import _nrt_python, rtsys

    from quadobs._kernels.in_time import interval_predict, scalar_correct, state_noise

    obs = _observer()
    k, z, P, stats = obs._in_time, obs._z, obs._P, obs._stats
    noise = state_noise_map(obs.immersion, np.eye(6) * 0.2)
    J, V, u = k._J, k._noise, np.array([0.1, 0.2, 0.3])
    calls = (
        (state_noise, (z, noise.L, noise.Vx, k._zero_extra, V, J[0], J[1])),
        (interval_predict, (z, P, u, 0.01, k.A0, k.Au, k.Bz, k.ptr, k.col, V, k._W, k._w, stats)),
        (scalar_correct, (z, P, k.C, 1, 4.0, 0.5, np.inf, stats, k._Pc)),
    )
    for kernel, args in calls:
        kernel(*args)  # compiled (or loaded) before counting
    enabled = _nrt_python.memsys_stats_enabled()
    _nrt_python.memsys_enable_stats()
    try:
        for kernel, args in calls:
            before = rtsys.get_allocation_stats().alloc
            kernel(*args)
            arrays = sum(isinstance(a, np.ndarray) for a in args)
            assert rtsys.get_allocation_stats().alloc - before == arrays, kernel
    finally:
        if not enabled:
            _nrt_python.memsys_disable_stats()
    assert obs.corrections == 2 and np.all(np.isfinite(P))


def test_where_the_kernels_do_not_apply_the_reference_runs():
    """A forgetting factor, or an A(u) whose structure has a cycle: the NumPy path, unchanged results."""
    assert _observer(theta=0.5).in_time_compiled is False
    assert structurally_nilpotent(np.array([[0, 1], [0, 0]])) is True
    assert structurally_nilpotent(np.array([[0, 1], [1, 0]])) is False
    obs = pickle.loads(pickle.dumps(_observer()))
    assert obs.in_time_compiled
    obs.hold(np.zeros(3))
    obs.predict(0.013)
    assert np.all(np.isfinite(obs.P))
