"""Typed results of a run: what `compute_metrics` returns and metrics.json holds.

Every section is a dataclass whose field names are the metrics.json keys, so
`RunMetrics.to_json()` is the file and readers in other modules (the console
summary, the fleet harness, the bench, the sweep) get attribute access and a type
checker instead of string keys. Times in s, distances in m, NED frame.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from sim_bridge.reports.launch_so3 import So3Study
from sim_bridge.reports.launch_study import LaunchComparison
from sim_bridge.world.transport import LinkStats


def finite_or_none(x: Any) -> float | None:
    """float(x), or None for None and NaN (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return None if math.isnan(x) else x


@dataclass(frozen=True)
class VehicleSettle:
    """One vehicle's recovery: settle time after release and drift from the release point
    (None when it never stabilised)."""

    vehicle: int
    """1-based, as in the paper's figures."""
    release_s: float
    stabilised: bool
    settle_time_s: float | None = None
    drift_m: float | None = None
    drift_horizontal_m: float | None = None
    altitude_loss_m: float | None = None


@dataclass(frozen=True)
class Stabilisation:
    """Recovery after release, over the vehicles (metrics.json "stabilisation"): settle
    times in s after release, drifts in m from the release point (None: no vehicle
    stabilised), and each vehicle's own figures."""

    all_stabilised: bool
    max_settle_time_s: float | None
    mean_settle_time_s: float | None
    max_drift_m: float | None
    mean_drift_m: float | None
    per_vehicle: list[VehicleSettle]


@dataclass(frozen=True)
class Assembly:
    """When the formation assembled and when transit started, s of mission time (None: it
    never happened)."""

    all_assembled_s: float | None
    assembly_time_after_last_release_s: float | None
    transit_start_s: float | None
    transit_start_spread_s: float | None
    """Latest minus earliest transit start held by the vehicles at the end (0 = agreed)."""


@dataclass(frozen=True)
class Series:
    """A time series as JSON lists: t_s (s) and, per sample, the largest formation error
    (m; None where no vehicle was in formation)."""

    t_s: list[float]
    max_m: list[float | None]


@dataclass(frozen=True)
class FormationDeviation:
    """Largest distance of a formation-phase vehicle from its slot h_i(t), m: where the
    formation is judged (the end, or the end of the hover for a mission that lands), the
    worst during transit, and a ~1 Hz series."""

    final_max_m: float | None
    max_during_transit_m: float | None
    series_1hz: Series


@dataclass(frozen=True)
class Separation:
    """Closest approach between healthy vehicles (centre to centre, m), pairs closer than the
    safety distance, collisions, and how close a vehicle with a failed rotor came to a healthy
    one. Sampled on every recorder update: each agent tick headless (sampled_at_hz is the
    scenario's agent rate), each SITL tick in a fleet run."""

    safety_distance_m: float
    min_pair_distance_m: float | None
    min_pair_time_s: float | None
    min_pair_vehicles: list[int]
    """1-based ids of the closest pair."""
    pairs_below_safety_distance: int
    sampled_at_hz: float
    collision_distance_m: float = 0.2
    collisions: int = 0
    """Pairs of healthy vehicles whose centres came within collision_distance_m."""
    min_failed_distance_m: float | None = None
    """Closest approach of a vehicle with a failed rotor to a healthy one (None: no failure)."""
    failed_contacts: int = 0
    """(failed, healthy) pairs within collision_distance_m."""


@dataclass(frozen=True)
class RotorFailureOutcome:
    """One injected rotor failure: when it came, when the vehicle's own agent declared
    loss of control (phase FAILED), and where the vehicle ended up."""

    vehicle: int
    """1-based."""
    failed_at_s: float
    detected_at_s: float | None
    detection_latency_s: float | None
    final_height_m: float | None
    """Height above the ground at the end of the run (0: it came down)."""


@dataclass(frozen=True)
class ObstacleClearance:
    """Smallest gap between a vehicle centre and an obstacle's surface, m, when (s) and
    whose (1-based); None without obstacles. margin_m is the required clearance."""

    min_clearance_m: float | None
    min_clearance_time_s: float | None
    min_clearance_vehicle: int | None
    margin_m: float


@dataclass(frozen=True)
class MissionOutcome:
    """Whether and when the mission completed: every counted vehicle holding its final
    slot, or, for a mission that lands, every one landed and disarmed."""

    completed: bool
    completion_time_s: float | None
    ended_early: str | None = None
    """"interrupted" (Ctrl-C) or "aborted" (no agent left to fly it): an early end is never a
    completion, whatever was reached before it. None for a run that ran its course."""
    landed_early_s: float | None = None
    """A mission that holds station: when every counted vehicle had landed and disarmed before
    it completed (a swarm LAND it was not written with, e.g. an operator's); the run ended
    there and the mission is not complete. None otherwise."""


@dataclass(frozen=True)
class LandingOutcome:
    """A mission that lands (mission.phases.land_after_hover_s): the formation is judged at
    the end of the hover (FormationDeviation.final_max_m), the landing here."""

    land_start_s: float | None
    """When the first vehicle began to land (the end of the hover)."""
    vehicles_down: int
    """Vehicles landed and disarmed at the end of the run (of those judged)."""
    vehicles_judged: int
    """Vehicles the landing is judged on (healthy, with a live agent)."""
    all_down_s: float | None
    """When the last of them was down (None: not all were)."""
    min_pair_distance_descending_m: float | None
    """Closest approach of two judged vehicles while any was landing."""
    pairs_below_safety_distance_descending: int


@dataclass(frozen=True)
class CommandOutcome:
    """One swarm command (sim_bridge.reports.record.CommandRecord), summarised: how many vehicles
    held it and flew it, and how late after its effective time (applied - effective, s; a
    vehicle that held it in time flies it at its first agent tick from then)."""

    seq: int
    kind: str
    issued_s: float
    effective_s: float | None
    refused: str | None
    vehicles: int
    held: int
    applied: int
    lag_p50_s: float | None
    lag_p95_s: float | None
    lag_max_s: float | None
    within_1s: int
    """Vehicles that flew it no later than 1 s after its effective time (the issue's figure)."""


@dataclass(frozen=True)
class CommandsOutcome:
    """Every swarm command of a run, and the lag of every vehicle over all of them."""

    commands: list[CommandOutcome]
    lag_p50_s: float | None
    lag_p95_s: float | None
    lag_max_s: float | None
    all_applied_within_1s: bool
    """Every vehicle flew every command the source issued within 1 s of its effective time."""
    refused: int
    """Commands the source refused (named in their entries)."""


@dataclass(frozen=True)
class Performance:
    """What the run cost: wall-clock and simulated seconds, their ratio, vehicle physics
    steps (per wall second), and the physics and agent rates it ran at (Hz)."""

    wall_s: float
    sim_s: float
    real_time_factor: float | None
    vehicle_steps: int
    vehicle_steps_per_s: float | None
    physics_rate_hz: float
    agent_rate_hz: float


@dataclass(frozen=True)
class RunMetrics:
    """Everything metrics.json reports of one run (the JSON keys are these field names).

    checks: the acceptance criteria by name (True = passed); `passed` is all of them.
    """

    scenario: str
    seed: int
    n_vehicles: int
    inner_loop_controller: str
    stabilisation: Stabilisation
    assembly: Assembly
    link: LinkStats
    formation_deviation: FormationDeviation
    separation: Separation
    obstacles: ObstacleClearance
    mission: MissionOutcome
    performance: Performance
    rotor_failures: list[RotorFailureOutcome] = field(default_factory=list)
    landing: LandingOutcome | None = None
    """Only for a mission that lands."""
    commands: CommandsOutcome | None = None
    """Only for a run with swarm commands."""
    launch_study: list[LaunchComparison] | None = None
    launch_so3: So3Study | None = None
    """Both controllers over releases at random attitudes (summary in JSON; per draw in launch_so3.csv)."""
    checks: dict[str, bool] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return all(self.checks.values())

    def to_json(self) -> dict:
        """The metrics.json document (launch_study only when one was flown)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "launch_study":
                if value is not None:
                    out[f.name] = {c.key: c.to_json() for c in value}  # as launch_study_json
            elif f.name == "launch_so3":
                if value is not None:
                    out[f.name] = value.summary()
            elif dataclasses.is_dataclass(value):
                out[f.name] = dataclasses.asdict(value)  # type: ignore[arg-type]
            elif f.name == "rotor_failures":
                out[f.name] = [dataclasses.asdict(r) for r in value]
            else:
                out[f.name] = value
        return out
