"""`python -m sim_bridge.fuzz`: mutated and hostile MAVLink against every port we open.

One run starts a SITL (6 vehicles, carrier launch, the GCS endpoint, the radio) and one
agent process (vehicle 0, flying configs/small_6.yaml), then sends seeded frames, paced, round-robin to:
SITL vehicles 0-2, the SITL's GCS endpoint, the agent's autopilot port and its swarm
port. Vehicles 3-5 are left alone and watched: their heartbeats (asked for at 5 Hz)
must never pause for a second. At the end it checks that no process died, no
traceback was printed, the SITL's RSS grew by less than 5 % after warm-up, and the
SITL kept real time, and writes a JSON report (FuzzReport).

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

from companion.link.msgdef import swarmdrop as sd  # noqa: E402
from companion.link.wire import Codec, _crc_with_extra, split_datagram  # noqa: E402
from sim_bridge.fleet import find_free_udp_range, terminate_all  # noqa: E402
from sim_bridge.sitl.status import SitlStatus  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
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

    @property
    def ok(self) -> bool:
        return (not self.crashes and not self.tracebacks and self.max_heartbeat_gap_s < 1.0
                and self.rss_growth < 0.05 and self.rtf is not None and self.rtf >= 0.99)


# ---------------------------------------------------------------------------- the corpus
def corpus() -> list[bytes]:
    """Valid frames (some with hostile values) of what the SITL and the agent handle."""
    msgs = []
    for tsys in (0, 1, 2, 3, 255):
        msgs += [
            mavlink.MAVLink_command_long_message(tsys, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 176, 0, 1, 6, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 22, 0, NAN, NAN, NAN, NAN, NAN, NAN, 1e30),
            mavlink.MAVLink_command_long_message(tsys, 1, 511, 0, 33, 2.0 ** 40, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 511, 0, 0, 1, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 510, 0, INF, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_long_message(tsys, 1, 31010, 0, 0, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_command_int_message(tsys, 1, 6, 520, 0, 0, 1, 0, 0, 0, 2 ** 31 - 1, -2 ** 31, NAN),
            mavlink.MAVLink_param_request_list_message(tsys, 1),
            mavlink.MAVLink_param_request_read_message(tsys, 1, b"\xff" * 16, -1),
            mavlink.MAVLink_param_set_message(tsys, 1, b"SD_GEO_KX", 1e30, 9),
            mavlink.MAVLink_param_set_message(tsys, 1, b"SD_GEO_KV", NAN, 9),
            mavlink.MAVLink_param_set_message(tsys, 1, b"COM_OF_LOSS_T", 0.5, 9),
            mavlink.MAVLink_set_position_target_local_ned_message(0, tsys, 1, 1, 0, 1e30, NAN, INF, 1e30, -1e30,
                                                                   NAN, 1e30, 0, 0, NAN, 1e30),
            mavlink.MAVLink_set_position_target_local_ned_message(0, tsys, 1, 1, 3135, 0, 0, 0, 0, 0, 0,
                                                                   NAN, INF, -INF, 0, 0),
            mavlink.MAVLink_set_attitude_target_message(0, tsys, 1, 0, [NAN, 0, 0, 0], 1e30, 0, 0, NAN),
            mavlink.MAVLink_set_attitude_target_message(0, tsys, 1, 128, [1, 0, 0, 0], 1e30, -1e30, INF, INF),
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
        mavlink.MAVLink_command_ack_message(400, 0, 0, 0, 255, 255),
        mavlink.MAVLink_param_value_message(b"MPC_THR_HOVER", NAN, 9, 65535, 65535),
        mavlink.MAVLink_message_interval_message(33, -1),
        sd.MAVLink_swarmdrop_state_message(2 ** 63, 2 ** 63, NAN, INF, 1e30, 0, 0, 0, [NAN, 0, 0, 0], 255, 255, 3),
        sd.MAVLink_swarmdrop_state_message(0, 0, 0, 0, 0, 0, 0, 0, [1, 0, 0, 0], 2, 1, 250),
        sd.MAVLink_swarmdrop_tick_message(2 ** 63),
    ]
    codec = Codec(mavlink, sd)
    out = []
    for i, m in enumerate(msgs):
        sysid = (i * 37) % 256
        out.append(codec.encode(m, sysid, 190, i & 0xFF) if m.get_msgId() not in (59900, 59901)
                   else codec.encode(m, 4, 191, i & 0xFF))
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
            msg = mavlink.MAVLink_command_long_message(k + 1, 1, 511, 0, 0, HEARTBEAT_PERIOD_US, 0, 0, 0, 0, 0)
            s.sendto(codec.encode(msg, 255, 190, 0), ("127.0.0.1", local_ports[k]))
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.is_set():
            for key, _ in self.sel.select(0.05):
                k = key.data
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

    data = yaml.safe_load((ROOT / "configs" / "small_6.yaml").read_text())
    data["duration_s"] = 3600.0
    path = out_dir / "fuzz_mission.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run(frames: int, seed: int, out_dir: Path, rate_hz: float = 12000.0, quiet: bool = False) -> FuzzReport:
    """One fuzz run (module docstring). Every process it starts, it stops."""
    out_dir.mkdir(parents=True, exist_ok=True)
    mission = _write_mission(out_dir)
    base = find_free_udp_range(2 * N_VEHICLES + 3, seed)
    remote, local = base, base + N_VEHICLES  # vehicle k sends to remote + k, listens on local + k
    medium, gcs_remote, swarm = base + 2 * N_VEHICLES, base + 2 * N_VEHICLES + 1, base + 2 * N_VEHICLES + 2
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
        for line in sitl.stdout:
            lines.append(line)
            sitl_log.write(line)
            if "SITL READY" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    agent = None
    watch = None
    try:
        if not ready.wait(120):
            raise RuntimeError("the SITL did not start:\n" + "".join(lines[-20:]))
        gcs_port = int(re.search(r"gcs \(all vehicles\): udp [\d.]+:(\d+)", "".join(lines)).group(1))
        agent_log = out_dir / "agent.log"
        agent = subprocess.Popen([py, "-m", "swarmdrop.cli", "agent", "--vehicle-id", "0", "--autopilot",
                                  f"udpin://127.0.0.1:{remote}", "--mission", str(mission), "--swarm-bind",
                                  f"127.0.0.1:{swarm}", "--swarm-peer", f"127.0.0.1:{medium}", "--log-file",
                                  str(agent_log), "--no-stderr-log"], cwd=ROOT, stdout=subprocess.DEVNULL,
                                 stderr=open(out_dir / "agent.stderr", "w"))
        watch = Watch(remote, {k: local + k for k in WATCHED})
        watch.thread.start()
        targets = {f"sitl_vehicle_{k}": local + k for k in ATTACKED}
        targets |= {"sitl_gcs": gcs_port, "agent_autopilot": remote, "agent_swarm": swarm}
        names, ports = list(targets), list(targets.values())
        per_port = dict.fromkeys(names, 0)
        mut = Mutator(seed)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.bind(("127.0.0.1", 0))
        t0 = time.monotonic()
        rss0, sent, batch = None, 0, 8
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
            lag = t0 + sent / rate_hz - time.monotonic()
            if lag > 0:
                time.sleep(lag)  # pacing: the fuzz is a rate, not a busy loop
            if not quiet and sent % progress_every < batch:
                print(f"\rfuzz: {sent}/{frames} frames", end="", file=sys.stderr, flush=True)
        wall = time.monotonic() - t0
        time.sleep(1.0)  # the last heartbeat window (bounded: the watcher's gap covers it)
        tx.close()
        rss1 = _rss_mb(sitl.pid)
        if not quiet:
            print(file=sys.stderr)
        crashes = [f"{name} exited with {p.poll()}" for name, p in (("sitl", sitl), ("agent", agent))
                   if p.poll() is not None]
        rtf, rtfs = _status_rtfs(lines, wall + 1.0)
        watch.close()
        rss0 = rss0 if rss0 is not None else rss1
        return FuzzReport(
            frames=sent, seed=seed, wall_s=wall, frames_per_s=sent / wall, crashes=crashes, tracebacks=[],
            max_heartbeat_gap_s=watch.max_gap_s, sitl_rss_mb_start=rss0, sitl_rss_mb_end=rss1,
            rss_growth=(rss1 - rss0) / rss0 if rss0 else float("nan"),
            rtf=rtf, rtf_min_window=min(rtfs) if rtfs else None,
            per_port=per_port)
    finally:
        if watch is not None and not watch.stop.is_set():
            watch.close()
        terminate_all((agent, sitl))
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
    p = argparse.ArgumentParser(prog="python -m sim_bridge.fuzz", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--rate", type=float, default=12000.0, help="frames per second sent (paced)")
    p.add_argument("--out", default="runs/fuzz", help="logs of the SITL and the agent")
    p.add_argument("--json", default="bench/results/fuzz.json", help="the report")
    args = p.parse_args(argv)
    out = Path(args.out)
    report = run(args.frames, args.seed, out, args.rate)
    report.tracebacks = find_tracebacks(out)
    data = dataclasses.asdict(report) | {"ok": report.ok}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(data, indent=1))
    print(json.dumps(data, indent=1))
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
