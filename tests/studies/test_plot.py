"""``quadobs plot``: figures of a run, a campaign folder and the le2013 study, from short runs made here."""

import struct
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.studies.plot import PANELS, figure, render
from quadobs.studies.plot._figure import style

# A bounded-noise run short enough for a test, with a 1 s excitation window so that the
# monitor fills in: every run panel has data.
_SCENARIO = """
name = "plot-test"
description = "ifac2021 trajectory, four beacons, bounded noise, 2.5 s"
dimension = 3
duration = 2.5
physics_rate = 1000.0
seed = 3

[[beacons]]
position = [0.0, 0.0, 0.0]
[[beacons]]
position = [-40.0, 0.0, 0.0]
[[beacons]]
position = [-20.0, 40.0, 0.0]
[[beacons]]
position = [-20.0, 20.0, 15.0]

[trajectory]
offset = [-20.0, 20.0, 0.0]
terms = [
    { axis = 0, amplitude = 20.0, omega = 1.0, function = "cos" },
    { axis = 1, amplitude = 10.0, omega = 2.0, function = "sin" },
    { axis = 2, amplitude = -4.0, omega = 4.0, function = "cos" },
]

[noise]
range_bound = 0.05
range_rate = 10.0
accel_bound = 0.01

[observer]
S0 = 100.0
V = 1e-4
W = 1.0

[initial]
kind = "zero"

[zonotope]
position_bound = 30.0
velocity_bound = 30.0

[excitation]
window = 1.0
"""


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    from quadobs.studies.campaign import run_campaign
    from quadobs.studies.le2013.study import run_le2013
    from quadobs.testbed.scenario import load_scenario

    d = tmp_path_factory.mktemp("plot")
    toml = d / "plot-test.toml"
    toml.write_text(_SCENARIO)
    assert (
        main(
            [
                "run",
                str(toml),
                "--estimators",
                "augmented,zonotope",
                "--out",
                str(d / "run.rrd"),
                "--no-progress",
            ]
        )
        == 0
    )
    run_campaign(
        load_scenario("ifac2021-noisy", duration=3.0),
        runs=2,
        estimators=["augmented", "ekf"],
        out_dir=d / "camp",
        workers=0,
        progress=False,
    )
    run_le2013(d / "le.rrd", None, seed=0, steps=12, runs=2)
    return {"run": d / "run.rrd", "campaign": d / "camp", "le2013": d / "le.rrd", "dir": d}


def png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.mark.parametrize("kind", ["run", "campaign", "le2013"])
def test_default_figure_is_a_png_of_the_requested_size(inputs, tmp_path, kind, capsys):
    out = tmp_path / "fig" / f"{kind}.png"
    assert main(["plot", str(inputs[kind]), "--out", str(out), "--size", "5x3", "--dpi", "80"]) == 0
    assert f"figure: {out}" in capsys.readouterr().out
    assert out.stat().st_size > 10_000
    assert png_size(out) == (400, 240)
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary file left


@pytest.mark.parametrize("kind", ["run", "campaign", "le2013"])
def test_every_panel_draws_with_units_on_its_axes(inputs, kind):
    panels = [p for p in PANELS[kind] if p != "wind"]  # wind scenarios only
    fig, dpi = figure(inputs[kind], panels, size=(10, 8), dpi=50)
    axes = fig.axes
    assert len(axes) >= len(panels)
    for ax in axes:
        assert ax.has_data(), ax.get_title()
        for label in (ax.get_xlabel(), ax.get_ylabel()):
            assert label.endswith(")") and "(" in label, (ax.get_title(), label)
    titles = " ".join(ax.get_title() for ax in axes)
    if kind == "run":
        assert "bounds" in titles and "excitation" in titles.lower()


def test_default_size_is_a_two_column_paper_width(inputs, tmp_path):
    out = render(inputs["le2013"], tmp_path / "le.png", ["width-x1"])
    assert png_size(out) == (1050, 675)  # 7.0 x 4.5 in at 150 dpi


@pytest.mark.parametrize("fmt", ["png", "pdf", "svg"])
def test_same_input_gives_the_same_bytes(inputs, tmp_path, fmt):
    what = ["paths3d", "position", "nis"] if fmt != "png" else None
    a = render(inputs["run"], tmp_path / f"a.{fmt}", what, size=(5, 3), dpi=60)
    b = render(inputs["run"], tmp_path / f"b.{fmt}", what, size=(5, 3), dpi=60)
    assert a.stat().st_size > 5_000
    assert a.read_bytes() == b.read_bytes()
    head = a.read_bytes()[:8]
    assert head.startswith({"png": b"\x89PNG", "pdf": b"%PDF", "svg": b"<?xml"}[fmt])


def test_campaign_statistics_file_and_folder_give_the_same_figure(inputs, tmp_path):
    a = render(inputs["campaign"], tmp_path / "a.png", ["rmse", "final"], size=(4, 3), dpi=50)
    b = render(
        inputs["campaign"] / "statistics.rrd",
        tmp_path / "b.png",
        ["rmse", "final"],
        size=(4, 3),
        dpi=50,
    )
    assert a.read_bytes() == b.read_bytes()


def test_le2013_sets_at_chosen_samples(inputs):
    fig, _ = figure(inputs["le2013"], ["sets"], samples=[2, 7, 12], size=(4, 6), dpi=50)
    assert [ax.get_title() for ax in fig.axes] == [
        "Sets X_k, k = 2",
        "Sets X_k, k = 7",
        "Sets X_k, k = 12",
    ]
    with pytest.raises(QuadobsError, match="--samples: 13 is not a sample"):
        figure(inputs["le2013"], ["sets"], samples=[13])


def test_line_styles_differ_without_colour():
    styles = [style(i, 100) for i in range(6)]
    assert len({(s["linestyle"], s["marker"]) for s in styles}) == 6
    assert all(
        float(s["color"]) == float(s["color"]) and 0 <= float(s["color"]) < 1 for s in styles
    )  # greys


def _fails(capsys, args, expected):
    assert main(["plot", *map(str, args)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("quadobs: error:") and "\n" not in err, err
    assert expected in err, err


def test_malformed_and_foreign_inputs_give_one_line(inputs, tmp_path, capsys):
    out = tmp_path / "new" / "fig.png"
    text = tmp_path / "notes.rrd"
    text.write_text("not a recording\n")
    _fails(
        capsys, [text, "--out", out], "notes.rrd': cannot be read, damaged or not a rerun recording"
    )
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(inputs["run"].read_bytes()[:200])
    _fails(capsys, [cut, "--out", out], "cut.rrd")
    _fails(
        capsys,
        [inputs["le2013"], "--out", out, "--what", "paths"],
        "--what paths: not a panel of a le2013 input",
    )
    _fails(
        capsys,
        [inputs["run"], "--out", out, "--what", "sets"],
        "--what sets: not a panel of a run input",
    )
    _fails(capsys, [inputs["run"], "--out", out, "--what", "wobble"], "--what wobble")
    _fails(
        capsys,
        [inputs["run"], "--out", out, "--what", "paths,wind"],
        "--what wind: the recording has no wind estimate",
    )
    _fails(capsys, [inputs["run"], "--out", tmp_path / "fig.jpg"], "format '.jpg' not supported")
    _fails(capsys, [inputs["run"], "--out", out, "--size", "7xwide"], "--size")
    _fails(capsys, [inputs["run"], "--out", out, "--samples", "3"], "--samples")
    _fails(capsys, [tmp_path / "missing.rrd", "--out", out], "no such file")
    _fails(capsys, [tmp_path, "--out", out], "not a campaign folder")
    assert not (tmp_path / "new").exists()  # nothing written, not even the folder


def test_a_recording_of_another_kind_is_refused(tmp_path, capsys):
    import rerun as rr

    path = tmp_path / "other.rrd"
    rec = rr.RecordingStream("someone-else", recording_id="x")
    rec.save(str(path))
    rec.set_time("step", sequence=0)
    rec.log("foo/bar", rr.Scalars([1.0]))
    rec.flush()
    rec.disconnect()
    _fails(
        capsys,
        [path, "--out", tmp_path / "f.png"],
        "not a quadobs run, campaign or le2013 recording",
    )


def test_a_panel_without_data_is_refused_and_nothing_written(inputs, tmp_path, capsys):
    out = tmp_path / "fig.png"
    _fails(
        capsys,
        [inputs["le2013"], "--out", out, "--what", "sets", "--samples", "99"],
        "--samples: 99",
    )
    assert not out.exists()


def test_without_matplotlib_the_error_says_how_to_install(inputs, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    _fails(capsys, [inputs["le2013"], "--out", tmp_path / "f.png"], "pip install 'quadobs[plot]'")
    assert not (tmp_path / "f.png").exists()


def test_the_package_does_not_import_matplotlib():
    code = (
        "import sys, quadobs, quadobs.cli, quadobs.studies.plot; print('matplotlib' in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"


def test_help_lists_the_panels(capsys):
    with pytest.raises(SystemExit):
        main(["plot", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for kind, names in PANELS.items():
        for name in names:
            assert name in text, (kind, name)
    assert np.isfinite(7.0) and "7.0x4.5" in text


def test_estimators_keeps_only_those_named_and_refuses_one_not_recorded(inputs, tmp_path, capsys):
    """``--estimators``: the position panel of a run with two estimators drawn with one of
    them; a campaign's method the same; a name not in the recording is refused in one line
    naming those that are, nothing written."""
    both, _ = figure(inputs["run"], ["position"], dpi=50)
    one, _ = figure(inputs["run"], ["position"], dpi=50, estimators=["zonotope"])
    labels = [line.get_label() for line in one.axes[0].get_lines()]
    assert len(one.axes[0].get_lines()) < len(both.axes[0].get_lines())
    assert any("zonotope" in label for label in labels)
    assert not any("augmented" in label for label in labels)
    camp, _ = figure(inputs["campaign"], ["rmse"], dpi=50, estimators=["ekf"])
    assert not any("augmented" in line.get_label() for line in camp.axes[0].get_lines())
    out = tmp_path / "f.png"
    code = main(["plot", str(inputs["run"]), "--out", str(out), "--estimators", "ekf"])
    err = capsys.readouterr().err
    assert (
        code == 2
        and "--estimators: ekf not in run.rrd (its estimators: augmented, zonotope)" in err
    )
    assert not out.exists()
