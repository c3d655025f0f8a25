"""PX4: OFFBOARD mode, custom_mode = main << 16 | sub << 24, bytewise integer parameters."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

from companion.link.dialects.base import (
    MODE_FLAG_AUTO,
    MODE_FLAG_CUSTOM,
    MODE_FLAG_GUIDED,
    MODE_FLAG_MANUAL_INPUT,
    MODE_FLAG_STABILIZE,
    STATE_ACTIVE,
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

COM_OBL_RC_ACT_MODES = {0: Mode.POSITION, 1: Mode.POSITION, 2: Mode.MANUAL}
"""The pilot's mode each COM_OBL_RC_ACT value 0-2 asks for (1, Altitude, has no Mode of its own
here: reported as Position)."""
PX4_STOP_LEAD_S = 0.6
"""Hold and Land fly to the stop point Navigator predicts from the horizontal speed s:
s^2 / (2 MPC_ACC_HOR) + s accel_delay_max / MPC_JERK_AUTO with accel_delay_max = 0.6
MPC_JERK_AUTO (Navigator::preproject_stop_point, TrajMath computeBrakingDistanceFromVelocity),
so a lead of 0.6 s whatever the jerk limit."""
PX4_NO_RC_DRIFT_M = 4.0
"""Horizontal drift of PX4 v1.16's descent with no horizontal control (COM_OBL_RC_ACT 0 without
RC) from a hover, in SIH with no wind (../shared/notes/mavlink-facts.md), m: its tilt and
accelerometer bias act unopposed; wind adds to it."""


def _px4(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


PX4_LOOP_DEFAULTS = {
    "MPC_XY_P": 0.95,
    "MPC_XY_VEL_P_ACC": 1.8,
    "MPC_XY_VEL_I_ACC": 0.4,
    "MPC_Z_P": 1.0,
    "MPC_Z_VEL_P_ACC": 4.0,
    "MPC_Z_VEL_I_ACC": 2.0,
}
"""The position-loop parameters and their defaults, in PositionLoop's field order."""


class Px4(AutopilotDialect):
    """PX4: offboard is OFFBOARD, take-off starts from Hold (AUTO.LOITER), custom_mode is
    main << 16 | sub << 24; integer parameters travel bytewise, and there is no carrier
    mode (a carrier release is PX4's throw launch, COM_THROW_EN)."""

    name = "px4"
    autopilot_id = 12  # MAV_AUTOPILOT_PX4
    param_encoding = "bytewise"
    hover_thrust_param = "MPC_THR_HOVER"
    setpoint_timeout_param = "COM_OF_LOSS_T"
    modes = {Mode.MANUAL: _px4(1), Mode.POSITION: _px4(3), Mode.OFFBOARD: _px4(6), Mode.TAKEOFF: _px4(4, 2),
             Mode.HOLD: _px4(4, 3), Mode.RETURN: _px4(4, 5), Mode.LAND: _px4(4, 6)}
    takeoff_from_mode = Mode.HOLD
    carrier_mode = None
    _names = {Mode.MANUAL: "Manual", Mode.POSITION: "Position", Mode.OFFBOARD: "Offboard", Mode.TAKEOFF: "Takeoff",
              Mode.HOLD: "Hold", Mode.RETURN: "Return", Mode.LAND: "Land"}

    def mode_name(self, custom_mode: int) -> str:
        mode = self.mode_of(custom_mode)
        if mode is not None:
            return self._names[mode]
        return f"PX4 mode {custom_mode >> 16 & 0xFF}/{custom_mode >> 24 & 0xFF}"

    def set_mode_params(self, mode: Mode) -> tuple[float, float, float]:
        cm = self.modes[mode]
        return float(MODE_FLAG_CUSTOM), float(cm >> 16 & 0xFF), float(cm >> 24 & 0xFF)

    def mode_from_set_mode(self, param1: float, param2: float, param3: float) -> Mode | None:
        if not (math.isfinite(param1) and math.isfinite(param2)) or not int(param1) & MODE_FLAG_CUSTOM:
            return None
        main = int(param2)
        sub = int(param3) if math.isfinite(param3) and main == 4 else 0
        return self.mode_of(_px4(main, sub))

    def base_mode(self, mode: Mode, armed: bool) -> int:
        flags = MODE_FLAG_CUSTOM | MODE_FLAG_STABILIZE
        if mode in (Mode.TAKEOFF, Mode.HOLD, Mode.LAND, Mode.OFFBOARD, Mode.RETURN):
            flags |= MODE_FLAG_AUTO | MODE_FLAG_GUIDED
        elif mode == Mode.POSITION:
            flags |= MODE_FLAG_MANUAL_INPUT
        return flags | (128 if armed else 0)

    def launch_ready(self, hb: HeartbeatState) -> bool:
        # PX4's throw launch keeps the vehicle in its mode (Hold/Position) and reports
        # system_status FLIGHT_TERMINATION until the throw is detected; our SITL shows
        # Takeoff while it recovers. Ready: armed, active, in the air, not taking off.
        return (hb.armed and hb.system_status == STATE_ACTIVE and hb.in_air
                and self.mode_of(hb.custom_mode) in (Mode.HOLD, Mode.POSITION, Mode.OFFBOARD))

    def takeoff_params(self, altitude_rel_m: float, home_alt_amsl_m: float) -> tuple[float, ...]:
        nan = math.nan
        return (nan, nan, nan, nan, nan, nan, home_alt_amsl_m + altitude_rel_m)  # param7: AMSL altitude

    def carrier_params(self) -> dict[str, float]:
        return {"COM_THROW_EN": 1}

    def attitude_params(self) -> dict[str, float]:
        return {}

    def thrust_field(self, thrust_over_weight: float, hover_thrust: float, cos_tilt: float) -> float:
        # PX4 flies SET_ATTITUDE_TARGET.thrust as normalised collective thrust
        # (thrust_body z = -thrust), without tilt compensation.
        return clamp01(thrust_over_weight * hover_thrust)

    def collective_from_thrust_field(self, thrust: float, cos_tilt: float) -> float:
        return clamp01(thrust)

    loop_params = tuple(PX4_LOOP_DEFAULTS)

    def position_loop(self, params: Mapping[str, float]) -> PositionLoop:
        """PX4 mc_pos_control's PositionControl (v1.14-v1.16 defaults): P on position, PID on velocity."""
        return PositionLoop(*(param_or(params, n, d) for n, d in PX4_LOOP_DEFAULTS.items()))

    loss_params = ("COM_OF_LOSS_T", "COM_OBL_RC_ACT", "MPC_LAND_SPEED", "MPC_ACC_HOR", "MPC_ACC_UP_MAX",
                   "MPC_ACC_DOWN_MAX", "MPC_JERK_AUTO")
    loss_required_params = ("COM_OF_LOSS_T", "COM_OBL_RC_ACT")

    def loss_behaviour(self, params: Mapping[str, float], rc: bool = False) -> LossBehaviour:
        """PX4 (commander, offboard loss; ../shared/notes/mavlink-facts.md, PX4 v1.16 SIH): the
        last setpoint is flown as it was for COM_OF_LOSS_T (default 1 s), then COM_OBL_RC_ACT
        (default 0): 0 Position, 1 Altitude, 2 Manual are a pilot's modes; without RC PX4's
        fallback descends at MPC_LAND_SPEED with no horizontal control (it drifts; measured
        4 m from a hover); 3 Return, 4 Land, 5 Hold (for ever, never lands by itself),
        6 Terminate, 7 Disarm; any other value is Position's (failsafe.cpp,
        fromOffboardLossActParam's default). Hold and Land stop at the point Navigator predicts
        (preproject_stop_point: s^2/(2 MPC_ACC_HOR) + 0.6 s) within MPC_ACC_HOR and
        MPC_JERK_AUTO, vertically within MPC_ACC_UP_MAX / MPC_ACC_DOWN_MAX."""
        timeout = param_or(params, "COM_OF_LOSS_T", 1.0)
        action = int(param_or(params, "COM_OBL_RC_ACT", 0.0))
        land = param_or(params, "MPC_LAND_SPEED", 0.7)
        jerk = param_or(params, "MPC_JERK_AUTO", 4.0)
        hold = LossBehaviour(
            timeout, CarryOn.SETPOINT, AfterLoss.HOLD, Mode.HOLD, brake_hor_mps2=param_or(params, "MPC_ACC_HOR", 3.0),
            brake_ver_mps2=min(param_or(params, "MPC_ACC_UP_MAX", 4.0), param_or(params, "MPC_ACC_DOWN_MAX", 3.0)),
            jerk_hor_mps3=jerk, jerk_ver_mps3=jerk, stop_lead_s=PX4_STOP_LEAD_S,
            params=tuple((n, float(params[n])) for n in self.loss_params if n in params), action_param="COM_OBL_RC_ACT")
        if action in COM_OBL_RC_ACT_MODES or action not in range(8):
            mode = COM_OBL_RC_ACT_MODES.get(action, Mode.POSITION)
            if rc:
                return replace(hold, then=AfterLoss.PILOT, mode=mode)
            return replace(hold, then=AfterLoss.DESCEND, mode=mode, descent_speed_mps=land, drift_m=PX4_NO_RC_DRIFT_M)
        if action == 3:
            return replace(hold, then=AfterLoss.RETURN, mode=Mode.RETURN, descent_speed_mps=land)
        if action == 4:
            return replace(hold, then=AfterLoss.LAND, mode=Mode.LAND, descent_speed_mps=land)
        if action in (6, 7):
            return replace(hold, then=AfterLoss.MOTORS_OFF)
        return hold  # 5

    def loss_fix(self, then: AfterLoss) -> dict[str, float]:
        if then == AfterLoss.HOLD:
            return {"COM_OBL_RC_ACT": 5}
        if then == AfterLoss.LAND:
            return {"COM_OBL_RC_ACT": 4}
        raise ValueError(f"PX4 is set to {then.value} on offboard loss by no swarmdrop option; set COM_OBL_RC_ACT "
                         "yourself")

    def loss_fix_text(self) -> str:
        return "set COM_OBL_RC_ACT to 5 (Hold) or 4 (Land)"
