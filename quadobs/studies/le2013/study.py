"""The example of section 5 of [LE2013], reproduced.

.. math::

    x_{k+1} = \\begin{bmatrix} 0 & -0.5 \\\\ 1 & 1 + 0.3\\delta \\end{bmatrix} x_k
              + 0.02 \\begin{bmatrix} -6 \\\\ 1 \\end{bmatrix} w_k, \\qquad
    y_k = \\begin{bmatrix} -2 & 1 \\\\ 1 & 1 \\end{bmatrix} x_k + 0.2 v_k,

``|delta| <= 1``, ``||w_k||_inf, ||v_k||_inf <= 1``, ``x_0 in 3 B^2``, zonotopes of at most 20
generators. Each run draws ``delta`` (constant over the run), ``x_0``, ``w_k`` and ``v_k``
uniformly from their bounds with a seeded generator, and runs the estimators on the same
measurements: segment and volume minimisation (Alamo et al. 2005, applied output after
output) and the P-radius gains of the first and second approaches, plus the second
approach with the gains printed in the paper (a reference for the gain discrepancy).

:func:`run_le2013` produces the recording and the JSON summary of ``quadobs run le2013``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.estimators.zonotopic import ZonotopicEstimator
from quadobs.sets.zonotope import IntervalMatrix, Zonotope

__all__ = [
    "A_INTERVAL",
    "METHODS",
    "NOISE_BOUND",
    "PAPER_GAINS",
    "C",
    "F",
    "Le2013Run",
    "design_gains",
    "make_estimator",
    "reproduce",
    "run_le2013",
    "simulate",
]

A_INTERVAL = IntervalMatrix.from_mid_rad([[0.0, -0.5], [1.0, 1.0]], [[0.0, 0.0], [0.0, 0.3]])
F = 0.02 * np.array([[-6.0], [1.0]])
C = np.array([[-2.0, 1.0], [1.0, 1.0]])
NOISE_BOUND = 0.2
X0_RADIUS = 3.0
MAX_GENERATORS = 20
#: Gains printed in section 5 (rows lambda_1, lambda_2).
PAPER_GAINS = {
    "first_approach": [[-0.2137, 0.5726], [0.3684, 0.3570]],
    "second_approach": [[-0.2137, 0.5726], [0.2839, 0.5085]],
}
#: Estimators compared (keys of the summary).
METHODS = ("segment", "volume", "pradius1", "pradius2", "pradius2_paper")


def design_gains(betas=None) -> dict:
    """P-radius designs of both approaches for the example (:func:`quadobs.pradius_gains`)."""
    from quadobs.sets.pradius import pradius_gains

    return {
        "first_approach": pradius_gains(A_INTERVAL, F, C, NOISE_BOUND, approach=1, betas=betas),
        "second_approach": pradius_gains(A_INTERVAL, F, C, NOISE_BOUND, approach=2, betas=betas),
    }


def simulate(seed: int, steps: int) -> dict:
    """One seeded trajectory: ``delta``, ``x (steps + 1, 2)`` (``x_0..x_K``), ``y (steps + 1, 2)`` (row 0 unused, NaN)."""
    rng = np.random.default_rng(seed)
    delta = rng.uniform(-1.0, 1.0)
    A = np.array([[0.0, -0.5], [1.0, 1.0 + 0.3 * delta]])
    x = np.empty((steps + 1, 2))
    y = np.full((steps + 1, 2), np.nan)
    x[0] = rng.uniform(-X0_RADIUS, X0_RADIUS, 2)
    w = rng.uniform(-1.0, 1.0, (steps, 1))
    v = rng.uniform(-1.0, 1.0, (steps, 2))
    for k in range(1, steps + 1):
        x[k] = A @ x[k - 1] + F @ w[k - 1]
        y[k] = C @ x[k] + NOISE_BOUND * v[k - 1]
    return {"delta": delta, "A": A, "x": x, "y": y}


@dataclass
class Le2013Run:
    """One run of every method on one trajectory.

    ``bounds[m] (K+1, 2, 2)`` interval hulls, ``widths[m] (K+1, 2)``, ``volume[m] (K+1,)``,
    ``inside[m] (K+1,)`` exact containment of the true state, ``seconds[m]`` online time of
    the ``K`` steps, ``sets[m]`` the zonotopes (kept only when asked).
    """

    seed: int
    truth: np.ndarray
    bounds: dict
    widths: dict
    volume: dict
    inside: dict
    seconds: dict
    sets: dict | None


def make_estimator(
    method: str, designs: dict | None = None, *, backend: str = "auto"
) -> ZonotopicEstimator:
    """The estimator ``method`` (one of :data:`METHODS`) of the example, at ``X_0 = 3 B^2``.

    ``designs`` (from :func:`design_gains`) is needed by ``"pradius1"`` and ``"pradius2"``;
    ``backend`` is that of :class:`~quadobs.estimators.zonotopic.ZonotopicEstimator`.
    """
    if method not in METHODS:
        raise QuadobsError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if method in ("pradius1", "pradius2") and designs is None:
        raise QuadobsError(f"designs: method {method!r} needs the designs of design_gains()")
    found: dict = designs or {}
    gains = {
        "segment": lambda: "segment",
        "volume": lambda: "volume",
        "pradius1": lambda: found["first_approach"].gains,
        "pradius2": lambda: found["second_approach"].gains,
        "pradius2_paper": lambda: np.array(PAPER_GAINS["second_approach"]),
    }[method]()
    X0 = Zonotope(np.zeros(2), X0_RADIUS * np.eye(2))
    return ZonotopicEstimator(
        A_INTERVAL, F, C, NOISE_BOUND, X0, gains, max_generators=MAX_GENERATORS, backend=backend
    )


def run_once(
    designs: dict, seed: int, steps: int, *, keep_sets: bool = False, methods=METHODS
) -> Le2013Run:
    """All methods on the trajectory of ``seed`` (:func:`simulate`)."""
    sim = simulate(seed, steps)
    x, y = sim["x"], sim["y"]
    ests = {m: make_estimator(m, designs) for m in METHODS if m in methods}
    out = Le2013Run(seed, x, {}, {}, {}, {}, {}, {} if keep_sets else None)
    for m, est in ests.items():
        bounds = np.empty((steps + 1, 2, 2))
        vol = np.empty(steps + 1)
        inside = np.empty(steps + 1, dtype=bool)
        sets = [est.zonotope]
        elapsed = 0.0
        Z = est.zonotope
        for k in range(steps + 1):
            if k:
                t0 = time.perf_counter()
                Z = est.step(y[k])
                elapsed += time.perf_counter() - t0
                if keep_sets:
                    sets.append(Z)
            bounds[k] = Z.interval_hull()
            vol[k] = Z.volume()
            inside[k] = Z.contains(x[k], method="halfspace")
        out.bounds[m] = bounds
        out.widths[m] = bounds[:, :, 1] - bounds[:, :, 0]
        out.volume[m] = vol
        out.inside[m] = inside
        out.seconds[m] = elapsed
        if keep_sets and out.sets is not None:
            out.sets[m] = sets
    return out


def reproduce(
    *, seed: int = 0, steps: int = 50, runs: int = 50, designs: dict | None = None, methods=METHODS
) -> dict:
    """Section 5 over ``runs`` seeded trajectories (seeds ``seed, seed + 1, ...``).

    Returns
    -------
    dict
        ``designs``, ``first`` (the :class:`Le2013Run` of ``seed``, with its zonotopes), and
        per method: ``containment`` (fraction of the ``runs (steps + 1)`` states inside their
        set), ``mean_width (K+1, 2)`` and ``mean_volume (K+1,)`` over runs, ``online_us``
        (mean online time per step, microseconds), ``total_online_s`` (mean online time of the
        ``steps`` steps of one run).
    """
    if steps < 1 or runs < 1:
        raise QuadobsError(f"steps, runs: must be at least 1, got {steps}, {runs}")
    if designs is None:
        designs = design_gains()
    res: dict[str, Any] = {"designs": designs, "methods": list(methods)}
    acc: dict[str, dict[str, Any]] = {
        m: {
            "inside": 0,
            "width": np.zeros((steps + 1, 2)),
            "volume": np.zeros(steps + 1),
            "seconds": 0.0,
        }
        for m in methods
    }
    first = None
    for r in range(runs):
        run = run_once(designs, seed + r, steps, keep_sets=(r == 0), methods=methods)
        if r == 0:
            first = run
        for m in methods:
            a = acc[m]
            a["inside"] += int(run.inside[m].sum())
            a["width"] += run.widths[m]
            a["volume"] += run.volume[m]
            a["seconds"] += run.seconds[m]
    res["first"] = first
    total = runs * (steps + 1)
    res["containment"] = {m: acc[m]["inside"] / total for m in methods}
    res["mean_width"] = {m: acc[m]["width"] / runs for m in methods}
    res["mean_volume"] = {m: acc[m]["volume"] / runs for m in methods}
    res["online_us"] = {m: 1e6 * acc[m]["seconds"] / (runs * steps) for m in methods}
    res["total_online_s"] = {m: acc[m]["seconds"] / runs for m in methods}
    res["steps"], res["runs"], res["seed"] = steps, runs, seed
    return res


def summary_of(res: dict) -> dict:
    """The JSON summary of a :func:`reproduce` result (keys documented in the README, "Guaranteed estimation with zonotopes")."""
    d = res["designs"]
    methods = res["methods"]

    def r(x, k=6):
        return [round(float(v), k) for v in np.ravel(x)]

    per_step_mean = {
        m: {
            "width_x1": r(res["mean_width"][m][:, 0]),
            "width_x2": r(res["mean_width"][m][:, 1]),
            "volume": r(res["mean_volume"][m], 8),
        }
        for m in methods
    }
    return {
        "scenario": "le2013",
        "steps": res["steps"],
        "runs": res["runs"],
        "seed": res["seed"],
        "gains": {k: [r(row) for row in v.gains] for k, v in d.items()},
        "paper_gains": PAPER_GAINS,
        "design": {
            k: {
                "beta": r(v.beta),
                "tau": r(v.tau),
                "lmi_margin": v.lmi_margin,
                "solver": v.solver,
                "offline_s": round(v.seconds, 4),
            }
            for k, v in d.items()
        },
        "containment": {m: res["containment"][m] for m in methods},
        # mean over runs and over steps 1..K (the initial box is the same for all methods)
        "mean_width": {m: r(res["mean_width"][m][1:].mean(axis=0)) for m in methods},
        "mean_volume": {m: round(float(res["mean_volume"][m][1:].mean()), 8) for m in methods},
        "final_width": {m: r(res["mean_width"][m][-1]) for m in methods},
        "timing": {
            "offline_s": {k: round(v.seconds, 4) for k, v in d.items()},
            "online_us_per_step": {m: round(res["online_us"][m], 2) for m in methods},
            "online_total_s": {m: round(res["total_online_s"][m], 6) for m in methods},
        },
        "per_step_mean": per_step_mean,
    }


def run_le2013(
    out=None,
    summary_path=None,
    *,
    seed: int = 0,
    steps: int = 50,
    runs: int = 50,
    progress: bool = False,
) -> dict:
    """``quadobs run le2013``: design, reproduce, record (``out``, ``.rrd``) and summarise (``summary_path``)."""
    if out is not None or summary_path is not None:
        from quadobs.errors import check_writable

        for path in (out, summary_path):
            if path is not None:
                check_writable(path)
    res = reproduce(seed=seed, steps=steps, runs=runs)
    summary = summary_of(res)
    summary["recording"] = None if out is None else str(out)
    if out is not None:
        from quadobs.studies.le2013.recording import record_le2013

        record_le2013(out, res, format_table(summary_of(res)))
    if summary_path is not None:
        from quadobs.testbed.episode import write_json_atomic

        write_json_atomic(summary_path, summary)
    return summary


def format_table(summary: dict) -> str:
    """The comparison as text: gains next to the paper's, widths, volume, containment, timings."""
    lines = []
    for k in ("first_approach", "second_approach"):
        ours, paper = summary["gains"][k], summary["paper_gains"][k]
        for i, (a, b) in enumerate(zip(ours, paper)):
            lines.append(
                f"{k} lambda_{i + 1}: [{a[0]:+.4f} {a[1]:+.4f}]   paper [{b[0]:+.4f} {b[1]:+.4f}]"
            )
    lines.append(
        f"{summary['runs']} runs x {summary['steps']} steps (seeds {summary['seed']}..{summary['seed'] + summary['runs'] - 1})"
    )
    head = f"{'method':16s} {'width x1':>9s} {'width x2':>9s} {'volume':>9s} {'inside':>7s} {'us/step':>8s}"
    lines.append(head)
    t = summary["timing"]["online_us_per_step"]
    for m, w in summary["mean_width"].items():
        lines.append(
            f"{m:16s} {w[0]:9.4f} {w[1]:9.4f} {summary['mean_volume'][m]:9.5f} {summary['containment'][m]:7.3f} {t[m]:8.1f}"
        )
    off = summary["timing"]["offline_s"]
    lines.append(
        f"offline LMI design: first approach {off['first_approach']:.3f} s, second approach {off['second_approach']:.3f} s"
    )
    return "\n".join(lines)
