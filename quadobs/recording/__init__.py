"""The recording layer: buffered columns to rerun ``.rrd`` files, the default blueprint, reading back (imports rerun)."""

from quadobs.recording.episode import EpisodeLog, default_blueprint
from quadobs.recording.reader import list_entities, read_series, read_text_log
from quadobs.recording.recorder import Recorder, Series, check_writable

__all__ = [
    "EpisodeLog",
    "Recorder",
    "Series",
    "check_writable",
    "default_blueprint",
    "list_entities",
    "read_series",
    "read_text_log",
]
