"""ArduCopter: GUIDED mode, ArduCopter mode numbers, integer parameters carried by value."""
from __future__ import annotations

import math
from collections.abc import Mapping

from companion.link.dialects.base import (
    MODE_FLAG_CUSTOM,
    MODE_FLAG_GUIDED,
    MODE_FLAG_MANUAL_INPUT,
    MODE_FLAG_STABILIZE,
    AfterLoss,
    AutopilotDialect,
    CarryOn,
    HeartbeatState,
    LossBehaviour,
    Mode,
    PositionLoop,
    clamp01,
    param_or,
)
from companion.link.setpoints import SetpointRules

STABILIZE, GUIDED, LOITER, RTL, LAND, BRAKE, THROW = 0, 4, 5, 6, 9, 17, 18
GUID_OPTIONS_THRUST = 8
"""GUID_OPTIONS bit 3: SET_ATTITUDE_TARGET.thrust is thrust, not a climb rate."""
ANGLE_BOOST_COS_MIN = 0.1
"""ArduPilot's angle boost divides by max(cos(lean), 0.1)."""


ARDUPILOT_LOOP_DEFAULTS = {
    "PSC_POSXY_P": 1.0,
    "PSC_VELXY_P": 2.0,
    "PSC_VELXY_I": 1.0,
    "PSC_POSZ_P": 1.0,
    "PSC_VELZ_P": 5.0,
    "PSC_VELZ_I": 0.0,
}
"""The position-loop parameters and their defaults, in PositionLoop's field order."""


class ArduPilot(AutopilotDialect):
    """ArduCopter: offboard is GUIDED, take-off starts from GUIDED, a carrier release is a
    THROW; integer parameters travel C-cast, and GUIDED refuses the setpoints its own
    checks refuse (setpoint_rules)."""

    name = "ardupilot"
    autopilot_id = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
    param_encoding = "c_cast"
    hover_thrust_param = "MOT_THST_HOVER"
    setpoint_timeout_param = "GUID_TIMEOUT"
    # ArduCopter takes off in GUIDED: TAKEOFF has no mode number of its own.
    modes = {Mode.MANUAL: STABILIZE, Mode.OFFBOARD: GUIDED, Mode.POSITION: LOITER, Mode.HOLD: BRAKE,
             Mode.RETURN: RTL, Mode.LAND: LAND, Mode.THROW: THROW}
    takeoff_from_mode = Mode.OFFBOARD
    carrier_mode = Mode.THROW
    # GUIDED's own checks (mode_guided.cpp, GCS_MAVLink_Copter.cpp handle_message_set_*_target)
    setpoint_rules = SetpointRules(position_acceleration_needs_velocity=True, refuse_throttle_ignore=True,
                                   refuse_partial_rates=True, unit_quaternion_tol=1e-3)
    _names = {STABILIZE: "STABILIZE", GUIDED: "GUIDED", LOITER: "LOITER", RTL: "RTL", LAND: "LAND", BRAKE: "BRAKE",
              THROW: "THROW"}

    def custom_mode(self, mode: Mode) -> int:
        return GUIDED if mode == Mode.TAKEOFF else self.modes[mode]

    def mode_name(self, custom_mode: int) -> str:
        return self._names.get(custom_mode, f"ArduCopter mode {custom_mode}")

    def set_mode_params(self, mode: Mode) -> tuple[float, float, float]:
        return float(MODE_FLAG_CUSTOM), float(self.custom_mode(mode)), 0.0

    def mode_from_set_mode(self, param1: float, param2: float, param3: float) -> Mode | None:
        if not (math.isfinite(param1) and math.isfinite(param2)) or not int(param1) & MODE_FLAG_CUSTOM:
            return None
        return self.mode_of(int(param2))

    def base_mode(self, mode: Mode, armed: bool) -> int:
        flags = MODE_FLAG_CUSTOM | MODE_FLAG_STABILIZE | MODE_FLAG_MANUAL_INPUT
        if mode in (Mode.OFFBOARD, Mode.TAKEOFF, Mode.POSITION, Mode.HOLD, Mode.RETURN, Mode.LAND, Mode.THROW):
            flags |= MODE_FLAG_GUIDED  # ArduPilot sets it while its position controller runs
        return flags | (128 if armed else 0)

    def launch_ready(self, hb: HeartbeatState) -> bool:
        # THROW switches to THROW_NEXTMODE once recovered (carrier_params sets GUIDED);
        # after a GUIDED take-off the vehicle stays in GUIDED (the agent checks the height).
        return hb.armed and hb.in_air and hb.custom_mode in (GUIDED, LOITER, BRAKE)

    def takeoff_params(self, altitude_rel_m: float, home_alt_amsl_m: float) -> tuple[float, ...]:
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, altitude_rel_m)  # param7: altitude above home

    def carrier_params(self) -> dict[str, float]:
        return {"THROW_NEXTMODE": GUIDED}

    def attitude_params(self) -> dict[str, float]:
        return {"GUID_OPTIONS": GUID_OPTIONS_THRUST}  # merged into the current bits by the caller

    def thrust_field(self, thrust_over_weight: float, hover_thrust: float, cos_tilt: float) -> float:
        # ArduPilot applies angle boost (divides by cos of the lean angle), so the field
        # is the vertical-equivalent throttle: collective times cos(tilt).
        return clamp01(thrust_over_weight * hover_thrust * max(cos_tilt, ANGLE_BOOST_COS_MIN))

    def collective_from_thrust_field(self, thrust: float, cos_tilt: float) -> float:
        return clamp01(clamp01(thrust) / max(cos_tilt, ANGLE_BOOST_COS_MIN))

    loop_params = tuple(ARDUPILOT_LOOP_DEFAULTS)

    def position_loop(self, params: Mapping[str, float]) -> PositionLoop:
        """ArduCopter AC_PosControl (4.6 defaults): P on position (linear near the target), PID on the
        horizontal velocity; vertically PSC_VELZ_I is 0 (the ACCZ loop integrates acceleration
        error, not position), so the agent keeps its own integral on that axis."""
        return PositionLoop(*(param_or(params, n, d) for n, d in ARDUPILOT_LOOP_DEFAULTS.items()))

    loss_params = ("GUID_TIMEOUT", "WPNAV_ACCEL", "WPNAV_ACCEL_Z", "PSC_JERK_XY", "PSC_JERK_Z")
    loss_required_params = ("GUID_TIMEOUT",)

    def loss_behaviour(self, params: Mapping[str, float], rc: bool = False) -> LossBehaviour:
        """ArduCopter GUIDED (mode_guided.cpp; ../shared/notes/mavlink-facts.md, Copter 4.6
        SITL): until GUID_TIMEOUT (default 3 s) the target keeps moving along the last
        velocity and acceleration; then they are zeroed and the vehicle stops and holds in
        GUIDED, armed, for ever (no mode change, no landing). An RC link changes nothing.
        It stops within GUIDED's kinematic limits (pva_control_start): WPNAV_ACCEL and
        WPNAV_ACCEL_Z (cm/s^2), the position controller's PSC_JERK_XY and PSC_JERK_Z."""
        cm = 0.01
        return LossBehaviour(
            param_or(params, "GUID_TIMEOUT", 3.0), CarryOn.VELOCITY_ACCELERATION, AfterLoss.HOLD, Mode.OFFBOARD,
            brake_hor_mps2=param_or(params, "WPNAV_ACCEL", 250.0) * cm,
            brake_ver_mps2=param_or(params, "WPNAV_ACCEL_Z", 100.0) * cm,
            jerk_hor_mps3=param_or(params, "PSC_JERK_XY", 5.0), jerk_ver_mps3=param_or(params, "PSC_JERK_Z", 5.0),
            params=tuple((n, float(params[n])) for n in self.loss_params if n in params))

    def loss_fix(self, then: AfterLoss) -> dict[str, float]:
        if then == AfterLoss.HOLD:
            return {}  # GUIDED holds after GUID_TIMEOUT whatever the parameters
        raise ValueError(f"ArduCopter's GUIDED always stops and holds after GUID_TIMEOUT; it cannot be set to "
                         f"{then.value}")

    def loss_fix_text(self) -> str:
        return "ArduCopter GUIDED always holds (nothing to set)"
