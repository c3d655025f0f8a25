"""The autopilots' own position and velocity loops (sim_bridge.world.position_loop), run by
the fused physics stepper, and what an estimator's bias and a wrong hover-thrust parameter do
to a vehicle they fly: closed forms against the simulated airframe (issue 18)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.params import GRAVITY_MPS2, InnerLoopConfig, VehicleParams
from companion.state import FleetSetpoint
from sim_bridge.sitl.autopilots import autopilot_named
from sim_bridge.sitl.params_table import ParamTable
from sim_bridge.world.autopilot_model import AutopilotConfig, hover_thrust_errors
from sim_bridge.world.estimator import EstimatorConfig, bias_disturbance_ned_mps2
from sim_bridge.world.physics import Physics, WindConfig, hover_state, hover_thrust_norm
from sim_bridge.world.position_loop import LOOP_ARDUPILOT, LOOP_PX4, PositionController, PositionLoopGains

CRAZYFLIE_DRAG = 0.0065
"""N/(m/s): docs/vehicle.md's drag coefficient for a disturbed world."""
DT = 0.002
HOVER_Z = -10.0


def default_gains(autopilot: str, vp: VehicleParams, hover_param: float | None = None,
                  **params: float) -> PositionLoopGains:
    """The autopilot's loop with its default parameters (its own table, as the SITL builds it),
    and `params` set in it."""
    true = hover_thrust_norm(vp)
    behaviour = autopilot_named(autopilot)
    table = ParamTable(behaviour.param_specs(InnerLoopConfig(), 1, true if hover_param is None else hover_param))
    for name, value in params.items():
        assert table.set(name, value), name
    return behaviour.position_loop(table, true)


def fly_position_hold(vp: VehicleParams, gains: PositionLoopGains, seconds: float, wind=(0.0, 0.0, 0.0),
                      bias=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """One vehicle at rest at a fixed position setpoint from t = 0 (when wind and bias start):
    (times (T,), position errors (T, 3)) every 20 ms."""
    physics = Physics(vp, InnerLoopConfig(), dt_s=DT, wind=WindConfig(steady_ned_mps=wind) if any(wind) else None)
    state = hover_state(1, vp, np.array([[0.0, 0.0, HOVER_Z]]))
    sp = FleetSetpoint.empty(1)
    sp.pos_ned_m[0] = (0.0, 0.0, HOVER_Z)
    sp.yaw_rad[0] = 0.0
    loop = PositionController(1)
    loop.set_gains(0, gains)
    acc = np.array([bias], float)
    t, err = [0.0], [np.zeros(3)]
    for k in range(int(round(seconds / 0.02))):
        physics.step(state, sp, 10, acc_ext_ned_mps2=acc, loop=loop)
        t.append((k + 1) * 0.02)
        err.append(state.pos_ned_m[0] - sp.pos_ned_m[0])
    return np.array(t), np.array(err)


# ---------------------------------------------------------------------------- closed forms
def characteristic_polynomial(g: PositionLoopGains, drag_per_s: float) -> np.ndarray:
    """Horizontal closed loop of a position hold (error e = x - x_sp), continuous time, the
    inner attitude loop and the filters taken as ideal: P(s) e = 0 after a disturbance step.

    PX4 (D on the measured velocity derivative):
        (1 + Kd) s^3 + (Kv + c) s^2 + (Kv Kp + Ki) s + Ki Kp
    ArduPilot (D on the derivative of the velocity error, Kp (x_sp - x) - v):
        (1 + Kd) s^3 + (Kv + Kd Kp + c) s^2 + (Kv Kp + Ki) s + Ki Kp
    with c the drag per unit mass."""
    kp, kv, ki, kd = g.pos_p_xy_per_s, g.vel_p_xy_per_s, g.vel_i_xy_per_s2, g.vel_d_xy
    damping = kv + drag_per_s + (kd * kp if g.style == LOOP_ARDUPILOT else 0.0)
    return np.array([1.0 + kd, damping, kv * kp + ki, ki * kp])


def step_disturbance_error(poly: np.ndarray, d_mps2: float, t: np.ndarray) -> np.ndarray:
    """e(t) after an acceleration disturbance d stepping on at t = 0 from rest: E(s) = d / P(s),
    by partial fractions (distinct roots)."""
    d_poly = np.polyder(poly)
    return np.real(sum(d_mps2 * np.exp(p * t) / np.polyval(d_poly, p) for p in np.roots(poly)))


def settling_time_s(poly: np.ndarray, d_mps2: float, band_m: float) -> float:
    """Last time the closed-form error is outside +-band_m."""
    t = np.arange(0.0, 120.0, 0.001)
    out = np.flatnonzero(np.abs(step_disturbance_error(poly, d_mps2, t)) >= band_m)
    return float(t[out[-1]]) if len(out) else 0.0


# ---------------------------------------------------------------------------- tests
def test_default_gains_are_the_autopilots_own():
    vp = VehicleParams()
    px4, apm = default_gains("px4", vp), default_gains("ardupilot", vp)
    assert (px4.style, px4.pos_p_xy_per_s, px4.vel_p_xy_per_s, px4.vel_i_xy_per_s2, px4.vel_d_xy) == (
        LOOP_PX4, 0.95, 1.8, 0.4, 0.2)  # MPC_XY_P, MPC_XY_VEL_P_ACC, _I_ACC, _D_ACC
    assert (px4.pos_p_z_per_s, px4.vel_p_z_per_s, px4.vel_i_z_per_s2, px4.vel_d_z) == (1.0, 4.0, 2.0, 0.0)
    assert (apm.style, apm.pos_p_xy_per_s, apm.vel_p_xy_per_s, apm.vel_i_xy_per_s2, apm.vel_d_xy) == (
        LOOP_ARDUPILOT, 1.0, 2.0, 1.0, 0.5)  # PSC_POSXY_P, PSC_VELXY_P, _I, _D
    assert apm.vel_imax_xy_mps2 == 10.0  # PSC_VELXY_IMAX 1000 cm/s^2
    assert (apm.pos_p_z_per_s, apm.vel_p_z_per_s, apm.vel_i_z_per_s2) == (1.0, 5.0, 0.0)  # PSC_POSZ_P, PSC_VELZ_P, _I
    # the vertical integrator is the acceleration loop's (PSC_ACCZ_P 0.5, _I 1.0, _IMAX 800: throttle 1/1000 per cm/s^2)
    assert (apm.acc_z_p_per_mps2, apm.acc_z_i_per_mps2s, apm.acc_z_imax) == pytest.approx((0.05, 0.1, 0.8))


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_steady_wind_is_held_to_10_cm_within_the_closed_form_settling_time(autopilot):
    """5 m/s of steady wind on a Crazyflie with drag (docs/vehicle.md) at a fixed position
    setpoint: the default gains' closed loop gives the settling time into +-0.1 m; the
    simulated vehicle is inside the band from then on (0.5 s allowed for the attitude loop,
    motors and filters the closed form leaves out), and the integrator takes the offset away."""
    vp = VehicleParams(drag_coeff_n_per_mps=CRAZYFLIE_DRAG)
    g = default_gains(autopilot, vp)
    drag = CRAZYFLIE_DRAG / vp.mass_kg
    d = drag * 5.0  # the wind's push at rest, m/s^2
    poly = characteristic_polynomial(g, drag)
    assert (np.real(np.roots(poly)) < 0).all()
    ts = settling_time_s(poly, d, 0.1)
    assert 3.0 < ts < 15.0, ts  # (PX4 ~9.3 s: its velocity integrator is slow; ArduPilot ~4.6 s)
    t, err = fly_position_hold(vp, g, ts + 20.0, wind=(5.0, 0.0, 0.0))
    ex = err[:, 0]
    peak = step_disturbance_error(poly, d, np.arange(0, ts, 0.01))
    assert np.abs(ex).max() == pytest.approx(np.abs(peak).max(), rel=0.15)  # the closed form is the loop flown
    assert np.abs(ex[t < ts - 1.0]).max() > 0.1  # (the band is not met from the start: the test has teeth)
    assert np.abs(ex[t >= ts + 0.5]).max() < 0.1
    assert abs(ex[-1]) < 0.01 and np.abs(err[:, 1:]).max() < 0.02  # no steady offset; y and z undisturbed


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_a_disturbance_leaves_the_closed_form_offset_under_a_p_only_loop_and_none_with_the_integrators(autopilot):
    """An estimator-bias-like disturbance d (tilt error horizontally, accelerometer bias
    vertically): with the integrators off the position error settles at the closed-form
    offset d / (Kv Kp (1 + d_z / g)) per horizontal axis, and vertically d / (Kv Kp) for PX4
    and d / (K Kv Kp) for ArduPilot, whose throttle comes from an acceleration loop of gain
    K = PSC_ACCZ_P g / hover thrust on the measured acceleration; with the integrators the
    offset goes."""
    vp = VehicleParams()
    g = default_gains(autopilot, vp)
    d = np.array([0.34, -0.2, 0.25])
    p_only = dataclasses.replace(g, vel_i_xy_per_s2=0.0, vel_i_z_per_s2=0.0, acc_z_i_per_mps2s=0.0)
    _, err = fly_position_hold(vp, p_only, 40.0, bias=d)
    # Both take the tilt from the horizontal acceleration against 1 g and scale the thrust for
    # the vertical: holding d_z up, the horizontal acceleration realised is (1 + d_z / g) times
    # the one asked for.
    xy = d[:2] / (g.vel_p_xy_per_s * g.pos_p_xy_per_s * (1.0 + d[2] / GRAVITY_MPS2))
    z_gain = g.vel_p_z_per_s * g.pos_p_z_per_s
    if autopilot == "ardupilot":  # the throttle's P on the measured acceleration: K a_target = -d at rest
        z_gain *= g.acc_z_p_per_mps2 * GRAVITY_MPS2 / g.hover_true
    np.testing.assert_allclose(err[-1, :2], xy, rtol=0.01, atol=1e-4)
    assert err[-1, 2] == pytest.approx(d[2] / z_gain, rel=0.01)
    _, err = fly_position_hold(vp, g, 60.0, bias=d)
    assert np.abs(err[-1]).max() < 2e-3


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_a_hover_thrust_parameter_off_by_e_offsets_the_height_without_integrators_and_not_with(autopilot):
    """The autopilot scales thrust by its hover-thrust parameter (PX4 with MPC_USE_HTE 0; by
    default PX4 flies its estimator's value), Th (1 + e) against the airframe's true Th: PX4
    realises (1 + e) times the specific force it asks for, so a P-only vertical loop
    settles g e / ((1 + e) Kv Kp) high; ArduPilot adds Th e of throttle
    at its hover point, g e of acceleration, settling g e / (K Kv Kp) high. The integrators
    (PX4 MPC_Z_VEL_I_ACC, ArduPilot PSC_ACCZ_I) take it away."""
    vp = VehicleParams()
    e = 0.07
    if autopilot == "px4":  # by default PX4 flies its hover-thrust estimator's value, not the parameter
        assert default_gains(autopilot, vp, hover_param=hover_thrust_norm(vp) * (1 + e)).hover_param \
            == hover_thrust_norm(vp)
    g = default_gains(autopilot, vp, hover_param=hover_thrust_norm(vp) * (1 + e),
                      **({"MPC_USE_HTE": 0} if autopilot == "px4" else {}))
    assert g.hover_param == pytest.approx(g.hover_true * 1.07)
    p_only = dataclasses.replace(g, vel_i_z_per_s2=0.0, acc_z_i_per_mps2s=0.0)
    _, err = fly_position_hold(vp, p_only, 30.0)
    kz = g.vel_p_z_per_s * g.pos_p_z_per_s
    if autopilot == "px4":
        expect = -GRAVITY_MPS2 * e / ((1 + e) * kz)
    else:
        expect = -GRAVITY_MPS2 * e / (g.acc_z_p_per_mps2 * GRAVITY_MPS2 / g.hover_true * kz)
    assert err[-1, 2] == pytest.approx(expect, rel=0.01)  # NED: negative is high
    _, err = fly_position_hold(vp, g, 40.0)
    assert abs(err[-1, 2]) < 2e-3


def test_bias_draws_are_seeded_per_vehicle_and_zero_by_default():
    assert not EstimatorConfig().biased
    np.testing.assert_array_equal(bias_disturbance_ned_mps2(EstimatorConfig(), 5, 1), np.zeros((5, 3)))
    cfg = EstimatorConfig(tilt_error_std_deg=2.0, accel_bias_std_mps2=0.3)
    a, b = bias_disturbance_ned_mps2(cfg, 2000, 7), bias_disturbance_ned_mps2(cfg, 2000, 7)
    np.testing.assert_array_equal(a, b)  # its own seeded stream
    assert not np.array_equal(a, bias_disturbance_ned_mps2(cfg, 2000, 8))
    np.testing.assert_array_equal(bias_disturbance_ned_mps2(cfg, 3, 7), a[:3])  # vehicle k's draw does not depend on N
    # horizontal: g tan(tilt), the tilt ~ N(0, 2 deg) per axis; vertical: N(0, 0.3)
    assert np.std(a[:, 0]) == pytest.approx(GRAVITY_MPS2 * math.tan(math.radians(2.0)), rel=0.1)
    assert np.std(a[:, 2]) == pytest.approx(0.3, rel=0.1)
    assert abs(np.mean(np.arctan2(a[:, 1], a[:, 0]))) < 0.15  # any direction


def test_hover_thrust_errors_are_uniform_per_vehicle_and_zero_by_default():
    assert AutopilotConfig().hover_thrust_error == 0.0 and AutopilotConfig().name == "px4"
    np.testing.assert_array_equal(hover_thrust_errors(0.0, 4, 3), np.zeros(4))
    e = hover_thrust_errors(0.1, 5000, 3)
    assert np.abs(e).max() <= 0.1 and e.min() < -0.09 and e.max() > 0.09
    np.testing.assert_array_equal(e[:10], hover_thrust_errors(0.1, 10, 3))


def test_zero_bias_and_no_loop_fly_as_before():
    """An external acceleration of zero, and a controller whose rows have no loop, change nothing."""
    vp = VehicleParams()
    sp = FleetSetpoint.empty(2)
    sp.pos_ned_m[:] = (1.0, -2.0, -5.0)
    runs = []
    for kw in ({}, {"acc_ext_ned_mps2": np.zeros((2, 3)), "loop": PositionController(2)}):
        physics = Physics(vp, InnerLoopConfig(), dt_s=DT)
        state = hover_state(2, vp)
        for _ in range(200):
            physics.step(state, sp, 5, **kw)
        runs.append(state.pos_ned_m.copy())
    np.testing.assert_array_equal(runs[0], runs[1])
