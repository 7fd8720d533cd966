"""The one staged writer: every output file appears complete or not at all, and a folder as a whole.

A file is written by a callback into a staging file beside its target
(:func:`quadobs.errors.staging_path`: ``.<name>.<pid>-<random>.partial``), put on the disk
(``fsync``), given the target's permissions (an existing file keeps its own, a new one gets
``0o666`` less the umask) and renamed onto the target (``os.replace``, atomic on one file
system). On any failure the staging file is removed and the target is untouched; an
``OSError`` (a full disk) becomes one line naming the path.

A folder (a campaign's) is written the same way as a whole by :func:`write_folder_staged`:
its files go into a staging folder beside it, which replaces the previous folder once
every file is in it, so a failure at any point leaves the previous folder as it was.

Every writer of the package uses these: the JSON summaries and the log format's CSV files
(:mod:`quadobs.testbed.outputs`), the campaign's Parquet tables and recordings, the figures of
:mod:`quadobs.studies.plot`; the recorder streams into a staging file of the same name and
publishes it with :func:`publish`.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

from quadobs.errors import QuadobsError, RunFault, output_target, staging_owner, staging_path

__all__ = ["check_replaceable_folder", "publish", "swap_in", "write_folder_staged", "write_staged"]


def _new_file_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def publish(tmp: Path, target: Path, mode: int | None = None) -> None:
    """Put the complete staging file ``tmp`` on the disk and rename it onto ``target``.

    ``mode``: the permissions to give it (default: the target's, else those of a new file).
    """
    if mode is None:
        try:
            mode = os.stat(target).st_mode & 0o7777
        except FileNotFoundError:
            mode = _new_file_mode()
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fchmod(fd, mode)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, target)


def write_staged(
    path: str | Path, write: Callable[[Path], object], what: str = "output path"
) -> Path:
    """Call ``write(tmp)`` to fill a staging file beside ``path``, then publish it onto the target.

    The target is :func:`quadobs.errors.output_target` of ``path`` (a symbolic link is written
    through). On any failure the staging file is removed and the target is untouched; an
    ``OSError`` becomes a one-line :class:`~quadobs.errors.RunFault` (a fault of the run, exit
    status 1) naming ``what`` and the path. Returns the target.
    """
    target = output_target(path, what)
    tmp = staging_path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        publish(tmp, target)
    except OSError as exc:  # a full disk, a file size limit: a fault of the run (exit 1)
        tmp.unlink(missing_ok=True)
        raise RunFault(
            f"{what} {os.fspath(path)!r}: cannot be written ({exc.strerror or exc})"
        ) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target


def check_replaceable_folder(folder: str | Path, allowed: set[str], what: str) -> None:
    """Refuse, in one line, a ``folder`` that :func:`write_folder_staged` may not replace.

    It may be absent, or a folder holding only names in ``allowed`` (the files that the
    writer puts there) and staging files: replaced whole, anything else in it would be lost.
    """
    shown = os.fspath(folder)
    path = Path(os.path.realpath(shown))
    if not os.path.lexists(path):
        return
    if not path.is_dir():
        raise QuadobsError(f"{what} {shown!r}: exists and is not a folder")
    try:
        names = os.listdir(path)
    except OSError as exc:
        raise QuadobsError(f"{what} {shown!r}: cannot be read ({exc.strerror or exc})") from None
    other = sorted(n for n in names if n not in allowed and staging_owner(Path(n)) is None)
    if other:
        raise QuadobsError(
            f"{what} {shown!r}: holds {other[0]!r}"
            + (f" and {len(other) - 1} more" if len(other) > 1 else "")
            + f", not written here; the folder is replaced whole (it may hold only {', '.join(sorted(allowed))})"
        )


def write_folder_staged(
    folder: str | Path,
    write: Callable[[Path], object],
    what: str = "output folder",
    allowed: set[str] | None = None,
) -> Path:
    """Call ``write(tmp_folder)`` to fill a staging folder, then put it in place of ``folder`` as a whole.

    The staging folder is made beside ``folder`` (same file system). Once ``write`` returns,
    each file in it is put on the disk, and the staging folder replaces ``folder``: the
    previous folder is first renamed aside, then the new one renamed into place (with the
    previous one's permissions), then the previous one removed. An existing ``folder`` must
    pass :func:`check_replaceable_folder` with ``allowed`` (default: the names ``write``
    put in the staging folder). A failure while writing (a full disk) removes the staging
    folder and leaves ``folder`` as it was; one line names ``what`` and the folder. Returns
    the folder.
    """
    target = Path(os.path.realpath(os.fspath(folder)))
    if allowed is not None:
        check_replaceable_folder(folder, allowed, what)
    elif target.exists() and not target.is_dir():
        raise QuadobsError(f"{what} {os.fspath(folder)!r}: exists and is not a folder")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = staging_path(target)
    try:
        tmp.mkdir()
        write(tmp)
        if allowed is None:
            check_replaceable_folder(folder, set(os.listdir(tmp)), what)
        for entry in os.scandir(tmp):
            if entry.is_file(follow_symlinks=False):
                publish(Path(entry.path), Path(entry.path), _new_file_mode())
        swap_in(tmp, target)
    except OSError as exc:  # a full disk: a fault of the run (status 1), not bad input
        shutil.rmtree(tmp, ignore_errors=True)
        raise RunFault(
            f"{what} {os.fspath(folder)!r}: cannot be written ({exc.strerror or exc}); "
            "the previous folder is unchanged"
        ) from None
    except QuadobsError as exc:  # a file of the folder: named in the folder, not the staging one
        shutil.rmtree(tmp, ignore_errors=True)
        raise type(exc)(  # a write that failed (RunFault) stays one, bad input stays bad input
            f"{what} {os.fspath(folder)!r}: "
            + str(exc).replace(os.fspath(tmp), os.fspath(folder))
            + "; the previous folder is unchanged"
        ) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def swap_in(new: Path, target: Path) -> None:
    """Rename the complete folder ``new`` onto ``target``, the previous ``target`` removed after."""
    if not target.exists():
        os.rename(new, target)
        return
    os.chmod(new, os.stat(target).st_mode & 0o7777)
    if _exchange(new, target):  # one atomic step: the previous folder now under the staging name
        shutil.rmtree(new, ignore_errors=True)
        return
    old = staging_path(target).with_suffix(".old")
    os.rename(target, old)
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(old, target)  # the previous folder back in place
        raise
    shutil.rmtree(old, ignore_errors=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``).

    Returns False where the system call is missing or refused (another system, a file system
    without it); then nothing has changed.
    """
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    done = renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange)
    return done == 0
