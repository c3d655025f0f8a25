"""Geometric SE(3) controller (paper eq. 7-16), NED world / FRD body.

Sign conventions (see docs/controllers.md for the derivation):
    * eq. 2: m vdot = m g e3 - f R e3, so thrust acts along -b3 (up when level).
    * The desired thrust *vector* (NED, newtons) is
      t = m (a_cmd - g e3) = -k_x e_x - k_v e_v - m g e3 + m xddot_d  (eq. 16's numerator);
      the body must point b3 opposite to it: b3d = -t / |t|. The paper prints eq. 16
      without the minus sign; with eq. 2's sign convention that would command an
      inverted vehicle, so the evident intent (Lee et al. 2010) is implemented.
    * f = -t . R e3 (eq. 14), clipped to [0, f_max]: hover with R = I gives f = m g.

Setpoint semantics follow PX4 offboard (see FleetSetpoint). All per-vehicle maths
lives in kernels operating on tuples (companion.control.kernel): the companion runs
them interpreted, the fused physics stepper compiled; ``geometric_control`` is a
thin batch wrapper looping the same core.
"""
from __future__ import annotations

import math

import numpy as np

from companion.control.kernel import kernel
from companion.control.so3 import cross, load_mat, mattmul, mattvec, mul, norm, scale, sub
from companion.frames import quat_wxyz_to_rot9 as quat_to_rot
from companion.frames import rot9_to_quat_wxyz as rot_to_quat
from companion.params import GRAVITY_MPS2, GeometricGains, PIDGains, VehicleParams
from companion.state import FleetSetpoint, FleetState

# ---- controller parameter vector layout (float64 array, built by pack_control_params)
CP_MASS, CP_G, CP_JXX, CP_JYY, CP_JZZ, CP_FMAX = 0, 1, 2, 3, 4, 5
CP_KX, CP_KV, CP_KR, CP_KOM, CP_TAN_TILT, CP_ACC_MAX = 6, 7, 8, 9, 10, 11
CP_P_ATT, CP_P_VEL = 12, 13
CP_LARGE_ANGLE, CP_YAW_SHARE = 14, 15
N_CP = 16

# ---- packed setpoint row layout (N, N_SP), built by pack_setpoint
SP_POS, SP_VEL, SP_ACC, SP_YAW, SP_YAWRATE, SP_Q, SP_THRUST, SP_RATE = 0, 3, 6, 9, 10, 11, 15, 16
N_SP = 19
_SP_FIELDS = ("vel_ned_mps", "acc_ned_mps2", "yaw_rad", "yaw_rate_radps", "att_q_wxyz", "thrust_norm",
              "body_rate_radps")

MIN_VERTICAL_THRUST_FRAC = 0.05
"""Lowest upward thrust component kept, as a fraction of weight: commands that ask for
more than 1 g downward are clipped here so that b3d stays defined and upright."""


def max_thrust_n(vp: VehicleParams) -> float:
    """Collective thrust with all rotors at rotor_speed_max: 4 k_f Q_max^2 (N)."""
    return 4.0 * vp.thrust_coeff_n_per_radps2 * vp.rotor_speed_max_radps ** 2


def pack_control_params(vp: VehicleParams, gains: GeometricGains, pid: PIDGains | None = None) -> np.ndarray:
    """Flatten the parameters the controller cores need into a float64 (N_CP,) array."""
    pid = pid or PIDGains()
    p = np.zeros(N_CP)
    p[CP_MASS], p[CP_G] = vp.mass_kg, GRAVITY_MPS2
    p[CP_JXX], p[CP_JYY], p[CP_JZZ] = vp.inertia_xx_kgm2, vp.inertia_yy_kgm2, vp.inertia_zz_kgm2
    p[CP_FMAX] = max_thrust_n(vp)
    p[CP_KX], p[CP_KV] = gains.kx_per_s2, gains.kv_per_s
    p[CP_KR], p[CP_KOM] = gains.kR_per_s2, gains.kOmega_per_s
    p[CP_TAN_TILT] = math.tan(math.radians(gains.tilt_max_deg))
    p[CP_ACC_MAX] = gains.acc_max_mps2
    p[CP_P_ATT], p[CP_P_VEL] = pid.att_integral_pole_per_s, pid.vel_integral_pole_per_s
    p[CP_LARGE_ANGLE] = 1.0 if gains.large_angle else 0.0
    p[CP_YAW_SHARE] = gains.yaw_error_max_rad
    return p


def pack_setpoint(sp: FleetSetpoint) -> np.ndarray:
    """(N, N_SP) float64 array of a FleetSetpoint, column layout SP_*.

    Raises:
        ValueError: if the setpoint arrays do not share the first axis N.
    """
    block = sp.pos_ned_m.base
    if block is not None and block.shape == (sp.pos_ned_m.shape[0], N_SP) and block.dtype == np.float64 \
            and block.flags.c_contiguous and all(getattr(sp, f).base is block for f in _SP_FIELDS):
        return block  # made by FleetSetpoint.empty: its block has this layout already
    cols = [sp.pos_ned_m, sp.vel_ned_mps, sp.acc_ned_mps2, sp.yaw_rad[:, None], sp.yaw_rate_radps[:, None],
            sp.att_q_wxyz, sp.thrust_norm[:, None], sp.body_rate_radps]
    n = sp.pos_ned_m.shape[0]
    if any(c.shape[0] != n for c in cols):
        raise ValueError("FleetSetpoint arrays disagree on N")
    return np.ascontiguousarray(np.concatenate([np.asarray(c, float).reshape(n, -1) for c in cols], axis=1))


# ----------------------------------------------------------------------------- shared kernels

@kernel
def thrust_vector(ax, ay, az, prm):
    """Saturated desired thrust vector t = m (a - g e3) in NED newtons.

    Order: (1) |a| <= acc_max; (2) upward component >= MIN_VERTICAL_THRUST_FRAC * m g;
    (3) tilt: horizontal <= vertical * tan(tilt_max), vertical kept (vertical priority);
    (4) |t| <= f_max, vertical kept first, horizontal gets what is left.
    """
    m, g = prm[CP_MASS], prm[CP_G]
    an = math.sqrt(ax * ax + ay * ay + az * az)
    amax = prm[CP_ACC_MAX]
    if an > amax:
        s = amax / an
        ax, ay, az = ax * s, ay * s, az * s
    tx, ty, tz = m * ax, m * ay, m * (az - g)
    tz = min(tz, -MIN_VERTICAL_THRUST_FRAC * m * g)
    fmax = prm[CP_FMAX]
    if -tz >= fmax:
        return 0.0, 0.0, -fmax
    hmax = min(-tz * prm[CP_TAN_TILT], math.sqrt(fmax * fmax - tz * tz))
    h = math.sqrt(tx * tx + ty * ty)
    if h > hmax:
        s = hmax / h
        tx, ty = tx * s, ty * s
    return tx, ty, tz


@kernel
def yaw_target(rot, sp):
    """(yaw_d, yaw_rate_ff): yaw_rad if finite; else current heading + yaw-rate feed-forward.

    Without a yaw angle the yaw error is zero by construction and the rate term of the
    attitude law tracks yaw_rate (0 when NaN), so yaw integrates the commanded rate
    without controller memory.
    """
    rate = sp[SP_YAWRATE]
    if not math.isfinite(rate):
        rate = 0.0
    yaw = sp[SP_YAW]
    if math.isfinite(yaw):
        return yaw, rate
    return math.atan2(rot[3], rot[0]), rate


@kernel
def desired_rot(b3, yaw):
    """eq. 15: R_d = [b1d, b3d x b1d, b3d], b1d = heading projected perpendicular to b3d."""
    b1c = (math.cos(yaw), math.sin(yaw), 0.0)
    b2 = cross(b3, b1c)
    n2 = norm(b2)
    if n2 < 1e-6:  # b3d horizontal along the heading (excluded by the tilt limit): use world e2
        b2 = cross(b3, (-math.sin(yaw), math.cos(yaw), 0.0))
        b2 = cross(b2, b3)
        n2 = norm(b2)
    b2 = scale(b2, 1.0 / n2)
    b1 = cross(b2, b3)
    return (b1[0], b2[0], b3[0], b1[1], b2[1], b3[1], b1[2], b2[2], b3[2])


@kernel
def attitude_law(rot, rot_d, om, om_d, prm):
    """eq. 7-9 with Omegadot_d = 0. Gains are per unit inertia: k_R = J kR, k_Om = J kOm.

    Returns the body moment (3-tuple, N m).
    """
    j = (prm[CP_JXX], prm[CP_JYY], prm[CP_JZZ])
    rdt_r = mattmul(rot_d, rot)
    # eq. 7: e_R = 1/2 vee(R_d^T R - R^T R_d); vee of (A - A^T) is twice vee's antisymmetric part
    e_r = (0.5 * (rdt_r[7] - rdt_r[5]), 0.5 * (rdt_r[2] - rdt_r[6]), 0.5 * (rdt_r[3] - rdt_r[1]))
    om_d_body = mattvec(rdt_r, om_d)          # R^T R_d Omega_d
    e_om = sub(om, om_d_body)
    kr, kom = prm[CP_KR], prm[CP_KOM]
    jom = mul(j, om)
    gyro = cross(om, jom)                     # Omega x J Omega
    ff = mul(j, cross(om, om_d_body))     # J hat(Omega) R^T R_d Omega_d
    return (-kr * j[0] * e_r[0] - kom * j[0] * e_om[0] + gyro[0] - ff[0],
            -kr * j[1] * e_r[1] - kom * j[1] * e_om[1] + gyro[1] - ff[1],
            -kr * j[2] * e_r[2] - kom * j[2] * e_om[2] + gyro[2] - ff[2])


@kernel
def tilt_first_error(rot, rot_d, om, yaw_free):
    """Attitude error for any attitude: (e_tilt_x, e_tilt_y, e_yaw) in the body frame, rad-like.

    The rotation from the current to the desired attitude, q_e = q_xy * q_z (the
    decomposition of Brescianini and D'Andrea, 2018), splits into a tilt about an axis in
    the body xy-plane and a yaw about body z. Each part is returned as 2 vec(q), which is
    the rotation vector to first order (near hover eq. 7, with the sign that M = +k_R J e
    drives it to zero); its magnitude 2 sin(angle/2) grows all the way to 180 deg, where
    eq. 7's sin(angle) falls back to 0 (the error of Lee et al.'s exponentially attractive
    variant, 2011).
    Exactly inverted with no preferred axis, the vehicle tilts about the axis it already
    turns about (or roll), so that two nearby starts do not fight over the direction.
    yaw_free: no yaw is commanded, so the yaw part is 0 and only the tilt is corrected.
    """
    w, x, y, z = rot_to_quat(mattmul(rot, rot_d))  # R^T R_d: current -> desired, body frame
    a = math.sqrt(w * w + z * z)
    if a > 1e-9:
        tx, ty = (w * x - y * z) / a, (w * y + x * z) / a
        cz, sz = w / a, z / a
    else:  # 180 deg about a horizontal body axis
        tx, ty, cz, sz = x, y, 1.0, 0.0
    if a < 1e-6 and abs(tx) + abs(ty) < 1e-9:
        tx, ty = 1.0, 0.0
    if a < 0.05:  # nearly inverted: keep turning the way the body already turns (no chatter)
        if om[0] * tx + om[1] * ty < 0.0:
            tx, ty = -tx, -ty
    ez = 0.0 if yaw_free else 2.0 * sz * (1.0 if cz >= 0.0 else -1.0)
    return 2.0 * tx, 2.0 * ty, ez


@kernel
def attitude_law_large_angle(rot, rot_d, om, om_d, yaw_free, prm):
    """Tilt-first attitude law for any attitude (docs/controllers.md, "Large angles").

    M = J (k_R e - k_Om (Omega - R^T R_d Omega_d)) + Omega x J Omega - J hat(Omega) R^T R_d Omega_d,
    with e from tilt_first_error and the yaw part clipped to CP_YAW_SHARE rad so that a
    large heading error never takes roll/pitch authority (the allocator gives roll/pitch
    priority as well). Near hover this equals attitude_law (eq. 9) to first order.
    """
    j = (prm[CP_JXX], prm[CP_JYY], prm[CP_JZZ])
    ex, ey, ez = tilt_first_error(rot, rot_d, om, yaw_free)
    ymax = prm[CP_YAW_SHARE]
    ez = min(max(ez, -ymax), ymax)
    rdt_r = mattmul(rot_d, rot)
    om_d_body = mattvec(rdt_r, om_d)
    e_om = sub(om, om_d_body)
    kr, kom = prm[CP_KR], prm[CP_KOM]
    gyro = cross(om, mul(j, om))
    ff = mul(j, cross(om, om_d_body))
    return (kr * j[0] * ex - kom * j[0] * e_om[0] + gyro[0] - ff[0],
            kr * j[1] * ey - kom * j[1] * e_om[1] + gyro[1] - ff[1],
            kr * j[2] * ez - kom * j[2] * e_om[2] + gyro[2] - ff[2])


@kernel
def attitude_mode_target(sp, prm):
    """(R_d, f, Omega_d) of an attitude-mode setpoint (att_q_wxyz finite).

    thrust_norm NaN means hover thrust m g; body_rate NaN components are 0.
    """
    rot_d = quat_to_rot(sp[SP_Q], sp[SP_Q + 1], sp[SP_Q + 2], sp[SP_Q + 3])
    tn = sp[SP_THRUST]
    fmax = prm[CP_FMAX]
    f = tn * fmax if math.isfinite(tn) else prm[CP_MASS] * prm[CP_G]
    f = min(max(f, 0.0), fmax)
    r0, r1, r2 = sp[SP_RATE], sp[SP_RATE + 1], sp[SP_RATE + 2]
    om_d = (r0 if math.isfinite(r0) else 0.0, r1 if math.isfinite(r1) else 0.0, r2 if math.isfinite(r2) else 0.0)
    return rot_d, f, om_d


@kernel
def _axis_accel(p, v, sp, k, kx, kv):
    """PD acceleration command on one NED axis k with PX4 offboard masks (eq. 12-13)."""
    a = sp[SP_ACC + k]
    a = a if math.isfinite(a) else 0.0
    pd, vd = sp[SP_POS + k], sp[SP_VEL + k]
    if math.isfinite(pd):
        a -= kx * (p[k] - pd) + kv * (v[k] - (vd if math.isfinite(vd) else 0.0))
    elif math.isfinite(vd):
        a -= kv * (v[k] - vd)
    return a


@kernel
def position_law(pos, vel, rot, sp, prm):
    """eq. 12-16 for a position-family setpoint row: (R_d 9-tuple, f [N], Omega_d 3-tuple).

    The autopilot's inner loop runs it at the physics rate; a companion in attitude
    output mode runs it at its setpoint rate and sends R_d and f as SET_ATTITUDE_TARGET.
    """
    kx, kv = prm[CP_KX], prm[CP_KV]
    ax = _axis_accel(pos, vel, sp, 0, kx, kv)
    ay = _axis_accel(pos, vel, sp, 1, kx, kv)
    az = _axis_accel(pos, vel, sp, 2, kx, kv)
    t = thrust_vector(ax, ay, az, prm)
    tn = norm(t)
    b3d = (-t[0] / tn, -t[1] / tn, -t[2] / tn)
    yaw_d, yaw_rate = yaw_target(rot, sp)
    rot_d = desired_rot(b3d, yaw_d)
    # eq. 14: f = -t . R e3 = |t| cos(phi), phi between b3 and b3d (projection on the body axis).
    f = -(t[0] * rot[2] + t[1] * rot[5] + t[2] * rot[8])
    if prm[CP_LARGE_ANGLE] > 0.0 and rot[8] > 0.0:
        # Thrust scheduled by where body z points (docs/controllers.md, "Large angles").
        # While it is below the horizon (rot[8] = cos tilt > 0), at least the thrust whose
        # vertical part is t's, up to f_max. This only binds when the body is tilted further
        # than b3d (rolling in, the projection is larger): the rotors stay spun up and the
        # height is held while a thrown vehicle rolls back upright. Above the horizon eq. 14's
        # projection is negative: no thrust, so an inverted vehicle never pushes itself at
        # the ground. Near hover (b3 close to b3d) both are |t| to first order.
        f = max(f, min(-t[2] / rot[8], prm[CP_FMAX]))
    f = min(max(f, 0.0), prm[CP_FMAX])
    # yaw rate about world e3, expressed in the desired body frame: R_d^T e3 * rate
    om_d = (rot_d[6] * yaw_rate, rot_d[7] * yaw_rate, rot_d[8] * yaw_rate)
    return rot_d, f, om_d


@kernel
def geometric_core(pos, vel, rot, om, sp, prm):
    """One vehicle: (f [N], M [N m] 3-tuple) from state tuples and a packed setpoint row."""
    if math.isfinite(sp[SP_Q]):
        rot_d, f, om_d = attitude_mode_target(sp, prm)
        yaw_free = False
    else:
        rot_d, f, om_d = position_law(pos, vel, rot, sp, prm)
        yaw_free = not math.isfinite(sp[SP_YAW])
    if prm[CP_LARGE_ANGLE] > 0.0:
        m = attitude_law_large_angle(rot, rot_d, om, om_d, yaw_free, prm)
    else:
        m = attitude_law(rot, rot_d, om, om_d, prm)
    return f, m


@kernel
def _geometric_batch(pos, vel, rot, om, sp, prm, thrust_out, moment_out):
    for i in range(pos.shape[0]):
        f, m = geometric_core((pos[i, 0], pos[i, 1], pos[i, 2]), (vel[i, 0], vel[i, 1], vel[i, 2]),
                              load_mat(rot, i), (om[i, 0], om[i, 1], om[i, 2]), sp[i], prm)
        thrust_out[i] = f
        moment_out[i, 0], moment_out[i, 1], moment_out[i, 2] = m


def geometric_control(state: FleetState, sp: FleetSetpoint, vp: VehicleParams,
                      gains: GeometricGains) -> tuple[np.ndarray, np.ndarray]:
    """Geometric controller for a fleet (the same core the physics stepper compiles).

    Args:
        state: FleetState with N vehicles.
        sp: FleetSetpoint with the same N.
    Returns:
        thrust_n (N,) collective thrust in [0, 4 k_f Q_max^2]; moment_body_nm (N, 3) FRD.
    Raises:
        ValueError: if state and setpoint sizes differ.
    """
    if sp.n != state.n:
        raise ValueError(f"setpoint N={sp.n} != state N={state.n}")
    thrust = np.empty(state.n)
    moment = np.empty((state.n, 3))
    _geometric_batch(np.ascontiguousarray(state.pos_ned_m, float), np.ascontiguousarray(state.vel_ned_mps, float),
                     np.ascontiguousarray(state.rot_body_to_ned, float),
                     np.ascontiguousarray(state.omega_body_radps, float),
                     pack_setpoint(sp), pack_control_params(vp, gains), thrust, moment)
    return thrust, moment
