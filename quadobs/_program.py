"""How the ``quadobs`` program takes SIGINT and SIGTERM, from its start-up to its exit.

:func:`quadobs.cli.main` calls :func:`take_signals` before anything heavy is imported (this
module loads the standard library alone). While a command runs, a signal raises
``KeyboardInterrupt`` (SIGTERM as SIGINT): the command stops, keeps what it has done, and the
program exits with status 130 and the line ``quadobs: interrupted``. Three ways Python has of
losing that interrupt are covered: one raised where it cannot propagate (a ``__del__``, a
weakref callback; :func:`keep_lost_interrupts` sends it again), one turned into another error
and dropped by the importing package (:func:`stop_if_interrupted`, and :func:`quadobs.cli.main`
counts it), and one during the interpreter's exit, after the command (:func:`end_program`).
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable
from typing import Any, ClassVar

__all__ = [
    "INTERRUPTED",
    "INTERRUPTED_LINE",
    "Signals",
    "end_now",
    "give_back_signals",
    "stop_if_interrupted",
    "take_signals",
]


#: Exit status of a command stopped by a signal (128 + SIGINT), whichever of SIGINT and SIGTERM it was.
INTERRUPTED = 130
INTERRUPTED_LINE = "quadobs: interrupted"


class Signals:
    """What a SIGINT or SIGTERM does while :func:`quadobs.cli.main` holds the handlers (one state per process).

    ``mode`` is ``"raise"``: a ``KeyboardInterrupt`` (the command stops and keeps what it has
    done); ``"hold"``: kept in ``held`` until the caller's handlers are back (an in-process
    call returning); ``"exit"``: status 130 at once (the program, its command over).
    ``last``: the last signal taken; ``raised``: the interrupts raised during the command;
    ``lost``: a signal whose ``KeyboardInterrupt`` was lost (:func:`keep_lost_interrupts`) and
    not taken since; ``said``: the line saying so has been written; ``hook``: the
    ``sys.unraisablehook`` replaced; ``status``: the program's exit status, once known;
    ``ending``: :func:`end_program` is registered.
    """

    mode = "raise"
    held: ClassVar[list[int]] = []
    last = 0
    raised = 0
    lost = 0
    said = False
    hook: Callable[[Any], Any] | None = None
    status: int | None = None
    ending = False


def on_signal(signum, frame) -> None:
    """The handler of SIGINT and SIGTERM: what :attr:`Signals.mode` says."""
    Signals.last, Signals.lost = signum, 0
    if Signals.mode == "raise":
        Signals.raised += 1
        raise KeyboardInterrupt
    if Signals.mode == "hold":
        Signals.held.append(signum)
        return
    end_now(INTERRUPTED)  # pragma: no cover - ends the process; exercised by subprocess tests


def end_now(
    status: int,
) -> None:  # pragma: no cover - ends the process; exercised by subprocess tests
    """End the program with ``status`` now, after what is buffered on stdout and stderr (its outputs
    are complete and in place by then), saying "interrupted" once when it is 130."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (
            BaseException
        ):  # a write cut short by the signal, a closed pipe: nothing more to save
            pass
    if Signals.lost:  # an interrupt lost at the very end (see keep_lost_interrupts)
        status = INTERRUPTED
    if status == INTERRUPTED and not Signals.said:
        try:
            os.write(2, (INTERRUPTED_LINE + "\n").encode())
        except OSError:
            pass
    os._exit(status)


def end_program() -> None:  # pragma: no cover - ends the process; exercised by subprocess tests
    """The program's last exit callback (registered first, so every other one has run): end the
    process with the command's status, skipping the interpreter's teardown.

    That teardown takes 0.4 to 0.7 s after a run (NumPy, Numba, MuJoCo, rerun) with SIGINT and
    SIGTERM back at their defaults, so a signal then would kill the process silently; there is
    nothing left to save in it. Without a status (an uncaught exception) it does nothing.
    """
    if Signals.status is not None:
        end_now(Signals.status)


def keep_lost_interrupts(unraisable) -> None:
    """``sys.unraisablehook`` while :func:`quadobs.cli.main` holds the signals.

    A ``KeyboardInterrupt`` raised where Python cannot propagate it (a weakref callback, such
    as the import system's module locks use, or a ``__del__``) would be printed as "Exception
    ignored" and lost (rerun's ``RecordingStream.__del__`` is one such place), and the command
    would run on. The signal is noted in ``Signals.lost`` and sent again from a helper thread a
    moment later, once that callback is over; a command that ends before it arrives ends with
    status 130 all the same. Anything else goes to the previous hook.
    """
    if (
        isinstance(unraisable.exc_value, KeyboardInterrupt)
        and Signals.mode == "raise"
        and Signals.last
    ):
        import _thread

        Signals.lost = Signals.last
        _thread.start_new_thread(send_again, (Signals.last,))
        return
    (Signals.hook or sys.__unraisablehook__)(unraisable)


def send_again(signum: int) -> None:  # pragma: no cover - a helper thread
    import time

    time.sleep(0.01)
    if Signals.lost == signum:  # not taken meanwhile
        os.kill(os.getpid(), signum)


def take_signals(previous: dict, program: bool) -> None:
    """Route SIGINT and SIGTERM to :func:`on_signal` in ``"raise"`` mode, noting the handlers replaced
    in ``previous`` (and :func:`keep_lost_interrupts` as ``sys.unraisablehook``); for the program,
    :func:`end_program` becomes its first exit callback, hence its last to run. A SIGINT the parent
    ignores (a background job) stays ignored; outside the main thread, where handlers cannot be
    set, nothing changes."""
    Signals.mode, Signals.said, Signals.last, Signals.raised, Signals.lost = "raise", False, 0, 0, 0
    if program and not Signals.ending:
        import atexit

        atexit.register(end_program)
        Signals.ending = True
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            if sig == signal.SIGINT and signal.getsignal(sig) == signal.SIG_IGN:
                continue
            previous[sig] = signal.signal(sig, on_signal)
        except ValueError:  # not the main thread
            return
    Signals.hook, sys.unraisablehook = sys.unraisablehook, keep_lost_interrupts


def give_back_signals(previous: dict) -> None:
    """Restore what :func:`take_signals` replaced, then deliver the signals held meanwhile."""
    if sys.unraisablehook is keep_lost_interrupts:
        sys.unraisablehook = Signals.hook or sys.__unraisablehook__
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    Signals.mode = "raise"
    held, Signals.held = Signals.held, []
    for sig in held:
        signal.raise_signal(sig)


def stop_if_interrupted() -> None:
    """Raise the interrupt again when one was raised during the command and it is still running.

    The commands call this once their modules are loaded, before their long part. A Ctrl-C
    during the initialisation of a compiled module can come out as an ``ImportError`` that the
    importing package catches and drops (MuJoCo does so for its optional renderer), and the
    command would run on to its end.
    """
    if Signals.raised:
        raise KeyboardInterrupt
