"""A plan on the wire: SWARMDROP_PLAN + SWARMDROP_SLOTS (`plan_messages`) and their
reassembly on a lossy, reordering, duplicating link (`PlanAssembler`).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from companion.commands.plan import (
    _FLAGS_KNOWN,
    FLAG_ABORT,
    FLAG_EXCLUDED_LAND,
    FLAG_HOLD,
    FLAG_LAND_AT_END,
    KINDS,
    MAX_PENDING_PLANS,
    NO_SLOT_WIRE,
    PLAN_WAYPOINTS_MAX,
    SLOTS_PER_MESSAGE,
    WIRE_VEHICLES_MAX,
    SwarmPlan,
)
from companion.control.shapes import SHAPES, FormationSpec
from companion.mission import Mission

_codec: Any = None


def _default_codec() -> Any:
    global _codec
    if _codec is None:
        from companion.link.msgdef import swarmdrop
        from companion.link.wire import Codec

        _codec = Codec(swarmdrop)
    return _codec


def _msgids() -> tuple[int, int]:
    from companion.link.enums import MsgId

    return int(MsgId.SWARMDROP_PLAN), int(MsgId.SWARMDROP_SLOTS)


def _bitmask(ids: Iterable[int]) -> tuple[int, ...]:
    b = [0] * 32
    for v in ids:
        b[v // 8] |= 1 << (v % 8)
    return tuple(b)


def _from_bitmask(bits: Sequence[int], n: int) -> frozenset[int] | None:
    """The ids set in a 32-byte bitmask; None if a bit at or beyond n is set."""
    out = set()
    for k, byte in enumerate(bits):
        byte = int(byte)
        for b in range(8):
            if byte >> b & 1:
                v = 8 * k + b
                if v >= n:
                    return None
                out.add(v)
    return frozenset(out)


def _epoch_us(epoch_unix_s: float) -> int:
    return int(round(epoch_unix_s * 1e6))


def plan_messages(plan: SwarmPlan, epoch_unix_s: float, codec: Any = None) -> list[tuple[int, tuple]]:
    """A plan as messages: one SWARMDROP_PLAN, then the SWARMDROP_SLOTS chunks of its slot
    table (SLOTS_PER_MESSAGE vehicles each), as (msgid, values) for Codec.encode_fields,
    built with the codec's named-field builders.

    Args:
        plan: a plan with seq >= 1 (quantised: CommandSource's are; others are carried at
            wire precision).
        epoch_unix_s: Unix time of mission time 0 (effective_usec = epoch + effective_s).
        codec: a companion.link.wire.Codec of the swarmdrop dialect (default: one of its own).
    Raises:
        ValueError: seq 0, more than WIRE_VEHICLES_MAX vehicles, more than 8 waypoints, or
            an effective time before the Unix epoch.
    """
    if plan.seq < 1:
        raise ValueError("plan 0 is the mission's own plan: it is never sent")
    n = plan.n_vehicles
    if n > WIRE_VEHICLES_MAX:
        raise ValueError(f"{n} vehicles: a plan carries at most {WIRE_VEHICLES_MAX}")
    if len(plan.waypoints_ned_m) > PLAN_WAYPOINTS_MAX:
        raise ValueError(f"{len(plan.waypoints_ned_m)} waypoints: a plan carries at most {PLAN_WAYPOINTS_MAX}")
    eff_us = _epoch_us(epoch_unix_s) + round(plan.effective_s * 1e6)
    if eff_us < 0:
        raise ValueError(f"effective time {plan.effective_s} s is before the Unix epoch")
    codec = codec or _default_codec()
    plan_id, slots_id = _msgids()
    wps = [float(x) for p in plan.waypoints_ned_m for x in p]
    wps += [0.0] * (3 * PLAN_WAYPOINTS_MAX - len(wps))
    flags = ((FLAG_HOLD if plan.hold else 0) | (FLAG_LAND_AT_END if plan.land_at_end else 0)
             | (FLAG_ABORT if plan.abort else 0) | (FLAG_EXCLUDED_LAND if plan.excluded_land else 0))
    f = plan.formation
    out = [(plan_id, codec.builder(plan_id)(
        effective_usec=eff_us, seq=plan.seq, waypoints=tuple(wps), speed=plan.speed_mps, radius=f.radius_m,
        spacing=f.spacing_m, rotation=f.rotation_rad, morph_time=plan.morph_s, excluded=_bitmask(plan.excluded),
        landing=_bitmask(plan.landing), kind=KINDS.index(plan.kind), n_waypoints=len(plan.waypoints_ned_m),
        shape=SHAPES.index(f.shape), flags=flags, n_vehicles=n,
        start_velocity=tuple(float(x) for x in plan.start_velocity_ned_mps)))]
    build_slots = codec.builder(slots_id)
    for first in range(0, n, SLOTS_PER_MESSAGE):
        chunk = [NO_SLOT_WIRE if s < 0 else s for s in plan.slot_of[first:first + SLOTS_PER_MESSAGE]]
        out.append((slots_id, build_slots(seq=plan.seq, first=first, count=len(chunk),
                                          slot=tuple(chunk + [0] * (SLOTS_PER_MESSAGE - len(chunk))))))
    return out


@dataclass
class AssemblerStats:
    """What a PlanAssembler has seen (counters only grow)."""

    completed: int = 0
    """Plans assembled and returned."""
    stale: int = 0
    """Messages of a seq older than the newest plan completed: dropped."""
    duplicates: int = 0
    """Messages already held (identical), or of the newest plan completed (relayed copies): dropped."""
    conflicts: int = 0
    """Messages of a held seq and part with different content: the first is kept."""
    rejected: int = 0
    """Hostile or malformed messages or slot tables (never raised): dropped."""
    evicted: int = 0
    """Plans in progress dropped to keep at most max_pending."""
    last_reject: str = ""
    """Why the last message or plan was rejected."""


@dataclass
class _Pending:
    head: tuple | None = None  # the PLAN's fields, decoded and checked
    chunks: dict[int, tuple[int, ...]] = dataclasses.field(default_factory=dict)  # first -> slots


class PlanAssembler:
    """Reassembles SwarmPlans from decoded SWARMDROP_PLAN / SWARMDROP_SLOTS messages that a
    lossy link may lose, delay, reorder and duplicate.

    A plan is returned once its PLAN and every SLOTS chunk of its seq are held. Only seqs
    newer than the newest plan completed are kept (a stale or reordered plan never undoes a
    newer one), at most max_pending of them (the oldest in progress is dropped first).
    Hostile input (non-finite numbers, too many waypoints, bits beyond the fleet, unknown
    kind, shape or flags, a slot table that is not a permutation) is rejected and counted
    in `stats`, never raised.

    Args:
        n_vehicles: vehicles in the mission (a plan for another count is rejected).
        epoch_unix_s: Unix time of mission time 0.
        circle_order: the mission's formation.slot_order: how a circle's slots are laid out
            (the wire does not carry it; companion.control.shapes).
        max_pending: seqs in progress at most.
    """

    def __init__(self, n_vehicles: int, epoch_unix_s: float, *, circle_order: str = "sequential",
                 max_pending: int = MAX_PENDING_PLANS):
        if not 1 <= n_vehicles <= WIRE_VEHICLES_MAX:
            raise ValueError(f"n_vehicles must be 1..{WIRE_VEHICLES_MAX}, got {n_vehicles}")
        if circle_order not in ("sequential", "interleaved"):
            raise ValueError(f"unknown circle order {circle_order!r}")
        self.n = n_vehicles
        self.epoch_us = _epoch_us(epoch_unix_s)
        self.circle_order = circle_order
        self.max_pending = max(1, int(max_pending))
        self.newest_seq = 0
        """Seq of the newest plan completed (0: none yet, the mission's own plan)."""
        self.newest: SwarmPlan | None = None
        """The newest plan completed."""
        self.stats = AssemblerStats()
        self._pending: dict[int, _Pending] = {}
        self._plan_id, self._slots_id = _msgids()

    @classmethod
    def for_mission(cls, mission: Mission, epoch_unix_s: float, **kw: Any) -> PlanAssembler:
        """An assembler for a mission's vehicle count and circle order."""
        return cls(mission.n, epoch_unix_s, circle_order=mission.cfg.formation.slot_order, **kw)

    def set_epoch(self, epoch_unix_s: float) -> None:
        """Change the mission epoch (plans in progress are dropped: their times were read with the old one)."""
        self.epoch_us = _epoch_us(epoch_unix_s)
        self._pending.clear()

    @property
    def pending_seqs(self) -> tuple[int, ...]:
        """Seqs in progress (bounded by max_pending)."""
        return tuple(sorted(self._pending))

    def feed(self, msg: Any) -> SwarmPlan | None:
        """Take one decoded message (Codec.decode's object; other messages are ignored).

        Returns:
            The plan this message completes, or None.
        """
        msgid = getattr(type(msg), "id", None)
        names: tuple[str, ...]
        if msgid == self._plan_id:
            names = ("effective_usec", "seq", "waypoints", "speed", "radius", "spacing", "rotation", "morph_time",
                     "excluded", "landing", "kind", "n_waypoints", "shape", "flags", "n_vehicles", "start_velocity")
        elif msgid == self._slots_id:
            names = ("seq", "first", "count", "slot")
        else:
            return None
        try:
            fields = {k: getattr(msg, k) for k in names}
        except AttributeError as exc:
            return self._reject(f"message without field: {exc}")
        return self.feed_fields(msgid, fields)

    def feed_fields(self, msgid: int, fields: Mapping[str, Any]) -> SwarmPlan | None:
        """Take one message as its field values by name (as feed). Never raises for bad values."""
        try:
            if msgid == self._plan_id:
                return self._feed_plan(fields)
            if msgid == self._slots_id:
                return self._feed_slots(fields)
        except (KeyError, TypeError, ValueError, OverflowError, IndexError) as exc:
            return self._reject(f"malformed message: {exc}")
        return None

    # ------------------------------------------------------------------ internals
    def _reject(self, why: str) -> SwarmPlan | None:
        self.stats.rejected += 1
        self.stats.last_reject = why
        return None

    def _slot_for(self, seq: int) -> _Pending | None:
        """The in-progress entry of seq (made if new), or None if stale."""
        if seq <= self.newest_seq:
            if seq == self.newest_seq:
                self.stats.duplicates += 1  # (agents relay the newest plan: its copies keep coming)
            else:
                self.stats.stale += 1
            return None
        entry = self._pending.get(seq)
        if entry is None:
            if len(self._pending) >= self.max_pending:
                oldest = min(self._pending)
                if oldest > seq:  # every plan in progress is newer than this one
                    self.stats.evicted += 1
                    return None
                del self._pending[oldest]
                self.stats.evicted += 1
            entry = self._pending[seq] = _Pending()
        return entry

    def _feed_plan(self, f: Mapping[str, Any]) -> SwarmPlan | None:
        seq = int(f["seq"])
        if seq < 1:
            return self._reject("PLAN with seq 0 (the mission's own plan is never sent)")
        n_wp, kind, shape, flags, n_veh = (int(f[k]) for k in ("n_waypoints", "kind", "shape", "flags", "n_vehicles"))
        if n_veh != self.n:
            return self._reject(f"PLAN {seq} for {n_veh} vehicles; the mission has {self.n}")
        if not 0 <= kind < len(KINDS):
            return self._reject(f"PLAN {seq}: unknown kind {kind}")
        if not 0 <= shape < len(SHAPES):
            return self._reject(f"PLAN {seq}: unknown shape {shape}")
        if flags & ~_FLAGS_KNOWN:
            return self._reject(f"PLAN {seq}: unknown flag bits 0x{flags & ~_FLAGS_KNOWN:02x}")
        if not 0 <= n_wp <= PLAN_WAYPOINTS_MAX:
            return self._reject(f"PLAN {seq}: {n_wp} waypoints (at most {PLAN_WAYPOINTS_MAX})")
        if flags & FLAG_HOLD and n_wp == 0:
            return self._reject(f"PLAN {seq}: hold without a waypoint")
        raw = [float(x) for x in f["waypoints"]]
        if len(raw) != 3 * PLAN_WAYPOINTS_MAX:
            return self._reject(f"PLAN {seq}: {len(raw)} waypoint values")
        nums = [float(f[k]) for k in ("speed", "radius", "spacing", "rotation", "morph_time")]
        v0 = [float(x) for x in f.get("start_velocity", (0.0, 0.0, 0.0))]  # (older senders: absent, zero)
        if len(v0) != 3:
            return self._reject(f"PLAN {seq}: {len(v0)} start velocity values")
        if not all(math.isfinite(x) for x in raw[:3 * n_wp] + nums + v0):
            return self._reject(f"PLAN {seq}: non-finite waypoint, speed, size, rotation, morph time or start velocity")
        speed, radius, spacing, rotation, morph = nums
        if not (speed > 0 and radius > 0 and spacing > 0 and morph >= 0):
            return self._reject(f"PLAN {seq}: speed, radius and spacing must be > 0 and morph time >= 0")
        excluded = _from_bitmask(f["excluded"], self.n)
        landing = _from_bitmask(f["landing"], self.n)
        if excluded is None or landing is None:
            return self._reject(f"PLAN {seq}: excluded or landing bits beyond vehicle {self.n - 1}")
        eff_us = int(f["effective_usec"])
        s_name = SHAPES[shape]
        formation = FormationSpec(shape=s_name, radius_m=radius, spacing_m=spacing, rotation_rad=rotation,
                                  slot_order=self.circle_order if s_name == "circle" else "sequential")  # type: ignore[arg-type]
        head = (seq, KINDS[kind], (eff_us - self.epoch_us) / 1e6,
                tuple((raw[3 * k], raw[3 * k + 1], raw[3 * k + 2]) for k in range(n_wp)), speed, bool(flags & FLAG_HOLD),
                bool(flags & FLAG_LAND_AT_END), formation, morph, excluded, bool(flags & FLAG_EXCLUDED_LAND), landing,
                bool(flags & FLAG_ABORT), (v0[0], v0[1], v0[2]))
        entry = self._slot_for(seq)
        if entry is None:
            return None
        if entry.head is not None:
            if entry.head == head:
                self.stats.duplicates += 1
            else:
                self.stats.conflicts += 1
            return None
        entry.head = head
        return self._complete(seq)

    def _feed_slots(self, f: Mapping[str, Any]) -> SwarmPlan | None:
        seq, first, count = int(f["seq"]), int(f["first"]), int(f["count"])
        if seq < 1:
            return self._reject("SLOTS with seq 0")
        if first % SLOTS_PER_MESSAGE or not 0 <= first < self.n or count != min(SLOTS_PER_MESSAGE, self.n - first):
            return self._reject(f"SLOTS {seq}: chunk first={first} count={count} does not tile {self.n} vehicles")
        raw = [int(x) for x in f["slot"]][:count]
        if len(raw) != count or any(not (s == NO_SLOT_WIRE or 0 <= s < self.n) for s in raw):
            return self._reject(f"SLOTS {seq}: a slot index outside 0..{self.n - 1} (or 255)")
        slots = tuple(-1 if s == NO_SLOT_WIRE else s for s in raw)
        entry = self._slot_for(seq)
        if entry is None:
            return None
        held = entry.chunks.get(first)
        if held is not None:
            if held == slots:
                self.stats.duplicates += 1
            else:
                self.stats.conflicts += 1
            return None
        entry.chunks[first] = slots
        return self._complete(seq)

    def _complete(self, seq: int) -> SwarmPlan | None:
        entry = self._pending[seq]
        if entry.head is None or len(entry.chunks) * SLOTS_PER_MESSAGE < self.n:
            return None
        slot_of = tuple(s for first in sorted(entry.chunks) for s in entry.chunks[first])
        (seq, kind, eff, wps, speed, hold, land_end, formation, morph, excluded, excl_land, landing, abort,
         v0) = entry.head
        del self._pending[seq]
        taken = sorted(s for s in slot_of if s >= 0)
        if taken != list(range(len(taken))):
            return self._reject(f"plan {seq}: the slot table is not a permutation of 0..{len(taken) - 1}")
        if any(slot_of[v] >= 0 for v in excluded):
            return self._reject(f"plan {seq}: an excluded vehicle holds a slot")
        plan = SwarmPlan(seq=seq, kind=kind, effective_s=eff, waypoints_ned_m=wps, speed_mps=speed, hold=hold,
                         land_at_end=land_end, formation=formation, morph_s=morph, slot_of=slot_of, excluded=excluded,
                         excluded_land=excl_land, landing=landing, abort=abort, start_velocity_ned_mps=v0)
        self.newest_seq, self.newest = seq, plan
        for s in [s for s in self._pending if s <= seq]:
            del self._pending[s]
        self.stats.completed += 1
        return plan

