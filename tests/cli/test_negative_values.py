"""``quadobs replay LOG --biases -0.2,0.1,...``: a list of numbers whose first is negative, given
after a space, read as written (argparse alone takes it for an option)."""

import json

import numpy as np
import pytest

from quadobs.cli import main, negative_values
from quadobs.testbed.logs import RangeLog, write_log


def _log():
    """Four beacons, a vehicle at rest ranging them in turn for 5 s (noise-free)."""
    beacons = np.array([[0.0, 0.0], [12.0, 0.0], [12.0, 9.0], [0.0, 9.0]])
    t = np.arange(0.0, 5.0, 0.05)
    h = np.arange(t.size) % 4
    rho = np.linalg.norm(beacons[h] - [4.0, 3.0], axis=1)
    truth = np.column_stack([t, np.full(t.size, 4.0), np.full(t.size, 3.0)])
    return RangeLog(
        "rest", np.arange(4), beacons, np.column_stack([t, h, rho]), np.empty((0, 1)),
        float("nan"), truth, input_kind="none", truth_columns=("time", "x", "y"),
    )  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["replay", "L", "--biases", "-0.2,0.1"], ["replay", "L", "--biases=-0.2,0.1"]),
        (["replay", "L", "--biases", "-.5,1"], ["replay", "L", "--biases=-.5,1"]),
        (["replay", "L", "--biases=-0.2,0.1"], ["replay", "L", "--biases=-0.2,0.1"]),
        (["replay", "L", "--biases", "0.2,-0.1"], ["replay", "L", "--biases", "0.2,-0.1"]),
        (
            ["replay", "L", "--biases", "--no-progress"],
            ["replay", "L", "--biases", "--no-progress"],
        ),
        (["replay", "--", "--biases", "-1"], ["replay", "--", "--biases", "-1"]),
        (["replay", "L", "--biases"], ["replay", "L", "--biases"]),
    ],
)
def test_only_a_negative_number_list_after_biases_is_joined(argv, expected):
    assert negative_values(argv) == expected


def test_replay_takes_negative_biases_after_a_space(tmp_path, capsys):
    folder = write_log(_log(), tmp_path / "rest")
    summary = tmp_path / "s.json"
    common = [
        "replay",
        str(folder),
        "--no-progress",
        "--estimators",
        "ekf",
        "--tune",
        "range_sigma=0.05",
    ]
    assert main([*common, "--biases", "-0.2,0.1,0,-1e-1", "--summary", str(summary)]) == 0
    assert json.loads(summary.read_text())["biases"] == [-0.2, 0.1, 0.0, -0.1]
    capsys.readouterr()
    assert main([*common, "--biases", "-0.2,0.1"]) == 2  # the count is checked as for any value
    err = capsys.readouterr().err.strip()
    assert err == "quadobs: error: --biases: 2 values for 4 beacons"
