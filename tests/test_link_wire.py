"""companion.link.framing and companion.link.wire and the swarmdrop dialect, checked against pymavlink as the reference:
CRC, byte-exact encode, field-exact decode (MAVLink 1 and 2, signed, truncated payloads),
typed errors and a seeded fuzz, datagram/stream framing, and the generated dialect itself."""
from __future__ import annotations

import filecmp
import importlib.util
import math
import random
import struct
import sys

import pytest
from pymavlink.dialects.v10 import common as common_v1
from pymavlink.dialects.v20 import common, python_array_test
from pymavlink.dialects.v20 import test as pymavlink_test
from pymavlink.generator.mavcrc import x25crc_slow

from companion.link import framing, wire
from companion.link.framing import (
    BadCrc,
    BadLength,
    BadMagic,
    EncodeError,
    FrameError,
    FrameSplitter,
    TruncatedFrame,
    UnknownMessage,
    UnsupportedIncompatFlags,
    crc16_x25,
    crc16_x25_hqx,
    signature_of,
    split_datagram,
)
from companion.link.msgdef import generate
from companion.link.msgdef import swarmdrop as sd
from companion.link.wire import Codec

INT_RANGES = {"int8_t": (-128, 127), "uint8_t": (0, 255), "int16_t": (-2**15, 2**15 - 1),
              "uint16_t": (0, 2**16 - 1), "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1),
              "int64_t": (-2**63, 2**63 - 1), "uint64_t": (0, 2**64 - 1)}
F32 = struct.Struct("<f")


# ----------------------------------------------------------------------------- helpers
def _scalar(rng: random.Random, ftype: str):
    if rng.random() < 0.25:  # zeros exercise MAVLink 2 trailing-zero truncation
        return 0.0 if ftype in ("float", "double") else 0
    if ftype in INT_RANGES:
        lo, hi = INT_RANGES[ftype]
        return rng.choice((lo, hi, rng.randint(lo, hi)))
    if ftype == "float":
        v = rng.choice((math.nan, math.inf, -0.0, rng.uniform(-1e6, 1e6), rng.uniform(-1, 1)))
        return F32.unpack(F32.pack(v))[0] if rng.random() < 0.5 else v  # some not float32-exact
    if ftype == "double":
        return rng.choice((math.nan, -math.inf, rng.uniform(-1e300, 1e300), rng.random()))
    raise AssertionError(ftype)


def _chars(rng: random.Random, n: int, exotic: bool) -> bytes:
    k = rng.randint(0, n)
    if exotic:  # embedded NULs and non-ASCII bytes: decode quirks must match pymavlink's
        return bytes(rng.choice((0, 0x80, 0xFF, rng.randint(1, 255))) for _ in range(k))
    return bytes(rng.randint(0x20, 0x7E) for _ in range(k))


def random_values(cls, rng: random.Random, exotic: bool = False) -> list:
    """Constructor arguments (declaration order) with values valid for each field's type."""
    out = []
    for name, ftype in zip(cls.fieldnames, cls.fieldtypes):
        k = cls.ordered_fieldnames.index(name)
        n = cls.array_lengths[k]
        if ftype == "char":  # a scalar char ("c" format) must be exactly one byte
            out.append(_chars(rng, n, exotic) if n else bytes([rng.randint(0x20, 0x7E)]))
        elif n:
            out.append([_scalar(rng, ftype) for _ in range(n)])
        else:
            out.append(_scalar(rng, ftype))
    if rng.random() < 0.05:  # an all-zero payload still keeps one byte on the wire
        out = [bytes(len(v)) if isinstance(v, bytes) else [0] * len(v) if isinstance(v, list) else 0 for v in out]
    return out


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def assert_same_message(ours, ref) -> None:
    """Every field (with its Python type), raw char bytes and header accessor equal."""
    assert type(ours) is type(ref) or ours.get_type() == ref.get_type()
    for name in ref.get_fieldnames():
        assert _same(getattr(ours, name), getattr(ref, name)), (ref.get_type(), name, getattr(ours, name),
                                                                 getattr(ref, name))
        raw = f"_{name}_raw"
        if hasattr(ref, raw):
            assert getattr(ours, raw) == getattr(ref, raw), (ref.get_type(), raw)
    for acc in ("get_type", "get_msgId", "get_srcSystem", "get_srcComponent", "get_seq", "get_crc",
                "get_fieldnames"):
        assert getattr(ours, acc)() == getattr(ref, acc)(), acc
    for attr in ("mlen", "incompat_flags", "compat_flags"):
        assert getattr(ours.get_header(), attr) == getattr(ref.get_header(), attr), attr
    assert set(vars(ref)) <= set(vars(ours))  # every attribute pymavlink sets is there


def pym_pack(module, msg, sysid: int, compid: int, seq: int, **kw) -> bytes:
    mav = module.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return msg.pack(mav, **kw)


def pym_decode(module, frame: bytes):
    return module.MAVLink(None).decode(bytearray(frame))


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec(sd)


# ----------------------------------------------------------------------------- CRC
def test_crc_matches_pymavlink_for_random_buffers():
    rng = random.Random(1)
    for _ in range(2000):
        data = rng.randbytes(rng.randint(0, 300))
        ref = x25crc_slow()
        ref.accumulate(data)
        assert crc16_x25(data) == ref.crc == crc16_x25_hqx(data)
        start = rng.randint(0, 0xFFFF)  # continuing from any running value
        ref.crc = start
        ref.accumulate(data)
        assert crc16_x25(data, start) == ref.crc == crc16_x25_hqx(bytearray(data), start)


def test_codec_without_fastcrc_uses_the_binascii_path(monkeypatch):
    """Load second copies of framing.py and wire.py with fastcrc unimportable: same frames,
    same CRCs."""
    monkeypatch.setitem(sys.modules, "fastcrc", None)
    monkeypatch.setitem(sys.modules, "fastcrc.crc16", None)
    spec = importlib.util.spec_from_file_location("_framing_no_fastcrc", framing.__file__)
    slow_framing = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(slow_framing)
    assert slow_framing.CRC_BACKEND == "binascii" and framing.CRC_BACKEND == "fastcrc"
    monkeypatch.setitem(sys.modules, "companion.link.framing", slow_framing)  # what the copy of wire.py imports
    spec = importlib.util.spec_from_file_location("_wire_no_fastcrc", wire.__file__)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod._crc is slow_framing.crc16_x25_hqx
    rng = random.Random(2)
    slow = mod.Codec(sd)
    for cls in sd.mavlink_map.values():
        msg = cls(*random_values(cls, rng))
        frame = slow.encode(msg, 1, 1, 7)
        assert frame == pym_pack(sd, msg, 1, 1, 7)
        assert_same_message(slow.decode(frame), pym_decode(sd, frame))


# ----------------------------------------------------------------------------- encode / decode
def test_encode_is_byte_exact_and_decode_field_exact_for_every_dialect_message(codec):
    rng = random.Random(3)
    for msgid, cls in sd.mavlink_map.items():
        for case in range(25):
            values = random_values(cls, rng, exotic=case % 3 == 0)
            msg = cls(*values)
            sysid, compid, seq = rng.randint(0, 255), rng.randint(0, 255), rng.randint(0, 255)
            ref = pym_pack(sd, msg, sysid, compid, seq)
            assert codec.encode(msg, sysid, compid, seq) == ref, (cls.msgname, values)
            assert codec.encode_fields(msgid, values, sysid, compid, seq) == ref, cls.msgname
            ours = codec.decode(ref)
            assert type(ours) is cls
            assert_same_message(ours, pym_decode(sd, ref))
            assert ours.get_msgbuf() == ref
            assert codec.encode(ours, sysid, compid, seq) == ref  # a decoded message re-encodes identically


def test_decode_of_encode_returns_the_field_values(codec):
    rng = random.Random(4)
    cls = sd.MAVLink_swarmdrop_state_message
    for _ in range(200):
        values = random_values(cls, rng)
        msg = codec.decode(codec.encode_fields(cls.id, values, 3, 1, 0))
        for name, ftype, v in zip(cls.fieldnames, cls.fieldtypes, values):
            f32 = (lambda x: F32.unpack(F32.pack(x))[0]) if ftype == "float" else (lambda x: x)
            want = [f32(x) for x in v] if isinstance(v, list) else f32(v)
            assert _same(getattr(msg, name), want), name


def test_swarmdrop_state_layout():
    cls = sd.MAVLink_swarmdrop_state_message
    assert cls.unpacker.size == 63 <= 64  # 59 bytes, plus the plan_seq extension (MAVLink 2: CRC_EXTRA unchanged)
    assert cls.unpacker.format == "<QQffffff4fBBBI"
    assert cls.crc_extra == 132 and cls.fieldnames[-1] == "plan_seq"  # as before the extension
    assert (sd.SWARMDROP_STATE_FLAGS_ASSEMBLED, sd.SWARMDROP_STATE_FLAGS_OWN_STATE_VALID,
            sd.SWARMDROP_STATE_FLAGS_READY) == (1, 2, 4)
    assert sd.MAVLINK_MSG_ID_SWARMDROP_STATE == generate.SWARMDROP_STATE_ID
    assert sd.MAVLINK_MSG_ID_SWARMDROP_TICK == generate.SWARMDROP_TICK_ID


@pytest.mark.parametrize("dialect", [common, pymavlink_test, python_array_test], ids=lambda m: m.__name__)
def test_codec_with_pymavlink_dialects_for_every_message(dialect):
    """The SITL uses the codec with common: byte-exact and field-exact there too, lazily
    built. pymavlink's test dialects add every array type and a scalar char field."""
    c = Codec(dialect)
    assert not c._specs  # nothing built at construction
    rng = random.Random(5)
    for msgid, cls in dialect.mavlink_map.items():
        for case in range(3):
            values = random_values(cls, rng, exotic=case == 0)
            msg = cls(*values)
            ref = pym_pack(dialect, msg, 1, 1, case)
            assert c.encode(msg, 1, 1, case) == ref, cls.msgname
            assert c.encode_fields(msgid, values, 1, 1, case) == ref, cls.msgname
            assert_same_message(c.decode(ref), pym_decode(dialect, ref))
    assert len(c._specs) == len(dialect.mavlink_map)


def test_decode_mavlink1_frames_from_pymavlink_v10_and_force_mavlink1(codec):
    """pymavlink's v10 modules (what mavutil loads without MAVLINK20) pack MAVLink 1 frames
    without extension fields; the v20 modules' force_mavlink1 packs them with. Both decode,
    missing extensions as zeros, exactly as pymavlink's v20 decode does."""
    rng = random.Random(6)
    n = 0
    for msgid, cls in sd.mavlink_map.items():
        v1_cls = common_v1.mavlink_map.get(msgid)
        if v1_cls is None:
            continue
        for _ in range(5):
            frame = pym_pack(common_v1, v1_cls(*random_values(v1_cls, rng)), 9, 2, 200)
            assert frame[0] == 0xFE
            ours = codec.decode(frame)
            assert_same_message(ours, pym_decode(sd, frame))
            assert ours.get_header().incompat_flags == 0
            frame = pym_pack(sd, cls(*random_values(cls, rng)), 9, 2, 201, force_mavlink1=True)
            assert frame[0] == 0xFE
            assert_same_message(codec.decode(frame), pym_decode(sd, frame))
            n += 1
    assert n >= 25
    statustext = codec.decode(pym_pack(common_v1, common_v1.MAVLink_statustext_message(3, b"v1"), 1, 1, 0))
    assert (statustext.text, statustext.id, statustext.chunk_seq) == ("v1", 0, 0)


def test_char_arrays_follow_pymavlink(codec):
    """str cut at the first NUL, ASCII with U+FFFD replacements; _raw keeps the bytes up to
    the trailing NULs; a str given to encode_fields is UTF-8 encoded."""
    cases = [b"hello", b"", b"a\x00b", b"caf\xc3\xa9", b"x" * 50, b"\x00\x00abc"]
    for text in cases:
        frame = pym_pack(sd, sd.MAVLink_statustext_message(6, text, 0, 0), 1, 1, 0)
        ours, ref = codec.decode(frame), pym_decode(sd, frame)
        assert_same_message(ours, ref)
        assert ours.text == text.split(b"\x00", 1)[0].decode("ascii", errors="replace")
    assert codec.decode(codec.encode_fields(253, [6, "café"], 1, 1, 0))._text_raw == "café".encode()
    p = codec.decode(pym_pack(sd, sd.MAVLink_param_value_message(b"MPC_XY_VEL_MAX", 12.0, 9, 100, 3), 1, 1, 0))
    assert p.param_id == "MPC_XY_VEL_MAX" and isinstance(p.param_id, str)


def test_extension_fields_and_defaults(codec):
    """Trailing extension fields may be left out of encode_fields (constructor defaults),
    HEARTBEAT.mavlink_version too; a newer sender's extra payload bytes are ignored."""
    full = codec.encode_fields(253, [4, b"hi", 0, 0], 1, 1, 0)
    assert codec.encode_fields(253, [4, b"hi"], 1, 1, 0) == full
    hb = codec.encode_fields(0, [2, 12, 129, 393216, 4], 1, 1, 0)
    assert hb == pym_pack(sd, sd.MAVLink_heartbeat_message(2, 12, 129, 393216, 4, 3), 1, 1, 0)
    t_us = 0x0102030405060708  # no trailing zero byte: the 8-byte payload goes out whole
    tick = codec.encode_fields(sd.MAVLINK_MSG_ID_SWARMDROP_TICK, [t_us], 1, 1, 0)
    body = bytearray(tick[1:-2])
    assert body[0] == 8
    body[0] += 4
    body += b"\x01\x02\x03\x04"  # 4 bytes of fields we do not know, valid CRC
    crc_extra = sd.MAVLink_swarmdrop_tick_message.crc_extra
    longer = b"\xfd" + bytes(body) + framing._crc_with_extra(bytes(body), crc_extra).to_bytes(2, "little")
    assert codec.decode(longer).time_usec == t_us


def test_signed_frames_decode_and_expose_the_signature(codec):
    mav = sd.MAVLink(None, srcSystem=5, srcComponent=1)
    mav.signing.secret_key = bytes(range(32))
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 3
    mav.signing.timestamp = 123456789
    frame = sd.MAVLink_local_position_ned_message(10, 1.0, 2.0, 3.0, 0.0, 0.0, 0.5).pack(mav)
    msg = codec.decode(frame)
    assert msg.get_header().incompat_flags == 1 and (msg.x, msg.vz) == (1.0, 0.5)
    assert signature_of(msg) == (3, 123456789, frame[-6:])
    assert signature_of(codec.decode(codec.encode(msg, 5, 1, 0))) is None
    assert not msg.get_signed()  # the codec does not check signatures (companion.link.signing does)


# ----------------------------------------------------------------------------- errors
def test_typed_errors(codec):
    good = codec.encode_fields(32, [1, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 1, 1, 0)
    for cut in range(len(good)):
        with pytest.raises(TruncatedFrame):
            codec.decode(good[:cut])
    with pytest.raises(BadLength):
        codec.decode(good + b"\x00")
    bad = bytearray(good)
    bad[12] ^= 0x40
    with pytest.raises(BadCrc):
        codec.decode(bytes(bad))
    for first in (0x00, 0x55, 0xFC, 0xFF):
        with pytest.raises(BadMagic):
            codec.decode(bytes([first]) + good[1:])
    unknown = bytearray(good)
    unknown[7:10] = (9999).to_bytes(3, "little")
    with pytest.raises(UnknownMessage) as ei:
        codec.decode(bytes(unknown))
    assert ei.value.msgid == 9999
    for flags in (0x02, 0x03, 0x80):
        f = bytearray(good)
        f[2] = flags
        with pytest.raises(UnsupportedIncompatFlags):
            codec.decode(bytes(f))
    for exc in (TruncatedFrame, BadLength, BadCrc, BadMagic, UnknownMessage, UnsupportedIncompatFlags):
        assert issubclass(exc, FrameError) and issubclass(exc, ValueError)


@pytest.mark.parametrize("msgid, values", [
    (32, [math.nan, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),  # NaN into uint32
    (32, [-1, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),  # negative into uint32
    (32, [1, 1e39, 2.0, 3.0, 4.0, 5.0, 6.0]),  # beyond float32
    (32, [1, "x", 2.0, 3.0, 4.0, 5.0, 6.0]),  # str into float
    (0, [300, 12, 0, 0, 4]),  # 300 into uint8
    (0, [2.5, 12, 0, 0, 4]),  # float into uint8
    (59900, [1, 0, 0, 0, 0, 0, 0, 0, [1, 0, 0], 0, 0, 0]),  # q too short
    (59900, [1, 0, 0, 0, 0, 0, 0, 0, [1, 0, 0, 0, 0], 0, 0, 0]),  # q too long
    (59900, [1, 0, 0, 0, 0, 0, 0, 0, 1.0, 0, 0, 0]),  # q not a sequence
    (32, [1, 1.0]),  # too few values
    (12345, [1]),  # unknown id
])
def test_encode_errors_are_typed(codec, msgid, values):
    with pytest.raises(EncodeError):
        codec.encode_fields(msgid, values, 1, 1, 0)


def test_encode_errors_for_header_bytes_and_bad_objects(codec):
    msg = sd.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)
    for sysid, compid, seq in ((256, 1, 0), (1, -1, 0), (1, 1, 256)):
        with pytest.raises(EncodeError):
            codec.encode(msg, sysid, compid, seq)
    msg.type = math.nan
    with pytest.raises(EncodeError):
        codec.encode(msg, 1, 1, 0)
    with pytest.raises(EncodeError):
        codec.encode(object(), 1, 1, 0)


def test_fuzz_mutated_frames_raise_only_frame_errors(codec):
    """20 000 mutated frames (bit flips, cuts, extensions, random header bytes; half with a
    recomputed valid CRC so the payload paths see arbitrary lengths and bytes)."""
    rng = random.Random(7)
    pool = []
    for cls in sd.mavlink_map.values():
        for _ in range(2):
            msg = cls(*random_values(cls, rng, exotic=True))
            pool.append(pym_pack(sd, msg, 1, 1, 0))
            if cls.id <= 255:
                pool.append(pym_pack(sd, msg, 1, 1, 0, force_mavlink1=True))
    signer = sd.MAVLink(None, 1, 1)
    signer.signing.secret_key, signer.signing.sign_outgoing = bytes(32), True
    pool.append(sd.MAVLink_swarmdrop_tick_message(5).pack(signer))
    outcomes = {}
    for _ in range(20_000):
        f = bytearray(rng.choice(pool))
        for _ in range(rng.randint(1, 3)):
            op = rng.randrange(6)
            if op == 0 and f:
                f[rng.randrange(len(f))] ^= 1 << rng.randrange(8)
            elif op == 1:
                del f[rng.randrange(len(f) + 1):]
            elif op == 2:
                f += rng.randbytes(rng.randint(1, 20))
            elif op == 3 and len(f) > 3:
                f[rng.randrange(1, 4)] = rng.randrange(256)  # length, flags or seq/len
            elif op == 4:
                f = bytearray(rng.randbytes(rng.randint(0, 300)))
            elif op == 5 and len(f) > 10:
                f[7:10] = rng.choice(list(sd.mavlink_map)).to_bytes(3, "little")
        if rng.random() < 0.5 and len(f) >= 8 and f[0] in (0xFD, 0xFE):
            hl = 10 if f[0] == 0xFD else 6
            end = hl + f[1]
            msgid = (f[7] | f[8] << 8 | f[9] << 16) if hl == 10 and len(f) >= 10 else f[5]
            extra = codec.crc_extra(msgid)
            if extra is not None and end + 2 <= len(f):
                f[end:end + 2] = framing._crc_with_extra(bytes(f[1:end]), extra).to_bytes(2, "little")
        try:
            codec.decode(bytes(f))
            outcome = "ok"
        except FrameError as exc:
            outcome = type(exc).__name__
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    assert outcomes.get("ok", 0) > 1000 and len(outcomes) >= 6, outcomes  # every path was exercised


# ----------------------------------------------------------------------------- framing
def _garbage(rng: random.Random, with_magic: bool) -> bytes:
    g = bytearray(rng.randbytes(rng.randint(0, 40)))
    if not with_magic:
        return bytes(b for b in g if b not in (0xFD, 0xFE))
    if g and rng.random() < 0.5:
        g[rng.randrange(len(g))] = rng.choice((0xFD, 0xFE))
    return bytes(g)


def _frames(rng: random.Random, n: int) -> list[bytes]:
    out = []
    for _ in range(n):
        cls = rng.choice(list(sd.mavlink_map.values()))
        msg = cls(*random_values(cls, rng))
        kw = {"force_mavlink1": True} if cls.id <= 255 and rng.random() < 0.2 else {}
        out.append(pym_pack(sd, msg, 1, 1, rng.randrange(256), **kw))
    return out


def test_frame_splitter_resynchronises_in_a_stream(codec):
    rng = random.Random(9)
    frames = _frames(rng, 300)
    parts = []
    for f in frames:
        parts.append(_garbage(rng, True))
        if rng.random() < 0.1:  # a corrupted copy before the real one
            bad = bytearray(f)
            bad[-1] ^= 0xFF
            parts.append(bytes(bad))
        parts.append(f)
    parts.append(bytes(300))  # lets a false start in the last garbage run out
    stream = b"".join(parts)
    sp = FrameSplitter(codec.crc_extra)
    got, i = [], 0
    while i < len(stream):
        n = rng.randint(1, 200)
        got += sp.feed(stream[i:i + n])
        i += n
    assert got == frames
    assert sp.frames == len(frames)
    assert sp.bytes_skipped == len(stream) - sum(map(len, frames))
    assert sp.bad_crc >= 1 and sp.overflows == 0


def test_frame_splitter_framing_only_and_bounds(codec):
    rng = random.Random(10)
    frames = _frames(rng, 50)
    stream = b"".join(_garbage(rng, False) + f for f in frames)
    sp = FrameSplitter()
    got = [fr for k in range(0, len(stream), 7) for fr in sp.feed(stream[k:k + 7])]
    assert got == frames and sp.bytes_skipped == len(stream) - sum(map(len, frames))
    # unsupported incompat flags are a false start; a signed frame passes whole
    signer = sd.MAVLink(None, 1, 1)
    signer.signing.secret_key, signer.signing.sign_outgoing = bytes(32), True
    signed = sd.MAVLink_swarmdrop_tick_message(5).pack(signer)
    odd = bytearray(frames[0])
    odd[0], odd[2] = 0xFD, 0x04
    sp = FrameSplitter(codec.crc_extra)
    assert sp.feed(bytes(odd[:3]) + signed) == [signed] and sp.bytes_skipped == 3
    with pytest.raises(ValueError):
        FrameSplitter(max_buffer=100)


def test_split_datagram_one_frame_many_frames_garbage_and_truncation():
    rng = random.Random(11)
    frames = _frames(rng, 40)
    signer = sd.MAVLink(None, 1, 1)
    signer.signing.secret_key, signer.signing.sign_outgoing = bytes(32), True
    signed = sd.MAVLink_swarmdrop_tick_message(5).pack(signer)
    for f in frames + [signed]:  # one whole frame a datagram (the fast path), as bytes or a view
        assert split_datagram(f) == ([f], 0) and split_datagram(bytearray(f)) == ([f], 0)
        assert type(split_datagram(bytearray(f))[0][0]) is bytes
    assert split_datagram(b"".join(frames[:5])) == (frames[:5], 0)
    junk = _garbage(rng, False)
    assert split_datagram(junk + frames[0] + frames[1]) == ([frames[0], frames[1]], len(junk))
    assert split_datagram(frames[0] + b"\x00") == ([frames[0]], 1)  # one byte more: not the fast path
    v2 = next(f for f in frames if f[0] == 0xFD)
    assert split_datagram(v2[:-1]) == ([], len(v2) - 1)  # one byte short: truncated, all skipped


# ----------------------------------------------------------------------------- the dialect
def test_generated_dialect_is_reproducible(tmp_path):
    xml_path, py_path = generate.generate(tmp_path)
    for p in (xml_path, py_path):
        assert filecmp.cmp(p, generate.HERE / p.name, shallow=False), f"{p.name} is stale: regenerate"


def test_project_ids_collide_with_nothing_in_all_xml():
    ids = generate.all_xml_message_ids()
    assert len(ids) > 300
    assert generate.SWARMDROP_STATE_ID not in ids and generate.SWARMDROP_TICK_ID not in ids
    assert not any(i in ids for i in generate.ID_BLOCK)
    generate.check_ids(ids)
    with pytest.raises(generate.GenerateError):
        generate.check_ids({generate.SWARMDROP_TICK_ID: "INTRUDER"})


def test_copied_common_messages_equal_pymavlink_common():
    """Same CRC_EXTRA (enum attributes stripped: they do not enter it) and the same layout."""
    assert set(sd.mavlink_map) == set(generate.COMMON_MESSAGES) | {
        generate.SWARMDROP_STATE_ID, generate.SWARMDROP_TICK_ID, generate.SWARMDROP_PLAN_ID, generate.SWARMDROP_SLOTS_ID}
    for msgid, name in generate.COMMON_MESSAGES.items():
        ours, ref = sd.mavlink_map[msgid], common.mavlink_map[msgid]
        assert ours.msgname == ref.msgname == name
        assert ours.crc_extra == ref.crc_extra, name
        assert (ours.fieldnames, ours.ordered_fieldnames, ours.fieldtypes, ours.unpacker.format) == (
            ref.fieldnames, ref.ordered_fieldnames, ref.fieldtypes, ref.unpacker.format), name
        assert not ours.fieldenums_by_name and ours.fieldunits_by_name == ref.fieldunits_by_name
    assert sd.MAVLink.heartbeat_encode.__defaults__ == common.MAVLink.heartbeat_encode.__defaults__  # version 3
