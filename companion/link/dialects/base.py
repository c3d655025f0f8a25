"""The autopilot dialect base class: what differs between PX4 and ArduPilot.

Both ends use it: the agent to drive a real (or simulated) autopilot, the SITL to
behave like one. A dialect is picked from the HEARTBEAT's `autopilot` field
(`dialect_for_autopilot`). Everything autopilot-specific lives in its subclass:
mode numbers, the set-mode command, how integer parameters travel, the hover-thrust
and setpoint-timeout parameters, how SET_ATTITUDE_TARGET's thrust is read, what
"ready after launch" looks like, and what to configure before flight. A third
autopilot is one new file in this folder (the registry imports every module here).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar

from companion.link.params import Encoding

# MAV_MODE_FLAG bits of HEARTBEAT.base_mode
MODE_FLAG_CUSTOM = 1
MODE_FLAG_TEST = 2
MODE_FLAG_AUTO = 4
MODE_FLAG_GUIDED = 8
MODE_FLAG_STABILIZE = 16
MODE_FLAG_HIL = 32
MODE_FLAG_MANUAL_INPUT = 64
MODE_FLAG_ARMED = 128
# MAV_STATE
STATE_STANDBY, STATE_ACTIVE, STATE_CRITICAL, STATE_FLIGHT_TERMINATION = 3, 4, 5, 8
# MAV_LANDED_STATE
LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 0, 1, 2, 3, 4


class Mode(Enum):
    """What a flight mode does, whatever an autopilot calls it."""

    MANUAL = "manual"
    POSITION = "position"
    HOLD = "hold"
    OFFBOARD = "offboard"  # PX4 OFFBOARD, ArduPilot GUIDED: a companion's setpoints are flown
    TAKEOFF = "takeoff"
    LAND = "land"
    RETURN = "return"
    THROW = "throw"


@dataclass(frozen=True)
class HeartbeatState:
    """The parts of an autopilot's state a companion reads (HEARTBEAT, EXTENDED_SYS_STATE)."""

    custom_mode: int
    base_mode: int
    system_status: int
    landed_state: int = LANDED_UNDEFINED

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & MODE_FLAG_ARMED)

    @property
    def in_air(self) -> bool:
        return self.landed_state in (LANDED_IN_AIR, LANDED_LANDING)


class AutopilotDialect(ABC):
    """One autopilot family's MAVLink conventions (class attributes and small pure methods)."""

    name: ClassVar[str]
    autopilot_id: ClassVar[int]
    """HEARTBEAT.autopilot (MAV_AUTOPILOT)."""
    param_encoding: ClassVar[Encoding]
    hover_thrust_param: ClassVar[str]
    """Normalised collective thrust that hovers (0..1)."""
    setpoint_timeout_param: ClassVar[str]
    """How long the autopilot flies on without a new companion setpoint."""
    modes: ClassVar[dict[Mode, int]]
    """custom_mode of each Mode it has (Modes it lacks are absent)."""

    def custom_mode(self, mode: Mode) -> int:
        """custom_mode for a Mode. Raises KeyError: this autopilot has no such mode."""
        return self.modes[mode]

    def mode_of(self, custom_mode: int) -> Mode | None:
        """The Mode a custom_mode means (None: a mode swarmdrop does not use)."""
        for mode, value in self.modes.items():
            if value == custom_mode:
                return mode
        return None

    @abstractmethod
    def mode_name(self, custom_mode: int) -> str:
        """A human-readable name (logs, STATUSTEXT)."""

    @abstractmethod
    def set_mode_params(self, mode: Mode) -> tuple[float, float, float]:
        """(param1, param2, param3) of MAV_CMD_DO_SET_MODE (176) for a Mode."""

    @abstractmethod
    def mode_from_set_mode(self, param1: float, param2: float, param3: float) -> Mode | None:
        """The Mode a DO_SET_MODE asks for (SITL side); None if unknown or malformed."""

    @abstractmethod
    def base_mode(self, mode: Mode, armed: bool) -> int:
        """HEARTBEAT.base_mode this autopilot reports (SITL side)."""

    @abstractmethod
    def launch_ready(self, hb: HeartbeatState) -> bool:
        """The vehicle has recovered from its launch (throw recovery or take-off
        finished) and will fly companion setpoints once switched to Mode.OFFBOARD."""

    @abstractmethod
    def takeoff_params(self, altitude_rel_m: float, home_alt_amsl_m: float) -> tuple[float, ...]:
        """The seven params of MAV_CMD_NAV_TAKEOFF (22) to climb altitude_rel_m above home."""

    takeoff_from_mode: ClassVar[Mode]
    """The mode to be in (armed) before MAV_CMD_NAV_TAKEOFF."""

    @abstractmethod
    def carrier_params(self) -> dict[str, float]:
        """Parameters that must hold before a carrier release (throw launch)."""

    @abstractmethod
    def attitude_params(self) -> dict[str, float]:
        """Parameters that must hold before SET_ATTITUDE_TARGET thrust means thrust."""

    carrier_mode: ClassVar[Mode | None]
    """Mode to select on the carrier before release (None: any)."""

    @abstractmethod
    def thrust_field(self, thrust_over_weight: float, hover_thrust: float, cos_tilt: float) -> float:
        """SET_ATTITUDE_TARGET.thrust for a collective thrust of thrust_over_weight
        times the weight, with the vehicle tilted by arccos(cos_tilt) (0..1)."""

    @abstractmethod
    def collective_from_thrust_field(self, thrust: float, cos_tilt: float) -> float:
        """Inverse of thrust_field as a fraction of maximum thrust (SITL side), before
        the hover normalisation: what the motors are asked for."""


def clamp01(x: float) -> float:
    return 0.0 if not x > 0.0 else (1.0 if x > 1.0 else x)
