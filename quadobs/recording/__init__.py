"""The recording layer: buffered columns to rerun ``.rrd`` files, reading back (imports rerun)."""

from quadobs.recording.reader import list_entities, read_series, read_text_log
from quadobs.recording.recorder import Recorder, Series, check_writable

__all__ = [
    "Recorder",
    "Series",
    "check_writable",
    "list_entities",
    "read_series",
    "read_text_log",
]
