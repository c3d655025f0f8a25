"""PX4 in the SITL: its parameters (names and defaults of PX4 v1.14-v1.16), position and
velocity loop gains, Offboard rules, offboard-loss failsafe (COM_OBL_RC_ACT, as the px4
dialect's LossBehaviour says), throw launch and failure injection.

Sources: PX4 commander (offboardCheck.cpp, commander_params.c), mc_pos_control
(multicopter_position_control_gain_params.yaml, PositionControl.cpp,
MulticopterPositionControl.cpp), mavlink_receiver.cpp; ../shared/notes/mavlink-facts.md.
"""
from __future__ import annotations

import math

from companion.link.dialects import Mode
from companion.link.enums import MavSeverity, MavState, MavType
from companion.link.limits import SetpointLimits
from companion.params import InnerLoopConfig
from sim_bridge.sitl.autopilots.base import AutopilotBehaviour, Machine
from sim_bridge.sitl.params_table import ParamSpec, ParamTable, Role, int_param, real_param
from sim_bridge.world.autopilot_model import DISARM_LAND_S
from sim_bridge.world.position_loop import LOOP_PX4, PositionLoopGains


class Px4Behaviour(AutopilotBehaviour):
    """PX4: Offboard needs a live setpoint stream; the last setpoint is flown for
    COM_OF_LOSS_T, then COM_OBL_RC_ACT (0-2 without RC: descend with no horizontal control,
    4 Land, 5 Hold for ever); a throw launch flies in Takeoff and ends in Hold."""

    name = "px4"
    offboard_needs_stream = True
    armed_docked_state = MavState.MAV_STATE_FLIGHT_TERMINATION  # as PX4 while throw launch holds the motors
    release_mode = Mode.TAKEOFF
    after_takeoff_mode = Mode.HOLD
    supports_failure_injection = True
    heartbeat_on_change = False  # a 1 Hz stream: a new mode shows in the next one (mavlink-facts.md)

    def own_specs(self, inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> list[ParamSpec]:
        f, i, R = real_param, int_param, Role
        return [
            f("MIS_TAKEOFF_ALT", 2.5, 0.0, 1000.0, "take-off altitude above home, m", (R.TAKEOFF_ALT_M,)),
            f("MPC_TKO_SPEED", 1.5, 0.1, 10.0, "take-off climb speed, m/s", (R.TAKEOFF_SPEED_MPS,)),
            f("MPC_LAND_SPEED", 0.7, 0.1, 5.0, "landing descent speed, m/s", (R.DESCENT_SPEED_MPS, R.LAND_SPEED_MPS)),
            f("MPC_TILTMAX_AIR", inner.geometric.tilt_max_deg, 1.0, 89.0, "tilt limit of the position controller, deg",
              (R.TILT_MAX_DEG,)),
            f("MPC_THR_HOVER", hover_thrust, 0.05, 0.95, "normalised collective thrust that hovers", (R.HOVER_THRUST,),
              read_only=True),
            i("MPC_USE_HTE", 1, 0, 1, "1: the position loop flies on the hover-thrust estimator's value (modelled "
              "converged to the airframe's true hover thrust), not MPC_THR_HOVER"),
            f("MPC_THR_MIN", 0.12, 0.0, 1.0, "offboard thrust floor (normalised)"),
            f("MPC_THR_MAX", 1.0, 0.0, 1.0, "offboard thrust ceiling (normalised)"),
            f("MPC_XY_VEL_MAX", 12.0, 0.0, 20.0, "horizontal speed limit of offboard velocity setpoints, m/s"),
            f("MPC_Z_VEL_MAX_UP", 3.0, 0.5, 8.0, "climb speed limit, m/s"),
            f("MPC_Z_VEL_MAX_DN", 1.5, 0.5, 4.0, "descent speed limit, m/s"),
            f("MC_ROLLRATE_MAX", 220.0, 0.0, 1800.0, "roll rate limit, deg/s"),
            f("MC_PITCHRATE_MAX", 220.0, 0.0, 1800.0, "pitch rate limit, deg/s"),
            f("MC_YAWRATE_MAX", 200.0, 0.0, 1800.0, "yaw rate limit, deg/s"),
            f("MPC_XY_P", 0.95, 0.0, 2.0, "horizontal position gain: velocity per position error, 1/s"),
            f("MPC_XY_VEL_P_ACC", 1.8, 1.2, 5.0, "horizontal velocity P: acceleration per velocity error, 1/s"),
            f("MPC_XY_VEL_I_ACC", 0.4, 0.0, 60.0, "horizontal velocity I: acceleration per velocity integral, 1/s^2"),
            f("MPC_XY_VEL_D_ACC", 0.2, 0.1, 2.0, "horizontal velocity D: acceleration per velocity derivative"),
            f("MPC_Z_P", 1.0, 0.1, 1.5, "vertical position gain: velocity per position error, 1/s"),
            f("MPC_Z_VEL_P_ACC", 4.0, 2.0, 15.0, "vertical velocity P: acceleration per velocity error, 1/s"),
            f("MPC_Z_VEL_I_ACC", 2.0, 0.2, 3.0, "vertical velocity I: acceleration per velocity integral, 1/s^2"),
            f("MPC_Z_VEL_D_ACC", 0.0, 0.0, 2.0, "vertical velocity D: acceleration per velocity derivative"),
            f("MPC_VELD_LP", 5.0, 0.0, 10.0, "low-pass of the velocity derivative (the D terms), Hz"),
            # Read by the agents for their ghost of a silent vehicle (its stop); the SITL's Hold
            # and Land fly a step target through the loops above, not PX4's jerk-limited one.
            f("MPC_ACC_HOR", 3.0, 2.0, 15.0, "horizontal acceleration limit of auto modes, m/s^2"),
            f("MPC_ACC_UP_MAX", 4.0, 2.0, 15.0, "upward acceleration limit of auto modes, m/s^2"),
            f("MPC_ACC_DOWN_MAX", 3.0, 2.0, 15.0, "downward acceleration limit of auto modes, m/s^2"),
            f("MPC_JERK_AUTO", 4.0, 1.0, 80.0, "jerk limit of auto modes, m/s^3"),
            f("MPC_THR_XY_MARG", 0.3, 0.0, 0.5, "horizontal thrust kept while vertical thrust has priority"),
            f("COM_OF_LOSS_T", 1.0, 0.0, 60.0, "offboard setpoint timeout: the last setpoint is flown this long, s",
              (R.OFFBOARD_TIMEOUT_S,)),
            i("COM_OBL_RC_ACT", 0, 0, 7, "offboard loss action: 0 Position, 1 Altitude, 2 Manual (no RC: descend "
              "without horizontal control), 3 Return (= Land here), 4 Land, 5 Hold, 6 Terminate, 7 Disarm"),
            f("COM_DISARM_PRFLT", 10.0, -1.0, 20.0, "disarm if armed and not taken off within, s (<=0 off)",
              (R.DISARM_PREFLIGHT_S,)),
            f("COM_DISARM_LAND", DISARM_LAND_S, -1.0, 20.0, "disarm after landing detected, s (<0 off)",
              (R.DISARM_LAND_S,)),
            i("GF_ACTION", 2, 0, 5, "geofence action: 0 none, 1 warn, 2 hold, 3 return(=land), 4 terminate, 5 land"),
            f("GF_MAX_HOR_DIST", 0.0, 0.0, 1e6, "geofence horizontal radius from home, m (0 off)"),
            f("GF_MAX_VER_DIST", 0.0, 0.0, 1e6, "geofence maximum height above home, m (0 off)"),
            i("COM_THROW_EN", 1, 0, 1, "stabilise after carrier release (throw launch)"),
            i("SYS_FAILURE_EN", 0, 0, 1, "accept MAV_CMD_INJECT_FAILURE (motor off only in the SITL)"),
            i("MAV_SYS_ID", sysid, 1, 250, "MAVLink system id (read only in the SITL)", read_only=True),
            i("MAV_COMP_ID", 1, 1, 250, "MAVLink component id (read only in the SITL)", read_only=True),
            i("MAV_TYPE", MavType.MAV_TYPE_QUADROTOR, 0, 30, "vehicle type (quadrotor)", read_only=True),
            i("SYS_AUTOSTART", 4001, 0, 9999999, "airframe (generic quadrotor x)", read_only=True),
        ]

    def throw_enabled(self, table: ParamTable) -> bool:
        return table["COM_THROW_EN"] >= 1

    def position_loop(self, table: ParamTable, hover_thrust_true: float) -> PositionLoopGains:
        """mc_pos_control's PositionControl with the table's MPC_* gains and Offboard limits
        (MPC_XY_VEL_MAX, MPC_Z_VEL_MAX_UP/DN, MPC_TILTMAX_AIR, MPC_THR_MIN/MAX), thrust scaled by
        MPC_THR_HOVER, or with MPC_USE_HTE 1 (PX4's default) by the hover-thrust estimator's
        value, modelled as converged to the airframe's true hover thrust (a real PX4 SIH read
        0.49 against MPC_THR_HOVER 0.5: ../shared notes, issue 18); the D terms act on the
        velocity derivative, low-passed at MPC_VELD_LP.

        Why the estimator matters: with the loop on a wrong hover thrust, the vertical
        integrator holds the difference, and PositionControl's horizontal anti-windup, which
        compares the demanded with the produced horizontal acceleration (a0 (1 - a2 / g) with a
        vertical demand a2), then winds the horizontal integrator against a sustained
        feed-forward: a vehicle in a long 3 m/s^2 demand drifted off for good in our model."""
        t = table
        thr_min = max(t["MPC_THR_MIN"], 1e-3)  # (PositionControl::setThrustLimits keeps a thrust direction)
        return PositionLoopGains(
            style=LOOP_PX4, pos_p_xy_per_s=t["MPC_XY_P"], pos_p_z_per_s=t["MPC_Z_P"],
            vel_p_xy_per_s=t["MPC_XY_VEL_P_ACC"], vel_i_xy_per_s2=t["MPC_XY_VEL_I_ACC"], vel_d_xy=t["MPC_XY_VEL_D_ACC"],
            vel_p_z_per_s=t["MPC_Z_VEL_P_ACC"], vel_i_z_per_s2=t["MPC_Z_VEL_I_ACC"], vel_d_z=t["MPC_Z_VEL_D_ACC"],
            vel_max_xy_mps=t["MPC_XY_VEL_MAX"], vel_max_up_mps=t["MPC_Z_VEL_MAX_UP"],
            vel_max_dn_mps=t["MPC_Z_VEL_MAX_DN"], tilt_max_rad=math.radians(min(t.role(Role.TILT_MAX_DEG), 89.0)),
            thr_min=thr_min, thr_max=max(thr_min, t["MPC_THR_MAX"]), thr_xy_margin=t["MPC_THR_XY_MARG"],
            hover_param=hover_thrust_true if t["MPC_USE_HTE"] >= 1 else t.role(Role.HOVER_THRUST),
            hover_true=hover_thrust_true, vel_d_lp_hz=t["MPC_VELD_LP"])

    def failure_injection_enabled(self, table: ParamTable) -> bool:
        return table.get("SYS_FAILURE_EN", 0.0) == 1.0

    def limits(self, table: ParamTable) -> SetpointLimits:
        t, d = table, math.radians
        return SetpointLimits(
            xy_vel_max_mps=t["MPC_XY_VEL_MAX"], z_vel_max_up_mps=t["MPC_Z_VEL_MAX_UP"],
            z_vel_max_dn_mps=t["MPC_Z_VEL_MAX_DN"], tilt_max_rad=d(t.role(Role.TILT_MAX_DEG)), thr_min=t["MPC_THR_MIN"],
            thr_max=max(t["MPC_THR_MIN"], t["MPC_THR_MAX"]), roll_rate_max_radps=d(t["MC_ROLLRATE_MAX"]),
            pitch_rate_max_radps=d(t["MC_PITCHRATE_MAX"]), yaw_rate_max_radps=d(t["MC_YAWRATE_MAX"]))

    def geofence(self, table: ParamTable) -> tuple[int, float, float]:
        return int(table["GF_ACTION"]), table["GF_MAX_HOR_DIST"], table["GF_MAX_VER_DIST"]

    def takeoff_alt_rel_m(self, ap: Machine, param7: float, home_alt_amsl_m: float) -> float | None:
        """param7 is an AMSL altitude (NaN: MIS_TAKEOFF_ALT above home), in any mode."""
        return param7 - home_alt_amsl_m if math.isfinite(param7) else ap.knobs.takeoff_alt_m

    def throw_recovered(self, ap: Machine, now_s: float) -> None:
        ap.set_mode(Mode.HOLD, now_s)
        ap.event(MavSeverity.MAV_SEVERITY_INFO, "Throw launch: stable, Hold (ready for offboard)")
