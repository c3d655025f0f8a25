"""Offboard setpoint messages: type_mask encoding (companion) and decoding (SITL).

Pure functions on plain numbers (no sockets). The agent encodes its setpoints
with ``position_target_fields`` / ``attitude_target_fields`` and the SITL decodes
what it receives with ``decode_position_target`` / ``decode_attitude_target``, so
both ends read the bits one way. Decoding follows PX4 (reference behaviour:
PX4 MavlinkReceiver::handle_message_set_position_target_local_ned and
handle_message_set_attitude_target (v1.14-v1.16):

* SET_POSITION_TARGET_LOCAL_NED, frame LOCAL_NED (1): every ignore bit turns its
  axis into NaN ("not commanded").
* frame BODY_NED (8): position is never used; velocity (if no velocity ignore bit
  is set) is rotated by the vehicle yaw, acceleration (if no acceleration ignore
  bit is set) by the full attitude; an ignored axis inside a used group counts 0.
* any other frame is rejected; FORCE_SET together with an acceleration is rejected;
  a message without any position, velocity or acceleration is rejected.
* yaw / yaw_rate are NaN when their ignore bit is set.
* SET_ATTITUDE_TARGET: the quaternion (NED->FRD, w x y z) unless ATTITUDE_IGNORE;
  otherwise body rates if at least one rate is not ignored. Thrust is 0 when
  THROTTLE_IGNORE is set (PX4 leaves thrust_body zero).)

Other autopilots refuse more (ArduPilot's GUIDED, docs/companion.md: position +
acceleration without velocity, THROTTLE_IGNORE, a partial set of rate-ignore bits, a
quaternion that is not unit). Each autopilot dialect names what it refuses as a
``SetpointRules`` (``AutopilotDialect.setpoint_rules``), the decoders take it, and the
encoders below never produce any of those.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.link.enums import AttitudeTargetTypemask, MavFrame, PositionTargetTypemask

MAV_FRAME_LOCAL_NED = MavFrame.MAV_FRAME_LOCAL_NED
MAV_FRAME_BODY_NED = MavFrame.MAV_FRAME_BODY_NED

@dataclass(frozen=True)
class SetpointRules:
    """What an autopilot refuses beyond the PX4 decoding rules above (default: nothing more)."""

    position_acceleration_needs_velocity: bool = False
    """A setpoint with position and acceleration but no velocity is refused."""
    refuse_throttle_ignore: bool = False
    """SET_ATTITUDE_TARGET with THROTTLE_IGNORE is refused."""
    refuse_partial_rates: bool = False
    """SET_ATTITUDE_TARGET must ignore all three body rates or none."""
    unit_quaternion_tol: float | None = None
    """|q| must be 1 within this (None: any quaternion that normalises)."""


_P, _A = PositionTargetTypemask, AttitudeTargetTypemask
POS_IGNORE = (_P.POSITION_TARGET_TYPEMASK_X_IGNORE, _P.POSITION_TARGET_TYPEMASK_Y_IGNORE,
              _P.POSITION_TARGET_TYPEMASK_Z_IGNORE)
VEL_IGNORE = (_P.POSITION_TARGET_TYPEMASK_VX_IGNORE, _P.POSITION_TARGET_TYPEMASK_VY_IGNORE,
              _P.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
ACC_IGNORE = (_P.POSITION_TARGET_TYPEMASK_AX_IGNORE, _P.POSITION_TARGET_TYPEMASK_AY_IGNORE,
              _P.POSITION_TARGET_TYPEMASK_AZ_IGNORE)
FORCE_SET = _P.POSITION_TARGET_TYPEMASK_FORCE_SET
YAW_IGNORE = _P.POSITION_TARGET_TYPEMASK_YAW_IGNORE
YAW_RATE_IGNORE = _P.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

ATT_ROLL_RATE_IGNORE = _A.ATTITUDE_TARGET_TYPEMASK_BODY_ROLL_RATE_IGNORE
ATT_PITCH_RATE_IGNORE = _A.ATTITUDE_TARGET_TYPEMASK_BODY_PITCH_RATE_IGNORE
ATT_YAW_RATE_IGNORE = _A.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE
ATT_RATES_IGNORE = ATT_ROLL_RATE_IGNORE | ATT_PITCH_RATE_IGNORE | ATT_YAW_RATE_IGNORE
ATT_THRUST_BODY_SET = 1 << 5
"""THRUST_BODY_SET (bit 5) of newer common.xml; the pymavlink this project pins has no name for it."""
ATT_THROTTLE_IGNORE = _A.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
ATT_ATTITUDE_IGNORE = _A.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE


@dataclass
class TrajectorySetpoint:
    """One vehicle's position-family setpoint (FleetSetpoint row semantics)."""

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    acc_ned_mps2: np.ndarray
    yaw_rad: float
    yaw_rate_radps: float


@dataclass
class AttitudeSetpoint:
    """One vehicle's attitude or body-rate setpoint.

    att_q_wxyz is None for a body-rate setpoint: the SITL then integrates the
    rates into a moving attitude target for the geometric controller.
    """

    att_q_wxyz: np.ndarray | None
    thrust_norm: float
    body_rate_radps: np.ndarray


@dataclass(frozen=True)
class Rejected:
    """A setpoint message the autopilot would drop, returned in place of the setpoint;
    `reason` is the text the SITL reports (STATUSTEXT) for it."""

    reason: str


def _axes(values, mask: int, bits, fill: float) -> np.ndarray:
    return np.array([fill if mask & b else float(v) for v, b in zip(values, bits)])


def _yaw_of(rot_body_to_ned: np.ndarray) -> float:
    return math.atan2(rot_body_to_ned[1, 0], rot_body_to_ned[0, 0])


def decode_position_target(
    type_mask: int,
    frame: int,
    pos: tuple[float, float, float],
    vel: tuple[float, float, float],
    acc: tuple[float, float, float],
    yaw: float,
    yaw_rate: float,
    rot_body_to_ned: np.ndarray,
    rules: SetpointRules = SetpointRules(),
) -> TrajectorySetpoint | Rejected:
    """SET_POSITION_TARGET_LOCAL_NED fields -> setpoint, or why PX4 (or, with rules, the
    autopilot that has them) would drop it."""
    nan = math.nan
    if frame == MAV_FRAME_LOCAL_NED:
        p = _axes(pos, type_mask, POS_IGNORE, nan)
        v = _axes(vel, type_mask, VEL_IGNORE, nan)
        a = _axes(acc, type_mask, ACC_IGNORE, nan)
    elif frame == MAV_FRAME_BODY_NED:
        p = np.full(3, nan)
        if type_mask & sum(VEL_IGNORE):
            v = np.full(3, nan)
        else:
            vb = _axes(vel, type_mask, VEL_IGNORE, 0.0)
            c, s = math.cos(_yaw_of(rot_body_to_ned)), math.sin(_yaw_of(rot_body_to_ned))
            v = np.array([c * vb[0] - s * vb[1], s * vb[0] + c * vb[1], vb[2]])
        if type_mask & sum(ACC_IGNORE):
            a = np.full(3, nan)
        else:
            a = rot_body_to_ned @ _axes(acc, type_mask, ACC_IGNORE, 0.0)
    else:
        return Rejected(f"SET_POSITION_TARGET_LOCAL_NED coordinate frame {frame} unsupported")
    has_pos = bool(np.isfinite(p).any())
    has_vel = bool(np.isfinite(v).any())
    has_acc = bool(np.isfinite(a).any())
    if has_acc and type_mask & FORCE_SET:
        return Rejected("SET_POSITION_TARGET_LOCAL_NED force not supported")
    if not (has_pos or has_vel or has_acc):
        return Rejected("SET_POSITION_TARGET_LOCAL_NED invalid")
    if rules.position_acceleration_needs_velocity and math.isfinite(p[0]) and math.isfinite(a[0]) \
            and not math.isfinite(v[0]):
        return Rejected("SET_POSITION_TARGET_LOCAL_NED position with acceleration needs velocity")
    return TrajectorySetpoint(
        pos_ned_m=p, vel_ned_mps=v, acc_ned_mps2=a,
        yaw_rad=nan if type_mask & YAW_IGNORE else float(yaw),
        yaw_rate_radps=nan if type_mask & YAW_RATE_IGNORE else float(yaw_rate),
    )


def decode_attitude_target(
    type_mask: int,
    q_wxyz: tuple[float, float, float, float],
    body_rates_radps: tuple[float, float, float],
    thrust: float,
    rules: SetpointRules = SetpointRules(),
) -> AttitudeSetpoint | Rejected:
    """SET_ATTITUDE_TARGET fields -> setpoint, or why it is dropped (rules: what the
    autopilot refuses beyond PX4, e.g. ArduPilot's handle_message_set_attitude_target)."""
    if rules.refuse_throttle_ignore and type_mask & ATT_THROTTLE_IGNORE:
        return Rejected("SET_ATTITUDE_TARGET throttle ignored")
    if rules.refuse_partial_rates and type_mask & ATT_RATES_IGNORE not in (0, ATT_RATES_IGNORE):
        return Rejected("SET_ATTITUDE_TARGET partial rate mask")
    tol = rules.unit_quaternion_tol
    if tol is not None and not type_mask & ATT_ATTITUDE_IGNORE \
            and not abs(math.sqrt(sum(float(x) * float(x) for x in q_wxyz)) - 1.0) <= tol:
        return Rejected("SET_ATTITUDE_TARGET quaternion not unit")
    # Non-finite thrust or rates stay non-finite here: companion.link.limits.check_attitude
    # rejects them (treating NaN thrust as 0 dropped the vehicle out of the sky).
    thrust_norm = 0.0 if type_mask & ATT_THROTTLE_IGNORE else float(thrust)
    rate_bits = (ATT_ROLL_RATE_IGNORE, ATT_PITCH_RATE_IGNORE, ATT_YAW_RATE_IGNORE)
    rates = _axes(body_rates_radps, type_mask, rate_bits, 0.0)
    if not type_mask & ATT_ATTITUDE_IGNORE:
        q = np.array(q_wxyz, dtype=float)
        norm = float(np.linalg.norm(q))
        if not np.isfinite(q).all() or norm < 0.5:
            return Rejected("SET_ATTITUDE_TARGET invalid quaternion")
        q = q / norm
        if q[0] < 0:
            q = -q
        return AttitudeSetpoint(att_q_wxyz=q, thrust_norm=thrust_norm, body_rate_radps=rates)
    if (type_mask & ATT_RATES_IGNORE) != ATT_RATES_IGNORE:
        return AttitudeSetpoint(att_q_wxyz=None, thrust_norm=thrust_norm, body_rate_radps=rates)
    return Rejected("SET_ATTITUDE_TARGET ignores attitude and all rates")


def position_target_fields(pos_ned_m, vel_ned_mps, acc_ned_mps2, yaw_rad: float, yaw_rate_radps: float
                           ) -> tuple[int, tuple[float, ...]]:
    """SET_POSITION_TARGET_LOCAL_NED (frame LOCAL_NED) for one setpoint row.

    A NaN axis becomes its ignore bit (and 0 on the wire); yaw and yaw rate likewise.
    Groups are kept whole (a group with any NaN axis is ignored entirely), because
    ArduPilot checks masks per group.

    Args:
        pos_ned_m, vel_ned_mps, acc_ned_mps2: 3 values each (NaN = not commanded), local NED.
        yaw_rad, yaw_rate_radps: NaN = not commanded.
    Returns:
        (type_mask, (x, y, z, vx, vy, vz, afx, afy, afz, yaw, yaw_rate)).
    Raises:
        ValueError: nothing commanded, or position and acceleration without velocity
            (ArduPilot rejects that combination).
    """
    mask = 0
    out: list[float] = []
    used = []
    for values, bits in ((pos_ned_m, POS_IGNORE), (vel_ned_mps, VEL_IGNORE), (acc_ned_mps2, ACC_IGNORE)):
        x, y, z = (float(values[0]), float(values[1]), float(values[2]))
        if math.isfinite(x + y + z):  # all three finite (NaN or inf poisons the sum)
            out += (x, y, z)
            used.append(True)
        else:
            mask |= bits[0] | bits[1] | bits[2]
            out += (0.0, 0.0, 0.0)
            used.append(False)
    if not (used[0] or used[1] or used[2]):
        raise ValueError("setpoint commands no position, velocity or acceleration")
    if used[0] and used[2] and not used[1]:
        raise ValueError("position with acceleration needs velocity (ArduPilot rejects it)")
    for value, bit in ((yaw_rad, YAW_IGNORE), (yaw_rate_radps, YAW_RATE_IGNORE)):
        if math.isfinite(value):
            out.append(float(value))
        else:
            mask |= bit
            out.append(0.0)
    return mask, tuple(out)


def attitude_target_fields(q_wxyz, thrust: float, body_rate_radps=None) -> tuple[int, tuple]:
    """SET_ATTITUDE_TARGET for an attitude (w, x, y, z, NED->FRD) and a thrust field.

    Body rates are feed-forward (all three or none: ArduPilot rejects a partial set).
    Returns (type_mask, (q (4-list), roll_rate, pitch_rate, yaw_rate, thrust)).

    Raises:
        ValueError: non-finite or zero quaternion, or non-finite thrust.
    """
    q = [float(v) for v in q_wxyz]
    norm = math.sqrt(sum(v * v for v in q))
    if not (math.isfinite(norm) and norm > 0.5) or not math.isfinite(thrust):
        raise ValueError("attitude setpoint needs a finite unit quaternion and thrust")
    q = [v / norm for v in q]
    rates = [float(v) for v in body_rate_radps] if body_rate_radps is not None else [math.nan] * 3
    if all(math.isfinite(r) for r in rates):
        mask = 0
    else:
        mask = ATT_ROLL_RATE_IGNORE | ATT_PITCH_RATE_IGNORE | ATT_YAW_RATE_IGNORE
        rates = [0.0, 0.0, 0.0]
    return mask, (q, rates[0], rates[1], rates[2], float(thrust))
