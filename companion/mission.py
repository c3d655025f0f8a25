"""The mission model: formation offsets r_i, the formation-centre path c(t),
obstacles, topology, APF and phase-transition settings (paper section 4).

MissionConfig is what YAML holds; Mission is the derived, ready-to-use form that
every Agent of the swarm builds identically from the same config.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass as plain_dataclass
from functools import cached_property
from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.control import topology
from companion.control.formation import ConsensusGains, check_stability
from companion.control.shapes import Shape, offsets_for, spec_from_config

Vec3 = tuple[float, float, float]


@dataclass(config=STRICT)
class FormationConfig:
    """The formation's shape around its centre (companion.control.shapes, docs/scenario.md):
    a horizontal circle of radius_m (the default), a line, grid or wedge of spacing_m, or a
    3-D shell of radius_m, turned to the bearing rotation_deg (of the shape's forward axis,
    clockwise from north). Vehicle i takes slot i.

    slot_order (circle only) "sequential": vehicle i at bearing 360*i/N deg from north.
    slot_order "interleaved": vehicles alternate west/east and fill the circle from
    its south end to its north end, so that vehicles released earlier (further
    south along a northbound carrier track) take the southern slots; this keeps
    assembly paths short and mostly uncrossed (docs/scenario.md).

    Raises:
        pydantic.ValidationError: an unknown shape or order, a size not > 0, a rotation not finite.
    """

    shape: Shape = "circle"
    radius_m: float = Field(default=40.0, gt=0)
    slot_order: Literal["sequential", "interleaved"] = "interleaved"
    spacing_m: float = Field(default=5.0, gt=0)
    """Line, grid and wedge: distance between neighbouring slots, m."""
    rotation_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    """Bearing of the shape's forward axis, clockwise from north, degrees."""


@dataclass(config=STRICT)
class Obstacle:
    """A static spherical obstacle in the mission frame (NED, m) that the APF steers
    around (eq. 29-30).

    Raises:
        pydantic.ValidationError: radius_m not > 0, or a coordinate not finite.
    """

    centre_ned_m: Vec3
    radius_m: float = Field(gt=0)


@dataclass(config=STRICT)
class TopologyConfig:
    """Who hears whom in the consensus law (eq. 27-28): the weight matrix Mission builds
    with companion.control.topology, every link of weight `weight`.

    Raises:
        pydantic.ValidationError: an unknown kind, weight not > 0 or k < 1.
    """

    kind: Literal["chain", "ring", "complete", "k_nearest"] = "chain"
    weight: float = Field(default=1.0, gt=0)
    k: int = Field(default=3, ge=1)
    """Neighbour count for k_nearest (by formation offsets)."""


@dataclass(config=STRICT)
class ApfConfig:
    """Eq. 29-30 with the normalisation of docs/formation.md: K4/K5 are peak
    repulsive accelerations, influence distances set where the field vanishes."""

    kappa: float = Field(default=3.0, gt=0)
    vehicle_gain_mps2: float = Field(default=8.0, ge=0)
    """K4, the push from one vehicle at contact, m/s^2. 8: at the 1 m separation the push
    (8 psi(1/4) = 3.6 m/s^2 with the defaults) beats the consensus bound (3 m/s^2), so the
    formation law alone cannot press a vehicle into a neighbour that does not give way (one
    still recovering from its launch); with 6 it could, to 0.8 m (docs/formation.md)."""
    vehicle_influence_m: float = Field(default=4.0, gt=0)
    sensing_radius_m: float = Field(default=10.0, gt=0)
    obstacle_gain_mps2: float = Field(default=10.0, ge=0)
    obstacle_influence_m: float = Field(default=8.0, gt=0)
    closing_decel_mps2: float = Field(default=1.5, ge=0)
    """A pair of vehicles closing in is repelled as if already as close as it will be once
    braked at this deceleration, m/s^2 (docs/formation.md, "Closing speed"); 0: eq. 30 as
    printed (position only). A pair that keeps its distance is pushed as eq. 30 says either way."""


@dataclass(config=STRICT)
class PhaseConfig:
    """Explicit phase-transition thresholds (docs/agent.md)."""

    stable_tilt_deg: float = Field(default=15.0, gt=0)
    """Tilt under which a recovered vehicle counts as calm, deg. A vehicle that holds its
    place in steady wind, or against its estimator's tilt error, hovers tilted: at 5 deg
    (0.87 m/s^2 to hold) a 3-sigma tilt error of paper_40's estimator kept 9 of 100 seeds
    from ever leaving STABILISE. 15 deg still refuses a vehicle mid-recovery (the speed and
    the dwell must hold too)."""
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
class LossEnvelope:
    """The mission's assumption about companion loss (docs/swarm.md, "Ghosts"): for at most
    timeout_s the last setpoint keeps acting, then the autopilot stops within these limits
    and holds ("hold") or lands straight down ("land", which also covers a hold). The
    defaults cover PX4 (COM_OF_LOSS_T 1 s, COM_OBL_RC_ACT 5 Hold, MPC_ACC_HOR 3,
    MPC_JERK_AUTO 4, its 0.6 s stop lead) and ArduPilot GUIDED with GUID_TIMEOUT 1 s
    (WPNAV_ACCEL 2.5, WPNAV_ACCEL_Z 1, PSC_JERK_XY/Z 5), each with its stock limits."""

    timeout_s: float = Field(default=1.0, ge=0)
    """The longest setpoint timeout (PX4 COM_OF_LOSS_T, ArduPilot GUID_TIMEOUT), s."""
    then: Literal["hold", "land"] = "hold"
    """"hold": every autopilot stops and holds (PX4 COM_OBL_RC_ACT 5, ArduPilot GUIDED; what
    `swarmdrop agent --set-loss-action hold` and the fleet harness set); "land": some may land
    straight down where they stop (PX4 4), so every ghost reaches the ground."""
    brake_hor_mps2: float = Field(default=2.5, gt=0)
    """The weakest horizontal deceleration of a stop, m/s^2."""
    brake_ver_mps2: float = Field(default=1.0, gt=0)
    """The weakest vertical deceleration, m/s^2."""
    jerk_hor_mps3: float = Field(default=4.0, gt=0)
    jerk_ver_mps3: float = Field(default=4.0, gt=0)
    stop_lead_s: float = Field(default=0.6, ge=0)
    """The longest lead of an autopilot's own stop point (PX4: 0.6 s), s."""
    descent_speed_mps: float = Field(default=0.7, gt=0)

    def behaviour(self):  # -> companion.link.dialects.base.LossBehaviour
        """As a LossBehaviour (what companion.control.ghost.ghost_capsules takes)."""
        from companion.link.dialects.base import AfterLoss, CarryOn, LossBehaviour, Mode
        return LossBehaviour(self.timeout_s, CarryOn.VELOCITY_ACCELERATION, AfterLoss(self.then), Mode.HOLD,
                             descent_speed_mps=self.descent_speed_mps if self.then == "land" else 0.0,
                             brake_hor_mps2=self.brake_hor_mps2, brake_ver_mps2=self.brake_ver_mps2,
                             jerk_hor_mps3=self.jerk_hor_mps3, jerk_ver_mps3=self.jerk_ver_mps3,
                             stop_lead_s=self.stop_lead_s)

    def exceeded_by(self, loss) -> list[str]:
        """How an autopilot's LossBehaviour goes beyond this envelope ([] if it does not):
        one phrase per limit, naming the autopilot's value and the mission's."""
        return [phrase for _kind, phrase in self.excesses(loss)]

    def excesses(self, loss) -> list[tuple[str, str]]:
        """exceeded_by's phrases with their kind: "timeout" (the setpoint timeout), "action"
        (what the autopilot does after it) or "limit" (braking, jerk, stop lead), which
        decides the fix (companion.node.setup_rules.loss_refusal)."""
        from companion.link.dialects.base import AfterLoss
        tol = 1e-6  # relative: parameters travel as float32
        out = []
        if loss.timeout_s > self.timeout_s * (1.0 + tol) + 1e-9:
            out.append(("timeout", f"its setpoint timeout {loss.timeout_s:g} s is longer than the mission's "
                                   f"{self.timeout_s:g} s"))
        if loss.then == AfterLoss.LAND and self.then == "hold":
            out.append(("action", "it lands where the mission assumes a hold"))
        elif loss.then not in (AfterLoss.HOLD, AfterLoss.LAND):
            out.append(("action", f"it {loss.what_then()}"))
        for name, mine, theirs in (("horizontal braking", loss.brake_hor_mps2, self.brake_hor_mps2),
                                   ("vertical braking", loss.brake_ver_mps2, self.brake_ver_mps2),
                                   ("horizontal jerk", loss.jerk_hor_mps3, self.jerk_hor_mps3),
                                   ("vertical jerk", loss.jerk_ver_mps3, self.jerk_ver_mps3)):
            if mine < theirs * (1.0 - tol):
                out.append(("limit", f"its {name} limit {mine:g} is below the mission's {theirs:g}"))
        if loss.stop_lead_s > self.stop_lead_s * (1.0 + tol) + 1e-9:
            out.append(("limit", f"its stop lead {loss.stop_lead_s:g} s is longer than the mission's "
                                 f"{self.stop_lead_s:g} s"))
        return out


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
    go_stall_s: float = Field(default=30.0, ge=0)
    """A vehicle heard recovering (STABILISE) or trying to assemble (ASSEMBLE) but not
    assembled, e.g. an autopilot that holds it off its slot, holds the start at most this
    long: then the start is proposed without it, if go_quorum of those heard are assembled
    (docs/swarm.md). Vehicles still docked are coming: they are waited for. The laggards
    follow the moving formation from where they are."""
    go_quorum: float = Field(default=0.5, ge=0, le=1)
    """Fraction of the vehicles heard alive that must be assembled for the stall rule."""
    own_timeout_s: float = Field(default=0.5, gt=0)
    """The agent's own state older than this counts as invalid: it commands a stop."""
    ghost_radius_m: float = Field(default=1.0, gt=0)
    """A silent vehicle's size plus its autopilot's hold error, m: the least radius of its
    ghost (companion.control.ghost)."""
    ghost_accel_mps2: float = Field(default=0.5, ge=0)
    """A, the acceleration feed-forward a silent vehicle's ghost allows, m/s^2: at most this,
    and at most the bound the output stage enforced in the state it was last heard in
    (setpoint.acc_ff_hover_mps2 settled at station, on the feed-forward less the learnt bias;
    acc_ff_max_mps2 otherwise), so the ghost is a true bound only where that bound is the
    smaller (docs/swarm.md, "Ghosts")."""
    loss: LossEnvelope = LossEnvelope()
    """What every autopilot of the mission does at worst when its companion falls silent: the
    swarm's shared model of a silent vehicle (every agent draws every ghost from it); each
    agent checks its own autopilot against it at set-up."""


@dataclass(config=STRICT)
class SlotIntegralConfig:
    """Where the agent's integral action on its own slot error (ConsensusGains.ki_pos_per_s3,
    docs/formation.md "Integral action") may grow: near a still slot, with the error stuck
    and the consensus term unsaturated (conditional integration), and how much it may command
    (anti-windup). It learns a steady bias (estimator tilt error, accelerometer bias, a wrong
    hover thrust, steady wind) and holds it while it may not grow. What it integrates leaves
    out what eq. 27's consensus term and eq. 30's repulsion ask of the vehicle, so it learns
    neither a neighbour's lag nor an obstacle's push."""

    zone_m: float = Field(default=3.0, gt=0)
    """It grows only while what is left to learn (the law's residual: a bias b shows as
    b / |k2_pos|, 2.5 m at accel_max with the default gains) is within this (beyond: a transient)."""
    accel_max_mps2: float = Field(default=1.5, gt=0)
    """|k_i z| never exceeds this (covers ~8 deg of tilt error, or a 15 % hover-thrust error)."""
    slot_speed_max_mps: float = Field(default=0.1, ge=0)
    """... and only while the slot itself is (nearly) still (assembly, hover): a path-following
    lag in transit is a transient, not a bias; in transit the integral holds what it learnt."""
    stuck_rate_per_s: float = Field(default=0.25, ge=0)
    """... and only while the error is stuck: the vehicle moves relative to its slot at less than
    this times the residual (+ stuck_speed_mps) per second. eq. 27 alone closes a transient at its
    slowest pole's rate or faster (0.54/s with the default gains: docs/formation.md); a bias
    holds the error still; the integral's own correction closes it at ~0.22/s. So an offset
    that holds is learnt, a transient's tail is not (it would leave a residue to unlearn)."""
    stuck_speed_mps: float = Field(default=0.005, ge=0)
    """Speed allowance of the stuck test (estimator noise near the slot), m/s."""
    dt_max_s: float = Field(default=0.2, gt=0)
    """A longer gap between plans (a stall, lost telemetry) integrates as this long."""
    autopilot_ki_per_s3: float = Field(default=0.1, ge=0, allow_inf_nan=False)
    """Acceleration output, on the axes where the autopilot has a velocity integrator (PX4
    horizontal and vertical, ArduPilot horizontal): the same gated residual is also driven
    into that integrator through the position target, so that it learns at this rate
    (companion.slot_hold; docs/agent.md, "Whose integrator"). 0: not driven. The law's
    stability is checked with ki_pos_per_s3 plus this (the driven axes)."""
    drive_zone_m: float = Field(default=10.0, gt=0)
    """The drive acts while the error is stuck and the residual within this (the agent's own
    integral: zone_m, a still slot, unsaturated): it also unwinds an autopilot integrator
    wound against the agent (docs/agent.md, "Whose integrator")."""
    drive_max_m: float = Field(default=1.0, gt=0)
    """The drive moves the position target at most this far (a silent vehicle's autopilot
    keeps the last target: the ghost's radius must cover it)."""


@dataclass(config=STRICT)
class HoverThrustConfig:
    """The online hover-thrust estimate of attitude output (companion.output.HoverThrustEstimator).

    Raises:
        pydantic.ValidationError: a value out of its range.
    """

    window_s: float = Field(default=0.5, gt=0, le=5.0)
    """The vertical acceleration is measured over windows this long (velocity change over
    the window: the noise of one velocity sample is spread over it)."""
    tau_s: float = Field(default=2.0, gt=0)
    """Time constant of the estimate (a first-order filter over the windows' measurements)."""
    bound_frac: float = Field(default=0.2, gt=0, lt=1)
    """The estimate stays within the parameter's value times 1 -+ this (PX4's estimator
    allows +-0.2 around MPC_THR_HOVER as well)."""
    tilt_max_deg: float = Field(default=30.0, gt=0, lt=90)
    """Windows flown more tilted than this are not used (the thrust model is least sure there)."""


@dataclass(config=STRICT)
class SetpointConfig:
    """What the agent sends in formation phases (docs/agent.md)."""

    kind: Literal["state", "acceleration"] = "state"
    """"state": position, velocity and acceleration that agree (the state eq. 31's
    acceleration leads to lead_s ahead); "acceleration": the acceleration alone."""
    lead_s: float = Field(default=0.02, ge=0)
    """Horizon of the state setpoint; the setpoint period."""
    acc_ff_max_mps2: float = Field(default=3.0, gt=0)
    """Bound on the acceleration feed-forward sent (norm; the output stage, companion.output).
    An autopilot that loses its companion keeps acting on it (ArduPilot for GUID_TIMEOUT T, PX4
    for COM_OF_LOSS_T), so it bounds the overshoot on loss: v T + acc_ff_max T^2 / 2
    (docs/agent.md). 3 m/s^2 is the consensus term's own bound; on paper_40 the planner asks
    more than that in 0.13 % of its commands (the repulsion, briefly)."""
    acc_ff_hover_mps2: float = Field(default=3.0, gt=0)
    """The feed-forward bound for a vehicle settled at station (HOVER, slower than
    phases.assembled_speed_mps), m/s^2, at most acc_ff_max_mps2, on the acceleration *less the
    bias the agent has learnt* (its slot-hold integral: that part moves nothing and keeps
    cancelling the bias after a loss). At or under swarm.ghost_accel_mps2 (0.5) the ghost of a
    vehicle that falls silent there is a true bound (docs/swarm.md, "Ghosts"). Off by default:
    with a wandering GPS error (0.3 m) the vehicles need more than 0.5 to follow their
    estimates, and small_6 ended 1.27 m off instead of under 1 m (tests/test_estimator.py).
    Bounding the whole feed-forward instead left vehicles circling their slots 0.3-0.6 m off
    (paper_40's shipped bias needs up to 0.75 m/s^2 at station on seed 15)."""
    hover_thrust: HoverThrustConfig = HoverThrustConfig()
    """Attitude output's online hover-thrust estimate."""

    def __post_init__(self) -> None:
        if self.acc_ff_hover_mps2 > self.acc_ff_max_mps2:
            raise ValueError(f"acc_ff_hover_mps2 {self.acc_ff_hover_mps2} must be at most acc_ff_max_mps2 "
                             f"{self.acc_ff_max_mps2}")


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
    """The mission as YAML holds it (scenario `mission:`, or a mission file for
    `swarmdrop agent`): formation, centre path (NED metres in the mission frame), obstacles,
    topology, gains, phase thresholds, swarm link, setpoint form and launch. Mission is the
    form an agent flies by.

    Raises:
        pydantic.ValidationError: a value out of range, an unknown key, or no waypoint.
    """

    n_vehicles: int = Field(default=40, ge=1, le=10_000)
    """Vehicles in the mission. 10,000 bounds what validation itself allocates; each runner
    has a lower limit of its own (headless 1,000; MAVLink 250: docs/scenario.md)."""
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
    slot_integral: SlotIntegralConfig = SlotIntegralConfig()
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

    @property
    def stability_gains(self) -> ConsensusGains:
        """The gains the closed loop is checked with: eq. 27's with the integral rate of the
        driven axes (the agent's plus the autopilot's: the larger, the less damped)."""
        c = self.consensus
        if c.ki_pos_per_s3 <= 0.0:
            return c
        return dataclasses.replace(c, ki_pos_per_s3=c.ki_pos_per_s3 + self.slot_integral.autopilot_ki_per_s3)

    @model_validator(mode="after")
    def _need_waypoint(self):
        if len(self.waypoints_ned_m) < 1:
            raise ValueError("waypoints_ned_m needs at least the assembly point")
        return self


def formation_offsets_ned_m(cfg: FormationConfig, n: int) -> np.ndarray:
    """Slot offsets r_i of eq. 25 of the config's shape, (n, 3) NED metres: slot i is vehicle
    i's (companion.control.shapes.offsets_for, the one home of every shape)."""
    return offsets_for(spec_from_config(cfg), n)


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
        self.weights = build_topology(cfg.topology, self.offsets_ned_m)
        self.neighbours = topology.neighbour_table(self.weights)
        """(N, K) indices of the vehicles each one hears (-1 padded): the consensus loop
        visits only these, not all N columns of the weight matrix."""
        self.closed_loop_eigenvalues = check_stability(self.weights, cfg.stability_gains)
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


def build_topology(cfg: TopologyConfig, offsets_ned_m: np.ndarray) -> np.ndarray:
    """The consensus weights W (N, N) of a topology over N vehicles whose slot offsets are
    offsets_ned_m (only k_nearest reads them), as every agent builds them."""
    n = len(offsets_ned_m)
    if cfg.kind == "chain":
        return topology.chain(n, cfg.weight)
    if cfg.kind == "ring":
        return topology.ring(n, cfg.weight)
    if cfg.kind == "complete":
        return topology.complete(n, cfg.weight)
    return topology.k_nearest(offsets_ned_m, min(cfg.k, max(n - 1, 1)), cfg.weight)
