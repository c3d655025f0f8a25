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
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # launch_study imports the scenario, which imports the transport, which uses these types
    from sim_bridge.launch_so3 import So3Study
    from sim_bridge.launch_study import LaunchComparison


def finite_or_none(x: Any) -> float | None:
    """float(x), or None for None and NaN (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return None if math.isnan(x) else x


@dataclass(frozen=True)
class AgeSummary:
    """Ages of neighbour states when delivered, s (None when nothing was delivered)."""

    count: int = 0
    mean: float | None = None
    p50: float | None = None
    p90: float | None = None
    p99: float | None = None
    max: float | None = None


@dataclass(frozen=True)
class MeanMax:
    mean: float | None = None
    max: float | None = None


@dataclass(frozen=True)
class LinkStats:
    """Neighbour transport of one run: the headless transport or the SITL's radio medium.

    Fields a transport does not measure are None (the headless transport has no bytes,
    the radio medium no configured-but-unused kind).
    """

    copies_sent: int = 0
    """Copies of published states addressed to receivers (one per sender-receiver pair)."""
    copies_delivered: int = 0
    delivered_fraction: float | None = None
    age_at_delivery_s: AgeSummary = field(default_factory=AgeSummary)
    kind: str | None = None
    loss: float | None = None
    delay_s: float | None = None
    jitter_s: float | None = None
    bytes_per_s_per_vehicle: MeanMax | None = None
    states_received: int | None = None
    copies_lost: int | None = None
    bad_frames: int | None = None
    foreign_frames: int | None = None

    @classmethod
    def from_json(cls, d: dict | None) -> "LinkStats":
        """Read the dict run.json stores (older runs may lack fields)."""
        d = dict(d or {})
        d["age_at_delivery_s"] = AgeSummary(**d.get("age_at_delivery_s", {}))
        if d.get("bytes_per_s_per_vehicle") is not None:
            d["bytes_per_s_per_vehicle"] = MeanMax(**d["bytes_per_s_per_vehicle"])
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


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
    all_stabilised: bool
    max_settle_time_s: float | None
    mean_settle_time_s: float | None
    max_drift_m: float | None
    mean_drift_m: float | None
    per_vehicle: list[VehicleSettle]


@dataclass(frozen=True)
class Assembly:
    all_assembled_s: float | None
    assembly_time_after_last_release_s: float | None
    transit_start_s: float | None
    transit_start_spread_s: float | None
    """Latest minus earliest transit start held by the vehicles at the end (0 = agreed)."""


@dataclass(frozen=True)
class Series:
    t_s: list[float]
    max_m: list[float | None]


@dataclass(frozen=True)
class FormationDeviation:
    final_max_m: float | None
    max_during_transit_m: float | None
    series_1hz: Series


@dataclass(frozen=True)
class Separation:
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
    min_clearance_m: float | None
    min_clearance_time_s: float | None
    min_clearance_vehicle: int | None
    margin_m: float


@dataclass(frozen=True)
class MissionOutcome:
    completed: bool
    completion_time_s: float | None


@dataclass(frozen=True)
class Performance:
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
