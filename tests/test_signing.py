"""MAVLink 2 signing: keys, interoperability with pymavlink, and an attacker in another process.

With signing required, unsigned, forged (wrong key) and replayed (captured and resent)
messages must not arm, disarm, change mode, set a parameter, release or move a vehicle,
on the SITL or on an agent's swarm port, and each is counted. A signed pymavlink client
still flies the vehicle.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.signing import Signing, SigningError, TimestampStore, load_key, write_key  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from sim_bridge.sitl.background import BackgroundSitl
from sim_bridge.sitl.config import (
    SigningConfig,  # noqa: E402
    sitl_config,  # noqa: E402
)
from sim_bridge.sitl.server import SitlServer  # noqa: E402
from sim_bridge.sitl.testing import MavClient, local_endpoints  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WRONG_KEY = bytes(range(100, 132))

ATTACKER = textwrap.dedent('''
    """An attacker on the link: sends what it is given, then counts any reply (bounded)."""
    import json, socket, sys, time
    args = json.loads(sys.argv[1])
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.1)
    for hexframe in args["frames"]:
        s.sendto(bytes.fromhex(hexframe), ("127.0.0.1", args["port"]))
        time.sleep(0.002)
    replies, t_end = 0, time.monotonic() + args["listen_s"]
    while time.monotonic() < t_end:
        try:
            data, _ = s.recvfrom(65535)
            replies += 1
        except socket.timeout:
            pass
    print(json.dumps({"sent": len(args["frames"]), "replies": replies}))
''')


def run_attacker(port: int, frames: list[bytes], listen_s: float = 1.0) -> dict:
    """A separate process sends the frames to 127.0.0.1:port; returns what it saw."""
    arg = json.dumps({"port": port, "frames": [f.hex() for f in frames], "listen_s": listen_s})
    out = subprocess.run([sys.executable, "-c", ATTACKER, arg], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def _mav(sysid=255, compid=190, key: bytes | None = None, link_id: int = 0) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = link_id
        mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
    return mav


def _hostile_commands(target: int) -> list:
    """Arm, mode OFFBOARD, a parameter, release, a setpoint: what must not get through."""
    return [
        mavlink.MAVLink_command_long_message(target, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_command_long_message(target, 1, 176, 0, 1, 6, 0, 0, 0, 0, 0),
        mavlink.MAVLink_param_set_message(target, 1, b"COM_OF_LOSS_T", 9.0, 9),
        mavlink.MAVLink_command_long_message(target, 1, 31010, 0, 0, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_set_position_target_local_ned_message(0, target, 1, 1, 0b110111000111, 0, 0, 0,
                                                               5, 0, 0, 0, 0, 0, 0, 0),
    ]


def _sd_mav(sysid: int, key: bytes | None = None) -> swarmdrop.MAVLink:
    """A project-dialect encoder for vehicle sysid's companion (compid 191), optionally signing."""
    mav = swarmdrop.MAVLink(None, srcSystem=sysid, srcComponent=191)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = 1
        mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
    return mav


@pytest.fixture()
def key_file(tmp_path) -> Path:
    path = tmp_path / "signing.key"
    write_key(path)
    return path


# ---------------------------------------------------------------------------- keys and the codec
def test_key_files_are_checked(tmp_path):
    good = tmp_path / "k"
    key = write_key(good)
    assert load_key(good) == key and good.stat().st_mode & 0o777 == 0o600
    os.chmod(good, 0o644)
    with pytest.raises(SigningError, match="readable by others.*chmod 600"):
        load_key(good)
    short = tmp_path / "short"
    short.write_text("abcd")
    os.chmod(short, 0o600)
    with pytest.raises(SigningError, match="32-byte") as err:
        load_key(short)
    assert "abcd" not in str(err.value)  # a key never appears in a message
    with pytest.raises(SigningError, match="needs a 32-byte key"):
        Signing("require", b"")
    with pytest.raises(SigningError, match="expected one of"):
        Signing("sometimes", key)


def test_our_signatures_and_pymavlinks_verify_both_ways_and_replays_fail():
    key = bytes(range(32))
    codec = Codec(mavlink, swarmdrop)
    ours = Signing("require", key, link_id=3, crc_extra=codec.crc_extra)
    msg = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    frame = ours.sign(codec.encode(msg, 255, 190, 7))
    rx = mavlink.MAVLink(None)
    rx.signing.secret_key = key
    got = rx.parse_char(frame)
    assert got is not None and got.get_signed() and rx.signing.badsig_count == 0
    theirs = bytes(msg.pack(_mav(key=key, link_id=1)))
    check = Signing("require", key, crc_extra=codec.crc_extra)
    assert check.check(theirs) and codec.decode(theirs).command == 400
    assert not check.check(theirs) and check.counters.replayed == 1  # the same frame again
    forged = bytes(msg.pack(_mav(key=WRONG_KEY)))
    assert not check.check(forged) and check.counters.bad_signature == 1
    unsigned = bytes(msg.pack(_mav()))
    assert not check.check(unsigned) and check.counters.unsigned == 1
    radio = bytes(mavlink.MAVLink_radio_status_message(200, 190, 100, 90, 80, 0, 0).pack(_mav()))
    assert check.check(radio) and check.counters.accepted_unsigned == 1  # PX4 accepts RADIO_STATUS unsigned
    optional = Signing("optional", key, crc_extra=codec.crc_extra)
    assert optional.check(unsigned) and not optional.check(forged)


def test_timestamps_survive_a_restart(tmp_path):
    """A restarted sender never reuses a timestamp, even with its clock set back an hour."""
    store_path = tmp_path / "ts"
    clock = [time.time()]
    a = Signing("require", bytes(32), store=TimestampStore(store_path), wall_clock=lambda: clock[0])
    codec = Codec(mavlink)
    a.crc_extra = codec.crc_extra
    hb = codec.encode(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3), 1, 1, 0)
    last = int.from_bytes(a.sign(hb)[-12:-6], "little")
    a.close()
    clock[0] -= 3600.0
    b = Signing("require", bytes(32), store=TimestampStore(store_path), wall_clock=lambda: clock[0],
                crc_extra=codec.crc_extra)
    assert int.from_bytes(b.sign(hb)[-12:-6], "little") > last


# ---------------------------------------------------------------------------- the SITL
def test_sitl_with_signing_required_ignores_unsigned_forged_and_replayed(key_file):
    key = load_key(key_file)
    cfg = sitl_config(2, endpoints=local_endpoints(2), signing=SigningConfig(mode="require", key_file=str(key_file)))
    bg = BackgroundSitl(cfg)
    server = bg.start()
    c = MavClient(cfg.endpoints.remote_base_port + 0)
    c.conn.setup_signing(key, sign_outgoing=True)
    try:
        assert c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 1 and m.get_signed(), 5) is not None
        ep, ap = server.endpoints[0], server.autopilots[0]
        port = ep.link.local_port
        # a signed client flies it: arm (captured), set a parameter (captured), then undo both
        capture_mav = c.conn.mav
        arm = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        arm_frame = bytes(arm.pack(capture_mav))
        c.conn.write(arm_frame)
        assert c.wait("COMMAND_ACK", lambda m: m.command == 400 and m.result == 0, 3) is not None
        assert ap.armed
        set_frame = bytes(mavlink.MAVLink_param_set_message(1, 1, b"COM_OF_LOSS_T", 2.5, 9).pack(capture_mav))
        c.conn.write(set_frame)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T" and m.param_value == 2.5, 3)
        c.mav.command_long_send(1, 1, 400, 0, 0, 0, 0, 0, 0, 0, 0)
        assert c.wait("COMMAND_ACK", lambda m: m.command == 400 and m.result == 0, 3) is not None
        c.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 3.0, 9)
        assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T" and m.param_value == 3.0, 3)
        assert not ap.armed
        mode_before, sg = ap.mode, ep.signing.counters
        before = (sg.unsigned, sg.bad_signature, sg.replayed)
        hostile = _hostile_commands(1)
        frames = [bytes(m.pack(_mav())) for m in hostile]  # unsigned
        frames += [bytes(m.pack(_mav(key=WRONG_KEY))) for m in hostile]  # forged
        frames += [arm_frame, set_frame]  # replayed
        seen = run_attacker(port, frames)
        assert seen["replies"] == 0, "the SITL answered an attacker"
        deadline = time.monotonic() + 3.0  # the SITL has read them all when the counters say so
        while (sg.unsigned - before[0], sg.bad_signature - before[1], sg.replayed - before[2]) != (5, 5, 2):
            assert time.monotonic() < deadline, sg
            time.sleep(0.02)  # polling a condition with a deadline
        assert not ap.armed and ap.mode == mode_before and server.params[0]["COM_OF_LOSS_T"] == 3.0
        assert math.isnan(server.fleet.released_at_s[0]) and ap.offb.sp is None
        # telemetry still goes to the signed client, not to whoever sent the last datagram
        c.drain()
        assert c.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 1, 3) is not None
        # and the signed client still commands it
        c.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        assert c.wait("COMMAND_ACK", lambda m: m.command == 400 and m.result == 0, 3) is not None
        assert server.signing_stats()["0"].replayed >= 2
    finally:
        c.close()
        bg.stop()


def test_setup_signing_only_over_a_trusted_link(key_file):
    """SETUP_SIGNING installs a key only when it arrives signed with the current key."""
    server = SitlServer(sitl_config(1, signing=SigningConfig(mode="require", key_file=str(key_file))))
    sg = server.links.signing.endpoint(0)

    class Ep:
        signing = sg

        def queue_fields(self, *a, **k):
            pass

    new_key = bytes(range(1, 33))
    msg = mavlink.MAVLink_setup_signing_message(1, 1, list(new_key), 0)
    server.router.handle(Ep(), msg, None, 0)  # decoded from an unsigned frame
    assert sg.key == load_key(key_file) and server.router.setup_signing_refused == 1
    codec = Codec(mavlink)
    signed = sg.sign(codec.encode(msg, 255, 190, 0))
    server.router.handle(Ep(), codec.decode(signed), None, 0)
    assert sg.key == new_key


def test_sitl_refuses_an_unsafe_key_file(tmp_path):
    path = tmp_path / "k"
    write_key(path)
    os.chmod(path, 0o640)
    out = subprocess.run([sys.executable, "-m", "sim_bridge.sitl", "--vehicles", "1", "--signing", "require",
                          "--signing-key", str(path), "--duration", "0.1"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2 and "readable by others" in out.stderr and path.read_text().strip() not in out.stderr


# ---------------------------------------------------------------------------- an agent's swarm port
def test_swarm_port_with_signing_required_drops_hostile_states(key_file):
    """The agent's swarm link: only states signed with the fleet key reach the swarm view."""
    from companion.link.endpoints import MavEndpoint, UdpLink
    from companion.node.swarmlink import SwarmLink, view_for

    key = load_key(key_file)
    codec = Codec(swarmdrop)
    sg = Signing("require", key, link_id=1, crc_extra=codec.crc_extra)
    ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), codec, 1, 191, signing=sg)
    view = view_for(4)
    link = SwarmLink(ep, 0, [], view)
    link.set_epoch(time.time() - 10.0)
    link.now_us = int(time.time() * 1e6) + 60_000_000  # (the tick path's clock)
    try:
        def state(vid: int, t_us: int) -> object:
            return swarmdrop.MAVLink_swarmdrop_state_message(t_us, 0, 1.0, 2.0, -5.0, 0.0, 0.0, 0.0,
                                                             [1.0, 0.0, 0.0, 0.0], 2, 0, vid)

        now_us = int(time.time() * 1e6)
        good = bytes(state(2, now_us).pack(_sd_mav(3, key=key)))
        frames = [bytes(state(1, now_us).pack(_sd_mav(2))),                 # unsigned
                  bytes(state(1, now_us).pack(_sd_mav(2, key=WRONG_KEY))),  # forged
                  good, good]                                                 # one good, then its replay
        run_attacker(ep.link.local_port, frames, listen_s=0.1)
        deadline = time.monotonic() + 3.0
        while sg.counters.unsigned + sg.counters.bad_signature + sg.counters.replayed < 3:
            link.poll()
            assert time.monotonic() < deadline, sg.counters
            time.sleep(0.02)  # polling a condition with a deadline
        link.poll()
        assert (sg.counters.unsigned, sg.counters.bad_signature, sg.counters.replayed) == (1, 1, 1)
        assert link.states_in == 1  # only the signed state of vehicle 2
    finally:
        ep.close()
