"""P-radius gain design (problem 9, Algorithm 2): the paper's gains, and the P-radius decrease
condition checked by brute force on random generator matrices."""

import numpy as np
import pytest

from quadobs import IntervalMatrix, QuadobsError, Zonotope, pradius_gains
from quadobs.studies.le2013.study import A_INTERVAL, NOISE_BOUND, PAPER_GAINS, C, F


@pytest.fixture(scope="module")
def designs():
    return {ap: pradius_gains(A_INTERVAL, F, C, NOISE_BOUND, approach=ap) for ap in (1, 2)}


def test_first_approach_reproduces_the_papers_gains(designs):
    np.testing.assert_allclose(designs[1].gains, PAPER_GAINS["first_approach"], atol=1e-4)
    # Algorithm 2 starts with the first approach's lambda_1
    np.testing.assert_allclose(designs[2].gains[0], PAPER_GAINS["second_approach"][0], atol=1e-4)


def test_design_fields_and_lmi_margin(designs):
    for ap, d in designs.items():
        assert d.approach == ap
        assert d.gains.shape == (2, 2) and d.P.shape == (2, 2, 2)
        assert np.all((0 < d.beta) & (d.beta < 1)) and np.all(d.tau > 0)
        assert d.lmi_margin > -1e-7
        for P in d.P:
            assert np.linalg.eigvalsh(P)[0] > 0
        assert d.psi == pytest.approx(0.02**2 * 37)


def _brute_check(design, A_list, Fm, Cm, rng, trials=40):
    """L_{k/j} <= beta_j L_{k-1} + offset_j for random H_{k-1}, exact P-radii by vertex enumeration."""
    n = Cm.shape[1]
    phi = design.noise_bounds
    worst = -np.inf
    for _ in range(trials):
        r = int(rng.integers(1, 6))
        H = rng.standard_normal((n, r)) * rng.uniform(0.1, 5.0)
        for A in A_list:
            if design.approach == 1:
                for i, (lam, c) in enumerate(zip(design.gains, Cm)):
                    kappa = np.eye(n) - np.outer(lam, c)
                    Hn = np.hstack([kappa @ A @ H, kappa @ Fm, phi[i] * lam[:, None]])
                    P = design.P[i]
                    bound = design.beta[i] * Zonotope(np.zeros(n), H).p_radius(P) + design.offset(i)
                    worst = max(worst, Zonotope(np.zeros(n), Hn).p_radius(P) / bound)
            else:
                Hn = np.hstack([A @ H, Fm])
                for j, (lam, c) in enumerate(zip(design.gains, Cm)):
                    kappa = np.eye(n) - np.outer(lam, c)
                    Hn = np.hstack([kappa @ Hn, phi[j] * lam[:, None]])
                    P = design.P[j]
                    bound = design.beta[j] * Zonotope(np.zeros(n), H).p_radius(P) + design.offset(j)
                    worst = max(worst, Zonotope(np.zeros(n), Hn).p_radius(P) / bound)
    return worst


def test_pradius_decrease_condition_holds_on_random_generators(designs, rng):
    inner = [
        A_INTERVAL.lower + rng.uniform(0, 1, (2, 2)) * (A_INTERVAL.upper - A_INTERVAL.lower)
        for _ in range(3)
    ]
    A_list = list(A_INTERVAL.vertices()) + inner
    for d in designs.values():
        assert _brute_check(d, A_list, F, C, rng) <= 1 + 1e-6


def test_random_three_state_system_both_approaches(rng):
    n = 3
    A0 = rng.standard_normal((n, n))
    A0 *= 0.8 / max(abs(np.linalg.eigvals(A0)))
    A = IntervalMatrix.from_mid_rad(A0, np.where(np.eye(n) > 0, 0.03, 0.0))
    Fm = 0.05 * rng.standard_normal((n, 2))
    Cm = rng.standard_normal((2, n))
    for ap in (1, 2):
        d = pradius_gains(A, Fm, Cm, [0.1, 0.2], approach=ap, betas=np.linspace(0.05, 0.95, 10))
        assert d.lmi_margin > -1e-7
        assert _brute_check(d, list(A.vertices()), Fm, Cm, rng, trials=15) <= 1 + 1e-6


def test_infeasible_design_is_a_clear_error():
    # x2 is unstable and does not reach the output: no gain can contract the P-radius
    with pytest.raises(QuadobsError, match="infeasible"):
        pradius_gains(
            np.diag([0.5, 1.5]), [0.1, 0.1], [[1.0, 0.0]], 0.1, approach=1, betas=[0.3, 0.6, 0.9]
        )


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"noise_bounds": 0.0}, "noise_bounds"),
        ({"approach": 3}, "approach"),
        ({"C": np.ones((2, 3))}, "C"),
        ({"F": np.ones((3, 1))}, "F"),
        ({"betas": [0.5, 1.0]}, "betas"),
    ],
)
def test_bad_input(kwargs, match):
    args = {"A_vertices": np.eye(2) * 0.5, "F": [0.1, 0.0], "C": [[1.0, 0.0]], "noise_bounds": 0.1}
    args.update(kwargs)
    with pytest.raises(QuadobsError, match=match):
        pradius_gains(**args)


def test_design_without_cvxpy_names_the_extra(monkeypatch):
    """A core install (no cvxpy) is told in one line which extra adds the LMI design."""
    import sys

    monkeypatch.setitem(sys.modules, "cvxpy", None)  # import cvxpy raises ImportError
    with pytest.raises(QuadobsError) as info:
        pradius_gains(np.eye(2) * 0.5, np.eye(2) * 0.1, np.array([[1.0, 0.0]]), 0.1)
    message = str(info.value)
    assert "\n" not in message
    assert "pip install 'quadobs[sets]'" in message and message.startswith("pradius_gains:")
