"""QuadraticSystem validation and the vehicle systems."""

import numpy as np
import pytest

from quadobs import QuadobsError, QuadraticSystem, range_outputs, vehicle_system, wind_system


def test_shapes_and_output(rng):
    A = rng.standard_normal((3, 3))
    C = rng.standard_normal((2, 3, 3))
    C = C + C.transpose(0, 2, 1)
    d = rng.standard_normal((2, 3))
    s = QuadraticSystem(A, rng.standard_normal((3, 1)), C, d)
    assert (s.n, s.p, s.q) == (3, 1, 2)
    x = rng.standard_normal(3)
    np.testing.assert_allclose(s.output(x), [0.5 * x @ C[h] @ x + d[h] @ x for h in range(2)])
    assert s.output(rng.standard_normal((4, 5, 3))).shape == (4, 5, 2)
    with pytest.raises(ValueError):
        s.A[0, 0] = 1.0  # frozen arrays


def test_single_output_shorthand():
    s = QuadraticSystem(np.zeros((2, 2)), [1.0, 0.0], np.eye(2), [0.0, 1.0])
    assert s.C.shape == (1, 2, 2) and s.d.shape == (1, 2) and s.B.shape == (2, 1)


def test_non_symmetric_output_is_refused_or_symmetrised():
    C = np.array([[1.0, 2.0], [0.0, 1.0]])
    with pytest.raises(QuadobsError, match=r"C\[0\]: output matrix is not symmetric"):
        QuadraticSystem(np.zeros((2, 2)), np.zeros((2, 1)), C)
    s = QuadraticSystem(np.zeros((2, 2)), np.zeros((2, 1)), C, symmetrize=True)
    np.testing.assert_array_equal(s.C[0], [[1.0, 1.0], [1.0, 1.0]])
    x = np.array([0.3, -0.7])
    assert s.output(x)[0] == pytest.approx(0.5 * x @ C @ x)


@pytest.mark.parametrize(
    "args,match",
    [
        ((np.zeros((2, 3)), np.zeros((2, 1)), np.eye(2)), "A: expected a non-empty square matrix"),
        ((np.zeros((2, 2)), np.zeros((3, 1)), np.eye(2)), r"B: expected shape \(2, p\)"),
        ((np.zeros((2, 2)), np.zeros((2, 1)), np.eye(3)), r"C: expected shape \(q, 2, 2\)"),
        ((np.zeros((2, 2)), np.zeros((2, 1)), np.zeros((0, 2, 2))), "no outputs"),
        ((np.zeros((2, 2)), np.zeros((2, 1)), np.zeros((1, 2, 2))), "identically zero"),
        (
            (np.array([[np.inf, 0], [0, 0]]), np.zeros((2, 1)), np.eye(2)),
            "A: holds a non-finite value",
        ),
        (
            (np.zeros((2, 2)), np.zeros((2, 1)), np.eye(2), np.zeros((2, 2))),
            r"d: expected shape \(1, 2\)",
        ),
        ((np.zeros((2, 2)), "abc", np.eye(2)), "B: expected a numeric array"),
    ],
)
def test_bad_systems_are_named(args, match):
    with pytest.raises(QuadobsError, match=match):
        QuadraticSystem(*args)


def test_vehicle_outputs_are_shifted_half_squared_ranges(rng):
    beacons = rng.standard_normal((4, 3)) * 10
    s = vehicle_system(3, beacons)
    x = rng.standard_normal(6) * 5
    rho = np.linalg.norm(x[:3] - beacons, axis=1)
    np.testing.assert_allclose(s.output(x), range_outputs(rho, beacons), rtol=1e-12, atol=1e-10)


def test_wind_system_matches_the_slide():
    s = wind_system(3, np.zeros((1, 3)))
    x = np.arange(9.0)
    p, va, vw = x[:3], x[3:6], x[6:]
    np.testing.assert_allclose(s.A @ x, np.concatenate([va + vw, np.zeros(6)]))
    np.testing.assert_allclose(s.output(x), [0.5 * p @ p, 0.5 * va @ va])
