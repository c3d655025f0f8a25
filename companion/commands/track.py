"""A plan in force, and the reference every vehicle flies under it (docs/swarm.md, "The
reference"). Pure: numpy, companion.mission, companion.control.topology.

A `Track` is a plan as a group of vehicles flies it: the plan, plus what they brought into
it at its effective time e (where every vehicle was: the start of the slot morph, of the
moves of vehicles leaving the formation). `enter(plan, prev, mission, t_go)` makes it from
the track flown before; `Track.at(t, t_go)` gives every vehicle's reference position,
velocity and acceleration h_i, h_i', h_i'' (the consensus law's slot, eq. 25-27, with the
morph's velocity and acceleration fed forward). The source and every agent compute the same
tracks from the same plans, so a vehicle that heard every plan flies exactly what the source
planned; one that missed some starts its moves from where it was.

Each vehicle has one role under a plan:

* SLOT: in the formation (a slot, neither excluded nor landing): h = centre + morph offset;
  it takes part in consensus (`Track.consensus`, `Track.weights`, `Track.neighbours`: the
  mission's topology rebuilt over these vehicles only).
* PARK: excluded, holding. It leaves the formation's layer vertically: a smooth move
  (`slots.quintic_move`) from its state at e to rest on the parking layer, `clear_m`
  (the larger of the separation and the vehicles' APF influence) above the formation's top
  at e (below its bottom while the centre climbs, ground permitting: the formation then
  climbs away from it), half its coasting distance ahead (so it keeps pace with a cruising
  formation while it climbs, then stops: peak deceleration and climb within the hold brake,
  vertical speed PARK_CLIMB_SPEED_MPS). A parked vehicle stays put under later plans unless
  the formation's layer comes within clear_m of it (it moves clear again) or it lands.
* LAND: landing. A lander with a slot flies it until its descent starts (layered:
  slots.landing_start_offsets_s, from the time the slots are still: the morph's end, the
  held centre's stop, an RTL's arrival). One without (an excluded vehicle) first moves, at
  its height, radially out of the formation's footprint if its column holds a slot (so that
  it never descends onto one), then descends with its layer. A vehicle that leaves a moving
  formation to land descends at land_speed_mps while coasting at its slot's velocity until
  it is clear_m below the staying formation, then stops horizontally (quintic) and descends
  straight down: `land_handover_s` is when the agent can hand it to its LAND phase (straight
  down on the autopilot), `land_point_ned_m` where.

Landers with a slot and RTL's vehicles stay in `consensus` only if they are not in the plan's
landing set (RTL keeps its formation until its vehicles start down; an agent leaves a
neighbour in its LAND phase out of consensus anyway).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from companion.commands.centre import centre_arrival_s, centre_state, plan_centre
from companion.commands.plan import SwarmPlan, hold_brake_mps2
from companion.commands.slots import (
    QUINTIC_STOP_ACCEL,
    START_VELOCITY_PEAK_ACCEL,
    landing_start_offsets_s,
    min_jerk_time_s,
    morph_fraction,
    plan_offsets_ned_m,
    quintic_move,
)
from companion.control import topology
from companion.feasibility import SEPARATION_M
from companion.mission import Mission, build_topology

SLOT, PARK, LAND = 0, 1, 2
"""Roles of a vehicle under a plan (module docstring)."""
PARK_CLIMB_SPEED_MPS = 2.0
"""Peak climb speed of an excluded vehicle to its parking layer, m/s (PX4's MPC_Z_VEL_MAX_UP is 3)."""
SIDESTEP_SPEED_MPS = 1.0
"""Peak speed of a parked vehicle's move out of the formation's footprint before it lands, m/s."""
CLIMBING_MPS = 0.1
"""A centre climbing faster than this (m/s) parks excluded vehicles below the formation."""
STILL_MPS = 1e-6
"""A lander slower than this horizontally is still: it descends straight down at once."""


def clear_m(mission: Mission, separation_m: float = SEPARATION_M) -> float:
    """Vertical clearance between the formation and vehicles leaving it (parking above,
    landing below), m: the separation, or the vehicles' APF influence if larger (so that a
    formation passing over or under them is not pushed)."""
    return max(separation_m, mission.cfg.apf.vehicle_influence_m)


@dataclass(frozen=True, eq=False)
class Track:
    """A plan in force as a group of vehicles flies it (module docstring). Arrays are per
    vehicle of the mission, (N,) or (N, 3), NED m, m/s, s of mission time; NaN where unused.

    Attributes:
        plan: the plan.
        t_go_s: the transit start the entry state was computed with (NaN: none agreed).
        role: SLOT, PARK or LAND.
        target_ned_m: the plan's slot offsets (NaN: no slot).
        morph_from_ned_m, morph_start_s, morph_s: the slot morph (offsets it starts from).
        mv_t0_s, mv_p0_ned_m, mv_v0_ned_mps, mv_target_ned_m, mv_duration_s: the quintic move
            of PARK vehicles, and of LAND vehicles without a slot before their descent.
        land_start_s, land_p_ned_m, land_v_ned_mps, land_coast_s, land_stop_s: the descent of
            LAND vehicles: when it starts, from where and at what velocity, how long it coasts,
            how long its horizontal stop takes.
        land_handover_s, land_point_ned_m: when and where a lander is still horizontally
            (from then on: straight down at land_speed_mps).
        consensus: (N,) bool, takes part in consensus (SLOT and not in plan.landing).
        weights, neighbours: the consensus graph over those vehicles ((N, N), (N, K)).
    """

    plan: SwarmPlan
    t_go_s: float
    role: np.ndarray
    target_ned_m: np.ndarray
    morph_from_ned_m: np.ndarray
    morph_start_s: float
    morph_s: float
    mv_t0_s: np.ndarray
    mv_p0_ned_m: np.ndarray
    mv_v0_ned_mps: np.ndarray
    mv_target_ned_m: np.ndarray
    mv_duration_s: np.ndarray
    land_start_s: np.ndarray
    land_p_ned_m: np.ndarray
    land_v_ned_mps: np.ndarray
    land_coast_s: np.ndarray
    land_stop_s: np.ndarray
    land_handover_s: np.ndarray
    land_point_ned_m: np.ndarray
    consensus: np.ndarray
    weights: np.ndarray
    neighbours: np.ndarray
    land_speed_mps: float
    ground_z_m: float | None

    @functools.cached_property
    def _moving_rows(self) -> np.ndarray:
        """Vehicles that are not simply in their slot: PARK, LAND, and RTL's (descending at the end)."""
        return np.flatnonzero((self.role != SLOT) | np.isfinite(self.land_start_s))

    @property
    def morph_end_s(self) -> float:
        """When the slot morph ends (mission time, s)."""
        return self.morph_start_s + self.morph_s

    def centre_end_s(self, mission: Mission, t_go_s: float) -> float:
        """When the plan's centre comes to rest at the end of its path (TRANSIT -> HOVER;
        NaN for the mission's path without t_go)."""
        return centre_arrival_s(self.plan, mission, t_go_s)

    def at(self, t_s: float, mission: Mission, t_go_s: float, out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every vehicle's reference at mission time t_s: position, velocity, acceleration
        ((N, 3) each, written into `out` if given). Under plan 0 with no morph, exactly
        `mission.offsets_ned_m + c`, `c'`, `c''` with c = mission.path.at(Mission.tau_s(t, t_go)).
        """
        pos, vel, acc = out if out is not None else (np.empty_like(self.target_ned_m) for _ in range(3))
        c_pos, c_vel, c_acc = centre_state(self.plan, t_s, mission, t_go_s)
        s, ds, dds = morph_fraction(t_s, self.morph_start_s, self.morph_s) if self.morph_s > 0 else (1.0, 0.0, 0.0)
        if s >= 1.0 and ds == 0.0:  # no morph under way: the slots as the mission's own reference has them
            np.add(self.target_ned_m, c_pos, out=pos)
            vel[...] = c_vel  # every slot moves with the centre
            acc[...] = c_acc
        else:
            d = self.target_ned_m - self.morph_from_ned_m
            np.add(self.morph_from_ned_m + s * d, c_pos, out=pos)
            np.add(ds * d, c_vel, out=vel)
            np.add(dds * d, c_acc, out=acc)
        rows = self._moving_rows
        if len(rows):
            p, v, a = self._moves(np.array([t_s]), rows, pos[None, rows], vel[None, rows], acc[None, rows])
            pos[rows], vel[rows], acc[rows] = p[0], v[0], a[0]
        return pos, vel, acc

    def positions(self, times_s: np.ndarray, mission: Mission, t_go_s: float) -> np.ndarray:
        """Every vehicle's reference position at each of S mission times, (S, N, 3): `at`'s
        positions, vectorised over time (for the source's sampled checks)."""
        ts = np.asarray(times_s, dtype=float).reshape(-1)
        c = np.array([centre_state(self.plan, t, mission, t_go_s)[0] for t in ts.tolist()]).reshape(-1, 3)
        if self.morph_s > 0:
            u = np.clip((ts - self.morph_start_s) / self.morph_s, 0.0, 1.0)[:, None, None]
            offs = self.morph_from_ned_m + (u * u * u * (10.0 + u * (-15.0 + 6.0 * u))) \
                * (self.target_ned_m - self.morph_from_ned_m)
        else:
            offs = np.broadcast_to(self.target_ned_m, (len(ts), *self.target_ned_m.shape))
        pos = offs + c[:, None, :]
        rows = self._moving_rows
        if len(rows):
            pos[:, rows] = self._moves(ts, rows, pos[:, rows], pos[:, rows], pos[:, rows], positions_only=True)[0]
        return pos

    def _moves(self, ts: np.ndarray, rows: np.ndarray, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
               positions_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The PARK and LAND rows (module docstring) at times ts (S,): (S, K, 3) each, from the
        slot values given (pos, vel, acc (S, K, 3)) where neither moves nor descents apply."""
        t = ts[:, None]
        down = self.land_start_s[rows] <= t  # (S, K)
        pre = ~down & np.isnan(self.target_ned_m[rows, 0])
        if pre.any():  # parked, or landers without a slot before their descent: the quintic move
            p, v, a = quintic_move(self.mv_p0_ned_m[rows], self.mv_v0_ned_mps[rows], self.mv_target_ned_m[rows],
                                   self.mv_duration_s[rows], t - self.mv_t0_s[rows])
            pos = np.where(pre[..., None], p, pos)
            if not positions_only:
                vel, acc = np.where(pre[..., None], v, vel), np.where(pre[..., None], a, acc)
        if down.any():
            p, v, a = self._descent(t - self.land_start_s[rows], rows)
            pos = np.where(down[..., None], p, pos)
            if not positions_only:
                vel, acc = np.where(down[..., None], v, vel), np.where(down[..., None], a, acc)
        return pos, vel, acc

    def _descent(self, tau: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Landers `rows` tau (S, K) after their descent starts: coasting, a quintic stop,
        straight down at land_speed_mps to the ground."""
        p0, v0 = self.land_p_ned_m[rows], self.land_v_ned_mps[rows]
        vh = v0 * np.array([1.0, 1.0, 0.0])
        coast = self.land_coast_s[rows]
        stop_t = self.land_stop_s[rows]
        at_coast_end = p0 + vh * coast[:, None]
        p, v, a = quintic_move(at_coast_end, vh, at_coast_end + vh * (stop_t / 2.0)[:, None], stop_t, tau - coast)
        coasting = (tau < coast)[..., None]
        if coasting.any():
            p = np.where(coasting, p0 + vh * tau[..., None], p)
            v = np.where(coasting, vh, v)
            a = np.where(coasting, 0.0, a)
        z = p0[:, 2] + self.land_speed_mps * tau
        vz = np.full(tau.shape, self.land_speed_mps)
        if self.ground_z_m is not None:
            landed = z >= self.ground_z_m
            z = np.where(landed, np.maximum(self.ground_z_m, p0[:, 2]), z)
            vz = np.where(landed, 0.0, vz)
        p[..., 2], v[..., 2], a[..., 2] = z, vz, 0.0
        return p, v, a


def initial_track(plan: SwarmPlan, mission: Mission) -> Track:
    """The track of the mission's own plan (seq 0): every vehicle in its slot, the mission's
    offsets, weights and neighbours (the very arrays)."""
    n = plan.n_vehicles
    target = mission.offsets_ned_m if n == mission.n else plan_offsets_ned_m(plan)
    nan3, nan1 = np.full((n, 3), np.nan), np.full(n, np.nan)
    weights, neighbours = ((mission.weights, mission.neighbours) if n == mission.n
                           else consensus_graph(mission, tuple(range(n)), target))
    cfg = mission.cfg
    return Track(plan, math.nan, np.full(n, SLOT, np.int8), target, target, plan.effective_s, 0.0, nan1, nan3, nan3,
                 nan3, nan1, nan1, nan3, nan3, nan1, nan1, nan1, nan3, np.ones(n, bool), weights, neighbours,
                 cfg.phases.land_speed_mps, cfg.ground_z_m)


@functools.lru_cache(maxsize=32)
def _graph(mission: Mission, active: tuple[int, ...], target_bytes: bytes | None) -> tuple[np.ndarray, np.ndarray]:
    n = mission.n
    act = np.asarray(active, dtype=np.intp)
    offs = np.frombuffer(target_bytes, dtype=float).reshape(n, 3)[act] if target_bytes is not None else np.zeros((len(act), 3))
    w = np.zeros((n, n))
    if len(act):
        w[np.ix_(act, act)] = build_topology(mission.cfg.topology, offs)
    w.setflags(write=False)
    nbr = topology.neighbour_table(w)
    nbr.setflags(write=False)
    return w, nbr


def consensus_graph(mission: Mission, active: tuple[int, ...], target_ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The consensus weights (N, N) and neighbour table (N, K) over the vehicles `active`
    (ascending ids), as Mission builds its own over all: the mission's topology kind among
    them only (a chain in id order, a ring, complete, or k nearest by their target slots),
    zero rows and columns for the others. The mission's own arrays when every vehicle is
    active in the mission's slots. Cached; read-only arrays.
    """
    n = mission.n
    if active == tuple(range(n)) and (mission.cfg.topology.kind != "k_nearest"
                                      or np.array_equal(target_ned_m, mission.offsets_ned_m)):
        return mission.weights, mission.neighbours
    key = np.ascontiguousarray(target_ned_m, dtype=float).tobytes() if mission.cfg.topology.kind == "k_nearest" else None
    return _graph(mission, active, key)


def enter(plan: SwarmPlan, prev: Track, mission: Mission, t_go_s: float, separation_m: float = SEPARATION_M) -> Track:
    """The track of `plan` for vehicles that flew `prev` until plan.effective_s (e), with
    transit start t_go_s then (module docstring). Pure and deterministic: equal inputs give
    equal tracks, so rows that flew the same track with the same t_go share the next one.

    Raises:
        ValueError: the plan is for another number of vehicles than prev.
    """
    n = plan.n_vehicles
    if n != prev.plan.n_vehicles:
        raise ValueError(f"plan {plan.seq} has {n} vehicles, the track before it {prev.plan.n_vehicles}")
    cfg = mission.cfg
    e = plan.effective_s
    brake = hold_brake_mps2(mission)
    clear = clear_m(mission, separation_m)
    land_speed = cfg.phases.land_speed_mps
    target = plan_offsets_ned_m(plan)
    slotted = ~np.isnan(target[:, 0])
    landing = np.zeros(n, bool)
    landing[[v for v in plan.landing if 0 <= v < n]] = True
    role = np.where(landing, LAND, np.where(slotted, SLOT, PARK)).astype(np.int8)
    # where everyone was at e (the track flown until then), and the new centre there
    p_e, v_e, _ = prev.at(e, mission, t_go_s)
    c_e, cv_e, _ = centre_state(plan, e, mission, t_go_s)
    if np.array_equal(prev.target_ned_m, target, equal_nan=True):  # same slots: the morph under way goes on
        morph_from, m_start, m_s = prev.morph_from_ned_m, prev.morph_start_s, prev.morph_s
    else:
        morph_from = np.where(slotted[:, None], p_e - c_e, np.nan)
        m_start, m_s = e, plan.morph_s
    b = _Builder(n, e, brake, land_speed, clear)
    # the parking layer: clear_m above the formation's top at e (its old and new slots), or
    # below its bottom while the centre climbs (it climbs away from a vehicle parked there)
    form = slotted & np.isfinite(morph_from[:, 0])
    if form.any():
        top_z = float(np.min(c_e[2] + np.minimum(morph_from[form, 2], target[form, 2])))
        bottom_z = float(np.max(c_e[2] + np.maximum(morph_from[form, 2], target[form, 2])))
    else:
        top_z, bottom_z = math.inf, -math.inf
    above, below = top_z - clear, bottom_z + clear
    ground = cfg.ground_z_m
    park_below = cv_e[2] < -CLIMBING_MPS and (ground is None or below < ground - clear)
    for i in np.flatnonzero(role == PARK).tolist():
        z_prev = float(prev.mv_target_ned_m[i, 2])
        if prev.role[i] == PARK and (z_prev <= above + 1e-6 or z_prev >= below - 1e-6):
            b.copy_move(prev, i)  # parked clear of the formation's layer already: goes on as it was going
        else:
            b.park(i, p_e[i], v_e[i], max(float(p_e[i, 2]), below) if park_below else min(float(p_e[i, 2]), above))
    # landings: the layers start once the slots are still (the morph's end, the held centre's
    # stop, an RTL's arrival)
    stay = slotted & ~landing
    # a subset lands now, leaving the formation downwards; every vehicle (a held centre) once
    # the centre has stopped and the slots' morph has ended
    still = max(e, m_start + m_s)
    s0 = max(still, e + _brake_s(plan, mission)) if plan.hold else e
    c0, _, _ = centre_state(plan, s0, mission, t_go_s)
    low_stay = float(np.max(c0[2] + target[stay, 2])) if stay.any() else -math.inf
    layered: list[tuple[int, float, float]] = []  # (vehicle, height, earliest start)
    for i in np.flatnonzero(landing).tolist():
        going = prev.land_start_s[i] <= e  # (also an RTL's vehicle that has started down)
        if going or (prev.role[i] == LAND and not slotted[i]):
            b.copy_land(prev, i, p_e[i], v_e[i], going, low_stay)  # a landing under way goes on
        elif slotted[i]:
            layered.append((i, float(c0[2] + target[i, 2]), s0))
        elif prev.role[i] == PARK:  # out of the footprint at its height, then down with its layer
            z = float(prev.mv_target_ned_m[i, 2]) if np.isfinite(prev.mv_target_ned_m[i, 2]) else float(p_e[i, 2])
            b.sidestep(i, p_e[i], v_e[i], z, c0, c0 + target[slotted], separation_m)
            layered.append((i, float(b.mv_target[i, 2]), max(s0, e + float(b.mv_t[i]))))
        else:  # it leaves its slot to land where it is, now
            b.land(i, e, p_e[i], v_e[i], low_stay)
    if plan.land_at_end:  # RTL: the formation lands when its centre has arrived
        arrive = max(still, centre_arrival_s(plan, mission, t_go_s))
        c_a, _, _ = centre_state(plan, arrive, mission, t_go_s)
        layered += [(i, float(c_a[2] + target[i, 2]), arrive) for i in np.flatnonzero(stay).tolist()]
    if layered:
        pts = np.zeros((len(layered), 3))
        pts[:, 2] = [z for _, z, _ in layered]
        offs = landing_start_offsets_s(pts, land_speed, separation_m)
        base = min(ref for *_, ref in layered)
        for (i, _, ref), off in zip(layered, offs.tolist()):
            start = max(ref, base + off)
            if slotted[i]:
                p, v = _slot_state(plan, mission, t_go_s, target, morph_from, m_start, m_s, i, start)
                b.land(i, start, p, v, low_stay if landing[i] else -math.inf)
            else:
                b.land(i, start, b.mv_target[i], np.zeros(3), -math.inf)
    consensus = stay
    weights, neighbours = consensus_graph(mission, tuple(np.flatnonzero(consensus).tolist()), target)
    return Track(plan, t_go_s, role, target, morph_from, m_start, m_s, b.mv_t0, b.mv_p0, b.mv_v0, b.mv_target, b.mv_t,
                 b.ld_start, b.ld_p, b.ld_v, b.ld_coast, b.ld_stop, b.ld_handover, b.ld_point, consensus, weights,
                 neighbours, land_speed, cfg.ground_z_m)


def _brake_s(plan: SwarmPlan, mission: Mission) -> float:
    motion = plan_centre(plan, mission)
    return 0.0 if motion is None else motion.brake_s


def _slot_state(plan, mission, t_go_s, target, morph_from, m_start, m_s, i, t_s) -> tuple[np.ndarray, np.ndarray]:
    c, cv, _ = centre_state(plan, t_s, mission, t_go_s)
    s, ds, _ = morph_fraction(t_s, m_start, m_s)
    d = target[i] - morph_from[i]
    return c + morph_from[i] + s * d, cv + ds * d


def _out_of_footprint(q: np.ndarray, centre: np.ndarray, foot: np.ndarray, separation_m: float) -> np.ndarray:
    """Where a parked vehicle that would stop at q lands from: q if its column is at least
    separation_m from every column of the formation (foot (K, 3)), else radially out from the
    centre to the footprint's radius plus separation_m (every column then at least that far)."""
    if not len(foot):
        return q
    if float(np.hypot(foot[:, 0] - q[0], foot[:, 1] - q[1]).min()) >= separation_m:
        return q
    radius = float(np.max(np.hypot(foot[:, 0] - centre[0], foot[:, 1] - centre[1]))) + separation_m * 1.01
    d = np.array([q[0] - centre[0], q[1] - centre[1]])
    r = float(np.hypot(d[0], d[1]))
    u = d / r if r > 1e-6 else np.array([1.0, 0.0])
    out = q.copy()
    out[:2] = centre[:2] + u * max(r, radius)
    return out


class _Builder:
    """Per-vehicle move and landing parameters of a track being made (from its effective time t0)."""

    def __init__(self, n: int, t0: float, brake: float, land_speed: float, clear: float):
        self.t0, self.brake, self.land_speed, self.clear = t0, brake, land_speed, clear
        nan1, nan3 = (lambda: np.full(n, np.nan)), (lambda: np.full((n, 3), np.nan))
        self.mv_t0, self.mv_p0, self.mv_v0, self.mv_target, self.mv_t = nan1(), nan3(), nan3(), nan3(), nan1()
        self.ld_start, self.ld_p, self.ld_v, self.ld_coast, self.ld_stop = nan1(), nan3(), nan3(), nan1(), nan1()
        self.ld_handover, self.ld_point = nan1(), nan3()

    def _stop_s(self, v: np.ndarray) -> float:
        """How long a quintic stop from v takes: the horizontal stop within the brake, the
        vertical start velocity shed within it too."""
        return max(QUINTIC_STOP_ACCEL * float(np.hypot(v[0], v[1])), START_VELOCITY_PEAK_ACCEL * abs(float(v[2]))) \
            / self.brake

    def park(self, i: int, p: np.ndarray, v: np.ndarray, z: float) -> None:
        """Vehicle i, at p moving at v at t0, to rest at height z (NED), half its coasting
        distance ahead: a quintic whose velocity never reverses horizontally."""
        duration = max(min_jerk_time_s(abs(z - float(p[2])), PARK_CLIMB_SPEED_MPS, self.brake), self._stop_s(v))
        target = np.array([p[0] + v[0] * duration / 2.0, p[1] + v[1] * duration / 2.0, z])
        self.mv_t0[i], self.mv_p0[i], self.mv_v0[i], self.mv_target[i], self.mv_t[i] = self.t0, p, v, target, duration

    def sidestep(self, i: int, p: np.ndarray, v: np.ndarray, z: float, centre: np.ndarray, foot: np.ndarray,
                 separation_m: float) -> None:
        """Vehicle i, parked, to the point it lands from (_out_of_footprint) at height z."""
        self.park(i, p, v, z)
        out = _out_of_footprint(self.mv_target[i].copy(), centre, foot, separation_m)
        shift = float(np.hypot(out[0] - self.mv_target[i, 0], out[1] - self.mv_target[i, 1]))
        if shift > 0.0:
            self.mv_target[i] = out
            self.mv_t[i] = self.mv_t[i] + min_jerk_time_s(shift, SIDESTEP_SPEED_MPS, self.brake)

    def land(self, i: int, start: float, p: np.ndarray, v: np.ndarray, low_stay_z: float) -> None:
        """Vehicle i descends from p at start, coasting at v's horizontal part until clear_m
        below low_stay_z (the staying formation's lowest slot), then stopping (quintic)."""
        vh = np.array([v[0], v[1], 0.0])
        speed = float(np.linalg.norm(vh))
        if speed < STILL_MPS:
            coast = stop = 0.0
        else:
            coast = max(0.0, low_stay_z + self.clear - float(p[2])) / self.land_speed if math.isfinite(low_stay_z) else 0.0
            stop = QUINTIC_STOP_ACCEL * speed / self.brake
        point = p + vh * (coast + stop / 2.0)
        point[2] = p[2] + self.land_speed * (coast + stop)
        self.ld_start[i], self.ld_p[i], self.ld_v[i], self.ld_coast[i], self.ld_stop[i] = start, p, v, coast, stop
        self.ld_handover[i], self.ld_point[i] = start + coast + stop, point

    def copy_move(self, prev: Track, i: int) -> None:
        self.mv_t0[i], self.mv_p0[i], self.mv_v0[i] = prev.mv_t0_s[i], prev.mv_p0_ned_m[i], prev.mv_v0_ned_mps[i]
        self.mv_target[i], self.mv_t[i] = prev.mv_target_ned_m[i], prev.mv_duration_s[i]

    def copy_land(self, prev: Track, i: int, p: np.ndarray, v: np.ndarray, going: bool, low_stay_z: float) -> None:
        """Vehicle i's landing of the track before goes on. One that had not started down yet
        and has lost its slot starts down from where it is (p, v) now."""
        self.copy_move(prev, i)
        self.ld_start[i], self.ld_p[i], self.ld_v[i] = prev.land_start_s[i], prev.land_p_ned_m[i], prev.land_v_ned_mps[i]
        self.ld_coast[i], self.ld_stop[i] = prev.land_coast_s[i], prev.land_stop_s[i]
        self.ld_handover[i], self.ld_point[i] = prev.land_handover_s[i], prev.land_point_ned_m[i]
        if not going and not np.isfinite(prev.mv_t0_s[i]):  # it waited in a slot it has lost: down from here, now
            self.land(i, self.t0, p, v, low_stay_z)
