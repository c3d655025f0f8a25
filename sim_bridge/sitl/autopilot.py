"""Per-vehicle PX4-like flight state machine: pure logic, no sockets, no pymavlink.

One Autopilot per simulated vehicle. It reads the vehicle's row of the shared
FleetState, decides modes, arming, failsafes, landing and throw recovery, and
publishes the inner-loop setpoint of its vehicle in `sp` (a one-row FleetSetpoint;
`sp_version` increments on every change). Times are simulation seconds passed in
by the caller (injected clock). Human-readable events queue up in `events` as
(MAV_SEVERITY, text) for STATUSTEXT.
"""
from __future__ import annotations

import math
from enum import IntEnum

import numpy as np

from companion.state import FleetSetpoint, FleetState
from companion.frames import rot_to_quat_wxyz
from sim_bridge.sitl.offboard import AttitudeSetpoint, TrajectorySetpoint
from sim_bridge.sitl.params_table import ParamTable

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_SEVERITY
SEV_CRITICAL, SEV_WARNING, SEV_NOTICE, SEV_INFO = 2, 4, 5, 6
FORCE_MAGIC = 21196

ON_GROUND_TOL_M = 0.02
AIRBORNE_HEIGHT_M = 0.15
LAND_DETECT_S = 0.2
LAND_SPEED_MAX_MPS = 0.3
HOLD_BRAKE_MPS2 = 3.0
HOLD_BRAKE_MAX_M = 10.0


class Mode(IntEnum):
    """PX4 custom_mode = main << 16 | sub << 24."""

    MANUAL = 1 << 16
    POSCTL = 3 << 16
    OFFBOARD = 6 << 16
    TAKEOFF = (4 << 16) | (2 << 24)
    HOLD = (4 << 16) | (3 << 24)
    LAND = (4 << 16) | (6 << 24)


MODE_BY_MAIN_SUB = {(3, 0): Mode.POSCTL, (6, 0): Mode.OFFBOARD, (4, 2): Mode.TAKEOFF,
                    (4, 3): Mode.HOLD, (4, 6): Mode.LAND}
MODE_NAMES = {Mode.MANUAL: "Manual", Mode.POSCTL: "Position", Mode.OFFBOARD: "Offboard",
              Mode.TAKEOFF: "Takeoff", Mode.HOLD: "Hold", Mode.LAND: "Land"}


class LandedState(IntEnum):
    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class Autopilot:
    def __init__(self, index: int, sysid: int, params: ParamTable, state: FleetState,
                 ground_z_m: float, home_ned_m: np.ndarray, docked: bool = False, now_s: float = 0.0):
        self.index = index
        self.sysid = sysid
        self.params = params
        self.state = state
        self.ground_z_m = ground_z_m
        self.home_ned_m = np.asarray(home_ned_m, dtype=float)
        self.armed = False
        self.mode = Mode.HOLD
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
        """Set on any mode or arming change; the server then sends a HEARTBEAT at once."""
        self._offb: TrajectorySetpoint | AttitudeSetpoint | None = None
        self._offb_last_t = -math.inf
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

    # ---- reported state ------------------------------------------------------
    @property
    def custom_mode(self) -> int:
        return int(self.mode)

    @property
    def base_mode(self) -> int:
        flags = 1 | 16  # CUSTOM_MODE_ENABLED | STABILIZE_ENABLED
        if self.mode in (Mode.TAKEOFF, Mode.HOLD, Mode.LAND, Mode.OFFBOARD):
            flags |= 4 | 8  # AUTO | GUIDED
        elif self.mode == Mode.POSCTL:
            flags |= 64  # MANUAL_INPUT
        return flags | (128 if self.armed else 0)

    @property
    def system_status(self) -> int:
        if self._failsafe_t is not None:
            return 5  # MAV_STATE_CRITICAL
        return 4 if self.armed else 3  # ACTIVE / STANDBY

    @property
    def landed_state(self) -> LandedState:
        if self.landed:
            return LandedState.ON_GROUND
        if self.mode == Mode.TAKEOFF and self.armed:
            return LandedState.TAKEOFF
        if self.mode == Mode.LAND:
            return LandedState.LANDING
        return LandedState.IN_AIR

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
        return self._offb is not None and now_s - self._offb_last_t <= self.params["COM_OF_LOSS_T"]

    def prearm_failure(self, now_s: float) -> str | None:
        if self.docked:
            return "docked on carrier"
        if self._fence_breached:
            return "geofence breached"
        if self.mode == Mode.OFFBOARD and not self.offboard_live(now_s):
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
            if why is None and not self.landed and not force:
                why = "not landed"
            if why is not None and not force:
                self._event(SEV_CRITICAL, f"Arming denied: {why}")
                return TEMPORARILY_REJECTED
            self._arm(now_s)
            return ACCEPTED
        if not self.armed:
            return ACCEPTED
        if not self.landed and not force:
            self._event(SEV_CRITICAL, "Disarming denied: not landed")
            return TEMPORARILY_REJECTED
        self._disarm(now_s, "Disarmed by external command")
        return ACCEPTED

    def command_takeoff(self, alt_amsl_m: float, home_alt_amsl_m: float, now_s: float) -> int:
        if self.docked:
            return TEMPORARILY_REJECTED
        if math.isfinite(alt_amsl_m):
            alt_rel = alt_amsl_m - home_alt_amsl_m
        else:
            alt_rel = self.params["MIS_TAKEOFF_ALT"]
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
        if not (math.isfinite(base) and math.isfinite(main)):
            return DENIED
        if not int(base) & 1:
            return DENIED
        main_i = int(main)
        sub_i = int(sub) if math.isfinite(sub) and main_i == 4 else 0
        mode = MODE_BY_MAIN_SUB.get((main_i, sub_i))
        if mode is None:
            return DENIED
        if self.docked:
            return TEMPORARILY_REJECTED
        if mode == self.mode:
            self._failsafe_t = None
            return ACCEPTED
        if mode == Mode.OFFBOARD and not self.offboard_live(now_s):
            self._event(SEV_CRITICAL, "Switching to Offboard is currently not available")
            return TEMPORARILY_REJECTED
        if mode == Mode.TAKEOFF:
            self._tko_target_z = self.home_ned_m[2] - self.params["MIS_TAKEOFF_ALT"]
        self._set_mode(mode, now_s)
        return ACCEPTED

    def command_release(self) -> int:
        if not self.docked:
            return DENIED
        self.release_requested = True
        return ACCEPTED

    # ---- offboard setpoints -----------------------------------------------------
    def on_offboard_setpoint(self, sp: TrajectorySetpoint | AttitudeSetpoint, now_s: float) -> None:
        self._offb = sp
        self._offb_last_t = now_s
        if self.mode == Mode.OFFBOARD:
            self._publish()

    # ---- events from the server -------------------------------------------------
    def on_released(self, now_s: float) -> None:
        """The server has placed the vehicle at the carrier with its release attitude."""
        self.docked = False
        self.release_requested = False
        self.landed = False
        self._ground_since_t = None
        if self.params["COM_THROW_EN"] >= 1:
            self.armed = True
            self._armed_t = now_s
            self._airborne_since_arm = True
            self.throwing = True
            self.mode = Mode.TAKEOFF
            self.changed = True
            self._event(SEV_INFO, "Released from carrier: throw launch, stabilising")
        else:
            self._event(SEV_WARNING, "Released from carrier disarmed (COM_THROW_EN=0)")
        self._publish()

    def tick(self, now_s: float) -> None:
        """Periodic logic: landing detection, take-off ramp, failsafes, auto-disarm, throw."""
        dt = max(0.0, now_s - self._last_tick_t)
        self._last_tick_t = now_s
        if self.docked:
            return
        self._detect_landing(now_s)
        p = self.params
        if self.armed:
            if self._airborne_since_arm:
                t_land = p["COM_DISARM_LAND"]
                if self.landed and t_land >= 0 and now_s - self._landed_t >= t_land:
                    self._disarm(now_s, "Disarmed by auto disarm after landing")
            else:
                t_pre = p["COM_DISARM_PRFLT"]
                if t_pre > 0 and now_s - self._armed_t >= t_pre:
                    self._disarm(now_s, "Disarmed by auto preflight disarming")
        if self.throwing:
            self._throw_progress(now_s)
        if self.mode == Mode.OFFBOARD and not self.offboard_live(now_s):
            self._set_mode(Mode.HOLD, now_s)
            self._failsafe_t = now_s
            self._event(SEV_CRITICAL, "Failsafe: offboard signal lost, Hold")
        elif self._failsafe_t is not None and self.mode == Mode.HOLD:
            t_land = p["SD_OBL_LAND_T"]
            if t_land >= 0 and now_s - self._failsafe_t >= t_land and not self.landed:
                self._set_mode(Mode.LAND, now_s)
                self._failsafe_t = now_s
                self._event(SEV_CRITICAL, "Failsafe: offboard still lost, Land")
        if self.mode == Mode.TAKEOFF and self.armed and not self.throwing:
            self._takeoff_progress(now_s, dt)
        self._check_geofence(now_s)

    # ---- internals ---------------------------------------------------------------
    def _event(self, severity: int, text: str) -> None:
        self.events.append((severity, text))

    def _arm(self, now_s: float) -> None:
        self.armed = True
        self.changed = True
        self._armed_t = now_s
        self._airborne_since_arm = not self.landed
        self._capture_hold()
        self._tko_sp_z = self.pos[2]
        self._event(SEV_INFO, "Armed by external command")
        self._publish()

    def _disarm(self, now_s: float, why: str) -> None:
        self.armed = False
        self.throwing = False
        self.changed = True
        self._event(SEV_INFO, why)
        self._publish()

    def _set_mode(self, mode: Mode, now_s: float) -> None:
        self.mode = mode
        self.changed = True
        self._failsafe_t = None
        if mode != Mode.TAKEOFF:
            self.throwing = False
        self._capture_hold()
        self._tko_sp_z = self.pos[2]
        self._event(SEV_INFO, f"Mode: {MODE_NAMES[mode]}")
        self._publish()

    def _capture_hold(self) -> None:
        """Hold where the vehicle comes to rest braking at HOLD_BRAKE_MPS2 (as PX4 brakes first)."""
        self._hold_pos = self.pos.copy()
        if self.landed:
            self._hold_pos[2] = max(self._hold_pos[2], self.ground_z_m)
        else:
            v = self.vel
            speed = float(np.linalg.norm(v))
            if speed > 0.05:
                self._hold_pos += v * min(speed / (2.0 * HOLD_BRAKE_MPS2), HOLD_BRAKE_MAX_M / speed)
            self._hold_pos[2] = min(self._hold_pos[2], self.ground_z_m)
        self._hold_yaw = self.yaw

    def _detect_landing(self, now_s: float) -> None:
        on_ground = self.pos[2] >= self.ground_z_m - ON_GROUND_TOL_M
        slow = float(np.linalg.norm(self.vel)) < LAND_SPEED_MAX_MPS
        if on_ground and slow:
            if self._ground_since_t is None:
                self._ground_since_t = now_s
            if not self.landed and now_s - self._ground_since_t >= LAND_DETECT_S:
                self.landed = True
                self._landed_t = now_s
                self._event(SEV_INFO, "Landing detected")
                if self.mode in (Mode.HOLD, Mode.POSCTL, Mode.LAND, Mode.TAKEOFF):
                    self._capture_hold()
                    self._publish()
        else:
            self._ground_since_t = None
            if self.landed and self.pos[2] < self.ground_z_m - AIRBORNE_HEIGHT_M:
                self.landed = False
                if self.armed and not self._airborne_since_arm:
                    self._airborne_since_arm = True
                    self._event(SEV_INFO, "Takeoff detected")

    def _takeoff_progress(self, now_s: float, dt: float) -> None:
        speed = self.params["MPC_TKO_SPEED"]
        target = self._tko_target_z
        self._tko_sp_z = max(target, self._tko_sp_z - speed * dt) if self._tko_sp_z > target \
            else min(target, self._tko_sp_z + speed * dt)
        if abs(self.pos[2] - target) < 0.1 and self._tko_sp_z == target:
            self._set_mode(Mode.HOLD, now_s)
            self._hold_pos[2] = target
            self._publish()
            return
        self._publish()

    def _throw_progress(self, now_s: float) -> None:
        p = self.params
        tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, float(self.rot[2, 2])))))
        rate = float(np.linalg.norm(self.state.omega_body_radps[self.index]))
        speed = float(np.linalg.norm(self.vel))
        if tilt_deg < p["SD_THR_TILT"] and rate < p["SD_THR_RATE"] and speed < p["SD_THR_SPEED"]:
            self.throwing = False
            self._set_mode(Mode.HOLD, now_s)
            self._event(SEV_INFO, "Throw launch: stable, Hold (ready for offboard)")

    def _check_geofence(self, now_s: float) -> None:
        p = self.params
        r_max, h_max = p["GF_MAX_HOR_DIST"], p["GF_MAX_VER_DIST"]
        d = self.pos - self.home_ned_m
        breach = (r_max > 0 and math.hypot(d[0], d[1]) > r_max) or (h_max > 0 and -d[2] > h_max)
        if breach and not self._fence_breached:
            self._fence_breached = True
            action = int(p["GF_ACTION"])
            self._event(SEV_CRITICAL, "Geofence violated")
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
        if not self.armed:
            sp.att_q_wxyz[0] = rot_to_quat_wxyz(self.rot[None])[0]
            sp.thrust_norm[0] = 0.0
            sp.body_rate_radps[0] = 0.0
        elif self.throwing:
            sp.vel_ned_mps[0] = 0.0
            sp.yaw_rad[0] = self.yaw
        elif self.mode == Mode.OFFBOARD and self._offb is not None:
            o = self._offb
            if isinstance(o, TrajectorySetpoint):
                sp.pos_ned_m[0] = o.pos_ned_m
                sp.vel_ned_mps[0] = o.vel_ned_mps
                sp.acc_ned_mps2[0] = o.acc_ned_mps2
                sp.yaw_rad[0] = o.yaw_rad
                sp.yaw_rate_radps[0] = o.yaw_rate_radps
                if not (math.isfinite(o.yaw_rad) or math.isfinite(o.yaw_rate_radps)):
                    sp.yaw_rad[0] = self._hold_yaw
            else:
                sp.thrust_norm[0] = o.thrust_norm
                sp.body_rate_radps[0] = o.body_rate_radps
                if o.att_q_wxyz is None:
                    self.rates_only = True
                    self.rate_q_reset = True
                    sp.att_q_wxyz[0] = rot_to_quat_wxyz(self.rot[None])[0]
                else:
                    sp.att_q_wxyz[0] = o.att_q_wxyz
        elif self.mode == Mode.LAND:
            sp.pos_ned_m[0, :2] = self._hold_pos[:2]
            sp.vel_ned_mps[0, 2] = self.params["MPC_LAND_SPEED"]
            sp.yaw_rad[0] = self._hold_yaw
        elif self.mode == Mode.TAKEOFF:
            sp.pos_ned_m[0] = (self._hold_pos[0], self._hold_pos[1], self._tko_sp_z)
            climbing = self._tko_sp_z != self._tko_target_z
            direction = -1.0 if self._tko_target_z < self._tko_sp_z else 1.0
            sp.vel_ned_mps[0] = (0.0, 0.0, direction * self.params["MPC_TKO_SPEED"] if climbing else 0.0)
            sp.yaw_rad[0] = self._hold_yaw
        else:  # HOLD, POSCTL, MANUAL (no RC: behaves like Hold)
            sp.pos_ned_m[0] = self._hold_pos
            sp.yaw_rad[0] = self._hold_yaw
        self.sp_version += 1
