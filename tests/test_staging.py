"""The one staged writer: a file or a folder complete or not at all, the previous one kept on failure."""

import errno
import os
import stat

import pytest

from quadobs.errors import QuadobsError
from quadobs.staging import write_folder_staged, write_staged


def test_a_file_is_replaced_whole_and_keeps_its_permissions(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    os.chmod(target, 0o640)
    write_staged(target, lambda tmp: tmp.write_text("new"))
    assert target.read_text() == "new"
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_failed_write_leaves_the_previous_file_and_no_staging_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")

    def full_disk(tmp):
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(QuadobsError, match=r"^out '.*out.txt': cannot be written \(No space"):
        write_staged(target, full_disk, "out")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_folder_is_replaced_as_a_whole(tmp_path):
    folder = tmp_path / "camp"
    folder.mkdir()
    (folder / "old.json").write_text("{}")

    def write(tmp):
        (tmp / "a.json").write_text("1")
        (tmp / "b.json").write_text("2")

    allowed = {"old.json", "a.json", "b.json"}  # names the writer owns
    assert write_folder_staged(folder, write, allowed=allowed) == folder.resolve()
    assert sorted(p.name for p in folder.iterdir()) == ["a.json", "b.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camp"]

    def fails(tmp):
        (tmp / "a.json").write_text("3")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(QuadobsError, match="No space left on device"):
        write_folder_staged(folder, fails, "out_dir")
    assert (folder / "a.json").read_text() == "1" and (folder / "b.json").read_text() == "2"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camp"]


def test_a_folder_target_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "camp").write_text("not a folder")
    with pytest.raises(QuadobsError, match="exists and is not a folder"):
        write_folder_staged(tmp_path / "camp", lambda tmp: None)


def test_a_folder_holding_other_names_is_not_replaced(tmp_path):
    folder = tmp_path / "camp"
    folder.mkdir()
    (folder / "mine.txt").write_text("kept")
    with pytest.raises(QuadobsError, match="holds 'mine.txt'"):
        write_folder_staged(folder, lambda tmp: (tmp / "a.json").write_text("1"), "out", {"a.json"})
    with pytest.raises(QuadobsError, match="holds 'mine.txt'"):
        write_folder_staged(folder, lambda tmp: (tmp / "a.json").write_text("1"), "out")
    assert sorted(p.name for p in folder.iterdir()) == ["mine.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camp"]
