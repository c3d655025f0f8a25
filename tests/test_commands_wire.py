"""Swarm commands on the wire (companion/commands/wire.py): SWARMDROP_PLAN + SWARMDROP_SLOTS,
byte-exact round trips through the real codec, the start_velocity extension (old frames stay
byte-identical), and reassembly on a link that loses, reorders, duplicates and lies."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest

from companion.commands import (
    FLAG_ABORT,
    FLAG_EXCLUDED_LAND,
    FLAG_HOLD,
    FLAG_LAND_AT_END,
    KINDS,
    PLAN_WAYPOINTS_MAX,
    SLOTS_PER_MESSAGE,
    CommandSource,
    PlanAssembler,
    SwarmPlan,
    initial_plan,
    plan_messages,
    plan_offsets_ned_m,
)
from companion.control.shapes import SHAPES, FormationSpec
from companion.link.enums import MsgId
from companion.link.msgdef import generate
from companion.link.msgdef import swarmdrop as sd
from companion.link.wire import Codec
from companion.mission import FormationConfig, Mission, MissionConfig

EPOCH = 1_767_225_600.0  # 2026-01-01 00:00 UTC, an hour boundary as the agents use
CODEC = Codec(sd)
WPS = ((100.0, 0.0, -40.0), (300.0, 0.0, -40.0), (300.0, 200.0, -50.0), (100.0, 200.0, -50.0))


def _mission(n: int = 40, **kw) -> Mission:
    kw.setdefault("waypoints_ned_m", WPS)
    return Mission(MissionConfig(n_vehicles=n, **kw))


@pytest.fixture(scope="module")
def mission() -> Mission:
    return _mission()


def _frames(plan: SwarmPlan, epoch: float = EPOCH) -> list[bytes]:
    return [CODEC.encode_fields(msgid, vals, 255, 190, k) for k, (msgid, vals) in enumerate(plan_messages(plan, epoch))]


def _assemble(frames, asm: PlanAssembler) -> SwarmPlan | None:
    out = None
    for f in frames:
        got = asm.feed(CODEC.decode(f))
        out = got or out
    return out


def _session(mission: Mission) -> list[SwarmPlan]:
    """A run of every command kind, as an operator might issue them (in transit: start
    velocities on the wire); a short one past 60 vehicles (the wire is what is tested)."""
    src = CommandSource(mission)
    src.set_t_go(60.0)
    if mission.n > 60:
        return [src.hold(70.0), src.formation(72.0, FormationSpec("grid")), src.exclude(100.0, [3, mission.n - 1]),
                src.land(125.0, [5, 6]), src.abort(130.0)]
    return [src.hold(70.0), src.formation(72.0, FormationSpec("wedge", spacing_m=6.0)), src.resume(90.0),
            src.exclude(100.0, [3, 17]), src.rejoin(120.0, [17]), src.land(125.0, [5, 6]),
            src.formation(130.0, FormationSpec("shell", radius_m=8.0)),
            src.goto(140.0, [(0.0, 0.0, -45.0)], 5.0),
            src.exclude(150.0, [9], land=True), src.rtl(170.0), src.land(400.0), src.abort(420.0)]


# ----------------------------------------------------------------------------- the wire
def test_wire_tables_match_the_dialect():
    assert [getattr(sd, f"SWARMDROP_COMMAND_{k.upper()}") for k in KINDS] == list(range(len(KINDS)))
    assert [getattr(sd, f"SWARMDROP_SHAPE_{s.upper()}") for s in SHAPES] == list(range(len(SHAPES)))
    assert (FLAG_HOLD, FLAG_LAND_AT_END, FLAG_ABORT, FLAG_EXCLUDED_LAND) == (
        sd.SWARMDROP_PLAN_FLAGS_HOLD, sd.SWARMDROP_PLAN_FLAGS_LAND_AT_END, sd.SWARMDROP_PLAN_FLAGS_ABORT,
        sd.SWARMDROP_PLAN_FLAGS_EXCLUDED_LAND)
    assert (PLAN_WAYPOINTS_MAX, SLOTS_PER_MESSAGE) == (generate.PLAN_WAYPOINTS_MAX, generate.SLOTS_PER_MESSAGE)


@pytest.mark.parametrize("n", [1, 7, 40, 200, 201, 250, 255])
def test_round_trip_is_exact(n):
    m = _mission(n, formation=FormationConfig(radius_m=max(40.0, n / 2.0)))
    plans = _session(m) if n >= 20 else [CommandSource(m).hold(3.0)]
    for p in plans:
        frames = _frames(p)
        assert len(frames) == 1 + math.ceil(n / SLOTS_PER_MESSAGE)
        got = _assemble(frames, PlanAssembler.for_mission(m, EPOCH))
        assert got == p
        assert _frames(got) == frames  # a relay re-encodes the same bytes
        assert np.array_equal(plan_offsets_ned_m(got), plan_offsets_ned_m(p), equal_nan=True)


def test_start_velocity_is_an_extension_old_frames_stay_byte_identical(mission):
    """SWARMDROP_PLAN.start_velocity is a MAVLink 2 extension: CRC_EXTRA is unchanged (20),
    a plan starting from rest encodes to the very bytes of the message without it (the zeros
    are truncated), a frame from an older sender assembles with a zero start velocity, and a
    moving start crosses the wire exactly (float32)."""
    cls = sd.MAVLink_swarmdrop_plan_message
    assert cls.crc_extra == 20 and cls.fieldnames[-2:] == ["n_vehicles", "start_velocity"]
    src = CommandSource(mission)
    src.set_t_go(60.0)
    resting = src.formation(10.0, FormationSpec("grid", spacing_m=6.0))
    moving = src.hold(100.0)
    assert resting.start_velocity_ned_mps == (0.0, 0.0, 0.0) and np.linalg.norm(moving.start_velocity_ned_mps) > 3.9
    (pid, values), _ = plan_messages(resting, EPOCH)
    base = CODEC.encode_fields(pid, values[:-1], 255, 190, 0)  # every field but the extension
    assert CODEC.encode_fields(pid, values, 255, 190, 0) == base
    assert len(base) == 10 + 197 + 2  # MAVLink 2 header, the base payload, CRC
    asm = PlanAssembler.for_mission(mission, EPOCH)
    assert _assemble([base] + _frames(resting)[1:], asm) == resting
    got = _assemble(_frames(moving), PlanAssembler.for_mission(mission, EPOCH))
    assert got == moving and got.start_velocity_ned_mps == moving.start_velocity_ned_mps


def test_plan_messages_refuse_what_the_wire_cannot_carry(mission):
    with pytest.raises(ValueError):
        plan_messages(initial_plan(mission), EPOCH)
    big = CommandSource(_mission(256, formation=FormationConfig(radius_m=100.0))).hold(1.0)
    with pytest.raises(ValueError, match="at most 255"):
        plan_messages(big, EPOCH)


def test_reordered_duplicated_messages_give_the_newest_plan(mission):
    plans = _session(mission)
    frames = [f for p in plans for f in _frames(p)]
    rng = random.Random(4)
    for _ in range(20):
        shuffled = frames * 2
        rng.shuffle(shuffled)
        asm = PlanAssembler.for_mission(mission, EPOCH)
        seen = []
        for f in shuffled:
            got = asm.feed(CODEC.decode(f))
            if got is not None:
                seen.append(got.seq)
                assert got == plans[got.seq - 1]
        assert seen == sorted(seen) and len(set(seen)) == len(seen)  # never an older one after a newer one
        assert asm.newest == plans[-1]
        assert asm.stats.duplicates + asm.stats.stale > 0
        assert len(asm.pending_seqs) <= asm.max_pending


def test_a_vehicle_that_missed_commands_converges_on_the_newest(mission):
    plans = _session(mission)
    asm = PlanAssembler.for_mission(mission, EPOCH)
    assert _assemble(_frames(plans[-3]), asm) == plans[-3]
    for f in _frames(plans[2]):  # an old plan, relayed late
        assert asm.feed(CODEC.decode(f)) is None
    assert asm.newest == plans[-3] and asm.stats.stale == len(_frames(plans[2]))


def test_loss_of_a_chunk_holds_the_plan_back_until_it_comes():
    m = _mission(250, formation=FormationConfig(radius_m=125.0))
    p = CommandSource(m).formation(1.0, FormationSpec("grid", spacing_m=5.0))
    head, first, second = _frames(p)
    asm = PlanAssembler.for_mission(m, EPOCH)
    assert asm.feed(CODEC.decode(second)) is None
    assert asm.feed(CODEC.decode(head)) is None
    assert asm.pending_seqs == (1,)
    assert asm.feed(CODEC.decode(first)) == p
    assert asm.pending_seqs == ()


def test_memory_stays_bounded_under_a_flood_of_new_seqs(mission):
    asm = PlanAssembler.for_mission(mission, EPOCH)
    p = CommandSource(mission).hold(1.0)
    head = plan_messages(p, EPOCH)[0]
    build = CODEC.builder(MsgId.SWARMDROP_PLAN)
    values = dict(zip(build.fields, head[1]))
    for seq in range(1, 1000):
        asm.feed(CODEC.decode(CODEC.encode_fields(MsgId.SWARMDROP_PLAN, build(**{**values, "seq": seq}), 1, 1, 0)))
    assert len(asm.pending_seqs) <= asm.max_pending and asm.stats.evicted > 0
    assert asm.pending_seqs == tuple(range(996, 1000))


def _hostile(plan_values: dict, slot_values: list[dict]) -> list[bytes]:
    build_p = CODEC.builder(MsgId.SWARMDROP_PLAN)
    build_s = CODEC.builder(MsgId.SWARMDROP_SLOTS)
    return [CODEC.encode_fields(MsgId.SWARMDROP_PLAN, build_p(**plan_values), 9, 9, 0)] + \
        [CODEC.encode_fields(MsgId.SWARMDROP_SLOTS, build_s(**v), 9, 9, 0) for v in slot_values]


@pytest.mark.parametrize("change,why", [
    ({"waypoints": (math.nan,) + (0.0,) * 23}, "non-finite"),
    ({"speed": math.inf}, "non-finite"),
    ({"radius": 0.0}, "must be > 0"),
    ({"morph_time": -1.0}, "morph"),
    ({"start_velocity": (0.0, math.nan, 0.0)}, "start velocity"),
    ({"n_waypoints": 9}, "waypoints"),
    ({"kind": 10}, "unknown kind"),
    ({"shape": 5}, "unknown shape"),
    ({"flags": 16}, "unknown flag"),
    ({"n_vehicles": 41}, "vehicles"),
    ({"seq": 0}, "seq 0"),
    ({"excluded": (0,) * 5 + (1,) + (0,) * 26}, "bits beyond"),  # vehicle 40 of 40
    ({"landing": (0,) * 31 + (128,)}, "bits beyond"),
    ({"flags": FLAG_HOLD, "n_waypoints": 0}, "hold without"),
    ({"excluded": (1,) + (0,) * 31}, "excluded vehicle holds a slot"),
])
def test_hostile_plans_are_rejected_and_counted(mission, change, why):
    p = CommandSource(mission).hold(1.0)
    (pid, pv), (sid, sv) = plan_messages(p, EPOCH)
    values = dict(zip(CODEC.builder(pid).fields, pv))
    slots = dict(zip(CODEC.builder(sid).fields, sv))
    if "seq" in change:
        slots["seq"] = change["seq"]
    asm = PlanAssembler.for_mission(mission, EPOCH)
    assert _assemble(_hostile({**values, **change}, [slots]), asm) is None
    assert asm.stats.rejected >= 1 and why in asm.stats.last_reject
    assert asm.newest is None and asm.newest_seq == 0
    assert _assemble(_frames(p), asm) == p  # the honest plan still goes through


@pytest.mark.parametrize("change,why", [
    ({"first": 1}, "tile"),
    ({"count": 39}, "tile"),
    ({"first": 200, "count": 40}, "tile"),
    ({"slot": (40,) + tuple(range(1, 40)) + (0,) * 160}, "outside"),
    ({"slot": (0, 0) + tuple(range(2, 40)) + (0,) * 160}, "permutation"),
    ({"slot": (1,) + tuple(range(1, 40)) + (0,) * 160}, "permutation"),
])
def test_hostile_slot_tables_are_rejected_and_counted(mission, change, why):
    p = CommandSource(mission).hold(1.0)
    (pid, pv), (sid, sv) = plan_messages(p, EPOCH)
    values = dict(zip(CODEC.builder(pid).fields, pv))
    slots = dict(zip(CODEC.builder(sid).fields, sv))
    asm = PlanAssembler.for_mission(mission, EPOCH)
    assert _assemble(_hostile(values, [{**slots, **change}]), asm) is None
    assert asm.stats.rejected >= 1 and why in asm.stats.last_reject


def test_conflicting_copies_keep_the_first(mission):
    p = CommandSource(mission).hold(1.0)
    (pid, pv), (sid, sv) = plan_messages(p, EPOCH)
    values = dict(zip(CODEC.builder(pid).fields, pv))
    asm = PlanAssembler.for_mission(mission, EPOCH)
    asm.feed(CODEC.decode(_hostile({**values, "speed": 9.0}, [])[0]))
    asm.feed(CODEC.decode(_frames(p)[0]))
    assert asm.stats.conflicts == 1
    got = asm.feed(CODEC.decode(_frames(p)[1]))
    assert got is not None and got.speed_mps == 9.0  # (unsigned links cannot tell who is right: use signing)


def test_other_messages_and_garbage_objects_are_ignored_or_rejected(mission):
    asm = PlanAssembler.for_mission(mission, EPOCH)
    assert asm.feed(object()) is None and asm.stats.rejected == 0

    class Half:
        id = int(MsgId.SWARMDROP_PLAN)
        seq = 3
    assert asm.feed(Half()) is None and asm.stats.rejected == 1
    assert asm.feed_fields(int(MsgId.SWARMDROP_SLOTS), {"seq": "x"}) is None and asm.stats.rejected == 2
