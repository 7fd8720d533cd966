"""The fast paths of the testbed against the plain ones: block stepping, batched vehicles, sensors, recording."""

import json
import math

import numpy as np
import pytest

from quadobs import load_scenario
from quadobs.cli import main
from quadobs.evaluation.convergence import ConvergenceTracker
from quadobs.recording import Recorder, read_series
from quadobs.studies.bench import BENCH_KEYS
from quadobs.testbed.scenario import parse_scenario
from quadobs.testbed.sensors import SensorModel
from quadobs.testbed.worlds import BlockStepper, VehicleSim
from quadobs.testbed.worlds.batch import VehicleBatch

pytest.importorskip("numba")

BEACONS = np.array([[0.0, 0.0, 0.0], [10.0, 5.0, -3.0]])
WINDS = [None, np.array([1.0, -2.0, 0.5])]


@pytest.mark.parametrize("wind", WINDS, ids=["calm", "wind"])
def test_block_stepper_reads_what_vehicle_sim_reads(wind):
    sc = load_scenario("ifac2021")
    acc = sc.trajectory.step_accelerations(0.0, 1e-3, 300)
    plain, fast = VehicleSim(3, BEACONS, wind=wind), VehicleSim(3, BEACONS, wind=wind)
    for sim in (plain, fast):
        sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
    stepper = BlockStepper(fast, 200)
    for start in (0, 200):
        nblk = stepper.begin(acc[start : start + 200])
        for j in range(nblk):
            x = plain.state()
            plain.step(acc[start + j])
            stepper.step(j)
            row = stepper.out[j]
            np.testing.assert_allclose(stepper.out[j, stepper.truth], x, rtol=1e-14, atol=1e-13)
            np.testing.assert_allclose(row[stepper.ranges], plain.ranges(), rtol=1e-14)
            np.testing.assert_allclose(
                row[stepper.accel], plain.accelerometer(), rtol=1e-13, atol=1e-13
            )
            np.testing.assert_allclose(row[stepper.airspeed][0], plain.airspeed(), rtol=1e-13)
        np.testing.assert_allclose(
            stepper.out[nblk, stepper.truth], plain.state(), rtol=1e-14, atol=1e-13
        )


@pytest.mark.parametrize("wind", WINDS, ids=["calm", "wind"])
def test_vehicle_batch_equals_separate_vehicles(rng, wind):
    B = 4
    p0, v0 = 10 * rng.standard_normal((B, 3)), rng.standard_normal((B, 3))
    sims = [VehicleSim(3, BEACONS, wind=wind) for _ in range(B)]
    for sim, p, v in zip(sims, p0, v0):
        sim.reset(p, v)
    with VehicleBatch(3, BEACONS, B, wind=wind) as batch:
        batch.reset(p0, v0)
        np.testing.assert_allclose(batch.states(), [s.state() for s in sims], rtol=1e-15)
        for _ in range(100):
            acc = rng.standard_normal((B, 3))
            batch.step(acc)
            for sim, a in zip(sims, acc):
                sim.step(a)
            np.testing.assert_allclose(
                batch.states(), [s.state() for s in sims], rtol=1e-13, atol=1e-13
            )
            np.testing.assert_allclose(batch.ranges(), [s.ranges() for s in sims], rtol=1e-13)
            np.testing.assert_allclose(
                batch.accelerometer(), [s.accelerometer() for s in sims], rtol=1e-13, atol=1e-12
            )
            np.testing.assert_allclose(batch.airspeed(), [s.airspeed() for s in sims], rtol=1e-13)


def test_compiled_range_transform_equals_numpy():
    """Noise, rates and dropouts: the sensor layer's compiled path draws and computes the same values."""
    data = load_scenario("ifac2021", duration=1.0).to_dict()
    data["beacons"] = [{"position": list(b)} for b in BEACONS]
    data["noise"] = {"range_std": 0.3, "accel_std": 0.05, "range_rate": 250.0, "dropout": 0.2}
    sc = parse_scenario(data)
    fast, plain = SensorModel(sc), SensorModel(sc)
    plain._fast = None
    rng = np.random.default_rng(1)
    for k in range(500):
        r = rng.uniform(1, 50, 2)
        np.testing.assert_array_equal(fast.outputs(k, r), plain.outputs(k, r))
        np.testing.assert_array_equal(fast.measured_ranges, plain.measured_ranges)
    assert fast.dropped == plain.dropped > 0


def _noisy_wind_scenario():
    data = load_scenario("ifac2021", duration=5.0).to_dict()
    data["beacons"] = [{"position": list(b)} for b in BEACONS]
    data["wind"] = {"velocity": [1.0, -2.0, 0.5]}
    data["noise"] = {
        "range_std": 0.3,
        "accel_std": 0.05,
        "airspeed_std": 0.1,
        "range_rate": 500.0,
        "airspeed_rate": 250.0,
        "dropout": 0.1,
        "outlier_probability": 0.05,
        "outlier_std": 20.0,
    }
    return parse_scenario(data)


def test_block_stepper_applies_the_sensor_layer_as_step_by_step_calls():
    """Noise drawn a block at a time, rates, dropouts, outliers, airspeed: the same y, u and counts
    as SensorModel.outputs and SensorModel.input called step by step on the same readings."""
    sc = _noisy_wind_scenario()
    acc = sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps)
    sim = VehicleSim(3, sc.beacons, wind=sc.wind)
    sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
    ref, sensors = SensorModel(sc), SensorModel(sc)
    stepper = BlockStepper(sim, 3000, sensors)
    for k0 in range(0, sc.steps, 3000):  # the draws cross the 4096-row blocks of the streams
        nblk = stepper.begin(acc[k0 : k0 + 3000], k0)
        events = np.zeros((nblk, 2), dtype=np.int64)
        for j in range(nblk):
            stepper.step(j)
            row = stepper.out[j]
            before = (ref.outliers_injected, ref.dropped)
            y = ref.outputs(k0 + j, row[stepper.ranges].copy(), float(row[stepper.airspeed][0]))
            events[j] = (ref.outliers_injected - before[0], ref.dropped - before[1])
            np.testing.assert_array_equal(row[stepper.y], y)
            np.testing.assert_array_equal(row[stepper.measured], ref.measured_ranges)
            np.testing.assert_array_equal(row[stepper.u], ref.input(row[stepper.accel].copy()))
        stepper.commit(nblk)
        np.testing.assert_array_equal(
            stepper.events[:nblk], events
        )  # per-step outliers delivered, samples dropped
    assert (sensors.dropped, sensors.outliers_injected) == (ref.dropped, ref.outliers_injected)
    assert ref.dropped > 0 and ref.outliers_injected > 0


def test_tracker_update_many_equals_update():
    rng = np.random.default_rng(2)
    for _ in range(50):
        t = np.arange(40) * 0.1
        v = rng.uniform(0, 2, 40) * np.linspace(1, 0, 40) ** rng.integers(0, 3)
        v[rng.random(40) < 0.05] = np.nan
        a, b = ConvergenceTracker((1.0, 0.1)), ConvergenceTracker((1.0, 0.1))
        for i in range(40):
            a.update(t[i], v[i])
        for chunk in np.array_split(np.arange(40), 3):
            b.update_many(t[chunk], v[chunk])
        np.testing.assert_array_equal(a.times(), b.times())  # NaN (not converged) equals NaN


def test_recording_survives_sends_that_do_not_wait(tmp_path):
    """Buffers are refilled while rerun writes the previous rows: every row reads back exactly."""
    path = tmp_path / "rows.rrd"
    with Recorder(path, recording_id="rows", capacity=64) as rec:
        s = rec.series("values", 2)
        for k in range(2000):
            i = rec.row(k, k * 1e-3)
            s.buf[i] = (k, -2.0 * k)
    back = read_series(path, "values")
    np.testing.assert_array_equal(back["step"], np.arange(2000))
    np.testing.assert_array_equal(
        back["values"], np.stack([np.arange(2000.0), -2.0 * np.arange(2000)], axis=1)
    )


@pytest.mark.slow
def test_cold_start_is_measured_on_an_empty_kernel_cache():
    from quadobs.studies.bench import _cold_start

    figures = _cold_start()
    assert set(figures) == {"cold_run_s", "compile_s", "first_run_s"}
    assert all(math.isfinite(v) and v > 0 for v in figures.values())
    # after 'quadobs compile' the run compiles nothing: faster than the run that compiles
    assert figures["first_run_s"] < figures["cold_run_s"]


def test_bench_command_writes_the_figures(tmp_path, capsys):
    path = tmp_path / "bench.json"
    args = [
        "bench",
        "--steps",
        "300",
        "--repeats",
        "1",
        "--batch",
        "4",
        "--batch-steps",
        "3",
        "--quick",
        "--no-cold-start",  # compiles every kernel twice: measured by the slow test below
        "--quiet",
        "--json",
        str(path),
    ]
    assert main(args) == 0
    data = json.loads(path.read_text())
    assert "cold_start" not in data
    assert data["targets"]["first run after quadobs compile <= 5 s"] is None  # not measured
    assert set(BENCH_KEYS) <= set(data)
    for key in BENCH_KEYS:  # every figure measured: a number, finite and positive
        assert isinstance(data[key], float) and math.isfinite(data[key]) and data[key] > 0, key
    assert data["bare_steps_per_s"] > 0
    assert data["recording_fraction"] < 1  # 1 - t_norec / t_rec
    assert data["batch"]["vehicles"] == 4 and data["scaling"]
    oit = data["observer_in_time"]  # compiled, on the grid and through the NumPy reference
    assert all(oit[k] > 0 for k in ("in_time_step_us", "grid_step_us", "in_time_numpy_step_us"))
    for key in ("loop_ratio", "step_loop_ratio", "recording_fraction", "step_recording_fraction"):
        q = data["spread"][key]  # median and quartiles over the repeats
        assert q["q1"] <= q["median"] == data[key] <= q["q3"] and q["iqr"] == pytest.approx(
            q["q3"] - q["q1"]
        )
    assert data["campaign"]["runs"] >= 2 and data["campaign"]["episodes_per_s"] > 0
    assert (
        set(data["lmi_design_split_s"]) == {"first_approach", "second_approach"}
        and data["lmi_import_s"] >= 0
    )
    assert (
        data["zonotope_vehicle"]["scenario"] == "ifac2021-bounded"
        and data["zonotope_vehicle"]["correct_every_step_us"] > 0
    )
    le = data["le2013_step_us"]
    assert set(le) == {"segment", "volume", "pradius1", "pradius2", "pradius2_paper"}
    assert all(v[b] > 0 for v in le.values() for b in ("numba", "numpy"))
    assert data["zonotope_step_us"] == le["pradius2"]["numba"]
    out = capsys.readouterr().out
    assert "bare MuJoCo stepping" in out and "batch of 4 vehicles" in out
    assert main(["bench", "--steps", "0"]) == 2


def test_block_stepper_numpy_path_agrees():
    """The path used without Numba: VehicleSim's readings and SensorModel step by step."""
    sc = _noisy_wind_scenario()
    acc = sc.trajectory.step_accelerations(0.0, sc.dt, 500)
    steppers = []
    for compiled in (True, False):
        sim = VehicleSim(3, sc.beacons, wind=sc.wind)
        sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
        st = BlockStepper(sim, 500, SensorModel(sc))
        if not compiled:
            st._read = None
        st.begin(acc, 0)
        for j in range(500):
            st.step(j)
        st.commit(500)
        steppers.append(st)
    a, b = (st.out[:500] for st in steppers)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    assert steppers[0].sensors.dropped == steppers[1].sensors.dropped


def test_generic_estimators_are_recorded_beside_the_compiled_one(tmp_path):
    """An Estimator that implements only step/x_hat/x_covariance goes through the generic record path."""
    import quadobs.testbed.registry as registry
    from quadobs.estimators.base import Estimator
    from quadobs.testbed.episode import run_episode

    class Frozen(Estimator):  # keeps its initial guess; a covariance of 2 I
        def __init__(self, x0):
            self.x0 = np.array(x0, dtype=float)
            self.name = "frozen"

        def step(self, u, y):
            pass

        @property
        def x_hat(self):
            return self.x0

        @property
        def x_covariance(self):
            return 2.0 * np.eye(self.x0.size)

    registry.register_estimator("frozen", lambda scenario, x0, name: Frozen(x0))
    try:
        path = tmp_path / "two.rrd"
        run_episode(
            load_scenario("ifac2021", duration=0.5), estimators=["augmented", "frozen"], out=path
        )
    finally:
        registry._REGISTRY.pop("frozen")
    trace = read_series(path, "observer/frozen/covariance_trace")["values"][:, 0]
    np.testing.assert_array_equal(trace, 12.0)
    err = read_series(path, "errors/frozen/position/norm")["values"][:, 0]
    assert len(err) == 501 and err[0] > 20.0
    assert read_series(path, "observer/augmented/covariance_trace")["values"][
        0, 0
    ] == pytest.approx(900.0)


def test_read_kernel_is_compiled_once_for_the_arguments_it_gets():
    """The stepper warms its kernel at construction with the layouts a run then passes, so no
    compilation happens inside the loop (where it would be counted as simulation time)."""
    pytest.importorskip("numba")
    from quadobs.testbed.worlds._read import read_step

    sc = load_scenario("ifac2021", duration=0.5)
    sim = VehicleSim(3, sc.beacons)
    sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
    stepper = BlockStepper(sim, 500, SensorModel(sc))
    compiled = list(read_step.signatures)
    nblk = stepper.begin(sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps))
    for j in range(nblk):
        stepper.step(j)
    assert read_step.signatures == compiled and len(compiled) == 1


@pytest.mark.parametrize(
    "kind, width", [("scalars", 1), ("scalars", 3), ("points3d", 3), ("translation", 3)]
)
def test_recorder_columns_are_those_of_rerun_archetypes(kind, width):
    """The columns the recorder builds directly hold the same descriptor, Arrow type and values as the archetype's."""
    import rerun as rr

    from quadobs.recording.recorder import _columns

    vals = np.random.default_rng(4).normal(size=(37, width)) * 1e3
    vals[5] = np.nan
    made = {
        "scalars": lambda: rr.Scalars.columns(scalars=vals),
        "points3d": lambda: rr.Points3D.columns(positions=vals),
        "translation": lambda: rr.Transform3D.columns(translation=vals),
    }[kind]()
    (ours,), (theirs,) = _columns(kind, vals), list(made)
    assert ours.component_descriptor() == theirs.component_descriptor()
    a, b = ours.as_arrow_array(), theirs.as_arrow_array()
    assert a.type == b.type and a.offsets.equals(b.offsets)
    a, b = a.flatten(), b.flatten()
    if kind != "scalars":
        a, b = a.flatten(), b.flatten()
    np.testing.assert_array_equal(
        a.to_numpy(zero_copy_only=False), b.to_numpy(zero_copy_only=False)
    )  # NaN too


def _rerun_threads() -> int:
    import os

    names = []
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                names.append(f.read().strip())
        except OSError:
            pass
    return sum(n.startswith(("ChunkBatcher", "RecordingStream")) for n in names)


@pytest.mark.skipif(
    not __import__("os").path.isdir("/proc/self/task"), reason="thread names from /proc (Linux)"
)
def test_a_closed_recorder_leaves_no_rerun_threads(tmp_path):
    """rerun's threads of a recording end when the recorder closes (they used to stay for the life of the process)."""
    for k in range(3):
        with Recorder(tmp_path / f"r{k}.rrd", recording_id=f"r{k}") as rec:
            s = rec.series("values", 1)
            s.buf[rec.row(0, 0.0)] = 1.0
    before = _rerun_threads()
    for k in range(5):
        with Recorder(tmp_path / f"s{k}.rrd", recording_id=f"s{k}") as rec:
            s = rec.series("values", 1)
            s.buf[rec.row(0, 0.0)] = 1.0
    assert _rerun_threads() <= before
