"""Low ``ulimit -n`` and ``ulimit -v``, a full disk under ``plot``: one line, status 1, nothing left behind."""

import glob
import resource
import signal
import tempfile
from pathlib import Path

import pytest

from quadobs.cli import main


def _limit(kind, value):
    def apply():
        resource.setrlimit(kind, (value, value))

    return apply


def _fifo_folders() -> set[str]:
    return set(glob.glob(str(Path(tempfile.gettempdir()) / "quadobs-rrd-*")))


def _one_line_fault(proc, timeout=300):
    out, err = proc.communicate(timeout=timeout)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert proc.returncode == 1, err
    assert len(lines) == 1 and lines[0].startswith("quadobs: error:"), err
    return lines[0]


@pytest.mark.parametrize("files", [8, 12])
def test_few_file_descriptors_end_the_run_in_one_line(tmp_path, cli_process, files):
    before = _fifo_folders()
    rrd = tmp_path / "r.rrd"
    proc = cli_process(
        "run", "ifac2021", "--duration", "0.2", "--no-progress", "--out", str(rrd),
        preexec_fn=_limit(resource.RLIMIT_NOFILE, files),
    )  # fmt: skip
    line = _one_line_fault(proc)
    assert "Too many open files" in line and "ulimit -n" in line
    assert _fifo_folders() <= before and list(tmp_path.iterdir()) == []


def test_little_address_space_ends_the_run_in_one_line(tmp_path, cli_process):
    proc = cli_process(
        "run", "ifac2021", "--duration", "0.2", "--no-progress", "--out", str(tmp_path / "r.rrd"),
        preexec_fn=_limit(resource.RLIMIT_AS, 700_000_000),
    )  # fmt: skip
    assert "ulimit -v" in _one_line_fault(proc)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    rrd = tmp_path_factory.mktemp("run") / "r.rrd"
    assert main(["run", "ifac2021", "--duration", "0.3", "--no-progress", "--out", str(rrd)]) == 0
    return rrd


def test_plot_refuses_a_read_only_file_and_its_input(recording, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    ro = tmp_path / "ro.png"
    ro.write_bytes(b"mine")
    ro.chmod(0o444)
    assert main(["plot", str(recording), "--out", str(ro)]) == 2
    assert "read-only" in capsys.readouterr().err and ro.read_bytes() == b"mine"
    before = recording.read_bytes()
    assert main(["plot", str(recording), "--out", str(recording)]) == 2
    assert recording.read_bytes() == before


def test_plot_on_a_full_disk_keeps_the_previous_figure(recording, tmp_path, cli_process):
    pytest.importorskip("matplotlib")
    # a first use of matplotlib on a machine writes its font list (and fc-list its cache): done
    # here, beforehand, so that the full disk meets the figure, the write under test
    from matplotlib import font_manager

    assert font_manager.fontManager.ttflist
    fig = tmp_path / "f.png"
    fig.write_bytes(b"previous")

    def full_disk():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (3000, 3000))

    proc = cli_process("plot", str(recording), "--out", str(fig), preexec_fn=full_disk)
    assert "cannot be written" in _one_line_fault(proc)
    assert fig.read_bytes() == b"previous" and [p.name for p in tmp_path.iterdir()] == ["f.png"]
