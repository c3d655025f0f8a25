"""pymavlink/mavutil against a 5-vehicle SITL: heartbeat/modes, commands, params,
offboard loss, bad input. Each test flies its own vehicle so they do not interact."""
from __future__ import annotations

import math
import os
import socket
import struct
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.dialects import Mode, dialect_named  # noqa: E402
from sim_bridge.sitl.background import BackgroundSitl  # noqa: E402
from sim_bridge.sitl.config import sitl_config  # noqa: E402
from sim_bridge.sitl.heartbeat import HEARTBEAT_PERIOD_S  # noqa: E402
from sim_bridge.sitl.params_table import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32, encode_param_value  # noqa: E402
from sim_bridge.sitl.testing import MavClient, local_endpoints, pack_frame, running_sitl, vehicle_client  # noqa: E402

PX4 = dialect_named("px4")

N = 5
NAN = math.nan
POS_ONLY_MASK = 0x9F8 | 0x400  # position, yaw ignored


@pytest.fixture(scope="module")
def sitl():
    with running_sitl(N) as server:
        yield server


def test_heartbeat_and_mode_decoding(sitl):
    c = vehicle_client(sitl, 3)
    try:
        hb = c.wait("HEARTBEAT", timeout_s=3)
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (4, 1)
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.custom_mode == PX4.custom_mode(Mode.HOLD) == 50593792
        assert mavutil.mode_string_v10(hb) == "LOITER"
        assert c.conn.mavlink20()
        for main, sub, name in ((3, 0, "POSCTL"), (4, 6, "LAND"), (4, 3, "LOITER")):
            ack = c.command(4, 176, 1, main, sub)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED
            hb = c.wait("HEARTBEAT", lambda m: m.custom_mode == (main << 16 | sub << 24), 3)
            assert mavutil.mode_string_v10(hb) == name
        # streams present at default rates
        for t in ("SYS_STATUS", "EXTENDED_SYS_STATE", "LOCAL_POSITION_NED", "ATTITUDE", "ATTITUDE_QUATERNION",
                  "GLOBAL_POSITION_INT", "GPS_RAW_INT", "HOME_POSITION", "SYSTEM_TIME"):
            assert c.wait(t, timeout_s=3) is not None, t
        ss = c.wait("SYS_STATUS", timeout_s=3)
        assert ss.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
        gp = c.wait("GLOBAL_POSITION_INT", timeout_s=3)
        assert abs(gp.lat / 1e7 - sitl.cfg.home.lat_deg) < 1e-3 and abs(gp.alt / 1e3 - sitl.cfg.home.alt_amsl_m) < 1
    finally:
        c.close()


def test_arm_commands_acks_and_protocol(sitl):
    c = vehicle_client(sitl, 0)
    try:
        ack = c.command(1, 400, 1, target_component=0)  # mavutil style: compid 0
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert (ack.get_srcSystem(), ack.get_srcComponent()) == (1, 1)
        assert (ack.target_system, ack.target_component) == (255, 190)
        assert c.wait("HEARTBEAT", lambda m: m.base_mode & 128, 3) is not None
        assert c.command(1, 400, 1).result == mavlink.MAV_RESULT_ACCEPTED  # duplicate: idempotent
        assert c.command(1, 400, NAN).result == mavlink.MAV_RESULT_DENIED  # NaN arm flag
        assert c.command(1, 12345).result == mavlink.MAV_RESULT_UNSUPPORTED
        assert c.command(1, 176, 1, 9, 0).result == mavlink.MAV_RESULT_DENIED  # unknown PX4 mode
        assert c.command(1, 400, 0).result == mavlink.MAV_RESULT_ACCEPTED
        assert c.wait("HEARTBEAT", lambda m: not m.base_mode & 128, 3) is not None
        # COMMAND_INT where it applies, UNSUPPORTED where it does not
        c.mav.command_int_send(1, 1, 0, 176, 0, 0, 1, 4, 3, 0, 0, 0, 0.0)
        assert c.wait("COMMAND_ACK", lambda m: m.command == 176, 3).result == mavlink.MAV_RESULT_ACCEPTED
        c.mav.command_int_send(1, 1, 0, 31000, 0, 0, 0, 0, 0, 0, 0, 0, 0.0)
        assert c.wait("COMMAND_ACK", lambda m: m.command == 31000, 3).result == mavlink.MAV_RESULT_UNSUPPORTED
        # REQUEST_MESSAGE and SET_MESSAGE_INTERVAL
        assert c.command(1, 512, 148).result == mavlink.MAV_RESULT_ACCEPTED
        av = c.wait("AUTOPILOT_VERSION", timeout_s=3)
        assert av.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        assert c.command(1, 511, 32, 20000).result == mavlink.MAV_RESULT_ACCEPTED  # 50 Hz
        c.drain()
        t = [c.wait("LOCAL_POSITION_NED", timeout_s=2).time_boot_ms for _ in range(11)]
        assert (t[-1] - t[0]) / 10 < 35  # ~20 ms apart (default would be 100 ms)
        assert c.command(1, 511, 32, 0).result == mavlink.MAV_RESULT_ACCEPTED  # back to default
        assert c.command(1, 512, NAN).result == mavlink.MAV_RESULT_DENIED
        # TIMESYNC and PING replies
        c.mav.timesync_send(0, 1234567)
        assert c.wait("TIMESYNC", lambda m: m.ts1 == 1234567 and m.tc1 > 0, 3) is not None
        c.mav.ping_send(42, 7, 0, 0)
        assert c.wait("PING", lambda m: m.seq == 7 and m.target_system == 255, 3) is not None
        # MAVLink FTP is not provided: requests are NAKed at once (MAVProxy falls back to params)
        req = [0] * 251
        req[0], req[2], req[3] = 5, 0, 4  # seq 5, session 0, OpenFileRO
        c.mav.file_transfer_protocol_send(0, 1, 1, req)
        nak = c.wait("FILE_TRANSFER_PROTOCOL", timeout_s=3)
        assert nak.payload[3] == 129 and nak.payload[5] == 4 and nak.payload[0] == 6
    finally:
        c.close()


def test_full_parameter_list_and_set(sitl):
    c = vehicle_client(sitl, 0)
    try:
        c.mav.param_request_list_send(1, 1)
        seen: dict[int, object] = {}
        first = c.wait("PARAM_VALUE", timeout_s=3)
        count = first.param_count
        seen[first.param_index] = first
        while len(seen) < count:
            m = c.wait("PARAM_VALUE", timeout_s=3)
            assert m is not None, f"got {len(seen)} of {count}"
            seen[m.param_index] = m
        names = {m.param_id for m in seen.values()}
        assert {"MIS_TAKEOFF_ALT", "COM_OF_LOSS_T", "COM_DISARM_PRFLT", "MPC_TILTMAX_AIR", "GF_ACTION"} <= names
        # int params travel byte-wise (PX4): 2 -> float with the int's bytes
        gf = next(m for m in seen.values() if m.param_id == "GF_ACTION")
        assert gf.param_type == MAV_PARAM_TYPE_INT32
        assert struct.unpack("<i", struct.pack("<f", gf.param_value))[0] == 2
        # read by name and by index
        c.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
        m = c.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT", 3)
        c.mav.param_request_read_send(1, 1, b"", m.param_index)
        assert c.wait("PARAM_VALUE", lambda x: x.param_index == m.param_index, 3).param_id == "MIS_TAKEOFF_ALT"
        # set with echo; out-of-range echoes the unchanged value
        c.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 4.5, MAV_PARAM_TYPE_REAL32)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT", 3).param_value == 4.5
        c.mav.param_set_send(1, 1, b"GF_ACTION", encode_param_value(5, MAV_PARAM_TYPE_INT32), MAV_PARAM_TYPE_INT32)
        echo = c.wait("PARAM_VALUE", lambda m: m.param_id == "GF_ACTION", 3)
        assert struct.unpack("<i", struct.pack("<f", echo.param_value))[0] == 5
        c.mav.param_set_send(1, 1, b"MPC_TILTMAX_AIR", 120.0, MAV_PARAM_TYPE_REAL32)
        echo = c.wait("PARAM_VALUE", lambda m: m.param_id == "MPC_TILTMAX_AIR", 3)
        assert echo.param_value == pytest.approx(sitl.cfg.inner_loop.geometric.tilt_max_deg)
        assert sitl.params[0]["MIS_TAKEOFF_ALT"] == 4.5 and sitl.params[1]["MIS_TAKEOFF_ALT"] == 2.5
    finally:
        c.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 2.5, MAV_PARAM_TYPE_REAL32)
        c.close()


def test_offboard_loss_flies_the_setpoint_for_com_of_loss_t_then_holds_and_never_lands(sitl):
    """PX4 with COM_OBL_RC_ACT 5: Hold COM_OF_LOSS_T after the last setpoint, CRITICAL, and it
    stays in Hold, airborne (PX4's Hold never lands by itself); Land (4) lands."""
    k, sysid = 1, 2
    c = vehicle_client(sitl, k)
    try:
        c.mav.param_set_send(sysid, 1, b"COM_OF_LOSS_T", 0.5, MAV_PARAM_TYPE_REAL32)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T" and m.param_value == 0.5, 3)
        c.mav.param_set_send(sysid, 1, b"COM_OBL_RC_ACT", encode_param_value(5, MAV_PARAM_TYPE_INT32),
                             MAV_PARAM_TYPE_INT32)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT", 3)
        assert sitl.params[k]["COM_OBL_RC_ACT"] == 5
        home = sitl.home_ned_m[k]

        def setpoint():
            c.mav.set_position_target_local_ned_send(0, sysid, 1, 1, POS_ONLY_MASK, home[0], home[1], -2.0,
                                                     0, 0, 0, 0, 0, 0, 0, 0)

        # Offboard is refused without a setpoint stream
        assert c.command(sysid, 176, 1, 6, 0).result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        setpoint()
        assert c.command(sysid, 176, 1, 6, 0).result == mavlink.MAV_RESULT_ACCEPTED
        setpoint()
        assert c.command(sysid, 400, 1).result == mavlink.MAV_RESULT_ACCEPTED
        deadline = time.monotonic() + 8
        while time.monotonic() < deadline:  # stream until airborne near 2 m
            setpoint()
            lp = c.wait("LOCAL_POSITION_NED", timeout_s=1)
            if lp is not None and lp.z < -1.5:
                break
        else:
            pytest.fail("did not climb in offboard")
        setpoint()
        t_stop = time.monotonic()
        # The failsafe acts COM_OF_LOSS_T after the last setpoint and says so at once (STATUSTEXT);
        # PX4's HEARTBEAT is a 1 Hz stream, so Hold shows in the vehicle's next slot, up to a
        # period later (sim_bridge.sitl.heartbeat).
        hold = PX4.custom_mode(Mode.HOLD)
        first: dict[str, float] = {}
        hb = None
        deadline = time.monotonic() + 3
        while len(first) < 2 and time.monotonic() < deadline:
            m = c.wait(["STATUSTEXT", "HEARTBEAT"], timeout_s=deadline - time.monotonic())
            if m is None:
                break
            if m.get_type() == "STATUSTEXT" and m.severity == mavlink.MAV_SEVERITY_CRITICAL:
                first.setdefault("text", time.monotonic())
            elif m.get_type() == "HEARTBEAT" and m.custom_mode == hold and "hb" not in first:
                first["hb"], hb = time.monotonic(), m
        assert hb is not None and hb.system_status == 5  # CRITICAL: in failsafe
        # (wall-clock slack for a SITL thread that shares the GIL with this test on a busy machine)
        assert "text" in first and 0.5 - 0.1 <= first["text"] - t_stop <= 0.5 + 0.5
        assert first["hb"] - t_stop <= 0.5 + HEARTBEAT_PERIOD_S + 0.5
        # Hold for ever: a few seconds on, still Hold and in the air
        assert c.wait("HEARTBEAT", lambda m: m.custom_mode != PX4.custom_mode(Mode.HOLD), 4) is None
        assert sitl.autopilots[k].mode == Mode.HOLD and not sitl.autopilots[k].landed
        # COM_OBL_RC_ACT 4: the next loss lands
        c.mav.param_set_send(sysid, 1, b"COM_OBL_RC_ACT", encode_param_value(4, MAV_PARAM_TYPE_INT32),
                             MAV_PARAM_TYPE_INT32)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT", 3)
        setpoint()
        assert c.command(sysid, 176, 1, 6, 0).result == mavlink.MAV_RESULT_ACCEPTED
        for _ in range(5):
            setpoint()
            time.sleep(0.05)
        assert c.wait("HEARTBEAT", lambda m: m.custom_mode == PX4.custom_mode(Mode.LAND), 3) is not None
        assert sitl.autopilots[k].mode == Mode.LAND
    finally:
        c.command(sysid, 400, 0, 21196)
        c.close()


def test_inject_motor_failure_needs_sys_failure_en_and_brings_the_vehicle_down(sitl):
    """MAV_CMD_INJECT_FAILURE as PX4 takes it (`failure motor off -i 2`): refused until
    SYS_FAILURE_EN is 1, then the motor stops and the hovering vehicle falls."""
    k, sysid = 4, 5
    c = vehicle_client(sitl, k)
    try:
        motor_off = (420, 101, 1, 2)  # FAILURE_UNIT_SYSTEM_MOTOR, FAILURE_TYPE_OFF, motor 2
        assert c.command(sysid, *motor_off).result == mavlink.MAV_RESULT_DENIED
        c.mav.param_set_send(sysid, 1, b"SYS_FAILURE_EN", encode_param_value(1, MAV_PARAM_TYPE_INT32),
                             MAV_PARAM_TYPE_INT32)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "SYS_FAILURE_EN", 3)
        assert c.command(sysid, 420, 100, 1, 1).result == mavlink.MAV_RESULT_UNSUPPORTED  # a sensor: not modelled
        assert c.command(sysid, 420, 101, 1, NAN).result == mavlink.MAV_RESULT_DENIED
        assert c.command(sysid, 176, 1, 4, 2).result == mavlink.MAV_RESULT_ACCEPTED  # Takeoff
        assert c.command(sysid, 400, 1).result == mavlink.MAV_RESULT_ACCEPTED
        assert c.wait("LOCAL_POSITION_NED", lambda m: m.z < -2.0, 10) is not None
        assert c.command(sysid, *motor_off).result == mavlink.MAV_RESULT_ACCEPTED
        assert sitl.rotor_faults.scale[k].tolist() == [1.0, 0.0, 1.0, 1.0]
        assert c.wait("STATUSTEXT", lambda m: "motor failure" in m.text, 3) is not None
        att = c.wait("ATTITUDE", lambda m: math.hypot(m.roll, m.pitch) > math.radians(60), 3)
        assert att is not None  # it cannot hold attitude on three rotors
        assert c.wait("LOCAL_POSITION_NED", lambda m: m.z > -0.5, 10) is not None  # down
    finally:
        c.command(sysid, 400, 0, 21196)
        c.close()


def test_bad_input_leaves_sitl_and_other_vehicles_unaffected(sitl):
    victim, other = 2, 3
    c_other = vehicle_client(sitl, other)
    c = vehicle_client(sitl, victim)
    try:
        ep = sitl.endpoints[victim]
        port = ep.link.local_port
        bad_before = ep.bad_frames + ep.link.bytes_skipped
        arm = mavlink.MAVLink_command_long_message(4, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # for sysid 4
        good = pack_frame(arm)
        wrong_crc = bytearray(pack_frame(mavlink.MAVLink_command_long_message(3, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)))
        wrong_crc[-1] ^= 0xFF
        junk = [b"", b"\x00", b"\xfd", b"\xfd\xff\x00", bytes(range(256)), good[:7], good[:-3], bytes(wrong_crc),
                b"\xfe\x05" + b"\x00" * 20, b"\xfd" * 300, os.urandom(1000), good]
        # the client speaks first (first contact, as a GCS or companion does): the stranger's
        # frames below, the valid one included, cannot take the victim's link from it (PX4)
        c.mav.param_request_read_send(3, 1, b"COM_OF_LOSS_T", -1)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T", 3) is not None
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for blob in junk:
                s.sendto(blob, ("127.0.0.1", port))
        # the victim still answers and was not armed by any of it (the arm was for sysid 4)
        c.mav.param_request_read_send(3, 1, b"COM_OF_LOSS_T", -1)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T", 3) is not None
        assert c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 3 and not m.base_mode & 128, 3)
        c.drain()  # telemetry still comes to the client, not to the stranger
        assert c.wait("LOCAL_POSITION_NED", lambda m: m.get_srcSystem() == 3, 3) is not None
        assert ep.bad_frames + ep.link.bytes_skipped > bad_before
        # the vehicle the stray arm named was not armed through another vehicle's link
        hb = c_other.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 4, 3)
        assert hb is not None and not hb.base_mode & 128
        assert not sitl.autopilots[other].armed and not sitl.autopilots[victim].armed
        assert c_other.wait("LOCAL_POSITION_NED", timeout_s=2) is not None
    finally:
        c.close()
        c_other.close()


def test_shared_gcs_endpoint_carries_all_vehicles():
    import dataclasses

    from sim_bridge.sitl.testing import free_udp_base_port

    ep = dataclasses.replace(local_endpoints(3), gcs_enabled=True, gcs_remote_port=free_udp_base_port(1))
    bg = BackgroundSitl(sitl_config(3, endpoints=ep))
    server = bg.start()
    c = MavClient(ep.gcs_remote_port)
    try:
        seen = set()
        for _ in range(30):
            hb = c.wait("HEARTBEAT", timeout_s=3)
            assert hb is not None
            seen.add(hb.get_srcSystem())
            if seen == {1, 2, 3}:
                break
        assert seen == {1, 2, 3}
        ack = c.command(2, 400, 1)
        assert ack.get_srcSystem() == 2 and ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert [ap.armed for ap in server.autopilots] == [False, True, False]
        c.mav.param_request_read_send(0, 0, b"MAV_SYS_ID", -1)  # broadcast: every vehicle answers
        ids = set()
        for _ in range(3):
            m = c.wait("PARAM_VALUE", lambda m: m.param_id == "MAV_SYS_ID", 3)
            assert m is not None
            ids.add((m.get_srcSystem(), struct.unpack("<i", struct.pack("<f", m.param_value))[0]))
        assert ids == {(1, 1), (2, 2), (3, 3)}
    finally:
        c.command(2, 400, 0)
        c.close()
        bg.stop()


def test_stream_intervals_are_per_link_as_on_px4_and_ardupilot():
    """A companion's 50 Hz request on its vehicle's endpoint leaves the shared GCS endpoint at
    the default rate, and the GCS's own requests (off, another rate) leave the companion's
    streams alone: PX4 keeps intervals per MAVLink instance, ArduPilot per channel."""
    import dataclasses

    from sim_bridge.sitl.testing import free_udp_base_port

    def spacing_ms(client, name, sysid, count=11):
        client.drain()
        t = [client.wait(name, lambda m: m.get_srcSystem() == sysid, 3).time_boot_ms for _ in range(count)]
        return (t[-1] - t[0]) / (count - 1)

    ep = dataclasses.replace(local_endpoints(2), gcs_enabled=True, gcs_remote_port=free_udp_base_port(1))
    bg = BackgroundSitl(sitl_config(2, endpoints=ep))
    bg.start()
    companion, gcs = MavClient(ep.vehicle_remote_port(0)), MavClient(ep.gcs_remote_port)
    try:
        assert companion.wait("HEARTBEAT", timeout_s=3) is not None and gcs.wait("HEARTBEAT", timeout_s=3) is not None
        assert companion.command(1, 511, 32, 20000).result == mavlink.MAV_RESULT_ACCEPTED  # LPN at 50 Hz
        assert spacing_ms(companion, "LOCAL_POSITION_NED", 1) < 35  # ~20 ms
        assert spacing_ms(gcs, "LOCAL_POSITION_NED", 1) > 80  # still the default 100 ms
        # each link reports its own interval (MESSAGE_INTERVAL after GET_MESSAGE_INTERVAL)
        assert companion.command(1, 510, 32).result == mavlink.MAV_RESULT_ACCEPTED
        assert companion.wait("MESSAGE_INTERVAL", lambda m: m.message_id == 32, 3).interval_us == 20000
        assert gcs.command(1, 510, 32).result == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.wait("MESSAGE_INTERVAL", lambda m: m.message_id == 32, 3).interval_us == 100000
        # the GCS turns ATTITUDE off for itself: the companion still gets it
        assert gcs.command(1, 511, 30, -1).result == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(1, 510, 30).result == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.wait("MESSAGE_INTERVAL", lambda m: m.message_id == 30, 3).interval_us == -1
        assert companion.wait("ATTITUDE", lambda m: m.get_srcSystem() == 1, 3) is not None
        gcs.drain()
        # over five of vehicle 1's positions (0.5 s of its 10 Hz stream) the GCS gets no ATTITUDE
        # of vehicle 1 (it would get about five), while vehicle 2's ATTITUDE still comes
        seen: list[str] = []
        for _ in range(200):  # bounded
            m = gcs.wait(["LOCAL_POSITION_NED", "ATTITUDE"], lambda m: m.get_srcSystem() in (1, 2), 3)
            assert m is not None
            seen.append(f"{m.get_type()}:{m.get_srcSystem()}")
            if seen.count("LOCAL_POSITION_NED:1") >= 5:
                break
        assert seen.count("LOCAL_POSITION_NED:1") >= 5 and "ATTITUDE:1" not in seen and "ATTITUDE:2" in seen
    finally:
        companion.close()
        gcs.close()
        bg.stop()
