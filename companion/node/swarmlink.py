"""The agent's link to its neighbours: SWARMDROP_STATE out, everyone's states in.

Each agent sends only its own state, signed with its own sysid (vehicle_id + 1),
to a list of peer addresses: the radio medium (one send, docs/swarm-link.md) or
every other vehicle (unicast). What arrives goes into the agent's SwarmView with
its stamp; a message for another mission slot than its sender's sysid says, with
a non-finite stamp, or that does not decode, is counted and dropped.

A state that claims this vehicle's own id is either its own echo (our sysid, and a
stamp and position we published: a peer or medium sent it back) or an identity
conflict: someone else flies as this vehicle. A conflict is logged (rate-limited),
counted, and kept in the view as an intruder, which the agent avoids like a vehicle
and reports in its published flags (docs/swarm.md).

Swarm plans (docs/swarm.md, "Swarm commands") arrive as SWARMDROP_PLAN and SWARMDROP_SLOTS
frames from the operator's console or from other agents' relays; a PlanAssembler puts them
together (any order, any mix of senders, duplicates and losses), and each whole plan goes to
`on_plan` (the agent's plan book). `relay` sends the newest plan this agent holds on to its
peers. Under `--signing require` the endpoint has already dropped every unsigned, forged or
replayed frame (counted there): only signed plans are obeyed.

In lockstep the medium ends each tick's batch with a SWARMDROP_TICK, which tells
the agent it has heard everything due.
"""
from __future__ import annotations

import collections
import logging
import math
import struct
import time
from typing import Callable, TypedDict

from companion.commands import PlanAssembler, SwarmPlan
from companion.link.endpoints import MavEndpoint
from companion.link.enums import MsgId
from companion.node.stats import SwarmLinkStats
from companion.swarm import FUTURE_TOLERANCE_S, INTRUDER_SLOTS, PHASE_COUNT, SwarmStates, SwarmView

log = logging.getLogger("swarmdrop.swarm")

_STATE = MsgId.SWARMDROP_STATE  # bound once: compared per received message
_TICK = MsgId.SWARMDROP_TICK
_PLAN_IDS = frozenset((int(MsgId.SWARMDROP_PLAN), int(MsgId.SWARMDROP_SLOTS)))
_POS = struct.Struct("<3f")
ECHO_MEMORY = 64
"""Own publications remembered to recognise their echoes (6.4 s at 10 Hz)."""
FUTURE_TOLERANCE_US = round(FUTURE_TOLERANCE_S * 1e6)
"""companion.swarm.FUTURE_TOLERANCE_S in the wire's µs."""
CONFLICT_LOG_PERIOD_S = 10.0
"""At most one conflict log line per sender per this many (wall) seconds after the first."""


class SwarmLink:
    """Neighbour states over MAVLink.

    Args:
        endpoint: a MavEndpoint on the swarm socket (sysid = own sysid, compid 191).
        vehicle_id: this vehicle's index in the mission.
        peers: addresses to send the own state to.
        view: the agent's SwarmView (one receiver row).

    The mission epoch (Unix time of mission time 0; message times are Unix µs) is None
    until the agent knows its autopilot's clock (set_epoch): states heard before then are
    dropped (counted as rejected), never stored with a stamp in another time base. Nor is a
    state stamped over FUTURE_TOLERANCE_US ahead of `now_us`, the vehicle's clock at its
    newest tick (the tick path sets it; counted as future, and until the first tick every
    state is dropped so).
    """

    def __init__(self, endpoint: MavEndpoint, vehicle_id: int, peers: list[tuple[str, int]], view: SwarmView,
                 sysids: list[int] | None = None, assembler: PlanAssembler | None = None,
                 on_plan: Callable[[SwarmPlan], object] | None = None):
        self.ep = endpoint
        self.vehicle_id = vehicle_id
        self.peers = list(peers)
        self.view = view
        self.sysids = list(sysids) if sysids is not None else [k + 1 for k in range(view.n_vehicles)]
        """The sysid each vehicle's state must come from (the mission's: vehicle_id + 1)."""
        self.epoch_us: int | None = None
        self.marker_us = -1
        """time_usec of the newest SWARMDROP_TICK from the medium."""
        self.states_in = 0
        self.rejected = 0
        self.future = 0
        """States (and radio tick markers) dropped for a stamp over FUTURE_TOLERANCE_US ahead of now_us."""
        self.now_us: int | None = None
        """Unix µs of the vehicle's own clock at its newest tick (set by the tick path)."""
        self.sent = 0
        self.own_echoes = 0
        """States of our own that came back (a peer or medium echoing them): ignored."""
        self._published: collections.deque = collections.deque(maxlen=ECHO_MEMORY)
        """(time_usec, packed position) of our last publications, to recognise echoes."""
        self._intruder_slot: dict[tuple, int] = {}
        """Conflicting sender (sysid, address) -> its intruder slot in the view."""
        self._conflict_log: dict[tuple, tuple[float, int]] = {}
        """Sender -> (wall time of its last log line, conflicts since)."""
        self.last_conflict = ""
        """Who last claimed our id (for the statistics)."""
        self._build_state = endpoint.codec.builder(_STATE)
        self.assembler = assembler
        """Puts plan frames together (None: plans are not listened to)."""
        self.on_plan = on_plan
        """Called with every whole plan heard (the agent's plan book takes the newest)."""
        self.plan_frames_in = 0
        self.plans_in = 0
        """Whole plans put together (each seq once; relays repeat them: duplicates are dropped)."""
        self.plan_frames_out = 0

    def set_epoch(self, epoch_unix_s: float) -> None:
        self.epoch_us = int(round(epoch_unix_s * 1e6))
        if self.assembler is not None:
            self.assembler.set_epoch(epoch_unix_s)

    def poll(self) -> int:
        """Take everything waiting; returns the number of states applied to the view."""
        applied = 0
        view, own, n, epoch, sysids = self.view, self.vehicle_id, self.view.n_vehicles, self.epoch_us, self.sysids
        latest_us = -1 if self.now_us is None else self.now_us + FUTURE_TOLERANCE_US
        for msgid, sysid, _compid, w, addr in self.ep.poll_raw():
            if msgid == _STATE:
                # wire order: time_usec, t_go_usec, x, y, z, vx, vy, vz, q[4], phase, flags, vehicle_id
                if w[0] > latest_us and epoch is not None:  # (no epoch: rejected below)
                    self.future += 1
                    continue
                j = w[14]
                if j == own and epoch is not None and w[12] < PHASE_COUNT:
                    self._own_id_claimed(sysid, addr, w, epoch)
                    continue
                if j >= n or sysid != sysids[j] or epoch is None or w[12] >= PHASE_COUNT:
                    self.rejected += 1
                    continue
                self.states_in += 1
                if view.receive_one(0, j, (w[0] - epoch) * 1e-6, w[2:5], w[5:8], w[12], w[13],
                                    (w[1] - epoch) * 1e-6 if w[1] else math.nan):
                    applied += 1
            elif msgid == _TICK:
                # (a marker from the future would end every lockstep wait until then; before the
                # first tick there is no clock to judge by, and the first tick may wait for one)
                if w[0] > latest_us and self.now_us is not None:
                    self.future += 1
                else:
                    self.marker_us = max(self.marker_us, w[0])
            elif msgid in _PLAN_IDS and self.assembler is not None and epoch is not None:
                self.plan_frames_in += 1
                plan = self.assembler.feed_fields(msgid, self.ep.codec.named(msgid, w))
                if plan is not None:
                    self.plans_in += 1
                    if self.on_plan is not None:
                        self.on_plan(plan)
            else:
                self.rejected += 1
        return applied

    def relay(self, messages: list) -> None:
        """Queue a plan's messages ((msgid, values) pairs: companion.commands.plan_messages) to
        every peer: the newest plan this agent holds, passed on (docs/swarm.md, relays)."""
        for msgid, values in messages:
            for addr in self.peers:
                self.ep.queue_fields(msgid, values, addr)
                self.plan_frames_out += 1

    def publish(self, states: SwarmStates) -> None:
        """Queue this vehicle's state (one row) to every peer."""
        s = states
        if self.epoch_us is None:
            raise RuntimeError("SwarmLink.publish before set_epoch: no mission clock yet")
        t_us = self.epoch_us + int(round(float(s.stamp_s[0]) * 1e6))
        go = float(s.t_go_s[0])
        t_go_us = self.epoch_us + int(round(go * 1e6)) if math.isfinite(go) else 0
        p, v, q = s.pos_ned_m[0], s.vel_ned_mps[0], s.att_q_wxyz[0]
        x, y, z = float(p[0]), float(p[1]), float(p[2])
        values = self._build_state(time_usec=t_us, t_go_usec=t_go_us, x=x, y=y, z=z, vx=float(v[0]), vy=float(v[1]),
                                   vz=float(v[2]), q=[float(c) for c in q], phase=int(s.phase[0]),
                                   flags=int(s.flags[0]), vehicle_id=self.vehicle_id,
                                   plan_seq=0 if s.plan_seq is None else int(s.plan_seq[0]))
        for addr in self.peers:
            self.ep.queue_fields(_STATE, values, addr)
        self._published.append((t_us, _POS.pack(x, y, z)))
        self.sent += 1

    def _own_id_claimed(self, sysid: int, addr, w: tuple, epoch_us: int) -> None:
        """A state that names this vehicle: our own echo (our sysid, and a stamp and position
        we sent: floats compared as their wire bytes, so NaN matches NaN), or a conflict."""
        if sysid == self.ep.sysid and (w[0], _POS.pack(w[2], w[3], w[4])) in self._published:
            self.own_echoes += 1
            return
        key = (sysid, addr)
        slot = self._intruder_slot.get(key)
        if slot is None:
            slot = self._new_slot(key)
        self.view.receive_intruder(0, slot, (w[0] - epoch_us) * 1e-6, w[2:5], w[5:8], w[12], w[13])
        self.last_conflict = f"sysid {sysid} at {_addr_text(addr)}"
        now = time.monotonic()
        last, since = self._conflict_log.get(key, (-math.inf, 0))
        if now - last < CONFLICT_LOG_PERIOD_S:
            self._conflict_log[key] = (last, since + 1)
            return
        self._conflict_log[key] = (now, 0)
        if since == 0 and last == -math.inf:
            log.error("identity conflict: a SWARMDROP_STATE from %s claims this vehicle's id %d: two vehicles fly "
                      "as one (check --vehicle-id); avoiding it as an obstacle", self.last_conflict, self.vehicle_id)
        else:
            log.warning("identity conflict: %d more states from %s claim vehicle id %d in %.0f s (%d in all)",
                        since + 1, self.last_conflict, self.vehicle_id, now - last, self.conflicts)

    def _new_slot(self, key: tuple) -> int:
        """An intruder slot for a new conflicting sender: a free one, else the one heard longest ago."""
        used = set(self._intruder_slot.values())
        free = [k for k in range(INTRUDER_SLOTS) if k not in used]
        if free:
            slot = free[0]
        else:
            it = self.view.intruders
            assert it is not None  # slots are used only once intruders exist
            stamps = [-math.inf if x != x else x for x in it.stamp_s[0].tolist()]  # NaN: never stored
            slot = stamps.index(min(stamps))
            self._intruder_slot = {k: s for k, s in self._intruder_slot.items() if s != slot}
            it.stamp_s[0, slot] = math.nan  # the new sender starts afresh
        self._intruder_slot[key] = slot
        return slot

    @property
    def conflicts(self) -> int:
        """States received that claimed this vehicle's id and were not its own."""
        it = self.view.intruders
        return 0 if it is None else int(it.conflicts[0])

    def identity(self) -> SwarmIdentity:
        """The swarm link's part of the statistics' identity section (IdentityStats): conflicts."""
        return SwarmIdentity(conflicts=self.conflicts, conflict_sources=len(self._conflict_log),
                             last_conflict=self.last_conflict or None, own_echoes=self.own_echoes)

    def counters(self) -> SwarmLinkStats:
        """The statistics' swarm section."""
        ep = self.ep
        asm = self.assembler
        return SwarmLinkStats(states_in=self.states_in, rejected=self.rejected, future=self.future,
                              bad_frames=ep.bad_frames,
                              stale_or_duplicate=int(self.view.ignored_old[0]), published=self.sent,
                              bytes_out=ep.link.bytes_out, bytes_in=ep.link.bytes_in,
                              plan_frames_in=self.plan_frames_in, plans_in=self.plans_in,
                              plan_frames_rejected=0 if asm is None else asm.stats.rejected,
                              plan_frames_out=self.plan_frames_out)


class SwarmIdentity(TypedDict):
    """Who claimed this vehicle's id on the swarm link (the IdentityStats fields of the same names)."""

    conflicts: int
    conflict_sources: int
    """Distinct senders (sysid, address) that claimed it."""
    last_conflict: str | None
    own_echoes: int


def _addr_text(addr) -> str:
    return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) and len(addr) >= 2 else str(addr)


def view_for(n_vehicles: int) -> SwarmView:
    """A one-receiver view of the mission's vehicles."""
    return SwarmView.unknown(1, n_vehicles)

