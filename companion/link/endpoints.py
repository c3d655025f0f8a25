"""MAVLink endpoints: UDP, TCP and serial byte pipes, and the message layer on top.

`open_link(url)` gives a non-blocking `Link` (a socket or a serial port) with a
file descriptor that an asyncio loop watches (`loop.add_reader`); `recv()` drains
what is waiting in one call, so a flood costs one wake-up, not one per datagram.
`MavEndpoint` puts a codec and a bounded outbox on a Link: received frames come
out as messages (bad frames are counted and dropped, never raised), messages to
send are data in the outbox until `flush()` packs and sends them. The agent and
the SITL use the same classes.

URLs (companion.link.urls has every accepted form, from MAVSDK, pymavlink and MAVROS):
    udpin://HOST:PORT      listen; answer the peer (below)
    udpout://HOST:PORT     send there from an ephemeral port
    tcp://HOST:PORT        connect as a client
    serial:///dev/ttyAMA0:921600   a UART (8N1, raw; 57600 baud if none is given)

Who a listening UDP link answers (its reply address; docs/signing.md):
    * signing off: the sender of the last frame that decoded (nothing can be verified;
      as pymavlink and MAVProxy), or with first_contact_only (the SITL's autopilots, as
      PX4) the first sender for good.
    * peer_ids (an agent's own autopilot link): only frames from that (sysid, compid)
      claim or move it; with signing off it keeps the first such sender, hands over to
      another only after reclaim_after_s without a frame from the one it has, and drops
      frames claiming those ids from any other address meanwhile (counted in
      stranger_drops: a spoofed autopilot on the companion's port can neither take its
      setpoints nor feed it telemetry while the real one talks).
    * signing on (optional or require): only a TRUSTED frame moves it: signed, verified,
      new to the vehicle's replay table, and for a vehicle the link serves
      (companion.link.signing). An unsigned frame that is let through (RADIO_STATUS,
      ADSB_VEHICLE, COLLISION under require; anything under optional) moves nothing; under
      optional it may claim a link that nobody has claimed yet (first contact, as PX4),
      so that unsigned clients still get answers.
    * before any of that: the configured remote (the SITL's default destinations), or
      nobody (udpin: frames are counted in no_peer_drops).
Rejected frames (bad CRC, unknown, unsigned, forged, replayed) never move it.
"""
from __future__ import annotations

import collections
import errno
import math
import os
import socket
import time
from typing import Any, Callable, Sequence

from companion.link.framing import (
    MAGIC_V2,
    EncodeError,
    FrameError,
    FrameSplitter,
    UnknownMessage,
    frame_ids,
    split_datagram,
)
from companion.link.signing import TRUSTED, UNSIGNED, Signing
from companion.link.tlog import Tlog
from companion.link.urls import EndpointError, LinkAddress, parse_url  # noqa: F401  (re-exported)
from companion.link.wire import Codec

MAX_DATAGRAMS_PER_RECV = 512
"""A recv() call returns after this many datagrams even if more are waiting, so a
flood on one link cannot starve the rest of the loop."""
UDP_RCVBUF_BYTES = 1 << 20
DATAGRAM_BYTES = 1400
"""Frames for one destination are packed into datagrams up to this size (under a typical MTU)."""

class Link:
    """A non-blocking MAVLink byte pipe. Subclasses: UdpLink, StreamLink.

    Attributes (counters):
        bytes_in, bytes_out, frames_in: traffic.
        bytes_skipped: bytes that were not part of a whole frame (garbage, truncation).
        send_errors: sends the OS refused (buffer full, peer gone); the frame is dropped.
        no_peer_drops: frames dropped because nobody has talked to a listening link yet.
        stranger_drops: frames claiming peer_ids from another address than the peer's
            (UdpLink with peer_ids, signing off).
    """

    def __init__(self) -> None:
        self.bytes_in = self.bytes_out = self.frames_in = 0
        self.bytes_skipped = self.send_errors = self.no_peer_drops = self.stranger_drops = 0

    def fileno(self) -> int:
        raise NotImplementedError

    def recv(self, max_datagrams: int = MAX_DATAGRAMS_PER_RECV) -> list[tuple[bytes, Any]]:
        """Whole frames waiting now, with the address they came from; never blocks.

        Args:
            max_datagrams: a datagram link reads at most this many datagrams (1: one, and no
                read that finds the socket empty; a level-triggered event loop calls again
                while more wait). A stream link reads what is there either way.
        """
        raise NotImplementedError

    def send(self, frame: bytes, addr: Any = None) -> bool:
        """Send one frame (to addr, or the link's peer); False if it was dropped."""
        raise NotImplementedError

    def note_peer(self, addr: Any) -> None:
        """A trusted frame came from addr (datagram links may answer there from now on)."""

    def note_first_contact(self, addr: Any) -> None:
        """An accepted but unverified frame came from addr: a datagram link nobody has
        claimed yet may answer there; a claimed one stays where it is."""

    def note_unverified(self, addr: Any) -> None:
        """A frame came from addr with signing off (nothing can be verified): follow the last
        sender, or with first_contact_only keep the first (UdpLink with peer_ids: its rule)."""
        if self.first_contact_only:
            self.note_first_contact(addr)
        else:
            self.note_peer(addr)

    learn_remote = False
    """Frames may move where the link sends (a listening UdpLink): else no note_* call matters."""
    first_contact_only = False
    """With signing off, answer the first sender for good (UdpLink's option), not the last."""
    peer_ids: tuple[int, int] | None = None
    """Only frames from this (sysid, compid) claim or move the reply address (UdpLink's option)."""

    def stranger(self, addr: Any) -> bool:
        """With signing off and peer_ids: a frame claiming peer_ids from addr comes from
        someone else than the peer this link answers (and the peer is still talking)."""
        return False

    def close(self) -> None:
        raise NotImplementedError


class UdpLink(Link):
    """One UDP socket.

    Args:
        bind: local (host, port) to listen on; port 0 = ephemeral.
        remote: where to send until someone talks to us (None: nowhere yet).
        learn_remote: answer where trusted frames come from (udpin; the module docstring
            says which frames are trusted).
        first_contact_only: with signing off, answer the first sender for good instead of the
            last one (PX4: its UDP client address is fixed at first contact), so that a
            stranger's frames cannot take the link from whoever spoke first.
        peer_ids: (sysid, compid) of the one system this link serves (an agent's autopilot):
            frames from other ids never claim or move the reply address. With signing off
            the link then behaves as first_contact_only, except that another address may
            take it over once the one it answers has sent nothing for reclaim_after_s (an
            autopilot or router restarted on a new port); until then frames claiming
            peer_ids from elsewhere are dropped (stranger_drops).
        reclaim_after_s: see peer_ids, s. clock: monotonic seconds (injected for tests).
    Raises:
        OSError: the port cannot be bound (the message names host:port).
    """

    def __init__(self, bind: tuple[str, int] = ("127.0.0.1", 0), remote: tuple[str, int] | None = None,
                 learn_remote: bool = True, first_contact_only: bool = False,
                 peer_ids: tuple[int, int] | None = None, reclaim_after_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic):
        super().__init__()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RCVBUF_BYTES)
        except OSError:  # a smaller buffer still works
            pass
        try:
            self.sock.bind(bind)
        except (OSError, OverflowError, TypeError) as exc:  # in use, no such address, bad port
            self.sock.close()
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise OSError(getattr(exc, "errno", None) or errno.EINVAL,
                          f"cannot listen on UDP {bind[0] or '0.0.0.0'}:{bind[1]}: {reason}") from None
        self.sock.setblocking(False)
        self.remote = remote
        self.learn_remote = learn_remote
        self.first_contact_only = first_contact_only or peer_ids is not None
        self.peer_ids = peer_ids
        self.reclaim_after_s = reclaim_after_s
        self._clock = clock
        self._remote_heard_s = -math.inf
        """clock() when the peer (remote) last sent a frame that counted (peer_ids links)."""
        self.claimed = False
        """Someone has talked to us (first contact): only trusted frames move remote now."""

    @property
    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def fileno(self) -> int:
        return self.sock.fileno()

    def recv(self, max_datagrams: int = MAX_DATAGRAMS_PER_RECV) -> list[tuple[bytes, Any]]:
        out: list[tuple[bytes, Any]] = []
        sock = self.sock
        for _ in range(max_datagrams):
            try:
                data, addr = sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ICMP port unreachable reported on a later call
                continue
            self.bytes_in += len(data)
            frames, skipped = split_datagram(data)
            self.bytes_skipped += skipped
            self.frames_in += len(frames)
            out += [(f, addr) for f in frames]
        return out

    def note_peer(self, addr: Any) -> None:
        """A trusted frame came from addr (it decoded and, with signing on, was signed,
        verified and new to the vehicle): with learn_remote, answer there from now on."""
        if self.learn_remote and addr is not None:
            self.remote = addr
            self.claimed = True
            self._remote_heard_s = self._clock()

    def note_first_contact(self, addr: Any) -> None:
        if self.learn_remote and addr is not None and not self.claimed:
            self.remote = addr
            self.claimed = True
            self._remote_heard_s = self._clock()

    def note_unverified(self, addr: Any) -> None:
        if self.peer_ids is None:
            super().note_unverified(addr)
            return
        if not self.learn_remote or addr is None:
            return
        now = self._clock()
        if self.claimed and addr != self.remote and now - self._remote_heard_s < self.reclaim_after_s:
            return
        self.remote = addr
        self.claimed = True
        self._remote_heard_s = now

    def stranger(self, addr: Any) -> bool:
        return (self.peer_ids is not None and self.claimed and addr != self.remote
                and self._clock() - self._remote_heard_s < self.reclaim_after_s)

    def send(self, frame: bytes, addr: Any = None) -> bool:
        dest = addr or self.remote
        if dest is None:
            self.no_peer_drops += 1
            return False
        try:
            self.sock.sendto(frame, dest)
        except OSError:
            self.send_errors += 1
            return False
        self.bytes_out += len(frame)
        return True

    def close(self) -> None:
        self.sock.close()


class StreamLink(Link):
    """A byte stream (TCP socket or serial port) cut into frames by a FrameSplitter.

    Args:
        fd_owner: the socket object, or an int file descriptor (serial).
        crc_extra: msgid -> CRC_EXTRA for resynchronising on corrupt bytes (Codec.crc_extra).
    """

    def __init__(self, fd_owner: socket.socket | int, crc_extra: Callable[[int], int | None] | None = None):
        super().__init__()
        self._sock = fd_owner if isinstance(fd_owner, socket.socket) else None
        self._fd = fd_owner.fileno() if isinstance(fd_owner, socket.socket) else int(fd_owner)
        self._splitter = FrameSplitter(crc_extra)

    def fileno(self) -> int:
        return self._fd

    def recv(self, max_datagrams: int = MAX_DATAGRAMS_PER_RECV) -> list[tuple[bytes, Any]]:
        out: list[tuple[bytes, Any]] = []
        for _ in range(64):
            try:
                data = os.read(self._fd, 65536)
            except (BlockingIOError, InterruptedError):
                break
            if not data:  # peer closed
                break
            self.bytes_in += len(data)
            before = self._splitter.bytes_skipped
            frames = self._splitter.feed(data)
            self.bytes_skipped += self._splitter.bytes_skipped - before
            self.frames_in += len(frames)
            out += [(f, None) for f in frames]
        return out

    def send(self, frame: bytes, addr: Any = None) -> bool:
        try:
            n = os.write(self._fd, frame)
        except OSError:
            self.send_errors += 1
            return False
        if n != len(frame):  # a partial write would desynchronise the peer's parser
            self.send_errors += 1
            return False
        self.bytes_out += n
        return True

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
        else:
            os.close(self._fd)


def _open_serial(device: str, baud: int) -> int:
    import termios  # POSIX only; imported here so that importing this module works anywhere

    fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    attrs = termios.tcgetattr(fd)
    speed = getattr(termios, f"B{baud}")
    attrs[0] = 0  # iflag: raw
    attrs[1] = 0  # oflag
    attrs[2] = termios.CS8 | termios.CREAD | termios.CLOCAL  # cflag: 8N1
    attrs[3] = 0  # lflag: no echo, no canonical mode
    attrs[4] = attrs[5] = speed
    termios.tcsetattr(fd, termios.TCSANOW, attrs)
    return fd


def open_link(url: str | LinkAddress, crc_extra: Callable[[int], int | None] | None = None,
              connect_timeout_s: float = 5.0, peer_ids: tuple[int, int] | None = None) -> Link:
    """Open a link from its URL (companion.link.urls).

    Args:
        connect_timeout_s: how long a TCP connect may take (a server that answers nothing).
        peer_ids: udpin only: the (sysid, compid) the link serves (UdpLink's peer_ids rule).
    Raises:
        EndpointError: bad URL. OSError: cannot bind, connect or open the device; the
            message names the URL (a serial port: the device and the baud rate apart), and
            its errno is the OS's (ECONNREFUSED: no TCP server listens there yet).
    """
    a = parse_url(url) if isinstance(url, str) else url
    if a.scheme == "serial":
        import termios

        try:
            return StreamLink(_open_serial(a.device, a.baud), crc_extra)
        except OSError as exc:
            raise OSError(exc.errno or errno.EIO,
                          f"serial device {a.device} (at {a.baud} baud): {exc.strerror or exc}") from None
        except termios.error as exc:  # (an existing file that is not a terminal: /dev/null, a regular file)
            code, text = (*exc.args, errno.ENOTTY, "not a terminal")[:2]
            raise OSError(code if isinstance(code, int) else errno.ENOTTY,
                          f"serial device {a.device} (at {a.baud} baud): not a serial port ({text})") from None
    try:
        if a.scheme == "udpin":
            remote = (a.remote_host, a.remote_port) if a.remote_port else None
            return UdpLink(bind=(a.host, a.port), remote=remote, learn_remote=True, peer_ids=peer_ids)
        if a.scheme == "udpout":
            return UdpLink(bind=("0.0.0.0" if a.host not in ("127.0.0.1", "localhost") else "127.0.0.1", 0),
                           remote=(a.host, a.port), learn_remote=False)
        sock = socket.create_connection((a.host, a.port), timeout=connect_timeout_s)
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return StreamLink(sock, crc_extra)
    except OSError as exc:
        code = exc.errno or (errno.ETIMEDOUT if isinstance(exc, TimeoutError) else errno.EIO)
        raise OSError(code, f"{url}: {exc.strerror or exc}") from None


class MavEndpoint:
    """Messages over one Link: decode what arrives, queue and flush what leaves.

    The outbox is bounded: when it is full the oldest message is dropped and
    counted, so a burst of replies can never grow memory without limit.

    Args:
        link: the byte pipe.
        codec: frame <-> message (companion.link.wire.Codec).
        sysid, compid: our ids for messages sent without explicit ids.
        tlog: log every frame sent and received (optional).
        outbox_max: messages held before the oldest is dropped.
        signing: MAVLink 2 signing of this link (companion.link.signing); None = off.
    """

    def __init__(self, link: Link, codec: Codec, sysid: int, compid: int, tlog: Tlog | None = None,
                 outbox_max: int = 4096, signing: Signing | None = None):
        self.signing = signing if signing is not None and signing.active else None
        self.link = link
        self.codec = codec
        self.sysid = sysid
        self.compid = compid
        self.tlog = tlog
        self._outbox: collections.deque = collections.deque(maxlen=outbox_max)
        self._seq: dict[tuple[int, int], int] = {}
        self.received = self.sent = 0
        self.bad_frames = 0
        """Frames that failed to decode (CRC, truncated, bad flags): counted and dropped."""
        self.unknown = 0
        """Well-formed frames of messages this codec's dialect does not define: dropped."""
        self.unencodable = 0
        """Queued messages that could not be encoded (out-of-range values): dropped."""
        self.outbox_drops = 0
        self.on_unknown: Callable[[int, bytes], None] | None = None
        """Told (msgid, frame) of each well-formed frame whose message the codec does not
        define (counted in unknown and dropped either way)."""

    def _drain(self, take: Callable[[bytes, Any], None], max_datagrams: int = MAX_DATAGRAMS_PER_RECV) -> None:
        """Pass every waiting frame and its source address to take, which decodes it and
        keeps the result; a frame take rejects is counted (unknown / bad) and dropped, a
        kept one goes to the tlog. A kept frame moves the link's reply address only as the
        module docstring says. Never raises on bad input."""
        n, tlog, sg, link, last_addr = 0, self.tlog, self.signing, self.link, None
        peer_ids, learn = link.peer_ids, link.learn_remote
        verdict = TRUSTED
        for frame, addr in link.recv(max_datagrams):
            ids_match = peer_ids is None or frame_ids(frame) == peer_ids
            if sg is not None:
                verdict = sg.verdict(frame)
                if not verdict:
                    continue  # unsigned / forged / replayed: counted in sg.counters
            elif peer_ids is not None and ids_match and link.stranger(addr):
                link.stranger_drops += 1  # someone else claims to be our autopilot: nothing to verify
                continue
            try:
                take(frame, addr)
            except UnknownMessage as err:
                self.unknown += 1
                if self.on_unknown is not None:
                    self.on_unknown(err.msgid, frame)
                continue
            except FrameError:
                self.bad_frames += 1
                continue
            if tlog is not None:
                tlog.write(frame)
            if not learn or not ids_match:
                pass  # a link that never moves, or another system on the port (a ground station)
            elif sg is None:  # nothing to verify: Link.note_unverified's rule
                if addr != last_addr:
                    link.note_unverified(addr)
                    last_addr = addr
            elif verdict == TRUSTED:
                link.note_peer(addr)
            elif verdict == UNSIGNED and sg.claims_unsigned:
                link.note_first_contact(addr)
            n += 1
        self.received += n

    def poll(self) -> list[tuple[Any, Any]]:
        """(message, source address) for everything waiting; never raises on bad input."""
        out, decode = [], self.codec.decode
        self._drain(lambda frame, addr: out.append((decode(frame), addr)))
        return out

    def poll_split(self, raw_ids: frozenset, max_datagrams: int = MAX_DATAGRAMS_PER_RECV) -> tuple[list, list]:
        """Like poll, but messages whose id is in raw_ids come as (msgid, sysid, compid,
        wire-order values) tuples (no message object); returns (raw list, message list).
        max_datagrams: as Link.recv's."""
        raw, msgs = [], []
        decode, decode_raw = self.codec.decode, self.codec.decode_raw

        def take(frame: bytes, _addr: Any) -> None:
            msgid = frame[7] | frame[8] << 8 | frame[9] << 16 if frame[0] == MAGIC_V2 and len(frame) > 9 else -1
            if msgid in raw_ids:
                raw.append(decode_raw(frame))
            else:
                msgs.append(decode(frame))

        self._drain(take, max_datagrams)
        return raw, msgs

    def poll_raw(self) -> list[tuple[int, int, int, tuple, Any]]:
        """(msgid, sysid, compid, wire-order values, source address) for everything waiting:
        poll without message objects (Codec.decode_raw), for high-rate messages."""
        out, decode_raw = [], self.codec.decode_raw
        self._drain(lambda frame, addr: out.append((*decode_raw(frame), addr)))
        return out

    def queue(self, msg: Any, addr: Any = None, sysid: int | None = None, compid: int | None = None) -> None:
        """Queue a message object (sent by the next flush)."""
        if len(self._outbox) == self._outbox.maxlen:
            self.outbox_drops += 1
        self._outbox.append((msg, None, addr, sysid, compid))

    def queue_fields(self, msgid: int, values: Sequence, addr: Any = None, sysid: int | None = None,
                     compid: int | None = None) -> None:
        """Queue a message given as its id and field values in declaration order (fast path)."""
        if len(self._outbox) == self._outbox.maxlen:
            self.outbox_drops += 1
        self._outbox.append((msgid, values, addr, sysid, compid))

    @property
    def pending(self) -> int:
        return len(self._outbox)

    def flush(self, budget: int | None = None) -> int:
        """Pack and send queued messages, at most budget of them; returns how many were sent.

        Consecutive frames for one destination share a datagram (up to DATAGRAM_BYTES),
        as PX4 batches its UDP output: a receiver then wakes once for a tick's telemetry.
        Stream links get the same bytes in one write.
        """
        out, link, codec, tlog, seqs, sg = self._outbox, self.link, self.codec, self.tlog, self._seq, self.signing
        n = len(out) if budget is None else min(budget, len(out))
        sent = 0
        buf, buf_addr, buf_frames = b"", None, 0
        for _ in range(n):
            msg, values, addr, sysid, compid = out.popleft()
            key = (self.sysid if sysid is None else sysid, self.compid if compid is None else compid)
            seq = seqs.get(key, 0)
            try:
                if values is None:
                    frame = codec.encode(msg, key[0], key[1], seq)
                else:
                    frame = codec.encode_fields(msg, values, key[0], key[1], seq)
            except EncodeError:
                self.unencodable += 1
                continue
            seqs[key] = (seq + 1) & 0xFF
            if sg is not None:
                frame = sg.sign(frame)
            if tlog is not None:
                tlog.write(frame)
            if buf and (addr != buf_addr or len(buf) + len(frame) > DATAGRAM_BYTES):
                if link.send(buf, buf_addr):
                    sent += buf_frames
                buf, buf_frames = b"", 0
            buf += frame
            buf_addr = addr
            buf_frames += 1
        if buf and link.send(buf, buf_addr):
            sent += buf_frames
        self.sent += sent
        return sent

    def close(self) -> None:
        if self.signing is not None:
            self.signing.close()
        self.link.close()
