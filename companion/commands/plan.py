"""The plan snapshot: `SwarmPlan`, its constants and wire limits, and rounding to the wire
(docs/swarm.md, "Swarm commands"). Pure: numpy, companion.mission, companion.control.shapes.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.control.shapes import FormationSpec, spec_from_config
from companion.mission import Mission

CommandKind = Literal["none", "hold", "resume", "goto", "formation", "exclude", "rejoin", "land", "rtl", "abort"]
KINDS: tuple[CommandKind, ...] = ("none", "hold", "resume", "goto", "formation", "exclude", "rejoin", "land", "rtl",
                                  "abort")
"""Command kinds in the order of the wire's SWARMDROP_COMMAND values (none = 0 ... abort = 9)."""

DEFAULT_LEAD_S = 1.0
"""A command's plan applies this long after it is issued, s: time for a lossy link (and the
agents' relays of the newest plan) to deliver it to every vehicle before it is due. On a link
losing 20 % of messages with 100 ms of delay, where every agent relays the newest plan at the
swarm rate (10 Hz), a vehicle that has heard neither the source nor any of k relaying
neighbours by then has missed about 9 (1 + k) copies of each of the plan's two messages:
probability about 2 x 0.2^(9 (1 + k)) (4e-7 with no neighbour at all; docs/swarm.md)."""
URGENT_LEAD_S = 0.3
"""The lead of HOLD, s: it must stop the swarm within 2 s of the operator's press (a centre at
3 m/s: 0.3 s + 3 / HOLD_BRAKE_MPS2 = 1.5 s, and the vehicles' lag). By then a vehicle has had
the source's first copy and one round of relays (probability of missing both about 2 x 0.2^(1 + k));
one that hears it later applies it at once, up to a relay round (0.1-0.2 s) late: its reference
then jumps by at most HOLD_BRAKE_MPS2 x that in velocity (0.5 m/s), which the consensus law absorbs.
ABORT has no lead at all: an agent applies it as soon as it holds it."""
HOLD_BRAKE_MPS2 = 2.5
"""Deceleration of the formation centre when it is held (HOLD, LAND of all), m/s^2; at most
HOLD_BRAKE_SHARE of the mission's consensus_accel_max_mps2 (the consensus law's bound: the rest
of it stays for closing slot errors). 3 m/s stop in 1.25 s over 1.9 m with the default bound
(3 m/s^2: 2.4 m/s^2)."""
HOLD_BRAKE_SHARE = 0.8
DEFAULT_MORPH_SPEED_MPS = 1.0
"""Peak speed of the fastest slot, relative to the formation centre, during a formation
change (m/s): slow enough for the consensus loop to track it inside its linear range."""
MIN_JERK_PEAK_SPEED = 1.875
"""Peak of ds/du of the minimum-jerk profile s(u) = 10u^3 - 15u^4 + 6u^5."""
MIN_JERK_PEAK_ACCEL = 10.0 / math.sqrt(3.0)
"""Peak of |d2s/du2| of the same profile (5.7735)."""
LAND_MARGIN_S = 1.0
"""A landing vehicle waits this long beyond the time a vehicle below it needs to reach the
ground (touch-down and land detection), s."""
LEVEL_TOL_M = 0.25
"""Slots whose heights differ by less than this are level: they descend together."""
UNKNOWN_GROUND_DEPTH_M = 100.0
"""With the ground unknown (mission.ground_z_m None), landings are timed as if it lay this
far below the lowest landing point (as the ghost columns of docs/swarm.md)."""
PLAN_WAYPOINTS_MAX = 8
"""Centre waypoints one SWARMDROP_PLAN carries (companion/link/msgdef/generate.py)."""
SLOTS_PER_MESSAGE = 200
"""Vehicles one SWARMDROP_SLOTS carries (companion/link/msgdef/generate.py)."""
WIRE_VEHICLES_MAX = 255
"""Vehicles a plan can carry on the wire (uint8 n_vehicles; slot 255 means none)."""
NO_SLOT_WIRE = 255
WAYPOINT_MAX_M = 1.0e6
"""A commanded waypoint coordinate beyond this (m) is refused."""
MAX_PENDING_PLANS = 4
"""Plans a PlanAssembler reassembles at once (newer than the newest complete one)."""

FLAG_HOLD = 1
FLAG_LAND_AT_END = 2
FLAG_ABORT = 4
FLAG_EXCLUDED_LAND = 8
_FLAGS_KNOWN = FLAG_HOLD | FLAG_LAND_AT_END | FLAG_ABORT | FLAG_EXCLUDED_LAND

Point = tuple[float, float, float]


class CommandError(ValueError):
    """A command cannot be made into a plan (bad parameters, or not possible now: e.g.
    RESUME with nothing held, any command after ABORT). The current plan is unchanged."""



@dataclass(frozen=True)
class SwarmPlan:
    """A plan snapshot: the whole of what the swarm does from `effective_s` on.

    Attributes:
        seq: plan number, increasing; 0 = the mission's own plan (never sent).
        kind: the command that made it (KINDS).
        effective_s: mission time at which every agent applies it, s.
        waypoints_ned_m: the formation centre's path: the first is the centre at
            effective_s, the rest are flown in order at speed_mps (rest-to-rest legs with
            the mission's transit_accel_mps2 and waypoint_dwell_s). EMPTY = the mission's own
            path, flown from the transit start t_go the swarm agrees (as seq 0).
        speed_mps: centre speed along waypoints_ned_m.
        hold: the centre stays at waypoints_ned_m[0].
        land_at_end: every vehicle with a slot lands when the centre reaches the last
            waypoint (RTL).
        formation: shape, size, rotation (companion.control.shapes).
        morph_s: the move from the slots flown before effective_s to this plan's slots
            takes this long (minimum-jerk, the same profile for every vehicle), s.
        slot_of: one entry per vehicle: its slot index in offsets_for(formation, n_slots),
            or -1 (no slot: excluded, or landing since an earlier plan).
        excluded: vehicles out of consensus (they hold where they are, or land).
        excluded_land: set when every excluded vehicle also lands (excluded <= landing).
        landing: vehicles that land. Those with a slot land at it, staggered
            (landing_schedule); those without land where they are.
        abort: every agent hands its vehicle to the autopilot's Hold/Loiter and commands nothing.
        start_velocity_ned_mps: the centre's velocity at effective_s (plans with waypoints):
            the centre's path blends from it (companion.commands.centre), so that no command
            makes its velocity jump. Zero for plans that follow the mission's path.
    """

    seq: int
    kind: CommandKind
    effective_s: float
    waypoints_ned_m: tuple[Point, ...]
    speed_mps: float
    hold: bool
    land_at_end: bool
    formation: FormationSpec
    morph_s: float
    slot_of: tuple[int, ...]
    excluded: frozenset[int] = frozenset()
    excluded_land: bool = False
    landing: frozenset[int] = frozenset()
    abort: bool = False
    start_velocity_ned_mps: Point = (0.0, 0.0, 0.0)

    @property
    def n_vehicles(self) -> int:
        """Vehicles in the mission (the slot table's length)."""
        return len(self.slot_of)

    @property
    def n_slots(self) -> int:
        """Slots of the formation: the vehicles that hold one."""
        return sum(1 for s in self.slot_of if s >= 0)

    @property
    def follows_mission(self) -> bool:
        """The centre flies the mission's own path (no waypoints of its own)."""
        return not self.waypoints_ned_m


def initial_plan(mission: Mission, n_vehicles: int | None = None) -> SwarmPlan:
    """Seq 0: the mission's own plan (its path from t_go, its formation, vehicle i in slot i).

    Its slot offsets equal `mission.offsets_ned_m` exactly for n_vehicles = mission.n.
    """
    n = mission.n if n_vehicles is None else int(n_vehicles)
    return SwarmPlan(seq=0, kind="none", effective_s=0.0, waypoints_ned_m=(), speed_mps=mission.cfg.transit_speed_mps,
                     hold=False, land_at_end=False, formation=spec_from_config(mission.cfg.formation), morph_s=0.0,
                     slot_of=tuple(range(n)))


def _f32(x: float) -> float:
    """x as the wire's float32 carries it."""
    return float(np.float32(x))


def _usec(t_s: float) -> float:
    """t_s rounded to the wire's microseconds."""
    return round(t_s * 1e6) / 1e6


def quantised(plan: SwarmPlan) -> SwarmPlan:
    """The plan with every number as the wire carries it (float32 fields, microsecond
    effective time), so that what the source holds equals what every receiver assembles."""
    return dataclasses.replace(
        plan, effective_s=_usec(plan.effective_s),
        waypoints_ned_m=tuple((_f32(p[0]), _f32(p[1]), _f32(p[2])) for p in plan.waypoints_ned_m),
        speed_mps=_f32(plan.speed_mps), morph_s=_f32(plan.morph_s),
        start_velocity_ned_mps=tuple(_f32(x) for x in plan.start_velocity_ned_mps),  # type: ignore[arg-type]
        formation=dataclasses.replace(plan.formation, radius_m=_f32(plan.formation.radius_m),
                                      spacing_m=_f32(plan.formation.spacing_m),
                                      rotation_rad=_f32(plan.formation.rotation_rad)))



def lead_s(kind: CommandKind, normal_s: float = DEFAULT_LEAD_S, urgent_s: float = URGENT_LEAD_S) -> float:
    """How long after its issue a command's plan applies, s: none for ABORT, urgent_s for HOLD,
    normal_s for the others (DEFAULT_LEAD_S, URGENT_LEAD_S)."""
    return 0.0 if kind == "abort" else urgent_s if kind == "hold" else normal_s


def hold_brake_mps2(mission: Mission) -> float:
    """Deceleration of a held centre under this mission, m/s^2: HOLD_BRAKE_MPS2, at most
    HOLD_BRAKE_SHARE of mission.consensus_accel_max_mps2."""
    return min(HOLD_BRAKE_MPS2, HOLD_BRAKE_SHARE * mission.cfg.consensus_accel_max_mps2)


def blend_accel_mps2(plan: SwarmPlan, mission: Mission) -> float:
    """How fast a plan's centre sheds its start velocity, m/s^2: a held centre brakes at
    hold_brake_mps2; any other path blends at the mission's transit_accel_mps2, the rate its own
    legs accelerate at, so that a plan that keeps a path flown at cruise keeps its speed."""
    return hold_brake_mps2(mission) if plan.hold else mission.cfg.transit_accel_mps2
