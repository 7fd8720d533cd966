"""Every public step refuses a non-finite input, an infinite output, a wrong shape or an empty output,
and leaves the estimator as it was; NaN in the outputs still means a missing sample."""

import numpy as np
import pytest

import quadobs
from quadobs import QuadobsError, load_scenario
from quadobs.testbed.registry import build_estimators

GOOD_U, GOOD_Y = np.array([1.0, 0.0, 0.0]), np.array([50.0])
BAD = {
    "nan u": (np.array([np.nan, 0.0, 0.0]), GOOD_Y),
    "inf u": (np.array([0.0, -np.inf, 0.0]), GOOD_Y),
    "inf y": (GOOD_U, np.array([np.inf])),
    "short u": (np.zeros(2), GOOD_Y),
    "empty y": (GOOD_U, np.zeros(0)),
    "2-D y": (GOOD_U, np.zeros((1, 1))),
    "text u": ("abc", GOOD_Y),
}


def _estimators():
    sc = load_scenario("ifac2021-noisy")
    ests = build_estimators(sc, ["augmented", "ekf", "ukf"], np.zeros(sc.state_dim))
    ests.append(quadobs.AugmentedObserver(quadobs.immerse(sc.system()), dt=sc.dt, backend="numpy"))
    return ests


def _state(est):
    P = est.x_covariance
    return np.array(est.x_hat), None if P is None else np.array(P)


@pytest.mark.parametrize("call", ["step", "step_and_record"])
@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_operands_raise_and_change_nothing(call, case):
    u, y = BAD[case]
    for est in _estimators():
        est.step(GOOD_U, GOOD_Y)
        before = _state(est)
        with pytest.raises(QuadobsError, match=r"^(u|y)\b"):
            if call == "step":
                est.step(u, y)
            else:
                est.step_and_record(u, y, np.zeros(est.x_hat.shape[0] + 3))
        after = _state(est)
        np.testing.assert_array_equal(
            before[0], after[0], err_msg=f"{est.name}: x_hat changed ({case})"
        )
        if before[1] is not None:
            np.testing.assert_array_equal(
                before[1], after[1], err_msg=f"{est.name}: covariance changed ({case})"
            )
        est.step(GOOD_U, GOOD_Y)  # still usable
        assert np.isfinite(est.x_hat).all()


def test_nan_output_still_means_missing():
    for est in _estimators():
        out = np.zeros(est.x_hat.shape[0] + 3)
        est.step_and_record(GOOD_U, np.array([np.nan]), out)
        assert np.isfinite(est.x_hat).all() and np.isfinite(out[: est.x_hat.shape[0]]).all()


# -- the batch observer ------------------------------------------------------------------------

B = 5
BATCH_BAD = {
    "nan U": lambda U, Y: U.__setitem__((3, 0), np.nan),
    "inf U": lambda U, Y: U.__setitem__((4, 2), -np.inf),
    "inf Y": lambda U, Y: Y.__setitem__((2, 0), np.inf),
}


def _batches():
    """A batch of each backend (one threaded), the members started apart, a few steps in."""
    from quadobs.estimators.augmented_batch import BatchAugmentedObserver

    sc = load_scenario("ifac2021-noisy")
    template = quadobs.AugmentedObserver(quadobs.immerse(sc.system()), dt=sc.dt, backend="numpy")
    x0 = np.random.default_rng(7).normal(size=(B, sc.state_dim))
    batches = [
        BatchAugmentedObserver(template, B, x0=x0, backend=b, threads=t)
        for b, t in (("numba", 0), ("numba", 2), ("numpy", 0))
    ]
    for batch in batches:
        for _ in range(3):
            batch.step(np.tile(GOOD_U, (B, 1)), np.tile(GOOD_Y, (B, 1)))
    return batches


def _batch_state(batch):
    return batch.Z.copy(), batch.P.copy(), batch._stats.copy()


@pytest.mark.parametrize("case", sorted(BATCH_BAD))
def test_batch_refuses_bad_values_naming_the_member_and_changes_no_member(case):
    for batch in _batches():
        U, Y = np.tile(GOOD_U, (B, 1)), np.tile(GOOD_Y, (B, 1))
        BATCH_BAD[case](U, Y)
        member = int(np.argmax(~np.isfinite(U).all(axis=1) | np.isinf(Y).any(axis=1)))
        before = _batch_state(batch)
        with pytest.raises(
            QuadobsError, match=rf"^{case.split()[1]}\[{member}\]: holds a non-finite value"
        ):
            batch.step(U, Y)
        for a, b in zip(before, _batch_state(batch)):
            np.testing.assert_array_equal(
                a, b, err_msg=f"{batch.backend} threads={batch.__dict__.get('_threads')}: {case}"
            )
        batch.step(np.tile(GOOD_U, (B, 1)), np.tile(GOOD_Y, (B, 1)))  # still usable
        assert np.isfinite(batch.Z).all()


@pytest.mark.parametrize(
    "U, Y",
    [
        (np.zeros((B, 2)), np.full((B, 1), 50.0)),  # short rows of U
        (np.zeros((B, 3)), np.zeros((B, 0))),  # empty outputs
        (np.zeros((B - 1, 3)), np.full((B - 1, 1), 50.0)),  # a member short
        (np.zeros(3), np.full(1, 50.0)),  # one member's operands, no batch axis
        ("abc", np.full((B, 1), 50.0)),
    ],
    ids=["short U", "empty Y", "short batch", "no batch axis", "text U"],
)
def test_batch_refuses_wrong_shapes_and_changes_nothing(U, Y):
    for batch in _batches():
        before = _batch_state(batch)
        with pytest.raises(QuadobsError, match=r"^(U|Y)\b"):
            batch.step(U, Y)
        for a, b in zip(before, _batch_state(batch)):
            np.testing.assert_array_equal(a, b)


def test_batch_nan_outputs_still_mean_missing():
    """NaN in ``Y`` is a missing sample, member by member: the members without it are corrected."""
    for batch in _batches():
        Y = np.tile(GOOD_Y, (B, 1))
        Y[1] = np.nan
        corrections = batch.corrections.copy()
        batch.step(np.tile(GOOD_U, (B, 1)), Y)
        assert np.isfinite(batch.Z).all()
        np.testing.assert_array_equal(batch.corrections - corrections, [1, 0, 1, 1, 1])
