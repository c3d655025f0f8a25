"""`swarmdrop simulate --live HOST:PORT`: a headless run streamed to a console in real time.

`LiveStream` is an observer of the headless runner (sim_bridge.runs.headless.TICK_OBSERVERS):
on every agent tick it waits until the wall clock has caught up with mission time (so the
run flies at real-time pace, `speed` times faster if asked) and sends the states the agents
published that tick as SWARMDROP_STATE frames, exactly as agents put them on the swarm link
(sysid vehicle_id + 1, mission NED, stamps in Unix µs: the wall clock at the start plus
mission time), packed into datagrams of at most 1,400 bytes, to the console's swarm port
(`swarmdrop console --swarm-bind HOST:PORT`).

Any size: SWARMDROP_STATE.vehicle_id is a byte and sysids stop at 250, so a run of more than
250 vehicles sends vehicle 250 b + k as vehicle_id k, sysid k + 1, from component
SIM_BANK_COMPID_BASE + b (the console's convention, swarmdrop/console/live.py; a test keeps
the two equal). A console that is not there costs nothing but the sends.
"""
from __future__ import annotations

import math
import socket
import time
from typing import Callable

import numpy as np

from companion.link.enums import MavComponent, MsgId
from companion.link.msgdef import swarmdrop as sd
from companion.link.wire import Codec
from companion.swarm import SwarmStates
from sim_bridge.runs import headless

SIM_BANK_COMPID_BASE = 25
"""MAV_COMP_ID_USER1: bank b of SIM_BANK_SIZE vehicles comes from component 25 + b (as the console reads it)."""
SIM_BANK_SIZE = 250
SIM_BANKS = 4
DATAGRAM_BYTES = 1400
DEFAULT_ADDRESS = ("127.0.0.1", 14650)
"""The console's default swarm port (swarmdrop console --swarm-bind)."""


class LiveStream:
    """Streams the headless run's published states to addr (use as a context manager).

    Args:
        addr: the console's swarm port (host, port).
        n_vehicles: the mission's vehicle count (more than SIM_BANK_SIZE: banked ids).
        speed: mission seconds per wall second (1: real time).
    Raises:
        ValueError: more than SIM_BANKS * SIM_BANK_SIZE vehicles, or a speed not > 0.
    """

    def __init__(self, addr: tuple[str, int], n_vehicles: int, speed: float = 1.0,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 sleep: Callable[[float], None] = time.sleep):
        if n_vehicles > SIM_BANKS * SIM_BANK_SIZE:
            raise ValueError(f"{n_vehicles} vehicles: a live stream carries at most {SIM_BANKS * SIM_BANK_SIZE}")
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed {speed!r}: must be > 0")
        self.addr = addr
        self.banked = n_vehicles > SIM_BANK_SIZE
        self.speed = speed
        self.clock, self.wall, self.sleep = clock, wall, sleep
        self.codec = Codec(sd)
        self.build = self.codec.builder(MsgId.SWARMDROP_STATE)
        self.sock: socket.socket | None = None
        self._t0: float | None = None
        self._epoch_us = 0
        self._seq = 0
        self.states_sent = 0
        self.datagrams_sent = 0
        self.send_errors = 0

    def __enter__(self) -> "LiveStream":
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        headless.TICK_OBSERVERS.append(self)
        return self

    def __exit__(self, *exc) -> None:
        if self in headless.TICK_OBSERVERS:
            headless.TICK_OBSERVERS.remove(self)
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def __call__(self, t_s: float, published: SwarmStates | None) -> None:
        """The observer: pace to the wall clock, then send what was published at t_s."""
        if self._t0 is None:
            self._t0 = self.clock() - t_s / self.speed
            self._epoch_us = int(round((self.wall() - t_s) * 1e6))
        lag = self._t0 + t_s / self.speed - self.clock()
        if lag > 0:
            self.sleep(lag)  # real-time pace: the run waits for the wall clock
        if published is not None and len(published):
            self._send(self.frames(published))

    def frames(self, s: SwarmStates) -> list[bytes]:
        """SWARMDROP_STATE frames of the published rows."""
        out = []
        ep = self._epoch_us
        ids = np.asarray(s.vehicle_id).tolist()
        stamp = np.asarray(s.stamp_s, float).tolist()
        go = np.asarray(s.t_go_s, float).tolist()
        pos = np.asarray(s.pos_ned_m, float).tolist()
        vel = np.asarray(s.vel_ned_mps, float).tolist()
        q = np.asarray(s.att_q_wxyz, float).tolist()
        phase = np.asarray(s.phase).tolist()
        flags = np.asarray(s.flags).tolist()
        for r, k in enumerate(ids):
            bank, vid = divmod(int(k), SIM_BANK_SIZE)
            compid = SIM_BANK_COMPID_BASE + bank if self.banked else MavComponent.MAV_COMP_ID_ONBOARD_COMPUTER
            p, v = pos[r], vel[r]
            values = self.build(time_usec=ep + int(round(stamp[r] * 1e6)),
                                t_go_usec=ep + int(round(go[r] * 1e6)) if math.isfinite(go[r]) else 0,
                                x=p[0], y=p[1], z=p[2], vx=v[0], vy=v[1], vz=v[2], q=q[r], phase=int(phase[r]),
                                flags=int(flags[r]) & 0xFF, vehicle_id=vid)
            self._seq = (self._seq + 1) & 0xFF
            out.append(self.codec.encode_fields(MsgId.SWARMDROP_STATE, values, vid + 1, compid, self._seq))
        return out

    def _send(self, frames: list[bytes]) -> None:
        buf = b""
        for f in frames:
            if len(buf) + len(f) > DATAGRAM_BYTES and buf:
                self._sendto(buf)
                buf = b""
            buf += f
        if buf:
            self._sendto(buf)
        self.states_sent += len(frames)

    def _sendto(self, buf: bytes) -> None:
        assert self.sock is not None  # (frames are sent only inside the context)
        try:
            self.sock.sendto(buf, self.addr)
            self.datagrams_sent += 1
        except OSError:  # nobody listening (ICMP), a full buffer: the run goes on
            self.send_errors += 1
