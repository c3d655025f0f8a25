"""The simulated swarm radio: one broadcast in, copies out to the vehicles in range.

Every agent sends its SWARMDROP_STATE once, to the medium's UDP port (a mesh
radio's broadcast, without multicast). The medium decides with the RadioModel of
the neighbour transports (sim_bridge.world.transport: same seed, same fate) which
vehicles hear each copy and when, on simulation time, and forwards the frames
unchanged (a signature stays valid) to each receiving agent, batched into one
datagram per agent per tick. All-to-all unicast would cost every agent N-1 sends
per update; here it costs one, which is also what a mesh radio does.

In lockstep each agent's batch ends with a SWARMDROP_TICK for the tick, so an
agent knows it has everything due before it steps (docs/sitl.md).

It also keeps what the fleet harness and the recorder need: every vehicle's last
published phase, flags and transit start, bytes per vehicle, and ages.

Monitors (an operator's console, docs/console.md): every state the radio takes is also
copied, unchanged and at once, to each monitor address (`set_monitors`, `--medium-monitor`),
one batch per receive. Swarm plans (SWARMDROP_PLAN, SWARMDROP_SLOTS; docs/swarm.md) travel
two ways, unchanged (the agents check signatures and seqs themselves), and are copied to
the monitors at once:

* from a vehicle's own sender (an agent relaying the newest plan it holds) and from the
  SITL's own command source (`send_plan`: a scenario's `commands:` schedule, sender N, a
  ground station at the fleet's centroid): **on the radio**, each copy lost and delayed by
  the link's RadioModel on a hash stream of its own (the headless plan radio's salt,
  sim_bridge.world.plan_radio), delivered with the states at each receiver's swarm tick,
  so a lockstep run repeats exactly; at most `relay_frames_per_s` a vehicle (simulated
  time; more are dropped and counted). `plan_listener` hears, on simulation time, which
  plan frame reached which vehicles and which plan_seq each vehicle's states carry
  (sim_bridge.sitl.commands records the schedule's commands from them);
* from anyone else (an operator's console, a peer without a vehicle id): forwarded at once
  and without the link's faults to every vehicle's agent, at most `command_rate` a second
  (wall clock: more are dropped and counted). That path follows the wall clock, so a
  lockstep run with a console's commands does not repeat exactly.

States keep every rule below.

One vehicle id, one sender: the first source address that sends a vehicle's state
owns that id. A state for the same id from another address (two agents started with
one --vehicle-id) is refused and counted (`id_conflicts`, also in `foreign`), never
forwarded as that vehicle, until the owner has been silent for REBIND_AFTER_S of
simulated time (an agent restarted on a new port takes its id back). Only the owner
gets a copy, at once: a radio would let it hear the impostor, and its agent then
avoids it as an intruder (an identity conflict, docs/swarm.md).
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from companion.commands import SLOTS_PER_MESSAGE
from companion.link.endpoints import UdpLink
from companion.link.framing import FrameError
from companion.link.msgdef import swarmdrop as sd
from companion.link.wire import Codec
from companion.swarm import PHASE_COUNT
from sim_bridge.world.plan_radio import FRAME_SLOTS_US, PLAN_STREAM_SALT
from sim_bridge.world.transport import AgeHistogram, LinkConfig, LinkStats, MeanMax, RadioModel

MAX_DATAGRAM_BYTES = 1400
"""Batches larger than this go out as several datagrams (one radio frame's worth)."""
_STATE_ID = sd.MAVLINK_MSG_ID_SWARMDROP_STATE
_COMMAND_IDS = frozenset({sd.MAVLINK_MSG_ID_SWARMDROP_PLAN, sd.MAVLINK_MSG_ID_SWARMDROP_SLOTS})
COMMAND_FRAMES_PER_S = 200.0
COMMAND_FRAMES_PER_S_PER_VEHICLE = 8.0
"""SWARMDROP_PLAN / SLOTS frames forwarded per (wall) second at most: COMMAND_FRAMES_PER_S plus
this per vehicle (every agent relays the newest plan, a plan of 255 vehicles is 3 frames), in
bursts of up to twice that."""
RELAY_FRAMES_PER_S = 60.0
"""Plan frames a vehicle may put on the radio per simulated second by default (an agent relays
its newest plan, up to 3 frames, at the swarm rate), in bursts of up to twice that."""
_STATE_COPY = -1
_UNTRACKED_PLAN = -2
"""_p_plan of a pending copy: a state; a plan frame the listener is not told of (else seq << 8 | part)."""
REBIND_AFTER_S = 3.0
"""Simulated seconds of silence after which a vehicle id's sender may change (the
swarm's peer_timeout_s default: by then its neighbours count it as gone too)."""


def relay_frames_per_s(n: int, swarm_rate_hz: float) -> float:
    """The plan frames a vehicle may put on the radio per simulated second: twice what an agent
    relaying on every swarm tick sends (a plan of n vehicles is 1 + ceil(n / 200) frames),
    at least RELAY_FRAMES_PER_S."""
    return max(RELAY_FRAMES_PER_S, 2.0 * (1 + math.ceil(n / SLOTS_PER_MESSAGE)) * swarm_rate_hz)


class PlanListener(Protocol):
    """Who hears what the radio does with swarm plans (sim_bridge.sitl.commands.SitlCommands)."""

    def plan_delivered(self, seq: int, part: int, receivers: np.ndarray, sim_s: float) -> None:
        """Frame `part` of plan seq (0 the SWARMDROP_PLAN, 1 + k the k-th SWARMDROP_SLOTS chunk)
        reached these vehicles at simulation time sim_s."""

    def state_plan_seq(self, k: int, stamp_s: float, plan_seq: int) -> None:
        """Vehicle k published a state stamped stamp_s (simulation time) with a plan_seq higher
        than any of its states before."""


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
        relay_frames_per_s: plan frames a vehicle may put on the radio per simulated second.
    """

    def __init__(self, n: int, link: LinkConfig, seed: int, epoch_unix_s: float, bind: tuple[str, int],
                 agent_ports: list[int] | None = None, host: str = "127.0.0.1", signing=None,
                 monitors: Sequence[tuple[str, int]] = (), wall_clock=time.monotonic,
                 relay_frames_per_s: float = RELAY_FRAMES_PER_S):
        self.signing = signing
        """Signs the radio's own end-of-tick marker when the fleet is signed (agents'
        states are forwarded as they were sent, signatures and all), and checks every frame
        the radio takes: one that signing would drop (unsigned under `require`, forged,
        replayed) is dropped and counted (`unverified`), before it could claim a vehicle's
        id, move the radio's view of a vehicle, or use the command budget."""
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
        self._p_plan = np.zeros(0, dtype=np.int64)
        """_STATE_COPY, or a plan frame: seq << 8 | part (_UNTRACKED_PLAN: not told)."""
        self.plan_radio = RadioModel(link, int(seed) ^ PLAN_STREAM_SALT)
        """The fates of plan frames (the headless plan radio's stream: sim_bridge.world.plan_radio)."""
        self._plan_inbox: list[tuple[int, bytes, int]] = []
        """Plan frames to put on the radio at the next schedule(): (sender, frame, seq << 8 | part)."""
        self.plan_parts = 1 + math.ceil(n / SLOTS_PER_MESSAGE)
        """Frames of one plan of this fleet (SWARMDROP_PLAN + SLOTS chunks)."""
        self.plan_listener: PlanListener | None = None
        self.plan_seq = np.zeros(n, dtype=np.int64)
        """The highest plan_seq each vehicle's states have carried."""
        self.relay_frames_per_s = relay_frames_per_s
        self._relay_tokens = np.full(n, 2.0 * relay_frames_per_s)
        self._relay_at_s = np.zeros(n)
        self.plan_frames_in = 0
        """Plan frames put on the radio (relays and the SITL's source)."""
        self.relays_in = 0
        """Vehicles' plan frames taken for the radio."""
        self.plan_copies_delivered = 0
        self.relays_dropped = 0
        """Vehicles' plan frames over relay_frames_per_s: dropped."""
        self._sender_of: dict[tuple, int] = {}
        """Source address -> the vehicle id it owns (the inverse of src)."""
        self.latest_stamp_us = np.full(n, -1, dtype=np.int64)
        """time_usec of the newest state received from each vehicle (lockstep gate)."""
        self.phase = np.zeros(n, dtype=np.int8)
        self.flags = np.zeros(n, dtype=np.uint8)
        self.t_go_s = np.full(n, np.nan)
        self.bytes_in = np.zeros(n, dtype=np.int64)
        self.states_in = np.zeros(n, dtype=np.int64)
        self.copies_sent = self.copies_delivered = self.copies_lost = 0
        self.bad_frames = 0
        """Frames that do not decode, states with a phase outside the seven, and frames signing
        drops (unverified): dropped."""
        self.unverified = 0
        """Frames the fleet's signing drops (signed fleets only; also in bad_frames)."""
        self.foreign = 0
        """Frames that are not a SWARMDROP_STATE of a known vehicle: dropped."""
        self.src: list[tuple | None] = [None] * n
        """The source address that owns each vehicle id (its first sender)."""
        self._src_heard_s = np.full(n, -np.inf)
        """Simulated time at which each owner was last heard."""
        self.sim_s = 0.0
        """The simulated time of the last schedule/deliver call."""
        self.id_conflicts = 0
        """States refused because another address already sends that vehicle id (also in foreign)."""
        self.conflict_ids: set[int] = set()
        """Vehicle ids that some second sender claimed."""
        self.ages = AgeHistogram()
        self.monitors: list[tuple[str, int]] = list(monitors)
        """Where every state taken is copied (operators' consoles)."""
        self.monitor_copies = 0
        """Frames copied to monitors (states and plans, per monitor)."""
        self.commands_forwarded = 0
        """SWARMDROP_PLAN / SLOTS frames forwarded to the agents."""
        self.commands_dropped = 0
        """SWARMDROP_PLAN / SLOTS frames dropped by the rate limit."""
        self._wall = wall_clock
        self.command_rate = COMMAND_FRAMES_PER_S + COMMAND_FRAMES_PER_S_PER_VEHICLE * n
        self._cmd_tokens = 2 * self.command_rate
        self._cmd_at = wall_clock()

    def set_monitors(self, monitors: Sequence[tuple[str, int]]) -> None:
        """Copy every state taken from now on to these addresses (host, port)."""
        self.monitors = list(monitors)

    def _command_allowed(self) -> bool:
        now = self._wall()
        self._cmd_tokens = min(2 * self.command_rate, self._cmd_tokens + (now - self._cmd_at) * self.command_rate)
        self._cmd_at = now
        if self._cmd_tokens < 1.0:
            self.commands_dropped += 1
            return False
        self._cmd_tokens -= 1.0
        return True

    @property
    def port(self) -> int:
        return self.link.local_port

    def fileno(self) -> int:
        return self.link.fileno()

    def receive(self) -> int:
        """Take what agents sent (their copies are scheduled by the next schedule()); copy the
        states taken to the monitors; put vehicles' plan relays on the radio (at the next
        schedule()) and forward other plans at once. Returns the number of states taken."""
        taken = 0
        to_monitors: list[bytes] = []
        commands: list[tuple[bytes, tuple]] = []
        sg = self.signing
        for frame, addr in self.link.recv():
            if sg is not None and not sg.check(frame):
                self.unverified += 1
                self.bad_frames += 1
                continue
            try:
                msg = self.codec.decode(frame)
            except FrameError:
                self.bad_frames += 1
                continue
            msgid = msg.get_msgId()
            if msgid in _COMMAND_IDS:
                k = self._sender_of.get(addr)
                if k is None:  # an operator's console: at once, without the link's faults
                    if self._command_allowed():
                        commands.append((frame, addr))
                elif self._relay_allowed(k):  # a vehicle's relay: on the radio
                    self._plan_inbox.append((k, frame, self._plan_key(msg)))
                    self.relays_in += 1
                    if self.monitors:
                        to_monitors.append(frame)
                continue
            if msgid != _STATE_ID or not 0 <= msg.vehicle_id < self.n \
                    or msg.get_srcSystem() != msg.vehicle_id + 1:
                self.foreign += 1
                continue
            if msg.phase >= PHASE_COUNT:  # hostile or corrupt: agents would drop it too
                self.bad_frames += 1
                continue
            k = msg.vehicle_id
            if self.src[k] != addr:
                if self.src[k] is not None and self.sim_s - self._src_heard_s[k] <= REBIND_AFTER_S:
                    self.id_conflicts += 1  # a second sender for one id: refused, never forwarded
                    self.foreign += 1
                    self.conflict_ids.add(k)
                    self._tell_owner(k, frame, int(msg.time_usec) * 1e-6 - self.epoch_unix_s)
                    continue
                if self._sender_of.get(self.src[k]) == k:
                    del self._sender_of[self.src[k]]
                self.src[k] = addr
                self._sender_of[addr] = k
            self._src_heard_s[k] = self.sim_s
            if self._learn:
                self.addr[k] = addr
            self.bytes_in[k] += len(frame)
            self.states_in[k] += 1
            stamp_us = int(msg.time_usec)
            seq = int(msg.plan_seq)
            if seq > self.plan_seq[k]:
                self.plan_seq[k] = seq
                if self.plan_listener is not None:
                    self.plan_listener.state_plan_seq(k, stamp_us * 1e-6 - self.epoch_unix_s, seq)
            if stamp_us > self.latest_stamp_us[k]:
                self.latest_stamp_us[k] = stamp_us
                self.phase[k], self.flags[k] = msg.phase, msg.flags
                self.t_go_s[k] = (msg.t_go_usec * 1e-6 - self.epoch_unix_s) if msg.t_go_usec else math.nan
            self._inbox.append((k, stamp_us * 1e-6 - self.epoch_unix_s, frame))
            if self.monitors:
                to_monitors.append(frame)
            taken += 1
        if commands:
            self._forward_commands(commands)
            if self.monitors:
                to_monitors += [f for f, _ in commands]
        for addr in self.monitors if to_monitors else ():
            self._send_batch(to_monitors, addr)
            self.monitor_copies += len(to_monitors)
        return taken

    def _relay_allowed(self, k: int) -> bool:
        """Vehicle k's token bucket on simulated time (deterministic in lockstep)."""
        rate = self.relay_frames_per_s
        tokens = min(2.0 * rate, self._relay_tokens[k] + (self.sim_s - self._relay_at_s[k]) * rate)
        self._relay_at_s[k] = self.sim_s
        if tokens < 1.0:
            self._relay_tokens[k] = tokens
            self.relays_dropped += 1
            return False
        self._relay_tokens[k] = tokens - 1.0
        return True

    def _plan_key(self, msg) -> int:
        """seq << 8 | part of a decoded plan frame, or _UNTRACKED_PLAN (a seq or chunk that is
        not one of this fleet's: the agents judge it, the listener never hears of it)."""
        seq = int(msg.seq)
        if msg.get_msgId() == sd.MAVLINK_MSG_ID_SWARMDROP_PLAN:
            part = 0
        else:
            first = int(msg.first)
            part = 1 + first // SLOTS_PER_MESSAGE if first % SLOTS_PER_MESSAGE == 0 else -1
        if not (0 < seq < 1 << 40 and 0 <= part < self.plan_parts):
            return _UNTRACKED_PLAN
        return seq << 8 | part

    def send_plan(self, frames: Sequence[bytes], seq: int) -> None:
        """The SITL's own command source sends one plan's frames (plan_messages order: the
        SWARMDROP_PLAN, then the SLOTS chunks), encoded and signed: on the radio at the next
        schedule(), from sender N at the fleet's centroid, and to the monitors at once."""
        for part, frame in enumerate(frames):
            key = seq << 8 | part if 0 < seq < 1 << 40 and part < self.plan_parts else _UNTRACKED_PLAN
            self._plan_inbox.append((self.n, frame, key))
        for addr in self.monitors:
            self._send_batch(list(frames), addr)
            self.monitor_copies += len(frames)

    def _schedule_plans(self, sim_s: float, pos: np.ndarray) -> None:
        """The fates of the plan frames taken since the last call: copies on the radio."""
        inbox, self._plan_inbox = self._plan_inbox, []
        self.plan_frames_in += len(inbox)
        senders = np.array([k for k, _, _ in inbox], np.int64)
        slot = np.zeros(len(inbox), np.int64)  # a sender's frames at one instant get distinct hash keys
        count: dict[int, int] = {}
        for i, k in enumerate(senders.tolist()):
            slot[i] = count.get(k, 0)
            count[k] = slot[i] + 1
        stamps = (round(sim_s * 1e6) * FRAME_SLOTS_US + slot) * 1e-6
        finite = np.isfinite(pos).all(axis=1)
        centroid = pos[finite].mean(axis=0) if finite.any() else np.zeros(3)
        s_pos = np.where((senders < self.n)[:, None], pos[np.minimum(senders, self.n - 1)], centroid)
        m_idx, rcv, when = self.plan_radio.deliveries(senders, stamps, sim_s, s_pos, pos)
        base = len(self._frames)
        self._frames += [f for _, f, _ in inbox]
        keys = np.array([key for _, _, key in inbox], np.int64)
        self._queue(when, rcv, base + m_idx, np.full(len(rcv), np.nan), keys[m_idx])

    def _queue(self, when: np.ndarray, rcv: np.ndarray, frame: np.ndarray, stamp: np.ndarray,
               plan: np.ndarray) -> None:
        self._p_when = np.concatenate([self._p_when, when])
        self._p_rcv = np.concatenate([self._p_rcv, rcv])
        self._p_frame = np.concatenate([self._p_frame, frame])
        self._p_stamp = np.concatenate([self._p_stamp, stamp])
        self._p_plan = np.concatenate([self._p_plan, plan])

    def _forward_commands(self, commands: list[tuple[bytes, tuple]]) -> None:
        """PLAN / SLOTS frames to every agent with an address but the sender's own vehicle."""
        for k in range(self.n):
            addr = self.addr[k]
            if addr is None:
                continue
            frames = [f for f, src in commands if src != self.src[k]]
            if frames:
                self._send_batch(frames, addr)
                self.commands_forwarded += len(frames)

    def _send_batch(self, frames: list[bytes], addr: tuple) -> None:
        """Frames to one address, packed into datagrams of at most MAX_DATAGRAM_BYTES."""
        buf = b""
        for f in frames:
            if len(buf) + len(f) > MAX_DATAGRAM_BYTES and buf:
                self.link.send(buf, addr)
                buf = b""
            buf += f
        if buf:
            self.link.send(buf, addr)

    def _tell_owner(self, k: int, frame: bytes, stamp_s: float) -> None:
        """Queue a refused state (another sender claiming vehicle k) for vehicle k's agent
        alone, due now: the owner must know of the impostor to keep clear of it."""
        self._queue(np.array([self.sim_s]), np.array([k], np.int64), np.array([len(self._frames)], np.int64),
                    np.array([stamp_s]), np.array([_STATE_COPY], np.int64))
        self._frames.append(frame)

    def schedule(self, sim_s: float, positions_ned_m: np.ndarray) -> None:
        """Decide the fate of every copy of the states received since the last call
        (one vectorised draw for all of them)."""
        self.sim_s = sim_s
        if self._plan_inbox:
            self._schedule_plans(sim_s, np.asarray(positions_ned_m, float))
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
        self._queue(when, rcv, base + m_idx, stamps[m_idx], np.full(len(rcv), _STATE_COPY, np.int64))

    def deliver(self, sim_s: float, receivers: np.ndarray, tick_marker: bool) -> int:
        """Send the copies due by sim_s to the given receivers, one batch per agent, plus the
        lockstep end-of-tick marker when asked. Returns the number of state copies sent
        (plan frames ride in the same batches, counted apart: plan_copies_delivered).

        Args:
            receivers: (N,) bool, the agents at a control tick now (the others get theirs
                at their own tick: one datagram per agent per tick, not one per SITL tick).
        """
        self.sim_s = sim_s
        due = (self._p_when <= sim_s + 1e-9) & receivers[self._p_rcv] if len(self._p_when) else np.zeros(0, bool)
        batches: dict[int, list[bytes]] = {}
        n_due = 0
        if due.any():
            idx = np.flatnonzero(due)
            idx = idx[np.argsort(self._p_rcv[idx], kind="stable")]
            frames = self._frames
            for r, fi in zip(self._p_rcv[idx].tolist(), self._p_frame[idx].tolist()):
                batches.setdefault(r, []).append(frames[fi])
            plan = self._p_plan[idx]
            states = plan == _STATE_COPY
            n_due = int(states.sum())
            if n_due < len(idx):  # plan frames among them: not states (ages, link counters)
                self._plans_delivered(sim_s, self._p_rcv[idx[~states]], plan[~states])
                idx = idx[states]
            self.ages.add(sim_s - self._p_stamp[idx])
            keep = ~due
            self._p_when, self._p_rcv = self._p_when[keep], self._p_rcv[keep]
            self._p_frame, self._p_stamp = self._p_frame[keep], self._p_stamp[keep]
            self._p_plan = self._p_plan[keep]
            if not len(self._p_frame):  # nothing in flight: forget the frames too
                self._frames = []
            elif len(self._frames) > 4 * len(self._p_frame) + 1024:  # compact the frame store
                live = np.unique(self._p_frame)
                remap = np.full(len(self._frames), -1, dtype=np.int64)
                remap[live] = np.arange(len(live))
                self._frames = [self._frames[i] for i in live.tolist()]
                self._p_frame = remap[self._p_frame]
        if tick_marker:
            marker = self.codec.encode_fields(sd.MAVLINK_MSG_ID_SWARMDROP_TICK,
                                              [int(round((self.epoch_unix_s + sim_s) * 1e6))], 255, 0, 0)
            if self.signing is not None:
                marker = self.signing.sign(marker)
            for k in np.flatnonzero(receivers).tolist():
                batches.setdefault(k, []).append(marker)
        for k, frames in batches.items():
            addr = self.addr[k]
            if addr is not None:
                self._send_batch(frames, addr)
        self.copies_delivered += n_due
        return n_due

    def _plans_delivered(self, sim_s: float, rcv: np.ndarray, keys: np.ndarray) -> None:
        """Count the plan copies delivered now and tell the listener, one call per frame."""
        self.plan_copies_delivered += len(keys)
        if self.plan_listener is None:
            return
        tracked = keys >= 0
        for key in np.unique(keys[tracked]).tolist():
            self.plan_listener.plan_delivered(key >> 8, key & 0xFF, rcv[keys == key], sim_s)

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
