"""Library diagnostics through logging: nothing configured on import; the command line's -v and -q."""

import logging
import subprocess
import sys

from quadobs.cli import main


def test_importing_the_package_configures_no_logging():
    code = (
        "import logging, quadobs, quadobs.cli, quadobs.studies.campaign, quadobs.testbed.outputs\n"
        "names = [n for n in logging.root.manager.loggerDict if n.startswith('quadobs')]\n"
        "loggers = [logging.getLogger(n) for n in names]\n"
        "assert names and all(not g.handlers and g.level == logging.NOTSET for g in loggers), names\n"
        "assert not logging.root.handlers\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_verbose_shows_the_library_progress_and_quiet_hides_warnings(tmp_path, capsys):
    args = ["campaign", "ifac2021-noisy", "--runs", "1", "--duration", "0.2", "--workers", "0"]
    args += ["--estimators", "augmented", "--no-progress"]
    assert main(["-v", *args, "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "quadobs: info: campaign ifac2021-noisy: 1 runs to do, 0 kept" in err.splitlines()
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    assert "quadobs: info:" not in capsys.readouterr().err  # default: warnings and notices only
    # the command's handler is gone after it: the library's loggers are as they were
    assert not logging.getLogger("quadobs").handlers
    assert logging.getLogger("quadobs").level == logging.NOTSET


def test_quiet_keeps_errors(capsys):
    assert main(["-q", "run", "no-such-scenario"]) == 2
    assert "unknown name 'no-such-scenario'" in capsys.readouterr().err
