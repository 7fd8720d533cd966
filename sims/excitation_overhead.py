"""What the live excitation monitor costs: an episode with and without it, and one update alone.

    python sims/excitation_overhead.py [--scenario ifac2021] [--duration 10]

Prints the episode throughput (physics steps per second, estimators and recording
included) with the monitor on and off, alternated over a few repetitions, and the cost
of one monitor update (the window Gramian and its eigenvalues) and of the monitor fed a
chunk at a time (as the episode loop feeds it) or step by step.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.testbed.episode import run_episode
from quadobs.testbed.excitation import scenario_monitor


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="ifac2021")
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    on = load_scenario(args.scenario, duration=args.duration)
    off = on.with_settings({"excitation.monitor": False})
    rates = {"monitor on": [], "monitor off": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            for label, sc in (("monitor off", off), ("monitor on", on)):
                s = run_episode(sc, out=Path(tmp) / "run.rrd")
                rates[label].append(s.summary["steps_per_second"])
    for label, r in rates.items():
        print(
            f"{args.scenario} {args.duration:g} s, recorded: {label:11s} {np.median(r):8.0f} steps/s (median of {len(r)})"
        )
    print(
        f"throughput ratio on/off: {np.median(rates['monitor on']) / np.median(rates['monitor off']):.3f}"
    )

    u = on.trajectory.step_accelerations(0.0, on.dt, on.steps)
    mon = scenario_monitor(on)  # fed as the episode loop feeds it: a chunk per call
    t0 = time.perf_counter()
    k = 0
    while k < len(u):
        n = mon.room
        mon.push_many(u[k : k + n])
        k += n
    chunked = time.perf_counter() - t0
    mon = scenario_monitor(on)  # fed one step per call
    t0 = time.perf_counter()
    for uk in u:
        mon.push(uk)
    total = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(50):
        mon._update()
    upd = (time.perf_counter() - t0) / 50
    print(
        f"monitor alone: {chunked / len(u) * 1e6:.2f} us per physics step fed a chunk at a time (push_many), "
        f"{total / len(u) * 1e6:.2f} fed step by step (push), on average ({mon.updates} updates); "
        f"one update {upd * 1e3:.2f} ms (window {mon.L} hold steps, N = {mon.immersion.dim})"
    )


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
