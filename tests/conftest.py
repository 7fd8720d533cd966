import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings as hypothesis_settings

ROOT = Path(__file__).resolve().parents[1]

# The property-based tests draw the same examples on every run, as every other random test
# takes a fixed seed: a failure reproduces, and a run does not fail by the luck of its draws.
# HYPOTHESIS_PROFILE=explore draws new examples each run (to look for new failures).
hypothesis_settings.register_profile("fixed", derandomize=True)
hypothesis_settings.register_profile("explore", derandomize=False)
hypothesis_settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fixed"))

# A test run started in the background of a non-interactive shell inherits SIGINT ignored,
# and so would every child it starts: the tests of Ctrl-C need it as a terminal gives it.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def rng():
    return np.random.default_rng(20211)


@pytest.fixture
def cli_process():
    """Start ``python -m quadobs.cli ARGS...`` as child processes, killed when the test ends.

    ``cli_process(*args, module="quadobs.cli", path=(), env=None, **popen_kw)`` returns the
    ``subprocess.Popen`` of ``python -m MODULE ARGS...``, run from the repository root with
    ``path`` and this checkout on ``PYTHONPATH`` and the variables ``env`` added to this
    process's environment, stdout and stderr piped as text unless ``popen_kw`` says
    otherwise. Every child still running when the test ends, passed or failed, is killed
    (SIGKILL) and reaped, so none outlives its test.
    """
    started: list[subprocess.Popen] = []

    def start(
        *args: str, module: str = "quadobs.cli", path=(), env=None, **popen_kw
    ) -> subprocess.Popen:
        pythonpath = os.pathsep.join([*map(str, path), str(ROOT)])
        kw = dict(
            cwd=ROOT,
            env=dict(os.environ, PYTHONPATH=pythonpath, **(env or {})),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        kw.update(popen_kw)
        proc = subprocess.Popen([sys.executable, "-m", module, *args], **kw)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        try:
            proc.communicate(timeout=60)
        except (
            subprocess.TimeoutExpired,
            ValueError,
        ):  # pragma: no cover - a child that cannot be reaped
            pass


def random_nilpotent(rng, n, index=None):
    """A random nilpotent matrix ``T N T^-1`` of nilpotency index ``index`` (default ``n``).

    ``N`` is block diagonal with shift (Jordan) blocks of sizes at most ``index``, one of
    them of size ``index``, and random nonzero superdiagonal entries.
    """
    index = n if index is None else index
    sizes = [index]
    while sum(sizes) < n:
        sizes.append(int(rng.integers(1, min(index, n - sum(sizes)) + 1)))
    N = np.zeros((n, n))
    start = 0
    for size in sizes:
        for i in range(size - 1):
            N[start + i, start + i + 1] = rng.uniform(0.5, 2.0) * rng.choice([-1, 1])
        start += size
    T = rng.standard_normal((n, n)) + n * np.eye(n)
    return T @ N @ np.linalg.inv(T)


def random_system(rng, n, p, q, linear=True):
    from quadobs import QuadraticSystem

    A = rng.standard_normal((n, n)) / np.sqrt(n)
    B = rng.standard_normal((n, p))
    C = rng.standard_normal((q, n, n))
    C = C + C.transpose(0, 2, 1)
    d = rng.standard_normal((q, n)) if linear else None
    return QuadraticSystem(A, B, C, d)


def call_main(argv):
    """``quadobs.cli.main(argv)`` in this process: the exit status, stdout and stderr."""
    import io
    from contextlib import redirect_stderr, redirect_stdout

    from quadobs.cli import main

    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's own usage errors
            code = exc.code
    return code, out.getvalue(), err.getvalue()
