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

Keys come from a file (64 hex digits, or 32 raw bytes) that only its owner may read;
never from the command line, the environment or a log. Timestamps are taken from the
wall clock and never go backwards: a `TimestampStore` file keeps the last one, so a
restarted sender never reuses one.
"""
from __future__ import annotations

import hashlib
import os
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

from companion.link.wire import IFLAG_SIGNED, SIGNATURE_LEN, _crc_with_extra

SigningMode = Literal["off", "optional", "require"]
MODES: tuple[str, ...] = ("off", "optional", "require")

ACCEPT_UNSIGNED = frozenset({109, 246, 247})
"""RADIO_STATUS, ADSB_VEHICLE, COLLISION: accepted unsigned even when signing is required (PX4)."""
MSGID_SETUP_SIGNING = 256

EPOCH_2015_UNIX_S = 1420070400
REPLAY_WINDOW_10US = 6_000_000
"""A new stream's first timestamp may be at most 60 s older than the newest seen (MAVLink spec)."""
STREAMS_MAX = 1024
"""Streams remembered per receiver; beyond this the oldest is forgotten (bounded memory)."""


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
    """Signed frames with a timestamp not newer than the last of their stream (or too old)."""
    accepted_unsigned: int = 0
    """Unsigned frames let through (optional mode, or on the accept-unsigned list)."""


@dataclass
class Signing:
    """The signing layer of one link (both directions).

    Args:
        mode: "off", "optional" or "require".
        key: the 32-byte secret (required unless mode is "off").
        link_id: the link id written into what we sign.
        store: keeps our last timestamp across restarts.
        crc_extra: msgid -> CRC_EXTRA (the codec's), to re-checksum a frame we sign.
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

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise SigningError(f"signing mode {self.mode!r}: expected one of {', '.join(MODES)}")
        if self.mode != "off" and len(self.key) != 32:
            raise SigningError(f"signing mode {self.mode!r} needs a 32-byte key (--signing-key FILE)")
        self._ts = max(now_10us(self.wall_clock), self.store.last + 1)
        self._hash = hashlib.sha256(self.key)
        """SHA-256 state after the key: copied per frame instead of hashing key + frame anew."""
        self._streams: dict[tuple[int, int, int], int] = {}
        self._newest = 0

    @property
    def active(self) -> bool:
        return self.mode != "off"

    # ---- outgoing --------------------------------------------------------------------
    def sign(self, frame: bytes) -> bytes:
        """A MAVLink 2 frame (unsigned, as the codec encodes it) signed with our key."""
        if frame[0] != 0xFD or frame[2] & IFLAG_SIGNED:
            return frame  # MAVLink 1 cannot be signed; an already signed frame stays as it is
        end = 10 + frame[1]
        msgid = frame[7] | frame[8] << 8 | frame[9] << 16
        extra = self.crc_extra(msgid) if self.crc_extra is not None else None
        if extra is None:
            return frame
        body = bytes((frame[1], frame[2] | IFLAG_SIGNED)) + frame[3:end]  # the CRC covers the flags
        crc = _crc_with_extra(body, extra)
        self._ts = max(self._ts + 1, now_10us(self.wall_clock))
        self.store.note(self._ts, time.monotonic())
        signed = b"".join((b"\xfd", body, crc.to_bytes(2, "little"), bytes((self.link_id & 0xFF,)),
                           self._ts.to_bytes(6, "little")))
        h = self._hash.copy()
        h.update(signed)
        return signed + h.digest()[:6]

    # ---- incoming --------------------------------------------------------------------
    def check(self, frame: bytes) -> bool:
        """True if the frame may be decoded; False (counted) if signing drops it.
        Called for every well-delimited frame before it is decoded."""
        if self.mode == "off":
            return True
        if frame[0] != 0xFD or not frame[2] & IFLAG_SIGNED:
            msgid = frame[7] | frame[8] << 8 | frame[9] << 16 if frame[0] == 0xFD and len(frame) > 9 else \
                (frame[5] if len(frame) > 5 else -1)
            if self.mode == "optional" or msgid in ACCEPT_UNSIGNED:
                self.counters.accepted_unsigned += 1
                return True
            self.counters.unsigned += 1
            return False
        end = 12 + frame[1]
        if len(frame) < end + SIGNATURE_LEN:
            self.counters.bad_signature += 1
            return False
        signed_part, sig = frame[:end + 7], frame[end + 7:end + 13]
        h = self._hash.copy()
        h.update(signed_part)
        if h.digest()[:6] != sig:
            self.counters.bad_signature += 1
            return False
        link_id = frame[end]
        ts = int.from_bytes(frame[end + 1:end + 7], "little")
        key = (link_id, frame[5], frame[6])
        last = self._streams.get(key)
        if last is None:
            if ts + REPLAY_WINDOW_10US < self._newest:
                self.counters.replayed += 1
                return False
            if len(self._streams) >= STREAMS_MAX:
                self._streams.pop(next(iter(self._streams)))
        elif ts <= last:
            self.counters.replayed += 1
            return False
        self._streams[key] = ts
        self._newest = max(self._newest, ts)
        return True

    def set_key(self, key: bytes) -> None:
        """A new key (SETUP_SIGNING over a trusted link): streams start afresh."""
        if len(key) != 32:
            raise SigningError("a signing key is 32 bytes")
        self.key = bytes(key)
        self._hash = hashlib.sha256(self.key)
        self._streams.clear()

    def close(self) -> None:
        self.store.close()
