"""Who an agent's `udpin` autopilot link answers with signing off (UdpLink peer_ids).

An attacker with pymavlink sends to the companion's autopilot port. Before, the link
answered the sender of the last frame that decoded, so one stranger's frame took the
agent's setpoints (the autopilot then failed safe: "offboard signal lost"). Now only
frames of the autopilot's (sysid, compid) claim the link, the first such sender keeps it
while it talks, frames claiming its ids from elsewhere are dropped meanwhile (a spoofed
autopilot cannot feed the planner), and another address takes over only after the one it
has is silent for reclaim_after_s (an autopilot or router restarted on a new port).

Everything binds 127.0.0.1; waiting is select() with a deadline; the link's clock is a
fake, so "silent for 2 s" takes no time.
"""
from __future__ import annotations

import os
import select
import socket
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.endpoints import MavEndpoint, UdpLink, open_link  # noqa: E402
from companion.link.framing import frame_ids  # noqa: E402
from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.wire import Codec  # noqa: E402

AUTOPILOT = (1, 1)
DEADLINE_S = 3.0


class Clock:
    """A monotonic clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.t_s = 100.0

    def __call__(self) -> float:
        return self.t_s


class Peer:
    """A UDP socket on 127.0.0.1 that sends MAVLink as (sysid, compid)."""

    def __init__(self, sysid: int, compid: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    @property
    def addr(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def heartbeat(self, port: int) -> None:
        self.sock.sendto(bytes(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3).pack(self.mav)),
                         ("127.0.0.1", port))

    def position(self, port: int, x_m: float) -> None:
        msg = mavlink.MAVLink_local_position_ned_message(1000, x_m, 0.0, -5.0, 0.0, 0.0, 0.0)
        self.sock.sendto(bytes(msg.pack(self.mav)), ("127.0.0.1", port))

    def received(self) -> int:
        """Datagrams waiting for this socket (read and counted)."""
        n = 0
        while True:
            try:
                self.sock.recvfrom(65535)
            except BlockingIOError:
                return n
            n += 1

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def parts():
    clock = Clock()
    codec = Codec(mavlink, swarmdrop)
    ep = MavEndpoint(UdpLink(("127.0.0.1", 0), peer_ids=AUTOPILOT, clock=clock), codec, 1, 191)
    ap, gcs, spoof = Peer(*AUTOPILOT), Peer(255, 190), Peer(*AUTOPILOT)
    yield clock, ep, ap, gcs, spoof
    for p in (ap, gcs, spoof):
        p.close()
    ep.close()


def _read(ep: MavEndpoint, n: int) -> list:
    """Poll until n more frames were handled (accepted or dropped), at most DEADLINE_S."""
    link = ep.link
    target = link.frames_in + n
    got: list = []
    deadline = time.monotonic() + DEADLINE_S
    while link.frames_in < target:
        left = deadline - time.monotonic()
        assert left > 0, f"only {link.frames_in - target + n} of {n} frames arrived"
        select.select([link.fileno()], [], [], left)
        got += ep.poll()
    return got


def _answered(ep: MavEndpoint, *peers: Peer) -> list[int]:
    """Send one HEARTBEAT from the endpoint; how many datagrams each peer got."""
    ep.queue(mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 0, 4))
    ep.flush()
    deadline = time.monotonic() + DEADLINE_S
    counts = [0] * len(peers)
    while sum(counts) == 0 and time.monotonic() < deadline:
        select.select([p.sock for p in peers], [], [], deadline - time.monotonic())
        counts = [c + p.received() for c, p in zip(counts, peers)]
    return counts


def test_frame_ids_reads_mavlink1_and_2_headers():
    mav = mavlink.MAVLink(None, srcSystem=42, srcComponent=7)
    msg = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3)
    assert frame_ids(bytes(msg.pack(mav))) == (42, 7)
    assert frame_ids(bytes(msg.pack(mav, force_mavlink1=True))) == (42, 7)
    assert frame_ids(b"\xfd\x00\x00") is None


def test_only_the_autopilot_claims_the_link(parts):
    """A ground station's frame on the port first: received, but the link answers nobody;
    the autopilot's HEARTBEAT then claims it."""
    clock, ep, ap, gcs, _ = parts
    gcs.heartbeat(ep.link.local_port)
    assert len(_read(ep, 1)) == 1  # let through (VehicleLink ignores other systems)
    assert ep.link.remote is None
    ap.heartbeat(ep.link.local_port)
    _read(ep, 1)
    assert ep.link.remote == ap.addr
    assert _answered(ep, ap, gcs) == [1, 0]


def test_a_stranger_takes_neither_setpoints_nor_telemetry(parts):
    """While the autopilot talks: another system's frames move nothing; frames spoofing the
    autopilot's ids from another address are dropped and counted; setpoints keep going to
    the autopilot. Fails on the last-sender rule (the stranger gets the reply)."""
    clock, ep, ap, gcs, spoof = parts
    port = ep.link.local_port
    ap.heartbeat(port)
    _read(ep, 1)
    for step in range(5):
        clock.t_s += 0.5  # the autopilot keeps talking every 0.5 s (below reclaim_after_s)
        ap.position(port, 1.0)
        gcs.heartbeat(port)
        spoof.position(port, 99.0)
        msgs = _read(ep, 3)
        xs = [m.x for m, _ in msgs if m.get_type() == "LOCAL_POSITION_NED"]
        assert xs == [1.0], "a spoofed position reached the agent"
        assert ep.link.remote == ap.addr
    assert ep.link.stranger_drops == 5
    assert _answered(ep, ap, gcs, spoof) == [1, 0, 0]


def test_another_address_takes_over_only_after_the_autopilot_falls_silent(parts):
    """An autopilot restarted on a new port: its frames are dropped while the old address
    was heard within reclaim_after_s (2 s), and claim the link after that."""
    clock, ep, ap, _, moved = parts
    port = ep.link.local_port
    ap.heartbeat(port)
    _read(ep, 1)
    clock.t_s += 1.9
    moved.heartbeat(port)
    assert _read(ep, 1) == [] and ep.link.remote == ap.addr
    clock.t_s += 0.2  # 2.1 s since the old address last spoke
    moved.heartbeat(port)
    assert len(_read(ep, 1)) == 1
    assert ep.link.remote == moved.addr
    ap.heartbeat(port)  # the old one is now the stranger
    assert _read(ep, 1) == []
    assert _answered(ep, ap, moved) == [0, 1]


def test_open_link_gives_udpin_the_rule_and_udpout_none():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    link = open_link(f"udpin://127.0.0.1:{port}", peer_ids=AUTOPILOT)
    out = open_link("udpout://127.0.0.1:14550")
    try:
        assert isinstance(link, UdpLink) and link.peer_ids == AUTOPILOT and link.first_contact_only
        assert isinstance(out, UdpLink) and out.peer_ids is None and out.remote == ("127.0.0.1", 14550)
    finally:
        link.close()
        out.close()


@pytest.mark.parametrize("event_loop", ["asyncio", "uvloop"])
def test_one_datagram_a_read_and_the_loop_calls_again_while_more_wait(event_loop):
    """The agent reads one datagram each time its autopilot socket is readable (TickPath:
    no last read that finds the socket empty, a syscall a tick): the event loops it flies on
    call a reader again while data waits (level-triggered), so three datagrams queued at
    once are three calls, in order, and nothing is left."""
    import asyncio

    from companion.node.cli import event_loop_factory  # (what `swarmdrop agent --event-loop` flies on)

    link = UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=True)
    peer = Peer(*AUTOPILOT)
    try:
        for _ in range(3):
            peer.heartbeat(link.local_port)
        assert select.select([link.fileno()], [], [], DEADLINE_S)[0]  # (loopback delivers on send: all three wait)
        reads: list[int] = []

        async def body() -> None:
            loop = asyncio.get_running_loop()
            done = loop.create_future()

            def readable() -> None:
                reads.append(len(link.recv(1)))
                if len(reads) == 3:
                    done.set_result(None)

            loop.add_reader(link.fileno(), readable)
            try:
                await asyncio.wait_for(done, DEADLINE_S)
            finally:
                loop.remove_reader(link.fileno())

        factory, _ = event_loop_factory(event_loop)
        with asyncio.Runner(loop_factory=factory) as runner:
            runner.run(body())
        assert reads == [1, 1, 1] and link.frames_in == 3
        assert link.recv(1) == [] and link.recv() == []  # nothing left
    finally:
        link.close()
        peer.sock.close()
