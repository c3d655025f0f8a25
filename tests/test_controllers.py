"""Geometric and PID controllers: recovery, pole matching, setpoint semantics."""
import dataclasses

import numpy as np
import pytest

from companion import frames
from companion.control.geometric import geometric_control, max_thrust_n
from companion.control.pid import pid_control, pid_gains_per_unit
from companion.control.so3 import exp_so3_np
from companion.params import GRAVITY_MPS2, GeometricGains, InnerLoopConfig, PIDGains, VehicleParams
from companion.state import FleetSetpoint, FleetState
from sim_bridge.world.physics import Physics, hover_state

VP = VehicleParams()
GG = GeometricGains()


def _psi(r, r_d):
    """psi(R, R_d) = 1/2 tr(I - R_d^T R), batched."""
    return 0.5 * np.trace(np.eye(3) - np.swapaxes(r_d, -1, -2) @ r, axis1=-2, axis2=-1)


def _settle_time(ctrl, rot0, vel0, t_end=3.0, gains=GG):
    """Time after which tilt < 5 deg and |v| < 0.2 m/s hold until t_end (velocity-zero setpoint)."""
    n = rot0.shape[0]
    ph = Physics(VP, InnerLoopConfig(controller=ctrl, geometric=gains))
    st = hover_state(n, VP)
    st.rot_body_to_ned[:] = rot0
    st.vel_ned_mps[:] = vel0
    sp = FleetSetpoint.empty(n)
    sp.vel_ned_mps[:] = 0.0
    last_bad = np.zeros(n)
    k_per = 10
    for k in range(int(round(t_end / 1e-3)) // k_per):
        ph.step(st, sp, n_steps=k_per)
        ok = (np.degrees(frames.tilt_rad(st.rot_body_to_ned)) < 5.0) & (np.linalg.norm(st.vel_ned_mps, axis=1) < 0.2)
        last_bad[~ok] = (k + 1) * k_per * 1e-3
    return last_bad


def test_geometric_recovers_from_90deg_roll_at_5mps_within_1p5s():
    rot0 = frames.euler_zyx_to_rot(np.radians([90.0, -90.0, 90.0, 0.0, 60.0]),
                                   np.radians([0.0, 0.0, 0.0, 90.0 - 1e-6, 45.0]),
                                   np.radians([0.0, 0.0, 1.0, 0.0, -2.0]))
    t = _settle_time("geometric", rot0, np.array([5.0, 0.0, 0.0]))
    assert np.all(t < 1.3), t  # requirement 1.5 s; paper case (first) measured 1.0 s


def test_geometric_converges_from_many_attitudes():
    rng = np.random.default_rng(11)
    q = rng.normal(size=(40, 4))
    rots = frames.quat_wxyz_to_rot(q)
    rots = np.concatenate([rots, frames.euler_zyx_to_rot(np.radians([179.0, -179.0]), 0.0, 0.0)[:]], axis=0)
    n = rots.shape[0]
    assert np.all(_psi(rots, np.eye(3)) < 2.0)
    ph = Physics(VP, InnerLoopConfig(controller="geometric"))
    st = hover_state(n, VP, pos_ned_m=np.zeros((n, 3)))
    st.rot_body_to_ned[:] = rots
    sp = FleetSetpoint.empty(n)
    sp.pos_ned_m[:] = 0.0
    sp.yaw_rad[:] = 0.0
    worst_tilt = np.zeros(n)
    for _ in range(100):  # 10 s; after the first 5 s the fleet must be upright
        ph.step(st, sp, n_steps=100)
        worst_tilt = np.maximum(worst_tilt, frames.tilt_rad(st.rot_body_to_ned)) if _ >= 50 else worst_tilt
    assert np.degrees(worst_tilt).max() < 20.0
    assert np.all(_psi(st.rot_body_to_ned, np.eye(3)) < 1e-8)
    assert np.all(np.linalg.norm(st.omega_body_radps, axis=1) < 1e-3)
    np.testing.assert_allclose(st.pos_ned_m, 0.0, atol=0.01)
    np.testing.assert_allclose(st.vel_ned_mps, 0.0, atol=0.01)


# ----------------------------------------------------------------------------- pole matching

def _closed_loop_jacobian(ctrl, sp, vp, gains, pid):
    """Continuous-time Jacobian about level hover at the origin (rotor lag must be 0).

    State z = [x (3), v (3), delta (3), omega (3)] (+ xi (6) for the PID), R = exp(hat(delta)).
    """
    nz = 12 if ctrl == "geometric" else 18
    j = np.array([vp.inertia_xx_kgm2, vp.inertia_yy_kgm2, vp.inertia_zz_kgm2])

    def deriv(z):
        st = FleetState.zeros(1)
        st.pos_ned_m[0], st.vel_ned_mps[0], st.omega_body_radps[0] = z[0:3], z[3:6], z[9:12]
        st.rot_body_to_ned[0] = exp_so3_np(z[6:9])
        if ctrl == "geometric":
            f, m = geometric_control(st, sp, vp, gains)
        else:
            st.ctrl_integral[0] = z[12:18]
            f, m = pid_control(st, sp, vp, gains, pid, dt_s=1.0)  # xi += 1.0 * rate: exact rate
        w = z[9:12]
        dz = np.zeros(nz)
        dz[0:3] = z[3:6]
        dz[3:6] = GRAVITY_MPS2 * np.array([0, 0, 1.0]) - f[0] / vp.mass_kg * st.rot_body_to_ned[0, :, 2]
        dz[6:9] = w  # d/dt of exp coordinates at delta = 0, to first order
        dz[9:12] = (m[0] - np.cross(w, j * w)) / j
        if ctrl == "pid":
            dz[12:18] = st.ctrl_integral[0] - z[12:18]
        return dz

    eps = 1e-7
    cols = [(deriv(e * eps) - deriv(-e * eps)) / (2 * eps) for e in np.eye(nz)]
    return np.array(cols).T


def _match(eig_geo, eig_pid, tol):
    """Remove each geometric eigenvalue from the PID set (nearest match); return the rest."""
    rest = list(eig_pid)
    worst = 0.0
    for lam in eig_geo:
        k = int(np.argmin([abs(lam - mu) for mu in rest]))
        worst = max(worst, abs(lam - rest[k]) / (1.0 + abs(lam)))
        rest.pop(k)
    assert worst < tol, worst
    return np.sort_complex(np.array(rest))


# distinct (not critically damped) poles so that finite-difference eigenvalues are well conditioned
GAINS_LIN = GeometricGains(kR_per_s2=400.0, kOmega_per_s=30.0, kx_per_s2=4.0, kv_per_s=5.0)
VP_LIN = VehicleParams(motor_time_constant_s=0.0)


def test_pid_gain_algebra():
    """(s^2 + a s + b)(s + p) == s^3 + Kd' s^2 + Kp' s + Ki, and the velocity-loop analogue."""
    pid = PIDGains(att_integral_pole_per_s=3.0, vel_integral_pole_per_s=0.7)
    g = pid_gains_per_unit(GAINS_LIN, pid)
    a, b, p = GAINS_LIN.kOmega_per_s, GAINS_LIN.kR_per_s2, 3.0
    np.testing.assert_allclose(np.polymul([1, a, b], [1, p]), [1, g["att_kd_per_s"], g["att_kp_per_s2"], g["att_ki_per_s3"]])
    kx, kv, pv = GAINS_LIN.kx_per_s2, GAINS_LIN.kv_per_s, 0.7
    # position axis, ideal attitude: s^3 + Kv' s^2 + (Kx' + Ki) s + Ki kx / kv
    np.testing.assert_allclose(np.polymul([1, kv, kx], [1, pv]),
                               [1, g["vel_kp_per_s"], g["pos_kp_per_s2"] + g["vel_ki_per_s2"], g["vel_ki_per_s2"] * kx / kv])
    # velocity-only axis: s^2 + Kv' s + Ki
    np.testing.assert_allclose(np.polymul([1, kv], [1, pv]), [1, g["vel_kp_per_s"], g["vel_ki_per_s2"]])


def test_small_angle_poles_attitude_mode_match_exactly():
    pid = PIDGains(att_integral_pole_per_s=2.0, vel_integral_pole_per_s=0.5)
    sp = FleetSetpoint.empty(1)
    sp.att_q_wxyz[0] = [1.0, 0, 0, 0]
    sp.thrust_norm[0] = VP_LIN.mass_kg * GRAVITY_MPS2 / max_thrust_n(VP_LIN)
    eg = np.linalg.eigvals(_closed_loop_jacobian("geometric", sp, VP_LIN, GAINS_LIN, pid))
    ep = np.linalg.eigvals(_closed_loop_jacobian("pid", sp, VP_LIN, GAINS_LIN, pid))
    rest = _match(eg, ep, tol=1e-5)
    # the extra modes: 3 attitude integrators at -p_att, 3 idle velocity integrators at 0
    np.testing.assert_allclose(np.sort(rest.real), [-2.0, -2.0, -2.0, 0, 0, 0], atol=1e-5)
    np.testing.assert_allclose(rest.imag, 0.0, atol=1e-6)


def test_small_angle_poles_position_hold_full_cascade():
    sp = FleetSetpoint.empty(1)
    sp.pos_ned_m[0] = 0.0
    sp.yaw_rad[0] = 0.0
    eg = np.linalg.eigvals(_closed_loop_jacobian("geometric", sp, VP_LIN, GAINS_LIN, None))
    assert np.all(eg.real < -0.5)  # the geometric closed loop is stable about hover
    # attitude integrators only: geometric poles exact, extra = -p_att (x3) and idle xi_v at 0 (x3)
    pid = PIDGains()  # the defaults: attitude integrators on, velocity integrator off
    ep = np.linalg.eigvals(_closed_loop_jacobian("pid", sp, VP_LIN, GAINS_LIN, pid))
    rest = _match(eg, ep, tol=1e-5)
    np.testing.assert_allclose(np.sort(rest.real), [-2.0, -2.0, -2.0, 0, 0, 0], atol=1e-5)
    # a velocity integrator: exact only with an ideal attitude loop (test_pid_gain_algebra);
    # through the finite-bandwidth attitude loop the outer poles shift (see docs/controllers.md)
    pid = PIDGains(att_integral_pole_per_s=2.0, vel_integral_pole_per_s=0.5)
    ep = np.linalg.eigvals(_closed_loop_jacobian("pid", sp, VP_LIN, GAINS_LIN, pid))
    assert np.all(ep.real < 0)
    # vertical (s^2 + kv s + kx) and yaw (s^2 + kOm s + kR) loops have no attitude dynamics in
    # between: exact, plus the vertical integrator pole at exactly -p_vel
    exact = np.concatenate([np.roots([1, GAINS_LIN.kv_per_s, GAINS_LIN.kx_per_s2]),
                            np.roots([1, GAINS_LIN.kOmega_per_s, GAINS_LIN.kR_per_s2]), [-0.5]])
    for lam in exact:
        assert np.min(np.abs(ep - lam)) < 1e-5, lam
    # horizontal: measured worst shift 15 % (-8.09 -> -9.30); all geometric poles within 20 %
    rest = _match(eg, ep, tol=0.2)
    assert np.sum(np.isclose(rest, -2.0, atol=1e-5)) == 3


# ----------------------------------------------------------------------------- setpoint semantics

def _fly(ctrl, st, sp, seconds, **kw):
    ph = Physics(VP, InnerLoopConfig(controller=ctrl, **kw))
    ph.step(st, sp, n_steps=int(round(seconds / 1e-3)))
    return ph


def test_hover_outputs_and_all_nan_setpoint():
    st = hover_state(2, VP)
    for sp in (FleetSetpoint.empty(2), _pos_sp(2, 0.0)):
        f, m = geometric_control(st, sp, VP, GG)
        np.testing.assert_allclose(f, VP.mass_kg * GRAVITY_MPS2, rtol=1e-12)
        np.testing.assert_allclose(m, 0.0, atol=1e-15)
        f, m = pid_control(st.copy(), sp, VP, GG, PIDGains(), 1e-3)
        np.testing.assert_allclose(f, VP.mass_kg * GRAVITY_MPS2, rtol=1e-12)
        np.testing.assert_allclose(m, 0.0, atol=1e-15)
    with pytest.raises(ValueError):
        geometric_control(st, FleetSetpoint.empty(3), VP, GG)


def _pos_sp(n, value):
    sp = FleetSetpoint.empty(n)
    sp.pos_ned_m[:] = value
    return sp


@pytest.mark.parametrize("ctrl", ["geometric", "pid"])
def test_position_only_holds_and_returns(ctrl):
    st = hover_state(1, VP, pos_ned_m=[[1.0, -2.0, -3.0]])
    st.vel_ned_mps[0] = [0.5, 0.3, -0.2]
    _fly(ctrl, st, _pos_sp(1, [[1.0, -2.0, -3.0]]), 8.0)
    np.testing.assert_allclose(st.pos_ned_m[0], [1.0, -2.0, -3.0], atol=0.02)
    np.testing.assert_allclose(st.vel_ned_mps[0], 0.0, atol=0.02)


@pytest.mark.parametrize("ctrl", ["geometric", "pid"])
def test_accel_only_produces_that_acceleration(ctrl):
    acc = np.array([1.0, -0.5, -0.3])
    st = hover_state(1, VP)
    sp = FleetSetpoint.empty(1)
    sp.acc_ned_mps2[0] = acc
    _fly(ctrl, st, sp, 2.0)  # let the 72 ms motors and the attitude loop settle
    v0 = st.vel_ned_mps[0].copy()
    _fly(ctrl, st, sp, 0.5)
    np.testing.assert_allclose((st.vel_ned_mps[0] - v0) / 0.5, acc, atol=2e-3)


@pytest.mark.parametrize("ctrl", ["geometric", "pid"])
def test_yaw_setpoint_and_yaw_rate(ctrl):
    st = hover_state(2, VP)
    sp = _pos_sp(2, 0.0)
    sp.yaw_rad[0] = 2.5
    sp.yaw_rate_radps[1] = 0.8
    _fly(ctrl, st, sp, 3.0)
    assert abs(frames.wrap_pi(frames.yaw_rad(st.rot_body_to_ned[0]) - 2.5)) < 2e-3
    y0 = frames.yaw_rad(st.rot_body_to_ned[1])
    _fly(ctrl, st, sp, 0.5)
    assert abs(frames.wrap_pi(frames.yaw_rad(st.rot_body_to_ned[1]) - y0) - 0.4) < 5e-3


@pytest.mark.parametrize("ctrl", ["geometric", "pid"])
def test_attitude_mode_quaternion_and_thrust_norm(ctrl):
    st = hover_state(2, VP)
    sp = FleetSetpoint.empty(2)
    sp.att_q_wxyz[0] = frames.euler_zyx_to_quat_wxyz(0.0, 0.0, 0.0)
    sp.thrust_norm[0] = 0.7
    sp.att_q_wxyz[1] = frames.euler_zyx_to_quat_wxyz(np.radians(10.0), np.radians(-5.0), 0.3)
    sp.thrust_norm[1] = 0.5
    _fly(ctrl, st, sp, 3.0)  # PID yaw (no setpoint weight) keeps a slow integrator tail
    v0 = st.vel_ned_mps.copy()
    _fly(ctrl, st, sp, 0.2)
    a = (st.vel_ned_mps - v0) / 0.2
    fmax = max_thrust_n(VP)
    assert abs(a[0, 2] - (GRAVITY_MPS2 - 0.7 * fmax / VP.mass_kg)) < 1e-2
    np.testing.assert_allclose(frames.rot_to_euler_zyx(st.rot_body_to_ned[1]), [np.radians(10.0), np.radians(-5.0), 0.3],
                               atol=2e-3)
    expected = GRAVITY_MPS2 * np.array([0, 0, 1.0]) - 0.5 * fmax / VP.mass_kg * st.rot_body_to_ned[1, :, 2]
    np.testing.assert_allclose(a[1], expected, atol=1e-2)


@pytest.mark.parametrize("large_angle, overshoot_deg", [(False, 5.0), (True, 6.0)])
def test_tilt_and_thrust_limits_hold_on_a_long_reposition(large_angle, overshoot_deg):
    st = hover_state(1, VP)
    sp = _pos_sp(1, [[200.0, 0.0, 0.0]])
    gains = dataclasses.replace(GG, large_angle=large_angle)
    ph = Physics(VP, InnerLoopConfig(controller="geometric", geometric=gains))
    worst = 0.0
    for _ in range(200):
        ph.step(st, sp, n_steps=10)
        worst = max(worst, frames.tilt_rad(st.rot_body_to_ned[0]))
    # The commanded tilt is clipped; the 72 ms motors let the real tilt overshoot it by a few
    # degrees. The large-angle error is 2 sin(25 deg) = 0.85 for this 50 deg step where eq. 7's
    # is sin(50 deg) = 0.77: a stiffer step, about 2 deg more overshoot.
    assert np.degrees(worst) < GG.tilt_max_deg + overshoot_deg
    assert np.degrees(worst) > GG.tilt_max_deg - 5.0  # the limit is what binds
    assert abs(st.vel_ned_mps[0, 2]) < 0.3  # vertical priority: altitude held while tilting
