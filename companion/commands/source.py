"""The command source: the authoritative current plan, one method per command (docs/swarm.md,
"The commands"). Pure: no clock, no I/O.

The source flies, in its head, exactly what a vehicle that hears every plan on time flies:
the chain of `Track`s (companion.commands.track) from the mission's own plan. Every new plan
starts from where that puts the swarm at its effective time (the centre's position and
velocity, each vehicle's offset), and is checked (companion.commands.checks) before it is
issued: a refused command raises CommandError and changes nothing.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.commands import checks
from companion.commands.centre import centre_state, stop_point, waypoints_ahead
from companion.commands.plan import (
    DEFAULT_LEAD_S,
    DEFAULT_MORPH_SPEED_MPS,
    PLAN_WAYPOINTS_MAX,
    URGENT_LEAD_S,
    WAYPOINT_MAX_M,
    CommandError,
    CommandKind,
    Point,
    SwarmPlan,
    _f32,
    _usec,
    blend_accel_mps2,
    initial_plan,
    lead_s,
    quantised,
)
from companion.commands.slots import horizontal_closest_m, min_jerk_time_s
from companion.commands.track import Track, enter, initial_track
from companion.control.assignment import assign_slots
from companion.control.shapes import FormationSpec, SlotOrder, offsets_for
from companion.feasibility import SEPARATION_M
from companion.mission import Mission

if TYPE_CHECKING:
    from companion.commands.schedule import CommandEntry

LAND_SPREAD_MAX = 4.0
"""LAND of every vehicle spreads a formation whose landing columns are closer than the
separation (a 3-D shell) by at most this factor before it descends; beyond: refused."""


@dataclass(frozen=True)
class _Resume:
    """What RESUME flies after a HOLD: the waypoints of the held path not yet reached
    (None: the mission's own path, held before the centre had left waypoint 0)."""

    waypoints: tuple[Point, ...] | None
    speed_mps: float
    land_at_end: bool


class CommandSource:
    """The authoritative current plan, and one method per command, each returning the new
    SwarmPlan (seq + 1, effective = issue time + its lead, never before the current plan's).

    Pure: no clock, no I/O. The plans it returns are already quantised to the wire
    (`quantised`), so they equal what every agent assembles from `plan_messages`.

    Args:
        mission: the mission every agent flies (centre path, formation, accelerations).
        n_vehicles: vehicles in the mission (default mission.n).
        lead_s: how long after issue a plan applies (DEFAULT_LEAD_S); HOLD: urgent_lead_s
            (URGENT_LEAD_S); ABORT: at once.
        morph_speed_mps: peak slot speed of a formation change (DEFAULT_MORPH_SPEED_MPS).
        separation_m: what the source keeps vehicles apart by (companion.feasibility.SEPARATION_M,
            a scenario's safety.separation_m).

    Commands must be issued in time order (t_s never decreasing). Any command after ABORT
    raises CommandError: ABORT hands every vehicle to its autopilot for good.
    """

    def __init__(self, mission: Mission, n_vehicles: int | None = None, *, lead_s: float = DEFAULT_LEAD_S,
                 urgent_lead_s: float = URGENT_LEAD_S, morph_speed_mps: float = DEFAULT_MORPH_SPEED_MPS,
                 separation_m: float = SEPARATION_M):
        for name, x in (("lead_s", lead_s), ("urgent_lead_s", urgent_lead_s)):
            if not (math.isfinite(x) and x >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {x}")
        for name, x in (("morph_speed_mps", morph_speed_mps), ("separation_m", separation_m)):
            if not (math.isfinite(x) and x > 0):
                raise ValueError(f"{name} must be finite and > 0, got {x}")
        self.mission = mission
        self.plan = initial_plan(mission, n_vehicles)
        self.n = self.plan.n_vehicles
        self.lead_s = lead_s
        self.urgent_lead_s = urgent_lead_s
        self.morph_speed_mps = morph_speed_mps
        self.separation_m = separation_m
        self.t_go_s = math.nan
        self.plans: list[SwarmPlan] = [self.plan]
        """Every plan made, seq 0 first (plans[k].seq == k)."""
        self.track: Track = initial_track(self.plan, mission)
        """The current plan as a vehicle that heard every plan on time flies it."""
        self.landed: dict[int, np.ndarray] = {}
        """Vehicles whose descent had begun when a later plan applied, and where they land
        (later landings must not descend onto them)."""
        self._circle_order = mission.cfg.formation.slot_order
        self._resume: _Resume | None = None
        self._last_issue_s = -math.inf

    # ------------------------------------------------------------------ queries
    def set_t_go(self, t_go_s: float) -> None:
        """The transit start the swarm agreed (mission time; NaN: none yet)."""
        self.t_go_s = float(t_go_s)

    def centre_ned_m(self, t_s: float) -> np.ndarray:
        """Where the current plan puts the formation centre at t_s, (3,)."""
        return centre_state(self.plan, t_s, self.mission, self.t_go_s)[0]

    def reference(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every vehicle's reference under the current plan at t_s: position, velocity,
        acceleration, (n, 3) each (companion.commands.track)."""
        return self.track.at(t_s, self.mission, self.t_go_s)

    def offsets_ned_m(self, t_s: float) -> np.ndarray:
        """Each vehicle's reference at t_s less the centre, (n, 3): its slot offset (morph
        included) in the formation; where it parks or lands otherwise."""
        return self.reference(t_s)[0] - self.centre_ned_m(t_s)

    @property
    def active(self) -> tuple[int, ...]:
        """Vehicles that take part in the formation's next re-assignment: neither excluded nor landing."""
        gone = self.plan.excluded | self.plan.landing
        return tuple(v for v in range(self.n) if v not in gone)

    def descending(self, t_s: float) -> frozenset[int]:
        """Vehicles whose descent has begun by t_s under the current plan (an RTL's too): every
        later plan lists them as landing, and none can rejoin."""
        return frozenset(np.flatnonzero(self.track.land_start_s <= t_s).tolist())

    def morph_time_s(self, largest_move_m: float) -> float:
        """How long a formation change whose largest slot move is largest_move_m takes, s:
        the minimum-jerk move whose peak speed is morph_speed_mps and whose peak acceleration
        is the mission's transit_accel_mps2, whichever is longer (0 for no move)."""
        return min_jerk_time_s(largest_move_m, self.morph_speed_mps, self.mission.cfg.transit_accel_mps2)

    # ------------------------------------------------------------------ commands
    def hold(self, t_s: float) -> SwarmPlan:
        """HOLD: the centre brakes from its velocity at the effective time (URGENT_LEAD_S after
        issue) to a stop at hold_brake_mps2; the formation is kept (a morph under way completes)."""
        e = self._begin(t_s, "hold")
        if not self.plan.hold:
            self._resume = self._rest_of_path(e)
        return self._commit(t_s, "hold", e, **self._held(e), land_at_end=False, **self._keep_slots(e))

    def resume(self, t_s: float) -> SwarmPlan:
        """RESUME: from where the held centre is along the rest of the path that was held (at
        its speed; an RTL's landing at the end is kept).

        Raises:
            CommandError: nothing is held; the rest of the path has more than 8 waypoints.
        """
        e = self._begin(t_s, "resume")
        r = self._resume
        if not self.plan.hold or r is None:
            raise CommandError("RESUME: the centre is not held")
        if r.waypoints is None and (math.isnan(self.t_go_s) or self.t_go_s >= e):
            # held before the mission's transit began: its own plan again (t_go starts the transit)
            centre: dict[str, Any] = dict(waypoints_ned_m=(), speed_mps=self.mission.cfg.transit_speed_mps,
                                          start_velocity_ned_mps=(0.0, 0.0, 0.0))
        else:  # (held before the transit, and the agreed start has passed: the mission's waypoints from now)
            rest = _points(self.mission.path.waypoints_ned_m[1:]) if r.waypoints is None else r.waypoints
            centre = self._path_from(e, rest, hold=False)
            centre["speed_mps"] = r.speed_mps
        self._check_waypoint_count(centre["waypoints_ned_m"], "RESUME: the rest of the held path")
        plan = self._commit(t_s, "resume", e, hold=False, land_at_end=r.land_at_end, **centre, **self._keep_slots(e))
        self._resume = None
        return plan

    def goto(self, t_s: float, waypoints_ned_m: Sequence[Sequence[float]], speed_mps: float | None = None) -> SwarmPlan:
        """GOTO: the centre turns from its motion at the effective time towards the new
        waypoints (at most 7: the wire carries 8 with the start) and flies them at speed_mps
        (default: the mission's transit speed). A hold ends.

        Raises:
            CommandError: no waypoint, more than 7, a non-finite or absurd coordinate, speed not > 0.
        """
        e = self._begin(t_s, "goto")
        wps = _check_points(waypoints_ned_m, "GOTO")
        if len(wps) > PLAN_WAYPOINTS_MAX - 1:
            raise CommandError(f"GOTO: {len(wps)} waypoints; a plan carries at most {PLAN_WAYPOINTS_MAX - 1} "
                               "besides the centre's start")
        return self._goto(t_s, e, "goto", wps, self._speed(speed_mps, "GOTO"), land_at_end=False)

    def rtl(self, t_s: float) -> SwarmPlan:
        """RTL: GOTO the launch area (the mission's assembly point, waypoint 0) at the
        mission's transit speed, then every vehicle with a slot lands there, in layers."""
        e = self._begin(t_s, "rtl")
        home = _points(self.mission.path.waypoints_ned_m[:1])
        return self._goto(t_s, e, "rtl", home, self.mission.cfg.transit_speed_mps, land_at_end=True)

    def formation(self, t_s: float, spec: FormationSpec) -> SwarmPlan:
        """FORMATION: a new shape, size or rotation for the vehicles neither excluded nor
        landing; the new slot table minimises the sum of squared moves from where they are
        (companion.control.assignment), and the move takes morph_s (`morph_time_s`).
        A circle takes the mission's slot order (companion.control.shapes).

        Raises:
            CommandError: no vehicle left to form up; slots closer than the separation; two
                vehicles passing closer than it during the change (companion.commands.checks).
        """
        e = self._begin(t_s, "formation")
        gone = self.plan.excluded | self.plan.landing | self.descending(e)
        active = tuple(v for v in range(self.n) if v not in gone)
        if not active:
            raise CommandError("FORMATION: every vehicle is excluded or landing")
        return self._commit(t_s, "formation", e, **self._reform(e, self._normalised(spec), active))

    def exclude(self, t_s: float, ids: Iterable[int], land: bool = False) -> SwarmPlan:
        """EXCLUDE: the vehicles leave consensus and the formation layer: they park
        (companion.commands.track: above the formation, then still) or, with land=True, land
        where they are; the others close the gap (the shape for the new count, re-assigned).

        Raises:
            CommandError: an id outside the mission, or none given; a move that is unsafe.
        """
        e = self._begin(t_s, "exclude")
        ids_ = self._ids(ids, "EXCLUDE")
        excluded = self.plan.excluded | ids_
        landing = (self.plan.landing | ids_ if land else self.plan.landing) | self.descending(e)
        active = tuple(v for v in range(self.n) if v not in excluded and v not in landing)
        return self._commit(t_s, "exclude", e, excluded=excluded, landing=landing,
                            excluded_land=bool(excluded) and excluded <= landing,
                            **self._reform(e, self.plan.formation, active))

    def rejoin(self, t_s: float, ids: Iterable[int]) -> SwarmPlan:
        """REJOIN: excluded (or landing) vehicles come back: the shape for the new count,
        re-assigned from where every vehicle is (a parked one descends into its slot).

        Raises:
            CommandError: an id outside the mission, or one that is neither excluded nor landing.
        """
        e = self._begin(t_s, "rejoin")
        ids_ = self._ids(ids, "REJOIN")
        down = ids_ & self.descending(e)
        if down:
            raise CommandError(f"REJOIN: vehicle(s) {sorted(down)} have started to land")
        back = ids_ - self.plan.excluded - self.plan.landing
        if back:
            raise CommandError(f"REJOIN: vehicle(s) {sorted(back)} are neither excluded nor landing")
        excluded = self.plan.excluded - ids_
        landing = (self.plan.landing - ids_) | self.descending(e)
        active = tuple(v for v in range(self.n) if v not in excluded and v not in landing)
        return self._commit(t_s, "rejoin", e, excluded=excluded, landing=landing,
                            excluded_land=bool(excluded) and excluded <= landing,
                            **self._reform(e, self.plan.formation, active))

    def land(self, t_s: float, ids: Iterable[int] | None = None) -> SwarmPlan:
        """LAND: ids=None: every vehicle lands. The centre brakes to a stop (as HOLD); once it
        and the slots are still, the formation descends in layers (lowest first); a formation
        whose landing columns are closer than the separation (a 3-D shell) first spreads
        (its size times k, up to LAND_SPREAD_MAX); parked vehicles move out of its footprint
        and land with the top layer. A subset: those vehicles land from their slots, in
        layers, leaving a moving formation downwards; the centre and the others go on,
        keeping their slots (FORMATION closes the gap).

        Raises:
            CommandError: an id outside the mission, or an empty subset; a lander above a
                vehicle that stays, or two landing columns closer than the separation.
        """
        e = self._begin(t_s, "land")
        p = self.plan
        if ids is None:
            if not p.hold:
                self._resume = self._rest_of_path(e)
            changes = dict(**self._held(e), land_at_end=False, landing=frozenset(range(self.n)),
                           excluded_land=bool(p.excluded), **self._keep_slots(e))
            changes.update(self._spread_to_land(e, changes))
            return self._commit(t_s, "land", e, **changes)
        landing = p.landing | self._ids(ids, "LAND") | self.descending(e)
        return self._commit(t_s, "land", e, landing=landing, excluded_land=bool(p.excluded) and p.excluded <= landing,
                            **self._copy_centre(e), **self._keep_slots(e))

    def abort(self, t_s: float) -> SwarmPlan:
        """ABORT: every agent hands its vehicle to the autopilot's own Hold/Loiter now: the
        plan's effective time is the issue time itself (no lead), so every agent applies it
        as soon as it holds it. Final: no command can follow."""
        e = self._begin(t_s, "abort")
        return self._commit(t_s, "abort", e, abort=True, **self._copy_centre(e), **self._keep_slots(e))

    def apply(self, entry: CommandEntry) -> SwarmPlan:
        """Issue one entry of a scenario's `commands:` schedule (vehicles 1-based there)."""
        k, t = entry.kind, entry.t_s
        ids = None if entry.vehicles is None else [v - 1 for v in entry.vehicles]
        if k == "hold":
            return self.hold(t)
        if k == "resume":
            return self.resume(t)
        if k == "goto":
            return self.goto(t, entry.waypoints_ned_m or (), entry.speed_mps)
        if k == "formation":
            return self.formation(t, entry.formation_spec(self.plan.formation))
        if k == "exclude":
            return self.exclude(t, ids or (), land=bool(entry.land))
        if k == "rejoin":
            return self.rejoin(t, ids or ())
        if k == "land":
            return self.land(t, ids)
        if k == "rtl":
            return self.rtl(t)
        return self.abort(t)

    # ------------------------------------------------------------------ internals
    def _begin(self, t_s: float, kind: CommandKind) -> float:
        """The effective time of a command issued at t_s (checks it can be issued): t_s plus
        its lead (lead_s), never before the current plan's; ABORT at t_s itself."""
        if self.plan.abort:
            raise CommandError(f"the swarm was aborted (plan {self.plan.seq}): no command can follow")
        if not math.isfinite(t_s):
            raise CommandError(f"command time must be finite, got {t_s}")
        if t_s < self._last_issue_s:
            raise CommandError(f"commands must be issued in time order: {t_s} s is before the last one "
                               f"({self._last_issue_s} s)")
        if kind == "abort":
            return _usec(t_s)
        return _usec(max(t_s + lead_s(kind, self.lead_s, self.urgent_lead_s), self.plan.effective_s))

    def _commit(self, t_s: float, kind: CommandKind, e: float, **changes: Any) -> SwarmPlan:
        p = self.plan
        changes["landing"] = changes.get("landing", p.landing) | self.descending(e)  # a descent never stops
        plan = quantised(dataclasses.replace(p, seq=p.seq + 1, kind=kind, effective_s=e, **changes))
        what = kind.upper()
        self._check_waypoint_count(plan.waypoints_ned_m, what)
        track = enter(plan, self.track, self.mission, self.t_go_s, self.separation_m)
        landed = dict(self.landed)
        old = self.track
        for v in np.flatnonzero(old.land_start_s <= e).tolist():
            landed.setdefault(v, old.land_point_ned_m[v].copy())
        if not plan.abort:
            self._check(what, track, landed)
        self.track = track
        self.plan = plan
        self.plans.append(plan)
        self.landed = landed
        self._last_issue_s = t_s
        return plan

    def _check(self, what: str, track: Track, landed: dict[int, np.ndarray]) -> None:
        m, sep, t_go = self.mission, self.separation_m, self.t_go_s
        n_slots = track.plan.n_slots
        if n_slots > 1 and track.morph_start_s == track.plan.effective_s:  # a new layout
            checks.shape_spacing(what, track.plan.formation, n_slots, sep)
        checks.morph_spacing(what, track, sep)
        checks.path_bounds(what, track, m, t_go)
        checks.graph_stability(what, track, m)
        new_landers = np.isfinite(track.land_start_s) & ~np.isin(np.arange(self.n), list(landed))
        checks.landing_columns(what, track, m, t_go, landed, sep, new_landers)
        checks.clearance(what, track, m, t_go, sep)

    def _centre(self, e: float) -> tuple[Point, Point]:
        """The current plan's centre at e: position and velocity (as tuples)."""
        c, v, _ = centre_state(self.plan, e, self.mission, self.t_go_s)
        return _point(c), _point(v)

    def _held(self, e: float) -> dict[str, Any]:
        """A held centre from e: braking from its motion then to a stop."""
        p0, v0 = self._centre(e)
        return dict(waypoints_ned_m=(p0,), start_velocity_ned_mps=v0, hold=True)

    def _path_from(self, e: float, rest: Sequence[Point], hold: bool) -> dict[str, Any]:
        """A centre path from the centre's motion at e through `rest`: the plan's waypoints
        start with the centre at e, its start velocity is the centre's then, and the leading
        waypoints its stop point has already passed are dropped (companion.commands.centre)."""
        p0, v0 = self._centre(e)
        probe = dataclasses.replace(self.plan, hold=hold)
        stop = stop_point(np.array(p0), np.array(v0), blend_accel_mps2(probe, self.mission))
        rest = list(rest)
        while rest:  # a waypoint the stop point is at or beyond, seen from p0, has been passed
            w = np.array(rest[0])
            if float(np.dot(stop - w, w - np.array(p0))) >= 0.0 and len(rest) > 1:
                rest.pop(0)
            else:
                break
        return dict(waypoints_ned_m=_dedup((p0, *rest)), start_velocity_ned_mps=v0)

    def _copy_centre(self, e: float) -> dict[str, Any]:
        """The current centre motion, carried into a plan that applies at e: the mission's
        path carries over unchanged; a hold brakes on to the same stop; a commanded path goes
        on from the centre's position and velocity at e through the waypoints still ahead."""
        p = self.plan
        if p.follows_mission:
            return {}
        if p.hold:
            return self._held(e)
        return self._path_from(e, waypoints_ahead(p, self.mission, e, self.t_go_s), hold=False)

    def _rest_of_path(self, e: float) -> _Resume:
        p = self.plan
        speed = self.mission.cfg.transit_speed_mps if p.follows_mission else p.speed_mps
        if p.follows_mission and not Mission.tau_s(e, self.t_go_s) > 0:
            return _Resume(None, speed, p.land_at_end)
        return _Resume(waypoints_ahead(p, self.mission, e, self.t_go_s), speed, p.land_at_end)

    def _goto(self, t_s: float, e: float, kind: CommandKind, wps: tuple[Point, ...], speed: float,
              land_at_end: bool) -> SwarmPlan:
        changes = dict(**self._path_from(e, wps, hold=False), speed_mps=speed, hold=False, land_at_end=land_at_end,
                       **self._keep_slots(e))
        if land_at_end:
            changes.update(self._spread_to_land(e, changes))
        plan = self._commit(t_s, kind, e, **changes)
        self._resume = None
        return plan

    def _keep_slots(self, e: float) -> dict[str, Any]:
        """Slots unchanged: a morph under way goes on and ends on time (morph_s: what is left
        of it at e, for vehicles that missed the plan that began it)."""
        tr = self.track
        return dict(morph_s=max(0.0, tr.morph_end_s - e) if tr.morph_s > 0 else 0.0)

    def _reform(self, e: float, spec: FormationSpec, active: tuple[int, ...]) -> dict[str, Any]:
        """The shape for the active vehicles, assigned from where each is at e (its reference
        then, relative to the centre: a parked vehicle from its parking point)."""
        pos, _, _ = self.track.at(e, self.mission, self.t_go_s)
        cur = pos - self.centre_ned_m(e)
        rows = list(active)
        slot_of = [-1] * self.n
        largest = 0.0
        if rows:
            old = cur[rows]
            new = offsets_for(spec, len(rows))
            take = assign_slots(old, new)
            for v, s in zip(rows, take):
                slot_of[v] = int(s)
            largest = float(np.linalg.norm(new[take] - old, axis=1).max())
        morph = self.morph_time_s(largest)
        return dict(formation=spec, slot_of=tuple(slot_of), morph_s=morph, **self._copy_centre(e))

    def _spread_to_land(self, e: float, changes: dict[str, Any]) -> dict[str, Any]:
        """LAND of all: if the slots' landing columns are closer than the separation, the
        formation first grows by k (radius or spacing): every distance grows along the
        straight-line morph, so it is safe; k is the smallest that clears them."""
        spec = self.plan.formation
        slot_of = self.plan.slot_of
        n_slots = sum(1 for s in slot_of if s >= 0)
        if n_slots < 2:
            return {}
        offs = offsets_for(spec, n_slots)
        d, _, _ = horizontal_closest_m(offs)
        if d >= self.separation_m:
            return {}
        k = self.separation_m / max(d, 1e-9) * 1.01
        if k > LAND_SPREAD_MAX:
            raise CommandError(f"LAND: the {spec.shape}'s landing columns are {d:.3g} m apart; spreading it "
                               f"{k:.3g} times exceeds {LAND_SPREAD_MAX:g}: change to a planar formation first")
        grown = self._rounded(dataclasses.replace(spec, radius_m=spec.radius_m * k, spacing_m=spec.spacing_m * k),
                              spec.slot_order)
        pos, _, _ = self.track.at(e, self.mission, self.t_go_s)
        cur = (pos - self.centre_ned_m(e))[[v for v, s in enumerate(slot_of) if s >= 0]]
        largest = float(np.linalg.norm(offsets_for(grown, n_slots)[[s for s in slot_of if s >= 0]] - cur, axis=1).max())
        return dict(formation=grown, morph_s=max(self.morph_time_s(largest), changes.get("morph_s", 0.0)))

    def _normalised(self, spec: FormationSpec) -> FormationSpec:
        if not isinstance(spec, FormationSpec):
            raise CommandError(f"FORMATION: expected a FormationSpec, got {type(spec).__name__}")
        order: SlotOrder = self._circle_order if spec.shape == "circle" else "sequential"
        try:
            return self._rounded(spec, order)
        except ValueError as exc:  # (a size beyond float32)
            raise CommandError(f"FORMATION: {exc}") from None

    @staticmethod
    def _rounded(spec: FormationSpec, order: SlotOrder) -> FormationSpec:
        # (as the wire carries it, so that the slots are assigned to the very offsets every agent computes)
        return dataclasses.replace(spec, slot_order=order, radius_m=_f32(spec.radius_m), spacing_m=_f32(spec.spacing_m),
                                   rotation_rad=_f32(spec.rotation_rad))

    def _ids(self, ids: Iterable[int], what: str) -> frozenset[int]:
        try:
            out = frozenset(int(i) for i in ids)
        except (TypeError, ValueError):
            raise CommandError(f"{what}: vehicle ids must be whole numbers, got {ids!r}") from None
        if not out:
            raise CommandError(f"{what}: no vehicle given")
        bad = sorted(i for i in out if not 0 <= i < self.n)
        if bad:
            raise CommandError(f"{what}: vehicle id(s) {bad} are not in the mission (0..{self.n - 1})")
        return out

    def _speed(self, speed_mps: float | None, what: str) -> float:
        if speed_mps is None:
            return self.mission.cfg.transit_speed_mps
        if not (math.isfinite(speed_mps) and speed_mps > 0):
            raise CommandError(f"{what}: speed must be finite and > 0, got {speed_mps}")
        return float(speed_mps)

    @staticmethod
    def _check_waypoint_count(wps: tuple, what: str) -> None:
        if len(wps) > PLAN_WAYPOINTS_MAX:
            raise CommandError(f"{what} has {len(wps)} waypoints; a plan carries at most {PLAN_WAYPOINTS_MAX}")


def _point(a: np.ndarray) -> Point:
    return (float(a[0]), float(a[1]), float(a[2]))


def _points(a: np.ndarray) -> tuple[Point, ...]:
    return tuple((float(p[0]), float(p[1]), float(p[2])) for p in np.asarray(a, dtype=float).reshape(-1, 3))


def _dedup(wps: Sequence[Point]) -> tuple[Point, ...]:
    """Drop points equal to the one before (a zero leg would add a dwell)."""
    out: list[Point] = []
    for p in wps:
        if not out or math.dist(p, out[-1]) > 1e-9:
            out.append(p)
    return tuple(out)


def _check_points(waypoints: Sequence[Sequence[float]], what: str) -> tuple[Point, ...]:
    try:
        a = np.asarray(waypoints, dtype=float)
    except (TypeError, ValueError):
        raise CommandError(f"{what}: waypoints must be numbers x, y, z (NED, m)") from None
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        raise CommandError(f"{what}: give one or more waypoints of three numbers x, y, z (NED, m)")
    if not np.all(np.isfinite(a)) or np.abs(a).max() > WAYPOINT_MAX_M:
        raise CommandError(f"{what}: waypoints must be finite and within {WAYPOINT_MAX_M:g} m of the origin")
    return _points(a)

