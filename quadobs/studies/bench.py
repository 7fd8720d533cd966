"""``quadobs bench``: how much the estimators cost beside the physics, measured side by side.

Every figure is measured in the same process and run. Ratios are formed within one
repeat (bare physics, then the loop without and with recording, one after the other) and
the reported value is the median over the repeats, so a machine whose load changes
during the run still gives comparable numbers; per-step costs are medians too.

Figures (keys of the JSON written by ``--json``):

``bare_steps_per_s``, ``bare_step_us``
    ``mujoco.mj_step`` of the testbed vehicle (``ifac2021`` model) in a Python loop.
``observer_loop_ratio``
    Steps per second of ``quadobs run`` without recording (physics, sensors, augmented
    observer, errors) over bare physics, on the path ``quadobs run`` takes by default
    (the block path, :mod:`quadobs.testbed.episode`).
``loop_ratio``
    The same with the ``.rrd`` recording: physics + observer + recording over bare physics.
``recording_fraction``
    Share of the recorded loop's time due to the recording: ``1 - t_norec / t_rec``.
``serial_observer_loop_ratio``, ``serial_loop_ratio``, ``serial_recording_fraction``
    The same three figures on the block path without the background thread
    (``PointMassWorld(pipelined=False)``: each block's physics in the loop's own thread),
    measured in the same repeats: what the second core brings.
``step_observer_loop_ratio``, ``step_loop_ratio``, ``step_recording_fraction``
    The same three figures on the per-step path (``run_episode(path="step")``), measured
    in the same repeats.
``spread``
    For each ratio and fraction above: ``median``, quartiles ``q1``, ``q3`` and ``iqr``
    over the repeats.
``best``
    The same three figures from the fastest run of each kind (least disturbed by other
    load on the machine).
``cold_start``
    A first run on a fresh kernel cache (:func:`_cold_start`): ``cold_run_s``,
    ``compile_s`` (``quadobs compile``), ``first_run_s`` (the run after it). Absent with
    ``--no-cold-start``.
``observer_block_step_us``
    One row of :meth:`AugmentedObserver.step_block` (a block of rows in one compiled call).
``observer_in_time_step_us``, ``observer_in_time``
    One step of ``quadrotor-uwb``'s live observer, each range at its own time and the
    prediction through the exponentials of the interval (:func:`_observer_in_time_us`), with
    the grid step of the same observer beside it (``observer_in_time["grid_step_us"]``) and the
    same step in time through the NumPy reference (``observer_in_time["in_time_numpy_step_us"]``).
``campaign``
    Episodes per second of ``ifac2021-noisy`` (the default estimators, with the traces a
    campaign collects) over all cores, against as many bare physics episodes of the same
    length on as many processes: ``campaign_ratio`` once the campaign's workers are
    started (:func:`_campaign`), ``cold_campaign_ratio`` with their start-up.
``quadrotor``
    The quadrotor in the loop (``quadrotor-uwb-augmented``, 20 s: physics, controller,
    IMU and UWB sensors, augmented observer, recording) against bare ``mj_step`` on
    ``models/quadrotor.xml``; ``quadrotor_ratio`` is the median of their ratio over the repeats.
``observer_step_us``, ``observer_numpy_step_us``
    One :meth:`AugmentedObserver.step` (compiled; NumPy reference) on the vehicle.
``ekf_step_us``, ``ukf_step_us``
    One step of the estimators registered as ``ekf`` and ``ukf`` (``null`` where not
    registered; ``notes`` says why).
``zonotope_vehicle_step_us``, ``zonotope_vehicle``
    One step of the guaranteed (zonotopic) vehicle estimator on ``ifac2021-bounded``, the
    ranges sampled at the scenario's rate; ``zonotope_vehicle`` adds the cost with outputs
    at every step.
``lmi_design_s``, ``lmi_design_split_s``, ``lmi_import_s``
    The offline P-radius design of ``le2013`` (:func:`quadobs.studies.le2013.study.design_gains`: both
    approaches, seconds of wall-clock), the time of each approach, and the one-off import
    of the modelling package (cvxpy), paid before the design is timed.
``zonotope_step_us``, ``le2013_step_us``
    The online step of the ``le2013`` estimator with the second approach's gains
    (compiled); ``le2013_step_us`` holds every method, compiled (``numba``) and the NumPy
    reference (``numpy``), each the mean over runs of 50 steps from ``X_0``.
``batch``
    ``B`` vehicles stepped together (:class:`~quadobs.testbed.worlds.batch.VehicleBatch`) with a
    :class:`~quadobs.estimators.augmented_batch.BatchAugmentedObserver`: vehicle-steps per second of the physics
    alone and with sensors and observers; ``batch_ratio`` is their ratio.
``scaling``
    Observer step cost against the state dimension ``n``, the number of outputs ``q``
    and the augmented dimension ``N`` (fastest of a few repeats: the table shows growth;
    each row also holds the median, ``<backend>_median_us``).
``observer_step_us_N38``
    One :meth:`AugmentedObserver.step` on a system with a dense transition and ``N = 38``
    (the ``dense`` row of ``scaling``, :func:`_dense_system`; median over the repeats): the
    compiled kernel's dense path (:mod:`quadobs._kernels.observer`).
``log_read``
    Reading a log's ``ranges.csv`` of 300 000 rows (:func:`log_read_figure`): seconds of
    the format's reader (``pyarrow.csv`` and the schema's checks) against a ``float()`` per
    cell in Python (how the format was read before, and how it is still read to name a
    faulty row), the median of the repeats, and ``log_read_speedup``, their ratio.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["BENCH_KEYS", "print_bench", "run_bench"]

#: Keys every bench JSON holds (``ekf_step_us``, ``ukf_step_us`` are ``null`` if those estimators are not registered).
BENCH_KEYS = (
    "loop_ratio",
    "batch_ratio",
    "recording_fraction",
    "observer_step_us",
    "observer_step_us_N38",
    "ekf_step_us",
    "ukf_step_us",
    "zonotope_step_us",
    "zonotope_vehicle_step_us",
    "lmi_design_s",
    "step_loop_ratio",
    "observer_block_step_us",
    "campaign_ratio",
    "observer_in_time_step_us",
)


def _median(xs) -> float | None:
    xs = [x for x in xs if x is not None]
    return float(statistics.median(xs)) if xs else None


def _middle(xs: list[float]) -> float:
    """The median of measurements that all exist (at least one)."""
    return float(statistics.median(xs))


def _timed_us(
    run: Callable[[Any], object], units: int, repeats: int, make: Callable[[], Any] | None = None
) -> list[float]:
    """Wall time (us) per unit of work of ``run(obj)``, once per repeat: the one timing loop.

    ``run`` does ``units`` units of work (steps, rows) on ``obj``, which is ``make()`` (a
    fresh estimator, built outside the timing) or ``None``.
    """
    times = []
    for _ in range(repeats):
        obj = make() if make is not None else None
        t0 = time.perf_counter()
        run(obj)
        times.append((time.perf_counter() - t0) / units * 1e6)
    return times


def _stepper(est, U, Y, calls: int) -> Callable[[Any], None]:
    """``est.step(U[k], Y[k])`` for ``k < calls`` (on ``est``, or on the object given when ``est`` is None)."""

    def run(obj) -> None:
        e = est if est is not None else obj
        for k in range(calls):
            e.step(U[k], Y[k])

    return run


# -- single vehicle --------------------------------------------------------------------


def _bare_physics_us(scenario, steps: int) -> float:
    import mujoco

    from quadobs.testbed.worlds import VehicleSim

    sim = VehicleSim.of(scenario)
    m, d, step = sim.model, sim.data, mujoco.mj_step
    for _ in range(min(steps, 1000)):  # warm caches
        step(m, d)
    t0 = time.perf_counter()
    for _ in range(steps):
        step(m, d)
    return (time.perf_counter() - t0) / steps * 1e6


def _quartiles(xs) -> dict:
    """Median, quartiles and interquartile range of ``xs``."""
    q1, med, q3 = (float(v) for v in np.percentile(np.asarray(xs, dtype=float), [25, 50, 75]))
    return {"median": med, "q1": q1, "q3": q3, "iqr": q3 - q1}


def _loop_us(scenario, out: Path | None, path: str = "auto", pipelined: bool = True) -> float:
    """Wall time per step of ``run_episode`` with the augmented observer; ``pipelined=False``:
    the block path with each block's physics computed in the loop's own thread."""
    import functools

    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.worlds import PointMassWorld

    world = None if pipelined else functools.partial(PointMassWorld, pipelined=False)
    summary = run_episode(
        scenario, estimators=["augmented"], out=out, path=path, world=world
    ).summary
    return summary["wall_time"] / summary["physics_steps"] * 1e6


def _cold_start(scenario: str = "ifac2021") -> dict:
    """Seconds from the command to the end of a one-step ``quadobs run`` on a fresh kernel cache.

    An upper bound on the time a first run of a fresh install spends before its first
    step: the whole process (interpreter, imports, kernels, world, one step, summary) with
    ``NUMBA_CACHE_DIR`` an empty folder. ``cold_run_s``: the run compiles what it needs
    itself (side by side, :mod:`quadobs._kernels.precompile`); ``compile_s``: ``quadobs
    compile`` on an empty cache (the ahead-of-time step of the installation in the
    README); ``first_run_s``: the run after it.
    """
    import subprocess

    run = [sys.executable, "-m", "quadobs", "run", scenario, "--duration", "0.001", "--no-progress"]
    out = {}
    for key, commands in (
        ("cold_run_s", [run]),
        ("compile_s", [[sys.executable, "-m", "quadobs", "compile"], run]),
    ):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            for name, cmd in zip((key, "first_run_s"), commands):
                t0 = time.perf_counter()
                subprocess.run(cmd, env=env, check=True, capture_output=True)
                out[name] = time.perf_counter() - t0
    return out


def _vehicle_data(scenario, steps: int):
    """Noise-free inputs and outputs ``(u_k, y_k)`` of the scenario's reference trajectory."""
    dt = scenario.dt
    t = np.arange(steps) * dt
    acc = scenario.trajectory.step_accelerations(0.0, dt, steps)
    pos = scenario.trajectory.position(t)
    x = np.concatenate([pos, scenario.trajectory.velocity_at(t)], axis=1)
    if scenario.has_wind:
        x = np.concatenate(
            [
                x[:, : scenario.dimension],
                x[:, scenario.dimension :] - scenario.wind,
                np.broadcast_to(scenario.wind, pos.shape),
            ],
            axis=1,
        )
    y = scenario.system().output(x)
    return np.ascontiguousarray(acc), np.ascontiguousarray(y), x[0]


def _estimator_step_us(
    scenario, name: str, calls: int, repeats: int
) -> tuple[float | None, str | None]:
    """Median cost of one ``step`` of the registered estimator ``name`` on the scenario's data."""
    from quadobs.testbed.registry import available_estimators, build_estimators

    if name not in available_estimators(scenario):
        return None, f"{name}: not registered in this build"
    try:
        U, Y, x0 = _vehicle_data(scenario, calls)
        est = build_estimators(scenario, [name], x0)[0]
        est.step(U[0], Y[0])
        return _middle(_timed_us(_stepper(est, U, Y, calls), calls, repeats)), None
    except Exception as exc:
        return None, f"{name}: could not be measured ({type(exc).__name__}: {exc})"


def _observer_step_us(scenario, calls: int, repeats: int, backend: str) -> float:
    from quadobs.testbed.factories import augmented_observer

    U, Y, x0 = _vehicle_data(scenario, calls)
    obs = augmented_observer(scenario, np.zeros(scenario.state_dim))
    if backend != obs.backend:
        from quadobs.estimators.augmented import AugmentedObserver

        obs = AugmentedObserver(
            obs.immersion,
            scenario.dt,
            V=obs.model.V,
            W=obs.W,
            P0=obs.P.copy(),
            theta=obs.model.theta,
            sample_period=scenario.dt,
            gate=obs.gate,
            backend=backend,
        )
    obs.prepare("step")  # compiled (or loaded) before the timing
    return _middle(_timed_us(_stepper(obs, U, Y, calls), calls, repeats))


def _observer_block_step_us(scenario, calls: int, repeats: int) -> float:
    """Cost of one row of :meth:`AugmentedObserver.step_block` over blocks of ``calls`` rows."""
    from quadobs.testbed.factories import augmented_observer

    U, Y, x0 = _vehicle_data(scenario, calls)
    obs = augmented_observer(scenario, np.zeros(scenario.state_dim))
    rec = np.zeros((calls, scenario.state_dim + 3))
    return _middle(_timed_us(lambda _: obs.step_block(U, Y, rec), calls, repeats))


def _observer_in_time_us(calls: int, repeats: int) -> dict:
    """One step of ``quadrotor-uwb``'s live observer, ranges in time, against the grid step.

    ``in_time_step_us``: :class:`~quadobs.testbed.ranges_in_time.RangesInTime` (each range
    corrected at its own time with its own variance, then the prediction over the step through
    the exponentials of the interval with the state-dependent noise); ``grid_step_us``: the
    same scenario's :class:`~quadobs.estimators.augmented.AugmentedObserver` step on the grid
    (compiled). Both take the reference trajectory's noise-free inputs and one range per step,
    the anchors in turn. ``in_time_numpy_step_us``: the same step in time through the NumPy
    reference of the prediction and the correction (``in_time_compiled = False``), side by side.
    """
    from quadobs.testbed.factories import augmented_observer, live_observer
    from quadobs.testbed.scenario import load_scenario

    sc = load_scenario("quadrotor-uwb")
    U, Y, x0 = _vehicle_data(sc, calls)
    Y = np.where(np.arange(Y.shape[1]) == (np.arange(calls) % Y.shape[1])[:, None], Y, np.nan)

    def numpy_in_time(sc, x0):
        est = live_observer(sc, x0)
        est.inner.in_time_compiled = False
        return est

    times = {}
    for key, build in (
        ("in_time_step_us", live_observer),
        ("grid_step_us", augmented_observer),
        ("in_time_numpy_step_us", numpy_in_time),
    ):
        _stepper(build(sc, x0), U, Y, min(calls, 20))(None)  # kernels compiled (or loaded)

        def make(build=build):
            return build(sc, x0)

        times[key] = _middle(_timed_us(_stepper(None, U, Y, calls), calls, repeats, make))
    return {"scenario": sc.name, "steps": calls, **times}


# -- campaign throughput ----------------------------------------------------------------


def _bare_episode(task: tuple) -> float:
    """One bare physics episode (``mj_step`` in a Python loop) of ``steps`` steps; returns its seconds."""
    import mujoco

    from quadobs.testbed.scenario import load_scenario
    from quadobs.testbed.worlds import VehicleSim

    name, steps = task
    sc = load_scenario(name)
    t0 = time.perf_counter()
    sim = VehicleSim.of(sc)
    m, d, step = sim.model, sim.data, mujoco.mj_step
    for _ in range(steps):
        step(m, d)
    return time.perf_counter() - t0


def _campaign(name: str, runs: int, duration: float, workers: int) -> dict:
    """Episodes per second of a campaign on all cores against bare physics episodes on as many processes.

    A campaign starts its own worker processes (interpreter, imports, kernels from the
    cache), which a short campaign's figure mostly measures; the bare episodes run on
    workers started beforehand. So the campaign is timed twice, with ``runs`` and
    ``2 runs`` episodes: the difference gives its rate once started
    (``marginal_episodes_per_s``, against the bare rate in ``campaign_ratio``) and its
    start-up (``startup_s``); ``episodes_per_s`` is the first campaign's figure, start-up
    included (``cold_campaign_ratio`` against the bare rate).
    """
    from concurrent.futures import ProcessPoolExecutor

    from quadobs.studies.campaign import run_campaign
    from quadobs.testbed.scenario import load_scenario

    sc = load_scenario(name, duration=duration)
    times = []
    for n in (runs, 2 * runs):
        t0 = time.perf_counter()
        run_campaign(sc, runs=n, workers=workers, record=False)
        times.append(time.perf_counter() - t0)
    with ProcessPoolExecutor(max_workers=workers) as pool:
        list(pool.map(_bare_episode, [(name, 10)] * workers))  # start the workers, import MuJoCo
        t0 = time.perf_counter()
        list(pool.map(_bare_episode, [(name, sc.steps)] * runs))
        bare = time.perf_counter() - t0
    marginal = runs / max(times[1] - times[0], 1e-9)
    return {
        "scenario": name,
        "runs": runs,
        "duration": duration,
        "workers": workers,
        "episodes_per_s": runs / times[0],
        "marginal_episodes_per_s": marginal,
        "startup_s": max(times[0] - runs / marginal, 0.0),
        "bare_episodes_per_s": runs / bare,
        "campaign_ratio": marginal * bare / runs,
        "cold_campaign_ratio": bare / times[0],
    }


# -- le2013 (zonotopes) ----------------------------------------------------------------


def _lmi_design_s() -> tuple[float, dict, float, dict]:
    """Offline P-radius design of ``le2013`` (:func:`quadobs.studies.le2013.study.design_gains`: both approaches).

    Returns the wall-clock seconds, the seconds of each approach (``PRadiusDesign.seconds``),
    the seconds of importing the modelling package, which is done first (a cost paid once
    per process), so that the figure is the design alone, and the designs (for the online
    figures).
    """
    import quadobs.studies.le2013.study as le2013
    from quadobs.sets.pradius import require_lmi_solvers

    t0 = time.perf_counter()
    require_lmi_solvers("bench")  # imports cvxpy

    import_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    designs = le2013.design_gains()
    total = time.perf_counter() - t0
    return total, {k: d.seconds for k, d in designs.items()}, import_s, designs


def _le2013_run_us(designs, method: str, backend: str, steps: int, repeats: int) -> float:
    """Median over ``repeats`` runs of ``steps`` steps from ``X_0`` of the mean online step (us)."""
    import quadobs.studies.le2013.study as le2013

    Y = le2013.simulate(0, steps)["y"]

    def run(est) -> None:
        for k in range(1, steps + 1):
            est.step(Y[k])

    make = lambda: le2013.make_estimator(method, designs, backend=backend)  # noqa: E731
    return _middle(_timed_us(run, steps, repeats, make))


def _le2013_step_us(designs, calls: int, repeats: int) -> dict:
    """Online step of every ``le2013`` method, compiled (``"numba"``) and NumPy reference (us).

    Runs of ``min(calls, 50)`` steps (the paper's length) from ``X_0``, repeated until
    ``calls`` steps are timed; the volume method (a linear program per output) and the
    reference run fewer.
    """
    from quadobs.studies.le2013.study import METHODS

    steps = min(calls, 50)
    runs = max(repeats, calls // steps)
    out = {}
    for m in METHODS:
        slow = m == "volume"
        out[m] = {
            "numba": _le2013_run_us(
                designs, m, "numba", steps, max(runs // 20, 1) if slow else runs
            ),
            "numpy": _le2013_run_us(
                designs, m, "numpy", steps, max(runs // 20, 1) if slow else max(runs // 5, 1)
            ),
        }
    return out


def _vehicle_zonotope_us(calls: int, repeats: int) -> dict:
    """Step of the vehicle zonotope estimator on ``ifac2021-bounded`` (its reference trajectory, noise-free data).

    ``step_us``: the outputs sampled as in the scenario (``range_every`` physics steps apart,
    NaN between); ``correct_every_step_us``: outputs at every step (the worst case).
    """
    from quadobs.testbed.registry import build_estimators
    from quadobs.testbed.scenario import load_scenario

    sc = load_scenario("ifac2021-bounded")
    U, Y, x0 = _vehicle_data(sc, calls)
    every = sc.sample_interval(sc.noise.range_rate, "range_rate")
    Ys = np.full_like(Y, np.nan)
    Ys[::every] = Y[::every]
    res = {"scenario": sc.name, "range_every": every, "steps": calls}
    for key, data in (("step_us", Ys), ("correct_every_step_us", Y)):
        make = lambda: build_estimators(sc, ["zonotope"], x0)[0]  # noqa: E731
        res[key] = _middle(_timed_us(_stepper(None, U, data, calls), calls, repeats, make))
    return res


# -- batch -----------------------------------------------------------------------------


def _batch(scenario, B: int, steps: int, repeats: int, threads: int) -> dict:
    from quadobs.core.system import range_outputs
    from quadobs.estimators.augmented_batch import BatchAugmentedObserver
    from quadobs.testbed.factories import augmented_observer
    from quadobs.testbed.worlds.batch import VehicleBatch

    rng = np.random.default_rng(scenario.seed)
    dim, dt = scenario.dimension, scenario.dt
    acc = scenario.trajectory.step_accelerations(0.0, dt, steps)
    p0 = scenario.trajectory.position(0.0) + rng.uniform(-10.0, 10.0, (B, dim))
    v0 = scenario.trajectory.velocity_at(0.0) + rng.uniform(-1.0, 1.0, (B, dim))
    template = augmented_observer(scenario, np.zeros(scenario.state_dim))
    phys, full = [], []
    with VehicleBatch(
        dim,
        scenario.beacons,
        B,
        timestep=dt,
        wind=scenario.wind,
        model_path=scenario.model,
        threads=threads,
    ) as vb:
        vb.reset(p0, v0)
        vb.step(acc[0])
        for _ in range(repeats):
            vb.reset(p0, v0)
            t0 = time.perf_counter()
            for k in range(steps):
                vb.step(acc[k])
            phys.append((time.perf_counter() - t0) / (steps * B) * 1e6)
            vb.reset(p0, v0)
            obs = BatchAugmentedObserver(template, B, threads=threads)
            t0 = time.perf_counter()
            for k in range(steps):
                vb.step(acc[k])
                Y = range_outputs(vb.ranges(), scenario.beacons)
                if scenario.has_wind:
                    Y = np.concatenate([Y, 0.5 * vb.airspeed()[:, None] ** 2], axis=1)
                obs.step(np.ascontiguousarray(vb.accelerometer()), np.ascontiguousarray(Y))
            full.append((time.perf_counter() - t0) / (steps * B) * 1e6)
            obs.close()
    ratios = [p / f for p, f in zip(phys, full)]
    return {
        "vehicles": B,
        "steps": steps,
        "threads": threads,
        "physics_vehicle_steps_per_s": 1e6 / _middle(phys),
        "with_observer_vehicle_steps_per_s": 1e6 / _middle(full),
        "physics_us_per_vehicle_step": _middle(phys),
        "with_observer_us_per_vehicle_step": _middle(full),
        "batch_ratio": _middle(ratios),
    }


# -- scaling ---------------------------------------------------------------------------


def _dense_system():
    """A system with a dense transition whose augmented state has ``N = 38`` entries (``n = 8``, one output).

    ``A = V J V^T`` with ``V`` a random rotation and ``J`` three stable rotation-scaling
    blocks and two stable real eigenvalues, and ``C = V C' V^T`` with ``C'`` a random
    symmetric matrix whose coupling of the first two blocks (4 entries) and of the third
    block with the first real eigenvalue (2 entries) is zero: in the eigenbasis of ``A``
    those entries span an ``L_A``-invariant part of ``Sym(8)`` the output never reaches, so
    ``n_aux = 36 - 6 = 30`` (certified, :func:`quadobs.immerse`) where a generic output
    gives 36. ``A`` and ``Phi`` are dense (``Phi`` 83 % nonzero).
    """
    from scipy.linalg import block_diag

    from quadobs.core.system import QuadraticSystem

    rng = np.random.default_rng(27)  # a draw whose auxiliary count is certified with a wide margin
    blocks = []
    for _ in range(3):
        a, b = rng.uniform(-0.6, -0.1), rng.uniform(0.3, 1.5)
        blocks.append(np.array([[a, b], [-b, a]]))
    blocks += [np.array([[rng.uniform(-1.0, -0.1)]]) for _ in range(2)]
    J = block_diag(*blocks)
    n = J.shape[0]
    V = np.linalg.qr(rng.standard_normal((n, n)))[0]
    Cp = rng.standard_normal((n, n))
    Cp = Cp + Cp.T
    Cp[0:2, 2:4] = Cp[2:4, 0:2] = 0.0
    Cp[4:6, 6:7] = Cp[6:7, 4:6] = 0.0
    return QuadraticSystem(V @ J @ V.T, rng.standard_normal((n, 1)), (V @ Cp @ V.T)[None])


def _warm(im, backend: str, u0, y0) -> Callable[[], Any]:
    """A maker of augmented observers on ``im`` that have taken one step (compiled before the timing)."""

    def make():
        from quadobs.estimators.augmented import AugmentedObserver

        obs = AugmentedObserver(im, 1e-3, backend=backend)
        obs.step(u0, y0)
        return obs

    return make


def _scaling(calls: int, quick: bool, repeats: int) -> list[dict]:
    from quadobs.core.immersion import immerse
    from quadobs.core.system import QuadraticSystem, vehicle_system, wind_system
    from quadobs.estimators.augmented import default_backend

    rng = np.random.default_rng(8)
    cases = [
        ("vehicle", 2, 1),
        ("vehicle", 3, 1),
        ("vehicle", 3, 4),
        ("wind", 3, 2),
        ("dense", 8, 1),
    ]
    if not quick:
        cases = [
            ("vehicle", 2, 1),
            ("vehicle", 2, 4),
            ("vehicle", 3, 1),
            ("vehicle", 3, 2),
            ("vehicle", 3, 4),
            ("vehicle", 3, 8),
            ("wind", 2, 2),
            ("wind", 3, 2),
            ("wind", 3, 4),
            ("random", 2, 1),
            ("random", 4, 1),
            ("random", 6, 1),
            ("random", 8, 1),
            ("random", 4, 3),
            ("dense", 8, 1),
        ]
    rows = []
    for kind, size, q in cases:
        if kind == "vehicle":
            system = vehicle_system(size, 10.0 * rng.standard_normal((q, size)))
        elif kind == "wind":
            system = wind_system(size, 10.0 * rng.standard_normal((q, size)))
        elif kind == "dense":
            system = _dense_system()
        else:
            A = rng.standard_normal((size, size)) / np.sqrt(size)
            C = rng.standard_normal((q, size, size))
            system = QuadraticSystem(A, rng.standard_normal((size, 1)), C + C.transpose(0, 2, 1))
        im = immerse(system)
        U = rng.standard_normal((calls, system.p))
        Y = rng.standard_normal((calls, system.q))
        row = {"system": kind, "n": system.n, "q": system.q, "N": im.dim}
        for backend, n_calls in ((default_backend(), calls), ("numpy", max(calls // 20, 10))):
            times = _timed_us(
                _stepper(None, U, Y, n_calls), n_calls, repeats, _warm(im, backend, U[0], Y[0])
            )
            row[f"{backend}_us"] = min(
                times
            )  # the fastest of the repeats: the table shows growth, not load
            row[f"{backend}_median_us"] = _median(times)
        rows.append(row)
    return rows


# -- the bench ---------------------------------------------------------------------------


def _quadrotor_case(steps: int, repeats: int) -> dict:
    """The quadrotor in the loop (``quadrotor-uwb-augmented``) against bare ``mj_step`` on ``models/quadrotor.xml``.

    Within each repeat: bare physics (the model at its trajectory's start, rotors at hover
    thrust, ``mj_step`` in a Python loop), then ``run_episode`` with the augmented observer
    and the ``.rrd`` recording (physics, controller flown on the estimate after the switch,
    IMU, UWB sensors, observer, flight sinks). ``quadrotor_ratio`` is the median over the
    repeats of bare time over loop time per step.
    """
    import mujoco

    from quadobs.testbed.episode import run_episode
    from quadobs.testbed.scenario import load_scenario
    from quadobs.testbed.worlds.quadrotor import quadrotor_model_path

    sc = load_scenario("quadrotor-uwb-augmented")
    sc = sc.with_overrides(duration=steps * sc.dt)
    m = mujoco.MjModel.from_xml_path(str(quadrotor_model_path()))
    m.opt.timestep = sc.dt
    d = mujoco.MjData(m)

    def bare() -> float:
        mujoco.mj_resetData(m, d)
        d.qpos[:3] = sc.trajectory.position(0.0)
        d.ctrl[:] = 0.0319 * 9.81 / 4
        t0 = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(m, d)
        return (time.perf_counter() - t0) / steps * 1e6

    bare_us, loop_us = [], []
    with tempfile.TemporaryDirectory() as tmp:
        run_episode(
            sc, estimators=["augmented"], out=Path(tmp) / "warm.rrd"
        )  # compiled kernels loaded
        for r in range(repeats):
            bare_us.append(bare())
            summary = run_episode(
                sc, estimators=["augmented"], out=Path(tmp) / f"quad{r}.rrd"
            ).summary
            loop_us.append(summary["wall_time"] / summary["physics_steps"] * 1e6)
    ratios = [b / x for b, x in zip(bare_us, loop_us)]
    return {
        "scenario": sc.name,
        "steps": steps,
        "repeats": repeats,
        "bare_step_us": _middle(bare_us),
        "loop_us": _middle(loop_us),
        "loop_steps_per_s": 1e6 / _middle(loop_us),
        "quadrotor_ratio": _middle(ratios),
        "spread": _quartiles(ratios),
    }


def run_bench(
    *,
    steps: int = 20000,
    repeats: int = 5,
    batch: int = 1000,
    batch_steps: int = 200,
    threads: int = 0,
    quick: bool = False,
    cold_start: bool = True,
    log=None,
) -> dict:
    """Measure every figure of the module docstring; returns the JSON-ready dictionary.

    Parameters
    ----------
    steps : int
        Physics steps per single-vehicle run (``ifac2021`` cut to this many steps).
    repeats : int
        Repeats of every measurement (the medians are reported).
    batch, batch_steps : int
        Vehicles in the batch and steps per batch run.
    threads : int
        Threads of MuJoCo's rollout pool and of the batched observer (0: the calling thread).
    quick : bool
        A small table of systems for the scaling figure.
    cold_start : bool
        Measure the first run on a fresh kernel cache (:func:`_cold_start`: it compiles every
        kernel twice, the longest part of a quick bench); ``False`` leaves ``cold_start`` out
        and its target unmeasured.
    log : callable, optional
        Called with a progress message before each part.
    """
    from quadobs.testbed.episode import single_threaded_blas

    with single_threaded_blas():  # as in ``quadobs run``: no BLAS worker threads beside the loop
        return _run_bench(steps, repeats, batch, batch_steps, threads, quick, cold_start, log)


def _run_bench(steps, repeats, batch, batch_steps, threads, quick, cold_start, log) -> dict:
    from quadobs.estimators.augmented import default_backend
    from quadobs.testbed.scenario import load_scenario

    say = log or (lambda msg: None)
    sc = load_scenario("ifac2021")
    sc = sc.with_overrides(duration=steps * sc.dt)
    notes: list[str] = []
    result = _machine_and_config(sc, steps, repeats, batch, batch_steps, threads)
    _single_vehicle(result, sc, steps, repeats, say)
    calls = max(min(steps, 5000), 100)
    _estimator_costs(result, sc, calls, repeats, say, notes)
    say(f"batch: {batch} vehicles x {batch_steps} steps, {repeats} repeats")
    result["batch"] = _batch(sc, batch, batch_steps, repeats, threads)
    result["batch_ratio"] = result["batch"]["batch_ratio"]

    workers = os.cpu_count() or 1
    episodes = (
        8 if quick else 2
    ) * workers  # short episodes: enough of them to time the rate once started
    say(
        f"campaign: ifac2021-noisy, {episodes} then {2 * episodes} episodes on {workers} processes, against bare physics"
    )
    result["campaign"] = _campaign("ifac2021-noisy", episodes, 1.0 if quick else 10.0, workers)
    result["campaign_ratio"] = result["campaign"]["campaign_ratio"]

    say("quadrotor: physics + controller + IMU/UWB + observer + recording against bare mj_step")
    result["quadrotor"] = _quadrotor_case(
        20000, max(min(repeats, 9), 3)
    )  # 20 s: take-off, flight on the estimate, landing
    say("scaling with n and q")
    result["scaling"] = _scaling(max(min(calls, 2000), 50), quick, max(repeats // 2, 1))
    dense_row = next(row for row in result["scaling"] if row["system"] == "dense")
    result["observer_step_us_N38"] = dense_row[f"{default_backend()}_median_us"]
    say("log reading: a 300k-row ranges.csv, pyarrow against a float() per cell")
    result["log_read"] = log_read_figure(repeats=max(min(repeats, 5), 1))
    if cold_start:
        say("first run on a fresh kernel cache, with and without 'quadobs compile' before it")
        result["cold_start"] = _cold_start()
    notes.append(
        "GPU batch figure: not measured (quadobs has no GPU path; the batch runs on the CPU)"
    )
    result["targets"] = _targets(result)
    result["notes"] = notes
    return result


def _machine_and_config(sc, steps, repeats, batch, batch_steps, threads) -> dict:
    """The bench's header: the machine (CPUs, load, versions) and the settings."""
    from quadobs.estimators.augmented import default_backend

    result: dict[str, Any] = {
        "machine": {
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "config": {
            "scenario": sc.name,
            "steps": steps,
            "repeats": repeats,
            "batch": batch,
            "batch_steps": batch_steps,
            "threads": threads,
        },
        "backend": default_backend(),
    }
    try:
        import mujoco

        result["machine"]["mujoco"] = mujoco.__version__
        import numba

        result["machine"]["numba"] = numba.__version__
    except ImportError:
        pass

    return result


def _single_vehicle(result: dict, sc, steps: int, repeats: int, say) -> None:
    """Bare physics against the loop, without and with recording, on the block and the per-step path."""
    loops = max(repeats, 9)  # enough for quartiles
    result["config"]["loop_repeats"] = loops
    say(
        f"single vehicle: {loops} x (bare physics, then the loop without and with recording on the block and the per-step path) of {steps} steps"
    )
    _loop_us(sc.with_overrides(duration=min(steps, 2000) * sc.dt), None)  # warm-up
    _loop_us(sc.with_overrides(duration=min(steps, 2000) * sc.dt), None, "step")
    runs: dict[str, list[float]] = {
        k: []
        for k in ("bare", "norec", "rec", "step_norec", "step_rec", "serial_norec", "serial_rec")
    }
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(loops):
            runs["bare"].append(_bare_physics_us(sc, steps))
            runs["norec"].append(_loop_us(sc, None))
            runs["rec"].append(_loop_us(sc, Path(tmp) / f"bench{r}.rrd"))
            runs["serial_norec"].append(_loop_us(sc, None, pipelined=False))
            runs["serial_rec"].append(_loop_us(sc, Path(tmp) / f"bench{r}1.rrd", pipelined=False))
            runs["step_norec"].append(_loop_us(sc, None, "step"))
            runs["step_rec"].append(_loop_us(sc, Path(tmp) / f"bench{r}s.rrd", "step"))
    bare, norec, rec = runs["bare"], runs["norec"], runs["rec"]
    result["bare_step_us"] = _median(bare)
    result["bare_steps_per_s"] = 1e6 / result["bare_step_us"]
    result["observer_loop_us"] = _median(norec)
    result["recorded_loop_us"] = _median(rec)
    result["step_recorded_loop_us"] = _median(runs["step_rec"])
    series = {}
    for prefix, a, b in (
        ("", "norec", "rec"),
        ("serial_", "serial_norec", "serial_rec"),
        ("step_", "step_norec", "step_rec"),
    ):
        series[f"{prefix}observer_loop_ratio"] = [x / y for x, y in zip(bare, runs[a])]
        series[f"{prefix}loop_ratio"] = [x / y for x, y in zip(bare, runs[b])]
        series[f"{prefix}recording_fraction"] = [1.0 - x / y for x, y in zip(runs[a], runs[b])]
    result["spread"] = {k: _quartiles(v) for k, v in series.items()}
    for k, v in result["spread"].items():
        result[k] = v["median"]
    # The same from the fastest run of each kind (the least disturbed by other load).
    result["best"] = {
        "bare_step_us": min(bare),
        "observer_loop_ratio": min(bare) / min(norec),
        "loop_ratio": min(bare) / min(rec),
        "recording_fraction": 1.0 - min(norec) / min(rec),
        "step_loop_ratio": min(bare) / min(runs["step_rec"]),
    }


def _estimator_costs(result: dict, sc, calls: int, repeats: int, say, notes: list[str]) -> None:
    """Per-step costs of the estimators, the LMI design and the online steps of le2013."""
    from quadobs.estimators.augmented import default_backend
    from quadobs.testbed.registry import available_estimators

    say("per-step costs of the estimators")
    result["observer_step_us"] = _observer_step_us(sc, calls, repeats, default_backend())
    result["observer_numpy_step_us"] = _observer_step_us(
        sc, max(calls // 20, 50), max(repeats // 2, 1), "numpy"
    )
    result["observer_block_step_us"] = _observer_block_step_us(sc, calls, repeats)
    result["observer_in_time"] = _observer_in_time_us(max(min(calls, 2000), 100), repeats)
    result["observer_in_time_step_us"] = result["observer_in_time"]["in_time_step_us"]
    for name, key in (("ekf", "ekf_step_us"), ("ukf", "ukf_step_us")):
        value, note = _estimator_step_us(sc, name, calls, repeats)
        result[key] = value
        if note:
            notes.append(note)
    result["zonotope_vehicle"] = _vehicle_zonotope_us(max(min(calls, 2000), 100), repeats)
    result["zonotope_vehicle_step_us"] = result["zonotope_vehicle"]["step_us"]
    say("le2013: offline LMI design and online steps of the zonotopic estimators")
    result["lmi_design_s"], result["lmi_design_split_s"], result["lmi_import_s"], designs = (
        _lmi_design_s()
    )
    result["le2013_step_us"] = _le2013_step_us(designs, min(calls, 1000), repeats)
    result["zonotope_step_us"] = result["le2013_step_us"]["pradius2"]["numba"]
    result["registered_estimators"] = available_estimators(sc)


def _targets(result: dict) -> dict:
    """Whether each target of the bench is met (``None`` where a figure is missing)."""
    return {
        "loop_ratio >= 1.0": _meets(result["loop_ratio"], 1.0, ">="),
        "batch_ratio >= 0.5": _meets(result["batch_ratio"], 0.5, ">="),
        "recording_fraction <= 0.1": _meets(result["recording_fraction"], 0.1, "<="),
        "recording_fraction iqr < 0.03": _meets(
            result["spread"]["recording_fraction"]["iqr"], 0.03, "<"
        ),
        "observer_step_us <= 3 (N = 9)": _meets(result["observer_step_us"], 3.0, "<="),
        "observer_step_us_N38 <= 40": _meets(result["observer_step_us_N38"], 40.0, "<="),
        "zonotope_step_us < 50": _meets(result["zonotope_step_us"], 50.0, "<"),
        "quadrotor_ratio >= 0.3": _meets(result["quadrotor"]["quadrotor_ratio"], 0.3, ">="),
        "first run after quadobs compile <= 5 s": _meets(
            (result.get("cold_start") or {}).get("first_run_s"), 5.0, "<="
        ),
        "log_read_speedup >= 5": _meets(
            (result.get("log_read") or {}).get("log_read_speedup"), 5.0, ">="
        ),
    }


def _meets(value, bound, op) -> bool | None:
    if value is None:
        return None
    return bool({">=": value >= bound, "<=": value <= bound, "<": value < bound}[op])


def _fmt(value, spec: str, unit: str = "") -> str:
    return "null" if value is None else f"{value:{spec}}{unit}"


def print_bench(r: dict, file=None) -> None:
    """The bench figures as a short report (on ``file``, default standard output)."""
    file = sys.stdout if file is None else file
    p = lambda *a: print(*a, file=file)  # noqa: E731
    m, c = r["machine"], r["config"]
    load = m.get("load_average")
    p(
        f"quadobs bench: {m['cpus']} CPUs, load average {', '.join(f'{x:.2f}' for x in load) if load else '?'}; "
        f"mujoco {m.get('mujoco', '?')}, numba {m.get('numba', 'missing')}; observer backend {r['backend']}; "
        f"medians of {c['repeats']} repeats"
    )
    p(f"single vehicle ({c['scenario']}, {c['steps']} steps per run)")
    p(
        f"  bare MuJoCo stepping            {r['bare_steps_per_s']:>10,.0f} steps/s  ({r['bare_step_us']:.2f} us/step)"
    )
    p(
        f"  physics + augmented observer    ratio {r['observer_loop_ratio']:.2f}        ({r['observer_loop_us']:.2f} us/step)"
    )
    p(
        f"  physics + observer + recording  ratio {r['loop_ratio']:.2f}        ({r['recorded_loop_us']:.2f} us/step); "
        f"recording {100 * r['recording_fraction']:.1f}% of the loop"
    )
    sp = r["spread"]
    p(
        f"  median [q1, q3] over {c.get('loop_repeats', c['repeats'])} repeats  block path (default)    block, one thread        per-step path"
    )
    for key, label in (
        ("observer_loop_ratio", "ratio without recording"),
        ("loop_ratio", "ratio with recording"),
        ("recording_fraction", "recording fraction"),
    ):
        cells = [sp[prefix + key] for prefix in ("", "serial_", "step_") if prefix + key in sp]
        p(
            f"  {label:31s} "
            + "    ".join(f"{a['median']:.3f} [{a['q1']:.3f}, {a['q3']:.3f}]" for a in cells)
        )
    b = r["best"]
    p(
        f"  fastest runs: bare {b['bare_step_us']:.2f} us/step, ratios {b['observer_loop_ratio']:.2f} and {b['loop_ratio']:.2f}, "
        f"recording {100 * b['recording_fraction']:.1f}%"
    )
    p("per-step cost (us)")
    p(
        f"  augmented observer (compiled)   {_fmt(r['observer_step_us'], '.2f')}   (NumPy reference {_fmt(r['observer_numpy_step_us'], '.1f')})"
    )
    p(
        f"  augmented observer, block path  {_fmt(r['observer_block_step_us'], '.2f')}   (one compiled call per block of rows)"
    )
    oit = r["observer_in_time"]
    p(
        f"  augmented observer, in time     {_fmt(r['observer_in_time_step_us'], '.2f')}   ({oit['scenario']}: ranges at their own times; "
        f"{_fmt(oit['grid_step_us'], '.2f')} on the grid; "
        f"{_fmt(oit.get('in_time_numpy_step_us'), '.2f')} in time through NumPy)"
    )
    p(f"  EKF                             {_fmt(r['ekf_step_us'], '.2f')}")
    p(f"  UKF                             {_fmt(r['ukf_step_us'], '.2f')}")
    zv = r["zonotope_vehicle"]
    p(
        f"  zonotopic, vehicle              {_fmt(r['zonotope_vehicle_step_us'], '.2f')}   ({zv['scenario']}, outputs every {zv['range_every']} steps; "
        f"{_fmt(zv['correct_every_step_us'], '.1f')} with outputs at every step)"
    )
    p(
        f"  zonotopic, le2013 (online)      {_fmt(r['zonotope_step_us'], '.2f')}   (P-radius, second approach)"
    )
    p(
        f"  LMI design le2013 (offline, s)  {_fmt(r['lmi_design_s'], '.3f')}   "
        f"({', '.join(f'{k} {v:.3f}' for k, v in r['lmi_design_split_s'].items())}; importing cvxpy before: {r['lmi_import_s']:.3f})"
    )
    p("le2013 online step per method (us): compiled / NumPy reference")
    for m, v in r["le2013_step_us"].items():
        p(f"  {m:16s} {v['numba']:>10.2f} / {v['numpy']:>10.2f}")
    _print_rest(r, p)


def _print_rest(r: dict, p) -> None:
    """The batch, campaign, quadrotor, cold-start and scaling figures, the targets and notes."""
    b = r["batch"]
    p(
        f"batch of {b['vehicles']} vehicles ({b['steps']} steps, threads {b['threads']} for the rollout and for the observers)"
    )
    p(
        f"  physics alone                   {b['physics_vehicle_steps_per_s']:>10,.0f} vehicle-steps/s ({b['physics_us_per_vehicle_step']:.2f} us)"
    )
    p(
        f"  physics + sensors + observers   {b['with_observer_vehicle_steps_per_s']:>10,.0f} vehicle-steps/s ({b['with_observer_us_per_vehicle_step']:.2f} us); "
        f"ratio {b['batch_ratio']:.2f}"
    )
    c = r["campaign"]
    p(
        f"campaign {c['scenario']} ({c['runs']} and {2 * c['runs']} episodes of {c['duration']:g} s on {c['workers']} processes)"
    )
    p(
        f"  testbed {c['marginal_episodes_per_s']:.2f} episodes/s once started, bare physics {c['bare_episodes_per_s']:.2f} "
        f"episodes/s; ratio {c['campaign_ratio']:.2f}"
    )
    p(
        f"  start-up of the campaign's workers {c['startup_s']:.2f} s; with it, {c['episodes_per_s']:.2f} episodes/s "
        f"(ratio {c['cold_campaign_ratio']:.2f})"
    )
    q = r["quadrotor"]
    p(
        f"quadrotor {q['scenario']} ({q['steps']} steps, {q['repeats']} repeats): bare mj_step {q['bare_step_us']:.2f} us/step, "
        f"loop with recording {q['loop_us']:.2f} us/step ({q['loop_steps_per_s']:,.0f} steps/s); ratio {q['quadrotor_ratio']:.2f} "
        f"[{q['spread']['q1']:.2f}, {q['spread']['q3']:.2f}]"
    )
    cs = r.get("cold_start")
    if cs is None:
        p("first run on a fresh kernel cache: not measured (--no-cold-start)")
    else:
        p(
            f"first run on a fresh kernel cache (one-step run, whole process): {cs['cold_run_s']:.1f} s compiling in the run; "
            f"'quadobs compile' {cs['compile_s']:.1f} s, then the first run {cs['first_run_s']:.1f} s"
        )
    p("observer step against the dimensions (us per step, fastest of a few repeats)")
    backend = r["backend"]
    p(f"  {'system':8s} {'n':>3s} {'q':>3s} {'N':>4s} {backend:>8s} {'numpy':>8s}")
    for row in r["scaling"]:
        p(
            f"  {row['system']:8s} {row['n']:>3d} {row['q']:>3d} {row['N']:>4d} {row.get(backend + '_us', float('nan')):>8.2f} {row['numpy_us']:>8.1f}"
        )
    if "log_read" in r:
        lr = r["log_read"]
        p(
            f"log reading ({lr['rows']:,} ranges): pyarrow {lr['arrow_s']:.3f} s, a float() per cell "
            f"{lr['per_cell_s']:.3f} s; {lr['log_read_speedup']:.1f}x"
        )
    p(
        "targets: "
        + ", ".join(
            f"{k}: {'met' if v else 'MISSED' if v is not None else 'n/a'}"
            for k, v in r["targets"].items()
        )
    )
    for note in r["notes"]:
        p(f"note: {note}")


def log_read_figure(rows: int = 300_000, repeats: int = 3) -> dict:
    """Seconds to read and check a ``ranges.csv`` of ``rows`` rows: the format's reader and a ``float()`` per cell.

    The file holds times at 100 Hz, ids of 8 beacons and ranges written as the format
    writes them (``repr``). Both readers are given the file's bytes and check every value
    against the schema; the medians over ``repeats`` are reported.
    """
    from quadobs.testbed.logs import files
    from quadobs.testbed.logs.schema import FILES, check_values

    rng = np.random.default_rng(0)
    t = np.arange(rows) * 0.01
    text = "time,beacon,range\n" + "".join(
        f"{float(a)!r},{int(b)},{float(c)!r}\n"
        for a, b, c in zip(t, np.arange(rows) % 8, rng.uniform(0.5, 30.0, rows))
    )
    spec = FILES["ranges.csv"]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ranges.csv"
        path.write_text(text)
        raw: bytes | None = path.read_bytes()
        header = ["time", "beacon", "range"]
        arrow, per_cell = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            raw = files.read_limited(path)
            assert raw is not None, "the file was just written"
            files.read_table(path, raw, spec, 2)
            arrow.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            raw = files.read_limited(path)
            assert raw is not None, "the file was just written"
            starts = files._line_starts(path, raw)
            values = files._python_values(path, raw, starts, header, tuple(header))
            check_values(str(path), spec, tuple(header), values)
            per_cell.append(time.perf_counter() - t0)
    a, b = _median(arrow), _median(per_cell)
    assert a is not None and b is not None, "repeats >= 1"
    return {"rows": rows, "arrow_s": a, "per_cell_s": b, "log_read_speedup": b / a}
