"""The quadrotor's robustness sweep: the identified vehicle and its variations, each flown on the truth and on an estimate.

The grid (:func:`robustness_grid`) varies one thing at a time from a quadrotor scenario:
the rotor's spin-up time constant at hover (0.06 and 0.2 s around the identified
0.136 s, the spin-down scaled with it), the mass (±20 %, the controller keeping the
nominal mass), the IMU's white noise (accelerometer, gyroscope and attitude errors ×3)
and gusts of wind on MuJoCo's fluid model (``[quadrotor] gust_speed``). :func:`sweep`
flies each point on the truth and on each estimator's estimate and reports crashes and
tracking (:func:`format_sweep` prints the table of ``docs/quadrotor.md``).
"""

from __future__ import annotations

__all__ = ["format_sweep", "robustness_grid", "sweep"]


def robustness_grid(scenario) -> list[tuple[str, list[str]]]:
    """``(label, settings)`` of each point of the grid, ``settings`` as for ``load_scenario``."""
    q = scenario.quadrotor
    noise = [
        f"quadrotor.accel_std={3.0 * q.accel_std!r}",
        f"quadrotor.gyro_std={3.0 * q.gyro_std!r}",
        f"quadrotor.attitude_std={3.0 * q.attitude_std!r}",
    ]
    return [
        ("identified rotor", []),
        ("rotor tau 0.06 s", ["quadrotor.rotor_tau_up=0.06"]),
        ("rotor tau 0.2 s", ["quadrotor.rotor_tau_up=0.2"]),
        ("mass -20 %", ["quadrotor.mass_scale=0.8"]),
        ("mass +20 %", ["quadrotor.mass_scale=1.2"]),
        ("IMU noise x3", noise),
        ("gusts 3 m/s", ["quadrotor.gust_speed=3.0"]),
    ]


def sweep(name: str, feedbacks=("augmented",), settings=()) -> list[dict]:
    """Fly each point of :func:`robustness_grid` of scenario ``name`` on the truth and on each of ``feedbacks``.

    Returns one row per flight: ``label``, ``flown_on``, ``crashed``, ``crash_time``,
    ``tracking_rms``, ``tracking_max`` (m) and the position RMSE after the switch of the
    estimator flown on (``None`` on the truth).
    """
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario

    base = load_scenario(name, settings=list(settings))
    rows = []
    for label, extra in robustness_grid(base):
        for flown in ("truth", *feedbacks):
            sc = load_scenario(name, settings=[*settings, *extra, f"control.feedback={flown}"])
            ests = [flown] if flown != "truth" else ["ekf"]
            s = run_episode(sc, estimators=ests).summary
            f = s["flight"]
            rows.append(
                {
                    "label": label,
                    "flown_on": flown,
                    "crashed": bool(f["crashed"]),
                    "crash_time": f["crash_time"],
                    "tracking_rms": f["tracking_rms"],
                    "tracking_max": f["tracking_max"],
                    "position_rmse": None
                    if flown == "truth"
                    else s["estimators"][flown]["flight_position_rmse"],
                }
            )
    return rows


def format_sweep(rows: list[dict]) -> str:
    """The sweep as a Markdown table."""
    out = [
        "| variation | flown on | crashed | tracking RMS / max (m) | position RMSE (m) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        crash = f"at {r['crash_time']:.1f} s" if r["crashed"] else "no"
        rmse = "-" if r["position_rmse"] is None else f"{r['position_rmse']:.3f}"
        out.append(
            f"| {r['label']} | {r['flown_on']} | {crash} | "
            f"{r['tracking_rms']:.3f} / {r['tracking_max']:.3f} | {rmse} |"
        )
    return "\n".join(out)
