"""What the command source checks before it issues a plan (docs/swarm.md, "What the source
refuses"). Each check raises CommandError naming the command, the vehicles and the numbers;
the source then keeps its current plan. Pure: numpy.

* `shape_spacing`: a formation whose slots are closer than the separation.
* `morph_spacing`: a slot morph whose exact closest approach (slots.morph_closest_m, every
  vehicle on its straight line with one profile) is under the separation. With the
  assignment's squared cost it is never under min(old gap, new gap) / sqrt(2), so a change
  between shapes spaced at least sqrt(2) separations passes; closer ones are computed.
* `path_bounds`: a slot at or below the ground, or outside mission.geofence, anywhere on the
  path still to fly (the centre sampled every 0.25 m; slots over their morph's box).
* `graph_stability`: consensus gains unstable on the topology rebuilt over the vehicles left.
* `landing_columns`: a lander above a vehicle that stays (within the separation horizontally,
  lower), or two landing columns (or one and a vehicle landed before) closer than the separation.
* `clearance`: vehicles leaving the formation (parking, landing) against every other vehicle,
  sampled every 0.25 m of relative motion until they are still.
"""
from __future__ import annotations

import math

import numpy as np

from companion.commands.centre import centre_state
from companion.commands.plan import CommandError
from companion.commands.slots import horizontal_closest_m, morph_closest_m
from companion.commands.track import LAND, PARK, Track
from companion.control.formation import FormationUnstableError, check_stability
from companion.control.shapes import FormationSpec, min_separation_m, offsets_for
from companion.mission import Mission

SAMPLE_M = 0.25
"""Sampled checks step at most this far (m) of the fastest relative motion."""
SAMPLES_MAX = 20_000
"""At most this many samples per sampled check (a longer horizon is sampled more coarsely)."""
CHUNK = 256
"""Times evaluated at once by a sampled check."""


def _uav(i: int) -> str:
    return f"UAV {i + 1}"  # 1-based, as metrics.json and the schedule


def shape_spacing(what: str, spec: FormationSpec, n_slots: int, separation_m: float) -> None:
    """Raises CommandError if the shape's slots for n_slots vehicles are closer than separation_m."""
    d = min_separation_m(offsets_for(spec, n_slots))
    if d < separation_m:
        size = "radius_m" if spec.shape in ("circle", "shell") else "spacing_m"
        raise CommandError(f"{what}: a {spec.shape} of {n_slots} with {size} {spec.size_m:g} puts slots {d:.3g} m apart, "
                           f"closer than the separation ({separation_m:g} m): make it larger")


def morph_spacing(what: str, track: Track, separation_m: float) -> None:
    """Raises CommandError if two vehicles of a new slot morph come closer than separation_m."""
    if track.morph_s <= 0 or track.morph_start_s != track.plan.effective_s:
        return
    d, i, j, s = morph_closest_m(track.morph_from_ned_m, track.target_ned_m)
    if d < separation_m:
        raise CommandError(f"{what}: {_uav(i)} and {_uav(j)} would pass {d:.3g} m apart during the formation change "
                           f"({s:.0%} of the way), closer than the separation ({separation_m:g} m)")


def graph_stability(what: str, track: Track, mission: Mission) -> None:
    """Raises CommandError if the consensus loop is not stable on the graph of the vehicles left."""
    act = np.flatnonzero(track.consensus)
    if len(act) == mission.n or not len(act):
        return
    try:
        check_stability(track.weights[np.ix_(act, act)], mission.cfg.stability_gains)
    except FormationUnstableError as err:
        raise CommandError(f"{what}: the consensus loop over the {len(act)} vehicles left is unstable: {err}") from None


def _centre_samples(track: Track, mission: Mission, t_go_s: float, end_s: float) -> np.ndarray:
    """Centre positions every SAMPLE_M of its path from the plan's effective time to end_s
    (for the mission's path without an agreed start: the whole path), (S, 3)."""
    plan = track.plan
    if plan.follows_mission and math.isnan(t_go_s):
        path = mission.path
        times = np.arange(0.0, path.duration_s + SAMPLE_M / max(path.v_max_mps, 1e-3),
                          SAMPLE_M / max(path.v_max_mps, 1e-3))
        return np.array([path.at(float(t))[0] for t in times[:SAMPLES_MAX]])
    t0 = plan.effective_s
    speed = max(plan.speed_mps, mission.cfg.transit_speed_mps, float(np.linalg.norm(plan.start_velocity_ned_mps)))
    step = SAMPLE_M / max(speed, 1e-3)
    n = min(SAMPLES_MAX, max(2, int(math.ceil((end_s - t0) / step)) + 1)) if math.isfinite(end_s) else 2
    return np.array([centre_state(plan, float(t), mission, t_go_s)[0] for t in np.linspace(t0, max(end_s, t0), n)])


def path_bounds(what: str, track: Track, mission: Mission, t_go_s: float) -> None:
    """Raises CommandError if a slot would be at or below the ground (mission.ground_z_m) or
    outside mission.geofence on the path still to fly, or a vehicle leaving the formation
    would park or land from outside the geofence."""
    cfg = mission.cfg
    slotted = np.isfinite(track.target_ned_m[:, 0])
    fence = cfg.geofence
    if slotted.any():
        offs = np.concatenate([track.target_ned_m[slotted], track.morph_from_ned_m[slotted]])
        offs = offs[np.isfinite(offs).all(axis=1)]
        lo, hi = offs.min(axis=0), offs.max(axis=0)
        end = max(track.centre_end_s(mission, t_go_s), track.morph_end_s)
        c = _centre_samples(track, mission, t_go_s, end)
        if cfg.ground_z_m is not None:
            k = int(np.argmax(c[:, 2]))
            if c[k, 2] + hi[2] >= cfg.ground_z_m:
                raise CommandError(f"{what}: the formation's lowest slot would be {c[k, 2] + hi[2] - cfg.ground_z_m:.3g} m "
                                   f"below the ground (z {cfg.ground_z_m:g}) with the centre at {_v(c[k])}")
        if fence is not None:
            fmin, fmax = np.asarray(fence.min_ned_m), np.asarray(fence.max_ned_m)
            out = np.flatnonzero(((c + lo) < fmin).any(axis=1) | ((c + hi) > fmax).any(axis=1))
            if len(out):
                raise CommandError(f"{what}: formation slots would leave mission.geofence with the centre at "
                                   f"{_v(c[out[0]])}")
    parked = track.mv_target_ned_m[np.isfinite(track.mv_target_ned_m).all(axis=1)]
    if cfg.ground_z_m is not None and len(parked) and float(parked[:, 2].max()) >= cfg.ground_z_m:
        raise CommandError(f"{what}: a vehicle leaving the formation would stop at or below the ground")
    if fence is not None:
        fmin, fmax = np.asarray(fence.min_ned_m), np.asarray(fence.max_ned_m)
        for name, pts in (("park", track.mv_target_ned_m), ("land from", track.land_point_ned_m)):
            bad = np.flatnonzero(np.isfinite(pts).all(axis=1) & ((pts < fmin) | (pts > fmax)).any(axis=1))
            if len(bad):
                raise CommandError(f"{what}: {_uav(int(bad[0]))} would {name} at {_v(pts[bad[0]])}, outside "
                                   "mission.geofence (no room above the formation: land it instead)")


def landing_columns(what: str, track: Track, mission: Mission, t_go_s: float, landed: dict[int, np.ndarray],
                    separation_m: float, new: np.ndarray) -> None:
    """Raises CommandError if a vehicle that starts to land under this plan (new: (N,) bool)
    would descend onto another: a vehicle that stays (a slot or parked) lower within
    separation_m horizontally when its descent starts, another lander's column, or the spot
    of a vehicle landed before (`landed`: vehicle -> point)."""
    rows = np.flatnonzero(new)
    starts = track.land_start_s[rows]
    for i, t0 in zip(rows.tolist(), starts.tolist()):
        pos, _, _ = track.at(t0, mission, t_go_s)
        col = track.land_point_ned_m[i]
        stays = (track.role != LAND) & (np.arange(len(pos)) != i) & ~np.isfinite(track.land_start_s)
        below = np.flatnonzero(stays & (pos[:, 2] > col[2]) & (np.hypot(pos[:, 0] - col[0], pos[:, 1] - col[1]) < separation_m))
        if len(below):
            j = int(below[0])
            raise CommandError(f"{what}: {_uav(i)} would descend onto {_uav(j)}, which stays "
                               f"{float(np.hypot(*(pos[j, :2] - col[:2]))):.3g} m to the side and "
                               f"{float(pos[j, 2] - col[2]):.3g} m below: land that one too, or reshape first")
    pts = track.land_point_ned_m
    every = np.flatnonzero(np.isfinite(track.land_start_s))
    before = np.array([v for v in landed if v not in set(rows.tolist())], dtype=np.intp)
    if len(rows) and len(before):
        spots = np.array([pts[v] if np.isfinite(pts[v, 0]) else landed[v] for v in before.tolist()])
        d, a, b = horizontal_closest_m(pts[rows], spots)
        if d < separation_m:
            raise CommandError(f"{what}: {_uav(int(rows[a]))} would land {d:.3g} m from {_uav(int(before[b]))}, which "
                               "landed (or started down) there before: move the formation (GOTO) first")
    d, a, b = horizontal_closest_m(pts[every])
    if d < separation_m:
        i, j = int(every[a]), int(every[b])
        raise CommandError(f"{what}: {_uav(i)} and {_uav(j)} would land {d:.3g} m apart, closer than the separation "
                           f"({separation_m:g} m): spread the formation (a larger size or a planar shape) first")


def clearance(what: str, track: Track, mission: Mission, t_go_s: float, separation_m: float) -> None:
    """Raises CommandError if a vehicle leaving the formation (parking, landing) would come
    closer than separation_m to any other vehicle before it is still (sampled)."""
    # parked vehicles (a formation may pass under them), and landers that move sideways (a
    # quintic move first, or coasting and stopping under a moving formation); a lander that
    # goes straight down from a still point is covered by landing_columns
    sideways = np.isfinite(track.mv_t0_s) | (track.land_coast_s > 0) | (track.land_stop_s > 0)
    moving = np.flatnonzero((track.role == PARK) | ((track.role == LAND) & sideways))
    if not len(moving):
        return
    e = track.plan.effective_s
    ends = [e, track.morph_end_s]
    ends += (track.mv_t0_s[moving] + track.mv_duration_s[moving])[np.isfinite(track.mv_t0_s[moving])].tolist()
    ends += track.land_handover_s[moving][np.isfinite(track.land_handover_s[moving])].tolist()
    if (track.role == PARK).any():  # the formation passes under parked vehicles until its centre rests
        end_c = track.centre_end_s(mission, t_go_s)
        ends.append(end_c if math.isfinite(end_c) else e)
    end = max(ends) + separation_m / max(track.land_speed_mps, 1e-3)
    speed = max(track.plan.speed_mps, mission.cfg.transit_speed_mps,
                float(np.linalg.norm(track.plan.start_velocity_ned_mps))) + 4.0  # + morph, climb, descent
    n = min(SAMPLES_MAX, max(2, int(math.ceil((end - e) * speed / SAMPLE_M)) + 1))
    times = np.linspace(e, end, n)
    for k0 in range(0, n, CHUNK):
        ts = times[k0:k0 + CHUNK]
        pos = track.positions(ts, mission, t_go_s)  # (S, N, 3)
        diff = pos[:, moving, None, :] - pos[:, None, :, :]
        d = np.sqrt(np.einsum("skni,skni->skn", diff, diff))  # (S, K, N)
        d[:, np.arange(len(moving)), moving] = np.inf
        d = np.where(np.isnan(d), np.inf, d)
        k = int(np.argmin(d))
        s_, a, j = np.unravel_index(k, d.shape)
        if d[s_, a, j] < separation_m:
            i = int(moving[a])
            role = "parks" if track.role[i] == PARK else "lands"
            raise CommandError(f"{what}: {_uav(i)}, which {role}, would pass {float(d[s_, a, j]):.3g} m from "
                               f"{_uav(int(j))} {ts[s_] - e:.1f} s after the plan applies, closer than the separation "
                               f"({separation_m:g} m)" + ("; HOLD first" if track.role[i] == PARK else ""))


def _v(p) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in p) + ")"
