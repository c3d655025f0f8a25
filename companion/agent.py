"""The sans-IO swarm agent: one code path for one vehicle or a batch of vehicles.

`Agent.step` takes the time, the agent's own vehicles' states and the swarm view
(everything heard about every vehicle, NaN where nothing is known) and returns
setpoints plus phases. It opens no socket and reads no clock: the headless
runner calls it in-process, the MAVLink companion wraps it for one vehicle.

Phases and their transitions (docs/agent.md):
    LAUNCH    -> STABILISE  when the vehicle is released from the carrier;
    STABILISE -> ASSEMBLE   when tilt < stable_tilt_deg and |v| < stable_speed_mps
                            have held for stable_dwell_s;
    ASSEMBLE  -> TRANSIT    at t_go: the first go_quantum_s boundary after every
                            vehicle of the swarm has reported "assembled";
    TRANSIT   -> HOVER      when the formation centre reaches the last waypoint;
    HOVER     -> LAND       land_after_hover_s after hover began, if configured.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from companion.control import apf
from companion.control.formation import consensus_accel, formation_reference
from companion.mission import Mission
from companion.state import FleetSetpoint


class Phase(IntEnum):
    LAUNCH = 0
    STABILISE = 1
    ASSEMBLE = 2
    TRANSIT = 3
    HOVER = 4
    LAND = 5


FORMATION_PHASES = (Phase.ASSEMBLE, Phase.TRANSIT, Phase.HOVER)
# Plain ints for the per-tick code: IntEnum attribute access costs ~1 us each.
_LAUNCH, _STABILISE, _ASSEMBLE, _TRANSIT, _HOVER, _LAND = (int(p) for p in Phase)
IN_FORMATION = np.isin(np.arange(len(Phase)), [int(p) for p in FORMATION_PHASES])  # lookup by phase value


def _norm_rows(a: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of an (n, 3) array (cheaper than np.linalg.norm)."""
    return np.sqrt(np.einsum("ij,ij->i", a, a))


@dataclass
class OwnState:
    """What an agent knows of its own n vehicles (from its autopilot).

    Attributes:
        pos_ned_m: (n, 3) NED position, m.
        vel_ned_mps: (n, 3) NED velocity, m/s.
        tilt_rad: (n,) angle between body z and world z, rad.
        released: (n,) bool, True once the vehicle has left the carrier.
    """

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    tilt_rad: np.ndarray
    released: np.ndarray


@dataclass
class SwarmView:
    """The latest known state of every vehicle of the swarm, indexed by vehicle id.

    Attributes:
        pos_ned_m: (N, 3), NaN rows for vehicles nothing is known of (docked, not heard).
        vel_ned_mps: (N, 3), likewise.
        phase: (N,) int Phase values (LAUNCH when unknown).
        assembled: (N,) bool, the vehicle has reached its slot at least once.
    """

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    phase: np.ndarray
    assembled: np.ndarray

    @classmethod
    def unknown(cls, n: int) -> "SwarmView":
        return cls(
            np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.zeros(n, dtype=np.int8), np.zeros(n, dtype=bool)
        )


@dataclass
class AgentOutput:
    """Setpoints (n rows, NaN = not commanded), phases and assembled flags of the
    agent's own vehicles, plus the agreed transit start time (NaN until known)."""

    setpoint: FleetSetpoint
    phase: np.ndarray
    assembled: np.ndarray
    t_go_s: float


class Agent:
    """Consensus-APF planner for the vehicles `ids` of a mission.

    Args:
        mission: the shared mission (every agent derives the same one).
        ids: (n,) vehicle ids this agent flies: one id on a companion computer,
            all ids in the headless runner.
    """

    def __init__(self, mission: Mission, ids: np.ndarray):
        self.mission = mission
        self.ids = np.asarray(ids, dtype=int)
        n = len(self.ids)
        self.phase = np.full(n, _LAUNCH, dtype=np.int8)
        self.stable_since_s = np.full(n, np.nan)
        self.assembled = np.zeros(n, dtype=bool)
        self.t_go_s = np.nan

    # ------------------------------------------------------------------ phases
    def _advance_phases(self, t_s: float, own: OwnState, swarm: SwarmView) -> None:
        ph = self.mission.cfg.phases
        phase = self.phase
        phase[(phase == _LAUNCH) & own.released] = _STABILISE

        stab = phase == _STABILISE
        calm = (own.tilt_rad < np.radians(ph.stable_tilt_deg)) & (
            _norm_rows(own.vel_ned_mps) < ph.stable_speed_mps
        )
        self.stable_since_s[stab & calm & np.isnan(self.stable_since_s)] = t_s
        self.stable_since_s[stab & ~calm] = np.nan
        done = stab & calm & (t_s - self.stable_since_s >= ph.stable_dwell_s - 1e-9)
        phase[done] = _ASSEMBLE

        if np.isnan(self.t_go_s) and bool(np.all(swarm.assembled)):
            q = ph.go_quantum_s
            self.t_go_s = (np.floor(t_s / q + 1e-9) + 1.0) * q
        if not np.isnan(self.t_go_s):
            t_hover = self.t_go_s + self.mission.path.duration_s
            phase[(phase == _ASSEMBLE) & (t_s >= self.t_go_s)] = _TRANSIT
            phase[(phase == _TRANSIT) & (t_s >= t_hover)] = _HOVER
            if ph.land_after_hover_s is not None:
                phase[(phase == _HOVER) & (t_s >= t_hover + ph.land_after_hover_s)] = _LAND

    # ---------------------------------------------------------------- planner
    def _merged_view(self, own: OwnState, swarm: SwarmView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The swarm view with this agent's own vehicles overwritten by what it
        knows first-hand: positions (N, 3), velocities (N, 3), phases (N,)."""
        pos, vel, phase = swarm.pos_ned_m.copy(), swarm.vel_ned_mps.copy(), swarm.phase.copy()
        pos[self.ids], vel[self.ids], phase[self.ids] = own.pos_ned_m, own.vel_ned_mps, self.phase
        return pos, vel, phase

    def _formation_accel(self, t_s: float, rows: np.ndarray, own: OwnState, swarm: SwarmView) -> np.ndarray:
        """Eq. 31 for the own vehicles `rows` (indices into self.ids): (len(rows), 3)."""
        m = self.mission
        cfg = m.cfg
        c_pos, c_vel, c_acc = m.path.at(m.tau_s(t_s, self.t_go_s))
        h_pos, h_vel, h_acc = formation_reference(m.offsets_ned_m, c_pos, c_vel, c_acc)

        ids = self.ids[rows]
        pos, vel, phase = self._merged_view(own, swarm)
        known = np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(vel), axis=1)
        # A neighbour takes part in consensus once it is flying in formation; until
        # then its (unknown or tumbling) state would only disturb its followers.
        in_formation = known & IN_FORMATION[phase]
        weights = m.weights * in_formation[None, :]
        # Saturate every vehicle's slot error at formation_error_max_m by sliding
        # its reference towards it; inside that radius this is eq. 27 exactly.
        err = np.nan_to_num(pos - h_pos)
        norm = _norm_rows(err)[:, None]
        excess = np.maximum(0.0, 1.0 - cfg.formation_error_max_m / np.maximum(norm, 1e-12))
        h_sat = h_pos + excess * err
        u1 = consensus_accel(pos, vel, h_sat, h_vel, h_acc, weights, cfg.consensus, rows=ids)

        # Repulsion from every airborne vehicle heard within the sensing radius
        # (stabilising ones included), whatever the consensus topology.
        airborne = known & (phase >= _STABILISE)
        others = np.where(airborne[:, None], pos, np.nan)
        a = cfg.apf
        u2 = apf.vehicle_repulsion(
            pos[ids], others, a.vehicle_gain_mps2, a.vehicle_influence_m, a.sensing_radius_m, a.kappa,
            self_index=ids,
        )
        if len(m.obstacle_radii_m):
            u2 = u2 + apf.obstacle_repulsion(
                pos[ids], m.obstacle_centres_ned_m, m.obstacle_radii_m, a.obstacle_gain_mps2,
                a.obstacle_influence_m, a.kappa,
            )
        return apf.combined_accel(u1, u2, cfg.consensus_accel_max_mps2, cfg.total_accel_max_mps2), h_pos[ids], h_vel[ids]

    def step(self, t_s: float, own: OwnState, swarm: SwarmView) -> AgentOutput:
        """Advance phases and compute setpoints for the agent's own vehicles.

        Args:
            t_s: mission time, s (the same clock for the whole swarm).
            own: states of this agent's vehicles, rows in the order of `ids`.
            swarm: the latest known states of all N vehicles (own rows included or not).
        Returns:
            AgentOutput with n setpoint rows.
        """
        self._advance_phases(t_s, own, swarm)
        n = len(self.ids)
        sp = FleetSetpoint.empty(n)
        phase = self.phase

        stab = phase == _STABILISE
        sp.vel_ned_mps[stab] = 0.0  # brake and level; yaw NaN holds the current heading

        rows = np.flatnonzero(IN_FORMATION[phase])
        if len(rows):
            acc, h_pos, h_vel = self._formation_accel(t_s, rows, own, swarm)
            sp.acc_ned_mps2[rows] = acc
            sp.yaw_rad[rows] = self.mission.yaw_rad
            ph = self.mission.cfg.phases
            near = (_norm_rows(own.pos_ned_m[rows] - h_pos) < ph.assembled_pos_m) & (
                _norm_rows(own.vel_ned_mps[rows] - h_vel) < ph.assembled_speed_mps
            )
            self.assembled[rows[near]] = True

        land = phase == _LAND
        sp.vel_ned_mps[land] = [0.0, 0.0, self.mission.cfg.phases.land_speed_mps]
        sp.yaw_rad[land] = self.mission.yaw_rad
        return AgentOutput(sp, phase.copy(), self.assembled.copy(), self.t_go_s)
