"""The kernels' on-disk cache checked before use: corrupt entries removed, an unwritable cache bypassed.

Numba keeps each compiled kernel as an index file ``<module>.<function>-<line>.pyXY.nbi``
(Numba's version, then the pickled source stamp and the table of signatures to data
files) and one data file ``....<n>.nbc`` per signature (pickled machine code), in the
package's ``__pycache__`` folders or under ``NUMBA_CACHE_DIR``. Numba trusts these files:
one damaged byte makes every later call of the kernel fail with an ``UnpicklingError``
or an ``EOFError``, for good, since the entry is never rewritten; bytes changed inside
the machine code still unpickle, and Numba links and runs that code (an illegal
instruction, a crash, or wrong numbers).

:func:`heal` reads every index and every data file it names, as Numba would (the same
``pickle`` steps), and removes the index and data files of each kernel whose entry does
not load; that kernel is then compiled again (and cached anew) on its next use, as on a
first run. An index of another Numba version or of another version of the source file is
left alone (Numba ignores it and writes a new one). Damage that still unpickles is caught
by the sha256 of each file, recorded in the folder's :data:`MANIFEST` (written last, whole,
by :func:`heal`) the first time the file is read intact: quadobs reads the cache before
every command that runs kernels and after ``quadobs compile`` and the compiling of a first
run's kernels, so a file is recorded as soon as quadobs has written it. Numba writes a file
under a temporary name and renames it into place, so a file it rewrites (a kernel compiled
for a new signature or a new version of its source) is another file, recorded afresh;
the same file holding other bytes was damaged where it lies. Reading and hashing the
whole cache of this package (about 40 files, 3 MB) takes a few tens of milliseconds.

:func:`writable` probes a cache folder with a file of :data:`PROBE_BYTES` (a full disk,
a read-only folder); where it fails :func:`bypass` turns the cache off for this process,
so the kernels are compiled in memory and the run proceeds uncached.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import stat
import sys
from pathlib import Path

__all__ = ["MANIFEST", "PROBE_BYTES", "bypass", "cache_folders", "heal", "writable"]

#: Bytes written to probe a cache folder: about the largest data file of a kernel (330 kB), doubled.
PROBE_BYTES = 1 << 20


def cache_folders(kernels) -> list[Path]:
    """The folders holding the cache of ``kernels`` (``"module:function"``), each once."""
    import importlib

    folders: list[Path] = []
    for spec in kernels:
        module, _, name = spec.partition(":")
        dispatcher = getattr(importlib.import_module(module), name)
        try:
            folder = Path(dispatcher._cache._cache_path)
        except AttributeError:  # no on-disk cache (JIT disabled, another Numba)
            continue
        if folder not in folders:
            folders.append(folder)
    return folders


#: The file in each cache folder that records the sha256 of every cache file read intact.
MANIFEST = "quadobs-kernels.sha256.json"

#: Largest cache file read (bytes); the largest data file of a kernel is about 330 kB.
MAX_FILE_BYTES = 64 << 20


def _read(path: Path, files: dict[str, dict]) -> bytes:
    """The bytes of the cache file ``path``, its sha256, size and inode recorded in ``files``.

    Only a regular file of at most :data:`MAX_FILE_BYTES` is read (a FIFO or a device in
    the cache would block or never end: ``OSError``).
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as fh:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise OSError(f"{path.name} is not a regular file")
        if status.st_size > MAX_FILE_BYTES:
            raise OSError(f"{path.name} is larger than {MAX_FILE_BYTES} bytes")
        raw = fh.read(status.st_size + 1)  # not MAX_FILE_BYTES: a buffer of that size every time
    digest = hashlib.sha256(raw).hexdigest()
    files[path.name] = {"sha256": digest, "size": len(raw), "inode": status.st_ino}
    return raw


def _read_entry(index: Path) -> tuple[str | None, dict[str, dict]]:
    """Load the kernel entry of ``index`` as Numba would.

    Returns why it cannot be loaded (an unreadable index or data file; ``None`` when it
    loads) and the record of every file read (:func:`_read`).
    """
    import numba

    files: dict[str, dict] = {}
    try:
        fh = io.BytesIO(_read(index, files))
        version = pickle.load(fh)
        if version != numba.__version__:
            return None, files  # another Numba's: ignored by this one
        _stamp, overloads = pickle.loads(fh.read())
        for data_name in overloads.values():
            pickle.loads(_read(index.parent / data_name, files))
    except FileNotFoundError:  # an index naming a data file that is gone: Numba compiles again
        return None, files
    except Exception as exc:  # any damage: UnpicklingError, EOFError, ValueError, OSError, ...
        return (f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__), files
    return None, files


def _changed_in_place(files: dict[str, dict], recorded: dict[str, dict]) -> str | None:
    """The first file of ``files`` whose bytes differ from its record while it is the same file.

    Numba writes every cache file whole under a temporary name and renames it into place,
    so a file it rewrote is a new file (another inode), recorded afresh. The same file
    (same inode) holding other bytes was changed where it lies: damage that still
    unpickles, such as bytes changed in the middle of the machine code.
    """
    for name, now in files.items():
        was = recorded.get(name)
        if isinstance(was, dict) and was.get("inode") == now["inode"]:
            if was.get("sha256") != now["sha256"]:
                return (
                    f"{name} changed in place since it was written: sha256 {now['sha256'][:12]}..., "
                    f"{str(was.get('sha256'))[:12]}... recorded"
                )
    return None


def _load_manifest(folder: Path) -> dict[str, dict]:
    """The records of :data:`MANIFEST` in ``folder``; none when it is missing or unreadable."""
    try:
        with open(folder / MANIFEST, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > MAX_FILE_BYTES:
                return {}
            data = json.loads(fh.read(size + 1))
        files = data["files"]
        return {k: v for k, v in files.items() if isinstance(k, str) and isinstance(v, dict)}
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError):
        return {}


def _write_manifest(folder: Path, files: dict[str, dict]) -> None:
    """Write :data:`MANIFEST` whole under a staging name and rename it into place.

    A folder that cannot take it (read-only, full) keeps the previous manifest: the
    records are a safeguard, and the cache works without them.
    """
    staging = folder / f".{MANIFEST}.{os.getpid()}.partial"
    try:
        staging.write_text(json.dumps({"version": 1, "files": files}, sort_keys=True))
        os.replace(staging, folder / MANIFEST)
    except OSError:
        try:
            staging.unlink()
        except OSError:
            pass


def _remove_entry(folder: Path, index: Path) -> bool:
    """Delete the index and data files of the kernel of ``index``; False when one cannot be deleted."""
    stem = index.name[: -len(".nbi")]
    removed = True
    for path in [index, *folder.glob(f"{stem}.*.nbc")]:
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        except OSError:
            removed = False
    return removed


def heal(folders) -> list[str]:
    """Remove every kernel entry of ``folders`` that does not load or was damaged; one line per entry removed.

    Each entry is read as Numba would (:func:`_read_entry`) and its files' sha256 compared
    with those recorded in the folder's :data:`MANIFEST` when they were first read intact
    (:func:`_changed_in_place`). Each line names the index file and the error; the
    entry's index and data files are deleted, so the kernel is compiled again when next
    used. The manifest is then written anew with the records of every intact entry (those
    written since the last call recorded for the first time), last. An entry that cannot
    be deleted (a read-only cache) is reported all the same: Numba will then fail on it,
    and :func:`bypass` is the way out.
    """
    lines = []
    for folder in map(Path, folders):
        try:
            indexes = sorted(folder.glob("*.nbi"))
        except OSError:
            continue
        recorded = _load_manifest(folder)
        intact: dict[str, dict] = {}
        for index in indexes:
            problem, files = _read_entry(index)
            state = "unreadable"
            if problem is None and (problem := _changed_in_place(files, recorded)) is not None:
                state = "damaged"
            if problem is None:
                intact.update(files)
                continue
            removed = _remove_entry(folder, index)
            lines.append(
                f"kernel cache entry {index} is {state} ({problem}); "
                + ("removed, the kernel is compiled again" if removed else "it cannot be removed")
            )
        if intact != recorded and (indexes or recorded):
            _write_manifest(folder, intact)
    return lines


def writable(folder: Path) -> str | None:
    """``None`` when ``folder`` takes a file of :data:`PROBE_BYTES`, else the reason (one phrase)."""
    probe = Path(folder) / f".quadobs-probe-{os.getpid()}"
    try:
        Path(folder).mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            block, left = memoryview(bytes(PROBE_BYTES)), PROBE_BYTES
            while left:  # a short write (a file size limit) is followed by the refusal
                left -= os.write(fd, block[PROBE_BYTES - left :])
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        return exc.strerror or str(exc)
    finally:
        try:
            probe.unlink()
        except OSError:
            pass
    return None


def bypass() -> int:
    """Turn the on-disk cache off for every loaded kernel of quadobs; returns how many.

    The kernels are then compiled in memory when first called, and nothing is read from
    or written to the cache in this process.
    """
    from numba.core.caching import NullCache
    from numba.core.dispatcher import Dispatcher

    count = 0
    for name, module in list(sys.modules.items()):
        if not name.startswith("quadobs") or module is None:
            continue
        for value in list(vars(module).values()):
            cache = getattr(value, "_cache", None) if isinstance(value, Dispatcher) else None
            if cache is not None and not isinstance(cache, NullCache):
                value._cache = NullCache()
                count += 1
    return count
