"""What the console's page and server say to each other over the websocket (docs/console.md).

Server to page:

* **frame** (binary, one websocket message per frame, `--frame-rate` Hz, 20 by default):
  a little-endian header and packed arrays, one entry per vehicle, that the page views
  with typed arrays without copying or parsing (`pack_frame`, `frame_layout`):

  ========== ======= ===========================================================
  offset     type    meaning
  ========== ======= ===========================================================
  0          u32     magic ``FRAME_MAGIC`` ("SDF1")
  4          u32     n, vehicles in the arrays
  8          f64     t: the data's clock, s (live: Unix time of the swarm's clock;
                     replay: mission time)
  16         f64     t_go: the transit start the swarm holds (same clock; NaN none)
  24         u32     frame sequence number
  28         u32     flags: bit 0 replay, bit 1 playing, bit 2 live clock
  32 ...     f32     pos[3n] (x, y, z interleaved, mission NED, m; NaN unknown),
                     vel[3n], yaw[n] (rad from north), age[n] (s since the state was
                     measured), slot[3n] (NaN none), ferr[n] (m to the slot; NaN none),
                     rate[n] (states/s heard)
             u32     plan_seq[n]
             u8      phase[n], flags[n], known[n] (1: heard at least once), then
                     zero padding to a multiple of 4
  ========== ======= ===========================================================

* **meta** (JSON text, on connect and when it changes): mode, vehicle count, phase names,
  the mission (origin, obstacles, geofence, waypoints), replay range, command status.
* **status** (JSON text, 2 Hz): fleet health, counters, autopilot modes/armed/battery,
  plans and who holds them.
* **result** (JSON text): the answer to a command or replay request.

Page to server (JSON text, at most `MAX_CLIENT_MESSAGE` bytes): ``{"type": "command",
"id": ..., "cmd": "hold" | ..., ...}`` and ``{"type": "replay", "op": "play" | "pause" |
"seek" | "speed", ...}``.

Imports: numpy only.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

FRAME_MAGIC = 0x31464453  # b"SDF1" little-endian
HEADER = struct.Struct("<IIddII")
FLAG_REPLAY, FLAG_PLAYING, FLAG_LIVE_CLOCK = 1, 2, 4
MAX_CLIENT_MESSAGE = 16384
"""Largest websocket message accepted from a page (a command is a few hundred bytes)."""


@dataclass
class Snapshot:
    """The fleet at one instant, as the page draws it (arrays of n vehicles).

    Attributes:
        t: the data's clock, s (live: Unix seconds of the swarm's clock; replay: mission s).
        t_go: transit start on the same clock (NaN: none).
        pos, vel: (n, 3) mission NED, m and m/s (NaN: unknown).
        yaw: (n,) heading, rad from north.
        age: (n,) s since the state was measured (NaN: never heard).
        slot: (n, 3) the vehicle's formation slot (NaN: none known).
        rate: (n,) states per second heard.
        plan_seq: (n,) seq of the newest plan the vehicle applied.
        phase, flags: (n,) as SWARMDROP_STATE.
        known: (n,) bool, heard at least once.
    """

    t: float
    t_go: float
    pos: np.ndarray
    vel: np.ndarray
    yaw: np.ndarray
    age: np.ndarray
    slot: np.ndarray
    rate: np.ndarray
    plan_seq: np.ndarray
    phase: np.ndarray
    flags: np.ndarray
    known: np.ndarray

    @property
    def n(self) -> int:
        return len(self.phase)

    @property
    def ferr(self) -> np.ndarray:
        """(n,) distance of each vehicle to its slot, m (NaN: no slot or no position)."""
        return np.linalg.norm(self.pos - self.slot, axis=1)

    @classmethod
    def empty(cls, n: int, t: float = float("nan")) -> "Snapshot":
        nan3 = np.full((n, 3), np.nan, np.float32)
        return cls(t, float("nan"), nan3, nan3.copy(), np.zeros(n, np.float32), np.full(n, np.nan, np.float32),
                   nan3.copy(), np.zeros(n, np.float32), np.zeros(n, np.uint32), np.zeros(n, np.uint8),
                   np.zeros(n, np.uint8), np.zeros(n, bool))


def frame_layout(n: int) -> dict[str, tuple[int, str, int]]:
    """name -> (byte offset, numpy dtype, element count) of every array of a frame of n vehicles."""
    out: dict[str, tuple[int, str, int]] = {}
    off = HEADER.size
    for name, dtype, count in (("pos", "<f4", 3 * n), ("vel", "<f4", 3 * n), ("yaw", "<f4", n), ("age", "<f4", n),
                               ("slot", "<f4", 3 * n), ("ferr", "<f4", n), ("rate", "<f4", n),
                               ("plan_seq", "<u4", n), ("phase", "u1", n), ("flags", "u1", n), ("known", "u1", n)):
        out[name] = (off, dtype, count)
        off += np.dtype(dtype).itemsize * count
    out["_end"] = ((off + 3) & ~3, "u1", 0)
    return out


def pack_frame(s: Snapshot, seq: int, flags: int) -> bytes:
    """One binary frame (module docstring) of a snapshot."""
    n = s.n
    lay = frame_layout(n)
    buf = bytearray(lay["_end"][0])
    HEADER.pack_into(buf, 0, FRAME_MAGIC, n, float(s.t), float(s.t_go), seq & 0xFFFFFFFF, flags)
    parts = {"pos": s.pos, "vel": s.vel, "yaw": s.yaw, "age": s.age, "slot": s.slot, "ferr": s.ferr, "rate": s.rate,
             "plan_seq": s.plan_seq, "phase": s.phase, "flags": s.flags, "known": s.known}
    for name, (off, dtype, count) in lay.items():
        if name == "_end":
            continue
        view = np.frombuffer(buf, dtype=dtype, count=count, offset=off)
        view[:] = np.asarray(parts[name]).reshape(-1)[:count]
    return bytes(buf)


def unpack_frame(data: bytes) -> dict:
    """The header and arrays of a frame (what the page does with typed arrays; for tests).

    Raises:
        ValueError: not a frame, or shorter than its vehicle count says.
    """
    if len(data) < HEADER.size:
        raise ValueError("shorter than a frame header")
    magic, n, t, t_go, seq, flags = HEADER.unpack_from(data, 0)
    if magic != FRAME_MAGIC:
        raise ValueError("not a console frame")
    lay = frame_layout(n)
    if len(data) < lay["_end"][0]:
        raise ValueError(f"{len(data)} bytes for {n} vehicles")
    out: dict = {"n": n, "t": t, "t_go": t_go, "seq": seq, "frame_flags": flags}
    for name, (off, dtype, count) in lay.items():
        if name != "_end":
            out[name] = np.frombuffer(data, dtype=dtype, count=count, offset=off)
    return out


def yaw_of(q_wxyz: np.ndarray) -> np.ndarray:
    """(n,) heading from (n, 4) attitude quaternions w, x, y, z (NED -> FRD), rad from north."""
    q = np.asarray(q_wxyz, float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
