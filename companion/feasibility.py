"""Can this mission be flown? Pure checks (no I/O) on a validated mission, run before
anything flies: by the simulators on a scenario (sim_bridge.scenario.scenario_findings)
and by the agent on its mission file.

A config that validates can still describe a mission that cannot work: a formation
slot inside an obstacle or below the ground, a waypoint a million kilometres away, a
transit faster than the autopilot will fly. Each check returns `Finding`s: an error
means the mission cannot work as written; a warning means it can fly but is unlikely
to meet its own checks (`--strict` makes warnings errors). The table of checks is in
docs/scenario.md ("Can it fly?").

Typical use (the agent):

    findings = check_mission(mf.mission, mf.vehicle, mf.inner_loop)
    errors = [f for f in findings if f.error]
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.control.formation import ConsensusGains, FormationUnstableError
from companion.link.limits import SetpointLimits
from companion.mission import Mission, MissionConfig, formation_offsets_ned_m
from companion.params import GRAVITY_MPS2, InnerLoopConfig, VehicleParams

SEPARATION_M = 1.0
"""The separation two vehicles must keep, m: the one value the mission's checks, the scenario's
safety.separation_m (its default), and the swarm commands' refusals and landing layers use."""
MAX_RANGE_M = 10_000.0
"""Waypoints and obstacles must lie within this of the mission origin: the mission frame is
a flat tangent plane, and 10 km out the Earth's surface is already 7.8 m below it."""
LOW_HEIGHT_M = 1.0
"""A formation slot less than this above the ground is a warning (ground contact, ground effect)."""
ROTORS = 4
MAVLINK_MAX_VEHICLES = 250
"""A MAVLink run gives every vehicle its own system id, 1..250 (the agent's --vehicle-id 0..249)."""
COMPLETION_TOL_M = 0.05
"""The tolerance the formation is judged on at the end of the hover (a scenario's
completion_tol_m, whose default this is; the agent's mission file does not carry it)."""
HOVER_START_ERROR_M = 1.0
"""How far off its slot a vehicle is assumed to be when the hover begins (what the arrival,
avoidance and the final leg's deceleration typically leave), for the settling estimate."""


@dataclass(frozen=True)
class Finding:
    """One reason a mission cannot work (error) or is unlikely to meet its checks (warning).

    Attributes:
        path: dotted config path of the offending setting, e.g. "mission.waypoints_ned_m.1".
        reason: one sentence, with the numbers.
        error: True for an error, False for a warning.
    """

    path: str
    reason: str
    error: bool = True

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"


def errors_of(findings: list[Finding], strict: bool = False) -> list[Finding]:
    """The findings that stop a run: the errors, and with strict the warnings too."""
    return [f for f in findings if f.error or strict]


def thrust_to_weight(vehicle: VehicleParams) -> float:
    """All rotors at full speed against the vehicle's weight (dimensionless)."""
    t_max_n = ROTORS * vehicle.thrust_coeff_n_per_radps2 * vehicle.rotor_speed_max_radps ** 2
    return t_max_n / (vehicle.mass_kg * GRAVITY_MPS2)


def max_horizontal_accel_mps2(vehicle: VehicleParams, inner: InnerLoopConfig) -> float:
    """Largest horizontal acceleration holding height: limited by full thrust and by the
    inner loop's tilt limit, m/s^2 (0 if the vehicle cannot hover)."""
    tw = thrust_to_weight(vehicle)
    by_thrust = GRAVITY_MPS2 * math.sqrt(max(tw * tw - 1.0, 0.0))
    by_tilt = GRAVITY_MPS2 * math.tan(math.radians(inner.geometric.tilt_max_deg))
    return min(by_thrust, by_tilt)


def segment_gap_m(a: np.ndarray, b: np.ndarray, centre: np.ndarray, radius_m: float) -> float:
    """Distance from the segment a-b to the surface of a sphere (negative: it enters it), m."""
    ab = b - a
    den = float(ab @ ab)
    u = 0.0 if den == 0.0 else min(1.0, max(0.0, float((centre - a) @ ab) / den))
    return float(np.linalg.norm(a + u * ab - centre)) - radius_m


def min_slot_distance_m(offsets_ned_m: np.ndarray) -> tuple[float, int, int]:
    """Smallest distance between two formation slots, and the pair (0-based); inf for one slot."""
    best, bi, bj = math.inf, -1, -1
    for i in range(len(offsets_ned_m) - 1):
        d = np.linalg.norm(offsets_ned_m[i + 1:] - offsets_ned_m[i], axis=1)
        j = int(np.argmin(d))
        if d[j] < best:
            best, bi, bj = float(d[j]), i, i + 1 + j
    return best, bi, bj


def check_mission(mission: MissionConfig, vehicle: VehicleParams | None = None, inner: InnerLoopConfig | None = None,
                  *, limits: SetpointLimits | None = None, separation_m: float = SEPARATION_M,
                  obstacle_margin_m: float = 0.0, ground_z_m: float | None = None,
                  launch_track_ned_m: tuple[np.ndarray, np.ndarray] | None = None,
                  max_vehicles: int | None = None, completion_tol_m: float = COMPLETION_TOL_M) -> list[Finding]:
    """Everything that stops this mission from working, or makes it unlikely to pass.

    Args:
        mission: the validated mission (mission frame, NED, m).
        vehicle, inner: the airframe and inner loop (defaults: the Crazyflie, geometric).
        limits: the autopilot's offboard limits (default PX4's: MPC_XY_VEL_MAX 12 m/s, ...).
        separation_m: neighbours' slots must be at least this far apart.
        obstacle_margin_m: slots and the launch track must clear obstacles by this.
        ground_z_m: ground height (NED z); default mission.ground_z_m (None: no ground check).
        launch_track_ned_m: (first, last) release point of the carrier, or None.
        max_vehicles: the runner's largest fleet (the agent: MAVLINK_MAX_VEHICLES), or None.
        completion_tol_m: the formation's tolerance at the end of a hover before landing.
    Returns:
        Findings, errors first; empty when the mission can be flown.
    """
    vehicle = vehicle or VehicleParams()
    inner = inner or InnerLoopConfig()
    limits = limits or SetpointLimits()
    ground = mission.ground_z_m if ground_z_m is None else ground_z_m
    out: list[Finding] = []
    if max_vehicles is not None and mission.n_vehicles > max_vehicles:
        return [Finding("mission.n_vehicles", f"{mission.n_vehicles} vehicles: a MAVLink run flies at most "
                        f"{max_vehicles} (one system id, 1-250, per vehicle)")]
    try:
        Mission(mission)
    except FormationUnstableError as err:
        out.append(Finding("mission.consensus", f"the formation's closed loop is unstable: {err}"))
    wps = np.asarray(mission.waypoints_ned_m, float)
    # absurd but finite values (a 1e300 m radius) overflow to inf on the way: they are reported
    # as findings, not as numpy RuntimeWarnings printed ahead of the error
    with np.errstate(over="ignore", invalid="ignore"):
        offsets = formation_offsets_ned_m(mission.formation, mission.n_vehicles)
        out += _ranges(mission, wps, offsets, launch_track_ned_m)
        out += _ground(mission, wps, offsets, ground, launch_track_ned_m)
        out += _fence(mission, wps, offsets, launch_track_ned_m)
        out += _obstacles(mission, wps, offsets, obstacle_margin_m, launch_track_ned_m)
        out += _spacing(mission, offsets, separation_m)
        out += _speeds(mission, wps, vehicle, inner, limits)
        out += _hover_before_landing(mission, completion_tol_m)
    return sorted(out, key=lambda f: not f.error)


def _ranges(m: MissionConfig, wps: np.ndarray, offsets: np.ndarray,
            track: tuple[np.ndarray, np.ndarray] | None) -> list[Finding]:
    """Waypoints, the formation slots around them, obstacles and the carrier's release points
    within MAX_RANGE_M of the origin (`not d <= ...` also catches a distance that overflowed)."""
    out = []
    for k, w in enumerate(wps):
        d = float(np.linalg.norm(w))
        if not d <= MAX_RANGE_M:
            out.append(Finding(f"mission.waypoints_ned_m.{k}", f"{d:.4g} m from the mission origin, beyond "
                               f"{MAX_RANGE_M:.0f} m (the mission frame is a flat tangent plane)"))
            continue
        slot_d = np.linalg.norm(w + offsets, axis=1)
        far = int(np.argmax(np.where(np.isfinite(slot_d), slot_d, np.inf)))
        if not slot_d[far] <= MAX_RANGE_M:
            out.append(Finding(f"mission.waypoints_ned_m.{k}", f"the slot of UAV {far + 1} "
                               f"(mission.formation.radius_m {m.formation.radius_m:g}) is {slot_d[far]:.4g} m "
                               f"from the mission origin, beyond {MAX_RANGE_M:.0f} m"))
    for j, o in enumerate(m.obstacles):
        d = float(np.linalg.norm(o.centre_ned_m))
        if not d <= MAX_RANGE_M:
            out.append(Finding(f"mission.obstacles.{j}.centre_ned_m", f"{d:.4g} m from the mission origin, beyond "
                               f"{MAX_RANGE_M:.0f} m"))
    if track is not None:
        for name, p in zip(("first", "last"), track):
            d = float(np.linalg.norm(p))
            if not d <= MAX_RANGE_M:
                out.append(Finding("carrier", f"the {name} release point {_v(p)} is {d:.4g} m from the mission "
                                   f"origin, beyond {MAX_RANGE_M:.0f} m"))
    return out


def _ground(m: MissionConfig, wps: np.ndarray, offsets: np.ndarray, ground: float | None,
            track: tuple[np.ndarray, np.ndarray] | None) -> list[Finding]:
    if ground is None:
        return []
    out = []
    low = float(np.max(offsets[:, 2])) if len(offsets) else 0.0  # the lowest slot (a shell's bottom)
    for k, w in enumerate(wps):  # straight legs stay above the ground if both ends do
        height = ground - w[2] - low
        if ground - w[2] <= 0:
            where = "on the ground" if ground == w[2] else f"{w[2] - ground:g} m below the ground"
            out.append(Finding(f"mission.waypoints_ned_m.{k}", f"z = {w[2]:g} m is {where} "
                               f"(NED z {ground:g} m; z is down, so 10 m up is z = -10)"))
        elif height <= 0:
            out.append(Finding(f"mission.waypoints_ned_m.{k}", f"the {m.formation.shape}'s lowest slot would be "
                               f"{-height:.3g} m below the ground here (mission.formation.radius_m "
                               f"{m.formation.radius_m:g}): raise the waypoint or make the formation smaller"))
        elif height < LOW_HEIGHT_M:
            out.append(Finding(f"mission.waypoints_ned_m.{k}", f"the formation would fly {height:.2g} m above the "
                               f"ground (under {LOW_HEIGHT_M:g} m)", error=False))
    if track is not None:
        for name, p in zip(("first", "last"), track):
            if p[2] >= ground:
                out.append(Finding("carrier", f"the {name} release point {_v(p)} is at or below the ground "
                                   f"(NED z {ground:g} m)"))
    return out


def _fence(m: MissionConfig, wps: np.ndarray, offsets: np.ndarray,
           track: tuple[np.ndarray, np.ndarray] | None) -> list[Finding]:
    if m.geofence is None:
        return []
    lo, hi = np.asarray(m.geofence.min_ned_m), np.asarray(m.geofence.max_ned_m)
    out = []
    for k, w in enumerate(wps):  # the box is convex: slots inside at both ends of a leg stay inside along it
        slots = w + offsets
        outside = np.flatnonzero(((slots < lo) | (slots > hi)).any(axis=1))
        if len(outside):
            out.append(Finding(f"mission.waypoints_ned_m.{k}", f"{len(outside)} formation slot(s) lie outside "
                               f"mission.geofence (e.g. UAV {outside[0] + 1} at {_v(slots[outside[0]])})"))
    if track is not None:
        for name, p in zip(("first", "last"), track):
            if ((p < lo) | (p > hi)).any():
                out.append(Finding("carrier", f"the {name} release point {_v(p)} lies outside mission.geofence"))
    return out


def _obstacles(m: MissionConfig, wps: np.ndarray, offsets: np.ndarray, margin_m: float,
               track: tuple[np.ndarray, np.ndarray] | None) -> list[Finding]:
    out = []
    apf = m.apf
    ends = {0: "the assembly point", len(wps) - 1: "the last waypoint (the final hover)"}
    if len(wps) == 1:
        ends = {0: "the assembly point (also the final hover)"}
    for j, o in enumerate(m.obstacles):
        c, r = np.asarray(o.centre_ned_m, float), o.radius_m
        path = f"mission.obstacles.{j}"
        for k, where in ends.items():
            gap = np.linalg.norm(wps[k] + offsets - c, axis=1) - r
            inside = np.flatnonzero(gap < margin_m)
            near = np.flatnonzero(gap < apf.obstacle_influence_m)
            if len(inside) == len(offsets):
                out.append(Finding(path, f"encloses the whole formation at {where} (waypoint {k})"))
            elif len(inside):
                out.append(Finding(path, f"holds the slot of UAV(s) {_ids(inside)} at {where} (waypoint {k}) "
                                   f"within {margin_m:g} m of its surface: they can never reach it"))
            elif len(near) and apf.obstacle_gain_mps2 > 0:
                out.append(Finding(path, f"the slot of UAV(s) {_ids(near)} at {where} (waypoint {k}) lies within "
                                   f"its repulsion (mission.apf.obstacle_influence_m {apf.obstacle_influence_m:g} m): "
                                   "the vehicle is held off its slot", error=False))
        if track is not None:
            gap = segment_gap_m(np.asarray(track[0], float), np.asarray(track[1], float), c, r)
            if gap < margin_m:
                how = "passes through it" if gap < 0 else f"passes {gap:.3g} m from its surface"
                out.append(Finding(path, f"the carrier's launch track {_v(track[0])} -> {_v(track[1])} {how} "
                                   f"(margin {margin_m:g} m): vehicles would be released into it"))
    return out


def _spacing(m: MissionConfig, offsets: np.ndarray, separation_m: float) -> list[Finding]:
    d, i, j = min_slot_distance_m(offsets)
    if not math.isfinite(d):
        return []
    shape = m.formation.shape
    size = "mission.formation.radius_m" if shape in ("circle", "shell") else "mission.formation.spacing_m"
    if d < separation_m:
        return [Finding(size, f"neighbouring slots (UAVs {i + 1} and {j + 1}) are {d:.3g} m apart, "
                        f"closer than the separation of {separation_m:g} m: make the {shape} larger")]
    if d < m.apf.vehicle_influence_m and m.apf.vehicle_gain_mps2 > 0:
        return [Finding(size, f"neighbouring slots (UAVs {i + 1} and {j + 1}) are {d:.3g} m apart, "
                        f"inside the vehicles' repulsion (mission.apf.vehicle_influence_m "
                        f"{m.apf.vehicle_influence_m:g} m): they push each other off their slots", error=False)]
    return []


def _speeds(m: MissionConfig, wps: np.ndarray, vehicle: VehicleParams, inner: InnerLoopConfig,
            lim: SetpointLimits) -> list[Finding]:
    out = []
    tw = thrust_to_weight(vehicle)
    if tw <= 1.0:
        out.append(Finding("vehicle", f"thrust-to-weight {tw:.3g}: full thrust "
                           f"({ROTORS} x thrust_coeff x rotor_speed_max^2) cannot lift mass_kg {vehicle.mass_kg:g}"))
        return out
    top = max(lim.xy_vel_max_mps, lim.z_vel_max_up_mps, lim.z_vel_max_dn_mps)
    if m.transit_speed_mps > top:
        out.append(Finding("mission.transit_speed_mps", f"{m.transit_speed_mps:g} m/s is beyond what the autopilot "
                           f"flies (MPC_XY_VEL_MAX {lim.xy_vel_max_mps:g} m/s, MPC_Z_VEL_MAX_UP "
                           f"{lim.z_vel_max_up_mps:g} m/s)"))
    else:
        for k in range(len(wps) - 1):
            d = wps[k + 1] - wps[k]
            dist = float(np.linalg.norm(d))
            if dist == 0.0:
                continue
            u = d / dist
            v = min(m.transit_speed_mps, math.sqrt(dist * m.transit_accel_mps2))
            for what, speed, cap, name in (("horizontal", v * math.hypot(u[0], u[1]), lim.xy_vel_max_mps, "MPC_XY_VEL_MAX"),
                                           ("climb", v * max(0.0, -u[2]), lim.z_vel_max_up_mps, "MPC_Z_VEL_MAX_UP"),
                                           ("descent", v * max(0.0, u[2]), lim.z_vel_max_dn_mps, "MPC_Z_VEL_MAX_DN")):
                if speed > cap + 1e-9:
                    out.append(Finding("mission.transit_speed_mps", f"the leg to waypoint {k + 1} needs a {what} speed "
                                       f"of {speed:.3g} m/s, beyond {name} {cap:g} m/s"))
    a_max = max_horizontal_accel_mps2(vehicle, inner)
    if m.transit_accel_mps2 > a_max:
        out.append(Finding("mission.transit_accel_mps2", f"{m.transit_accel_mps2:g} m/s^2 is beyond the vehicle's "
                           f"{a_max:.3g} m/s^2 (thrust-to-weight {tw:.3g}, tilt limit "
                           f"{inner.geometric.tilt_max_deg:g} deg)"))
    elif m.transit_accel_mps2 > m.consensus_accel_max_mps2:
        out.append(Finding("mission.transit_accel_mps2", f"{m.transit_accel_mps2:g} m/s^2 exceeds "
                           f"mission.consensus_accel_max_mps2 ({m.consensus_accel_max_mps2:g}): the vehicles fall "
                           "behind their slots", error=False))
    if m.total_accel_max_mps2 > a_max:
        out.append(Finding("mission.total_accel_max_mps2", f"{m.total_accel_max_mps2:g} m/s^2 is more than the "
                           f"vehicle can do ({a_max:.3g} m/s^2): the inner loop saturates", error=False))
    gains = m.consensus
    if gains.k2_vel_per_s != 0:
        cruise = abs(gains.k2_pos_per_s2 / gains.k2_vel_per_s) * m.formation_error_max_m
        if cruise > lim.xy_vel_max_mps:
            out.append(Finding("mission.formation_error_max_m", f"a vehicle far from its slot cruises at "
                               f"{cruise:.3g} m/s, beyond MPC_XY_VEL_MAX {lim.xy_vel_max_mps:g} m/s", error=False))
    if m.phases.land_after_hover_s is not None and m.phases.land_speed_mps > lim.z_vel_max_dn_mps:
        out.append(Finding("mission.phases.land_speed_mps", f"{m.phases.land_speed_mps:g} m/s is clamped to "
                           f"MPC_Z_VEL_MAX_DN {lim.z_vel_max_dn_mps:g} m/s by the autopilot", error=False))
    return out


def slot_loop_poles(gains: ConsensusGains) -> tuple[complex, complex] | None:
    """The poles of one vehicle's slot error about its slot, per axis, under eq. 27 with no
    neighbour error: e'' = (k1_vel + k2_vel) e' + (k1_pos + k2_pos) e, i.e. the roots of
    s^2 - (k1_vel + k2_vel) s - (k1_pos + k2_pos) (K1 = 0 by default: s^2 - k2_vel s - k2_pos;
    k2_* < 0 pull towards the slot, docs/formation.md). Slowest first; None unless both
    have negative real parts (check_stability reports an unstable loop)."""
    a = -(gains.k1_vel_per_s + gains.k2_vel_per_s)  # damping: s^2 + a s + b
    b = -(gains.k1_pos_per_s2 + gains.k2_pos_per_s2)
    if not (a > 0 and b > 0):
        return None
    root = np.sqrt(complex(a * a - 4.0 * b))
    slow, fast = (-a + root) / 2.0, (-a - root) / 2.0
    return (slow, fast) if slow.real >= fast.real else (fast, slow)


def settling_time_s(gains: ConsensusGains, tol_m: float, error_m: float = HOVER_START_ERROR_M) -> float | None:
    """How long the slot loop (slot_loop_poles) takes to bring an error of error_m, at rest,
    within tol_m for good: the last time |e(t)| >= tol_m, from the exact step response
    e(t) = error_m (p_f e^(p_s t) - p_s e^(p_f t)) / (p_f - p_s). For real poles that is
    about ln(p_f / (p_f - p_s) * error_m / tol_m) / |p_s|: the default gains (poles -0.6 and
    -1.0 /s) take 6.5 s from 1 m to 0.05 m. None for an unstable loop; 0 if already within."""
    poles = slot_loop_poles(gains)
    if poles is None:
        return None
    if error_m <= tol_m:
        return 0.0
    ps, pf = poles
    rate = -ps.real
    if abs(pf - ps) <= 1e-9 * abs(pf):  # a double pole p: e(t) = error_m (1 - p t) e^(p t)
        t = np.linspace(0.0, (2.0 * np.log(error_m / tol_m) + 10.0) / rate, 20001)  # (past the last crossing)
        e = error_m * (1.0 - ps.real * t) * np.exp(ps.real * t)
    else:
        envelope = (abs(pf) + abs(ps)) / abs(pf - ps)  # |e(t)| <= error_m * envelope * e^(-rate t)
        t = np.linspace(0.0, np.log(envelope * error_m / tol_m) / rate, 20001)
        e = (error_m * (pf * np.exp(ps * t) - ps * np.exp(pf * t)) / (pf - ps)).real
    above = np.flatnonzero(np.abs(e) >= tol_m)
    return float(t[above[-1]]) if len(above) else 0.0


def _hover_before_landing(m: MissionConfig, tol_m: float) -> list[Finding]:
    """A landing mission's hover must be long enough for the formation to settle within
    the tolerance it is judged on at its end (docs/scenario.md, "Can it fly?")."""
    hover = m.phases.land_after_hover_s
    if hover is None:
        return []
    settle = settling_time_s(m.consensus, tol_m)
    if settle is None or hover >= settle:
        return []
    ps, pf = slot_loop_poles(m.consensus) or (0j, 0j)
    g = m.consensus
    a, b = -(g.k1_vel_per_s + g.k2_vel_per_s), -(g.k1_pos_per_s2 + g.k2_pos_per_s2)
    poles = (f"{ps.real:.3g} and {pf.real:.3g} /s" if ps.imag == 0 else
             f"{ps.real:.3g} +/- {abs(ps.imag):.3g}j /s")
    return [Finding("mission.phases.land_after_hover_s", (
        f"{hover:g} s of hover before landing is shorter than the formation needs to settle: a vehicle "
        f"{HOVER_START_ERROR_M:g} m off its slot takes about {settle:.1f} s to come within {tol_m:g} m "
        f"(the tolerance it is judged on at the end of the hover), per axis s^2 + {a:.3g} s + {b:.3g} "
        f"(mission.consensus k2_vel_per_s {g.k2_vel_per_s:g}, k2_pos_per_s2 {g.k2_pos_per_s2:g}: poles "
        f"{poles}); hover at least {math.ceil(settle):g} s"), error=False)]


def _v(p) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in p) + ")"


def _ids(rows: np.ndarray, shown: int = 6) -> str:
    """1-based UAV numbers, as in metrics.json and the figures."""
    ids = ", ".join(str(int(i) + 1) for i in rows[:shown])
    return ids + (f" and {len(rows) - shown} more" if len(rows) > shown else "")
