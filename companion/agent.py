"""The sans-IO swarm agent: one code path for one vehicle or a batch of vehicles.

`Agent.step(t_s, own, view)` takes the mission time, the agent's own vehicles'
states (from their autopilots) and what each of them has heard of the swarm
(`companion.swarm.SwarmView`, one receiver row per own vehicle), and returns
setpoints, phases and the states to publish. It opens no socket and reads no
clock: the headless runner calls it for every vehicle at once, a companion
computer for its one vehicle, through the same lines.

Phases and their transitions (docs/agent.md):
    LAUNCH    -> STABILISE  the vehicle has left the carrier (or the ground);
    STABILISE -> ASSEMBLE   its autopilot reports it ready (throw recovery or take-off
                            done) and tilt < stable_tilt_deg, |v| < stable_speed_mps
                            have held for stable_dwell_s; until then the agent
                            commands nothing: the autopilot owns the recovery;
    ASSEMBLE  -> TRANSIT    at t_go, agreed by the swarm (docs/swarm.md);
    TRANSIT   -> HOVER      when the formation centre reaches the last waypoint;
    HOVER     -> LAND       land_after_hover_s after hover began, if configured;
    any of ASSEMBLE..LAND -> FAILED  the vehicle has lost control: tilt beyond
                            lost_tilt_deg for lost_dwell_s (PX4's failure detector
                            thresholds). FAILED is final: the agent commands nothing
                            (its autopilot's failsafe owns the vehicle) and keeps
                            publishing, so that its neighbours avoid it and leave it
                            out of consensus and of the transit-start quorum.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Callable

import numpy as np

from companion.control.apf import clip_sum_rows, pair_repulsion_rows, segment_repulsion_rows
from companion.control.formation import consensus_rows, gains_vector
from companion.control.kernel import kernel
from companion.mission import Mission
from companion.state import FleetSetpoint
from companion.swarm import FLAG_ASSEMBLED, FLAG_OWN_VALID, FLAG_READY, SwarmStates, SwarmView


class Phase(IntEnum):
    LAUNCH = 0
    STABILISE = 1
    ASSEMBLE = 2
    TRANSIT = 3
    HOVER = 4
    LAND = 5
    FAILED = 6


FORMATION_PHASES = (Phase.ASSEMBLE, Phase.TRANSIT, Phase.HOVER)
# Plain ints for the per-tick code: IntEnum attribute access costs ~1 us each.
_LAUNCH, _STABILISE, _ASSEMBLE, _TRANSIT, _HOVER, _LAND, _FAILED = (int(p) for p in Phase)
IN_FORMATION = np.isin(np.arange(len(Phase)), [int(p) for p in FORMATION_PHASES])  # lookup by phase value
GHOST_COLUMN_M = 100.0
"""Depth of a silent vehicle's column when the ground height is unknown."""


def _norm_rows(a: np.ndarray) -> np.ndarray:
    """Euclidean norm along the last axis (cheaper than np.linalg.norm)."""
    return np.sqrt(np.einsum("...i,...i->...", a, a))


@kernel
def neighbour_sets_rows(rows, ids, p, v_pos, v_vel, v_flags, v_phase, age, stale_after_s, in_formation, cutoff_m,
                        pred, usable, repel, ghost):
    """Who each own row uses for what this tick (docs/agent.md, "Who takes part in what").

    Row r (own vehicle ids[r], view row rows[r]) and vehicle j:
      trusted: heard within stale_after_s, published with FLAG_OWN_VALID, position and
        velocity finite (p.v not NaN), not the own vehicle;
      pred[r, j] = p_j + v_j age (trusted), p_j otherwise;
      usable: trusted and in a formation phase (consensus);
      repel: trusted, airborne (phase >= STABILISE) and within cutoff_m of the own
        position (pair repulsion; the kernel checks the cutoff again);
      ghost: heard, not trusted, airborne, with a position, not the own vehicle.

    Args: rows, ids (R,); p (R, 3); v_pos, v_vel (n, N, 3), v_flags, v_phase, age (n, N):
        the whole view; in_formation: bool by phase value. Outputs pred (R, N, 3),
        usable, repel, ghost (R, N) bool, written.
    """
    c2 = cutoff_m * cutoff_m
    for r in range(rows.shape[0]):
        vr, own = rows[r], ids[r]
        for j in range(v_pos.shape[1]):
            a = age[vr, j]
            x0, x1, x2 = v_pos[vr, j, 0], v_pos[vr, j, 1], v_pos[vr, j, 2]
            u0, u1, u2 = v_vel[vr, j, 0], v_vel[vr, j, 1], v_vel[vr, j, 2]
            ph = v_phase[vr, j]
            known = not math.isnan(x0 * u0 + x1 * u1 + x2 * u2)
            tr = a <= stale_after_s and (v_flags[vr, j] & FLAG_OWN_VALID) != 0 and known and j != own
            air = ph >= _STABILISE
            if tr:
                x0, x1, x2 = x0 + u0 * a, x1 + u1 * a, x2 + u2 * a
            pred[r, j, 0], pred[r, j, 1], pred[r, j, 2] = x0, x1, x2
            usable[r, j] = tr and in_formation[ph]
            if tr and air:
                d0, d1, d2 = x0 - p[r, 0], x1 - p[r, 1], x2 - p[r, 2]
                repel[r, j] = d0 * d0 + d1 * d1 + d2 * d2 < c2
            else:
                repel[r, j] = False
            ghost[r, j] = a < math.inf and not tr and air and not math.isnan(x0) and j != own


@kernel
def own_checks_rows(t_s, pos, vel, q, stamp_s, own_timeout_s, valid, cos_tilt):
    """Whether each own state can be flown on, and how upright the vehicle is.

    valid[i]: position, velocity and attitude quaternion all finite, and measured no more
    than own_timeout_s before t_s. cos_tilt[i]: R[2, 2] of the attitude (1 level, -1
    inverted), from the quaternion normalised (a zero quaternion is invalid anyway).

    Args: pos, vel (n, 3); q (n, 4) w first; stamp_s (n,). Written: valid (n,) bool,
        cos_tilt (n,).
    """
    for i in range(pos.shape[0]):
        # One sum is finite iff every term is (a NaN or an inf anywhere poisons it).
        total = ((pos[i, 0] + pos[i, 1]) + pos[i, 2]) + ((vel[i, 0] + vel[i, 1]) + vel[i, 2]) \
            + (((q[i, 0] + q[i, 1]) + q[i, 2]) + q[i, 3])
        valid[i] = math.isfinite(total) and t_s - stamp_s[i] <= own_timeout_s
        qn2 = max(q[i, 0] * q[i, 0] + q[i, 1] * q[i, 1] + q[i, 2] * q[i, 2] + q[i, 3] * q[i, 3], 1e-300)
        cos_tilt[i] = 1.0 - 2.0 * (q[i, 1] * q[i, 1] + q[i, 2] * q[i, 2]) / qn2


@kernel
def finish_rows(rows, p, v, acc, h_pos, h_vel, valid, ready, phase, state_kind, lead_s, yaw_rad, land_speed_mps,
                assembled_pos_m, assembled_speed_mps, sp_pos, sp_vel, sp_acc, sp_yaw, slot, assembled, flags):
    """The setpoints, slots, assembled and published flags of a tick (Agent.step).

    Formation row rows[r] (index into the own vehicles) flies acc[r]: as an acceleration,
    and with state_kind also as the state it leads to lead_s ahead (p + v lead +
    acc lead^2 / 2, v + acc lead), so that if the stream stops the autopilot holds near
    where the vehicle was heading; it is assembled once within assembled_pos_m of its
    slot h_pos[r] and assembled_speed_mps of the slot's velocity. Then every own
    vehicle: an invalid own state in ASSEMBLE or later stops (zero velocity, flown on
    the autopilot's own estimate); LAND descends at land_speed_mps; flags gets the
    FLAG_* bits.

    Args: rows (R,); p, v (n, 3) own state; acc, h_pos, h_vel (R, 3); valid, ready (n,)
        bool; phase (n,). Written: sp_pos, sp_vel, sp_acc, slot (n, 3), sp_yaw (n,)
        (NaN where not commanded, as given), assembled (n,) bool, flags (n,) uint8.
    """
    for r in range(rows.shape[0]):
        i = rows[r]
        d2 = 0.0
        e2 = 0.0
        for a in range(3):
            pa, va, aa = p[i, a], v[i, a], acc[r, a]
            sp_acc[i, a] = aa
            if state_kind:
                sp_pos[i, a] = pa + va * lead_s + 0.5 * aa * lead_s * lead_s
                sp_vel[i, a] = va + aa * lead_s
            slot[i, a] = h_pos[r, a]
            d2 += (pa - h_pos[r, a]) ** 2
            e2 += (va - h_vel[r, a]) ** 2
        sp_yaw[i] = yaw_rad
        if math.sqrt(d2) < assembled_pos_m and math.sqrt(e2) < assembled_speed_mps:
            assembled[i] = True
    for i in range(phase.shape[0]):
        if not valid[i] and phase[i] >= _ASSEMBLE:
            sp_vel[i, 0], sp_vel[i, 1], sp_vel[i, 2] = 0.0, 0.0, 0.0
        elif valid[i] and phase[i] == _LAND:
            sp_vel[i, 0], sp_vel[i, 1], sp_vel[i, 2] = 0.0, 0.0, land_speed_mps
            sp_yaw[i] = yaw_rad
        f = 0
        if assembled[i]:
            f |= FLAG_ASSEMBLED
        if valid[i]:
            f |= FLAG_OWN_VALID
        if ready[i]:
            f |= FLAG_READY
        flags[i] = f


@dataclass
class OwnState:
    """What an agent knows of its own n vehicles, first hand (from their autopilots).

    Attributes:
        pos_ned_m: (n, 3) position, mission NED frame, m.
        vel_ned_mps: (n, 3) velocity, mission NED frame, m/s.
        att_q_wxyz: (n, 4) attitude NED->FRD, w first.
        stamp_s: (n,) mission time at which this state was measured, s.
        released: (n,) bool, the vehicle has left the carrier (or the ground).
        ready: (n,) bool, its autopilot has finished the launch recovery (throw
            recovery or take-off) and accepts offboard setpoints.
    """

    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    att_q_wxyz: np.ndarray
    stamp_s: np.ndarray
    released: np.ndarray
    ready: np.ndarray


@dataclass(frozen=True)
class AgentKernels:
    """The per-vehicle loops the agent calls: plain Python by default (onboard);
    the simulator passes numba-compiled twins of the same functions (sim_bridge.jit)."""

    consensus_rows: Callable = consensus_rows
    neighbour_sets_rows: Callable = neighbour_sets_rows
    pair_repulsion_rows: Callable = pair_repulsion_rows
    segment_repulsion_rows: Callable = segment_repulsion_rows
    clip_sum_rows: Callable = clip_sum_rows
    own_checks_rows: Callable = own_checks_rows
    finish_rows: Callable = finish_rows


@dataclass
class AgentOutput:
    """What one step decided for the agent's n vehicles.

    Attributes:
        setpoint: n rows, NaN = not commanded (an all-NaN row: send nothing).
        phase: (n,) Phase values.
        assembled: (n,) bool, reached the slot at least once.
        t_go_s: (n,) transit start each vehicle holds, s (NaN = not agreed yet).
        own_valid: (n,) bool, the own state was finite and fresh.
        slot_ned_m: (n, 3) each vehicle's formation slot h_i(t) (NaN before ASSEMBLE).
        published: the n states to share with the swarm.
    """

    setpoint: FleetSetpoint
    phase: np.ndarray
    assembled: np.ndarray
    t_go_s: np.ndarray
    own_valid: np.ndarray
    slot_ned_m: np.ndarray
    published: SwarmStates = field(repr=False)


class Agent:
    """Consensus-APF planner for the vehicles `ids` of a mission.

    Args:
        mission: the shared mission (every agent derives the same one).
        ids: (n,) vehicle ids this agent flies: one id on a companion computer,
            all ids in the headless runner.
        kernels: the loops to run (default: interpreted, no JIT).
    """

    def __init__(self, mission: Mission, ids: np.ndarray, kernels: AgentKernels | None = None):
        self.mission = mission
        self.ids = np.asarray(ids, dtype=np.int64)
        self.kernels = kernels or AgentKernels()
        n = len(self.ids)
        self._rows = np.arange(n)
        self.phase = np.full(n, _LAUNCH, dtype=np.int8)
        self.stable_since_s = np.full(n, np.nan)
        self.assembled = np.zeros(n, dtype=bool)
        self.t_go_s = np.full(n, np.nan)
        self.go_ready_since_s = np.full(n, np.nan)
        self.lost_since_s = np.full(n, np.nan)
        self._lost_pending = False
        cfg = mission.cfg
        self._k = gains_vector(cfg.consensus)
        self._cos_tilt_max = math.cos(math.radians(cfg.phases.stable_tilt_deg))
        self._cos_lost = math.cos(math.radians(cfg.phases.lost_tilt_deg))
        k = self._n_obstacles = len(mission.obstacle_radii_m)
        # Static obstacles as zero-length capsules, one copy per own row (read-only views).
        self._obs_ends = np.broadcast_to(mission.obstacle_centres_ned_m, (n, k, 3))
        self._obs_r = np.broadcast_to(mission.obstacle_radii_m, (n, k))
        self._obs_use = np.broadcast_to(True, (n, k))
        self._no_rows = np.empty((0, 3))

    # ------------------------------------------------------------------ phases
    def _advance_phases(self, t_s: float, own: OwnState, valid: np.ndarray, cos_tilt: np.ndarray) -> None:
        ph = self.mission.cfg.phases
        phase = self.phase
        if phase.min() <= _STABILISE:  # (skipped once every own vehicle flies formation)
            phase[(phase == _LAUNCH) & own.released] = _STABILISE
            stab = phase == _STABILISE
            calm = valid & own.ready & (cos_tilt > self._cos_tilt_max) & (
                _norm_rows(own.vel_ned_mps) < ph.stable_speed_mps)
            self.stable_since_s[stab & calm & np.isnan(self.stable_since_s)] = t_s
            self.stable_since_s[stab & ~calm] = np.nan
            done = stab & calm & (t_s - self.stable_since_s >= ph.stable_dwell_s - 1e-9)
            phase[done] = _ASSEMBLE

        go = self.t_go_s
        has_go = ~np.isnan(go)
        if has_go.any():
            t_hover = go + self.mission.path.duration_s
            phase[(phase == _ASSEMBLE) & has_go & (t_s >= go)] = _TRANSIT
            phase[(phase == _TRANSIT) & (t_s >= t_hover)] = _HOVER
            if ph.land_after_hover_s is not None:
                phase[(phase == _HOVER) & (t_s >= t_hover + ph.land_after_hover_s)] = _LAND

        # Loss of control (a rotor gone): judged only once the launch recovery is over,
        # since a tumbling vehicle in STABILISE is the normal case there.
        over = cos_tilt < self._cos_lost
        if self._lost_pending or over.any():  # (skipped while nobody is tilted that far)
            tilted = (phase >= _ASSEMBLE) & (phase != _FAILED) & valid & over
            self.lost_since_s[tilted & np.isnan(self.lost_since_s)] = t_s
            self.lost_since_s[~tilted] = np.nan
            phase[tilted & (t_s - self.lost_since_s >= ph.lost_dwell_s - 1e-9)] = _FAILED
            self._lost_pending = bool(tilted.any())

    def _agree_t_go(self, t_s: float, view: SwarmView, age: np.ndarray) -> None:
        """The transit-start rule (docs/swarm.md): adopt the earliest t_go heard; with
        none, propose t + go_margin_s (rounded up to go_quantum_s) once this vehicle
        and every vehicle heard within peer_timeout_s report assembled, and either all
        N have been heard so, or that has held for go_wait_s."""
        sw, n_veh = self.mission.cfg.swarm, self.mission.n
        heard = np.fmin.reduce(view.t_go_s, axis=1) if n_veh else np.full(len(self.ids), np.nan)
        self.t_go_s = np.fmin(self.t_go_s, heard)
        pending = np.isnan(self.t_go_s)
        if not pending.any():
            return
        r, ids = self._rows, self.ids
        failed = view.phase == _FAILED  # heard to have lost control: not waited for
        failed[r, ids] = self.phase == _FAILED
        alive = (age <= sw.peer_timeout_s) & ~failed
        alive[r, ids] = ~failed[r, ids]
        asm = view.assembled()
        asm[r, ids] = self.assembled
        cond = self.assembled & ~failed[r, ids] & np.all(asm | ~alive, axis=1)
        self.go_ready_since_s = np.where(cond, np.fmin(self.go_ready_since_s, t_s), np.nan)
        everyone = np.sum((alive & asm) | failed, axis=1) == n_veh
        propose = pending & cond & (everyone | (t_s - self.go_ready_since_s >= sw.go_wait_s - 1e-9))
        if propose.any():
            q = self.mission.cfg.phases.go_quantum_s
            self.t_go_s[propose] = math.ceil((t_s + sw.go_margin_s) / q - 1e-9) * q

    # ---------------------------------------------------------------- planner
    def _formation_accel(self, t_s: float, rows: np.ndarray, own: OwnState, view: SwarmView,
                         age: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 31 for the own rows `rows` (indices into self.ids).

        Returns (acceleration (R, 3), slot h_i (R, 3), slot velocity (R, 3))."""
        m = self.mission
        cfg, sw, a, kern = m.cfg, m.cfg.swarm, m.cfg.apf, self.kernels
        n_rows = len(rows)
        ids = self.ids[rows]
        p, v = own.pos_ned_m[rows], own.vel_ned_mps[rows]
        n_veh = view.n_vehicles
        pred = np.empty((n_rows, n_veh, 3))
        usable, repel, ghost = (np.empty((n_rows, n_veh), np.bool_) for _ in range(3))
        kern.neighbour_sets_rows(rows, ids, p, view.pos_ned_m, view.vel_ned_mps, view.flags, view.phase, age,
                                 sw.stale_after_s, IN_FORMATION, min(a.sensing_radius_m, a.vehicle_influence_m),
                                 pred, usable, repel, ghost)
        # Every own row flies formation (the usual case): the view's arrays, not row copies.
        whole = n_rows == view.n_receivers
        vv = view.vel_ned_mps if whole else view.vel_ned_mps[rows]

        u1, h_pos_rows, h_vel_rows = self._consensus(t_s, self.t_go_s[rows], p, v, ids, pred, vv, usable)

        u2 = np.zeros((n_rows, 3))
        kern.pair_repulsion_rows(p, pred, repel, ids, a.vehicle_gain_mps2, a.vehicle_influence_m,
                                 min(a.sensing_radius_m, a.vehicle_influence_m), a.kappa, u2)
        if ghost.any():
            top, bottom = self._ghost_columns(view.pos_ned_m if whole else view.pos_ned_m[rows], vv)
            kern.segment_repulsion_rows(p, top, bottom, np.full(ghost.shape, sw.ghost_radius_m), ghost,
                                        a.vehicle_gain_mps2, a.vehicle_influence_m, a.kappa, u2)
        if self._n_obstacles:
            kern.segment_repulsion_rows(p, self._obs_ends[:n_rows], self._obs_ends[:n_rows], self._obs_r[:n_rows],
                                        self._obs_use[:n_rows], a.obstacle_gain_mps2, a.obstacle_influence_m, a.kappa,
                                        u2)
        acc = np.empty((n_rows, 3))
        kern.clip_sum_rows(u1, u2, cfg.consensus_accel_max_mps2, cfg.total_accel_max_mps2, acc)
        return acc, h_pos_rows, h_vel_rows

    def _consensus(self, t_s, go, p, v, ids, pred, vv, usable):
        """Eq. 27 for the rows, each on the reference of the transit start it holds
        (go (R,), NaN = none agreed yet: the assembly point). Rows holding different
        transit starts fly different references; usually there is one.
        Returns (u1, slot, slot velocity), each (R, 3); u1 is NaN in a row that read a
        non-finite value (excluded by the checks of _formation_accel: never flown)."""
        m = self.mission
        gl = go.tolist()  # Python's list beats numpy's per-call cost here
        g0 = gl[0]
        one_ref = gl.count(g0) == len(gl) if g0 == g0 else all(x != x for x in gl)  # (NaN != NaN)
        if one_ref:
            groups, h_sel = [g0], np.zeros(len(gl), np.int64)
        else:
            keys, h_sel = np.unique(np.where(np.isnan(go), -np.inf, go), return_inverse=True)
            groups = [math.nan if g == -np.inf else g for g in keys.tolist()]
        n_ref = len(groups)
        h_pos, h_vel, h_acc = (np.empty((n_ref, m.n, 3)) for _ in range(3))
        for g, t_go_s in enumerate(groups):
            c_pos, c_vel, c_acc = m.path.at(m.tau_s(t_s, t_go_s))
            h_pos[g] = m.offsets_ned_m + c_pos
            h_vel[g] = c_vel  # every slot moves with the centre
            h_acc[g] = c_acc
        out = np.empty((len(ids), 3))
        self.kernels.consensus_rows(p, v, ids, pred, vv, usable, h_pos, h_vel, h_acc, h_sel, m.weights, m.neighbours,
                                    self._k, m.cfg.formation_error_max_m, out)
        if n_ref == 1:
            return out, h_pos[0, ids], h_vel[0, ids]
        return out, h_pos[h_sel, ids], h_vel[h_sel, ids]

    def _ghost_columns(self, pos: np.ndarray, vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where a silent vehicle can be: its autopilot brakes to Hold (PX4 offboard loss,
        ArduPilot GUID_TIMEOUT) and later lands straight down. So the column from its
        braking point down to the ground. (..., 3) arrays in, two (..., 3) ends out."""
        sw = self.mission.cfg.swarm
        speed = _norm_rows(vel)[..., None]
        top = pos + np.nan_to_num(vel * speed / (2.0 * sw.ghost_brake_mps2))
        bottom = top.copy()
        ground = self.mission.cfg.ground_z_m
        bottom[..., 2] = np.maximum(top[..., 2], top[..., 2] + GHOST_COLUMN_M if ground is None else ground)
        return top, bottom

    def step(self, t_s: float, own: OwnState, view: SwarmView) -> AgentOutput:
        """Advance phases and compute setpoints for the agent's own vehicles.

        Args:
            t_s: mission time, s (one time base for the whole swarm, e.g. GNSS time).
            own: states of this agent's vehicles, rows in the order of `ids`.
            view: receiver row r = what own vehicle r has heard (n rows, N vehicles).
        Returns:
            AgentOutput with n rows. Never raises on bad data: a NaN or stale own state
            gives a stop (zero velocity) instead of a formation setpoint.
        """
        m = self.mission
        cfg = m.cfg
        n = len(self.ids)
        q = own.att_q_wxyz
        valid, cos_tilt = np.empty(n, np.bool_), np.empty(n)
        self.kernels.own_checks_rows(t_s, own.pos_ned_m, own.vel_ned_mps, q, np.asarray(own.stamp_s, float),
                                     cfg.swarm.own_timeout_s, valid, cos_tilt)
        age = view.age_s(t_s)
        self._advance_phases(t_s, own, valid, cos_tilt)
        phase = self.phase
        sp = FleetSetpoint.empty(n)
        slot = np.full((n, 3), np.nan)

        rows = np.flatnonzero(IN_FORMATION[phase] & valid)
        if len(rows):
            acc, h_pos, h_vel = self._formation_accel(t_s, rows, own, view, age)
        else:
            acc = h_pos = h_vel = self._no_rows
        ph = cfg.phases
        flags = np.empty(n, np.uint8)
        self.kernels.finish_rows(rows, own.pos_ned_m, own.vel_ned_mps, acc, h_pos, h_vel, valid,
                                 np.asarray(own.ready, np.bool_), phase, cfg.setpoint.kind == "state",
                                 cfg.setpoint.lead_s, m.yaw_rad, ph.land_speed_mps, ph.assembled_pos_m,
                                 ph.assembled_speed_mps, sp.pos_ned_m, sp.vel_ned_mps, sp.acc_ned_mps2, sp.yaw_rad,
                                 slot, self.assembled, flags)
        # After this tick's assembled flags: a vehicle that reaches its slot now counts now.
        self._agree_t_go(t_s, view, age)
        published = SwarmStates(self.ids.copy(), np.asarray(own.stamp_s, float).copy(), own.pos_ned_m.copy(),
                                own.vel_ned_mps.copy(), q.copy(), phase.copy(), flags, self.t_go_s.copy())
        return AgentOutput(sp, phase.copy(), self.assembled.copy(), self.t_go_s.copy(), valid, slot, published)
