"""The simulated swarm radio: one broadcast in, copies out to the vehicles in range.

Every agent sends its SWARMDROP_STATE once, to the medium's UDP port (a mesh
radio's broadcast, without multicast). The medium decides with the RadioModel of
the neighbour transports (sim_bridge.transport: same seed, same fate) which
vehicles hear each copy and when, on simulation time, and forwards the frames
unchanged (a signature stays valid) to each receiving agent, batched into one
datagram per agent per tick. All-to-all unicast would cost every agent N-1 sends
per update; here it costs one, which is also what a mesh radio does.

In lockstep each agent's batch ends with a SWARMDROP_TICK for the tick, so an
agent knows it has everything due before it steps (docs/sitl.md).

It also keeps what the fleet harness and the recorder need: every vehicle's last
published phase, flags and transit start, bytes per vehicle, and ages.
"""
from __future__ import annotations

import math

import numpy as np

from companion.link.endpoints import UdpLink
from companion.link.msgdef import swarmdrop as sd
from companion.link.wire import Codec, FrameError
from companion.swarm import PHASE_COUNT
from sim_bridge.results import LinkStats, MeanMax
from sim_bridge.transport import AgeHistogram, LinkConfig, RadioModel

MAX_DATAGRAM_BYTES = 1400
"""Batches larger than this go out as several datagrams (one radio frame's worth)."""
_STATE_ID = sd.MAVLINK_MSG_ID_SWARMDROP_STATE


class Medium:
    """The radio between the agents of one SITL.

    Args:
        n: vehicles.
        link: loss, delay, jitter, range.
        seed: the run's seed.
        epoch_unix_s: converts SWARMDROP_STATE time_usec (Unix) to simulation time.
        bind: local (host, port).
        agent_ports: where vehicle k's agent listens (None: the address it sends from).
        host: the agents' host.
    """

    def __init__(self, n: int, link: LinkConfig, seed: int, epoch_unix_s: float, bind: tuple[str, int],
                 agent_ports: list[int] | None = None, host: str = "127.0.0.1", signing=None):
        self.signing = signing
        """Signs the radio's own end-of-tick marker when the fleet is signed (agents'
        states are forwarded as they were sent, signatures and all)."""
        self.n = n
        self.radio = RadioModel(link, seed)
        self.epoch_unix_s = epoch_unix_s
        self.link = UdpLink(bind=bind, remote=None, learn_remote=False)
        self.codec = Codec(sd)
        self.addr: list[tuple[str, int] | None] = [(host, p) for p in agent_ports] if agent_ports else [None] * n
        self._learn = not agent_ports
        self._inbox: list[tuple[int, float, bytes]] = []
        self._frames: list[bytes] = []
        # copies in flight: delivery time, receiver, index into _frames, stamp (s)
        self._p_when = np.zeros(0)
        self._p_rcv = np.zeros(0, dtype=np.int64)
        self._p_frame = np.zeros(0, dtype=np.int64)
        self._p_stamp = np.zeros(0)
        self.latest_stamp_us = np.full(n, -1, dtype=np.int64)
        """time_usec of the newest state received from each vehicle (lockstep gate)."""
        self.phase = np.zeros(n, dtype=np.int8)
        self.flags = np.zeros(n, dtype=np.uint8)
        self.t_go_s = np.full(n, np.nan)
        self.bytes_in = np.zeros(n, dtype=np.int64)
        self.states_in = np.zeros(n, dtype=np.int64)
        self.copies_sent = self.copies_delivered = self.copies_lost = 0
        self.bad_frames = 0
        self.foreign = 0
        """Frames that are not a SWARMDROP_STATE of a known vehicle: dropped."""
        self.ages = AgeHistogram()

    @property
    def port(self) -> int:
        return self.link.local_port

    def fileno(self) -> int:
        return self.link.fileno()

    def receive(self) -> int:
        """Take what agents sent (their copies are scheduled by the next schedule()).
        Returns the number of states taken."""
        taken = 0
        for frame, addr in self.link.recv():
            try:
                msg = self.codec.decode(frame)
            except FrameError:
                self.bad_frames += 1
                continue
            if msg.get_msgId() != _STATE_ID or not 0 <= msg.vehicle_id < self.n \
                    or msg.get_srcSystem() != msg.vehicle_id + 1:
                self.foreign += 1
                continue
            if msg.phase >= PHASE_COUNT:  # hostile or corrupt: agents would drop it too
                self.bad_frames += 1
                continue
            k = msg.vehicle_id
            if self._learn:
                self.addr[k] = addr
            self.bytes_in[k] += len(frame)
            self.states_in[k] += 1
            stamp_us = int(msg.time_usec)
            if stamp_us > self.latest_stamp_us[k]:
                self.latest_stamp_us[k] = stamp_us
                self.phase[k], self.flags[k] = msg.phase, msg.flags
                self.t_go_s[k] = (msg.t_go_usec * 1e-6 - self.epoch_unix_s) if msg.t_go_usec else math.nan
            self._inbox.append((k, stamp_us * 1e-6 - self.epoch_unix_s, frame))
            taken += 1
        return taken

    def schedule(self, sim_s: float, positions_ned_m: np.ndarray) -> None:
        """Decide the fate of every copy of the states received since the last call
        (one vectorised draw for all of them)."""
        if not self._inbox:
            return
        inbox, self._inbox = self._inbox, []
        senders = np.array([k for k, _, _ in inbox])
        stamps = np.array([st for _, st, _ in inbox])
        pos = np.asarray(positions_ned_m, float)
        m_idx, rcv, when = self.radio.deliveries(senders, stamps, sim_s, pos[senders], pos)
        self.copies_sent += len(inbox) * (self.n - 1)
        self.copies_lost += len(inbox) * (self.n - 1) - len(rcv)
        base = len(self._frames)
        self._frames += [f for _, _, f in inbox]
        self._p_when = np.concatenate([self._p_when, when])
        self._p_rcv = np.concatenate([self._p_rcv, rcv])
        self._p_frame = np.concatenate([self._p_frame, base + m_idx])
        self._p_stamp = np.concatenate([self._p_stamp, stamps[m_idx]])

    def deliver(self, sim_s: float, receivers: np.ndarray, tick_marker: bool) -> int:
        """Send the copies due by sim_s to the given receivers, one batch per agent, plus the
        lockstep end-of-tick marker when asked. Returns the number of copies sent.

        Args:
            receivers: (N,) bool, the agents at a control tick now (the others get theirs
                at their own tick: one datagram per agent per tick, not one per SITL tick).
        """
        due = (self._p_when <= sim_s + 1e-9) & receivers[self._p_rcv] if len(self._p_when) else np.zeros(0, bool)
        batches: dict[int, list[bytes]] = {}
        if due.any():
            idx = np.flatnonzero(due)
            idx = idx[np.argsort(self._p_rcv[idx], kind="stable")]
            frames = self._frames
            for r, fi in zip(self._p_rcv[idx].tolist(), self._p_frame[idx].tolist()):
                batches.setdefault(r, []).append(frames[fi])
            self.ages.add(sim_s - self._p_stamp[idx])
            keep = ~due
            self._p_when, self._p_rcv = self._p_when[keep], self._p_rcv[keep]
            self._p_frame, self._p_stamp = self._p_frame[keep], self._p_stamp[keep]
            if not len(self._p_frame):  # nothing in flight: forget the frames too
                self._frames = []
            elif len(self._frames) > 4 * len(self._p_frame) + 1024:  # compact the frame store
                live = np.unique(self._p_frame)
                remap = np.full(len(self._frames), -1, dtype=np.int64)
                remap[live] = np.arange(len(live))
                self._frames = [self._frames[i] for i in live.tolist()]
                self._p_frame = remap[self._p_frame]
        n_due = int(due.sum())
        if tick_marker:
            marker = self.codec.encode_fields(sd.MAVLINK_MSG_ID_SWARMDROP_TICK,
                                              [int(round((self.epoch_unix_s + sim_s) * 1e6))], 255, 0, 0)
            if self.signing is not None:
                marker = self.signing.sign(marker)
            for k in np.flatnonzero(receivers).tolist():
                batches.setdefault(k, []).append(marker)
        for k, frames in batches.items():
            addr = self.addr[k]
            if addr is None:
                continue
            buf = b""
            for f in frames:
                if len(buf) + len(f) > MAX_DATAGRAM_BYTES and buf:
                    self.link.send(buf, addr)
                    buf = b""
                buf += f
            if buf:
                self.link.send(buf, addr)
        self.copies_delivered += n_due
        return n_due

    def stats(self, sim_s: float) -> LinkStats:
        """Link statistics for metrics.json (bytes/s per vehicle over the simulated time)."""
        dur = max(sim_s, 1e-9)
        per_vehicle = self.bytes_in / dur
        return LinkStats(
            kind=self.radio.cfg.kind, loss=self.radio.cfg.loss, delay_s=self.radio.cfg.delay_s,
            jitter_s=self.radio.cfg.jitter_s,
            bytes_per_s_per_vehicle=MeanMax(mean=float(per_vehicle.mean()), max=float(per_vehicle.max())),
            states_received=int(self.states_in.sum()), copies_sent=self.copies_sent,
            copies_delivered=self.copies_delivered,
            delivered_fraction=self.copies_delivered / self.copies_sent if self.copies_sent else None,
            copies_lost=self.copies_lost, bad_frames=self.bad_frames, foreign_frames=self.foreign,
            age_at_delivery_s=self.ages.summary(),
        )

    def close(self) -> None:
        self.link.close()
