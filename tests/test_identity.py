"""Vehicle identity (issue 16): one vehicle id, one autopilot, one sender.

The agent flies only the autopilot whose sysid the mission assigns to its vehicle id
(or an explicit --target-sysid), picks it out of several on one link, and says what it
waits for; a state that claims the receiver's own id from someone else is an identity
conflict (counted, logged, flagged, avoided); the SITL's radio refuses a second sender
of one vehicle id.
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import select
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from lean_agent import lean_agent_cmd  # noqa: E402
from pymavlink import mavutil  # noqa: E402

from companion.agent import Agent, OwnState, Phase  # noqa: E402
from companion.link.endpoints import MavEndpoint, UdpLink  # noqa: E402
from companion.link.msgdef import swarmdrop as md  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from companion.mission import Mission  # noqa: E402
from companion.node.config import load_mission_file  # noqa: E402
from companion.node.swarmlink import SwarmLink, view_for  # noqa: E402
from companion.swarm import FLAG_ID_CONFLICT, FLAG_OWN_VALID  # noqa: E402
from sim_bridge.sitl.testing import free_udp_base_port  # noqa: E402
from sim_bridge.world.transport import LinkConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GROUND4 = ROOT / "configs" / "ground_4.yaml"
EPOCH_UNIX_S = 1767225600.0
E_US = int(EPOCH_UNIX_S * 1e6)
Q_LEVEL = [1.0, 0.0, 0.0, 0.0]


def agent_cmd(*args: str) -> list[str]:
    """The agent as the onboard install runs it: none of the extras' packages importable."""
    return lean_agent_cmd(*args)


def _state(t_us: int, vehicle_id: int, pos, vel=(0.0, 0.0, 0.0), phase=int(Phase.ASSEMBLE), flags=FLAG_OWN_VALID):
    return [t_us, 0, *map(float, pos), *map(float, vel), Q_LEVEL, phase, flags, vehicle_id]


def _endpoint(sysid: int) -> MavEndpoint:
    return MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), Codec(md), sysid, 191)


def _send_state(ep: MavEndpoint, dest, sysid: int, *args, **kw) -> None:
    ep.queue_fields(md.MAVLINK_MSG_ID_SWARMDROP_STATE, _state(*args, **kw), dest, sysid=sysid)
    ep.flush()


def _poll_until(link: SwarmLink, cond, timeout_s: float = 3.0) -> None:
    """Poll the swarm socket (select with a deadline) until cond() holds."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        left = deadline - time.monotonic()
        assert left > 0, "timed out waiting for the swarm socket"
        select.select([link.ep.link.fileno()], [], [], min(left, 0.1))
        link.poll()


def _own(pos, t):
    return OwnState(np.array([pos], float), np.zeros((1, 3)), np.array([Q_LEVEL]), np.array([t]), np.array([True]),
                    np.array([True]))


# ---------------------------------------------------------------------------- swarm link: conflicts
@pytest.mark.timeout(30)
def test_a_state_claiming_the_receivers_id_is_a_conflict_counted_logged_flagged_and_repelled(caplog):
    """Two vehicles fly as vehicle 0: the forged one (another sysid, another address) is an
    intruder. The receiver counts and logs it (once, rate-limited), flags its own state,
    reports it in its statistics, and its commanded acceleration points away from it."""
    mf = load_mission_file(GROUND4)
    mission = Mission(mf.mission)
    own_id, t = 0, 20.0
    slot = mission.slot_ned_m(-1.0)[own_id]
    views = {name: view_for(mission.n) for name in ("quiet", "conflict")}
    agents = {name: Agent(mission, np.array([own_id])) for name in views}
    for a in agents.values():
        a.phase[:] = Phase.ASSEMBLE
    rx = _endpoint(own_id + 1)
    link = SwarmLink(rx, own_id, [], views["conflict"])
    link.set_epoch(EPOCH_UNIX_S)
    link.now_us = E_US + 3_600_000_000  # (the tick path's clock: every state here is of the past)
    forger = _endpoint(2)
    intruder = slot + np.array([1.5, 0.0, 0.0])  # 1.5 m north of the own vehicle, inside the APF influence
    caplog.set_level(logging.INFO, logger="swarmdrop.swarm")
    try:
        for k in range(5):  # five states within the log period: one log line
            _send_state(forger, ("127.0.0.1", rx.link.local_port), 2, E_US + int((t - 0.4 + 0.1 * k) * 1e6), own_id,
                        intruder)
        _poll_until(link, lambda: link.conflicts == 5)
    finally:
        forger.close()
        rx.close()
    assert link.states_in == 0 and link.rejected == 0
    assert np.isnan(views["conflict"].stamp_s[0]).all()  # never stored as a neighbour, nor as ourselves
    lines = [r for r in caplog.records if "identity conflict" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.ERROR
    assert "sysid 2 at 127.0.0.1:" in lines[0].getMessage() and "id 0" in lines[0].getMessage()
    ident = link.identity()
    assert ident["conflicts"] == 5 and ident["conflict_sources"] == 1 and ident["last_conflict"].startswith("sysid 2")

    out = {name: agents[name].step(t, _own(slot, t), views[name]) for name in views}
    du = out["conflict"].setpoint.acc_ned_mps2[0] - out["quiet"].setpoint.acc_ned_mps2[0]
    away = (slot - intruder) / np.linalg.norm(slot - intruder)
    # pushed straight south (to the float32 rounding of the wire's positions)
    assert np.dot(du, away) > 0.5 and np.linalg.norm(du - np.dot(du, away) * away) < 1e-6
    assert out["conflict"].published.flags[0] & FLAG_ID_CONFLICT
    assert not out["quiet"].published.flags[0] & FLAG_ID_CONFLICT
    # Aged like a neighbour: silent for 2 s it is a ghost column there, still avoided; after
    # peer_timeout_s the flag goes, the obstacle stays (a silent vehicle is avoided for good).
    t2 = t + 2.0
    out2 = {name: agents[name].step(t2, _own(slot, t2), views[name]) for name in views}
    du2 = out2["conflict"].setpoint.acc_ned_mps2[0] - out2["quiet"].setpoint.acc_ned_mps2[0]
    assert np.dot(du2, away) > 0.5
    t3 = t + mission.cfg.swarm.peer_timeout_s + 1.0
    out3 = agents["conflict"].step(t3, _own(slot, t3), views["conflict"])
    assert not out3.published.flags[0] & FLAG_ID_CONFLICT


@pytest.mark.timeout(30)
def test_own_echo_is_not_a_conflict_but_the_same_sysid_elsewhere_is():
    """Our own state sent back (a peer or medium echoing it) is ignored; a state with our id
    and our sysid (two agents both started as vehicle 0) but another position is a conflict."""
    n, own_id = 4, 0
    view = view_for(n)
    rx = _endpoint(own_id + 1)
    me = ("127.0.0.1", rx.link.local_port)
    link = SwarmLink(rx, own_id, [me], view)  # we are our own peer: every publication comes back
    link.set_epoch(EPOCH_UNIX_S)
    link.now_us = E_US + 3_600_000_000  # (the tick path's clock: every state here is of the past)
    mission = Mission(load_mission_file(GROUND4).mission)
    agent = Agent(mission, np.array([own_id]))
    twin = _endpoint(own_id + 1)
    try:
        for k in range(3):
            t = 1.0 + 0.1 * k
            link.publish(agent.step(t, _own([1.0, 2.0, -3.0], t), view).published)
            rx.flush()
        _poll_until(link, lambda: link.own_echoes == 3)
        assert link.conflicts == 0 and view.intruders is None
        # the same stamp (agents on one clock publish at the same instants), another position
        _send_state(twin, me, own_id + 1, E_US + 1_200_000, own_id, [4.0, 2.0, -3.0])
        _poll_until(link, lambda: link.conflicts == 1)
        assert link.own_echoes == 3 and view.intruders is not None
    finally:
        twin.close()
        rx.close()


# ---------------------------------------------------------------------------- SITL radio
def test_sitl_radio_refuses_a_second_sender_of_one_vehicle_id():
    """Two senders claim vehicle 0: the first owns the id; the later one is refused, counted,
    never forwarded as vehicle 0 to the others; only vehicle 0's own agent hears it."""
    from sim_bridge.sitl.medium import Medium

    n = 3
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n + 1)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
    first, agent1, agent2, second = socks
    ports = [s.getsockname()[1] for s in socks[:n]]
    radio = Medium(n, LinkConfig(), seed=1, epoch_unix_s=EPOCH_UNIX_S, bind=("127.0.0.1", 0), agent_ports=ports)
    dest = ("127.0.0.1", radio.port)

    def frame(stamp_us: int, x: float) -> bytes:
        return md.MAVLink_swarmdrop_state_message(stamp_us, 0, x, 0, -5, 0, 0, 0, Q_LEVEL, 2, 2, 0).pack(
            md.MAVLink(None, srcSystem=1, srcComponent=191))

    def received(sock) -> list:
        out = []
        while True:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                return out
            mav = md.MAVLink(None)
            out += [m for m in (mav.parse_buffer(data) or []) if m.get_type() == "SWARMDROP_STATE"]

    try:
        first.sendto(frame(E_US + 1_000_000, 1.0), dest)
        second.sendto(frame(E_US + 1_000_000, 7.0), dest)
        second.sendto(frame(E_US + 1_100_000, 7.0), dest)
        deadline = time.monotonic() + 5.0
        while int(radio.states_in[0]) + radio.id_conflicts < 3 and time.monotonic() < deadline:
            radio.receive()  # non-blocking: polled with a deadline until all three datagrams are in
        assert radio.states_in.tolist() == [1, 0, 0] and radio.id_conflicts == 2 and radio.conflict_ids == {0}
        assert radio.src[0] == first.getsockname()
        radio.schedule(1.0, np.zeros((n, 3)))
        radio.deliver(1.0, np.ones(n, bool), tick_marker=False)
        deadline = time.monotonic() + 5.0
        got: dict[int, list] = {0: [], 1: [], 2: []}
        while (len(got[0]) < 2 or len(got[1]) < 1 or len(got[2]) < 1) and time.monotonic() < deadline:
            select.select(socks[:n], [], [], 0.1)
            for k in range(n):
                got[k] += received(socks[k])
        assert [m.x for m in got[1]] == [1.0] and [m.x for m in got[2]] == [1.0]  # the others: the owner only
        assert sorted(m.x for m in got[0]) == [7.0, 7.0]  # the owner hears the impostor
        assert radio.stats(1.0).foreign_frames == 2
    finally:
        for s in socks:
            s.close()
        radio.close()


def test_a_signed_sitl_radio_lets_no_unsigned_stranger_claim_a_vehicle_id():
    """Under signing the radio checks what it takes: an unsigned state sent first for vehicle 0
    (a stranger) is dropped and counted, claims nothing, and the real agent's signed states own
    the id and reach the others. (The radio used to give the id to the first sender, signed or
    not, and refused the real vehicle's states as an identity conflict: it vanished from the
    swarm.) A replayed signed state is dropped too."""
    from companion.link.signing import Signing
    from sim_bridge.sitl.medium import Medium

    n, key = 3, bytes(range(32))
    codec = Codec(md)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n + 1)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
    owner, agent1, agent2, stranger = socks
    radio = Medium(n, LinkConfig(), seed=1, epoch_unix_s=EPOCH_UNIX_S, bind=("127.0.0.1", 0),
                   agent_ports=[s.getsockname()[1] for s in socks[:n]],
                   signing=Signing("require", key, link_id=200, crc_extra=codec.crc_extra))
    signer = Signing("require", key, link_id=1, crc_extra=codec.crc_extra)
    dest = ("127.0.0.1", radio.port)

    def frame(stamp_us: int, x: float) -> bytes:
        return md.MAVLink_swarmdrop_state_message(stamp_us, 0, x, 0, -5, 0, 0, 0, Q_LEVEL, 2, 2, 0).pack(
            md.MAVLink(None, srcSystem=1, srcComponent=191))

    try:
        stranger.sendto(frame(E_US + 1_000_000, 7.0), dest)  # first, unsigned
        signed = signer.sign(frame(E_US + 1_000_000, 1.0))
        owner.sendto(signed, dest)
        owner.sendto(signed, dest)  # a replay of it
        deadline = time.monotonic() + 5.0
        while int(radio.states_in[0]) + radio.unverified < 3 and time.monotonic() < deadline:
            radio.receive()  # non-blocking: polled with a deadline until all three datagrams are in
        assert radio.unverified == 2 and radio.states_in.tolist() == [1, 0, 0] and radio.id_conflicts == 0
        assert radio.src[0] == owner.getsockname()
        radio.schedule(1.0, np.zeros((n, 3)))
        radio.deliver(1.0, np.ones(n, bool), tick_marker=False)
        got = {}
        deadline = time.monotonic() + 5.0
        while len(got) < 2 and time.monotonic() < deadline:
            select.select([agent1, agent2], [], [], 0.1)
            for k, sock in ((1, agent1), (2, agent2)):
                try:
                    got[k] = sock.recv(65536)
                except BlockingIOError:
                    pass
        assert got == {1: signed, 2: signed}  # the owner's state, unchanged, signature and all
    finally:
        for s in socks:
            s.close()
        radio.close()


# ---------------------------------------------------------------------------- the agent says what it waits for
@pytest.mark.timeout(60)
def test_waiting_for_an_autopilot_is_logged_with_the_url_and_the_error_names_it(tmp_path):
    url = f"udpin://127.0.0.1:{free_udp_base_port(1)}"
    log = tmp_path / "agent.log"
    proc = subprocess.run(agent_cmd("--vehicle-id", "0", "--mission", str(GROUND4), "--autopilot", url,
                                    "--setup-timeout", "4", "--log-file", str(log), "--no-stderr-log"),
                          cwd=ROOT, capture_output=True, text=True, timeout=45)
    assert proc.returncode == 3, log.read_text()
    text = log.read_text()
    assert f"waiting for HEARTBEAT of autopilot sysid 1 on {url}" in text  # at once
    assert re.search(rf"INFO .*waiting for HEARTBEAT on {re.escape(url)}: [34] s", text), text  # then every 3 s
    err = [ln for ln in text.splitlines() if " ERROR " in ln]
    assert len(err) == 1 and url in err[0] and "HEARTBEAT" in err[0] and "sysid 1" in err[0], text


# ---------------------------------------------------------------------------- SITL: two agents, one id
def _sitl(tmp: Path, vehicles: int, ap_base: int, swarm_base: int | None = None, radio_port: int | None = None,
          gcs_port: int | None = None):
    from sim_bridge.sitl.background import BackgroundSitl
    from sim_bridge.sitl.config import EndpointConfig, MediumConfig, TimeConfig, sitl_config

    mcfg = load_mission_file(GROUND4).mission
    assert mcfg.origin is not None
    ep = EndpointConfig(remote_host="127.0.0.1", remote_base_port=ap_base, bind_host="127.0.0.1", local_base_port=0,
                        gcs_enabled=gcs_port is not None, gcs_remote_port=gcs_port or 14550)
    medium = MediumConfig(enabled=True, port=radio_port, agent_base_port=swarm_base) if radio_port else MediumConfig()
    cfg = sitl_config(vehicles, seed=4, launch="ground", origin=mcfg.origin, dialect="px4", endpoints=ep,
                      time=TimeConfig(epoch_unix_s=EPOCH_UNIX_S), medium=medium, tlog_path=str(tmp / "sitl.tlog"))
    return BackgroundSitl(cfg)


def _stop(*procs: subprocess.Popen | None) -> None:
    for p in procs:
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(10)


def _watch(server, cond, timeout_s: float, what: str, never_armed: list[int], logs: list[Path]) -> None:
    """Poll cond() with a deadline; meanwhile the vehicles never_armed must stay disarmed."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        armed = [k for k in never_armed if server.autopilots[k].armed]
        assert not armed, f"vehicle {armed} armed"
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}:\n" + "\n".join(p.read_text() for p in logs if p.exists()))
        time.sleep(0.05)  # polling a condition with a deadline


@pytest.mark.timeout(120)
def test_two_agents_with_one_vehicle_id_the_wrong_autopilot_is_refused_before_arming(tmp_path):
    """The issue's case: two `swarmdrop agent --vehicle-id 0` on SITL vehicles sysid 1 and 2
    (configs/ground_4.yaml). The one on sysid 2 refuses (exit 7, the message names both
    sysids and the link) and that vehicle never arms; the one on sysid 1 takes off."""
    base = free_udp_base_port(4 + 4 + 1)
    ap_base, swarm_base, radio = base, base + 4, base + 8
    bg = _sitl(tmp_path, 4, ap_base, swarm_base, radio)
    server = bg.start()
    logs = [tmp_path / "agent_a.log", tmp_path / "agent_b.log"]
    agents: list[subprocess.Popen] = []
    try:
        for k, log in enumerate(logs):
            agents.append(subprocess.Popen(
                agent_cmd("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{ap_base + k}", "--mission",
                          str(GROUND4), "--swarm-bind", f"127.0.0.1:{swarm_base + k}", "--swarm-peer",
                          f"127.0.0.1:{radio}", "--setup-timeout", "30", "--log-file", str(log), "--no-stderr-log",
                          "--set-loss-action", "hold",  # stock PX4 COM_OBL_RC_ACT 0 drifts: refused
                          "--stats", str(tmp_path / f"agent_{k}.json")),
                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        a, b = agents
        _watch(server, lambda: b.poll() is not None, 60, "agent B to refuse", [1], logs)
        assert b.returncode == 7, logs[1].read_text()
        err = [ln for ln in logs[1].read_text().splitlines() if " ERROR " in ln]
        assert len(err) == 1, logs[1].read_text()
        assert f"udpin://127.0.0.1:{ap_base + 1} is sysid 2" in err[0] and "vehicle 0" in err[0] \
            and "sysid 1" in err[0] and "--target-sysid" in err[0], err[0]
        assert "exit 7 (IDENTITY)" in logs[1].read_text()
        stats_b = json.loads((tmp_path / "agent_1.json").read_text())
        assert stats_b["identity"]["other_autopilots"].keys() == {"2"} and stats_b["autopilot"]["dialect"] is None
        _watch(server, lambda: server.autopilots[0].armed and server.state.pos_ned_m[0, 2] < -1.0, 60,
               "agent A to take off", [1], logs)
        assert a.poll() is None
        _stop(a)
        assert a.returncode == 0, logs[0].read_text()
    finally:
        _stop(*agents)
        bg.stop()
    # nothing was ever commanded to vehicle sysid 2
    conn = mavutil.mavlink_connection(str(tmp_path / "sitl.tlog"))
    to_2 = 0
    while (m := conn.recv_match(type=["COMMAND_LONG", "SET_POSITION_TARGET_LOCAL_NED", "PARAM_SET"])) is not None:
        to_2 += m.target_system == 2
    conn.close()
    assert to_2 == 0


@pytest.mark.timeout(120)
def test_on_a_link_with_several_autopilots_the_agent_flies_its_own_not_the_first_heard(tmp_path):
    """A router: the SITL's shared GCS port carries vehicles sysid 1, 2 and 3. The agent of
    vehicle 1 sets up, arms and takes off sysid 2; the others are ignored, never armed."""
    base = free_udp_base_port(4)
    gcs = base + 3
    bg = _sitl(tmp_path, 3, base, gcs_port=gcs)
    server = bg.start()
    log = tmp_path / "agent.log"
    stats = tmp_path / "agent.json"
    agent = subprocess.Popen(
        agent_cmd("--vehicle-id", "1", "--autopilot", f"udpin://127.0.0.1:{gcs}", "--mission", str(GROUND4),
                  "--setup-timeout", "30", "--log-file", str(log), "--no-stderr-log", "--stats", str(stats),
                  "--set-loss-action", "hold"),
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _watch(server, lambda: server.autopilots[1].armed and server.state.pos_ned_m[1, 2] < -1.0, 60,
               "vehicle sysid 2 to take off", [0, 2], [log])
        assert agent.poll() is None
        _stop(agent)
        assert agent.returncode == 0, log.read_text()
    finally:
        _stop(agent)
        bg.stop()
    ident = json.loads(stats.read_text())["identity"]
    assert ident["autopilot_sysid"] == 2 and not ident["override"]
    assert set(ident["other_autopilots"]) == {"1", "3"}
    assert "autopilot sysid 2 on udpin" in log.read_text()
    assert not math.isnan(json.loads(stats.read_text())["setup_s"])
