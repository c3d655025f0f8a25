"""Slots under a plan: offsets, the synchronised morph between slot tables and its exact
closest approach, the smooth moves of vehicles leaving the formation, and layered landings
(docs/swarm.md, "Slots and formation changes"). Pure: numpy.
"""
from __future__ import annotations

import math

import numpy as np

from companion.commands.plan import LEVEL_TOL_M, MIN_JERK_PEAK_ACCEL, MIN_JERK_PEAK_SPEED, SwarmPlan
from companion.control.shapes import offsets_for


def plan_offsets_ned_m(plan: SwarmPlan) -> np.ndarray:
    """Each vehicle's slot offset from the centre under a plan, (n_vehicles, 3) NED m; NaN
    rows for vehicles without a slot. (The target of the plan's morph.)"""
    slots = np.asarray(plan.slot_of, dtype=np.intp).reshape(-1)
    out = np.full((len(slots), 3), np.nan)
    has = slots >= 0
    if has.any():
        out[has] = offsets_for(plan.formation, int(has.sum()))[slots[has]]
    return out


def morph_fraction(t_s: float, effective_s: float, morph_s: float) -> tuple[float, float, float]:
    """How far the move from old slots to new ones is at t_s: (s, ds/dt, d2s/dt2), s from 0
    at effective_s to 1 at effective_s + morph_s along the minimum-jerk profile
    10u^3 - 15u^4 + 6u^5 (u = (t - effective_s) / morph_s): zero speed and acceleration at
    both ends; peak speed 1.875 / morph_s, peak acceleration 5.77 / morph_s^2 per metre moved.
    morph_s <= 0: a step at effective_s."""
    if not morph_s > 0:
        return (1.0 if t_s >= effective_s else 0.0), 0.0, 0.0
    u = min(max((t_s - effective_s) / morph_s, 0.0), 1.0)
    s = u * u * u * (10.0 + u * (-15.0 + 6.0 * u))
    ds = 30.0 * u * u * (1.0 - u) ** 2 / morph_s
    dds = 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u) / morph_s**2
    return s, ds, dds


def morph_offsets_ned_m(old_ned_m: np.ndarray, new_ned_m: np.ndarray, t_s: float, effective_s: float,
                        morph_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slot offsets during a morph: old + s(t) (new - old), with their velocity and
    acceleration relative to the centre ((n, 3) each). Every vehicle moves along its straight
    line with the same s(t): with slots assigned by companion.control.assignment no two
    vehicles ever come closer than min(old separation, new separation) / sqrt(2), and
    `morph_closest_m` gives the exact closest approach.
    A row whose old offset is NaN (a vehicle that had no slot) takes the new one at once;
    a NaN new row gives NaN."""
    old = np.asarray(old_ned_m, dtype=float)
    new = np.asarray(new_ned_m, dtype=float)
    s, ds, dds = morph_fraction(t_s, effective_s, morph_s)
    start = np.where(np.isnan(old), new, old)
    d = new - start
    return start + s * d, ds * d, dds * d


def morph_closest_m(old_ned_m: np.ndarray, new_ned_m: np.ndarray) -> tuple[float, int, int, float]:
    """The exact closest approach of two vehicles during a synchronised straight-line morph
    (every row i at old_i + s (new_i - old_i), one s for all, from 0 to 1): the minimum over
    pairs and over s of |d_ij(s)|, d_ij(s) = (1 - s) (a_i - a_j) + s (b_i - b_j), a quadratic
    in s per pair. Rows with a NaN are left out. O(n^2) memory (255 vehicles: 0.5 MB).

    Returns:
        (distance m, i, j, s at the closest point); (inf, -1, -1, nan) for fewer than 2 rows.
    """
    a = np.asarray(old_ned_m, dtype=float).reshape(-1, 3)
    b = np.asarray(new_ned_m, dtype=float).reshape(-1, 3)
    rows = np.flatnonzero(np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1))
    if len(rows) < 2:
        return math.inf, -1, -1, math.nan
    a, b = a[rows], b[rows]
    da = a[:, None, :] - a[None, :, :]
    dd = (b[:, None, :] - b[None, :, :]) - da
    qa = np.einsum("ijk,ijk->ij", dd, dd)
    qb = np.einsum("ijk,ijk->ij", da, dd)
    qc = np.einsum("ijk,ijk->ij", da, da)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(qa > 0, np.clip(-qb / np.where(qa > 0, qa, 1.0), 0.0, 1.0), 0.0)
    d2 = np.maximum(qc + s * (2.0 * qb + s * qa), 0.0)
    d2[np.diag_indices(len(rows))] = np.inf
    k = int(np.argmin(d2))
    i, j = divmod(k, len(rows))
    return math.sqrt(float(d2.flat[k])), int(rows[i]), int(rows[j]), float(s.flat[k])


def min_jerk_time_s(distance_m, speed_mps: float, accel_mps2: float):
    """How long a minimum-jerk move over distance_m takes so that its peak speed stays within
    speed_mps and its peak acceleration within accel_mps2, s (0 for no move); a float for a
    float, an array for an array."""
    d = np.abs(np.asarray(distance_m, dtype=float))
    t = np.where(d > 1e-9, np.maximum(MIN_JERK_PEAK_SPEED * d / speed_mps,
                                      np.sqrt(MIN_JERK_PEAK_ACCEL * d / accel_mps2)), 0.0)
    return float(t) if t.ndim == 0 else t


QUINTIC_STOP_ACCEL = 1.5
"""Peak of |p''| T / |v0| of `quintic_move` when it stops over v0 T / 2 (the target half the
coasting distance ahead): the stop takes T = 1.5 |v0| / a at a peak deceleration a."""
START_VELOCITY_PEAK_ACCEL = 3.84
"""Peak of |g''(u)| of the start-velocity basis g(u) = u - 6u^3 + 8u^4 - 3u^5 (at u = 0.2): a
`quintic_move` that starts at v0 across its direction of travel peaks at about 3.84 |v0| / T."""


def quintic_move(p0: np.ndarray, v0: np.ndarray, target: np.ndarray, duration_s: np.ndarray,
                 tau_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth move of K points from (p0, v0, zero acceleration) to rest at target (zero
    velocity and acceleration) over duration_s, evaluated tau_s after it starts: the quintic
    p = p0 + (target - p0) s(u) + v0 T g(u), u = tau / T, s the minimum-jerk profile and
    g(u) = u - 6u^3 + 8u^4 - 3u^5 (g(0) = g(1) = 0, g'(0) = 1; g'(1) = g''(0) = g''(1) = 0).
    Velocity and acceleration are continuous at both ends. With the target v0 T / 2 ahead
    (stopping), the velocity never reverses and the peak deceleration is 1.5 |v0| / T.

    Args: p0, v0, target (K, 3); duration_s (K,) (T <= 0: at the target); tau_s (..., K),
        e.g. (K,) or (S, K) for S times. Before the start (tau < 0): at p0 moving at v0; after
        the end: at the target, at rest.
    Returns: position, velocity, acceleration, (..., K, 3) each.
    """
    p0, v0, target = (np.asarray(x, dtype=float) for x in (p0, v0, target))
    big_t = np.asarray(duration_s, dtype=float)
    tau = np.asarray(tau_s, dtype=float)
    moving = big_t > 0
    safe_t = np.where(moving, big_t, 1.0)
    u = np.where(moving, np.clip(tau / safe_t, 0.0, 1.0), 1.0)[..., None]
    s = u * u * u * (10.0 + u * (-15.0 + 6.0 * u))
    ds = 30.0 * u * u * (1.0 - u) ** 2
    dds = 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u)
    g = u * (1.0 + u * u * (-6.0 + u * (8.0 - 3.0 * u)))
    dg = 1.0 + u * u * (-18.0 + u * (32.0 - 15.0 * u))
    ddg = u * (-36.0 + u * (96.0 - 60.0 * u))
    tt = safe_t[:, None]
    d = target - p0
    pos = p0 + d * s + v0 * tt * g
    vel = (d * ds) / tt + v0 * dg
    acc = (d * dds) / (tt * tt) + v0 * ddg / tt
    before = (tau < 0)[..., None]
    if before.any():
        pos = np.where(before, p0 + v0 * np.minimum(tau, 0.0)[..., None], pos)
        vel = np.where(before, v0, vel)
        acc = np.where(before, 0.0, acc)
    return pos, vel, acc


def landing_layers(z_ned_m: np.ndarray, level_tol_m: float = LEVEL_TOL_M) -> np.ndarray:
    """Layer number of each landing height, 0 = the lowest (largest NED z): heights are taken
    lowest first, and one within level_tol_m of the first height of the current layer joins
    it. NaN heights get -1. Deterministic; independent of the order the heights are listed in.
    """
    z = np.asarray(z_ned_m, dtype=float).reshape(-1)
    out = np.full(len(z), -1, dtype=np.int64)
    ok = np.flatnonzero(np.isfinite(z))
    if not len(ok):
        return out
    order = ok[np.argsort(-z[ok], kind="stable")]
    layer, top = 0, z[order[0]]
    for i in order:
        if top - z[i] > level_tol_m:
            layer, top = layer + 1, z[i]
        out[i] = layer
    return out


def landing_start_offsets_s(points_ned_m: np.ndarray, land_speed_mps: float, separation_m: float, *,
                            level_tol_m: float = LEVEL_TOL_M) -> np.ndarray:
    """When each vehicle starts its descent, s after the landing begins: in layers. Vehicles at
    one height (`landing_layers`) descend together, the lowest first; each layer starts when the
    one below has descended by separation_m (all descend at land_speed_mps), i.e. layer k at
    k separation_m / land_speed_mps. A 40-slot shell (40 layers) takes 39 x 1.43 s = 56 s at
    0.7 m/s and 1 m.

    What keeps the vehicles apart is that no landing column holds another vehicle (the source
    refuses or displaces such a plan: companion.commands.checks); the layers keep every vehicle
    above those below it by at least separation_m while they descend together.

    Args:
        points_ned_m: (n, 3) where each vehicle starts its descent; NaN rows: not landing (NaN out).
        land_speed_mps: descent speed (> 0).
        separation_m: vertical separation between layers (> 0).
    Returns:
        (n,) start offsets, s.
    Raises:
        ValueError: land_speed_mps or separation_m not > 0.
    """
    if not (land_speed_mps > 0 and separation_m > 0):
        raise ValueError(f"land_speed_mps and separation_m must be > 0, got {land_speed_mps}, {separation_m}")
    p = np.asarray(points_ned_m, dtype=float).reshape(-1, 3)
    layer = landing_layers(np.where(np.isfinite(p).all(axis=1), p[:, 2], np.nan), level_tol_m)
    return np.where(layer >= 0, layer * (separation_m / land_speed_mps), np.nan)


def horizontal_closest_m(a_ned_m: np.ndarray, b_ned_m: np.ndarray | None = None) -> tuple[float, int, int]:
    """The closest pair of landing columns: the smallest horizontal distance between a row of a
    and a row of b (b None: two distinct rows of a), and the pair; (inf, -1, -1) if none."""
    a = np.asarray(a_ned_m, dtype=float).reshape(-1, 3)[:, :2]
    same = b_ned_m is None
    bb = a if same else np.asarray(b_ned_m, dtype=float).reshape(-1, 3)[:, :2]
    if not len(a) or not len(bb):
        return math.inf, -1, -1
    d = np.hypot(a[:, None, 0] - bb[None, :, 0], a[:, None, 1] - bb[None, :, 1])
    d = np.where(np.isnan(d), np.inf, d)
    if same:
        d[np.diag_indices(len(a))] = np.inf
    k = int(np.argmin(d))
    i, j = divmod(k, d.shape[1])
    return float(d.flat[k]), i, j
