"""The project's error type and the small validators every public entry point uses.

Every malformed input (a wrong shape, a non-finite number, an unmet assumption, a
bad scenario field, a missing MJCF element) raises :class:`QuadobsError`, a
``ValueError`` subclass whose message names the offending field and the problem.

The module imports the standard library alone (NumPy when a validator first needs it), so
that the command line can load it before anything heavy, its signal handling in place.
"""

from __future__ import annotations

import math
import os
import re
import signal
import stat
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np


__all__ = [
    "STAGING_SUFFIX",
    "QuadobsError",
    "RunFault",
    "abbreviated",
    "as_array",
    "as_finite_scalar",
    "as_float_array",
    "caused_by_interrupt",
    "check_writable",
    "deferred_interrupts",
    "new_folders_removed_on_failure",
    "output_target",
    "run_script",
    "staging_owner",
    "staging_path",
]


class QuadobsError(ValueError):
    """Bad input to quadobs: the message names the field and what is wrong with it."""


class RunFault(QuadobsError):
    """A run that started and could not go on: an output that cannot be written (a full
    disk), a physics fault. The message names the path or the step; the command line
    prints it on one line and exits with status 1 (bad input is status 2)."""


#: Ending of a staged output's temporary file: ``.<target name>.<pid>-<random>.partial``,
#: beside the target; a leftover one (its process is gone) is removed by the next run
#: that writes the same target.
STAGING_SUFFIX = ".partial"
_STAGING = re.compile(
    r"^\.(?P<stem>.*)\.(?P<pid>\d+)-[0-9a-f]{6}" + re.escape(STAGING_SUFFIX) + "$"
)
#: Longest output path taken (characters); longer ones are refused at once.
MAX_PATH_CHARS = 1024
_FILE_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
)


def abbreviated(text: str, limit: int = 80) -> str:
    """``text`` as an error message shows it: whole up to ``limit`` characters, else its start
    and its end around ``...`` (``limit`` characters in all), so that a long path still shows
    its file name.

    Examples
    --------
    >>> abbreviated("/a/" + "b" * 100 + "/scenario.toml", 40)
    '/a/bbbbbbbbb...bbbbbbbbbbb/scenario.toml'
    """
    if len(text) <= limit:
        return text
    head = max((limit - 3) // 3, 1)
    return text[:head] + "..." + text[len(text) - (limit - 3 - head) :]


def output_target(path: str | Path, what: str = "output path") -> Path:
    """The regular file that an output named ``path`` replaces once complete.

    A symbolic link is followed (the file it points to is written, the link stays); a
    target that exists and is not a regular file (a directory, a device such as
    ``/dev/null`` or ``/dev/full``, a FIFO, a socket), a read-only file, a symbolic-link
    loop, a name holding NUL, longer than :data:`MAX_PATH_CHARS` characters or too long
    for its file system (with room for the staging name) are refused with a
    :class:`QuadobsError` naming ``what`` and the path.
    """
    text = os.fspath(path)
    shown = abbreviated(text)
    if "\0" in text:
        raise QuadobsError(f"{what} {shown!r}: holds a NUL character")
    if not text or len(text) > MAX_PATH_CHARS:
        raise QuadobsError(
            f"{what} {shown!r}: expected a file name of 1 to {MAX_PATH_CHARS} characters, got {len(text)}"
        )
    try:
        real = Path(os.path.realpath(text, strict=False))
        st = os.stat(real) if os.path.lexists(real) else None
    except (OSError, RuntimeError) as exc:  # a symbolic-link loop, a component that is a file
        raise QuadobsError(
            f"{what} {shown!r}: cannot be resolved ({getattr(exc, 'strerror', None) or exc})"
        ) from None
    if st is not None:
        kind = next((name for test, name in _FILE_KINDS if test(st.st_mode)), None)
        if kind is not None:
            raise QuadobsError(f"{what} {shown!r}: is {kind}, expected a regular file")
        if not (
            os.access(real, os.W_OK) and st.st_mode & 0o222
        ):  # no write bit: read-only, even for root
            raise QuadobsError(f"{what} {shown!r}: the existing file is read-only")
    if len(os.fsencode(real.name)) > 231 or not real.name:
        raise QuadobsError(f"{what} {shown!r}: file name too long or empty (at most 231 bytes)")
    return real


def staging_path(target: Path) -> Path:
    """A fresh temporary name beside ``target``: ``.<name>.<pid>-<random>.partial`` (see :data:`STAGING_SUFFIX`)."""
    return target.parent / f".{target.name}.{os.getpid()}-{os.urandom(3).hex()}{STAGING_SUFFIX}"


def staging_owner(path: Path) -> tuple[str, int] | None:
    """``(target name, pid)`` of a staging file named by :func:`staging_path`, else ``None``."""
    m = _STAGING.match(path.name)
    return None if m is None else (m["stem"], int(m["pid"]))


def as_float_array(name: str, value: Any, *, copy: bool = True) -> np.ndarray:
    """``value`` converted to a float64 array: a new one, or with ``copy=False`` a C-contiguous one
    that is ``value`` itself where it already is one; a :class:`QuadobsError` naming ``name`` when it is
    not numeric. Neither its shape nor its values are checked (:func:`as_array` does)."""
    import numpy as np

    try:
        return np.array(value, dtype=float) if copy else np.ascontiguousarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise QuadobsError(
            f"{name}: expected a numeric array, got {type(value).__name__} ({exc})"
        ) from None


def as_array(
    name: str,
    value: Any,
    shape: tuple[int | None, ...] | None = None,
    *,
    ndim: int | None = None,
    allow_nan: bool = False,
) -> np.ndarray:
    """Convert ``value`` to a float64 array and check its shape and finiteness.

    Parameters
    ----------
    name : str
        Field name used in error messages.
    value : array_like
        The value to convert.
    shape : tuple of int or None, optional
        Expected shape; ``None`` entries match any size.
    ndim : int, optional
        Expected number of dimensions (when ``shape`` is not given).
    allow_nan : bool
        Accept NaN entries (used for missing measurements); infinities are always refused.

    Raises
    ------
    QuadobsError
        If the value is not numeric, has the wrong shape, or holds non-finite numbers.
    """
    import numpy as np

    arr = as_float_array(name, value)
    if shape is not None:
        ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
        if not ok:
            want = (
                "("
                + ", ".join("any" if s is None else str(s) for s in shape)
                + ("," if len(shape) == 1 else "")
                + ")"
            )
            raise QuadobsError(f"{name}: expected shape {want}, got {arr.shape}")
    elif ndim is not None and arr.ndim != ndim:
        raise QuadobsError(f"{name}: expected a {ndim}-D array, got shape {arr.shape}")
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise QuadobsError(f"{name}: holds a non-finite value ({arr[idx]}) at index {idx}")
    return arr


def as_finite_scalar(
    name: str, value: Any, *, positive: bool = False, nonnegative: bool = False
) -> float:
    """Convert ``value`` to a finite float, optionally requiring a sign."""
    if isinstance(value, bool):
        raise QuadobsError(f"{name}: expected a number, got a boolean")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise QuadobsError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(x):
        raise QuadobsError(f"{name}: must be finite, got {x}")
    if positive and not x > 0:
        raise QuadobsError(f"{name}: must be positive, got {x}")
    if nonnegative and x < 0:
        raise QuadobsError(f"{name}: must be non-negative, got {x}")
    return x


def check_writable(path: str | Path) -> Path:
    """Fail early (before any simulation) if ``path`` cannot be written.

    Refuses what :func:`output_target` refuses, creates the parent folder if needed and
    probes it with a temporary file of the staging name's length.
    """
    path = Path(path)
    real = output_target(path)
    try:
        real.parent.mkdir(parents=True, exist_ok=True)
        probe = staging_path(real)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise QuadobsError(
            f"output path {str(path)!r}: cannot be written ({exc.strerror})"
        ) from None
    return path


def _missing_folders(path: Path) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, deepest first."""
    missing = []
    for folder in (path, *path.parents):
        try:
            if folder.exists() or folder.is_symlink():
                break
        except (OSError, ValueError):  # a name too long, holding NUL: nothing was created there
            continue
        missing.append(folder)
    return missing


@contextmanager
def new_folders_removed_on_failure(*paths: str | Path | None) -> Iterator[None]:
    """Remove the folders a failed command created on the way to its outputs.

    Before the section, notes which of ``paths`` (output files or folders; ``None`` is
    skipped) and their ancestors do not exist. When the section raises, every one of
    them that now exists and is empty is removed, deepest first, and the exception
    propagates; folders that hold something (a partial recording kept on purpose) and
    folders that existed before stay. A section that ends normally keeps everything.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> root = Path(tempfile.mkdtemp())
    >>> try:
    ...     with new_folders_removed_on_failure(root / "new" / "sub" / "x.json"):
    ...         _ = check_writable(root / "new" / "sub" / "x.json")  # creates new/sub
    ...         raise QuadobsError("estimators: unknown estimator 'nosuch'")
    ... except QuadobsError:
    ...     pass
    >>> list(root.iterdir())
    []
    """
    missing = [
        folder for p in paths if p is not None for folder in _missing_folders(Path(p).absolute())
    ]
    try:
        yield
    except BaseException:
        for folder in sorted(set(missing), key=lambda f: len(f.parts), reverse=True):
            try:
                folder.rmdir()  # only an empty folder goes; a file or a non-empty folder stays
            except (OSError, ValueError):
                pass
        raise


def caused_by_interrupt(exc: BaseException | None) -> bool:
    """Whether ``exc`` is a ``KeyboardInterrupt`` or was raised while one was handled (its cause and
    context chain): an import, a compiler or a validator cut short by Ctrl-C or SIGTERM. Such an
    error stands for the interrupt; code that turns errors into messages or records should let
    it through as one (``raise KeyboardInterrupt from exc``).

    A Ctrl-C during the initialisation of a compiled extension module, for one, surfaces as
    ``ImportError: initialization failed`` caused by the ``KeyboardInterrupt``.

    Examples
    --------
    >>> try:
    ...     try:
    ...         raise KeyboardInterrupt
    ...     except KeyboardInterrupt:
    ...         raise ImportError("initialization failed")
    ... except ImportError as exc:
    ...     caused_by_interrupt(exc)
    True
    >>> caused_by_interrupt(ValueError("x"))
    False
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


@contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold SIGINT and SIGTERM over a section that must not be cut in two.

    Sending a block of rows to a recording is such a section: stopped half-way, some
    series would hold the rows and others not, and sending the block again would
    duplicate them. A signal received inside is delivered when the section ends, to the
    handler installed before it (Ctrl-C then raises ``KeyboardInterrupt`` there). Outside
    the main thread, where handlers cannot be set, nothing is held. Sections nest.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous: dict[int, Any] = {}
    try:
        for sig in (int(signal.SIGINT), int(signal.SIGTERM)):
            previous[sig] = signal.signal(sig, lambda signum, frame: held.append(signum))
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in held:
            handler = previous[sig]
            if callable(handler):
                handler(sig, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(sig)


def run_script(main: Callable[[], object], name: str) -> None:
    """Run a script's ``main`` as the command line runs a command: bad input
    (:class:`QuadobsError`) printed on one line with exit status 2, a run that could not go on
    (:class:`RunFault`) with status 1, Ctrl-C with status 130; anything else propagates.

    Parameters
    ----------
    main : callable
        The script's entry point (it parses its own arguments).
    name : str
        The script's name, which starts the error line (``name: error: ...``).
    """
    import sys

    try:
        main()
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    except QuadobsError as exc:
        if caused_by_interrupt(exc):
            print(f"{name}: interrupted", file=sys.stderr)
            raise SystemExit(130) from None
        print(f"{name}: error: {exc}", file=sys.stderr)
        raise SystemExit(1 if isinstance(exc, RunFault) else 2) from None
