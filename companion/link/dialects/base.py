"""The autopilot dialect base class: what differs between autopilots (PX4, ArduPilot, ...).

Both ends use it: the agent to drive a real (or simulated) autopilot, the SITL to
behave like one. A dialect is picked from the HEARTBEAT's `autopilot` field
(`dialect_for_autopilot`). Everything autopilot-specific lives in its subclass:
mode numbers, the set-mode command, how integer parameters travel, the hover-thrust
and setpoint-timeout parameters, how SET_ATTITUDE_TARGET's thrust is read, what
"ready after launch" looks like, and what to configure before flight. A third
autopilot is one new file (a subclass registers itself: companion.link.registry). The
SITL's side of an autopilot, how it behaves, is sim_bridge/sitl/autopilots/ (docs/sitl.md).
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar

from companion.link.enums import MavLandedState, MavModeFlag, MavState
from companion.link.params import Encoding
from companion.link.setpoints import SetpointRules

_F, _S, _L = MavModeFlag, MavState, MavLandedState
# Short names for the values every dialect uses (companion/link/enums.py has them all).
MODE_FLAG_CUSTOM = _F.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
MODE_FLAG_TEST = _F.MAV_MODE_FLAG_TEST_ENABLED
MODE_FLAG_AUTO = _F.MAV_MODE_FLAG_AUTO_ENABLED
MODE_FLAG_GUIDED = _F.MAV_MODE_FLAG_GUIDED_ENABLED
MODE_FLAG_STABILIZE = _F.MAV_MODE_FLAG_STABILIZE_ENABLED
MODE_FLAG_HIL = _F.MAV_MODE_FLAG_HIL_ENABLED
MODE_FLAG_MANUAL_INPUT = _F.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
MODE_FLAG_ARMED = _F.MAV_MODE_FLAG_SAFETY_ARMED
STATE_STANDBY, STATE_ACTIVE, STATE_CRITICAL, STATE_FLIGHT_TERMINATION = (
    _S.MAV_STATE_STANDBY, _S.MAV_STATE_ACTIVE, _S.MAV_STATE_CRITICAL, _S.MAV_STATE_FLIGHT_TERMINATION)
LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = (
    _L.MAV_LANDED_STATE_UNDEFINED, _L.MAV_LANDED_STATE_ON_GROUND, _L.MAV_LANDED_STATE_IN_AIR,
    _L.MAV_LANDED_STATE_TAKEOFF, _L.MAV_LANDED_STATE_LANDING)


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


class CarryOn(Enum):
    """What of the last setpoint keeps acting after the companion falls silent, until the
    autopilot's setpoint timeout."""

    SETPOINT = "setpoint"
    """The whole last setpoint, as it was (PX4: its position target stays where it was)."""
    VELOCITY_ACCELERATION = "velocity_acceleration"
    """Its velocity and acceleration: the target moves on along them (ArduPilot GUIDED)."""


class AfterLoss(Enum):
    """What the autopilot does once the setpoint timeout has passed."""

    HOLD = "hold"
    """Stop and hold position, for ever (it never lands by itself)."""
    LAND = "land"
    """Land where it stops, holding position, at descent_speed_mps."""
    DESCEND = "descend"
    """Descend at descent_speed_mps with no horizontal control: it drifts (wind, bias, its
    own velocity) until it lands."""
    RETURN = "return"
    """Return to its home and land."""
    PILOT = "pilot"
    """Hand the vehicle to an RC pilot's mode."""
    MOTORS_OFF = "motors_off"
    """Terminate or disarm in the air: it falls."""


@dataclass(frozen=True)
class LossBehaviour:
    """What an autopilot does when its companion's setpoints stop (for a swarm's ghost of a
    silent member): for timeout_s the last setpoint keeps acting (carry_on says how much of
    it), then `then`, with the mode the autopilot reports from then on (Mode.OFFBOARD: it
    stays in its offboard mode, as ArduPilot's GUIDED) and the descent speed of LAND and
    DESCEND (m/s, down; 0 otherwise). Built by AutopilotDialect.loss_behaviour from the
    autopilot's parameters."""

    timeout_s: float
    carry_on: CarryOn
    then: AfterLoss
    mode: Mode
    descent_speed_mps: float = 0.0
    # How it brakes (the swarm's ghost, companion.control.ghost); the defaults are the ghost's
    # model before issue 18: 3 m/s^2 at once (an infinite jerk), no lead, no drift.
    brake_hor_mps2: float = 3.0
    """Horizontal deceleration limit when it stops (PX4 MPC_ACC_HOR, ArduPilot WPNAV_ACCEL), m/s^2."""
    brake_ver_mps2: float = 3.0
    """Vertical deceleration limit (PX4 the smaller of MPC_ACC_UP_MAX and MPC_ACC_DOWN_MAX,
    ArduPilot WPNAV_ACCEL_Z), m/s^2."""
    jerk_hor_mps3: float = math.inf
    """Horizontal jerk limit of its stop (PX4 MPC_JERK_AUTO, ArduPilot PSC_JERK_XY), m/s^3."""
    jerk_ver_mps3: float = math.inf
    """Vertical jerk limit (PX4 MPC_JERK_AUTO, ArduPilot PSC_JERK_Z), m/s^3."""
    stop_lead_s: float = 0.0
    """It flies to its own predicted stop point, s^2 / (2 brake_hor) + stop_lead_s s from a
    horizontal speed s (PX4: 0.6 s, Navigator::preproject_stop_point), s."""
    drift_m: float = 0.0
    """Horizontal drift beyond its carried speed while it descends or falls with no horizontal
    control (PX4 v1.16 SIH, no RC, from a hover: 4 m; ../shared/notes/mavlink-facts.md), m."""
    params: tuple[tuple[str, float], ...] = ()
    """The parameter values it was built from, (name, value) (logs and refusals name them)."""
    action_param: str = ""
    """The parameter whose value chose `then` ("" when nothing does: ArduPilot GUIDED)."""

    @property
    def drifts(self) -> bool:
        """After the timeout nothing holds the vehicle's horizontal position."""
        return self.then == AfterLoss.DESCEND

    @property
    def lands(self) -> bool:
        """It comes down by itself (landing, descending or falling)."""
        return self.then in (AfterLoss.LAND, AfterLoss.DESCEND, AfterLoss.MOTORS_OFF)

    @property
    def safe(self) -> bool:
        """It stops and holds or lands under position control: the swarm's ghost covers it
        tightly (a drift, a flight home, a pilot or a fall it does not)."""
        return self.then in (AfterLoss.HOLD, AfterLoss.LAND)

    def value(self, name: str) -> float | None:
        """The value of a parameter it was built from (None: not among them)."""
        return dict(self.params).get(name)

    def what_then(self) -> str:
        """What the vehicle does after the timeout, in words."""
        return {
            AfterLoss.HOLD: "stops and holds there for ever (it never lands by itself)",
            AfterLoss.LAND: f"stops and lands there at {self.descent_speed_mps:g} m/s",
            AfterLoss.DESCEND: f"descends at {self.descent_speed_mps:g} m/s with no horizontal control, drifting "
                               "until it lands",
            AfterLoss.RETURN: "flies to its home and lands there",
            AfterLoss.PILOT: "waits for an RC pilot to fly it",
            AfterLoss.MOTORS_OFF: "stops its motors and falls",
        }[self.then]

    def deciding(self) -> str:
        """The parameter (and value) that chose what it does after the timeout."""
        value = self.value(self.action_param)
        return f"{self.action_param} = {value:g}" if value is not None else f"{self.then.value} on setpoint timeout"

    def describe(self) -> str:
        """One line: how long and how it flies on, what then, how it brakes, and from which values."""
        carry = {CarryOn.SETPOINT: "flies its last setpoint as it was",
                 CarryOn.VELOCITY_ACCELERATION: "moves on along its last velocity and acceleration"}[self.carry_on]
        text = f"it {carry} for {self.timeout_s:g} s, then {self.what_then()}"
        if self.then in (AfterLoss.HOLD, AfterLoss.LAND):
            text += (f"; it stops at {self.brake_hor_mps2:g} m/s^2 horizontally, {self.brake_ver_mps2:g} vertically "
                     f"(jerk {self.jerk_hor_mps3:g}, {self.jerk_ver_mps3:g} m/s^3)")
        if self.params:
            text += " (" + ", ".join(f"{n} {v:g}" for n, v in self.params) + ")"
        return text


@dataclass(frozen=True)
class PositionLoop:
    """The part of an autopilot's position loops a companion's trajectory setpoint meets
    (docs/agent.md, "Whose integrator"): per axis group, position P (velocity per position
    error, 1/s), velocity P (acceleration per velocity error, 1/s) and velocity I
    (acceleration per velocity-error integral, 1/s^2; 0: the autopilot has no velocity
    integrator on that axis). Horizontal (xy) and vertical (z) as the autopilot's gains.
    """

    pos_p_xy_per_s: float
    vel_p_xy_per_s: float
    vel_i_xy_per_s2: float
    pos_p_z_per_s: float
    vel_p_z_per_s: float
    vel_i_z_per_s2: float

    def stiffness_per_s2(self) -> tuple[float, float, float]:
        """(north, east, down) acceleration the loops add per metre of position-target offset
        (velocity P times position P), 1/s^2: what the agent takes out of the feed-forward
        when it moves the target by a drive (companion.output, step 2)."""
        xy = self.pos_p_xy_per_s * self.vel_p_xy_per_s
        return xy, xy, self.pos_p_z_per_s * self.vel_p_z_per_s

    def drive_gain(self, ki_per_s3: float) -> tuple[float, float, float]:
        """(north, east, down) metres of target offset per metre of slot residual so that the
        autopilot's velocity integrator learns at ki_per_s3 (its rate per metre of offset is
        vel_i * pos_p), at most 1; 0 on an axis without a velocity integrator (the agent
        integrates that axis itself)."""
        def gain(i: float, p: float) -> float:
            rate = i * p
            return min(1.0, ki_per_s3 / rate) if rate > 0.0 and math.isfinite(rate) else 0.0
        xy = gain(self.vel_i_xy_per_s2, self.pos_p_xy_per_s)
        return xy, xy, gain(self.vel_i_z_per_s2, self.pos_p_z_per_s)


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
    setpoint_rules: ClassVar[SetpointRules] = SetpointRules()
    """What it refuses in offboard setpoints beyond PX4's decoding (companion.link.setpoints)."""

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

    loop_params: ClassVar[tuple[str, ...]] = ()
    """The parameters position_loop reads (fetch these from the autopilot; acceleration output)."""

    def position_loop(self, params: Mapping[str, float]) -> PositionLoop | None:
        """The autopilot's position-loop gains with these values of its loop_params (a missing
        one: the autopilot's default); None: this dialect does not say (the agent then keeps
        its own integral on every axis)."""
        return None

    loss_params: ClassVar[tuple[str, ...]]
    """The parameters loss_behaviour reads (fetch these from the autopilot)."""

    @abstractmethod
    def loss_behaviour(self, params: Mapping[str, float], rc: bool = False) -> LossBehaviour:
        """What this autopilot does when the companion's setpoints stop, with these values
        of its loss_params (a missing one: the autopilot's default); rc: an RC link to a
        pilot is present (a pilot's mode can then take over)."""

    loss_required_params: ClassVar[tuple[str, ...]] = ()
    """Those of loss_params that decide the action (the agent refuses to fly when one is not
    served); the others (braking limits) fall back to the autopilot's defaults."""

    def loss_fix(self, then: AfterLoss) -> dict[str, float]:
        """The parameter values that make the autopilot do `then` after the setpoint timeout
        (`swarmdrop agent --set-loss-action`; {}: it does so whatever its parameters).

        Raises:
            ValueError: this autopilot cannot be set to do that (the message says why).
        """
        raise ValueError(f"the {self.name} dialect does not say how to set its companion-loss action")

    def loss_fix_text(self) -> str:
        """How to make it stop and hold or land, in words (a refusal's fix)."""
        return "configure the autopilot to hold or land when its companion's setpoints stop"

    def loss_drifts(self, params: Mapping[str, float], rc: bool = False) -> bool:
        """These parameter values would leave a vehicle whose companion falls silent
        drifting, with no horizontal control (e.g. PX4 COM_OBL_RC_ACT 0, 1 or 2 without RC)."""
        return self.loss_behaviour(params, rc).drifts


def param_or(params: Mapping[str, float], name: str, default: float) -> float:
    """params[name] if present and finite, else default (a loss_behaviour helper)."""
    value = params.get(name, default)
    return float(value) if math.isfinite(value) else default


def clamp01(x: float) -> float:
    return 0.0 if not x > 0.0 else (1.0 if x > 1.0 else x)
