"""Staged outputs: every file a run writes appears complete or not at all.

A run's outputs (the ``.rrd`` recording, the JSON summary, a report) are written to a
temporary file beside their target, named ``.<target name>.<pid>-<random>.partial``
(:func:`quadobs.errors.staging_path`), and renamed onto the target once complete
(``os.replace``, atomic on one file system). Hence:

* a reader sees the previous file or the new one, never a part of one;
* a run killed (``SIGKILL``, a power cut) or failed leaves the previous files untouched
  and at most a ``.partial`` file, which the next run writing the same target removes
  once the process that made it is gone (:func:`clean_leftovers`);
* concurrent writers of one target each write their own temporary file: the last
  rename wins and the file is always one complete output;
* a symbolic link is written through (the file it points to is replaced, the link stays).

Before anything runs, :func:`check_outputs` refuses targets that are not regular files
(a directory, a device such as ``/dev/null``, a FIFO), read-only files, names too long
for the staging name, two outputs naming the same file and an output naming one of the
run's inputs (the scenario file, the model).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from quadobs.errors import QuadobsError, check_writable, output_target, staging_owner
from quadobs.staging import write_folder_staged, write_staged

__all__ = [
    "check_inside_folders",
    "check_output_folder",
    "check_outputs",
    "clean_leftovers",
    "cost_notice",
    "expected_cost",
    "fault_summary",
    "write_fault_summary",
    "write_folder_staged",
    "write_json_staged",
    "write_text_staged",
]

log = logging.getLogger("quadobs.testbed")


def _same_file(a: Path, b: Path) -> bool:
    """Whether the resolved paths ``a`` and ``b`` name one file (hard links included)."""
    if a == b:
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


def check_outputs(outputs: Mapping[str, Any], inputs: Mapping[str, Any] = {}) -> dict[str, Path]:
    """Check a run's outputs before it starts; returns the file each one will replace.

    Parameters
    ----------
    outputs : mapping of str to path or None
        Output name (used in messages, e.g. ``"--out"``) to path; ``None`` is skipped.
    inputs : mapping of str to path or None
        Files the run reads (``"scenario"``, ``"model"``): no output may name one of them.
        Entries that are not paths of existing files (a built-in scenario's name) are skipped.

    Raises
    ------
    QuadobsError
        An output refused by :func:`quadobs.errors.check_writable` (not a regular file,
        read-only, unwritable folder, too long a name), two outputs naming one file, or an
        output naming an input; nothing has been written (a missing parent folder may have
        been created, see :func:`quadobs.errors.new_folders_removed_on_failure`).
    """
    targets: dict[str, Path] = {}
    for name, path in outputs.items():
        if path is None:
            continue
        target = output_target(path, f"{name}")
        for other, seen in targets.items():
            if _same_file(target, seen):
                raise QuadobsError(f"{name}: names the same file as {other} ({os.fspath(path)!r})")
        for what, source in inputs.items():
            if (
                source
                and os.path.isfile(os.fspath(source))
                and _same_file(target, Path(os.path.realpath(source)))
            ):
                raise QuadobsError(
                    f"{name}: is the run's {what} file ({os.fspath(path)!r}); it would be overwritten"
                )
        check_writable(path)
        targets[name] = target
    for target in targets.values():
        clean_leftovers(target)
    return targets


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (on this machine)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def clean_leftovers(target: Path) -> list[Path]:
    """Remove the ``.partial`` files of ``target`` left by processes that are gone; returns them.

    Only files named by :func:`quadobs.errors.staging_path` for this very target are
    considered, and one is removed only when no process with its pid exists (a running
    writer's file stays).
    """
    removed: list[Path] = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    prefix = f".{target.name}."
    for entry in entries:
        if not entry.name.startswith(prefix):
            continue
        owner = staging_owner(Path(entry.name))
        if owner is None or owner[0] != target.name or owner[1] == os.getpid() or _alive(owner[1]):
            continue
        try:
            if entry.is_dir(follow_symlinks=False):  # a staged folder
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
            log.info("removed %s, left by a process that is gone", entry.path)
        except OSError:
            pass
    return removed


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json_staged(path: str | Path, data: dict, what: str = "output path") -> Path:
    """Write ``data`` as JSON through :func:`write_text_staged`. Returns the target."""
    return write_text_staged(
        path, json.dumps(data, indent=2, allow_nan=False, default=_json_default) + "\n", what
    )


def write_text_staged(path: str | Path, text: str, what: str = "output path") -> Path:
    """Write ``text`` through :func:`quadobs.staging.write_staged`: complete or not at all.

    The target is :func:`quadobs.errors.output_target` of ``path`` (a symbolic link is
    written through); a new file gets the usual permissions (``0o666`` less the umask), an
    existing one keeps its own. On any failure the staging file is removed and the target
    is untouched; an ``OSError`` (a full disk) becomes a one-line :class:`QuadobsError`
    naming the path. Returns the target.
    """

    def write(tmp: Path) -> None:
        with open(tmp, "x", newline="") as fh:
            fh.write(text)

    return write_staged(path, write, what)


def fault_summary(
    scenario, completed: int, error: BaseException, recording: str | None = None
) -> dict:
    """The summary of a run stopped by a fault (a physics fault, an output that cannot be written).

    It names the fault and the steps completed, and holds no error or convergence figure:
    a faulty run has none worth reporting.
    """
    return {
        "scenario": scenario.name,
        "source": scenario.source,
        "seed": scenario.seed,
        "physics_rate": scenario.physics_rate,
        "physics_steps": int(completed),
        "duration": completed * scenario.dt,
        "interrupted": False,
        "failed": True,
        "error": str(error),
        "recording": recording,
    }


def write_fault_summary(path, scenario, completed: int, error: BaseException) -> bool:
    """Write :func:`fault_summary` to ``path`` (``None``: nothing); False when it could not be written.

    Used while another error is on its way: a failure to write is swallowed, so the
    original error (a full disk, a physics fault) is the one reported.
    """
    if path is None:
        return False
    try:
        write_json_staged(path, fault_summary(scenario, completed, error))
    except QuadobsError:
        return False
    return True


#: Cost model of one episode, measured with runs of ``ifac2021`` (1 to 200 beacons) on a
#: 2-core machine (``docs/failure-behaviour.md``): seconds per physics step for the world and
#: per estimator, the part growing with the squared number of outputs ``q``, and bytes per
#: recorded row (fixed, per extra estimator, per output). Good to a factor of about 2.
STEP_SECONDS = {"world": 30e-6, "augmented": 10e-6, "other": 85e-6, "per_q2": 7.2e-8}
ROW_BYTES = {"base": 300.0, "per_estimator": 200.0, "per_output": 33.0}
#: Runs expected to take longer (s) or to write more (bytes) get a notice before they start.
NOTICE_SECONDS, NOTICE_BYTES = 60.0, 1e9


def expected_cost(scenario, estimators: list[str], recording: bool) -> dict:
    """Expected ``steps``, wall ``seconds`` and recording ``bytes`` (0 without one) of an episode.

    ``seconds = steps (c_w + sum_e (c_e + c_q q^2))`` and
    ``bytes = steps / record_every (b_0 + b_e (E - 1) + b_q q)`` with the constants of
    :data:`STEP_SECONDS` and :data:`ROW_BYTES`, ``q`` the number of outputs and ``E`` the
    number of estimators.
    """
    steps = int(scenario.steps)
    q = int(scenario.beacons.shape[0]) + (1 if scenario.has_wind else 0)
    c = STEP_SECONDS
    per = sum(
        c["augmented" if name.startswith("augmented") else "other"] + c["per_q2"] * q * q
        for name in estimators
    )
    rows = steps / scenario.record_every if recording else 0
    b = ROW_BYTES
    return {
        "steps": steps,
        "seconds": steps * (c["world"] + per),
        "bytes": rows
        * (b["base"] + b["per_estimator"] * (len(estimators) - 1) + b["per_output"] * q),
    }


def cost_notice(
    scenario, estimators: list[str], recording: bool, runs: int = 1, workers: int = 1
) -> str | None:
    """One line saying what a long or large run will cost, or ``None`` for an ordinary one."""
    cost = expected_cost(scenario, estimators, recording)
    seconds = cost["seconds"] * runs / max(workers, 1)
    size = cost["bytes"] * runs
    if seconds < NOTICE_SECONDS and size < NOTICE_BYTES:
        return None
    what = f"{cost['steps']:,} steps" + (f" x {runs} runs" if runs > 1 else "")
    line = f"quadobs: note: {what}, expected to take about {_duration(seconds)}"
    if size:
        line += f" and to write a recording of about {_bytes(size)} (record_every = {scenario.record_every})"
    return line + "; Ctrl-C stops it and keeps what is done"


def _two_digits(x: float) -> str:
    """``x`` to two significant digits, without an exponent: 330, 11, 1.1, 0.25."""
    return f"{float(f'{x:.2g}'):g}"


def _duration(seconds: float) -> str:
    for unit, span in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= span:
            return f"{_two_digits(seconds / span)} {unit}"
    return f"{_two_digits(seconds)} s"


def _bytes(n: float) -> str:
    for unit, span in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= span:
            return f"{_two_digits(n / span)} {unit}"
    return f"{n:.0f} bytes"


def check_output_folder(folder, known: tuple[str, ...], what: str) -> Path:
    """Check a folder output before any work; returns its resolved path.

    The folder is replaced as a whole (:func:`write_folder_staged`), so an existing one
    may hold only files named in ``known`` (a previous output of the same kind): anything
    else (a user's notes, another run's recording) would be lost, and is refused. A target
    that exists and is not a folder, or whose parent cannot take a new entry, is refused too.
    """
    text = os.fspath(folder)
    if "\0" in text or not text or len(text) > 1024:
        raise QuadobsError(f"{what} {text[:60]!r}: expected a folder name of 1 to 1024 characters")
    try:
        real = Path(os.path.realpath(text))
    except (OSError, RuntimeError) as exc:
        raise QuadobsError(f"{what} {text!r}: cannot be resolved ({exc})") from None
    if os.path.lexists(real):
        if not real.is_dir():
            raise QuadobsError(f"{what} {text!r}: exists and is not a folder")
        try:
            others = sorted(e.name for e in os.scandir(real) if e.name not in known)
        except OSError as exc:
            raise QuadobsError(f"{what} {text!r}: cannot be read ({exc.strerror})") from None
        if others:
            raise QuadobsError(
                f"{what} {text!r}: holds {others[0]!r}, which is not one of its files; "
                "the folder is replaced as a whole, so give a new or an output folder"
            )
    return real


def check_inside_folders(outputs: Mapping[str, Any], folders: Mapping[str, Any]) -> None:
    """Refuse an output file that lies in (or is) a folder output, which is replaced as a whole."""
    for fname, fpath in outputs.items():
        if fpath is None:
            continue
        real = Path(os.path.realpath(os.fspath(fpath)))
        for dname, dpath in folders.items():
            if dpath is None:
                continue
            folder = Path(os.path.realpath(os.fspath(dpath)))
            if real == folder or folder in real.parents:
                raise QuadobsError(
                    f"{fname}: {os.fspath(fpath)!r} lies in the {dname} folder, which is "
                    "replaced as a whole; write it elsewhere"
                )
