"""Setpoint hygiene, PX4-like: what an offboard setpoint may ask, shared by both ends.

The SITL applies `check_trajectory` / `check_attitude` to what it receives, as PX4's
offboard path and position controller would; the agent applies the same functions
to what it sends, so it never commands a non-finite or out-of-limit setpoint. The
rules, one table (docs/setpoint-hygiene.md):

- position / velocity / acceleration: x, y count in pairs; the xy pair and z each need a
  finite source, else "invalid setpoints" (PX4's offboard flight task / position control);
- velocity: horizontal norm <= MPC_XY_VEL_MAX, up <= MPC_Z_VEL_MAX_UP, down <= MPC_Z_VEL_MAX_DN;
- yaw rate: abs <= MC_YAWRATE_MAX; a non-finite yaw or yaw rate is "not commanded";
- thrust: non-finite is rejected; clamped to [MPC_THR_MIN, MPC_THR_MAX];
- body rates: non-finite is rejected; each clamped to MC_ROLLRATE_MAX / MC_PITCHRATE_MAX /
  MC_YAWRATE_MAX;
- attitude: tilt clamped to MPC_TILTMAX_AIR, heading kept.

Pure functions over small numpy arrays; no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from companion.control.kernel import kernel
from companion.link.setpoints import AttitudeSetpoint, Rejected, TrajectorySetpoint

INVALID_SETPOINTS = "invalid setpoints"
"""PX4's reason for its failsafe stop when a trajectory setpoint leaves an axis without a source."""


@dataclass(frozen=True)
class SetpointLimits:
    """Offboard limits (PX4 defaults; the SITL reads them from its parameters)."""

    xy_vel_max_mps: float = 12.0
    z_vel_max_up_mps: float = 3.0
    z_vel_max_dn_mps: float = 1.5
    tilt_max_rad: float = math.radians(45.0)
    thr_min: float = 0.12
    thr_max: float = 1.0
    roll_rate_max_radps: float = math.radians(220.0)
    pitch_rate_max_radps: float = math.radians(220.0)
    yaw_rate_max_radps: float = math.radians(200.0)


def _pair(v: np.ndarray) -> np.ndarray:
    """x, y count together: if either is not finite, both are NaN (PX4 checks them in pairs)."""
    out = np.array(v, dtype=float)
    if not (math.isfinite(out[0]) and math.isfinite(out[1])):
        out[0] = out[1] = math.nan
    if not math.isfinite(out[2]):
        out[2] = math.nan
    return out


def check_trajectory(sp: TrajectorySetpoint, lim: SetpointLimits) -> TrajectorySetpoint | Rejected:
    """Validate and clamp a position-family setpoint (shapes (3,), local NED, SI units).

    Returns the clamped setpoint, or Rejected(INVALID_SETPOINTS) when the xy pair or z has
    no finite position, velocity or acceleration (the receiver then stops the vehicle).
    """
    p, v, a = _pair(sp.pos_ned_m), _pair(sp.vel_ned_mps), _pair(sp.acc_ned_mps2)
    xy_ok = math.isfinite(p[0]) or math.isfinite(v[0]) or math.isfinite(a[0])
    z_ok = math.isfinite(p[2]) or math.isfinite(v[2]) or math.isfinite(a[2])
    if not (xy_ok and z_ok):
        return Rejected(INVALID_SETPOINTS)
    v[0], v[1], v[2] = clamp_velocity(float(v[0]), float(v[1]), float(v[2]), lim)
    yaw = float(sp.yaw_rad) if math.isfinite(sp.yaw_rad) else math.nan
    yr = float(sp.yaw_rate_radps)
    yr = min(max(yr, -lim.yaw_rate_max_radps), lim.yaw_rate_max_radps) if math.isfinite(yr) else math.nan
    return TrajectorySetpoint(pos_ned_m=p, vel_ned_mps=v, acc_ned_mps2=a, yaw_rad=yaw, yaw_rate_radps=yr)


def clamp_velocity(vx: float, vy: float, vz: float, lim: SetpointLimits) -> tuple[float, float, float]:
    """Velocity (m/s, NED) inside MPC_XY_VEL_MAX (horizontal norm) and MPC_Z_VEL_MAX_UP/DN;
    NaN axes stay NaN."""
    return clamp_velocity3(vx, vy, vz, lim.xy_vel_max_mps, lim.z_vel_max_up_mps, lim.z_vel_max_dn_mps)


@kernel
def clamp_velocity3(vx, vy, vz, xy_max_mps, up_max_mps, dn_max_mps):
    """clamp_velocity's kernel (scalars; the output stage's rows call it)."""
    h = math.hypot(vx, vy)
    if h > xy_max_mps:  # False for NaN
        vx, vy = vx * xy_max_mps / h, vy * xy_max_mps / h
    if vz == vz:
        vz = min(max(vz, -up_max_mps), dn_max_mps)
    return vx, vy, vz


def fence_trajectory(p: tuple, v: tuple, a: tuple, lo: tuple, hi: tuple, own: tuple) -> tuple[tuple, tuple, tuple]:
    """Keep a position-family setpoint inside the box lo..hi (m, mission NED): the position
    is clipped into it, and where the vehicle (own position) is at or beyond a face, velocity
    and acceleration components pointing further out are zeroed. Scalars (fence_axis per axis)."""
    out = [fence_axis(p[i], v[i], a[i], lo[i], hi[i], own[i]) for i in range(3)]
    return (out[0][0], out[1][0], out[2][0]), (out[0][1], out[1][1], out[2][1]), (out[0][2], out[1][2], out[2][2])


@kernel
def fence_axis(p, v, a, lo, hi, own):
    """fence_trajectory on one axis: (p, v, a) kept inside lo..hi given the own coordinate
    (NaN stays NaN: not commanded)."""
    if p == p:
        p = min(max(p, lo), hi)
    if own >= hi:
        v = min(v, 0.0) if v == v else v
        a = min(a, 0.0) if a == a else a
    elif own <= lo:
        v = max(v, 0.0) if v == v else v
        a = max(a, 0.0) if a == a else a
    return p, v, a


def clamp_tilt(q_wxyz: np.ndarray, tilt_max_rad: float) -> np.ndarray:
    """The attitude q (w, x, y, z; NED -> body FRD) with its tilt limited to tilt_max_rad
    (clamp_tilt_wxyz). Returns a new (4,) array."""
    w, x, y, z = (float(c) for c in q_wxyz)
    return np.array(clamp_tilt_wxyz(w, x, y, z, tilt_max_rad))


@kernel
def clamp_tilt_wxyz(w, x, y, z, tilt_max_rad):
    """clamp_tilt as scalars (the output stage's rows call it).

    The tilt is the rotation taking NED down to body down; it is shortened about the same
    axis, and the rest of the rotation (the heading) is kept. A quaternion within the
    limit is returned as it is; a clamped one normalised with w >= 0.
    """
    # body z (down) in NED: third column of R(q); its down component is cos(tilt)
    c = 1.0 - 2.0 * (x * x + y * y)
    tilt = math.acos(min(1.0, max(-1.0, c)))
    if tilt <= tilt_max_rad:  # the usual case
        return w, x, y, z
    bx, by = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x)
    # axis = e3 x b_z = (-by, bx, 0); upside down (no axis): tilt about x
    n = math.hypot(bx, by)
    ax, ay = (-by / n, bx / n) if n > 1e-9 else (1.0, 0.0)
    s, co = math.sin(tilt / 2.0), math.cos(tilt / 2.0)
    # q_rest = conj(qt) * q, qt = (co, ax s, ay s, 0): the heading part, q = qt * q_rest
    rw, rx, ry, rz = _qmul(co, -ax * s, -ay * s, 0.0, w, x, y, z)
    s, co = math.sin(tilt_max_rad / 2.0), math.cos(tilt_max_rad / 2.0)
    qw, qx, qy, qz = _qmul(co, ax * s, ay * s, 0.0, rw, rx, ry, rz)
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qw < 0.0:
        qn = -qn
    return qw / qn, qx / qn, qy / qn, qz / qn


@kernel
def _qmul(w1, x1, y1, z1, w2, x2, y2, z2):
    """Hamilton product of two quaternions given as scalars (w first)."""
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


def check_attitude(sp: AttitudeSetpoint, lim: SetpointLimits, thrust_is_thrust: bool = True
                   ) -> AttitudeSetpoint | Rejected:
    """Validate and clamp an attitude / body-rate setpoint.

    Args:
        thrust_is_thrust: the thrust field is normalised thrust (PX4; ArduPilot with
            GUID_OPTIONS bit 3), so MPC_THR_MIN/MAX apply; False: a climb rate (0..1).
    """
    if not math.isfinite(sp.thrust_norm):
        return Rejected("SET_ATTITUDE_TARGET thrust not finite")
    rates = np.asarray(sp.body_rate_radps, dtype=float)
    if not np.isfinite(rates).all():
        return Rejected("SET_ATTITUDE_TARGET body rate not finite")
    rmax = np.array([lim.roll_rate_max_radps, lim.pitch_rate_max_radps, lim.yaw_rate_max_radps])
    rates = np.clip(rates, -rmax, rmax)
    lo, hi = (lim.thr_min, lim.thr_max) if thrust_is_thrust else (0.0, 1.0)
    thrust = min(max(float(sp.thrust_norm), lo), hi)
    q = sp.att_q_wxyz
    if q is not None:
        q = clamp_tilt(q, lim.tilt_max_rad)
    return replace(sp, att_q_wxyz=q, thrust_norm=thrust, body_rate_radps=rates)
