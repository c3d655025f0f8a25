"""The toy autopilot's MAVLink conventions, for the companion (an AutopilotDialect).

Modes 1-4, a plain custom_mode number in DO_SET_MODE param2, integer parameters by value,
take-off altitude above home in param7, SET_ATTITUDE_TARGET thrust as normalised thrust.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

from companion.link.dialects.base import (
    MODE_FLAG_ARMED,
    MODE_FLAG_CUSTOM,
    AfterLoss,
    AutopilotDialect,
    CarryOn,
    HeartbeatState,
    LossBehaviour,
    Mode,
    clamp01,
    param_or,
)
from companion.link.enums import MavAutopilot

HOLD, TAKEOFF, OFFBOARD, LAND = 1, 2, 3, 4


class Toy(AutopilotDialect):
    """A minimal autopilot family: four modes, nothing else."""

    name = "toy"
    autopilot_id = MavAutopilot.MAV_AUTOPILOT_GENERIC
    param_encoding = "c_cast"
    hover_thrust_param = "TOY_HOVER"
    setpoint_timeout_param = "TOY_SP_TIMEOUT"
    modes = {Mode.HOLD: HOLD, Mode.TAKEOFF: TAKEOFF, Mode.OFFBOARD: OFFBOARD, Mode.LAND: LAND}
    takeoff_from_mode = Mode.HOLD
    carrier_mode = None

    def mode_name(self, custom_mode: int) -> str:
        mode = self.mode_of(custom_mode)
        return f"toy {mode.value}" if mode is not None else f"toy mode {custom_mode}"

    def set_mode_params(self, mode: Mode) -> tuple[float, float, float]:
        return float(MODE_FLAG_CUSTOM), float(self.modes[mode]), 0.0

    def mode_from_set_mode(self, param1: float, param2: float, param3: float) -> Mode | None:
        if not (math.isfinite(param1) and math.isfinite(param2)) or not int(param1) & MODE_FLAG_CUSTOM:
            return None
        return self.mode_of(int(param2))

    def base_mode(self, mode: Mode, armed: bool) -> int:
        return MODE_FLAG_CUSTOM | (MODE_FLAG_ARMED if armed else 0)

    def launch_ready(self, hb: HeartbeatState) -> bool:
        return hb.armed and hb.in_air and self.mode_of(hb.custom_mode) in (Mode.HOLD, Mode.OFFBOARD)

    def takeoff_params(self, altitude_rel_m: float, home_alt_amsl_m: float) -> tuple[float, ...]:
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, altitude_rel_m)

    def carrier_params(self) -> dict[str, float]:
        return {}

    def attitude_params(self) -> dict[str, float]:
        return {}

    def thrust_field(self, thrust_over_weight: float, hover_thrust: float, cos_tilt: float) -> float:
        return clamp01(thrust_over_weight * hover_thrust)

    def collective_from_thrust_field(self, thrust: float, cos_tilt: float) -> float:
        return clamp01(thrust)

    loss_params = ("TOY_SP_TIMEOUT",)

    def loss_behaviour(self, params: Mapping[str, float], rc: bool = False) -> LossBehaviour:
        return LossBehaviour(param_or(params, "TOY_SP_TIMEOUT", 0.5), CarryOn.SETPOINT, AfterLoss.HOLD, Mode.HOLD)
