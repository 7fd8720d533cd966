"""Buffered, columnar writing of per-step values to a rerun recording (``.rrd``).

Logging row by row costs about 100 µs a row; sending columns costs well under a
microsecond a row. A :class:`Recorder` keeps one preallocated buffer per series, the
caller writes each step's values into the current row, and every ``capacity`` rows the
buffers go out with ``send_columns`` on two timelines, ``step`` (sequence) and
``sim_time`` (duration), and the file is flushed. :meth:`Recorder.close` sends what is
left and writes the file's footer, so a run stopped by an exception or Ctrl-C still
leaves a complete file holding every step up to the stop.

Staging and bounded writes. The file is written to a staging file beside the target
(``.<name>.<pid>-<random>.partial``, :func:`quadobs.errors.staging_path`) and renamed onto
it by :meth:`Recorder.close`: the previous recording stays whole until the new one is
complete. rerun writes its stream into a pipe, never to the disk; a thread of ours copies
the pipe into the staging file (:class:`_PipeFile`). A failed write (a full disk, a file
size limit) is noticed at the next send, within one block of rows, and raised as a
one-line :class:`~quadobs.errors.RunFault` naming the path; the thread keeps draining the
pipe, so rerun never blocks on a disk that refuses data and :meth:`Recorder.close` ends.
"""

from __future__ import annotations

import fcntl
import functools
import os
import tempfile
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from quadobs.errors import (
    QuadobsError,
    RunFault,
    check_writable,
    deferred_interrupts,
    output_target,
    staging_path,
)
from quadobs.staging import publish

__all__ = ["Recorder", "Series", "check_writable"]

_KINDS = ("scalars", "points3d", "translation", "boxes3d")


#: Longest wait (s) for rerun to hand over the last bytes at :meth:`Recorder.close`.
CLOSE_TIMEOUT = 30.0

#: Bytes written between two ``fdatasync`` calls of the copying thread, so that the data
#: reaches the disk while the run goes on and the final ``fsync`` has little left to do.
SYNC_BYTES = 1 << 20

#: Size asked for the pipe between rerun and the copying thread (Linux; 1 MiB is the usual limit).
PIPE_BYTES = 1 << 20


class _PipeFile:
    """rerun's file sink pointed at a FIFO whose other end a daemon thread copies into ``path``.

    Writes go through ``os.write``, so a full disk or an exceeded file size limit is an
    ``OSError`` kept in :attr:`error`; from then on the thread reads and drops the rest of
    the stream (rerun's writer never blocks) and writes nothing more.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.error: OSError | None = None
        self.written = 0
        self._folder = tempfile.mkdtemp(prefix="quadobs-rrd-")
        self.fifo = os.path.join(self._folder, "stream.rrd")
        try:  # no FIFO left behind when the file cannot be opened (ulimit -n, a full disk)
            os.mkfifo(self.fifo, 0o600)
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except BaseException:
            self._unlink_fifo()
            raise
        self._thread = threading.Thread(target=self._drain, name="quadobs-recording", daemon=True)
        try:  # no thread (ulimit -v, ulimit -u): neither the file nor the FIFO is left behind
            self._thread.start()
        except BaseException:
            os.close(self._fd)
            _remove(Path(path))
            self._unlink_fifo()
            raise

    def _drain(self) -> None:
        try:
            src = os.open(self.fifo, os.O_RDONLY)  # returns once rerun has opened the other end
        except OSError as exc:  # no descriptor left (ulimit -n): the recorder reports it
            self.error = exc
            return
        finally:
            self._unlink_fifo()
        try:
            try:  # a larger pipe: rerun's writer seldom waits for this thread (which needs the GIL)
                fcntl.fcntl(src, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
            except (
                OSError,
                AttributeError,
            ):  # not Linux, or above the system's limit: the default size
                pass
            synced = 0
            while chunk := os.read(src, 1 << 20):
                if self.error is None:
                    self._write(chunk)
                    if (
                        self.written - synced >= SYNC_BYTES
                    ):  # on the disk as it comes: a short final fsync
                        synced = self.written
                        self._sync()
        finally:
            os.close(src)

    def _write(self, chunk: bytes) -> None:
        view = memoryview(chunk)
        try:
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
                self.written += n
        except OSError as exc:
            self.error = exc

    def _sync(self) -> None:
        try:
            os.fdatasync(self._fd)
        except OSError as exc:
            self.error = exc

    def _unlink_fifo(self) -> None:
        for remove, what in ((os.unlink, self.fifo), (os.rmdir, self._folder)):
            try:
                remove(what)
            except OSError:
                pass

    def release(self) -> None:
        """Unblock a thread still waiting for rerun to open the pipe (rerun never did)."""
        if self._thread.is_alive() and os.path.exists(self.fifo):
            try:
                os.close(os.open(self.fifo, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:
                pass

    def finish(self, timeout: float) -> bool:
        """Wait for the end of the stream (rerun disconnected), then close the file; False on a timeout."""
        self._thread.join(timeout)
        done = not self._thread.is_alive()
        if done and self.error is None:
            try:
                os.fsync(self._fd)
            except OSError as exc:
                self.error = exc
        os.close(self._fd)
        return done


class _ArrowBatch:
    """A component batch already in Arrow form (what :class:`rerun.ComponentColumn` reads of one)."""

    __slots__ = ("array",)

    def __init__(self, array) -> None:
        self.array = array

    def as_arrow_array(self):
        return self.array


@functools.cache
def _component(kind: str):
    """The rerun descriptor and Arrow value type of a series kind's component (from rerun's own archetype)."""
    v = np.zeros((1, 3))
    made = {
        "scalars": lambda: rr.Scalars.columns(scalars=v[:, :1]),
        "points3d": lambda: rr.Points3D.columns(positions=v),
        "translation": lambda: rr.Transform3D.columns(translation=v),
    }[kind]()
    (column,) = list(made)
    return column.component_descriptor(), column.as_arrow_array().type.value_type


def _columns(kind: str, vals: np.ndarray) -> list:
    """The component columns of ``vals`` ``(rows, width)``: the same Arrow data as the archetype's
    ``columns()`` gives, built directly (a tenth of the cost, which matters at every send)."""
    if kind == "boxes3d":
        return list(rr.Boxes3D.columns(centers=vals[:, :3], half_sizes=vals[:, 3:]))
    descriptor, value_type = _component(kind)
    rows, width = vals.shape
    if kind == "scalars":  # each row a list of ``width`` scalars
        values = pa.array(np.ascontiguousarray(vals, dtype=np.float64).ravel(), value_type)
        offsets = np.arange(0, rows * width + 1, width, dtype=np.int32)
    else:  # each row one 3-vector (single precision, as rerun stores positions and translations)
        flat = pa.array(np.ascontiguousarray(vals, dtype=np.float32).ravel(), value_type.value_type)
        values = pa.FixedSizeListArray.from_arrays(flat, type=value_type)
        offsets = np.arange(rows + 1, dtype=np.int32)
    return [rr.ComponentColumn(descriptor, _ArrowBatch(values), offsets=offsets)]


def _end_orphaned_streams() -> None:
    """End the threads of rerun recording streams no longer referenced (a closed recorder's).

    rerun frees an orphaned stream's batcher and sink threads only in this sweep (which
    ``rerun.init`` also runs); without it each recording left two to four idle threads
    behind for the life of the process, hundreds in a long campaign.
    """
    try:
        import rerun_bindings

        rerun_bindings.flush_and_cleanup_orphaned_recordings()
    except Exception:
        pass


def _remove(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass


def _abandon(file: _PipeFile, staging: Path) -> None:
    """Remove a staging file never published; free its copying thread if rerun never opened the pipe
    (a stop between the two), so that neither the thread nor the FIFO outlives the recorder."""
    file.release()
    _remove(staging)


@dataclass(eq=False)
class Series:
    """One entity's buffered per-step values.

    ``kind`` is ``"scalars"`` (one line per column), ``"points3d"`` (one point per row)
    or ``"translation"`` (the entity's ``Transform3D`` translation; a static box drawn at
    the entity then moves with it, latest-at, while point trails show history) or ``"boxes3d"`` (width 6:
    centre then half-sizes of an axis-aligned box). ``every`` sends one row in ``every``
    (aligned on the step index); ``skip_nan`` drops rows holding NaN (a sensor that did
    not sample that step).
    """

    entity: str
    width: int
    kind: str
    every: int
    skip_nan: bool
    buf: np.ndarray = field(repr=False)


class Recorder:
    """Column-buffered writer of one episode to an ``.rrd`` file.

    Parameters
    ----------
    path : str or Path
        Output file (``.rrd``): written to a staging file beside it and renamed onto it by
        :meth:`close` (a symbolic link is written through). After :meth:`fail` the
        staging file is kept instead (a valid recording of the steps before the failure,
        removed by the next run writing ``path``); after a write error it is removed.
    recording_id : str
        Fixed id of the recording (derived from scenario and seed by the runner), so the
        same run gives the same id.
    blueprint : rerun blueprint, optional
        Default layout stored in the file.
    capacity : int
        Rows buffered between sends.
    application_id : str
    """

    def __init__(
        self,
        path: str | Path,
        *,
        recording_id: str,
        blueprint=None,
        capacity: int = 4096,
        application_id: str = "quadobs",
    ) -> None:
        self.path = check_writable(path)
        self.target = output_target(self.path)
        self.staging = staging_path(self.target)
        self.capacity = int(capacity)
        self.failed = False
        self.error: RunFault | None = None
        try:
            # A staging file never published (a stop before the end, an exit) goes when the
            # recorder does, at the latest when the process exits normally. A stop waits until
            # that clean-up is in place: a Ctrl-C while the copying thread started (which takes
            # milliseconds on a loaded machine) left the staging file behind.
            with deferred_interrupts():
                self._file = _PipeFile(self.staging)
                self._discard = weakref.finalize(self, _abandon, self._file, self.staging)
        except OSError as exc:
            raise QuadobsError(
                f"output path {str(self.path)!r}: cannot be written ({exc.strerror})"
            ) from None
        self.published = False
        self._check_headroom()
        try:
            # a stop waits until rerun has its file and the blueprint (a Ctrl-C in between made
            # rerun drop what it had buffered, with a warning of its own on stderr)
            with deferred_interrupts():
                self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
                self.rec.save(self._file.fifo, default_blueprint=blueprint)
        except Exception as exc:  # rerun could not open its end (ulimit -n): nothing left behind
            self._file.release()
            self._file.finish(1.0)
            self._file._unlink_fifo()
            _remove(self.staging)
            self._discard.detach()
            reason = str(exc).split(" (os error")[0].split(", path:")[0].splitlines()[0]
            raise RunFault(f"recording {str(self.path)!r}: cannot be opened ({reason})") from None
        self.series_list: list[Series] = []
        self._steps = np.zeros(self.capacity, dtype=np.int64)
        self._times = np.zeros(self.capacity)
        self.n = 0
        self.rows_sent = 0
        self.closed = False

    #: File descriptors rerun needs free to open its file (its writer, its threads' wakers).
    HEADROOM = 4

    def _check_headroom(self) -> None:
        """A one-line fault, before rerun starts, when fewer than :attr:`HEADROOM` descriptors are
        free (``ulimit -n``): rerun would fail opening its file with a warning of its own."""
        opened, error = [], None
        try:
            for _ in range(self.HEADROOM):
                opened.append(os.open(os.devnull, os.O_RDONLY))
        except OSError as exc:
            error = exc
        finally:
            for fd in opened:
                os.close(fd)
        if error is not None:
            self._file.release()
            self._file.finish(1.0)
            self._file._unlink_fifo()
            _remove(self.staging)
            self._discard.detach()
            raise RunFault(
                f"recording {str(self.path)!r}: cannot be opened ({error.strerror}; see ulimit -n)"
            )

    # -- declaration ---------------------------------------------------------------

    def series(
        self,
        entity: str,
        width: int,
        kind: str = "scalars",
        *,
        every: int = 1,
        skip_nan: bool = False,
        names: list[str] | None = None,
        color: tuple[int, int, int] | None = None,
        radius: float | None = None,
        half_size: tuple[float, float, float] | None = None,
    ) -> Series:
        """Declare a buffered series; its static styling (names, colour, size) is logged once."""
        if kind not in _KINDS:
            raise QuadobsError(f"kind: expected one of {_KINDS}, got {kind!r}")
        s = Series(
            entity, width, kind, max(int(every), 1), skip_nan, np.zeros((self.capacity, width))
        )
        self.series_list.append(s)
        if kind == "scalars" and (names or color):
            kw: dict[str, Any] = {}
            if names:
                kw["names"] = names
            if color:
                kw["colors"] = [color] * width
            self.rec.log(entity, rr.SeriesLines(**kw), static=True)
        elif kind == "boxes3d" and color:
            self.rec.log(entity, rr.Boxes3D.from_fields(colors=[color]), static=True)
        elif kind == "points3d" and (color or radius):
            self.rec.log(entity, rr.Points3D.from_fields(colors=color, radii=radius), static=True)
        elif kind == "translation":
            self.rec.log(
                entity,
                rr.Boxes3D(
                    half_sizes=[half_size or (0.5, 0.5, 0.5)], colors=[color] if color else None
                ),
                static=True,
            )
        return s

    def static(self, entity: str, archetype) -> None:
        """Log a static (timeless) archetype, e.g. beacon positions or a description."""
        self.rec.log(entity, archetype, static=True)

    def text(
        self, entity: str, message: str, *, level: str = "INFO", step: int, time: float
    ) -> None:
        """Log one text message at a given step (rare events: warnings, interruptions); nothing once closed."""
        if self.rec is None:
            return
        self.rec.set_time("step", sequence=int(step))
        self.rec.set_time("sim_time", duration=float(time))
        self.rec.log(entity, rr.TextLog(message, level=level))
        self.rec.reset_time()

    # -- per-step ------------------------------------------------------------------

    def row(self, step: int, time: float) -> int:
        """Start a new row for ``step`` at ``time`` (s); returns its index into every ``Series.buf``."""
        if self.n == self.capacity:
            self.flush()
        i = self.n
        self._steps[i] = step
        self._times[i] = time
        self.n = i + 1
        return i

    def rows(self, steps: np.ndarray, times: np.ndarray) -> slice:
        """Start as many of the rows ``steps``/``times`` as fit before the next send.

        Returns the slice of every ``Series.buf`` they occupy; its length (at least one row)
        says how many were taken, the caller passes the rest again.
        """
        if self.n == self.capacity:
            self.flush()
        i = self.n
        c = min(self.capacity - i, len(steps))
        self._steps[i : i + c] = steps[:c]
        self._times[i : i + c] = times[:c]
        self.n = i + c
        return slice(i, i + c)

    def flush(self, *, wait: bool = False) -> None:
        """Send the buffered rows as columns and flush the file.

        The file is written by rerun's own thread: ``wait=False`` (the periodic sends)
        starts the write without waiting for it, so the simulation goes on meanwhile;
        :meth:`close` waits.
        """
        n = self.n
        if self.rec is None:  # closed
            return
        if n:
            with (
                deferred_interrupts()
            ):  # every series gets the rows, or none (a stop waits for the end)
                self._send(n)
        self.rec.flush(timeout_sec=CLOSE_TIMEOUT if wait else 0.0)
        self._check()

    def _check(self) -> None:
        """Raise the write error of the file once (a :class:`~quadobs.errors.RunFault` naming the path)."""
        exc = self._file.error
        if exc is not None and self.error is None:
            self.error = RunFault(
                f"recording {str(self.path)!r}: cannot be written ({exc.strerror or exc}) after "
                f"{self._file.written} bytes; the run stopped"
            )
            raise self.error

    def fail(self) -> None:
        """Mark the run as failed: :meth:`close` keeps the staging file and leaves the target untouched."""
        self.failed = True

    def _send(self, n: int) -> None:
        """Send rows ``[0, n)`` of the buffers as columns, one call per series."""
        # Copies: rerun may encode the columns on its own thread after this returns,
        # while the buffers are refilled.
        steps, times = self._steps[:n].copy(), self._times[:n].copy()
        every_row = [
            rr.TimeColumn("step", sequence=steps),
            rr.TimeColumn("sim_time", duration=times),
        ]
        for s in self.series_list:
            if s.every > 1:
                sel = np.flatnonzero(steps % s.every == 0)
                vals, st, tm = s.buf[:n][sel], steps[sel], times[sel]
            else:
                vals, st, tm = s.buf[:n].copy(), steps, times
            idx = every_row
            if s.skip_nan:
                keep = ~np.isnan(vals).any(axis=1)
                vals, st, tm = vals[keep], st[keep], tm[keep]
            if not len(st):
                continue
            if st is not steps:
                idx = [rr.TimeColumn("step", sequence=st), rr.TimeColumn("sim_time", duration=tm)]
            self.rec.send_columns(s.entity, indexes=idx, columns=_columns(s.kind, vals))
        self.rows_sent += n
        self.n = 0

    def close(self, *, publish: bool = True) -> None:
        """Send what is buffered, finish the file (footer included) and rename it onto the target; idempotent.

        With ``publish=False`` the complete file stays at its staging name until
        :meth:`publish` (the episode renames it after the summary is written, so the two
        are replaced together).

        Bounded: rerun gets :data:`CLOSE_TIMEOUT` seconds to hand over its last bytes. The
        target is replaced only by a complete file: after :meth:`fail` the staging file is
        kept (and named in the event log's error line), after a write error it is removed,
        and the write error is raised (once).
        """
        if self.closed:
            return
        self.closed = True
        pending = None
        try:
            self.flush(wait=True)
        except RunFault as exc:  # first seen now: raised below, once the file is dealt with
            pending = exc
        finally:
            self.rec.disconnect()
            self.rec = None  # type: ignore[assignment]  # closed: no method reads it after
            # the stream is now orphaned: rerun's threads for it end below
            _end_orphaned_streams()
            self._file.release()
            self._settle(self._file.finish(CLOSE_TIMEOUT), publish)
        if pending is not None:
            raise pending
        self._check()

    def _settle(self, done: bool, publish: bool) -> None:
        """After the stream ended: remove the staging file after a write error, keep it after
        :meth:`fail`, else publish it now or leave it for :meth:`publish`."""
        if self._file.error is not None or not done:
            if not done and self._file.error is None:
                self._file.error = OSError(
                    f"rerun did not finish the stream within {CLOSE_TIMEOUT:g} s"
                )
            self._discard()
        elif self.failed:
            self._discard.detach()  # kept: a valid recording of the steps before the failure
        elif publish:
            self.publish()

    def publish(self) -> None:
        """Rename the closed, complete staging file onto the target (once; nothing after a failure)."""
        if not self.closed or self.published or self.failed or self._file.error is not None:
            return
        try:
            publish(self.staging, self.target)
        except OSError as exc:
            self._discard()
            raise RunFault(
                f"recording {str(self.path)!r}: cannot be renamed into place ({exc.strerror})"
            ) from None
        self._discard.detach()
        self.published = True

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
