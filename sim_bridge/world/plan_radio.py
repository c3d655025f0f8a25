"""Swarm plans on the swarm radio, headless (docs/swarm.md, "Swarm commands"; issue 19).

A plan travels as frames: one SWARMDROP_PLAN and ceil(N / SLOTS_PER_MESSAGE) SWARMDROP_SLOTS
(companion.commands.wire). Each copy of each frame, from a sender to a receiver, is lost
and delayed as the run's `RadioModel` decides (the states' model: loss, delay, jitter, range),
keyed by its own hash stream; a receiver holds a plan once it has every frame of it, from
any mix of senders (PlanAssembler keeps partial plans the same way). The senders:

* the command source (the operator's console, the scenario's schedule), sender id N (no
  vehicle), which repeats every plan `source_repeats` times `source_repeat_s` apart (as the
  console does);
* every vehicle, which relays the newest complete plan it holds: once right after it first
  completes it (staggered by vehicle id over `relay_stagger_s`, so that forty relays do not
  share one instant), then every `relay_period_s` (at a phase set by its id).

So a plan reaches vehicles out of the source's range, and survives loss; `tests/
test_plan_radio.py` measures it.
"""
from __future__ import annotations

import heapq
import math

import numpy as np

from companion.commands.plan import SLOTS_PER_MESSAGE
from sim_bridge.world.transport import LinkConfig, RadioModel

PLAN_STREAM_SALT = 0x504C414E
"""Mixed into the run's seed for plan frames: their fates are drawn apart from the states'."""
FRAME_SLOTS_US = 16
"""A sender's frames at one instant get distinct hash keys: stamp_us * this + frame index."""


class PlanRadio:
    """Plan frames between a command source and n vehicles (module docstring).

    Args:
        cfg: the swarm radio (the run's link).
        n: vehicles (receiver rows 0..n-1; the source is sender n).
        seed: the run's seed.
        relay_period_s: a vehicle re-sends its newest plan this often, s.
        relay_stagger_s: its first relay of a new plan comes id / n of this after it completed it, s.
        source_repeats, source_repeat_s: the source sends each plan this many times, this far apart.
    """

    def __init__(self, cfg: LinkConfig, n: int, seed: int, *, relay_period_s: float = 1.0,
                 relay_stagger_s: float = 0.2, source_repeats: int = 3, source_repeat_s: float = 0.3):
        self.n = n
        self.radio = RadioModel(cfg, int(seed) ^ PLAN_STREAM_SALT)
        self.frames = 1 + math.ceil(n / SLOTS_PER_MESSAGE)
        self.relay_period_s, self.relay_stagger_s = relay_period_s, relay_stagger_s
        self.source_repeats, self.source_repeat_s = source_repeats, source_repeat_s
        self._queue: list[tuple[float, int, int, np.ndarray, np.ndarray]] = []
        """(delivery time, tiebreak, seq, frame index (d,), receiver rows (d,)) per send."""
        self._count = 0
        self._got: dict[int, np.ndarray] = {}
        """seq -> (n, frames) bool: which frames each row holds."""
        self.complete_s: dict[int, np.ndarray] = {}
        """seq -> (n,) when each row first held the whole plan (NaN: not yet)."""
        self._next_relay = np.full(n, math.inf)
        self._relay_seq = np.zeros(n, np.int64)
        self._source: list[tuple[float, int]] = []
        """(time, seq) of the source's sends still to come."""
        self.frames_sent = 0
        self.frames_delivered = 0

    def issue(self, t_s: float, seq: int) -> None:
        """The source issues plan `seq` at t_s (sent now and repeated)."""
        for k in range(self.source_repeats):
            heapq.heappush(self._source, (t_s + k * self.source_repeat_s, seq))
        self._got.setdefault(seq, np.zeros((self.n, self.frames), bool))
        self.complete_s.setdefault(seq, np.full(self.n, np.nan))

    def step(self, t_s: float, positions_ned_m: np.ndarray, newest_seq: np.ndarray) -> list[tuple[np.ndarray, int]]:
        """Send what is due by t_s, deliver what has arrived, and say who now holds a whole plan.

        Args:
            positions_ned_m: (n, 3) where the vehicles are (range; NaN: hears nothing).
            newest_seq: (n,) the newest plan each vehicle holds (its relays send it).
        Returns:
            [(rows, seq)]: rows that completed plan seq at this step (hand them to the book).
        """
        pos = np.asarray(positions_ned_m, float)
        while self._source and self._source[0][0] <= t_s + 1e-9:
            _, seq = heapq.heappop(self._source)
            self._send(t_s, self.n, seq, pos, self._source_pos(pos))
        due = np.flatnonzero((self._next_relay <= t_s + 1e-9) & (self._relay_seq > 0))
        for r in due.tolist():
            self._send(t_s, r, int(self._relay_seq[r]), pos, pos[r])
            self._next_relay[r] += self.relay_period_s * max(1, math.ceil((t_s - self._next_relay[r]) / self.relay_period_s
                                                                           + 1e-9))
        out = []
        while self._queue and self._queue[0][0] <= t_s + 1e-9:
            _, _, seq, frame, rows = heapq.heappop(self._queue)
            got = self._got[seq]
            before = got.all(axis=1)
            got[rows, frame] = True
            self.frames_delivered += len(rows)
            new = np.flatnonzero(got.all(axis=1) & ~before)
            if len(new):
                self.complete_s[seq][new] = t_s
                out.append((new, seq))
        # Relays follow what each vehicle holds (it may have taken a newer plan from elsewhere).
        newer = np.asarray(newest_seq) > self._relay_seq
        if newer.any():
            rows = np.flatnonzero(newer)
            self._relay_seq[rows] = np.asarray(newest_seq)[rows]
            self._next_relay[rows] = t_s + self.relay_stagger_s * rows / max(self.n, 1)
        return out

    def _source_pos(self, pos: np.ndarray) -> np.ndarray:
        """Where the source transmits from: the fleet's centroid (in range of the swarm)."""
        finite = np.isfinite(pos).all(axis=1)
        return pos[finite].mean(axis=0) if finite.any() else np.zeros(3)

    def _send(self, t_s: float, sender: int, seq: int, pos: np.ndarray, sender_pos: np.ndarray) -> None:
        stamp_us = round(t_s * 1e6) * FRAME_SLOTS_US
        n_f = self.frames
        senders = np.full(n_f, sender, np.int64)
        stamps = (stamp_us + np.arange(n_f)) * 1e-6
        msg, rcv, when = self.radio.deliveries(senders, stamps, t_s, np.tile(sender_pos, (n_f, 1)), pos)
        self.frames_sent += n_f * (self.n - (1 if sender < self.n else 0))
        if not len(msg):
            return
        self._got.setdefault(seq, np.zeros((self.n, n_f), bool))
        self.complete_s.setdefault(seq, np.full(self.n, np.nan))
        for w in np.unique(when).tolist():  # (one push per arrival time: the fixed delay gives one)
            at = when == w
            self._count += 1
            heapq.heappush(self._queue, (w, self._count, seq, msg[at], rcv[at]))
