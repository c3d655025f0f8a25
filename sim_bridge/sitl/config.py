"""Configuration of `swarmdrop sitl` (validated, YAML-loadable): the scenario schema for the
world, and the SITL's own sections for how it serves it."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator
from pydantic.dataclasses import dataclass

from companion.config import CONFIG_VERSION, STRICT, ConfigError, check_version, read_yaml, replace, validate
from companion.feasibility import MAVLINK_MAX_VEHICLES
from companion.mission import GeodeticOrigin, MissionConfig
from companion.params import InnerLoopConfig, VehicleParams
from sim_bridge.scenario import LaunchStudyConfig, ScenarioConfig
from sim_bridge.world.carrier import CarrierConfig
from sim_bridge.world.estimator import EstimatorConfig
from sim_bridge.world.faults import FaultsConfig
from sim_bridge.world.physics import WindConfig
from sim_bridge.world.transport import LinkConfig


@dataclass(config=STRICT)
class EndpointConfig:
    """The SITL's MAVLink UDP endpoints: one per vehicle (a block of ports from a base), and
    optionally one GCS link shared by every vehicle.

    Raises:
        pydantic.ValidationError: a port outside 1..65535 (a local port: 0..65535).
    """

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
    """The SITL's clock: pace against the wall clock, lockstep with the companions, and the
    tick, autopilot and physics rates the simulation steps at.

    Raises:
        pydantic.ValidationError: a value out of range (speed in (0, 1000], tick_s in
            (0, 0.1], physics_rate_hz >= 100, ...).
    """

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
    """Where vehicles start (the launch itself, ground or carrier, is scenario.mission.launch)."""

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
    """Vehicle k's agent listens on bind_host:agent_base_port+k (0: answer the address it sends from).
    Its faults are the scenario's `link`, its agents publish at mission.swarm.rate_hz."""
    monitors: tuple[str, ...] = ()
    """"HOST:PORT" of each monitor (an operator's console, `swarmdrop console`): the radio copies
    every state it takes there, and forwards the SWARMDROP_PLAN / SLOTS a monitor (or any
    peer) sends to every vehicle (docs/console.md)."""

    @field_validator("monitors")
    @classmethod
    def _monitor_addresses(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        for a in v:
            host, _, port = a.rpartition(":")
            if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
                raise ValueError(f"monitor {a!r}: expected HOST:PORT with a port from 1 to 65535")
        return v

    @property
    def monitor_addrs(self) -> list[tuple[str, int]]:
        """The monitors as (host, port)."""
        return [(a.rpartition(":")[0], int(a.rpartition(":")[2])) for a in self.monitors]


@dataclass(config=STRICT)
class SigningConfig:
    """MAVLink 2 signing on every vehicle endpoint and the GCS endpoint (docs/signing.md)."""

    mode: Literal["off", "optional", "require"] = "off"
    key_file: str | None = None
    """32-byte key (64 hex digits), readable by its owner only; needed unless mode is off."""
    timestamp_file: str | None = None
    """Keeps the last signing timestamp across restarts (default: KEY_FILE.timestamp)."""


PORT_MAX = 65535
"""The highest UDP port: base ports plus the vehicle count must stay within it."""
DEFAULT_HOME = GeodeticOrigin(lat_deg=47.397742, lon_deg=8.545594, alt_amsl_m=488.0)
"""Home (and the mission frame's origin) when the scenario gives no mission.origin: PX4 SITL's
default home, Zurich."""
LEGACY_KEYS = ("vehicles", "seed", "vehicle", "inner_loop", "ground_z_m", "wind", "estimator", "faults", "home",
               "carrier")
"""Top-level keys of a version-1 SITL config that version 2 reads from its scenario section."""


def default_scenario() -> ScenarioConfig:
    """The world of a SITL started without a scenario: one vehicle on the ground at DEFAULT_HOME."""
    return ScenarioConfig(name="sitl", mission=MissionConfig(n_vehicles=1, launch="ground"),
                          launch_study=LaunchStudyConfig(enabled=False))


@dataclass(config=STRICT)
class SitlConfig:
    """`swarmdrop sitl`: the simulated world and mission are a scenario (the same schema as
    `swarmdrop simulate`, sim_bridge.scenario.ScenarioConfig, read whole); the rest is how the
    SITL serves it: autopilot dialect, MAVLink endpoints and streams, clock, spawn, radio,
    signing, parameter overrides, tlog. The properties below read the world from the scenario."""

    version: int = CONFIG_VERSION
    """The config schema this file is written for (companion.config.CONFIG_VERSION)."""
    dialect: str = "px4"
    """Which autopilot every vehicle behaves like (HEARTBEAT, modes, parameters, setpoint rules):
    the name of a companion dialect with a SITL behaviour (sim_bridge/sitl/autopilots/)."""
    scenario: ScenarioConfig = dataclasses.field(default_factory=default_scenario)
    """The world: vehicle count (mission.n_vehicles), seed, airframe, inner loop, carrier, ground
    (physics.ground_z_m), wind, estimator errors, rotor faults, home (mission.origin), launch,
    the swarm radio's faults (link) and rate (mission.swarm.rate_hz), and the mission recorded."""
    endpoints: EndpointConfig = EndpointConfig()
    streams: StreamRates = StreamRates()
    time: TimeConfig = TimeConfig()
    spawn: SpawnConfig = SpawnConfig()
    params: dict[str, float] = Field(default_factory=dict)
    """Parameter overrides applied to every vehicle at start (name -> value)."""
    tlog_path: str | None = None
    medium: MediumConfig = MediumConfig()
    signing: SigningConfig = SigningConfig()

    @field_validator("version")
    @classmethod
    def _version(cls, v: int) -> int:
        return check_version(v)

    @field_validator("dialect")
    @classmethod
    def _known_autopilot(cls, name: str) -> str:
        from sim_bridge.sitl.autopilots import AUTOPILOTS

        if name not in AUTOPILOTS:
            raise ValueError(f"unknown autopilot {name!r} (known: {', '.join(sorted(AUTOPILOTS))})")
        return name

    @model_validator(mode="after")
    def _fits_mavlink(self):
        n = self.scenario.mission.n_vehicles
        if n > MAVLINK_MAX_VEHICLES:
            raise ValueError(f"scenario.mission.n_vehicles {n}: the SITL gives every vehicle a MAVLink system id, "
                             f"so it simulates at most {MAVLINK_MAX_VEHICLES}")
        return self

    @model_validator(mode="after")
    def _ports_fit(self):
        """Every vehicle's ports are real ports: a base port plus the vehicle count must stay
        within 65535 (checked here, before a socket is opened, not in sendto at vehicle k)."""
        n = self.scenario.mission.n_vehicles
        ep, med = self.endpoints, self.medium
        last_remote = ep.vehicle_remote_port(n - 1)
        if last_remote > PORT_MAX:
            step = " (stepping over endpoints.gcs_remote_port)" if last_remote != ep.remote_base_port + n - 1 else ""
            raise ValueError(f"endpoints.remote_base_port {ep.remote_base_port} (--remote-base-port): vehicle {n - 1} "
                             f"of {n} would send to port {last_remote}{step}, past {PORT_MAX}: use a base port of "
                             f"at most {ep.remote_base_port - (last_remote - PORT_MAX)}")
        for path, option, base in (("endpoints.local_base_port", "--local-base-port", ep.local_base_port),
                                   ("medium.agent_base_port", "--agent-base-port", med.agent_base_port)):
            if base and base + n - 1 > PORT_MAX:  # (0: ephemeral ports, or answer the sender)
                raise ValueError(f"{path} {base} ({option}): vehicle {n - 1} of {n} would use port {base + n - 1}, "
                                 f"past {PORT_MAX}: use a base port of at most {PORT_MAX - n + 1}")
        return self

    # ---- the world, read from the scenario ----------------------------------------
    @property
    def vehicles(self) -> int:
        """Number of simulated vehicles (sysids 1..vehicles)."""
        return self.scenario.mission.n_vehicles

    @property
    def seed(self) -> int:
        """Seed of every random draw (release attitudes, GNSS fixes, wind, faults, radio)."""
        return self.scenario.seed

    @property
    def vehicle(self) -> VehicleParams:
        """The airframe."""
        return self.scenario.vehicle

    @property
    def inner_loop(self) -> InnerLoopConfig:
        """The simulated inner loop's controller and gains (each vehicle's table may change them)."""
        return self.scenario.inner_loop

    @property
    def carrier(self) -> CarrierConfig:
        """The carrier's path and release schedule (carrier launches)."""
        return self.scenario.carrier

    @property
    def ground_z_m(self) -> float:
        """NED z of the ground plane (the SITL always has one: 0 when the scenario has none)."""
        g = self.scenario.physics.ground_z_m
        return 0.0 if g is None else g

    @property
    def wind(self) -> WindConfig:
        """One wind for the whole fleet (acts through drag)."""
        return self.scenario.physics.wind

    @property
    def estimator(self) -> EstimatorConfig:
        """GPS/estimator errors and latency on every reported state."""
        return self.scenario.estimator

    @property
    def faults(self) -> FaultsConfig:
        """Rotor failures (random ones drawn from the seed, as headless)."""
        return self.scenario.faults

    @property
    def home(self) -> GeodeticOrigin:
        """Geodetic home of the world frame: the mission's origin, else DEFAULT_HOME."""
        return self.scenario.mission.origin or DEFAULT_HOME

    @property
    def launch(self) -> Literal["carrier", "ground"]:
        """Vehicles start docked on the carrier or on the ground."""
        return self.scenario.mission.launch

    @property
    def link(self) -> LinkConfig:
        """The swarm radio's faults (loss, delay, range)."""
        return self.scenario.link

    @property
    def swarm_rate_hz(self) -> float:
        """How often agents publish (lockstep waits for these)."""
        return self.scenario.mission.swarm.rate_hz


def sitl_config(vehicles: int = 1, seed: int = 0, launch: Literal["carrier", "ground"] = "ground",
                origin: GeodeticOrigin | None = None, scenario: ScenarioConfig | None = None, **fields: Any) -> SitlConfig:
    """A SitlConfig for code and tests: the scenario (default_scenario, or the one given)
    with this vehicle count, seed, launch and origin, plus SitlConfig fields.

    Raises:
        ConfigError: a value that does not validate (named by its field).
    """
    sc = scenario or default_scenario()
    mission = replace(sc.mission, "arguments", n_vehicles=vehicles, launch=launch,
                      origin=origin if origin is not None else sc.mission.origin)
    return replace(SitlConfig(), "arguments", scenario=replace(sc, "arguments", seed=seed, mission=mission), **fields)


def _refuse_version_1(data: dict, source: str) -> None:
    """A version-1 SITL config (its world at the top level) gets a message saying where
    each key moved, instead of one "unknown key" per key.

    Raises:
        ConfigError: data holds version-1 keys and does not say it is version 2 or later.
    """
    legacy = [k for k in LEGACY_KEYS if k in data]
    if "launch" in (data.get("spawn") or {}) or {"link", "swarm_rate_hz"} & set(data.get("medium") or {}):
        legacy.append("spawn.launch / medium.link")
    version = data.get("version", 1)
    if legacy and not (isinstance(version, int) and version >= CONFIG_VERSION):
        raise ConfigError(
            f"{source}: a version-1 SITL config: since version {CONFIG_VERSION} the world is the `scenario:` section "
            f"(the scenario schema of `swarmdrop simulate`): move {', '.join(legacy)} into it (vehicles -> "
            "scenario.mission.n_vehicles, seed -> scenario.seed, home -> scenario.mission.origin, ground_z_m and wind "
            "-> scenario.physics, spawn.launch -> scenario.mission.launch, medium.link -> scenario.link; "
            "docs/sitl.md), and say `version: 2`")


def load_config(path: str | Path | None, **overrides: Any) -> SitlConfig:
    """YAML file (optional) + keyword overrides (SitlConfig fields) -> SitlConfig.

    Raises:
        ConfigError: missing or malformed file, unknown keys or bad values (named by dotted path).
    """
    data: dict = {}
    if path is not None:
        data = read_yaml(path) or {}
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level")
        _refuse_version_1(data, str(path))
    data.update({k: v for k, v in overrides.items() if v is not None})
    return validate(SitlConfig, data, str(path) if path is not None else "<sitl config>")
