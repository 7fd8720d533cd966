"""``[observer] tuning = "derived"``: the live observer tuned by the replay's rule from the stated figures."""

from __future__ import annotations

import numpy as np
import pytest

from quadobs.core.measurements import Measurement
from quadobs.errors import QuadobsError
from quadobs.estimators.augmented_tuning import anchor_scale, guess_variance
from quadobs.testbed.scenario import load_scenario


def _replay_twin(sc, x0):
    """The replay's observer of a log that states ``sc``'s figures: its anchors, range noise,
    IMU noise (``q_imu``, the live rule) and grid, the typical range of its geometry and the
    live guess's variance."""
    from quadobs.testbed.factories import _input_std
    from quadobs.testbed.logs.estimators import ReplaySetup, build_augmented

    s = ReplaySetup(
        sc.beacons, sc.dt, "imu", 0.0, anchor_scale(sc.beacons),
        range_sigma=sc.noise.range_std, q_imu=_input_std(sc) ** 2 * sc.dt,
        P0=guess_variance(sc.beacons, sc.noise.range_std, offset=sc.initial.position_spread),
        input_kind="imu_body",
    )  # fmt: skip
    return build_augmented(s, x0)


def test_the_live_and_the_replay_observer_take_the_same_tuning_from_the_same_figures():
    from quadobs.testbed.factories import augmented_observer
    from quadobs.testbed.imu import input_noise_std

    sc = load_scenario("quadrotor-uwb")
    x0 = np.array([1.2, -0.7, 1.1, 0.3, -0.2, 0.05])
    live, replay = augmented_observer(sc, x0), _replay_twin(sc, x0)
    np.testing.assert_array_equal(live.model.V, replay.model.V)
    np.testing.assert_array_equal(live.P, replay.P)
    np.testing.assert_array_equal(live.z, replay.z)
    # the grid's discrete R: W = R T at the live 100 Hz, W = R dt at the replay's grid
    np.testing.assert_allclose(live.R, replay.R, rtol=1e-12)
    z = replay.immersion.lift(np.array([-0.4, 2.1, 0.9, 1.5, 0.2, -0.3]))
    np.testing.assert_array_equal(live.noise_of(z), replay.noise_of(z))
    # the closed forms: q = sigma_u^2 dt on v, r^2 q on xi (r the farthest anchor), R at 4.44 m
    spec = sc.quadrotor
    q = input_noise_std(spec, round(sc.physics_rate / spec.attitude_rate), sc.dt) ** 2 * sc.dt
    r2 = max(np.sum(sc.beacons**2, axis=1))
    np.testing.assert_allclose(np.diag(live.model.V), [r2 * q] * 3 + [0.0] * 3 + [q] * 3)
    assert live.R[0, 0] == pytest.approx((np.sqrt(3**2 + 3**2 + 1.3**2) * 0.1) ** 2)
    assert live.P[3, 3] == pytest.approx(sc.initial.position_spread**2)


def test_the_live_observer_takes_each_range_in_time_as_the_replay_does():
    """:class:`RangesInTime` on grid outputs ``y = rho^2 / 2 - |a|^2 / 2`` is the replay's in-time
    observer given the ranges ``rho`` themselves (the same bits)."""
    from quadobs.testbed.registry import build_estimators

    sc = load_scenario("quadrotor-uwb")
    x0 = np.array([1.2, -0.7, 1.1, 0.3, -0.2, 0.05])
    live = build_estimators(sc, ["augmented"], x0)[0]
    replay = _replay_twin(sc, x0)
    rng = np.random.default_rng(3)
    a2 = np.sum(sc.beacons**2, axis=1)
    for k in range(30):
        t, u = k * sc.dt, rng.normal(size=3)
        y = np.full(8, np.nan)
        if k % 10 == 0:
            rho = np.linalg.norm(sc.beacons - x0[:3], axis=1) + 0.1 * rng.normal(size=8)
            y = 0.5 * rho**2 - 0.5 * a2
            for h in range(8):
                replay.correct(Measurement(t, "range", float(rho[h]), (h,), 0.1))
        live.step(u, y)
        assert np.isfinite(live.nis) == (k % 10 == 0)  # the step's NIS where it had ranges
        replay.hold(u)
        replay.predict(t + sc.dt)
    np.testing.assert_allclose(live.x_hat, replay.x_hat, rtol=1e-12, atol=1e-12)
    assert live.corrections == replay.corrections == 24


def test_a_derived_tuning_refuses_what_it_replaces_and_what_it_cannot_derive():
    from quadobs.testbed.factories import derived_settings
    from quadobs.testbed.registry import build_estimators

    with pytest.raises(QuadobsError, match=r"observer\.V: not used with tuning"):
        load_scenario("quadrotor-uwb", settings=["observer.V=1e-3"])
    sc = load_scenario("quadrotor-uwb", settings=["noise.range_std=0.0"])
    with pytest.raises(QuadobsError, match="needs the stated range noise"):
        build_estimators(sc, ["augmented"], np.zeros(6))
    wind = load_scenario("wind")
    with pytest.raises(QuadobsError, match="airspeed"):
        derived_settings(wind, np.zeros(wind.state_dim))


def test_a_derived_tuning_survives_a_copy_and_leaves_the_other_scenarios_as_they_were():
    sc = load_scenario("quadrotor-uwb")
    again = sc.with_overrides(seed=4)
    assert again.observer.tuning == "derived" and "V" not in again.to_dict()["observer"]
    explicit = sc.with_settings(
        {"observer.tuning": "explicit", "observer.V": 3e-2, "observer.W": 0.2}
    )
    assert explicit.observer.V == 3e-2
    assert "tuning" not in load_scenario("ifac2021").to_dict()["observer"]


def test_a_variant_of_a_derived_observer_takes_its_own_anchors_in_time():
    from quadobs.testbed.ranges_in_time import RangesInTime
    from quadobs.testbed.registry import build_estimators

    sc = load_scenario(
        "quadrotor-uwb", settings=['observer.variants=[{name = "low", outputs = [0, 1, 2, 3]}]']
    )
    x0 = np.array([1.2, -0.7, 1.1, 0.3, -0.2, 0.05])
    full, low = build_estimators(sc, ["augmented", "low"], x0)
    assert isinstance(low.inner, RangesInTime) and low.inner.q == 4
    rho = np.linalg.norm(sc.beacons - x0[:3], axis=1)
    y = 0.5 * rho**2 - 0.5 * np.sum(sc.beacons**2, axis=1)
    for est in (full, low):
        est.step(np.zeros(3), y)
    assert full.corrections == 8 and low.corrections == 4
    # exact ranges at the guess: no correction moves it, and the step carries it by v dt
    np.testing.assert_allclose(low.x_hat[:3], x0[:3] + x0[3:] * sc.dt, atol=1e-9)


def test_a_setting_switches_a_tabled_scenario_to_the_derived_tuning():
    """``--set observer.tuning="derived"`` on a scenario whose table gives ``S0``, ``V`` and
    ``W`` drops them (a setting cannot remove a field); one given with it is still refused."""
    from quadobs import load_scenario
    from quadobs.errors import QuadobsError

    for sc in (
        load_scenario("ifac2021", settings=['observer.tuning="derived"']),
        load_scenario("ifac2021").with_settings(['observer.tuning="derived"']),
    ):
        assert sc.observer.tuning == "derived"
    with pytest.raises(QuadobsError, match="observer.W: not used"):
        load_scenario("ifac2021", settings=['observer.tuning="derived"', "observer.W=0.3"])
