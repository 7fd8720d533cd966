"""Localise the MuJoCo vehicle from one range measurement, the data flow in one file.

    python sims/localise_vehicle.py [--scenario ifac2021] [--duration S] [--out runs/localise.rrd]

Each physics step: MuJoCo advances the true vehicle under the commanded acceleration,
its sensors (describing the start of the step) give the range and the accelerometer,
the augmented observer corrects with the range and predicts over the step, and the
errors go to the recording. `quadobs run` does the same with more bookkeeping.
"""

import argparse
from pathlib import Path

import numpy as np
import rerun as rr

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.recording import Recorder
from quadobs.testbed.factories import augmented_observer
from quadobs.testbed.sensors import SensorModel
from quadobs.testbed.worlds import VehicleSim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="ifac2021")
    parser.add_argument("--duration", type=float, help="override the scenario duration (s)")
    parser.add_argument("--out", default="runs/localise.rrd")
    args = parser.parse_args()

    sc = load_scenario(args.scenario, duration=args.duration)
    sim = VehicleSim(sc.dimension, sc.beacons, timestep=sc.dt, wind=sc.wind)  # MuJoCo ground truth
    sim.reset(sc.trajectory.position(0.0), sc.trajectory.velocity_at(0.0))
    sensors = SensorModel(sc)  # noise and rates of the scenario, seeded
    observer = augmented_observer(sc, x0=np.zeros(sc.state_dim))  # Theorem 3 on the immersion
    accelerations = sc.trajectory.step_accelerations(0.0, sc.dt, sc.steps)

    with Recorder(args.out, recording_id=f"localise-{sc.name}") as rec:
        rec.static(
            "world/beacons",
            rr.Points3D(np.pad(sc.beacons, ((0, 0), (0, 3 - sc.dimension))), radii=0.6),
        )
        err = rec.series("errors/position", 1, names=["|p_hat - p|"])
        path = rec.series("world/estimate", 3, "points3d", every=10, radius=0.15)
        for k in range(sc.steps):
            truth = sim.state()  # x(t_k), from MuJoCo
            sim.step(accelerations[k])  # sensors now describe t_k
            y = sensors.outputs(k, sim.ranges(), sim.airspeed() if sc.has_wind else None)
            u = sensors.input(sim.accelerometer())
            row = rec.row(k, k * sc.dt)
            err.buf[row, 0] = np.linalg.norm(observer.x_hat[: sc.dimension] - truth[: sc.dimension])
            path.buf[row, : sc.dimension] = observer.x_hat[: sc.dimension]
            observer.step(u, y)  # correct with y(t_k), predict to t_(k+1) with u held
    final = np.linalg.norm(observer.x_hat[: sc.dimension] - sim.position())
    print(
        f"{sc.name}: final position error {final:.4f} m after {sc.duration:g} s; recording {args.out}"
    )


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
