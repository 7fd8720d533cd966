"""Scheduling of a campaign's runs: in the calling process, on local worker processes, or on a Dask cluster.

The local workers are a small pool written here rather than
:class:`concurrent.futures.ProcessPoolExecutor`, for what the fault tests ask of it: a worker
killed while holding a run (``SIGKILL``, the out-of-memory killer) breaks the whole
executor (``BrokenProcessPool`` for every run still queued), whereas here only that worker
is replaced and its run started again (``retries`` times, then reported failed with its
seed); and the workers end with the campaign's process even when it is killed
(``PR_SET_PDEATHSIG`` and a watch thread), which an executor does not arrange. Each worker
has its own pipe and the loop waits on every pipe and process sentinel at once
(:func:`multiprocessing.connection.wait`), so no dead worker can block it. pebble's
``ProcessPool`` restarts a dead worker too, but reports the run lost rather than retrying it
and adds a dependency for one loop.

Every finished result goes to ``done`` in the calling process as soon as it arrives, in the
order the runs finish; the caller keeps them (:mod:`quadobs.studies.campaign.storage`, for
``resume``) and sorts them by run index, so the order never changes a result.
"""

from __future__ import annotations

import logging
import os
import time as _time
import traceback
from collections.abc import Callable

from quadobs.errors import QuadobsError

__all__ = ["execute"]

log = logging.getLogger("quadobs.studies")

#: Seconds a worker gets to end after SIGTERM before it is killed (campaign stopped).
_TERMINATE_GRACE = 2.0


def lost_result(task: dict, exc: BaseException) -> dict:
    """The result of a run that returned nothing (its worker lost, a cluster's error): failed, with its seed."""
    return {
        "index": task["index"],
        "seed": task["seed"],
        "status": "failed",
        "error": f"{type(exc).__name__}: {exc}",
        "traceback": "".join(traceback.format_exception(exc)),
        "wall_time": float("nan"),
    }


def execute(
    tasks: list[dict],
    run: Callable[[dict], dict],
    done: Callable[[dict], None],
    *,
    scheduler: str | None,
    workers: int | None,
    start_method: str | None = None,
    retries: int = 2,
) -> tuple[bool, dict]:
    """Run ``run(task)`` for each task, handing each result to ``done``; returns whether Ctrl-C stopped it, and the backend.

    ``workers=0``: one after the other in this process; ``scheduler``: on the Dask cluster at
    that address; else on ``workers`` local processes (default: the number of CPUs).
    """
    if scheduler is not None:
        backend: dict = {"kind": "dask", "scheduler": scheduler}
        return _on_dask(tasks, run, done, scheduler, backend), backend
    if workers == 0:
        backend = {"kind": "in-process", "workers": 0}
        return _in_process(tasks, run, done), backend
    backend = {"kind": "processes", "workers": int(workers or os.cpu_count() or 1)}
    import multiprocessing

    context = (
        multiprocessing.get_context(start_method) if start_method else multiprocessing.get_context()
    )
    n = min(backend["workers"], len(tasks))
    interrupted = _run_local(tasks, n, context, run, done, lost_result, retries) if tasks else False
    backend["retries"] = retries
    return interrupted, backend


def _in_process(tasks: list[dict], run, done) -> bool:
    try:
        for task in tasks:
            done(run(task))
    except KeyboardInterrupt:
        return True
    return False


def _on_dask(tasks: list[dict], run, done, scheduler: str, backend: dict) -> bool:
    """The runs as futures of a Dask distributed client; returns whether Ctrl-C stopped it."""
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError:  # pragma: no cover - depends on the environment
        raise QuadobsError(
            "scheduler: running on a Dask cluster needs dask.distributed (pip install 'quadobs[cluster]')"
        ) from None
    try:
        client = Client(scheduler, timeout=30)
    except OSError as exc:
        raise QuadobsError(f"scheduler: cannot connect to {scheduler!r} ({exc})") from None
    interrupted = False
    try:
        backend["workers"] = len(client.scheduler_info().get("workers", {}))
        token = f"{os.getpid()}-{_time.time_ns()}"
        futures = {
            client.submit(run, t, pure=False, key=f"quadobs-run-{t['index']}-{token}"): t
            for t in tasks
        }
        try:
            for fut in dask_completed(list(futures)):
                if fut.status == "finished":
                    done(fut.result())
                else:
                    try:
                        why: BaseException = fut.exception()
                    except BaseException as e:  # cancelled, lost
                        why = e
                    done(lost_result(futures[fut], why))
        except KeyboardInterrupt:
            interrupted = True
            client.cancel(list(futures))
    finally:
        client.close()
    return interrupted


# --------------------------------------------------------------------------------------
# Local worker processes
# --------------------------------------------------------------------------------------


def _die_with_parent(parent: int) -> None:
    """In a worker: end when the campaign's process ends, even by ``SIGKILL``.

    On Linux the kernel sends ``SIGKILL`` when the parent dies (``prctl(PR_SET_PDEATHSIG)``);
    everywhere, a daemon thread checks once a second that the parent is still the same.
    """
    import threading

    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, 9)  # PR_SET_PDEATHSIG, SIGKILL
    except (OSError, AttributeError):  # not Linux
        pass
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)

    def watch() -> None:
        while True:
            _time.sleep(1.0)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="quadobs-parent-watch", daemon=True).start()


def _worker_main(conn, parent: int, run: Callable[[dict], dict]) -> None:
    """A local worker: ``run`` the tasks received on ``conn`` and send back each result, until EOF."""
    import signal

    signal.signal(
        signal.SIGINT, signal.SIG_IGN
    )  # Ctrl-C is the campaign's to handle: it stops the workers
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with_parent(parent)
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        conn.send(run(task))


class _Worker:
    """One local worker process and the task it holds (``None``: idle)."""

    def __init__(self, context, run: Callable[[dict], dict]) -> None:
        self.conn, child = context.Pipe(duplex=True)
        self.proc = context.Process(
            target=_worker_main,
            args=(child, os.getpid(), run),
            daemon=True,
            name="quadobs-campaign-worker",
        )
        self.proc.start()
        child.close()
        self.task: dict | None = None

    def give(self, task: dict) -> None:
        self.task = task
        self.conn.send(task)

    def stop(self) -> None:
        """End the process: SIGTERM, then SIGKILL after :data:`_TERMINATE_GRACE` seconds."""
        self.conn.close()
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(_TERMINATE_GRACE)
            if self.proc.is_alive():
                self.proc.kill()
        self.proc.join(_TERMINATE_GRACE)


def _run_local(tasks: list[dict], n: int, context, run, done, lost, retries: int) -> bool:
    """Run ``tasks`` on ``n`` local worker processes; returns whether Ctrl-C stopped it.

    Each worker has its own pipe, and the loop waits on every pipe and every process
    sentinel at once (``multiprocessing.connection.wait``), so no dead worker can block
    it: a worker that dies holding a run (``SIGKILL``, out of memory) is replaced and the
    run started again, at most ``retries`` times, then reported failed with its seed
    (``lost`` counts the losses). Ctrl-C (or SIGTERM mapped to it) ends every worker and
    keeps the finished runs; the workers end with the campaign's process in any case.
    """
    from collections import deque
    from multiprocessing.connection import wait

    queue = deque(tasks)
    losses: dict[int, int] = {}
    pool: list[_Worker] = []
    try:
        pool = [_Worker(context, run) for _ in range(n)]
        while queue or any(w.task is not None for w in pool):
            for i, w in enumerate(pool):
                if w.task is None and queue:
                    if not w.proc.is_alive():  # died while idle: a fresh one takes its place
                        w.stop()
                        pool[i] = w = _Worker(context, run)
                    try:
                        w.give(queue.popleft())
                    except (
                        OSError
                    ):  # died just now: the sentinel below reports it, the run is retried
                        pass
            busy = [w for w in pool if w.task is not None]
            ready = set(wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout=1.0))
            for i, w in enumerate(pool):
                if w.task is None or not (w.conn in ready or w.proc.sentinel in ready):
                    continue
                result = _receive(w)
                if result is not None:
                    w.task = None
                    result["lost"] = losses.get(result["index"], 0)
                    done(result)
                    continue
                task, w.task = w.task, None
                losses[task["index"]] = count = losses.get(task["index"], 0) + 1
                log.warning(
                    "campaign: run %d lost its worker process (%d of %d restarts)",
                    task["index"],
                    min(count, retries),
                    retries,
                )
                w.stop()
                pool[i] = _Worker(context, run)
                if count <= retries:
                    queue.appendleft(task)
                else:
                    code = w.proc.exitcode
                    why = (
                        f"killed by signal {-code}"
                        if code is not None and code < 0
                        else f"exit status {code}"
                    )
                    done(
                        {
                            **lost(
                                task, RuntimeError(f"worker process lost ({why}), {count} times")
                            ),
                            "lost": count,
                        }
                    )
        return False
    except KeyboardInterrupt:
        return True
    finally:
        _stop_all(pool)


def _stop_all(pool: list[_Worker]) -> None:
    """End every worker: SIGTERM to all, then SIGKILL to those still there after the grace period."""
    for w in pool:
        w.conn.close()
        if w.proc.is_alive():
            w.proc.terminate()
    deadline = _time.monotonic() + _TERMINATE_GRACE
    for w in pool:
        w.proc.join(max(deadline - _time.monotonic(), 0.0))
        if w.proc.is_alive():
            w.proc.kill()
            w.proc.join(_TERMINATE_GRACE)


def _receive(w: _Worker) -> dict | None:
    """The result a worker sent, or ``None`` when it died without one."""
    try:
        if w.conn.poll():
            return w.conn.recv()
    except (EOFError, OSError):
        pass
    return None
