"""The self-calibration's excess fit against what the simulation knows of the flights' excess.

For each flight of ``sims/flight_error_budget.py`` (a ``real`` or ``bias`` variant of the
exported ``quadrotor-uwb-realistic`` run; the same seeds, transforms and draws), the
self-calibration runs as the replay runs it (``quadobs replay DIR``: its chosen replay's
prequential residuals, step 8 of :mod:`quadobs.testbed.logs.calibration`; no truth read),
and its ranges are set beside the budget's oracle (``range_residuals``: each range less its
true distance and its anchor's true bias, with an excess where the room blocks the path at
the truth's position or the variant lengthened it). One row per flight (``docs/error-sources.md``,
"The excess fitted with less prediction error"):

* the oracle: the fraction of the scored ranges with an excess, the excess's median (m), and
  the line-of-sight ranges' spread (1.4826 times their median absolute deviation, m);
* the replay's fit to the residuals
  (:func:`~quadobs.testbed.logs.excess_model.fit_excess`: median m, shape, fraction; core m);
* the same fit to the same ranges' own errors (the oracle's, no prediction in them);
* both with a third component for outliers of either sign
  (:func:`check_excess.outlier_fit`: median, shape, fraction, the outliers' probability;
  core);

and, below the row, each anchor's share of the scored ranges with an excess (the oracle's).

    python sims/excess_fit_oracle.py --flights real:0,real:1,real:2,real:3,real:4,bias:3,bias:7,bias:9 --out budget/
"""

from __future__ import annotations

import argparse
import tempfile
import types
from pathlib import Path

import check_excess
import flight_error_budget as budget
import numpy as np
import replay_flight_variants as flight

from quadobs.errors import QuadobsError, run_script
from quadobs.testbed.logs import read_log


def _calibration_residuals(log):
    """The residuals step 8 of the self-calibration is given, as the replay runs it."""
    from quadobs.testbed.logs import calibration as cm

    seen = {}
    step8 = cm.calibrated_excess

    def keep(log_, res, options):
        seen["res"] = res
        return step8(log_, res, options)

    cm.calibrated_excess = keep
    try:
        cm.calibrate(log, dt=0.1, noise=cm.noise_keys(log, None))
    finally:
        cm.calibrated_excess = step8
    return seen["res"]


def _own_errors(f, res) -> tuple[np.ndarray, np.ndarray]:
    """The oracle's errors and line-of-sight flags of the residuals' ranges (by time and anchor)."""
    error, clear = budget.range_residuals(f)
    anchor = f.log.beacon_index(f.log.ranges[:, 1])
    at = {
        (round(float(t), 9), int(h)): k for k, (t, h) in enumerate(zip(f.log.ranges[:, 0], anchor))
    }
    index = np.array([at[round(float(t), 9), int(h)] for t, h in zip(res.t, res.h)])
    return error[index], clear[index]


def row(f, kind: str, seed: int) -> str:
    """One flight's row of the table (module docstring)."""
    from quadobs.testbed.logs.excess_model import fit_excess

    res = _calibration_residuals(f.log)
    error, clear = _own_errors(f, res)
    q = f.log.beacons.shape[0]
    spread = 1.4826 * np.median(np.abs(error[clear] - np.median(error[clear])))
    cells = [f"{np.mean(~clear):.2f}, {np.median(error[~clear]):.2f}, {spread:.3f}"]
    for r in (res.r, error):
        fit = fit_excess(r, res.h, q)
        cells.append(f"{fit.median:.2f}, {fit.shape:.2f}, {fit.fraction:.3f}; {fit.sigma:.3f}")
    for r in (error, res.r):
        m, s, pi, po, core = check_excess.outlier_fit(r, res.h, q)
        cells.append(f"{m:.2f}, {s:.2f}, {pi:.3f}, {po:.3f}; {core:.3f}")
    share = " ".join(f"{np.mean(~clear[res.h == j]):.2f}" for j in range(q))
    return f"| {kind} {seed} | " + " | ".join(cells) + f" |\n  per anchor, with an excess: {share}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--flights", default="real:1", help="KIND:SEED,... (KIND real or bias)")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--out", help="folder for the exports (default: a temporary one)")
    args = ap.parse_args()
    flights = []
    for item in args.flights.split(","):
        kind, _, seed = item.partition(":")
        if kind not in ("real", "bias") or not seed.isdigit():
            raise QuadobsError(
                f"--flights: expected KIND:SEED with KIND real or bias, got {item!r}"
            )
        flights.append((kind, int(seed)))
    draws = types.SimpleNamespace(
        accel_bias=0.2,
        gyro_bias=0.01,
        accel_vibration=1.0,
        gyro_vibration=0.05,
        yaw=1.0,
        stress="none",
    )  # flight_error_budget's defaults
    out = Path(args.out or tempfile.mkdtemp(prefix="excess-oracle-"))
    print(
        "| flight | oracle: fraction, median, line-of-sight spread | residuals | own errors"
        " | own errors, with outliers | residuals, with outliers |"
    )
    for kind, seed in flights:
        folder = out / f"seed{seed}"
        if not (folder / "meta.csv").exists():
            flight.export(seed, args.duration, draws.accel_bias, draws.gyro_bias, folder)
        f = budget._truth_of_flight(read_log(folder), seed, kind, draws)
        print(row(f, kind, seed), flush=True)


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
