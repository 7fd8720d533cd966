"""The transforms by which ``sims/replay_flight_variants.py`` gives an exported flight what a real
flight log has: each checked on a small body-IMU log (the replays themselves are the script's)."""

import dataclasses
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from test_replay_in_time import _imu_body_log  # the body-IMU log of the replay in time's tests

SCRIPT = Path(__file__).resolve().parents[2] / "sims" / "replay_flight_variants.py"


@pytest.fixture(scope="module")
def variants():
    spec = importlib.util.spec_from_file_location("replay_flight_variants", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _real(variants, kind, log=None):
    log = log or _imu_body_log(False)
    return log, variants.real_variant(log, kind, np.random.default_rng(0), 1.0, 0.05)


def test_vibration_and_rates(variants):
    log, vib = _real(variants, "vib")
    noise = vib.inputs[:, 1:] - log.inputs[:, 1:]
    assert np.std(noise[:, :3]) == pytest.approx(1.0, rel=0.05)
    assert np.std(noise[:, 3:]) == pytest.approx(0.05, rel=0.05)
    _, mean = _real(variants, "vib100")
    _, alias = _real(variants, "alias100")
    for v in (mean, alias):
        assert np.median(np.diff(v.inputs[:, 0])) == pytest.approx(0.05)  # 200 Hz / 10
    # the block mean has a tenth of the noise's variance, every tenth sample all of it
    assert np.std(mean.inputs[:, 1] - log.inputs[::10, 1]) < 0.4
    assert np.std(alias.inputs[:, 1] - log.inputs[::10, 1]) > 0.9


def test_clock_frame_and_gaps(variants):
    log, clock = _real(variants, "clock")
    assert clock.inputs[0, 0] - log.inputs[0, 0] == pytest.approx(variants.EPOCH + 0.02)
    assert clock.ranges[0, 0] - log.ranges[0, 0] == pytest.approx(variants.EPOCH)
    _, frd = _real(variants, "frd")
    assert np.all(frd.inputs[:, 3] < -9.0)  # az = -g, level
    _, uneven = _real(variants, "uneven")
    dt = np.diff(uneven.inputs[:, 0])
    assert dt.min() > 0.0 and np.count_nonzero(dt > 0.045) == variants.GAPS


def test_ranges_and_truth(variants):
    log, bias = _real(variants, "bias")
    excess = bias.ranges[:, 2] - log.ranges[:, 2]
    first = log.beacon_index(log.ranges[:, 1]) == 0
    assert np.median(excess[first]) == pytest.approx(-0.3)
    _, truth = _real(variants, "truth100")
    assert truth.truth_columns == ("time", "x", "y", "z")
    assert truth.truth[0, 0] >= log.inputs[0, 0] + 2.0
    assert np.median(np.diff(truth.truth[:, 0])) == pytest.approx(0.01)
    _, real = _real(variants, "real")
    assert np.all(np.isnan(real.range_std)) and real.name.endswith("-real")
    assert math.isclose(real.inputs[0, 0], variants.EPOCH + 0.02)


def test_real_less_one_step(variants):
    """``real-STEP`` is ``real`` on the same draws with only ``STEP``'s change undone."""
    log = _imu_body_log(False)
    log = dataclasses.replace(log, range_std=np.full(log.ranges.shape[0], 0.1))
    _, real = _real(variants, "real", log)
    _, no_bias = _real(variants, "real-bias", log)
    _, no_nostd = _real(variants, "real-nostd", log)
    _, no_clock = _real(variants, "real-clock", log)
    _, no_vib = _real(variants, "real-vib100", log)
    # the ranges as logged, the IMU drawn as in ``real``
    assert np.array_equal(no_bias.ranges[:, 2], log.ranges[:, 2])
    assert np.array_equal(no_bias.inputs, real.inputs)
    # the stated std kept, every draw as in ``real``
    assert np.all(np.isnan(real.range_std)) and np.all(no_nostd.range_std == 0.1)
    assert np.array_equal(no_nostd.ranges, real.ranges)
    assert np.array_equal(no_nostd.inputs, real.inputs)
    # the clocks as logged, the rest as in ``real``
    assert math.isclose(no_clock.inputs[0, 0], log.inputs[0, 0])
    assert np.array_equal(no_clock.ranges[:, 2], real.ranges[:, 2])
    assert np.allclose(no_clock.inputs[:, 1:], real.inputs[:, 1:])
    # no vibration: the native rate, and the range errors drawn as in ``real``
    assert no_vib.inputs.shape[0] > real.inputs.shape[0]
    assert np.array_equal(no_vib.ranges, real.ranges)
    assert no_bias.name.endswith("-real-bias")
