"""Per-vehicle flight state machine of the SITL: pure logic, no sockets.

One Autopilot per simulated vehicle, speaking one autopilot dialect (PX4 or
ArduCopter, companion.link.dialects): the dialect gives the mode numbers and
flags; this module gives the behaviour, with the differences that matter to a
companion (docs/sitl.md): PX4 stores offboard setpoints in any mode, needs a live
stream to enter OFFBOARD, flies the last setpoint for COM_OF_LOSS_T and then does what
COM_OBL_RC_ACT says; ArduPilot flies setpoints only in GUIDED, enters GUIDED without a
stream, moves its target on along the last velocity and acceleration until GUID_TIMEOUT,
then stops (or levels) but stays in GUIDED. What each does on loss is the companion
dialect's LossBehaviour for the vehicle's parameters (AutopilotBehaviour.offboard_lost). The
offboard target itself (the last setpoint, and what is left of it after a loss) is
sim_bridge.sitl.offboard_target.

It reads its vehicle's row of the shared FleetState (world NED frame) and
publishes the inner-loop setpoint in `sp` (a one-row FleetSetpoint, world frame;
`sp_version` increments on every change). Offboard setpoints arrive in the
vehicle's local frame (relative to its EKF origin) and are converted here. Times
are simulation seconds passed in by the caller. Human-readable events queue up in
`events` as (MAV_SEVERITY, text) for STATUSTEXT.
"""
from __future__ import annotations

import math

import numpy as np

from companion.frames import euler_zyx_to_quat_wxyz, rot_to_quat_wxyz
from companion.link.dialects import Mode
from companion.link.dialects.base import (
    LANDED_IN_AIR,
    LANDED_LANDING,
    LANDED_ON_GROUND,
    LANDED_TAKEOFF,
    STATE_ACTIVE,
    STATE_CRITICAL,
    STATE_STANDBY,
)
from companion.link.enums import MavResult, MavSeverity
from companion.link.setpoints import AttitudeSetpoint, TrajectorySetpoint
from companion.state import FleetSetpoint, FleetState
from sim_bridge.sitl.autopilots import AutopilotBehaviour
from sim_bridge.sitl.heartbeat import HeartbeatView
from sim_bridge.sitl.offboard_target import OffboardTarget
from sim_bridge.sitl.params_table import ParamTable
from sim_bridge.world.autopilot_model import (
    LAND_DETECT_S,
    THROW_UPRIGHT_COS,
    THROW_UPRIGHT_THRUST,
    hold_point,
    on_ground_and_slow,
    throw_recovered,
)

ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = (
    MavResult.MAV_RESULT_ACCEPTED, MavResult.MAV_RESULT_TEMPORARILY_REJECTED, MavResult.MAV_RESULT_DENIED,
    MavResult.MAV_RESULT_UNSUPPORTED, MavResult.MAV_RESULT_FAILED)
SEV_CRITICAL, SEV_WARNING, SEV_NOTICE, SEV_INFO = (
    MavSeverity.MAV_SEVERITY_CRITICAL, MavSeverity.MAV_SEVERITY_WARNING, MavSeverity.MAV_SEVERITY_NOTICE,
    MavSeverity.MAV_SEVERITY_INFO)
FORCE_MAGIC = 21196
"""MAV_CMD_COMPONENT_ARM_DISARM param2 that forces arming or disarming (MAVLink's own magic number)."""

AIRBORNE_HEIGHT_M = 0.15
SETTABLE = frozenset({Mode.POSITION, Mode.OFFBOARD, Mode.TAKEOFF, Mode.HOLD, Mode.LAND, Mode.THROW})
"""Modes a DO_SET_MODE may ask for (no RC: Manual and Return are refused)."""


class Autopilot:
    """The flight state machine of one simulated vehicle (module docstring): modes, arming,
    take-off, landing, failsafes and offboard setpoints, with its family's behaviour.

    Args:
        index: the vehicle's row in `state`; sysid: its MAVLink system id.
        params: its parameter table; behaviour: its autopilot family.
        state: the fleet's true state (world NED frame), read for this row.
        ground_z_m: NED z of the ground, m; home_ned_m: its home position (world NED, m).
        docked: on the carrier (waits for release); now_s: simulation time at creation, s.
    """

    def __init__(self, index: int, sysid: int, params: ParamTable, behaviour: AutopilotBehaviour, state: FleetState,
                 ground_z_m: float, home_ned_m: np.ndarray, docked: bool = False, now_s: float = 0.0):
        self.index = index
        self.sysid = sysid
        self.params = params
        self.behaviour = behaviour
        """How this vehicle's autopilot family behaves (sim_bridge/sitl/autopilots/)."""
        self.knobs = behaviour.knobs(params)
        self.dialect = behaviour.dialect
        self.state = state
        self.ground_z_m = ground_z_m
        self.home_ned_m = np.asarray(home_ned_m, dtype=float)
        self.origin_ned_m: np.ndarray | None = None
        """EKF origin in the world frame; None until the first GNSS fix."""
        self.armed = False
        self.mode = Mode.THROW if docked and self.dialect.carrier_mode == Mode.THROW else Mode.HOLD
        self.docked = docked
        self.throwing = False
        self.release_requested = False
        self.landed = True
        self.sp = FleetSetpoint.empty(1)
        self.sp_version = 0
        self.rates_only = False
        self.rate_q_reset = False
        self.events: list[tuple[int, str]] = []
        self.changed = False
        """A HEARTBEAT is due now: set on a mode or arming change where the family sends one at
        once, else when a 1 Hz slot shows a change (tick; sim_bridge.sitl.heartbeat); the server
        sends it and clears this."""
        self.setpoints_ignored = 0
        """Offboard setpoints dropped because the mode does not fly them (ArduPilot outside GUIDED)."""
        self.offb = OffboardTarget()
        """The companion's last setpoint (world frame) and what is left of it after a loss."""
        self._descend_drift = False
        """Failsafe descent with no horizontal control (PX4 COM_OBL_RC_ACT 0-2 without RC)."""
        self._uprighting = True
        """A throw is still being uprighted on attitude alone (behaviour.throw_uprights_first)."""
        self._now_s = now_s
        self.loop_reset = True
        """Set when the autopilot's position loops start afresh (arming, release); the fleet
        clears their memory and this flag."""
        self._failsafe_t: float | None = None
        self._ground_since_t: float | None = now_s
        self._landed_t = now_s
        self._armed_t = now_s
        self._airborne_since_arm = False
        self._last_tick_t = now_s
        self._hold_pos = self.pos.copy()
        self._hold_yaw = self.yaw
        self._tko_target_z = self.pos[2]
        self._tko_sp_z = self.pos[2]
        self._fence_breached = False
        self.heartbeat = HeartbeatView(behaviour.heartbeat_on_change, index, now_s,
                                       lambda: (self.base_mode, self.custom_mode, self.system_status))
        """What its HEARTBEAT says (sim_bridge.sitl.heartbeat)."""
        self._publish()

    # ---- vehicle state views -------------------------------------------------
    @property
    def pos(self) -> np.ndarray:
        return self.state.pos_ned_m[self.index]

    @property
    def vel(self) -> np.ndarray:
        return self.state.vel_ned_mps[self.index]

    @property
    def rot(self) -> np.ndarray:
        return self.state.rot_body_to_ned[self.index]

    @property
    def yaw(self) -> float:
        r = self.rot
        return math.atan2(r[1, 0], r[0, 0])

    @property
    def has_fix(self) -> bool:
        return self.origin_ned_m is not None

    # ---- reported state ------------------------------------------------------
    def _state_changed(self) -> None:
        """A mode or arming change: a HEARTBEAT at once where the family sends one (else its next slot shows it)."""
        if self.heartbeat.at_once:
            self.changed = True

    @property
    def custom_mode(self) -> int:
        return self.dialect.custom_mode(self.mode)

    @property
    def base_mode(self) -> int:
        return self.dialect.base_mode(self.mode, self.armed)

    @property
    def system_status(self) -> int:
        if self._failsafe_t is not None:
            return STATE_CRITICAL
        if self.armed and self.docked and self.behaviour.armed_docked_state is not None:
            return self.behaviour.armed_docked_state
        return STATE_ACTIVE if self.armed else STATE_STANDBY

    @property
    def landed_state(self) -> int:
        if self.landed:
            return LANDED_ON_GROUND
        if self.mode == Mode.TAKEOFF and self.armed:
            return LANDED_TAKEOFF
        if self.mode == Mode.LAND:
            return LANDED_LANDING
        return LANDED_IN_AIR

    @property
    def needs_physics(self) -> bool:
        """False while docked or resting disarmed on the ground (state frozen)."""
        if self.docked:
            return False
        return self.armed or not self.landed or float(np.abs(self.vel).max()) > 1e-3

    @property
    def fence_breached(self) -> bool:
        return self._fence_breached

    def offboard_live(self, now_s: float) -> bool:
        return self.offb.live(now_s, self.knobs.offboard_timeout_s)

    def prearm_failure(self, now_s: float) -> str | None:
        if self.docked and not self.behaviour.may_arm_docked(self.params, self.mode):
            return "docked on carrier"  # (with throw launch set up, arming on the carrier is the normal flow)
        if not self.has_fix:
            return "no GNSS fix"
        if self._fence_breached:
            return "geofence breached"
        if self.behaviour.offboard_needs_stream and self.mode == Mode.OFFBOARD and not self.offboard_live(now_s):
            return "no offboard signal"
        return None

    # ---- commands -------------------------------------------------------------
    def command_arm(self, p1: float, p2: float, now_s: float) -> int:
        if not math.isfinite(p1) or round(p1) not in (0, 1):
            return DENIED
        force = math.isfinite(p2) and round(p2) == FORCE_MAGIC
        if round(p1) == 1:
            if self.armed:
                return ACCEPTED
            why = self.prearm_failure(now_s)
            if why is None and not self.landed and not force and not self.docked:
                why = "not landed"
            if why is not None and not force:
                self.event(SEV_CRITICAL, f"Arming denied: {why}")
                return TEMPORARILY_REJECTED
            self._arm(now_s)
            return ACCEPTED
        if not self.armed:
            return ACCEPTED
        if not self.landed and not force:
            self.event(SEV_CRITICAL, "Disarming denied: not landed")
            return TEMPORARILY_REJECTED
        self._disarm(now_s, "Disarmed by external command")
        return ACCEPTED

    def command_takeoff(self, param7: float, home_alt_amsl_m: float, now_s: float) -> int:
        """MAV_CMD_NAV_TAKEOFF; what param7 means, and when it is refused, is the
        autopilot's (AutopilotBehaviour.takeoff_alt_rel_m)."""
        if self.docked:
            return TEMPORARILY_REJECTED
        alt_rel = self.behaviour.takeoff_alt_rel_m(self, param7, home_alt_amsl_m)
        if alt_rel is None:
            return FAILED
        if alt_rel < 0.1:
            return DENIED
        self._tko_target_z = self.home_ned_m[2] - alt_rel
        if self.mode == Mode.TAKEOFF:
            return ACCEPTED
        self._set_mode(Mode.TAKEOFF, now_s)
        return ACCEPTED

    def command_land(self, now_s: float) -> int:
        if self.docked:
            return TEMPORARILY_REJECTED
        if self.mode != Mode.LAND:
            self._set_mode(Mode.LAND, now_s)
        return ACCEPTED

    def command_set_mode(self, base: float, main: float, sub: float, now_s: float) -> int:
        mode = self.dialect.mode_from_set_mode(base, main, sub)
        if mode is None or mode not in SETTABLE or mode not in self.dialect.modes:
            return DENIED
        if self.docked and mode != self.dialect.carrier_mode:
            return TEMPORARILY_REJECTED
        if mode == self.mode:
            self._failsafe_t = None
            return ACCEPTED
        if mode == Mode.THROW and self.armed:
            self.event(SEV_CRITICAL, "Throw: select before arming")
            return TEMPORARILY_REJECTED
        if mode == Mode.OFFBOARD and not self.has_fix:
            return TEMPORARILY_REJECTED
        if mode == Mode.OFFBOARD and self.behaviour.offboard_needs_stream and not self.offboard_live(now_s):
            self.event(SEV_CRITICAL, "Switching to Offboard is currently not available")
            return TEMPORARILY_REJECTED
        if mode == Mode.TAKEOFF:
            self._tko_target_z = self.home_ned_m[2] - self.knobs.takeoff_alt_m
        if mode == Mode.OFFBOARD and self.behaviour.offboard_entry_clears_setpoint:
            self.offb.sp = None  # (ArduPilot's GUIDED starts holding; only setpoints sent from now on count)
        self._set_mode(mode, now_s)
        return ACCEPTED

    def command_release(self) -> int:
        if not self.docked:
            return DENIED
        self.release_requested = True
        return ACCEPTED

    # ---- origin ----------------------------------------------------------------
    def set_origin(self, origin_ned_m: np.ndarray, now_s: float, requested: bool = False) -> bool:
        """The EKF origin: set at the first fix; a later request moves it if the autopilot does."""
        if requested and self.has_fix and not self.behaviour.origin_movable:
            return False
        self.origin_ned_m = np.asarray(origin_ned_m, float).copy()
        self.event(SEV_INFO, "EKF origin set" if not requested else "EKF origin moved (local position reset)")
        return True

    # ---- offboard setpoints -----------------------------------------------------
    def on_offboard_setpoint(self, sp: TrajectorySetpoint | AttitudeSetpoint, now_s: float) -> bool:
        """A setpoint in the vehicle's local frame; False if this mode ignores it."""
        if self.behaviour.setpoints_only_in_offboard and self.mode != Mode.OFFBOARD:
            self.setpoints_ignored += 1
            return False
        if isinstance(sp, TrajectorySetpoint) and np.isfinite(sp.pos_ned_m).any():
            if not self.has_fix:
                self.setpoints_ignored += 1
                return False
            sp = TrajectorySetpoint(sp.pos_ned_m + self.origin_ned_m, sp.vel_ned_mps, sp.acc_ned_mps2, sp.yaw_rad,
                                    sp.yaw_rate_radps)
        self.offb.set(sp, now_s)
        self._now_s = now_s
        if self.mode == Mode.OFFBOARD:
            self._publish()
        return True

    def on_invalid_setpoint(self) -> None:
        """A trajectory setpoint left an axis without a finite source (PX4: "invalid
        setpoints"): in Offboard the vehicle stops (zero velocity) and holds its heading. The
        offboard signal is not refreshed, so a stream of invalid setpoints ends in the
        offboard-loss failsafe after COM_OF_LOSS_T, as in PX4."""
        if self.mode != Mode.OFFBOARD or self.offb.sp is None:
            return
        nan3 = np.full(3, np.nan)
        self.offb.sp = TrajectorySetpoint(nan3, np.zeros(3), nan3.copy(), self.yaw, math.nan)
        self._publish()

    # ---- events from the server -------------------------------------------------
    def on_released(self, now_s: float) -> None:
        """The server has placed the vehicle at the carrier with its release attitude."""
        self.docked = False
        self.release_requested = False
        self.landed = False
        self._ground_since_t = None
        self.loop_reset = True
        if self.knobs.throw_enabled:
            if not self.armed:  # SITL convenience: the carrier arms a vehicle nobody armed
                self.event(SEV_INFO, "Armed by the carrier at release")
            self.armed = True
            self._armed_t = now_s
            self._airborne_since_arm = True
            self.throwing = True
            self._uprighting = float(self.rot[2, 2]) <= THROW_UPRIGHT_COS
            self.mode = self.behaviour.release_mode
            self._state_changed()
            self.event(SEV_INFO, "Released from carrier: throw launch, stabilising")
        else:
            self.event(SEV_WARNING, "Released from carrier disarmed (COM_THROW_EN=0)")
        self._publish()

    def tick(self, now_s: float) -> None:
        """Periodic logic: landing detection, take-off ramp, failsafes, auto-disarm, throw."""
        dt = max(0.0, now_s - self._last_tick_t)
        self._last_tick_t = self._now_s = now_s
        if self.heartbeat.slot(now_s):
            self.changed = True
        if self.docked:
            return
        self._detect_landing(now_s)
        k = self.knobs
        if self.armed:
            if self._airborne_since_arm:
                t_land = k.disarm_land_s
                if self.landed and t_land >= 0 and now_s - self._landed_t >= t_land:
                    self._disarm(now_s, "Disarmed by auto disarm after landing")
            else:
                t_pre = k.disarm_preflight_s
                if t_pre > 0 and now_s - self._armed_t >= t_pre:
                    self._disarm(now_s, "Disarmed by auto preflight disarming")
        if self.throwing:
            self._throw_progress(now_s)
        self._offboard_watchdog(now_s)
        if self.mode == Mode.TAKEOFF and self.armed and not self.throwing:
            self._takeoff_progress(now_s, dt)
        if self.behaviour.attitude_thrust_follows_tilt and self.mode == Mode.OFFBOARD \
                and isinstance(self.offb.sp, AttitudeSetpoint) and not self.offb.timed_out:
            self._publish()  # the thrust follows the tilt (angle boost) or a climb rate
        elif self._target_moves_on() or (self.offb.stop_vel is not None and self.offb.timed_out
                                          and self.mode == Mode.OFFBOARD and now_s <= self.offb.stop_vel[2] + dt):
            self._publish()  # the target moves on along the last velocity and acceleration, or brakes to rest
        self._check_geofence(now_s)

    # ---- internals ---------------------------------------------------------------
    def _offboard_watchdog(self, now_s: float) -> None:
        if self.mode == Mode.OFFBOARD and self.offb.sp is not None and not self.offboard_live(now_s):
            if not self.offb.timed_out:
                self.behaviour.offboard_lost(self, now_s)

    def _target_moves_on(self) -> bool:
        """In the offboard mode, a target that moves on along its velocity and acceleration
        (ArduPilot GUIDED) and has not timed out."""
        return self.mode == Mode.OFFBOARD and self.offb.moves_on(self.knobs.loss)

    # ---- primitives the autopilot behaviours act through ---------------------------
    def event(self, severity: int, text: str) -> None:
        """A STATUSTEXT to the vehicle's ground stations (sent by the server)."""
        self.events.append((severity, text))

    def set_mode(self, mode: Mode, now_s: float) -> None:
        """Switch mode now (announced; the hold point is captured where the vehicle will stop)."""
        self._set_mode(mode, now_s)

    def failsafe_hold(self, now_s: float, text: str) -> None:
        """Offboard loss: Hold for ever, in failsafe (CRITICAL state) until the user changes mode."""
        self.failsafe_mode(Mode.HOLD, now_s, text)

    def failsafe_mode(self, mode: Mode, now_s: float, text: str, descend_drifting: bool = False) -> None:
        """Offboard loss: switch to mode, in failsafe (CRITICAL state); descend_drifting: it
        descends at the land speed with no horizontal control (PX4 with no RC for its
        Position/Altitude/Manual fallback), until it lands."""
        self._set_mode(mode, now_s)
        self._failsafe_t = now_s
        self._descend_drift = descend_drifting
        self.event(SEV_CRITICAL, text)
        self._publish()

    def failsafe_disarm(self, now_s: float, text: str) -> None:
        """Offboard loss: motors off in the air (PX4 COM_OBL_RC_ACT 6 Terminate, 7 Disarm)."""
        self._failsafe_t = now_s
        self.event(SEV_CRITICAL, text)
        self._disarm(now_s, "Disarmed by failsafe")

    def stop_offboard_in_place(self, text: str) -> None:
        """Offboard loss, staying in the offboard mode: a position target stops where it had
        moved on to (ArduPilot projects it along the last velocity and acceleration until the
        timeout), a velocity target becomes zero velocity (no position held), anything else
        stops where the vehicle comes to rest, until setpoints come again."""
        self.offb.stop(self._now_s, self.knobs.offboard_timeout_s, self.knobs.loss)
        self._capture_hold()
        self.event(SEV_WARNING, text)
        self._publish()

    def clear_offboard_setpoint(self) -> None:
        """Forget the last offboard setpoint (only setpoints sent from now on count)."""
        self.offb.sp = None

    def _arm(self, now_s: float) -> None:
        self.armed = True
        self._state_changed()
        self.loop_reset = True
        self._armed_t = now_s
        self._airborne_since_arm = not self.landed
        self._capture_hold()
        self._tko_sp_z = self.pos[2]
        self.event(SEV_INFO, "Armed by external command")
        self._publish()

    def _disarm(self, now_s: float, why: str) -> None:
        self.armed = False
        self.throwing = False
        self._state_changed()
        self.event(SEV_INFO, why)
        self._publish()

    def _set_mode(self, mode: Mode, now_s: float) -> None:
        self.mode = mode
        self._state_changed()
        self._failsafe_t = None
        self.offb.timed_out = False
        self._descend_drift = False
        if mode not in (Mode.TAKEOFF, Mode.THROW):
            self.throwing = False
        self._capture_hold()
        self._tko_sp_z = self.pos[2]
        self.event(SEV_INFO, f"Mode: {self.dialect.mode_name(self.custom_mode)}")
        self._publish()

    def _capture_hold(self) -> None:
        """Hold where the vehicle comes to rest braking (as PX4 and ArduPilot brake first)."""
        if self.landed:
            self._hold_pos = self.pos.copy()
            self._hold_pos[2] = max(self._hold_pos[2], self.ground_z_m)
        else:
            self._hold_pos = hold_point(self.pos, self.vel)
            self._hold_pos[2] = min(self._hold_pos[2], self.ground_z_m)
        self._hold_yaw = self.yaw

    def _detect_landing(self, now_s: float) -> None:
        if on_ground_and_slow(self.pos[2], float(np.linalg.norm(self.vel)), self.ground_z_m):
            if self._ground_since_t is None:
                self._ground_since_t = now_s
            if not self.landed and now_s - self._ground_since_t >= LAND_DETECT_S:
                self.landed = True
                self._landed_t = now_s
                self.event(SEV_INFO, "Landing detected")
                if self.mode in (Mode.HOLD, Mode.POSITION, Mode.LAND, Mode.TAKEOFF, Mode.OFFBOARD):
                    self._capture_hold()
                    self._publish()
        else:
            self._ground_since_t = None
            if self.landed and self.pos[2] < self.ground_z_m - AIRBORNE_HEIGHT_M:
                self.landed = False
                if self.armed and not self._airborne_since_arm:
                    self._airborne_since_arm = True
                    self.event(SEV_INFO, "Takeoff detected")

    def _takeoff_progress(self, now_s: float, dt: float) -> None:
        speed = self.knobs.takeoff_speed_mps
        target = self._tko_target_z
        self._tko_sp_z = max(target, self._tko_sp_z - speed * dt) if self._tko_sp_z > target \
            else min(target, self._tko_sp_z + speed * dt)
        if abs(self.pos[2] - target) < 0.1 and self._tko_sp_z == target:
            nxt = self.behaviour.after_takeoff_mode
            self._set_mode(nxt, now_s)
            if nxt == Mode.OFFBOARD and self.behaviour.offboard_entry_clears_setpoint:
                self.offb.sp = None
            self._hold_pos[2] = target
            self._publish()
            return
        self._publish()

    def _throw_progress(self, now_s: float) -> None:
        if self.behaviour.throw_uprights_first and self._uprighting != (self.rot[2, 2] <= THROW_UPRIGHT_COS):
            self._uprighting = not self._uprighting
            self._publish()  # uprighted: the position loops take over (or it tipped over again)
        rate = float(np.linalg.norm(self.state.omega_body_radps[self.index]))
        if throw_recovered(float(self.rot[2, 2]), rate, float(np.linalg.norm(self.vel)),
                           *self.knobs.throw_thresholds()):
            self.throwing = False
            self.behaviour.throw_recovered(self, now_s)

    def _check_geofence(self, now_s: float) -> None:
        action, r_max, h_max = self.knobs.geofence()
        d = self.pos - self.home_ned_m
        breach = (r_max > 0 and math.hypot(d[0], d[1]) > r_max) or (h_max > 0 and -d[2] > h_max)
        if breach and not self._fence_breached:
            self._fence_breached = True
            self.event(SEV_CRITICAL, "Geofence violated")
            if self.armed and not self.landed:
                if action == 2 and self.mode != Mode.HOLD:
                    self._set_mode(Mode.HOLD, now_s)
                elif action in (3, 5) and self.mode != Mode.LAND:
                    self._set_mode(Mode.LAND, now_s)
                elif action == 4:
                    self._disarm(now_s, "Geofence: flight termination")
        elif not breach:
            self._fence_breached = False

    def _publish(self) -> None:
        """Rebuild this vehicle's inner-loop setpoint from mode and arming state."""
        sp = self.sp
        for f in sp.__dataclass_fields__:
            getattr(sp, f)[...] = np.nan
        self.rates_only = False
        offb = self.offb
        offboard = self.mode == Mode.OFFBOARD and offb.sp is not None and not offb.timed_out
        if not self.armed:
            sp.att_q_wxyz[0] = rot_to_quat_wxyz(self.rot[None])[0]
            sp.thrust_norm[0] = 0.0
            sp.body_rate_radps[0] = 0.0
        elif self.throwing and self.behaviour.throw_uprights_first and self._uprighting:
            sp.att_q_wxyz[0] = euler_zyx_to_quat_wxyz(0.0, 0.0, self._hold_yaw)  # level, on attitude alone
            sp.thrust_norm[0] = THROW_UPRIGHT_THRUST
            sp.body_rate_radps[0] = 0.0
        elif self.throwing:
            sp.vel_ned_mps[0] = 0.0
            sp.yaw_rad[0] = self._hold_yaw
        elif offboard and isinstance(offb.sp, TrajectorySetpoint):
            o = offb.sp
            sp.pos_ned_m[0] = o.pos_ned_m
            sp.vel_ned_mps[0] = o.vel_ned_mps
            sp.acc_ned_mps2[0] = o.acc_ned_mps2
            if self._target_moves_on():
                sp.pos_ned_m[0], sp.vel_ned_mps[0] = offb.moved_on(o, max(0.0, self._now_s - offb.last_t))
            sp.yaw_rad[0] = o.yaw_rad
            sp.yaw_rate_radps[0] = o.yaw_rate_radps
            if not (math.isfinite(o.yaw_rad) or math.isfinite(o.yaw_rate_radps)):
                sp.yaw_rad[0] = self._hold_yaw
        elif offboard and isinstance(offb.sp, AttitudeSetpoint):
            att = offb.sp
            sp.thrust_norm[0] = self.behaviour.attitude_thrust(self, att)
            sp.body_rate_radps[0] = att.body_rate_radps
            if att.att_q_wxyz is None:
                self.rates_only = True
                self.rate_q_reset = True
                sp.att_q_wxyz[0] = rot_to_quat_wxyz(self.rot[None])[0]
            else:
                sp.att_q_wxyz[0] = att.att_q_wxyz
        elif self.mode == Mode.OFFBOARD and offb.timed_out and offb.stop_pos is not None:
            sp.pos_ned_m[0] = offb.stop_pos  # GUID_TIMEOUT: the target where it stopped, at rest
            sp.yaw_rad[0] = self._hold_yaw
        elif self.mode == Mode.OFFBOARD and offb.timed_out and offb.stop_vel is not None:
            # GUID_TIMEOUT: a velocity target zeroed
            sp.vel_ned_mps[0], sp.acc_ned_mps2[0] = offb.braking(self._now_s, self.knobs.loss)
            sp.yaw_rad[0] = self._hold_yaw
        elif self._descend_drift:
            sp.acc_ned_mps2[0, :2] = 0.0  # no horizontal control: level, drifting
            sp.vel_ned_mps[0, 2] = self.knobs.loss.descent_speed_mps
            sp.yaw_rad[0] = self._hold_yaw
        elif self.mode == Mode.LAND:
            sp.pos_ned_m[0, :2] = self._hold_pos[:2]
            sp.vel_ned_mps[0, 2] = self.knobs.land_speed_mps
            sp.yaw_rad[0] = self._hold_yaw
        elif self.mode == Mode.TAKEOFF:
            sp.pos_ned_m[0] = (self._hold_pos[0], self._hold_pos[1], self._tko_sp_z)
            climbing = self._tko_sp_z != self._tko_target_z
            direction = -1.0 if self._tko_target_z < self._tko_sp_z else 1.0
            sp.vel_ned_mps[0] = (0.0, 0.0, direction * self.knobs.takeoff_speed_mps if climbing else 0.0)
            sp.yaw_rad[0] = self._hold_yaw
        else:  # HOLD, POSITION, THROW (recovered), OFFBOARD without setpoints: hold
            sp.pos_ned_m[0] = self._hold_pos
            sp.yaw_rad[0] = self._hold_yaw
        self.sp_version += 1
