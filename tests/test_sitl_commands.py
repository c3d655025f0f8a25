"""A scenario's `commands:` schedule in the SITL (issue 19): the SITL's command source puts each
plan on its radio as a ground station, with the link's faults (like the states, on a hash
stream of their own), agents' relays travel the same way, and what the radio sees is recorded
per vehicle (held: every frame delivered; applied: the first state carrying the plan)."""
from __future__ import annotations

import select
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from companion.commands import CommandEntry, PlanAssembler
from companion.config import replace
from companion.link.enums import MsgId
from companion.link.framing import split_datagram
from companion.link.msgdef import swarmdrop as sd
from companion.link.signing import Signing, write_key
from companion.link.wire import Codec
from companion.mission import Mission
from sim_bridge.scenario import load_scenario
from sim_bridge.sitl.commands import REPEAT_S, REPEATS, SOURCE_COMPID, SOURCE_SYSID, SitlCommands
from sim_bridge.sitl.medium import Medium
from sim_bridge.world.transport import LinkConfig

ROOT = Path(__file__).resolve().parents[1]
E_S = 1_767_225_600.0
CODEC = Codec(sd)
BUILD_STATE = CODEC.builder(MsgId.SWARMDROP_STATE)
SCHEDULE = (CommandEntry(t_s=30.0, kind="hold"), CommandEntry(t_s=36.0, kind="resume"))


def _state(k: int, t_s: float, plan_seq: int = 0, t_go_s: float = 0.0) -> bytes:
    values = BUILD_STATE(time_usec=int(round((E_S + t_s) * 1e6)), t_go_usec=int(round((E_S + t_go_s) * 1e6)) if t_go_s
                         else 0, x=0.0, y=0.0, z=-10.0, vx=0.0, vy=0.0, vz=0.0, q=(1.0, 0.0, 0.0, 0.0), phase=3, flags=3,
                         vehicle_id=k, plan_seq=plan_seq)
    return CODEC.encode_fields(MsgId.SWARMDROP_STATE, values, k + 1, 191, 0)


def _msgid(frame: bytes) -> int:
    return frame[7] | frame[8] << 8 | frame[9] << 16


class Fleet:
    """A radio and n agents' sockets (the radio sends vehicle k's copies to socket k)."""

    def __init__(self, n: int, link: LinkConfig, seed: int = 5):
        self.n = n
        self.socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
        for s in self.socks:
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
        self.radio = Medium(n, link, seed=seed, epoch_unix_s=E_S, bind=("127.0.0.1", 0),
                            agent_ports=[s.getsockname()[1] for s in self.socks])
        self.dest = ("127.0.0.1", self.radio.port)

    def send(self, k: int, frame: bytes) -> None:
        """Agent k sends one frame to the radio, and the radio takes it."""
        before = self.radio.states_in.sum() + self.radio.relays_in
        self.socks[k].sendto(frame, self.dest)
        deadline = time.monotonic() + 5
        while self.radio.states_in.sum() + self.radio.relays_in == before:
            assert time.monotonic() < deadline, "the radio took nothing"
            select.select([self.radio.fileno()], [], [], 0.1)
            self.radio.receive()

    def drain(self, k: int) -> list[bytes]:
        out = []
        while True:
            try:
                out += split_datagram(self.socks[k].recv(65536))[0]
            except BlockingIOError:
                return out

    def collect(self, done, timeout_s: float = 5.0) -> list[list[bytes]]:
        """Every socket's frames, read until done(frames by socket) holds (the radio's copies are
        on the loopback: waited for, with a deadline, not slept for)."""
        got: list[list[bytes]] = [[] for _ in range(self.n)]
        deadline = time.monotonic() + timeout_s
        while True:
            for k in range(self.n):
                got[k] += self.drain(k)
            if done(got):
                return got
            assert time.monotonic() < deadline, "the radio's copies did not all arrive"
            select.select(self.socks, [], [], 0.05)

    def close(self) -> None:
        for s in self.socks:
            s.close()
        self.radio.close()


@pytest.fixture()
def mission():
    cfg = load_scenario(ROOT / "configs" / "small_6.yaml")
    return cfg, Mission(cfg.mission)


def test_a_relay_goes_on_the_radio_with_its_faults_and_repeats_exactly():
    """An agent's relay is a radio broadcast: every other vehicle gets it at its swarm tick after
    the link's delay, never the relaying one; its fates are hashed (two radios of one seed lose
    the same copies) on a stream apart from the states'."""
    plan = CODEC.encode_fields(MsgId.SWARMDROP_PLAN, CODEC.builder(MsgId.SWARMDROP_PLAN)(seq=1, n_vehicles=40), 2, 191, 0)
    got = []
    for _ in range(2):
        f = Fleet(40, LinkConfig(kind="lossy", loss=0.2, delay_s=0.1))
        try:
            f.send(3, _state(3, 1.0))  # vehicle 3's sender is known to the radio by its state
            f.send(3, plan)
            assert f.radio.commands_forwarded == 0  # not forwarded at once
            f.radio.schedule(1.0, np.zeros((40, 3)))
            assert f.radio.deliver(1.05, np.ones(40, bool), tick_marker=False) == 0  # nothing before the delay
            f.radio.deliver(1.1, np.ones(40, bool), tick_marker=False)

            def plans_in(frames):
                return [sum(_msgid(x) == MsgId.SWARMDROP_PLAN for x in fr) for fr in frames]

            # every copy the radio counts as delivered arrives (counted apart from the states)
            heard = plans_in(f.collect(lambda fr: sum(plans_in(fr)) >= f.radio.plan_copies_delivered))
            got.append(heard)
            assert heard[3] == 0 and set(heard) <= {0, 1}
            assert 20 <= sum(heard) <= 37  # 39 receivers, 20 % of them lost
            assert f.radio.plan_copies_delivered == sum(heard)
            assert f.radio.copies_delivered == 39 - f.radio.copies_lost
        finally:
            f.close()
    assert got[0] == got[1]


def test_a_vehicle_cannot_flood_the_radio_with_relays():
    f = Fleet(2, LinkConfig())
    plan = CODEC.encode_fields(MsgId.SWARMDROP_PLAN, CODEC.builder(MsgId.SWARMDROP_PLAN)(seq=1, n_vehicles=2), 1, 191, 0)
    try:
        f.send(0, _state(0, 1.0))
        for _ in range(20):  # 18 frames a datagram: 360 frames at one simulated instant
            f.socks[0].sendto(plan * 18, f.dest)
            deadline = time.monotonic() + 5
            while f.radio.relays_in + f.radio.relays_dropped < 18 * (_ + 1):
                assert time.monotonic() < deadline
                select.select([f.radio.fileno()], [], [], 0.1)
                f.radio.receive()
        assert f.radio.relays_in == int(2 * f.radio.relay_frames_per_s)  # the burst, then dropped and counted
        assert f.radio.relays_dropped == 360 - f.radio.relays_in
        f.radio.schedule(0.5, np.zeros((2, 3)))  # half a simulated second later: half a second's worth again
        f.send(0, plan * 40)
        assert f.radio.relays_in == int(2.5 * f.radio.relay_frames_per_s)
    finally:
        f.close()


@pytest.mark.parametrize("signed", [False, True])
def test_the_sitl_issues_its_schedule_as_a_ground_station_and_records_it(mission, tmp_path, signed):
    """HOLD at 30 s: the source (told the transit start by the states) sends the plan 3 times
    0.3 s apart as sysid 255 / component 190 (signed when the SITL signs), every vehicle
    assembles the very plan the source made; held = when its last frame arrived, applied =
    the stamp of the vehicle's first state with plan_seq >= 1."""
    cfg, m = mission
    cfg = replace(cfg, commands=SCHEDULE)
    sign = check = None
    if signed:
        key = tmp_path / "key"
        write_key(key)
        from companion.link.signing import load_key

        k = load_key(key)
        sign = Signing("require", k, link_id=201, crc_extra=CODEC.crc_extra).sign
        check = [Signing("require", k, link_id=9, crc_extra=CODEC.crc_extra) for _ in range(6)]  # one per agent
    f = Fleet(6, LinkConfig(kind="lossy", delay_s=0.1))
    cmds = SitlCommands(cfg, m, f.radio, E_S, CODEC, sign)
    asm = [PlanAssembler.for_mission(m, E_S) for _ in range(6)]
    try:
        for k in range(6):
            f.send(k, _state(k, 20.0, t_go_s=24.0))
        t, sends, plans = 29.0, [], [None] * 6
        while t < 31.5:
            cmds.step(t)
            before = f.radio.plan_frames_in
            f.radio.schedule(t, np.zeros((6, 3)))
            if f.radio.plan_frames_in > before:
                sends.append(round(t, 2))
            f.radio.deliver(t, np.ones(6, bool), tick_marker=False)
            t = round(t + 0.01, 2)

        def commands_in(frames):
            return sum(_msgid(x) != MsgId.SWARMDROP_STATE for fr in frames for x in fr)

        frames = f.collect(lambda fr: commands_in(fr) >= f.radio.plan_copies_delivered)
        for k in range(6):
            for frame in frames[k]:
                if _msgid(frame) == MsgId.SWARMDROP_STATE:
                    continue
                if check is not None:
                    assert check[k].check(frame), "an unsigned, forged or replayed command frame"
                assert (frame[5], frame[6]) == (SOURCE_SYSID, SOURCE_COMPID)
                plans[k] = asm[k].feed(CODEC.decode(frame)) or plans[k]
        assert sends == [30.0 + i * REPEAT_S for i in range(REPEATS)]
        assert cmds.source.t_go_s == pytest.approx(24.0)
        assert all(p == cmds.source.plans[1] for p in plans)  # the source's plan, bit for bit
        rec = cmds.records[0]
        assert (rec.seq, rec.kind, rec.issued_s, rec.effective_s) == (1, "hold", 30.0, pytest.approx(30.3))
        np.testing.assert_allclose(rec.held_s, 30.1)  # the link's delay
        assert np.isnan(rec.applied_s).all() and not cmds.settled()
        f.send(2, _state(2, 30.32, plan_seq=1))
        f.send(2, _state(2, 30.42, plan_seq=1))
        assert rec.applied_s[2] == pytest.approx(30.32) and np.isnan(rec.applied_s[[0, 1, 3, 4, 5]]).all()
        assert not cmds.settled(np.arange(6) == 2)  # RESUME is still to come
        cmds.step(36.0)
        for k in range(6):
            f.send(k, _state(k, 37.02, plan_seq=2))  # a vehicle that shows plan 2 has applied plan 1 too
        assert cmds.settled() and rec.applied_s[2] == pytest.approx(30.32)
        np.testing.assert_allclose(rec.applied_s[[0, 1, 3, 4, 5]], 37.02)
        np.testing.assert_allclose(cmds.records[1].applied_s, 37.02)
    finally:
        f.close()


def test_a_refused_command_is_recorded_with_its_reason(mission):
    cfg, m = mission
    cfg = replace(cfg, commands=(CommandEntry(t_s=30.0, kind="resume"),))
    f = Fleet(6, LinkConfig())
    try:
        cmds = SitlCommands(cfg, m, f.radio, E_S, CODEC)
        cmds.step(30.0)
        rec = cmds.records[0]
        assert rec.seq == 0 and "not held" in rec.refused and f.radio.plan_frames_in == 0
        assert cmds.settled()
    finally:
        f.close()
