"""The held-out check of the estimated non-line-of-sight excess (step 9 of the
self-calibration, :func:`quadobs.testbed.logs.calibration.estimator_excess`) on logs.

For each log folder: the replay's self-calibration (:func:`~quadobs.testbed.logs.calibration.calibrate`,
then the biases of each bias filter, :func:`~quadobs.testbed.logs.calibration.estimator_biases`),
then the check, ``ekf-bias-imu`` replayed under the fitted mixture and under the one-sided
gate, the same ranges held out. Prints the fitted excess, the held-out scores of both (the
mean negative log-likelihood under the fitted model, and the root mean capped square) and
whether the mixture was significantly better (kept) or not (dropped).

    python sims/replay_flight_variants.py --seeds 0 --variants real --out flights/
    python sims/check_excess.py flights/seed0-real
"""

from __future__ import annotations

import argparse

from quadobs.testbed.logs import read_log
from quadobs.testbed.logs.calibration import calibrate, estimator_biases, estimator_excess


def check(folder: str, estimator: str, dt: float) -> str:
    """One log's row of the table."""
    log = read_log(folder)
    cal = calibrate(log, dt=dt)
    estimator_biases(log, cal, [estimator], dt=dt)
    estimator_excess(log, cal, [estimator], dt=dt)
    e = cal.excess
    if "check" not in e:
        return f"{folder}: not checked ({'no excess chosen' if not e.get('chosen') else estimator + ' takes none'})"
    c = e["check"][estimator]
    sq = c["squared"]
    return (
        f"{folder}: excess {e['median']:.2f} m, shape {e['shape']:.2f}; held-out NLL mixture "
        f"{c['score']:.3f}, gate {c['reference_score']:.3f}; capped square {sq['score']:.3f} m, "
        f"{sq['reference_score']:.3f} m; {'kept' if e['chosen'] else 'dropped'}"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("folders", nargs="+", help="log folders (quadobs replay's)")
    ap.add_argument("--estimator", default="ekf-bias-imu")
    ap.add_argument("--dt", type=float, default=0.1)
    args = ap.parse_args()
    for folder in args.folders:
        print(check(folder, args.estimator, args.dt), flush=True)


if __name__ == "__main__":
    main()
