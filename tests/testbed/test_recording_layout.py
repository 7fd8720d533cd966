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
