"""The block path of an episode against the per-step path: the same rows, records and summaries, bit for bit."""

import json
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quadobs import load_scenario
from quadobs.estimators.base import BlockStep
from quadobs.recording import read_series
from quadobs.testbed.blocks import LEAD, TAIL, block_count
from quadobs.testbed.episode import WALL_CLOCK_KEYS, _Episode, run_episode, scenario_parts
from quadobs.testbed.factories import augmented_observer
from quadobs.testbed.sensors import SensorModel, spawn_streams
from quadobs.testbed.worlds import PointMassWorld

pytest.importorskip("numba")


def _summary(result) -> str:
    return json.dumps(
        {k: v for k, v in result.summary.items() if k not in WALL_CLOCK_KEYS}, sort_keys=True
    )


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


@pytest.mark.parametrize(
    ("name", "estimators", "duration", "every"), CASES, ids=[c[0] for c in CASES]
)
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
    for entity in (
        "errors/augmented/position/norm",
        "observer/augmented/nis",
        "measurements/dropped",
        "measurements/accelerometer",
    ):
        a, b = (
            read_series(tmp_path / "step.rrd", entity),
            read_series(tmp_path / "auto.rrd", entity),
        )
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
        runs[label] = (
            _summary(run_episode(sc, out=rrd, world=world)),
            read_series(rrd, "errors/augmented/position/norm"),
        )
    assert runs["pipelined"][0].replace(str(tmp_path / "pipelined"), "") == runs["serial"][
        0
    ].replace(str(tmp_path / "serial"), "")
    for key in ("step", "values"):
        np.testing.assert_array_equal(runs["pipelined"][1][key], runs["serial"][1][key])


@pytest.mark.parametrize("pipelined", [True, False])
def test_a_fault_in_the_block_computed_ahead_is_reported_for_its_block(monkeypatch, pipelined):
    """A control MuJoCo refuses at step 9000 (third block): the blocks before it complete and are kept, the error
    names the step, whether its physics ran ahead in the background or not."""
    from quadobs.testbed.worlds.model import PhysicsFault

    accelerations = PointMassWorld._accelerations

    def spiked(self, k0, count):
        acc = accelerations(self, k0, count)
        if k0 <= 9000 < k0 + count:
            acc[9000 - k0] = 1e12  # a force MuJoCo refuses (bad ctrl): it zeroes it
        return acc

    monkeypatch.setattr(PointMassWorld, "_accelerations", spiked)
    world = None if pipelined else _serial
    with pytest.raises(PhysicsFault, match=r"badctrl .* at step 9001 ") as info:
        run_episode(load_scenario("ifac2021", duration=20.0), world=world)
    assert "step 0 " not in str(info.value)


def _dummies() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if isinstance(t, threading._DummyThread)}


def _physics_threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name == "quadobs-physics"}


def test_one_physics_thread_per_reading_thread_kept_across_episodes():
    """The episodes one thread reads share one physics thread, which ends when that thread ends."""
    sc = load_scenario("ifac2021", duration=3.0)
    before, dummies = _physics_threads(), _dummies()
    seen = []

    def reader():
        for _ in range(3):
            run_episode(sc)
            seen.append(_physics_threads() - before)

    for _ in range(2):  # two reading threads, one after the other
        thread = threading.Thread(target=reader)
        thread.start()
        thread.join()
    first, second = seen[0], seen[3]
    assert len(first) == len(second) == 1 and first != second
    assert seen[:3] == [first] * 3 and seen[3:] == [second] * 3
    deadline = time.monotonic() + 5.0
    while _physics_threads() - before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not _physics_threads() - before
    assert _dummies() == dummies  # ending them registered no placeholder thread


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="fork")
def test_a_forked_child_gets_its_own_physics_thread_and_exits(tmp_path):
    """A process forked after episodes ran (its parent's physics thread does not exist in it) runs one and exits."""
    import subprocess
    import sys

    script = (
        "import os, sys\n"
        "from quadobs import load_scenario\n"
        "from quadobs.testbed.episode import run_episode\n"
        "sc = load_scenario('ifac2021', duration=3.0)\n"
        "run_episode(sc)\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    print(run_episode(sc).summary['physics_steps'], flush=True)\n"
        "    sys.exit(0)\n"
        "sys.exit(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.split() == ["3000"], done.stderr


def test_blocks_queued_ahead_are_undone_when_another_block_begins():
    """Three blocks queued on the physics thread, then a block that is not theirs begins: the data is back at
    the start of the first one queued, and the new block gives the rows that block would have given."""
    sc = load_scenario("ifac2021", duration=5.0)

    def world():
        w = PointMassWorld(sc, SensorModel(sc, spawn_streams(sc.seed)), 1024)
        w.prepare("block")
        return w

    ref = world()
    ref.begin_block(0, 1024)
    ref.fill(1024)
    expected = ref.out[: 1024 + 1].copy()
    ref.close()
    w = world()
    w.stepper.follow_data(0)
    for k in (0, 512, 1024):  # queued, not begun
        w.stepper.prefetch(w._accelerations(k, 512), k)
    assert not w.stepper.can_prefetch()
    w._queue = False
    assert (
        w.begin_block(0, 1024) == 1024
    )  # not the queued blocks' boundaries: undone, computed in this thread
    w.fill(1024)
    np.testing.assert_array_equal(
        w.out[: 1024 + 1][:, w.stepper.truth], expected[:, ref.stepper.truth]
    )
    w.close()


@settings(max_examples=200, deadline=None)
@given(steps=st.integers(1, 300000), capacity=st.sampled_from([300, 700, 1024, 8192]))
def test_block_schedule(steps, capacity):
    """Blocks cover the episode once; the first has at most LEAD steps, the others at most ``capacity`` and at least
    TAIL (but the last), each at least three quarters of the one before (but where ``capacity`` caps it)."""
    k, blocks = 0, []
    while k < steps:
        blocks.append(block_count(k, steps, capacity))
        assert 1 <= blocks[-1] <= max(capacity, 1)
        k += blocks[-1]
    assert k == steps and blocks[0] == min(steps, LEAD, capacity)
    inner = blocks[1:-1]
    assert all(b >= min(TAIL, capacity) for b in inner)
    assert all(b >= min(capacity, 3 * a // 4 - 1) for a, b in zip(inner, inner[1:]))
