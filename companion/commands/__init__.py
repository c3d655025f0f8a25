"""Swarm commands, the source side and the shared data model (sans-IO, pure; issue 19).

An operator (a console, a scenario schedule) commands the swarm in flight. Every command
makes a **plan snapshot**, `SwarmPlan`: the whole of what the swarm should do, numbered
(`seq`), applied by every agent at the same mission time (`effective_s`). The newest seq
wins, and a snapshot is complete in itself, so a vehicle that missed commands converges as
soon as it hears the newest one (docs/swarm.md, "Swarm commands").

Modules (everything public is re-exported here: `from companion.commands import X`):
    * plan: `SwarmPlan`, `initial_plan` (seq 0 = the mission's own plan), `quantised`, the
      constants and wire limits.
    * centre: `centre_state`, `centre_ned_m`, `centre_velocity_ned_mps`: where the formation
      centre is under a plan: the ONE function both the source and the agents use; a new
      path starts from the centre's position and velocity (no velocity jump).
    * slots: `plan_offsets_ned_m`, `morph_fraction`, `morph_offsets_ned_m`, `morph_closest_m`
      (each vehicle's slot offset under a plan, the synchronised move from old slots to new
      ones and its exact closest approach); `quintic_move`; `landing_start_offsets_s`
      (layered landings).
    * track: `Track`, `enter`, `initial_track`: a plan in force and every vehicle's reference
      under it (slots, parking, landing; the consensus graph over the vehicles left).
    * book: `PlanBook`: the receiver side, vectorised over receiver rows (plans held, the plan
      in force and a pending one per row, the references the agent flies, what to relay).
    * checks: what the source refuses (separation, morph, ground, geofence, landing columns).
    * source: `CommandSource`: holds the authoritative current plan; one method per command.
    * wire: `plan_messages`, `PlanAssembler`: the plan on the wire (SWARMDROP_PLAN +
      SWARMDROP_SLOTS) and its reassembly on a lossy, reordering, duplicating link.
    * schedule: `CommandEntry`, `check_schedule`, `schedule_problems`: the scenario's
      `commands:` schedule (YAML).

Units: mission NED frame, m, m/s, s of mission time; vehicle ids 0-based (the schedule's
`vehicles` are 1-based, as in metrics.json).

Imports: numpy, pydantic, companion.mission, companion.control.{shapes, assignment},
companion.link (the codec, only when messages are built without one given).
"""
from __future__ import annotations

from companion.commands.book import BookStats, PlanBook, RefGroup
from companion.commands.centre import (
    CentreMotion,
    centre_arrival_s,
    centre_ned_m,
    centre_state,
    centre_velocity_ned_mps,
    plan_centre,
    plan_path,
    plan_tau_s,
    remaining_waypoints,
    waypoints_ahead,
)
from companion.commands.plan import (
    DEFAULT_LEAD_S,
    DEFAULT_MORPH_SPEED_MPS,
    FLAG_ABORT,
    FLAG_EXCLUDED_LAND,
    FLAG_HOLD,
    FLAG_LAND_AT_END,
    HOLD_BRAKE_MPS2,
    KINDS,
    LAND_MARGIN_S,
    LEVEL_TOL_M,
    MAX_PENDING_PLANS,
    MIN_JERK_PEAK_ACCEL,
    MIN_JERK_PEAK_SPEED,
    NO_SLOT_WIRE,
    PLAN_WAYPOINTS_MAX,
    SLOTS_PER_MESSAGE,
    UNKNOWN_GROUND_DEPTH_M,
    URGENT_LEAD_S,
    WAYPOINT_MAX_M,
    WIRE_VEHICLES_MAX,
    CommandError,
    CommandKind,
    Point,
    SwarmPlan,
    blend_accel_mps2,
    hold_brake_mps2,
    initial_plan,
    lead_s,
    quantised,
)
from companion.commands.schedule import CommandEntry, check_schedule, schedule_problems
from companion.commands.slots import (
    landing_layers,
    landing_start_offsets_s,
    morph_closest_m,
    morph_fraction,
    morph_offsets_ned_m,
    plan_offsets_ned_m,
    quintic_move,
)
from companion.commands.source import CommandSource
from companion.commands.track import LAND, PARK, SLOT, Track, consensus_graph, enter, initial_track
from companion.commands.wire import AssemblerStats, PlanAssembler, plan_messages

__all__ = [
    "BookStats", "PlanBook", "RefGroup",
    "AssemblerStats", "CentreMotion", "CommandEntry", "CommandError", "CommandKind", "CommandSource",
    "DEFAULT_LEAD_S", "DEFAULT_MORPH_SPEED_MPS", "FLAG_ABORT", "FLAG_EXCLUDED_LAND", "FLAG_HOLD", "FLAG_LAND_AT_END",
    "HOLD_BRAKE_MPS2", "KINDS", "LAND", "LAND_MARGIN_S", "LEVEL_TOL_M", "MAX_PENDING_PLANS", "MIN_JERK_PEAK_ACCEL",
    "MIN_JERK_PEAK_SPEED", "NO_SLOT_WIRE", "PARK", "PLAN_WAYPOINTS_MAX", "PlanAssembler", "Point", "SLOT",
    "SLOTS_PER_MESSAGE", "SwarmPlan", "Track", "UNKNOWN_GROUND_DEPTH_M", "URGENT_LEAD_S", "WAYPOINT_MAX_M",
    "WIRE_VEHICLES_MAX", "blend_accel_mps2", "centre_arrival_s", "centre_ned_m", "centre_state",
    "centre_velocity_ned_mps", "check_schedule", "consensus_graph", "enter", "hold_brake_mps2", "initial_plan",
    "initial_track", "landing_layers", "landing_start_offsets_s", "lead_s", "morph_closest_m", "morph_fraction",
    "morph_offsets_ned_m", "plan_centre", "plan_messages", "plan_offsets_ned_m", "plan_path", "plan_tau_s",
    "quantised", "quintic_move", "remaining_waypoints", "schedule_problems", "waypoints_ahead",
]
