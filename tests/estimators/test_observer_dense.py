"""The dense path of the compiled observer's prediction (BLAS products) against the NumPy reference and the sparse path."""

import numpy as np
import pytest
from conftest import random_system

from quadobs import AugmentedObserver, QuadraticSystem, immerse, vehicle_system
from quadobs.core.held_input import HeldInputDiscretization
from quadobs.estimators.augmented import KernelModel
from quadobs.estimators.augmented_batch import BatchAugmentedObserver
from quadobs.studies.bench import _dense_system

kernels = pytest.importorskip("quadobs._kernels.observer")


def _takes_dense_path(obs) -> bool:
    return KernelModel(obs.model, obs._C, obs.R, obs.gate).dense


def _stable(rng, n, p, q, linear=True):
    """:func:`random_system` with ``A`` shifted to stable (the auxiliary count does not change with a shift)."""
    s = random_system(rng, n, p, q, linear)
    shift = np.linalg.eigvals(s.A).real.max() + 0.5
    return QuadraticSystem(s.A - shift * np.eye(n), s.B, s.C, s.d)


def _chain(n):
    """``n`` damped integrators in a chain, the first state squared as output: a sparse ``Phi`` (about half full)."""
    A = np.diag(np.ones(n - 1), 1) - 0.5 * np.eye(n)
    C = np.zeros((1, n, n))
    C[0, 0, 0] = 1.0
    B = np.zeros((n, 1))
    B[-1] = 1.0
    return QuadraticSystem(A, B, C)


def _forced(dense, monkeypatch):
    """A constructor of compiled observers whose prediction takes the dense path (``True``) or the sparse one."""

    def build(*args, **kw):
        with monkeypatch.context() as m:
            m.setattr(kernels, "dense_path", lambda N, nnz: dense)
            return AugmentedObserver(*args, **kw)

    return build


def _run(im, steps, seed, build=AugmentedObserver):
    """The compiled observer and the NumPy reference on data of the system itself (outputs with noise, some
    missing, an outlier every 500 steps for the gate); yields both after every step."""
    rng = np.random.default_rng(seed)
    dt = 0.01
    opts = dict(V=1e-4, W=1e-2, P0=1.0, theta=0.2, gate=30.0)
    fast = build(im, dt, backend="numba", **opts)
    ref = AugmentedObserver(im, dt, backend="numpy", **opts)
    disc = HeldInputDiscretization(im, dt)
    z = im.lift(rng.standard_normal(im.system.n))
    p, q = im.system.p, im.system.q
    for k in range(steps):
        u = np.sin(0.01 * k + np.arange(p)) + 0.3 * rng.standard_normal(p)
        y = im.output(z) + 0.1 * rng.standard_normal(q)
        y[rng.random(q) < 0.3] = np.nan
        if k % 500 == 7:
            y[:] = 1e4
        fast.step(u, y)
        ref.step(u, y)
        z = disc.predict(z, u)
        yield fast, ref


def _assert_agree(fast, ref, rtol):
    scale = np.abs(ref.P).max()
    np.testing.assert_allclose(fast.P, ref.P, rtol=0, atol=rtol * scale)
    np.testing.assert_allclose(fast.z, ref.z, rtol=0, atol=rtol * max(1.0, np.abs(ref.z).max()))
    assert np.array_equal(fast.P, fast.P.T)  # exactly symmetric
    assert fast.covariance_trace == pytest.approx(np.trace(fast.P), rel=1e-13)


def test_dense_path_follows_the_numpy_reference_over_a_long_run():
    """N = 38, a dense transition: 3000 steps with missing outputs and gated outliers agree to 1e-12 of the scale."""
    im = immerse(_dense_system())
    assert im.dim == 38
    for fast, ref in _run(im, 3000, seed=1):
        _assert_agree(fast, ref, 1e-12)
    assert _takes_dense_path(fast)
    assert (fast.corrections, fast.rejected) == (ref.corrections, ref.rejected)
    assert fast.rejected == 6 and fast.corrections > 1500
    assert np.linalg.eigvalsh(fast.P).min() > 0
    assert np.abs(fast.x_hat - ref.x_hat).max() < 1e-12 * max(1.0, np.abs(ref.x_hat).max())


@pytest.mark.parametrize(
    "system,dense",
    [
        (lambda rng: _stable(rng, 3, 1, 1, linear=False), False),  # N = 9, nnz N = 567
        (lambda rng: _stable(rng, 4, 1, 1, linear=False), True),  # N = 14, nnz N = 2184
        (lambda rng: _chain(4), False),  # N = 11, nnz N = 660
        (lambda rng: _chain(6), True),  # N = 17, nnz N = 2346
        (lambda rng: _stable(rng, 4, 2, 3), True),  # several inputs and outputs, linear terms
    ],
)
def test_each_side_of_the_threshold_follows_the_numpy_reference(rng, system, dense):
    """Systems just below and just above the threshold take the path it names, and agree with the reference
    (to 1e-10 of the scale: on the 6-chain, ``cond(P) ~ 2e6``, either path differs from it by 2e-11)."""
    im = immerse(system(rng))
    for fast, ref in _run(im, 1000, seed=2):
        _assert_agree(fast, ref, 1e-10)
    assert _takes_dense_path(fast) is dense
    assert fast.corrections == ref.corrections and fast.rejected == ref.rejected == 2


@pytest.mark.parametrize("name", ["vehicle", "random"])
def test_both_paths_agree_on_the_same_model(rng, monkeypatch, name):
    """Forced onto the other path, the same observer gives the same estimates to rounding, 1e-10 of the scale
    as against the reference (the vehicle's transition has exact zeros, the random one is full)."""
    im = immerse(
        vehicle_system(3, 10 * rng.standard_normal((2, 3)))
        if name == "vehicle"
        else _stable(rng, 4, 1, 2)
    )
    natural = [(f.z.copy(), f.P.copy()) for f, _ in _run(im, 400, seed=3)]
    forced = _run(im, 400, seed=3, build=_forced(name == "vehicle", monkeypatch))
    for (z, P), (fast, _) in zip(natural, forced):
        np.testing.assert_allclose(fast.P, P, rtol=0, atol=1e-10 * np.abs(P).max())
        np.testing.assert_allclose(fast.z, z, rtol=0, atol=1e-10 * max(1.0, np.abs(z).max()))
        assert np.array_equal(fast.P, fast.P.T)
    assert _takes_dense_path(fast) is (name == "random")  # the path it takes unforced


def test_dense_batch_and_block_equal_the_single_step():
    """On the dense path, a batch member and the block kernel give exactly what single steps give."""
    im = immerse(_dense_system())
    rng = np.random.default_rng(4)
    B, m, n = 3, 200, im.system.n
    U = rng.standard_normal((B, m, 1))
    Y = rng.standard_normal((B, m, 1))
    Y[rng.random(Y.shape) < 0.3] = np.nan
    template = AugmentedObserver(im, 0.01, V=1e-4, W=1e-2, P0=1.0)
    assert _takes_dense_path(template)
    x0 = rng.standard_normal((B, n))
    batch = BatchAugmentedObserver(template, B, x0=x0)
    singles = [AugmentedObserver(im, 0.01, V=1e-4, W=1e-2, P0=1.0, x0=x0[b]) for b in range(B)]
    blocks = [AugmentedObserver(im, 0.01, V=1e-4, W=1e-2, P0=1.0, x0=x0[b]) for b in range(B)]
    for k in range(m):
        batch.step(np.ascontiguousarray(U[:, k]), np.ascontiguousarray(Y[:, k]))
        for b in range(B):
            singles[b].step(U[b, k], Y[b, k])
    for b in range(B):
        blocks[b].step_block(U[b], Y[b], np.zeros((m, n + 3)))
        np.testing.assert_array_equal(batch.P[b], singles[b].P)
        np.testing.assert_array_equal(batch.Z[b], singles[b].z)
        np.testing.assert_array_equal(blocks[b].P, singles[b].P)
        np.testing.assert_array_equal(blocks[b].z, singles[b].z)


def test_built_in_scenarios_stay_on_the_sparse_path():
    """The vehicles' and quadrotors' transitions are sparse: their results stay those of the sparse path, to the bit."""
    from quadobs.testbed.factories import augmented_observer
    from quadobs.testbed.scenario import list_scenarios, load_scenario

    names = list(list_scenarios())
    for name in names:
        scenario = load_scenario(name)
        assert not _takes_dense_path(augmented_observer(scenario, np.zeros(scenario.state_dim))), (
            name
        )
    assert len(names) >= 10


def test_dense_path_rule():
    assert not kernels.dense_path(9, 30)  # the 3-D vehicle
    assert not kernels.dense_path(13, 49)  # the 3-D vehicle in wind
    assert kernels.dense_path(38, 1204)
    assert kernels.dense_path(40, 400) and not kernels.dense_path(40, 399)  # a quarter full
    assert kernels.dense_path(10, 100) and not kernels.dense_path(10, 99)  # 1000 multiply-adds
