"""The kernels' on-disk cache heals: unreadable entries removed and recompiled, an unwritable cache bypassed."""

import hashlib
import json
import os
import pickle
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from quadobs._kernels.cache import MANIFEST, cache_folders, heal, writable
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
    # the entry of the kernel as it is now (named by its line), not those an older source left
    from quadobs._kernels import observer

    line = observer.augmented_step_block.py_func.__code__.co_firstlineno
    files = sorted(folder.glob(f"observer.augmented_step_block-{line}.*"))
    if not any(f.suffix == ".nbi" for f in files):
        pytest.skip("no on-disk cache of the kernel")
    for f in files:
        shutil.copy2(f, tmp_path / f.name)
    return tmp_path


def test_an_intact_cache_is_left_alone(cache_copy):
    before = sorted(p.name for p in cache_copy.iterdir())
    assert heal([cache_copy]) == []
    assert sorted(p.name for p in cache_copy.iterdir() if p.name != MANIFEST) == before
    recorded = json.loads((cache_copy / MANIFEST).read_text())["files"]
    assert sorted(recorded) == before
    for name, record in recorded.items():
        data = (cache_copy / name).read_bytes()
        assert record["sha256"] == hashlib.sha256(data).hexdigest()
        assert record["size"] == len(data) and record["inode"] == os.stat(cache_copy / name).st_ino
    assert heal([cache_copy]) == []  # read again: the same records
    assert json.loads((cache_copy / MANIFEST).read_text())["files"] == recorded


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


def _flip_middle(path: Path, count: int = 64) -> None:
    """Invert ``count`` bytes in the middle of ``path``, in place (the same file)."""
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + count] = bytes(b ^ 0xFF for b in data[middle : middle + count])
    with open(path, "r+b") as fh:
        fh.write(data)


def test_bytes_changed_inside_the_machine_code_are_detected(cache_copy):
    """Damage that still unpickles: caught by the sha256 recorded when the entry was read intact."""
    assert heal([cache_copy]) == []  # recorded
    index = next(cache_copy.glob("*.nbi"))
    data = max(cache_copy.glob("*.nbc"), key=lambda p: p.stat().st_size)
    _flip_middle(data)
    pickle.loads(data.read_bytes())  # the damage is not in the pickle's framing
    lines = heal([cache_copy])
    assert len(lines) == 1 and "\n" not in lines[0], lines
    assert str(index) in lines[0] and "damaged" in lines[0] and data.name in lines[0]
    assert "sha256" in lines[0] and "compiled again" in lines[0]
    assert sorted(p.name for p in cache_copy.iterdir()) == [MANIFEST]
    assert json.loads((cache_copy / MANIFEST).read_text())["files"] == {}


def test_a_file_written_whole_again_is_recorded_afresh(cache_copy):
    """Numba rewrites a file under a temporary name and renames it (a new signature, a new source):
    not damage; the new bytes are recorded."""
    assert heal([cache_copy]) == []
    data = sorted(cache_copy.glob("*.nbc"))[0]
    other = pickle.dumps(pickle.loads(data.read_bytes()), protocol=2)
    assert hashlib.sha256(other).digest() != hashlib.sha256(data.read_bytes()).digest()
    staging = data.with_name(data.name + ".tmp.x")
    staging.write_bytes(other)
    os.replace(staging, data)
    assert heal([cache_copy]) == []
    record = json.loads((cache_copy / MANIFEST).read_text())["files"][data.name]
    assert record["sha256"] == hashlib.sha256(other).hexdigest()


@pytest.mark.parametrize("manifest", [b"", b"{not json", b'{"files": [1, 2]}', b"[" * 100000])
def test_an_unusable_manifest_is_written_anew(cache_copy, manifest):
    (cache_copy / MANIFEST).write_bytes(manifest)
    assert heal([cache_copy]) == []
    recorded = json.loads((cache_copy / MANIFEST).read_text())["files"]
    assert sorted(recorded) == sorted(p.name for p in cache_copy.iterdir() if p.name != MANIFEST)


def test_a_fifo_in_the_cache_is_removed_without_blocking(cache_copy):
    index = next(cache_copy.glob("*.nbi"))
    index.unlink()
    os.mkfifo(index)
    out: list = []
    reader = threading.Thread(target=lambda: out.append(heal([cache_copy])), daemon=True)
    reader.start()
    reader.join(30)
    assert out, "heal blocked on a FIFO"
    (line,) = out[0]
    assert "not a regular file" in line and not index.exists()


KERNEL_MODULE = """
import numpy as np
from numba import njit

@njit(cache=True)
def f(x):
    s = 0.0
    for i in range(x.shape[0]):
        s += np.sin(x[i]) * x[i] ** 2 + np.sqrt(abs(x[i]))
    return s
"""


def test_a_kernel_damaged_inside_its_machine_code_is_compiled_again(tmp_path):
    """A kernel of its own, cached; bytes flipped in the middle of its machine code: the next
    process is told in one line, compiles it again and gets the same number (Numba alone
    aborted, raised or returned the number, depending on where the bytes were changed)."""
    (tmp_path / "kmod.py").write_text(KERNEL_MODULE)
    code = (
        "import sys, numpy as np; from quadobs._kernels.cache import heal; "
        "[print(line, file=sys.stderr) for line in heal([sys.argv[1]])]; "
        "import kmod; print(repr(kmod.f(np.arange(10.0))))"
    )

    def child():
        return subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / "__pycache__")],
            capture_output=True,
            text=True,
            cwd=tmp_path,
            env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)])),
            timeout=300,
        )

    first = child()  # compiles and caches
    assert first.returncode == 0 and first.stderr == "", first.stderr
    assert child().stdout == first.stdout  # loads the cache, and records it
    (data,) = (tmp_path / "__pycache__").glob("kmod.f-*.nbc")
    _flip_middle(data)
    healed = child()
    notes = healed.stderr.splitlines()
    assert healed.returncode == 0 and len(notes) == 1 and "damaged" in notes[0], healed.stderr
    assert healed.stdout == first.stdout
    assert child().stderr == ""  # compiled again, cached and recorded: intact


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
