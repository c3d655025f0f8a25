"""Lockstep commands go with ticks (companion.node.vehicle.VehicleLink.tick_aligned).

In lockstep the SITL's clock waits for each companion's SWARMDROP_TICK. A command sent
between two ticks landed in whichever tick the SITL happened to be at, and the command
after it followed its answer one tick earlier or later depending on whether the answer
and the next telemetry came in one read or two: a ground launch was a tick late now and
then. Tick-aligned, a command leaves with a tick's messages and its answer reaches the
waiter at the end of a tick. These tests play that order on a real UDP link between a
scripted autopilot and the agent's VehicleLink, the "tick" done by hand.
"""
from __future__ import annotations

import asyncio
import select

import pytest

from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.enums import MavCmd, MavResult, MsgId
from companion.link.msgdef import swarmdrop as md
from companion.link.wire import Codec
from companion.mission import GeodeticOrigin
from companion.node import vehicle as vehicle_mod
from companion.node.vehicle import CommandError, VehicleLink

SYSID = 1
ORIGIN = GeodeticOrigin(lat_deg=47.397742, lon_deg=8.545594, alt_amsl_m=488.0)
ARM = MavCmd.MAV_CMD_COMPONENT_ARM_DISARM


@pytest.fixture
def link():
    ap = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=True), Codec(md), SYSID, 1)
    ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=("127.0.0.1", ap.link.local_port), learn_remote=False),
                     Codec(md), SYSID, 191)
    ap.link.remote = ("127.0.0.1", ep.link.local_port)
    yield ap, VehicleLink(ep, SYSID, ORIGIN, "udpout://127.0.0.1")
    ep.close()
    ap.close()


def _readable(ep: MavEndpoint, timeout_s: float = 0.0) -> bool:
    return bool(select.select([ep.link.fileno()], [], [], timeout_s)[0])


def _commands(ap: MavEndpoint) -> list:
    assert _readable(ap, 3.0), "no COMMAND_LONG reached the autopilot"
    return [m for m, _ in ap.poll() if m.get_type() == "COMMAND_LONG"]


def _ack(ap: MavEndpoint, v: VehicleLink, command: int) -> None:
    """The autopilot acknowledges; the agent reads the ACK (one read, no tick)."""
    ap.queue_fields(MsgId.COMMAND_ACK, ap.codec.builder(MsgId.COMMAND_ACK)(
        command=command, result=MavResult.MAV_RESULT_ACCEPTED, target_system=SYSID, target_component=191))
    ap.flush()
    assert _readable(v.ep, 3.0), "the ACK did not come back"
    for msg, _ in v.ep.poll():
        v.handle(msg)


async def _sent(ap: MavEndpoint, v: VehicleLink) -> list[int]:
    """A tick, a turn of the agent's loop: the commands that tick took to the autopilot."""
    _tick(v)
    await _turns()
    return [c.command for c in _commands(ap)]


async def _accepted(ap: MavEndpoint, v: VehicleLink, task: asyncio.Future, command: int) -> None:
    """The autopilot accepts; the next tick's end hands the answer over: the exchange is done."""
    _ack(ap, v, command)
    _tick(v)
    await _turns()
    assert task.done() and task.result() == MavResult.MAV_RESULT_ACCEPTED


async def _turns(n: int = 5) -> None:
    """Let the loop run the ready tasks (no time passes)."""
    for _ in range(n):
        await asyncio.sleep(0)


def _tick(v: VehicleLink) -> None:
    """What TickPath._tick does with the link in lockstep: send what is queued, then end the
    tick (50 Hz of simulated time)."""
    v.ep.flush()
    v.tick_done(v.tick_t_s + 0.02 if v.tick_t_s > -1.0 else 0.0)


def test_a_tick_aligned_command_leaves_with_a_tick_and_is_answered_at_a_tick_end(link):
    ap, v = link
    v.tick_aligned = True

    async def main():
        task = asyncio.ensure_future(v.command(ARM, [1.0]))
        await _turns()
        assert not _readable(ap) and v.ep.pending == 1  # queued, not sent between ticks
        _tick(v)
        (cmd,) = _commands(ap)
        assert cmd.command == ARM and cmd.param1 == 1.0
        _ack(ap, v, ARM)
        await _turns()
        assert not task.done()  # the answer waits for the end of a tick
        _tick(v)
        await _turns()
        assert task.done() and task.result() == MavResult.MAV_RESULT_ACCEPTED
        assert not _readable(ap)  # answered at the first try: no resend

    asyncio.run(main())


def test_the_next_command_leaves_with_the_tick_after_the_one_that_brought_the_answer(link):
    ap, v = link
    v.tick_aligned = True

    async def launch(log: list) -> None:
        await v.command(ARM, [1.0])
        log.append("armed")
        await v.command(MavCmd.MAV_CMD_NAV_TAKEOFF, [0.0] * 6 + [5.0])

    async def main():
        log: list = []
        task = asyncio.ensure_future(launch(log))
        await _turns()
        _tick(v)  # tick 1: the arm leaves
        assert [c.command for c in _commands(ap)] == [ARM]
        _ack(ap, v, ARM)  # read alone, before tick 2's telemetry
        await _turns()
        assert log == [] and not _readable(ap)
        _tick(v)  # tick 2: the answer reaches the launch at its end
        await _turns()
        assert log == ["armed"] and not _readable(ap)  # the take-off is queued, not sent
        _tick(v)  # tick 3: the take-off leaves
        assert [c.command for c in _commands(ap)] == [MavCmd.MAV_CMD_NAV_TAKEOFF]
        _ack(ap, v, MavCmd.MAV_CMD_NAV_TAKEOFF)
        _tick(v)
        await _turns()
        assert task.done() and task.exception() is None

    asyncio.run(main())


def test_a_tick_aligned_command_is_resent_after_its_timeout_in_simulated_time(link):
    ap, v = link
    v.tick_aligned = True

    async def main():
        task = asyncio.ensure_future(v.command(ARM, [1.0], timeout_s=0.1, retries=2))
        await _turns()
        assert await _sent(ap, v) == [ARM]  # t = 0 (the agent's loop runs between two ticks)
        for _ in range(5):  # t = 0.02 ... 0.1: no answer, no resend yet
            _tick(v)
            await _turns()
            assert not _readable(ap)
        assert await _sent(ap, v) == [ARM]  # t = 0.12: the resend leaves with this tick (queued at 0.1 s)
        await _accepted(ap, v, task, ARM)

    asyncio.run(main())


def test_a_stopped_exchange_leaves_the_others_waiting_for_their_tick(link):
    ap, v = link
    v.tick_aligned = True

    async def main():
        stopped = asyncio.ensure_future(v.command(MavCmd.MAV_CMD_SET_MESSAGE_INTERVAL, [30.0, -1.0]))
        arm = asyncio.ensure_future(v.command(ARM, [1.0]))
        await _turns()
        stopped.cancel()  # (e.g. the stream stopper at exit)
        await _turns()
        assert stopped.cancelled() and not arm.done()
        assert ARM in await _sent(ap, v)
        await _accepted(ap, v, arm, ARM)

    asyncio.run(main())


def test_an_exchange_begun_before_the_ticks_goes_on_with_them(link):
    # (a carrier launch's stream stops may be under way when the agent attaches)
    ap, v = link

    async def main():
        task = asyncio.ensure_future(v.command(ARM, [1.0], timeout_s=0.5, retries=2))
        await _turns()
        assert [c.command for c in _commands(ap)] == [ARM]  # sent at once: no ticks yet
        v.tick_aligned = True  # TickPath.attach
        for _ in range(300):  # its wall-clock try times out (0.5 s): the resend is queued...
            if v.ep.pending:
                break
            await asyncio.sleep(0.01)
        assert v.ep.pending and not _readable(ap)  # ...not sent between ticks
        assert await _sent(ap, v) == [ARM]
        await _accepted(ap, v, task, ARM)

    asyncio.run(main())


def test_a_tick_aligned_pause_counts_simulated_time(link):
    # (a refused ground launch retries after LAUNCH_RETRY_S: the same tick in every run)
    _, v = link
    v.tick_aligned = True

    async def main():
        task = asyncio.ensure_future(v.sleep_s(0.1))
        ended = []
        for _ in range(8):
            await _turns()
            if task.done():
                break
            _tick(v)
            ended.append(v.tick_t_s)
        await _turns()
        assert task.done() and task.exception() is None
        assert ended == pytest.approx([0.0, 0.02, 0.04, 0.06, 0.08, 0.10])  # from the first tick's end, 0.1 s on

    asyncio.run(main())


def test_without_lockstep_a_command_is_sent_and_answered_at_once(link):
    ap, v = link
    assert not v.tick_aligned  # the default: real autopilots, real-time runs

    async def main():
        task = asyncio.ensure_future(v.command(ARM, [1.0]))
        await _turns()
        assert [c.command for c in _commands(ap)] == [ARM] and v.ep.pending == 0
        _ack(ap, v, ARM)
        await _turns()
        assert task.done() and task.result() == MavResult.MAV_RESULT_ACCEPTED

    asyncio.run(main())


def test_a_tick_aligned_command_with_no_tick_to_carry_it_fails_clearly(link):
    ap, v = link
    v.tick_aligned = True
    assert v.tick_wait_s == vehicle_mod.TICK_WAIT_S  # (TickPath.attach: the set-up timeout, at least this)
    v.tick_wait_s = 0.05

    async def main():
        with pytest.raises(CommandError, match="no lockstep tick"):
            await v.command(ARM, [1.0])

    asyncio.run(main())
    assert not _readable(ap)
