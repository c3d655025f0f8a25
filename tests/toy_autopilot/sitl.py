"""How the toy autopilot behaves in the SITL (an AutopilotBehaviour): its own parameter
names, a P-on-position, P-on-velocity loop (PX4's structure, its own two gains), and on loss
of setpoints it holds where it stops."""
from __future__ import annotations

import math

from companion.link.dialects import Mode
from companion.link.enums import MavSeverity
from companion.params import InnerLoopConfig
from sim_bridge.sitl.autopilots.base import AutopilotBehaviour
from sim_bridge.sitl.params_table import ParamSpec, ParamTable, Role, real_param
from sim_bridge.world.position_loop import PositionLoopGains


class ToyBehaviour(AutopilotBehaviour):
    """Offboard needs no stream, a take-off ends in Hold, a lost stream ends in Hold."""

    name = "toy"

    def own_specs(self, inner: InnerLoopConfig, sysid: int, hover_thrust: float) -> list[ParamSpec]:
        f, R = real_param, Role
        return [
            f("TOY_TILT", inner.geometric.tilt_max_deg, 1.0, 89.0, "tilt limit, deg", (R.TILT_MAX_DEG,)),
            f("TOY_TKO_ALT", 2.0, 0.0, 100.0, "take-off height, m", (R.TAKEOFF_ALT_M,)),
            f("TOY_TKO_SPD", 1.0, 0.1, 5.0, "climb speed, m/s", (R.TAKEOFF_SPEED_MPS,)),
            f("TOY_DN_SPD", 0.8, 0.1, 5.0, "descent and landing speed, m/s", (R.DESCENT_SPEED_MPS, R.LAND_SPEED_MPS)),
            f("TOY_DISARM", 5.0, -1.0, 60.0, "auto-disarm after landing or idle arming, s",
              (R.DISARM_PREFLIGHT_S, R.DISARM_LAND_S)),
            f("TOY_HOVER", hover_thrust, 0.05, 0.95, "hover thrust", (R.HOVER_THRUST,), read_only=True),
            f("TOY_SP_TIMEOUT", 0.5, 0.1, 10.0, "setpoint timeout, s", (R.OFFBOARD_TIMEOUT_S,)),
            f("TOY_POS_P", 1.0, 0.1, 5.0, "position gain, 1/s"),
            f("TOY_VEL_P", 3.0, 0.5, 10.0, "velocity gain, 1/s"),
        ]

    def position_loop(self, table: ParamTable, hover_thrust_true: float) -> PositionLoopGains:
        p, v = table["TOY_POS_P"], table["TOY_VEL_P"]
        return PositionLoopGains(pos_p_xy_per_s=p, pos_p_z_per_s=p, vel_p_xy_per_s=v, vel_i_xy_per_s2=0.0, vel_d_xy=0.0,
                                 vel_p_z_per_s=v, vel_i_z_per_s2=0.0, tilt_max_rad=math.radians(table.role(Role.TILT_MAX_DEG)),
                                 hover_param=table.role(Role.HOVER_THRUST), hover_true=hover_thrust_true)

    def offboard_lost(self, ap, now_s: float) -> None:
        ap.failsafe_hold(now_s, "toy: setpoints lost, holding")

    def throw_recovered(self, ap, now_s: float) -> None:
        ap.set_mode(Mode.HOLD, now_s)
        ap.event(MavSeverity.MAV_SEVERITY_INFO, "toy: recovered")
