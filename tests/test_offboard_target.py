"""The SITL's offboard target (sim_bridge.sitl.offboard_target) in closed form: what is left
of the companion's last setpoint after a loss, per CarryOn (ArduPilot's GUIDED carries the
velocity and acceleration on, PX4 keeps the setpoint as it was)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.link.dialects import Mode
from companion.link.dialects.base import AfterLoss, CarryOn, LossBehaviour
from companion.link.setpoints import TrajectorySetpoint
from sim_bridge.sitl.offboard_target import OffboardTarget

NAN3 = np.full(3, np.nan)
ARDUPILOT = LossBehaviour(3.0, CarryOn.VELOCITY_ACCELERATION, AfterLoss.HOLD, Mode.OFFBOARD,
                          brake_hor_mps2=2.5, brake_ver_mps2=1.0)
PX4 = LossBehaviour(1.0, CarryOn.SETPOINT, AfterLoss.HOLD, Mode.HOLD)


def _traj(pos, vel, acc) -> TrajectorySetpoint:
    return TrajectorySetpoint(np.asarray(pos, float), np.asarray(vel, float), np.asarray(acc, float), 0.0, math.nan)


def test_a_position_target_moves_on_along_velocity_and_acceleration_then_stops_there():
    t = OffboardTarget()
    t.set(_traj([1.0, 2.0, -5.0], [2.0, 0.0, -0.5], [0.4, 0.0, 0.0]), now_s=10.0)
    assert t.live(10.9, 1.0) and not t.live(11.1, 1.0)
    assert t.moves_on(ARDUPILOT) and not t.moves_on(PX4)
    t.stop(13.0, ARDUPILOT.timeout_s, ARDUPILOT)
    # p + v T + a T^2 / 2 with T = 3 s
    assert t.timed_out and t.stop_pos == pytest.approx([1.0 + 6.0 + 1.8, 2.0, -5.0 - 1.5])
    assert t.stop_vel is None and not t.moves_on(ARDUPILOT)
    t.stop(13.0, PX4.timeout_s, PX4)  # PX4 keeps the setpoint where it was
    assert t.stop_pos == pytest.approx([1.0, 2.0, -5.0])
    t.set(_traj([0.0, 0.0, 0.0], NAN3, NAN3), now_s=20.0)  # a new setpoint: live again
    assert not t.timed_out and t.live(20.0, 1.0) and not t.moves_on(ARDUPILOT)  # nothing to carry on


def test_a_velocity_target_is_braked_to_rest_at_the_limits_without_a_position():
    t = OffboardTarget()
    t.set(_traj(NAN3, [3.0, 4.0, 2.0], NAN3), now_s=0.0)
    t.stop(3.0, ARDUPILOT.timeout_s, ARDUPILOT)
    assert t.stop_pos is None and t.stop_vel is not None
    v0, t0, t_zero = t.stop_vel
    assert v0 == pytest.approx([3.0, 4.0, 2.0]) and t0 == 3.0
    assert t_zero == pytest.approx(3.0 + max(5.0 / 2.5, 2.0 / 1.0))  # the slower axis: 2 s either way
    vel, acc = t.braking(4.0, ARDUPILOT)  # 1 s into the braking
    assert vel[:2] == pytest.approx([3.0 - 0.6 * 2.5, 4.0 - 0.8 * 2.5]) and vel[2] == pytest.approx(1.0)
    assert acc == pytest.approx([-1.5, -2.0, -1.0])
    vel, acc = t.braking(5.5, ARDUPILOT)
    assert vel == pytest.approx([0.0, 0.0, 0.0]) and acc == pytest.approx([0.0, 0.0, 0.0])
