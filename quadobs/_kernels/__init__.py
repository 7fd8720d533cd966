"""The compiled (Numba) kernels of the estimators, the Gramian and the zonotopes.

The kernels are compiled with ``cache=True``: the first run compiles them and writes the
machine code beside the modules (or under ``NUMBA_CACHE_DIR``); later runs load it.
:func:`cold_kernels` tells, without compiling anything, which kernels a first run would
compile, so that an application can say so before the silence;
:mod:`quadobs._kernels.precompile` compiles them side by side in child processes
(``quadobs compile``, run by the installation command of the README, or by a first run).
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable

__all__ = ["cold_kernels"]


def cold_kernels(kernels: Iterable[str]) -> list[str]:
    """The kernels among ``kernels`` that have no compiled code in Numba's on-disk cache.

    Parameters
    ----------
    kernels : iterable of str
        Kernels named ``"module:function"``, e.g. ``"quadobs._kernels.observer:augmented_step"``;
        each must be a Numba dispatcher compiled with ``cache=True``.

    Returns
    -------
    list of str
        Those whose cache index is missing, empty, or stale (written for another version
        of the source file): calling them compiles first. Reading an index loads a small
        file and compiles nothing. A kernel whose cache cannot be inspected (JIT disabled,
        a Numba without this cache layout) counts as cached.

    Examples
    --------
    >>> cold_kernels([]) == []
    True
    """
    cold = []
    for spec in kernels:
        module, _, name = spec.partition(":")
        dispatcher = getattr(
            importlib.import_module(module), name
        )  # a failed import (Ctrl-C, say) goes on
        try:
            index = dispatcher._cache._cache_file._load_index()
        except Exception:  # no cache to inspect: say nothing rather than guess
            continue
        if not index:
            cold.append(spec)
    return cold
