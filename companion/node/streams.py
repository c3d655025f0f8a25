"""Stopping the autopilot's streams the agent does not read (`--stop-unread-streams`).

Every datagram from the autopilot wakes the agent, and every message it carries is
received and decoded, read or not. An autopilot streams many messages the agent never
reads (PX4's `onboard` MAVLink mode streams dozens, ATTITUDE at 100 Hz among them; our
SITL sends ATTITUDE, GLOBAL_POSITION_INT, SYS_STATUS, ... to every link). On a link that is
the agent's alone, asking the autopilot to stop them (MAV_CMD_SET_MESSAGE_INTERVAL with
interval -1, which PX4 and ArduPilot apply to the link the command came on) saves those
wake-ups and decodes (docs/companion.md, "Streams").

Off by default: behind a MAVLink router the link's streams are also a ground station's,
and stopping them would freeze its map. The fleet harness turns it on (each SITL companion
port is its agent's alone).

How: the vehicle link reports each message id it receives from its autopilot and does not
read (`seen`); one task asks, one id at a time (a COMMAND_ACK names only the command, so
two SET_MESSAGE_INTERVAL in flight could not be told apart), for that stream to stop. An id
keeps arriving RE_ASK_AFTER_S after a stop was accepted (a ground station's
REQUEST_DATA_STREAM on ArduPilot turns streams back on): it is asked again, up to
MAX_ASKS requests in all. At most MAX_IDS ids are handled: the work stays bounded whatever arrives
(unknown ids cannot be checked: a forged frame costs one command at most).
"""
from __future__ import annotations

import asyncio
import collections
import logging
from typing import Awaitable, Callable

from companion.link.enums import MsgId
from companion.node.vehicle import CommandError

log = logging.getLogger("swarmdrop.agent")

MAX_IDS = 64
"""Message ids the agent asks about at most, per run."""
MAX_ASKS = 3
"""Requests to stop one id at most, per run."""
RE_ASK_AFTER_S = 10.0
"""An id still arriving this long after its stop was accepted is asked again, s (loop time)."""


def msg_name(msgid: int) -> str:
    """The message's name if the lean dialect knows it, else its id ("MSG 105")."""
    try:
        return MsgId(msgid).name
    except ValueError:
        return f"MSG {msgid}"


class UnreadStreams:
    """Asks the autopilot to stop the streams the agent does not read.

    Args:
        stop: sends MAV_CMD_SET_MESSAGE_INTERVAL(msgid, -1) and waits for its ACK
            (VehicleLink.stop_stream); raises CommandError if refused or unanswered.
        clock: monotonic time, s (the event loop's time).

    Attributes:
        stopped: ids whose stop the autopilot accepted, in order.
        refused: ids whose stop it refused or never answered (not streams it can stop:
            replies, or messages it sends on its own schedule).
    """

    def __init__(self, stop: Callable[[int], Awaitable[object]], clock: Callable[[], float]):
        self._stop = stop
        self._clock = clock
        self._asks: dict[int, int] = {}
        """Requests made per id (also: every id ever considered, bounded by MAX_IDS)."""
        self._accepted_at: dict[int, float] = {}
        self._queue: collections.deque[int] = collections.deque()
        self._wake = asyncio.Event()
        self.stopped: list[int] = []
        self.refused: list[int] = []
        self.ignored = 0
        """Ids not considered: MAX_IDS reached."""

    def seen(self, msgid: int) -> None:
        """A message the agent does not read came from its autopilot (cheap: called per such message)."""
        asks = self._asks.get(msgid)
        if asks is None:
            if len(self._asks) >= MAX_IDS:
                self.ignored += 1
                return
            self._asks[msgid] = 0
            self._queue.append(msgid)
            self._wake.set()
            return
        at = self._accepted_at.get(msgid)
        if at is not None and asks < MAX_ASKS and self._clock() - at >= RE_ASK_AFTER_S:
            del self._accepted_at[msgid]  # (queued once: it is back in _accepted_at only when answered)
            self._queue.append(msgid)
            self._wake.set()

    async def run(self) -> None:
        """Work the queue until cancelled."""
        while True:
            await self._wake.wait()
            self._wake.clear()
            done: list[str] = []
            while self._queue:
                msgid = self._queue.popleft()
                self._asks[msgid] += 1
                try:
                    await self._stop(msgid)
                except CommandError as err:
                    log.debug("stream %s not stopped: %s", msg_name(msgid), err)
                    if msgid not in self.refused:
                        self.refused.append(msgid)
                    continue
                self._accepted_at[msgid] = self._clock()
                if msgid not in self.stopped:
                    self.stopped.append(msgid)
                done.append(msg_name(msgid) + ("" if self._asks[msgid] == 1 else " (again)"))
            if done:
                log.info("stopped %d stream(s) the agent does not read on its autopilot link: %s "
                         "(--stop-unread-streams)", len(done), ", ".join(done))
