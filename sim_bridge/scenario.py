"""Scenario config: everything a run flies by, validated at load (`load_scenario`), and the
checks that a validated scenario can be flown by a given runner (`scenario_findings`)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator
from pydantic.dataclasses import dataclass

from companion.commands import CommandEntry, check_schedule
from companion.config import (
    CONFIG_VERSION,
    SEED_MAX,
    STRICT,
    ConfigError,
    check_version,
    mission_file_data,
    read_yaml,
    require_mission,
    validate,
)
from companion.control.formation import FormationUnstableError
from companion.feasibility import MAVLINK_MAX_VEHICLES, SEPARATION_M, Finding, check_mission, errors_of
from companion.link.limits import SetpointLimits
from companion.mission import CentrePath, Mission, MissionConfig
from companion.params import InnerLoopConfig, VehicleParams
from sim_bridge.world.autopilot_model import AutopilotConfig
from sim_bridge.world.carrier import CarrierConfig, carrier_position_ned_m, release_times_s
from sim_bridge.world.estimator import EstimatorConfig
from sim_bridge.world.faults import FaultsConfig, resolve_rotor_failures
from sim_bridge.world.physics import WindConfig
from sim_bridge.world.transport import LinkConfig

DURATION_MAX_S = 86_400.0
"""Longest run, s of simulated time (one day); the recording's memory bounds it further."""


@dataclass(config=STRICT)
class PhysicsConfig:
    """The simulated world's physics: step rate (headless; the SITL steps at its own
    time.physics_rate_hz), wind and the flat ground.

    Raises:
        pydantic.ValidationError: rate_hz below 500.
    """

    rate_hz: float = Field(default=500.0, ge=500.0)
    """Physics (and inner-loop controller) rate; >= 500 Hz."""
    wind: WindConfig = WindConfig()
    ground_z_m: float | None = 0.0
    """NED z of the ground plane (0 = take-off altitude); None disables ground contact."""


@dataclass(config=STRICT)
class AgentRateConfig:
    """The headless runner's agent rate, Hz: one agent step (and setpoint) for every vehicle
    per 1/rate_hz, with physics.rate_hz / rate_hz physics steps in between; the recorder
    samples separation and clearance at it too. (`swarmdrop agent` has its own --rate.)

    Raises:
        pydantic.ValidationError: rate_hz not > 0.
    """

    rate_hz: float = Field(default=50.0, gt=0)


@dataclass(config=STRICT)
class SafetyConfig:
    """Distances the run is judged by, m: separation between vehicles, clearance from
    obstacles, and what counts as a collision.

    Raises:
        pydantic.ValidationError: a distance not > 0 (obstacle_margin_m: < 0).
    """

    separation_m: float = Field(default=SEPARATION_M, gt=0)
    """Pairs closer than this count as separation violations (companion.feasibility.SEPARATION_M:
    the value the mission's checks and the swarm commands use)."""
    obstacle_margin_m: float = Field(default=1.0, ge=0)
    collision_m: float = Field(default=0.2, gt=0)
    """Two vehicles whose centres come closer than this collide: a Crazyflie 2.x spans
    about 0.13 m from prop tip to prop tip, and this adds a third for the props' reach."""


@dataclass(config=STRICT)
class OutputConfig:
    """What a run writes besides metrics: the log rate (Hz) of telemetry.npz, and whether and
    what the figures show (snapshot times in s, 1-based vehicle numbers).

    Raises:
        pydantic.ValidationError: log_rate_hz not > 0.
    """

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
    """Everything a run flies by: the world (airframe, inner loop, physics, carrier, estimator,
    faults, radio link), the mission (companion.mission.MissionConfig) and what a run records.
    The root of every config: `swarmdrop simulate`, `sweep` and `run` read it, the SITL reads
    it as its `scenario:` section, and every agent reads its mission, vehicle and inner loop."""

    version: int = CONFIG_VERSION
    """The config schema this file is written for (companion.config.CONFIG_VERSION)."""
    name: str = "scenario"
    seed: int = Field(default=0, ge=0, le=SEED_MAX)
    duration_s: float = Field(default=300.0, gt=0, le=DURATION_MAX_S)
    """Hard stop for the run, s of simulated time (at most a day)."""
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
    """Injected rotor failures (headless and SITL; sim_bridge/world/faults.py)."""
    autopilot: AutopilotConfig = AutopilotConfig()
    """Which autopilot the headless runner models, and its hover-thrust parameter's error
    (headless and SITL; sim_bridge/world/autopilot_model.py)."""
    commands: tuple[CommandEntry, ...] = ()
    """Operator commands issued in flight, in time order (companion.commands.CommandEntry;
    docs/swarm.md, "Swarm commands"): the simulators feed them through a CommandSource."""

    @field_validator("version")
    @classmethod
    def _version(cls, v: int) -> int:
        return check_version(v)

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
        check_schedule(self.commands, self.mission.n_vehicles, self.duration_s)
        if self.physics.wind.active and self.vehicle.drag_coeff_n_per_mps <= 0:
            raise ValueError(
                "physics.wind is set but vehicle.drag_coeff_n_per_mps is 0: wind acts only through drag, so it would "
                "have no effect; set a drag coefficient (a Crazyflie is about 0.0065 N/(m/s), docs/vehicle.md)"
            )
        return self


Runner = Literal["headless", "sitl", "fleet"]

HEADLESS_MAX_VEHICLES = 1000
"""The headless runner keeps every vehicle's view of every other (N x N arrays: 320 MB at
N = 1000, measured) and its tick costs O(N^2) (0.75 s per simulated second at N = 1000)."""
RECORD_MAX_BYTES = 2_000_000_000
"""A run records every vehicle at output.log_rate_hz in memory (RECORD_BYTES_PER_SAMPLE a
vehicle and sample, plus RECORD_BYTES_PER_TICK a sample); the arrays are stacked at the end,
which briefly needs as much again. Runs that would record more are refused."""
RECORD_BYTES_PER_SAMPLE = 150
RECORD_BYTES_PER_TICK = 1000


def ends_landed(cfg: ScenarioConfig) -> bool:
    """The run ends with every vehicle landing: mission.phases.land_after_hover_s, or a
    `commands:` entry that lands everyone (LAND without vehicles or naming every one, RTL). Such
    a run is complete when every counted vehicle is down, and its formation is judged before
    the landing."""
    every = set(range(1, cfg.mission.n_vehicles + 1))  # (commands name vehicles 1-based)
    return cfg.mission.phases.land_after_hover_s is not None or any(
        e.kind == "rtl" or (e.kind == "land" and (e.vehicles is None or set(e.vehicles) >= every))
        for e in cfg.commands)


def record_bytes(cfg: ScenarioConfig) -> float:
    """Memory the run's recording may reach by duration_s, bytes."""
    samples = cfg.duration_s * cfg.output.log_rate_hz + 1
    return samples * (cfg.mission.n_vehicles * RECORD_BYTES_PER_SAMPLE + RECORD_BYTES_PER_TICK)


def launch_track_ned_m(cfg: ScenarioConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The carrier's first and last scheduled release points (None for a ground launch)."""
    if cfg.mission.launch != "carrier":
        return None
    t = release_times_s(cfg.carrier, cfg.mission.n_vehicles)
    return carrier_position_ned_m(cfg.carrier, t[0]), carrier_position_ned_m(cfg.carrier, t[-1])


def scenario_findings(cfg: ScenarioConfig, runner: Runner = "headless") -> list[Finding]:
    """Whether `runner` can fly this scenario: the mission's own checks
    (companion.feasibility.check_mission, with the scenario's ground, separation, obstacle
    margin and launch track) plus the simulators' limits. Pure: no I/O.

    Returns: findings, errors first (docs/scenario.md, "Can it fly?").
    """
    m = cfg.mission
    out: list[Finding] = []
    limit = HEADLESS_MAX_VEHICLES if runner == "headless" else MAVLINK_MAX_VEHICLES
    if m.n_vehicles > limit:
        why = ("the headless runner's N x N arrays and O(N^2) tick" if runner == "headless" else
               "one MAVLink system id (1-250) per vehicle")
        out.append(Finding("mission.n_vehicles", f"{m.n_vehicles} vehicles: `swarmdrop "
                           f"{'simulate' if runner == 'headless' else 'run' if runner == 'fleet' else 'sitl'}` flies at "
                           f"most {limit} ({why})"))
        return out  # the rest would cost O(N^2) for nothing
    if runner == "headless" and m.launch != "carrier":  # (refused at load: before a run directory or a --live stream)
        out.append(Finding("mission.launch", f"{m.launch!r}: the headless runner flies carrier launches only; fly a "
                           "ground launch with `swarmdrop run` (the SITL and agents)"))
        return out
    if runner == "fleet" and m.origin is None:
        out.append(Finding("mission.origin", "missing: every `swarmdrop agent` converts its autopilot's own EKF frame "
                           "to the mission frame through this geodetic origin (give lat_deg, lon_deg, alt_amsl_m)"))
    rec = record_bytes(cfg)
    if rec > RECORD_MAX_BYTES:
        out.append(Finding("duration_s", f"{m.n_vehicles} vehicles recorded at output.log_rate_hz "
                           f"{cfg.output.log_rate_hz:g} Hz for {cfg.duration_s:g} s need {rec / 1e9:.3g} GB of memory, "
                           f"more than {RECORD_MAX_BYTES / 1e9:g} GB: shorten duration_s or lower output.log_rate_hz"))
    ground = cfg.physics.ground_z_m if cfg.physics.ground_z_m is not None else m.ground_z_m
    if runner == "fleet" and ground is not None and m.ground_z_m is not None:
        ground = min(ground, m.ground_z_m)  # each agent checks its mission against mission.ground_z_m too
    track = launch_track_ned_m(cfg)
    out += check_mission(m, cfg.vehicle, cfg.inner_loop, separation_m=cfg.safety.separation_m,
                         obstacle_margin_m=cfg.safety.obstacle_margin_m, ground_z_m=ground, launch_track_ned_m=track,
                         completion_tol_m=cfg.completion_tol_m)
    if m.phases.land_after_hover_s is not None and cfg.physics.ground_z_m is None:
        out.append(Finding("mission.phases.land_after_hover_s", "the vehicles land, but physics.ground_z_m is null "
                           "(no ground): they would descend for ever"))
    out += _timing(cfg)
    out += _radio(cfg)
    out += _carrier(cfg)
    return sorted(out, key=lambda f: not f.error)


LANDING_ALLOWANCE_S = 5.0
"""Time a landing takes beyond its descent (land detection and disarm), s."""


def _path_s(cfg: ScenarioConfig) -> float:
    m = cfg.mission
    return CentrePath(np.asarray(m.waypoints_ned_m, float), m.transit_speed_mps, m.transit_accel_mps2,
                      m.waypoint_dwell_s).duration_s


def _last_release_s(cfg: ScenarioConfig) -> float:
    m = cfg.mission
    if m.launch == "carrier" and cfg.carrier.release == "schedule":
        return float(release_times_s(cfg.carrier, m.n_vehicles)[-1])
    return 0.0


def _after_hover_s(cfg: ScenarioConfig) -> float:
    """From the start of the final hover to completion: the landing, or the completion hold."""
    m = cfg.mission
    land = m.phases.land_after_hover_s
    if land is None:
        return cfg.completion_hold_s
    ground = cfg.physics.ground_z_m if cfg.physics.ground_z_m is not None else m.ground_z_m
    height = 0.0 if ground is None else max(0.0, ground - float(m.waypoints_ned_m[-1][2]))
    return land + height / m.phases.land_speed_mps + LANDING_ALLOWANCE_S + cfg.completion_hold_s


def expected_end_s(cfg: ScenarioConfig, t_go_s: float = math.nan) -> float:
    """When the mission should end, s of mission time, for progress bars: the agreed
    transit start plus the centre path and what follows the hover; before a transit start
    is agreed, the last release plus those (a lower bound: assembly takes longer).
    Never more than duration_s."""
    start = t_go_s if math.isfinite(t_go_s) else _last_release_s(cfg)
    end = start + _path_s(cfg) + _after_hover_s(cfg)
    return min(cfg.duration_s, end) if math.isfinite(end) else cfg.duration_s


def _timing(cfg: ScenarioConfig) -> list[Finding]:
    """The mission cannot end before duration_s: the last release plus the centre path
    (plus the hover before landing) is a lower bound of its completion time."""
    m = cfg.mission
    with np.errstate(over="ignore", invalid="ignore"):  # (absurd waypoints are reported, not warned about)
        last, path_s = _last_release_s(cfg), _path_s(cfg)
    bound = last + path_s + (m.phases.land_after_hover_s or 0.0)
    if not math.isfinite(bound) or bound > cfg.duration_s:
        return [Finding("duration_s", f"the mission cannot end within {cfg.duration_s:g} s: the last release at "
                        f"{last:g} s plus {path_s:.4g} s on the centre path"
                        + (f" plus {m.phases.land_after_hover_s:g} s of hover" if m.phases.land_after_hover_s else "")
                        + f" is already {bound:.4g} s")]
    return []


def _radio(cfg: ScenarioConfig) -> list[Finding]:
    """With a radio range, every vehicle must hear its consensus neighbours in formation."""
    rng = cfg.link.range_m
    if rng is None:
        return []
    try:
        mission = Mission(cfg.mission)
    except FormationUnstableError:  # (reported by check_mission)
        return []
    i, j = np.nonzero(mission.weights)
    d = np.linalg.norm(mission.offsets_ned_m[i] - mission.offsets_ned_m[j], axis=1)
    far = np.flatnonzero(d > rng)
    if not len(far):
        return []
    k = far[np.argmax(d[far])]
    return [Finding("link.range_m", f"{rng:g} m: in formation UAV {i[k] + 1} is {d[k]:.3g} m from its consensus "
                    f"neighbour UAV {j[k] + 1} and would never hear it")]


def _carrier(cfg: ScenarioConfig) -> list[Finding]:
    v = float(np.linalg.norm(cfg.carrier.vel_ned_mps))
    xy_max = SetpointLimits().xy_vel_max_mps
    if cfg.mission.launch == "carrier" and v > xy_max:
        return [Finding("carrier.vel_ned_mps", f"vehicles are released at {v:.3g} m/s, faster than the autopilot "
                        f"flies (MPC_XY_VEL_MAX {xy_max:g} m/s)", error=False)]
    return []


def load_scenario(path: str | Path, seed: int | None = None, *, runner: Runner | None = "headless",
                  strict: bool = False, warn: Callable[[str], None] | None = None,
                  seed_option: str = "--seed") -> ScenarioConfig:
    """Load and validate a scenario YAML, and check that `runner` can fly it.

    Args:
        seed: overrides the file's seed (validated like it, and named as seed_option when bad).
        runner: "headless", "sitl" or "fleet": refuse what that runner cannot fly
            (sim_bridge.scenario.scenario_findings); None: validation only.
        strict: warnings are errors too.
        warn: called with each warning's text (default: warnings are dropped).
        seed_option: the command-line option the seed came from (for messages).
    Raises:
        ConfigError: an empty file or one without a `mission:` mapping; unknown keys or bad
            values, naming their dotted path; a bad seed override, naming seed_option; or a
            mission that cannot be flown (every error, with its path and reason).
    """
    data = file_data = mission_file_data(read_yaml(path), str(path))
    if seed is not None:
        validate(ScenarioConfig, {"seed": seed}, seed_option)  # a bad override is the option's fault, not the file's
        data = {**data, "seed": seed}
    cfg = validate(ScenarioConfig, data, str(path))
    require_mission(file_data, str(path))
    if runner is not None:
        check_findings(scenario_findings(cfg, runner), str(path), strict, warn)
    return cfg


def check_findings(findings: list[Finding], source: str, strict: bool = False,
                   warn: Callable[[str], None] | None = None) -> None:
    """Raise on the findings that stop a run; pass the other warnings to warn.

    Raises:
        ConfigError: "SOURCE: cannot be flown" and one line per error (path: reason).
    """
    stop = errors_of(findings, strict)
    if stop:
        lines = [f"  {f}" + ("" if f.error else " (a warning; --strict makes it an error)") for f in stop]
        raise ConfigError(f"{source}: the mission cannot be flown as configured ({len(stop)} problem(s)):\n"
                          + "\n".join(lines))
    for f in findings:
        if not f.error and warn is not None:
            warn(f"{source}: {f} (a warning; --strict makes it an error)")
