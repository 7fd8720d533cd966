"""Excitation of a scenario: its reference input, the report and the live monitor it configures.

The measures and conditions (:mod:`quadobs.observability`) take an immersion and an input;
these functions take them from a scenario.
"""

from __future__ import annotations

import numpy as np

from quadobs.core.immersion import Immersion, immerse
from quadobs.errors import QuadobsError, as_finite_scalar
from quadobs.observability.excitation import (
    ExcitationMonitor,
    ExcitationReport,
    HeldInput,
    excitation_report,
)


def scenario_input(scenario, step: float = 0.01, duration: float | None = None) -> HeldInput:
    """The commanded acceleration of ``scenario``'s reference, held over steps of ``step`` s.

    Each held value is the mean acceleration over its step
    (:meth:`~quadobs.testbed.trajectory.SinusoidTrajectory.step_accelerations`), and the
    derivatives are the analytic ones of the reference (zero while coasting).
    """
    step = as_finite_scalar("step", step, positive=True)
    duration = (
        scenario.duration
        if duration is None
        else as_finite_scalar("duration", duration, positive=True)
    )
    T = int(np.floor(duration / step + 1e-9))
    if T < 1:
        raise QuadobsError(f"step: {step} s is longer than the {duration} s to analyse")
    traj = scenario.trajectory
    return HeldInput(
        traj.step_accelerations(0.0, step, T),
        step,
        0.0,
        analytic=lambda t, k: traj.derivative(t, 2 + k),
        source=f"reference acceleration of scenario {scenario.name!r}, held over {step:g} s steps",
    )


def state_names(scenario) -> list[str]:
    """Names of the estimator state's entries: ``p_x .. v_z`` (``va_*``, ``vw_*`` with wind)."""
    axes = "xyz"[: scenario.dimension]
    groups = ["p", "va", "vw"] if scenario.has_wind else ["p", "v"]
    return [f"{g}_{a}" for g in groups for a in axes]


def scenario_report(
    scenario, window: float | None = None, step: float | None = None, **kwargs
) -> ExcitationReport:
    """:func:`excitation_report` for a scenario's reference input, in its observer's immersion.

    ``window`` defaults to the scenario's ``excitation.window``; ``step`` to the monitor's
    hold step. Needs neither MuJoCo nor rerun.
    """
    spec = scenario.excitation
    block = spec.grid(scenario.dt)[0]
    h = block * scenario.dt if step is None else as_finite_scalar("step", step, positive=True)
    if (
        scenario.duration / h > 1e7
    ):  # the input is sampled over the whole duration: bound the allocation
        raise QuadobsError(
            f"step: {h:g} s gives {scenario.duration / h:.3g} samples over {scenario.duration:g} s; at most 1e7"
        )
    delta = spec.window if window is None else as_finite_scalar("window", window, positive=True)
    if delta > scenario.duration:
        raise QuadobsError(
            f"window: {delta} s is longer than the scenario ({scenario.duration:g} s)"
        )
    im = immerse(scenario.system(), method=scenario.observer.immersion)
    return excitation_report(
        im,
        scenario_input(scenario, h),
        delta,
        threshold=spec.threshold,
        names=state_names(scenario),
        name=scenario.name,
        **kwargs,
    )


def scenario_monitor(scenario, immersion: Immersion | None = None) -> ExcitationMonitor | None:
    """The monitor configured by ``scenario.excitation`` (``None`` when ``monitor = false``)."""
    spec = scenario.excitation
    if not spec.monitor:
        return None
    block, L, upd = spec.grid(scenario.dt)
    im = (
        immerse(scenario.system(), method=scenario.observer.immersion)
        if immersion is None
        else immersion
    )
    return ExcitationMonitor(
        im, scenario.dt, block=block, window_blocks=L, update_blocks=upd, threshold=spec.threshold
    )
