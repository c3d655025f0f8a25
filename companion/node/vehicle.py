"""The agent's link to its own autopilot: telemetry in, commands and setpoints out.

`VehicleLink` keeps the newest of each message the agent uses, picks the autopilot
dialect from the first HEARTBEAT, converts the autopilot's clock to Unix time
(SYSTEM_TIME) and its local frame to the mission frame (GPS_GLOBAL_ORIGIN), and
offers commands and parameter access with timeout and retries (as MAVSDK does:
0.5 s, four sends). Only messages from the target system's autopilot component
(MAV_COMP_ID_AUTOPILOT1) count; anything malformed or non-finite is counted and dropped.

The target system is fixed in advance (the mission's sysid of this vehicle, or an
explicit override), never "the first autopilot heard": on a link that carries several
autopilots (a router) the others are counted in `other_autopilots` and ignored, and
the node refuses to fly when only others are heard (docs/companion.md, "Identity").
"""
from __future__ import annotations

import asyncio
import logging
import math
import struct
from dataclasses import dataclass
from typing import Callable

import numpy as np

from companion.frames import geodetic_to_ned
from companion.link.dialects import AutopilotDialect, HeartbeatState, UnknownAutopilot, dialect_for_autopilot
from companion.link.endpoints import MavEndpoint
from companion.link.enums import (
    MavAutopilot,
    MavCmd,
    MavComponent,
    MavLandedState,
    MavParamType,
    MavResult,
    MavState,
    MavType,
    MsgId,
)
from companion.link.framing import frame_ids
from companion.link.params import decode_param_value, encode_param_value, param_name
from companion.mission import GeodeticOrigin

log = logging.getLogger("swarmdrop.vehicle")

AUTOPILOT = MavComponent.MAV_COMP_ID_AUTOPILOT1
"""The component whose messages count, and that commands and setpoints are for."""
_LPN = MsgId.LOCAL_POSITION_NED  # bound once: handle_raw runs per message at the setpoint rate
RESULT_NAMES = {MavResult.MAV_RESULT_ACCEPTED: "ACCEPTED", MavResult.MAV_RESULT_TEMPORARILY_REJECTED: "TEMPORARILY_REJECTED",
                MavResult.MAV_RESULT_DENIED: "DENIED", MavResult.MAV_RESULT_UNSUPPORTED: "UNSUPPORTED",
                MavResult.MAV_RESULT_FAILED: "FAILED", MavResult.MAV_RESULT_IN_PROGRESS: "IN_PROGRESS",
                6: "CANCELLED"}
"""How a refusal names its MAV_RESULT in CommandError. 6 is MAV_RESULT_CANCELLED, which the
pinned pymavlink's common.xml (hence MavResult) does not have yet; a value without a name
(COMMAND_LONG_ONLY, COMMAND_INT_ONLY) is shown as its number."""
PARAM_INDEX_BY_NAME = -1
"""PARAM_REQUEST_READ.param_index that asks by param_id instead."""


STOP_INTERVAL_US = -1.0
"""MAV_CMD_SET_MESSAGE_INTERVAL's param2 that stops a stream (MESSAGE_INTERVAL: -1 = disabled)."""
TICK_WAIT_S = 60.0
"""Lockstep (VehicleLink.tick_aligned): how long a queued command may wait for the tick that
sends it, wall s (a fleet's clock starts once every agent is up: seconds for 40 processes)."""


class CommandError(RuntimeError):
    """A command was refused, or never acknowledged within its retries."""


@dataclass
class Sample:
    """One timed measurement from the autopilot."""

    time_boot_ms: int
    values: tuple


class VehicleLink:
    """Telemetry cache and command channel of one autopilot.

    Args:
        endpoint: the MAVLink endpoint to the autopilot.
        target_sysid: the autopilot's system id; other autopilots on the link are ignored.
        origin: the mission frame's geodetic origin.
        url: the link as the user gave it (for log lines).
    """

    def __init__(self, endpoint: MavEndpoint, target_sysid: int, origin: GeodeticOrigin, url: str = ""):
        self.ep = endpoint
        self.target_sysid = target_sysid
        self.url = url
        self.other_autopilots: dict[int, int] = {}
        """HEARTBEATs heard from autopilots with another sysid, by sysid (not ours: ignored)."""
        self.other_since = math.inf
        """Loop time at which the first of those was heard."""
        self.mission_origin = origin
        self.dialect: AutopilotDialect | None = None
        self.hb: HeartbeatState | None = None
        self.hb_loop_time = -math.inf
        self.hb_seq = 0
        """HEARTBEATs of our autopilot taken so far (each new one has a higher number, even
        two within one tick of the loop's clock, which is milliseconds on uvloop)."""
        self.landed_state = MavLandedState.MAV_LANDED_STATE_UNDEFINED
        self.lpn: Sample | None = None
        self.att: Sample | None = None
        self.origin_e7: tuple[int, int, int] | None = None
        self.offset_ned_m: np.ndarray | None = None
        """The autopilot's local frame origin in the mission frame (local + offset = mission)."""
        self.offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
        """offset_ned_m as floats (the per-tick path adds it without numpy)."""
        self.launch_ready = False
        """The dialect's launch_ready of the latest HEARTBEAT / EXTENDED_SYS_STATE (cached)."""
        self.unix_offset_us: int | None = None
        """time_unix_usec - time_boot_ms * 1000 from SYSTEM_TIME."""
        self._param_types: dict[str, int] = {}
        self.dropped_nonfinite = 0
        self.foreign = 0
        self._acks: dict[int, asyncio.Future] = {}
        self._param_waiters: dict[str, list[asyncio.Future]] = {}
        self._msg_waiters: dict[int, list[asyncio.Future]] = {}
        self.new_control = False
        """Set when a LOCAL_POSITION_NED newer than the last one arrived."""
        self.tick_aligned = False
        """Lockstep, once the ticks run (TickPath.attach): what this link queues leaves only
        with a tick's messages, before its SWARMDROP_TICK, and the answers to commands and
        requests reach their waiters only at the end of a tick (tick_done). A command
        then reaches the SITL, and the one after it follows its answer, at the same simulated
        tick in every run, however the processes happen to be scheduled (sent between ticks,
        it landed in whichever tick the SITL was at: a ground launch one tick late, now and
        then). Off (the default): sent and answered at once."""
        self._replies: list[tuple[asyncio.Future, object]] = []
        """Answers held for the end of the tick (tick_aligned)."""
        self._tick_waiters: list[asyncio.Future] = []
        """Resolved at the end of the next tick (tick_aligned): what was queued has left, and
        the answers that came before it are with their waiters. One future per waiter, so
        that cancelling one (a task stopped) leaves the others waiting."""
        self._tick_timer: asyncio.TimerHandle | None = None
        """Fails the _tick_waiters if no tick comes for TICK_WAIT_S."""
        self.tick_t_s = -math.inf
        """Simulated time of the last tick's end, s (tick_aligned: exchanges time out on it)."""
        self.tick_wait_s = TICK_WAIT_S
        """Wall time a tick-aligned exchange waits for a tick before it fails (TickPath.attach
        sets it to the node's set-up timeout, at least TICK_WAIT_S)."""
        self.unread: Callable[[int], None] | None = None
        """Told the id of each message from our autopilot that the agent does not read
        (companion.node.streams: --stop-unread-streams); None: nobody asks."""
        codec = endpoint.codec  # named-field builders, resolved once (companion.link.builder)
        self._heartbeat = codec.builder(MsgId.HEARTBEAT)
        self._command_long = codec.builder(MsgId.COMMAND_LONG)
        self._param_request_read = codec.builder(MsgId.PARAM_REQUEST_READ)
        self._param_set = codec.builder(MsgId.PARAM_SET)

    # ---------------------------------------------------------------- inbound
    RAW_IDS = frozenset({MsgId.ATTITUDE_QUATERNION, MsgId.LOCAL_POSITION_NED})
    """ATTITUDE_QUATERNION and LOCAL_POSITION_NED come at the setpoint rate: read raw."""

    def handle_raw(self, msgid: int, sysid: int, compid: int, w: tuple) -> None:
        """A LOCAL_POSITION_NED or ATTITUDE_QUATERNION as wire-order values (Codec.decode_raw)."""
        if compid != AUTOPILOT or sysid != self.target_sysid:
            self.foreign += 1
            return
        if msgid == _LPN:  # time_boot_ms, x, y, z, vx, vy, vz
            if not math.isfinite(w[1] + w[2] + w[3] + w[4] + w[5] + w[6]):
                self.dropped_nonfinite += 1
                return
            if self.lpn is None or w[0] != self.lpn.time_boot_ms:
                self.new_control = True
            self.lpn = Sample(w[0], w[1:7])
        else:  # time_boot_ms, q1..q4, rollspeed, pitchspeed, yawspeed (, repr_offset_q)
            q = w[1:5]
            if not math.isfinite(q[0] + q[1] + q[2] + q[3]) or q[0] * q[0] + q[1] * q[1] + q[2] * q[2] \
                    + q[3] * q[3] < 0.25:
                self.dropped_nonfinite += 1
                return
            self.att = Sample(w[0], q)

    def handle(self, msg) -> None:
        """One received message (anything; wrong sender or bad values are dropped)."""
        src = msg.get_srcSystem()
        t = msg.get_type()
        if msg.get_srcComponent() != AUTOPILOT or src != self.target_sysid:
            self.foreign += 1
            if t == "HEARTBEAT" and msg.get_srcComponent() == AUTOPILOT \
                    and msg.autopilot != MavAutopilot.MAV_AUTOPILOT_INVALID:
                self._other_autopilot(src)
            return
        msgid = msg.get_msgId()
        if msgid not in READ_IDS and self.unread is not None and msgid not in self._msg_waiters:
            self.unread(msgid)
        if msgid in self.RAW_IDS:  # one code path for these, whichever way they were decoded
            self.handle_raw(msgid, src, AUTOPILOT, tuple(getattr(msg, f) for f in msg.ordered_fieldnames))
        else:
            fn = getattr(self, "_on_" + t.lower(), None)
            if fn is not None:
                fn(msg)
        for fut in self._msg_waiters.pop(msgid, []):
            self._answer(fut, msg)

    def _answer(self, fut: asyncio.Future, value) -> None:
        """Hand a waiter its answer: now, or at the end of the tick (tick_aligned)."""
        if self.tick_aligned:
            self._replies.append((fut, value))
        elif not fut.done():
            fut.set_result(value)

    def tick_done(self, t_s: float) -> None:
        """The end of a tick at simulated time t_s, its messages sent (tick_aligned): hand the
        answers that came before it to their waiters, then wake the exchanges waiting for a
        tick's end (_ticks_for), which go on before the next tick is read."""
        self.tick_t_s = t_s
        if self._replies:
            replies, self._replies = self._replies, []
            for fut, value in replies:
                if not fut.done():
                    fut.set_result(value)
        waiters, self._tick_waiters = self._tick_waiters, []
        if self._tick_timer is not None:
            self._tick_timer.cancel()
            self._tick_timer = None
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)

    def _next_tick_end(self) -> asyncio.Future:
        """A future resolved at the end of the next tick (tick_aligned); it fails with
        CommandError if no tick comes for TICK_WAIT_S of wall time (the lockstep clock never
        started). Awaiting it is a single step of the loop."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        self._tick_waiters.append(fut)
        if self._tick_timer is None:
            self._tick_timer = loop.call_later(self.tick_wait_s, self._no_tick)
        return fut

    async def sleep_s(self, duration_s: float) -> None:
        """Wait duration_s of the autopilot's time: simulated, tick by tick, when tick_aligned
        (a retry then comes at the same tick in every run), else the loop's clock.

        Raises:
            CommandError: tick_aligned and no tick for tick_wait_s.
        """
        if self.tick_aligned:
            await self._ticks_for(duration_s)
        else:
            await asyncio.sleep(duration_s)

    async def _ticks_for(self, duration_s: float, answer: asyncio.Future | None = None) -> None:
        """(tick_aligned) Wait for the next tick's end (what is queued has left), then for
        duration_s more of simulated time, or until `answer` is done. Only a tick's end is
        awaited (no timeout wrapper, which takes several steps of the loop to pass an answer
        on): the waiter goes on, and queues what comes next, right after the tick that brought
        its answer, before the next tick is read, in every run.

        Raises:
            CommandError: no tick for tick_wait_s.
        """
        await self._next_tick_end()
        until = self.tick_t_s + duration_s
        while not (answer is not None and answer.done()) and self.tick_t_s < until - 1e-9:
            await self._next_tick_end()

    def _no_tick(self) -> None:
        """tick_wait_s without a tick: fail whoever waits for one."""
        self._tick_timer = None
        waiters, self._tick_waiters = self._tick_waiters, []
        err = CommandError(f"no lockstep tick for {self.tick_wait_s:g} s: nothing can be sent to the autopilot")
        for fut in waiters:
            if not fut.done():
                fut.set_exception(err)

    def _other_autopilot(self, sysid: int) -> None:
        """An autopilot that is not ours spoke on this link (a router, or the wrong port)."""
        if sysid not in self.other_autopilots:  # (bounded: a sysid is one byte)
            log.info("autopilot sysid %d on %s is not this vehicle's (sysid %d): ignored", sysid, self.url,
                     self.target_sysid)
            if not self.other_autopilots:
                self.other_since = asyncio.get_running_loop().time()
            self.other_autopilots[sysid] = 0
        self.other_autopilots[sysid] += 1

    def _on_heartbeat(self, msg) -> None:
        if msg.autopilot == MavAutopilot.MAV_AUTOPILOT_INVALID:  # a GCS or another companion
            return
        if self.dialect is None:
            try:
                self.dialect = dialect_for_autopilot(msg.autopilot)
            except UnknownAutopilot as err:
                log.error("%s", err)
                return
            log.info("autopilot sysid %d on %s speaks %s", msg.get_srcSystem(), self.url, self.dialect.name)
        self.hb = HeartbeatState(msg.custom_mode, msg.base_mode, msg.system_status, self.landed_state)
        self.launch_ready = self.dialect.launch_ready(self.hb)
        self.hb_loop_time = asyncio.get_running_loop().time()
        self.hb_seq += 1

    @property
    def ap(self) -> AutopilotDialect:
        """The autopilot's dialect, once its HEARTBEAT has been heard.

        Raises:
            CommandError: no autopilot heard yet (set-up waits for one before using this).
        """
        if self.dialect is None:
            raise CommandError("no autopilot HEARTBEAT heard yet")
        return self.dialect

    def _on_extended_sys_state(self, msg) -> None:
        self.landed_state = msg.landed_state
        if self.hb is not None:
            self.hb = HeartbeatState(self.hb.custom_mode, self.hb.base_mode, self.hb.system_status, msg.landed_state)
            self.launch_ready = self.dialect is not None and self.dialect.launch_ready(self.hb)

    def _on_gps_global_origin(self, msg) -> None:
        o = (msg.latitude, msg.longitude, msg.altitude)
        if o == self.origin_e7:
            return
        if not (-900_000_000 <= o[0] <= 900_000_000 and -1_800_000_000 <= o[1] <= 1_800_000_000):
            self.dropped_nonfinite += 1
            return
        m = self.mission_origin
        self.offset_ned_m = geodetic_to_ned(o[0] * 1e-7, o[1] * 1e-7, o[2] * 1e-3, m.lat_deg, m.lon_deg, m.alt_amsl_m)
        self.offset = (float(self.offset_ned_m[0]), float(self.offset_ned_m[1]), float(self.offset_ned_m[2]))
        if self.origin_e7 is not None:
            log.warning("EKF origin moved: local positions jump by %s m", np.round(self.offset_ned_m, 3))
        self.origin_e7 = o
        log.info("EKF origin %.7f %.7f %.3f m: local frame at %s m in the mission frame", o[0] * 1e-7, o[1] * 1e-7,
                 o[2] * 1e-3, np.round(self.offset_ned_m, 3).tolist())

    def _on_system_time(self, msg) -> None:
        if msg.time_unix_usec > 0:
            self.unix_offset_us = int(msg.time_unix_usec) - int(msg.time_boot_ms) * 1000

    def _on_command_ack(self, msg) -> None:
        fut = self._acks.get(msg.command)
        if fut is not None and not fut.done() and msg.result != MavResult.MAV_RESULT_IN_PROGRESS:
            self._answer(fut, msg.result)

    def _on_param_value(self, msg) -> None:
        name = param_name(msg.param_id)
        enc = self.dialect.param_encoding if self.dialect is not None else "bytewise"
        try:
            value = decode_param_value(msg.param_value, msg.param_type, enc)
        except (KeyError, ValueError, OverflowError, struct.error):
            self.dropped_nonfinite += 1
            return
        self._param_types[name] = msg.param_type
        for fut in self._param_waiters.pop(name, []):
            self._answer(fut, (value, msg.param_type))

    def _on_statustext(self, msg) -> None:
        log.info("autopilot: %s", msg.text)

    # ---------------------------------------------------------------- derived state
    def unix_us(self, time_boot_ms: int) -> int | None:
        return None if self.unix_offset_us is None else int(time_boot_ms) * 1000 + self.unix_offset_us

    # ---------------------------------------------------------------- outbound
    def send(self, msgid: int, values) -> None:
        """Queue a message for the autopilot (sent at the next flush).

        Args:
            msgid: a MsgId of the dialect.
            values: its field values in declaration order (a builder's output, Codec.builder).
        """
        self.ep.queue_fields(msgid, values)

    def heartbeat(self) -> None:
        """The companion's HEARTBEAT: an onboard controller, no autopilot, active."""
        self.send(MsgId.HEARTBEAT, self._heartbeat(
            type=MavType.MAV_TYPE_ONBOARD_CONTROLLER, autopilot=MavAutopilot.MAV_AUTOPILOT_INVALID, base_mode=0,
            custom_mode=0, system_status=MavState.MAV_STATE_ACTIVE))

    async def _exchange(self, send, waiter: asyncio.Future, what: str, timeout_s: float, retries: int):
        """Send, wait for the answer in waiter, resend on timeout; returns the answer.

        Each try goes the way the link is at that moment: sent at once and waited for on the
        loop's clock, or (tick_aligned, lockstep) sent with the next tick and looked for at
        each tick's end, timeout_s counted in simulated time (_ticks_for). An exchange
        begun before the ticks started (a carrier launch's stream stops) goes on with them.

        Raises:
            CommandError: no answer after `retries` tries, or no lockstep tick to send it.
        """
        for attempt in range(retries):
            send()
            if self.tick_aligned:
                try:
                    await self._ticks_for(timeout_s, waiter)
                except CommandError:
                    waiter.cancel()
                    raise
                if waiter.done():
                    return waiter.result()
            else:
                self.ep.flush()
                try:
                    return await asyncio.wait_for(asyncio.shield(waiter), timeout_s)
                except asyncio.TimeoutError:
                    pass
            log.debug("%s: no answer (attempt %d/%d)", what, attempt + 1, retries)
        waiter.cancel()
        raise CommandError(f"{what}: no answer after {retries} tries of {timeout_s} s")

    def _command_values(self, command: int, params, confirmation: int = 0) -> tuple:
        """COMMAND_LONG values for our autopilot. Params left out are sent as 0.0, as the
        agent always has (not the builder's NaN "use the default")."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        return self._command_long(target_system=self.target_sysid, target_component=AUTOPILOT, command=command,
                                  confirmation=confirmation, param1=p[0], param2=p[1], param3=p[2], param4=p[3],
                                  param5=p[4], param6=p[5], param7=p[6])

    def command_now(self, command: int, params) -> "asyncio.Task[int]":
        """Queue the first COMMAND_LONG now (it leaves with the next flush, in order with
        whatever is already queued) and return a task that waits for the ACK, resending
        as `command` does.

        Args:
            command: a MavCmd. params: up to 7 floats (param1...).
        """
        self.send(MsgId.COMMAND_LONG, self._command_values(command, params))
        return asyncio.ensure_future(self.command(command, params, first_sent=True))

    async def command(self, command: int, params, timeout_s: float = 0.5, retries: int = 4,
                      accept_temporarily_rejected: bool = False, first_sent: bool = False) -> int:
        """COMMAND_LONG with retries; returns the MAV_RESULT.

        Args:
            command: a MavCmd. params: up to 7 floats (param1...; the rest are 0.0).
            timeout_s: wait for the ACK this long per send, s. retries: sends in all.
            accept_temporarily_rejected: MAV_RESULT_TEMPORARILY_REJECTED counts as accepted.
            first_sent: command_now has already queued the first send.
        Raises:
            CommandError: no ACK, or a result other than ACCEPTED.
        """
        fut = asyncio.get_running_loop().create_future()
        self._acks[command] = fut
        sends = [first_sent]

        def send() -> None:
            if sends[0]:
                sends[0] = False
                return
            self.send(MsgId.COMMAND_LONG, self._command_values(command, params))

        try:
            result = await self._exchange(send, fut, f"command {command}", timeout_s, retries)
        finally:
            self._acks.pop(command, None)
        if result != MavResult.MAV_RESULT_ACCEPTED and not (
                accept_temporarily_rejected and result == MavResult.MAV_RESULT_TEMPORARILY_REJECTED):
            raise CommandError(f"command {command} refused: {RESULT_NAMES.get(result, result)}")
        return result

    async def request_message(self, msgid: int, timeout_s: float = 1.0, retries: int = 3):
        """MAV_CMD_REQUEST_MESSAGE until the message arrives; returns it.

        Args:
            msgid: a MsgId. timeout_s: wait this long per request, s. retries: requests in all.
        Raises:
            CommandError: it never came.
        """
        fut = asyncio.get_running_loop().create_future()
        self._msg_waiters.setdefault(msgid, []).append(fut)
        values = self._command_values(MavCmd.MAV_CMD_REQUEST_MESSAGE, [msgid])
        return await self._exchange(lambda: self.send(MsgId.COMMAND_LONG, values), fut, f"message {msgid}",
                                    timeout_s, retries)

    async def set_message_interval(self, msgid: int, interval_s: float) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL: stream msgid (a MsgId) every interval_s seconds.

        Raises:
            CommandError: refused, or not acknowledged.
        """
        await self.command(MavCmd.MAV_CMD_SET_MESSAGE_INTERVAL, [msgid, interval_s * 1e6])

    async def stop_stream(self, msgid: int) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL(msgid, -1): stop streaming msgid on this link.

        Raises:
            CommandError: refused, or not acknowledged.
        """
        await self.command(MavCmd.MAV_CMD_SET_MESSAGE_INTERVAL, [msgid, STOP_INTERVAL_US], timeout_s=0.5, retries=2)

    def unknown_frame(self, msgid: int, frame: bytes) -> None:
        """A frame of a message the lean dialect does not define (MavEndpoint.on_unknown):
        reported as unread if it claims to come from our autopilot."""
        if self.unread is not None and frame_ids(frame) == (self.target_sysid, AUTOPILOT):
            self.unread(msgid)

    async def get_param(self, name: str, timeout_s: float = 1.0, retries: int = 3) -> float:
        """PARAM_REQUEST_READ by name. Raises CommandError."""
        fut = asyncio.get_running_loop().create_future()
        self._param_waiters.setdefault(name, []).append(fut)
        value, _ = await self._exchange(
            lambda: self.send(MsgId.PARAM_REQUEST_READ, self._param_request_read(
                target_system=self.target_sysid, target_component=AUTOPILOT, param_id=name.encode(),
                param_index=PARAM_INDEX_BY_NAME)),
            fut, f"parameter {name}", timeout_s, retries)
        return value

    async def set_param(self, name: str, value: float, timeout_s: float = 1.0, retries: int = 3) -> float:
        """PARAM_SET, then check the echo. Raises CommandError if it does not take."""
        if name not in self._param_types:
            await self.get_param(name)  # learns the type to send
        ptype = self._param_types.get(name, MavParamType.MAV_PARAM_TYPE_REAL32)
        if self.dialect is None:
            raise CommandError(f"PARAM_SET {name}: no autopilot heard yet")
        enc = self.dialect.param_encoding
        wire = encode_param_value(value, ptype, enc)
        fut = asyncio.get_running_loop().create_future()
        self._param_waiters.setdefault(name, []).append(fut)
        got, _ = await self._exchange(
            lambda: self.send(MsgId.PARAM_SET, self._param_set(
                target_system=self.target_sysid, target_component=AUTOPILOT, param_id=name.encode(), param_value=wire,
                param_type=ptype)),
            fut, f"set {name}", timeout_s, retries)
        if abs(got - value) > 1e-6 * max(1.0, abs(value)):
            raise CommandError(f"parameter {name}: set to {value}, autopilot kept {got}")
        return got


READ_IDS = frozenset(VehicleLink.RAW_IDS | {MsgId[name[4:].upper()] for name in vars(VehicleLink)
                                            if name.startswith("_on_")})
"""The messages the agent reads from its autopilot (a `_on_<name>` handler, or RAW_IDS);
a message it waits for (request_message) counts as read while it waits."""
