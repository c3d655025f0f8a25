"""asyncio UDP endpoints: one socket each, one sender task per socket.

Callers queue message objects (data); the endpoint's single sender task packs
them with the per-sysid pymavlink packer (own sequence numbers) and sends them
to the endpoint's current remote: the configured default until a datagram
arrives, then whichever address last talked to it (as PX4 does).
Incoming datagrams are split into frames and decoded one by one; malformed,
truncated or wrong-CRC frames are counted and dropped.
"""
from __future__ import annotations

import asyncio
import collections
import logging
import os
import struct
import time
from typing import Callable

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

log = logging.getLogger(__name__)

MessageHandler = Callable[["UdpEndpoint", mavlink.MAVLink_message, tuple], None]


class Tlog:
    """A .tlog: each frame prefixed by its wall time in microseconds (big-endian uint64)."""

    def __init__(self, path: str):
        self._f = open(path, "wb")

    def write(self, frame: bytes) -> None:
        self._f.write(struct.pack(">Q", int(time.time() * 1e6)) + frame)

    def close(self) -> None:
        self._f.close()


def split_frames(data: bytes) -> tuple[list[bytes], int]:
    """Complete MAVLink 1/2 frames in one datagram, and the number of bytes skipped."""
    frames: list[bytes] = []
    skipped = 0
    i, n = 0, len(data)
    while i < n:
        magic = data[i]
        if magic == 0xFD and i + 3 <= n:
            size = 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
        elif magic == 0xFE and i + 2 <= n:
            size = 8 + data[i + 1]
        else:
            i += 1
            skipped += 1
            continue
        if i + size > n:  # truncated: the rest of the datagram cannot be a frame
            skipped += n - i
            break
        frames.append(bytes(data[i:i + size]))
        i += size
    return frames, skipped


class UdpEndpoint(asyncio.DatagramProtocol):
    def __init__(self, name: str, bind: tuple[str, int], default_remote: tuple[str, int],
                 on_message: MessageHandler, tlog: Tlog | None = None):
        self.name = name
        self.bind = bind
        self.remote = default_remote
        self.on_message = on_message
        self.tlog = tlog
        self.transport: asyncio.DatagramTransport | None = None
        self._outbox: collections.deque = collections.deque()
        self._wake = asyncio.Event()
        self._packers: dict[int, mavlink.MAVLink] = {}
        self._parser = mavlink.MAVLink(None, srcSystem=0, srcComponent=0)
        self._task: asyncio.Task | None = None
        self.sent = 0
        self.received = 0
        self.bad_frames = 0
        self.handler_errors = 0

    @property
    def local_port(self) -> int:
        return self.transport.get_extra_info("sockname")[1] if self.transport else 0

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: self, local_addr=self.bind)
        self._task = asyncio.create_task(self._sender(), name=f"send-{self.name}")

    def connection_made(self, transport) -> None:
        self.transport = transport

    def send(self, sysid: int, msg: mavlink.MAVLink_message, addr: tuple | None = None) -> None:
        """Queue a message from vehicle sysid (compid 1)."""
        self._outbox.append((sysid, msg, addr))
        if not self._wake.is_set():
            self._wake.set()

    async def _sender(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            out = self._outbox
            while out:
                sysid, msg, addr = out.popleft()
                packer = self._packers.get(sysid)
                if packer is None:
                    packer = self._packers[sysid] = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
                try:
                    frame = msg.pack(packer)
                except Exception:  # a builder bug must not kill the link
                    self.handler_errors += 1
                    log.exception("%s: cannot pack %s", self.name, msg.get_type())
                    continue
                if self.transport is None or self.transport.is_closing():
                    return
                self.transport.sendto(frame, addr or self.remote)
                self.sent += 1
                if self.tlog is not None:
                    self.tlog.write(frame)

    def datagram_received(self, data: bytes, addr) -> None:
        self.remote = addr
        frames, skipped = split_frames(data)
        if skipped:
            self.bad_frames += 1
        for frame in frames:
            try:
                msg = self._parser.decode(bytearray(frame))
            except Exception:
                self.bad_frames += 1
                continue
            if isinstance(msg, mavlink.MAVLink_unknown):
                continue
            self.received += 1
            if self.tlog is not None:
                self.tlog.write(frame)
            try:
                self.on_message(self, msg, addr)
            except Exception:  # bad content must never take the SITL down
                self.handler_errors += 1
                if self.handler_errors == 1:
                    log.exception("%s: error handling %s (further errors only counted)", self.name, msg.get_type())

    def error_received(self, exc) -> None:  # e.g. ICMP port unreachable: keep running
        pass

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
        if self.transport is not None:
            self.transport.close()
