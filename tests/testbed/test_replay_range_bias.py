"""``quadobs replay --tune range_bias=1``: the GTSAM peer's constant range bias per anchor as a
state, off by default."""

import json

import numpy as np
import pytest
from test_replay_in_time import ANCHORS_2D, _ranges, _straight, _truth  # the replay in time's logs

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.testbed.logs import RangeLog, write_log
from quadobs.testbed.logs.estimators import ReplaySetup, parse_tuning
from quadobs.testbed.logs.peer import build_peer

BIASES = np.array([0.3, -0.2, 0.25, -0.3])


def _biased_log():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 12.0, 0.04)
    p, v = _straight(t, 2)
    ranges = _ranges(t, ANCHORS_2D, p, rng, 0.05)
    ranges[:, 2] += BIASES[ranges[:, 1].astype(int)]
    truth, cols = _truth(t, p, v, 2)
    return RangeLog(
        "biased", np.arange(4), ANCHORS_2D, ranges, np.empty((0, 1)), float("nan"), truth,
        input_kind="none", truth_columns=cols,
    )  # fmt: skip


def test_the_setting_reaches_the_peer_and_is_off_by_default():
    setup = ReplaySetup(ANCHORS_2D, 0.1, "cv", 0.0, 5.0, input_kind="none")
    assert setup.range_bias == 0 and build_peer(setup, np.zeros(4)).noise.bias == "none"
    on = ReplaySetup(
        ANCHORS_2D, 0.1, "cv", 0.0, 5.0, input_kind="none", **parse_tuning(["range_bias=1"])
    )
    assert build_peer(on, np.zeros(4)).noise.bias == "state"
    with pytest.raises(QuadobsError, match="range_bias: expected 0 \\(off\\) or 1"):
        ReplaySetup(ANCHORS_2D, 0.1, "cv", 0.0, 5.0, input_kind="none", range_bias=0.5)


def test_biases_as_states_from_the_command_line(tmp_path):
    """Ranges biased by up to 0.3 m: with ``--tune range_bias=1`` the peer's error falls."""
    folder = write_log(_biased_log(), tmp_path / "biased")
    rmse = {}
    for flag in (0, 1):
        summary = tmp_path / f"s{flag}.json"
        args = [
            "replay",
            str(folder),
            "--no-progress",
            "--estimators",
            "isam2",
            "--calibrate",
            "none",
        ]
        args += [
            "--tune",
            "range_sigma=0.05",
            "--tune",
            "q_acc=1e-3",
            "--tune",
            f"range_bias={flag}",
        ]
        args += ["--initial-offset", "1", "--burn-in", "4", "--summary", str(summary)]
        assert main(args) == 0
        s = json.loads(summary.read_text())
        assert s["noise"]["range_bias"] == flag
        rmse[flag] = s["estimators"]["isam2"]["batch_rmse"]
    assert rmse[1] < 0.5 * rmse[0], rmse
