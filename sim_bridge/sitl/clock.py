"""Who holds the SITL's clock (docs/sitl.md, "Lockstep"): the bookkeeping that decides
whether the next tick may be taken, kept apart from the vehicles and the sockets.

Free-running, the server paces ticks on the wall clock at `time.speed`. In lockstep a
tick waits until every companion that drives the clock has answered the current
control tick (and, at its swarm ticks, reached the radio), and a plain client flying
offboard (MAVSDK) drives it with its setpoints. With `time.start_when_attached` the
clock stays at 0 until that many vehicles' companions have shown up.
"""
from __future__ import annotations

import math
from typing import Callable, Protocol

import numpy as np

from companion.link.dialects import Mode
from sim_bridge.sitl.autopilot import Autopilot
from sim_bridge.sitl.config import TimeConfig


class Radio(Protocol):
    """What the gate reads of the simulated swarm radio (sim_bridge.sitl.medium.Medium)."""

    latest_stamp_us: np.ndarray
    """(N,) Unix µs stamp of each vehicle's newest state heard (-1: none)."""


class LockstepGate:
    """Lockstep bookkeeping of N vehicles.

    Args:
        n: vehicles.
        time_cfg: the SITL's clock settings (lockstep, detach, start_when_attached).
        wall_clock: monotonic seconds (injected).
    """

    def __init__(self, n: int, time_cfg: TimeConfig, wall_clock: Callable[[], float]):
        self.cfg = time_cfg
        self.wall_clock = wall_clock
        self.sp_fresh = np.zeros(n, bool)
        """A setpoint came for the vehicle since the last tick (a plain client's clock)."""
        self.companion_us = np.full(n, -1, dtype=np.int64)
        """Unix µs of the newest control tick each lockstep companion has finished (-1: none yet)."""
        self.companion_wall = np.full(n, -math.inf)
        """Wall time each lockstep companion last answered (a silent one detaches)."""
        self.control_us = np.full(n, -1, dtype=np.int64)
        """Simulated µs of each vehicle's newest control tick (its last LOCAL_POSITION_NED)."""
        self.attached = np.zeros(n, bool)
        """A companion (any client) has talked to the vehicle's endpoint."""

    def note_companion_tick(self, k: int, time_usec: int) -> None:
        """A lockstep companion has finished the control tick at time_usec (Unix µs)."""
        self.companion_us[k] = max(self.companion_us[k], int(time_usec))
        self.companion_wall[k] = self.wall_clock()

    def waiting(self, t_us: int, unix_us: int, autopilots: list[Autopilot], radio: Radio | None,
                publish_ticks: Callable[[], np.ndarray]) -> bool:
        """True while a companion that drives the clock has not answered the current tick.

        Lockstep companions (they send SWARMDROP_TICK) answer every LOCAL_POSITION_NED
        they get; their swarm state for the tick must also have reached the radio when
        one is due. Other clients in Offboard drive the clock with their setpoints.

        Args:
            t_us: simulated time now, µs; unix_us: the same as Unix time, µs.
            publish_ticks: () -> (N,) bool, vehicles at one of their swarm ticks now.
        """
        wall = self.wall_clock()
        detach = self.cfg.lockstep_detach_s
        for k, ap in enumerate(autopilots):
            if self.companion_us[k] >= 0:
                if wall - self.companion_wall[k] > detach:
                    continue  # silent companion (crashed?): it no longer holds the clock
                if self.control_us[k] == t_us and self.companion_us[k] < unix_us:
                    return True
                if radio is not None and radio.latest_stamp_us[k] < unix_us and publish_ticks()[k]:
                    return True
            elif ap.behaviour.offboard_needs_stream and ap.mode == Mode.OFFBOARD and not self.sp_fresh[k]:
                return True  # a plain client (MAVSDK) in Offboard drives the clock with its setpoints
        return False

    def any_driver(self, autopilots: list[Autopilot]) -> bool:
        """Someone drives a lockstep clock now (else it free-runs at `speed`)."""
        wall = self.wall_clock()
        if ((self.companion_us >= 0) & (wall - self.companion_wall <= self.cfg.lockstep_detach_s)).any():
            return True
        return any(ap.behaviour.offboard_needs_stream and ap.mode == Mode.OFFBOARD for ap in autopilots)

    def held(self, ticks: int, fix_t: np.ndarray) -> bool:
        """The clock stays at 0 until start_when_attached vehicles have a companion.

        Args:
            ticks: ticks taken so far; fix_t: (N,) each vehicle's first GNSS fix time, s.
        """
        need = self.cfg.start_when_attached
        if ticks != 0 or need <= 0:
            return False
        if self.cfg.lockstep and not (fix_t > 0).any():
            # A lockstep companion holds the clock only once it has declared itself (its first
            # SWARMDROP_TICK); starting before all have would let the first ticks pass some of
            # them by, and the run would depend on the wall clock. (With delayed GPS fixes the
            # companions' set-up needs simulated time, so there the clock starts on attach.)
            return int((self.companion_us >= 0).sum()) < need
        return int(self.attached.sum()) < need
