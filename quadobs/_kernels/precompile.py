"""Compile a first run's kernels side by side, one process each, before the run starts.

A fresh install has no machine code in Numba's on-disk cache, and compiling the kernels
of an episode one after the other takes most of a first run's start-up (the observer's
block kernel alone several seconds). Each kernel is compiled by its own child process
from the argument types an episode calls it with (:data:`SIGNATURES`, checked against
what an episode actually compiles by the test suite); the children write the cache, and
the run then loads it. On ``c`` cores the wait is that of the slowest kernel rather than
the sum, as long as there are cores for them.

Nothing here is needed for correctness: a kernel that a child could not compile is
compiled by the run itself, as without this module.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterable
from typing import Any

__all__ = ["EPISODE", "SIGNATURES", "compile_side_by_side", "signature", "signatures"]

#: Argument types of each kernel as the testbed calls it: ``f``/``I`` float64/int64 arrays of
#: layout ``A``/``C`` and the dimension given, ``r`` read-only; ``i``, ``f`` alone: scalars. A
#: kernel called with more than one layout lists each signature (a tuple of tuples).
SIGNATURES: dict[str, Any] = {
    # an episode on the block path (the default): the observer, the world's read-out, the excitation monitor
    "quadobs._kernels.observer:augmented_step_block": (
        ("fA2", "fA2", "fC1", "fC1", "IC1", "fC2"),  # rows of a block: strided views of its columns
        (
            "fC2",
            "fC2",
            "fC1",
            "fC1",
            "IC1",
            "fC2",
        ),  # a single row (a sink due one step before a block ends)
    ),
    "quadobs.testbed.worlds._read:read_block": (
        "i",
        "fC2",
        "fC2",
        "fC2",
        "fC1",
        "i",
        "i",
        "fC1",
        "fC2",
        "fC2",
    ),
    "quadobs._kernels.gramian:held_run_terms": (
        "fC2",
        "fC2r",
        "fC3r",
        "fC2r",
        "fC3r",
        "fC4r",
        "fC2",
        "fC2",
        "fC2",
        "fC2",
        "fC2",
    ),
    "quadobs._kernels.observer:range_outputs": ("fC1", "fC1", "f", "fC1", "fC1", "fC1"),
    # the per-step path and the observer's public step
    "quadobs._kernels.observer:augmented_step_record": ("fC1", "fC1", "fC1", "fC1", "IC1", "fC1"),
    "quadobs._kernels.observer:augmented_step": ("fC1", "fC1", "fC1", "fC1", "IC1"),
    "quadobs.testbed.worlds._read:read_step": (
        "i",
        "fC2",
        "fC2",
        "fC1",
        "fC1",
        "fC2",
        "fC1",
        "fC1",
        "fC1",
        "fC2",
        "fC2",
    ),
    # the interface in time (measurements at their own times): the exponentials of each interval
    "quadobs._kernels.held_input:expm_series": ("fC2", "fC2", "fC2", "fC2"),
    # the augmented observer in time: the interval's prediction, the state noise, one range's correction
    "quadobs._kernels.in_time:interval_predict": (
        "fC1",
        "fC2",
        "fC1",
        "f",
        "fC2",
        "fC3",
        "fC2",
        "IC1",
        "IC1",
        "fC2",
        "fC3",
        "fC2",
        "fC1",
    ),
    "quadobs._kernels.in_time:state_noise": ("fC1", "fC3", "fC2", "fC2", "fC2", "fC2", "fC2"),
    "quadobs._kernels.in_time:scalar_correct": (
        "fC1",
        "fC2",
        "fC2",
        "i",
        "f",
        "f",
        "f",
        "fC1",
        "fC2",
    ),
}

#: The kernels of an episode on the default path.
EPISODE = tuple(list(SIGNATURES)[:4])


def signatures(spec: str) -> list[tuple]:
    """The code tuples of a kernel of :data:`SIGNATURES` (one or several)."""
    codes = SIGNATURES[spec]
    return list(codes) if isinstance(codes[0], tuple) else [codes]


def signature(codes: Iterable[str]) -> tuple:
    """Numba types from the codes of :data:`SIGNATURES`."""
    from numba import types

    out: list[Any] = []
    for code in codes:
        if code in ("i", "f"):
            out.append(types.int64 if code == "i" else types.float64)
            continue
        dtype = types.float64 if code[0] == "f" else types.int64
        layout: Any = code[1]  # "C", "F" or "A", as numba.types.Array names them
        out.append(types.Array(dtype, int(code[2]), layout, readonly=code.endswith("r")))
    return tuple(out)


def _compile_one(spec: str) -> None:
    """In a child: compile ``spec`` (``"module:function"``) for its signatures; Numba writes the cache."""
    import importlib

    module, _, name = spec.partition(":")
    dispatcher = getattr(importlib.import_module(module), name)
    for codes in signatures(spec):
        dispatcher.compile(signature(codes))


def compile_side_by_side(kernels: Iterable[str], timeout: float = 600.0) -> list[str]:
    """Compile ``kernels`` (keys of :data:`SIGNATURES`) in parallel child processes.

    Parameters
    ----------
    kernels : iterable of str
        The kernels to compile (others are ignored).
    timeout : float
        Seconds after which a child still compiling is stopped (its kernel is then
        compiled by the caller when first used).

    Returns
    -------
    list of str
        The kernels whose child ended with status 0.

    A ``KeyboardInterrupt`` while waiting stops every child before it goes on.
    """
    specs = [k for k in kernels if k in SIGNATURES]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    code = "import sys; from quadobs._kernels.precompile import _compile_one; _compile_one(sys.argv[1])"
    procs = {
        spec: subprocess.Popen(
            [sys.executable, "-c", code, spec],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for spec in specs
    }
    deadline = time.monotonic() + timeout
    done = []
    try:
        for spec, proc in procs.items():
            try:
                if proc.wait(timeout=max(deadline - time.monotonic(), 0.0)) == 0:
                    done.append(spec)
            except subprocess.TimeoutExpired:
                pass
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return done
