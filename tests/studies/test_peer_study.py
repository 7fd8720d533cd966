"""The peer's study on synthetic logs runs, deterministically, with figures that could fail."""

from __future__ import annotations

import pytest

pytest.importorskip("gtsam", reason="gtsam is not installed (the data extra)")

from quadobs.studies.peer import CASES, run_case


def test_a_short_case_runs_and_repeats_with_its_seed():
    name = "biased ranges, bias as a state"
    assert name in CASES
    a = run_case(name, duration=3.0, rate=25, burn_in=1.5, seed=3)
    b = run_case(name, duration=3.0, rate=25, burn_in=1.5, seed=3)
    assert a["measurements"] == 75 and a["online_rmse"] == b["online_rmse"]
    assert a["batch_rmse"] < 0.2 and a["bias_error_max"] < 0.3
