"""The SITL's autopilot behaviour base class: how an autopilot family behaves, as the
companion's dialect (companion/link/dialects/) says how it speaks.

The per-vehicle state machine (sim_bridge/sitl/autopilot.py) is autopilot-neutral: it
arms, takes off, flies offboard setpoints, detects landings, fails safe, and asks the
vehicle's `AutopilotBehaviour` wherever PX4 and ArduPilot differ:

* its parameter table (names, units, defaults, and which parameter plays which `Role`);
* its position and velocity loops' gains, from its own parameters (`position_loop`; the
  loop itself is sim_bridge.world.position_loop's, run by the physics stepper);
* offboard/GUIDED entry: whether a live setpoint stream is required, whether entering
  clears the last setpoint, whether setpoints outside it are flown;
* what it does when the companion's setpoints stop (`offboard_lost`, by default as the
  dialect's `LossBehaviour` for the table's parameters says);
* the mode after a take-off, after a throw launch, and on release from the carrier;
* origin rules (may SET_GPS_GLOBAL_ORIGIN move an existing origin?);
* take-off parameters (`takeoff_alt_rel_m`);
* setpoint rules (the dialect's `SetpointRules`) and what SET_ATTITUDE_TARGET's thrust
  means (`attitude_thrust`), its limits and geofence.

A behaviour is keyed by the companion dialect's `name` and registers itself by being
defined (companion.link.registry): a third autopilot is one new file here (or anywhere,
imported) beside its dialect. A behaviour holds no per-vehicle state: it is handed the
vehicle's state machine (as a `Machine`) or `ParamTable` where it needs them.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import ClassVar, Protocol

import numpy as np

from companion.link.dialects import AutopilotDialect, Mode, dialect_named
from companion.link.dialects.base import AfterLoss, LossBehaviour
from companion.link.limits import SetpointLimits
from companion.link.setpoints import AttitudeSetpoint
from companion.params import InnerLoopConfig
from sim_bridge.sitl.params_table import ParamSpec, ParamTable, Role, simulator_specs
from sim_bridge.world.position_loop import PositionLoopGains


class Machine(Protocol):
    """What a behaviour reads of one vehicle's state machine (sim_bridge.sitl.autopilot.Autopilot)
    and the primitives it acts through. A Protocol, so that the behaviours and the machine
    that calls them do not import each other."""

    mode: Mode
    armed: bool
    params: ParamTable

    @property
    def knobs(self) -> "Knobs": ...
    @property
    def rot(self) -> np.ndarray: ...
    @property
    def vel(self) -> np.ndarray: ...
    def event(self, severity: int, text: str) -> None: ...
    def set_mode(self, mode: Mode, now_s: float) -> None: ...
    def failsafe_hold(self, now_s: float, text: str) -> None: ...
    def failsafe_mode(self, mode: Mode, now_s: float, text: str, descend_drifting: bool = False) -> None: ...
    def failsafe_disarm(self, now_s: float, text: str) -> None: ...
    def stop_offboard_in_place(self, text: str) -> None: ...
    def clear_offboard_setpoint(self) -> None: ...


class AutopilotBehaviour(ABC):
    """One autopilot family's behaviour in the SITL (stateless; one instance per family)."""

    name: ClassVar[str]
    """The companion dialect's name (companion.link.dialects.DIALECTS)."""
    offboard_needs_stream: ClassVar[bool] = False
    """Offboard is refused, and arming in it fails pre-arm, without a live setpoint stream;
    a lockstep clock waits for a plain client's next setpoint while it flies offboard."""
    offboard_entry_clears_setpoint: ClassVar[bool] = False
    """Entering the offboard mode starts from a hold: only setpoints sent from then on count."""
    setpoints_only_in_offboard: ClassVar[bool] = False
    """Setpoints received outside the offboard mode are dropped (counted), not kept for it."""
    origin_movable: ClassVar[bool] = True
    """SET_GPS_GLOBAL_ORIGIN moves an origin the EKF already has."""
    armed_docked_state: ClassVar[int | None] = None
    """HEARTBEAT.system_status while armed on the carrier with the motors held (None: the usual)."""
    release_mode: ClassVar[Mode] = Mode.THROW
    """The mode a throw launch flies in from the release until the vehicle is recovered."""
    after_takeoff_mode: ClassVar[Mode] = Mode.HOLD
    """The mode a finished take-off switches to."""
    supports_failure_injection: ClassVar[bool] = False
    """MAV_CMD_INJECT_FAILURE exists (gated by its own parameter, `failure_injection_enabled`)."""
    throw_uprights_first: ClassVar[bool] = False
    """A throw launch first uprights the vehicle on attitude alone (level, THROW_UPRIGHT_THRUST, no
    angle boost) until cos(tilt) > THROW_UPRIGHT_COS, and only then flies the recovery's zero
    velocity through its position loops (ArduCopter's Throw_Uprighting stage); else the
    position loops fly it from the release (PX4)."""
    says_unknown_interval_id: ClassVar[bool] = False
    """A SET_MESSAGE_INTERVAL for a message it does not stream is answered FAILED (PX4 and
    ArduPilot alike) and also announced in a STATUSTEXT (ArduPilot: "No ap_message for
    mavlink id (N)", GCS_Common.cpp)."""
    heartbeat_on_change: ClassVar[bool] = True
    """A mode or arming change goes out in a HEARTBEAT at once, right after the command's ACK
    (ArduCopter's set_mode sends MSG_HEARTBEAT; for arming this is assumed, not read); else
    (PX4, whose HEARTBEAT is a 1 Hz stream) it shows in the next of its 1 Hz HEARTBEATs, up to a second after the ACK
    (../shared/notes/mavlink-facts.md): the order behind a companion's false "left offboard"."""
    attitude_thrust_follows_tilt: ClassVar[bool] = False
    """The inner-loop thrust of an attitude setpoint depends on the tilt (angle boost, a
    climb rate): the setpoint is rebuilt every tick while one is flown."""

    @property
    def dialect(self) -> AutopilotDialect:
        """The companion's side of this autopilot (modes, HEARTBEAT, encodings)."""
        return dialect_named(self.name)

    # ---- parameters ---------------------------------------------------------------
    @abstractmethod
    def own_specs(self, inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> list[ParamSpec]:
        """The autopilot's own parameters (names, units, defaults, roles).

        Args:
            inner: the simulated inner loop (tilt limit).
            sysid: the vehicle's MAVLink system id.
            hover_thrust: the simulated airframe's hover thrust as a fraction of maximum.
        """

    def param_specs(self, inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> tuple[ParamSpec, ...]:
        """Every parameter of one vehicle (own and the simulator's), in name order, as
        autopilots serve them.

        Raises:
            ValueError: a Role no parameter has, or a name given twice.
        """
        specs = sorted(simulator_specs(inner) + self.own_specs(inner, sysid, hover_thrust), key=lambda s: s.name)
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: a parameter name is given twice")
        missing = set(Role) - {r for s in specs for r in s.roles}
        if missing:
            raise ValueError(f"{self.name}: no parameter has role(s) {sorted(r.value for r in missing)}")
        return tuple(specs)

    def knobs(self, table: ParamTable) -> "Knobs":
        """What the state machine reads from one vehicle's table."""
        return Knobs(table, self)

    # ---- rules that read parameters ---------------------------------------------
    def throw_enabled(self, table: ParamTable) -> bool:
        """A carrier release is a throw launch (the autopilot recovers the vehicle)."""
        return True

    def may_arm_docked(self, table: ParamTable, mode: Mode) -> bool:
        """Arming on the carrier (before release) passes pre-arm in this mode."""
        return self.throw_enabled(table)

    def thrust_is_thrust(self, table: ParamTable) -> bool:
        """SET_ATTITUDE_TARGET.thrust is a thrust (else: something else, e.g. a climb rate)."""
        return True

    def loss_behaviour(self, table: ParamTable) -> LossBehaviour:
        """What this autopilot does when the companion's setpoints stop, with this table's
        values (the companion dialect's description: one home for it; the SITL has no RC)."""
        d = self.dialect
        return d.loss_behaviour({n: table[n] for n in d.loss_params if table.index_of(n) is not None}, rc=False)

    @abstractmethod
    def position_loop(self, table: ParamTable, hover_thrust_true: float) -> PositionLoopGains:
        """The gains and limits of this autopilot's position and velocity loops, in SI units,
        from its own parameters (sim_bridge.world.position_loop.PositionLoopGains).

        Args:
            table: the vehicle's parameter table (its hover-thrust parameter may be off).
            hover_thrust_true: the airframe's true hover thrust (fraction of maximum).
        """

    def failure_injection_enabled(self, table: ParamTable) -> bool:
        """MAV_CMD_INJECT_FAILURE is accepted now (supports_failure_injection and its parameter)."""
        return False

    def limits(self, table: ParamTable) -> SetpointLimits:
        """Offboard setpoint limits (companion.link.limits): the defaults, with the table's tilt."""
        return SetpointLimits(tilt_max_rad=math.radians(table.role(Role.TILT_MAX_DEG)))

    def geofence(self, table: ParamTable) -> tuple[int, float, float]:
        """(action, horizontal radius m, maximum height m); radius/height 0 = off.
        Actions as PX4's GF_ACTION: 2 hold, 3 and 5 land, 4 terminate, else warn."""
        return 0, 0.0, 0.0

    # ---- rules that act on the vehicle ------------------------------------------
    def takeoff_alt_rel_m(self, ap: Machine, param7: float, home_alt_amsl_m: float) -> float | None:
        """MAV_CMD_NAV_TAKEOFF: the height above home to climb to, or None if this autopilot
        refuses the command now (it has said why with a STATUSTEXT; the ACK is FAILED).
        Default: param7 is the height above home; 0 or NaN take the parameter's."""
        return param7 if math.isfinite(param7) and param7 > 0 else ap.knobs.takeoff_alt_m

    def offboard_lost(self, ap: Machine, now_s: float) -> None:
        """The companion's setpoints have stopped for the offboard timeout (while the
        vehicle flies offboard): do what the autopilot does. Default: what its LossBehaviour
        says (Return is Land here: the SITL has no RTL; a pilot's mode, which needs RC the
        SITL does not have, descends without horizontal control)."""
        lb = ap.knobs.loss
        if lb.mode == Mode.OFFBOARD:  # it stays in its offboard mode and stops (ArduPilot GUIDED)
            ap.stop_offboard_in_place(f"{self.dialect.mode_name(self.dialect.custom_mode(Mode.OFFBOARD))}: "
                                      "setpoint timeout, stopping")
        elif lb.then == AfterLoss.HOLD:
            ap.failsafe_hold(now_s, "Failsafe: offboard signal lost, Hold")
        elif lb.then in (AfterLoss.LAND, AfterLoss.RETURN):
            ap.failsafe_mode(Mode.LAND, now_s, "Failsafe: offboard signal lost, Land")
        elif lb.then == AfterLoss.MOTORS_OFF:
            ap.failsafe_disarm(now_s, "Failsafe: offboard signal lost, motors off")
        else:  # DESCEND (or PILOT without RC)
            name = self.dialect.mode_name(self.dialect.custom_mode(lb.mode))
            ap.failsafe_mode(lb.mode, now_s, f"Failsafe: offboard signal lost, {name}: no RC, descending",
                             descend_drifting=True)

    @abstractmethod
    def throw_recovered(self, ap: Machine, now_s: float) -> None:
        """A throw launch has recovered the vehicle: switch to the autopilot's next mode."""

    def attitude_thrust(self, ap: Machine, o: AttitudeSetpoint) -> float:
        """Fraction of maximum collective thrust the inner loop gets for an attitude
        setpoint (default: the field is the normalised thrust)."""
        return o.thrust_norm


class Knobs:
    """What the autopilot state machine reads from one vehicle's table, in SI units,
    whichever autopilot's names the table speaks (by Role, and the behaviour's rules).

    Args:
        table: the vehicle's parameter table.
        behaviour: its autopilot's behaviour.
    """

    def __init__(self, table: ParamTable, behaviour: AutopilotBehaviour):
        self.t = table
        self.behaviour = behaviour
        self._lim_version = -1
        self._lim = SetpointLimits()
        self._loss_version = -1
        self._loss: LossBehaviour | None = None

    @property
    def takeoff_alt_m(self) -> float:
        """Take-off height above home when the command gives none, m."""
        return self.t.role(Role.TAKEOFF_ALT_M)

    @property
    def takeoff_speed_mps(self) -> float:
        """Climb speed of a take-off, m/s."""
        return self.t.role(Role.TAKEOFF_SPEED_MPS)

    @property
    def descent_speed_mps(self) -> float:
        """Descent speed, m/s."""
        return self.t.role(Role.DESCENT_SPEED_MPS)

    @property
    def land_speed_mps(self) -> float:
        """Descent speed in Land, m/s."""
        return self.t.role(Role.LAND_SPEED_MPS)

    @property
    def offboard_timeout_s(self) -> float:
        """How long the autopilot flies on without a new companion setpoint, s."""
        return self.t.role(Role.OFFBOARD_TIMEOUT_S)

    @property
    def loss(self) -> LossBehaviour:
        """What the autopilot does when the companion's setpoints stop (cached per table version)."""
        t = self.t
        if self._loss_version != t.version or self._loss is None:
            self._loss_version, self._loss = t.version, self.behaviour.loss_behaviour(t)
        return self._loss

    @property
    def disarm_preflight_s(self) -> float:
        """Disarm this long after arming without a take-off, s (<= 0 off)."""
        return self.t.role(Role.DISARM_PREFLIGHT_S)

    @property
    def disarm_land_s(self) -> float:
        """Disarm this long after landing, s (< 0 off)."""
        return self.t.role(Role.DISARM_LAND_S)

    @property
    def throw_enabled(self) -> bool:
        """A carrier release is a throw launch."""
        return self.behaviour.throw_enabled(self.t)

    @property
    def hover_thrust(self) -> float:
        """Normalised collective thrust that hovers, as the parameter says."""
        return self.t.role(Role.HOVER_THRUST)

    @property
    def thrust_is_thrust(self) -> bool:
        """SET_ATTITUDE_TARGET.thrust is thrust."""
        return self.behaviour.thrust_is_thrust(self.t)

    def limits(self) -> SetpointLimits:
        """Offboard setpoint limits, cached per table version."""
        t = self.t
        if self._lim_version == t.version:
            return self._lim
        self._lim_version, self._lim = t.version, self.behaviour.limits(t)
        return self._lim

    def geofence(self) -> tuple[int, float, float]:
        """(action, horizontal radius m, maximum height m); radius/height 0 = off."""
        return self.behaviour.geofence(self.t)

    def throw_thresholds(self) -> tuple[float, float, float]:
        """Tilt (deg), body rate (rad/s) and speed (m/s) under which a throw is recovered."""
        return self.t["SD_THR_TILT"], self.t["SD_THR_RATE"], self.t["SD_THR_SPEED"]

