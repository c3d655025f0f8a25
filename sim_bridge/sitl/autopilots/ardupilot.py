"""ArduCopter in the SITL: its parameters (names, ArduPilot units: cm, cm/s, cdeg), its
position controller's gains (PSC_*), GUIDED rules, GUID_TIMEOUT (the target moves on along
the last velocity and acceleration, then stops and holds in GUIDED: the ardupilot dialect's
LossBehaviour), THROW mode and THROW_NEXTMODE, and SET_ATTITUDE_TARGET's thrust (a climb
rate unless GUID_OPTIONS bit 3).

Sources: ArduCopter mode_guided.cpp, mode_throw.cpp, GCS_MAVLink_Copter.cpp, Parameters.cpp;
AC_AttitudeControl/AC_PosControl.cpp (Copter defaults), AC_PID/AC_PID_2D.cpp;
../shared/notes/mavlink-facts.md (a real ArduCopter 4.6 SITL flown by the agent).
"""
from __future__ import annotations

import math

from companion.link.dialects import Mode
from companion.link.dialects.ardupilot import ANGLE_BOOST_COS_MIN, BRAKE, GUID_OPTIONS_THRUST, GUIDED, LAND, LOITER, THROW
from companion.link.enums import MavSeverity
from companion.link.setpoints import AttitudeSetpoint
from companion.params import GRAVITY_MPS2, InnerLoopConfig
from sim_bridge.sitl.autopilots.base import AutopilotBehaviour, Machine
from sim_bridge.sitl.params_table import ParamSpec, ParamTable, Role, int_param, real_param
from sim_bridge.world.position_loop import LOOP_ARDUPILOT, PositionLoopGains

NEXT_MODE = {GUIDED: Mode.OFFBOARD, LOITER: Mode.POSITION, BRAKE: Mode.HOLD, LAND: Mode.LAND, THROW: Mode.THROW}
"""THROW_NEXTMODE values the SITL flies, as the Mode they mean (others: stay in THROW)."""


class ArduPilotBehaviour(AutopilotBehaviour):
    """ArduCopter: setpoints count only in GUIDED, which starts holding; until GUID_TIMEOUT the
    target moves on along the last velocity and acceleration, then the vehicle stops and
    stays in GUIDED; a carrier release is a THROW, then THROW_NEXTMODE."""

    name = "ardupilot"
    offboard_entry_clears_setpoint = True
    setpoints_only_in_offboard = True
    origin_movable = False  # ArduPilot ignores SET_GPS_GLOBAL_ORIGIN once it has an origin
    release_mode = Mode.THROW
    after_takeoff_mode = Mode.OFFBOARD  # ArduCopter finishes its GUIDED take-off holding in GUIDED
    attitude_thrust_follows_tilt = True
    throw_uprights_first = True  # mode_throw.cpp: Throw_Uprighting before any position control
    says_unknown_interval_id = True

    def own_specs(self, inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> list[ParamSpec]:
        f, i, R = real_param, int_param, Role
        return [
            f("PILOT_TKOFF_ALT", 250.0, 0.0, 100000.0, "take-off altitude when NAV_TAKEOFF gives none, cm",
              (R.TAKEOFF_ALT_M,), divisor=100.0),
            f("WPNAV_SPEED_UP", 250.0, 10.0, 1000.0, "climb speed, cm/s", (R.TAKEOFF_SPEED_MPS,), divisor=100.0),
            f("WPNAV_SPEED_DN", 150.0, 10.0, 500.0, "descent speed, cm/s", (R.DESCENT_SPEED_MPS,), divisor=100.0),
            f("LAND_SPEED", 50.0, 30.0, 200.0, "final landing speed, cm/s", (R.LAND_SPEED_MPS,), divisor=100.0),
            f("ANGLE_MAX", inner.geometric.tilt_max_deg * 100.0, 1000.0, 8000.0, "tilt limit, centidegrees",
              (R.TILT_MAX_DEG,), divisor=100.0),
            f("MOT_THST_HOVER", hover_thrust, 0.05, 0.95, "normalised collective thrust that hovers", (R.HOVER_THRUST,),
              read_only=True),
            f("PSC_POSXY_P", 1.0, 0.5, 2.0, "horizontal position P: velocity per position error, 1/s"),
            f("PSC_VELXY_P", 2.0, 0.1, 6.0, "horizontal velocity P: acceleration per velocity error, 1/s"),
            f("PSC_VELXY_I", 1.0, 0.0, 1.0, "horizontal velocity I: acceleration per velocity integral, 1/s^2"),
            f("PSC_VELXY_D", 0.5, 0.0, 1.0, "horizontal velocity D: acceleration per velocity-error derivative"),
            f("PSC_VELXY_IMAX", 1000.0, 0.0, 4500.0, "horizontal velocity integrator limit, cm/s^2"),
            f("PSC_VELXY_FLTE", 5.0, 0.0, 100.0, "horizontal velocity error filter, Hz"),
            f("PSC_VELXY_FLTD", 5.0, 0.0, 100.0, "horizontal velocity D-term filter, Hz"),
            f("PSC_POSZ_P", 1.0, 1.0, 3.0, "vertical position P: climb rate per altitude error, 1/s"),
            f("PSC_VELZ_P", 5.0, 1.0, 8.0, "vertical velocity P: acceleration per climb-rate error, 1/s"),
            f("PSC_VELZ_I", 0.0, 0.0, 1.0, "vertical velocity I (Copter default 0: the ACCZ loop integrates), 1/s^2"),
            f("PSC_VELZ_IMAX", 1000.0, 0.0, 10000.0, "vertical velocity integrator limit, cm/s^2"),
            f("PSC_VELZ_FLTE", 5.0, 0.0, 100.0, "vertical velocity error filter, Hz"),
            f("PSC_ACCZ_P", 0.5, 0.2, 1.5, "vertical acceleration P: throttle (1/1000) per cm/s^2 of error"),
            f("PSC_ACCZ_I", 1.0, 0.0, 3.0, "vertical acceleration I: throttle (1/1000) per cm/s^2 s"),
            f("PSC_ACCZ_IMAX", 800.0, 0.0, 1000.0, "vertical acceleration integrator limit, throttle 1/1000 (d%)"),
            f("PSC_ACCZ_FLTE", 20.0, 1.0, 100.0, "vertical acceleration error filter, Hz"),
            f("WPNAV_SPEED", 1000.0, 20.0, 2000.0, "horizontal speed limit of position corrections in GUIDED, cm/s"),
            f("WPNAV_ACCEL", 250.0, 50.0, 500.0, "horizontal acceleration of the position controller's square "
              "root, cm/s^2"),
            f("WPNAV_ACCEL_Z", 100.0, 50.0, 500.0, "vertical acceleration of the position controller's square "
              "root, cm/s^2"),
            # Read by the agents for their ghost of a silent vehicle (its stop); the SITL's
            # GUIDED stop flies the loops above without ArduPilot's jerk-limited shaping.
            f("PSC_JERK_XY", 5.0, 1.0, 20.0, "horizontal jerk limit of the position controller, m/s^3"),
            f("PSC_JERK_Z", 5.0, 5.0, 50.0, "vertical jerk limit of the position controller, m/s^3"),
            f("GUID_TIMEOUT", 3.0, 0.1, 5.0, "GUIDED: setpoint timeout, s (then stop / level)",
              (R.OFFBOARD_TIMEOUT_S,)),
            i("GUID_OPTIONS", 0, 0, 65535, "GUIDED options; bit 3 (8): SET_ATTITUDE_TARGET thrust is thrust"),
            f("DISARM_DELAY", 10.0, 0.0, 127.0, "disarm this long after landing or arming without take-off, s",
              (R.DISARM_PREFLIGHT_S, R.DISARM_LAND_S)),
            i("THROW_NEXTMODE", THROW, 3, 18, "mode after a successful throw (4 GUIDED, 5 LOITER, 17 BRAKE, 18 stay)"),
            i("THROW_TYPE", 1, 0, 1, "throw type: 0 upward, 1 drop (a carrier release is a drop)"),
            i("SYSID_THISMAV", sysid, 1, 255, "MAVLink system id (read only in the SITL)", read_only=True),
            i("FRAME_CLASS", 1, 0, 20, "frame class (quad)", read_only=True),
        ]

    def may_arm_docked(self, table: ParamTable, mode: Mode) -> bool:
        return self.throw_enabled(table) and mode == Mode.THROW  # arm in THROW, then drop

    def thrust_is_thrust(self, table: ParamTable) -> bool:
        return (int(table["GUID_OPTIONS"]) & GUID_OPTIONS_THRUST) != 0

    def takeoff_alt_rel_m(self, ap: Machine, param7: float, home_alt_amsl_m: float) -> float | None:
        """Armed in GUIDED only; param7 is the height above home (0/NaN: PILOT_TKOFF_ALT)."""
        if ap.mode != Mode.OFFBOARD or not ap.armed:
            ap.event(MavSeverity.MAV_SEVERITY_CRITICAL, "Takeoff: arm in GUIDED first")
            return None
        return super().takeoff_alt_rel_m(ap, param7, home_alt_amsl_m)

    def position_loop(self, table: ParamTable, hover_thrust_true: float) -> PositionLoopGains:
        """AC_PosControl with the table's PSC_* gains (Copter defaults; cm and the accel loop's
        1/1000 throttle converted to SI), GUIDED's limits (WPNAV_SPEED, WPNAV_SPEED_UP/DN,
        WPNAV_ACCEL, WPNAV_ACCEL_Z, ANGLE_MAX) and MOT_THST_HOVER."""
        t = table
        return PositionLoopGains(
            style=LOOP_ARDUPILOT, pos_p_xy_per_s=t["PSC_POSXY_P"], pos_p_z_per_s=t["PSC_POSZ_P"],
            vel_p_xy_per_s=t["PSC_VELXY_P"], vel_i_xy_per_s2=t["PSC_VELXY_I"], vel_d_xy=t["PSC_VELXY_D"],
            vel_p_z_per_s=t["PSC_VELZ_P"], vel_i_z_per_s2=t["PSC_VELZ_I"], vel_d_z=0.0,
            vel_max_xy_mps=t["WPNAV_SPEED"] / 100.0, vel_max_up_mps=t.role(Role.TAKEOFF_SPEED_MPS),
            vel_max_dn_mps=t.role(Role.DESCENT_SPEED_MPS), tilt_max_rad=math.radians(min(t.role(Role.TILT_MAX_DEG), 89.0)),
            thr_min=0.0, thr_max=1.0, thr_xy_margin=0.0, hover_param=t.role(Role.HOVER_THRUST),
            hover_true=hover_thrust_true, vel_imax_xy_mps2=t["PSC_VELXY_IMAX"] / 100.0,
            vel_imax_z_mps2=t["PSC_VELZ_IMAX"] / 100.0, acc_z_p_per_mps2=t["PSC_ACCZ_P"] * 0.1,
            acc_z_i_per_mps2s=t["PSC_ACCZ_I"] * 0.1, acc_z_imax=t["PSC_ACCZ_IMAX"] / 1000.0,
            vel_err_lp_hz=t["PSC_VELXY_FLTE"], vel_z_err_lp_hz=t["PSC_VELZ_FLTE"], vel_d_lp_hz=t["PSC_VELXY_FLTD"],
            acc_err_lp_hz=t["PSC_ACCZ_FLTE"], pos_acc_xy_mps2=t["WPNAV_ACCEL"] / 100.0,
            pos_acc_z_mps2=t["WPNAV_ACCEL_Z"] / 100.0)

    def throw_recovered(self, ap: Machine, now_s: float) -> None:
        ap.event(MavSeverity.MAV_SEVERITY_INFO, "height achieved - controlling position")
        nxt = NEXT_MODE.get(int(ap.params["THROW_NEXTMODE"]), Mode.THROW)
        if nxt == Mode.OFFBOARD:
            ap.clear_offboard_setpoint()
        ap.set_mode(nxt, now_s)

    def attitude_thrust(self, ap: Machine, o: AttitudeSetpoint) -> float:
        cos_tilt = float(ap.rot[2, 2])
        k = ap.knobs
        if k.thrust_is_thrust:
            return self.dialect.collective_from_thrust_field(o.thrust_norm, cos_tilt)
        # Without GUID_OPTIONS bit 3 the field is a climb rate, 0.5 = hold height.
        t = o.thrust_norm
        climb = (t - 0.5) * 2.0 * (k.takeoff_speed_mps if t >= 0.5 else k.descent_speed_mps)
        kv = ap.params["PSC_VELZ_P"]  # (the climb-rate loop's P; its accel loop and integrators are not modelled here)
        a_up = kv * (climb + float(ap.vel[2]))  # vel[2] is down
        return min(1.0, max(0.0, k.hover_thrust * (1.0 + a_up / GRAVITY_MPS2) / max(cos_tilt, ANGLE_BOOST_COS_MIN)))
