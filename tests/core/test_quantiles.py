"""The quantiles of :mod:`quadobs.core.quantiles` against ``scipy.stats``: the same floats."""

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from quadobs.core import quantiles

PROBABILITIES = [1e-12, 1e-6, 1e-3, 0.025, 0.5, 0.95, 0.975, 0.999, 0.9973002039367398, 1 - 1e-9]


@pytest.mark.parametrize("q", PROBABILITIES)
def test_the_quantiles_are_scipy_stats_own_floats(q):
    for k in (1, 2, 3, 4, 7, 8, 19, 51, 500):
        assert quantiles.chi2_ppf(q, k) == float(stats.chi2.ppf(q, k))
        assert quantiles.chi2_isf(q, k) == float(stats.chi2.isf(q, k))
        assert quantiles.chi2_cdf(q * k, k) == float(stats.chi2.cdf(q * k, k))
        assert quantiles.student_t_ppf(q, k) == float(stats.t.ppf(q, k))
        assert quantiles.fisher_ppf(q, 3, k) == float(stats.f.ppf(q, 3, k))
    assert quantiles.norm_ppf(q) == float(stats.norm.ppf(q))


def test_the_sign_tests_tail_is_the_binomial_tests_p_value():
    for n in (*range(1, 60), 257, 1000, 4000, 10**7):
        for k in np.unique(np.linspace(1, n, 25).astype(int)):
            tail = quantiles.binomial_upper_tail(k, n)
            assert tail == float(stats.binomtest(int(k), n, 0.5, "greater").pvalue)
    assert quantiles.binomial_upper_tail(0, 5) == 1.0 and quantiles.binomial_upper_tail(6, 5) == 0.0
    assert quantiles.binomial_upper_tail(3, 3) == 0.125  # one sequence in 2^3


def test_a_replay_does_not_import_scipy_stats():
    """The reason for the module: the replay's filters, calibration and start import none of it."""
    code = (
        "import sys; import quadobs.cli, quadobs.testbed.logs.calibration, "
        "quadobs.testbed.logs.start_prior, quadobs.testbed.attitude, quadobs.studies.campaign; "
        "print('scipy.stats' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
