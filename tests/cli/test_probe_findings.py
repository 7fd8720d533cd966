"""What the re-run hostile probe found (``tests/reliability/test_probe.py``), each with a fast test."""

import errno
import os
import threading

import pytest

from quadobs.errors import QuadobsError, RunFault
from quadobs.staging import write_folder_staged
from quadobs.testbed.scenario import load_scenario


def test_a_scenario_file_that_is_a_fifo_is_refused_without_waiting(tmp_path):
    """Opened to be checked, a FIFO with no writer blocked ``quadobs show`` for ever."""
    fifo = tmp_path / "s.toml"
    os.mkfifo(fifo)
    errors: list = []

    def load():
        try:
            load_scenario(fifo)
        except QuadobsError as exc:
            errors.append(str(exc))

    reader = threading.Thread(target=load, daemon=True)
    reader.start()
    reader.join(30)
    assert errors and "not a regular file" in errors[0], "the FIFO blocked or was accepted"


def test_a_folder_that_cannot_be_written_is_a_fault_of_the_run(tmp_path):
    """A full disk while a folder is written is status 1 (a fault), not 2 (bad input)."""

    def full_disk(folder):
        (folder / "a.json").write_text("{}")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(
        RunFault, match=r"No space left on device\); the previous folder is unchanged"
    ):
        write_folder_staged(tmp_path / "out", full_disk, "out_dir")
    assert list(tmp_path.iterdir()) == []
