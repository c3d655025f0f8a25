"""PID cascade baseline, pole-matched to the geometric controller (docs/controllers.md).

Structure per vehicle:
    1. Velocity/position loop per NED axis (same masks as the geometric controller):
           a = a_ff - k_x e_x - (k_v + p_v) e_v + k_v p_v xi_v,
           xi_v' = v_sp - v = -(k_x / k_v) e_x - e_v   (position axis)   or  -e_v (velocity-only axis),
       i.e. PX4's cascade velocity error is integrated. With an ideal inner loop this gives
       (s^2 + k_v s + k_x)(s + p_v) on a position axis and (s + k_v)(s + p_v) on a
       velocity axis: the geometric poles plus one real pole at -p_v.
    2. Same acceleration/tilt/thrust saturation as the geometric controller, then the
       small-angle cascade: desired roll/pitch (ZYX) from the thrust direction and the
       yaw target, thrust = upward force / (cos roll cos pitch), clipped to [0, f_max].
    3. Attitude PID on wrapped ZYX Euler errors e, D on body rates, per unit inertia:
           alpha = K_p' e + K_i xi - K_d' (omega - omega_ff) [- (K_p' - k_R) theta_d on roll/pitch],
           K_p' = k_R + k_Om p,  K_d' = k_Om + p,  K_i = k_R p,  M = J alpha,
       so s^3 + K_d' s^2 + K_p' s + K_i = (s^2 + k_Om s + k_R)(s + p). The setpoint weight
       beta = k_R / K_p' on roll/pitch places the closed-loop zero at -p so that the
       integrator mode does not couple into the outer loop.

Integrator memory is FleetState.ctrl_integral: [0:3] attitude (roll, pitch, yaw) in
rad s, [3:6] velocity (N, E, D) in m; both clamped (anti-windup).
"""
from __future__ import annotations

import math

import numpy as np

from companion.control.geometric import (
    CP_FMAX,
    CP_G,
    CP_JXX,
    CP_JYY,
    CP_JZZ,
    CP_KOM,
    CP_KR,
    CP_KV,
    CP_KX,
    CP_P_ATT,
    CP_P_VEL,
    SP_ACC,
    SP_POS,
    SP_Q,
    SP_VEL,
    attitude_mode_target,
    pack_control_params,
    pack_setpoint,
    thrust_vector,
    yaw_target,
)
from companion.control.kernel import kernel
from companion.control.so3 import load_mat, norm
from companion.params import GeometricGains, PIDGains, VehicleParams
from companion.state import FleetSetpoint, FleetState

ATT_INTEGRAL_AUTHORITY = 0.2
"""|K_i xi_att| is clamped to this fraction of k_R (rad/s^2 per rad of P authority)."""
VEL_INTEGRAL_AUTHORITY_G = 0.3
"""|k_v p_v xi_vel| is clamped to this many g."""


@kernel(inline="always")
def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@kernel(inline="always")
def _clamp(x, lim):
    return min(max(x, -lim), lim)


@kernel
def _axis_pid(p, v, sp, k, kx, kv, pv, xi):
    """(a_k, xi_k') of one NED axis with the offboard masks."""
    a = sp[SP_ACC + k]
    a = a if math.isfinite(a) else 0.0
    pd, vd = sp[SP_POS + k], sp[SP_VEL + k]
    if math.isfinite(pd):
        ex = p[k] - pd
        ev = v[k] - (vd if math.isfinite(vd) else 0.0)
        a += -kx * ex - (kv + pv) * ev + kv * pv * xi
        dxi = -ev - (kx / kv * ex if kv > 0.0 else 0.0)
        return a, dxi
    if math.isfinite(vd):
        ev = v[k] - vd
        a += -(kv + pv) * ev + kv * pv * xi
        return a, -ev
    return a, 0.0


@kernel
def pid_core(pos, vel, rot, om, sp, prm, xi, dt):
    """One vehicle: (f [N], M [N m] 3-tuple, xi' 6-tuple) advancing the integrators by dt."""
    kr, kom, pa = prm[CP_KR], prm[CP_KOM], prm[CP_P_ATT]
    kp, kd, ki = kr + kom * pa, kom + pa, kr * pa
    roll, pitch, yaw = math.atan2(rot[7], rot[8]), math.asin(min(max(-rot[6], -1.0), 1.0)), math.atan2(rot[3], rot[0])
    xv0, xv1, xv2 = xi[3], xi[4], xi[5]
    if math.isfinite(sp[SP_Q]):
        rot_d, f, om_ff = attitude_mode_target(sp, prm)
        roll_d = math.atan2(rot_d[7], rot_d[8])
        pitch_d = math.asin(min(max(-rot_d[6], -1.0), 1.0))
        yaw_d = math.atan2(rot_d[3], rot_d[0])
    else:
        kx, kv, pv = prm[CP_KX], prm[CP_KV], prm[CP_P_VEL]
        ax, d0 = _axis_pid(pos, vel, sp, 0, kx, kv, pv, xv0)
        ay, d1 = _axis_pid(pos, vel, sp, 1, kx, kv, pv, xv1)
        az, d2 = _axis_pid(pos, vel, sp, 2, kx, kv, pv, xv2)
        vlim = VEL_INTEGRAL_AUTHORITY_G * prm[CP_G] / (kv * pv) if kv * pv > 0.0 else 1.0
        xv0, xv1, xv2 = _clamp(xv0 + dt * d0, vlim), _clamp(xv1 + dt * d1, vlim), _clamp(xv2 + dt * d2, vlim)
        t = thrust_vector(ax, ay, az, prm)
        tn = norm(t)
        yaw_d, yaw_rate = yaw_target(rot, sp)
        # desired roll/pitch: b3d = -t/|t| seen in the yaw-only frame is Ry(pitch) Rx(roll) e3
        cy, sy = math.cos(yaw_d), math.sin(yaw_d)
        ux = -(cy * t[0] + sy * t[1]) / tn
        uy = -(-sy * t[0] + cy * t[1]) / tn
        uz = -t[2] / tn
        pitch_d = math.atan2(ux, uz)
        roll_d = math.atan2(-uy, math.sqrt(ux * ux + uz * uz))
        c = rot[8]  # cos(roll) cos(pitch)
        f = min(-t[2] / c, prm[CP_FMAX]) if c > 0.0 else 0.0
        f = max(f, 0.0)
        om_ff = (rot[6] * yaw_rate, rot[7] * yaw_rate, rot[8] * yaw_rate)
    e0, e1, e2 = _wrap(roll_d - roll), _wrap(pitch_d - pitch), _wrap(yaw_d - yaw)
    a0 = kp * e0 - (kp - kr) * roll_d + ki * xi[0] - kd * (om[0] - om_ff[0])
    a1 = kp * e1 - (kp - kr) * pitch_d + ki * xi[1] - kd * (om[1] - om_ff[1])
    a2 = kp * e2 + ki * xi[2] - kd * (om[2] - om_ff[2])
    alim = ATT_INTEGRAL_AUTHORITY / pa if pa > 0.0 else 1.0
    xi_new = (_clamp(xi[0] + dt * e0, alim), _clamp(xi[1] + dt * e1, alim), _clamp(xi[2] + dt * e2, alim),
              xv0, xv1, xv2)
    m = (prm[CP_JXX] * a0, prm[CP_JYY] * a1, prm[CP_JZZ] * a2)
    return f, m, xi_new


@kernel
def _pid_batch(pos, vel, rot, om, integ, sp, prm, dt, thrust_out, moment_out):
    for i in range(pos.shape[0]):
        xi = (integ[i, 0], integ[i, 1], integ[i, 2], integ[i, 3], integ[i, 4], integ[i, 5])
        f, m, xi = pid_core((pos[i, 0], pos[i, 1], pos[i, 2]), (vel[i, 0], vel[i, 1], vel[i, 2]),
                            load_mat(rot, i), (om[i, 0], om[i, 1], om[i, 2]), sp[i], prm, xi, dt)
        thrust_out[i] = f
        moment_out[i, 0], moment_out[i, 1], moment_out[i, 2] = m
        for k in range(6):
            integ[i, k] = xi[k]


def pid_gains_per_unit(gains: GeometricGains, pid: PIDGains) -> dict[str, float]:
    """The derived per-unit gains (for docs and tests): attitude Kp', Kd', Ki, beta; velocity."""
    b, a, p = gains.kR_per_s2, gains.kOmega_per_s, pid.att_integral_pole_per_s
    kx, kv, pv = gains.kx_per_s2, gains.kv_per_s, pid.vel_integral_pole_per_s
    return {"att_kp_per_s2": b + a * p, "att_kd_per_s": a + p, "att_ki_per_s3": b * p,
            "att_setpoint_weight": b / (b + a * p), "pos_kp_per_s2": kx, "vel_kp_per_s": kv + pv,
            "vel_ki_per_s2": kv * pv}


def pid_control(state: FleetState, sp: FleetSetpoint, vp: VehicleParams, gains: GeometricGains,
                pid: PIDGains, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """PID cascade for a fleet; advances state.ctrl_integral by dt_s in place.

    Returns:
        thrust_n (N,), moment_body_nm (N, 3).
    Raises:
        ValueError: if state and setpoint sizes differ or dt_s is not positive.
    """
    if sp.n != state.n:
        raise ValueError(f"setpoint N={sp.n} != state N={state.n}")
    if not dt_s > 0:
        raise ValueError("dt_s must be > 0")
    integ = np.ascontiguousarray(state.ctrl_integral, float)
    thrust, moment = np.empty(state.n), np.empty((state.n, 3))
    _pid_batch(np.ascontiguousarray(state.pos_ned_m, float), np.ascontiguousarray(state.vel_ned_mps, float),
               np.ascontiguousarray(state.rot_body_to_ned, float), np.ascontiguousarray(state.omega_body_radps, float),
               integ, pack_setpoint(sp), pack_control_params(vp, gains, pid), float(dt_s), thrust, moment)
    state.ctrl_integral[...] = integ
    return thrust, moment
