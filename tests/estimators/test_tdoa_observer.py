"""The TDOA observer on the immersion against a textbook EKF, on noise-free and noisy data."""

import numpy as np
import pytest

from quadobs.core.measurements import Measurement, TdoaModel
from quadobs.core.system import vehicle_system
from quadobs.errors import QuadobsError
from quadobs.estimators.kalman import (
    ExtendedKalmanFilter,
    HeldInputModel,
    OutputModel,
    UnscentedKalmanFilter,
)
from quadobs.estimators.tdoa_observer import TdoaHandover, TdoaObserver
from quadobs.testbed.tdoa import PairsInTime, measurements, ordered_pairs, tdoa_outputs

ROOM = np.array(
    [[x, y, z] for z in (0.2, 2.8) for x, y in ((-3, -3), (3, -3), (3, 3), (-3, 3))], dtype=float
)
DT = 0.01
AMP, OMEGA, OFFSET = np.array([2.0, 1.2, 0.4]), np.array([0.3, 0.6, 0.3]), np.array([0, 0, 1.5])


def flight(steps, anchors=ROOM, std=0.0, seed=0):
    """A figure eight integrated exactly with the acceleration held over each step."""
    dim = anchors.shape[1]
    t = np.arange(steps) * DT
    acc = (-AMP * OMEGA**2 * np.sin(OMEGA * (t[:, None] + 0.5 * DT)))[:, :dim]
    x = np.empty((steps + 1, 2 * dim))
    x[0] = np.concatenate([OFFSET[:dim], (AMP * OMEGA)[:dim]])
    for k in range(steps):
        x[k + 1, :dim] = x[k, :dim] + DT * x[k, dim:] + 0.5 * DT**2 * acc[k]
        x[k + 1, dim:] = x[k, dim:] + DT * acc[k]
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2)]
    Y = tdoa_outputs(x[:steps, :dim], anchors, 1, std, *rngs)
    return x, acc, Y


class TextbookEkf:
    """The EKF on (p, v) with TDOA through TdoaModel.h/jacobian: the reference."""

    def __init__(self, anchors, x0, P0, q, std):
        dim = anchors.shape[1]
        self.model = TdoaModel(anchors, std)
        self.x, self.P, self.std = x0.copy(), np.diag(P0).astype(float), std
        I, Z = np.eye(dim), np.zeros((dim, dim))
        self.F = np.block([[I, DT * I], [Z, I]])
        self.G = np.vstack([0.5 * DT**2 * I, DT * I])
        self.Q = q / DT * self.G @ self.G.T  # white acceleration of intensity q, held per step
        self.dim = dim

    def step(self, u, y, pairs):
        for h in np.flatnonzero(np.isfinite(y)):
            m = Measurement(0.0, "tdoa", float(y[h]), pairs[h])
            H = np.zeros(2 * self.dim)
            H[: self.dim] = self.model.jacobian(self.x[: self.dim], m)
            S = H @ self.P @ H + self.std**2
            K = self.P @ H / S
            self.x = self.x + K * (m.value - self.model.h(self.x[: self.dim], m))
            IKH = np.eye(H.size) - np.outer(K, H)
            self.P = IKH @ self.P @ IKH.T + self.std**2 * np.outer(K, K)
        self.x = self.F @ self.x + self.G @ u
        self.P = self.F @ self.P @ self.F.T + self.Q


def run(est, x, acc, Y, pairs, ekf=False):
    X = np.empty_like(x)
    X[0] = est.x if ekf else est.x_hat
    for k in range(acc.shape[0]):
        if ekf:
            est.step(acc[k], Y[k], pairs)
            X[k + 1] = est.x
        else:
            est.step(acc[k], Y[k])
            X[k + 1] = est.x_hat
    return X


def test_started_at_the_truth_the_estimate_stays_exact():
    x, acc, Y = flight(300)
    pairs = ordered_pairs(8)
    obs = TdoaObserver(ROOM, DT, x[0], P0=1.0, std=0.1, accel_psd=0.0, pairs=pairs)
    X = run(obs, x, acc, Y, pairs)
    assert np.abs(X - x).max() < 1e-9


def test_from_ten_metres_off_it_converges_like_the_ekf_noise_free():
    """Noise-free: the observer converges from 10 m off to the truth, and to where an EKF
    started near the truth converges (both exact in the limit)."""
    x, acc, Y = flight(600)
    pairs = ordered_pairs(8)
    far = x[0] + np.array([10.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    obs = TdoaObserver(ROOM, DT, far, P0=[100.0] * 3 + [1.0] * 3, std=0.01, pairs=pairs)
    X = run(obs, x, acc, Y, pairs)
    err = np.linalg.norm(X[:, :3] - x[:, :3], axis=1)
    assert err[0] == pytest.approx(10.0)
    assert err[300] < 0.5  # within 3 s
    assert err[-1] < 1e-3
    near = x[0] + np.array([0.3, -0.2, 0.1, 0.0, 0.0, 0.0])
    ekf = TextbookEkf(ROOM, near, [1.0] * 3 + [1.0] * 3, 0.0, 0.01)
    E = run(ekf, x, acc, Y, pairs, ekf=True)
    assert np.linalg.norm(E[-1, :3] - x[-1, :3]) < 1e-3
    assert np.linalg.norm(X[-1] - E[-1]) < 2e-3


def test_noisy_accuracy_below_a_decimetre_the_ekf_closer_still():
    """Near the truth the EKF on (p, v) is the more accurate (the immersion carries 18 more
    states); the observer stays within the 0.1 m target."""
    x, acc, Y = flight(1500, std=0.1, seed=4)
    pairs = ordered_pairs(8)
    near = x[0] + np.array([0.5, -0.5, 0.2, 0.0, 0.0, 0.0])
    obs = TdoaObserver(ROOM, DT, near, P0=1.0, std=0.1, accel_psd=1e-6, pairs=pairs)
    ekf = TextbookEkf(ROOM, near, [1.0] * 6, 1e-6, 0.1)
    X = run(obs, x, acc, Y, pairs)
    E = run(ekf, x, acc, Y, pairs, ekf=True)
    late = slice(500, None)
    rmse_obs = np.sqrt(np.mean(np.sum((X[late, :3] - x[late, :3]) ** 2, axis=1)))
    rmse_ekf = np.sqrt(np.mean(np.sum((E[late, :3] - x[late, :3]) ** 2, axis=1)))
    assert rmse_ekf < rmse_obs < 0.1


def test_in_the_plane():
    room = ROOM[:4, :2]
    x, acc, Y = flight(500, anchors=room)
    pairs = ordered_pairs(4)
    far = x[0] + np.array([-10.0, 4.0, 0.0, 0.0])
    obs = TdoaObserver(room, DT, far, P0=[100.0, 100.0, 1.0, 1.0], std=0.01, pairs=pairs)
    X = run(obs, x, acc, Y, pairs)
    assert obs.model.immersion.n_aux == 9
    assert np.linalg.norm(X[-1, :2] - x[-1, :2]) < 1e-3


def test_measurements_in_time_give_the_grid_result():
    x, acc, Y = flight(200, std=0.1, seed=2)
    pairs = ordered_pairs(8)
    a = TdoaObserver(ROOM, DT, x[0] + 1.0, P0=4.0, accel_psd=1e-4, pairs=pairs)
    b = TdoaObserver(ROOM, DT, x[0] + 1.0, P0=4.0, accel_psd=1e-4)
    run(a, x, acc, Y, pairs)
    for k, events in enumerate(measurements(Y, DT, 0.1)):
        for m in events:
            b.correct(m)
        b.hold(acc[k])
        b.predict((k + 1) * DT)
    np.testing.assert_allclose(b.x_hat, a.x_hat, rtol=0, atol=1e-9)
    assert b.time == pytest.approx(200 * DT)


def test_bad_input_is_refused_with_one_line():
    obs = TdoaObserver(ROOM, DT, np.zeros(6), pairs=[(0, 1)])
    with pytest.raises(QuadobsError, match="takes TDOA"):
        obs.correct(Measurement(0.0, "range", 1.0, (0,)))
    with pytest.raises(QuadobsError, match="before"):
        obs.predict(-1.0)
    with pytest.raises(QuadobsError, match="pairs"):
        TdoaObserver(ROOM, DT, np.zeros(6), pairs=[(0, 8)])
    with pytest.raises(QuadobsError, match="y"):
        obs.step(np.zeros(3), np.zeros(2))


def project_filter(cls, x0, P0, q, std):
    """The project's EKF or UKF on the vehicle, correcting TDOA through TdoaModel."""
    system = vehicle_system(3, ROOM)
    dynamics = HeldInputModel(system, DT, input_covariance=q / DT)
    offsets = 0.5 * np.einsum("hi,hi->h", ROOM, ROOM)
    outputs = OutputModel(system, 0.01, offsets=offsets)
    return cls(dynamics, outputs, x0=x0, P0=P0, measurements=[TdoaModel(ROOM, std)])


@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
def test_project_filters_on_pairs_agree_with_the_observer_noise_free(cls):
    x, acc, Y = flight(400)
    pairs = ordered_pairs(8)
    near = x[0] + np.array([0.3, -0.2, 0.1, 0.0, 0.0, 0.0])
    filt = PairsInTime(project_filter(cls, near, 1.0, 0.0, 0.01), pairs, DT, 0.01)
    obs = TdoaObserver(ROOM, DT, near, P0=1.0, std=0.01, pairs=pairs)
    F, X = run(filt, x, acc, Y, pairs), run(obs, x, acc, Y, pairs)
    assert np.linalg.norm(F[-1, :3] - x[-1, :3]) < 1e-3
    assert np.linalg.norm(F[-1] - X[-1]) < 2e-3


def test_handover_from_ten_metres_off_then_the_ekf():
    x, acc, Y = flight(600, std=0.1, seed=5)
    pairs = ordered_pairs(8)
    far = x[0] + np.array([10.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    P0 = np.diag([100.0] * 3 + [1.0] * 3)
    obs = TdoaObserver(ROOM, DT, far, P0=P0, std=0.1, accel_psd=1e-6, pairs=pairs)

    def make(xh, P, t):
        ekf = project_filter(ExtendedKalmanFilter, xh, P, 1e-6, 0.1)
        ekf.time = t
        return ekf

    est = TdoaHandover(obs, make)
    X = run(est, x, acc, Y, pairs)
    assert est.filter is not None and 0.0 < est.handover_time < 3.0
    k = round(est.handover_time / DT)
    assert np.linalg.norm(X[k, :3] - x[k, :3]) < 1.0  # handed over near the truth
    err = np.linalg.norm(X[:, :3] - x[:, :3], axis=1)
    assert err[300] < 0.5
    assert np.sqrt(np.mean(err[300:] ** 2)) < 0.1
