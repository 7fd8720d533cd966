"""The block path of an episode against the per-step path: the same rows, records and summaries, bit for bit."""

import json

import numpy as np
import pytest

from quadobs import load_scenario
from quadobs.estimators.base import BlockStep
from quadobs.recording import read_series
from quadobs.testbed.episode import WALL_CLOCK_KEYS, _Episode, run_episode, scenario_parts
from quadobs.testbed.factories import augmented_observer
from quadobs.testbed.sensors import SensorModel, spawn_streams
from quadobs.testbed.worlds import PointMassWorld

pytest.importorskip("numba")


def _summary(result) -> str:
    return json.dumps({k: v for k, v in result.summary.items() if k not in WALL_CLOCK_KEYS}, sort_keys=True)


@pytest.mark.parametrize("name", ["ifac2021", "wind", "ifac2021-outliers", "beacons2d"])
def test_world_fills_a_block_as_its_steps_would(name):
    """One rollout and one compiled read per block write the rows of ``mj_step`` and a read per step."""
    sc = load_scenario(name)
    rows = {}
    for mode in ("step", "block"):
        world = PointMassWorld(sc, SensorModel(sc, spawn_streams(sc.seed)), 700)
        assert world.stepper._rollout is not None
        out = []
        for k0 in range(0, 2000, 700):
            count = world.begin_block(k0, min(700, 2000 - k0))
            if mode == "step":
                for j in range(count):
                    world.step(j)
            else:
                world.fill(count)
            world.commit(count)
            out.append(world.out[: count + 1].copy())
            out.append(world.events[:count].astype(float))
        rows[mode] = np.concatenate([o.ravel() for o in out])
    np.testing.assert_array_equal(rows["step"], rows["block"])


def test_step_block_equals_step_and_record_row_by_row():
    sc = load_scenario("ifac2021-noisy")
    rng = np.random.default_rng(3)
    m, n, q, p = 3000, sc.state_dim, sc.beacons.shape[0], sc.dimension
    raw = rng.normal(0.0, 50.0, (m, q + p + 1))
    raw[:, :q][rng.uniform(size=(m, q)) < 0.4] = np.nan  # missing outputs
    Y, U = raw[:, :q], raw[:, q : q + p]  # strided views, as an episode passes them
    one, blocked = (augmented_observer(sc, np.zeros(n)) for _ in range(2))
    assert isinstance(blocked, BlockStep) and blocked.blockwise
    r1, r2 = np.zeros((m, n + 3)), np.zeros((m, n + 3))
    for j in range(m):
        one.step_and_record(U[j], Y[j], r1[j])
    for j0, j1 in ((0, 1), (1, 1000), (1000, m)):
        blocked.step_block(U[j0:j1], Y[j0:j1], r2[j0:j1])
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(one.P, blocked.P)
    assert one.corrections == blocked.corrections > 0


def test_step_block_checks_its_operands():
    from quadobs import QuadobsError

    sc = load_scenario("ifac2021")
    obs = augmented_observer(sc, np.zeros(sc.state_dim))
    with pytest.raises(QuadobsError, match="out"):
        obs.step_block(np.zeros((4, 3)), np.zeros((4, 1)), np.zeros((3, sc.state_dim + 3)))
    with pytest.raises(QuadobsError, match="U"):
        obs.step_block(np.zeros((4, 2)), np.zeros((4, 1)), np.zeros((4, sc.state_dim + 3)))


CASES = [
    ("ifac2021", None, 9.0, 0),  # crosses block boundaries (1024 and 9216 steps)
    ("beacons", None, 3.0, 0),
    ("wind", None, 3.0, 7),  # with the traces (a sink due every 7 steps)
    ("ifac2021-noisy", ["augmented", "ekf", "ukf"], 2.0, 0),
    ("ifac2021-outliers", None, 9.0, 0),  # the gate
    ("ifac2021-bounded", ["augmented", "zonotope"], 1.0, 0),
    ("degenerate", None, 30.0, 0),  # the excitation monitor
]


@pytest.mark.parametrize(("name", "estimators", "duration", "every"), CASES, ids=[c[0] for c in CASES])
def test_block_and_per_step_paths_give_the_same_summary(name, estimators, duration, every):
    sc = load_scenario(name, duration=duration)
    step = run_episode(sc, estimators=estimators, path="step", collect_every=every)
    block = run_episode(sc, estimators=estimators, collect_every=every)
    assert _summary(step) == _summary(block)
    if every:
        for key, value in step.trace.items():
            if isinstance(value, dict):
                for est, arr in value.items():
                    np.testing.assert_array_equal(arr, block.trace[key][est])
            else:
                np.testing.assert_array_equal(value, block.trace[key])


def test_the_block_path_is_the_default_for_compiled_estimators_in_an_open_loop_world():
    def episode(sc, names, path="auto"):
        return _Episode(**scenario_parts(sc, names), path=path)

    sc = load_scenario("ifac2021-noisy", duration=0.1)
    assert episode(sc, ["augmented"]).blockwise
    assert not episode(sc, ["augmented"], "step").blockwise
    assert not episode(sc, ["augmented", "ekf"]).blockwise  # a Python estimator: per step
    bounded = load_scenario("ifac2021-bounded", duration=0.1)
    assert not episode(bounded, ["augmented", "zonotope"]).blockwise  # bounds of every row


def test_recordings_of_the_two_paths_hold_the_same_series(tmp_path):
    sc = load_scenario("ifac2021-outliers", duration=9.0)
    for path in ("step", "auto"):
        run_episode(sc, out=tmp_path / f"{path}.rrd", path=path)
    for entity in ("errors/augmented/position/norm", "observer/augmented/nis", "measurements/dropped", "measurements/accelerometer"):
        a, b = read_series(tmp_path / "step.rrd", entity), read_series(tmp_path / "auto.rrd", entity)
        np.testing.assert_array_equal(a["step"], b["step"])
        np.testing.assert_array_equal(a["values"], b["values"])


def test_path_is_checked():
    from quadobs import QuadobsError

    with pytest.raises(QuadobsError, match="path"):
        run_episode(load_scenario("ifac2021", duration=0.01), path="fast")


def _serial(scenario, sensors, capacity):
    return PointMassWorld(scenario, sensors, capacity, pipelined=False)


@pytest.mark.parametrize("name", ["ifac2021-outliers", "wind"])
def test_pipelined_physics_gives_the_same_bits(tmp_path, name):
    """The next block's physics computed in a background thread: the same summary and recording as in the loop's thread."""
    sc = load_scenario(name, duration=20.0)  # three blocks
    runs = {}
    for label, world in (("pipelined", None), ("serial", _serial)):
        (tmp_path / label).mkdir()
        rrd = tmp_path / label / "run.rrd"
        runs[label] = (_summary(run_episode(sc, out=rrd, world=world)), read_series(rrd, "errors/augmented/position/norm"))
    assert runs["pipelined"][0].replace(str(tmp_path / "pipelined"), "") == runs["serial"][0].replace(str(tmp_path / "serial"), "")
    for key in ("step", "values"):
        np.testing.assert_array_equal(runs["pipelined"][1][key], runs["serial"][1][key])


@pytest.mark.parametrize("pipelined", [True, False])
def test_a_fault_in_the_block_computed_ahead_is_reported_for_its_block(monkeypatch, pipelined):
    """A control MuJoCo refuses at step 9000 (second block): the block before it completes and is kept, the error
    names the second block, whether its physics ran ahead in the background or not."""
    from quadobs.testbed.worlds.model import PhysicsFault

    accelerations = PointMassWorld._accelerations

    def spiked(self, k0, count):
        acc = accelerations(self, k0, count)
        if k0 <= 9000 < k0 + count:
            acc[9000 - k0] = 1e12  # a force MuJoCo refuses (bad ctrl): it zeroes it
        return acc

    monkeypatch.setattr(PointMassWorld, "_accelerations", spiked)
    world = None if pipelined else _serial
    with pytest.raises(PhysicsFault, match=r"badctrl .* (between step 1024 and step 9216|at step 900[01]) ") as info:
        run_episode(load_scenario("ifac2021", duration=20.0), world=world)
    assert "step 0 " not in str(info.value)
