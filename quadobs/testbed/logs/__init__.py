"""Logged range data: the open log format (a folder of CSV files) and the built-in logs.

:mod:`quadobs.testbed.logs.format` reads and writes the format (:class:`RangeLog`);
:mod:`quadobs.testbed.logs.plaza` loads the CMU Plaza1 and Plaza2 range-only logs
[DJUGASH2006] from the files bundled with ``gtsam`` (the ``data`` extra).
"""

from quadobs.testbed.logs.format import LOG_FILES, RangeLog, read_log, write_log
from quadobs.testbed.logs.plaza import BUILTIN_LOGS, load_builtin, open_log

__all__ = [
    "BUILTIN_LOGS",
    "LOG_FILES",
    "RangeLog",
    "load_builtin",
    "open_log",
    "read_log",
    "write_log",
]
