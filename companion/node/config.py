"""What `swarmdrop agent` is told: the command line and the mission file, validated."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import yaml
from pydantic import Field
from pydantic.dataclasses import dataclass as pyd_dataclass

from companion.config import STRICT, ConfigError, validate
from companion.mission import MissionConfig
from companion.params import InnerLoopConfig, VehicleParams

AGENT_KEYS = ("mission", "vehicle", "inner_loop")
"""The sections of a scenario file the agent reads. The rest (physics, carrier, output,
...) configure the simulators, which validate them; the agent leaves them alone."""


@pyd_dataclass(config=STRICT)
class MissionFile:
    """The parts of a mission (scenario) YAML an agent flies by."""

    mission: MissionConfig = MissionConfig()
    vehicle: VehicleParams = VehicleParams()
    """Mass, inertia and thrust limits: the attitude output mode's position law uses them."""
    inner_loop: InnerLoopConfig = InnerLoopConfig()
    """Gains of the position law (eq. 12-16) for the attitude output mode."""


def load_mission_file(path: str | Path) -> MissionFile:
    """Read a mission/scenario YAML and validate the sections the agent uses.

    Raises:
        ConfigError: missing file, bad YAML, or an invalid value in mission/vehicle/inner_loop
            (named by its dotted path); or no mission.origin (the agent needs the frame).
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such mission file") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    mf = validate(MissionFile, {k: data[k] for k in AGENT_KEYS if k in data}, str(path))
    if mf.mission.origin is None:
        raise ConfigError(f"{path}: mission.origin: required by swarmdrop agent (the geodetic origin of the "
                          "mission frame that every vehicle's local frame is converted to)")
    return mf


@dataclass
class NodeConfig:
    """One agent process (the `swarmdrop agent` arguments).

    Attributes:
        vehicle_id: index of this vehicle in the mission (0-based; sysid vehicle_id+1 by default).
        autopilot_url: the autopilot link (companion.link.endpoints URL).
        swarm_bind: (host, port) of the swarm socket.
        swarm_peers: where to send this vehicle's state (the radio medium, or each peer).
        output: "acceleration" (SET_POSITION_TARGET_LOCAL_NED) or "attitude" (SET_ATTITUDE_TARGET).
        rate_hz: setpoint rate (also the telemetry rate it requests).
        launch: "carrier" (the autopilot's throw recovery) or "ground" (arm, take off).
        takeoff_alt_m: ground launch climb above home, m.
        lockstep: the SITL's lockstep: answer every control tick, wait for the radio's marker.
    """

    vehicle_id: int
    autopilot_url: str
    mission: MissionFile
    swarm_bind: tuple[str, int] = ("0.0.0.0", 0)
    swarm_peers: list[tuple[str, int]] = field(default_factory=list)
    sysid: int | None = None
    target_sysid: int | None = None
    output: Literal["acceleration", "attitude"] = "acceleration"
    rate_hz: float = 50.0
    plan_every: int = 5
    """Run the planner (Agent.step) every this many setpoint ticks (and on every tick it
    publishes its state); in between the last plan's state is advanced along its
    acceleration (docs/companion.md). 5 at 50 Hz: the planner at the swarm rate, 10 Hz."""
    launch: Literal["carrier", "ground"] = "carrier"
    takeoff_alt_m: float = 5.0
    lockstep: bool = False
    heartbeat_timeout_s: float = 5.0
    setup_timeout_s: float = 120.0
    stats_path: Path | None = None
    signing: Literal["off", "optional", "require"] = "off"
    """MAVLink 2 signing on the autopilot link and the swarm link (docs/signing.md)."""
    signing_key_file: Path | None = None
    """The 32-byte key file (owner-readable only); its last timestamps go to KEY.timestamp-SYSID."""

    @property
    def own_sysid(self) -> int:
        return self.vehicle_id + 1 if self.sysid is None else self.sysid


@pyd_dataclass(config=STRICT)
class _Checks:
    vehicle_id: int = Field(ge=0, le=249)
    rate_hz: float = Field(gt=2.0, le=400.0)
    takeoff_alt_m: float = Field(gt=0.5, le=500.0)
    plan_every: int = Field(ge=1, le=50)


def check_node(cfg: NodeConfig) -> NodeConfig:
    """Validate the numbers of a NodeConfig against the mission.

    Raises:
        ConfigError: naming the argument and the reason.
    """
    validate(_Checks, {"vehicle_id": cfg.vehicle_id, "rate_hz": cfg.rate_hz, "takeoff_alt_m": cfg.takeoff_alt_m,
                       "plan_every": cfg.plan_every}, "arguments")
    n = cfg.mission.mission.n_vehicles
    if cfg.vehicle_id >= n:
        raise ConfigError(f"arguments: --vehicle-id {cfg.vehicle_id} is outside the mission's {n} vehicles")
    return cfg
