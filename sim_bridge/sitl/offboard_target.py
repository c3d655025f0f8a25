"""A simulated autopilot's offboard target: the companion's last setpoint (world frame), when
it came, and what is left of it once the companion has gone silent.

PX4 flies the last setpoint for COM_OF_LOSS_T; ArduPilot's GUIDED moves its target on along
the last velocity and acceleration until GUID_TIMEOUT, then stops it there (a position
target) or brakes a velocity target to rest with no position held (companion.link.dialects:
LossBehaviour, CarryOn). The state machine (sim_bridge.sitl.autopilot) decides when; this
holds the target and does the kinematics. Pure logic: times are simulation seconds passed
in by the caller.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.link.dialects.base import CarryOn, LossBehaviour
from companion.link.setpoints import AttitudeSetpoint, TrajectorySetpoint
from sim_bridge.world.autopilot_model import braked_velocity


@dataclass
class OffboardTarget:
    """The last offboard setpoint and its fate.

    Attributes:
        sp: the last setpoint (a trajectory in the world frame, or an attitude); None: none
            since the mode was entered (ArduPilot) or ever.
        last_t: when it came, s. timed_out: the companion has been silent past the timeout.
        stop_pos: where a timed-out position target stopped (ArduPilot: moved on), world NED.
        stop_vel: a timed-out velocity target (no position): (its velocity, when it timed
            out, when it is zero); brought to zero at the loss behaviour's braking limits,
            no position held (ArduPilot GUIDED zeroes it through its kinematic shaping).
    """

    sp: TrajectorySetpoint | AttitudeSetpoint | None = None
    last_t: float = -math.inf
    timed_out: bool = False
    stop_pos: np.ndarray | None = None
    stop_vel: tuple[np.ndarray, float, float] | None = None

    def set(self, sp: TrajectorySetpoint | AttitudeSetpoint, now_s: float) -> None:
        """A new setpoint (world frame) at now_s: the target is live again."""
        self.sp = sp
        self.last_t = now_s
        self.timed_out = False

    def live(self, now_s: float, timeout_s: float) -> bool:
        return self.sp is not None and now_s - self.last_t <= timeout_s

    def moves_on(self, loss: LossBehaviour) -> bool:
        """A trajectory target with a velocity or an acceleration that the autopilot carries on
        along them (ArduPilot GUIDED), not timed out (the caller checks the mode)."""
        o = self.sp
        return (isinstance(o, TrajectorySetpoint) and not self.timed_out
                and loss.carry_on == CarryOn.VELOCITY_ACCELERATION
                and bool(np.isfinite(o.vel_ned_mps).any() or np.isfinite(o.acc_ned_mps2).any()))

    @staticmethod
    def moved_on(o: TrajectorySetpoint, tau_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) of target o moved on for tau_s along its velocity and
        acceleration (NaN axes stay NaN)."""
        acc = np.where(np.isfinite(o.acc_ned_mps2), o.acc_ned_mps2, 0.0)
        vel0 = np.where(np.isfinite(o.vel_ned_mps), o.vel_ned_mps, 0.0)
        return o.pos_ned_m + vel0 * tau_s + 0.5 * acc * tau_s * tau_s, o.vel_ned_mps + acc * tau_s

    def braking(self, now_s: float, loss: LossBehaviour) -> tuple[np.ndarray, np.ndarray]:
        """(velocity, acceleration) of a zeroed velocity target at now_s: brought from its
        value at the timeout to zero at the loss behaviour's braking limits (horizontal,
        vertical)."""
        assert self.stop_vel is not None  # (only called while one is braking)
        v0, t0, _ = self.stop_vel
        return braked_velocity(v0, max(0.0, now_s - t0), loss.brake_hor_mps2, loss.brake_ver_mps2)

    def stop(self, now_s: float, timeout_s: float, loss: LossBehaviour) -> None:
        """The companion has been silent for timeout_s: a position target stops where it had
        moved on to (or where it was, if the autopilot does not carry it on), a velocity
        target is braked to zero, anything else leaves nothing (the caller holds)."""
        o = self.sp
        self.timed_out = True
        self.stop_pos, self.stop_vel = None, None
        if isinstance(o, TrajectorySetpoint) and np.isfinite(o.pos_ned_m).all():
            if loss.carry_on == CarryOn.VELOCITY_ACCELERATION:
                self.stop_pos = self.moved_on(o, timeout_s)[0]
            else:
                self.stop_pos = o.pos_ned_m.copy()
        elif isinstance(o, TrajectorySetpoint) and np.isfinite(o.vel_ned_mps).all():
            v0 = self.moved_on(o, timeout_s)[1]
            t_brake = max(float(np.linalg.norm(v0[:2])) / loss.brake_hor_mps2,
                          abs(float(v0[2])) / loss.brake_ver_mps2)
            self.stop_vel = (v0, now_s, now_s + t_brake)
