"""The world interface and the episode loop over it: a closed-loop world, and the summary
against the trace collected beside it."""

import numpy as np
import pytest

from quadobs import QuadobsError, load_scenario
from quadobs.recording import read_series
from quadobs.testbed.episode import run_episode
from quadobs.testbed.sinks import merge
from quadobs.testbed.worlds import Columns, PointMassWorld, World


class SteeredPointMass(World):
    """A double integrator ranging to the scenario's beacons, steered by an estimate to ``target``.

    Row ``j``: the truth ``(p, v)``, ``y_h = |p - a_h|^2 / 2 - |a_h|^2 / 2`` and the applied
    acceleration ``u = -kp (p_hat - target) - kd v_hat`` computed from the estimate it is given.
    """

    closed_loop = True
    controller = "augmented"

    def __init__(self, scenario, sensors, capacity, target, kp=1.0, kd=2.0):
        d, qb = scenario.dimension, scenario.beacons.shape[0]
        self.dim, self.a, self.dt = d, scenario.beacons, scenario.dt
        self.target, self.kp, self.kd = np.asarray(target, dtype=float), kp, kd
        self.columns = Columns(
            truth=slice(0, 2 * d),
            y=slice(2 * d, 2 * d + qb),
            u=slice(2 * d + qb, 3 * d + qb),
            measured=slice(3 * d + qb, 3 * d + 2 * qb),
            width=3 * d + 2 * qb,
        )
        self.out = np.zeros((capacity + 1, self.columns.width))
        self.events = np.zeros((capacity + 1, 2), dtype=np.int64)
        traj = scenario.trajectory
        self.x = np.concatenate([traj.position(0.0), traj.velocity_at(0.0)])
        self.given = []

    def state(self):
        return self.x.copy()

    def begin_block(self, k0, count):
        self.out[0, self.columns.truth] = self.x
        return count

    def step(self, j, estimate=None):
        d, c, row = self.dim, self.columns, self.out[j]
        self.given.append(np.array(estimate))
        p, v = self.x[:d], self.x[d:]
        rho = np.linalg.norm(p - self.a, axis=1)
        row[c.measured] = rho
        row[c.y] = 0.5 * rho**2 - 0.5 * np.einsum("hi,hi->h", self.a, self.a)
        acc = -self.kp * (estimate[:d] - self.target) - self.kd * estimate[d : 2 * d]
        row[c.u] = acc
        self.x = np.concatenate([p + v * self.dt + 0.5 * acc * self.dt**2, v + acc * self.dt])
        self.out[j + 1, c.truth] = self.x


def test_a_closed_loop_world_is_steered_by_the_named_estimate():
    """The world gets x_hat_k of `augmented` before each step (the trace's row k) and its
    controls use it: the vehicle ends at the target, far from the open-loop trajectory."""
    sc = load_scenario("beacons", duration=12.0)
    target = np.array([5.0, -3.0, 2.0])
    worlds = []

    def make(scenario, sensors, capacity):
        worlds.append(SteeredPointMass(scenario, sensors, capacity, target))
        return worlds[0]

    res = run_episode(
        sc, estimators=["augmented", "augmented_1beacon"], collect_every=1, world=make
    )
    w = worlds[0]
    assert len(w.given) == sc.steps
    np.testing.assert_array_equal(np.array(w.given), res.trace["estimates"]["augmented"][:-1])
    np.testing.assert_allclose(res.trace["truth"][-1, :3], target, atol=0.05)
    assert np.linalg.norm(sc.trajectory.position(sc.duration) - target) > 10.0
    assert res.summary["final_position_error"] < 0.05
    with pytest.raises(QuadobsError, match="closed-loop"):
        w.fill(3)


def test_the_world_controller_must_name_an_estimator_of_the_episode():
    sc = load_scenario("beacons", duration=0.1)

    def make(scenario, sensors, capacity):
        w = SteeredPointMass(scenario, sensors, capacity, np.zeros(3))
        w.controller = "ekf"
        return w

    with pytest.raises(QuadobsError, match="world.controller"):
        run_episode(sc, estimators=["augmented"], world=make)


def test_columns_are_checked():
    with pytest.raises(QuadobsError, match="columns.measured"):
        Columns(truth=slice(0, 4), y=slice(4, 6), u=slice(6, 8), measured=slice(8, 12), width=10)


def test_the_point_mass_world_fills_a_block_like_step_by_step():
    """fill(count) and step(j) one at a time give the same rows (open loop)."""
    from quadobs.testbed.sensors import SensorModel, spawn_streams

    sc = load_scenario("ifac2021-outliers", duration=0.5)
    rows = []
    for by_step in (False, True):
        w = PointMassWorld(sc, SensorModel(sc, spawn_streams(sc.seed)), 600)
        assert not w.closed_loop and w.columns.n == 6
        count = w.begin_block(0, sc.steps)
        if by_step:
            for j in range(count):
                w.step(j)
        else:
            w.fill(count)
        w.commit(count)
        rows.append((w.out[: count + 1].copy(), w.events[:count].copy()))
    np.testing.assert_array_equal(rows[0][0], rows[1][0])
    np.testing.assert_array_equal(rows[0][1], rows[1][1])


def test_summary_agrees_with_the_collected_trace_and_the_recording(tmp_path):
    """Every figure of the summary recomputed from the trace of every step: final errors,
    convergence times, and each gate's rejections (NIS above the gate) against the
    estimator's own counter, which the recording's running count ends on too."""
    sc = load_scenario("ifac2021-outliers", duration=3.0)
    rrd = tmp_path / "o.rrd"
    res = run_episode(sc, estimators=["augmented", "ekf", "ukf"], collect_every=1, out=rrd)
    s, tr = res.summary, res.trace
    X, t = tr["truth"], tr["time"]
    assert s["physics_steps"] == sc.steps and len(t) == sc.steps + 1
    gated = 0
    for name, entry in s["estimators"].items():
        e = tr["estimates"][name] - X
        ep = np.linalg.norm(e[:, :3], axis=1)
        assert entry["final_position_error"] == pytest.approx(ep[-1], rel=1e-12)
        assert entry["final_velocity_error"] == pytest.approx(np.linalg.norm(e[-1, 3:6]), rel=1e-12)
        for key, c in (("time_to_1m", 1.0), ("time_to_0p1m", 0.1)):
            above = np.flatnonzero(~(ep < c))
            expected = (
                None
                if above.size and above[-1] == len(ep) - 1
                else round(t[above[-1] + 1] if above.size else t[0], 9)
            )
            assert entry[key] == expected
        if entry.get("gate") is not None:
            with np.errstate(invalid="ignore"):
                hits = int(np.sum(tr["nis"][name] > entry["gate"]))
            assert entry["rejected"] == hits
            rejected = read_series(rrd, f"observer/{name}/rejected")["values"][:, 0]
            assert rejected[-1] == hits and np.all(np.diff(rejected) >= 0)
            gated += hits > 0
    assert gated >= 1  # the outliers do trip a gate: the comparison is not vacuous


def test_merge_is_recursive_and_later_fragments_win():
    assert merge([{"a": {"b": 1, "c": 2}, "d": 1}, {"a": {"c": 3}, "d": {"e": 1}}]) == {
        "a": {"b": 1, "c": 3},
        "d": {"e": 1},
    }
