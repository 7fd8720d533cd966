"""The recording's layout at the scene's scale: sizes follow the beacons' extent, the views are built."""

import pytest

from quadobs.testbed.episode_log import _eye, default_blueprint, scene_size
from quadobs.testbed.scenario import load_scenario
from quadobs.testbed.sinks import EpisodeFrame


@pytest.mark.parametrize(
    "name, size", [("quadrotor-uwb", 6.0), ("beacons", 40.0), ("ifac2021", 30.0)]
)
def test_the_scene_size_is_the_beacons_extent(name, size):
    frame = EpisodeFrame.of(load_scenario(name))
    assert scene_size(frame) == pytest.approx(size)
    assert default_blueprint(frame, ["augmented"]) is not None


def test_the_eye_looks_at_the_room_from_a_room_away():
    frame = EpisodeFrame.of(load_scenario("quadrotor-uwb"))
    assert _eye(frame) is not None
    assert _eye(EpisodeFrame.of(load_scenario("ifac2021"))) is None  # a single beacon


def _views(container):
    for item in container.contents:
        yield from _views(item) if hasattr(item, "kind") else [item]


def _ranges(view, name, field):
    return getattr(view.properties[name], field).as_arrow_array().to_pylist()


def test_trails_and_plots_cover_the_run_on_either_timeline():
    blueprint = default_blueprint(EpisodeFrame.of(load_scenario("quadrotor-uwb")), ["augmented"])
    views = list(_views(blueprint.root_container))
    (three_d,) = [v for v in views if v.class_identifier == "3D"]
    plots = [v for v in views if v.class_identifier == "TimeSeries"]
    assert len(plots) >= 4
    # the viewer opens a recording on its "step" timeline: the trail from the start to the cursor
    trail = _ranges(three_d, "VisibleTimeRanges", "ranges")
    assert {r["timeline"] for r in trail} == {"sim_time", "step"}
    assert all(r["range"] == {"start": None, "end": 0} for r in trail)
    for plot in plots:  # data and x axis over the whole run (None: unbounded)
        data = _ranges(plot, "VisibleTimeRanges", "ranges")
        assert {r["timeline"] for r in data} == {"sim_time", "step"}
        assert all(r["range"] == {"start": None, "end": None} for r in data)
        assert _ranges(plot, "TimeAxis", "view_range") == [{"start": None, "end": None}]
