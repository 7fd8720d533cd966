"""The GTSAM peer's keyframes: a TDOA or a range taken after its node is placed on the node's
position and velocity at its own time (the Jacobians against finite differences, exact on a
constant velocity); iSAM2 updates once per node (TDOA) or with each range, and the replay
keeps a node every 0.1 s wherever a node has a velocity."""

from __future__ import annotations

import numpy as np
import pytest

from quadobs.core.measurements import Measurement

gtsam = pytest.importorskip("gtsam", reason="gtsam is not installed (the data extra)")

from quadobs.errors import QuadobsError  # noqa: E402
from quadobs.estimators.gtsam_factors import range_factor, tdoa_factor  # noqa: E402
from quadobs.estimators.gtsam_peer import Isam2Peer, PeerNoise  # noqa: E402
from quadobs.testbed.logs.peer import KEY_PERIOD, TDOA_KEY_PERIOD, keyframes  # noqa: E402

ANCHORS = np.array(
    [[0, 0, 0.2], [8, 0, 2.5], [8, 6, 0.3], [0, 6, 2.8], [4, -1, 1.5], [4, 7, 0.5]], float
)
P0, V = np.array([2.0, 1.0, 1.0]), np.array([0.4, 0.3, 0.05])


def _tangent_difference(factor, values, key, kind, eps=1e-6):
    """Central differences of the factor's error along the tangent of ``key``."""

    def at(delta):
        v = gtsam.Values(values)
        if kind == "pose3":
            v.update(key, values.atPose3(key).retract(delta))
        else:
            v.update(key, values.atVector(key) + delta)
        return factor.unwhitenedError(v)

    n = 6 if kind == "pose3" else 3
    return np.column_stack([(at(eps * e) - at(-eps * e)) / (2 * eps) for e in np.eye(n)])


def _node_values(kind: str, seed: int):
    """A node's position (a vector or a ``Pose3``) and velocity, drawn: their keys and values."""
    rng = np.random.default_rng(seed)
    x, v = gtsam.symbol("x", 0), gtsam.symbol("v", 0)
    values = gtsam.Values()
    if kind == "pose3":
        values.insert(x, gtsam.Pose3(gtsam.Rot3.RzRyRx(*rng.uniform(-1, 1, 3)), rng.normal(size=3)))
    else:
        values.insert(x, rng.normal(size=3))
    values.insert(v, rng.normal(size=3))
    return x, v, values


@pytest.mark.parametrize("kind", ["point", "pose3"])
def test_a_tdoa_after_its_node_has_the_jacobians_of_its_position_and_velocity(kind):
    x, v, values = _node_values(kind, 2)
    noise = gtsam.noiseModel.Unit.Create(1)
    factor = tdoa_factor(gtsam, noise, x, kind, ANCHORS[0], ANCHORS[3], 0.4, v, 0.07)
    A = factor.linearize(values).jacobian()[0]
    np.testing.assert_allclose(A[:, :-3], _tangent_difference(factor, values, x, kind), atol=1e-6)
    np.testing.assert_allclose(
        A[:, -3:], _tangent_difference(factor, values, v, "point"), atol=1e-6
    )
    # the position 0.07 s on: the error is that of a factor on p + 0.07 v
    p = values.atPose3(x).translation() if kind == "pose3" else values.atVector(x)
    p = np.asarray(p) + 0.07 * values.atVector(v)
    d = np.linalg.norm(p - ANCHORS[0]) - np.linalg.norm(p - ANCHORS[3])
    assert abs(factor.unwhitenedError(values)[0] - (d - 0.4)) < 1e-12


def _constant_velocity_tdoa(key_period: float):
    """TDOA at 50 Hz without noise on a constant velocity, the peer 1.5 m off."""
    noise = PeerNoise(range_sigma=0.05, velocity_sigma=100.0, key_period=key_period)
    est = Isam2Peer(ANCHORS, "none", x0=np.r_[P0 + [1.5, -1.0, 0.8], 0, 0, 0], P0=1e4, noise=noise)
    updates = []
    update = est.isam.update

    class Counting:  # the ISAM2 object's update, counted
        def __getattr__(self, name):
            return getattr(est.isam_inner, name)

        def update(self, *args):
            updates.append(est.time)
            return update(*args)

    est.isam_inner, est.isam = est.isam, Counting()
    for k in range(1, 301):
        t = k * 0.02
        est.predict(t)
        p = P0 + V * t
        i, j = k % 6, (k + 1 + (k // 6) % 5) % 6
        d = np.linalg.norm(p - ANCHORS[i]) - np.linalg.norm(p - ANCHORS[j])
        est.correct(Measurement(t, "tdoa", float(d), (i, j)))
        _ = est.x_hat  # read every step, as the replay does
    return est, updates


def test_keyframes_are_exact_on_a_constant_velocity_and_update_once_a_node():
    every, updates = _constant_velocity_tdoa(0.0)
    keyed, key_updates = _constant_velocity_tdoa(0.1)
    assert len(every.node_times) == 301 and len(updates) >= 300  # a node, an update a TDOA
    # a node opens with the first TDOA more than 0.1 s after the last (six TDOA each): one
    # update a node
    assert len(keyed.node_times) == 51 and len(key_updates) <= 51
    T, P = keyed.batch_trajectory()
    truth = P0 + V * np.asarray(T)[:, None]
    assert np.max(np.linalg.norm(P - truth, axis=1)) < 1e-4  # the offsets: exact, not v tau off
    assert np.linalg.norm(keyed.x_hat[:3] - (P0 + V * 6.0)) < 1e-3
    assert TDOA_KEY_PERIOD == 0.1


@pytest.mark.parametrize("kind", ["point", "pose3"])
@pytest.mark.parametrize("with_bias", [False, True])
def test_a_range_after_its_node_has_the_jacobians_of_its_position_velocity_and_bias(
    kind, with_bias
):
    x, v, values = _node_values(kind, 3)
    b = gtsam.symbol("r", 0)
    values.insert(b, np.array([0.3]))
    noise = gtsam.noiseModel.Unit.Create(1)
    bias_key = b if with_bias else None
    factor = range_factor(gtsam, noise, x, kind, ANCHORS[1], 5.0, bias_key, v, 0.06)
    A = factor.linearize(values).jacobian()[0]
    n = 6 if kind == "pose3" else 3
    np.testing.assert_allclose(A[:, :n], _tangent_difference(factor, values, x, kind), atol=1e-6)
    np.testing.assert_allclose(
        A[:, -3:], _tangent_difference(factor, values, v, "point"), atol=1e-6
    )
    if with_bias:
        np.testing.assert_allclose(A[:, n], [1.0])
    p = values.atPose3(x).translation() if kind == "pose3" else values.atVector(x)
    p = np.asarray(p) + 0.06 * values.atVector(v)
    expected = np.linalg.norm(p - ANCHORS[1]) + (0.3 if with_bias else 0.0) - 5.0
    assert abs(factor.unwhitenedError(values)[0] - expected) < 1e-12


def _constant_velocity_ranges(key_period: float, updates: str):
    """Ranges at 50 Hz without noise (the anchors in turn) on a constant velocity, the peer
    1.5 m off; iSAM2's updates counted."""
    noise = PeerNoise(
        range_sigma=0.05, velocity_sigma=100.0, key_period=key_period, updates=updates
    )
    est = Isam2Peer(ANCHORS, "none", x0=np.r_[P0 + [1.5, -1.0, 0.8], 0, 0, 0], P0=1e4, noise=noise)
    updates_at = []
    inner = est.isam

    class Counting:  # the ISAM2 object's update, counted
        def __getattr__(self, name):
            return getattr(inner, name)

        def update(self, *args):
            updates_at.append(est.time)
            return inner.update(*args)

    est.isam = Counting()
    for k in range(1, 301):
        t = k * 0.02
        est.predict(t)
        h = k % len(ANCHORS)
        rho = np.linalg.norm(P0 + V * t - ANCHORS[h])
        est.correct(Measurement(t, "range", float(rho), (h,)))
        _ = est.x_hat  # read every step, as the replay does
    return est, updates_at


def test_ranges_on_keyframes_are_exact_and_update_with_each_range():
    keyed, updates = _constant_velocity_ranges(0.1, "measurement")
    # a node opens with the first range more than 0.1 s after the last: six ranges each
    assert len(keyed.node_times) == 51
    assert len(updates) >= 300  # every range reaches the online estimate as it comes
    T, P = keyed.batch_trajectory()
    truth = P0 + V * np.asarray(T)[:, None]
    assert np.max(np.linalg.norm(P - truth, axis=1)) < 1e-4  # exact, not v tau off
    assert np.linalg.norm(keyed.x_hat[:3] - (P0 + V * 6.0)) < 1e-3
    # once a node: the node's ranges reach iSAM2 when the next node opens
    _, node_updates = _constant_velocity_ranges(0.1, "node")
    assert len(node_updates) <= 51


def test_the_replay_keeps_a_node_every_tenth_of_a_second_where_a_node_has_a_velocity():
    assert KEY_PERIOD == 0.1 and TDOA_KEY_PERIOD == KEY_PERIOD
    for kind in ("imu_body", "imu", "none"):
        assert keyframes(kind, ("range",)) == {"key_period": 0.1, "updates": "measurement"}
    assert keyframes("odometry", ("range",)) == {"key_period": 0.0, "updates": "node"}
    for kind in ("odometry", "imu_body", "none"):
        assert keyframes(kind, ("tdoa",)) == {"key_period": 0.1, "updates": "node"}
    with pytest.raises(QuadobsError, match="updates: expected 'node' or 'measurement'"):
        PeerNoise(updates="range")


def test_keyframes_stepped_on_the_grid_give_a_position_at_every_step():
    """On the grid (``step``) with keyframes the nodes are some steps apart: the smoothed and
    batch figures interpolate between them to every step, as in time."""
    noise = PeerNoise(range_sigma=0.05, velocity_sigma=100.0, key_period=0.1)
    x0 = np.r_[P0 + [0.5, -0.4, 0.3], 0, 0, 0]
    est = Isam2Peer(ANCHORS, "accel_nav", x0=x0, P0=1e4, noise=noise, dt=0.02)
    a2 = np.einsum("hi,hi->h", ANCHORS, ANCHORS)
    for k in range(300):
        y = np.full(len(ANCHORS), np.nan)
        h = k % len(ANCHORS)
        rho = np.linalg.norm(P0 + V * (k * 0.02) - ANCHORS[h])
        y[h] = 0.5 * rho**2 - 0.5 * a2[h]
        est.step(np.zeros(3), y)
    assert len(est.node_times) < 60  # about one node in six steps
    k, P = est.batch_optimum()
    last = round((est.node_times[-1] - est.node_times[0]) / 0.02)
    assert last >= 294  # every step to the last node's
    np.testing.assert_array_equal(k, np.arange(last + 1))
    truth = P0 + V * (k * 0.02)[:, None]
    assert np.max(np.linalg.norm(P - truth, axis=1)) < 1e-3
