"""The signing holes of issue 16, found with pymavlink against `swarmdrop sitl --signing require`.

One test per hole; each fails on the code before commit 0e6a0ac:
1. an unsigned RADIO_STATUS (accepted unsigned, as PX4 does; MAVLink 1 and 2) redirected the
   telemetry of a vehicle endpoint, of the GCS endpoint and of an agent's udpin autopilot link;
2. a signed frame captured on the GCS endpoint was accepted again on the vehicle's own
   endpoint, and the reverse (one replay table per endpoint instead of per vehicle);
3. replayed frames that are not new moved the reply address: a vehicle's own HEARTBEAT sent
   back to it, a frame for vehicle 1 replayed to vehicle 2 (its case of a station's HEARTBEAT,
   which names no target, still failed after 0e6a0ac: the vehicle endpoints now share a
   replay table for such frames, companion.link.signing.FleetScope);
4. an unsigned or wrong-key SETUP_SIGNING was dropped silently (not counted, not answered);
5. the .tlog kept the key of a SETUP_SIGNING in clear.

"The signed client keeps every message" is checked with MAVLink sequence numbers: an
endpoint numbers the frames of each (sysid, compid) 0..255 in turn, so a frame sent
elsewhere leaves a gap in what the client saw. Everything binds 127.0.0.1; waiting is
select() with deadlines, never a sleep.
"""
from __future__ import annotations

import contextlib
import os
import random
import select
import socket
import time
from pathlib import Path
from typing import Callable, Iterator

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.endpoints import MavEndpoint, UdpLink  # noqa: E402
from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.signing import Signing, write_key  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from sim_bridge.sitl.background import BackgroundSitl
from sim_bridge.sitl.config import (  # noqa: E402
    EndpointConfig,
    SigningConfig,
    sitl_config,  # noqa: E402
)
from sim_bridge.sitl.server import SitlServer  # noqa: E402
from sim_bridge.sitl.testing import MavClient, free_udp_base_port  # noqa: E402

KEY = random.Random(16).randbytes(32)
WRONG_KEY = random.Random(1616).randbytes(32)
NEW_KEY = random.Random(160).randbytes(32)
DEADLINE_S = 4.0
PARAM = b"COM_OF_LOSS_T"
AFTER = 8
"""Frames a client must receive from each vehicle after an injection was processed."""


def _now_10us() -> int:
    return int((time.time() - 1420070400) * 1e5)


def _mav(sysid: int = 255, compid: int = 190, key: bytes | None = None, link_id: int = 0) -> mavlink.MAVLink:
    """A pymavlink encoder, signing with key if given."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = link_id
        mav.signing.timestamp = _now_10us()
    return mav


def _radio_status(mavlink1: bool) -> bytes:
    """An unsigned RADIO_STATUS (PX4 accepts it unsigned), MAVLink 1 or 2."""
    msg = mavlink.MAVLink_radio_status_message(200, 190, 100, 90, 80, 0, 0)
    frame = bytes(msg.pack(_mav(), force_mavlink1=mavlink1))
    assert frame[0] == (0xFE if mavlink1 else 0xFD)
    return frame


class Ground:
    """A signed pymavlink ground station where the SITL sends (MavClient) that keeps every
    message it receives, in order."""

    def __init__(self, port: int, link_id: int):
        self.client = MavClient(port)
        self.client.conn.setup_signing(KEY, sign_outgoing=True, link_id=link_id)
        self.mav = self.client.mav
        self.msgs: list = []
        self.bad = 0

    def fileno(self) -> int:
        return self.client.conn.port.fileno()

    def drain(self) -> None:
        for _ in range(100_000):
            try:
                m = self.client.conn.recv_match(blocking=False)
            except mavutil.mavlink.MAVError:  # pymavlink raises on a bad signature or a replay
                self.bad += 1
                continue
            if m is None:
                return
            if m.get_type() == "BAD_DATA":
                self.bad += 1
            else:
                self.msgs.append(m)

    def got(self, sysid: int, mtype: str | None = None, since: int = 0, pred: Callable = lambda m: True) -> list:
        return [m for m in self.msgs[since:] if m.get_srcSystem() == sysid and m.get_srcComponent() == 1
                and (mtype is None or m.get_type() == mtype) and pred(m)]

    def gaps(self, sysid: int) -> list[tuple[int, int]]:
        """(seq, next seq) wherever a frame of vehicle sysid is missing from what we received."""
        seqs = [m.get_seq() for m in self.got(sysid)]
        return [(a, b) for a, b in zip(seqs, seqs[1:]) if b != (a + 1) & 0xFF]

    def close(self) -> None:
        self.client.close()


class AgentLink:
    """An agent's autopilot link as `swarmdrop agent` opens it for udpin://127.0.0.1:PORT,
    with signing required (the test reads it: drain = poll)."""

    def __init__(self):
        self.codec = Codec(mavlink, swarmdrop)
        self.signing = Signing("require", KEY, link_id=0, crc_extra=self.codec.crc_extra)
        self.ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=True, peer_ids=(1, 1)),
                              self.codec, 1, 191, signing=self.signing)
        self.port = self.ep.link.local_port

    def fileno(self) -> int:
        return self.ep.link.fileno()

    def drain(self) -> None:
        self.ep.poll()

    def send_heartbeats(self, n: int) -> None:
        for _ in range(n):
            self.ep.queue(mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 0, 4))
        self.ep.flush()

    def close(self) -> None:
        self.ep.close()


class SignedAutopilot:
    """The autopilot behind an agent's link: a UDP socket on 127.0.0.1 and a signing pymavlink
    parser that keeps every message it receives."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.mav = _mav(1, 1, KEY, link_id=3)
        self.msgs: list = []

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, msg, port: int) -> None:
        self.sock.sendto(bytes(msg.pack(self.mav)), ("127.0.0.1", port))
        self.mav.seq = (self.mav.seq + 1) & 0xFF

    def drain(self) -> None:
        for _ in range(10_000):
            try:
                data = self.sock.recv(65535)
            except BlockingIOError:
                return
            self.msgs += self.mav.parse_buffer(data) or []  # raises on a bad signature or a replay

    def close(self) -> None:
        self.sock.close()


class Attacker:
    """A UDP socket of its own on 127.0.0.1: sends raw frames, keeps whatever comes back."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)

    def send(self, frame: bytes, port: int) -> None:
        self.sock.sendto(frame, ("127.0.0.1", port))

    def received(self) -> list[bytes]:
        """Datagrams waiting now. Called once a client has received frames the SITL sent after
        the attack was processed: anything sent here would have been sent (and delivered over
        loopback) before those."""
        out = []
        for _ in range(10_000):
            try:
                out.append(self.sock.recv(65535))
            except BlockingIOError:
                return out
        return out

    def close(self) -> None:
        self.sock.close()


def _pump(*parts, wait_s: float = 0.02) -> None:
    """Wait (select) up to wait_s for any part to become readable, then drain them all."""
    select.select(parts, [], [], wait_s)
    for p in parts:
        p.drain()


def _until(cond: Callable[[], bool], parts, what: str, timeout_s: float = DEADLINE_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        _pump(*parts)


def _param_value(g: Ground, sysid: int, since: int) -> float | None:
    vals = g.got(sysid, "PARAM_VALUE", since, lambda m: m.param_id == PARAM.decode())
    return vals[-1].param_value if vals else None


def _ask_param(g: Ground, sysid: int, parts, what: str) -> float:
    """A signed PARAM_REQUEST_READ from g, and its answer: a barrier for what was sent to the
    same endpoint before it (one socket's datagrams are read in order)."""
    mark = len(g.msgs)
    g.mav.param_request_read_send(sysid, 1, PARAM, -1)
    _until(lambda: _param_value(g, sysid, mark) is not None, parts, what)
    value = _param_value(g, sysid, mark)
    assert value is not None
    return value


def _set_param(g: Ground, sysid: int, value: float, parts) -> bytes:
    """A signed PARAM_SET from g, applied (its PARAM_VALUE seen); returns the frame as sent."""
    frame = bytes(mavlink.MAVLink_param_set_message(sysid, 1, PARAM, value, 9).pack(g.mav))
    g.mav.seq = (g.mav.seq + 1) & 0xFF
    assert frame[2] & 0x01, "not signed"
    mark = len(g.msgs)
    g.client.conn.write(frame)
    _until(lambda: _param_value(g, sysid, mark) == value, parts, f"PARAM_VALUE {value}")
    return frame


@pytest.fixture()
def key_file(tmp_path) -> Path:
    path = tmp_path / "fleet.key"
    write_key(path, KEY)
    return path


@contextlib.contextmanager
def _sitl(key_file: Path, vehicles: int, gcs: bool = False, tlog: Path | None = None) -> Iterator[SitlServer]:
    """A SITL with signing required; vehicle k sends to base+k, the GCS endpoint to base+vehicles."""
    base = free_udp_base_port(vehicles + 1)
    ec = EndpointConfig(remote_host="127.0.0.1", remote_base_port=base, bind_host="127.0.0.1", local_base_port=0,
                        gcs_enabled=gcs, gcs_remote_port=base + vehicles)
    cfg = sitl_config(vehicles, seed=16, endpoints=ec, tlog_path=str(tlog) if tlog else None,
                      signing=SigningConfig(mode="require", key_file=str(key_file)))
    bg = BackgroundSitl(cfg)
    server = bg.start()
    try:
        yield server
    finally:
        bg.stop()


def _signed_ground(server: SitlServer, k: int | None, link_id: int, closing: contextlib.ExitStack) -> Ground:
    """A signed station on vehicle k's endpoint (k None: the GCS endpoint), heard from and
    claiming the link with a signed HEARTBEAT (answered: it has been processed)."""
    ec = server.cfg.endpoints
    g = Ground(ec.gcs_remote_port if k is None else ec.vehicle_remote_port(k), link_id)
    closing.callback(g.close)
    sysid = 1 if k is None else k + 1
    _until(lambda: bool(g.got(sysid, "HEARTBEAT", pred=lambda m: m.get_signed())), [g], "a signed HEARTBEAT")
    g.mav.heartbeat_send(6, 8, 0, 0, 0)
    _ask_param(g, sysid, [g], "the claim")
    return g


# ---------------------------------------------------------------------------------------- hole 1
def test_unsigned_radio_status_redirects_no_telemetry(key_file):
    """Hole 1. An unsigned RADIO_STATUS (MAVLink 1, then 2) from another socket, sent to a
    vehicle endpoint, to the GCS endpoint and to an agent's udpin autopilot link, all under
    require: it is let through (counted in accepted_unsigned), but every signed client keeps
    every message (no sequence gap, a HEARTBEAT of every vehicle after each injection), and
    the attacker receives nothing."""
    with _sitl(key_file, 2, gcs=True) as server, contextlib.ExitStack() as closing:
        veh = _signed_ground(server, 0, 1, closing)
        gcs = _signed_ground(server, None, 2, closing)
        agent, ap, attacker = AgentLink(), SignedAutopilot(), Attacker()
        for part in (agent, ap, attacker):
            closing.callback(part.close)
        ap.send(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3), agent.port)  # first contact, signed
        _until(lambda: agent.ep.received == 1, [agent], "the autopilot's HEARTBEAT")
        assert agent.ep.link.remote[1] == ap.sock.getsockname()[1]
        ports = {"0": server.endpoints[0].link.local_port, "gcs": server.gcs.link.local_port}
        parts = [veh, gcs, agent, ap]
        for rnd, mavlink1 in enumerate((True, False), start=1):
            frame = _radio_status(mavlink1)
            before = server.signing_stats()
            for port in (*ports.values(), agent.port):
                attacker.send(frame, port)
            agent.send_heartbeats(5)  # the agent sends before and after it reads the attack
            _until(lambda: agent.signing.counters.accepted_unsigned == rnd, [agent, ap], "the agent to read it")
            agent.send_heartbeats(5)
            _until(lambda: all(server.signing_stats()[e].accepted_unsigned == before[e].accepted_unsigned + 1
                               for e in ports), parts, "the SITL to read it")
            _pump(*parts, wait_s=0)  # what the SITL sent before it read the attack is here by now:
            m_veh, m_gcs = len(veh.msgs), len(gcs.msgs)  # what arrives from here was sent after
            _until(lambda: len(veh.got(1, since=m_veh)) >= AFTER and veh.got(1, "HEARTBEAT", m_veh)
                   and all(len(gcs.got(s, since=m_gcs)) >= AFTER and gcs.got(s, "HEARTBEAT", m_gcs) for s in (1, 2))
                   and len(ap.msgs) == 10 * rnd, parts, "telemetry after the attack")
            assert attacker.received() == [], "telemetry went to the attacker"
            now = server.signing_stats()
            assert all(now[e].unsigned == before[e].unsigned for e in ports)
        assert veh.gaps(1) == [] and gcs.gaps(1) == [] and gcs.gaps(2) == [], "a signed client lost messages"
        assert veh.bad == gcs.bad == 0
        seqs = [m.get_seq() for m in ap.msgs]
        assert seqs == list(range(seqs[0], seqs[0] + 20)), "the autopilot lost messages"
        assert agent.signing.counters.accepted_unsigned == 2 and agent.signing.counters.unsigned == 0
        assert agent.ep.link.remote[1] == ap.sock.getsockname()[1]
        assert server.endpoints[0].link.remote == ("127.0.0.1", server.cfg.endpoints.vehicle_remote_port(0))
        assert server.gcs.link.remote == ("127.0.0.1", server.cfg.endpoints.gcs_remote_port)


# ---------------------------------------------------------------------------------------- hole 2
def test_signed_frame_replayed_across_a_vehicles_endpoints_is_rejected(key_file):
    """Hole 2. A signed PARAM_SET captured on the GCS endpoint and replayed (from another
    socket) to the vehicle's own endpoint is dropped as a replay: the parameter keeps the
    value set since, nothing answers the attacker. The same from the vehicle's endpoint to the
    GCS endpoint. (The two stations sign with different link ids, as two ground stations do:
    each endpoint alone has never seen the captured frame's stream.)"""
    with _sitl(key_file, 1, gcs=True) as server, contextlib.ExitStack() as closing:
        gcs = _signed_ground(server, None, 2, closing)
        veh = _signed_ground(server, 0, 1, closing)
        parts = [gcs, veh]
        attacker = Attacker()
        closing.callback(attacker.close)
        cases = [(gcs, veh, "0", server.endpoints[0].link.local_port, 2.5, 3.0),
                 (veh, gcs, "gcs", server.gcs.link.local_port, 2.0, 3.5)]
        for captured_on, replayed_on, name, port, old, new in cases:
            captured = _set_param(captured_on, 1, old, parts)
            _set_param(captured_on, 1, new, parts)
            before = server.signing_stats()[name].replayed
            attacker.send(captured, port)
            # answered after the replay was read (one socket's datagrams are read in order)
            assert _ask_param(replayed_on, 1, parts, "the parameter") == new, f"replayed on {name}: parameter changed"
            assert server.params[0][PARAM.decode()] == new
            _until(lambda: server.signing_stats()[name].replayed == before + 1, parts,
                   f"the replay on endpoint {name} to be counted")
            assert attacker.received() == [], "the SITL answered the replay"


# ---------------------------------------------------------------------------------------- hole 3
def test_replayed_frames_move_no_reply_address(key_file):
    """Hole 3. From another socket: vehicle 1's own signed HEARTBEAT sent back to it; frames
    vehicle 1 received from its station replayed to vehicle 2: a PARAM_REQUEST_READ for
    vehicle 1, and the station's HEARTBEAT (no target field; vehicle 2's station signs with
    another link id, as pymavlink gives each connection its own, so the stream is new to vehicle
    2). Each is counted as replayed, the vehicle's signed client keeps every message, the
    attacker receives nothing."""
    with _sitl(key_file, 2) as server, contextlib.ExitStack() as closing:
        c1 = _signed_ground(server, 0, 1, closing)
        c2 = _signed_ground(server, 1, 2, closing)
        parts = [c1, c2]
        attacker = Attacker()
        closing.callback(attacker.close)
        own_hb = bytes(c1.got(1, "HEARTBEAT")[-1].get_msgbuf())
        assert own_hb[2] & 0x01 and len(own_hb) == 12 + own_hb[1] + 13  # signed by vehicle 1
        gcs_hb = bytes(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 4).pack(c1.mav))  # names no target
        c1.mav.seq = (c1.mav.seq + 1) & 0xFF
        for_v1 = bytes(mavlink.MAVLink_param_request_read_message(1, 1, PARAM, -1).pack(c1.mav))
        c1.client.conn.write(gcs_hb)
        mark = len(c1.msgs)
        c1.client.conn.write(for_v1)  # vehicle 1 reads both and answers the second
        _until(lambda: _param_value(c1, 1, mark) is not None, parts, "vehicle 1's answer")
        for frame, k, client in ((own_hb, 0, c1), (for_v1, 1, c2), (gcs_hb, 1, c2)):
            ep = server.endpoints[k]
            before = server.signing_stats()[str(k)].replayed
            read = before + ep.received  # nobody else talks to the endpoint meanwhile
            attacker.send(frame, ep.link.local_port)
            _until(lambda: server.signing_stats()[str(k)].replayed + ep.received > read, parts,
                   f"vehicle {k + 1} to read the replay")
            _pump(*parts, wait_s=0)
            after = len(client.msgs)  # what arrives from here was sent after the replay was read
            _until(lambda: len(client.got(k + 1, since=after)) >= AFTER, parts,
                   f"vehicle {k + 1}'s telemetry after the replay")
            assert attacker.received() == [], f"vehicle {k + 1} answered the attacker"
            assert server.signing_stats()[str(k)].replayed == before + 1
            assert server.endpoints[k].link.remote == ("127.0.0.1", server.cfg.endpoints.vehicle_remote_port(k))
        assert c1.gaps(1) == [] and c2.gaps(2) == [], "a signed client lost messages"


# ---------------------------------------------------------------------------------------- hole 4
def test_refused_setup_signing_is_counted_and_answered(key_file):
    """Hole 4. An unsigned SETUP_SIGNING on vehicle 1's endpoint and a wrong-key one for vehicle
    2 on the GCS endpoint install no key; each is counted (per link: setup_signing_refused,
    with unsigned / bad_signature; the router's total) and answered by a CRITICAL STATUSTEXT
    from that vehicle to its ground stations (its own endpoint and the GCS endpoint), never to
    the sender."""
    with _sitl(key_file, 2, gcs=True) as server, contextlib.ExitStack() as closing:
        veh = _signed_ground(server, 0, 1, closing)
        gcs = _signed_ground(server, None, 2, closing)
        parts = [veh, gcs]
        attacker = Attacker()
        closing.callback(attacker.close)
        before = server.signing_stats()
        marks = len(veh.msgs), len(gcs.msgs)
        unsigned = mavlink.MAVLink_setup_signing_message(1, 1, list(WRONG_KEY), _now_10us()).pack(_mav())
        forged = mavlink.MAVLink_setup_signing_message(2, 1, list(WRONG_KEY), _now_10us()).pack(
            _mav(key=WRONG_KEY, link_id=7))
        attacker.send(bytes(unsigned), server.endpoints[0].link.local_port)
        attacker.send(bytes(forged), server.gcs.link.local_port)

        def refused(g: Ground, sysid: int, since: int) -> list:
            return g.got(sysid, "STATUSTEXT", since, lambda m: "SETUP_SIGNING refused" in m.text)

        _until(lambda: refused(veh, 1, marks[0]) and refused(gcs, 1, marks[1]) and refused(gcs, 2, marks[1]),
               parts, "STATUSTEXT 'SETUP_SIGNING refused' from vehicles 1 and 2")
        for text in refused(veh, 1, marks[0]) + refused(gcs, 1, marks[1]) + refused(gcs, 2, marks[1]):
            assert text.severity == mavlink.MAV_SEVERITY_CRITICAL and text.get_signed()
        now = server.signing_stats()
        assert now["0"].setup_signing_refused == before["0"].setup_signing_refused + 1
        assert now["0"].unsigned == before["0"].unsigned + 1
        assert now["gcs"].setup_signing_refused == before["gcs"].setup_signing_refused + 1
        assert now["gcs"].bad_signature == before["gcs"].bad_signature + 1
        assert now["1"].setup_signing_refused == 0
        assert server.router.setup_signing_refused == 2
        assert all(ep.signing.key == KEY for ep in server.endpoints + [server.gcs])
        assert attacker.received() == [], "the refusal went to the sender"
        assert _ask_param(veh, 1, parts, "vehicle 1 still answers its signed client") > 0


# ---------------------------------------------------------------------------------------- hole 5
def test_tlog_never_holds_a_setup_signing_key(key_file, tmp_path):
    """Hole 5. A valid signed SETUP_SIGNING installs a new key (the client then talks with it),
    and the SITL's --tlog holds the frame with its 32 key bytes zeroed: neither key occurs in
    the file, and pymavlink reads the redacted SETUP_SIGNING (target, initial timestamp)."""
    tlog = tmp_path / "sitl.tlog"
    initial_ts = _now_10us()
    with _sitl(key_file, 1, tlog=tlog) as server, contextlib.ExitStack() as closing:
        veh = _signed_ground(server, 0, 1, closing)
        veh.mav.setup_signing_send(1, 1, list(NEW_KEY), initial_ts)
        # the SITL checks a whole read of frames before it handles any: a frame signed with
        # the new key may follow only once the key is installed
        _until(lambda: server.endpoints[0].signing.key == NEW_KEY, [veh], "the new key")
        veh.client.conn.setup_signing(NEW_KEY, sign_outgoing=True, link_id=1)
        _ask_param(veh, 1, [veh], "an answer signed with the new key")  # pymavlink verified it
    data = tlog.read_bytes()
    assert len(data) > 1000
    assert NEW_KEY not in data and KEY not in data, "a signing key is in the tlog"
    log = mavutil.mavlink_connection(str(tlog))
    found = []
    for _ in range(1_000_000):
        m = log.recv_match(type="SETUP_SIGNING")
        if m is None:
            break
        found.append(m)
    log.close()
    assert len(found) == 1
    assert (found[0].target_system, found[0].target_component) == (1, 1)
    assert found[0].initial_timestamp == initial_ts and list(found[0].secret_key) == [0] * 32
