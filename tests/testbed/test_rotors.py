"""The identified rotor: step responses against the closed forms and the identified model, the world's rotors, the gains' margin."""

import math

import numpy as np
import pytest

from quadobs.testbed.controllers import (
    CRAZYFLIE,
    LEAD_FILTER,
    closed_loop_poles,
    lead,
    smallest_damping,
)
from quadobs.testbed.rotors import IDENTIFIED, settled_time

_HOVER = CRAZYFLIE.mass * 9.81 / 4.0


def test_the_time_constants_at_hover_are_the_identified_ones():
    up, down = IDENTIFIED.time_constants(CRAZYFLIE.mass)
    assert up == pytest.approx(0.136, abs=5e-4) and down == pytest.approx(0.108, abs=5e-4)
    assert IDENTIFIED.hover_speed(CRAZYFLIE.mass) == pytest.approx(18968, abs=2)
    assert float(IDENTIFIED.thrust(IDENTIFIED.speed(0.05))) == pytest.approx(0.05)


@pytest.mark.parametrize("sign, tau", [(1.0, 0.136), (-1.0, 0.108)])
def test_a_small_thrust_step_at_hover_settles_with_the_linearised_time_constant(sign, tau):
    w = IDENTIFIED.hover_speed(CRAZYFLIE.mass)
    t = settled_time(IDENTIFIED, w, _HOVER * (1.0 + 0.005 * sign), 1.0 - math.exp(-1.0), 1e-4)
    assert t == pytest.approx(tau, rel=0.01)


def test_the_exact_steps_agree_with_a_fine_integration_of_the_identified_model():
    """Spinning up and down from hover: the exact step against Euler at 1 us on ``rotor_dyn_coef``."""
    w0 = IDENTIFIED.hover_speed(CRAZYFLIE.mass)
    for command in (0.12, 0.02, 0.0):
        c = float(IDENTIFIED.speed(max(command, IDENTIFIED.thrust_min)))
        w = w0
        for _ in range(50_000):  # 0.05 s
            rate = (
                7.355623702172756 * (c - w) if c > w else 0.00024443862952110715 * (c * c - w * w)
            )
            w += 1e-6 * rate
        exact, _ = IDENTIFIED.step(np.array([w0]), command, 0.05)
        assert exact[0] == pytest.approx(w, rel=1e-5)


def test_stopped_motors_spin_down_as_the_closed_form():
    w0, h = 20000.0, 0.2
    w, T = IDENTIFIED.step(np.array([w0]), 0.1, h, running=False)
    assert w[0] == pytest.approx(w0 / (1.0 + IDENTIFIED.k_down * w0 * h))
    assert T[0] == pytest.approx(float(IDENTIFIED.thrust(w[0])))


def test_the_commands_are_clamped_to_the_motor_limits():
    w, T = IDENTIFIED.step(np.zeros(1), 0.0, 10.0)
    assert T[0] == pytest.approx(IDENTIFIED.thrust_min, rel=1e-9)
    w, T = IDENTIFIED.step(np.zeros(1), 1.0, 10.0)
    assert T[0] == pytest.approx(IDENTIFIED.thrust_max, rel=1e-9)


def test_the_compiled_rotor_step_agrees_with_the_numpy_reference():
    from quadobs._kernels.quadrotor import rotor_step

    rng = np.random.default_rng(3)
    w = rng.uniform(0.0, 23000.0, 4)
    cmd = rng.uniform(-0.01, 0.15, 4)
    for running in (True, False):
        ref_w, ref_T = IDENTIFIED.step(w, cmd, 1e-3, running)
        ww, T = w.copy(), np.zeros(4)
        rotor_step(cmd, running, ww, IDENTIFIED.packed(), 1e-3, T)
        assert np.allclose(ww, ref_w, rtol=1e-12) and np.allclose(T, ref_T, rtol=1e-12)


def test_the_world_hovers_on_the_identified_rotors_and_records_their_thrust():
    from quadobs.testbed.scenario import load_scenario
    from quadobs.testbed.sensors import SensorModel
    from quadobs.testbed.worlds.quadrotor import QuadrotorWorld

    sc = load_scenario("quadrotor-uwb", settings=["duration=8.0"])
    world = QuadrotorWorld(sc, SensorModel(sc), 4000)
    world.begin_block(0, 4000)
    for j in range(4000):
        world.step(j)
    thrust = world.out[:4000, world.spans["thrust"]]
    assert np.all(thrust[0] == 0.0)  # at rest at first
    assert thrust[1000:].min() >= IDENTIFIED.thrust_min - 1e-12  # then never below idle
    assert thrust[-500:].sum(axis=1).mean() == pytest.approx(4 * _HOVER, rel=0.1)
    assert world.crashed_at is None


def test_the_lead_keeps_a_margin_over_the_rotor_time_constants():
    tau_u, _ = IDENTIFIED.time_constants(CRAZYFLIE.mass)
    taus = np.linspace(0.06, 0.2, 15)
    assert smallest_damping(2.0, 12.0, 0.9, taus, tau_u, LEAD_FILTER) > 0.5
    assert smallest_damping(2.0, 12.0, 0.9, taus, tau_u, LEAD_FILTER, integral=0.5) > 0.5
    assert smallest_damping(2.0, 12.0, 0.9, [0.136]) < 0.0  # the same gains without the lead
    # without the lead, the best attitude bandwidth (to 0.25 rad/s) leaves little damping
    best = max(smallest_damping(2.0, wa, 0.9, taus) for wa in np.arange(3.0, 12.0, 0.25))
    assert best < 0.1


def test_the_attitude_loop_alone_is_stable_below_two_zeta_over_tau():
    """Without the position loop (``k_x = k_v = 0``): Routh's ``k_W > tau k_R``."""
    tau, zeta = 0.136, 0.9
    edge = 2.0 * zeta / tau
    for wa, stable in ((0.95 * edge, True), (1.05 * edge, False)):
        r = closed_loop_poles(1e-9, wa, zeta, tau)
        assert (np.max(r.real) < 0.0) == stable


def test_the_compiled_lead_agrees_with_the_numpy_reference_and_inverts_a_lag():
    from quadobs._kernels.quadrotor import lead as compiled

    rng = np.random.default_rng(5)
    s1, s2, o1, o2 = np.zeros(8), np.zeros(8), np.zeros(4), np.zeros(4)
    for _ in range(20):
        d = rng.uniform(0.0, 0.1, 4)
        lead(d, s1, 0.136, 0.108, 500.0, 0.1, o1)
        compiled(d, s2, 0.136, 0.108, 500.0, 0.1, o2)
        assert np.allclose(o1, o2, rtol=1e-12) and np.allclose(s1, s2, rtol=1e-12)
    # a ramp: the filtered slope settles on the ramp's slope, so the command leads it by tau
    st, out = np.zeros(8), np.zeros(4)
    for k in range(400):
        lead(np.full(4, 0.05 + 0.01 * k / 500.0), st, 0.136, 0.108, 500.0, 0.1, out)
    assert out[0] == pytest.approx(0.05 + 0.01 * 399 / 500.0 + 0.136 * 0.01, rel=1e-9)
