"""EKF and UKF with a fictitious process noise: how much of their failure to converge is overconfidence.

    python sims/tuned_baselines.py [--scenario ifac2021-noisy] [--accel-std 3.0] [--runs 100] [--duration S]
                                   [--workers N] [--out DIR]

The registered baselines ``ekf`` and ``ukf`` use the scenario's true noise levels; with a
noise-free accelerometer their process noise is zero and their covariance can collapse
onto a wrong solution. This script registers ``ekf_tuned`` and ``ukf_tuned``: the same
filters with the accelerometer noise of their model raised to ``--accel-std`` (m/s^2, per
physics step: ``Q_d = sigma^2 G G^T``), a tuning, and runs a campaign of them (the same
seeds as ``quadobs campaign`` on the scenario).
"""

import argparse
from pathlib import Path

from quadobs import load_scenario
from quadobs.errors import run_script
from quadobs.estimators.kalman import ExtendedKalmanFilter, HeldInputModel, UnscentedKalmanFilter
from quadobs.studies.campaign import print_campaign, run_campaign
from quadobs.testbed.factories import baseline_settings
from quadobs.testbed.registry import register_estimator


def tuned(cls, accel_std: float):
    def factory(scenario, x0, name):
        s = baseline_settings(scenario)
        dynamics = HeldInputModel(s.dynamics.system, scenario.dt, input_covariance=accel_std**2)
        return cls(dynamics, s.outputs, x0=x0, P0=s.P0, gate=scenario.observer.gate)

    return factory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="ifac2021-noisy")
    parser.add_argument("--accel-std", type=float, default=3.0)
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--duration", type=float, help="override the scenario duration (s)")
    parser.add_argument(
        "--workers",
        type=int,
        help="local processes (default: the number of CPUs; 0: in this process)",
    )
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    register_estimator("ekf_tuned", tuned(ExtendedKalmanFilter, args.accel_std))
    register_estimator("ukf_tuned", tuned(UnscentedKalmanFilter, args.accel_std))
    # local processes are forked on Linux, so they see the registrations above
    result = run_campaign(
        load_scenario(args.scenario, duration=args.duration),
        runs=args.runs,
        workers=args.workers,
        estimators=["ekf_tuned", "ukf_tuned"],
        out_dir=args.out,
        progress=True,
    )
    print(
        f"process noise of the filters' model: accelerometer sigma = {args.accel_std:g} m/s^2 per step (a tuning)"
    )
    print_campaign(result.summary)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
