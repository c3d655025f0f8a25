"""A synthetic swarm on the swarm link: SWARMDROP_STATE frames of N vehicles flying circles.

For trying the console and measuring it without a simulator (the bench's 1,000 vehicles at
10 Hz, the browser tests): every vehicle orbits its own slot on a grid while the grid's
centre drifts north, phases spread over the seven, stamps on the wall clock. Vehicles past
249 are sent in the simulated feed's banks (swarmdrop.console.live, "Vehicle ids beyond
249"). `python -m swarmdrop.console.synthetic --vehicles 1000 --to 127.0.0.1:14650`.
"""
from __future__ import annotations

import argparse
import math
import socket
import sys
import time

import numpy as np

from companion.link.enums import MavComponent, MsgId
from companion.link.msgdef import swarmdrop as sd
from companion.link.wire import Codec
from swarmdrop.console.live import SIM_BANK_COMPID_BASE, SIM_BANK_SIZE

DATAGRAM_BYTES = 1400


class SyntheticSwarm:
    """N synthetic vehicles; `frames(t)` are their states at wall time t.

    Args:
        n: vehicles (up to 1,000).
        spacing_m: grid spacing of their slots.
        phases: give the vehicles different phases (else all TRANSIT).
    """

    def __init__(self, n: int, spacing_m: float = 6.0, phases: bool = True, t0: float | None = None):
        self.n = n
        self.codec = Codec(sd)
        self.build = self.codec.builder(MsgId.SWARMDROP_STATE)
        side = max(1, math.ceil(math.sqrt(n)))
        k = np.arange(n)
        self.slot = np.stack([(k // side - side / 2) * spacing_m, (k % side - side / 2) * spacing_m,
                              -10.0 - (k % 3) * 2.0], axis=1)
        self.phase = (k % 7) if phases else np.full(n, 3)
        self.t0 = time.time() if t0 is None else t0
        self.seq = 0

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(pos, vel, yaw) of every vehicle at wall time t."""
        tau = t - self.t0
        w = 0.6
        ph = np.arange(self.n) * 0.37
        centre = np.array([0.5 * tau, 0.0, 0.0])
        r = 1.5
        pos = self.slot + centre + np.stack([r * np.cos(w * tau + ph), r * np.sin(w * tau + ph), np.zeros(self.n)], 1)
        vel = np.stack([-r * w * np.sin(w * tau + ph) + 0.5, r * w * np.cos(w * tau + ph), np.zeros(self.n)], 1)
        yaw = np.arctan2(vel[:, 1], vel[:, 0])
        return pos, vel, yaw

    def frames(self, t: float, ids=None) -> list[bytes]:
        """Encoded states of the given vehicles (all) at wall time t."""
        pos, vel, yaw = self.state(t)
        out = []
        t_us = int(t * 1e6)
        t_go = int((self.t0 + 5.0) * 1e6)
        for k in (range(self.n) if ids is None else ids):
            bank, vid = divmod(int(k), SIM_BANK_SIZE)
            compid = SIM_BANK_COMPID_BASE + bank if self.n > SIM_BANK_SIZE else MavComponent.MAV_COMP_ID_ONBOARD_COMPUTER
            half = 0.5 * float(yaw[k])
            values = self.build(time_usec=t_us, t_go_usec=t_go, x=float(pos[k, 0]), y=float(pos[k, 1]),
                                z=float(pos[k, 2]), vx=float(vel[k, 0]), vy=float(vel[k, 1]), vz=0.0,
                                q=(math.cos(half), 0.0, 0.0, math.sin(half)), phase=int(self.phase[k]), flags=3,
                                vehicle_id=vid)
            self.seq = (self.seq + 1) & 0xFF
            out.append(self.codec.encode_fields(MsgId.SWARMDROP_STATE, values, vid + 1, compid, self.seq))
        return out


def send_batched(sock: socket.socket, frames: list[bytes], addr: tuple[str, int]) -> int:
    """Send frames packed into datagrams of at most DATAGRAM_BYTES; returns the datagram count."""
    buf, count = b"", 0
    for f in frames:
        if len(buf) + len(f) > DATAGRAM_BYTES and buf:
            sock.sendto(buf, addr)
            count += 1
            buf = b""
        buf += f
    if buf:
        sock.sendto(buf, addr)
        count += 1
    return count


def run(n: int, rate_hz: float, addr: tuple[str, int], duration_s: float | None = None, stop=None) -> None:
    """Send N vehicles' states at rate_hz each (spread over the period) until duration_s or stop()."""
    swarm = SyntheticSwarm(n)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
    slices = max(1, int(round(100.0 / rate_hz)))  # 100 sends per second, each a slice of the fleet
    period = 1.0 / (rate_hz * slices)
    t_start = time.monotonic()
    k = 0
    try:
        while (duration_s is None or time.monotonic() - t_start < duration_s) and not (stop and stop()):
            ids = range(k % slices, n, slices)
            send_batched(sock, swarm.frames(time.time(), ids), addr)
            k += 1
            delay = t_start + k * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # pacing the feed, not waiting for anything
    finally:
        sock.close()


def main(argv: list[str] | None = None) -> int:
    from companion.node.cli import _hostport

    p = argparse.ArgumentParser(prog="python -m swarmdrop.console.synthetic", description=__doc__.split("\n\n")[0])
    p.add_argument("--vehicles", type=int, default=1000, help="1 to 1000 (default 1000)")
    p.add_argument("--rate", type=float, default=10.0, help="states per second per vehicle (default 10)")
    p.add_argument("--to", type=_hostport, default=("127.0.0.1", 14650), metavar="HOST:PORT",
                   help="the console's swarm port (default 127.0.0.1:14650)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: never)")
    a = p.parse_args(argv)
    if not 1 <= a.vehicles <= 1000 or not 0 < a.rate <= 50:
        print("--vehicles 1..1000, --rate above 0 and up to 50", file=sys.stderr)
        return 2
    try:
        run(a.vehicles, a.rate, a.to, a.duration)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
