"""The autopilot's own position and velocity loops (PX4 mc_pos_control PositionControl.cpp,
ArduCopter AC_PosControl), run by the fused physics stepper at every physics step on every
position-family setpoint (position, velocity, acceleration; attitude setpoints bypass it):
they turn the setpoint into the acceleration the inner geometric controller then flies, as
the real autopilots hand their attitude controller a thrust vector. One kernel for both
autopilots: a row's STYLE picks PX4's or ArduPilot's structure, its gains come from the
autopilot's own parameter table (sim_bridge/sitl/autopilots/, `position_loop`).

The autopilot model (`sim_bridge.world.autopilot_model.AutopilotModel`) and the SITL's
vehicles hold one `PositionController` each; the fused physics stepper runs it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from companion.control.geometric import SP_ACC, SP_POS, SP_VEL
from companion.link.limits import SetpointLimits

_PX4_LIMITS = SetpointLimits()
"""PX4's default speed, tilt and thrust limits (MPC_*): one home, companion.link.limits."""

LOOP_OFF, LOOP_PX4, LOOP_ARDUPILOT = 0, 1, 2
"""Gain-row STYLE: no loop (the setpoint goes to the inner controller as it is), PX4, ArduPilot."""

(G_STYLE, G_POS_P_XY, G_POS_P_Z, G_VEL_P_XY, G_VEL_I_XY, G_VEL_D_XY, G_VEL_P_Z, G_VEL_I_Z, G_VEL_D_Z,
 G_VEL_MAX_XY, G_VEL_MAX_UP, G_VEL_MAX_DN, G_TILT_MAX, G_THR_MIN, G_THR_MAX, G_THR_XY_MARGIN, G_HOVER_PARAM,
 G_HOVER_TRUE, G_VEL_IMAX_XY, G_VEL_IMAX_Z, G_ACC_Z_P, G_ACC_Z_I, G_ACC_Z_IMAX, G_VEL_ERR_LP_HZ, G_VEL_Z_ERR_LP_HZ,
 G_VEL_D_LP_HZ, G_ACC_ERR_LP_HZ, G_POS_ACC_XY, G_POS_ACC_Z, G_TILT_COS, G_TILT_SIN) = range(31)
N_G = 31
"""Gain-row layout (SI units: 1/s, 1/s^2, m/s, m/s^2, rad, normalised thrust, Hz)."""
M_INT, M_VPREV, M_DFILT, M_EFILT, M_ACC_I, M_ACC_E, M_LIMIT, M_STARTED = 0, 3, 6, 9, 12, 13, 14, 17
N_M = 18
"""Memory-row layout: velocity integrator (3, m/s^2), previous velocity (3), filtered
derivative term (3), filtered velocity error (3, ArduPilot), vertical acceleration-loop
integrator (thrust) and its filtered error (ArduPilot), the limit vector of the last
step (3, ArduPilot), and whether the row has run since its last reset."""

_ANGLE_BOOST_COS_MIN = 0.1
"""ArduPilot's angle boost divides by max(cos(lean), 0.1) (companion.link.dialects.ardupilot)."""


@dataclass(frozen=True)
class PositionLoopGains:
    """One vehicle's position and velocity loops in SI units, as its autopilot's parameters
    set them (built by the autopilot behaviour from its table: PX4 MPC_*, ArduPilot PSC_*
    converted from cm). Defaults: PX4's (mc_pos_control, v1.14-v1.16).

    style: LOOP_PX4 (P on position, PID on velocity with D on the measured velocity
    derivative, tracking anti-windup horizontally, conditional integration and |I| <= g
    vertically, thrust from the hover-thrust parameter) or LOOP_ARDUPILOT (square-root
    P on position, PID on the filtered velocity error with the integrator held against
    the acceleration limit and clamped to IMAX, an acceleration PI loop to throttle
    vertically). hover_param is what the autopilot believes hovers, hover_true what does.
    """

    style: int = LOOP_PX4
    pos_p_xy_per_s: float = 0.95
    pos_p_z_per_s: float = 1.0
    vel_p_xy_per_s: float = 1.8
    vel_i_xy_per_s2: float = 0.4
    vel_d_xy: float = 0.2
    vel_p_z_per_s: float = 4.0
    vel_i_z_per_s2: float = 2.0
    vel_d_z: float = 0.0
    vel_max_xy_mps: float = _PX4_LIMITS.xy_vel_max_mps
    vel_max_up_mps: float = _PX4_LIMITS.z_vel_max_up_mps
    vel_max_dn_mps: float = _PX4_LIMITS.z_vel_max_dn_mps
    tilt_max_rad: float = _PX4_LIMITS.tilt_max_rad
    thr_min: float = _PX4_LIMITS.thr_min
    thr_max: float = _PX4_LIMITS.thr_max
    thr_xy_margin: float = 0.3
    hover_param: float = 0.5
    hover_true: float = 0.5
    vel_imax_xy_mps2: float = math.inf
    vel_imax_z_mps2: float = math.inf
    acc_z_p_per_mps2: float = 0.0
    """ArduPilot: throttle per m/s^2 of vertical acceleration error (PSC_ACCZ_P / 10)."""
    acc_z_i_per_mps2s: float = 0.0
    """ArduPilot: throttle per m/s^2 s (PSC_ACCZ_I / 10)."""
    acc_z_imax: float = 0.0
    """ArduPilot: integrator limit, throttle (PSC_ACCZ_IMAX / 1000; at least the hover throttle)."""
    vel_err_lp_hz: float = 0.0
    """Low-pass on the horizontal velocity error (ArduPilot PSC_VELXY_FLTE; 0: none)."""
    vel_z_err_lp_hz: float = 0.0
    """Low-pass on the vertical velocity error (ArduPilot PSC_VELZ_FLTE; 0: none)."""
    vel_d_lp_hz: float = 5.0
    """Low-pass of the D term's input (PX4 MPC_VELD_LP, ArduPilot PSC_VELXY_FLTD; 0: none)."""
    acc_err_lp_hz: float = 0.0
    """ArduPilot: low-pass on the vertical acceleration error (PSC_ACCZ_FLTE)."""
    pos_acc_xy_mps2: float = 0.0
    """ArduPilot: the square-root position controller's acceleration (WPNAV_ACCEL; 0: linear P)."""
    pos_acc_z_mps2: float = 0.0
    """ArduPilot: the same vertically (WPNAV_ACCEL_Z)."""

    def row(self) -> np.ndarray:
        """The (N_G,) gain row the kernel reads."""
        return np.array([self.style, self.pos_p_xy_per_s, self.pos_p_z_per_s, self.vel_p_xy_per_s,
                         self.vel_i_xy_per_s2, self.vel_d_xy, self.vel_p_z_per_s, self.vel_i_z_per_s2, self.vel_d_z,
                         self.vel_max_xy_mps, self.vel_max_up_mps, self.vel_max_dn_mps, self.tilt_max_rad,
                         self.thr_min, self.thr_max, self.thr_xy_margin, self.hover_param, self.hover_true,
                         self.vel_imax_xy_mps2, self.vel_imax_z_mps2, self.acc_z_p_per_mps2, self.acc_z_i_per_mps2s,
                         self.acc_z_imax, self.vel_err_lp_hz, self.vel_z_err_lp_hz, self.vel_d_lp_hz, self.acc_err_lp_hz,
                         self.pos_acc_xy_mps2, self.pos_acc_z_mps2, math.cos(self.tilt_max_rad),
                         math.sin(self.tilt_max_rad)], dtype=np.float64)


class PositionController:
    """The position loops of N vehicles: per-row gains (N, N_G) and memory (N, N_M), which
    the physics stepper runs and updates (Physics.step(..., loop=...)).

    Args:
        n: vehicles; every row starts with no loop (LOOP_OFF) until `set_gains`.
    """

    def __init__(self, n: int):
        self.gains = np.zeros((n, N_G))
        self.memory = np.zeros((n, N_M))

    def set_gains(self, rows, gains: PositionLoopGains) -> None:
        """Give rows (an index, slice, mask or index array) these gains; memory is kept."""
        self.gains[rows] = gains.row()

    def reset(self, rows) -> None:
        """Clear the integrators and filters of rows (on the ground, at a release, disarmed):
        the next step starts them from the vehicle's state."""
        self.memory[rows] = 0.0

    def view(self, rows: slice) -> "PositionController":
        """A controller over a contiguous block of rows that shares this one's arrays."""
        out = PositionController(0)
        out.gains, out.memory = self.gains[rows], self.memory[rows]
        return out


@njit(cache=True, inline="always")
def _lp_alpha(dt, hz):
    """First-order low-pass coefficient for cut-off hz at step dt (1: no filter)."""
    if hz <= 0.0:
        return 1.0
    b = 2.0 * math.pi * hz * dt
    return b / (1.0 + b)


@njit(cache=True, inline="always")
def _sqrt_controller(err, p, acc, dt):
    """ArduPilot's sqrt_controller: P for small errors, a square root beyond acc/p^2 so that
    braking needs at most acc; never asks for more than closes the error in one step."""
    if acc <= 0.0 or p <= 0.0:
        out = err * p
    else:
        lin = acc / (p * p)
        if err > lin:
            out = math.sqrt(2.0 * acc * (err - 0.5 * lin))
        elif err < -lin:
            out = -math.sqrt(2.0 * acc * (-err - 0.5 * lin))
        else:
            out = err * p
    if dt > 0.0:
        lim = abs(err) / dt
        out = min(max(out, -lim), lim)
    return out


@njit(cache=True, inline="always")
def _add_if_finite(setpoint, addition):
    """PX4 ControlMath::addIfNotNan: the sum if both are finite, the one that is if one is."""
    if math.isfinite(setpoint):
        return setpoint + addition if math.isfinite(addition) else setpoint
    return addition


@njit(cache=True, inline="always")
def _p_axis(ps, x, kp):
    return kp * (ps - x) if math.isfinite(ps) else math.nan


@njit(cache=True, inline="always")
def _px4_loop(p, v, sp, g, m, dt, grav):
    """PX4 PositionControl::_positionControl, _velocityControl, _accelerationControl (one
    step): the normalised thrust vector (NED, up is -z) the attitude controller gets."""
    hov = g[G_HOVER_PARAM]
    # velocity derivative (BlockDerivative on the velocity, low-passed at MPC_VELD_LP), kept in m
    a_d = _lp_alpha(dt, g[G_VEL_D_LP_HZ])
    if m[M_STARTED] == 0.0:
        for k in range(3):
            m[M_VPREV + k] = v[k]
            m[M_DFILT + k] = 0.0
        m[M_STARTED] = 1.0
    inv_dt = 1.0 / dt
    for k in range(3):
        m[M_DFILT + k] += ((v[k] - m[M_VPREV + k]) * inv_dt - m[M_DFILT + k]) * a_d
        m[M_VPREV + k] = v[k]
    # position P, added to the velocity feed-forward where both are given
    vp0 = _p_axis(sp[SP_POS], p[0], g[G_POS_P_XY])
    vp1 = _p_axis(sp[SP_POS + 1], p[1], g[G_POS_P_XY])
    vp2 = _p_axis(sp[SP_POS + 2], p[2], g[G_POS_P_Z])
    vs0 = _add_if_finite(sp[SP_VEL], vp0)
    vs1 = _add_if_finite(sp[SP_VEL + 1], vp1)
    vs2 = _add_if_finite(sp[SP_VEL + 2], vp2)
    # constrainXY: the position part has priority over the feed-forward; then z
    if math.isfinite(vs0) and math.isfinite(vs1):
        v0x = vp0 if math.isfinite(vp0) else 0.0
        v0y = vp1 if math.isfinite(vp1) else 0.0
        v1x, v1y = vs0 - v0x, vs1 - v0y
        vmax = g[G_VEL_MAX_XY]
        if (v0x + v1x) ** 2 + (v0y + v1y) ** 2 > vmax * vmax:
            n0 = math.sqrt(v0x * v0x + v0y * v0y)
            if n0 >= vmax or (v1x - v0x) ** 2 + (v1y - v0y) ** 2 < 1e-6:
                vs0, vs1 = v0x / n0 * vmax, v0y / n0 * vmax
            elif n0 < 0.001:
                n1 = math.sqrt(v1x * v1x + v1y * v1y)
                vs0, vs1 = v1x / n1 * vmax, v1y / n1 * vmax
            else:
                n1 = math.sqrt(v1x * v1x + v1y * v1y)
                ux, uy = v1x / n1, v1y / n1
                mm = ux * v0x + uy * v0y
                c = v0x * v0x + v0y * v0y - vmax * vmax
                sc = -mm + math.sqrt(mm * mm - c)
                vs0, vs1 = v0x + ux * sc, v0y + uy * sc
    if math.isfinite(vs2):
        vs2 = min(max(vs2, -g[G_VEL_MAX_UP]), g[G_VEL_MAX_DN])
    # velocity PID (D on the measured velocity derivative), added to the acceleration feed-forward
    kv, kvz = g[G_VEL_P_XY], g[G_VEL_P_Z]
    e0, e1, e2 = vs0 - v[0], vs1 - v[1], vs2 - v[2]
    a0 = _add_if_finite(sp[SP_ACC], e0 * kv + m[M_INT] - m[M_DFILT] * g[G_VEL_D_XY])
    a1 = _add_if_finite(sp[SP_ACC + 1], e1 * kv + m[M_INT + 1] - m[M_DFILT + 1] * g[G_VEL_D_XY])
    a2 = _add_if_finite(sp[SP_ACC + 2], e2 * kvz + m[M_INT + 2] - m[M_DFILT + 2] * g[G_VEL_D_Z])
    a0 = a0 if math.isfinite(a0) else 0.0  # (an axis with no source: the hygiene refuses it before)
    a1 = a1 if math.isfinite(a1) else 0.0
    a2 = a2 if math.isfinite(a2) else 0.0
    # _accelerationControl: tilt from the horizontal acceleration against 1 g, thrust from the hover thrust
    bx, by, bz = -a0, -a1, grav
    nb = math.sqrt(bx * bx + by * by + bz * bz)
    bx, by, bz = bx / nb, by / nb, bz / nb
    if bz < g[G_TILT_COS]:  # limitTilt (the angle from vertical beyond the limit)
        nr = math.sqrt(bx * bx + by * by)
        if nr < 1e-9:
            bx, by, nr = 1.0, 0.0, 1.0
        sn = g[G_TILT_SIN]
        bx, by, bz = sn * bx / nr, sn * by / nr, g[G_TILT_COS]
    coll = min((a2 * (hov / grav) - hov) / bz, -g[G_THR_MIN])
    tx, ty, tz = bx * coll, by * coll, bz * coll
    # anti-windup, vertical
    thr_min, thr_max = g[G_THR_MIN], g[G_THR_MAX]
    if (tz >= -thr_min and e2 >= 0.0) or (tz <= -thr_max and e2 <= 0.0):
        e2 = 0.0
    # vertical priority with a horizontal margin
    txy = math.sqrt(tx * tx + ty * ty)
    alloc = min(txy, g[G_THR_XY_MARGIN])
    tz = max(tz, -math.sqrt(max(thr_max * thr_max - alloc * alloc, 0.0)))
    rest = thr_max * thr_max - tz * tz
    txy_max = math.sqrt(rest) if rest > 0.0 else 0.0
    if txy > txy_max:
        tx, ty = tx / txy * txy_max, ty / txy * txy_max
    # tracking anti-windup, horizontal (Rundqwist): the integrator unsaturates the output
    px, py = tx * (grav / hov), ty * (grav / hov)
    if a0 * a0 + a1 * a1 > px * px + py * py:
        lx, ly = px, py
    else:
        lx, ly = a0, a1
    arw = 2.0 / kv if kv > 0.0 else 0.0
    e0 -= arw * (a0 - lx)
    e1 -= arw * (a1 - ly)
    ki, kiz = g[G_VEL_I_XY], g[G_VEL_I_Z]
    m[M_INT] += (e0 if math.isfinite(e0) else 0.0) * ki * dt
    m[M_INT + 1] += (e1 if math.isfinite(e1) else 0.0) * ki * dt
    iz = m[M_INT + 2] + (e2 if math.isfinite(e2) else 0.0) * kiz * dt
    m[M_INT + 2] = min(max(iz, -grav), grav)
    return tx, ty, tz


@njit(cache=True, inline="always")
def _ardupilot_loop(p, v, sp, g, m, dt, grav):
    """ArduCopter AC_PosControl::update_xy_controller and update_z_controller (one step),
    with the setpoint as the guided target: the normalised thrust vector (NED, up is -z)."""
    hov = g[G_HOVER_PARAM]
    a_e = _lp_alpha(dt, g[G_VEL_ERR_LP_HZ])
    a_ez = _lp_alpha(dt, g[G_VEL_Z_ERR_LP_HZ])
    a_d = _lp_alpha(dt, g[G_VEL_D_LP_HZ])
    a_a = _lp_alpha(dt, g[G_ACC_ERR_LP_HZ])
    first = m[M_STARTED] == 0.0
    if first:
        for k in range(3):
            m[M_VPREV + k] = v[k]
        m[M_STARTED] = 1.0
    a_meas_up = -(v[2] - m[M_VPREV + 2]) / dt
    for k in range(3):
        m[M_VPREV + k] = v[k]
    # horizontal position: square-root controller on the error vector, at most the speed limit
    has_pos = math.isfinite(sp[SP_POS]) and math.isfinite(sp[SP_POS + 1])
    has_vel = math.isfinite(sp[SP_VEL]) and math.isfinite(sp[SP_VEL + 1])
    cx, cy = 0.0, 0.0
    if has_pos:
        ex, ey = sp[SP_POS] - p[0], sp[SP_POS + 1] - p[1]
        en = math.hypot(ex, ey)
        if en > 0.0:
            cn = min(_sqrt_controller(en, g[G_POS_P_XY], g[G_POS_ACC_XY], dt), g[G_VEL_MAX_XY])
            cx, cy = ex / en * cn, ey / en * cn
    vt0 = cx + (sp[SP_VEL] if has_vel else 0.0)
    vt1 = cy + (sp[SP_VEL + 1] if has_vel else 0.0)
    # horizontal velocity PID (AC_PID_2D): filtered error, filtered derivative, integrator
    # held against the last limit vector and clamped to IMAX; no velocity target: no correction
    stab_vel = has_pos or has_vel
    ax, ay = 0.0, 0.0
    if stab_vel:
        ex, ey = vt0 - v[0], vt1 - v[1]
        if first:
            m[M_EFILT], m[M_EFILT + 1] = ex, ey
            m[M_DFILT], m[M_DFILT + 1] = 0.0, 0.0
        else:
            lx, ly = m[M_EFILT], m[M_EFILT + 1]
            m[M_EFILT] += (ex - lx) * a_e
            m[M_EFILT + 1] += (ey - ly) * a_e
            m[M_DFILT] += ((m[M_EFILT] - lx) / dt - m[M_DFILT]) * a_d
            m[M_DFILT + 1] += ((m[M_EFILT + 1] - ly) / dt - m[M_DFILT + 1]) * a_d
        ki = g[G_VEL_I_XY]
        dix, diy = m[M_EFILT] * ki * dt, m[M_EFILT + 1] * ki * dt
        if dix * m[M_LIMIT] + diy * m[M_LIMIT + 1] > 0.0:
            dix, diy = 0.0, 0.0
        ix, iy = m[M_INT] + dix, m[M_INT + 1] + diy
        il = math.hypot(ix, iy)
        imax = g[G_VEL_IMAX_XY]
        if il > imax:
            ix, iy = ix * imax / il, iy * imax / il
        m[M_INT], m[M_INT + 1] = ix, iy
        kp, kd = g[G_VEL_P_XY], g[G_VEL_D_XY]
        ax = m[M_EFILT] * kp + ix + m[M_DFILT] * kd
        ay = m[M_EFILT + 1] * kp + iy + m[M_DFILT + 1] * kd
    else:  # acceleration only: stop_vel_NE_stabilisation (no correction, integrator cleared)
        m[M_INT], m[M_INT + 1] = 0.0, 0.0
    if math.isfinite(sp[SP_ACC]) and math.isfinite(sp[SP_ACC + 1]):
        ax += sp[SP_ACC]
        ay += sp[SP_ACC + 1]
    # acceleration limit from the lean angle; the limit vector holds the integrator next step
    amax = grav * math.tan(g[G_TILT_MAX])
    an = math.hypot(ax, ay)
    if an > amax:
        m[M_LIMIT], m[M_LIMIT + 1] = ax, ay
        ax, ay = ax * amax / an, ay * amax / an
    else:
        m[M_LIMIT], m[M_LIMIT + 1] = 0.0, 0.0
    # vertical: square-root position controller (up is -z), velocity P(I), acceleration PI to throttle
    up_pos = -sp[SP_POS + 2]
    up_vel = -sp[SP_VEL + 2]
    up_acc = -sp[SP_ACC + 2]
    vt_up = 0.0
    if math.isfinite(up_pos):
        vt_up = _sqrt_controller(up_pos + p[2], g[G_POS_P_Z], g[G_POS_ACC_Z], dt)
        vt_up = min(max(vt_up, -g[G_VEL_MAX_DN]), g[G_VEL_MAX_UP])
    if math.isfinite(up_vel):
        vt_up += up_vel
    at_up = 0.0
    if math.isfinite(up_pos) or math.isfinite(up_vel):
        ez = vt_up - (-v[2])
        if first:
            m[M_EFILT + 2] = ez
        else:
            m[M_EFILT + 2] += (ez - m[M_EFILT + 2]) * a_ez
        lim_up, lim_dn = m[M_LIMIT + 2] > 0.0, m[M_LIMIT + 2] < 0.0
        ez_f = m[M_EFILT + 2]
        if not ((ez_f > 0.0 and lim_up) or (ez_f < 0.0 and lim_dn)):
            m[M_INT + 2] += ez_f * g[G_VEL_I_Z] * dt
            m[M_INT + 2] = min(max(m[M_INT + 2], -g[G_VEL_IMAX_Z]), g[G_VEL_IMAX_Z])
        at_up = ez_f * g[G_VEL_P_Z] + m[M_INT + 2]
    if math.isfinite(up_acc):
        at_up += up_acc
    ea = at_up - a_meas_up
    if first:
        m[M_ACC_E] = ea
    else:
        m[M_ACC_E] += (ea - m[M_ACC_E]) * a_a
    ea_f = m[M_ACC_E]
    limited = m[M_LIMIT + 2] != 0.0
    ia = m[M_ACC_I]
    if not limited or (ia > 0.0 and ea_f < 0.0) or (ia < 0.0 and ea_f > 0.0):
        ia += ea_f * g[G_ACC_Z_I] * dt
        imax = max(g[G_ACC_Z_IMAX], hov)
        ia = min(max(ia, -imax), imax)
    m[M_ACC_I] = ia
    thr = hov + ea_f * g[G_ACC_Z_P] + ia
    # thrust along the lean that gives (ax, ay) at 1 g, with angle boost
    dx, dy, dz = ax, ay, -grav
    dn = math.sqrt(dx * dx + dy * dy + dz * dz)
    cos_tilt = grav / dn
    thr = thr / max(cos_tilt, _ANGLE_BOOST_COS_MIN)
    if thr >= g[G_THR_MAX]:
        thr, m[M_LIMIT + 2] = g[G_THR_MAX], 1.0
    elif thr <= g[G_THR_MIN]:
        thr, m[M_LIMIT + 2] = g[G_THR_MIN], -1.0
    else:
        m[M_LIMIT + 2] = 0.0
    return thr * dx / dn, thr * dy / dn, thr * dz / dn


@njit(cache=True, inline="always")
def position_loop_accel(p, v, sp, g, m, dt, grav):
    """One physics step of a vehicle's position loops (gain row g, memory row m, packed
    setpoint row sp): the acceleration (NED m/s^2) the inner controller must realise so that
    the rotors give the autopilot's thrust. The autopilot scales thrust by its hover-thrust
    parameter; the airframe's true hover thrust turns that thrust back into acceleration."""
    if g[G_STYLE] == LOOP_ARDUPILOT:
        tx, ty, tz = _ardupilot_loop(p, v, sp, g, m, dt, grav)
    else:
        tx, ty, tz = _px4_loop(p, v, sp, g, m, dt, grav)
    k = grav / g[G_HOVER_TRUE]
    return tx * k, ty * k, tz * k + grav
