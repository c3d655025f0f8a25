"""SITL logic without sockets: parameter encoding, offboard masks, autopilot, carrier launch."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from companion.config import replace
from companion.link.enums import MsgId
from companion.link.setpoints import Rejected, decode_attitude_target, decode_position_target
from companion.params import InnerLoopConfig
from sim_bridge.sitl.autopilot import ACCEPTED, TEMPORARILY_REJECTED, Mode
from sim_bridge.sitl.autopilots import autopilot_named
from sim_bridge.sitl.config import default_scenario, sitl_config
from sim_bridge.sitl.heartbeat import HEARTBEAT_PHASE_STEP_S
from sim_bridge.sitl.params_table import (
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    ParamTable,
    decode_param_value,
    encode_param_value,
)
from sim_bridge.sitl.server import SitlServer
from sim_bridge.world.carrier import AttitudeDistribution, CarrierConfig
from sim_bridge.world.position_loop import G_POS_P_XY

NAN = math.nan
I3 = np.eye(3)


def test_param_bytewise_encoding_and_table_checks():
    wire = encode_param_value(2, MAV_PARAM_TYPE_INT32)
    assert struct.pack("<f", wire) == struct.pack("<i", 2)
    assert decode_param_value(wire, MAV_PARAM_TYPE_INT32) == 2
    assert encode_param_value(2.5, MAV_PARAM_TYPE_REAL32) == 2.5
    t = ParamTable(autopilot_named("px4").param_specs(InnerLoopConfig(), 7, 0.5))
    assert [s.name for s in t.specs] == sorted(s.name for s in t.specs)
    assert t["MAV_SYS_ID"] == 7
    assert t.set_wire("NOPE", 1.0, MAV_PARAM_TYPE_REAL32) is None
    assert not t.set("MAV_SYS_ID", 3) and t["MAV_SYS_ID"] == 7  # read only
    assert not t.set("MPC_TILTMAX_AIR", 95.0)  # out of range
    t.set_wire("COM_OF_LOSS_T", NAN, MAV_PARAM_TYPE_REAL32)
    assert t["COM_OF_LOSS_T"] == 1.0
    assert t.set("SD_GEO_KR", 150.0) and t.inner_loop(InnerLoopConfig()).geometric.kR_per_s2 == 150.0
    assert t.index_of("SD_GEO_KX") is None and t.index_of("SD_OBL_LAND_T") is None  # (its own loops; Hold never lands)
    assert t["COM_OBL_RC_ACT"] == 0 and t["MPC_XY_VEL_I_ACC"] == 0.4  # PX4's defaults


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


def _server(vehicles: int = 1, seed: int = 0, launch: str = "ground", carrier: CarrierConfig | None = None,
            **kw) -> SitlServer:
    sc = default_scenario() if carrier is None else replace(default_scenario(), carrier=carrier)
    return SitlServer(sitl_config(vehicles, seed=seed, launch=launch, scenario=sc, **kw))


def _run_until(server: SitlServer, pred, max_s: float) -> bool:
    for _ in range(int(max_s / server.tick_s)):
        server.step_once()
        if pred():
            return True
    return False


def _airborne_in_offboard(dialect: str = "px4", **params):
    """Vehicle 1 of 2 taken off to 2.5 m (PX4: Takeoff then Hold; ArduPilot: in GUIDED) and
    flying offboard a velocity of 1 m/s north at 2.5 m; returns (server, autopilot)."""
    s = _server(vehicles=2, dialect=dialect, params=params)
    ap = s.autopilots[1]
    guided = dialect == "ardupilot"
    if guided:
        assert ap.command_set_mode(1, 4, 0, s.sim_s) == ACCEPTED
    else:
        assert ap.command_set_mode(1, 6, 0, s.sim_s) == TEMPORARILY_REJECTED  # no setpoint stream
    assert ap.command_arm(1, NAN, s.sim_s) == ACCEPTED
    assert ap.command_takeoff(NAN if not guided else 2.5, s.home_alt_amsl_m, s.sim_s) == ACCEPTED
    s.after_change(1)
    assert _run_until(s, lambda: not ap.landed and ap.mode != Mode.TAKEOFF, 8)
    assert _run_until(s, lambda: abs(s.state.pos_ned_m[1, 2] + 2.5) < 0.05 and np.abs(s.state.vel_ned_mps[1]).max() < 0.05, 10)
    assert s.autopilots[0].landed and not s.autopilots[0].armed  # the other vehicle untouched
    start = s.state.pos_ned_m[1] - ap.origin_ned_m  # (setpoints are in the vehicle's own EKF frame)

    def stream(seconds: float) -> None:  # a position + velocity target moving north at 1 m/s, at 50 Hz
        for _ in range(int(round(seconds / 0.02))):
            x = start[0] + 1.0 * (s.sim_s - t0)
            ap.on_offboard_setpoint(decode_position_target(2496, 1, (x, start[1], start[2]), (1, 0, 0), (0, 0, 0), 0, 0,
                                                           I3), s.sim_s)
            s.after_change(1)
            _run_until(s, lambda: False, 0.02)
    t0 = s.sim_s
    stream(0.02)
    if not guided:
        assert ap.command_set_mode(1, 6, 0, s.sim_s) == ACCEPTED
    s.after_change(1)
    stream(6.0)
    assert ap.mode == Mode.OFFBOARD and s.state.vel_ned_mps[1, 0] == pytest.approx(1.0, abs=0.1)
    return s, ap


def _last_setpoint_s(ap) -> float:
    return ap.offb.last_t  # (when the autopilot took the last setpoint)


def _texts(ap) -> list[str]:
    """Every STATUSTEXT the autopilot queues from now on (the server drains ap.events)."""
    out: list[str] = []
    event = ap.event
    ap.event = lambda severity, text: (out.append(text), event(severity, text))[1]
    return out


def test_px4_offboard_loss_flies_the_last_setpoint_then_holds_for_ever_with_com_obl_rc_act_5():
    s, ap = _airborne_in_offboard(COM_OF_LOSS_T=0.5, COM_OBL_RC_ACT=5)
    t_last, x_last = _last_setpoint_s(ap), s.state.pos_ned_m[1, 0]
    texts = _texts(ap)
    # the last setpoint keeps acting, as it was: its position stays where it was (PX4 does not move it)
    assert _run_until(s, lambda: ap.mode != Mode.OFFBOARD, 2)
    assert ap.mode == Mode.HOLD and 0.5 - 1e-9 < s.sim_s - t_last <= 0.5 + 0.02 + 1e-9
    assert ap.system_status == 5  # CRITICAL: in failsafe
    assert "Failsafe: offboard signal lost, Hold" in texts
    # Hold: brake and stay, for ever (PX4's Hold never lands by itself)
    hold = ap.sp.pos_ned_m[0].copy()
    assert x_last < hold[0] < x_last + 1.0
    assert not _run_until(s, lambda: ap.mode != Mode.HOLD or ap.landed, 30)
    assert ap.armed and np.abs(s.state.pos_ned_m[1] - hold).max() < 0.02 and np.abs(s.state.vel_ned_mps[1]).max() < 0.01


def test_px4_offboard_loss_lands_with_com_obl_rc_act_4():
    s, ap = _airborne_in_offboard(COM_OF_LOSS_T=0.3, COM_OBL_RC_ACT=4, COM_DISARM_LAND=0.3)
    t_last = _last_setpoint_s(ap)
    assert _run_until(s, lambda: ap.mode != Mode.OFFBOARD, 2)
    assert ap.mode == Mode.LAND and s.sim_s - t_last <= 0.3 + 0.02 + 1e-9 and ap.system_status == 5
    x_land = ap.sp.pos_ned_m[0, 0]
    assert _run_until(s, lambda: s.state.pos_ned_m[1, 2] > -1.0, 5)
    assert s.state.vel_ned_mps[1, 2] == pytest.approx(0.7, abs=0.05)  # descending at MPC_LAND_SPEED
    assert _run_until(s, lambda: not ap.armed, 15)
    assert ap.landed and s.state.pos_ned_m[1, 2] == pytest.approx(0.0, abs=1e-6)
    # where it stopped, holding position (PX4's position loop has not quite closed the braking
    # estimate's gap when it touches down)
    assert s.state.pos_ned_m[1, 0] == pytest.approx(x_land, abs=0.25)


def test_px4_offboard_loss_with_the_stock_com_obl_rc_act_descends_drifting_without_rc():
    """COM_OBL_RC_ACT 0 (Position, the default) with no RC: PX4 reports Position and descends at
    MPC_LAND_SPEED with no horizontal control: the vehicle keeps drifting north at the speed
    it had (no wind, no drag here), lands and disarms."""
    s, ap = _airborne_in_offboard(COM_OF_LOSS_T=0.5, COM_DISARM_LAND=0.5)
    t_last, texts = _last_setpoint_s(ap), _texts(ap)
    assert _run_until(s, lambda: ap.mode != Mode.OFFBOARD, 2)
    assert ap.mode == Mode.POSITION and ap.system_status == 5 and 0.5 - 1e-9 < s.sim_s - t_last <= 0.52 + 1e-9
    assert "Failsafe: offboard signal lost, Position: no RC, descending" in texts
    x0, vx0 = s.state.pos_ned_m[1, 0], s.state.vel_ned_mps[1, 0]
    assert 0.5 < vx0 < 1.0  # (for COM_OF_LOSS_T the last setpoint's position stayed put: it began to brake)
    assert _run_until(s, lambda: s.state.pos_ned_m[1, 2] > -1.0, 5)
    assert s.state.vel_ned_mps[1, 2] == pytest.approx(0.7, abs=0.05)  # MPC_LAND_SPEED (the step overshoots a little)
    assert s.state.vel_ned_mps[1, 0] == pytest.approx(vx0, abs=0.1)  # still drifting
    assert _run_until(s, lambda: not ap.armed, 15)
    assert ap.landed and ap.mode == Mode.POSITION
    assert s.state.pos_ned_m[1, 0] - x0 > 2.0  # it drifted metres while descending


def test_ardupilot_guid_timeout_moves_the_target_on_then_holds_in_guided_for_ever():
    """A position + velocity target (1 m/s north) with an acceleration (0.5 m/s^2 north): after
    the last setpoint ArduPilot moves the target on along both until GUID_TIMEOUT, then the
    target stops there and the vehicle holds it in GUIDED, armed, for ever."""
    s, ap = _airborne_in_offboard("ardupilot", GUID_TIMEOUT=1.0)
    local = s.state.pos_ned_m[1] - ap.origin_ned_m
    ap.on_offboard_setpoint(decode_position_target(2048, 1, (local[0], local[1], -2.5), (1, 0, 0), (0.5, 0, 0), 0, 0, I3),
                            s.sim_s)
    s.after_change(1)
    t_last, p0, texts = s.sim_s, ap.sp.pos_ned_m[0, 0], _texts(ap)
    for tau in (0.2, 0.5, 0.8):  # the published target moves on: p0 + v tau + a tau^2 / 2, v0 + a tau
        _run_until(s, lambda: s.sim_s >= t_last + tau - 1e-9, 2)
        elapsed = ap._last_tick_t - t_last
        assert ap.mode == Mode.OFFBOARD
        assert ap.sp.pos_ned_m[0, 0] == pytest.approx(p0 + elapsed + 0.25 * elapsed ** 2, abs=1e-9)
        assert ap.sp.vel_ned_mps[0, 0] == pytest.approx(1.0 + 0.5 * elapsed, abs=1e-9)
    assert _run_until(s, lambda: ap.sp_version and np.isnan(ap.sp.vel_ned_mps[0, 0]), 1)
    assert 1.0 - 1e-9 < s.sim_s - t_last <= 1.02 + 1e-9
    x_stop = p0 + 1.0 + 0.25
    assert ap.sp.pos_ned_m[0, 0] == pytest.approx(x_stop, abs=1e-9)  # the target stopped where it had moved on to
    assert ap.mode == Mode.OFFBOARD and ap.armed and "GUIDED: setpoint timeout, stopping" in texts
    assert not _run_until(s, lambda: ap.mode != Mode.OFFBOARD or ap.landed or not ap.armed, 30)  # for ever
    assert s.state.pos_ned_m[1, 0] == pytest.approx(x_stop, abs=0.02) and np.abs(s.state.vel_ned_mps[1]).max() < 0.01


def test_table_gains_drive_the_physics():
    s = _server(vehicles=2)
    s.params[0].set("SD_GEO_KR", 150.0)
    s.after_change(0)
    assert len(s.fleet.physics_groups) == 2 and s.fleet.group[0] != s.fleet.group[1]
    assert s.fleet.physics_groups[s.fleet.group_keys[s.fleet.group[0]]].inner.geometric.kR_per_s2 == 150.0
    # the position loops' gains are per vehicle, from its own table (no physics group of their own)
    s.params[1].set("MPC_XY_P", 0.5)
    s.after_change(1)
    assert s.fleet.loop.gains[1, G_POS_P_XY] == 0.5 and s.fleet.loop.gains[0, G_POS_P_XY] == 0.95
    assert len(s.fleet.physics_groups) == 2


def test_carrier_release_schedule_and_throw_recovery():
    carrier = CarrierConfig(start_ned_m=(0.0, 0.0, -30.0), vel_ned_mps=(3.0, 0.0, 0.0), first_release_s=0.5,
                            release_interval_s=0.5, attitude=AttitudeDistribution(
                                kind="euler", roll_max_deg=60, pitch_max_deg=40, yaw_max_deg=180,
                                body_rate_std_radps=1.0))
    s = _server(vehicles=3, seed=3, launch="carrier", carrier=carrier)
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
    s = _server(vehicles=2, launch="carrier", carrier=CarrierConfig(release="command"))
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


@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
def test_a_mode_change_shows_in_px4s_next_1hz_heartbeat_and_in_ardupilots_at_once(dialect):
    """PX4 acknowledges a mode change before its next 1 Hz HEARTBEAT shows it (up to a second
    later: ../shared/notes/mavlink-facts.md); ArduCopter's set_mode sends a HEARTBEAT at once.
    The SITL's HEARTBEATs, sent at once or on the wall clock, say what each would say."""
    s = _server(vehicles=3, dialect=dialect)
    k = 2
    ap, d = s.autopilots[k], s.autopilots[k].dialect
    sent: list[tuple[float, int, int]] = []  # (sim time, custom_mode, base_mode) of each HEARTBEAT vehicle k sent
    broadcast = s.broadcast

    def record(j, msg):
        if j == k and msg[0] == MsgId.HEARTBEAT:
            sent.append((s.sim_s, msg[1][3], msg[1][2]))  # (declaration order: type, autopilot, base_mode, custom_mode, ...)
        broadcast(j, msg)

    s.broadcast = record
    assert _run_until(s, lambda: ap.has_fix, 30)  # (a position mode needs the EKF's fix)
    hold, position = d.custom_mode(Mode.HOLD), d.custom_mode(Mode.POSITION)
    assert s.telemetry.heartbeat(k)[1][3] == hold
    sent.clear()
    t_ack = s.sim_s
    assert ap.command_set_mode(*d.set_mode_params(Mode.POSITION), t_ack) == ACCEPTED and ap.mode == Mode.POSITION
    s.after_change(k)  # (as the server does right after it sends the ACK)
    if dialect == "ardupilot":
        assert sent == [(t_ack, position, sent[0][2])]  # one HEARTBEAT, right after the ACK, shows it
        return
    assert sent == [] and s.telemetry.heartbeat(k)[1][3] == hold  # nothing at once; a HEARTBEAT now says Hold
    assert _run_until(s, lambda: sent, 1.0 + 2 * s.tick_s)
    (t_shown, mode, _), = sent
    assert mode == position and 0.0 < t_shown - t_ack <= 1.0 + s.tick_s
    ap_tick_s = s.fleet.ap_every * s.tick_s  # (the autopilot logic's period: a slot is seen on its next tick)
    phase = (t_shown - k * HEARTBEAT_PHASE_STEP_S) % 1.0  # its slots: 1 s apart, at this vehicle's own phase
    assert phase < ap_tick_s + 1e-9
    sent.clear()
    assert ap.command_arm(1, NAN, s.sim_s) == ACCEPTED
    s.after_change(k)
    assert sent == []
    assert _run_until(s, lambda: sent, 1.0 + 2 * s.tick_s)
    assert abs(sent[0][0] - t_shown - 1.0) < 1e-9 and sent[0][2] & 128  # the next slot shows it armed
