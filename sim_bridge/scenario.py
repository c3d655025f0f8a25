"""Scenario config: everything `swarmdrop simulate` needs, validated at load."""
from __future__ import annotations

from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.mission import MissionConfig
from companion.params import InnerLoopConfig, VehicleParams
from sim_bridge.carrier import CarrierConfig
from sim_bridge.estimator import EstimatorConfig
from sim_bridge.faults import FaultsConfig, resolve_rotor_failures
from sim_bridge.physics import WindConfig
from sim_bridge.transport import LinkConfig


@dataclass(config=STRICT)
class PhysicsConfig:
    rate_hz: float = Field(default=500.0, ge=500.0)
    """Physics (and inner-loop controller) rate; >= 500 Hz."""
    wind: WindConfig = WindConfig()
    ground_z_m: float | None = 0.0
    """NED z of the ground plane (0 = take-off altitude); None disables ground contact."""


@dataclass(config=STRICT)
class AgentRateConfig:
    rate_hz: float = Field(default=50.0, gt=0)


@dataclass(config=STRICT)
class SafetyConfig:
    separation_m: float = Field(default=1.0, gt=0)
    """Pairs closer than this count as separation violations."""
    obstacle_margin_m: float = Field(default=1.0, ge=0)
    collision_m: float = Field(default=0.2, gt=0)
    """Two vehicles whose centres come closer than this collide: a Crazyflie 2.x spans
    about 0.13 m from prop tip to prop tip, and this adds a third for the props' reach."""


@dataclass(config=STRICT)
class OutputConfig:
    log_rate_hz: float = Field(default=50.0, gt=0)
    figures: bool = True
    snapshot_times_s: tuple[float, ...] = (30.0, 50.0, 70.0, 90.0, 110.0, 130.0, 150.0, 170.0)
    attitude_vehicles: tuple[int, ...] = (1, 15, 27, 40)
    """1-based vehicle numbers for the attitude-recovery figure (paper Fig. 6)."""
    avoidance_vehicles: tuple[int, int] = (8, 17)
    """1-based inclusive range of vehicles for the avoidance figure (paper Fig. 9)."""


@dataclass(config=STRICT)
class LaunchStudyConfig:
    """Geometric vs PID on single launches (paper Fig. 2 vs 3)."""

    enabled: bool = True
    speed_mps: float = Field(default=5.0, ge=0)
    roll_deg: tuple[float, ...] = (90.0, 179.0)
    duration_s: float = Field(default=6.0, gt=0)
    settle_tilt_deg: float = Field(default=5.0, gt=0)
    settle_speed_mps: float = Field(default=0.2, gt=0)
    release_height_m: float = Field(default=30.0, gt=0)
    """Height of every release above the (absent) ground."""
    so3_draws: int = Field(default=1000, ge=0)
    """Releases at attitudes uniform over SO(3), both controllers on the same draws (0 = off)."""
    body_rate_max_radps: float = Field(default=10.0, ge=0)
    """SO(3) draws: body rates uniform in the ball of this radius."""
    sample_period_s: float = Field(default=0.01, gt=0)
    """SO(3) draws: settling and height lost are judged on samples this far apart."""


@dataclass(config=STRICT)
class ScenarioConfig:
    name: str = "scenario"
    seed: int = 0
    duration_s: float = Field(default=300.0, gt=0)
    """Hard stop for the run, s of simulated time."""
    completion_tol_m: float = Field(default=0.05, gt=0)
    """The mission is complete when every vehicle hovers within this of its slot."""
    completion_hold_s: float = Field(default=5.0, ge=0)
    """Keep simulating this long after completion (station-keeping evidence)."""
    vehicle: VehicleParams = VehicleParams()
    inner_loop: InnerLoopConfig = InnerLoopConfig()
    physics: PhysicsConfig = PhysicsConfig()
    agent: AgentRateConfig = AgentRateConfig()
    carrier: CarrierConfig = CarrierConfig()
    mission: MissionConfig = MissionConfig()
    safety: SafetyConfig = SafetyConfig()
    output: OutputConfig = OutputConfig()
    launch_study: LaunchStudyConfig = LaunchStudyConfig()
    link: LinkConfig = LinkConfig()
    """How published neighbour states travel (headless: perfect or lossy)."""
    estimator: EstimatorConfig = EstimatorConfig()
    """GPS/estimator errors and latency on the states the agents receive (headless and SITL)."""
    faults: FaultsConfig = FaultsConfig()
    """Injected rotor failures (headless and SITL; sim_bridge/faults.py)."""

    @model_validator(mode="after")
    def _rates_divide(self):
        ratio = self.physics.rate_hz / self.agent.rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            raise ValueError(
                f"physics.rate_hz ({self.physics.rate_hz}) must be a whole multiple of agent.rate_hz ({self.agent.rate_hz})"
            )
        log_ratio = self.agent.rate_hz / self.output.log_rate_hz
        if abs(log_ratio - round(log_ratio)) > 1e-9 or log_ratio < 1:
            raise ValueError(
                f"agent.rate_hz ({self.agent.rate_hz}) must be a whole multiple of output.log_rate_hz ({self.output.log_rate_hz})"
            )
        if self.safety.collision_m > self.safety.separation_m:
            raise ValueError(f"safety.collision_m ({self.safety.collision_m}) exceeds safety.separation_m "
                             f"({self.safety.separation_m})")
        resolve_rotor_failures(self.faults, self.mission.n_vehicles, self.seed)  # raises what the run would
        if self.physics.wind.active and self.vehicle.drag_coeff_n_per_mps <= 0:
            raise ValueError(
                "physics.wind is set but vehicle.drag_coeff_n_per_mps is 0: wind acts only through drag, so it would "
                "have no effect; set a drag coefficient (a Crazyflie is about 0.0065 N/(m/s), docs/vehicle.md)"
            )
        return self
