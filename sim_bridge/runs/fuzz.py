"""`python -m sim_bridge.runs.fuzz`: mutated and hostile MAVLink against every port we open.

One run starts a SITL (6 vehicles, carrier launch, the GCS endpoint, the radio) and one
agent process (vehicle 0, flying configs/small_6.yaml; the fuzz waits until it is set up),
and with `console` (`make fuzz`) an operator's console (`swarmdrop console`, listening on a
swarm port and a GCS port), then
sends seeded frames, paced, round-robin to: SITL vehicles 0-2, the SITL's GCS endpoint, the
agent's autopilot port and its swarm port, and the console's swarm and GCS ports.
Vehicles 3-5 are left alone and watched: their heartbeats (asked for at 5 Hz) must never
pause for a second. At the end it checks that no process died, no traceback was printed,
the SITL's (and the console's) RSS grew by less than 5 % after warm-up, and the SITL kept
real time, and writes a JSON report (FuzzReport).

The frames: valid frames of the messages the SITL and agent handle (built with
pymavlink, many with NaN, inf or huge values), then mutated: bit flips, byte
overwrites, truncation, junk, length and incompat-flag changes, and, for half of
the payload mutations, a recomputed CRC so that the mutation reaches the handlers.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import selectors
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.enums import (  # noqa: E402
    AttitudeTargetTypemask,
    MavCmd,
    MavFrame,
    MavResult,
    MsgId,
    PositionTargetTypemask,
)
from companion.link.framing import _crc_with_extra, split_datagram
from companion.link.msgdef import swarmdrop as sd  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from companion.node.setup import SET_UP_LOG_TEXT  # noqa: E402
from sim_bridge.runs.procs import terminate_all  # noqa: E402
from sim_bridge.sitl.ports import find_free_udp_range  # noqa: E402
from sim_bridge.sitl.status import SitlStatus  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
N_VEHICLES = 6
ATTACKED = (0, 1, 2)
WATCHED = (3, 4, 5)
HEARTBEAT_PERIOD_US = 200_000
NAN, INF = float("nan"), float("inf")


@dataclass
class FuzzReport:
    """What one fuzz run measured (written as JSON)."""

    frames: int
    seed: int
    wall_s: float
    frames_per_s: float
    crashes: list[str]
    tracebacks: list[str]
    max_heartbeat_gap_s: float
    """Largest gap between heartbeats of the untouched vehicles (asked for every 0.2 s)."""
    sitl_rss_mb_start: float
    sitl_rss_mb_end: float
    rss_growth: float
    rtf: float | None
    """Simulated over wall time across the fuzz (the SITL's status lines)."""
    rtf_min_window: float | None
    """Smallest real-time factor of the SITL's 1 s status windows during the fuzz (noisy)."""
    per_port: dict[str, int] = field(default_factory=dict)
    console_rss_mb_start: float | None = None
    """The console's RSS after warm-up and at the end (None: no console in the run)."""
    console_rss_mb_end: float | None = None
    console_rss_growth: float | None = None

    @property
    def ok(self) -> bool:
        return (not self.crashes and not self.tracebacks and self.max_heartbeat_gap_s < 1.0
                and self.rss_growth < 0.05 and self.rtf is not None and self.rtf >= 0.99
                and (self.console_rss_growth is None or self.console_rss_growth < 0.05))


C = MavCmd
LOCAL_NED = MavFrame.MAV_FRAME_LOCAL_NED
_PT = PositionTargetTypemask
ACCEL_ONLY = (_PT.POSITION_TARGET_TYPEMASK_X_IGNORE | _PT.POSITION_TARGET_TYPEMASK_Y_IGNORE
              | _PT.POSITION_TARGET_TYPEMASK_Z_IGNORE | _PT.POSITION_TARGET_TYPEMASK_VX_IGNORE
              | _PT.POSITION_TARGET_TYPEMASK_VY_IGNORE | _PT.POSITION_TARGET_TYPEMASK_VZ_IGNORE
              | _PT.POSITION_TARGET_TYPEMASK_YAW_IGNORE | _PT.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
"""SET_POSITION_TARGET_LOCAL_NED type_mask: acceleration only (3135)."""
ATT_IGNORE = AttitudeTargetTypemask.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE

# ---------------------------------------------------------------------------- the corpus
def corpus() -> list[bytes]:
    """Valid frames (some with hostile values) of what the SITL and the agent handle."""
    msgs = []
    for tsys in (0, 1, 2, 3, 255):
        msgs += [
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_NAV_TAKEOFF, 0, NAN, NAN, NAN, NAN, NAN, NAN, 1e30),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_SET_MESSAGE_INTERVAL, 0, MsgId.GLOBAL_POSITION_INT,
                                                 2.0 ** 40, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_SET_MESSAGE_INTERVAL, 0, MsgId.HEARTBEAT, 1, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_GET_MESSAGE_INTERVAL, 0, INF, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_REQUEST_MESSAGE, 0, MsgId.AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, C.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_int_message(tsys, 1, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                               C.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 0, 0, 1, 0, 0, 0, 2 ** 31 - 1,
                                               -2 ** 31, NAN),
            mavlink.MAVLink_param_request_list_message(tsys, 1),
            mavlink.MAVLink_param_request_read_message(tsys, 1, b"\xff" * 16, -1),
            mavlink.MAVLink_param_set_message(tsys, 1, b"SD_GEO_KR", 1e30, 9),
            mavlink.MAVLink_param_set_message(tsys, 1, b"SD_GEO_KOM", NAN, 9),
            mavlink.MAVLink_param_set_message(tsys, 1, b"COM_OF_LOSS_T", 0.5, 9),
            mavlink.MAVLink_set_position_target_local_ned_message(0, tsys, 1, LOCAL_NED, 0, 1e30, NAN, INF, 1e30, -1e30,
                                                                   NAN, 1e30, 0, 0, NAN, 1e30),
            mavlink.MAVLink_set_position_target_local_ned_message(0, tsys, 1, LOCAL_NED, ACCEL_ONLY, 0, 0, 0, 0, 0, 0,
                                                                   NAN, INF, -INF, 0, 0),
            mavlink.MAVLink_set_attitude_target_message(0, tsys, 1, 0, [NAN, 0, 0, 0], 1e30, 0, 0, NAN),
            mavlink.MAVLink_set_attitude_target_message(0, tsys, 1, ATT_IGNORE, [1, 0, 0, 0], 1e30, -1e30, INF, INF),
            mavlink.MAVLink_set_gps_global_origin_message(tsys, 2 ** 31 - 1, -2 ** 31, 2 ** 31 - 1),
            mavlink.MAVLink_setup_signing_message(tsys, 1, list(range(32)), 2 ** 48 - 1),
        ]
    msgs += [
        mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3),
        mavlink.MAVLink_timesync_message(0, 2 ** 62),
        mavlink.MAVLink_ping_message(2 ** 63, 2 ** 31, 0, 0),
        mavlink.MAVLink_mission_request_list_message(1, 1, 0),
        mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(range(251))),
        mavlink.MAVLink_local_position_ned_message(2 ** 31, NAN, INF, 1e30, 0, 0, 0),
        mavlink.MAVLink_attitude_quaternion_message(0, NAN, 0, 0, 0, 1e30, 0, 0, [0, 0, 0, 0]),
        mavlink.MAVLink_system_time_message(2 ** 63, 2 ** 31),
        mavlink.MAVLink_gps_global_origin_message(2 ** 31 - 1, 2 ** 31 - 1, -2 ** 31, 0),
        mavlink.MAVLink_statustext_message(6, b"\xff" * 50, 0, 0),
        mavlink.MAVLink_command_ack_message(C.MAV_CMD_COMPONENT_ARM_DISARM, MavResult.MAV_RESULT_ACCEPTED, 0, 0,
                                           255, 255),
        mavlink.MAVLink_param_value_message(b"MPC_THR_HOVER", NAN, 9, 65535, 65535),
        mavlink.MAVLink_message_interval_message(MsgId.GLOBAL_POSITION_INT, -1),
        sd.MAVLink_swarmdrop_state_message(2 ** 63, 2 ** 63, NAN, INF, 1e30, 0, 0, 0, [NAN, 0, 0, 0], 255, 255, 3),
        sd.MAVLink_swarmdrop_state_message(0, 0, 0, 0, 0, 0, 0, 0, [1, 0, 0, 0], 2, 1, 250),
        sd.MAVLink_swarmdrop_tick_message(2 ** 63),
        sd.MAVLink_swarmdrop_state_message(2 ** 62, 0, 1.0, 2.0, -10.0, 0, 0, 0, [1, 0, 0, 0], 3, 3, 0, 2 ** 32 - 1),
        # plans and slot tables (a console's commands), valid and hostile
        sd.MAVLink_swarmdrop_plan_message(2 ** 63, 1, [0.0] * 24, 3.0, 10.0, 4.0, 0.0, 2.0, [0] * 32, [0] * 32, 1, 1, 0,
                                          1, 6),
        sd.MAVLink_swarmdrop_plan_message(0, 2 ** 32 - 1, [NAN, INF, 1e30] * 8, NAN, -1.0, 0.0, INF, -5.0, [255] * 32,
                                          [255] * 32, 255, 255, 255, 255, 255),
        sd.MAVLink_swarmdrop_plan_message(1, 7, [1e30] * 24, 1e30, 1e30, 1e30, 1e30, 1e30, [0] * 32, [1] * 32, 7, 8, 4,
                                          2, 6),
        sd.MAVLink_swarmdrop_slots_message(1, 0, 6, list(range(6)) + [0] * 194),
        sd.MAVLink_swarmdrop_slots_message(2 ** 32 - 1, 250, 255, [255] * 200),
    ]
    codec = Codec(mavlink, sd)
    out = []
    for i, m in enumerate(msgs):
        sysid = (i * 37) % 256
        swarm = (MsgId.SWARMDROP_STATE, MsgId.SWARMDROP_TICK, MsgId.SWARMDROP_PLAN, MsgId.SWARMDROP_SLOTS)
        out.append(codec.encode(m, sysid, 190, i & 0xFF) if m.get_msgId() not in swarm
                   else codec.encode(m, 4 if m.get_msgId() != MsgId.SWARMDROP_PLAN else 255, 191, i & 0xFF))
    return out


class Mutator:
    """Seeded mutations of corpus frames."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)
        self.corpus = corpus()
        self.codec = Codec(mavlink, sd)

    def frame(self) -> bytes:
        rng = self.rng
        f = bytearray(self.corpus[int(rng.integers(len(self.corpus)))])
        kind = int(rng.integers(8))
        if kind == 0:
            return bytes(f)  # the hostile-but-valid frame itself
        if kind in (1, 2):  # payload bytes changed, CRC recomputed: reaches the handlers
            for _ in range(int(rng.integers(1, 6))):
                if len(f) > 12:
                    f[10 + int(rng.integers(len(f) - 12))] = int(rng.integers(256))
            return self._recrc(f)
        if kind == 3:  # bit flips anywhere
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(len(f)))
                f[i] ^= 1 << int(rng.integers(8))
            return bytes(f)
        if kind == 4:  # truncated or extended
            cut = int(rng.integers(len(f) + 1))
            return bytes(f[:cut]) + rng.bytes(int(rng.integers(0, 8)))
        if kind == 5:  # incompat / compat flags, CRC recomputed
            f[2] = int(rng.integers(256))
            f[3] = int(rng.integers(256))
            return self._recrc(f)
        if kind == 6:  # length field lies
            f[1] = int(rng.integers(256))
            return bytes(f)
        return rng.bytes(int(rng.integers(1, 300)))  # junk

    def _recrc(self, f: bytearray) -> bytes:
        end = 10 + f[1]
        if f[0] != 0xFD or len(f) < end + 2:
            return bytes(f)
        extra = self.codec.crc_extra(f[7] | f[8] << 8 | f[9] << 16)
        if extra is None:
            return bytes(f)
        crc = _crc_with_extra(bytes(f[1:end]), extra)
        f[end:end + 2] = crc.to_bytes(2, "little")
        return bytes(f)


# ---------------------------------------------------------------------------- processes and watchers
def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


class Watch:
    """Listens where the watched vehicles send; records their heartbeat times."""

    def __init__(self, remote_base: int, local_ports: dict[int, int]):
        self.socks = {}
        self.last: dict[int, float] = {}
        self.max_gap_s = 0.0
        self.sel = selectors.DefaultSelector()
        self.stop = threading.Event()
        self.t_from = time.monotonic() + 1.5
        """Gaps count from here: the 1 Hz schedule runs out before the 5 Hz one starts."""
        codec = Codec(mavlink)
        for k in WATCHED:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", remote_base + k))
            s.setblocking(False)
            self.socks[k] = s
            self.sel.register(s, selectors.EVENT_READ, k)
            msg = mavlink.MAVLink_command_long_message(k + 1, 1, C.MAV_CMD_SET_MESSAGE_INTERVAL, 0, MsgId.HEARTBEAT,
                                                     HEARTBEAT_PERIOD_US, 0, 0, 0, 0, 0)
            s.sendto(codec.encode(msg, 255, 190, 0), ("127.0.0.1", local_ports[k]))
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.is_set():
            for key, _ in self.sel.select(0.05):
                k = key.data
                assert isinstance(key.fileobj, socket.socket)  # (only the sockets of self.socks are registered)
                while True:
                    try:
                        data = key.fileobj.recv(65535)
                    except BlockingIOError:
                        break
                    frames, _ = split_datagram(data)
                    now = time.monotonic()
                    for f in frames:
                        if f[0] == 0xFD and f[7] == 0 and f[8] == 0 and f[9] == 0 and f[5] == k + 1:
                            if k in self.last and self.last[k] >= self.t_from:
                                self.max_gap_s = max(self.max_gap_s, now - self.last[k])
                            self.last[k] = now
        now = time.monotonic()
        for k in WATCHED:  # a vehicle that went quiet at the end counts too
            if k in self.last:
                self.max_gap_s = max(self.max_gap_s, now - self.last[k])

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        for s in self.socks.values():
            s.close()


def _write_mission(out_dir: Path) -> Path:
    import yaml

    from companion.config import read_yaml

    data = read_yaml(ROOT / "configs" / "small_6.yaml")
    data["duration_s"] = 3600.0
    path = out_dir / "fuzz_mission.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _wait_ready(proc: subprocess.Popen, log: Path, marker: str, what: str, timeout_s: float = 60.0) -> None:
    """Poll `log` until it holds `marker` (the process's ready line).

    Raises:
        RuntimeError: `proc` exited or `timeout_s` passed first (the log's tail says why); the
            process is stopped.
    """
    deadline = time.monotonic() + timeout_s
    while not log.exists() or marker not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            terminate_all((proc,))
            tail = log.read_text(errors="replace")[-2000:] if log.exists() else "(no log)"
            raise RuntimeError(f"{what} did not start:\n" + tail)
        time.sleep(0.05)  # (polling its log for the ready line)


def _start_console(py: str, mission: Path, swarm: int, gcs: int, out_dir: Path) -> subprocess.Popen:
    """`swarmdrop console` on a swarm port and a GCS port (its page on a free port), ready.

    Raises:
        RuntimeError: it did not start (its output says why; e.g. aiohttp missing).
    """
    log = out_dir / "console.log"
    proc = subprocess.Popen([py, "-m", "swarmdrop.cli", "console", "--mission", str(mission), "--swarm-bind",
                             f"127.0.0.1:{swarm}", "--gcs", f"udpin://127.0.0.1:{gcs}", "--port", "0"], cwd=ROOT,
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)
    _wait_ready(proc, log, "CONSOLE READY", "the console")
    return proc


def _start_agent(py: str, mission: Path, autopilot: int, swarm: int, medium: int, out_dir: Path) -> subprocess.Popen:
    """`swarmdrop agent` for vehicle 0, set up (its autopilot heard, parameters read).

    The fuzz starts only then: like PX4, the SITL fixes a vehicle's reply address at first
    contact, so a fuzzer that spoke first would own vehicle 0's link and the agent would never
    hear its autopilot (a run that fuzzes an agent waiting for a HEARTBEAT tests little).
    It sets Hold as the loss action, as the fleet does: the SITL boots with PX4's stock
    COM_OBL_RC_ACT 0, which the agent refuses (exit 4).

    Raises:
        RuntimeError: the agent exited or was not set up within 60 s (its log's tail says why).
    """
    log = out_dir / "agent.log"
    log.unlink(missing_ok=True)  # the agent appends to its log: an earlier run's ready line must not count
    proc = subprocess.Popen([py, "-m", "swarmdrop.cli", "agent", "--vehicle-id", "0", "--autopilot",
                             f"udpin://127.0.0.1:{autopilot}", "--mission", str(mission), "--swarm-bind",
                             f"127.0.0.1:{swarm}", "--swarm-peer", f"127.0.0.1:{medium}", "--log-file", str(log),
                             "--no-stderr-log", "--set-loss-action", "hold", "--stats",
                             str(out_dir / "agent.json")],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=open(out_dir / "agent.stderr", "w"))
    _wait_ready(proc, log, SET_UP_LOG_TEXT, "the agent")
    return proc


def run(frames: int, seed: int, out_dir: Path, rate_hz: float = 12000.0, quiet: bool = False,
        console: bool = False) -> FuzzReport:
    """One fuzz run (module docstring); console: also start and attack `swarmdrop console`.
    Every process it starts, it stops."""
    out_dir.mkdir(parents=True, exist_ok=True)
    mission = _write_mission(out_dir)
    base = find_free_udp_range(2 * N_VEHICLES + 5, seed)
    remote, local = base, base + N_VEHICLES  # vehicle k sends to remote + k, listens on local + k
    medium, gcs_remote, swarm = base + 2 * N_VEHICLES, base + 2 * N_VEHICLES + 1, base + 2 * N_VEHICLES + 2
    console_swarm, console_gcs = base + 2 * N_VEHICLES + 3, base + 2 * N_VEHICLES + 4
    py = sys.executable
    sitl_log = open(out_dir / "sitl.log", "w")
    # No --scenario: its recorder keeps every sample of the run, memory that grows by design and
    # would hide (or fake) a leak; the agent's mission has the SITL's default home as its origin.
    sitl = subprocess.Popen([py, "-m", "sim_bridge.sitl", "--vehicles", str(N_VEHICLES), "--launch", "carrier",
                             "--seed", str(seed), "--remote-base-port",
                             str(remote), "--local-base-port", str(local), "--medium-port", str(medium), "--gcs",
                             "--gcs-port", str(gcs_remote), "--status"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert sitl.stdout is not None  # (stdout=PIPE)
        for line in sitl.stdout:
            lines.append(line)
            sitl_log.write(line)
            if "SITL READY" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    agent = None
    watch = None
    console_proc = None
    try:
        if not ready.wait(120):
            raise RuntimeError("the SITL did not start:\n" + "".join(lines[-20:]))
        gcs_line = re.search(r"gcs \(all vehicles\): udp [\d.]+:(\d+)", "".join(lines))
        assert gcs_line is not None  # (with --gcs the SITL prints this line before SITL READY)
        gcs_port = int(gcs_line.group(1))
        agent = _start_agent(py, mission, remote, swarm, medium, out_dir)
        if console:
            console_proc = _start_console(py, mission, console_swarm, console_gcs, out_dir)
        watch = Watch(remote, {k: local + k for k in WATCHED})
        watch.thread.start()
        targets = {f"sitl_vehicle_{k}": local + k for k in ATTACKED}
        targets |= {"sitl_gcs": gcs_port, "agent_autopilot": remote, "agent_swarm": swarm}
        if console:
            targets |= {"console_swarm": console_swarm, "console_gcs": console_gcs}
        names, ports = list(targets), list(targets.values())
        per_port = dict.fromkeys(names, 0)
        mut = Mutator(seed)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.bind(("127.0.0.1", 0))
        t0 = time.monotonic()
        rss0, sent, batch = None, 0, 8
        crss0: float | None = None
        progress_every = max(1, frames // 20)
        while sent < frames:
            i = (sent // batch) % len(ports)
            n = min(batch, frames - sent)
            blob = b"".join(mut.frame() for _ in range(n))
            try:
                tx.sendto(blob[:65000], ("127.0.0.1", ports[i]))
            except OSError:
                pass  # ICMP unreachable from a port that closed: counted as sent, checked below
            per_port[names[i]] += n
            sent += n
            if rss0 is None and sent >= frames // 10:
                rss0 = _rss_mb(sitl.pid)  # after the SITL's own warm-up
                crss0 = _rss_mb(console_proc.pid) if console_proc is not None else None
            lag = t0 + sent / rate_hz - time.monotonic()
            if lag > 0:
                time.sleep(lag)  # pacing: the fuzz is a rate, not a busy loop
            if not quiet and sent % progress_every < batch:
                print(f"\rfuzz: {sent}/{frames} frames", end="", file=sys.stderr, flush=True)
        wall = time.monotonic() - t0
        time.sleep(1.0)  # the last heartbeat window (bounded: the watcher's gap covers it)
        tx.close()
        rss1 = _rss_mb(sitl.pid)
        crss1 = _rss_mb(console_proc.pid) if console_proc is not None else None
        if not quiet:
            print(file=sys.stderr)
        crashes = [f"{name} exited with {p.poll()}" for name, p in (("sitl", sitl), ("agent", agent),
                                                                   ("console", console_proc))
                   if p is not None and p.poll() is not None]
        rtf, rtfs = _status_rtfs(lines, wall + 1.0)
        watch.close()
        rss0 = rss0 if rss0 is not None else rss1
        return FuzzReport(
            frames=sent, seed=seed, wall_s=wall, frames_per_s=sent / wall, crashes=crashes, tracebacks=[],
            max_heartbeat_gap_s=watch.max_gap_s, sitl_rss_mb_start=rss0, sitl_rss_mb_end=rss1,
            rss_growth=(rss1 - rss0) / rss0 if rss0 else float("nan"),
            rtf=rtf, rtf_min_window=min(rtfs) if rtfs else None,
            per_port=per_port, console_rss_mb_start=crss0, console_rss_mb_end=crss1,
            console_rss_growth=(crss1 - crss0) / crss0 if crss0 and crss1 is not None else None)
    finally:
        if watch is not None and not watch.stop.is_set():
            watch.close()
        terminate_all((agent, sitl, console_proc))
        sitl_log.close()


def _status_rtfs(lines: list[str], window_s: float) -> tuple[float | None, list[float]]:
    """(RTF over the last window_s of wall time, RTF of each status interval in it)."""
    st = []
    for line in lines:
        status = SitlStatus.from_line(line.rstrip("\n"))
        if status is not None:
            st.append((status.wall_s, status.sim_s))
    if len(st) < 2:
        return None, []
    t_end = st[-1][0]
    st = [s for s in st if s[0] >= t_end - window_s]
    if len(st) < 2 or st[-1][0] <= st[0][0]:
        return None, []
    overall = (st[-1][1] - st[0][1]) / (st[-1][0] - st[0][0])
    return overall, [(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(st, st[1:]) if b[0] > a[0]]


def find_tracebacks(out_dir: Path) -> list[str]:
    """Files of the run that contain a Python traceback."""
    return [p.name for p in sorted(out_dir.glob("*.log")) + sorted(out_dir.glob("*.stderr"))
            if "Traceback" in p.read_text(errors="replace")]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sim_bridge.runs.fuzz", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--rate", type=float, default=12000.0, help="frames per second sent (paced)")
    p.add_argument("--out", default="runs/fuzz", help="logs of the SITL and the agent")
    p.add_argument("--json", default="bench/results/fuzz.json", help="the report")
    p.add_argument("--no-console", action="store_true",
                   help="leave the operator's console out (default: attack a `swarmdrop console` too)")
    args = p.parse_args(argv)
    out = Path(args.out)
    report = run(args.frames, args.seed, out, args.rate, console=not args.no_console)
    report.tracebacks = find_tracebacks(out)
    data = dataclasses.asdict(report) | {"ok": report.ok}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(data, indent=1))
    print(json.dumps(data, indent=1))
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
