"""`swarmdrop console` without a browser: the frame protocol, the live model's rules for hostile
input, replay, the web server's guards, commands on the wire, the radio's monitors and plans,
the live stream of a headless run, and the import path (tests/test_console_browser.py drives
the page in Chromium)."""
from __future__ import annotations

import asyncio
import json
import math
import select
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.commands import URGENT_LEAD_S
from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.enums import MsgId
from companion.link.msgdef import swarmdrop as sd
from companion.link.signing import Signing, write_key
from companion.link.wire import Codec
from swarmdrop.console.live import SIM_BANK_COMPID_BASE, SIM_BANK_SIZE, FleetModel, GcsSource, SwarmSource
from swarmdrop.console.mission import MissionInfo, load_mission
from swarmdrop.console.protocol import FRAME_MAGIC, Snapshot, frame_layout, pack_frame, unpack_frame

ROOT = Path(__file__).resolve().parents[1]
SMALL6 = ROOT / "configs" / "small_6.yaml"
E_S = 1_767_225_600.0
CODEC = Codec(sd)
BUILD_STATE = CODEC.builder(MsgId.SWARMDROP_STATE)


def state_frame(k: int, t_s: float, pos=(1.0, 2.0, -10.0), phase: int = 3, sysid: int | None = None,
                compid: int = 191, plan_seq: int = 0, t_go_s: float | None = None) -> bytes:
    values = BUILD_STATE(time_usec=int(t_s * 1e6), t_go_usec=int(t_go_s * 1e6) if t_go_s else 0, x=pos[0], y=pos[1],
                         z=pos[2], vx=1.0, vy=0.0, vz=0.0, q=(1.0, 0.0, 0.0, 0.0), phase=phase, flags=3,
                         vehicle_id=k % 256, plan_seq=plan_seq)
    return CODEC.encode_fields(MsgId.SWARMDROP_STATE, values, (k % 250) + 1 if sysid is None else sysid, compid, 0)


class Clock:
    """A settable monotonic clock."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def _source(mission: MissionInfo | None = None, signing: Signing | None = None, clock=None):
    model = FleetModel(mission or MissionInfo("", None, []), clock=clock or time.monotonic)
    ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), CODEC, 255, 190, signing=signing)
    return SwarmSource(ep, model), model


def _send(port: int, *frames: bytes, sock: socket.socket | None = None) -> None:
    s = sock or socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for f in frames:
        s.sendto(f, ("127.0.0.1", port))
    if sock is None:
        s.close()


def _poll_until(src, cond, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        left = deadline - time.monotonic()
        assert left > 0, "timed out waiting for the console's socket"
        select.select([src.ep.link.fileno()], [], [], min(left, 0.1))
        src.poll()


# ---------------------------------------------------------------------------- the frame
def test_frame_round_trip_and_alignment():
    n = 7
    s = Snapshot.empty(n, t=E_S)
    s.pos[:] = np.arange(3 * n).reshape(n, 3)
    s.phase[:] = np.arange(n) % 7
    s.plan_seq[:] = 9
    s.known[:3] = True
    s.slot[:] = s.pos + 1.0
    data = pack_frame(s, 42, 5)
    assert len(data) % 4 == 0
    for name, (off, dtype, _count) in frame_layout(n).items():
        assert off % np.dtype(dtype).itemsize == 0, name  # the page's typed arrays need this
    d = unpack_frame(data)
    assert (d["n"], d["seq"], d["frame_flags"], d["t"]) == (n, 42, 5, E_S)
    assert np.array_equal(d["pos"], s.pos.reshape(-1)) and d["phase"].tolist() == s.phase.tolist()
    assert d["known"].tolist() == [1, 1, 1, 0, 0, 0, 0] and np.allclose(d["ferr"], math.sqrt(3))
    assert int.from_bytes(data[:4], "little") == FRAME_MAGIC
    with pytest.raises(ValueError):
        unpack_frame(data[:-8])


# ---------------------------------------------------------------------------- the live model
def test_states_are_taken_as_agents_take_them_and_hostile_ones_never_stick():
    clock = Clock()
    src, model = _source(load_mission(SMALL6), clock=clock)
    port = src.ep.link.local_port
    try:
        _send(port, state_frame(0, E_S + 10.0), state_frame(1, E_S + 10.0), state_frame(2, E_S + 10.0))
        _poll_until(src, lambda: model.known[:3].all())
        # refused: wrong sysid for the id, id outside the mission, a phase that is not one of the seven
        _send(port, state_frame(3, E_S + 10.0, sysid=9), state_frame(6, E_S + 10.0), state_frame(4, E_S + 10.0, phase=7),
              b"\xfd\x09garbage", state_frame(5, E_S + 10.0, pos=(1e30, float("nan"), 0.0)))
        _poll_until(src, lambda: model.counters.rejected == 3 and model.known[5])
        assert not model.known[3] and not model.known[4] and src.ep.bad_frames + src.ep.link.bytes_skipped > 0
        assert np.isnan(model.pos[5]).all()  # absurd coordinates are "unknown", never a place on the map
        snap = model.snapshot(clock())
        assert snap.n == 6 and math.isfinite(snap.t) and abs(snap.t - (E_S + 10.0)) < 1e-6
        # an older copy does not roll a vehicle back; a newer one moves it
        _send(port, state_frame(0, E_S + 9.0, pos=(5, 5, -5)), state_frame(0, E_S + 10.5, pos=(7, 7, -7)))
        _poll_until(src, lambda: model.counters.states >= 6)
        assert model.pos[0].tolist() == [7, 7, -7] and model.counters.old >= 1
        # a stamp from the far future is refused once the swarm's clock is known...
        _send(port, state_frame(1, E_S + 3600.0, pos=(9, 9, -9)))
        _poll_until(src, lambda: model.counters.future == 1)
        assert model.pos[1].tolist() == [1, 2, -10]
        # ...and a vehicle silent for RESTART_AFTER_S takes its next state whatever the stamp (a restarted sender)
        clock.t += 4.0
        _send(port, state_frame(2, E_S + 1.0, pos=(3, 3, -3)))
        _poll_until(src, lambda: model.pos[2].tolist() == [3, 3, -3])
    finally:
        src.ep.link.close()


def test_link_quality_ages_and_a_feed_of_any_size():
    clock = Clock(500.0)
    model = FleetModel(MissionInfo("", None, []), clock=clock)
    rows = []
    for k in range(3):
        rows.append((k, int((E_S + 1.0) * 1e6), 0, 0, k, -5, 0, 0, 0, 1, 0, 0, 0, 3, 3, 0))
    for sec in range(6):  # 3 vehicles, 10 states a second each, for 6 s
        for j in range(10):
            clock.t = 500.0 + sec + j / 10
            model.take_states([(k, int((E_S + sec + j / 10) * 1e6), *r[2:]) for k, r in enumerate(rows)])
    clock.t = 506.0
    s = model.snapshot()
    assert s.rate.tolist() == [10.0, 10.0, 10.0] and model.n_seen == 3
    assert np.allclose(s.age, 0.1, atol=1e-6)
    # ids past 249 come in banks: vehicle 250 b + k is vehicle_id k, sysid k + 1, component 25 + b
    src, model = _source()
    try:
        frames = [state_frame(k % SIM_BANK_SIZE, E_S, compid=SIM_BANK_COMPID_BASE + k // SIM_BANK_SIZE)
                  for k in (0, 249, 250, 777, 999)]
        frames[3] = CODEC.encode_fields(MsgId.SWARMDROP_STATE, BUILD_STATE(
            time_usec=int(E_S * 1e6), x=7.0, y=7.0, z=-7.0, q=(1.0, 0, 0, 0), phase=2, vehicle_id=777 % 250),
            777 % 250 + 1, SIM_BANK_COMPID_BASE + 3, 0)
        _send(src.ep.link.local_port, *frames)
        _poll_until(src, lambda: model.counters.states == 5)
        assert np.flatnonzero(model.known).tolist() == [0, 249, 250, 777, 999] and model.n_seen == 1000
        assert model.pos[777].tolist() == [7.0, 7.0, -7.0]
    finally:
        src.ep.link.close()


def test_signing_require_drops_unsigned_and_forged_states(tmp_path):
    key = write_key(tmp_path / "key")
    rx = Signing("require", key, link_id=2, crc_extra=CODEC.crc_extra)
    src, model = _source(load_mission(SMALL6), signing=rx)
    good = Signing("require", key, link_id=1, crc_extra=CODEC.crc_extra)
    bad = Signing("require", bytes(32), link_id=1, crc_extra=CODEC.crc_extra)
    try:
        _send(src.ep.link.local_port, state_frame(0, E_S), bad.sign(state_frame(1, E_S)), good.sign(state_frame(2, E_S)))
        _poll_until(src, lambda: model.known[2])
        c = model.counters.to_json(src.ep)
        assert not model.known[0] and not model.known[1] and c["unsigned"] == 1 and c["bad_signature"] == 1
    finally:
        src.ep.link.close()


def test_hostile_frames_never_raise_in_the_console_readers():
    """The fuzz harness's corpus and mutations, straight into the swarm and GCS readers."""
    from sim_bridge.runs.fuzz import Mutator
    from swarmdrop.console.feeds import LiveFeed

    mission = load_mission(SMALL6)
    src, model = _source(mission)
    gep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), CODEC, 255, 190)
    gcs = GcsSource(gep, {k + 1: k for k in range(6)}, model.capacity)
    feed = LiveFeed(mission, model, src, gcs)
    mut = Mutator(3)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for burst in range(60):
            blob = b"".join(mut.frame() for _ in range(50))
            _send(src.ep.link.local_port, blob[:65000], sock=tx)
            _send(gep.link.local_port, blob[:65000], sock=tx)
            for reader in (src, gcs):
                select.select([reader.ep.link.fileno()], [], [], 0.2)
                feed._read(reader)
            snap, _ = feed.snapshot()
            json.dumps(feed.status(snap), allow_nan=True)
            pack_frame(snap, burst, 4)
        assert feed.errors == 0, "a reader raised on hostile input"
        assert src.ep.bad_frames + model.counters.rejected + gcs.ignored > 0
    finally:
        tx.close()
        src.ep.link.close()
        gep.link.close()


def test_gcs_link_reads_mode_armed_battery_by_dialect():
    from companion.link.dialects import DIALECTS

    px4 = DIALECTS["px4"]
    src_ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), CODEC, 255, 190)
    gcs = GcsSource(src_ep, {1: 0, 2: 1}, 2)
    hb = CODEC.builder(MsgId.HEARTBEAT)
    sys_status = CODEC.builder(MsgId.SYS_STATUS)
    from companion.link.dialects.base import Mode

    frames = [CODEC.encode_fields(MsgId.HEARTBEAT, hb(type=2, autopilot=px4.autopilot_id, base_mode=128 | 1,
                                                      custom_mode=px4.custom_mode(Mode.OFFBOARD), system_status=4), 1, 1, 0),
              CODEC.encode_fields(MsgId.SYS_STATUS, sys_status(voltage_battery=15800, battery_remaining=87), 1, 1, 1),
              CODEC.encode_fields(MsgId.HEARTBEAT, hb(type=6, autopilot=8), 255, 190, 0)]  # a GCS: not a vehicle
    try:
        _send(src_ep.link.local_port, *frames)
        _poll_until(gcs, lambda: gcs.messages >= 2)
        j = gcs.to_json(2, time.monotonic())
        assert j["mode"][0].lower().startswith("offboard") and j["armed"] == [1, -1] and j["battery"] == [87, None]
        assert gcs.ignored == 1
    finally:
        src_ep.link.close()


# ---------------------------------------------------------------------------- replay
@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> Path:
    """A small headless run directory (small_6, 40 s)."""
    out = tmp_path_factory.mktemp("small6")
    proc = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "simulate", str(_short_config(out)), "--out",
                           str(out / "run"), "--quiet", "--no-figures"], cwd=ROOT, capture_output=True, text=True,
                          timeout=240)
    assert proc.returncode == 0, proc.stderr
    return out / "run"


def _short_config(tmp: Path) -> Path:
    import yaml

    from companion.config import read_yaml

    data = read_yaml(SMALL6)
    data["duration_s"] = 40.0
    p = tmp / "small_6_short.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_replay_of_a_run_directory_and_its_playhead(small_run):
    from swarmdrop.console.feeds import ReplayFeed, health
    from swarmdrop.console.replay import open_recording

    rec, mission = open_recording(small_run, None)
    assert rec.n == 6 and rec.t[0] == 0.0 and rec.t[-1] > 30.0 and mission is not None
    assert mission.to_json()["obstacles"] == [{"c": [40.0, 18.0, -12.0], "r": 4.0}]
    clock = Clock(0.0)
    feed = ReplayFeed(rec, mission, clock=clock)
    feed.start(None)  # type: ignore[arg-type]
    a, _ = feed.snapshot()
    clock.t += 10.0
    b, flags = feed.snapshot()
    assert b.t == pytest.approx(10.0, abs=0.05) and flags == 3 and not np.array_equal(a.pos, b.pos)
    asyncio.run(feed.request({"type": "replay", "op": "speed", "speed": 4}))
    clock.t += 1.0
    assert feed.snapshot()[0].t == pytest.approx(14.0, abs=0.05)
    asyncio.run(feed.request({"type": "replay", "op": "seek", "t": 25.0}))
    asyncio.run(feed.request({"type": "replay", "op": "pause"}))
    clock.t += 5.0
    s, flags = feed.snapshot()
    assert s.t == pytest.approx(25.0, abs=0.05) and flags == 1
    h = health(s)
    assert h["heard"] == 6 and h["min_sep_m"] > 1.0 and h["ferr_max_m"] is not None
    for bad in ({"type": "replay", "op": "seek", "t": "x"}, {"type": "replay", "op": "speed", "speed": 1e9},
                {"type": "replay", "op": "rm -rf"}, {"type": "command", "cmd": "hold"}):
        assert asyncio.run(feed.request(bad))["ok"] is False


def test_replay_of_a_console_tlog(tmp_path):
    from companion.link.tlog import Tlog
    from swarmdrop.console.replay import open_recording

    t = {"now": E_S}
    log = Tlog(tmp_path / "swarm.tlog", clock=lambda: t["now"])
    for i in range(50):
        t["now"] = E_S + i * 0.1
        for k in range(3):
            log.write(state_frame(k, E_S + i * 0.1, pos=(i * 0.5, k * 3.0, -10.0)))
        log.write(state_frame(5, E_S + i * 0.1, sysid=1))  # an impostor's sysid: not taken
    log.close()
    rec, _ = open_recording(tmp_path / "swarm.tlog", load_mission(SMALL6))
    assert rec.n == 6 and rec.t[-1] == pytest.approx(4.9, abs=0.11)
    s = rec.snapshot(2.0)
    assert s.known.tolist() == [True, True, True, False, False, False] and s.pos[1].tolist() == pytest.approx([10, 3, -10])
    assert s.rate[0] == pytest.approx(4.2, abs=0.3)  # 21 states (10 Hz, 2 s in) over the 5 s window


# ---------------------------------------------------------------------------- the web server
async def _serve(feed):
    from swarmdrop.console.server import ConsoleServer

    server = ConsoleServer(feed, "127.0.0.1", 0, frame_rate=20.0)
    await server.start()
    return server


async def _serve_live():
    """A console server on small_6's live feed: (server, the feed's swarm source, base URL)."""
    from swarmdrop.console.feeds import LiveFeed

    mission = load_mission(SMALL6)
    src, model = _source(mission)
    server = await _serve(LiveFeed(mission, model, src))
    return server, src, f"http://127.0.0.1:{server.port}"


async def test_server_guards_host_origin_and_hostile_page_messages():
    aiohttp = pytest.importorskip("aiohttp")
    server, src, base = await _serve_live()
    try:
        async with aiohttp.ClientSession() as http:
            async with http.get(base + "/") as r:
                assert r.status == 200 and "swarmdrop console" in await r.text()
                assert "frame-ancestors 'none'" in r.headers["Content-Security-Policy"]
            for name in ("console.js", "console.css", "geo.js"):
                async with http.get(f"{base}/static/{name}") as r:
                    assert r.status == 200
            async with http.get(base + "/static/..%2Fserver.py") as r:
                assert r.status == 404
            async with http.get(base + "/", headers={"Host": "evil.example:80"}) as r:
                assert r.status == 421  # DNS rebinding: another name for this address is refused
            async with http.get(base + "/ws", headers={"Origin": "http://evil.example"}) as r:
                assert r.status == 403  # another site's page cannot open the websocket
            async with http.get(base + "/api/meta") as r:
                meta = await r.json()
                assert meta["mode"] == "live" and meta["n"] == 6 and meta["mission"]["name"] == "small_6"
            _send(src.ep.link.local_port, state_frame(0, E_S), state_frame(1, E_S))
            async with http.ws_connect(base + "/ws", origin=base) as ws:
                first = await ws.receive_json(timeout=5)
                assert first["type"] == "meta"
                got_frame = got_status = False
                while not (got_frame and got_status):
                    msg = await ws.receive(timeout=5)
                    if msg.type == aiohttp.WSMsgType.BINARY:
                        d = unpack_frame(msg.data)
                        got_frame = d["n"] == 6 and d["known"][:2].tolist() == [1, 1]
                    elif json.loads(msg.data)["type"] == "status":
                        got_status = True
                for hostile in ("not json", "[1,2]", json.dumps({"type": "command", "cmd": "hold" * 100}),
                                json.dumps({"type": "replay", "op": "seek"}), "{" * 5000,
                                json.dumps({"type": "command", "cmd": "land", "id": "c1"})):
                    await ws.send_str(hostile)
                results = []
                while len(results) < 6:
                    msg = await ws.receive(timeout=5)
                    if msg.type == aiohttp.WSMsgType.TEXT and json.loads(msg.data)["type"] == "result":
                        results.append(json.loads(msg.data))
                assert all(r["ok"] is False for r in results)
                await ws.send_str("x" * 20000)  # over the size limit: the server closes this page
                while (await ws.receive(timeout=5)).type not in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED,
                                                                 aiohttp.WSMsgType.CLOSING):
                    pass
            async with http.get(base + "/api/status") as r:
                assert (await r.json())["health"]["heard"] == 2
    finally:
        await server.close()


async def test_api_status_follows_the_swarm_with_no_page_open():
    """A script polling /api/status (no browser) reads the swarm as it is now: the frame loop
    refreshes the status only for open pages, and /api/status once cached it for good."""
    aiohttp = pytest.importorskip("aiohttp")
    server, src, base = await _serve_live()
    try:
        async with aiohttp.ClientSession() as http:
            async with http.get(base + "/api/status") as r:
                assert (await r.json())["health"]["heard"] == 0
            _send(src.ep.link.local_port, state_frame(0, E_S), state_frame(1, E_S), state_frame(2, E_S))
            deadline = time.monotonic() + 5
            while True:  # polled, as a health script does (a status period is 0.5 s)
                async with http.get(base + "/api/status") as r:
                    if (await r.json())["health"]["heard"] == 3:
                        break
                assert time.monotonic() < deadline, "/api/status never showed the states sent"
                await asyncio.sleep(0.1)
    finally:
        await server.close()


# ---------------------------------------------------------------------------- commands on the wire
def test_commands_are_checked_signed_and_sent_as_plans(tmp_path):
    from companion.commands import PlanAssembler
    from swarmdrop.console.commands import CommandPanel

    key = write_key(tmp_path / "key")
    mission = load_mission(SMALL6)
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    sign = Signing("require", key, link_id=2, crc_extra=CODEC.crc_extra)
    ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), CODEC, 255, 190, signing=sign)
    panel = CommandPanel(mission, ep, [peer.getsockname()], {}, sysid=255, epoch_unix_s=E_S)
    s = Snapshot.empty(6, t=E_S + 30.0)
    s.t_go = E_S + 24.0
    s.known[:] = True
    panel.note_swarm(s)
    check = Signing("require", key, link_id=9, crc_extra=CODEC.crc_extra)
    asm = PlanAssembler.for_mission(mission.model, E_S)  # type: ignore[arg-type]

    def receive_plan():
        plan = None
        deadline = time.monotonic() + 5
        while plan is None:
            assert time.monotonic() < deadline, "no plan on the wire"
            select.select([peer], [], [], 0.2)
            data = peer.recv(65536)
            from companion.link.framing import split_datagram

            for f in split_datagram(data)[0]:
                assert check.check(f), "an unsigned or forged command frame"
                assert f[5] == 255  # from the ground station's sysid
                plan = asm.feed(CODEC.decode(f)) or plan
        return plan

    try:
        r = panel.request({"type": "command", "cmd": "hold"})
        assert r["ok"], r
        plan = receive_plan()
        # HOLD applies after its urgent lead (the operator must see the swarm stop within 2 s)
        assert plan.kind == "hold" and plan.seq == 1 and plan.effective_s == pytest.approx(30.0 + URGENT_LEAD_S)
        # LAND and ABORT need a confirmation; nonsense is refused with the reason, nothing sent
        assert not panel.request({"type": "command", "cmd": "land"})["ok"]
        for bad in ({"cmd": "goto", "waypoints": [[1, 2]], "speed": 3}, {"cmd": "goto", "waypoints": [[0, 0, -10]],
                    "speed": float("nan")}, {"cmd": "formation", "shape": "star"}, {"cmd": "exclude", "ids": [6]},
                    {"cmd": "formation", "shape": "line", "spacing": -1}, {"cmd": "reboot"}, {"cmd": None}):
            assert not panel.request({"type": "command", **bad})["ok"], bad
        assert panel.request({"type": "command", "cmd": "formation", "shape": "line", "spacing": 4.0,
                              "rotation_deg": 90})["ok"]
        plan = receive_plan()
        assert plan.kind == "formation" and plan.formation.shape == "line" and plan.seq == 2
        assert panel.request({"type": "command", "cmd": "land", "ids": [1, 3], "confirm": True})["ok"]
        plan = receive_plan()
        assert plan.kind == "land" and plan.landing == frozenset({1, 3})
        for seq, (req, kind) in enumerate((({"cmd": "goto", "waypoints": [[60, 30, -15], [80, 30, -15]], "speed": 2.5}, "goto"),
                                           ({"cmd": "exclude", "ids": [2], "land": False}, "exclude"),
                                           ({"cmd": "rejoin", "ids": [2]}, "rejoin"), ({"cmd": "rtl"}, "rtl"),
                                           ({"cmd": "abort", "confirm": True}, "abort")), start=4):
            r = panel.request({"type": "command", **req})
            assert r["ok"], (req, r)
            plan = receive_plan()
            assert (plan.seq, plan.kind) == (seq, kind)
        assert plan.abort and not panel.request({"type": "command", "cmd": "hold"})["ok"]  # nothing after ABORT
        # the swarm follows a plan newer than this console's: commands are refused, not silently ignored
        s.plan_seq[:] = 99
        panel.note_swarm(s)
        r = panel.request({"type": "command", "cmd": "resume"})
        assert not r["ok"] and "plan 99" in r["text"]
    finally:
        panel.close()
        ep.link.close()
        peer.close()


# ---------------------------------------------------------------------------- the SITL's radio: monitors and plans
def test_radio_copies_states_to_monitors_and_forwards_plans_to_every_vehicle():
    from sim_bridge.sitl.medium import Medium
    from sim_bridge.world.transport import LinkConfig

    n = 3
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n + 2)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
    agents, monitor, console_tx = socks[:n], socks[n], socks[n + 1]
    radio = Medium(n, LinkConfig(), seed=1, epoch_unix_s=E_S, bind=("127.0.0.1", 0),
                   agent_ports=[s.getsockname()[1] for s in agents])
    radio.set_monitors([monitor.getsockname()])
    dest = ("127.0.0.1", radio.port)

    def drain(sock) -> list:
        from companion.link.framing import split_datagram

        out = []
        while True:
            try:
                out += split_datagram(sock.recv(65536))[0]
            except BlockingIOError:
                return out

    def until(cond) -> None:
        deadline = time.monotonic() + 5
        while not cond():
            assert time.monotonic() < deadline
            select.select([radio.fileno()], [], [], 0.1)
            radio.receive()

    try:
        agents[0].sendto(state_frame(0, E_S + 1.0), dest)
        agents[1].sendto(state_frame(1, E_S + 1.0), dest)
        until(lambda: radio.monitor_copies >= 2)
        # the rule of one sender per id still holds: an impostor's state is refused and not copied
        console_tx.sendto(state_frame(0, E_S + 1.1), dest)
        until(lambda: radio.id_conflicts == 1)
        plan = CODEC.encode_fields(MsgId.SWARMDROP_PLAN, CODEC.builder(MsgId.SWARMDROP_PLAN)(seq=1, n_vehicles=3, speed=1.0,
                                                                                              radius=1.0, spacing=1.0),
                                   255, 190, 0)
        console_tx.sendto(plan, dest)
        agents[1].sendto(plan, dest)  # an agent relaying it: everyone but the relaying agent gets a copy
        until(lambda: radio.commands_forwarded >= 3 and radio.relays_in == 1)
        assert radio.commands_forwarded == 3  # the console's, at once; the agent's relay goes on the radio:
        radio.schedule(0.0, np.zeros((n, 3)))
        radio.deliver(0.0, np.ones(n, bool), tick_marker=False)  # (a perfect link: due at once)
        select.select([monitor], [], [], 1.0)
        got = drain(monitor)
        ids = [f[7] | f[8] << 8 | f[9] << 16 for f in got]
        assert ids.count(MsgId.SWARMDROP_STATE) == 2 and ids.count(MsgId.SWARMDROP_PLAN) >= 1
        plans = {k: sum(1 for f in drain(agents[k]) if (f[7] | f[8] << 8 | f[9] << 16) == MsgId.SWARMDROP_PLAN)
                 for k in range(n)}
        assert plans == {0: 2, 1: 1, 2: 2}  # every agent, but not back to the agent that relayed it
        assert radio.foreign == 1  # only the impostor's state; plans are not foreign
    finally:
        for s in socks:
            s.close()
        radio.close()


def test_radio_bounds_the_plans_it_forwards():
    """A flood of plans is cut at the radio's rate (the rest dropped and counted), not amplified N-fold."""
    from sim_bridge.sitl.medium import Medium
    from sim_bridge.world.transport import LinkConfig

    agent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    agent.bind(("127.0.0.1", 0))
    wall = Clock(0.0)
    radio = Medium(2, LinkConfig(), seed=1, epoch_unix_s=E_S, bind=("127.0.0.1", 0),
                   agent_ports=[agent.getsockname()[1]] * 2, wall_clock=wall)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    plan = CODEC.encode_fields(MsgId.SWARMDROP_PLAN, CODEC.builder(MsgId.SWARMDROP_PLAN)(seq=1, n_vehicles=2), 255, 190, 0)
    try:
        burst = plan * 18  # 18 frames a datagram
        for _ in range(60):
            tx.sendto(burst, ("127.0.0.1", radio.port))
        deadline = time.monotonic() + 5
        while radio.commands_dropped + radio.commands_forwarded // 2 < 60 * 18:
            assert time.monotonic() < deadline
            select.select([radio.fileno()], [], [], 0.1)
            radio.receive()
        assert radio.commands_forwarded // 2 == int(2 * radio.command_rate) and radio.commands_dropped > 0
    finally:
        tx.close()
        agent.close()
        radio.close()


def test_medium_monitor_options_are_checked():
    import argparse

    from companion.config import ConfigError
    from sim_bridge.sitl.cli import add_arguments, config_from_args

    p = argparse.ArgumentParser()
    add_arguments(p)
    with pytest.raises(ConfigError, match="needs the radio"):
        config_from_args(p.parse_args(["--vehicles", "2", "--medium-monitor", "127.0.0.1:9"]))
    cfg = config_from_args(p.parse_args(["--vehicles", "2", "--medium-port", "0", "--medium-monitor", "127.0.0.1:9"]))
    assert cfg.medium.monitor_addrs == [("127.0.0.1", 9)]
    with pytest.raises(ConfigError):
        config_from_args(p.parse_args(["--vehicles", "2", "--medium-port", "0", "--medium-monitor", "nowhere"]))


# ---------------------------------------------------------------------------- simulate --live
def test_live_stream_speaks_the_consoles_wire_at_any_size():
    from companion.swarm import SwarmStates
    from sim_bridge.runs import live

    assert (live.SIM_BANK_COMPID_BASE, live.SIM_BANK_SIZE) == (SIM_BANK_COMPID_BASE, SIM_BANK_SIZE)
    src, model = _source()
    clock = Clock(0.0)
    slept: list[float] = []
    n = 600
    try:
        with live.LiveStream(("127.0.0.1", src.ep.link.local_port), n, clock=clock, wall=lambda: E_S,
                             sleep=lambda s: slept.append(s)) as stream:
            ids = np.arange(n)
            pub = SwarmStates(ids, np.full(n, 0.0), np.stack([ids, ids, -np.ones(n)], 1).astype(float), np.zeros((n, 3)),
                              np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 2, np.int8), np.full(n, 3, np.uint8),
                              np.full(n, np.nan))
            stream(0.0, pub)
            clock.t = 0.05
            stream(0.1, None)  # paced: the runner waits for the wall clock
        assert slept == [pytest.approx(0.05)]
        _poll_until(src, lambda: model.counters.states == n)
        assert model.known.sum() == n and model.pos[599].tolist() == [599.0, 599.0, -1.0]
        assert model.stamp_s[0] == pytest.approx(E_S)
    finally:
        src.ep.link.close()


def test_headless_runner_calls_its_tick_observers(tmp_path):
    from sim_bridge.runs import headless
    from sim_bridge.scenario import load_scenario

    cfg = load_scenario(_short_config(tmp_path))
    import dataclasses

    cfg = dataclasses.replace(cfg, duration_s=2.0)
    seen: list[tuple[float, int]] = []

    def observe(t, published):
        seen.append((t, 0 if published is None else len(published)))

    headless.TICK_OBSERVERS.append(observe)
    try:
        headless.run_scenario(cfg, progress=False)
    finally:
        headless.TICK_OBSERVERS.remove(observe)
    ts = [t for t, _ in seen]
    assert ts == sorted(ts) and ts[-1] == pytest.approx(2.0) and sum(k for _, k in seen) == pytest.approx(6 * 2 * 10, abs=6)


# ---------------------------------------------------------------------------- command line and imports
def test_console_help_and_the_agent_never_imports_the_web_stack():
    out = subprocess.run([sys.executable, "-m", "swarmdrop.cli", "console", "--help"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0 and "--swarm-bind" in out.stdout and "--replay" in out.stdout
    assert "127.0.0.1" in out.stdout and "pip install 'swarmdrop[console]'" in out.stdout
    code = ("import json, runpy, sys\n"
            "sys.argv = ['swarmdrop', 'agent', '--help']\n"
            "try:\n    runpy.run_module('swarmdrop.cli', run_name='__main__')\nexcept SystemExit:\n    pass\n"
            "print('MODULES=' + json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('aiohttp', 'swarmdrop', 'yarl', 'multidict'))))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    mods = json.loads(proc.stdout.split("MODULES=", 1)[1])
    assert not [m for m in mods if not m.startswith("swarmdrop") or m.startswith("swarmdrop.console")], mods
    # building every subcommand's parser does not import the web stack either
    code = ("import sys\nfrom swarmdrop.cli import build_parser\nbuild_parser()\n"
            "print('aiohttp' in sys.modules)\n")
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=60).stdout.strip() == "False"


def test_console_without_aiohttp_says_what_to_install():
    """(aiohttp blocked in the child, whether it is installed or not.)"""
    code = ("import sys\nsys.modules['aiohttp'] = None\nfrom swarmdrop.cli import main\n"
            "sys.exit(main(['console', '--port', '0']))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "pip install 'swarmdrop[console]'" in proc.stderr and "Traceback" not in proc.stderr


def test_console_refuses_bad_options_with_exit_2(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "swarmdrop.cli", "console", "--port", "0", *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=60)

    for args, says in ((["--mission", str(tmp_path / "none.yaml")], "no such mission file"),
                       (["--signing", "require"], "--signing-key"),
                       (["--replay", str(tmp_path)], "no telemetry.npz"),
                       (["--frame-rate", "0"], "--frame-rate"), (["--gcs", "udpin://127.0.0.1:99999"], "PORT")):
        p = run(*args)
        assert p.returncode == 2 and says in p.stderr and "Traceback" not in p.stderr, (args, p.stderr)


def test_fleet_options_keep_the_console_off_for_library_callers(tmp_path):
    from companion.config import ConfigError
    from sim_bridge.runs.fleet import FleetOptions

    assert FleetOptions(out_dir=tmp_path).console is False
    with pytest.raises(ConfigError, match="--console-port"):
        FleetOptions(out_dir=tmp_path, console_port=70000).check()
    from swarmdrop.cli import build_parser

    args = build_parser().parse_args(["run", "configs/small_6.yaml"])
    assert args.no_console is False and args.console_port == 0


@pytest.mark.timeout(180)
def test_short_fuzz_run_with_the_console_crashes_nothing(tmp_path):
    from sim_bridge.runs.fuzz import find_tracebacks, run

    report = run(frames=30_000, seed=5, out_dir=tmp_path, quiet=True, console=True)
    assert report.crashes == [] and find_tracebacks(tmp_path) == [], report
    assert report.per_port["console_swarm"] > 3000 and report.per_port["console_gcs"] > 3000
    assert report.console_rss_growth is not None and report.console_rss_growth < 0.2, report



async def test_a_closed_tcp_gcs_link_is_let_go_not_spun_on():
    """A router that closes the console's TCP link: the reader is removed (no busy loop on EOF)."""
    from companion.link.endpoints import open_link
    from swarmdrop.console.feeds import LiveFeed

    closed = asyncio.Event()

    async def accept_and_close(reader, writer):
        writer.close()
        closed.set()

    server = await asyncio.start_server(accept_and_close, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    mission = load_mission(SMALL6)
    src, model = _source(mission)
    gep = MavEndpoint(open_link(f"tcp://127.0.0.1:{port}", CODEC.crc_extra), CODEC, 255, 190)
    feed = LiveFeed(mission, model, src, GcsSource(gep, {k + 1: k for k in range(6)}, 6))
    feed.start(asyncio.get_running_loop())
    try:
        await asyncio.wait_for(closed.wait(), 5)
        deadline = time.monotonic() + 5
        while not feed.gcs_closed:
            assert time.monotonic() < deadline, "the closed link is still read"
            await asyncio.sleep(0.01)
        snap, _ = feed.snapshot()
        assert feed.status(snap)["ap"]["closed"] is True and feed.errors == 0
    finally:
        feed.close(asyncio.get_running_loop())
        server.close()
        await server.wait_closed()
