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
PHASE_COUNT = 7
"""Phases are 0 .. PHASE_COUNT - 1 (companion.agent.Phase; a test keeps them equal). A state
with any other phase is hostile or corrupt and is dropped: the agent indexes by phase."""


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
    """

    vehicle_id: np.ndarray
    stamp_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    att_q_wxyz: np.ndarray
    phase: np.ndarray
    flags: np.ndarray
    t_go_s: np.ndarray

    def __len__(self) -> int:
        return len(self.vehicle_id)

    def select(self, idx) -> "SwarmStates":
        """The rows selected by idx (index array or mask), as a new SwarmStates."""
        return SwarmStates(*(np.asarray(getattr(self, f))[idx] for f in self.__dataclass_fields__))

    def rows(self, sl: slice) -> "SwarmStates":
        """The rows of slice sl, as views of these arrays (no copy)."""
        return SwarmStates(*(getattr(self, f)[sl] for f in self.__dataclass_fields__))


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
            simulator passes its compiled twin, sim_bridge.jit).
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
        if not (0 <= vehicle_id < self.n_vehicles and stamp_s == stamp_s and abs(stamp_s) != np.inf
                and 0 <= phase < PHASE_COUNT):
            return False
        held = self.stamp_s[row, vehicle_id]
        if held == held and stamp_s <= held:
            self.ignored_old[row] += 1
            return False
        self.pos_ned_m[row, vehicle_id] = pos_ned_m
        self.vel_ned_mps[row, vehicle_id] = vel_ned_mps
        self.stamp_s[row, vehicle_id] = stamp_s
        self.phase[row, vehicle_id] = phase
        self.flags[row, vehicle_id] = flags
        self.t_go_s[row, vehicle_id] = t_go_s
        self.received[row] += 1
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
    k = (int(t_us) + period_us // 2) // period_us
    if isinstance(vehicle_id, (int, np.integer)):
        return (k + int(vehicle_id)) % per == 0
    return (k + np.asarray(vehicle_id)) % per == 0
