"""The kernels' on-disk cache heals: unreadable entries removed and recompiled, an unwritable cache bypassed."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from quadobs._kernels.cache import cache_folders, heal, writable
from quadobs.cli import AUGMENTED_KERNELS, EPISODE_KERNELS

ROOT = Path(__file__).resolve().parents[1]
KERNEL = "quadobs._kernels.observer:augmented_step_block"


@pytest.fixture
def cache_copy(tmp_path):
    """A copy of the observer's block kernel's cache entry (index and data files), in ``tmp_path``."""
    from quadobs._kernels import cold_kernels
    from quadobs._kernels.precompile import compile_side_by_side

    if cold_kernels([KERNEL]):
        compile_side_by_side([KERNEL])
    (folder,) = cache_folders([KERNEL])
    files = sorted(folder.glob("observer.augmented_step_block-*"))
    if not any(f.suffix == ".nbi" for f in files):
        pytest.skip("no on-disk cache of the kernel")
    for f in files:
        shutil.copy2(f, tmp_path / f.name)
    return tmp_path


def test_an_intact_cache_is_left_alone(cache_copy):
    before = sorted(p.name for p in cache_copy.iterdir())
    assert heal([cache_copy]) == []
    assert sorted(p.name for p in cache_copy.iterdir()) == before


@pytest.mark.parametrize("damage", ["random data file", "empty index", "truncated data file"])
def test_an_unreadable_entry_is_reported_in_one_line_and_removed(cache_copy, damage):
    index = next(cache_copy.glob("*.nbi"))
    data = sorted(cache_copy.glob("*.nbc"))[0]
    if damage == "random data file":
        with open(data, "r+b") as fh:
            fh.write(bytes(range(256)) * 4)
    elif damage == "empty index":
        index.write_bytes(b"")
    else:
        data.write_bytes(data.read_bytes()[:100])
    lines = heal([cache_copy])
    assert len(lines) == 1 and "\n" not in lines[0]
    assert str(index) in lines[0] and "compiled again" in lines[0]
    assert list(cache_copy.iterdir()) == []


def test_the_episode_kernels_cache_lives_in_the_package_or_numba_cache_dir():
    folders = cache_folders(EPISODE_KERNELS + AUGMENTED_KERNELS)
    assert folders and all(
        f.name == "__pycache__" or "NUMBA_CACHE_DIR" in os.environ for f in folders
    )


def test_a_full_cache_disk_is_detected(tmp_path):
    """A file size limit below the probe (as a full disk): the reason, in a child process."""
    code = (
        "import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
        "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096)); "
        "from quadobs._kernels.cache import writable; print(writable(sys.argv[1]))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
        timeout=60,
    )
    assert out.stdout.strip() == "File too large", out.stderr
    assert writable(tmp_path) is None and list(tmp_path.iterdir()) == []


def test_bypass_turns_the_cache_off_for_the_loaded_kernels():
    code = (
        "import quadobs._kernels.observer as o; from quadobs._kernels.cache import bypass; "
        "from numba.core.caching import NullCache; n = bypass(); "
        "print(n > 3, isinstance(o.augmented_step_block._cache, NullCache))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
        timeout=120,
    )
    assert out.stdout.split() == ["True", "True"], out.stderr


@pytest.mark.slow
def test_compile_heals_a_corrupt_entry_and_reports_what_it_read_back(tmp_path, cli_process):
    """A cache of its own (NUMBA_CACHE_DIR), compiled, one data file damaged: ``quadobs compile`` says
    so in one line, compiles that kernel again and counts every kernel as cached (minutes)."""
    env = {"NUMBA_CACHE_DIR": str(tmp_path)}
    proc = cli_process("compile", env=env)
    out, err = proc.communicate(timeout=1200)
    assert proc.returncode == 0 and "7 of 7 in the cache" in out, err
    (data,) = [p for p in tmp_path.rglob("observer.range_outputs-*.1.nbc")]
    with open(data, "r+b") as fh:
        fh.write(bytes(range(256)) * 4)
    proc = cli_process("compile", env=env)
    out, err = proc.communicate(timeout=1200)
    notes = [ln for ln in err.splitlines() if ln.startswith("quadobs: note: kernel cache entry")]
    assert proc.returncode == 0 and len(notes) == 1 and "range_outputs" in notes[0], err
    assert "1 of 1 kernels compiled" in out and "7 of 7 in the cache" in out, out
