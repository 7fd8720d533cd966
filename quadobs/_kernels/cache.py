"""The kernels' on-disk cache checked before use: corrupt entries removed, an unwritable cache bypassed.

Numba keeps each compiled kernel as an index file ``<module>.<function>-<line>.pyXY.nbi``
(Numba's version, then the pickled source stamp and the table of signatures to data
files) and one data file ``....<n>.nbc`` per signature (pickled machine code), in the
package's ``__pycache__`` folders or under ``NUMBA_CACHE_DIR``. Numba trusts these files:
one damaged byte makes every later call of the kernel fail with an ``UnpicklingError``
or an ``EOFError``, for good, since the entry is never rewritten.

:func:`heal` reads every index and every data file it names, as Numba would (the same
``pickle`` steps), and removes the index and data files of each kernel whose entry does
not load; that kernel is then compiled again (and cached anew) on its next use, as on a
first run. An index of another Numba version or of another version of the source file is
left alone (Numba ignores it and writes a new one). Reading the whole cache of this
package (about 35 files, 2.7 MB) takes a few tens of milliseconds.

:func:`writable` probes a cache folder with a file of :data:`PROBE_BYTES` (a full disk,
a read-only folder); where it fails :func:`bypass` turns the cache off for this process,
so the kernels are compiled in memory and the run proceeds uncached.
"""

from __future__ import annotations

import os
import pickle
import sys
from pathlib import Path

__all__ = ["PROBE_BYTES", "bypass", "cache_folders", "heal", "writable"]

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


def _entry_problem(index: Path) -> str | None:
    """Why the kernel of ``index`` cannot be loaded (an unreadable index or data file), else ``None``."""
    import numba

    try:
        with open(index, "rb") as fh:
            version = pickle.load(fh)
            rest = fh.read()
        if version != numba.__version__:
            return None  # another Numba's: ignored by this one
        _stamp, overloads = pickle.loads(rest)
        for data_name in overloads.values():
            with open(index.parent / data_name, "rb") as fh:
                pickle.loads(fh.read())
    except FileNotFoundError:  # an index naming a data file that is gone: Numba compiles again
        return None
    except Exception as exc:  # any damage: UnpicklingError, EOFError, ValueError, OSError, ...
        return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return None


def heal(folders) -> list[str]:
    """Remove every kernel entry of ``folders`` that does not load; one line per entry removed.

    Each line names the index file and the error; the entry's index and data files are
    deleted, so the kernel is compiled again when next used. An entry that cannot be
    deleted (a read-only cache) is reported all the same: Numba will then fail on it, and
    :func:`bypass` is the way out.
    """
    lines = []
    for folder in folders:
        try:
            indexes = sorted(Path(folder).glob("*.nbi"))
        except OSError:
            continue
        for index in indexes:
            problem = _entry_problem(index)
            if problem is None:
                continue
            stem = index.name[: -len(".nbi")]
            removed = True
            for path in [index, *Path(folder).glob(f"{stem}.*.nbc")]:
                try:
                    path.unlink()
                except FileNotFoundError:
                    pass
                except OSError:
                    removed = False
            lines.append(
                f"kernel cache entry {index} is unreadable ({problem}); "
                + ("removed, the kernel is compiled again" if removed else "it cannot be removed")
            )
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
