"""PX4: OFFBOARD mode, custom_mode = main << 16 | sub << 24, bytewise integer parameters."""
from __future__ import annotations

import math

from companion.link.dialects.base import (
    MODE_FLAG_AUTO,
    MODE_FLAG_CUSTOM,
    MODE_FLAG_GUIDED,
    MODE_FLAG_MANUAL_INPUT,
    MODE_FLAG_STABILIZE,
    STATE_ACTIVE,
    AutopilotDialect,
    HeartbeatState,
    Mode,
    clamp01,
)


def _px4(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


class Px4(AutopilotDialect):
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
