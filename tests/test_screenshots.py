"""sims/screenshots.py: each world's recording in rerun's web viewer under headless Chromium."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "sims" / "screenshots.py"


def _run(args, tmp_path, path=None):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    if path is not None:
        env["PATH"] = path
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )


def test_without_chromium_it_stops_at_once_with_one_line(tmp_path):
    done = _run(["--out", str(tmp_path)], tmp_path, path=str(Path(sys.executable).parent))
    assert done.returncode == 2
    assert "chromium is not on the PATH" in done.stderr.strip().splitlines()[-1]
    assert not list(tmp_path.glob("*.png"))


def test_an_unknown_world_is_refused(tmp_path):
    done = _run(["--worlds", "nowhere", "--out", str(tmp_path)], tmp_path)
    assert done.returncode == 2 and "unknown world(s) nowhere" in done.stderr


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("chromium") is None and shutil.which("chromium-browser") is None,
    reason="needs chromium",
)
def test_the_viewer_renders_the_quadrotor_world(tmp_path):
    image = pytest.importorskip("PIL.Image")
    done = _run(["--worlds", "quadrotor-uwb", "--duration", "8", "--out", "shots"], tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    png = tmp_path / "shots" / "viewer-quadrotor-uwb.png"
    assert png.is_file()
    pixels = np.asarray(image.open(png).convert("RGB"), dtype=float)
    assert pixels.shape == (750, 1200, 3)
    # a page still loading is one dark colour with a line of text; the viewer has many colours
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 500
    assert pixels.std() > 20
    # the 3-D view (drawn with WebGL, in software) shows the orange beacons, not a blank canvas
    scene = pixels[60:440, 160:630]
    orange = (scene[..., 0] > 200) & (scene[..., 1] > 90) & (scene[..., 1] < 200)
    assert (orange & (scene[..., 2] < 90)).sum() > 100
