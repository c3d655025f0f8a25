"""Telemetry logs (.tlog): every frame with the time it passed, as QGC and MAVProxy write them.

Format: for each frame, an 8-byte big-endian unsigned microsecond Unix timestamp
followed by the raw MAVLink frame. pymavlink's mavlogdump/mavutil read it.

No key reaches a tlog: a SETUP_SIGNING frame (which carries a signing key in clear) is
written with its 32 key bytes zeroed and its CRC recomputed, so the record still says
that a key was set up, for which system and from when (initial_timestamp), and
mavlogdump still reads it; its signature, if it had one, no longer verifies.
"""
from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Callable, Iterator

from companion.link.enums import MsgId
from companion.link.framing import HEADER_LEN_V1, HEADER_LEN_V2, IFLAG_SIGNED, MAGIC_V1, MAGIC_V2, SIGNATURE_LEN, _crc_with_extra
from companion.link.msgdef.swarmdrop import MAVLink_setup_signing_message

_STAMP = struct.Struct(">Q")
SETUP_SIGNING_CRC_EXTRA = MAVLink_setup_signing_message.crc_extra
SETUP_SIGNING_KEY_AT = 10
"""Payload offset of SETUP_SIGNING.secret_key[32] (wire order: u64, u8, u8, then the key)."""
_SETUP_SIGNING_ID3 = MsgId.SETUP_SIGNING.to_bytes(3, "little")
"""SETUP_SIGNING's id as a MAVLink 2 header carries it (bytes 7..9)."""
_CRC_LEN = 2


def redact_setup_signing(frame: bytes) -> bytes:
    """A MAVLink 2 SETUP_SIGNING frame with its key bytes zeroed and its CRC recomputed
    (any other frame unchanged). Truncated payloads (MAVLink 2 drops trailing zeros) keep
    their length."""
    if len(frame) < HEADER_LEN_V2 + _CRC_LEN or frame[0] != MAGIC_V2 or frame[7:10] != _SETUP_SIGNING_ID3:
        return frame
    end = HEADER_LEN_V2 + frame[1]
    if len(frame) < end + _CRC_LEN:
        return frame
    body = bytearray(frame[:end])
    key_at = HEADER_LEN_V2 + SETUP_SIGNING_KEY_AT
    key_end = min(end, key_at + 32)
    body[key_at:key_end] = bytes(max(0, key_end - key_at))
    crc = _crc_with_extra(body[1:], SETUP_SIGNING_CRC_EXTRA)
    return bytes(body) + crc.to_bytes(2, "little") + frame[end + 2:]


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
        if frame[0] == MAGIC_V2 and len(frame) > 9 and frame[8] == _SETUP_SIGNING_ID3[1]:  # cheap pre-check of the id
            frame = redact_setup_signing(frame)
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
        if magic == MAGIC_V2:
            size = HEADER_LEN_V2 + ln + _CRC_LEN + (SIGNATURE_LEN if data[i + 10] & IFLAG_SIGNED else 0)
        elif magic == MAGIC_V1:
            size = HEADER_LEN_V1 + ln + _CRC_LEN
        else:
            return
        if i + 8 + size > len(data):
            return
        yield us * 1e-6, data[i + 8:i + 8 + size]
        i += 8 + size
