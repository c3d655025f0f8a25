"""--stop-unread-streams: the agent asks its autopilot to stop the streams it does not read.

The asking (companion.node.streams.UnreadStreams) runs against a fake `stop` coroutine
and a clock the test moves; what counts as unread comes from a real VehicleLink fed with
frames the lean codec encodes (and a pymavlink frame the codec does not define) over
127.0.0.1. Flying with it against the SITL: tests/test_agent_node.py.
"""
from __future__ import annotations

import asyncio
import os
import select
import socket

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.endpoints import MavEndpoint, UdpLink  # noqa: E402
from companion.link.enums import MavAutopilot, MavState, MavType, MsgId  # noqa: E402
from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from companion.mission import GeodeticOrigin  # noqa: E402
from companion.node import streams  # noqa: E402
from companion.node.streams import MAX_ASKS, MAX_IDS, RE_ASK_AFTER_S, UnreadStreams  # noqa: E402
from companion.node.vehicle import READ_IDS, CommandError, VehicleLink  # noqa: E402

ORIGIN = GeodeticOrigin(lat_deg=47.397742, lon_deg=8.545594, alt_amsl_m=488.0)


class Clock:
    """A monotonic clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.t_s = 0.0

    def __call__(self) -> float:
        return self.t_s


class FakeAutopilot:
    """Answers stop requests: accepts, or refuses the ids in `refuse` (CommandError)."""

    def __init__(self, refuse=()) -> None:
        self.asked: list[int] = []
        self.refuse = set(refuse)

    async def stop(self, msgid: int) -> None:
        self.asked.append(msgid)
        if msgid in self.refuse:
            raise CommandError(f"command 511 refused: MAV_RESULT_DENIED ({msgid})")


async def _settle() -> None:
    """Let the worker take everything queued (it only awaits the fake's coroutines)."""
    for _ in range(20):
        await asyncio.sleep(0)  # yielding to the worker task, not waiting for time


def _drive(us: UnreadStreams, steps) -> None:
    """Run the worker while `steps` (callables) feed it, each followed by a settle."""

    async def main() -> None:
        task = asyncio.ensure_future(us.run())
        try:
            for step in steps:
                step()
                await _settle()
        finally:
            task.cancel()

    asyncio.run(main())


def test_each_unread_id_is_asked_once_in_order_and_refusals_are_kept_apart():
    ap, clock = FakeAutopilot(refuse={MsgId.STATUSTEXT + 1000}), Clock()
    us = UnreadStreams(ap.stop, clock)
    ids = [MsgId.ATTITUDE, MsgId.GLOBAL_POSITION_INT, MsgId.STATUSTEXT + 1000, MsgId.SYS_STATUS]
    _drive(us, [lambda: [us.seen(m) for m in ids for _ in range(3)]])  # each arrives three times
    assert ap.asked == ids
    assert us.stopped == [MsgId.ATTITUDE, MsgId.GLOBAL_POSITION_INT, MsgId.SYS_STATUS]
    assert us.refused == [MsgId.STATUSTEXT + 1000]


def test_an_id_that_keeps_coming_is_asked_again_after_the_wait_and_at_most_max_asks_times():
    ap, clock = FakeAutopilot(), Clock()
    us = UnreadStreams(ap.stop, clock)
    steps = [lambda: us.seen(MsgId.ATTITUDE)]
    # in flight when it was stopped: not asked again before RE_ASK_AFTER_S
    steps.append(lambda: (setattr(clock, "t_s", clock.t_s + RE_ASK_AFTER_S - 0.1), us.seen(MsgId.ATTITUDE)))
    for _ in range(2 * MAX_ASKS):  # a ground station keeps turning it back on
        steps.append(lambda: (setattr(clock, "t_s", clock.t_s + RE_ASK_AFTER_S + 0.1), us.seen(MsgId.ATTITUDE)))
    _drive(us, steps)
    assert ap.asked == [MsgId.ATTITUDE] * MAX_ASKS
    assert us.stopped == [MsgId.ATTITUDE]


def test_the_ids_considered_are_bounded():
    ap, clock = FakeAutopilot(), Clock()
    us = UnreadStreams(ap.stop, clock)
    _drive(us, [lambda: [us.seen(1000 + k) for k in range(MAX_IDS + 10)]])
    assert len(ap.asked) == MAX_IDS and us.ignored == 10


def _vehicle() -> tuple[VehicleLink, Codec, list[int]]:
    codec = Codec(swarmdrop)
    ep = MavEndpoint(UdpLink(("127.0.0.1", 0), learn_remote=False), codec, 1, 191)
    v = VehicleLink(ep, 1, ORIGIN)
    told: list[int] = []
    v.unread = told.append
    return v, codec, told


def _message(codec: Codec, msgid: int, sysid: int = 1, compid: int = 1, **fields):
    return codec.decode(codec.encode_fields(msgid, codec.builder(msgid)(**fields), sysid, compid, 0))


def test_the_vehicle_link_reports_only_unread_messages_of_its_own_autopilot():
    v, codec, told = _vehicle()
    assert {MsgId.HEARTBEAT, MsgId.LOCAL_POSITION_NED, MsgId.ATTITUDE_QUATERNION, MsgId.COMMAND_ACK,
            MsgId.EXTENDED_SYS_STATE, MsgId.SYSTEM_TIME, MsgId.GPS_GLOBAL_ORIGIN} <= READ_IDS
    hb = dict(type=MavType.MAV_TYPE_QUADROTOR, autopilot=MavAutopilot.MAV_AUTOPILOT_PX4, base_mode=0, custom_mode=0,
              system_status=MavState.MAV_STATE_STANDBY, mavlink_version=3)
    att = dict(time_boot_ms=10, roll=0.0, pitch=0.0, yaw=0.0, rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0)
    asyncio.run(_feed(v, [_message(codec, MsgId.HEARTBEAT, **hb),                 # read
                          _message(codec, MsgId.ATTITUDE, **att),                  # ours, unread
                          _message(codec, MsgId.ATTITUDE, sysid=2, **att),         # another vehicle's
                          _message(codec, MsgId.ATTITUDE, compid=191, **att)]))    # another component's
    assert told == [MsgId.ATTITUDE]


async def _feed(v: VehicleLink, msgs) -> None:
    for m in msgs:
        v.handle(m)


def test_a_message_the_codec_does_not_define_is_reported_by_its_id_if_it_claims_our_autopilot():
    v, _codec, told = _vehicle()
    ep = v.ep
    ep.on_unknown = v.unknown_frame
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    other = mavlink.MAVLink(None, srcSystem=9, srcComponent=1)
    imu = mavlink.MAVLink_highres_imu_message(1, *([0.0] * 13), 0)  # HIGHRES_IMU (105): not in the lean dialect
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for m in (mav, other):
            tx.sendto(imu.pack(m), ("127.0.0.1", ep.link.local_port))
        got = 0
        while got < 2:
            r, _, _ = select.select([ep.link.fileno()], [], [], 3.0)
            assert r, "the frames did not arrive"
            ep.poll()
            got = ep.unknown
    finally:
        tx.close()
        ep.close()
    assert told == [105]
    assert streams.msg_name(105) == "MSG 105" and streams.msg_name(MsgId.ATTITUDE) == "ATTITUDE"
