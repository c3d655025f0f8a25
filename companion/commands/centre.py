"""The formation centre under a plan: the ONE function the source and every agent use
(docs/swarm.md, "The centre"). Pure: numpy, companion.mission.

A plan that follows the mission's path (no waypoints: seq 0, and commands that keep it)
puts the centre on `mission.path` at `Mission.tau_s(t, t_go)`, exactly as before any command.

A plan with waypoints starts where the centre was at its effective time, p0 =
waypoints_ned_m[0], moving at v0 = start_velocity_ned_mps, and never makes the velocity
jump. With a the plan's blend rate (`blend_accel_mps2`: the hold brake for a held centre,
the mission's transit acceleration otherwise), tau = t - effective_s:

    c(tau) = P(tau) + d(tau)

* d, the lag, sheds v0 at the constant rate a: d(tau) = -s_b + v0 tau - a tau^2 v0/|v0| / 2
  for tau < T_b = |v0| / a, then 0; s_b = v0 |v0| / (2 a) is the braking distance, so
  d(0) = -s_b, d'(0) = v0, and d ends at rest at 0.
* P is the rest-to-rest CentrePath of the mission's kind (trapezoidal legs at speed_mps and
  transit_accel_mps2, waypoint_dwell_s) from the STOP POINT p0 + s_b through the other
  waypoints (a held centre: the stop point alone). The first of them is dropped when it lies
  within STOP_DEDUP_M of the stop point.

So c(0) = p0, c'(0) = v0, |c''| <= a + transit_accel_mps2, and c ends exactly on P.
* HOLD (P at rest at the stop point): the centre brakes to a stop at the constant deceleration
  a along v0, p0 + s_b being where it stops.
* A plan that keeps a path flown at cruise speed v (e.g. FORMATION during a GOTO): P starts
  from rest s_b ahead and gains speed at transit_accel while d loses it at the same rate: c
  keeps v exactly, and P then cruises on and stops at the next waypoint as the old path would.
* GOTO, RTL, RESUME: the centre turns from v0 towards the new waypoints smoothly.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from companion.commands.plan import Point, SwarmPlan, blend_accel_mps2
from companion.mission import CentrePath, Mission

STOP_DEDUP_M = 1e-3
"""A plan's second waypoint this close to its stop point is dropped (a zero leg would add a dwell)."""
_ZERO = np.zeros(3)


@dataclass(frozen=True, eq=False)
class CentreMotion:
    """The centre of one plan with waypoints (module docstring): c(t) = P(t - t0) + d(t - t0).

    Attributes:
        path: P, the rest-to-rest CentrePath from the stop point.
        t0_s: its time origin (the plan's effective_s), mission time, s.
        p0_ned_m, v0_ned_mps: (3,) the centre's position and velocity at t0_s.
        blend_mps2: a, the rate at which the lag sheds v0, m/s^2 (> 0).
    """

    path: CentrePath
    t0_s: float
    p0_ned_m: np.ndarray
    v0_ned_mps: np.ndarray
    blend_mps2: float

    @functools.cached_property
    def brake_s(self) -> float:
        """T_b: how long the lag lasts, s."""
        return float(np.linalg.norm(self.v0_ned_mps)) / self.blend_mps2

    @functools.cached_property
    def stop_ned_m(self) -> np.ndarray:
        """p0 + s_b: where P starts, (3,)."""
        return stop_point(self.p0_ned_m, self.v0_ned_mps, self.blend_mps2)

    @functools.cached_property
    def duration_s(self) -> float:
        """From t0_s until the centre comes to rest at the end, s."""
        return max(self.path.duration_s, self.brake_s)

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """c, c', c'' at mission time t_s, (3,) each (before t0_s: p0, v0, 0)."""
        tau = t_s - self.t0_s
        if tau <= 0.0:
            return self.p0_ned_m.copy(), self.v0_ned_mps.copy(), _ZERO.copy()
        c, v, a = self.path.at(tau)
        if tau < self.brake_s:
            v0 = self.v0_ned_mps
            u = v0 / float(np.linalg.norm(v0))
            b = self.blend_mps2
            c = c + (-0.5 * b * (self.brake_s - tau) ** 2) * u  # d = -s_b + v0 tau - b tau^2 u / 2
            v = v + v0 - (b * tau) * u
            a = a - b * u
        return c, v, a


def stop_point(p0_ned_m: np.ndarray, v0_ned_mps: np.ndarray, decel_mps2: float) -> np.ndarray:
    """Where a point at p0 moving at v0 stops under the constant deceleration decel along v0:
    p0 + v0 |v0| / (2 decel), (3,)."""
    v0 = np.asarray(v0_ned_mps, dtype=float)
    return np.asarray(p0_ned_m, dtype=float) + v0 * (float(np.linalg.norm(v0)) / (2.0 * decel_mps2))


@functools.lru_cache(maxsize=64)
def _motion(waypoints: tuple[Point, ...], v0: Point, t0: float, speed: float, hold: bool, accel: float, dwell: float,
            blend: float) -> CentreMotion:
    p0 = np.asarray(waypoints[0], dtype=float)
    v = np.asarray(v0, dtype=float)
    stop = stop_point(p0, v, blend)
    rest = [np.asarray(w, dtype=float) for w in ([] if hold else waypoints[1:])]
    if rest and float(np.linalg.norm(rest[0] - stop)) < STOP_DEDUP_M:
        rest = rest[1:]
    path = CentrePath(np.vstack([stop, *rest]) if rest else stop.reshape(1, 3), speed, accel, dwell)
    return CentreMotion(path, t0, p0, v, blend)


def plan_centre(plan: SwarmPlan, mission: Mission) -> CentreMotion | None:
    """The centre motion of a plan with waypoints (cached), None for one that follows the
    mission's path (mission.path from t_go)."""
    if plan.follows_mission:
        return None
    cfg = mission.cfg
    return _motion(plan.waypoints_ned_m, plan.start_velocity_ned_mps, plan.effective_s, plan.speed_mps, plan.hold,
                   cfg.transit_accel_mps2, cfg.waypoint_dwell_s, blend_accel_mps2(plan, mission))


def plan_path(plan: SwarmPlan, mission: Mission) -> CentrePath:
    """The rest-to-rest CentrePath under a plan's centre: the mission's own (`mission.path`,
    time since t_go) for a plan without waypoints, else P of the module docstring (time since
    plan.effective_s): from the stop point through the plan's other waypoints. Cached."""
    motion = plan_centre(plan, mission)
    return mission.path if motion is None else motion.path


def plan_tau_s(plan: SwarmPlan, t_s: float, t_go_s: float) -> float:
    """Time on the plan's centre path at mission time t_s (negative: not started; -1 while a
    mission-path plan has no agreed t_go)."""
    return Mission.tau_s(t_s, t_go_s) if plan.follows_mission else t_s - plan.effective_s


def centre_state(plan: SwarmPlan, t_s: float, mission: Mission, t_go_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The formation centre under a plan at mission time t_s: c, c', c'' ((3,) each, NED m,
    m/s, m/s^2). The one definition the source and every agent use (module docstring).

    * no waypoints (seq 0 and plans that keep the mission's path): mission.path at
      Mission.tau_s(t_s, t_go_s) (at waypoint 0 while t_go_s is NaN), bit for bit;
    * else: the plan's CentreMotion (from waypoints_ned_m[0] at start_velocity_ned_mps;
      braking to a stop for a hold).
    """
    motion = plan_centre(plan, mission)
    if motion is None:
        return mission.path.at(Mission.tau_s(t_s, t_go_s))
    return motion.at(t_s)


def centre_ned_m(plan: SwarmPlan, t_s, mission: Mission, t_go_s: float) -> np.ndarray:
    """The centre position at t_s: (3,) for a scalar t_s, (*t.shape, 3) for an array."""
    return _over_t(plan, t_s, mission, t_go_s, 0)


def centre_velocity_ned_mps(plan: SwarmPlan, t_s, mission: Mission, t_go_s: float) -> np.ndarray:
    """The centre velocity at t_s: (3,) for a scalar t_s, (*t.shape, 3) for an array."""
    return _over_t(plan, t_s, mission, t_go_s, 1)


def _over_t(plan: SwarmPlan, t_s, mission: Mission, t_go_s: float, which: int) -> np.ndarray:
    if np.ndim(t_s) == 0:
        return centre_state(plan, float(t_s), mission, t_go_s)[which]
    t = np.asarray(t_s, dtype=float)
    out = np.array([centre_state(plan, float(x), mission, t_go_s)[which] for x in t.ravel()]).reshape(-1, 3)
    return out.reshape(*t.shape, 3)


def centre_arrival_s(plan: SwarmPlan, mission: Mission, t_go_s: float) -> float:
    """Mission time at which the plan's centre comes to rest at the end of its path (a hold:
    at its stop point; NaN: a mission path without t_go). TRANSIT -> HOVER."""
    motion = plan_centre(plan, mission)
    if motion is None:
        return t_go_s + mission.path.duration_s
    return plan.effective_s + motion.duration_s


def _legs(path: CentrePath) -> list[tuple[float, float]]:
    """(move time, dwell) of each leg of a CentrePath, as CentrePath.at times them."""
    out = []
    w = path.waypoints_ned_m
    for k in range(len(w) - 1):
        dist = float(np.linalg.norm(w[k + 1] - w[k]))
        v = min(path.v_max_mps, math.sqrt(dist * path.a_max_mps2))
        t_acc = v / path.a_max_mps2
        t_cruise = (dist - v * t_acc) / v if v > 0 else 0.0
        out.append((2 * t_acc + t_cruise, path.dwell_s))
    return out


def remaining_waypoints(path: CentrePath, tau_s: float) -> tuple[Point, ...]:
    """The path still ahead at tau_s: the centre's point then, and the waypoints not yet
    reached (a waypoint being dwelt at counts as reached). Points equal to the one before
    are dropped (they would add a dwell)."""
    c = path.at(tau_s)[0]
    here = (float(c[0]), float(c[1]), float(c[2]))
    return (here, *_points_after(path, tau_s, here))


def _points_after(path: CentrePath, tau_s: float, here: Point) -> tuple[Point, ...]:
    w = path.waypoints_ned_m
    nxt = len(w)
    if tau_s <= 0:
        nxt = 1
    else:
        t = tau_s
        for k, (move, dwell) in enumerate(_legs(path)):
            if t < move:
                nxt = k + 1
                break
            t -= move + dwell
            if t < 0:  # dwelling at waypoint k + 1
                nxt = k + 2
                break
    out = [here]
    for p in w[nxt:]:
        q = tuple(float(x) for x in p)
        if math.dist(q, out[-1]) > 1e-9:
            out.append(q)  # type: ignore[arg-type]
    return tuple(out[1:])  # type: ignore[return-value]


def waypoints_ahead(plan: SwarmPlan, mission: Mission, t_s: float, t_go_s: float) -> tuple[Point, ...]:
    """The waypoints of a plan's path not yet reached at t_s (by P; for the mission's path,
    by mission.path at tau_s), without the centre's point: what a plan made at t_s that keeps
    the path still has to fly. Empty for a hold or once the path is done."""
    if plan.hold:
        return ()
    path = plan_path(plan, mission)
    tau = plan_tau_s(plan, t_s, t_go_s)
    here = path.at(tau)[0]
    return _points_after(path, tau, (float(here[0]), float(here[1]), float(here[2])))
