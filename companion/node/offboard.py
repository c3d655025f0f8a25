"""The switch to offboard control: PX4 OFFBOARD, ArduPilot GUIDED (Mode.OFFBOARD of the dialect).

The agent asks for it once it flies formation and its setpoints are going out (an
autopilot refuses offboard without a setpoint stream). It asks once at a time, with the
command's own resends (VehicleLink.command_now); after a refusal it asks again on a
later tick. Whether the autopilot is in it is read off its HEARTBEAT, never assumed from
the ACK: PX4 acknowledges the mode change before its next 1 Hz HEARTBEAT shows it (up to
a second later), so an accepted ACK only opens a wait of OFFBOARD_CONFIRM_S for a
HEARTBEAT in offboard. Only a HEARTBEAT in another mode after one in offboard is an exit:
the agent lets it be and counts it (`left`, the stats' left_offboard); whoever took the
vehicle out (its failsafe, a pilot) decides, the agent never switches it back.

    IDLE --ensure--> REQUESTING --ACK accepted--> CONFIRMING --HEARTBEAT: offboard--> ENGAGED
      ^                  |                           |                                 |
      +----refused-------+                           | no HEARTBEAT in offboard        | HEARTBEAT:
      +----------------------------------------------+ within OFFBOARD_CONFIRM_S       | another mode
                                                                                       v
                                                      ENGAGED <--HEARTBEAT: offboard-- LOST

From any state, a new HEARTBEAT in offboard means ENGAGED. Every HEARTBEAT is judged
once, when it is new: a tick that comes between the ACK and the next HEARTBEAT sees the
HEARTBEAT from before the switch, which says nothing about the switch.
"""
from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from enum import Enum, auto

from companion.link.dialects import Mode
from companion.link.enums import MavCmd
from companion.node.vehicle import VehicleLink

log = logging.getLogger("swarmdrop.agent")  # the agent's log lines keep one logger name

OFFBOARD_CONFIRM_S = 3.0
"""After the autopilot accepts the switch (its COMMAND_ACK), how long its HEARTBEAT may take
to show offboard, s; past it the ACK is not believed and the agent asks again. PX4 sends its
HEARTBEAT at 1 Hz and acknowledges the mode change before the next one shows it (up to 1 s
later; ../shared/notes/mavlink-facts.md), so the wait must outlast one heartbeat period plus
one HEARTBEAT lost on the link and the link's delay: three periods. MAVSDK waits the same 3 s
for the same confirmation (it stops streaming when the HEARTBEAT does not show offboard)."""


class OffboardState(Enum):
    """Where the engagement of offboard control stands."""

    IDLE = auto()
    """Not asked yet, or the last request was refused or never confirmed (ask again)."""
    REQUESTING = auto()
    """MAV_CMD_DO_SET_MODE sent, its ACK awaited (with resends)."""
    CONFIRMING = auto()
    """The autopilot accepted the command; its HEARTBEAT has not shown offboard yet
    (for up to OFFBOARD_CONFIRM_S)."""
    ENGAGED = auto()
    """The autopilot's HEARTBEAT shows offboard."""
    LOST = auto()
    """A HEARTBEAT showed another mode after one showed offboard: not asked again."""


class Offboard:
    """The offboard engagement of one autopilot.

    Args:
        vehicle: the autopilot link (its HEARTBEAT has been heard: set-up waited for it).
        clock: monotonic time, s (default: the running event loop's time; in lockstep, once
            sends go with ticks (vehicle.tick_aligned), the simulated time of the last tick's
            end, so that the wait for a HEARTBEAT that PX4 sends once a simulated second ends
            on the same tick in every run, however fast the run goes).
    """

    def __init__(self, vehicle: VehicleLink, clock: Callable[[], float] | None = None):
        self.vehicle = vehicle
        self.clock = clock or self._clock
        self.state = OffboardState.IDLE
        self.task: asyncio.Task | None = None
        """The last request (AgentNode.run cancels it at exit)."""
        self.left = 0
        """Times the autopilot left offboard after its HEARTBEAT had shown it (stats: left_offboard)."""
        self.accepted_at = math.nan
        """clock() when the last request was accepted (NaN: none pending confirmation)."""
        self._judged = 0
        """hb_seq of the newest HEARTBEAT already judged."""

    def _clock(self) -> float:
        v = self.vehicle
        return v.tick_t_s if v.tick_aligned else asyncio.get_running_loop().time()

    def ensure(self) -> None:
        """Called on every tick that sent a formation setpoint: judge a HEARTBEAT that is new
        since the last call, ask for offboard if it is not engaged and nobody took it out,
        and give up on an accepted request its HEARTBEAT never confirmed.

        Raises:
            CommandError: no autopilot HEARTBEAT heard yet (cannot happen after set-up).
        """
        v = self.vehicle
        hb = v.hb
        if hb is not None and v.hb_seq > self._judged:
            self._judged = v.hb_seq
            if v.ap.mode_of(hb.custom_mode) == Mode.OFFBOARD:
                if self.state is not OffboardState.ENGAGED:
                    self._engaged()
                return
            if self.state is OffboardState.ENGAGED:
                self.state = OffboardState.LOST
                self.left += 1
                log.warning("autopilot left %s for %s; not switching back (its failsafe or pilot decides)",
                            self._name(), v.ap.mode_name(hb.custom_mode))
                return
            # CONFIRMING: a HEARTBEAT in the old mode after the ACK was composed before the switch
        if self.state is OffboardState.CONFIRMING and self.clock() - self.accepted_at > OFFBOARD_CONFIRM_S:
            log.warning("autopilot accepted the switch to %s but its HEARTBEAT has not shown it within %g s; "
                        "asking again", self._name(), OFFBOARD_CONFIRM_S)
            self.state = OffboardState.IDLE
        if self.state is OffboardState.IDLE:
            self.state = OffboardState.REQUESTING
            task = v.command_now(MavCmd.MAV_CMD_DO_SET_MODE, v.ap.set_mode_params(Mode.OFFBOARD))
            task.add_done_callback(self._done)
            self.task = task

    def _engaged(self) -> None:
        since = "" if math.isnan(self.accepted_at) else f", {self.clock() - self.accepted_at:.1f} s after its ACK"
        log.info("autopilot in %s (its HEARTBEAT%s)", self._name(), since)
        self.state = OffboardState.ENGAGED
        self.accepted_at = math.nan

    def _name(self) -> str:
        ap = self.vehicle.ap
        return ap.mode_name(ap.custom_mode(Mode.OFFBOARD))

    def _done(self, task: asyncio.Task) -> None:
        """The request ended: accepted (CONFIRMING: wait for the HEARTBEAT), or refused after
        its resends (IDLE: ask again). Ignored if a HEARTBEAT already decided (the state
        moved on meanwhile)."""
        if task.cancelled() or self.state is not OffboardState.REQUESTING:
            return
        err = task.exception()
        if err is not None:
            log.warning("switch to offboard: %s (asking again)", err)
            self.state = OffboardState.IDLE
        else:
            self.state = OffboardState.CONFIRMING
            self.accepted_at = self.clock()
            log.debug("autopilot accepted the switch to %s; waiting for its HEARTBEAT to show it", self._name())
