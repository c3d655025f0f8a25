"""The SITL's two autopilot dialects, seen by a pymavlink ground station: ArduPilot's
HEARTBEAT, mode numbers, parameters by value and GUIDED rules against PX4's; per-vehicle
EKF origins (GPS_GLOBAL_ORIGIN, LOCAL_POSITION_NED, SET_GPS_GLOBAL_ORIGIN); SYSTEM_TIME
and TIMESYNC on simulation time; GLOBAL_POSITION_INT on WGS-84; command edge cases.

Vehicles spawn on the ground on a 1 km grid, so that every vehicle has its own EKF origin
far from the others and the earth's curvature shows in the geodetic conversions."""
from __future__ import annotations

import math
import os
import random
import struct

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.frames import geodetic_to_ned, ned_to_geodetic  # noqa: E402
from companion.link.dialects import Mode, dialect_named  # noqa: E402
from sim_bridge.sitl.background import BackgroundSitl  # noqa: E402
from sim_bridge.sitl.config import (  # noqa: E402
    SpawnConfig,
    TimeConfig,
    sitl_config,  # noqa: E402
)
from sim_bridge.sitl.params_table import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32, encode_param_value  # noqa: E402
from sim_bridge.sitl.testing import MavClient, local_endpoints  # noqa: E402

EPOCH_UNIX_S = 1767225600.0
GRID_M = 1000.0
N = 3
PX4 = dialect_named("px4")
ARDUPILOT = dialect_named("ardupilot")
GUIDED, LOITER, LAND, BRAKE = 4, 5, 9, 17  # ArduCopter mode numbers
VEL_MASK = 0xDC7  # SET_POSITION_TARGET_LOCAL_NED: velocity only, yaw and yaw rate ignored
ACCEPTED, TEMPORARILY_REJECTED, DENIED, FAILED = 0, 1, 2, 4


def _sitl(dialect: str, speed: float = 1.0, **spawn):
    cfg = sitl_config(N, launch="ground", dialect=dialect, endpoints=local_endpoints(N),
                      spawn=SpawnConfig(grid_spacing_m=GRID_M, **spawn),
                     time=TimeConfig(epoch_unix_s=EPOCH_UNIX_S, speed=speed))
    return BackgroundSitl(cfg)


@pytest.fixture(scope="module")
def px4():
    bg = _sitl("px4")
    server = bg.start()
    yield server
    bg.stop()


@pytest.fixture(scope="module")
def ardupilot():
    bg = _sitl("ardupilot", speed=2.0)
    server = bg.start()
    yield server
    bg.stop()


@pytest.fixture(params=["px4", "ardupilot"])
def sitl(request):
    return request.getfixturevalue(request.param)


def client(server, k: int) -> MavClient:
    c = MavClient(server.cfg.endpoints.vehicle_remote_port(k))
    assert c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == k + 1, 5.0) is not None
    return c


def home(server) -> tuple[float, float, float]:
    h = server.cfg.home
    return h.lat_deg, h.lon_deg, h.alt_amsl_m


def origin_world(server, msg) -> np.ndarray:
    """A GPS_GLOBAL_ORIGIN as a point of the SITL's world frame (NED at home)."""
    return geodetic_to_ned(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3, *home(server))


def request(c: MavClient, sysid: int, msgid: int, msg_type: str, timeout_s: float = 3.0):
    c.drain()
    ack = c.command(sysid, 512, msgid)
    assert ack is not None and ack.result == ACCEPTED, ack
    m = c.wait(msg_type, timeout_s=timeout_s)
    assert m is not None, msg_type
    return m


def read_param(c: MavClient, sysid: int, name: str):
    c.mav.param_request_read_send(sysid, 1, name.encode(), -1)
    m = c.wait("PARAM_VALUE", lambda m: m.param_id == name, 3)
    assert m is not None, name
    return m


def set_param(c: MavClient, sysid: int, name: str, wire: float, ptype: int):
    c.mav.param_set_send(sysid, 1, name.encode(), wire, ptype)
    m = c.wait("PARAM_VALUE", lambda m: m.param_id == name, 3)
    assert m is not None, name
    return m


def mode_heartbeat(c: MavClient, sysid: int, custom_mode: int, timeout_s: float = 3.0):
    return c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == sysid and m.custom_mode == custom_mode, timeout_s)


# ---------------------------------------------------------------------------- identity and modes
@pytest.mark.timeout(60)
def test_ardupilot_heartbeat_and_arducopter_mode_numbers(ardupilot, px4):
    c = client(ardupilot, 2)
    try:
        hb = c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 3, 3)
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (3, 1)
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA == 3 and hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and not hb.base_mode & 128
        assert hb.custom_mode == BRAKE and mavutil.mode_string_v10(hb) == "BRAKE"
        for number, name in ((GUIDED, "GUIDED"), (LOITER, "LOITER"), (LAND, "LAND"), (BRAKE, "BRAKE")):
            assert c.command(3, 176, 1, number, 0).result == ACCEPTED  # ArduPilot: param2 is the mode number
            hb = mode_heartbeat(c, 3, number)
            assert hb is not None and mavutil.mode_string_v10(hb) == name
        assert c.command(3, 176, 1, 1, 0).result == DENIED  # ACRO: not offered without RC
        assert c.command(3, 176, 1, 4, 3).result == ACCEPTED  # a PX4-style (4, 3) is GUIDED here
        assert mode_heartbeat(c, 3, GUIDED) is not None
        assert c.command(3, 176, 1, BRAKE, 0).result == ACCEPTED
        av = request(c, 3, 148, "AUTOPILOT_VERSION")
        assert av.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
        assert not av.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    finally:
        c.close()
    c = client(px4, 2)
    try:
        hb = c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 3, 3)
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.custom_mode == PX4.custom_mode(Mode.HOLD)
        av = request(c, 3, 148, "AUTOPILOT_VERSION")
        assert av.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    finally:
        c.close()


# ---------------------------------------------------------------------------- parameters
@pytest.mark.timeout(60)
def test_integer_parameters_by_value_on_ardupilot_bytewise_on_px4(ardupilot, px4):
    c = client(ardupilot, 1)
    try:
        m = read_param(c, 2, "THROW_NEXTMODE")
        assert m.param_type == MAV_PARAM_TYPE_INT32 and m.param_value == 18.0  # C cast: the number itself
        assert read_param(c, 2, "SYSID_THISMAV").param_value == 2.0
        assert set_param(c, 2, "THROW_NEXTMODE", 4.0, MAV_PARAM_TYPE_INT32).param_value == 4.0
        assert ardupilot.params[1]["THROW_NEXTMODE"] == 4 and ardupilot.params[0]["THROW_NEXTMODE"] == 18
        # PX4's byte-wise float for 5 means about 7e-45 by value: out of range, refused, echo unchanged
        tiny = encode_param_value(5, MAV_PARAM_TYPE_INT32, "bytewise")
        assert set_param(c, 2, "THROW_NEXTMODE", tiny, MAV_PARAM_TYPE_INT32).param_value == 4.0
        assert set_param(c, 2, "THROW_NEXTMODE", 18.0, MAV_PARAM_TYPE_INT32).param_value == 18.0
        assert read_param(c, 2, "GUID_TIMEOUT").param_type == MAV_PARAM_TYPE_REAL32
    finally:
        c.close()
    c = client(px4, 1)
    try:
        m = read_param(c, 2, "GF_ACTION")
        assert m.param_type == MAV_PARAM_TYPE_INT32
        assert struct.unpack("<i", struct.pack("<f", m.param_value))[0] == 2 and m.param_value != 2.0
        assert struct.unpack("<i", struct.pack("<f", read_param(c, 2, "MAV_SYS_ID").param_value))[0] == 2
        echo = set_param(c, 2, "GF_ACTION", encode_param_value(3, MAV_PARAM_TYPE_INT32, "bytewise"),
                         MAV_PARAM_TYPE_INT32)
        assert struct.unpack("<i", struct.pack("<f", echo.param_value))[0] == 3
        assert px4.params[1]["GF_ACTION"] == 3
        set_param(c, 2, "GF_ACTION", encode_param_value(2, MAV_PARAM_TYPE_INT32, "bytewise"), MAV_PARAM_TYPE_INT32)
    finally:
        c.close()


# ---------------------------------------------------------------------------- ArduPilot GUIDED rules
def _track(c: MavClient, until, max_msgs: int = 400, before_each=None):
    """LOCAL_POSITION_NED samples until until(lpn, samples); before_each() runs before
    waiting for each one (e.g. to stream a setpoint per sample)."""
    samples = []
    for _ in range(max_msgs):
        if before_each is not None:
            before_each()
        m = c.wait("LOCAL_POSITION_NED", timeout_s=2)
        assert m is not None
        samples.append(m)
        if until(m, samples):
            return samples
    pytest.fail("condition not reached")


def _fly_velocity(c: MavClient, sysid: int, vn: float, until, timeout_s: float):
    """Stream a north-velocity setpoint, one per LOCAL_POSITION_NED, until until(lpn) or the deadline."""
    def send() -> None:
        c.mav.set_position_target_local_ned_send(0, sysid, 1, mavlink.MAV_FRAME_LOCAL_NED, VEL_MASK, 0, 0, 0,
                                                 vn, 0, 0, 0, 0, 0, 0, 0)
    return _track(c, until, int(timeout_s * 10) + 10, send)  # LOCAL_POSITION_NED at 10 Hz of simulated time


@pytest.mark.timeout(90)
def test_ardupilot_setpoints_only_in_guided_and_guid_timeout_stops_in_guided(ardupilot):
    k, sysid = 0, 1
    c = client(ardupilot, k)
    try:
        assert set_param(c, sysid, "GUID_TIMEOUT", 1.0, MAV_PARAM_TYPE_REAL32).param_value == 1.0
        assert c.command(sysid, 176, 1, GUIDED, 0).result == ACCEPTED
        assert c.command(sysid, 400, 1).result == ACCEPTED
        assert c.command(sysid, 22, 0, 0, 0, 0, 0, 0, 2.0).result == ACCEPTED  # param7: metres above home
        _track(c, lambda m, s: m.z < -1.9 and abs(m.vz) < 0.1)
        hb = mode_heartbeat(c, sysid, GUIDED)
        assert hb is not None and hb.base_mode & 128
        # outside GUIDED a setpoint stream is ignored: LOITER holds
        assert c.command(sysid, 176, 1, LOITER, 0).result == ACCEPTED
        assert mode_heartbeat(c, sysid, LOITER) is not None
        c.drain()
        first = c.wait("LOCAL_POSITION_NED", timeout_s=2)
        s = _fly_velocity(c, sysid, 1.0, lambda m, s: m.time_boot_ms >= first.time_boot_ms + 1500, 5)
        assert max(abs(m.vx) for m in s) < 0.1 and abs(s[-1].x - first.x) < 0.1
        # in GUIDED the same stream is flown
        assert c.command(sysid, 176, 1, GUIDED, 0).result == ACCEPTED
        assert mode_heartbeat(c, sysid, GUIDED) is not None
        s = _fly_velocity(c, sysid, 1.0, lambda m, s: m.vx > 0.9, 8)
        t_stop_ms = s[-1].time_boot_ms
        # the stream stops: the last target is flown until GUID_TIMEOUT (1 s), then the vehicle brakes to rest
        s = _track(c, lambda m, s: m.time_boot_ms >= t_stop_ms + 3500)
        early = [m for m in s if t_stop_ms + 300 <= m.time_boot_ms <= t_stop_ms + 700]
        assert early and min(m.vx for m in early) > 0.7
        assert math.hypot(s[-1].vx, s[-1].vy) < 0.1 and abs(s[-1].vz) < 0.1
        x_stop = s[-1].x
        s = _track(c, lambda m, s: m.time_boot_ms >= t_stop_ms + 4500)
        # at rest where it stopped: GUIDED zeroes the velocity target (braking at WPNAV_ACCEL) and
        # holds zero velocity, not a position, so its velocity integrator lets it creep a few cm
        assert abs(s[-1].x - x_stop) < 0.1
        hb = c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == sysid, 3)
        assert hb.custom_mode == GUIDED and hb.base_mode & 128  # still GUIDED and armed
        # LAND: straight down, then on the ground (disarm)
        assert c.command(sysid, 176, 1, LAND, 0).result == ACCEPTED
        s = _track(c, lambda m, s: m.z > -0.03 and math.hypot(m.vx, m.vy, m.vz) < 0.05)
        assert abs(s[-1].x - x_stop) < 0.1
    finally:
        c.command(sysid, 400, 0, 21196)
        c.close()


# ---------------------------------------------------------------------------- EKF origins
@pytest.mark.timeout(60)
def test_gps_global_origin_on_request_and_local_position_relative_to_it(sitl):
    origins = []
    for k in (1, 2):  # vehicles no test flies
        c = client(sitl, k)
        try:
            o = request(c, k + 1, 49, "GPS_GLOBAL_ORIGIN")
            assert o.get_srcSystem() == k + 1
            w = origin_world(sitl, o)
            origins.append(w)
            lp = c.wait("LOCAL_POSITION_NED", timeout_s=3)
            true = sitl.state.pos_ned_m[k].copy()  # at rest on the ground: not stepped
            assert np.allclose([lp.x, lp.y, lp.z], true - w, atol=1e-4), (lp, true, w)
            assert np.linalg.norm(sitl.home_ned_m[k] - w) < 0.02  # first fix at its spawn point (1e-7 deg, mm)
        finally:
            c.close()
    assert np.linalg.norm(origins[0] - origins[1]) == pytest.approx(GRID_M * math.sqrt(2), abs=0.02)


@pytest.mark.timeout(60)
def test_no_origin_before_the_first_fix():
    bg = _sitl("px4", gps_fix_delay_max_s=1e7)  # first fixes far in the future
    server = bg.start()
    c = client(server, 0)
    try:
        ack = c.command(1, 512, 49)
        assert ack.result == TEMPORARILY_REJECTED
        assert c.wait("LOCAL_POSITION_NED", timeout_s=1.0) is None
        gps = c.wait("GPS_RAW_INT", timeout_s=3)
        assert gps.fix_type < 3
        assert c.command(1, 400, 1).result == TEMPORARILY_REJECTED  # no GNSS fix: no arming
    finally:
        c.close()
        bg.stop()


@pytest.mark.timeout(60)
def test_set_gps_global_origin_moves_px4_not_ardupilot(px4, ardupilot):
    for server, moves in ((px4, True), (ardupilot, False)):
        k = 2
        c = client(server, k)
        try:
            before = request(c, k + 1, 49, "GPS_GLOBAL_ORIGIN")
            lp0 = c.wait("LOCAL_POSITION_NED", timeout_s=3)
            new = (before.latitude + 100, before.longitude - 50, before.altitude + 1500)  # ~1.1 m N, 0.4 m W, 1.5 m up
            c.mav.set_gps_global_origin_send(0, *new, 0)  # broadcast: PX4 only takes its own sysid
            c.mav.set_gps_global_origin_send(k + 1, *new, 0)
            if moves:
                o = c.wait("GPS_GLOBAL_ORIGIN", lambda m: (m.latitude, m.longitude, m.altitude) == new, 3)
                assert o is not None
            c.drain()
            after = request(c, k + 1, 49, "GPS_GLOBAL_ORIGIN")
            got = (after.latitude, after.longitude, after.altitude)
            assert got == (new if moves else (before.latitude, before.longitude, before.altitude))
            lp1 = c.wait("LOCAL_POSITION_NED", timeout_s=3)
            shift = origin_world(server, after) - origin_world(server, before)
            assert np.allclose([lp1.x, lp1.y, lp1.z], np.array([lp0.x, lp0.y, lp0.z]) - shift, atol=1e-3)
            assert (np.linalg.norm(shift) > 1.0) == moves
        finally:
            c.mav.set_gps_global_origin_send(k + 1, before.latitude, before.longitude, before.altitude, 0)
            c.close()


# ---------------------------------------------------------------------------- time
@pytest.mark.timeout(60)
def test_system_time_is_epoch_plus_sim_time_and_timesync_is_sim_ns(px4):
    c = client(px4, 0)
    try:
        epoch_us = int(EPOCH_UNIX_S * 1e6)
        st = c.wait("SYSTEM_TIME", timeout_s=3)  # streamed
        assert abs(st.time_unix_usec - epoch_us - st.time_boot_ms * 1000) <= 2
        rnd = random.Random(5)
        for _ in range(12):  # requested at arbitrary instants between the streams
            c.drain()
            c.mav.command_long_send(1, 1, 512, 0, 2, 0, 0, 0, 0, 0, 0)
            st = c.wait("SYSTEM_TIME", timeout_s=3)
            assert st is not None
            assert abs(st.time_unix_usec - epoch_us - st.time_boot_ms * 1000) <= 2, (st.time_unix_usec, st.time_boot_ms)
            assert st.time_boot_ms * 1e-3 <= px4.sim_s + 1e-6
            c.wait("HEARTBEAT", timeout_s=rnd.uniform(0.0, 0.07))  # vary the phase (a bounded wait, not a sync)
        lp = c.wait("LOCAL_POSITION_NED", timeout_s=3)
        c.mav.timesync_send(0, 987654321)
        ts = c.wait("TIMESYNC", lambda m: m.ts1 == 987654321 and m.tc1 != 0, 3)
        assert lp.time_boot_ms * 1e6 <= ts.tc1 <= px4.sim_s * 1e9 + 1e3  # the autopilot's boot clock, ns
    finally:
        c.close()


# ---------------------------------------------------------------------------- geodesy
@pytest.mark.timeout(60)
def test_global_position_int_is_wgs84_of_the_true_position(sitl):
    for k in range(N):
        c = client(sitl, k)
        try:
            gp = c.wait("GLOBAL_POSITION_INT", timeout_s=3)
            true = sitl.state.pos_ned_m[k].copy()
            lat, lon, alt = ned_to_geodetic(true, *home(sitl))
            assert abs(gp.lat - float(lat) * 1e7) <= 0.5 + 1e-6 and abs(gp.lon - float(lon) * 1e7) <= 0.5 + 1e-6
            assert abs(gp.alt - float(alt) * 1e3) <= 0.5 + 1e-6
            assert gp.relative_alt == 0  # on its home point
            # ~700 m from the origin on the tangent plane the ellipsoid lies ~4 cm lower: not a flat earth
            assert gp.alt - round(sitl.cfg.home.alt_amsl_m * 1e3) > 30
        finally:
            c.close()


# ---------------------------------------------------------------------------- commands
@pytest.mark.timeout(60)
def test_command_int_520_and_message_interval_limits(sitl):
    c = client(sitl, 1)
    try:
        c.mav.command_int_send(2, 1, 0, 520, 0, 0, 1, 0, 0, 0, 0, 0, 0.0)
        ack = c.wait("COMMAND_ACK", lambda m: m.command == 520, 3)
        assert ack.result == ACCEPTED and (ack.target_system, ack.target_component) == (255, 190)
        assert c.wait("AUTOPILOT_VERSION", timeout_s=3) is not None
        for too_long in (2.0 ** 31, 3e9):  # MESSAGE_INTERVAL.interval_us is an int32
            assert c.command(2, 511, 32, too_long).result == DENIED
        assert c.command(2, 511, 32, 250000).result == ACCEPTED
        c.mav.command_long_send(2, 1, 510, 0, 32, 0, 0, 0, 0, 0, 0)
        mi = c.wait("MESSAGE_INTERVAL", lambda m: m.message_id == 32, 3)
        assert mi.interval_us == 250000
        assert c.command(2, 511, 32, 0).result == ACCEPTED  # back to the default (10 Hz)
        c.mav.command_long_send(2, 1, 510, 0, 32, 0, 0, 0, 0, 0, 0)
        assert c.wait("MESSAGE_INTERVAL", lambda m: m.message_id == 32, 3).interval_us == 100000
        # a message it does not stream (HIGHRES_IMU): FAILED on both autopilots; ArduPilot says so
        assert c.command(2, 511, 105, -1).result == FAILED
        if sitl.cfg.dialect == "ardupilot":
            assert c.wait("STATUSTEXT", lambda m: m.text == "No ap_message for mavlink id (105)", 3) is not None
    finally:
        c.close()
