"""Run the degenerate scenario and print, from its recording, what the excitation monitor shows.

    python sims/excitation_degenerate.py [--duration S] [--out runs/degenerate.rrd] [--every 2]

Every ``--every`` seconds: the position error, the trace of the position-velocity
covariance, the measure mu = lambda_min W(t - delta, t), how many directions of the
window are below the threshold, and the observer's largest variance along them. Open
the recording with ``rerun runs/degenerate.rrd`` for the same curves.
"""

import argparse
from pathlib import Path

import numpy as np

from quadobs import QuadobsError, load_scenario
from quadobs.errors import run_script
from quadobs.recording import read_series, read_text_log
from quadobs.testbed.episode import run_episode

COLUMNS = [
    ("|e_p| (m)", "errors/augmented/position/norm", "{:9.4f}"),
    ("tr P_x", "observer/augmented/covariance_trace", "{:9.3g}"),
    ("mu", "excitation/measure", "{:9.2e}"),
    ("unexcited", "excitation/unexcited_directions", "{:9.0f}"),
    ("var unexc.", "excitation/unexcited_variance/augmented", "{:10.3g}"),
]


def read_or_empty(path: str, entity: str) -> dict:
    """The series at ``entity``, or an empty one when nothing was recorded there (a run shorter than the window)."""
    try:
        return read_series(path, entity)
    except QuadobsError:
        return {"sim_time": np.empty(0), "values": np.empty((0, 1))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="degenerate")
    parser.add_argument("--out", default="runs/degenerate.rrd")
    parser.add_argument("--every", type=float, default=2.0)
    parser.add_argument("--duration", type=float, help="override the scenario duration (s)")
    args = parser.parse_args()

    sc = load_scenario(args.scenario, duration=args.duration)
    summary = run_episode(sc, out=args.out).summary
    ex = summary["excitation"]
    series = {entity: read_or_empty(args.out, entity) for _, entity, _ in COLUMNS}
    print(
        f"{sc.name}: coasting over {', '.join(f'[{a:.2f}, {b:.2f})' for a, b in sc.trajectory.coast)} s; "
        f"window {ex['window']:g} s, threshold {ex['threshold']:g}"
    )
    print("  t (s)  " + " ".join(f"{name:>10s}" for name, _, _ in COLUMNS))
    for t in np.arange(0.0, sc.duration + 1e-9, args.every):
        cells = []
        for _, entity, fmt in COLUMNS:
            s = series[entity]
            i = np.searchsorted(s["sim_time"], t + 1e-9) - 1
            # a value counts if recorded within one update period (gaps: nothing below the threshold)
            ok = i >= 0 and t - s["sim_time"][i] <= ex["update_period"] + 1e-9
            cells.append(fmt.format(s["values"][i, 0]).rjust(10) if ok else "-".rjust(10))
        print(f"  {t:5.1f}  " + " ".join(cells))
    low = [[round(a, 3), round(b, 3)] for a, b in ex["low_segments"]]
    if ex["min_measure"] is None:
        print(f"low segments (s): {low}; no full window of {ex['window']:g} s in {sc.duration:g} s")
    else:
        print(
            f"low segments (s): {low}, min mu {ex['min_measure']:.3g} at t = {ex['min_measure_time']:.1f} s"
        )
    for _step, t, level, text in read_text_log(args.out, "events"):
        print(f"event at t = {t:.3f} s [{level}]: {text}")
    print(f"final position error {summary['final_position_error']:.4f} m; recording {args.out}")


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
