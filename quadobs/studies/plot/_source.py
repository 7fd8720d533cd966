"""What a figure is drawn from: a run's ``.rrd``, a campaign folder or the le2013 recording.

The kind is told by the recording's entities (:mod:`quadobs.testbed.episode_log`,
:mod:`quadobs.studies.campaign`, :mod:`quadobs.studies.le2013.recording`), never by the
file name. A file that is not a rerun recording, or a recording with none of these
layouts, is refused with a one-line :class:`~quadobs.errors.QuadobsError`.
"""

from __future__ import annotations

import re
import warnings
from contextlib import contextmanager
from functools import cached_property
from pathlib import Path

import numpy as np

from quadobs.errors import QuadobsError
from quadobs.recording.reader import list_entities, read_series

__all__ = ["Source", "open_source"]

KINDS = ("run", "campaign", "le2013")


def _one_line(exc: BaseException) -> str:
    """The last line of the reader's message, without its ``Failed to read RRD file at PATH:`` prefix."""
    text = str(exc).strip().splitlines()
    line = text[-1].strip() if text else type(exc).__name__
    return re.sub(r"^Failed to read RRD file at .*?: ", "", line)


@contextmanager
def _reading(path: Path, what: str = "recording"):
    """Turn the reader's failures into one line naming ``path``, and silence its warnings (a file without footer)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            yield
        except QuadobsError:
            raise
        except Exception as exc:
            raise QuadobsError(
                f"{what} {str(path)!r}: cannot be read, damaged or not a rerun recording ({_one_line(exc)})"
            ) from None


class Source:
    """A recording opened for plotting: its ``kind`` (``run``, ``campaign``, ``le2013``) and cached series.

    Parameters
    ----------
    path : Path
        The ``.rrd`` file (for a campaign, its ``statistics.rrd``).
    kind : str
    folder : Path, optional
        The campaign folder (``runs.parquet`` beside ``statistics.rrd``).
    """

    def __init__(
        self, path: Path, kind: str, entities: list[str], folder: Path | None = None
    ) -> None:
        self.path, self.kind, self.entities, self.folder = path, kind, entities, folder
        self._cache: dict[str, dict[str, np.ndarray]] = {}

    def has(self, entity: str) -> bool:
        return "/" + entity.strip("/") in self.entities

    def series(self, entity: str) -> dict[str, np.ndarray]:
        """``step``, ``sim_time`` (s) and ``values (T, width)`` of ``entity`` (see :func:`read_series`)."""
        if entity not in self._cache:
            with _reading(self.path):
                self._cache[entity] = read_series(self.path, entity)
        return self._cache[entity]

    def names(self, pattern: str) -> list[str]:
        """The ``<x>`` of the entities matching ``pattern`` (a path with one ``<x>``), in recording order."""
        rx = re.compile(
            "^/" + re.escape(pattern.strip("/")).replace(re.escape("<x>"), "([^/]+)") + "$"
        )
        out = []
        for e in self.entities:
            m = rx.match(e)
            if m and m.group(1) not in out:
                out.append(m.group(1))
        return out

    @cached_property
    def estimators(self) -> list[str]:
        """Estimator (or method) names of the recording, sorted."""
        pattern = {
            "run": "errors/<x>/position/norm",
            "campaign": "stats/<x>/position/rmse",
            "le2013": "le2013/width/<x>",
        }[self.kind]
        return sorted(self.names(pattern))

    def select(self, names) -> None:
        """Keep only the estimators ``names`` (in that order) in every panel; refused in one line
        where one is not in the recording, naming those that are."""
        known = self.estimators
        names = list(dict.fromkeys(names))
        unknown = [n for n in names if n not in known]
        if unknown or not names:
            raise QuadobsError(
                f"--estimators: {', '.join(unknown) or '(none)'} not in {self.path.name} "
                f"(its estimators: {', '.join(known)})"
            )
        self.__dict__["estimators"] = names  # the cached property's value

    def strips(self, entity: str) -> dict[int, list[np.ndarray]]:
        """Line strips (``LineStrips2D``) or points (``Points2D``) logged at ``entity``, per ``step``."""
        from rerun.chunk import RrdReader

        entity = "/" + entity.strip("/")
        out: dict[int, list[np.ndarray]] = {}
        with _reading(self.path):
            for ch in RrdReader(self.path).stream():
                if ch.is_static or str(ch.entity_path) != entity:
                    continue
                rb = ch.to_record_batch()
                comp = next(
                    (
                        c
                        for c in ("LineStrips2D:strips", "Points2D:positions")
                        if c in rb.schema.names
                    ),
                    None,
                )
                if comp is None or "step" not in rb.schema.names:
                    continue
                for s, v in zip(rb.column("step").to_pylist(), rb.column(comp).to_pylist()):
                    out[int(s)] = (
                        [np.asarray(x, dtype=float) for x in v]
                        if comp.startswith("Line")
                        else [np.asarray(v, dtype=float)]
                    )
        if not out:
            raise QuadobsError(f"recording {str(self.path)!r}: no sets at entity {entity!r}")
        return out

    def static_points(self, entity: str) -> np.ndarray | None:
        """The static ``Points3D`` logged at ``entity`` (e.g. the beacons), or None."""
        from rerun.chunk import RrdReader

        entity = "/" + entity.strip("/")
        with _reading(self.path):
            for ch in RrdReader(self.path).stream():
                if ch.is_static and str(ch.entity_path) == entity:
                    rb = ch.to_record_batch()
                    if "Points3D:positions" in rb.schema.names:
                        return np.asarray(
                            rb.column("Points3D:positions").to_pylist()[-1], dtype=float
                        )
        return None

    def runs_table(self) -> dict[str, list]:
        """The campaign's ``runs.parquet`` as columns."""
        path = (self.folder or self.path.parent) / "runs.parquet"
        if not path.is_file():
            raise QuadobsError(
                f"campaign {str(path.parent)!r}: no runs.parquet beside statistics.rrd"
            )
        import pyarrow.parquet as pq

        try:
            return pq.read_table(path).to_pydict()
        except Exception as exc:
            raise QuadobsError(
                f"campaign table {str(path)!r}: cannot be read ({_one_line(exc)})"
            ) from None


def _kind_of(entities: list[str]) -> str | None:
    if any(e.startswith("/le2013/") for e in entities):
        return "le2013"
    if any(e.startswith("/stats/") and e.endswith("/position/rmse") for e in entities):
        return "campaign"
    if "/world/truth/path" in entities and any(e.startswith("/errors/") for e in entities):
        return "run"
    return None


def open_source(path: str | Path) -> Source:
    """Open a run's ``.rrd``, a campaign folder (or its ``statistics.rrd``) or the le2013 ``.rrd``.

    Raises
    ------
    QuadobsError
        If ``path`` does not exist, is not a rerun recording, or holds none of the layouts.
    """
    path = Path(path)
    folder = None
    if path.is_dir():
        folder, path = path, path / "statistics.rrd"
        if not path.is_file():
            raise QuadobsError(
                f"input {str(folder)!r}: a folder without statistics.rrd is not a campaign folder"
            )
    elif not path.exists():
        raise QuadobsError(f"input {str(path)!r}: no such file or folder")
    with _reading(path, "input"):
        entities = list_entities(path)
    kind = _kind_of(entities)
    if kind is None:
        raise QuadobsError(f"input {str(path)!r}: not a quadobs run, campaign or le2013 recording")
    if kind == "campaign" and folder is None:
        folder = path.parent
    return Source(path, kind, entities, folder)
