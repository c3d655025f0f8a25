"""The live feed: the swarm link (SWARMDROP_STATE, PLAN, SLOTS) and a GCS link, into one model.

The console is a listening peer of the swarm link: it binds `--swarm-bind`, where a radio
medium copies every state to it (the SITL's radio with `--medium-monitor`), or where agents
send their states (one more `--swarm-peer` of theirs), or where `swarmdrop simulate --live`
streams a headless run. Everything it receives is hostile until proven otherwise:

* frames are read in bounded batches (companion.link.endpoints: at most 512 datagrams per
  wake-up), checked by the signing layer when signing is on (unsigned, forged and replayed
  frames are dropped and counted), and decoded by the project codec; a frame that does not
  decode is counted (`bad_frames`, `unknown`) and dropped;
* a state is taken only as the agents take one (docs/swarm-link.md): its sender's sysid
  is the mission's sysid of its vehicle_id, the id is in the mission, the phase is one of
  the seven; positions and velocities beyond `COORD_MAX_M`, `SPEED_MAX_MPS` or not finite
  are kept as "unknown" (drawn as such), never as a place on the map;
* a vehicle's newest state wins (a duplicate or reordered copy never rolls it back), unless
  the vehicle has been silent for `RESTART_AFTER_S` (a restarted sender, or a hostile
  stamp from the future that would otherwise shadow the real one for good); once the
  swarm's clock is known (the median over vehicles of stamp minus arrival), a stamp more
  than `FUTURE_S` ahead of it is refused (`future`);
* memory is bounded: vehicles up to the mission's count (`MAX_VEHICLES` without one), the
  plans seen up to `PLANS_KEPT`, the peers learnt up to `PEERS_MAX`.

Vehicle ids beyond 249 (a headless run of up to 1,000 vehicles streamed with
`swarmdrop simulate --live`): SWARMDROP_STATE.vehicle_id is a byte and sysids stop at 250,
so a simulated feed of more vehicles sends vehicle `250 b + k` as vehicle_id k, sysid k + 1,
from component `SIM_BANK_COMPID_BASE + b` (MAV_COMP_ID_USER1 ..). Agents never send from
those components; only a simulator's feed does (sim_bridge/runs/live.py).

The GCS link (`--gcs URL`, e.g. the SITL's shared GCS endpoint or a router) gives each
autopilot's mode (named by its dialect, picked from HEARTBEAT.autopilot), armed state,
landed state and battery (SYS_STATUS, BATTERY_STATUS). The console never sends on it.
"""
from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from companion.link.endpoints import MavEndpoint
from companion.link.enums import MavComponent, MsgId
from companion.link.msgdef import swarmdrop as sd
from companion.swarm import PHASE_COUNT
from swarmdrop.console.mission import MissionInfo
from swarmdrop.console.protocol import Snapshot, yaw_of

SIM_BANK_COMPID_BASE = 25
"""MAV_COMP_ID_USER1: a simulated feed's bank b of 250 vehicles comes from component 25 + b."""
SIM_BANKS = 4
SIM_BANK_SIZE = 250
MAX_VEHICLES = SIM_BANKS * SIM_BANK_SIZE
"""Vehicles the console tracks without a mission (and the most with one)."""
COORD_MAX_M = 1.0e6
SPEED_MAX_MPS = 1.0e4
RESTART_AFTER_S = 3.0
"""A vehicle silent this long (console's clock) takes any next state, even an older stamp."""
FUTURE_S = 5.0
"""A stamp this far ahead of the swarm's clock is refused (once the clock is known)."""
CLOCK_WINDOW_S = 10.0
"""The swarm's clock is the median over vehicles heard within this (console s)."""
RATE_WINDOW_S = 5
"""states/s heard: over the last this many whole seconds."""
PLANS_KEPT = 64
PEERS_MAX = 64
PHASE_NAMES = tuple(sd.enums["SWARMDROP_PHASE"][k].name.removeprefix("SWARMDROP_PHASE_").lower()
                    for k in range(PHASE_COUNT))
COMMAND_NAMES = {k: e.name.removeprefix("SWARMDROP_COMMAND_").lower()
                 for k, e in sd.enums["SWARMDROP_COMMAND"].items() if not e.name.endswith("ENUM_END")}
SHAPE_NAMES = {k: e.name.removeprefix("SWARMDROP_SHAPE_").lower()
               for k, e in sd.enums["SWARMDROP_SHAPE"].items() if not e.name.endswith("ENUM_END")}
_STATE, _PLAN, _SLOTS, _TICK = MsgId.SWARMDROP_STATE, MsgId.SWARMDROP_PLAN, MsgId.SWARMDROP_SLOTS, MsgId.SWARMDROP_TICK
_AUTOPILOT = MavComponent.MAV_COMP_ID_AUTOPILOT1


@dataclass
class SwarmCounters:
    """What the swarm link brought, and what was dropped and why (the page shows them)."""

    states: int = 0
    """States taken (valid; also those older than the one held)."""
    rejected: int = 0
    """Decoded frames refused: wrong sysid for the id, id outside the mission, bad phase, other messages."""
    old: int = 0
    """States not newer than the one held (duplicates, reordered copies)."""
    future: int = 0
    """States stamped more than FUTURE_S ahead of the swarm's clock."""
    plans: int = 0
    """SWARMDROP_PLAN / SWARMDROP_SLOTS frames heard (also relayed copies)."""

    def to_json(self, ep: MavEndpoint) -> dict[str, int]:
        sg = ep.signing
        out = {"states": self.states, "rejected": self.rejected, "old": self.old, "future": self.future,
               "plans": self.plans, "bad_frames": ep.bad_frames, "unknown": ep.unknown,
               "bytes_skipped": ep.link.bytes_skipped, "bytes_in": ep.link.bytes_in}
        if sg is not None:
            c = sg.counters
            out |= {"unsigned": c.unsigned, "bad_signature": c.bad_signature, "replayed": c.replayed}
        return out


@dataclass
class PlanSeen:
    """A SWARMDROP_PLAN heard on the swarm link (ours, relayed, or another source's)."""

    seq: int
    kind: int
    effective_s: float
    """Unix s (the swarm's clock)."""
    shape: int
    flags: int
    n_waypoints: int
    sysid: int
    copies: int = 1
    slot_chunks: set[int] = field(default_factory=set)
    """SWARMDROP_SLOTS chunks heard (their `first` index)."""

    def to_json(self) -> dict[str, Any]:
        return {"seq": self.seq, "kind": COMMAND_NAMES.get(self.kind, str(self.kind)),
                "effective_s": self.effective_s, "shape": SHAPE_NAMES.get(self.shape, str(self.shape)),
                "flags": self.flags, "n_waypoints": self.n_waypoints, "sysid": self.sysid, "copies": self.copies,
                "slot_chunks": len(self.slot_chunks)}


class FleetModel:
    """The newest state of every vehicle, with arrival times, link rates and the swarm's clock.

    Args:
        mission: the mission (its vehicle count and sysids), or one with no config.
        clock: the console's monotonic clock (s).
    """

    def __init__(self, mission: MissionInfo, clock=time.monotonic):
        self.mission = mission
        self.clock = clock
        cap = mission.n if mission.n is not None else MAX_VEHICLES
        self.capacity = min(cap, MAX_VEHICLES)
        self.sysid_of = np.array(mission.sysids[:self.capacity] if mission.config is not None
                                 else [(k % SIM_BANK_SIZE) + 1 for k in range(self.capacity)], np.int64)
        n = self.capacity
        self.n_seen = mission.n if mission.n is not None else 0
        """Vehicles drawn: the mission's count, else one more than the largest id heard."""
        self.stamp_s = np.full(n, -np.inf)
        self.arrival_s = np.full(n, -np.inf)
        self.t_go_s = np.full(n, np.nan)
        self.pos = np.full((n, 3), np.nan)
        self.vel = np.full((n, 3), np.nan)
        self.q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self.phase = np.zeros(n, np.uint8)
        self.flags = np.zeros(n, np.uint8)
        self.plan_seq = np.zeros(n, np.uint32)
        self.known = np.zeros(n, bool)
        self._buckets = np.zeros((RATE_WINDOW_S + 1, n), np.int32)
        self._bucket_sec = np.full(RATE_WINDOW_S + 1, -1, np.int64)
        self.clock_offset_s = math.nan
        """Swarm clock minus console clock (median over recently heard vehicles)."""
        self._offset = np.full(n, np.nan)
        self.counters = SwarmCounters()
        self.plans: OrderedDict[int, PlanSeen] = OrderedDict()

    # ---- input ---------------------------------------------------------------------
    def take_states(self, rows: list[tuple], now_s: float | None = None) -> int:
        """Apply a batch of states that passed the per-frame checks.

        Args:
            rows: (vehicle index, time_usec, t_go_usec, x, y, z, vx, vy, vz, qw, qx, qy, qz,
                phase, flags, plan_seq), one per state.
        Returns:
            States applied (newer than what was held).
        """
        if not rows:
            return 0
        now = self.clock() if now_s is None else now_s
        a = np.array(rows, dtype=np.float64)
        ids = a[:, 0].astype(np.int64)
        self.counters.states += len(ids)
        self._count_rate(ids, now)
        stamp = a[:, 1] * 1e-6
        # the newest of each id in the batch
        order = np.lexsort((stamp, ids))
        ids_o = ids[order]
        last = np.r_[ids_o[1:] != ids_o[:-1], True]
        pick = order[last]
        self.counters.old += len(ids) - len(pick)
        ids, a, stamp = ids[pick], a[pick], stamp[pick]
        if math.isfinite(self.clock_offset_s):
            future = stamp - now > self.clock_offset_s + FUTURE_S
            if future.any():
                self.counters.future += int(future.sum())
                keep = ~future
                ids, a, stamp = ids[keep], a[keep], stamp[keep]
        newer = (stamp > self.stamp_s[ids]) | (now - self.arrival_s[ids] > RESTART_AFTER_S)
        self.counters.old += int((~newer).sum())
        ids, a, stamp = ids[newer], a[newer], stamp[newer]
        if not len(ids):
            return 0
        self.stamp_s[ids] = stamp
        self.arrival_s[ids] = now
        self._offset[ids] = stamp - now
        self.t_go_s[ids] = np.where(a[:, 2] > 0, a[:, 2] * 1e-6, np.nan)
        pos, vel = a[:, 3:6], a[:, 6:9]
        pos[~(np.abs(pos) <= COORD_MAX_M).all(axis=1)] = np.nan
        vel[~(np.abs(vel) <= SPEED_MAX_MPS).all(axis=1)] = np.nan
        self.pos[ids], self.vel[ids] = pos, vel
        q = a[:, 9:13]
        q[~np.isfinite(q).all(axis=1)] = (1.0, 0.0, 0.0, 0.0)
        self.q[ids] = q
        self.phase[ids] = a[:, 13]
        self.flags[ids] = a[:, 14]
        self.plan_seq[ids] = a[:, 15]
        self.known[ids] = True
        if self.mission.n is None:
            self.n_seen = max(self.n_seen, int(ids.max()) + 1)
        return len(ids)

    def _count_rate(self, ids: np.ndarray, now: float) -> None:
        sec = int(now)
        b = sec % len(self._bucket_sec)
        if self._bucket_sec[b] != sec:
            self._bucket_sec[b] = sec
            self._buckets[b] = 0
        np.add.at(self._buckets[b], ids, 1)

    def note_plan(self, seq: int, kind: int, effective_us: int, shape: int, flags: int, n_waypoints: int,
                  sysid: int) -> None:
        self.counters.plans += 1
        p = self.plans.get(seq)
        if p is not None:
            p.copies += 1
            return
        self.plans[seq] = PlanSeen(seq, kind, effective_us * 1e-6, shape, flags, n_waypoints, sysid)
        while len(self.plans) > PLANS_KEPT:
            self.plans.popitem(last=False)

    def note_slots(self, seq: int, first: int) -> None:
        self.counters.plans += 1
        p = self.plans.get(seq)
        if p is not None and len(p.slot_chunks) < 64:
            p.slot_chunks.add(first)

    # ---- output --------------------------------------------------------------------
    def update_clock(self, now: float) -> None:
        recent = (now - self.arrival_s < CLOCK_WINDOW_S) & self.known
        self.clock_offset_s = float(np.median(self._offset[recent])) if recent.any() else math.nan

    def rates(self, now: float) -> np.ndarray:
        sec = int(now)
        full = (self._bucket_sec < sec) & (self._bucket_sec >= sec - RATE_WINDOW_S)
        return self._buckets[full].sum(axis=0) / float(RATE_WINDOW_S)

    def swarm_t_go(self, now: float) -> float:
        """The transit start the swarm holds (median of what recently heard vehicles hold; NaN none)."""
        recent = (now - self.arrival_s < CLOCK_WINDOW_S) & np.isfinite(self.t_go_s)
        return float(np.median(self.t_go_s[recent])) if recent.any() else math.nan

    def snapshot(self, now_s: float | None = None) -> Snapshot:
        """The fleet now (the first n_seen vehicles), with the mission's slots for the vehicles
        that hold no operator's plan (the command panel fills in the others)."""
        now = self.clock() if now_s is None else now_s
        self.update_clock(now)
        n = self.n_seen
        t = now + self.clock_offset_s if math.isfinite(self.clock_offset_s) else math.nan
        t_go = self.swarm_t_go(now)
        known = self.known[:n]
        since = now - self.arrival_s[:n]
        age = np.where(known, np.fmax(since, (t - self.stamp_s[:n]) if math.isfinite(t) else since), np.nan)
        ms = self.mission.slots(t - t_go if math.isfinite(t) and math.isfinite(t_go) else -1.0)
        slots = np.full((n, 3), np.nan)
        if ms is not None:
            m = min(n, len(ms))
            slots[:m] = np.where((self.plan_seq[:m] == 0)[:, None], ms[:m], np.nan)  # under a plan: not the mission's
        return Snapshot(t=t, t_go=t_go, pos=self.pos[:n], vel=self.vel[:n], yaw=yaw_of(self.q[:n]),
                        age=age, slot=slots[:n], rate=self.rates(now)[:n], plan_seq=self.plan_seq[:n],
                        phase=self.phase[:n], flags=self.flags[:n], known=known.copy())


class SwarmSource:
    """The console's swarm socket: reads and checks frames into a FleetModel.

    Args:
        endpoint: a MavEndpoint on the bound UDP socket (with the signing layer, if any).
        model: where states go.
        tlog: also write every frame that decoded to this (companion.link.tlog.Tlog), or None.
    """

    def __init__(self, endpoint: MavEndpoint, model: FleetModel, tlog=None):
        self.ep = endpoint
        self.model = model
        self.tlog = tlog
        if tlog is not None:
            endpoint.tlog = tlog
        self.on_plan: Callable[[int, dict[str, Any]], None] | None = None
        """Called with (msgid, fields by name) for every SWARMDROP_PLAN / SLOTS (the command panel)."""
        self.peers: OrderedDict[Any, float] = OrderedDict()
        """Source addresses of accepted states (where commands go without --swarm-peer), newest last."""

    def poll(self) -> int:
        """Take everything waiting (bounded per call); returns the states applied."""
        m = self.model
        c = m.counters
        cap = m.capacity
        sysid_of = m.sysid_of
        rows: list[tuple] = []
        now = m.clock()
        for msgid, sysid, compid, w, addr in self.ep.poll_raw():
            if msgid == _STATE:
                # wire order: time_usec, t_go_usec, x, y, z, vx, vy, vz, q[4], phase, flags, vehicle_id, plan_seq
                vid = w[14]
                if SIM_BANK_COMPID_BASE <= compid < SIM_BANK_COMPID_BASE + SIM_BANKS:  # a simulated feed's bank
                    k = vid + (compid - SIM_BANK_COMPID_BASE) * SIM_BANK_SIZE
                    ok = vid < SIM_BANK_SIZE and sysid == vid + 1
                else:
                    k = vid
                    ok = k < cap and sysid == sysid_of[k]
                if not ok or k >= cap or w[12] >= PHASE_COUNT:
                    c.rejected += 1
                    continue
                rows.append((k, w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7], w[8], w[9], w[10], w[11], w[12],
                             w[13], w[15]))
                if addr not in self.peers:
                    if len(self.peers) >= PEERS_MAX:
                        self.peers.popitem(last=False)
                    self.peers[addr] = now
            elif msgid == _PLAN:
                p = _PLAN_AT
                m.note_plan(w[p["seq"]], w[p["kind"]], w[p["effective_usec"]], w[p["shape"]], w[p["flags"]],
                            w[p["n_waypoints"]], sysid)
                if self.on_plan is not None:
                    self.on_plan(msgid, fields_of(_PLAN_CLS, w))
            elif msgid == _SLOTS:
                m.note_slots(w[_SLOTS_AT["seq"]], w[_SLOTS_AT["first"]])
                if self.on_plan is not None:
                    self.on_plan(msgid, fields_of(_SLOTS_CLS, w))
            elif msgid != _TICK:
                c.rejected += 1
        return m.take_states(rows, now)


@dataclass
class AutopilotView:
    """What the GCS link says of each vehicle's autopilot (arrays of the model's capacity)."""

    mode: list[str]
    armed: np.ndarray
    """1 armed, 0 disarmed, -1 unknown."""
    battery_pct: np.ndarray
    voltage_v: np.ndarray
    landed: np.ndarray
    """MAV_LANDED_STATE (0: undefined or unknown)."""
    heard_s: np.ndarray
    """Console time of the last HEARTBEAT."""


class GcsSource:
    """A MAVLink link to the autopilots (a GCS endpoint or router): modes, armed, battery.

    Args:
        endpoint: a MavEndpoint on the opened link (listening; the console never sends on it).
        sysids: vehicle index of each autopilot sysid.
        capacity: vehicles.
    """

    def __init__(self, endpoint: MavEndpoint, sysids: dict[int, int], capacity: int, clock=time.monotonic):
        self.ep = endpoint
        self.index = dict(sysids)
        self.clock = clock
        self.view = AutopilotView(["" for _ in range(capacity)], np.full(capacity, -1, np.int8),
                                  np.full(capacity, np.nan), np.full(capacity, np.nan), np.zeros(capacity, np.int8),
                                  np.full(capacity, -np.inf))
        self._dialect: dict[int, Any] = {}
        self.messages = 0
        self.ignored = 0

    def poll(self) -> int:
        from companion.link.dialects import UnknownAutopilot, dialect_for_autopilot

        v, index, taken = self.view, self.index, 0
        for msgid, sysid, compid, w, _addr in self.ep.poll_raw():
            k = index.get(sysid)
            if k is None or compid != _AUTOPILOT:
                self.ignored += 1
                continue
            taken += 1
            if msgid == MsgId.HEARTBEAT:
                h = _HB_AT
                custom, ap, base = w[h["custom_mode"]], w[h["autopilot"]], w[h["base_mode"]]
                d = self._dialect.get(ap)
                if d is None and ap not in self._dialect:
                    try:
                        d = dialect_for_autopilot(ap)
                    except UnknownAutopilot:
                        d = None
                    if len(self._dialect) < 16:
                        self._dialect[ap] = d
                try:
                    v.mode[k] = d.mode_name(custom) if d is not None else f"mode {custom}"
                except Exception:  # a dialect must not take the console down on a hostile value
                    v.mode[k] = f"mode {custom}"
                v.armed[k] = 1 if base & 128 else 0
                v.heard_s[k] = self.clock()
            elif msgid == MsgId.SYS_STATUS:
                mv = w[_SYS_AT["voltage_battery"]]
                self._battery(k, w[_SYS_AT["battery_remaining"]], mv * 1e-3 if mv != 0xFFFF else math.nan)
            elif msgid == MsgId.BATTERY_STATUS:
                self._battery(k, w[_BATT_AT["battery_remaining"]], math.nan)
            elif msgid == MsgId.EXTENDED_SYS_STATE:
                v.landed[k] = w[_EXT_AT["landed_state"]]
            else:
                taken -= 1
        self.messages += taken
        return taken

    def _battery(self, k: int, remaining: int, volts: float) -> None:
        v = self.view
        if 0 <= remaining <= 100:
            v.battery_pct[k] = remaining
        if math.isfinite(volts) and 0 < volts < 1000:
            v.voltage_v[k] = volts

    def to_json(self, n: int, now: float) -> dict[str, Any]:
        v = self.view
        stale = now - v.heard_s[:n] > 3.0
        return {"mode": [("" if s else m) for m, s in zip(v.mode[:n], stale.tolist())],
                "armed": np.where(stale, -1, v.armed[:n]).tolist(),
                "battery": [None if not math.isfinite(b) else round(float(b)) for b in v.battery_pct[:n].tolist()],
                "landed": v.landed[:n].tolist(), "stale": stale.tolist(), "messages": self.messages,
                "bad_frames": self.ep.bad_frames}


def wire_index(cls: Any) -> dict[str, int]:
    """name -> index of each field in Codec.decode_raw's flattened wire-order tuple."""
    out, i = {}, 0
    for f, length in zip(cls.ordered_fieldnames, cls.array_lengths):
        out[f] = i
        i += length or 1
    return out


def fields_of(cls: Any, w: tuple) -> dict[str, Any]:
    """Codec.decode_raw's wire-order values of a message as {field name: value (arrays as lists)}."""
    out, i = {}, 0
    for f, length in zip(cls.ordered_fieldnames, cls.array_lengths):
        out[f] = list(w[i:i + length]) if length else w[i]
        i += length or 1
    return out


_PLAN_CLS, _SLOTS_CLS = sd.MAVLink_swarmdrop_plan_message, sd.MAVLink_swarmdrop_slots_message
_PLAN_AT = wire_index(_PLAN_CLS)
_SLOTS_AT = wire_index(_SLOTS_CLS)
_HB_AT = wire_index(sd.MAVLink_heartbeat_message)
_SYS_AT = wire_index(sd.MAVLink_sys_status_message)
_BATT_AT = wire_index(sd.MAVLink_battery_status_message)
_EXT_AT = wire_index(sd.MAVLink_extended_sys_state_message)
