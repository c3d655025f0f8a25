"""What a simulated vehicle's HEARTBEAT says, and when it says something new.

ArduCopter's set_mode sends a HEARTBEAT at once, right after the command's ACK. PX4's
HEARTBEAT is a 1 Hz stream: a command is acknowledged first and its new mode or arming
shows in the next HEARTBEAT, up to a second later (../shared/notes/mavlink-facts.md) -
the order behind a companion's false "left offboard". Which one a family does is its
`AutopilotBehaviour.heartbeat_on_change`.

For a 1 Hz family the shown state changes only at slots of simulation time, so that the
HEARTBEATs the server also sends on the wall clock say nothing a lockstep run could see
earlier in one run than in another.
"""
from __future__ import annotations

import math
from typing import Callable

HEARTBEAT_PERIOD_S = 1.0
"""The period of a 1 Hz family's HEARTBEAT stream in simulation time, s."""
HEARTBEAT_PHASE_STEP_S = 0.381966
"""Vehicle k's slots fall at k times this (mod the period) past each whole period: real
autopilots, booted at different instants, do not all send together (1 - 1/golden ratio: spread evenly)."""

Fields = tuple[int, int, int]
"""(base_mode, custom_mode, system_status)."""


class HeartbeatView:
    """The HEARTBEAT fields one vehicle shows.

    Args:
        at_once: a change shows at once (ArduPilot); else at the next 1 Hz slot (PX4).
        index: the vehicle's row (its slots' phase). now_s: simulation time now, s.
        live: the state as it is now.
    """

    def __init__(self, at_once: bool, index: int, now_s: float, live: Callable[[], Fields]):
        self.at_once = at_once
        self._live = live
        self._slot_s = now_s + (index * HEARTBEAT_PHASE_STEP_S) % HEARTBEAT_PERIOD_S
        """Simulation time of the next slot, s."""
        self._shown = live()

    def fields(self) -> Fields:
        """What a HEARTBEAT sent now says."""
        return self._live() if self.at_once else self._shown

    def slot(self, now_s: float) -> bool:
        """Called on each autopilot tick: True if a slot came and showed a change (a 1 Hz
        family then sends its next HEARTBEAT now)."""
        if self.at_once or now_s < self._slot_s - 1e-9:
            return False
        self._slot_s += HEARTBEAT_PERIOD_S * (1 + math.floor((now_s - self._slot_s) / HEARTBEAT_PERIOD_S + 1e-9))
        live = self._live()
        if live == self._shown:
            return False
        self._shown = live
        return True
