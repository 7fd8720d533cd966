"""A crash is never silent: the printed table, the exit status, the recording, the campaign's counts."""

import io
import json
import math

import numpy as np

from quadobs.cli import EXIT_CRASHED, main, print_summary
from quadobs.testbed.flight import crash_counts, crash_line, crash_record

_CRASH = ["--duration", "7", "--set", "control.crash_distance=0.01", "--estimators", "ekf"]


def test_a_crash_is_printed_and_fails_the_run_when_asked(tmp_path):
    out, summary = tmp_path / "c.rrd", tmp_path / "s.json"
    code = main(["run", "quadrotor-uwb", "--no-progress", "--out", str(out)] + _CRASH)
    assert code == 0
    code = main(
        ["run", "quadrotor-uwb", "--no-progress", "--fail-on-crash", "--summary", str(summary)]
        + _CRASH
    )
    assert code == EXIT_CRASHED
    text = io.StringIO()
    print_summary(json.loads(summary.read_text()), file=text)
    assert "CRASHED at" in text.getvalue() and "tracking error" in text.getvalue()

    from quadobs.recording.reader import read_series, read_text_log

    events = [m for *_, m in read_text_log(out, "events") if "crashed at" in m]
    assert len(events) == 1
    crashed = read_series(out, "flight/crashed")
    values = np.asarray(crashed["values"])
    assert np.nanmax(values) == 1.0 and np.nanmin(values) == 0.0


def test_a_flight_without_a_crash_exits_0_with_the_option():
    code = main(
        ["run", "quadrotor-uwb", "--no-progress", "--fail-on-crash", "--duration", "7"]
        + ["--estimators", "ekf"]
    )
    assert code == 0


def test_the_crashes_are_counted_per_estimator_flown_on():
    flights = [
        {"feedback": "augmented", "time_on_estimate": 5.0, "crashed": True, "crash_time": 6.5},
        {"feedback": "augmented", "time_on_estimate": 5.0, "crashed": False, "crash_time": None},
        {"feedback": "augmented", "time_on_estimate": 0.0, "crashed": True, "crash_time": 1.0},
    ]
    runs = [{**f, **crash_record(f)} for f in flights]
    counts = crash_counts(runs)
    assert counts["augmented"] == {"runs": 2, "crashed": 1, "crash_times": [6.5]}
    assert counts["truth"] == {"runs": 1, "crashed": 1, "crash_times": [1.0]}
    assert math.isnan(runs[1]["crash_time"])
    assert crash_line({"flight": flights[1]}) is None and crash_line({}) is None
    assert crash_line({"flight": {**flights[0], "crash_cause": "x"}}).startswith(
        "CRASHED at 6.50 s (flying on augmented): x"
    )
