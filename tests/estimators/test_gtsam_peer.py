"""The GTSAM peer: its factors against closed forms and finite differences, and small synthetic logs
(a known trajectory, its IMU, ranges and TDOA with noise and outliers) in 2-D and 3-D."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError

gtsam = pytest.importorskip("gtsam", reason="gtsam is not installed (the data extra)")

from quadobs.estimators.gtsam_factors import (  # noqa: E402
    double_integrator_covariance,
    double_integrator_factor,
    range_factor,
    tdoa_factor,
)
from quadobs.estimators.gtsam_peer import Isam2Peer, PeerNoise  # noqa: E402

ANCHORS_3D = np.array(
    [[0, 0, 0.2], [8, 0, 2.5], [8, 6, 0.3], [0, 6, 2.8], [4, -1, 1.5], [4, 7, 0.5]], float
)
ANCHORS_2D = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0]])
W = 0.5  # rad/s along the circle


def circle(t: float, dim: int = 3):
    """Position, velocity and acceleration on a circle of radius 2 m (3-D: with a vertical wave)."""
    c, s = math.cos(W * t), math.sin(W * t)
    p = np.array([4 + 2 * c, 3 + 2 * s, 1.5 + 0.3 * math.sin(2 * W * t)])
    v = np.array([-2 * W * s, 2 * W * c, 0.6 * W * math.cos(2 * W * t)])
    a = np.array([-2 * W**2 * c, -2 * W**2 * s, -1.2 * W**2 * math.sin(2 * W * t)])
    return p[:dim], v[:dim], a[:dim]


def line(t: float, dim: int = 3):
    """A constant velocity: what the constant-velocity prior describes exactly."""
    p0, v = np.array([2.0, 1.0, 1.0])[:dim], np.array([0.4, 0.3, 0.05])[:dim]
    return p0 + v * t, v, np.zeros(dim)


def unit_noise(dim: int = 1):
    return gtsam.noiseModel.Unit.Create(dim)


def run(est, truth, measure, *, rate, duration, inputs=None, imu_rate=None):
    """Feed a synthetic log through the time interface; the position errors at the measurement times."""
    dim = est.dim
    errs, times = [], []
    sub = 1 if imu_rate is None else imu_rate // rate
    dt = 1.0 / (rate * sub)
    for k in range(1, int(duration / dt) + 1):
        t = k * dt
        est.predict(t)
        p = truth(t, dim)[0]
        if k % sub == 0:
            for m in measure(t, k // sub, p):
                est.correct(m)
            errs.append(float(np.linalg.norm(est.x_hat[:dim] - p)))
            times.append(t)
        if inputs is not None:
            est.hold(inputs(t))
    return np.array(times), np.array(errs)


def ranges(anchors, sigma, rng, bias=None, outliers=0.0):
    """One range per call to the anchors in turn (round robin), with noise, biases and positive outliers."""
    b = np.zeros(len(anchors)) if bias is None else bias

    def measure(t, k, p):
        h = k % len(anchors)
        rho = np.linalg.norm(p - anchors[h]) + b[h] + sigma * rng.standard_normal()
        if outliers and rng.uniform() < outliers:
            rho += rng.uniform(2.0, 6.0)  # non-line-of-sight: metres longer
        return [Measurement(t, "range", float(rho), (h,))]

    return measure


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# -- the factors --------------------------------------------------------------------------


def _numeric_jacobian(factor, values, key, kind, eps=1e-6):
    """Central differences of the factor's error along gtsam's tangent of the variable ``key``."""

    def at(delta):
        v = gtsam.Values(values)
        if kind == "point":
            v.update(key, values.atVector(key) + delta)
        elif kind == "pose2":
            v.update(key, values.atPose2(key).retract(delta))
        else:
            v.update(key, values.atPose3(key).retract(delta))
        return factor.unwhitenedError(v)

    dof = {"point": values.atVector(key).size if kind == "point" else 0, "pose2": 3, "pose3": 6}
    n = dof[kind]
    cols = [(at(eps * e) - at(-eps * e)) / (2 * eps) for e in np.eye(n)]
    return np.column_stack(cols)


def _variable(kind: str, rng):
    if kind == "point":
        return rng.normal(size=3) * 3
    if kind == "pose2":
        return gtsam.Pose2(*rng.normal(size=2) * 3, rng.uniform(-3, 3))
    return gtsam.Pose3(gtsam.Rot3.RzRyRx(*rng.uniform(-1, 1, 3)), rng.normal(size=3) * 3)


@pytest.mark.parametrize("kind", ["point", "pose2", "pose3"])
def test_the_range_and_tdoa_jacobians_match_finite_differences(kind):
    rng = np.random.default_rng(4)
    d = 2 if kind == "pose2" else 3
    x, b = gtsam.symbol("x", 0), gtsam.symbol("r", 0)
    values = gtsam.Values()
    values.insert(x, _variable(kind, rng))
    values.insert(b, np.array([0.3]))
    ai, aj = rng.normal(size=d) * 5, rng.normal(size=d) * 5
    for factor, keys in (
        (range_factor(gtsam, unit_noise(), x, kind, ai, 4.0), [x]),
        (range_factor(gtsam, unit_noise(), x, kind, ai, 4.0, bias_key=b), [x, b]),
        (tdoa_factor(gtsam, unit_noise(), x, kind, ai, aj, 0.5), [x]),
    ):
        A = factor.linearize(values).jacobian()[0]  # whitened by a unit noise: the Jacobian itself
        numeric = _numeric_jacobian(factor, values, x, kind)
        np.testing.assert_allclose(A[:, : numeric.shape[1]], numeric, atol=1e-6)
        if len(keys) == 2:
            np.testing.assert_allclose(A[:, -1], [1.0])  # d e / d bias


def test_known_biases_are_subtracted():
    bias = np.array([0.3, -0.2, 0.1, 0.25, -0.3, 0.0])
    out = {}
    for known in (None, bias):
        rng = np.random.default_rng(1)
        x0 = np.concatenate([line(0.0)[0] + 1.0, np.zeros(3)])
        noise = PeerNoise(range_sigma=0.02)
        est = Isam2Peer(ANCHORS_3D, "none", x0=x0, P0=4.0, noise=noise, fixed_bias=known)
        times, errs = run(est, line, ranges(ANCHORS_3D, 0.02, rng, bias), rate=25, duration=4.0)
        out[known is None] = rms(errs[times > 2.0])
    assert out[False] < 0.1 and out[False] < 0.5 * out[True], out


def test_the_factors_vanish_on_noise_free_data():
    p = np.array([1.0, 2.0, 0.5])
    a, c = ANCHORS_3D[1], ANCHORS_3D[3]
    x = gtsam.symbol("x", 0)
    values = gtsam.Values()
    values.insert(x, p)
    rho = float(np.linalg.norm(p - a))
    d = rho - float(np.linalg.norm(p - c))
    assert (
        abs(range_factor(gtsam, unit_noise(), x, "point", a, rho).unwhitenedError(values)[0])
        < 1e-12
    )
    assert (
        abs(tdoa_factor(gtsam, unit_noise(), x, "point", a, c, d).unwhitenedError(values)[0])
        < 1e-12
    )


def test_the_double_integrator_is_exact_for_a_constant_acceleration_and_its_covariance_closed_form():
    rng = np.random.default_rng(2)
    T, q, d = 0.7, 0.3, 3
    p, v, a = rng.normal(size=(3, d))
    keys = [gtsam.symbol(c, i) for i, c in ((0, "x"), (0, "v"), (1, "x"), (1, "v"))]
    values = gtsam.Values()
    for k, val in zip(keys, (p, v, p + v * T + 0.5 * a * T**2, v + a * T)):
        values.insert(k, val)
    f = double_integrator_factor(gtsam, keys, T, 0.5 * a * T**2, a * T, q)
    np.testing.assert_allclose(f.unwhitenedError(values), 0.0, atol=1e-12)
    # Q = int_0^T Phi(s) G q G^T Phi(s)^T ds with Phi(s) = [[I, s I], [0, I]], G = [0; I]
    s = np.linspace(0.0, T, 20001)
    integrand = q * np.array([[s**2, s], [s, np.ones_like(s)]])
    Q1 = np.trapezoid(integrand, s, axis=-1)
    np.testing.assert_allclose(double_integrator_covariance(q, T, 1), Q1, rtol=1e-6)
    # and its Jacobians: the error is linear, so a finite step is exact
    R = gtsam.noiseModel.Gaussian.Covariance(double_integrator_covariance(q, T, d)).R()
    J = np.linalg.solve(R, f.linearize(values).jacobian()[0])  # un-whitened
    for j, k in enumerate(keys):
        numeric = _numeric_jacobian(f, values, k, "point")
        np.testing.assert_allclose(J[:, 3 * j : 3 * j + 3], numeric, atol=1e-6)


# -- the peer on synthetic logs -----------------------------------------------------------


def test_tdoa_alone_on_noise_free_data_recovers_the_trajectory_exactly():
    """A constant velocity, TDOA to six anchors in turn without noise, 2 m off, priors that hardly pull:
    the batch optimum is the truth."""
    x0 = np.concatenate([line(0.0)[0] + [1.5, -1.0, 0.8], np.zeros(3)])
    noise = PeerNoise(range_sigma=0.05, velocity_sigma=100.0)
    est = Isam2Peer(ANCHORS_3D, "none", x0=x0, P0=1e4, noise=noise)

    def measure(t, k, p):
        i, j = k % 6, (k + 1 + (k // 6) % 5) % 6
        d = np.linalg.norm(p - ANCHORS_3D[i]) - np.linalg.norm(p - ANCHORS_3D[j])
        return [Measurement(t, "tdoa", float(d), (i, j))]

    times, errs = run(est, line, measure, rate=25, duration=6.0)
    assert errs[0] > 0.3 and errs[-1] < 1e-3  # online: from metres off to the truth
    T, P = est.batch_trajectory()
    truth = np.array([line(t)[0] for t in T])
    assert np.max(np.linalg.norm(P - truth, axis=1)) < 1e-4  # every node, the first included
    assert est.corrections == len(times)


@pytest.mark.parametrize("dim", [2, 3])
def test_ranges_alone_converge_with_the_constant_velocity_prior(dim):
    rng = np.random.default_rng(dim)
    anchors = ANCHORS_2D if dim == 2 else ANCHORS_3D
    x0 = np.concatenate([circle(0.0, dim)[0] + 3.0, np.zeros(dim)])
    est = Isam2Peer(anchors, "none", x0=x0, P0=25.0, noise=PeerNoise(range_sigma=0.05))
    times, errs = run(est, circle, ranges(anchors, 0.05, rng), rate=25, duration=8.0)
    assert errs[0] > 2.0
    assert rms(errs[times > 3.0]) < 0.15  # a few times the 0.05 m noise, while turning
    T, P = est.batch_trajectory()
    truth = np.array([circle(t, dim)[0] for t in T])
    batch = np.linalg.norm(P - truth, axis=1)
    assert rms(batch[T > 3.0]) < rms(errs[times > 3.0])  # the smoother sees both sides


def test_a_robust_loss_resists_non_line_of_sight_outliers():
    out = {}
    for loss in ("none", "huber", "cauchy"):
        rng = np.random.default_rng(7)  # the same log for each loss
        x0 = np.concatenate([circle(0.0, 2)[0] + 1.0, np.zeros(2)])
        noise = PeerNoise(range_sigma=0.05, loss=loss)
        est = Isam2Peer(ANCHORS_2D, "none", x0=x0, P0=4.0, noise=noise)
        meas = ranges(ANCHORS_2D, 0.05, rng, outliers=0.15)
        times, errs = run(est, circle, meas, rate=25, duration=8.0)
        out[loss] = rms(errs[times > 2.0])
    assert out["huber"] < 0.5 * out["none"] and out["cauchy"] < 0.5 * out["none"], out
    assert out["cauchy"] < 0.15, out


def test_a_bias_per_anchor_is_recovered_as_a_state():
    bias = np.array([0.3, -0.2, 0.1, 0.25, -0.3, 0.0])
    out, est = {}, None
    for mode in ("none", "state"):
        rng = np.random.default_rng(11)
        x0 = np.concatenate([circle(0.0)[0] + 1.0, np.zeros(3)])
        est = Isam2Peer(
            ANCHORS_3D, "none", x0=x0, P0=4.0, noise=PeerNoise(range_sigma=0.05, bias=mode)
        )
        times, errs = run(est, circle, ranges(ANCHORS_3D, 0.05, rng, bias), rate=30, duration=10.0)
        out[mode] = rms(errs[times > 4.0])
    assert np.max(np.abs(est.biases - bias)) < 0.06, est.biases
    assert out["state"] < 0.5 * out["none"], out


def test_ranges_with_a_navigation_frame_accelerometer():
    rng = np.random.default_rng(5)
    x0 = np.concatenate([circle(0.0)[0] + 2.0, np.zeros(3)])
    noise = PeerNoise(range_sigma=0.05, q_imu=1e-3)
    est = Isam2Peer(ANCHORS_3D, "accel_nav", x0=x0, P0=16.0, noise=noise)
    times, errs = run(
        est,
        circle,
        ranges(ANCHORS_3D, 0.05, rng),
        rate=25,
        duration=6.0,
        inputs=lambda t: circle(t)[2] + 0.03 * rng.standard_normal(3),
        imu_rate=100,
    )
    assert errs[0] > 1.0 and rms(errs[times > 2.0]) < 0.06


def _imu(t: float, yaw0: float, yaw_rate: float) -> np.ndarray:
    """The body IMU on the circle, the body yawing at a constant rate: ``f = R^T (a + g e_z)``, ``omega = (0, 0, r)``."""
    _, _, a = circle(t)
    psi = yaw0 + yaw_rate * t
    c, s = math.cos(psi), math.sin(psi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.concatenate([R.T @ (a + [0.0, 0.0, 9.80665]), [0.0, 0.0, yaw_rate]])


def test_ranges_with_body_imu_preintegration_and_an_unknown_yaw():
    rng = np.random.default_rng(3)
    x0 = np.concatenate([circle(0.0)[0] + [2.0, -1.0, 0.5], np.zeros(3)])
    noise = PeerNoise(range_sigma=0.05, q_imu=1e-3)
    est = Isam2Peer(ANCHORS_3D, "imu_body", x0=x0, P0=16.0, noise=noise, heading0=0.0)
    est.hold(_imu(0.0, 0.3, 0.2))
    times, errs = run(
        est,
        circle,
        ranges(ANCHORS_3D, 0.05, rng),
        rate=25,
        duration=5.0,
        inputs=lambda t: _imu(t, 0.3, 0.2),  # the yaw starts 0.3 rad from the guess
        imu_rate=200,
    )
    assert errs[0] > 1.0 and rms(errs[times > 2.0]) < 0.08
    assert est.x_hat.shape == (6,)


def test_planar_odometry_on_the_grid_and_in_time_agree():
    """``step(u, y)`` is the grid's shorthand of ``correct``/``hold``/``predict``: the same graph, the same estimates."""
    rng = np.random.default_rng(9)
    dt, steps = 0.1, 120
    x0 = circle(0.0, 2)[0] + [3.0, -2.0]
    heading0 = math.pi / 2  # the circle's tangent at t = 0
    noise = PeerNoise(range_sigma=0.05, q_xy=0.01)
    a = Isam2Peer(ANCHORS_2D, "odometry", x0=x0, noise=noise, dt=dt, heading0=heading0, P0=25.0)
    b = Isam2Peer(ANCHORS_2D, "odometry", x0=x0, noise=noise, dt=dt, heading0=heading0, P0=25.0)
    c = Isam2Peer(ANCHORS_2D, "odometry", x0=x0, noise=noise, heading0=heading0, P0=25.0)
    a2 = np.einsum("hi,hi->h", ANCHORS_2D, ANCHORS_2D)
    for k in range(steps):
        t = k * dt
        p, v, _ = circle(t, 2)
        y = np.full(4, np.nan)
        if k % 2 == 0:
            h = (k // 2) % 4
            rho = float(np.linalg.norm(p - ANCHORS_2D[h]) + 0.05 * rng.standard_normal())
            y[h] = 0.5 * rho**2 - 0.5 * a2[h]
            b.correct(Measurement(t, "range", rho, (h,)))
            c.correct(Measurement(t, "range", rho, (h,)))
        u = np.array([*v, W])  # the grid's velocity in the odometry's frame, and the yaw rate
        a.step(u, y)
        b.hold(u)
        b.predict((k + 1) * dt)
        c.hold(np.array([2 * W, W]))  # the body's speed and yaw rate
        c.predict((k + 1) * dt)
        np.testing.assert_allclose(a.x_hat, b.x_hat, rtol=0, atol=1e-9)  # times summed apart
    for est in (a, c):
        assert np.linalg.norm(est.x_hat - circle(steps * dt, 2)[0]) < 0.1
    steps_a, P = a.online_positions()
    assert steps_a[1] == 2 and P.shape == (steps // 2, 2)


def test_what_the_peer_cannot_take_is_refused_in_one_line():
    with pytest.raises(QuadobsError, match="imu_body needs a 3-D log"):
        Isam2Peer(ANCHORS_2D, "imu_body", x0=np.zeros(2))
    with pytest.raises(QuadobsError, match="planar odometry needs a 2-D log"):
        Isam2Peer(ANCHORS_3D, "odometry", x0=np.zeros(3))
    with pytest.raises(QuadobsError, match="inputs of kind 'gps'"):
        Isam2Peer(ANCHORS_3D, "gps", x0=np.zeros(3))
    with pytest.raises(QuadobsError, match="loss: expected one of huber, cauchy, none"):
        PeerNoise(loss="tukey")
    with pytest.raises(QuadobsError, match="range_sigma: expected a positive finite number"):
        PeerNoise(range_sigma=0.0)
    with pytest.raises(QuadobsError, match=r"attitude_sigma\[2\]: expected a positive"):
        PeerNoise(attitude_sigma=(0.1, 0.1, math.inf))
    est = Isam2Peer(ANCHORS_3D, "none", x0=np.zeros(3))
    est.predict(1.0)
    with pytest.raises(QuadobsError, match="before its current time"):
        est.predict(0.5)
    with pytest.raises(
        QuadobsError, match="a range measurement at t = 2 s, but the estimate is at 1 s"
    ):
        est.correct(Measurement(2.0, "range", 1.0, (0,)))
    with pytest.raises(QuadobsError, match="anchor index"):
        est.correct(Measurement(1.0, "tdoa", 1.0, (0, 9)))
    with pytest.raises(QuadobsError, match="exclude each other"):
        Isam2Peer(
            ANCHORS_3D, "none", x0=np.zeros(3), noise=PeerNoise(bias="state"), fixed_bias=np.ones(6)
        )
    imu = Isam2Peer(ANCHORS_3D, "imu_body", x0=np.zeros(3))
    with pytest.raises(QuadobsError, match="needs an input held"):
        imu.predict(0.1)


def test_an_update_gtsam_refuses_is_reported_as_lost_not_as_an_estimate(monkeypatch):
    """gtsam's Cholesky declares this graph indeterminate (the reason the double integrator runs
    on QR): the peer says why and its estimate turns NaN, which the replay reports as diverged."""
    from quadobs.estimators import gtsam_motion

    monkeypatch.setattr(gtsam_motion.DoubleIntegratorMotion, "factorization", "CHOLESKY")
    est = Isam2Peer(
        ANCHORS_3D,
        "none",
        x0=np.array([9.0, 0.0, 2.5, 0.0, 0.0, 0.0]),
        P0=100.0,
        noise=PeerNoise(range_sigma=0.05),
    )
    est.predict(0.02)
    est.correct(Measurement(0.02, "range", 6.0, (1,)))
    assert np.all(np.isnan(est.x_hat))
    assert est.failure.startswith("iSAM2 update at t = 0.02 s failed: Indeterminate linear system")
    est.predict(0.04)  # time still moves on; nothing more is solved
    est.correct(Measurement(0.04, "range", 6.0, (2,)))
    assert np.all(np.isnan(est.x_hat)) and np.all(np.isnan(est.batch_trajectory()[1]))


def test_the_replay_names_what_a_log_has_that_the_peer_cannot_take():
    from quadobs.testbed.logs.peer import check_peer, peer_input_kind

    assert peer_input_kind("imu") == "accel_nav" and peer_input_kind("none") == "none"
    for kind, dim in (("odometry", 2), ("imu", 2), ("imu", 3), ("none", 2), ("imu_body", 3)):
        check_peer(kind, dim)  # taken
    with pytest.raises(QuadobsError, match=r"^estimators: 'isam2' cannot take a log with a body"):
        check_peer("imu_body", 2)


def test_the_start_of_a_log_moves_the_first_node():
    rng = np.random.default_rng(0)
    est = Isam2Peer(ANCHORS_3D, "none", x0=np.concatenate([line(0.0)[0], np.zeros(3)]), P0=1.0)
    est.time = 1000.0  # a log's clock
    for k in range(1, 50):
        t = 1000.0 + k / 25
        est.predict(t)
        p = line(t - 1000.0)[0]
        rho = float(np.linalg.norm(p - ANCHORS_3D[k % 6]) + 0.01 * rng.standard_normal())
        est.correct(Measurement(t, "range", rho, (k % 6,)))
    times, _ = est.online_trajectory()
    assert times[0] == 1000.0 and times[1] == pytest.approx(1000.04)
    assert np.linalg.norm(est.x_hat[:3] - line(49 / 25)[0]) < 0.1
    with pytest.raises(QuadobsError, match="only before the first correction"):
        est.time = 0.0


def test_nodes_in_time_reach_the_grid_by_interpolation_over_short_gaps_only():
    est = Isam2Peer(ANCHORS_2D, "none", x0=np.zeros(2), dt=0.1)
    T = np.array([0.0, 0.25, 0.5, 3.0, 3.2])
    P = np.column_stack([T, 2 * T])  # a straight line: interpolation is exact on it
    k, Q = est._on_grid(T, P)
    t = k * 0.1
    assert np.all((t <= 0.5 + 1e-9) | (t >= 3.0 - 1e-9))  # none across the 2.5 s gap
    assert k[0] == 0 and k[-1] == 32 and 30 in k
    np.testing.assert_allclose(Q, np.column_stack([t, 2 * t]), atol=1e-12)


def test_a_body_imu_in_a_north_east_down_frame():
    """At rest in a z-down frame the accelerometer reads ``-g`` along the body's z."""
    p = np.array([3.0, 2.0, -1.5])
    anchors = ANCHORS_3D * [1.0, 1.0, -1.0]
    errors = {}
    for frame in ("ned", "enu"):
        x0 = np.r_[p + 0.5, np.zeros(3)]
        noise = PeerNoise(range_sigma=0.01, frame=frame)
        est = Isam2Peer(anchors, "imu_body", x0=x0, P0=1.0, noise=noise)
        est.hold(np.array([0.0, 0.0, -9.80665, 0.0, 0.0, 0.0]))
        for k in range(1, 61):
            t = k / 30
            est.predict(t)
            rho = float(np.linalg.norm(p - anchors[k % 6]))
            est.correct(Measurement(t, "range", rho, (k % 6,)))
        errors[frame] = float(np.linalg.norm(est.x_hat[:3] - p))
    assert errors["ned"] < 0.02 and errors["enu"] > 10 * errors["ned"], errors
    with pytest.raises(QuadobsError, match="frame: expected 'enu' or 'ned'"):
        PeerNoise(frame="nwu")


def test_a_graph_built_without_isam2_has_the_same_batch_optimum():
    """``online=False`` builds the same graph without iSAM2's updates: Levenberg-Marquardt
    from the inputs' propagation reaches the optimum it reaches from iSAM2's estimate."""
    bias = np.array([0.3, -0.2, 0.1, 0.25, -0.3, 0.0])
    out = {}
    for online in (True, False):
        rng = np.random.default_rng(7)
        x0 = np.concatenate([circle(0.0)[0] + 1.0, np.zeros(3)])
        noise = PeerNoise(range_sigma=0.05, q_imu=1e-3, bias="state")
        est = Isam2Peer(ANCHORS_3D, "accel_nav", x0=x0, P0=4.0, noise=noise, online=online)
        run(
            est,
            circle,
            ranges(ANCHORS_3D, 0.05, rng, bias),
            rate=25,
            duration=4.0,
            inputs=lambda t, rng=rng: circle(t)[2] + 0.03 * rng.standard_normal(3),
            imu_rate=100,
        )
        out[online] = est.batch_trajectory(), est
    (t_on, p_on), on = out[True]
    (t_off, p_off), off = out[False]
    assert off.isam.size() == 0 and on.isam.size() > 0
    assert np.array_equal(t_on, t_off)
    # the same optimum up to Levenberg-Marquardt's stopping tolerance (1e-5 relative in the cost)
    assert np.max(np.abs(p_on - p_off)) < 1e-3, np.max(np.abs(p_on - p_off))
    # ... from a start (the inputs' propagation from the guess 1.7 m off) far from it
    _, p_start = off._positions(off.values)
    assert np.max(np.linalg.norm(p_start - p_off, axis=1)) > 1.0
    # no iSAM2 estimate to give: refused, not the propagation passed off as one
    for what in ("online_trajectory", "biases"):
        with pytest.raises(QuadobsError, match=f"{what}: the peer was built with online=False"):
            getattr(off, what)() if what == "online_trajectory" else off.biases
