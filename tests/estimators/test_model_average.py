"""The model average (:mod:`quadobs.estimators.model_average`): the mixture's closed forms."""

import numpy as np
import pytest
from test_in_time import DT, _filter, _run_in_time, _trajectory

from quadobs import QuadobsError
from quadobs.estimators.kalman import ExtendedKalmanFilter, UnscentedKalmanFilter
from quadobs.estimators.model_average import ModelAverage
from quadobs.estimators.robust import LockOut


def _members(system):
    return [_filter(ExtendedKalmanFilter, system), _filter(UnscentedKalmanFilter, system)]


def test_the_average_is_the_members_mean_and_their_mixtures_covariance():
    system, U, _, M = _trajectory(60)
    alone = _members(system)
    for est in alone:
        _run_in_time(est, U, M)
    avg = ModelAverage(_members(system), "average")
    _run_in_time(avg, U, M)
    x = [e.x_hat for e in alone]
    mean = (x[0] + x[1]) / 2
    np.testing.assert_allclose(avg.x_hat, mean, rtol=0, atol=1e-12)
    spread = sum(np.outer(xi - mean, xi - mean) for xi in x) / 2
    P = (alone[0].x_covariance + alone[1].x_covariance) / 2 + spread
    np.testing.assert_allclose(avg.x_covariance, P, rtol=1e-12, atol=1e-14)
    assert avg.covariance_trace == pytest.approx(np.trace(P), rel=1e-12)
    assert avg.time == pytest.approx(len(M) * DT)
    assert not np.allclose(x[0], x[1])  # two filters, two estimates: the mean is a third


def test_an_average_of_one_is_its_member_and_steps_on_the_grid_as_it():
    system, U, Y, _ = _trajectory(40)
    one = _filter(ExtendedKalmanFilter, system)
    avg = ModelAverage([_filter(ExtendedKalmanFilter, system)])
    for u, y in zip(U, Y, strict=True):
        one.step(u, y)
        avg.step(u, y)
    np.testing.assert_array_equal(avg.x_hat, one.x_hat)
    np.testing.assert_array_equal(avg.x_covariance, one.x_covariance)
    assert avg.nis == one.nis


def test_the_earliest_member_given_up_makes_the_average_diverged():
    system, *_ = _trajectory(1)
    members = _members(system)
    for m, name in zip(members, ("first", "second"), strict=True):
        m.name, m.lockout = name, LockOut()
    avg = ModelAverage(members, "average")
    assert avg.lockout.diverged is None and avg.lockout.locked_at_end() is None
    members[0].lockout.diverged = {"time": 5.0, "step": 50, "reason": "implausible state"}
    members[1].lockout.diverged = {"time": 2.0, "step": 20, "reason": "out of re-initialisations"}
    record = avg.lockout.diverged
    assert record["reason"] == "member second: out of re-initialisations"
    assert avg.lockout.summary()["diverged"] == record
    members[0].lockout = LockOut()  # read when asked: a lock-out replaced is the one read
    members[0].lockout.resets.append({"time": 1.0, "step": 10, "reason": "locked out"})
    assert avg.lockout.resets == [
        {"time": 1.0, "step": 10, "reason": "locked out", "member": "first"}
    ]


def test_the_averages_counts_are_its_members_sums():
    system, U, _, M = _trajectory(60)
    members = [
        _filter(ExtendedKalmanFilter, system, gate=0.5),
        _filter(ExtendedKalmanFilter, system),
    ]
    avg = ModelAverage(members, "average")
    _run_in_time(avg, U, M)
    assert members[0].rejected > 0  # a tight gate: some ranges refused by the first
    assert avg.rejected == members[0].rejected + members[1].rejected
    assert avg.corrections == members[0].corrections + members[1].corrections
    assert avg.gate == members[0].gate


def test_members_of_different_states_are_refused_in_one_line():
    system, *_ = _trajectory(1)
    with pytest.raises(QuadobsError, match="at least one member"):
        ModelAverage([], "average")

    class Three(ExtendedKalmanFilter):
        x_hat = property(lambda self: np.zeros(3))

    odd = _filter(Three, system)
    with pytest.raises(QuadobsError, match="differ in shape"):
        ModelAverage([_filter(ExtendedKalmanFilter, system), odd], "average")
    raw = _filter(ExtendedKalmanFilter, system)
    raw.replay_input = "imu_body"
    with pytest.raises(QuadobsError, match="read different inputs"):
        ModelAverage([_filter(ExtendedKalmanFilter, system), raw], "average")


def test_a_member_that_never_took_its_fix_is_the_averages_start_up_record():
    from quadobs.estimators.startup import not_started

    system, *_ = _trajectory(1)
    members = _members(system)
    for m, name in zip(members, ("first", "second"), strict=True):
        m.name = name
    avg = ModelAverage(members, "average")
    assert not_started(avg) is None
    members[1].fixes, members[1].fix_pending = 0, True
    members[1].time = 3.0
    assert not_started(avg)["reason"] == (
        "member second: no multilateration fix from its ranges by the end of the run"
    )
