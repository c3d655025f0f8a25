"""`swarmdrop agent`, the companion process of one vehicle: its exit codes, what it
imports onboard, the swarm link's input rules, and a ground launch against the SITL."""
from __future__ import annotations

import json
import math
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

os.environ.setdefault("MAVLINK20", "1")
from lean_agent import EXTRAS_ONLY, lean_agent_cmd, lean_cmd  # noqa: E402
from pymavlink import mavutil  # noqa: E402

from companion.agent import Phase  # noqa: E402
from companion.link.dialects import Mode, dialect_named  # noqa: E402
from companion.link.endpoints import MavEndpoint, UdpLink  # noqa: E402
from companion.link.msgdef import swarmdrop as md  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from companion.mission import formation_offsets_ned_m  # noqa: E402
from companion.node.config import load_mission_file  # noqa: E402
from companion.node.swarmlink import SwarmLink, view_for  # noqa: E402
from sim_bridge.sitl.testing import free_udp_base_port  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SMALL6 = ROOT / "configs" / "small_6.yaml"
EPOCH_UNIX_S = 1767225600.0
ORIGIN = {"lat_deg": 47.397742, "lon_deg": 8.545594, "alt_amsl_m": 488.0}
ONBOARD_BANNED = ("numba", "scipy", "matplotlib", "tqdm", "sim_bridge")


def agent_cmd(*args: str) -> list[str]:
    """The agent as the onboard install runs it: none of the extras' packages importable."""
    return lean_agent_cmd(*args)


def run_agent(*args: str, timeout_s: float = 30.0) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    proc = subprocess.run(agent_cmd(*args), cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    return proc, time.monotonic() - t0


def free_port() -> int:
    return free_udp_base_port(1)


# ---------------------------------------------------------------------------- a. bad input -> 2
def _mission_without_origin(tmp: Path) -> Path:
    data = yaml.safe_load(SMALL6.read_text())
    del data["mission"]["origin"]
    p = tmp / "no_origin.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _mission_bad_value(tmp: Path) -> Path:
    data = yaml.safe_load(SMALL6.read_text())
    data["mission"]["formation"]["radius_m"] = -5
    p = tmp / "bad_radius.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


BAD_CASES = {
    "vehicle id outside the mission": (lambda tmp: ["--vehicle-id", "6", "--mission", str(SMALL6)],
                                       "--vehicle-id 6 is outside the mission's 6 vehicles"),
    "mission without origin": (lambda tmp: ["--vehicle-id", "0", "--mission", str(_mission_without_origin(tmp))],
                               "mission.origin"),
    "invalid mission value": (lambda tmp: ["--vehicle-id", "0", "--mission", str(_mission_bad_value(tmp))],
                              "mission.formation.radius_m"),
    "missing mission file": (lambda tmp: ["--vehicle-id", "0", "--mission", str(tmp / "nope.yaml")],
                             "no such mission file"),
    "bad autopilot url": (lambda tmp: ["--vehicle-id", "0", "--mission", str(SMALL6), "--autopilot", "bogus://x:1"],
                          "unknown scheme 'bogus'"),
    "bad swarm address": (lambda tmp: ["--vehicle-id", "0", "--mission", str(SMALL6), "--swarm-bind", "nohost"],
                          "expected HOST:PORT"),
    "rate out of range": (lambda tmp: ["--vehicle-id", "0", "--mission", str(SMALL6), "--rate", "1000"],
                          "--rate: Input should be less than or equal to 400"),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_arguments_or_mission_exit_2_with_a_message(case, tmp_path):
    make_args, expected = BAD_CASES[case]
    args = make_args(tmp_path)
    if "--autopilot" not in args:
        args += ["--autopilot", f"udpin://127.0.0.1:{free_port()}"]
    proc, _ = run_agent(*args)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert expected in proc.stderr, proc.stderr


@pytest.mark.timeout(60)
def test_uvloop_asked_for_where_it_cannot_be_imported_exits_2_naming_the_way_out(tmp_path):
    cmd = lean_cmd("agent", "--vehicle-id", "0", "--mission", str(SMALL6), "--autopilot",
                   f"udpin://127.0.0.1:{free_port()}", "--event-loop", "uvloop",
                   blocked=(*EXTRAS_ONLY, "sim_bridge", "uvloop"))
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "--event-loop uvloop: uvloop cannot be imported" in proc.stderr
    assert "--event-loop asyncio" in proc.stderr


def test_event_loop_choice():
    import asyncio

    uvloop = pytest.importorskip("uvloop")  # (in the base install where pyproject's marker brings it)
    from companion.config import ConfigError
    from companion.node.cli import event_loop_factory

    factory, name = event_loop_factory("auto")  # (uvloop is in the base install)
    assert factory is uvloop.new_event_loop and name == f"uvloop {uvloop.__version__}"
    assert event_loop_factory("uvloop")[0] is uvloop.new_event_loop
    factory, name = event_loop_factory("asyncio")
    assert factory is None and name.startswith("asyncio")
    with asyncio.Runner(loop_factory=event_loop_factory("auto")[0]) as r:  # what the agent flies on
        assert r.run(_loop_type()) is uvloop.Loop
    with pytest.raises(ConfigError, match="expected one of auto, uvloop, asyncio"):
        event_loop_factory("trio")


async def _loop_type() -> type:
    import asyncio

    return type(asyncio.get_running_loop())


@pytest.mark.timeout(60)
def test_auto_event_loop_falls_back_to_asyncio_where_uvloop_cannot_be_imported(tmp_path):
    stats = tmp_path / "stats.json"
    cmd = lean_cmd("agent", "--vehicle-id", "0", "--mission", str(SMALL6), "--autopilot",
                   f"udpin://127.0.0.1:{free_port()}", "--setup-timeout", "1", "--stats", str(stats),
                   blocked=(*EXTRAS_ONLY, "sim_bridge", "uvloop"))
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 3, (proc.stdout, proc.stderr)  # (no autopilot there: it got as far as set-up)
    assert "event loop: asyncio (Python " in proc.stderr
    assert json.loads(stats.read_text())["event_loop"].startswith("asyncio")


# ---------------------------------------------------------------------------- b. no autopilot -> 3
@pytest.mark.timeout(60)
def test_no_autopilot_exits_3_within_the_setup_timeout(tmp_path):
    stats = tmp_path / "stats.json"
    proc, wall = run_agent("--vehicle-id", "0", "--mission", str(SMALL6), "--autopilot",
                           f"udpin://127.0.0.1:{free_port()}", "--setup-timeout", "1", "--stats", str(stats))
    assert proc.returncode == 3, (proc.stdout, proc.stderr)
    assert "HEARTBEAT" in proc.stderr
    assert wall < 15.0  # 1 s of waiting plus interpreter start-up on a loaded machine
    assert json.loads(stats.read_text())["autopilot"]["dialect"] is None


# ---------------------------------------------------------------------------- c. onboard imports
@pytest.mark.timeout(60)
def test_onboard_modules_import_no_simulator_or_plotting_packages():
    code = ("import json, sys\n"
            "import companion.node.runner, companion.node.cli\n"
            f"banned = {ONBOARD_BANNED!r}\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in banned)))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == []


@pytest.mark.timeout(60)
def test_agent_help_imports_no_simulator_or_plotting_packages():
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "swarmdrop.cli", "agent", "--help"], cwd=ROOT,
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    assert "--vehicle-id" in proc.stdout and "--autopilot" in proc.stdout
    imported = [ln.rsplit("|", 1)[1].strip() for ln in proc.stderr.splitlines() if ln.startswith("import time:")]
    assert "companion.node.cli" in imported  # the -X importtime report is there
    assert [m for m in imported if m.split(".")[0] in ONBOARD_BANNED] == []
    # the same in-process, through the console script's entry point
    code = ("import json, runpy, sys\n"
            "sys.argv = ['swarmdrop', 'agent', '--help']\n"
            "try:\n    runpy.run_module('swarmdrop.cli', run_name='__main__')\nexcept SystemExit:\n    pass\n"
            f"banned = {ONBOARD_BANNED!r}\n"
            "print('MODULES=' + json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in banned)))\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.split("MODULES=", 1)[1]) == []


# ---------------------------------------------------------------------------- d. SwarmLink input rules
def _state_values(t_us: int, vehicle_id: int, pos=(0.0, 0.0, 0.0), vel=(0.0, 0.0, 0.0), phase=2, flags=2):
    return [t_us, 0, *map(float, pos), *map(float, vel), [1.0, 0.0, 0.0, 0.0], phase, flags, vehicle_id]


class _Sender:
    """A MAVLink endpoint that signs SWARMDROP_STATEs with whatever sysid a case needs."""

    def __init__(self, dest: tuple[str, int]):
        self.codec = Codec(md)
        self.ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), self.codec, 2, 191)
        self.dest = dest

    def state(self, sysid: int, *args, **kw) -> None:
        self.ep.queue_fields(md.MAVLINK_MSG_ID_SWARMDROP_STATE, _state_values(*args, **kw), self.dest, sysid=sysid)
        self.ep.flush()

    def raw(self, data: bytes) -> None:
        self.ep.link.send(data, self.dest)

    def frame(self, sysid: int, *args, **kw) -> bytes:
        return self.codec.encode_fields(md.MAVLINK_MSG_ID_SWARMDROP_STATE, _state_values(*args, **kw), sysid, 191, 0)

    def close(self) -> None:
        self.ep.close()


def _poll_until(link: SwarmLink, cond, timeout_s: float = 3.0) -> None:
    """Poll the swarm socket (select with a deadline) until cond() holds."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        left = deadline - time.monotonic()
        assert left > 0, "timed out waiting for the swarm socket"
        select.select([link.ep.link.fileno()], [], [], min(left, 0.1))
        link.poll()


@pytest.mark.timeout(30)
def test_swarm_link_input_rules_over_udp():
    n, own = 4, 0
    view = view_for(n)
    rx_ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), Codec(md), own + 1, 191)
    link = SwarmLink(rx_ep, own, [], view)
    tx = _Sender(("127.0.0.1", rx_ep.link.local_port))
    e_us = int(EPOCH_UNIX_S * 1e6)
    try:
        # before the agent knows its clock nothing is stored (no stamp in another time base)
        tx.state(2, e_us + 1_000_000, 1, (7, 7, 7))
        _poll_until(link, lambda: link.rejected == 1)
        assert np.isnan(view.stamp_s[0]).all()
        link.set_epoch(EPOCH_UNIX_S)
        # until the first tick tells the link the vehicle's clock, every state is too early to trust
        tx.state(2, e_us + 1_000_000, 1, (7, 7, 7))
        _poll_until(link, lambda: link.future == 1)
        link.now_us = e_us + 5_100_000  # (the tick path: the vehicle's clock at its newest tick)
        # the own id from someone else is an identity conflict (kept apart, never as a neighbour)
        tx.state(own + 1, e_us + 5_000_000, own, (9, 9, 9))
        _poll_until(link, lambda: link.conflicts == 1)
        # dropped: out-of-range id, sysid that is not vehicle_id + 1, undecodable bytes
        tx.state(n + 1, e_us + 5_000_000, n, (9, 9, 9))
        tx.state(5, e_us + 5_000_000, 2, (9, 9, 9))
        _poll_until(link, lambda: link.rejected == 3)
        bad = bytearray(tx.frame(2, e_us + 5_000_000, 1, (9, 9, 9)))
        bad[-1] ^= 0xFF  # wrong CRC
        junk = [bytes(bad), bytes(range(7, 71)) + b"\xfd\x03", tx.frame(2, e_us + 5_000_000, 1, (9, 9, 9))[:20]]
        bytes_before = rx_ep.link.bytes_in
        for blob in junk:
            tx.raw(blob)
        _poll_until(link, lambda: rx_ep.link.bytes_in >= bytes_before + sum(map(len, junk)))
        assert rx_ep.bad_frames >= 1 and rx_ep.link.bytes_skipped > 0
        assert np.isnan(view.stamp_s[0]).all() and link.states_in == 0 and link.rejected == 3
        # a good state, then an older copy (reordered) and a duplicate: the newest is kept
        tx.state(2, e_us + 5_000_000, 1, (1, 2, 3), (0.5, 0, 0))
        _poll_until(link, lambda: link.states_in == 1)
        assert view.stamp_s[0, 1] == pytest.approx(5.0) and view.pos_ned_m[0, 1].tolist() == [1, 2, 3]
        tx.state(2, e_us + 4_000_000, 1, (8, 8, 8))
        tx.state(2, e_us + 5_000_000, 1, (8, 8, 8))
        _poll_until(link, lambda: link.states_in == 3)
        assert view.ignored_old[0] == 2
        assert view.stamp_s[0, 1] == pytest.approx(5.0) and view.pos_ned_m[0, 1].tolist() == [1, 2, 3]
        tx.state(2, e_us + 5_100_000, 1, (4, 5, 6))
        _poll_until(link, lambda: link.states_in == 4)
        assert view.stamp_s[0, 1] == pytest.approx(5.1) and view.pos_ned_m[0, 1].tolist() == [4, 5, 6]
        assert np.isnan(view.stamp_s[0, [0, 2, 3]]).all()  # nobody else was ever stored
        assert link.rejected == 3 and link.conflicts == 1
        # a state stamped an hour ahead (a wrong clock, a forgery) is dropped and counted: kept, it
        # would have hidden every real state of vehicle 1 for an hour as older; 0.4 s ahead is kept
        tx.state(2, e_us + 3_605_000_000, 1, (9, 9, 9))
        _poll_until(link, lambda: link.future == 2)
        assert view.stamp_s[0, 1] == pytest.approx(5.1) and link.counters().future == 2
        tx.state(2, e_us + 5_500_000, 1, (3, 3, 3))
        _poll_until(link, lambda: link.states_in == 5)
        assert view.stamp_s[0, 1] == pytest.approx(5.5) and view.pos_ned_m[0, 1].tolist() == [3, 3, 3]
        # the radio's end-of-tick marker is taken whoever signs it, but not from the future
        tx.ep.queue_fields(md.MAVLINK_MSG_ID_SWARMDROP_TICK, [e_us + 3_605_000_000], tx.dest, sysid=255, compid=0)
        tx.ep.flush()
        _poll_until(link, lambda: link.future == 3)
        tx.ep.queue_fields(md.MAVLINK_MSG_ID_SWARMDROP_TICK, [e_us + 5_100_000], tx.dest, sysid=255, compid=0)
        tx.ep.flush()
        _poll_until(link, lambda: link.marker_us == e_us + 5_100_000)
    finally:
        tx.close()
        rx_ep.close()


# ---------------------------------------------------------------------------- e. ground launch vs SITL
def _ground_mission(tmp: Path) -> Path:
    data = {"name": "ground_1", "seed": 3, "mission": {
        "n_vehicles": 1, "formation": {"radius_m": 2.0}, "waypoints_ned_m": [[3.0, 1.0, -4.0]],
        "launch": "ground", "takeoff_alt_m": 2.5, "origin": ORIGIN}}
    p = tmp / "ground_1.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _wait_for(cond, timeout_s: float, what: str, proc: subprocess.Popen | None = None, log: Path | None = None):
    deadline = time.monotonic() + timeout_s
    while not cond():
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"agent exited {proc.returncode} while waiting for {what}:\n"
                        f"{log.read_text() if log and log.exists() else ''}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}:\n{log.read_text() if log and log.exists() else ''}")
        time.sleep(0.05)  # polling a condition with a deadline


@pytest.mark.timeout(120)
@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
def test_ground_launch_takes_off_and_flies_to_its_slot(dialect, tmp_path):
    from companion.mission import GeodeticOrigin
    from sim_bridge.sitl.background import BackgroundSitl
    from sim_bridge.sitl.config import EndpointConfig, MediumConfig, TimeConfig, sitl_config

    d = dialect_named(dialect)
    mission_path = _ground_mission(tmp_path)
    mcfg = load_mission_file(mission_path).mission
    slot = formation_offsets_ned_m(mcfg.formation, 1)[0] + np.array(mcfg.waypoints_ned_m[-1])
    base = free_udp_base_port(3)
    ap_port, swarm_port, radio_port = base, base + 1, base + 2
    tlog = tmp_path / "sitl.tlog"
    cfg = sitl_config(
        1, seed=3, launch="ground", origin=GeodeticOrigin(**ORIGIN), dialect=dialect,
        endpoints=EndpointConfig(remote_host="127.0.0.1", remote_base_port=ap_port, bind_host="127.0.0.1",
                                 local_base_port=0),
        time=TimeConfig(lockstep=True, epoch_unix_s=EPOCH_UNIX_S),
        medium=MediumConfig(enabled=True, port=radio_port, agent_base_port=swarm_port), tlog_path=str(tlog))
    bg = BackgroundSitl(cfg)
    server = bg.start()
    log = tmp_path / "agent.log"
    agent = subprocess.Popen(
        agent_cmd("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{ap_port}", "--mission", str(mission_path),
                  "--swarm-bind", f"127.0.0.1:{swarm_port}", "--swarm-peer", f"127.0.0.1:{radio_port}",
                  "--launch", "ground", "--lockstep", "--setup-timeout", "20", "--log-file", str(log),
                  "--set-loss-action", "hold",  # the SITL's PX4 boots with COM_OBL_RC_ACT 0 (drifts): refused
                  "--no-stderr-log", "--stats", str(tmp_path / "agent.json"),
                  # PX4: the link is the agent's alone (the streams it does not read are stopped), on
                  # the default event loop (uvloop); ArduPilot: the default streams (left alone), on
                  # the standard library's loop
                  *(["--stop-unread-streams"] if dialect == "px4" else ["--event-loop", "asyncio"])),
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: log.exists() and "-> HOVER" in log.read_text(), 90, "HOVER", agent, log)

        def settled() -> bool:
            p, v = server.state.pos_ned_m[0].copy(), server.state.vel_ned_mps[0].copy()
            return bool(np.linalg.norm(p - slot) < 0.05 and np.linalg.norm(v) < 0.05)

        _wait_for(settled, 30, "the vehicle to settle at its slot", agent, log)
        assert server.autopilots[0].mode == Mode.OFFBOARD and server.autopilots[0].armed
        agent.send_signal(signal.SIGTERM)
        assert agent.wait(15) == 0, agent.stderr.read()
    finally:
        if agent.poll() is None:
            agent.kill()
            agent.wait(10)
        bg.stop()
    text = log.read_text()
    for phase in ("LAUNCH -> STABILISE", "STABILISE -> ASSEMBLE", "-> HOVER"):
        assert phase in text, text
    # what crossed the link: arming and the autopilot's take-off command, accepted, before any setpoint
    conn = mavutil.mavlink_connection(str(tlog))
    acks, first_sp_t, cmds, climbed_t, modes, last_att_t = {}, None, [], None, [], None
    last_sp_t = -math.inf
    while True:
        m = conn.recv_match(type=["COMMAND_LONG", "COMMAND_ACK", "SET_POSITION_TARGET_LOCAL_NED",
                                  "LOCAL_POSITION_NED", "HEARTBEAT", "ATTITUDE"])
        if m is None:
            break
        t = m._timestamp - EPOCH_UNIX_S
        typ = m.get_type()
        if typ == "COMMAND_LONG" and m.get_srcComponent() == 191:
            cmds.append((t, m.command))
        elif typ == "COMMAND_ACK":
            acks.setdefault(m.command, []).append(m.result)
        elif typ == "SET_POSITION_TARGET_LOCAL_NED":
            first_sp_t = t if first_sp_t is None else first_sp_t
            last_sp_t = t
        elif typ == "LOCAL_POSITION_NED" and climbed_t is None and m.z < -(mcfg.takeoff_alt_m - 0.2):
            climbed_t = t
        elif typ == "HEARTBEAT" and m.get_srcComponent() == 1:
            modes.append((t, m.custom_mode))
        elif typ == "ATTITUDE":
            last_att_t = t
    conn.close()
    assert 400 in [c for _, c in cmds] and 22 in [c for _, c in cmds]
    assert 0 in acks[400] and 0 in acks[22]  # MAV_RESULT_ACCEPTED
    t_takeoff = next(t for t, c in cmds if c == 22)
    assert climbed_t is not None and first_sp_t is not None
    assert t_takeoff <= climbed_t < first_sp_t  # the autopilot climbed on its own take-off
    shown = [mode for _, mode in modes]
    if dialect == "px4":
        assert d.custom_mode(Mode.TAKEOFF) in shown and d.custom_mode(Mode.HOLD) in shown
    # flown in offboard to the agent's last setpoint (after it the SITL may stop late on a busy
    # machine, and PX4's COM_OF_LOSS_T failsafe then shows Hold: not the agent's doing)
    assert [mode for t, mode in modes if t <= last_sp_t][-1] == d.custom_mode(Mode.OFFBOARD)
    stats = json.loads((tmp_path / "agent.json").read_text())
    assert stats["phase"] == Phase.HOVER.name and stats["autopilot"]["dialect"] == dialect
    assert stats["event_loop"].split()[0] == ("uvloop" if dialect == "px4" else "asyncio")
    assert f"event loop: {stats['event_loop']}" in text
    # The SITL streams ATTITUDE (10 Hz), GLOBAL_POSITION_INT, SYS_STATUS, GPS_RAW_INT, HOME_POSITION and
    # BATTERY_STATUS by default; the agent reads none of them (it asked for LOCAL_POSITION_NED,
    # ATTITUDE_QUATERNION, EXTENDED_SYS_STATE and SYSTEM_TIME, which it keeps).
    assert last_att_t is not None
    if dialect == "px4":
        assert sorted(stats["autopilot"]["streams_stopped"]) == sorted(
            ["ATTITUDE", "GLOBAL_POSITION_INT", "SYS_STATUS", "GPS_RAW_INT", "HOME_POSITION", "BATTERY_STATUS"])
        assert last_att_t < first_sp_t  # stopped at the end of set-up, before the first setpoint
    else:
        assert stats["autopilot"]["streams_stopped"] == [] and last_att_t > first_sp_t + 1.0
