"""Reading per-step series back from an ``.rrd`` file (``rerun.chunk.RrdReader``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader

from quadobs.errors import QuadobsError

__all__ = ["list_entities", "read_series", "read_text_log"]

_COMPONENTS = {
    "Scalars:scalars": "scalars",
    "Points3D:positions": "points3d",
    "Transform3D:translation": "translation",
}


def _chunks(path: str | Path):
    path = Path(path)
    if not path.is_file():
        raise QuadobsError(f"recording {str(path)!r}: no such file")
    return RrdReader(path).stream()


def list_entities(path: str | Path) -> list[str]:
    """Entity paths holding temporal data in the recording."""
    return sorted({str(ch.entity_path) for ch in _chunks(path) if not ch.is_static})


def read_series(path: str | Path, entity: str) -> dict[str, np.ndarray]:
    """Temporal values of ``entity``, ordered by step.

    Returns
    -------
    dict
        ``step`` (T,) int, ``sim_time`` (T,) float seconds, ``values`` (T, width).

    Raises
    ------
    QuadobsError
        If the file does not exist or has no temporal data at ``entity``.
    """
    entity = "/" + entity.strip("/")
    steps, times, values = [], [], []
    for ch in _chunks(path):
        if ch.is_static or str(ch.entity_path) != entity:
            continue
        rb = ch.to_record_batch()
        names = rb.schema.names
        comp = next((c for c in _COMPONENTS if c in names), None)
        if comp is None or "step" not in names:
            continue
        steps.append(np.asarray(rb.column("step").to_numpy(zero_copy_only=False), dtype=np.int64))
        times.append(rb.column("sim_time").cast("int64").to_numpy(zero_copy_only=False) * 1e-9)
        col = rb.column(comp).to_pylist()
        values.append(np.array([np.ravel(v) for v in col], dtype=float))
    if not steps:
        raise QuadobsError(f"recording {str(path)!r}: no temporal data at entity {entity!r}")
    step = np.concatenate(steps)
    order = np.argsort(step, kind="stable")
    return {
        "step": step[order],
        "sim_time": np.concatenate(times)[order],
        "values": np.concatenate(values)[order],
    }


def read_text_log(path: str | Path, entity: str) -> list[tuple[int, float, str, str]]:
    """``(step, sim_time, level, text)`` of the text messages logged at ``entity``."""
    entity = "/" + entity.strip("/")
    out = []
    for ch in _chunks(path):
        if ch.is_static or str(ch.entity_path) != entity:
            continue
        rb = ch.to_record_batch()
        if "TextLog:text" not in rb.schema.names:
            continue
        st = rb.column("step").to_pylist()
        tm = rb.column("sim_time").cast("int64").to_pylist()
        tx = rb.column("TextLog:text").to_pylist()
        lv = (
            rb.column("TextLog:level").to_pylist()
            if "TextLog:level" in rb.schema.names
            else [[None]] * len(st)
        )
        for s, t, x, lvl in zip(st, tm, tx, lv):
            out.append((int(s), t * 1e-9, (lvl or [None])[0], x[0]))
    return sorted(out)
