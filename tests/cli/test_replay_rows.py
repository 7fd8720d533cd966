"""The replay's printed rows and reason, and the paths panel's limits: their closed forms."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np


def _summary(estimators: dict, burn_in: float = 0.0) -> dict:
    return {
        "log": "room", "duration": 60.0, "ranges": {"placed": 100}, "model": "odometry",
        "measurements": {"dropped": 0, "outliers_injected": 0}, "interrupted": False,
        "noise": {}, "has_truth": True, "burn_in": burn_in, "anchor_extent": 3.2,
        "estimators": estimators,
    }  # fmt: skip


def _figures(rmse: float, **extra) -> dict:
    return {
        "rmse": rmse, "max_error": 2 * rmse, "final_position_error": rmse,
        "seconds_per_measurement": 1e-4, "diverged": None, **extra,
    }  # fmt: skip


def test_the_rows_say_the_burn_in_fit_the_longest_name_and_flag_what_the_summary_flags(capsys):
    from quadobs.cli import _print_replay_rows

    same = {
        "estimator": "ekf-bias-imu",
        "reason": "no non-line-of-sight excess identified in the log",
    }
    rows = {
        "ekf": _figures(0.3, within_extent=True),
        "ekf-bias-imu-average": _figures(0.2, within_extent=True, same_as=same),
        "augmented": _figures(40.0, within_extent=False),
        "ukf": {**_figures(math.nan), "diverged": {"t": 1.0}},
    }
    log = SimpleNamespace(beacons=np.zeros((4, 2)))
    _print_replay_rows(_summary(rows, burn_in=5.0), log)
    lines = capsys.readouterr().out.splitlines()
    width = len("ekf-bias-imu-average")
    assert lines[1].startswith(f"  {'ekf':{width}s} rmse after 5 s 0.3 m")
    assert lines[2].endswith(
        "[the same filter as ekf-bias-imu: no non-line-of-sight excess identified in the log]"
    )
    assert lines[3].endswith("[final error larger than the anchors' extent, 3.2 m]")
    assert lines[4] == f"  {'ukf':{width}s} rmse invalid (diverged)"
    _print_replay_rows(_summary({"ekf": _figures(0.3)}), log)
    assert capsys.readouterr().out.splitlines()[1].startswith("  ekf        rmse 0.3 m")


def test_a_reason_is_printed_a_clause_a_line_outside_brackets():
    from quadobs.cli import _reason_lines

    assert _reason_lines("a: x (p; q); b [c; d]; e") == "\n  - a: x (p; q)\n  - b [c; d]\n  - e"
    assert _reason_lines("") == ""


def test_the_paths_panel_is_held_to_the_truth_and_the_anchors():
    from quadobs.studies.plot.run import _field_limits

    limits = {}
    ax = SimpleNamespace(
        set_xlim=lambda a, b: limits.__setitem__("x", (a, b)),
        set_ylim=lambda a, b: limits.__setitem__("y", (a, b)),
    )
    truth = np.array([[0.5, 0.5], [2.5, 1.5], [np.nan, np.nan]])
    beacons = np.array([[0.0, 0.0], [3.0, 2.0]])
    _field_limits(ax, truth, beacons)  # extent 3 m: a fifth of it, 0.6 m, around
    np.testing.assert_allclose(limits["x"], (-0.6, 3.6))
    np.testing.assert_allclose(limits["y"], (-0.6, 2.6))
    _field_limits(ax, np.array([[1.0, 1.0]]), None)  # one point: at least 0.5 m around
    np.testing.assert_allclose(limits["x"], (0.5, 1.5))
