"""The quadrotor's flight figures: summary keys and recorded series of a :class:`~quadobs.testbed.worlds.quadrotor.QuadrotorWorld`.

Summary (``summary["flight"]``), over the flight ``[takeoff, landing start)``:

* ``tracking_rms``, ``tracking_max``: ``|r(t_k) - p_k|`` (m), reference minus true position;
* ``crashed`` (and ``crash_time``, ``crash_cause``): the tracking error passed
  ``control.crash_distance`` or the vehicle turned upside down (the rotors are then
  stopped); :func:`crash_line` says it in one line beside the printed table;
* ``time_on_estimate``: seconds flown on an estimate (``control.feedback``);
* per estimator, ``summary["estimators"][name]["flight_position_rmse"]``: the RMS position
  error over ``[max(takeoff, switch_time), landing start)`` (after convergence).

Recording: ``world/reference/path`` (reference trail), ``world/quadrotor`` (the body with
its attitude: a ``Transform3D`` per recorded 3-D frame), ``flight/rotors`` (commanded
thrusts, N), ``flight/thrust`` (the rotors' thrusts, N), ``flight/tracking_error`` (m),
``flight/on_estimate`` (0/1), ``flight/crashed`` (0/1) and, at the crash, a warning
``events`` message with its time and cause.

:func:`crash_counts` counts a campaign's crashes per estimator flown on.
"""

from __future__ import annotations

import math

import numpy as np

from quadobs.testbed.sinks import Rows, Sink

__all__ = ["FlightSink", "crash_counts", "crash_line", "crash_record"]


class FlightSink(Sink):
    """Flight summary and recording of a quadrotor world (see the module docstring).

    Parameters
    ----------
    world : QuadrotorWorld
    recording : RecordingSink or None
    """

    def __init__(self, world, recording=None) -> None:
        self.world, self.recording = world, recording
        self.track_sq = self.track_max = 0.0
        self.track_n = 0
        self.on_estimate = 0
        self.err_sq: dict[str, float] = {}
        self.err_n = 0

    def begin(self, ctx) -> None:
        super().begin(ctx)
        self.err_sq = {name: 0.0 for name in ctx.names}
        if self.recording is not None:
            self._declare(self.recording.recorder, ctx.frame)
            self.recording.extras.append(self.fill)

    def _declare(self, r, frame) -> None:
        import rerun as rr

        self.every = every = frame.trail_every
        self.ref_path = r.series(
            "world/reference/path", 3, "points3d", every=every, color=(120, 120, 120), radius=0.02
        )
        self.rotors = r.series("flight/rotors", 4, names=[f"rotor {i} (N)" for i in range(4)])
        self.tracking = r.series(
            "flight/tracking_error", 1, names=["|r - p| (m)"], color=(200, 40, 40)
        )
        self.estimate = r.series("flight/on_estimate", 1, names=["on the estimate"])
        self.thrust = r.series(
            "flight/thrust", 4, names=[f"rotor {i} thrust (N)" for i in range(4)]
        )
        self.crashed = r.series("flight/crashed", 1, names=["crashed"], color=(200, 0, 0))
        self.marked = False
        arm = 0.046 * 2
        r.static(
            "world/quadrotor",
            rr.Boxes3D(
                half_sizes=[[arm, 0.008, 0.005], [0.008, arm, 0.005]],
                rotation_axis_angles=[rr.RotationAxisAngle([0, 0, 1], degrees=45)] * 2,
                colors=[(220, 60, 60), (60, 60, 60)],
            ),
        )

    def fill(self, rows: slice, steps: np.ndarray) -> None:
        """The flight series of the recorder rows ``rows`` (physics ``steps`` of the current block)."""
        w = self.world
        raw = w.out[steps - w.k0]
        sp = w.spans
        self.ref_path.buf[rows] = raw[:, sp["reference"]]
        self.rotors.buf[rows] = raw[:, sp["rotors"]]
        self.tracking.buf[rows, 0] = raw[:, sp["tracking"]][:, 0]
        self.estimate.buf[rows, 0] = raw[:, sp["on_estimate"]][:, 0]
        self.thrust.buf[rows] = raw[:, sp["thrust"]]
        self.crashed.buf[rows, 0] = raw[:, sp["crashed"]][:, 0]

    def block(self, rows: Rows) -> None:
        w = self.world
        raw = rows.block.raw[: rows.count]
        sp = w.spans
        t = rows.t
        flight = (
            (t >= w.plan.takeoff)
            & (t < w.plan.land_start)
            & np.isfinite(raw[:, sp["tracking"]][:, 0])
        )
        err = raw[flight, sp["tracking"]][:, 0]
        self.track_sq += float(err @ err)
        self.track_n += int(err.size)
        self.track_max = max(self.track_max, float(err.max(initial=0.0)))
        self.on_estimate += int(np.nansum(raw[:, sp["on_estimate"]][:, 0]))
        after = flight & (t >= w.control.switch_time)
        for name, est in rows.estimates.items():
            e = est[after, :3] - rows.truth[after, :3]
            self.err_sq[name] += float(np.einsum("ij,ij->", e, e))
        self.err_n += int(after.sum())
        if self.recording is not None:
            self._attitude(rows, raw)
            self._mark_crash()

    def _mark_crash(self) -> None:
        """A warning in the recording's ``events`` at the crash, once."""
        w = self.world
        if w.crashed_at is None or self.marked:
            return
        self.marked = True
        dt = self.ctx.frame.dt
        self.recording.recorder.text(
            "events",
            f"crashed at {w.crashed_at * dt:.3f} s: {w.crash_cause}",
            level="WARN",
            step=w.crashed_at,
            time=w.crashed_at * dt,
        )

    def _attitude(self, rows: Rows, raw: np.ndarray) -> None:
        import rerun as rr

        sel = np.flatnonzero(
            (rows.ks % self.every == 0) & np.isfinite(raw[:, self.world.spans["attitude"]][:, 0])
        )
        if not sel.size:
            return
        q = raw[sel][:, self.world.spans["attitude"]]
        rr.send_columns(
            "world/quadrotor",
            indexes=[
                rr.TimeColumn("step", sequence=rows.ks[sel]),
                rr.TimeColumn("sim_time", duration=rows.t[sel]),
            ],
            columns=rr.Transform3D.columns(
                translation=rows.truth[sel, :3], quaternion=q[:, [1, 2, 3, 0]]
            ),
            recording=self.recording.recorder.rec,
        )

    def end(self, completed: int, interrupted: bool) -> dict:
        w, dt = self.world, self.ctx.frame.dt
        crashed = w.crashed_at is not None
        flight = {
            "feedback": w.control.feedback,
            "switch_time": w.control.switch_time if w.controller else None,
            "tracking_rms": math.sqrt(self.track_sq / self.track_n) if self.track_n else None,
            "tracking_max": self.track_max if self.track_n else None,
            "crashed": crashed,
            "crash_time": w.crashed_at * dt if crashed else None,
            "crash_cause": w.crash_cause,
            "time_on_estimate": self.on_estimate * dt,
        }
        per = {
            name: {"flight_position_rmse": math.sqrt(sq / self.err_n) if self.err_n else None}
            for name, sq in self.err_sq.items()
        }
        return {"flight": flight, "estimators": per}


def crash_line(summary: dict) -> str | None:
    """``"CRASHED at 6.40 s (flying on augmented): tracking error ..."``, or None for a flight without a crash (or no flight)."""
    f = summary.get("flight")
    if not f or not f.get("crashed"):
        return None
    on = f["feedback"] if f.get("time_on_estimate") else "truth"
    return f"CRASHED at {f['crash_time']:.2f} s (flying on {on}): {f.get('crash_cause') or 'unknown cause'}"


def crash_counts(flights: list[dict]) -> dict:
    """Crashes per estimator flown on, over a campaign's flights (``summary["flight"]`` of each run).

    ``flights`` hold at least :func:`crash_record`'s keys. Returns
    ``{name: {"runs": n, "crashed": k, "crash_times": [...]}}``, ``name`` the estimator
    flown on (``"truth"`` for flights on the truth only).
    """
    out: dict[str, dict] = {}
    for f in flights:
        c = out.setdefault(f["flown_on"], {"runs": 0, "crashed": 0, "crash_times": []})
        c["runs"] += 1
        if f.get("crashed"):
            c["crashed"] += 1
            c["crash_times"].append(float(f["crash_time"]))
    return out


def crash_record(flight: dict) -> dict:
    """What :func:`crash_counts` needs of one run's ``summary["flight"]``: the estimator flown on and the crash time (NaN: none)."""
    flown = flight["feedback"] if flight.get("time_on_estimate") else "truth"
    t = flight.get("crash_time")
    return {"flown_on": flown, "crash_time": float("nan") if t is None else float(t)}
