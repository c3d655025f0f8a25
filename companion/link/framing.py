"""MAVLink 1/2 framing for the companion link: the frame constants, the CRC, the typed
frame errors, whole frames out of a datagram or a byte stream, and the signature block.

The codec (message <-> frame, companion/link/wire.py), the signing layer
(companion/link/signing.py) and the tlog reader (companion/link/tlog.py) share these.

Pieces:
    * ``crc16_x25``: CRC-16/MCRF4XX (fastcrc when installed, else binascii.crc_hqx).
    * ``split_datagram``: the whole frames of one UDP datagram.
    * ``FrameSplitter``: whole frames out of a byte stream (TCP, serial), resynchronising.
    * Typed errors: ``FrameError`` subclasses on decode, ``EncodeError`` on encode.
    * ``signature_of``: the 13-byte signature block a decoded signed frame keeps (checked by
      companion.link.signing, not here).

Imports: stdlib only (plus ``fastcrc`` when installed). No numpy: this runs onboard.
"""
from __future__ import annotations

import functools
from binascii import crc_hqx
from collections.abc import Callable
from typing import Any, NamedTuple

_fastcrc_mcrf4xx: Callable[..., int] | None
try:  # C implementation of exactly the MAVLink CRC; optional
    from fastcrc.crc16 import mcrf4xx as _fastcrc_mcrf4xx
except ImportError:  # pragma: no cover - depends on the environment
    _fastcrc_mcrf4xx = None

MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
MAGIC_V2_BYTES = bytes((MAGIC_V2,))
HEADER_LEN_V1 = 6
HEADER_LEN_V2 = 10
IFLAG_SIGNED = 0x01
SIGNATURE_LEN = 13
MAX_FRAME_LEN = HEADER_LEN_V2 + 255 + 2 + SIGNATURE_LEN  # 280 bytes


# ----------------------------------------------------------------------------- CRC
_REV8 = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))  # bit-reversal of each byte value


def _rev16(x: int) -> int:
    return (_REV8[x & 0xFF] << 8) | _REV8[x >> 8]


def crc16_x25_hqx(data: bytes | bytearray, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX of data with binascii.crc_hqx (the fallback when fastcrc is absent).

    MCRF4XX is the reflected form of CRC-CCITT (poly 0x1021, no final xor) that crc_hqx
    computes unreflected, so reflect the input bytes, the initial value and the result;
    all three reflections run in C (bytes.translate, crc_hqx), which keeps this ~100x
    faster than a per-byte Python loop.

    Args:
        data: bytes-like.
        crc: running CRC to continue from (0xFFFF to start).
    Returns:
        The 16-bit CRC.
    """
    return _rev16(crc_hqx(bytes(data).translate(_REV8), _rev16(crc)))


_crc = _fastcrc_mcrf4xx if _fastcrc_mcrf4xx is not None else crc16_x25_hqx
CRC_BACKEND = "fastcrc" if _fastcrc_mcrf4xx is not None else "binascii"


def crc16_x25(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX ("X.25" in the MAVLink sources) of data, continuing from crc.

    Args:
        data: bytes or bytearray.
        crc: running CRC (0xFFFF to start).
    Returns:
        The 16-bit CRC (MAVLink then accumulates the message's CRC_EXTRA byte).
    """
    return _crc(data, crc)


# ----------------------------------------------------------------------------- errors
class FrameError(ValueError):
    """A byte string is not a valid MAVLink frame of the codec's dialect."""


class BadMagic(FrameError):
    """The first byte is neither 0xFD (MAVLink 2) nor 0xFE (MAVLink 1)."""


class TruncatedFrame(FrameError):
    """The frame is shorter than its header (or its length byte) says."""


class BadLength(FrameError):
    """The frame is longer than its length byte says (trailing bytes)."""


class BadCrc(FrameError):
    """The checksum does not match (corruption, or a different definition of the message)."""


class UnknownMessage(FrameError):
    """The message id is not in the dialect (its CRC cannot even be checked).

    Attributes:
        msgid: the frame's message id.
    """

    def __init__(self, msgid: int):
        super().__init__(f"message id {msgid} is not in the dialect")
        self.msgid = msgid


class UnsupportedIncompatFlags(FrameError):
    """MAVLink 2 incompat flags other than 0x01 (signed): the reference C parser drops these."""


class EncodeError(ValueError):
    """A message or field values cannot be encoded (value out of range for its type, wrong
    array length, wrong type, unknown message id, header byte out of 0..255)."""


# ----------------------------------------------------------------------------- framing
def frame_ids(frame: bytes) -> tuple[int, int] | None:
    """(sysid, compid) of a whole MAVLink 1 or 2 frame (from split_datagram or FrameSplitter);
    None if it is too short to hold them."""
    if frame[0] == MAGIC_V2:
        return (frame[5], frame[6]) if len(frame) > 6 else None
    return (frame[3], frame[4]) if len(frame) > 4 else None


def split_datagram(data: bytes) -> tuple[list[bytes], int]:
    """Complete MAVLink 1/2 frames in one datagram, and the number of bytes skipped.

    Framing only (no CRC check): bytes that cannot start a frame are skipped one by one;
    a frame that runs past the end of the datagram ends the scan (the rest is counted as
    skipped, since a datagram never continues in the next one).

    Args:
        data: one UDP datagram.
    Returns:
        (frames, skipped_bytes).
    """
    n = len(data)
    if n > 2 and data[0] == MAGIC_V2 and n == 12 + data[1] + (SIGNATURE_LEN if data[2] & IFLAG_SIGNED else 0):
        # one whole MAVLink 2 frame, the common case (PX4 and our endpoints send one frame a
        # datagram, the swarm's states come one a datagram): no scan, no copy
        return [data if type(data) is bytes else bytes(data)], 0
    frames: list[bytes] = []
    skipped = 0
    i = 0
    while i < n:
        magic = data[i]
        if magic == MAGIC_V2 and i + 3 <= n:
            size = 12 + data[i + 1] + (SIGNATURE_LEN if data[i + 2] & IFLAG_SIGNED else 0)
        elif magic == MAGIC_V1 and i + 2 <= n:
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


class FrameSplitter:
    """Whole MAVLink 1/2 frames out of a byte stream (TCP, serial).

    Bytes before a start marker are skipped. With ``crc_extra`` given (e.g.
    ``Codec.crc_extra``), each candidate frame's CRC is checked and a frame that fails,
    or whose message id the lookup does not know, is treated as a false start: one byte
    is dropped and the scan resumes right after the false marker, so a 0xFD inside
    garbage cannot swallow the real frames that follow. Without it, framing relies on
    the length byte alone (fine for a router that forwards unknown messages). MAVLink 2
    frames with unsupported incompat flags are false starts too (as in the C parser).

    Between feeds only an incomplete frame stays buffered (< MAX_FRAME_LEN bytes); the
    ``max_buffer`` bound is a hard memory guard on top: beyond it the oldest bytes are
    dropped and counted.

    Attributes:
        frames: frames returned so far.
        bytes_skipped: bytes discarded (garbage, false starts, overflow).
        bad_crc: false starts detected by CRC or unknown message id.
        overflows: times the buffer bound dropped bytes.
    """

    def __init__(self, crc_extra: Callable[[int], int | None] | None = None, max_buffer: int = 65536):
        """
        Args:
            crc_extra: msgid -> CRC_EXTRA, or None for an unknown id; None: no CRC check.
            max_buffer: bound on buffered bytes (>= MAX_FRAME_LEN).
        Raises:
            ValueError: if max_buffer < MAX_FRAME_LEN (a whole frame must fit).
        """
        if max_buffer < MAX_FRAME_LEN:
            raise ValueError(f"max_buffer must be >= {MAX_FRAME_LEN}")
        self.crc_extra = crc_extra
        self.max_buffer = max_buffer
        self._buf = bytearray()
        self.frames = 0
        self.bytes_skipped = 0
        self.bad_crc = 0
        self.overflows = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Append stream bytes and return the frames they complete, in order."""
        buf = self._buf
        buf += data
        out: list[bytes] = []
        crc_extra = self.crc_extra
        i, n, skipped = 0, len(buf), 0
        while i < n:
            j = buf.find(MAGIC_V2, i)
            k = buf.find(MAGIC_V1, i, j if j >= 0 else n)
            if k >= 0:
                j = k
            if j < 0:
                skipped += n - i
                i = n
                break
            skipped += j - i
            i = j
            if buf[i] == MAGIC_V2:
                if n - i < 3:
                    break
                flags = buf[i + 2]
                if flags & ~IFLAG_SIGNED:
                    i += 1
                    skipped += 1
                    continue
                end = i + HEADER_LEN_V2 + buf[i + 1]
                size = end - i + 2 + (SIGNATURE_LEN if flags else 0)
            else:
                if n - i < 2:
                    break
                end = i + HEADER_LEN_V1 + buf[i + 1]
                size = end - i + 2
            if n - i < size:
                break  # wait for the rest of the frame
            if crc_extra is not None:
                msgid = buf[i + 7] | buf[i + 8] << 8 | buf[i + 9] << 16 if buf[i] == MAGIC_V2 else buf[i + 5]
                extra = crc_extra(msgid)
                if extra is None or _crc_with_extra(buf[i + 1:end], extra) != buf[end] | buf[end + 1] << 8:
                    self.bad_crc += 1
                    i += 1
                    skipped += 1
                    continue
            out.append(bytes(buf[i:i + size]))
            i += size
        del buf[:i]
        if len(buf) > self.max_buffer:  # cannot happen with valid framing; a hard bound all the same
            drop = len(buf) - self.max_buffer
            del buf[:drop]
            skipped += drop
            self.overflows += 1
        self.bytes_skipped += skipped
        self.frames += len(out)
        return out


@functools.lru_cache(maxsize=256)  # one table per CRC_EXTRA value, shared by messages
def _extra_table(extra: int) -> tuple[int, ...]:
    """Accumulating one byte into a CRC-16/MCRF4XX is crc >> 8 ^ T[crc & 0xFF]; this is T
    for the byte ``extra``, so adding a message's CRC_EXTRA costs one lookup."""
    table = []
    for low in range(256):
        tmp = extra ^ low
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        table.append((tmp << 8) ^ (tmp << 3) ^ (tmp >> 4))
    return tuple(table)


def _crc_with_extra(data: bytes | bytearray, extra: int) -> int:
    """MAVLink frame checksum: CRC of data (frame[1:end]) then of the CRC_EXTRA byte."""
    crc = _crc(data, 0xFFFF)
    tmp = extra ^ (crc & 0xFF)
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    return (crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)


# ----------------------------------------------------------------------------- signature
class Signature(NamedTuple):
    """The MAVLink 2 signature block of a signed frame (not verified by this module)."""
    link_id: int
    timestamp: int  # units of 10 us since 2015-01-01 00:00:00 UTC
    signature: bytes  # 6 bytes: first 48 bits of SHA-256(key + frame + link_id + timestamp)


def signature_of(msg: Any) -> Signature | None:
    """The signature block of a message decoded by ``Codec.decode``, None if it was unsigned."""
    block = msg.__dict__.get("_signature_block")
    if block is None:
        return None
    return Signature(block[0], int.from_bytes(block[1:7], "little"), bytes(block[7:13]))
