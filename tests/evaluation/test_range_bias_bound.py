"""The online bound of ranging with bias states against closed forms, and the information of a
range with a log-normal excess."""

import math

import numpy as np
import pytest

from quadobs.errors import QuadobsError
from quadobs.evaluation.range_bias_bound import (
    excess_fisher_information,
    range_bias_crb,
    rmse_bound,
)

#: six anchors on the axes, 3 m from the origin
ANCHORS = np.vstack([3.0 * np.eye(3), -3.0 * np.eye(3)])


def static_problem(p0: float, sigma_b: float):
    """A vehicle at rest at the origin (zero velocity known, no process noise): the state
    ``(p, v, b)`` with ``F`` the double integrator's step."""
    q, dt = ANCHORS.shape[0], 0.01
    F = np.eye(6 + q)
    F[:3, 3:6] = dt * np.eye(3)
    P0 = np.zeros((6 + q, 6 + q))
    P0[:3, :3] = p0**2 * np.eye(3)
    P0[6:, 6:] = sigma_b**2 * np.eye(q)
    return F, np.zeros_like(F), P0


@pytest.mark.parametrize("sigma_b", [0.0, 0.2])
def test_static_bound_is_the_closed_form(sigma_b):
    """N ranges to each of six anchors in opposite pairs on the axes from the origin: with
    unknown biases of prior ``sigma_b`` each anchor's N ranges act as one of variance
    ``sigma^2 / N + sigma_b^2``, so ``P_pp = (1 / p0^2 + 2 N / (sigma^2 + N sigma_b^2))^-1 I``
    (``sigma_b = 0``: known biases)."""
    p0, sigma, N = 2.0, 0.1, 7
    F, Q, P0 = static_problem(p0, sigma_b)
    q = ANCHORS.shape[0]
    anchor = np.tile(np.arange(q), N)
    step = np.arange(anchor.size)
    steps = anchor.size + 1
    info = np.full(anchor.size, 1.0 / sigma**2)
    B = range_bias_crb(F, Q, P0, steps, ANCHORS, step, anchor, np.zeros((anchor.size, 3)), info)
    expected = 1.0 / (1.0 / p0**2 + 2.0 * N / (sigma**2 + N * sigma_b**2))
    np.testing.assert_allclose(B[-1][:3, :3], expected * np.eye(3), rtol=1e-9, atol=1e-15)
    keep = np.zeros(B.shape[0], dtype=bool)
    keep[-1] = True
    assert rmse_bound(B, 3, keep) == pytest.approx(math.sqrt(3.0 * expected), rel=1e-9)
    if sigma_b == 0.0:  # known biases stay known
        assert not B[:, 6:, :].any() and not B[:, :, 6:].any()
    else:  # each bias: its prior and its N ranges less what the position takes
        assert np.all(np.diag(B[-1])[6:] < sigma_b**2)


def test_a_range_without_information_adds_none():
    F, Q, P0 = static_problem(2.0, 0.2)
    B = range_bias_crb(F, Q, P0, 3, ANCHORS, [0, 1], [0, 1], np.zeros((2, 3)), [0.0, 0.0])
    np.testing.assert_allclose(B[-1], P0)


def test_bad_ranges_are_refused():
    F, Q, P0 = static_problem(2.0, 0.2)
    with pytest.raises(QuadobsError, match="anchor"):
        range_bias_crb(F, Q, P0, 3, ANCHORS, [0], [6], np.zeros((1, 3)), [1.0])
    with pytest.raises(QuadobsError, match="step"):
        range_bias_crb(F, Q, P0, 3, ANCHORS, [3], [0], np.zeros((1, 3)), [1.0])


def test_excess_information_between_its_limits():
    """Between the linear estimator's ``1 / (sigma^2 + Var e)`` and the noise's ``1 / sigma^2``;
    a nearly constant excess (a tiny shape) leaves ``1 / sigma^2``; the grid's resolution does
    not move it."""
    sigma, median, shape = 0.1, 0.3, 0.6
    J = excess_fisher_information(sigma, median, shape)
    var_e = median**2 * math.exp(shape**2) * (math.exp(shape**2) - 1.0)
    assert 1.0 / (sigma**2 + var_e) < J < 1.0 / sigma**2
    assert excess_fisher_information(sigma, median, shape, resolution=20) == pytest.approx(J)
    assert excess_fisher_information(sigma, median, 1e-3) == pytest.approx(1 / sigma**2, rel=1e-3)
    assert excess_fisher_information(sigma, median, 1.0) < J  # a wider excess tells less


def test_excess_information_by_quadrature():
    """The same integral ``int f'^2 / f`` by Gauss-Hermite quadrature over the excess's normal
    variable and the trapezoid rule over ``y``."""
    sigma, median, shape = 0.1, 0.3, 0.6
    z, w = np.polynomial.hermite_e.hermegauss(150)
    w = w / w.sum()
    e = median * np.exp(shape * z)
    y = np.linspace(-1.0, 6.0, 20001)
    g = np.exp(-0.5 * ((y[:, None] - e[None, :]) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
    f = g @ w
    df = (g * (-(y[:, None] - e[None, :]) / sigma**2)) @ w
    J = np.trapezoid(df**2 / np.maximum(f, 1e-300), y)
    assert excess_fisher_information(sigma, median, shape) == pytest.approx(J, rel=2e-3)


def test_excess_information_refuses_bad_figures():
    with pytest.raises(QuadobsError, match="sigma"):
        excess_fisher_information(0.0, 0.3, 0.6)
