"""MAVLink 2 message signing: keys, signing what leaves, checking what arrives.

The MAVLink 2 signing protocol (mavlink.io "Message Signing"): a signed frame has
incompat flag 0x01 and 13 more bytes: link id (1), timestamp (6, units of 10 µs since
2015-01-01 UTC) and signature (6) = the first 48 bits of
SHA-256(secret key (32) + frame from magic to CRC + link id + timestamp).

A receiver keeps the last timestamp of every (link id, system id, component id) stream
and accepts a signed frame only with a good signature and a newer timestamp (a new
stream: not more than a minute older than the newest timestamp seen), so a captured
frame cannot be replayed. Modes, as PX4's MAV_SIGN_CFG:

    off       nothing signed, nothing checked (signature blocks are ignored)
    optional  sign what we send; unsigned frames are accepted, signed ones must verify
    require   sign what we send; unsigned frames are dropped, except the few that
              PX4 accepts unsigned (RADIO_STATUS, ADSB_VEHICLE, COLLISION)

What a frame may do besides being decoded (docs/signing.md): `check` returns a verdict.
Only a TRUSTED frame (signing off: any frame; on: a signed frame that verifies and is new
to the vehicle) may move a UDP link's reply address; an UNSIGNED one that was let through
moves nothing (companion.link.endpoints).

Replay tables: every vehicle has one `ReplayTable` for all of its links (as PX4), so a
frame captured on one link is a replay on the others, and every frame a link signs is
recorded in it, so the vehicle's own frames sent back to it are replays too. A link
that serves several vehicles (the SITL's GCS endpoint) passes a `ReplayScope` that
picks the tables of the vehicles a frame is for; in the SITL a frame that names no
target system, received by one vehicle, is a replay for the others too (FleetScope).

Keys come from a file (64 hex digits, or 32 raw bytes) that only its owner may read;
never from the command line, the environment or a log. Timestamps are taken from the
wall clock and never go backwards: a `TimestampStore` file keeps the last one, so a
restarted sender never reuses one.
"""
from __future__ import annotations

import hashlib
import os
import re
import stat
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Protocol, Sequence

from companion.link.enums import MsgId
from companion.link.framing import IFLAG_SIGNED, MAGIC_V2, MAGIC_V2_BYTES, SIGNATURE_LEN, _crc_with_extra

SigningMode = Literal["off", "optional", "require"]
MODES: tuple[str, ...] = ("off", "optional", "require")

ACCEPT_UNSIGNED = frozenset({MsgId.RADIO_STATUS, MsgId.ADSB_VEHICLE, MsgId.COLLISION})
"""Accepted unsigned even when signing is required (PX4)."""

EPOCH_2015_UNIX_S = 1420070400
REPLAY_WINDOW_10US = 6_000_000
"""A new stream's first timestamp may be at most 60 s older than the newest seen (MAVLink spec)."""
STREAMS_MAX = 1024
"""Streams remembered per replay table; beyond this the oldest is forgotten (bounded memory)."""
SETUP_SIGNING_TARGET_AT = 8
"""Payload offset of SETUP_SIGNING.target_system (wire order: initial_timestamp u64 first)."""

REJECTED, UNSIGNED, VERIFIED, TRUSTED = 0, 1, 2, 3
"""Verdicts of `Signing.verdict`: dropped; let through unsigned (optional mode, or the
accept-unsigned list); signed, verified and new, but for no vehicle this link serves;
signed, verified, new and for this link (or signing off). Only TRUSTED gives a frame
power over the link itself (its reply address)."""


class SigningError(ValueError):
    """A key file that cannot be used, or a bad signing setting; the message says why."""


def load_key(path: str | Path) -> bytes:
    """Read a 32-byte secret key from a file (64 hex digits, or 32 raw bytes).

    Raises:
        SigningError: missing or unreadable file, readable by group or others, or not a
            32-byte key. The message never contains the key.
    """
    p = Path(path)
    try:
        st = p.stat()
        data = p.read_bytes()
    except OSError as exc:
        raise SigningError(f"{p}: cannot read the signing key ({exc.strerror or exc})") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SigningError(f"{p}: the signing key is readable by others (mode {stat.S_IMODE(st.st_mode):03o});"
                           f" run: chmod 600 {p}")
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(data) == 32:
        return data
    raise SigningError(f"{p}: expected a 32-byte key (64 hex digits or 32 raw bytes)")


def write_key(path: str | Path, key: bytes | None = None) -> bytes:
    """Create a key file readable only by its owner (a new random key unless given)."""
    key = os.urandom(32) if key is None else key
    if len(key) != 32:
        raise SigningError("a signing key is 32 bytes")
    p = Path(path)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    os.chmod(p, 0o600)
    return key


def now_10us(wall_clock: Callable[[], float] = time.time) -> int:
    """The signing clock: 10 µs units since 2015-01-01 UTC."""
    return int((wall_clock() - EPOCH_2015_UNIX_S) * 1e5)


class TimestampStore:
    """The last signing timestamp, in a file, so that a restart never reuses one.

    Args:
        path: the file (created if missing); None keeps nothing (wall clock only).
        every_s: how often `note` writes it (and at `close`).
    """

    def __init__(self, path: str | Path | None, every_s: float = 10.0):
        self.path = Path(path) if path is not None else None
        self.every_s = every_s
        self._written_at = -1e18
        self.last = 0
        if self.path is not None:
            try:
                self.last = int(self.path.read_text().strip() or 0)
            except (OSError, ValueError):
                self.last = 0

    def note(self, timestamp: int, mono_s: float) -> None:
        self.last = max(self.last, timestamp)
        if self.path is not None and mono_s - self._written_at >= self.every_s:
            self._written_at = mono_s
            self._write()

    def _write(self) -> None:
        if self.path is None:
            return
        tmp = self.path.with_suffix(self.path.suffix + ".tmp")
        try:
            tmp.write_text(f"{self.last}\n")
            os.replace(tmp, self.path)
        except OSError:
            pass  # a read-only disk must not stop the link; the wall clock still moves on

    def close(self) -> None:
        if self.path is not None:
            self._write()


@dataclass
class SigningCounters:
    """What a link's signing layer dropped (per link; reported in stats)."""

    unsigned: int = 0
    """Unsigned frames dropped because signing is required."""
    bad_signature: int = 0
    """Signed frames whose signature did not verify (wrong key, altered bytes)."""
    replayed: int = 0
    """Signed frames not new to the vehicle: a timestamp not newer than the last of their
    stream (on any link of the vehicle, including what it sent itself), or too old."""
    accepted_unsigned: int = 0
    """Unsigned frames let through (optional mode, or on the accept-unsigned list)."""
    setup_signing_refused: int = 0
    """SETUP_SIGNING frames refused on this link (unsigned, wrong key, replayed; also
    counted in the ones above), each answered by the SITL with a STATUSTEXT."""


class ReplayTable:
    """The last timestamp of every (link id, system id, component id) stream one vehicle
    has heard or sent, on all of its links (PX4 keeps one per vehicle too).

    A frame is new when its timestamp is newer than the last of its stream; a stream not
    seen before may start at most `window_10us` before the newest timestamp seen (None:
    any stream not seen is new). Holds at most `streams_max` streams (the oldest is
    forgotten first).
    """

    __slots__ = ("streams", "newest", "streams_max", "window_10us")

    def __init__(self, streams_max: int = STREAMS_MAX, window_10us: int | None = REPLAY_WINDOW_10US):
        self.streams: dict[tuple[int, int, int], int] = {}
        self.newest = 0
        self.streams_max = streams_max
        self.window_10us = window_10us

    def is_new(self, stream: tuple[int, int, int], ts_10us: int) -> bool:
        last = self.streams.get(stream)
        if last is None:
            return self.window_10us is None or ts_10us + self.window_10us >= self.newest
        return ts_10us > last

    def record(self, stream: tuple[int, int, int], ts_10us: int) -> None:
        streams = self.streams
        last = streams.get(stream)
        if last is None:
            if len(streams) >= self.streams_max:
                streams.pop(next(iter(streams)))
            streams[stream] = ts_10us
        elif ts_10us > last:
            streams[stream] = ts_10us
        if ts_10us > self.newest:
            self.newest = ts_10us


class ReplayScope(Protocol):
    """Which replay tables a link uses, for a link that serves several vehicles."""

    def received(self, frame: bytes) -> tuple[Sequence[ReplayTable], bool]:
        """For a signed frame that verified: the tables it must be new to (and is then
        recorded in), and whether it is for a vehicle this link serves (only then may it
        move the link's reply address)."""
        ...

    def sent(self, frame: bytes) -> ReplayTable | None:
        """The table that records a frame this link signed (its sender's)."""
        ...


def target_system_offsets(*dialects: Any) -> dict[int, int]:
    """msgid -> payload byte offset of its target_system field, for every message of the
    given mavgen modules that has one (wire order: mavgen's struct format, one item per field)."""
    out: dict[int, int] = {}
    for module in dialects:
        for msgid, cls in module.mavlink_map.items():
            wire = list(cls.ordered_fieldnames)
            if "target_system" not in wire or msgid in out:
                continue
            items = re.findall(r"\d*[a-zA-Z?]", cls.unpacker.format.lstrip("<>=!@"))
            out[msgid] = struct.calcsize("<" + "".join(items[:wire.index("target_system")]))
    return out


class FleetScope:
    """Replay tables of a process that simulates vehicles 1..n (the SITL): one table per
    vehicle, shared by the vehicle's own endpoint and the shared GCS endpoint.

    A received signed frame is checked against the table of the vehicle its target_system
    names; a broadcast (target 0, or no target field) against the tables of every vehicle
    this link serves (its own vehicle, or all of them on the GCS endpoint); a frame that
    claims to come from one of our autopilots (sysid k+1, compid 1) also against vehicle k's
    table, where everything vehicle k signed is recorded. A frame for a system this link
    does not serve is checked against the link's tables but moves nothing.

    A frame that names no target cannot say which vehicle it was for: on a vehicle endpoint
    it is also checked against `untargeted`, one table that every vehicle endpoint shares,
    so that a station's HEARTBEAT captured on vehicle 1's endpoint is a replay on vehicle
    2's (without it, the frame is new to vehicle 2 and would move its reply address).

    Args:
        tables: one per vehicle (index k = sysid k+1).
        served: the vehicle index of a vehicle endpoint; None for the GCS endpoint.
        offsets: target_system_offsets of the dialects.
        autopilot_compid: the component id our vehicles sign as.
        untargeted: the table shared by the vehicle endpoints for frames without a target
            (None: none). On the GCS endpoint such a frame is recorded in every vehicle's table.
    """

    def __init__(self, tables: Sequence[ReplayTable], served: int | None, offsets: dict[int, int],
                 autopilot_compid: int = 1, untargeted: ReplayTable | None = None):
        self.tables = tables
        self.served = served
        self.offsets = offsets
        self.autopilot_compid = autopilot_compid
        self._own = (tables[served],) if served is not None else tuple(tables)
        shared = (untargeted,) if served is not None and untargeted is not None else ()
        self._own_untargeted = (*self._own, *shared)

    def received(self, frame: bytes) -> tuple[Sequence[ReplayTable], bool]:
        n = len(self.tables)
        at = self.offsets.get(frame[7] | frame[8] << 8 | frame[9] << 16)
        target = frame[10 + at] if at is not None and at < frame[1] else 0  # truncated: 0
        if target == 0:
            tables: Sequence[ReplayTable] = self._own_untargeted
            ours = True
        elif target <= n:
            tables = (self.tables[target - 1],)
            ours = self.served is None or self.served == target - 1
        else:
            tables, ours = self._own, False
        src = frame[5]
        if 0 < src <= n and frame[6] == self.autopilot_compid and self.tables[src - 1] not in tables:
            tables = (*tables, self.tables[src - 1])
        return tables, ours

    def sent(self, frame: bytes) -> ReplayTable | None:
        src = frame[5]
        return self.tables[src - 1] if 0 < src <= len(self.tables) else None


@dataclass
class Signing:
    """The signing layer of one link (both directions).

    Args:
        mode: "off", "optional" or "require".
        key: the 32-byte secret (required unless mode is "off").
        link_id: the link id written into what we sign.
        store: keeps our last timestamp across restarts.
        crc_extra: msgid -> CRC_EXTRA (the codec's), to re-checksum a frame we sign.
        replay: the vehicle's replay table; give every link of one vehicle the same one
            (default: a table of this link's own).
        scope: for a link that serves several vehicles: picks the tables per frame
            (FleetScope); replaces `replay`.
        on_setup_refused: called with (target_system, reason) for every SETUP_SIGNING this
            layer drops ("unsigned", "wrong key" or "replayed"), so that its owner can answer.
    Raises:
        SigningError: an unknown mode, or no 32-byte key for a signing mode.
    """

    mode: SigningMode
    key: bytes = b""
    link_id: int = 0
    store: TimestampStore = field(default_factory=lambda: TimestampStore(None))
    crc_extra: Callable[[int], int | None] | None = None
    wall_clock: Callable[[], float] = time.time
    counters: SigningCounters = field(default_factory=SigningCounters)
    replay: ReplayTable = field(default_factory=ReplayTable)
    scope: ReplayScope | None = None
    on_setup_refused: Callable[[int, str], None] | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise SigningError(f"signing mode {self.mode!r}: expected one of {', '.join(MODES)}")
        if self.mode != "off" and len(self.key) != 32:
            raise SigningError(f"signing mode {self.mode!r} needs a 32-byte key (--signing-key FILE)")
        self._ts = max(now_10us(self.wall_clock), self.store.last + 1)
        self._hash = hashlib.sha256(self.key)
        """SHA-256 state after the key: copied per frame instead of hashing key + frame anew."""
        self._own = (self.replay,)

    @property
    def active(self) -> bool:
        return self.mode != "off"

    @property
    def claims_unsigned(self) -> bool:
        """Optional mode: an unsigned frame may claim a UDP link nobody has claimed yet
        (first contact, as PX4), never move it (companion.link.endpoints)."""
        return self.mode == "optional"

    # ---- outgoing --------------------------------------------------------------------
    def sign(self, frame: bytes) -> bytes:
        """A MAVLink 2 frame (unsigned, as the codec encodes it) signed with our key; its
        stream is recorded in the sender's replay table (an echo of it is a replay)."""
        if frame[0] != MAGIC_V2 or frame[2] & IFLAG_SIGNED:
            return frame  # MAVLink 1 cannot be signed; an already signed frame stays as it is
        end = 10 + frame[1]
        msgid = frame[7] | frame[8] << 8 | frame[9] << 16
        extra = self.crc_extra(msgid) if self.crc_extra is not None else None
        if extra is None:
            return frame
        body = bytes((frame[1], frame[2] | IFLAG_SIGNED)) + frame[3:end]  # the CRC covers the flags
        crc = _crc_with_extra(body, extra)
        self._ts = ts = max(self._ts + 1, now_10us(self.wall_clock))
        self.store.note(ts, time.monotonic())
        table = self.replay if self.scope is None else self.scope.sent(frame)
        if table is not None:
            table.record((self.link_id & 0xFF, frame[5], frame[6]), ts)
        signed = b"".join((MAGIC_V2_BYTES, body, crc.to_bytes(2, "little"), bytes((self.link_id & 0xFF,)),
                           ts.to_bytes(6, "little")))
        h = self._hash.copy()
        h.update(signed)
        return signed + h.digest()[:6]

    # ---- incoming --------------------------------------------------------------------
    def check(self, frame: bytes) -> bool:
        """True if the frame may be decoded; False (counted) if signing drops it."""
        return self.verdict(frame) != REJECTED

    def verdict(self, frame: bytes) -> int:
        """REJECTED (counted), UNSIGNED, VERIFIED or TRUSTED (module constants) for one
        well-delimited frame, before it is decoded. A frame that passes is recorded in the
        replay tables it was checked against."""
        if self.mode == "off":
            return TRUSTED
        if frame[0] != MAGIC_V2 or not frame[2] & IFLAG_SIGNED:
            msgid = frame[7] | frame[8] << 8 | frame[9] << 16 if frame[0] == MAGIC_V2 and len(frame) > 9 else \
                (frame[5] if len(frame) > 5 else -1)
            if self.mode == "optional" or msgid in ACCEPT_UNSIGNED:
                self.counters.accepted_unsigned += 1
                return UNSIGNED
            self.counters.unsigned += 1
            return self._refuse(frame, msgid, "unsigned")
        msgid = frame[7] | frame[8] << 8 | frame[9] << 16
        end = 12 + frame[1]
        if len(frame) < end + SIGNATURE_LEN:
            self.counters.bad_signature += 1
            return self._refuse(frame, msgid, "wrong key")
        h = self._hash.copy()
        h.update(frame[:end + 7])
        if h.digest()[:6] != frame[end + 7:end + 13]:
            self.counters.bad_signature += 1
            return self._refuse(frame, msgid, "wrong key")
        ts = int.from_bytes(frame[end + 1:end + 7], "little")
        stream = (frame[end], frame[5], frame[6])
        if self.scope is None:
            tables: Sequence[ReplayTable] = self._own
            ours = True
        else:
            tables, ours = self.scope.received(frame)
        for table in tables:
            if not table.is_new(stream, ts):
                self.counters.replayed += 1
                return self._refuse(frame, msgid, "replayed")
        for table in tables:
            table.record(stream, ts)
        return TRUSTED if ours else VERIFIED

    def _refuse(self, frame: bytes, msgid: int, reason: str) -> int:
        """REJECTED; a SETUP_SIGNING is also counted as such and reported to on_setup_refused."""
        if msgid == MsgId.SETUP_SIGNING:
            self.counters.setup_signing_refused += 1
            if self.on_setup_refused is not None:
                at = 10 + SETUP_SIGNING_TARGET_AT
                self.on_setup_refused(frame[at] if frame[1] > SETUP_SIGNING_TARGET_AT else 0, reason)
        return REJECTED

    def set_key(self, key: bytes) -> None:
        """A new key (SETUP_SIGNING over a trusted link). The replay tables stay: senders'
        timestamps keep increasing across a key change, and a table may be shared."""
        if len(key) != 32:
            raise SigningError("a signing key is 32 bytes")
        self.key = bytes(key)
        self._hash = hashlib.sha256(self.key)

    def close(self) -> None:
        self.store.close()
