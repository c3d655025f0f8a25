"""SITL logic without sockets: parameter encoding, offboard masks, autopilot, carrier launch."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from companion.link.setpoints import Rejected, decode_attitude_target, decode_position_target
from companion.params import InnerLoopConfig
from sim_bridge.carrier import AttitudeDistribution, CarrierConfig
from sim_bridge.sitl.autopilot import ACCEPTED, TEMPORARILY_REJECTED, Mode
from sim_bridge.sitl.config import SitlConfig, SpawnConfig
from sim_bridge.sitl.params_table import (
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    ParamTable,
    decode_param_value,
    default_specs,
    encode_param_value,
)
from sim_bridge.sitl.server import SitlServer

NAN = math.nan
I3 = np.eye(3)


def test_param_bytewise_encoding_and_table_checks():
    wire = encode_param_value(2, MAV_PARAM_TYPE_INT32)
    assert struct.pack("<f", wire) == struct.pack("<i", 2)
    assert decode_param_value(wire, MAV_PARAM_TYPE_INT32) == 2
    assert encode_param_value(2.5, MAV_PARAM_TYPE_REAL32) == 2.5
    t = ParamTable(default_specs(InnerLoopConfig(), 7))
    assert [s.name for s in t.specs] == sorted(s.name for s in t.specs)
    assert t["MAV_SYS_ID"] == 7
    assert t.set_wire("NOPE", 1.0, MAV_PARAM_TYPE_REAL32) is None
    assert not t.set("MAV_SYS_ID", 3) and t["MAV_SYS_ID"] == 7  # read only
    assert not t.set("MPC_TILTMAX_AIR", 95.0)  # out of range
    t.set_wire("COM_OF_LOSS_T", NAN, MAV_PARAM_TYPE_REAL32)
    assert t["COM_OF_LOSS_T"] == 1.0
    assert t.set("SD_GEO_KX", 2.0) and t.inner_loop(InnerLoopConfig()).geometric.kx_per_s2 == 2.0


@pytest.mark.parametrize("mask, frame, expect", [
    (2552, 1, ("pos",)),               # position (+yaw)
    (2503, 1, ("vel",)),               # velocity
    (2496, 1, ("pos", "vel")),
    (2048, 1, ("pos", "vel", "acc")),  # pos + vel + acc feed-forward
    (3135, 1, ("acc",)),               # acceleration only
    (1479, 8, ("vel",)),               # body-frame velocity + yaw rate
    (1031, 8, ("vel", "acc")),         # body velocity + acceleration + yaw rate
])
def test_position_target_masks_accepted(mask, frame, expect):
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # yaw 90 deg
    sp = decode_position_target(mask, frame, (1, 2, -3), (1, 0, 0), (0.5, 0, 0), 0.3, 0.1, rot)
    assert not isinstance(sp, Rejected)
    assert np.isfinite(sp.pos_ned_m).all() == ("pos" in expect)
    assert np.isfinite(sp.vel_ned_mps).all() == ("vel" in expect)
    assert np.isfinite(sp.acc_ned_mps2).all() == ("acc" in expect)
    if frame == 8:  # body velocity rotated by yaw: forward -> east
        assert sp.vel_ned_mps == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)
    assert math.isnan(sp.yaw_rad) == bool(mask & 1024)
    assert math.isnan(sp.yaw_rate_radps) == bool(mask & 2048)


def test_position_target_per_axis_and_rejections():
    sp = decode_position_target(0b111111100 | 3072, 1, (1, 2, -3), (0, 0, 0), (0, 0, 0), 0, 0, I3)
    assert sp.pos_ned_m[:2] == pytest.approx([1, 2]) and math.isnan(sp.pos_ned_m[2])  # z ignored only
    assert isinstance(decode_position_target(3135 | 512, 1, (0,) * 3, (0,) * 3, (1, 0, 0), 0, 0, I3),
                      Rejected)  # FORCE with acceleration
    assert isinstance(decode_position_target(2552, 7, (1, 2, 3), (0,) * 3, (0,) * 3, 0, 0, I3), Rejected)  # frame 7
    assert isinstance(decode_position_target(0xFFF, 1, (1, 2, 3), (0,) * 3, (0,) * 3, 0, 0, I3), Rejected)
    assert isinstance(decode_position_target(2552, 8, (1, 2, 3), (0,) * 3, (0,) * 3, 0, 0, I3), Rejected)  # body pos
    sp = decode_position_target(2552, 1, (NAN, 2, 3), (0,) * 3, (0,) * 3, 0, 0, I3)  # NaN value = not commanded
    assert math.isnan(sp.pos_ned_m[0]) and sp.pos_ned_m[1] == 2


def test_attitude_target_masks():
    sp = decode_attitude_target(7, (2.0, 0, 0, 0), (0, 0, 0), 0.6)
    assert sp.att_q_wxyz == pytest.approx([1, 0, 0, 0]) and sp.thrust_norm == 0.6
    sp = decode_attitude_target(128, (1, 0, 0, 0), (0.1, 0.2, NAN), 0.5)
    assert sp.att_q_wxyz is None and sp.body_rate_radps[:2] == pytest.approx([0.1, 0.2])
    assert math.isnan(sp.body_rate_radps[2])  # kept for the hygiene check, which rejects it
    from companion.link.limits import SetpointLimits, check_attitude
    assert isinstance(check_attitude(sp, SetpointLimits()), Rejected)
    assert decode_attitude_target(64 | 7, (1, 0, 0, 0), (0, 0, 0), 0.9).thrust_norm == 0.0  # PX4: thrust 0
    assert isinstance(decode_attitude_target(128 | 7, (1, 0, 0, 0), (0, 0, 0), 0.5), Rejected)
    assert isinstance(decode_attitude_target(7, (NAN, 0, 0, 0), (0, 0, 0), 0.5), Rejected)


def _server(**kw) -> SitlServer:
    return SitlServer(SitlConfig(**kw))


def _run_until(server: SitlServer, pred, max_s: float) -> bool:
    for _ in range(int(max_s / server.tick_s)):
        server.step_once()
        if pred():
            return True
    return False


def test_takeoff_hold_offboard_loss_land_disarm_without_sockets():
    s = _server(vehicles=2, params={"COM_OF_LOSS_T": 0.3, "SD_OBL_LAND_T": 0.4, "COM_DISARM_LAND": 0.3})
    ap = s.autopilots[1]
    assert ap.command_set_mode(1, 6, 0, s.sim_s) == TEMPORARILY_REJECTED  # no setpoint stream
    assert ap.command_arm(1, NAN, s.sim_s) == ACCEPTED
    assert ap.command_takeoff(NAN, s.home_alt_amsl_m, s.sim_s) == ACCEPTED
    s.after_change(1)
    assert _run_until(s, lambda: ap.mode == Mode.HOLD, 6)
    assert s.state.pos_ned_m[1, 2] == pytest.approx(-2.5, abs=0.15)  # MIS_TAKEOFF_ALT
    assert s.autopilots[0].landed and not s.autopilots[0].armed  # the other vehicle untouched
    sp = decode_position_target(3135, 1, (0,) * 3, (0,) * 3, (0, 0, 0), 0, 0, I3)
    ap.on_offboard_setpoint(sp, s.sim_s)
    assert ap.command_set_mode(1, 6, 0, s.sim_s) == ACCEPTED
    s.after_change(1)
    t_last = s.sim_s
    assert _run_until(s, lambda: ap.mode != Mode.OFFBOARD, 2)
    assert ap.mode == Mode.HOLD and s.sim_s - t_last <= 0.3 + 0.05
    assert _run_until(s, lambda: ap.mode == Mode.LAND, 2) and s.sim_s - t_last <= 0.3 + 0.4 + 0.1
    assert _run_until(s, lambda: not ap.armed, 15)
    assert ap.landed and s.state.pos_ned_m[1, 2] == pytest.approx(0.0, abs=1e-6)


def test_table_gains_drive_the_physics():
    s = _server(vehicles=2)
    s.params[0].set("SD_GEO_KX", 1.0)
    s.after_change(0)
    assert len(s._physics) == 2 and s._group[0] != s._group[1]
    assert s._physics[s._group_keys[s._group[0]]].inner.geometric.kx_per_s2 == 1.0


def test_carrier_release_schedule_and_throw_recovery():
    carrier = CarrierConfig(start_ned_m=(0.0, 0.0, -30.0), vel_ned_mps=(3.0, 0.0, 0.0), first_release_s=0.5,
                            release_interval_s=0.5, attitude=AttitudeDistribution(
                                kind="euler", roll_max_deg=60, pitch_max_deg=40, yaw_max_deg=180,
                                body_rate_std_radps=1.0))
    s = _server(vehicles=3, seed=3, spawn=SpawnConfig(launch="carrier"), carrier=carrier)
    aps = s.autopilots
    assert all(ap.docked for ap in aps) and aps[0].command_arm(1, NAN, 0.0) == ACCEPTED  # armed for the throw
    assert aps[0].system_status == 8 and not aps[0].needs_physics  # motors locked until the release
    aps[2].params.set("COM_THROW_EN", 0)
    assert aps[2].command_arm(1, NAN, 0.0) == TEMPORARILY_REJECTED  # no throw launch: no arming on the carrier
    aps[2].params.set("COM_THROW_EN", 1)
    assert _run_until(s, lambda: not aps[0].docked, 1.0)
    assert aps[1].docked and aps[0].armed and aps[0].mode == Mode.TAKEOFF
    assert s.state.pos_ned_m[1] == pytest.approx([3.0 * s.sim_s, 0, -30.0])  # docked ones ride the carrier
    assert _run_until(s, lambda: all(ap.mode == Mode.HOLD and not ap.docked for ap in aps), 10)
    tilt = np.degrees(np.arccos(s.state.rot_body_to_ned[:, 2, 2]))
    assert (tilt < 10).all() and (np.linalg.norm(s.state.vel_ned_mps, axis=1) < 0.5).all()
    assert (s.state.pos_ned_m[:, 2] < -20).all()  # recovered in the air


def test_carrier_release_on_command():
    s = _server(vehicles=2, spawn=SpawnConfig(launch="carrier"), carrier=CarrierConfig(release="command"))
    assert not _run_until(s, lambda: not s.autopilots[1].docked, 0.5)
    assert s.autopilots[1].command_release() == ACCEPTED
    s.step_once()
    assert not s.autopilots[1].docked and s.autopilots[0].docked


def test_preflight_auto_disarm_and_geofence_action():
    s = _server(vehicles=1, params={"COM_DISARM_PRFLT": 0.5, "GF_ACTION": 5})
    ap = s.autopilots[0]
    assert ap.command_arm(1, NAN, s.sim_s) == ACCEPTED
    assert _run_until(s, lambda: not ap.armed, 1.0) and s.sim_s == pytest.approx(0.5, abs=0.05)
    ap.command_arm(1, NAN, s.sim_s)
    ap.command_takeoff(NAN, s.home_alt_amsl_m, s.sim_s)
    s.after_change(0)
    assert _run_until(s, lambda: ap.mode == Mode.HOLD, 6)
    s.params[0].set("GF_MAX_VER_DIST", 2.0)  # now 2.5 m up: outside the fence
    assert _run_until(s, lambda: ap.mode == Mode.LAND, 0.2)
    assert ap.command_arm(0, NAN, s.sim_s) == TEMPORARILY_REJECTED  # no disarm in the air without force
    assert ap.command_arm(0, 21196, s.sim_s) == ACCEPTED


def test_body_rate_setpoint_is_integrated_into_an_attitude_target():
    s = _server(vehicles=1)
    ap = s.autopilots[0]
    ap.command_arm(1, NAN, s.sim_s)
    ap.command_takeoff(NAN, s.home_alt_amsl_m, s.sim_s)
    s.after_change(0)
    assert _run_until(s, lambda: ap.mode == Mode.HOLD, 6)
    yaw0 = math.atan2(s.state.rot_body_to_ned[0, 1, 0], s.state.rot_body_to_ned[0, 0, 0])
    sp = decode_attitude_target(128 | 1 | 2, (1, 0, 0, 0), (0.0, 0.0, 0.5), 0.512)  # yaw rate only
    ap.on_offboard_setpoint(sp, s.sim_s)
    assert ap.command_set_mode(1, 6, 0, s.sim_s) == ACCEPTED
    s.after_change(0)
    t0 = s.sim_s
    _run_until(s, lambda: s.sim_s - t0 >= 0.8, 1.0)
    yaw1 = math.atan2(s.state.rot_body_to_ned[0, 1, 0], s.state.rot_body_to_ned[0, 0, 0])
    assert ap.mode == Mode.OFFBOARD
    assert yaw1 - yaw0 == pytest.approx(0.4, abs=0.1)
    assert np.degrees(np.arccos(s.state.rot_body_to_ned[0, 2, 2])) < 3
