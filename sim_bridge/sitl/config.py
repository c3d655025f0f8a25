"""Configuration of `swarmdrop sitl` (validated, YAML-loadable)."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass

from companion.config import STRICT, ConfigError, validate
from companion.params import InnerLoopConfig, VehicleParams
from sim_bridge.carrier import CarrierConfig
from sim_bridge.estimator import EstimatorConfig
from sim_bridge.faults import FaultsConfig, resolve_rotor_failures
from sim_bridge.physics import WindConfig
from sim_bridge.transport import LinkConfig


@dataclass(config=STRICT)
class EndpointConfig:
    remote_host: str = "127.0.0.1"
    remote_base_port: int = Field(default=14540, ge=1, le=65535)
    """Vehicle k sends to remote_host:remote_base_port+k until someone talks to it."""
    bind_host: str = "127.0.0.1"
    local_base_port: int = Field(default=18570, ge=0, le=65535)
    """Vehicle k listens on bind_host:local_base_port+k (0 = ephemeral ports)."""
    gcs_enabled: bool = False
    gcs_remote_port: int = Field(default=14550, ge=1, le=65535)
    gcs_local_port: int = Field(default=0, ge=0, le=65535)
    """Shared GCS link carrying every vehicle (0 = ephemeral local port)."""

    def vehicle_remote_port(self, k: int) -> int:
        """Default remote port of vehicle k: remote_base_port + k, stepping over the GCS
        port (14550) so that vehicle 10 and beyond never talk into a ground station's socket."""
        port = self.remote_base_port + k
        if self.remote_base_port <= self.gcs_remote_port <= port:
            port += 1
        return port


@dataclass(config=STRICT)
class HomeConfig:
    lat_deg: float = Field(default=47.397742, ge=-90, le=90)
    lon_deg: float = Field(default=8.545594, ge=-180, le=180)
    alt_amsl_m: float = 488.0


@dataclass(config=STRICT)
class StreamRates:
    """Default telemetry rates, Hz (0 = off). HEARTBEAT runs on wall-clock time,
    the others on simulation time (as PX4's streams run on PX4's clock)."""

    heartbeat: float = Field(default=1.0, ge=0)
    sys_status: float = Field(default=1.0, ge=0)
    extended_sys_state: float = Field(default=1.0, ge=0)
    local_position_ned: float = Field(default=10.0, ge=0)
    attitude: float = Field(default=10.0, ge=0)
    attitude_quaternion: float = Field(default=10.0, ge=0)
    global_position_int: float = Field(default=5.0, ge=0)
    gps_raw_int: float = Field(default=1.0, ge=0)
    home_position: float = Field(default=1.0, ge=0)
    system_time: float = Field(default=1.0, ge=0)
    battery_status: float = Field(default=0.5, ge=0)


@dataclass(config=STRICT)
class TimeConfig:
    speed: float = Field(default=1.0, gt=0, le=1000)
    """Simulation seconds per wall second (free-running and lockstep-idle pacing)."""
    lockstep: bool = False
    """Simulation time waits for the vehicles' companions (docs/sitl.md, "Lockstep")."""
    lockstep_detach_s: float = Field(default=2.0, gt=0)
    """Wall seconds after which a silent companion no longer holds the lockstep clock."""
    epoch_unix_s: float | None = None
    """SYSTEM_TIME.time_unix_usec = this + simulation time (None: the wall clock at start)."""
    start_when_attached: int = Field(default=0, ge=0)
    """The clock stays at 0 until this many vehicles have heard from a companion
    (a fleet run starts its mission only when every agent is up)."""
    tick_s: float = Field(default=0.01, gt=0, le=0.1)
    """Outer step: setpoints are sampled, telemetry scheduled and lockstep gated per tick."""
    autopilot_rate_hz: float = Field(default=50.0, gt=0)
    """Rate of the mode/failsafe/landing logic (rounded to whole ticks)."""
    physics_rate_hz: float = Field(default=500.0, ge=100)


@dataclass(config=STRICT)
class SpawnConfig:
    launch: Literal["ground", "carrier"] = "ground"
    grid_spacing_m: float = Field(default=2.0, gt=0)
    """Ground spawn: vehicle k at a square grid position around the origin."""
    gps_fix_delay_max_s: float = Field(default=0.0, ge=0)
    """Each vehicle gets its first GNSS fix at a random time in [0, this] (seeded), and its
    EKF origin where it is then: docked vehicles ride the carrier meanwhile, so origins differ."""


@dataclass(config=STRICT)
class MediumConfig:
    """The simulated swarm radio (sim_bridge.sitl.medium): agents send their state to
    one port, the medium forwards it to the vehicles in range with the link's faults."""

    enabled: bool = False
    port: int = Field(default=0, ge=0, le=65535)
    """UDP port on bind_host (0 = ephemeral)."""
    agent_base_port: int = Field(default=0, ge=0, le=65535)
    """Vehicle k's agent listens on bind_host:agent_base_port+k (0: answer the address it sends from)."""
    link: LinkConfig = LinkConfig()
    swarm_rate_hz: float = Field(default=10.0, gt=0)
    """How often agents publish (the mission's swarm.rate_hz; lockstep waits for these)."""


@dataclass(config=STRICT)
class SigningConfig:
    """MAVLink 2 signing on every vehicle endpoint and the GCS endpoint (docs/signing.md)."""

    mode: Literal["off", "optional", "require"] = "off"
    key_file: str | None = None
    """32-byte key (64 hex digits), readable by its owner only; needed unless mode is off."""
    timestamp_file: str | None = None
    """Keeps the last signing timestamp across restarts (default: KEY_FILE.timestamp)."""


@dataclass(config=STRICT)
class SitlConfig:
    vehicles: int = Field(default=1, ge=1, le=250)
    dialect: Literal["px4", "ardupilot"] = "px4"
    """Which autopilot every vehicle behaves like (HEARTBEAT, modes, parameters, setpoint rules)."""
    seed: int = 0
    vehicle: VehicleParams = VehicleParams()
    inner_loop: InnerLoopConfig = InnerLoopConfig()
    ground_z_m: float = 0.0
    wind: WindConfig = WindConfig()
    """One wind for the whole fleet, drawn from the SITL's seed (as headless; acts through drag)."""
    estimator: EstimatorConfig = EstimatorConfig()
    """GPS/estimator errors and latency on every reported state (the inner loop flies the true one)."""
    faults: FaultsConfig = FaultsConfig()
    """Rotor failures at given times (random ones drawn from seed, as headless); vehicle k is sysid k."""
    endpoints: EndpointConfig = EndpointConfig()
    home: HomeConfig = HomeConfig()
    streams: StreamRates = StreamRates()
    time: TimeConfig = TimeConfig()
    spawn: SpawnConfig = SpawnConfig()
    carrier: CarrierConfig = CarrierConfig()
    params: dict[str, float] = Field(default_factory=dict)
    """Parameter overrides applied to every vehicle at start (name -> value)."""
    tlog_path: str | None = None
    medium: MediumConfig = MediumConfig()
    signing: SigningConfig = SigningConfig()

    @model_validator(mode="after")
    def _wind_needs_drag(self):
        if self.wind.active and self.vehicle.drag_coeff_n_per_mps <= 0:
            raise ValueError("wind is set but vehicle.drag_coeff_n_per_mps is 0: wind acts only through drag")
        resolve_rotor_failures(self.faults, self.vehicles, self.seed)  # raises what the SITL would
        return self


def load_config(path: str | Path | None, **overrides) -> SitlConfig:
    """YAML file (optional) + keyword overrides -> SitlConfig.

    Raises:
        ConfigError: missing or malformed file, unknown keys or bad values (named by dotted path).
    """
    data: dict = {}
    if path is not None:
        try:
            data = yaml.safe_load(Path(path).read_text()) or {}
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such config file") from None
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML: {err}") from None
    data.update({k: v for k, v in overrides.items() if v is not None})
    return validate(SitlConfig, data, str(path) if path is not None else "<sitl config>")
