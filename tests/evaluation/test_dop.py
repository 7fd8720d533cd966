"""Dilution of precision of ranges and TDOA against closed forms."""

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.evaluation.dop import pdop, range_information, tdoa_information

CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)


def test_centre_of_a_cube():
    """At the centre the u_i are the cube's diagonals: sum u u^T = (8/3) I, mean zero."""
    J_r = range_information(CUBE, np.zeros(3))
    J_t = tdoa_information(CUBE, np.zeros(3))
    np.testing.assert_allclose(J_r, np.eye(3) / 3)
    np.testing.assert_allclose(J_t, 2 / 7 * 8 / 3 * np.eye(3))
    assert pdop(J_r) == pytest.approx(3.0)
    assert pdop(J_t) == pytest.approx(np.sqrt(3 * 21 / 16))


def test_tdoa_information_is_the_pair_average():
    p = np.array([0.3, -0.7, 2.5])
    u = (p - CUBE) / np.linalg.norm(p - CUBE, axis=1)[:, None]
    J = sum(np.outer(u[i] - u[j], u[i] - u[j]) for i in range(8) for j in range(8) if i != j)
    np.testing.assert_allclose(tdoa_information(CUBE, p), J / 56, atol=1e-14)


def test_far_away_tdoa_loses_the_range_and_pdop_is_infinite_when_singular():
    far = np.array([0.0, 0.0, 1e3])
    assert pdop(tdoa_information(CUBE, far)) > 50 * pdop(range_information(CUBE, far))
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert np.isinf(pdop(range_information(line, np.array([2.0, 0.0, 0.0]))))
    with pytest.raises(QuadobsError, match="anchors, points"):
        range_information(CUBE, np.zeros(2))
