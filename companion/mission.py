"""The mission model: formation offsets r_i, the formation-centre path c(t),
obstacles, topology, APF and phase-transition settings (paper section 4).

MissionConfig is what YAML holds; Mission is the derived, ready-to-use form that
every Agent of the swarm builds identically from the same config.
"""
from __future__ import annotations

from dataclasses import dataclass as plain_dataclass
from functools import cached_property
from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.control import topology
from companion.control.formation import ConsensusGains, check_stability

Vec3 = tuple[float, float, float]


@dataclass(config=STRICT)
class FormationConfig:
    """A horizontal circle of radius_m around the formation centre.

    slot_order "sequential": vehicle i at bearing 360*i/N deg from north.
    slot_order "interleaved": vehicles alternate west/east and fill the circle from
    its south end to its north end, so that vehicles released earlier (further
    south along a northbound carrier track) take the southern slots; this keeps
    assembly paths short and mostly uncrossed (docs/scenario.md).
    """

    shape: Literal["circle"] = "circle"
    radius_m: float = Field(default=40.0, gt=0)
    slot_order: Literal["sequential", "interleaved"] = "interleaved"


@dataclass(config=STRICT)
class Obstacle:
    centre_ned_m: Vec3
    radius_m: float = Field(gt=0)


@dataclass(config=STRICT)
class TopologyConfig:
    kind: Literal["chain", "ring", "complete", "k_nearest"] = "chain"
    weight: float = Field(default=1.0, gt=0)
    k: int = Field(default=3, ge=1)
    """Neighbour count for k_nearest (by formation offsets)."""


@dataclass(config=STRICT)
class ApfConfig:
    """Eq. 29-30 with the normalisation of docs/formation.md: K4/K5 are peak
    repulsive accelerations, influence distances set where the field vanishes."""

    kappa: float = Field(default=3.0, gt=0)
    vehicle_gain_mps2: float = Field(default=6.0, ge=0)
    vehicle_influence_m: float = Field(default=4.0, gt=0)
    sensing_radius_m: float = Field(default=10.0, gt=0)
    obstacle_gain_mps2: float = Field(default=10.0, ge=0)
    obstacle_influence_m: float = Field(default=8.0, gt=0)


@dataclass(config=STRICT)
class PhaseConfig:
    """Explicit phase-transition thresholds (docs/agent.md)."""

    stable_tilt_deg: float = Field(default=5.0, gt=0)
    stable_speed_mps: float = Field(default=0.2, gt=0)
    stable_dwell_s: float = Field(default=0.3, ge=0)
    assembled_pos_m: float = Field(default=0.5, gt=0)
    assembled_speed_mps: float = Field(default=0.3, gt=0)
    go_quantum_s: float = Field(default=1.0, gt=0)
    """Transit-start proposals are rounded up to a multiple of this (round numbers in logs;
    the agreement itself is the earliest proposal heard, docs/swarm.md)."""
    land_after_hover_s: float | None = Field(default=None, ge=0)
    """Land this long after hover begins; None = hold station."""
    land_speed_mps: float = Field(default=0.7, gt=0)
    lost_tilt_deg: float = Field(default=60.0, gt=0, le=180)
    """In a formation phase, tilt beyond this for lost_dwell_s means loss of control
    (phase FAILED). PX4's failure detector uses 60 deg (FD_FAIL_R, FD_FAIL_P)."""
    lost_dwell_s: float = Field(default=0.3, ge=0)
    """How long the tilt must last (PX4: FD_FAIL_R_TTRI, FD_FAIL_P_TTRI, 0.3 s)."""


@dataclass(config=STRICT)
class SwarmConfig:
    """The swarm contract on a lossy, delayed link (docs/swarm.md)."""

    rate_hz: float = Field(default=10.0, gt=0, le=100)
    """How often every agent publishes its own state, Hz."""
    stale_after_s: float = Field(default=0.5, gt=0)
    """A neighbour state older than this leaves consensus and is avoided as a 'ghost'
    (the column its autopilot can hold and land in) instead of as a vehicle."""
    peer_timeout_s: float = Field(default=3.0, gt=0)
    """A vehicle unheard for this long no longer blocks the transit start."""
    go_margin_s: float = Field(default=2.0, ge=0)
    """A transit-start proposal lies this far ahead, so that it reaches everyone
    (link delay and relays) before it is due."""
    go_wait_s: float = Field(default=10.0, ge=0)
    """With some vehicles of the mission never heard or silent, the others start
    once everything they hear has been assembled for this long."""
    own_timeout_s: float = Field(default=0.5, gt=0)
    """The agent's own state older than this counts as invalid: it commands a stop."""
    ghost_radius_m: float = Field(default=1.0, gt=0)
    """Radius of a silent vehicle's column (hold error of its autopilot plus its size)."""
    ghost_brake_mps2: float = Field(default=3.0, gt=0)
    """Deceleration assumed for a silent vehicle's autopilot when it brakes to Hold."""


@dataclass(config=STRICT)
class SetpointConfig:
    """What the agent sends in formation phases (docs/agent.md)."""

    kind: Literal["state", "acceleration"] = "state"
    """"state": position, velocity and acceleration that agree (the state eq. 31's
    acceleration leads to lead_s ahead); "acceleration": the acceleration alone."""
    lead_s: float = Field(default=0.02, ge=0)
    """Horizon of the state setpoint; the setpoint period."""


@dataclass(config=STRICT)
class GeofenceConfig:
    """A box in the mission frame that the agent's setpoints never leave (docs/setpoint-hygiene.md)."""

    min_ned_m: Vec3
    max_ned_m: Vec3

    def __post_init__(self) -> None:
        if not all(lo < hi for lo, hi in zip(self.min_ned_m, self.max_ned_m)):
            raise ValueError("geofence: every min_ned_m axis must be below its max_ned_m axis")


@dataclass(config=STRICT)
class GeodeticOrigin:
    """The geodetic point at which the mission NED frame has its origin (WGS-84)."""

    lat_deg: float = Field(ge=-90, le=90)
    lon_deg: float = Field(ge=-180, le=180)
    alt_amsl_m: float = Field(ge=-500, le=10000)


@dataclass(config=STRICT)
class MissionConfig:
    n_vehicles: int = Field(default=40, ge=1)
    formation: FormationConfig = FormationConfig()
    waypoints_ned_m: tuple[Vec3, ...] = ((100.0, 0.0, -10.0),)
    """Formation-centre waypoints: the first is where the formation assembles, the
    rest are flown in order during transit."""
    transit_speed_mps: float = Field(default=4.0, gt=0)
    transit_accel_mps2: float = Field(default=0.5, gt=0)
    waypoint_dwell_s: float = Field(default=0.0, ge=0)
    yaw_deg: float = 0.0
    obstacles: tuple[Obstacle, ...] = ()
    topology: TopologyConfig = TopologyConfig()
    consensus: ConsensusGains = ConsensusGains()
    apf: ApfConfig = ApfConfig()
    formation_error_max_m: float = Field(default=8.0, gt=0)
    """Slot-position error at which the consensus law saturates (docs/formation.md):
    far from its slot a vehicle then cruises at |k2_pos| * this / |k2_vel| m/s
    instead of accelerating without bound."""
    consensus_accel_max_mps2: float = Field(default=3.0, gt=0)
    total_accel_max_mps2: float = Field(default=8.0, gt=0)
    phases: PhaseConfig = PhaseConfig()
    swarm: SwarmConfig = SwarmConfig()
    setpoint: SetpointConfig = SetpointConfig()
    launch: Literal["carrier", "ground"] = "carrier"
    """How the vehicles get airborne: thrown from the carrier (the autopilot recovers
    them), or armed and taken off from the ground by their agents."""
    takeoff_alt_m: float = Field(default=5.0, gt=0.5, le=500)
    """Ground launch: climb this far above home before assembling."""
    geofence: GeofenceConfig | None = None
    """Optional: a mission-frame box the agent keeps its setpoints in (None: no fence)."""
    origin: GeodeticOrigin | None = None
    """Geodetic origin of the mission frame; every vehicle's local frame is converted
    to it. Needed by `swarmdrop agent`; the headless runner flies in the mission frame."""
    ground_z_m: float | None = 0.0
    """Ground height in the mission frame (NED z, m): where a silent vehicle's column
    ends. None = unknown: the column then reaches 100 m below its last position."""

    @model_validator(mode="after")
    def _need_waypoint(self):
        if len(self.waypoints_ned_m) < 1:
            raise ValueError("waypoints_ned_m needs at least the assembly point")
        return self


def formation_offsets_ned_m(cfg: FormationConfig, n: int) -> np.ndarray:
    """Slot offsets r_i of eq. 25, shape (n, 3), NED metres, in the horizontal plane."""
    if cfg.slot_order == "sequential":
        bearing = 2.0 * np.pi * np.arange(n) / n
    else:
        # Vehicle i: side alternates west/east, position along the circle from south.
        i = np.arange(n)
        pairs = (n + 1) // 2
        phi = np.pi * ((i // 2) + 0.5) / pairs  # angle from south, (0, pi)
        side = np.where(i % 2 == 0, -1.0, 1.0)
        bearing = np.pi - side * phi  # from north, clockwise (towards east)
    r = cfg.radius_m
    return np.stack([r * np.cos(bearing), r * np.sin(bearing), np.zeros(n)], axis=1)


@plain_dataclass(frozen=True)
class CentrePath:
    """Piecewise rest-to-rest trapezoidal profile through the waypoints.

    Each leg starts and ends at rest, speed <= v_max and |accel| <= a_max.
    """

    waypoints_ned_m: np.ndarray  # (K, 3)
    v_max_mps: float
    a_max_mps2: float
    dwell_s: float

    @cached_property
    def _leg_table(self) -> tuple:
        return tuple(self._legs())

    def _legs(self):
        for k in range(len(self.waypoints_ned_m) - 1):
            a, b = self.waypoints_ned_m[k], self.waypoints_ned_m[k + 1]
            dist = float(np.linalg.norm(b - a))
            v = min(self.v_max_mps, np.sqrt(dist * self.a_max_mps2))
            t_acc = v / self.a_max_mps2
            t_cruise = (dist - v * t_acc) / v if v > 0 else 0.0
            yield a, b, dist, v, t_acc, t_cruise

    @cached_property
    def duration_s(self) -> float:
        """Time from transit start to arrival at the last waypoint, s."""
        return sum(2 * t_acc + t_cr + self.dwell_s for *_, t_acc, t_cr in self._leg_table)

    def at(self, tau_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """c(t), c'(t), c''(t) at tau_s seconds after transit start (tau < 0: at
        the assembly point). Returns three (3,) arrays: m, m/s, m/s^2."""
        zero = np.zeros(3)
        if tau_s <= 0 or len(self.waypoints_ned_m) == 1:
            return self.waypoints_ned_m[0].copy(), zero, zero.copy()
        t = tau_s
        for a, b, dist, v, t_acc, t_cr in self._leg_table:
            leg_t = 2 * t_acc + t_cr
            if t < leg_t and dist > 0:
                u = (b - a) / dist
                if t < t_acc:
                    s, sd, sdd = 0.5 * self.a_max_mps2 * t**2, self.a_max_mps2 * t, self.a_max_mps2
                elif t < t_acc + t_cr:
                    s, sd, sdd = 0.5 * v * t_acc + v * (t - t_acc), v, 0.0
                else:
                    tr = leg_t - t
                    s, sd, sdd = dist - 0.5 * self.a_max_mps2 * tr**2, self.a_max_mps2 * tr, -self.a_max_mps2
                return a + s * u, sd * u, sdd * u
            t -= leg_t
            if t < self.dwell_s:
                return b.copy(), zero, zero.copy()
            t -= self.dwell_s
        return self.waypoints_ned_m[-1].copy(), zero, zero.copy()


class Mission:
    """Derived mission: every agent builds the same one from the same config.

    Raises:
        FormationUnstableError: the consensus gains and topology give a closed loop
            (eq. 28) that is not Hurwitz.
    """

    def __init__(self, cfg: MissionConfig):
        self.cfg = cfg
        n = cfg.n_vehicles
        self.n = n
        self.offsets_ned_m = formation_offsets_ned_m(cfg.formation, n)
        self.weights = _build_topology(cfg.topology, self.offsets_ned_m)
        self.neighbours = topology.neighbour_table(self.weights)
        """(N, K) indices of the vehicles each one hears (-1 padded): the consensus loop
        visits only these, not all N columns of the weight matrix."""
        self.closed_loop_eigenvalues = check_stability(self.weights, cfg.consensus)
        self.path = CentrePath(
            np.asarray(cfg.waypoints_ned_m, dtype=float),
            cfg.transit_speed_mps,
            cfg.transit_accel_mps2,
            cfg.waypoint_dwell_s,
        )
        self.obstacle_centres_ned_m = np.array([o.centre_ned_m for o in cfg.obstacles], dtype=float).reshape(-1, 3)
        self.obstacle_radii_m = np.array([o.radius_m for o in cfg.obstacles], dtype=float)
        self.yaw_rad = float(np.radians(cfg.yaw_deg))

    @staticmethod
    def tau_s(t_s: float, t_go_s: float) -> float:
        """Time on the centre path at mission time t_s: since transit start t_go_s,
        or -1 (the assembly point) while t_go_s is not agreed yet (NaN)."""
        return -1.0 if np.isnan(t_go_s) else t_s - t_go_s

    def slot_ned_m(self, tau_s: float) -> np.ndarray:
        """Every vehicle's formation slot h_i at tau_s after transit start, (N, 3)."""
        c, _, _ = self.path.at(tau_s)
        return self.offsets_ned_m + c


def _build_topology(cfg: TopologyConfig, offsets_ned_m: np.ndarray) -> np.ndarray:
    n = len(offsets_ned_m)
    if cfg.kind == "chain":
        return topology.chain(n, cfg.weight)
    if cfg.kind == "ring":
        return topology.ring(n, cfg.weight)
    if cfg.kind == "complete":
        return topology.complete(n, cfg.weight)
    return topology.k_nearest(offsets_ned_m, min(cfg.k, max(n - 1, 1)), cfg.weight)
