"""The swarm contract: what vehicles tell each other, and what each has heard.

Every vehicle publishes only its own state (`SwarmStates`, one row per vehicle:
position and velocity in the mission frame, attitude, phase, flags and its
transit-start value), stamped with the mission time at which it was measured.
Each receiver keeps the newest state it has heard of every vehicle in a
`SwarmView`. Messages may be lost, late, duplicated or reordered: a state never
replaces a newer one, and every entry carries its stamp, so the agent can ask
how old it is (`SwarmView.age_s`) and decide what it is still good for
(docs/swarm.md). The receiver axis lets one array hold many receivers' views:
the headless runner keeps one view per simulated vehicle, a companion keeps one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from companion.control.kernel import kernel

FLAG_ASSEMBLED = 1
"""The vehicle has reached its formation slot at least once."""
FLAG_OWN_VALID = 2
"""The vehicle's own state estimate was finite and fresh when published."""
FLAG_READY = 4
"""Its autopilot reports it recovered from launch (throw or take-off done)."""
FLAG_ID_CONFLICT = 8
"""The vehicle has heard, within swarm.peer_timeout_s, another sender claim its vehicle id
(an identity conflict, docs/swarm.md): neighbours and the operator see it in its state."""
FLAG_HANDED_OVER = 16
"""An ABORT plan handed the vehicle to its autopilot's own Hold: its agent commands nothing."""
INTRUDER_SLOTS = 4
"""Senders per receiver kept as intruders (a fifth takes the slot heard longest ago)."""
PHASE_COUNT = 7
"""Phases are 0 .. PHASE_COUNT - 1 (companion.agent.Phase; a test keeps them equal). A state
with any other phase is hostile or corrupt and is dropped: the agent indexes by phase."""
FUTURE_TOLERANCE_S = 0.5
"""A state stamped more than this ahead of the receiver's own clock is dropped (an agent's
swarm link: companion.node.swarmlink), s. Kept, it would be the newest for as long as it is early,
and every real state of its vehicle until then would be dropped as older: one datagram
stamped an hour ahead (a wrong clock, or anyone who can reach an unsigned swarm port) would
hide the vehicle behind a frozen copy for an hour. GNSS clocks agree to milliseconds; a
state may be one tick (20 ms) ahead of the receiver's last tick."""


@dataclass
class SwarmStates:
    """States published by k vehicles (the payload of the swarm link).

    Attributes:
        vehicle_id: (k,) int, index of the vehicle in the mission.
        stamp_s: (k,) mission time at which the state was measured, s.
        pos_ned_m: (k, 3) position, mission NED frame, m (NaN when invalid).
        vel_ned_mps: (k, 3) velocity, mission NED frame, m/s.
        att_q_wxyz: (k, 4) attitude NED->FRD, w first.
        phase: (k,) int8 agent phase (companion.agent.Phase).
        flags: (k,) uint8, FLAG_* bits.
        t_go_s: (k,) the sender's transit start, mission time, s (NaN = none yet).
        plan_seq: (k,) seq of the swarm plan the sender flies (0: the mission's own), or None
            (not known: states heard on the link carry it to the console, not into views).
    """

    vehicle_id: np.ndarray
    stamp_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    att_q_wxyz: np.ndarray
    phase: np.ndarray
    flags: np.ndarray
    t_go_s: np.ndarray
    plan_seq: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.vehicle_id)

    def select(self, idx) -> "SwarmStates":
        """The rows selected by idx (index array or mask), as a new SwarmStates."""
        # (plan_seq alone may be None; mypy cannot tell the fields apart in the generator)
        return SwarmStates(*(None if getattr(self, f) is None else np.asarray(getattr(self, f))[idx]  # type: ignore[arg-type]
                             for f in self.__dataclass_fields__))

    def rows(self, sl: slice) -> "SwarmStates":
        """The rows of slice sl, as views of these arrays (no copy)."""
        return SwarmStates(*(None if getattr(self, f) is None else getattr(self, f)[sl]  # type: ignore[arg-type]
                             for f in self.__dataclass_fields__))


@dataclass
class Intruders:
    """What n receivers have heard from senders that claim the receiver's own vehicle id
    (identity conflicts, docs/swarm.md), one slot per sender, kept like a neighbour entry:
    the newest stamp wins, and the agent avoids the sender as a vehicle (predicted while
    fresh, a ghost column once silent), never as itself.

    Attributes:
        pos_ned_m, vel_ned_mps: (n, K, 3) mission NED, m and m/s; NaN = slot unused.
        stamp_s: (n, K) measurement time, s; NaN = slot unused.
        phase: (n, K) int8; flags: (n, K) uint8 FLAG_* bits, as the sender published them.
        conflicts: (n,) int, states received that claimed the receiver's id.
    """

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    stamp_s: np.ndarray
    phase: np.ndarray
    flags: np.ndarray
    conflicts: np.ndarray

    @classmethod
    def none(cls, n_receivers: int, slots: int = INTRUDER_SLOTS) -> "Intruders":
        n, k = n_receivers, slots
        return cls(np.full((n, k, 3), np.nan), np.full((n, k, 3), np.nan), np.full((n, k), np.nan),
                   np.zeros((n, k), np.int8), np.zeros((n, k), np.uint8), np.zeros(n, np.int64))

    def age_s(self, t_s: float) -> np.ndarray:
        """(n, K) age of every slot at mission time t_s, s; inf where unused."""
        return np.fmin(t_s - self.stamp_s, np.inf)

    def heard_within(self, t_s: float, window_s: float) -> np.ndarray:
        """(n,) bool: some sender claimed the receiver's id within window_s before t_s."""
        return np.any(t_s - self.stamp_s <= window_s, axis=1)  # NaN (unused) compares False


@dataclass
class SwarmView:
    """The newest state each of n receivers has heard from each of N vehicles.

    Attributes:
        pos_ned_m: (n, N, 3) position, mission NED, m; NaN = never heard.
        vel_ned_mps: (n, N, 3) velocity, m/s.
        stamp_s: (n, N) measurement time of that state, s; NaN = never heard.
        phase: (n, N) int8 phase (0 = LAUNCH when never heard).
        flags: (n, N) uint8 FLAG_* bits.
        t_go_s: (n, N) that vehicle's transit start, s (NaN = none).
        received: (n,) int, states applied per receiver (for link statistics).
        ignored_old: (n,) int, states dropped because a newer one was already held.
        receive_kernel: the loop `receive` runs (None: receive_rows, interpreted; the
            simulator passes its compiled twin, sim_bridge.world.jit).
        intruders: senders that claimed a receiver's own id (None until one has:
            the agent's per-tick cost is one test while there is no conflict).
    """

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    stamp_s: np.ndarray
    phase: np.ndarray
    flags: np.ndarray
    t_go_s: np.ndarray
    received: np.ndarray
    ignored_old: np.ndarray
    receive_kernel: Callable | None = field(default=None, repr=False, compare=False)
    intruders: Intruders | None = field(default=None, repr=False, compare=False)
    _broadcast_idx: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def unknown(cls, n_receivers: int, n_vehicles: int, receive_kernel: Callable | None = None) -> "SwarmView":
        """A view in which nothing has been heard yet."""
        n, m = n_receivers, n_vehicles
        return cls(np.full((n, m, 3), np.nan), np.full((n, m, 3), np.nan), np.full((n, m), np.nan),
                   np.zeros((n, m), dtype=np.int8), np.zeros((n, m), dtype=np.uint8), np.full((n, m), np.nan),
                   np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64), receive_kernel)

    @property
    def n_receivers(self) -> int:
        return self.stamp_s.shape[0]

    @property
    def n_vehicles(self) -> int:
        return self.stamp_s.shape[1]

    def age_s(self, t_s: float) -> np.ndarray:
        """(n, N) age of every entry at mission time t_s, s; inf where never heard."""
        return np.fmin(t_s - self.stamp_s, np.inf)  # fmin takes the number: NaN (never heard) -> inf

    def assembled(self) -> np.ndarray:
        """(n, N) bool: the FLAG_ASSEMBLED bit of every entry."""
        return (self.flags & FLAG_ASSEMBLED) != 0

    def receive(self, rows: np.ndarray, states: SwarmStates) -> int:
        """Apply states[k] to receiver rows[k], in order; a state older than (or as old as)
        the one held is ignored, so the newest wins whatever the order. Returns how many
        were applied.

        Args:
            rows: (k,) receiver index of each state.
            states: k states; vehicle_id outside [0, N) or a non-finite stamp is
                ignored (a hostile or corrupt message must not index out of range).
        """
        return self._apply(np.ascontiguousarray(rows, np.int64), np.arange(len(states)), states)

    def _apply(self, rows: np.ndarray, src: np.ndarray, states: SwarmStates) -> int:
        f8 = np.float64
        return (self.receive_kernel or receive_rows)(
            rows, src, np.ascontiguousarray(states.vehicle_id, np.int64),
            np.ascontiguousarray(states.stamp_s, f8), np.ascontiguousarray(states.pos_ned_m, f8),
            np.ascontiguousarray(states.vel_ned_mps, f8), np.ascontiguousarray(states.phase, np.int8),
            np.ascontiguousarray(states.flags, np.uint8), np.ascontiguousarray(states.t_go_s, f8),
            self.pos_ned_m, self.vel_ned_mps, self.stamp_s, self.phase, self.flags, self.t_go_s, self.received,
            self.ignored_old)

    def receive_all(self, states: SwarmStates) -> None:
        """Every receiver gets every state (a lossless broadcast); same newest-wins rule.

        Each receiver's own vehicle is written too: the agent takes its own entry
        first hand and never reads it from the view.
        """
        k, n = len(states), self.n_receivers
        if k:
            idx = self._broadcast_idx.get(k)
            if idx is None:  # a handful of sizes recur (the publishers per tick): build each once
                idx = self._broadcast_idx[k] = (np.repeat(np.arange(n), k), np.tile(np.arange(k), n))
            self._apply(idx[0], idx[1], states)

    def receive_one(self, row: int, vehicle_id: int, stamp_s: float, pos_ned_m, vel_ned_mps, phase: int,
                    flags: int, t_go_s: float) -> bool:
        """One state for one receiver (the onboard path: no arrays built). Same rules
        as receive. Returns True if it was applied."""
        if not 0 <= vehicle_id < self.stamp_s.shape[1]:
            return False
        stored = _store_newest(self, (row, vehicle_id), stamp_s, pos_ned_m, vel_ned_mps, phase, flags)
        if stored:
            self.t_go_s[row, vehicle_id] = t_go_s
            self.received[row] += 1
        elif stored is not None:
            self.ignored_old[row] += 1
        return bool(stored)

    def receive_intruder(self, row: int, slot: int, stamp_s: float, pos_ned_m, vel_ned_mps, phase: int,
                         flags: int) -> bool:
        """A state that claims receiver row's own vehicle id but is not its own (an identity
        conflict: the caller decides that, e.g. companion.node.swarmlink), from the sender
        kept in intruder slot `slot`. Counted in intruders.conflicts; stored with the
        rules of receive_one (newest stamp wins). Returns True if it was stored."""
        if self.intruders is None:
            self.intruders = Intruders.none(self.n_receivers)
        it = self.intruders
        it.conflicts[row] += 1
        return 0 <= slot < it.stamp_s.shape[1] and bool(
            _store_newest(it, (row, slot), stamp_s, pos_ned_m, vel_ned_mps, phase, flags))


def _store_newest(into, at: tuple[int, int], stamp_s: float, pos_ned_m, vel_ned_mps, phase: int,
                  flags: int) -> bool | None:
    """Store one state at index `at` of into's (pos_ned_m, vel_ned_mps, stamp_s, phase,
    flags) arrays if its stamp is newer than the one held. Returns True if stored, False
    if not newer, None if it is invalid (non-finite stamp, phase outside the seven)."""
    if not (stamp_s == stamp_s and abs(stamp_s) != np.inf and 0 <= phase < PHASE_COUNT):
        return None
    held = into.stamp_s[at]
    if held == held and stamp_s <= held:
        return False
    into.pos_ned_m[at] = pos_ned_m
    into.vel_ned_mps[at] = vel_ned_mps
    into.stamp_s[at] = stamp_s
    into.phase[at] = phase
    into.flags[at] = flags
    return True


@kernel
def receive_rows(rows, src, ids, stamp, pos, vel, phase, flags, t_go, v_pos, v_vel, v_stamp, v_phase, v_flags,
                 v_t_go, received, ignored_old):
    """The loop of SwarmView.receive: state src[k] (ids[src[k]], stamp[src[k]], ...) to
    receiver rows[k].

    Out-of-range ids, rows or phases and non-finite stamps are skipped; a stamp not newer than
    the one held counts in ignored_old. Returns the number applied.
    """
    n_r, n_v = v_stamp.shape
    applied = 0
    for m in range(rows.shape[0]):
        k = src[m]
        r, v, s = rows[m], ids[k], stamp[k]
        if r < 0 or r >= n_r or v < 0 or v >= n_v or not math.isfinite(s) or phase[k] < 0 \
                or phase[k] >= PHASE_COUNT:
            continue
        held = v_stamp[r, v]
        if held == held and s <= held:
            ignored_old[r] += 1
            continue
        for a in range(3):
            v_pos[r, v, a] = pos[k, a]
            v_vel[r, v, a] = vel[k, a]
        v_stamp[r, v] = s
        v_phase[r, v] = phase[k]
        v_flags[r, v] = flags[k]
        v_t_go[r, v] = t_go[k]
        received[r] += 1
        applied += 1
    return applied


def tick_index(t_us: int, period_us: int) -> int:
    """The number of the control tick at t_us: the nearest multiple of period_us (integer
    µs, so that the agent, the SITL and the headless runner count ticks alike)."""
    return (int(t_us) + period_us // 2) // period_us


def swarm_due(t_us: int, rate_hz: float, vehicle_id, period_us: int):
    """Whether vehicle(s) publish at the control tick t_us: once per 1/rate_hz, each
    vehicle on its own tick offset (vehicle_id modulo the ticks per period), so that the
    swarm does not talk all at once.

    Integer microseconds on purpose: the agent (Unix time from its autopilot), the SITL
    (which gates lockstep on these messages) and the headless runner must decide alike.

    Args:
        t_us: time of the control tick, µs (any epoch shared by the callers).
        rate_hz: publishing rate.
        vehicle_id: int or (k,) ints.
        period_us: control tick period, µs (the setpoint period).
    """
    per = max(1, int(round(1e6 / (rate_hz * period_us))))
    k = tick_index(t_us, period_us)
    if isinstance(vehicle_id, (int, np.integer)):
        return (k + int(vehicle_id)) % per == 0
    return (k + np.asarray(vehicle_id)) % per == 0
