"""The figures of the built-in scenarios shown in the documentation (``docs/figures``).

Regenerate them all with one command (a few minutes: every built-in scenario is run at
its full duration, the le2013 study at its defaults, and a campaign of ``ifac2021-noisy``)::

    python -m quadobs.studies.plot docs/figures

Each figure is the default figure of its input (:func:`quadobs.studies.plot.render`), at
7.0 x 4.5 in and 100 dpi (700 x 450 pixels) to keep the documentation light.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

__all__ = ["ESTIMATORS", "make_figures"]

DPI = 100
ESTIMATORS = {
    "ifac2021-noisy": ["augmented", "ekf", "ukf"],
    "ifac2021-outliers": ["augmented", "ekf", "ukf"],
    "ifac2021-bounded": ["augmented", "zonotope"],
}
"""Estimators drawn for a scenario (default: the augmented observer and the scenario's variants)."""
CAMPAIGN: dict[str, Any] = {
    "scenario": "ifac2021-noisy",
    "runs": 16,
    "duration": 20.0,
    "estimators": ["augmented", "ekf", "ukf"],
}


def make_figures(folder, *, only=None, log=print) -> list[Path]:
    """Run the built-in scenarios, the le2013 study and a campaign, and write their figures to ``folder``.

    Parameters
    ----------
    folder : str or Path
        Where ``<scenario>.png``, ``le2013.png`` and ``campaign-<scenario>.png`` go.
    only : list of str, optional
        Names to make (scenario names, ``le2013``, ``campaign``); default: all.
    log : callable
        Progress messages.

    Returns
    -------
    list of Path
        The figures written.
    """
    from quadobs.studies.campaign import run_campaign
    from quadobs.studies.le2013.study import run_le2013
    from quadobs.studies.plot import render
    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.registry import default_estimators
    from quadobs.testbed.scenario import list_scenarios, load_scenario

    folder = Path(folder)
    names = list(list_scenarios()) + ["le2013", "campaign"]
    wanted = names if only is None else list(only)
    unknown = [n for n in wanted if n not in names]
    if unknown:
        from quadobs.errors import QuadobsError

        raise QuadobsError(f"figure {unknown[0]!r}: not a built-in scenario, le2013 or campaign")
    written = []
    with tempfile.TemporaryDirectory(prefix="quadobs-figures-") as tmp:
        for name in wanted:
            log(f"[figures] {name}")
            rrd = Path(tmp) / f"{name}.rrd"
            if name == "le2013":
                run_le2013(rrd)
                written.append(render(rrd, folder / "le2013.png", dpi=DPI))
            elif name == "campaign":
                sc = load_scenario(CAMPAIGN["scenario"], duration=CAMPAIGN["duration"])
                run_campaign(
                    sc,
                    runs=CAMPAIGN["runs"],
                    estimators=CAMPAIGN["estimators"],
                    out_dir=Path(tmp) / "camp",
                    progress=False,
                )
                written.append(
                    render(
                        Path(tmp) / "camp", folder / f"campaign-{CAMPAIGN['scenario']}.png", dpi=DPI
                    )
                )
            else:
                sc = load_scenario(name)
                run_episode(
                    sc,
                    estimators=ESTIMATORS.get(name, default_estimators(sc)),
                    out=rrd,
                    progress=False,
                )
                written.append(render(rrd, folder / f"{name}.png", dpi=DPI))
    return written
