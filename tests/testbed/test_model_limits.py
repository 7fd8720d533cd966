"""MJCF files checked before MuJoCo parses them; MuJoCo's multi-line errors on one line."""

import time

import pytest

from quadobs import QuadobsError
from quadobs.testbed.worlds.model import MAX_BODIES, load_vehicle_model


def test_a_model_of_100000_bodies_is_refused_before_mujoco_parses_it(tmp_path):
    path = tmp_path / "many.xml"
    path.write_text(
        "<mujoco><worldbody>" + "<body><geom size='.1'/></body>" * 100_000 + "</worldbody></mujoco>"
    )
    t0 = time.perf_counter()
    with pytest.raises(QuadobsError, match=f"100,000 bodies; .* at most {MAX_BODIES:,}"):
        load_vehicle_model([[0.0, 0.0]], path=path)
    assert time.perf_counter() - t0 < 1.0


def test_mujocos_multi_line_errors_become_one_line(tmp_path):
    path = tmp_path / "bad.xml"
    path.write_text("<mujoco>\n<worldbody>\n<body>\n<nosuch/>\n</body>\n</worldbody>\n</mujoco>\n")
    with pytest.raises(QuadobsError) as info:
        load_vehicle_model([[0.0, 0.0]], path=path)
    message = str(info.value)
    assert "\n" not in message and "bad.xml" in message and "nosuch" in message
