"""The compiled observer kernels against the NumPy reference, the batched observer against the single one."""

import numpy as np
import pytest
from conftest import random_system

from quadobs import AugmentedObserver, QuadobsError, immerse, vehicle_system, wind_system
from quadobs.estimators.augmented_batch import BatchAugmentedObserver

pytest.importorskip("numba")


def _systems(rng):
    return {
        "vehicle 3-D, 1 beacon": vehicle_system(3, np.zeros((1, 3))),
        "vehicle 2-D, 3 beacons": vehicle_system(2, 10 * rng.standard_normal((3, 2))),
        "wind 3-D, 2 beacons": wind_system(3, 10 * rng.standard_normal((2, 3))),
        "random n=4, p=2, q=2": random_system(rng, 4, 2, 2),
    }


def _settings(im, seed, **kw):
    rng = np.random.default_rng(seed)
    N = im.dim
    V = rng.standard_normal((N, N))
    return dict(
        V=1e-3 * V @ V.T, W=np.diag(rng.uniform(0.5, 2.0, im.system.q)), P0=10.0, theta=0.3, **kw
    )


def _pair(im, rng, **kw):
    opts = _settings(im, int(rng.integers(1 << 30)), **kw)
    return AugmentedObserver(im, 0.01, backend="numba", **opts), AugmentedObserver(
        im, 0.01, backend="numpy", **opts
    )


@pytest.mark.parametrize(
    "name",
    [
        "vehicle 3-D, 1 beacon",
        "vehicle 2-D, 3 beacons",
        "wind 3-D, 2 beacons",
        "random n=4, p=2, q=2",
    ],
)
def test_compiled_kernel_equals_the_numpy_reference(rng, name):
    """Random inputs and outputs, some missing, and a gate that rejects some: same estimates to rounding."""
    im = immerse(_systems(rng)[name])
    fast, ref = _pair(im, rng, gate=30.0)
    q, p = im.system.q, im.system.p
    for k in range(400):
        u = rng.standard_normal(p)
        y = 3.0 * rng.standard_normal(q)
        y[rng.random(q) < 0.3] = np.nan
        if k % 50 == 7:
            y[:] = 1e4  # an outlier the gate rejects
        fast.step(u, y)
        ref.step(u, y)
        scale = max(1.0, np.abs(ref.P).max())
        np.testing.assert_allclose(
            fast.z, ref.z, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(ref.z).max())
        )
        np.testing.assert_allclose(fast.P, ref.P, rtol=1e-9, atol=1e-11 * scale)
        assert np.array_equal(fast.P, fast.P.T)
        if np.isnan(ref.nis):
            assert np.isnan(fast.nis)
        else:
            assert fast.nis == pytest.approx(ref.nis, rel=1e-8)
    assert (fast.corrections, fast.rejected) == (ref.corrections, ref.rejected)
    assert fast.rejected > 0 and fast.corrections > 0
    assert fast.covariance_trace == pytest.approx(np.trace(fast.P), rel=1e-12)
    assert ref.covariance_trace == pytest.approx(np.trace(ref.P), rel=1e-12)


def test_correct_and_predict_halves_match_the_reference(rng):
    im = immerse(_systems(rng)["vehicle 2-D, 3 beacons"])
    fast, ref = _pair(im, rng)
    y, u = np.array([4.0, np.nan, -2.0]), np.array([0.3, -0.7])
    for obs in (fast, ref):
        obs.correct(y)
        obs.predict(u)
        obs.predict([1.0, 2.0])  # lists are accepted
    np.testing.assert_allclose(fast.z, ref.z, rtol=1e-12)
    np.testing.assert_allclose(fast.P, ref.P, rtol=1e-10, atol=1e-14)


def test_state_can_be_reassigned_and_bad_shapes_are_named(rng):
    im = immerse(vehicle_system(3, np.zeros((1, 3))))
    obs = AugmentedObserver(im, 0.01, backend="numba")
    obs.z = np.arange(9.0)
    obs.P = 2.0 * np.eye(9)
    np.testing.assert_array_equal(obs.x_hat, np.arange(3.0, 9.0))
    assert obs.covariance_trace == 18.0
    with pytest.raises(QuadobsError, match=r"u: expected shape \(3,\)"):
        obs.step(np.zeros(2), np.zeros(1))
    with pytest.raises(QuadobsError, match=r"y: expected shape \(1,\)"):
        obs.step(np.zeros(3), np.zeros(2))
    with pytest.raises(QuadobsError, match="backend"):
        AugmentedObserver(im, 0.01, backend="fortran")


@pytest.mark.parametrize("backend,threads", [("numba", 0), ("numba", 2), ("numpy", 0)])
def test_batched_observer_equals_single_observers(rng, backend, threads):
    """Member b of the batch evolves exactly as a single observer fed the same data."""
    im = immerse(_systems(rng)["wind 3-D, 2 beacons"])
    template = AugmentedObserver(im, 0.01, backend=backend, **_settings(im, 5, gate=50.0))
    B, n, q, p = 5, im.system.n, im.system.q, im.system.p
    x0 = rng.standard_normal((B, n))
    batch = BatchAugmentedObserver(template, B, x0=x0, backend=backend, threads=threads)
    singles = [
        AugmentedObserver(im, 0.01, backend=backend, x0=x0[b], **_settings(im, 5, gate=50.0))
        for b in range(B)
    ]
    for _k in range(150):
        U = rng.standard_normal((B, p))
        Y = 3.0 * rng.standard_normal((B, q))
        Y[rng.random((B, q)) < 0.3] = np.nan
        batch.step(U, Y)
        for b, single in enumerate(singles):
            single.step(U[b], Y[b])
    for b, single in enumerate(singles):
        np.testing.assert_allclose(batch.Z[b], single.z, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(batch.P[b], single.P, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(batch.x_hat[b], single.x_hat, rtol=1e-12, atol=1e-12)
        assert batch.corrections[b] == single.corrections and batch.rejected[b] == single.rejected
        assert batch.covariance_trace[b] == pytest.approx(single.covariance_trace, rel=1e-12)
    assert batch.x_covariance.shape == (B, n, n)
    with pytest.raises(QuadobsError, match=r"U: expected shape \(5, 3\)"):
        batch.step(np.zeros((4, 3)), np.zeros((5, q)))
    batch.close()
    with pytest.raises(QuadobsError, match="batch"):
        BatchAugmentedObserver(template, 0)


def test_step_and_record_equals_step_with_reads(rng):
    """The fused record path writes x_hat and trace(P) before the step and the NIS after it."""
    im = immerse(_systems(rng)["vehicle 2-D, 3 beacons"])
    b = AugmentedObserver(im, 0.01, backend="numba", **_settings(im, 3, gate=30.0))
    a = AugmentedObserver(im, 0.01, backend="numba", **_settings(im, 3, gate=30.0))
    n = im.system.n
    out = np.zeros(n + 3)
    for _k in range(50):
        u, y = rng.standard_normal(2), 3.0 * rng.standard_normal(3)
        y[rng.random(3) < 0.3] = np.nan
        expected = np.concatenate([b.x_hat, [b.covariance_trace]])
        b.step(u, y)
        a.step_and_record(u, y, out)
        np.testing.assert_array_equal(out[: n + 1], expected)
        np.testing.assert_array_equal(out[n + 1], b.nis)
        assert out[n + 2] == b.rejected
        np.testing.assert_array_equal(a.P, b.P)
    with pytest.raises(QuadobsError, match="out: expected a float64 array"):
        a.step_and_record(u, y, np.zeros(n))


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_observers_survive_pickling(rng, backend):
    """A copy made by pickle (as a process pool does) steps on exactly like the original."""
    import pickle

    im = immerse(_systems(rng)["vehicle 2-D, 3 beacons"])
    single = AugmentedObserver(im, 0.01, backend=backend, **_settings(im, 4))
    batch = BatchAugmentedObserver(
        single, 3, x0=rng.standard_normal((3, 4)), backend=backend, threads=2
    )
    for _ in range(5):
        single.step(rng.standard_normal(2), rng.standard_normal(3))
        batch.step(rng.standard_normal((3, 2)), rng.standard_normal((3, 3)))
    single2, batch2 = pickle.loads(pickle.dumps(single)), pickle.loads(pickle.dumps(batch))
    for _ in range(5):
        u, y, U, Y = (
            rng.standard_normal(2),
            rng.standard_normal(3),
            rng.standard_normal((3, 2)),
            rng.standard_normal((3, 3)),
        )
        for obs in (single, single2):
            obs.step(u, y)
        for b in (batch, batch2):
            b.step(U, Y)
    np.testing.assert_array_equal(single2.z, single.z)
    np.testing.assert_array_equal(single2.P, single.P)
    assert (
        single2.corrections == single.corrections
        and single2.covariance_trace == single.covariance_trace
    )
    np.testing.assert_array_equal(batch2.Z, batch.Z)
    np.testing.assert_array_equal(batch2.P, batch.P)
    np.testing.assert_array_equal(batch2.corrections, batch.corrections)
    batch.close()
    batch2.close()
