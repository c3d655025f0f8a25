"""Offboard engagement is confirmed by HEARTBEAT, not by the ACK (companion.node.offboard).

PX4 acknowledges DO_SET_MODE before its next 1 Hz HEARTBEAT shows OFFBOARD (up to a
second later, ../shared/notes/mavlink-facts.md). These tests play that exact order on a
real UDP link between a scripted autopilot and the agent's VehicleLink, with the clock
injected: the wait after the ACK is not an exit, a HEARTBEAT in another mode after one
in offboard is, and an ACK whose HEARTBEAT never comes is asked again (not an exit).
"""
from __future__ import annotations

import asyncio
import select
import time

import pytest

from companion.link.dialects import Mode, dialect_named
from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.enums import MavCmd, MavResult, MavState, MavType, MsgId
from companion.link.msgdef import swarmdrop as md
from companion.link.wire import Codec
from companion.mission import GeodeticOrigin
from companion.node.offboard import OFFBOARD_CONFIRM_S, Offboard, OffboardState
from companion.node.vehicle import VehicleLink

SYSID = 1
ORIGIN = GeodeticOrigin(lat_deg=47.397742, lon_deg=8.545594, alt_amsl_m=488.0)


class ScriptedAutopilot:
    """An autopilot endpoint the test speaks for, message by message."""

    def __init__(self, dialect: str):
        self.d = dialect_named(dialect)
        self.ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=True), Codec(md), SYSID, 1)
        self._hb = self.ep.codec.builder(MsgId.HEARTBEAT)
        self._ack = self.ep.codec.builder(MsgId.COMMAND_ACK)

    @property
    def port(self) -> int:
        return self.ep.link.local_port

    def heartbeat(self, mode: Mode) -> None:
        self.ep.queue_fields(MsgId.HEARTBEAT, self._hb(
            type=MavType.MAV_TYPE_QUADROTOR, autopilot=self.d.autopilot_id, base_mode=self.d.base_mode(mode, True),
            custom_mode=self.d.custom_mode(mode), system_status=MavState.MAV_STATE_ACTIVE))
        self.ep.flush()

    def ack(self, command: int, result: int) -> None:
        self.ep.queue_fields(MsgId.COMMAND_ACK, self._ack(command=command, result=result, target_system=SYSID,
                                                          target_component=191))
        self.ep.flush()

    def commands(self, timeout_s: float = 3.0) -> list:
        """The COMMAND_LONGs that have come (waits for at least one)."""
        out: list = []
        deadline = time.monotonic() + timeout_s
        while not out:
            left = deadline - time.monotonic()
            assert left > 0, "no COMMAND_LONG from the agent"
            select.select([self.ep.link.fileno()], [], [], min(left, 0.1))
            out = [m for m, _ in self.ep.poll() if m.get_type() == "COMMAND_LONG"]
        return out

    def close(self) -> None:
        self.ep.close()


class Agent:
    """The agent's side: a VehicleLink fed from its socket, and the Offboard under test."""

    def __init__(self, ap: ScriptedAutopilot):
        self.now = 0.0
        self.ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=("127.0.0.1", ap.port), learn_remote=False),
                              Codec(md), SYSID, 191)
        self.v = VehicleLink(self.ep, SYSID, ORIGIN, "udpout://127.0.0.1")
        self.off = Offboard(self.v, clock=lambda: self.now)
        ap.ep.link.remote = ("127.0.0.1", self.ep.link.local_port)  # the autopilot's telemetry goes here

    async def pump(self, cond, timeout_s: float = 3.0) -> None:
        """Read the link (select with a deadline) and run the loop's callbacks until cond() holds."""
        deadline = time.monotonic() + timeout_s
        while True:
            for msg, _ in self.ep.poll():
                self.v.handle(msg)
            await asyncio.sleep(0)  # (lets a finished command's done-callback run)
            if cond():
                return
            left = deadline - time.monotonic()
            assert left > 0, "timed out waiting on the autopilot link"
            select.select([self.ep.link.fileno()], [], [], min(left, 0.05))

    async def tick(self) -> None:
        """One formation tick: what TickPath does after sending a setpoint; then the loop
        runs once (a request's task starts waiting for its ACK, as between real ticks)."""
        self.off.ensure()
        self.ep.flush()
        await asyncio.sleep(0)

    def close(self) -> None:
        self.ep.close()


async def _engage_px4_order(ap: ScriptedAutopilot, ag: Agent) -> float:
    """Hold, the request, the ACK; then ticks at 50 Hz for 0.98 s while the autopilot's
    HEARTBEAT still shows Hold (one composed before the switch arrives after the ACK); then
    the HEARTBEAT in offboard. Returns the loop time of the HEARTBEAT that confirmed."""
    ap.heartbeat(Mode.HOLD)
    await ag.pump(lambda: ag.v.hb is not None)
    await ag.tick()
    assert ag.off.state is OffboardState.REQUESTING
    (cmd,) = ap.commands()
    assert cmd.command == MavCmd.MAV_CMD_DO_SET_MODE
    assert ap.d.mode_from_set_mode(cmd.param1, cmd.param2, cmd.param3) == Mode.OFFBOARD
    ap.ack(MavCmd.MAV_CMD_DO_SET_MODE, MavResult.MAV_RESULT_ACCEPTED)
    await ag.pump(lambda: ag.off.state is OffboardState.CONFIRMING)
    for k in range(49):  # 0.98 s of ticks with the old HEARTBEAT, and a new one still in Hold
        ag.now += 0.02
        if k == 10:
            ap.heartbeat(Mode.HOLD)
            await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
        await ag.tick()
        assert ag.off.state is OffboardState.CONFIRMING and ag.off.left == 0
    ap.heartbeat(Mode.OFFBOARD)
    await ag.pump(lambda: ag.v.hb is not None and ag.v.ap.mode_of(ag.v.hb.custom_mode) == Mode.OFFBOARD)
    await ag.tick()
    assert ag.off.state is OffboardState.ENGAGED and ag.off.left == 0
    return ag.v.hb_loop_time


@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
def test_ack_before_the_heartbeat_is_not_an_exit_and_a_real_exit_counts_once(dialect):
    async def main() -> None:
        ap = ScriptedAutopilot(dialect)
        ag = Agent(ap)
        try:
            await _engage_px4_order(ap, ag)
            for _ in range(3):  # more HEARTBEATs in offboard, ticks between them: still engaged
                ap.heartbeat(Mode.OFFBOARD)
                await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
                for _ in range(5):
                    ag.now += 0.2
                    await ag.tick()
                assert ag.off.state is OffboardState.ENGAGED and ag.off.left == 0
            ap.heartbeat(Mode.HOLD)  # its failsafe (or a pilot) took the vehicle out: a real exit
            await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
            await ag.tick()
            assert ag.off.state is OffboardState.LOST and ag.off.left == 1
            for _ in range(10):  # the same HEARTBEAT on later ticks is not a second exit, nor is asking again
                ag.now += 0.02
                await ag.tick()
            ap.heartbeat(Mode.HOLD)
            await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
            await ag.tick()
            assert ag.off.state is OffboardState.LOST and ag.off.left == 1
            assert not [m for m, _ in ap.ep.poll() if m.get_type() == "COMMAND_LONG"]  # never switched back
        finally:
            ag.close()
            ap.close()

    asyncio.run(main())


def test_an_accepted_switch_its_heartbeat_never_shows_is_asked_again_not_counted_as_an_exit():
    async def main() -> None:
        ap = ScriptedAutopilot("px4")
        ag = Agent(ap)
        try:
            ap.heartbeat(Mode.HOLD)
            await ag.pump(lambda: ag.v.hb is not None)
            await ag.tick()
            ap.commands()
            ap.ack(MavCmd.MAV_CMD_DO_SET_MODE, MavResult.MAV_RESULT_ACCEPTED)
            await ag.pump(lambda: ag.off.state is OffboardState.CONFIRMING)
            ag.now += OFFBOARD_CONFIRM_S - 0.01  # within the grace: waiting
            await ag.tick()
            assert ag.off.state is OffboardState.CONFIRMING
            ap.heartbeat(Mode.HOLD)
            await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
            ag.now += 0.02  # past it, and the HEARTBEAT still shows Hold: ask again
            await ag.tick()
            assert ag.off.state is OffboardState.REQUESTING and ag.off.left == 0
            (cmd,) = ap.commands()
            assert cmd.command == MavCmd.MAV_CMD_DO_SET_MODE
        finally:
            if ag.off.task is not None:
                ag.off.task.cancel()
            ag.close()
            ap.close()

    asyncio.run(main())


def test_the_grace_outlasts_two_heartbeat_periods():
    """PX4 and ArduPilot send HEARTBEAT at 1 Hz: the next one after the ACK, and one more if
    that one is lost, both come within the grace."""
    assert OFFBOARD_CONFIRM_S > 2 * 1.0



@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
def test_heartbeats_in_one_tick_of_the_loop_clock_are_each_judged(dialect):
    """uvloop's loop clock counts whole milliseconds: two HEARTBEATs taken within one (a
    link that delayed them and delivers them together) must still be judged one by one."""
    async def main() -> None:
        ap = ScriptedAutopilot(dialect)
        ag = Agent(ap)
        try:
            await _engage_px4_order(ap, ag)
            loop = asyncio.get_running_loop()
            frozen = loop.time()
            loop.time = lambda: frozen  # type: ignore[method-assign]  # (the loop's clock stands still)
            ap.heartbeat(Mode.OFFBOARD)
            await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
            await ag.tick()
            assert ag.off.state is OffboardState.ENGAGED
            ap.heartbeat(Mode.HOLD)  # a real exit, stamped with the same loop time
            await ag.pump(lambda: ag.off._judged < ag.v.hb_seq)
            assert ag.v.hb_loop_time == frozen
            await ag.tick()
            assert ag.off.state is OffboardState.LOST and ag.off.left == 1
        finally:
            ag.close()
            ap.close()

    asyncio.run(main())


def test_in_lockstep_the_wait_for_the_heartbeat_runs_on_simulated_time():
    """Outside lockstep the wait runs on the loop's clock; once sends go with a lockstep SITL's
    ticks, on the simulated time of the last tick's end: a lockstep run slower than real time
    must not give up on a HEARTBEAT that PX4 sends once a simulated second (nor a faster one
    wait longer), or two runs would differ."""
    async def body() -> None:
        ap = ScriptedAutopilot("px4")
        ag = Agent(ap)
        try:
            off = Offboard(ag.v)  # (the default clock)
            loop = asyncio.get_running_loop()
            assert abs(off.clock() - loop.time()) < 0.5
            ag.v.tick_aligned = True
            ag.v.tick_done(1234.5)
            assert off.clock() == 1234.5
            off.state, off.accepted_at = OffboardState.CONFIRMING, 1234.5
            ag.v.tick_done(1234.5 + OFFBOARD_CONFIRM_S - 0.02)  # wall time means nothing here
            off.ensure()
            assert off.state is OffboardState.CONFIRMING
        finally:
            ag.close()
            ap.close()

    asyncio.run(body())
