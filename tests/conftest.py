import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(20211)


def random_nilpotent(rng, n, index=None):
    """A random nilpotent matrix ``T N T^-1`` of nilpotency index ``index`` (default ``n``).

    ``N`` is block diagonal with shift (Jordan) blocks of sizes at most ``index``, one of
    them of size ``index``, and random nonzero superdiagonal entries.
    """
    index = n if index is None else index
    sizes = [index]
    while sum(sizes) < n:
        sizes.append(int(rng.integers(1, min(index, n - sum(sizes)) + 1)))
    N = np.zeros((n, n))
    start = 0
    for size in sizes:
        for i in range(size - 1):
            N[start + i, start + i + 1] = rng.uniform(0.5, 2.0) * rng.choice([-1, 1])
        start += size
    T = rng.standard_normal((n, n)) + n * np.eye(n)
    return T @ N @ np.linalg.inv(T)


def random_system(rng, n, p, q, linear=True):
    from quadobs import QuadraticSystem

    A = rng.standard_normal((n, n)) / np.sqrt(n)
    B = rng.standard_normal((n, p))
    C = rng.standard_normal((q, n, n))
    C = C + C.transpose(0, 2, 1)
    d = rng.standard_normal((q, n)) if linear else None
    return QuadraticSystem(A, B, C, d)
