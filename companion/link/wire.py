"""Lean MAVLink 1/2 codec for the companion link: frame <-> message for one dialect.

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
``Codec.builder`` gives a message's named-field builder for ``encode_fields``
(companion.link.builder).

The framing it stands on (constants, CRC, typed errors, ``split_datagram``,
``FrameSplitter``, ``signature_of``) is companion/link/framing.py. Signed frames (incompat
flag 0x01) decode here with their signature block kept on the message; companion.link.signing
checks it.

Imports: stdlib only (plus ``fastcrc`` when installed). No numpy: this runs onboard.
"""
from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from operator import attrgetter, itemgetter
from typing import Any

from companion.link.builder import compile_builder
from companion.link.framing import (
    HEADER_LEN_V1,
    HEADER_LEN_V2,
    IFLAG_SIGNED,
    MAGIC_V1,
    MAGIC_V2,
    MAGIC_V2_BYTES,
    SIGNATURE_LEN,
    BadCrc,
    BadLength,
    BadMagic,
    EncodeError,
    TruncatedFrame,
    UnknownMessage,
    UnsupportedIncompatFlags,
    _crc,
    _extra_table,
)

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
        r = self._parse(frame)  # (indexed, not star-unpacked: that built a list per frame, 39 a plan step)
        return r[2], r[7], r[8], r[1]

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
        Signed frames: see ``companion.link.framing.signature_of``; ``get_signed()`` stays False
        (the codec does not check signatures: companion.link.signing does).

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
