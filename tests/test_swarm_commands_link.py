"""Swarm plans on the agent's swarm link (issue 19): SWARMDROP_PLAN + SLOTS frames from a
ground station or a relaying agent become the plan the agent flies; under --signing require
only signed plans count (unsigned, forged and replayed frames are dropped and counted); the
agent relays the newest plan it holds, byte for byte what the source sent."""
import select
import time

import numpy as np
import pytest

from companion.commands import CommandSource, PlanAssembler, PlanBook, plan_messages
from companion.control.shapes import FormationSpec
from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.msgdef import swarmdrop as md
from companion.link.signing import Signing
from companion.link.wire import Codec
from companion.mission import Mission, MissionConfig
from companion.node.swarmlink import SwarmLink, view_for

EPOCH_UNIX_S = 1_790_000_000.0
KEY = bytes(range(32))
WRONG_KEY = bytes(32)


def _mission(n=4):
    return Mission(MissionConfig(n_vehicles=n, formation={"radius_m": 6.0},
                                 waypoints_ned_m=((0.0, 0.0, -10.0), (100.0, 0.0, -10.0))))


def _endpoint(sysid: int, signing: Signing | None = None) -> MavEndpoint:
    codec = Codec(md)
    if signing is not None:
        signing.crc_extra = codec.crc_extra
    return MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), codec, sysid, 191,
                       signing=signing)


class _Rx:
    """One agent's swarm link with a plan assembler; plans heard go to `got`."""

    def __init__(self, m: Mission, signing: Signing | None = None):
        self.got: list = []
        self.ep = _endpoint(1, signing)
        self.link = SwarmLink(self.ep, 0, [], view_for(m.n), None, PlanAssembler.for_mission(m, 0.0), self.got.append)
        self.link.set_epoch(EPOCH_UNIX_S)
        self.link.now_us = int(EPOCH_UNIX_S * 1e6) + 3_600_000_000  # (the tick path's clock)
        self.addr = ("127.0.0.1", self.ep.link.local_port)

    def poll_until(self, cond, timeout_s: float = 3.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not cond():
            left = deadline - time.monotonic()
            assert left > 0, "timed out waiting for the swarm socket"
            select.select([self.ep.link.fileno()], [], [], min(left, 0.1))
            self.link.poll()


def _frames(ep: MavEndpoint, plan, dest, sysid=255, reverse=False) -> None:
    msgs = plan_messages(plan, EPOCH_UNIX_S, ep.codec)
    for msgid, values in (msgs[::-1] if reverse else msgs):
        ep.queue_fields(msgid, values, dest, sysid=sysid, compid=190)
    ep.flush()


@pytest.mark.timeout(30)
def test_a_plan_from_the_ground_station_reaches_the_agent_in_any_order_once():
    m = _mission()
    plan = CommandSource(m).formation(5.0, FormationSpec(shape="line", spacing_m=4.0))
    rx, tx = _Rx(m), _endpoint(255)
    try:
        _frames(tx, plan, rx.addr, reverse=True)  # SLOTS before PLAN
        rx.poll_until(lambda: len(rx.got) == 1)
        assert rx.got[0] == plan  # the wire carries the plan exactly (it was quantised by its source)
        _frames(tx, plan, rx.addr)  # a relayed copy: a duplicate, not a second plan
        rx.poll_until(lambda: rx.link.plan_frames_in == 4)
        assert len(rx.got) == 1 and rx.link.plans_in == 1
    finally:
        rx.ep.close()
        tx.close()


@pytest.mark.timeout(30)
def test_under_signing_require_only_signed_plans_are_obeyed():
    """Unsigned, forged (another key) and replayed plan frames never make a plan; each is
    counted by the signing layer; the same plan signed with the fleet key does."""
    m = _mission()
    src = CommandSource(m)
    plan = src.hold(5.0)
    sg = Signing("require", KEY, link_id=1)
    rx = _Rx(m, sg)
    unsigned, forged = _endpoint(255), _endpoint(255, Signing("require", WRONG_KEY, link_id=2))
    good = _endpoint(255, Signing("require", KEY, link_id=3))
    try:
        _frames(unsigned, plan, rx.addr)
        _frames(forged, plan, rx.addr)
        rx.poll_until(lambda: sg.counters.unsigned + sg.counters.bad_signature >= 4)
        assert rx.got == [] and rx.link.plan_frames_in == 0
        # the good frames, captured on their way, and replayed after the real ones
        msgs = plan_messages(plan, EPOCH_UNIX_S, good.codec)
        wire = [good.codec.encode_fields(mid, vals, 255, 190, k) for k, (mid, vals) in enumerate(msgs)]
        signed = [good.signing.sign(f) for f in wire]
        for f in signed:
            good.link.send(f, rx.addr)
        rx.poll_until(lambda: len(rx.got) == 1)
        assert rx.got[0] == plan
        for f in signed:
            good.link.send(f, rx.addr)
        rx.poll_until(lambda: sg.counters.replayed >= 2)
        assert len(rx.got) == 1 and rx.link.plan_frames_in == 2
    finally:
        for e in (rx.ep, unsigned, forged, good):
            e.close()


@pytest.mark.timeout(30)
def test_an_agent_relays_the_plan_it_holds_byte_for_byte():
    """What a relay sends decodes to the same plan at another agent (a vehicle out of the
    console's range gets it through its neighbours)."""
    m = _mission()
    plan = CommandSource(m).hold(5.0)
    a, b = _Rx(m), _Rx(m)
    a.link.peers = [b.addr]
    tx = _endpoint(255)
    try:
        _frames(tx, plan, a.addr)
        a.poll_until(lambda: len(a.got) == 1)
        book = PlanBook(m, 1)
        book.receive([0], a.got[0])
        a.link.relay(book.relay_messages(0, EPOCH_UNIX_S, a.ep.codec))
        a.ep.flush()
        b.poll_until(lambda: len(b.got) == 1)
        assert b.got[0] == plan and a.link.plan_frames_out == 2
        assert np.array_equal(book.newest_seq, [plan.seq])
    finally:
        for e in (a.ep, b.ep, tx):
            e.close()
