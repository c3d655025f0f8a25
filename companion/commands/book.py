"""The receiver side of swarm commands, vectorised over receiver rows (docs/swarm.md,
"On the vehicles"). Pure: numpy; no clock, no I/O.

A `PlanBook` serves R receiver rows: one on a companion computer, every vehicle's in the
headless runner (each row hears the link on its own). It holds the few distinct plans and
tracks the rows use and, per row, the plan in force and at most one pending newer one:

    book = PlanBook(mission, n_rows)
    book.receive(rows, plan)        # a plan assembled (PlanAssembler) by those rows
    book.advance(t_s, t_go_rows)    # pending plans whose effective time has come take force
    for g in book.references(t_s, t_go_rows):   # the references to fly (companion.agent)
        ... g.rows, g.h_pos (G, N, 3), g.h_vel, g.h_acc, g.h_sel, g.track.weights, ...
    book.plan_seq                   # per row, for SWARMDROP_STATE.plan_seq
    book.relay_messages(row, epoch) # the newest complete plan the row holds, as messages

Rules (docs/swarm.md, "Agreement rules"): the newest seq wins; a stale, duplicated or
reordered plan never undoes a newer one; a pending plan takes force at its effective time,
or at once if that has passed (then as if at its effective time: every row that flew the
same plans before it flies the same reference after it, however late it heard it).

Memory is bounded by the rows: a row keeps at most its plan in force and one pending plan,
so a flood of plans with new seqs only ever replaces the pending one (counted in
`stats.superseded`), and the book holds at most 2 R + 1 plans and R + 1 tracks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.commands.checks import shape_spacing
from companion.commands.plan import CommandError, SwarmPlan, initial_plan
from companion.commands.track import Track, enter, initial_track
from companion.feasibility import SEPARATION_M
from companion.mission import Mission


@dataclass
class BookStats:
    """What a PlanBook has been given and dropped (counters, per row and plan)."""

    received: int = 0
    """Row-plans taken as pending."""
    applied: int = 0
    """Row-plans that took force."""
    stale: int = 0
    """Row-plans older than the newest the row holds: dropped."""
    duplicates: int = 0
    """Row-plans the row holds already (relayed copies): dropped."""
    conflicts: int = 0
    """Row-plans with a seq the row holds but other content: dropped (the first is kept)."""
    superseded: int = 0
    """Pending row-plans replaced by a newer one before their effective time."""
    rejected: int = 0
    """Plans for another vehicle count, or (ABORT aside) with a formation whose slots are closer
    than the separation: dropped."""


@dataclass
class RefGroup:
    """The rows that fly one track, and their references (companion.commands.track).

    Attributes:
        rows: (R_g,) the book rows (indices) in this group.
        track: the track they fly: consensus (N,) bool, weights (N, N), neighbours (N, K),
            role, land_start_s, land_handover_s, land_point_ned_m, plan (abort: plan.abort).
        t_go_s: (G,) the transit starts the rows hold (NaN: none), one reference each.
        h_pos, h_vel, h_acc: (G, N, 3) every vehicle's reference under each t_go.
        h_sel: (R_g,) which of the G references each row flies (as consensus_rows takes it).
        centre_end_s: (G,) when the plan's centre comes to rest (TRANSIT -> HOVER), NaN: unknown.
    """

    rows: np.ndarray
    track: Track
    t_go_s: np.ndarray
    h_pos: np.ndarray
    h_vel: np.ndarray
    h_acc: np.ndarray
    h_sel: np.ndarray
    centre_end_s: np.ndarray = field(repr=False)


class PlanBook:
    """Plans held by R receiver rows (module docstring).

    Args:
        mission: the mission (every row's; its own plan is seq 0).
        n_rows: receiver rows (>= 1).
        separation_m: what the tracks keep vehicles apart by (landing layers, parking).
    """

    def __init__(self, mission: Mission, n_rows: int, *, separation_m: float = SEPARATION_M):
        if n_rows < 1:
            raise ValueError(f"n_rows must be >= 1, got {n_rows}")
        self.mission = mission
        self.separation_m = separation_m
        self.n_rows = int(n_rows)
        plan0 = initial_plan(mission)
        self._plans: dict[int, SwarmPlan] = {0: plan0}
        self._tracks: dict[int, Track] = {0: initial_track(plan0, mission)}
        self._made: dict[tuple, int] = {}
        self._next_track = 1
        self.track_of = np.zeros(self.n_rows, dtype=np.int64)
        """(R,) the track each row flies (an id of the book)."""
        self.plan_seq = np.zeros(self.n_rows, dtype=np.int64)
        """(R,) seq of the plan in force in each row (SWARMDROP_STATE.plan_seq)."""
        self.pending_seq = np.zeros(self.n_rows, dtype=np.int64)
        """(R,) seq of the newer plan each row holds until its effective time (0: none)."""
        self.stats = BookStats()
        self._messages: dict[tuple[int, int], list] = {}

    # ------------------------------------------------------------------ queries
    @property
    def newest_seq(self) -> np.ndarray:
        """(R,) the newest plan each row holds (pending or in force)."""
        return np.maximum(self.plan_seq, self.pending_seq)

    @property
    def plans_held(self) -> int:
        """Distinct plans the book holds (bounded by 2 R + 1)."""
        return len(self._plans)

    def track(self, row: int) -> Track:
        """The track row `row` flies."""
        return self._tracks[int(self.track_of[row])]

    def plan(self, seq: int) -> SwarmPlan | None:
        """A plan the book holds, by seq (None if not held)."""
        return self._plans.get(int(seq))

    def relay_messages(self, row: int, epoch_unix_s: float, codec: Any = None) -> list:
        """What row `row` relays: the messages of the newest complete plan it holds
        (plan_messages: (msgid, values) pairs; cached per plan), [] under the mission's own."""
        seq = int(max(self.plan_seq[row], self.pending_seq[row]))
        if seq == 0:
            return []
        key = (seq, round(epoch_unix_s * 1e6))
        if key not in self._messages:
            from companion.commands.wire import plan_messages

            self._messages = {k: v for k, v in self._messages.items() if k[0] in self._plans}
            self._messages[key] = plan_messages(self._plans[seq], epoch_unix_s, codec)
        return self._messages[key]

    # ------------------------------------------------------------------ updates
    def receive(self, rows, plan: SwarmPlan) -> np.ndarray:
        """Rows `rows` (indices or a bool mask) have assembled `plan`. Rows that hold nothing as
        new take it as their pending plan (replacing an older pending one); the others count it
        as stale, a duplicate or a conflict. Returns the rows that took it."""
        rows = self._rows(rows)
        if plan.n_vehicles != self.mission.n or plan.seq < 1 or not self._spaced(plan):
            self.stats.rejected += len(rows)
            return rows[:0]
        held = self._plans.get(plan.seq)
        if held is not None and held != plan:
            self.stats.conflicts += len(rows)
            return rows[:0]
        newest = self.newest_seq[rows]
        take = rows[newest < plan.seq]
        self.stats.stale += int(np.sum(newest > plan.seq))
        self.stats.duplicates += int(np.sum(newest == plan.seq))
        if len(take):
            self.stats.superseded += int(np.sum(self.pending_seq[take] > 0))
            self.pending_seq[take] = plan.seq
            self.stats.received += len(take)
            self._plans.setdefault(plan.seq, plan)
            self._prune()
        return take

    def _spaced(self, plan: SwarmPlan) -> bool:
        """The plan's formation keeps its slots the separation apart (checked again here, on the
        receiving side: the sender's checks do not protect against a forged or buggy sender). An
        ABORT always passes: it hands every vehicle to its autopilot."""
        if plan.abort or plan.n_slots < 2:
            return True
        try:
            shape_spacing(f"plan {plan.seq}", plan.formation, plan.n_slots, self.separation_m)
        except CommandError:
            return False
        return True

    def advance(self, t_s: float, t_go_rows) -> np.ndarray:
        """Pending plans whose effective time has come (t_s >= effective_s) take force, entered
        from the track each row flew, with the transit start it holds (t_go_rows (R,), NaN:
        none). Returns the rows whose plan changed."""
        pend = (self.pending_seq > 0).nonzero()[0]
        if not len(pend):
            return pend
        due = pend[[self._plans[int(s)].effective_s <= t_s for s in self.pending_seq[pend].tolist()]]
        if not len(due):
            return due
        t_go = self._per_row(t_go_rows)
        for r in due.tolist():
            seq = int(self.pending_seq[r])
            key = (int(self.track_of[r]), seq, _key(float(t_go[r])))
            tid = self._made.get(key)
            if tid is None:
                tid = self._next_track
                self._next_track += 1
                self._tracks[tid] = enter(self._plans[seq], self._tracks[key[0]], self.mission, float(t_go[r]),
                                          self.separation_m)
                self._made[key] = tid
            self.track_of[r] = tid
            self.plan_seq[r] = seq
            self.pending_seq[r] = 0
        self.stats.applied += len(due)
        self._prune()
        return due

    def references(self, t_s: float, t_go_rows, rows=None) -> list[RefGroup]:
        """The references the rows fly at t_s: one RefGroup per track in use, each with one
        reference per transit start its rows hold (t_go_rows (R,), NaN: none). Under the
        mission's own plan with one transit start: one group whose h_pos[0] is exactly
        mission.offsets_ned_m + c, h_vel[0] every row c', h_acc[0] c'' (c = mission.path.at(
        Mission.tau_s(t_s, t_go))), its weights and neighbours mission.weights and .neighbours.

        Args:
            rows: the book rows wanted (indices; default all), e.g. those in a formation phase.
        """
        rows = np.arange(self.n_rows) if rows is None else self._rows(rows)
        t_go = self._per_row(t_go_rows)[rows]
        tracks = self.track_of[rows]
        out = []
        tl = tracks.tolist()
        ids = [tl[0]] if tl and tl.count(tl[0]) == len(tl) else sorted(set(tl))
        for tid in ids:
            sel = np.arange(len(rows)) if len(ids) == 1 else np.flatnonzero(tracks == tid)
            out.append(self._group(t_s, rows[sel], t_go[sel], self._tracks[tid]))
        return out

    # ------------------------------------------------------------------ internals
    def _group(self, t_s: float, rows: np.ndarray, t_go: np.ndarray, track: Track) -> RefGroup:
        gl = t_go.tolist()
        g0 = gl[0]
        one = gl.count(g0) == len(gl) if g0 == g0 else all(x != x for x in gl)  # (NaN != NaN)
        if one:
            groups, h_sel = [g0], np.zeros(len(gl), np.int64)
        else:
            keys, h_sel = np.unique(np.where(np.isnan(t_go), -np.inf, t_go), return_inverse=True)
            groups = [math.nan if g == -np.inf else g for g in keys.tolist()]
        n = track.target_ned_m.shape[0]
        h_pos, h_vel, h_acc = (np.empty((len(groups), n, 3)) for _ in range(3))
        ends = np.empty(len(groups))
        for g, t_go_s in enumerate(groups):
            track.at(t_s, self.mission, t_go_s, out=(h_pos[g], h_vel[g], h_acc[g]))
            ends[g] = track.centre_end_s(self.mission, t_go_s)
        return RefGroup(rows, track, np.asarray(groups, dtype=float), h_pos, h_vel, h_acc, h_sel, ends)

    def _per_row(self, t_go_rows) -> np.ndarray:
        """t_go_rows as (n_rows,) floats: a scalar (or one value) broadcast, an array as it is."""
        t_go = np.asarray(t_go_rows, dtype=float)
        # (np.broadcast_to only when needed: it is a Python-level call worth 10 us a plan step)
        return t_go if t_go.shape == (self.n_rows,) else np.broadcast_to(t_go, (self.n_rows,))

    def _rows(self, rows) -> np.ndarray:
        r = np.asarray(rows)
        return np.flatnonzero(r) if r.dtype == bool else r.astype(np.int64).reshape(-1)

    def _prune(self) -> None:
        """Keep only the plans and tracks some row uses (the memory bound)."""
        used_tracks = set(self.track_of.tolist())
        if len(self._tracks) > len(used_tracks):
            self._tracks = {k: v for k, v in self._tracks.items() if k in used_tracks}
            self._made = {k: v for k, v in self._made.items() if v in used_tracks and k[0] in used_tracks}
        used = set(self.plan_seq.tolist()) | set(self.pending_seq.tolist()) | {0}
        if len(self._plans) > len(used):
            self._plans = {k: v for k, v in self._plans.items() if k in used}


def _key(t_go_s: float) -> float:
    return -math.inf if math.isnan(t_go_s) else t_go_s
