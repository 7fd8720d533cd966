"""A start-up from a multilateration that never sets the position is reported in the summary's
``startup`` entry (quadobs.estimators.startup.not_started); the filter ran from its prior, so
its figures stand and it is not a lock-out."""

from __future__ import annotations

import numpy as np
import pytest

from quadobs.core.measurements import Measurement
from quadobs.core.system import odometry_system
from quadobs.estimators.kalman import HeldInputModel, OutputModel
from quadobs.estimators.startup import FixedStartEKF, not_started, start_threshold
from quadobs.testbed.divergence import given_up, startup_record
from quadobs.testbed.logs import RangeLog
from quadobs.testbed.logs.replay import run_replay

BEACONS = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 20.0], [0.0, 20.0]])
#: every start-up from a fix: the EKF, UKF (startup), a bias filter, a heading filter
STARTING = ["ekf", "ukf", "ekf-bias", "ukf-heading"]


def _parked(heard, duration: float) -> RangeLog:
    """A vehicle parked at (10, 8) m, noise-free ranges at 4 Hz from the anchors ``heard`` in turn."""
    t = np.arange(0.0, duration, 0.1)
    inputs = np.column_stack([t, np.zeros_like(t), np.zeros_like(t)])
    tr = np.arange(0.05, duration - 0.1, 0.25)
    h = np.asarray(heard)[np.arange(tr.size) % len(heard)]
    p = np.array([10.0, 8.0])
    ranges = np.column_stack([tr, h, np.linalg.norm(p - BEACONS[h], axis=1)])
    truth = np.column_stack([t, np.full_like(t, 10.0), np.full_like(t, 8.0)])
    return RangeLog("parked", np.arange(4), BEACONS, ranges, inputs, 0.0, truth)


@pytest.mark.parametrize(
    ("duration", "why"),
    [(8.0, "given up"), (2.0, "by the end of the run")],  # 32 ranges of one anchor; 8
)
def test_a_replay_whose_fix_cannot_be_made_reports_its_filters_without_fix(duration, why, capsys):
    """One anchor heard: no multilateration. Over 8 s the start-ups give up after four rounds
    (16 ranges, t = 3.8 s); over 2 s they are still waiting at the end. Either way every filter
    that starts from a fix has a ``startup`` entry saying why, keeps its figures (it ran from
    its prior) and is not reported diverged; the CLI's line says so; the observer (no such
    start-up) has no entry."""
    from quadobs.cli import print_diverged

    summary = run_replay(_parked([0], duration), estimators=[*STARTING, "augmented"], batch=False)
    for name in STARTING:
        e = summary["estimators"][name]
        assert e["diverged"] is None and why in e["startup"]["reason"]
        assert e["rmse"] is not None and e["max_error"] is not None
    assert summary["estimators"]["augmented"]["diverged"] is None
    assert "startup" not in summary["estimators"]["augmented"]
    assert summary["estimators"]["augmented"]["rmse"] > 0.0
    print_diverged(summary)
    out = capsys.readouterr().out
    assert out.count("NO START-UP FIX") == len(STARTING) and "DIVERGED" not in out


def test_the_same_log_with_every_anchor_heard_starts_them_all():
    summary = run_replay(_parked([0, 1, 2, 3], 6.0), estimators=STARTING, batch=False)
    for name in STARTING:
        assert summary["estimators"][name]["diverged"] is None
        assert "startup" not in summary["estimators"][name]
        assert summary["estimators"][name]["rmse"] is not None


def test_an_armed_filter_without_ranges_has_no_fix_and_a_fixed_one_has():
    """The record as the live summary reads it (:func:`~quadobs.testbed.divergence.startup_record`):
    armed and without a range, no fix at its time; after a round of ranges, None. Neither is a
    lock-out (:func:`~quadobs.testbed.divergence.given_up`)."""
    system = odometry_system(BEACONS)
    dyn = HeldInputModel(system, 0.1, V=np.eye(2))
    offsets = 0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS)
    est = FixedStartEKF(
        dyn, OutputModel(system, 0.25, offsets=offsets), x0=np.zeros(2), P0=2500.0 * np.eye(2)
    )
    est.start_from_fix(2, start_threshold(BEACONS, 0.5))
    est.hold(np.zeros(3))
    est.predict(1.0)
    assert given_up(est) is None
    assert startup_record(est) == {
        "step": 10,
        "t": 1.0,
        "reason": "no multilateration fix from its ranges by the end of the run",
    }
    p = np.array([10.0, 8.0])
    for h in range(4):
        est.correct(Measurement(1.0, "range", float(np.linalg.norm(p - BEACONS[h])), (h,)))
    assert est.fixes and not_started(est) is None and startup_record(est) is None
