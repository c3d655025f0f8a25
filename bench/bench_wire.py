"""Cost per message of the companion's MAVLink codec (companion.link.wire) against pymavlink.

Why: the onboard computer handles ~500 messages/s; the codec's budget is <= 5 us per
decode and per encode of a small message. ``run()`` returns a dict (the caller decides
where to write it); ``python -m bench.bench_wire`` prints it as JSON.

Each figure is the best of several repeats of a timed loop (steady state, caches warm),
in microseconds per message. "first_decode_us" is one decode by a fresh Codec, i.e.
including building that message type's plan (median of a few fresh codecs).
"encode_named_us" encodes through the named-field builder (``Codec.builder``, resolved
once), the way the agent and the SITL build messages; "build_named_us" is the builder
call alone, what naming the fields costs over a positional list ("encode_fields_us").
"""
from __future__ import annotations

import json
import os
import platform
import statistics
import time
import timeit

from pymavlink.dialects.v20 import common

from companion.link import framing, wire
from companion.link.msgdef import swarmdrop as sd

SYSID, COMPID, SEQ = 7, 1, 42


def _messages() -> list:
    return [
        sd.MAVLink_local_position_ned_message(123456, 1.5, -2.25, -30.0, 0.5, -0.25, 0.1),
        sd.MAVLink_set_position_target_local_ned_message(
            123456, 1, 1, 1, 3135, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.8, -0.4, 0.1, 0.0, 0.0),
        sd.MAVLink_swarmdrop_state_message(
            1_767_225_600_000_000, 1_767_225_660_000_000, 12.5, -3.0, -40.0, 4.0, 0.5, -0.1,
            [0.99, 0.01, -0.02, 0.1], 2, 0b011, 17),
    ]


def _best_us(fn, number: int, repeat: int) -> float:
    return min(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6


def _first_decode_us(frame: bytes, tries: int = 7) -> float:
    times = []
    for _ in range(tries):
        codec = wire.Codec(sd)
        t0 = time.perf_counter()
        codec.decode(frame)
        times.append((time.perf_counter() - t0) * 1e6)
    return statistics.median(times)


def _case(msg, number: int, repeat: int) -> dict:
    codec = wire.Codec(sd)
    packer = sd.MAVLink(None, srcSystem=SYSID, srcComponent=COMPID)
    packer.seq = SEQ
    frame = msg.pack(packer)
    if codec.encode(msg, SYSID, COMPID, SEQ) != frame:
        raise AssertionError(f"{msg.get_type()}: codec and pymavlink frames differ")
    values = [getattr(msg, name) for name in msg.fieldnames]
    msgid = type(msg).id
    build = codec.builder(msgid)  # resolved once (companion.link.builder), as the agent and SITL do
    named = {name: getattr(msg, name) for name in msg.fieldnames}
    if codec.encode_fields(msgid, build(**named), SYSID, COMPID, SEQ) != frame:
        raise AssertionError(f"{msg.get_type()}: the named-field builder's frame differs")
    parser = sd.MAVLink(None)
    parser.robust_parsing = True

    ours = {
        "decode_us": _best_us(lambda: codec.decode(frame), number, repeat),
        "encode_us": _best_us(lambda: codec.encode(msg, SYSID, COMPID, SEQ), number, repeat),
        "encode_fields_us": _best_us(lambda: codec.encode_fields(msgid, values, SYSID, COMPID, SEQ), number, repeat),
        "build_named_us": _best_us(lambda: build(**named), number, repeat),
        "encode_named_us": _best_us(lambda: codec.encode_fields(msgid, build(**named), SYSID, COMPID, SEQ), number,
                                    repeat),
        "first_decode_us": _first_decode_us(frame),
    }
    pym = {
        "decode_us": _best_us(lambda: parser.decode(bytearray(frame)), number, repeat),
        "parse_buffer_us": _best_us(lambda: parser.parse_buffer(frame), number, repeat),
        "pack_us": _best_us(lambda: msg.pack(packer), number, repeat),
    }
    return {
        "message": msg.get_type(),
        "frame_bytes": len(frame),
        "ours": ours,
        "pymavlink": pym,
        "decode_speedup": pym["decode_us"] / ours["decode_us"],
        "encode_speedup": pym["pack_us"] / ours["encode_us"],
    }


def run(number: int = 20_000, repeat: int = 5) -> dict:
    """Measure decode/encode cost per message for three message types, ours vs pymavlink.

    Args:
        number: calls per timed loop.
        repeat: timed loops per figure (the best one is kept).
    Returns:
        dict with "cases" (one per message type, figures in us per message) and host info.
    """
    cases = [_case(m, number, repeat) for m in _messages()]
    # the same codec on pymavlink's common dialect (what the SITL uses): decode only
    c_codec = wire.Codec(common)
    c_frame = sd.MAVLink_local_position_ned_message(1, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0).pack(sd.MAVLink(None, 1, 1))
    return {
        "benchmark": "wire_codec",
        "crc_backend": framing.CRC_BACKEND,
        "cases": cases,
        "common_dialect_local_position_ned_decode_us": _best_us(lambda: c_codec.decode(c_frame), number, repeat),
        "host": {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()},
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
