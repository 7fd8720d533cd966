"""Measurements of one time as one measurement vector: ``correct_many`` against the grid's step,
the textbook batch update, the sequential one, and the replay feeding equal stamps together."""

import math

import numpy as np
import pytest

from quadobs import QuadobsError, vehicle_system
from quadobs.core.measurements import Measurement
from quadobs.core.system import QuadraticSystem
from quadobs.estimators.base import Estimator
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.testbed.logs.events import InTimeOnGrid

BEACONS = np.array([[0.0, 0.0], [20.0, 0.0], [5.0, 15.0]])
DT = 0.05
TRUTH = np.array([6.0, 3.0])


def _filter(cls, std=0.1):
    system = vehicle_system(2, BEACONS)
    dyn = HeldInputModel(system, DT, V=np.diag([0.0, 0.0, 0.2, 0.2]))
    out = OutputModel(system, std**2, offsets=0.5 * np.einsum("hi,hi->h", BEACONS, BEACONS))
    return cls(dyn, out, x0=[4.0, 5.0, 0.0, 0.0], P0=np.diag([9.0, 9.0, 1.0, 1.0]))


def _ranges(t=0.0, std=0.1, order=(2, 0, 1)):
    rho = np.linalg.norm(TRUTH - BEACONS, axis=1) + np.array([0.05, -0.08, 0.03])
    return [Measurement(t, "range", float(rho[h]), (h,), std) for h in order]


def _outputs(ms):
    y = np.full(len(BEACONS), np.nan)
    for m in ms:
        h = m.anchors[0]
        y[h] = 0.5 * m.value**2 - 0.5 * float(BEACONS[h] @ BEACONS[h])
    return y


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_ranges_of_one_time_are_corrected_as_the_grid_corrects_a_steps_outputs(cls):
    """``correct_many`` of three ranges (in any order) is the grid's ``correct_outputs`` of the
    same three outputs, and differs from correcting by them one after the other (a nonlinear
    model relinearised between them)."""
    joint, grid, seq = _filter(cls), _filter(cls), _filter(cls)
    ms = _ranges()
    joint.correct_many(ms)
    grid.correct_outputs(_outputs(ms))
    for m in ms:
        seq.correct(m)
    np.testing.assert_allclose(joint.x_hat, grid.x_hat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(joint.x_covariance, grid.x_covariance, rtol=0, atol=1e-12)
    assert joint.nis_dof == 3 and joint.corrections == 1 and seq.corrections == 3
    assert np.abs(joint.x_hat - seq.x_hat).max() > 1e-3


def test_the_joint_correction_is_the_textbook_batch_update():
    """EKF: ``H`` the stacked range Jacobians at the prior, ``S = H P H^T + R``,
    ``K = P H^T S^-1``, ``x+ = x + K (rho - h(x))``, ``P+ = (I - K H) P (I - K H)^T + K R K^T``
    with each range's own variance on the diagonal of ``R``."""
    est = _filter(ExtendedKalmanFilter, std=1.0)  # R of the model: 1 m^2; the ranges state theirs
    x, P = est.x_hat, est.x_covariance
    ms = _ranges(order=(0, 1, 2))
    stds = np.array([0.1, 0.2, 0.3])
    ms = [Measurement(m.t, m.kind, m.value, m.anchors, s) for m, s in zip(ms, stds)]
    est.correct_many(ms)
    diff = x[:2] - BEACONS
    rho_pred = np.linalg.norm(diff, axis=1)
    H = np.zeros((3, 4))
    H[:, :2] = diff / rho_pred[:, None]
    R = np.diag(stds**2)
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    nu = np.array([m.value for m in ms]) - rho_pred
    IKH = np.eye(4) - K @ H
    np.testing.assert_allclose(est.x_hat, x + K @ nu, rtol=0, atol=1e-10)
    np.testing.assert_allclose(est.x_covariance, IKH @ P @ IKH.T + K @ R @ K.T, atol=1e-10)
    assert est.nis == pytest.approx(float(nu @ np.linalg.solve(S, nu)), rel=1e-10)


def test_joint_and_sequential_agree_for_outputs_linear_in_the_state():
    """For outputs linear in the state (``C = 0``) one joint Kalman correction and the sequential
    ones give the same posterior (the textbook identity), to rounding."""
    A = np.zeros((2, 2))
    B = np.eye(2)
    C = np.zeros((3, 2, 2))
    d = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, -1.0]])
    system = QuadraticSystem(A, B, C, d)
    make = lambda: ExtendedKalmanFilter(  # noqa: E731
        HeldInputModel(system, DT), OutputModel(system, np.diag([0.04, 0.09, 0.01])),
        x0=[0.5, -0.5], P0=np.diag([4.0, 2.0]),
    )  # fmt: skip
    y = np.array([1.2, 0.7, 0.3])
    joint, seq = make(), make()
    joint.correct_outputs(y)
    for h in range(3):
        one = np.full(3, np.nan)
        one[h] = y[h]
        seq.correct_outputs(one)
    np.testing.assert_allclose(joint.x_hat, seq.x_hat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(joint.x_covariance, seq.x_covariance, rtol=0, atol=1e-12)


def test_a_batch_it_cannot_take_jointly_is_corrected_one_at_a_time():
    """Two ranges of one anchor, or a single one, go through ``correct`` one after the other; a
    range of another time is refused before anything changes."""
    ms = _ranges()
    twice = [ms[0], Measurement(0.0, "range", ms[0].value + 0.1, ms[0].anchors, 0.1)]
    a, b = _filter(ExtendedKalmanFilter), _filter(ExtendedKalmanFilter)
    a.correct_many(twice)
    for m in twice:
        b.correct(m)
    np.testing.assert_array_equal(a.x_hat, b.x_hat)
    late = _ranges()[:2] + _ranges(t=0.01)[2:]
    ekf, spy = _filter(ExtendedKalmanFilter), _Spy()  # the joint path, the default one
    x = ekf.x_hat
    for est in (ekf, spy):
        with pytest.raises(QuadobsError, match="predict to its time first"):
            est.correct_many(late)
    np.testing.assert_array_equal(ekf.x_hat, x)
    assert spy.calls == []


def test_a_bias_filters_round_of_one_time_in_time_is_its_grid_step():
    """The filter with bias states, its start-up fix pending, fed each step's eight ranges with
    one timestamp (``correct_many``) follows the grid's ``step`` to rounding: the same fix,
    the same opening of the biases, the same estimate."""
    from quadobs.core.measurements import RangeModel
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter, biased_models

    anchors = np.array(
        [[x, y, z] for z in (0.2, 2.8) for x, y in ((-3, -3), (3, -3), (3, 3), (-3, 3))]
    )
    biases = np.array([0.1, -0.2, 0.3, 0.05, -0.15, 0.2, 0.0, -0.3])
    system = vehicle_system(3, anchors)

    def make():
        model = RangeModel(anchors, 0.05, bias="state")
        dyn, out, P0 = biased_models(system, 0.01, 0.05, 0.02, 4.0 * np.eye(6), model)
        x0 = np.r_[2.0, 3.0, 0.0, np.zeros(3), np.zeros(8)]
        return BiasedExtendedKalmanFilter(dyn, out, x0=x0, P0=P0, vehicle_n=6)

    grid, timed = make(), make()
    assert grid.fix_pending and timed.fix_pending
    rng = np.random.default_rng(2)
    offsets = 0.5 * (anchors**2).sum(1)
    p, v = np.array([0.0, 0.0, 1.5]), np.array([0.6, 0.8, 0.1])
    for k in range(60):
        a = np.array([np.sin(0.3 * k), np.cos(0.2 * k), 0.0])
        rho = np.linalg.norm(p - anchors, axis=1) + biases + 0.05 * rng.standard_normal(8)
        p, v = p + v * 0.01 + 0.5 * a * 1e-4, v + a * 0.01
        grid.step(a, 0.5 * rho**2 - offsets)
        t = k * 0.01
        timed.correct_many([Measurement(t, "range", float(r), (h,)) for h, r in enumerate(rho)])
        timed.hold(a)
        timed.predict(t + 0.01)
    assert timed.fixes == grid.fixes == [0.0]
    assert timed.opened_at == pytest.approx(grid.opened_at) and len(grid.opened_at) == 1
    np.testing.assert_allclose(timed.x_hat, grid.x_hat, rtol=0, atol=1e-9)
    np.testing.assert_allclose(timed.biases, grid.biases, rtol=0, atol=1e-9)


class _Spy(Estimator):
    """Records how it is fed: ``("one", t)`` per :meth:`correct`, ``("many", t, count)`` per
    :meth:`correct_many`."""

    def __init__(self):
        self.calls = []

    def step(self, u, y):  # pragma: no cover - fed in time only
        raise AssertionError

    @property
    def x_hat(self):
        return np.zeros(2)

    def _input_dimension(self):
        return 1

    def _propagate(self, dt, u):
        pass

    def _correct_measurement(self, m):
        self.calls.append(("one", m.t))

    def correct_many(self, measurements):
        ms = list(measurements)
        if ms[0].t == ms[-1].t:
            self.calls.append(("many", ms[0].t, len(ms)))
        else:  # as the default does
            super().correct_many(ms)


class _Events:
    def __init__(self, times):
        self.measurements = [Measurement(t, "range", 5.0, (h % 3,)) for h, t in enumerate(times)]
        self.times = np.array(times)

    def inputs(self, raw=False):
        return np.array([0.0, 0.02]), np.zeros((2, 1))


def test_the_replay_feeds_equal_stamps_as_one_vector_and_distinct_ones_singly():
    """Stamps ``0, 0, 0, 0.013, 0.02, 0.02`` (an input also at 0.02): one call of three, one
    range, one call of two; never across a grid step's end."""
    spy = _Spy()
    feed = InTimeOnGrid(spy, _Events([0.0, 0.0, 0.0, 0.013, 0.02, 0.02, 0.03]), np.arange(4) * 0.01)
    for _ in range(3):
        feed.step(np.zeros(1), np.zeros(3))
    assert spy.calls == [("many", 0.0, 3), ("one", 0.013), ("many", 0.02, 2)]
    assert math.isclose(spy.time, 0.03)


GATED_BEACONS = np.array([[0.0, 0.0], [20.0, 0.0], [5.0, 15.0], [18.0, 17.0]])


def _gated(cls):
    """A filter at the truth, consistent with ranges of 0.1 m, gated at ``chi^2_0.999(1)``."""
    system = vehicle_system(2, GATED_BEACONS)
    dyn = HeldInputModel(system, DT, V=np.diag([0.0, 0.0, 1e-6, 1e-6]))
    offsets = 0.5 * np.einsum("hi,hi->h", GATED_BEACONS, GATED_BEACONS)
    out = OutputModel(system, 0.01, offsets=offsets)
    x0, P0 = [6.0, 3.0, 0.0, 0.0], np.diag([1e-4, 1e-4, 1e-6, 1e-6])
    return cls(dyn, out, x0=x0, P0=P0, gate=10.83)


def _gated_round(est, rho):
    return [Measurement(est.time, "range", float(r), (h,), 0.1) for h, r in enumerate(rho)]


def test_a_gated_filter_judges_each_range_of_one_time_alone():
    """With a gate on ``chi^2(1)``, four ranges of one time are corrected one after the other
    (the result of ``correct`` on each, exactly), each judged alone: a consistent filter
    rejects about ``0.1 %`` of them, where one joint NIS of ``chi^2(4)`` against that gate
    would reject about 3 % of the rounds."""
    joint, seq = _gated(ExtendedKalmanFilter), _gated(ExtendedKalmanFilter)
    rng = np.random.default_rng(0)
    truth = np.linalg.norm(np.array([6.0, 3.0]) - GATED_BEACONS, axis=1)
    for _ in range(400):
        ms = _gated_round(joint, truth + 0.1 * rng.standard_normal(4))
        joint.correct_many(ms)
        for m in ms:
            seq.correct(m)
        joint.predict(joint.time + DT)
        seq.predict(seq.time + DT)
    np.testing.assert_array_equal(joint.x_hat, seq.x_hat)
    assert (joint.corrections, joint.rejected) == (seq.corrections, seq.rejected)
    assert joint.corrections + joint.rejected == 1600 and joint.nis_dof == 4
    assert joint.rejected / 1600 < 0.005


def _round_outputs(rho):
    """The grid's outputs ``y_h = rho_h^2 / 2 - |a_h|^2 / 2`` of ranges ``rho``."""
    return 0.5 * np.asarray(rho) ** 2 - 0.5 * np.einsum("hi,hi->h", GATED_BEACONS, GATED_BEACONS)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_the_gated_grid_step_judges_each_output_alone_as_correct_many_does(cls):
    """``step(u, y)`` with four ranges present and a gate: the result of ``correct_many`` on the
    same ranges, to the bit (one place), and of ``correct`` on each in turn; the recorded NIS
    is the sum of the four scalar ones with four degrees of freedom."""
    grid, many, seq = _gated(cls), _gated(cls), _gated(cls)
    rng = np.random.default_rng(1)
    truth = np.linalg.norm(np.array([6.0, 3.0]) - GATED_BEACONS, axis=1)
    for _ in range(20):
        rho = truth + 0.1 * rng.standard_normal(4)
        ms = _gated_round(many, rho)
        nis = 0.0
        for m in ms:
            seq.correct(m)
            nis += seq.nis
        many.correct_many(ms)
        grid.step(np.zeros(2), _round_outputs(rho))
        for f in (many, seq):
            f.predict(f.time + DT)
        assert (grid.nis, grid.nis_dof) == (pytest.approx(nis, rel=1e-9), 4)
    for f in (many, seq):
        np.testing.assert_allclose(grid.x_hat, f.x_hat, rtol=0, atol=1e-12)
        np.testing.assert_allclose(grid.x_covariance, f.x_covariance, rtol=0, atol=1e-15)
        assert (grid.corrections, grid.rejected) == (f.corrections, f.rejected) == (80, 0)


def test_a_round_each_range_of_which_passes_is_not_rejected_for_its_joint_nis():
    """Four ranges each ``2.9 sqrt(S)`` off (NIS about 8.4 < 10.83 each, about 25 jointly, beyond
    the gate stated for one range): the grid step takes all four, one at a time, where a
    joint NIS against the gate would have rejected the round; a 2 m outlier among them is
    rejected alone."""
    for outlier, counts in ((0.0, (4, 0)), (2.0, (3, 1))):
        est = _gated(ExtendedKalmanFilter)
        _, H = est.outputs.linearize(est.x_hat)
        S = np.einsum("hi,ij,hj->h", H, est.x_covariance, H) + 0.01
        rho = np.linalg.norm(np.array([6.0, 3.0]) - GATED_BEACONS, axis=1)
        rho = rho + 2.9 * np.sqrt(S) * np.array([1.0, -1.0, 1.0, -1.0])
        rho[1] += outlier
        est.step(np.zeros(2), _round_outputs(rho))
        assert (est.corrections, est.rejected) == counts


def test_correlated_outputs_are_gated_jointly_at_the_same_probability():
    """Correlated noise cannot be split: one joint correction, gated at the ``chi^2(k)`` quantile
    of the probability the gate keeps for one output (10.83 -> 0.999 -> 13.82 for two, 18.47
    for four); the threshold is closed form, and a joint NIS between the two is accepted."""
    from scipy import stats

    est = _gated(ExtendedKalmanFilter)
    assert est.gate_threshold(1) == 10.83
    p = stats.chi2.cdf(10.83, 1)
    for k in (2, 4):
        assert est.gate_threshold(k) == pytest.approx(stats.chi2.ppf(p, k), rel=1e-9)
    assert est.gate_threshold(2) == pytest.approx(13.82, abs=0.01)
    R = 0.01 * (np.eye(4) + 0.5 * (np.ones((4, 4)) - np.eye(4)))
    system = est.outputs.system
    for scale, counts in ((1.0, (1, 0)), (1.5, (0, 1))):
        f = _gated(ExtendedKalmanFilter)
        f.outputs = OutputModel(system, R, offsets=f.outputs.offsets)
        z, H = f.outputs.linearize(f.x_hat)
        S = H @ f.x_covariance @ H.T + R
        nu = np.array([1.0, -1.0, 1.0, -1.0])
        nu *= scale * np.sqrt(15.0 / (nu @ np.linalg.solve(S, nu)))  # NIS 15, then 33.75
        f.step(np.zeros(2), _round_outputs(z + nu))
        assert (f.corrections, f.rejected, f.nis_dof) == (*counts, 4)
        assert f.nis == pytest.approx(15.0 * scale**2, rel=1e-9)


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_one_outlier_of_a_gated_round_leaves_the_other_ranges(cls):
    """A range 2 m long among four of one time is rejected alone; the other three correct."""
    est = _gated(cls)
    rho = np.linalg.norm(np.array([6.0, 3.0]) - GATED_BEACONS, axis=1) + [0.05, 2.0, -0.04, 0.02]
    est.correct_many(_gated_round(est, rho))
    assert (est.corrections, est.rejected) == (3, 1)


def test_the_nis_window_covers_its_degrees_of_freedom_and_tests_their_chi2():
    """Scalar NIS values: the window of ``2q`` of them against ``chi^2(2q)``, as before; an
    8-dof NIS takes the place of eight of them; NIS values drawn from ``chi^2(8)`` pass the
    test at ``probability`` (window of two of them, ``chi^2(16)``)."""
    from scipy import stats

    from quadobs.estimators.bias_states import NisWindow

    w = NisWindow(16, 0.9)
    for _ in range(20):
        w.append(0.5, 1)
    assert (len(w), w.dof) == (16, 16) and w.consistent()
    w.append(30.0, 8)
    assert (len(w), w.dof) == (9, 16)
    assert w.threshold(16) == pytest.approx(stats.chi2.ppf(0.9, 16), rel=1e-12)
    assert not w.consistent()  # 8 * 0.5 + 30 > 23.5
    w.clear()
    rng = np.random.default_rng(3)
    passed = []
    for nis in rng.chisquare(8, 2000):
        w.append(float(nis), 8)
        if w.dof >= 16:
            passed.append(w.consistent())
    assert len(w) == 2 and abs(np.mean(passed) - 0.9) < 0.04


def test_a_bias_filter_fed_whole_rounds_opens_its_biases_after_two_rounds():
    """The eight ranges of one time corrected jointly (one NIS of 8 dof each): the biases open
    once two rounds (16 dof) are consistent, at the third round (the first makes the start-up's
    fix and is not corrected by), as the same ranges corrected one at a time open them after
    sixteen corrections, at the same round."""
    from quadobs.core.measurements import RangeModel
    from quadobs.estimators.bias_states import BiasedExtendedKalmanFilter, biased_models

    anchors = np.array(
        [[x, y, z] for z in (0.2, 2.8) for x, y in ((-3, -3), (3, -3), (3, 3), (-3, 3))]
    )
    biases = np.array([0.1, -0.2, 0.3, 0.05, -0.15, 0.2, 0.0, -0.3])
    system = vehicle_system(3, anchors)
    opened = {}
    for mode in ("joint", "sequential"):
        model = RangeModel(anchors, 0.05, bias="state")
        dyn, out, P0 = biased_models(system, 0.01, 0.05, 0.02, 4.0 * np.eye(6), model)
        x0 = np.r_[2.0, 3.0, 0.0, np.zeros(3), np.zeros(8)]
        est = BiasedExtendedKalmanFilter(dyn, out, x0=x0, P0=P0, vehicle_n=6)
        rng = np.random.default_rng(2)
        p, v = np.array([0.0, 0.0, 1.5]), np.array([0.6, 0.8, 0.1])
        for k in range(20):
            a = np.array([np.sin(0.3 * k), np.cos(0.2 * k), 0.0])
            rho = np.linalg.norm(p - anchors, axis=1) + biases + 0.05 * rng.standard_normal(8)
            p, v = p + v * 0.01 + 0.5 * a * 1e-4, v + a * 0.01
            ms = [Measurement(k * 0.01, "range", float(r), (h,)) for h, r in enumerate(rho)]
            if mode == "joint":
                est.correct_many(ms)
            else:
                for m in ms:
                    est.correct(m)
            est.hold(a)
            est.predict(k * 0.01 + 0.01)
        opened[mode] = est.opened_at
    assert opened["joint"] == pytest.approx([0.02])
    assert opened["sequential"] == pytest.approx([0.02])


def test_the_gate_s_quantile_follows_a_reassigned_gate():
    """``chi^2(2)``'s tail is ``exp(-x / 2)``: the threshold for two outputs is
    ``-2 ln P(chi^2(1) > gate)`` in closed form, for whatever gate the filter holds now."""
    import math

    est = _gated(ExtendedKalmanFilter)
    for gate in (10.83, 6.63):
        est.gate = gate
        tail = math.erfc(math.sqrt(gate / 2))
        assert est.gate_threshold(2) == pytest.approx(-2.0 * math.log(tail), rel=1e-9)
