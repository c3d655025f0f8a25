"""Telemetry logs (.tlog): every frame with the time it passed, as QGC and MAVProxy write them.

Format: for each frame, an 8-byte big-endian unsigned microsecond Unix timestamp
followed by the raw MAVLink frame. pymavlink's mavlogdump/mavutil read it.
"""
from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Callable, Iterator

_STAMP = struct.Struct(">Q")


class Tlog:
    """Append-only .tlog writer.

    Args:
        path: file to create (truncated).
        clock: Unix time in seconds (injected: a simulator passes its simulated clock).
    Raises:
        OSError: the file cannot be created.
    """

    def __init__(self, path: str | Path, clock: Callable[[], float] = time.time):
        self.path = Path(path)
        self._f = open(self.path, "wb")
        self._clock = clock
        self.frames = 0

    def write(self, frame: bytes) -> None:
        self._f.write(_STAMP.pack(int(self._clock() * 1e6)) + frame)
        self.frames += 1

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


def read_tlog(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """(Unix time s, frame bytes) of every record; stops at a truncated tail.

    Frames are delimited by their own length fields (MAVLink 1 or 2, signed or not).
    """
    data = Path(path).read_bytes()
    i = 0
    while i + 8 + 3 <= len(data):
        (us,) = _STAMP.unpack_from(data, i)
        magic, ln = data[i + 8], data[i + 9]
        if magic == 0xFD:
            size = 12 + ln + (13 if data[i + 10] & 1 else 0)
        elif magic == 0xFE:
            size = 8 + ln
        else:
            return
        if i + 8 + size > len(data):
            return
        yield us * 1e-6, data[i + 8:i + 8 + size]
        i += 8 + size
