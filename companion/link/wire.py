"""Lean MAVLink 1/2 framing and codec for the companion link.

Why not pymavlink's parser: ``MAVLink.decode`` costs ~5 us per small message warm (~9 us
through ``parse_buffer``, as mavutil uses it) and much more cold, its stream parser raises
untyped exceptions, and ``mavutil`` drags in much more.
The companion runs on a small onboard computer at ~500 messages/s, so this module does
the minimum per frame: one ``struct`` unpack of the header, one C-speed CRC, one
precompiled ``struct.Struct`` for the payload, and one dict for the message object.

What it keeps from pymavlink: the dialect is a mavgen-generated module (its
``mavlink_map`` gives the message classes, struct formats, field orders and CRC_EXTRA),
and ``Codec.decode`` returns instances of those classes, so code written against
pymavlink messages (``get_type()``, field attributes, ``get_srcSystem()``...) keeps
working; ``Codec.encode`` is byte-exact with ``msg.pack(MAVLink(None, sysid, compid))``.

Pieces:
    * ``crc16_x25``: CRC-16/MCRF4XX (fastcrc when installed, else binascii.crc_hqx).
    * ``split_datagram``: the whole frames of one UDP datagram.
    * ``FrameSplitter``: whole frames out of a byte stream (TCP, serial), resynchronising.
    * ``Codec``: frame <-> message for one dialect module; ``Codec.builder`` gives a
      message's named-field builder for ``encode_fields`` (companion.link.builder).
    * Typed errors: ``FrameError`` subclasses on decode, ``EncodeError`` on encode.

Signing: signed frames (incompat flag 0x01) decode, but their signature is NOT verified
yet; the 13-byte signature block is kept on the message (``signature_of``).

Imports: stdlib only (plus ``fastcrc`` when installed). No numpy: this runs onboard.
"""
from __future__ import annotations

import functools
import struct
from binascii import crc_hqx
from collections.abc import Callable, Sequence
from operator import attrgetter, itemgetter
from typing import Any, NamedTuple

from companion.link.builder import compile_builder

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
    frames: list[bytes] = []
    skipped = 0
    i, n = 0, len(data)
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


# ----------------------------------------------------------------------------- codec
_V2_HEADER = struct.Struct("<BBBBBBHB")  # after the magic: len, incompat, compat, seq, sys, comp, id lo16, id hi8
_V1_HEADER = struct.Struct("<BBBBB")  # after the magic: len, seq, sys, comp, id
_V2_HEAD_OUT = struct.Struct("<6B")  # len, incompat, compat, seq, sys, comp (the 3 id bytes are precomputed)
_ENCODE_ERRORS = (struct.error, TypeError, ValueError, OverflowError, AttributeError, IndexError)


def _getter(indices: Sequence[int]) -> Callable[[Sequence], tuple]:
    """itemgetter that always returns a tuple (itemgetter(i) returns a bare item)."""
    if len(indices) == 1:
        i = indices[0]
        return lambda t: (t[i],)
    return itemgetter(*indices)


class _Spec:
    """Everything the hot paths need about one message type, precomputed once."""

    __slots__ = ("cls", "crc_extra", "extra_table", "unpacker", "size", "zeros", "static", "scalars", "arrays",
                 "chars", "id3", "wire_get", "decl_to_wire", "wire_arrays", "wire_chars",
                 "n_fields", "defaults")

    def __init__(self, cls: Any, base_init: Callable[..., None], mavlink_cls: Any):
        # cls: a pymavlink message class; their attributes are generated, hence Any
        self.cls = cls
        self.crc_extra = cls.crc_extra
        self.extra_table = _extra_table(cls.crc_extra)
        self.unpacker = cls.unpacker
        self.size = cls.unpacker.size
        self.zeros = bytes(self.size)  # to pad MAVLink 2 trailing-zero-truncated (or v1) payloads
        decl, wire = list(cls.fieldnames), list(cls.ordered_fieldnames)
        wire_pos = list(cls.orders)  # declaration index -> wire index
        decl_of_wire = [wire_pos.index(k) for k in range(len(wire))]
        items = cls.lengths  # struct items per wire field (arrays: their length; char[n]: 1)
        alen = cls.array_lengths  # array length per wire field (0: scalar)
        is_char = [cls.fieldtypes[decl_of_wire[k]] == "char" for k in range(len(wire))]
        start = [sum(items[:k]) for k in range(len(wire))]

        # The attributes pymavlink's constructor sets besides the fields, taken from the
        # base initialiser itself so that they follow the installed pymavlink.
        proto: Any = object.__new__(cls)
        base_init(proto, cls.id, cls.msgname)
        proto._fieldnames = cls.fieldnames
        proto._instance_field = cls.instance_field
        proto._instance_offset = cls.instance_offset
        proto._signature_block = None
        # Field keys are pre-inserted (None) so the per-decode copy already has its final
        # size and the fields only overwrite values: no dict resize in the hot path.
        raw_names = [f"_{wire[k]}_raw" for k in range(len(wire)) if is_char[k]]
        self.static = dict(vars(proto)) | dict.fromkeys(decl + raw_names)

        # decode plan, in declaration order. pymavlink quirk kept: a numeric array of
        # length 1 decodes to a bare number (its decode checks "L == 1").
        scalars, arrays, chars = [], [], []
        for name in decl:
            k = wire.index(name)
            if is_char[k]:
                chars.append((name, f"_{name}_raw", start[k]))
            elif alen[k] > 1:
                arrays.append((name, start[k], start[k] + alen[k]))
            else:
                scalars.append((name, start[k]))
        self.scalars = tuple(scalars)
        self.arrays = tuple(arrays)
        self.chars = tuple(chars)

        # encode plan, in wire order. char fields are packed from "_<name>_raw", the bytes
        # given to the constructor, exactly as the generated pack() does.
        self.id3 = cls.id.to_bytes(3, "little")
        attrs = [f"_{n}_raw" if is_char[k] else n for k, n in enumerate(wire)]
        self.wire_get = attrgetter(*attrs) if len(attrs) > 1 else (lambda m, a=attrs[0]: (getattr(m, a),))
        self.decl_to_wire = _getter(decl_of_wire)
        self.wire_arrays = tuple((k, alen[k]) for k in range(len(wire)) if alen[k] and not is_char[k])
        self.wire_chars = tuple(k for k in range(len(wire)) if is_char[k])
        self.n_fields = len(decl)
        # Defaults of the generated MAVLink.<name>_encode(): extension fields and constants
        # (HEARTBEAT.mavlink_version, which the class constructor itself does not default).
        encode = getattr(mavlink_cls, f"{cls.msgname.lower()}_encode", cls.__init__)
        self.defaults = tuple(encode.__defaults__ or ())


class Codec:
    """Frame <-> message for one mavgen-generated (MAVLink 2) dialect module.

    Works with ``companion.link.msgdef.swarmdrop`` and with pymavlink's own modules
    (e.g. ``pymavlink.dialects.v20.common``). Per-message plans are built on the first
    use of each id, so construction is free even for dialects with hundreds of messages.
    Not thread-safe for concurrent first use of an id (harmless: both build the same plan).
    """

    def __init__(self, dialect: Any, *extra: Any):
        """
        Args:
            dialect: a mavgen Python module (has mavlink_map, MAVLink_header, MAVLink_message).
            extra: more such modules whose messages the first lacks (e.g. the project's
                SWARMDROP_* messages next to pymavlink's common in the SITL).
        """
        self.dialect = dialect
        self._map: dict[int, Any] = dict(dialect.mavlink_map)
        self._owner: dict[int, Any] = {}
        for module in extra:
            for msgid, cls in module.mavlink_map.items():
                if msgid not in self._map:
                    self._map[msgid] = cls
                    self._owner[msgid] = module
        self._header_cls = dialect.MAVLink_header
        self._base_init = dialect.MAVLink_message.__init__
        self._specs: dict[int, _Spec] = {}
        self._builders: dict[int, Callable[..., tuple]] = {}

    def _spec(self, msgid: int) -> _Spec:
        cls = self._map.get(msgid)
        if cls is None:
            raise UnknownMessage(msgid)
        owner = self._owner.get(msgid, self.dialect)
        spec = self._specs[msgid] = _Spec(cls, owner.MAVLink_message.__init__, owner.MAVLink)
        return spec

    def crc_extra(self, msgid: int) -> int | None:
        """CRC_EXTRA of a message id, None if the dialect does not define it."""
        cls = self._map.get(msgid)
        return None if cls is None else cls.crc_extra

    # ------------------------------------------------------------------------- decode
    def _parse(self, frame: bytes):
        """Validate one frame: (spec, unpacked wire tuple, msgid, incompat, compat, mlen, seq,
        sysid, compid, hl, end, sig, crc). Raises the FrameError subclasses."""
        n = len(frame)
        if not n:
            raise TruncatedFrame("empty frame")
        magic = frame[0]
        if magic == MAGIC_V2:
            if n < 12:
                raise TruncatedFrame(f"{n} bytes: shorter than a MAVLink 2 header and CRC")
            mlen, incompat, compat, seq, sysid, compid, id_lo, id_hi = _V2_HEADER.unpack_from(frame, 1)
            msgid = id_lo | id_hi << 16
            hl = HEADER_LEN_V2
            sig = 0
            if incompat:
                if incompat & ~IFLAG_SIGNED:
                    raise UnsupportedIncompatFlags(f"incompat flags 0x{incompat:02x}")
                sig = SIGNATURE_LEN
        elif magic == MAGIC_V1:
            if n < 8:
                raise TruncatedFrame(f"{n} bytes: shorter than a MAVLink 1 header and CRC")
            mlen, seq, sysid, compid, msgid = _V1_HEADER.unpack_from(frame, 1)
            incompat = compat = sig = 0
            hl = HEADER_LEN_V1
        else:
            raise BadMagic(f"start byte 0x{magic:02x}")
        end = hl + mlen
        if n != end + 2 + sig:
            if n < end + 2 + sig:
                raise TruncatedFrame(f"{n} bytes, the header says {end + 2 + sig}")
            raise BadLength(f"{n} bytes, the header says {end + 2 + sig}")
        spec = self._specs.get(msgid) or self._spec(msgid)

        crc = _crc(frame[1:end], 0xFFFF)
        crc = (crc >> 8) ^ spec.extra_table[crc & 0xFF]  # accumulate the CRC_EXTRA byte
        if crc != frame[end] | frame[end + 1] << 8:
            raise BadCrc(f"msgid {msgid}: CRC 0x{frame[end] | frame[end + 1] << 8:04x}, computed 0x{crc:04x}")

        if mlen >= spec.size:
            t = spec.unpacker.unpack_from(frame, hl)
        else:
            t = spec.unpacker.unpack(frame[hl:end] + spec.zeros[mlen:])
        return spec, t, msgid, incompat, compat, mlen, seq, sysid, compid, hl, end, sig, crc

    def decode_raw(self, frame: bytes) -> tuple[int, int, int, tuple]:
        """(msgid, sysid, compid, payload values in WIRE order, arrays flattened) of one frame,
        with every check of decode but no message object: the hot path for a message
        the caller reads field by field (wire order: cls.ordered_fieldnames).

        Raises:
            The FrameError subclasses, as decode.
        """
        if type(frame) is not bytes:
            frame = bytes(frame)
        _, t, msgid, _, _, _, _, sysid, compid, *_ = self._parse(frame)
        return msgid, sysid, compid, t

    def named(self, msgid: int, values: tuple) -> dict[str, Any]:
        """decode_raw's wire-order values of one message by field name: scalars as they are,
        numeric arrays as lists, char arrays as their raw bytes (the low-rate path for a
        message read by name from a raw poll).

        Raises:
            UnknownMessage: the id is not in the dialect.
        """
        spec = self._specs.get(msgid) or self._spec(msgid)
        out: dict[str, Any] = {name: values[i] for name, i in spec.scalars}
        for name, a, b in spec.arrays:
            out[name] = list(values[a:b])
        for name, _raw, i in spec.chars:
            out[name] = values[i]
        return out

    def decode(self, frame: bytes) -> Any:
        """Decode one whole MAVLink 1 or 2 frame into an instance of the dialect's class.

        Fields follow pymavlink's decode exactly: numeric arrays are lists, char arrays
        are str (cut at the first NUL, ASCII with U+FFFD for other bytes; the NUL-stripped
        bytes are on ``_<name>_raw``), MAVLink 2 payloads truncated of trailing zeros and
        MAVLink 1 payloads without extension fields are zero-padded, extra payload bytes
        (fields of a newer definition) are ignored. ``get_srcSystem()``, ``get_seq()``,
        ``get_header().incompat_flags``, ``get_msgbuf()`` (the frame), ``get_crc()`` work.
        Signed frames: see ``signature_of``; ``get_signed()`` stays False (not verified).

        Args:
            frame: exactly one frame (bytes or bytearray), e.g. from split_datagram.
        Returns:
            The message object.
        Raises:
            BadMagic, TruncatedFrame, BadLength, UnsupportedIncompatFlags, UnknownMessage,
            BadCrc: all subclasses of FrameError (a ValueError); nothing else for bytes input.
        """
        if type(frame) is not bytes:
            frame = bytes(frame)
        spec, t, msgid, incompat, compat, mlen, seq, sysid, compid, hl, end, sig, crc = self._parse(frame)
        d = spec.static.copy()
        for name, k in spec.scalars:  # a loop of stores beats d.update(zip(...)) by ~40 %
            d[name] = t[k]
        for name, a, b in spec.arrays:
            d[name] = list(t[a:b])
        for name, raw_name, k in spec.chars:
            raw = d[raw_name] = t[k].rstrip(b"\x00")
            d[name] = raw.partition(b"\x00")[0].decode("ascii", errors="replace")
        d["_header"] = self._header_cls(msgid, incompat, compat, mlen, seq, sysid, compid)
        d["_msgbuf"] = frame
        d["_payload"] = frame[hl:end]
        d["_crc"] = crc
        if sig:
            d["_signature_block"] = frame[end + 2:]
        msg = object.__new__(spec.cls)
        msg.__dict__ = d
        return msg

    # ------------------------------------------------------------------------- encode
    def encode(self, msg: Any, sysid: int, compid: int, seq: int) -> bytes:
        """Encode a message object of the dialect as an unsigned MAVLink 2 frame.

        Byte-exact with pymavlink's ``msg.pack(MAVLink(None, srcSystem=sysid,
        srcComponent=compid))`` at the same seq, trailing-zero truncation included.
        As in pymavlink, char fields are taken from ``_<name>_raw`` (what the constructor
        got, or what decode stripped), not from the str attribute.

        Args:
            msg: instance of a message class of the dialect (or of a dialect that defines
                the message identically).
            sysid, compid, seq: header bytes, each 0..255 (wrap seq yourself).
        Returns:
            The frame.
        Raises:
            EncodeError: unknown message, value out of range for its type (NaN or 300
                into an int field, 1e39 into a float), wrong array length or type.
        """
        try:
            msgid = type(msg).id  # not msg.id: STATUSTEXT has a field called "id"
            spec = self._specs.get(msgid) or self._spec_for_encode(msgid)
            values = spec.wire_get(msg)
        except (AttributeError, TypeError) as exc:  # not a message of a mavgen dialect
            raise EncodeError(f"{type(msg).__name__}: {exc}") from None
        return self._frame(spec, values, sysid, compid, seq)

    def encode_fields(self, msgid: int, values: Sequence, sysid: int, compid: int, seq: int) -> bytes:
        """Encode field values directly, without building a message object (fast path).

        Args:
            msgid: message id of the dialect.
            values: field values in DECLARATION order, i.e. the XML order, the order of
                ``cls.fieldnames`` and of the generated constructor's arguments (extension
                fields last). Trailing fields with a default in the generated
                ``MAVLink.<name>_encode`` (extension fields, HEARTBEAT.mavlink_version) may
                be left out. Numeric arrays: a sequence of exactly the array length; char
                arrays: bytes or str (UTF-8).
            sysid, compid, seq: header bytes, each 0..255.
        Returns:
            The MAVLink 2 frame, the same bytes as encoding the equivalent message object.
        Raises:
            EncodeError: unknown id, missing/extra values, or a value that does not fit.
        """
        try:
            spec = self._specs.get(msgid) or self._spec_for_encode(msgid)
            if len(values) != spec.n_fields:
                values = self._complete(spec, values)
            values = spec.decl_to_wire(values)
        except TypeError as exc:  # values is not a sequence, msgid not an int
            raise EncodeError(f"message {msgid!r}: {exc}") from None
        return self._frame(spec, values, sysid, compid, seq)

    def builder(self, msgid: int) -> Callable[..., tuple]:
        """The named-field builder of a message: ``build(**fields)`` -> its values for encode_fields.

        Example::

            build = codec.builder(MsgId.COMMAND_LONG)  # once, e.g. at start-up
            codec.encode_fields(MsgId.COMMAND_LONG, build(target_system=1, target_component=1,
                                command=MavCmd.MAV_CMD_COMPONENT_ARM_DISARM, param1=1.0), sysid, compid, seq)

        The builder is compiled on the first request for a message and cached. Fields left
        out take the defaults of companion.link.builder (NaN for command params 1-7, the
        generated encoder's defaults for extensions, else zeros); an unknown field name
        raises TypeError naming it.

        Raises:
            EncodeError: the message id is not in the dialect.
        """
        build = self._builders.get(msgid)
        if build is None:
            spec = self._specs.get(msgid) or self._spec_for_encode(msgid)
            build = self._builders[msgid] = compile_builder(spec.cls, spec.defaults)
        return build

    def _spec_for_encode(self, msgid: int) -> _Spec:
        try:
            return self._spec(msgid)
        except UnknownMessage:
            raise EncodeError(f"message id {msgid} is not in the dialect") from None

    @staticmethod
    def _complete(spec: _Spec, values: Sequence) -> tuple:
        n_required = spec.n_fields - len(spec.defaults)
        if not n_required <= len(values) <= spec.n_fields:
            raise EncodeError(f"{spec.cls.msgname}: {len(values)} values, expected "
                              f"{n_required}..{spec.n_fields} in declaration order {spec.cls.fieldnames}")
        return (*values, *spec.defaults[len(values) - n_required:])

    def _frame(self, spec: _Spec, values: tuple, sysid: int, compid: int, seq: int) -> bytes:
        try:
            vals: list[Any] | tuple = values
            if spec.wire_chars:
                vals = list(vals)
                for k in spec.wire_chars:
                    if isinstance(vals[k], str):
                        vals[k] = vals[k].encode()
            if spec.wire_arrays:
                vals = _flatten(vals, spec.wire_arrays)
            payload = spec.unpacker.pack(*vals)
            # MAVLink 2 drops trailing zero bytes of the payload, keeping at least one
            payload = payload.rstrip(b"\x00") or payload[:1]
            body = _V2_HEAD_OUT.pack(len(payload), 0, 0, seq, sysid, compid) + spec.id3 + payload
        except _ENCODE_ERRORS as exc:
            raise EncodeError(f"{spec.cls.msgname}: {exc}") from None
        crc = _crc(body, 0xFFFF)
        crc = (crc >> 8) ^ spec.extra_table[crc & 0xFF]
        return b"".join((MAGIC_V2_BYTES, body, crc.to_bytes(2, "little")))


def _flatten(values: Sequence, wire_arrays: tuple[tuple[int, int], ...]) -> list:
    """Wire-ordered values with the numeric arrays spliced in (struct wants flat items).

    Raises:
        EncodeError: an array has the wrong length (struct alone would not notice when two
            arrays' errors cancel out).
        TypeError: an array value is not a sequence (mapped to EncodeError by the caller).
    """
    flat: list = []
    prev = 0
    for k, n in wire_arrays:
        flat.extend(values[prev:k])
        a = values[k]
        if n == 1 and not hasattr(a, "__len__"):  # pymavlink decodes length-1 arrays to bare numbers
            flat.append(a)
        else:
            if len(a) != n:
                raise EncodeError(f"array of {len(a)} values for a field of {n}")
            flat.extend(a)
        prev = k + 1
    flat.extend(values[prev:])
    return flat
