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
    TRANSIT   -> HOVER      when the formation centre comes to rest at the end of its path
                            (the mission's, or a swarm command's plan: docs/swarm.md);
    HOVER     -> TRANSIT    when a newer plan moves the centre again (GOTO, RESUME, RTL);
    HOVER     -> LAND       land_after_hover_s after hover began, if configured;
    any formation phase -> LAND  at the handover time a LAND or RTL plan gives the vehicle;
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
from typing import Callable

import numpy as np

from companion.avoidance import Avoidance, neighbour_sets_rows, settled_rows, vehicle_cutoff_m
from companion.commands.book import PlanBook, RefGroup
from companion.commands.track import LAND as ROLE_LAND
from companion.control.apf import clip_sum_rows, pair_repulsion_rows, segment_repulsion_rows
from companion.control.formation import consensus_rows, gains_vector
from companion.control.kernel import kernel
from companion.link.dialects.base import PositionLoop
from companion.mission import Mission
from companion.phases import (
    _ASSEMBLE,
    _FAILED,
    _HOVER,
    _LAND,
    _LAUNCH,
    _STABILISE,
    _TRANSIT,
    IN_FORMATION,
)
from companion.phases import FORMATION_PHASES as FORMATION_PHASES  # (re-exported: users import them from here)
from companion.phases import Phase as Phase
from companion.slot_hold import SlotIntegral
from companion.state import FleetSetpoint
from companion.swarm import (
    FLAG_ASSEMBLED,
    FLAG_HANDED_OVER,
    FLAG_ID_CONFLICT,
    FLAG_OWN_VALID,
    FLAG_READY,
    SwarmStates,
    SwarmView,
)


def _norm_rows(a: np.ndarray) -> np.ndarray:
    """Euclidean norm along the last axis (cheaper than np.linalg.norm)."""
    return np.sqrt(np.einsum("...i,...i->...", a, a))


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
                land_xy, assembled_pos_m, assembled_speed_mps, sp_pos, sp_vel, sp_acc, sp_yaw, slot, assembled, flags):
    """The setpoints, slots, assembled and published flags of a tick (Agent.step).

    Formation row rows[r] (index into the own vehicles) flies acc[r]: as an acceleration,
    and with state_kind also as the state it leads to lead_s ahead (p + v lead +
    acc lead^2 / 2, v + acc lead), so that if the stream stops the autopilot holds near
    where the vehicle was heading; it is assembled once within assembled_pos_m of its
    slot h_pos[r] and assembled_speed_mps of the slot's velocity. Then every own
    vehicle: an invalid own state in ASSEMBLE or later stops (zero velocity, flown on
    the autopilot's own estimate); LAND descends at land_speed_mps over the point where
    it began (land_xy: the position target holds it there, so the autopilot's loops take
    out a bias or a wind instead of letting the vehicle drift into a neighbour's
    column); flags gets the FLAG_* bits.

    Args: rows (R,); p, v (n, 3) own state; acc, h_pos, h_vel (R, 3); valid, ready (n,)
        bool; phase (n,); land_xy (n, 2) NED m, where each LAND began. Written: sp_pos, sp_vel, sp_acc, slot (n, 3), sp_yaw (n,)
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
            if state_kind:  # the column over the landing point, and a height that leads as the speed
                sp_pos[i, 0], sp_pos[i, 1] = land_xy[i, 0], land_xy[i, 1]
                sp_pos[i, 2] = p[i, 2] + land_speed_mps * lead_s
            sp_yaw[i] = yaw_rad
        f = 0
        if assembled[i]:
            f |= FLAG_ASSEMBLED
        if valid[i]:
            f |= FLAG_OWN_VALID
        if ready[i]:
            f |= FLAG_READY
        flags[i] = f


@dataclass(frozen=True)
class GoDecision:
    """One vehicle proposed the transit start (docs/swarm.md, "Agreeing on the transit start").

    Attributes:
        t_s: when, mission time, s. vehicle_id: who. t_go_s: the start proposed, s.
        left_waiting: vehicles heard alive but not assembled that the proposal did not wait
            for (the stall rule); empty when everyone heard was assembled.
    """

    t_s: float
    vehicle_id: int
    t_go_s: float
    left_waiting: tuple[int, ...]


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
    the simulator passes numba-compiled twins of the same functions (sim_bridge.world.jit)."""

    consensus_rows: Callable = consensus_rows
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
        plan_seq: (n,) seq of the swarm plan each vehicle flies (0: the mission's own).
        handed_over: (n,) bool, an ABORT plan handed the vehicle to its autopilot's own Hold:
            the agent sends nothing (its node switches the autopilot to Hold).
        drive_ned_m: (n, 3) the slot-hold drive (below).
    """

    setpoint: FleetSetpoint
    phase: np.ndarray
    assembled: np.ndarray
    t_go_s: np.ndarray
    own_valid: np.ndarray
    slot_ned_m: np.ndarray
    published: SwarmStates = field(repr=False)
    plan_seq: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    handed_over: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    drive_ned_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(n, 3) how far the position target is moved off the setpoint's state so that the
    autopilot's velocity integrator learns the bias (companion.slot_hold), NED m; the
    output stage applies it (and takes its pull out of the feed-forward)."""
    acc_ff_max_mps2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(n,) the feed-forward bound the output stage applies to each row's setpoint, m/s^2:
    setpoint.acc_ff_hover_mps2 when settled at station (HOVER and slower than
    phases.assembled_speed_mps: companion.avoidance.settled_rows), so that the ghost of a
    vehicle silent there is small (docs/swarm.md, "Ghosts"); setpoint.acc_ff_max_mps2
    otherwise (a vehicle still braking into its slot, or pushed by a gust, keeps its authority).
    Where tighter, it bounds the acceleration less acc_bias_ned_mps2."""
    acc_bias_ned_mps2: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(n, 3) the part of each setpoint's acceleration that cancels the bias the agent has
    learnt (-k_i z, companion.slot_hold; 0 outside formation), NED m/s^2: it moves nothing,
    and keeps cancelling the bias when the companion falls silent, so acc_ff_max_mps2 leaves
    it out."""


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
        self.avoid = Avoidance(mission, self.kernels)
        """Take-off columns, ghosts and intruders (companion.avoidance)."""
        n = len(self.ids)
        self._rows = np.arange(n)
        self.phase = np.full(n, _LAUNCH, dtype=np.int8)
        self.stable_since_s = np.full(n, np.nan)
        self.assembled = np.zeros(n, dtype=bool)
        self.land_xy_ned_m = np.full((n, 2), np.nan)
        """(n, 2) where each vehicle in LAND began its descent (NaN: not landing), NED m."""
        self._any_land_xy = False
        self.t_go_s = np.full(n, np.nan)
        self.go_ready_since_s = np.full(n, np.nan)
        self.go_stall_since_s = np.full(n, np.nan)
        """(n,) since when every vehicle this one still awaits has been trying to assemble
        (the stall rule's clock; NaN: not so now)."""
        self.go_decisions: list[GoDecision] = []
        """Transit starts proposed by this agent's vehicles, newest last (the caller logs
        and clears them: sans-IO)."""
        self.lost_since_s = np.full(n, np.nan)
        self._lost_pending = False
        self.plans = PlanBook(mission, n)
        """The swarm plans each own vehicle holds (companion.commands: receive what the link
        brings with `plans.receive(rows, plan)`; step applies them at their effective time)."""
        self.handed_over = np.zeros(n, bool)
        """(n,) an ABORT plan handed the vehicle to its autopilot: for good (docs/swarm.md)."""
        self._any_handed_over = False
        self._never = np.full(n, np.nan)
        self._groups: list[RefGroup] = []
        self.slot_hold = SlotIntegral(mission.cfg, n)
        """The integral on each vehicle's slot residual, the agent's own or driven into its
        autopilot's velocity integrator (companion.slot_hold; set_autopilot_loop)."""
        self._t_prev_s = math.nan
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

    def set_autopilot_loop(self, rows, loop: PositionLoop | None) -> None:
        """The autopilots of rows fly the trajectory setpoint with these position loops
        (acceleration output): the slot-hold integral is driven into their velocity
        integrators where they have one (companion.slot_hold). Without a position target
        (setpoint.kind "acceleration") there is nothing to drive: the agent keeps its own.
        """
        self.slot_hold.set_autopilot_loop(rows, loop if self.mission.cfg.setpoint.kind == "state" else None)

    # ------------------------------------------------------------------ phases
    def _advance_phases(self, t_s: float, own: OwnState, valid: np.ndarray, cos_tilt: np.ndarray,
                        centre_end_s: np.ndarray, land_at_s: np.ndarray) -> None:
        """Phase transitions (module docstring). centre_end_s (n,): when each row's centre
        comes to rest (its plan's path); land_at_s (n,): when its plan hands it to LAND (NaN)."""
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
            t_hover = centre_end_s
            phase[(phase == _ASSEMBLE) & has_go & (t_s >= go)] = _TRANSIT
            phase[(phase == _TRANSIT) & (t_s >= t_hover)] = _HOVER
            phase[(phase == _HOVER) & (t_s < t_hover)] = _TRANSIT  # a newer plan moves the centre again
            if ph.land_after_hover_s is not None:
                phase[(phase == _HOVER) & (t_s >= t_hover + ph.land_after_hover_s)] = _LAND
        if not np.isnan(land_at_s).all():  # a plan lands some vehicles (LAND, RTL, EXCLUDE with landing)
            phase[IN_FORMATION[phase] & (t_s >= land_at_s)] = _LAND

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
        N have been heard so, or that has held for go_wait_s; or, so that no vehicle that
        is heard but cannot assemble holds the swarm hostage, once this vehicle is assembled,
        every vehicle it still awaits has been airborne (recovering or trying to assemble) for
        go_stall_s, and at least go_quorum of the vehicles heard are assembled (GoDecision
        says which were left waiting)."""
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
        own_ok = self.assembled & ~failed[r, ids]
        cond = own_ok & np.all(asm | ~alive, axis=1)
        self.go_ready_since_s = np.where(cond, np.fmin(self.go_ready_since_s, t_s), np.nan)
        everyone = np.sum((alive & asm) | failed, axis=1) == n_veh
        propose = pending & cond & (everyone | (t_s - self.go_ready_since_s >= sw.go_wait_s - 1e-9))
        # The stall clock runs while every vehicle still awaited has left the carrier or the
        # ground (recovering or assembling): one docked is coming; one that recovers or
        # assembles for go_stall_s may be stuck (a biased estimate or steady wind can hold a
        # vehicle's tilt or speed outside the stabilisation test for ever).
        trying = view.phase >= _STABILISE
        trying[r, ids] = self.phase >= _STABILISE
        stuck_only = own_ok & np.all(asm | ~alive | trying, axis=1)
        self.go_stall_since_s = np.where(stuck_only, np.fmin(self.go_stall_since_s, t_s), np.nan)
        n_alive, n_ready = np.sum(alive, axis=1), np.sum(alive & asm, axis=1)
        stalled = pending & stuck_only & ~propose & (t_s - self.go_stall_since_s >= sw.go_stall_s - 1e-9) \
            & (n_ready >= sw.go_quorum * n_alive)
        if propose.any() or stalled.any():
            q = self.mission.cfg.phases.go_quantum_s
            go = math.ceil((t_s + sw.go_margin_s) / q - 1e-9) * q
            self.t_go_s[propose | stalled] = go
            for k in np.flatnonzero(propose | stalled).tolist():
                waiting = tuple(np.flatnonzero(alive[k] & ~asm[k]).tolist()) if stalled[k] else ()
                self.go_decisions.append(GoDecision(t_s, int(ids[k]), go, waiting))

    # ---------------------------------------------------------------- planner
    def _formation_accel(self, t_s: float, rows: np.ndarray, own: OwnState, view: SwarmView,
                         age: np.ndarray, groups: list[RefGroup]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 31 for the own rows `rows` (indices into self.ids), on the references of their
        plans (`groups`: PlanBook.references for every own row).

        Returns (acceleration (R, 3), slot h_i (R, 3), slot velocity (R, 3))."""
        m = self.mission
        cfg, sw, a, kern = m.cfg, m.cfg.swarm, m.cfg.apf, self.kernels
        n_rows = len(rows)
        ids = self.ids[rows]
        p, v = own.pos_ned_m[rows], own.vel_ned_mps[rows]
        n_veh = view.n_vehicles
        pred = np.empty((n_rows, n_veh, 3))
        usable, repel, ghost = (np.empty((n_rows, n_veh), np.bool_) for _ in range(3))
        cutoff = vehicle_cutoff_m(a)
        neighbour_sets_rows(rows, ids, p, view.pos_ned_m, view.vel_ned_mps, view.flags, view.phase, age,
                            sw.stale_after_s, IN_FORMATION, cutoff, pred, usable, repel, ghost)
        # Every own row flies formation (the usual case): the view's arrays, not row copies.
        whole = n_rows == view.n_receivers
        vv = view.vel_ned_mps if whole else view.vel_ned_mps[rows]

        u1, h_pos_rows, h_vel_rows, resid = self._consensus(rows, groups, p, v, ids, pred, vv, usable)

        u2 = np.zeros((n_rows, 3))
        if cfg.launch == "ground":  # neighbours still on the ground or taking off: their columns
            self.avoid.takeoff_columns(rows, p, view, age, ids, whole, repel, u2)
        kern.pair_repulsion_rows(p, v, pred, vv, repel, ids, a.vehicle_gain_mps2, a.vehicle_influence_m, cutoff,
                                 a.kappa, a.closing_decel_mps2, u2)
        if ghost.any():
            self.avoid.ghosts(p, view.pos_ned_m if whole else view.pos_ned_m[rows], vv,
                               age if whole else age[rows], view.phase if whole else view.phase[rows], ghost, u2)
        if view.intruders is not None:  # (an identity conflict has been heard: rare)
            self.avoid.intruders(rows, p, v, view.intruders, view.intruders.age_s(t_s), u2)
        if self._n_obstacles:
            kern.segment_repulsion_rows(p, self._obs_ends[:n_rows], self._obs_ends[:n_rows], self._obs_r[:n_rows],
                                        self._obs_use[:n_rows], a.obstacle_gain_mps2, a.obstacle_influence_m, a.kappa,
                                        u2)
        if cfg.consensus.ki_pos_per_s3 > 0:
            self.slot_hold.update(t_s - self._t_prev_s, rows, p, v, h_pos_rows, h_vel_rows, resid, u1, u2)
        acc = np.empty((n_rows, 3))
        kern.clip_sum_rows(u1, u2, cfg.consensus_accel_max_mps2, cfg.total_accel_max_mps2, acc)
        return acc, h_pos_rows, h_vel_rows

    def _consensus(self, rows, groups, p, v, ids, pred, vv, usable):
        """Eq. 27 for the rows, each on the reference its plan gives it (the RefGroups of
        PlanBook.references: one per plan in force, each with one reference per transit start
        its rows hold; usually one and one). The consensus graph is the plan's (its vehicles
        left in the formation: companion.commands.track).
        Returns (u1, slot, slot velocity, the law's position residual), each (R, 3); u1 is
        NaN in a row that read a non-finite value (excluded by the checks of
        _formation_accel: never flown)."""
        m = self.mission
        out, resid = np.empty((len(ids), 3)), np.empty((len(ids), 3))
        if len(groups) == 1 and len(groups[0].rows) == len(rows):  # the usual case: one plan, every row
            g = groups[0]
            h_sel = g.h_sel
            self.kernels.consensus_rows(p, v, ids, pred, vv, usable, g.h_pos, g.h_vel, g.h_acc, h_sel, g.track.weights,
                                        g.track.neighbours, self._k, m.cfg.formation_error_max_m, out, resid)
            if len(g.t_go_s) == 1:
                return out, g.h_pos[0, ids], g.h_vel[0, ids], resid
            return out, g.h_pos[h_sel, ids], g.h_vel[h_sel, ids], resid
        h_pos_rows, h_vel_rows = np.empty((len(ids), 3)), np.empty((len(ids), 3))
        for g in groups:
            at = np.searchsorted(rows, g.rows)  # (the groups' rows are exactly `rows`, sorted)
            o, rs = np.empty((len(at), 3)), np.empty((len(at), 3))
            self.kernels.consensus_rows(p[at], v[at], ids[at], pred[at], vv[at], usable[at], g.h_pos, g.h_vel, g.h_acc,
                                        g.h_sel, g.track.weights, g.track.neighbours, self._k,
                                        m.cfg.formation_error_max_m, o, rs)
            out[at], resid[at] = o, rs
            h_pos_rows[at], h_vel_rows[at] = g.h_pos[g.h_sel, ids[at]], g.h_vel[g.h_sel, ids[at]]
        return out, h_pos_rows, h_vel_rows, resid

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
        book = self.plans
        book.advance(t_s, self.t_go_s)
        centre_end, land_at = self._plan_times(t_s, book.references(t_s, self.t_go_s))
        self._advance_phases(t_s, own, valid, cos_tilt, centre_end, land_at)
        phase = self.phase
        sp = FleetSetpoint.empty(n)
        slot = np.full((n, 3), np.nan)

        rows = (IN_FORMATION[phase] & valid & ~self.handed_over).nonzero()[0]
        self.slot_hold.clear_drive()
        if len(rows):
            groups = self._groups if len(rows) == n else book.references(t_s, self.t_go_s, rows)
            acc, h_pos, h_vel = self._formation_accel(t_s, rows, own, view, age, groups)
        else:
            acc = h_pos = h_vel = self._no_rows
        ph = cfg.phases
        flags = np.empty(n, np.uint8)
        landing = phase == _LAND
        if self._any_land_xy or landing.any():  # (a formation tick does no more than this test)
            self.land_xy_ned_m[~landing] = np.nan
            starts = landing & np.isnan(self.land_xy_ned_m[:, 0])
            self.land_xy_ned_m[starts] = own.pos_ned_m[starts, :2]
            self._any_land_xy = bool(landing.any())
        self.kernels.finish_rows(rows, own.pos_ned_m, own.vel_ned_mps, acc, h_pos, h_vel, valid,
                                 np.asarray(own.ready, np.bool_), phase, cfg.setpoint.kind == "state",
                                 cfg.setpoint.lead_s, m.yaw_rad, ph.land_speed_mps, self.land_xy_ned_m,
                                 ph.assembled_pos_m,
                                 ph.assembled_speed_mps, sp.pos_ned_m, sp.vel_ned_mps, sp.acc_ned_mps2, sp.yaw_rad,
                                 slot, self.assembled, flags)
        if view.intruders is not None:  # someone else claims our id: say so in our state
            flags[view.intruders.heard_within(t_s, cfg.swarm.peer_timeout_s)] |= FLAG_ID_CONFLICT
        if self._any_handed_over:  # ABORT: nothing is sent; the node hands the vehicle to Hold
            ho = self.handed_over
            for f in (sp.pos_ned_m, sp.vel_ned_mps, sp.acc_ned_mps2):
                f[ho] = np.nan
            sp.yaw_rad[ho] = np.nan
            flags[ho] |= FLAG_HANDED_OVER
        # After this tick's assembled flags: a vehicle that reaches its slot now counts now.
        self._agree_t_go(t_s, view, age)
        self._t_prev_s = t_s
        seq = book.plan_seq.copy()
        published = SwarmStates(self.ids.copy(), np.asarray(own.stamp_s, float).copy(), own.pos_ned_m.copy(),
                                own.vel_ned_mps.copy(), q.copy(), phase.copy(), flags, self.t_go_s.copy(), seq)
        bias = np.zeros((n, 3))
        bias[rows] = self.slot_hold.bias_accel(rows)
        return AgentOutput(sp, phase.copy(), self.assembled.copy(), self.t_go_s.copy(), valid, slot, published, seq,
                           self.handed_over.copy(), self.slot_hold.drive_ned_m.copy(),
                           np.where(settled_rows(phase, own.vel_ned_mps, cfg.phases.assembled_speed_mps),
                                    cfg.setpoint.acc_ff_hover_mps2, cfg.setpoint.acc_ff_max_mps2), bias)

    def _plan_times(self, t_s: float, groups: list[RefGroup]) -> tuple[np.ndarray, np.ndarray]:
        """What each row's plan says of time (and ABORT): when its centre comes to rest, when it
        is handed to LAND (NaN: never). Keeps the groups for this step's formation rows.
        Returns ((n,), (n,)) s."""
        n = len(self.ids)
        self._groups = groups
        if len(groups) == 1 and groups[0].track.plan.seq == 0 and len(groups[0].t_go_s) == 1:
            # The mission's own plan, one transit start (every step until a command comes).
            return np.full(n, groups[0].centre_end_s[0]), self._never
        centre_end, land_at = np.empty(n), np.full(n, np.nan)
        for g in groups:
            tr = g.track
            centre_end[g.rows] = g.centre_end_s[g.h_sel]
            if tr.plan.abort:
                self.handed_over[g.rows] = True
                self._any_handed_over = True
            lands = tr.role[self.ids[g.rows]] == ROLE_LAND
            if lands.any():
                land_at[g.rows[lands]] = tr.land_handover_s[self.ids[g.rows[lands]]]
        return centre_end, land_at
