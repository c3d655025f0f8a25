"""What `swarmdrop agent` is told: the command line and the mission file, validated."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

from pydantic import Field, field_validator
from pydantic.dataclasses import dataclass as pyd_dataclass

from companion.config import (
    CONFIG_VERSION,
    STRICT,
    ConfigError,
    check_version,
    mission_file_data,
    read_yaml,
    require_mission,
    validate,
)
from companion.feasibility import MAVLINK_MAX_VEHICLES, Finding, check_mission, errors_of
from companion.mission import MissionConfig
from companion.params import InnerLoopConfig, VehicleParams

AGENT_KEYS = ("version", "mission", "vehicle", "inner_loop")
"""The sections of a scenario file the agent reads. The rest (physics, carrier, output,
...) configure the simulators, which validate them; the agent leaves them alone."""


@pyd_dataclass(config=STRICT)
class MissionFile:
    """The parts of a mission (scenario) YAML an agent flies by."""

    version: int = CONFIG_VERSION
    """The config schema the file is written for (companion.config.CONFIG_VERSION)."""
    mission: MissionConfig = MissionConfig()
    vehicle: VehicleParams = VehicleParams()
    """Mass, inertia and thrust limits: the attitude output mode's position law uses them."""
    inner_loop: InnerLoopConfig = InnerLoopConfig()
    """Gains of the position law (eq. 12-16) for the attitude output mode."""

    @field_validator("version")
    @classmethod
    def _version(cls, v: int) -> int:
        return check_version(v)


def load_mission_file(path: str | Path) -> MissionFile:
    """Read a mission/scenario YAML and validate the sections the agent uses.

    Raises:
        ConfigError: missing file, bad YAML (also a key given twice), no `mission:` mapping, or
            an invalid value in mission/vehicle/inner_loop (named by its dotted path); or no
            mission.origin (the agent needs the frame).
    """
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such mission file")
    # (a directory, an unreadable or undecodable file, bad YAML, a key given twice, an empty
    # file or no `mission:` mapping: ConfigError)
    data = mission_file_data(read_yaml(path), str(path))
    mf = validate(MissionFile, {k: data[k] for k in AGENT_KEYS if k in data}, str(path))
    require_mission(data, str(path))
    if mf.mission.origin is None:
        raise ConfigError(f"{path}: mission.origin: required by swarmdrop agent (the geodetic origin of the "
                          "mission frame that every vehicle's local frame is converted to)")
    return mf


def mission_sysids(mission: MissionConfig) -> list[int]:
    """The MAVLink system id the mission assigns to each vehicle, in vehicle order: its
    autopilot's, and its companion's on the swarm link (docs/companion.md, "Identity").

    Vehicle k is sysid k + 1, as the SITL and the fleet harness number them, unless the
    mission gives an explicit map (`mission.sysids`, read here once MissionConfig has it).
    """
    explicit = getattr(mission, "sysids", None)
    return list(explicit) if explicit is not None else [k + 1 for k in range(mission.n_vehicles)]


@dataclass
class NodeConfig:
    """One agent process (the `swarmdrop agent` arguments).

    Attributes:
        vehicle_id: index of this vehicle in the mission (0-based; sysid vehicle_id+1 by default).
        sysid: own MAVLink sysid on both links (None: the mission's sysid of vehicle_id).
        target_sysid: the autopilot's sysid given explicitly (--target-sysid): an override of
            the mission's sysid of vehicle_id, which the agent otherwise insists on.
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
    allow_drifting_loss: bool = False
    """Fly although the autopilot's companion-loss parameters would leave the vehicle where the
    swarm's ghost does not cover it (drifting, returning home, falling): a WARNING instead of
    a refusal (docs/companion.md, "Companion loss")."""
    set_loss_action: Literal["hold", "land"] | None = None
    """Set the autopilot's companion-loss action to this at set-up (PX4 COM_OBL_RC_ACT 5 or 4),
    logged at WARNING with the old value; None: only read and verify it."""
    stop_unread_streams: bool = False
    """The autopilot link is the agent's alone: stop the streams it does not read on it
    (companion.node.streams; docs/companion.md, "Streams")."""

    @property
    def assigned_sysid(self) -> int:
        """The sysid the mission assigns to this vehicle id (vehicle_id + 1 by default)."""
        return mission_sysids(self.mission.mission)[self.vehicle_id]

    @property
    def own_sysid(self) -> int:
        return self.assigned_sysid if self.sysid is None else self.sysid

    @property
    def autopilot_sysid(self) -> int:
        """The sysid of the autopilot this agent flies: --target-sysid, else the mission's."""
        return self.assigned_sysid if self.target_sysid is None else self.target_sysid


RATE_HZ_MIN, RATE_HZ_MAX = 2.0, 400.0
"""--rate: above RATE_HZ_MIN (the setpoint stream must outpace the autopilot's offboard loss
timeout) and at most RATE_HZ_MAX, Hz (the fleet harness checks its --rate against these too)."""
SETUP_TIMEOUT_MAX_S = 86400.0
"""--setup-timeout: at most a day."""


@pyd_dataclass(config=STRICT)
class _Checks:
    """The command line's numbers, each named by its option (every float finite: STRICT)."""

    vehicle_id: int = Field(ge=0, le=249, alias="--vehicle-id")
    rate_hz: float = Field(gt=RATE_HZ_MIN, le=RATE_HZ_MAX, alias="--rate")
    takeoff_alt_m: float = Field(gt=0.5, le=500.0, alias="--takeoff-alt")
    plan_every: int = Field(ge=1, le=50, alias="--plan-every")
    setup_timeout_s: float = Field(gt=0.0, le=SETUP_TIMEOUT_MAX_S, alias="--setup-timeout")
    heartbeat_timeout_s: float = Field(gt=0.0, le=SETUP_TIMEOUT_MAX_S, alias="heartbeat_timeout_s")
    sysid: int | None = Field(default=None, ge=1, le=255, alias="--sysid")
    target_sysid: int | None = Field(default=None, ge=1, le=255, alias="--target-sysid")


def mission_findings(mf: MissionFile) -> list[Finding]:
    """Whether the agent can fly this mission (companion.feasibility.check_mission with the
    MAVLink fleet's limit of 250 vehicles; docs/scenario.md, "Can it fly?"). Pure."""
    return check_mission(mf.mission, mf.vehicle, mf.inner_loop, max_vehicles=MAVLINK_MAX_VEHICLES)


def check_node(cfg: NodeConfig, *, strict: bool = False, warn: Callable[[str], None] | None = None,
               source: str = "mission") -> NodeConfig:
    """Validate the numbers of a NodeConfig against the mission, and refuse a mission that
    cannot be flown (mission_findings), before any link is opened.

    Args:
        strict: feasibility warnings are errors too (`swarmdrop agent --strict`).
        warn: called with each remaining warning's text (default: logged as a warning).
        source: what the findings are reported against (the mission file's path).
    Raises:
        ConfigError: naming the option and the reason (a number out of range or not finite,
            --signing-key without --signing); or "SOURCE: the mission cannot be flown" and one
            line (dotted path: reason) per error.
    """
    validate(_Checks, {"--vehicle-id": cfg.vehicle_id, "--rate": cfg.rate_hz, "--takeoff-alt": cfg.takeoff_alt_m,
                       "--plan-every": cfg.plan_every, "--setup-timeout": cfg.setup_timeout_s,
                       "heartbeat_timeout_s": cfg.heartbeat_timeout_s, "--sysid": cfg.sysid,
                       "--target-sysid": cfg.target_sysid}, "arguments")
    if cfg.signing_key_file is not None and cfg.signing == "off":
        raise ConfigError(f"arguments: --signing-key {cfg.signing_key_file} needs --signing optional|require: with "
                          "--signing off the key is not used and nothing is signed")
    n = cfg.mission.mission.n_vehicles
    if cfg.vehicle_id >= n:
        raise ConfigError(f"arguments: --vehicle-id {cfg.vehicle_id} is outside the mission's {n} vehicles")
    findings = mission_findings(cfg.mission)
    stop = errors_of(findings, strict)
    if stop:
        lines = [f"  {f}" + ("" if f.error else " (a warning; --strict makes it an error)") for f in stop]
        raise ConfigError(f"{source}: the mission cannot be flown as configured ({len(stop)} problem(s)):\n"
                          + "\n".join(lines))
    warn = warn or logging.getLogger("swarmdrop.agent").warning
    for f in findings:
        if not f.error:
            warn(f"{source}: {f} (a warning; --strict makes it an error)")
    return cfg
