"""Section 5 of the Automatica 2013 paper: containment over seeded runs, the paper's ordering of
the methods, and ``quadobs run le2013`` (recording and summary)."""

import json

import numpy as np
import pytest

from quadobs import IntervalMatrix, Zonotope, ZonotopicEstimator
from quadobs.cli import main
from quadobs.errors import QuadobsError
from quadobs.studies.le2013.study import (
    A_INTERVAL,
    METHODS,
    NOISE_BOUND,
    PAPER_GAINS,
    C,
    F,
    design_gains,
    reproduce,
    run_once,
    simulate,
    summary_of,
)


@pytest.fixture(scope="module")
def designs():
    return design_gains()


@pytest.fixture(scope="module")
def study(designs):
    return reproduce(seed=100, steps=40, runs=12, designs=designs)


def test_true_state_inside_every_set_at_every_step(study):
    for m, frac in study["containment"].items():
        assert frac == 1.0, m


def test_methods_compare_as_in_the_paper(study):
    w = {m: study["mean_width"][m][1:].mean(axis=0) for m in study["methods"]}
    vol = {m: study["mean_volume"][m][1:].mean() for m in study["methods"]}
    final = {m: study["mean_width"][m][-1] for m in study["methods"]}
    # the second approach is tighter than the first and than segment minimisation, in both bounds and volume
    assert np.all(w["pradius2"] < w["segment"]) and vol["pradius2"] < vol["segment"]
    assert np.all(w["pradius2"] < w["pradius1"]) and vol["pradius2"] < vol["pradius1"]
    # the first approach ends tighter than segment minimisation on x2 (its transient is longer)
    assert final["pradius1"][1] < final["segment"][1]
    # volume minimisation has the smallest volume
    assert vol["volume"] <= min(vol.values()) + 1e-12
    # and the P-radius methods are cheaper online than volume minimisation
    assert study["online_us"]["pradius2"] < study["online_us"]["volume"]


def test_a_set_shrinks_from_the_initial_box(study):
    for m in study["methods"]:
        assert np.all(study["mean_width"][m][-1] < 0.25 * study["mean_width"][m][0])


def test_simulation_is_seeded_and_respects_the_bounds():
    a, b, c = simulate(5, 30), simulate(5, 30), simulate(6, 30)
    np.testing.assert_array_equal(a["x"], b["x"])
    assert not np.array_equal(a["x"], c["x"])
    assert np.all(np.abs(a["x"][0]) <= 3.0) and abs(a["delta"]) <= 1.0
    resid = a["y"][1:] - a["x"][1:] @ C.T
    assert np.all(np.abs(resid) <= NOISE_BOUND)
    assert A_INTERVAL.contains(a["A"])


def test_estimator_with_uncertain_a_handles_missing_outputs(designs):
    sim = simulate(3, 30)
    est = ZonotopicEstimator(
        A_INTERVAL,
        F,
        C,
        NOISE_BOUND,
        Zonotope(np.zeros(2), 3 * np.eye(2)),
        designs["second_approach"],
    )
    for k in range(1, 31):
        y = sim["y"][k].copy()
        if k % 3 == 0:
            y[1] = np.nan
        Z = est.step(y)
        assert Z.order <= 20
        assert Z.contains(sim["x"][k])


def test_point_matrix_estimator_is_tighter_than_the_interval_one(designs):
    sim = simulate(4, 30)
    X0 = Zonotope(np.zeros(2), 3 * np.eye(2))
    exact = ZonotopicEstimator(IntervalMatrix.point(sim["A"]), F, C, NOISE_BOUND, X0, "segment")
    robust = ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, X0, "segment")
    we, wr = [], []
    for k in range(1, 31):
        we.append(exact.step(sim["y"][k]).widths())
        wr.append(robust.step(sim["y"][k]).widths())
        assert exact.zonotope.contains(sim["x"][k])
    assert np.mean(we) < np.mean(wr)


def test_cli_run_le2013_writes_recording_and_summary(tmp_path, capsys):
    from quadobs.recording import list_entities, read_series

    rrd, js = tmp_path / "le.rrd", tmp_path / "le.json"
    assert (
        main(
            [
                "run",
                "le2013",
                "--out",
                str(rrd),
                "--summary",
                str(js),
                "--runs",
                "3",
                "--duration",
                "20",
                "--seed",
                "7",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "second_approach lambda_2" in out and "paper" in out
    data = json.loads(js.read_text())
    assert data["runs"] == 3 and data["steps"] == 20 and data["seed"] == 7
    assert set(data["gains"]) == {"first_approach", "second_approach"}
    assert np.array(data["gains"]["first_approach"]).shape == (2, 2)
    np.testing.assert_allclose(
        data["gains"]["first_approach"], [[-0.2137, 0.5726], [0.3684, 0.3570]], atol=1e-4
    )
    for key in ("containment", "mean_width"):
        assert set(data[key]) == {"segment", "volume", "pradius1", "pradius2", "pradius2_paper"}
    assert all(v == 1.0 for v in data["containment"].values())
    assert all(len(v) == 2 for v in data["mean_width"].values())
    entities = set(list_entities(rrd))
    assert {
        "/le2013/truth",
        "/le2013/width/segment",
        "/le2013/bounds/pradius2/x1",
        "/le2013/sets/volume",
    } <= entities
    width = read_series(rrd, "le2013/width/pradius2")
    assert width["values"].shape == (21, 2)
    first = run_once(design_gains(), 7, 20, methods=("pradius2",))
    np.testing.assert_allclose(width["values"], first.widths["pradius2"], rtol=1e-12)
    bounds = read_series(rrd, "le2013/bounds/segment/x1")["values"]
    truth = read_series(rrd, "le2013/truth")["values"]
    assert np.all((bounds[:, 0] <= truth[:, 0]) & (truth[:, 0] <= bounds[:, 1]))


def test_summary_is_reproducible(designs):
    a = summary_of(reproduce(seed=1, steps=10, runs=2, designs=designs))
    b = summary_of(reproduce(seed=1, steps=10, runs=2, designs=designs))
    for key in ("gains", "containment", "mean_width", "mean_volume", "per_step_mean"):
        assert a[key] == b[key]


def _run_backend(designs, method, backend, seed, steps, y=None):
    sim = simulate(seed, steps)
    gains = {
        "segment": "segment",
        "volume": "volume",
        "pradius1": designs["first_approach"],
        "pradius2": designs["second_approach"],
        "pradius2_paper": PAPER_GAINS["second_approach"],
    }[method]
    est = ZonotopicEstimator(
        A_INTERVAL,
        F,
        C,
        NOISE_BOUND,
        Zonotope(np.zeros(2), 3 * np.eye(2)),
        gains,
        max_generators=20,
        backend=backend,
    )
    assert est.backend == backend
    Y = sim["y"] if y is None else y
    return sim, [est.zonotope] + [est.step(Y[k]) for k in range(1, steps + 1)]


@pytest.mark.parametrize("method", METHODS)
def test_compiled_step_matches_the_reference_over_a_run(designs, method):
    """The compiled kernels and the NumPy reference give the same sets to rounding, step by step."""
    steps = 50 if method != "volume" else 25
    sim, ref = _run_backend(designs, method, "numpy", 11, steps)
    _, fast = _run_backend(designs, method, "numba", 11, steps)
    for k, (a, b) in enumerate(zip(ref, fast)):
        assert b.generators.shape == a.generators.shape, k
        assert b.order <= 20
        scale = np.abs(a.generators).sum()
        np.testing.assert_allclose(b.center, a.center, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(b.generators, a.generators, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(b.widths(), a.widths(), rtol=1e-12)
        assert b.contains(sim["x"][k], method="halfspace") and a.contains(
            sim["x"][k], method="halfspace"
        )
        assert not b.center.flags.writeable and not b.generators.flags.writeable


def test_compiled_step_handles_missing_outputs_and_refuses_infinities(designs):
    sim = simulate(2, 20)
    Y = sim["y"].copy()
    Y[3::4, 0] = np.nan
    Y[5::6, 1] = np.nan
    for method in ("segment", "pradius2"):
        _, ref = _run_backend(designs, method, "numpy", 2, 20, Y)
        _, fast = _run_backend(designs, method, "numba", 2, 20, Y)
        for k, (a, b) in enumerate(zip(ref, fast)):
            np.testing.assert_allclose(
                b.generators, a.generators, rtol=0, atol=1e-12 * np.abs(a.generators).sum()
            )
            assert b.contains(sim["x"][k])
    for backend in ("numpy", "numba"):
        est = ZonotopicEstimator(
            A_INTERVAL,
            F,
            C,
            NOISE_BOUND,
            Zonotope(np.zeros(2), 3 * np.eye(2)),
            "segment",
            backend=backend,
        )
        before = est.zonotope
        with pytest.raises(QuadobsError, match="y"):
            est.step([np.inf, 0.0])
        with pytest.raises(QuadobsError, match="y"):
            est.step([0.0, 0.0, 0.0])
        assert est.zonotope is before or np.array_equal(est.zonotope.generators, before.generators)


def test_compiled_backend_mixes_with_the_reference_methods(designs):
    """``predict``/``correct`` (reference) and ``step`` (kernels) share one state; pickling keeps it."""
    import pickle

    sim = simulate(9, 12)
    X0 = Zonotope(np.zeros(2), 3 * np.eye(2))
    ref = ZonotopicEstimator(
        A_INTERVAL, F, C, NOISE_BOUND, X0, designs["second_approach"], backend="numpy"
    )
    fast = ZonotopicEstimator(
        A_INTERVAL, F, C, NOISE_BOUND, X0, designs["second_approach"], backend="numba"
    )
    for k in range(1, 13):
        if k % 3 == 0:
            fast.predict()
            fast.correct(sim["y"][k])
            ref.step(sim["y"][k])
        elif k % 3 == 1:
            fast.step(sim["y"][k])
            ref.step(sim["y"][k])
        else:
            fast = pickle.loads(pickle.dumps(fast))
            fast.step(sim["y"][k])
            ref.step(sim["y"][k])
        np.testing.assert_allclose(
            fast.zonotope.generators, ref.zonotope.generators, rtol=0, atol=1e-12
        )
        np.testing.assert_allclose(fast.x_hat, ref.x_hat, rtol=0, atol=1e-12)
    fast.predict()
    fast.predict()  # two predictions without reduction: more generators than the buffer held
    ref.predict()
    ref.predict()
    np.testing.assert_allclose(
        fast.step(sim["y"][1]).generators, ref.step(sim["y"][1]).generators, rtol=0, atol=1e-12
    )


def test_backend_choice():
    X0 = Zonotope(np.zeros(2), 3 * np.eye(2))
    assert ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, X0, "segment").backend == "numba"
    custom = ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, X0, lambda Z, c, phi: np.zeros(2))
    assert custom.backend == "numpy"
    assert (
        ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, X0, "segment", reduction="girard").backend
        == "numpy"
    )
    with pytest.raises(QuadobsError, match="backend"):
        ZonotopicEstimator(
            A_INTERVAL, F, C, NOISE_BOUND, X0, lambda Z, c, phi: np.zeros(2), backend="numba"
        )
    with pytest.raises(QuadobsError, match="backend"):
        ZonotopicEstimator(A_INTERVAL, F, C, NOISE_BOUND, X0, "segment", backend="gpu")


@pytest.mark.parametrize("gain", ["segment", "volume", "fixed"])
def test_compiled_step_matches_the_reference_in_three_dimensions(gain):
    """n = 3, three outputs, two disturbance columns, an interval [A] with a zero radius row (no box column there)."""
    rng = np.random.default_rng(21)
    mid = (
        0.7 * np.linalg.qr(rng.standard_normal((3, 3)))[0]
    )  # stable: the sets stay of moderate size
    rad = np.abs(0.05 * rng.standard_normal((3, 3)))
    rad[1] = 0.0
    Ai = IntervalMatrix.from_mid_rad(mid, rad)
    Fm, Cm, phi = (
        0.1 * rng.standard_normal((3, 2)),
        rng.standard_normal((3, 3)),
        np.array([0.1, 0.2, 0.05]),
    )
    g = 0.2 * rng.standard_normal((3, 3)) if gain == "fixed" else gain
    X0 = Zonotope(rng.standard_normal(3), rng.standard_normal((3, 5)))
    ests = [
        ZonotopicEstimator(Ai, Fm, Cm, phi, X0, g, max_generators=8, backend=b)
        for b in ("numpy", "numba")
    ]
    x = X0.center.copy()
    A = mid + rad * rng.uniform(-1, 1, (3, 3))
    for k in range(15 if gain == "volume" else 40):
        x = A @ x + Fm @ rng.uniform(-1, 1, 2)
        y = Cm @ x + phi * rng.uniform(-1, 1, 3)
        if k % 5 == 4:
            y[k % 3] = np.nan
        a, b = (e.step(y) for e in ests)
        assert a.order == b.order <= 8
        scale = np.abs(a.generators).sum() + np.abs(a.center).sum()
        np.testing.assert_allclose(b.center, a.center, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(b.generators, a.generators, rtol=0, atol=1e-12 * scale)
        assert b.contains(x, method="lp")
