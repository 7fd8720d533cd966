"""Reading and writing the files of a log folder, within limits.

Reading. :func:`read_limited` opens a log file without blocking (a FIFO is refused, not
waited on), refuses what is not a regular file (a device such as ``/dev/zero``, a
directory, a dangling symbolic link, a link loop) and a file larger than
:data:`~quadobs.testbed.logs.schema.MAX_FILE_BYTES` before reading it, then reads it
whole. :func:`read_table` checks the line lengths
(:data:`~quadobs.testbed.logs.schema.MAX_LINE_BYTES`) and the header, and parses the rows
with ``pyarrow.csv`` (Arrow's multi-threaded C++ reader: a 300k-row ``ranges.csv`` in a
small fraction of the time a ``float()`` per cell takes, see ``quadobs bench``). Where
Arrow refuses a row, the file is read again row by row in Python only to name the row and
the column of the fault; a UTF-8 byte-order mark is skipped.

Writing. :func:`staged_folder` builds a folder beside its target and puts it in place
whole: a failure leaves the previous folder as it was.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import math
import os
import shutil
import stat
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError, RunFault, staging_owner, staging_path
from quadobs.testbed.logs.schema import (
    MAX_FILE_BYTES,
    MAX_LINE_BYTES,
    SORT_REACH,
    TIME,
    FileSpec,
    blank_rows,
    check_values,
)

__all__ = ["check_replaceable_folder", "read_limited", "read_table", "staged_folder"]


def read_limited(path: Path) -> bytes | None:
    """The bytes of the log file ``path``, or None where nothing (not even a link) has that name.

    Raises
    ------
    QuadobsError
        Not a regular file (a FIFO, a device, a directory), a dangling symbolic link or a
        link loop, unreadable, or larger than ``MAX_FILE_BYTES``; nothing has been read.
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        if os.path.islink(path):
            raise QuadobsError(f"{path}: a dangling symbolic link") from None
        return None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise QuadobsError(f"{path}: a symbolic link loop") from None
        raise QuadobsError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise QuadobsError(f"{path}: not a regular file")
        if st.st_size > MAX_FILE_BYTES:
            raise QuadobsError(f"{path}: larger than {MAX_FILE_BYTES} bytes")
        chunks, size = [], 0
        while size <= MAX_FILE_BYTES:
            chunk = os.read(fd, min(1 << 24, MAX_FILE_BYTES + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise QuadobsError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    finally:
        os.close(fd)
    if size > MAX_FILE_BYTES:  # it grew while read
        raise QuadobsError(f"{path}: larger than {MAX_FILE_BYTES} bytes")
    return b"".join(chunks)


def _line_starts(path: Path, raw: bytes) -> np.ndarray:
    """Offsets of each line's first byte, and one past the end; checks :data:`MAX_LINE_BYTES`."""
    data, chunk = np.frombuffer(raw, dtype=np.uint8), 1 << 24  # a chunk's mask at a time
    parts = [np.zeros(0, dtype=np.int64)]
    for i in range(0, data.size, chunk):
        c = data[i : i + chunk]
        following = np.append(data[i + 1 : i + chunk + 1], 0)[: c.size]
        # a line ends at LF, or at a CR not followed by LF (as the CSV parser reads it)
        parts.append(np.flatnonzero((c == 10) | ((c == 13) & (following != 10))) + i)
    ends = np.concatenate(parts)
    starts = np.concatenate([[0], ends + 1, [len(raw) + 1]]) if raw else np.array([0, 1])
    lengths = np.diff(starts) - 1
    bad = np.flatnonzero(lengths > MAX_LINE_BYTES)
    if bad.size:
        raise QuadobsError(
            f"{path}, row {int(bad[0]) + 1}: a line of {int(lengths[bad[0]])} bytes, more than {MAX_LINE_BYTES}"
        )
    return starts


def _line(raw: bytes, starts: np.ndarray, k: int) -> list[str]:
    """The cells of line ``k`` (0-based) as the csv module reads them (none past the end)."""
    if k + 1 >= starts.size:
        return []
    text = raw[starts[k] : max(starts[k + 1] - 1, starts[k])].decode("utf-8-sig", "replace")
    text = text.rstrip("\r")
    try:
        return next(csv.reader([text]), [])
    except csv.Error:  # a stray carriage return or quote: the cells as split by commas
        return text.split(",")


def _trimmed(raw: bytes) -> bytes:
    """``raw`` without blank lines (or spaces) after its last row: an editor's trailing empty
    lines are no rows. A blank line between rows is kept here, and left out by
    :func:`read_table` with a note."""
    body = raw.rstrip(b" \t\r\n")
    return body + b"\n" if body else body


def text_rows(path: Path, raw: bytes) -> list[list[str]]:
    """Every row of a small CSV file (``meta.csv``), line lengths checked, a BOM skipped,
    blank lines after the last row left out."""
    raw = _trimmed(raw)
    starts = _line_starts(path, raw)
    try:
        raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise QuadobsError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    lines = starts.size - 1
    if lines and starts[-2] >= len(raw):  # the last line end, not an empty line
        lines -= 1
    return [_line(raw, starts, k) for k in range(lines)]  # numbered as the data files' rows


def read_table(
    path: Path,
    raw: bytes,
    spec: FileSpec,
    version: int,
    notes: list | None = None,
    row_map: dict | None = None,
) -> tuple[tuple[str, ...], np.ndarray]:
    """The columns (in memory order, :meth:`FileSpec.columns_of`) and values of one log file.

    Every value is held to ``spec`` (:func:`~quadobs.testbed.logs.schema.check_values`);
    errors name the file, the row and the column in one line. Blank lines after the last row
    are left out, and so are empty lines between rows and the rows of a timed file with an
    empty or NaN value
    (:func:`~quadobs.testbed.logs.schema.blank_rows`); rows out of time order by at most
    :data:`~quadobs.testbed.logs.schema.SORT_REACH`, and single rows written late
    (:data:`~quadobs.testbed.logs.schema.LATE_ROWS`), are sorted (stably). Each of the two is
    said in one line appended to ``notes`` (where given); where rows were left out or
    sorted, ``row_map[path.name]`` (where given) holds the data row of the file (0-based) of
    each row returned, for messages that name a row later.
    """
    raw = _trimmed(raw)
    starts = _line_starts(path, raw)
    try:
        header = [h.strip() for h in _line(raw, starts, 0)]
        raw[: starts[1] - 1].decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise QuadobsError(f"{path}, row 1: not UTF-8 text (byte {exc.start})") from None
    if not raw.strip():
        raise QuadobsError(f"{path}, row 1: empty file; expected the header {spec.described}")
    columns = spec.columns_of(header, version)
    if columns is None:
        newer = spec.columns_of(header, 2) if version < 2 else None
        hint = "; add the row version,2 to meta.csv" if newer else ""
        known = {c for variant in spec.variants for c in variant} | set(spec.optional)
        unknown = [h for h in header if h not in known]
        if unknown and not newer:
            whole = any(set(v) <= set(header) for v in spec.variants)  # only extra columns
            fix = "leave it out" if whole else "rename it to a column expected, or leave it out"
            hint = f"; {', '.join(map(repr, unknown))} not a column of the format ({fix})"
        raise QuadobsError(
            f"{path}, row 1: header {','.join(header)!r}; expected {spec.described}{hint}"
        )
    order = [header.index(c) for c in columns]
    try:
        values = _arrow_values(raw, header, columns)
    except Exception:  # pyarrow refused a row: find it, or read what Arrow would not
        values = _python_values(path, raw, starts, header, columns)

    empty = _empty_lines(raw, starts, values)
    blank = blank_rows(spec, columns, values) | empty
    if blank.size and blank.all():
        raise QuadobsError(f"{path}: each of its {blank.size} rows has an empty or NaN value")
    rows = np.flatnonzero(~blank) if blank.any() else None
    if rows is not None:
        values = values[rows]

    def cell(i: int, c: int) -> str:
        row = _line(raw, starts, (i if rows is None else int(rows[i])) + 1)
        return row[order[c]].strip() if order[c] < len(row) else ""

    timed = columns[0] == TIME
    check_values(str(path), spec, columns, values, cell, rows, SORT_REACH if timed else 0.0)
    counts = (int(empty.sum()), int(blank.sum() - empty.sum()))
    unsorted = timed and bool(np.any(np.diff(values[:, 0]) < 0.0))
    by_time = np.argsort(values[:, 0], kind="stable") if unsorted else None
    if row_map is not None and (rows is not None or by_time is not None):
        read = np.arange(values.shape[0]) if rows is None else rows
        row_map[path.name] = read if by_time is None else read[by_time]
    return columns, _sorted(path, values, counts, notes, by_time)


def _empty_lines(raw: bytes, starts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The rows (a mask) that are empty lines between rows (no cell, or only spaces: a
    writer's doubled line ends), which a reader leaves out."""
    empty = np.zeros(values.shape[0], dtype=bool)
    if values.ndim != 2 or not values.shape[1]:
        return empty
    for i in np.flatnonzero(np.isnan(values).all(axis=1)):
        k = int(i) + 1  # the data row's line
        if k + 1 < starts.size:
            empty[i] = not raw[starts[k] : max(starts[k + 1] - 1, starts[k])].strip()
    return empty


def _sorted(
    path: Path, values: np.ndarray, left_out: tuple, notes: list | None, by_time
) -> np.ndarray:
    """A file's rows in the order ``by_time`` (None: as they are), with a note of the rows
    left out (``left_out``: the empty lines, and the rows with an empty or NaN value) and of
    those out of order (how many, and the furthest back)."""
    said = []
    if left_out[0]:
        said.append(f"{left_out[0]} empty line{'s' * (left_out[0] > 1)} between rows left out")
    if left_out[1]:
        said.append(f"{left_out[1]} rows with an empty or NaN value left out (no measurement)")
    if by_time is not None:
        t = values[:, 0]
        back = np.maximum.accumulate(t) - t
        late = int(np.count_nonzero(back > 0.0))
        said.append(
            f"{late} rows stamped before an earlier row (by up to {back.max():.3g} s) sorted by time"
        )
        values = values[by_time]
    if said and notes is not None:
        notes.append(f"{path.name}: {'; '.join(said)}")
    return values


def _arrow_values(raw: bytes, header: list[str], columns: tuple[str, ...]) -> np.ndarray:
    """The values, columns in ``columns`` order, parsed by ``pyarrow.csv`` (nulls as NaN)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    table = pacsv.read_csv(
        pa.BufferReader(raw),
        read_options=pacsv.ReadOptions(skip_rows=1, column_names=header),
        parse_options=pacsv.ParseOptions(ignore_empty_lines=False),
        convert_options=pacsv.ConvertOptions(column_types={h: pa.float64() for h in header}),
    )
    values = np.empty((table.num_rows, len(columns)))
    for c, name in enumerate(columns):
        _fill_float_column(values[:, c], table.column(name).chunks)
    return values


def _fill_float_column(out: np.ndarray, chunks) -> None:
    """Write the float64 arrow ``chunks`` into ``out``, nulls as NaN, from their buffers (the
    values and the validity bitmap, least significant bit first): arrow's own ``to_numpy``
    imports pandas (over half a second of a replay's start) to convert the nulls."""
    row = 0
    for chunk in chunks:
        n, offset = len(chunk), chunk.offset
        validity, data = chunk.buffers()
        part = out[row : row + n]
        part[:] = np.frombuffer(data, dtype=np.float64, count=offset + n)[offset:]
        if chunk.null_count:
            bits = np.unpackbits(np.frombuffer(validity, dtype=np.uint8), bitorder="little")
            part[bits[offset : offset + n] == 0] = np.nan
        row += n


def _python_values(
    path: Path,
    raw: bytes,
    starts: np.ndarray,
    header: list[str],
    columns: tuple[str, ...],
) -> np.ndarray:
    """The values read row by row in Python: the slow path that names a faulty row and column.
    An empty cell, or an empty line, reads as NaN, as Arrow reads it: :func:`read_table`
    leaves such rows out or refuses them by the same rules on either path."""
    order = [header.index(c) for c in columns]
    rows = starts.size - 2
    if rows > 0 and starts[-2] >= len(raw):  # a last line end, not an empty line
        rows -= 1
    values = np.empty((rows, len(columns)))
    for i in range(rows):
        row = _line(raw, starts, i + 1)
        if len(row) <= 1 and not "".join(row).strip():  # an empty line: left out later
            values[i] = math.nan
            continue
        if len(row) != len(header):
            raise QuadobsError(
                f"{path}, row {i + 2}: {len(row)} columns, expected {len(header)} ({','.join(header)})"
            )
        for c, k in enumerate(order):
            text = row[k].strip()
            try:
                values[i, c] = float(text) if text else math.nan  # empty: judged later
            except ValueError:
                what = (
                    "an integer anchor id (number the anchors; a name may not stand for one)"
                    if columns[c] in ID_COLUMNS
                    else "a finite number"
                )
                raise QuadobsError(
                    f"{path}, row {i + 2}, column {columns[c]}: {text!r} is not {what}"
                ) from None
    return values


#: The columns that hold anchor ids (integers).
ID_COLUMNS = ("id", "beacon", "anchor_i", "anchor_j")


def _remove_dead_stages(target: Path) -> None:
    """Remove staging folders of ``target`` left by processes that are gone."""
    with contextlib.suppress(OSError):
        for entry in os.scandir(target.parent):
            owner = staging_owner(Path(entry.name))
            if owner is None or owner[0] != target.name or owner[1] == os.getpid():
                continue
            try:
                os.kill(owner[1], 0)
            except ProcessLookupError:
                shutil.rmtree(entry.path, ignore_errors=True)
            except OSError:
                pass


@contextlib.contextmanager
def staged_folder(folder: str | Path, allowed, what: str) -> Iterator[Path]:
    """A fresh folder to fill, put in place of ``folder`` in one rename once the block ends.

    An existing ``folder`` may hold only names in ``allowed`` (a set of names, or a test of
    a name): it is replaced whole, so a folder holding anything else is refused before
    anything is written. On any
    failure the staging folder is removed and ``folder`` is as it was. The previous
    folder is moved aside, the new one renamed in, and the previous one removed: a crash
    between the two renames leaves the previous folder complete under its staging name.
    """
    target = Path(os.path.realpath(folder))
    check_replaceable_folder(folder, allowed, what)
    _remove_dead_stages(target)
    stage = staging_path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        stage.mkdir()
    except OSError as exc:
        raise QuadobsError(
            f"{what} {os.fspath(folder)!r}: cannot be created ({exc.strerror or exc})"
        ) from None
    try:
        yield stage
        _swap_in(stage, target)
    except OSError as exc:  # a full disk: a fault of the run (status 1), not bad input
        shutil.rmtree(stage, ignore_errors=True)
        raise RunFault(
            f"{what} {os.fspath(folder)!r}: cannot be written ({exc.strerror or exc})"
        ) from None
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


def _swap_in(stage: Path, target: Path) -> None:
    """Every file of ``stage`` on the disk, then ``stage`` in place of ``target``
    (:func:`quadobs.staging.swap_in`: one atomic exchange where the system has it)."""
    from quadobs.staging import swap_in

    for entry in os.scandir(stage):
        fd = os.open(entry.path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    swap_in(stage, target)


def check_replaceable_folder(folder: str | Path, allowed, what: str, outputs=()) -> None:
    """A one-line error unless ``folder`` is absent, or a folder holding only names in ``allowed``
    (a set, or a test of a name); and none of the command's other ``outputs`` (paths or None)
    lies in it (the folder is replaced whole, they would be lost)."""
    path = Path(folder)
    shown = os.fspath(folder)
    inside = Path(os.path.realpath(path))
    for other in outputs:
        if other is not None and inside in Path(os.path.realpath(other)).parents:
            raise QuadobsError(
                f"{what} {shown!r}: holds the output {os.fspath(other)!r}, and the folder is replaced whole"
            )
    if os.path.lexists(path) and not os.path.isdir(path):
        raise QuadobsError(f"{what} {shown!r}: exists and is not a folder")
    if not path.exists():
        return
    try:
        names = sorted(os.listdir(path))
    except OSError as exc:
        raise QuadobsError(f"{what} {shown!r}: cannot be read ({exc.strerror or exc})") from None
    keep = allowed if callable(allowed) else allowed.__contains__
    other = [n for n in names if not keep(n)]
    if other:
        raise QuadobsError(
            f"{what} {shown!r}: holds {other[0]!r}, which is not part of what is written there; "
            "the folder is replaced whole, so give a new or empty folder"
        )
    if not os.access(Path(os.path.realpath(path)).parent, os.W_OK):
        raise QuadobsError(f"{what} {shown!r}: its parent folder is not writable")
