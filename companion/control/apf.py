"""Artificial-potential-field collision avoidance, paper eq. 29-31 (pure numpy).

Eq. 29-30 as printed: phi(d) = -(e^{k d} - e^{k}), applied along the unit vector
TOWARD the other body, (x_j - x_i)/|x_j - x_i|. For k > 0 and d < 1, phi > 0, so
the printed law attracts. We implement the evident repulsive intent with an
explicit length scale and amplitude. With dbar = d / influence:

    psi(dbar) = (exp(kappa (1 - dbar)) - 1) / (exp(kappa) - 1)   for dbar < 1, else 0,

psi(0) = 1, psi(1) = 0, continuous, strictly decreasing (any kappa != 0;
kappa -> 0 gives the linear 1 - dbar), and the acceleration points AWAY from the
other body with magnitude gain * psi. So gains (K4, K5) are peak repulsive
accelerations per body in m/s^2. Relation to the printed form with k = -kappa:

    phi(dbar) = e^{-kappa} - e^{-kappa dbar}
              = -e^{-kappa dbar} (1 - e^{-kappa (1 - dbar)})
              = -(1 - e^{-kappa}) psi(dbar),

i.e. the printed phi with a negative exponent times the toward-vector is our
away-push with K4_ours = (1 - e^{-kappa}) K4_paper, and the printed zero at
d = 1 (in unspecified units) becomes d = influence radius. kappa > 0 concentrates
the push near contact; kappa < 0 spreads it out.

Distances are Euclidean in NED metres; accelerations NED m/s^2.
"""
from __future__ import annotations

import math

import numpy as np

from companion.control.kernel import kernel

__all__ = ["psi", "vehicle_repulsion", "obstacle_repulsion", "combined_accel", "TIE_BREAK_DIR_NED"]

TIE_BREAK_DIR_NED = np.array([1.0, 0.0, 0.0])
"""Push direction for coincident bodies (north, horizontal: never into the ground).
Between two vehicles the higher index is pushed +north and the lower -north, so
the pair separates deterministically."""



def psi(dbar: np.ndarray, kappa: float) -> np.ndarray:
    """Normalised repulsion profile: 1 at dbar <= 0, 0 at dbar >= 1, decreasing.

    Evaluated without overflow for any finite kappa (|kappa| up to ~1e300).

    Args:
        dbar: any shape, distance / influence distance (<= 0 counts as contact).
        kappa: shape parameter (k_APF of eq. 29 with flipped sign), finite.

    Returns:
        Same shape as dbar, in [0, 1].

    Raises:
        ValueError: kappa not finite.
    """
    if not np.isfinite(kappa):
        raise ValueError(f"kappa must be finite, got {kappa!r}")
    x = np.clip(np.asarray(dbar, dtype=float), 0.0, 1.0)
    if abs(kappa) < 1e-12:
        out = 1.0 - x
    elif kappa > 0:
        # e^{-k x} (1 - e^{-k (1 - x)}) / (1 - e^{-k}): all exponents <= 0.
        out = np.exp(-kappa * x) * np.expm1(-kappa * (1.0 - x)) / np.expm1(-kappa)
    else:
        out = np.expm1(kappa * (1.0 - x)) / np.expm1(kappa)  # exponents <= 0 already
    return np.where(np.asarray(dbar) >= 1.0, 0.0, out)


def _check_positive(**kw) -> None:
    for name, v in kw.items():
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")


def _points(name: str, a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return a


def repel_cutoff_m(sensing_radius_m: float, influence_radius_m: float, closing_decel_mps2: float) -> float:
    """How far a vehicle looks for bodies to be repelled by, m: the influence distance (never
    beyond the sensing radius), or everything sensed when closing speeds are judged (a body
    closing in from further away may be within the influence distance once braked;
    pair_repulsion_rows)."""
    if closing_decel_mps2 > 0:
        return sensing_radius_m
    return min(sensing_radius_m, influence_radius_m)


def vehicle_repulsion(
    pos_ned_m: np.ndarray,
    others_pos_ned_m: np.ndarray,
    gain_mps2: float,
    influence_radius_m: float,
    sensing_radius_m: float,
    kappa: float,
    self_index: np.ndarray | None = None,
    query_index: np.ndarray | None = None,
    vel_ned_mps: np.ndarray | None = None,
    others_vel_ned_mps: np.ndarray | None = None,
    closing_decel_mps2: float = 0.0,
) -> np.ndarray:
    """Inter-vehicle repulsion, first term of eq. 30 (normalised, repulsive).

        u_i = gain * sum_{j sensed, j != i} psi(|x_i - x_j| / influence) (x_i - x_j) / |x_i - x_j|

    Every body within the sensing radius counts, not just the consensus
    neighbours of eq. 27: with the paper's chain topology vehicle i hears only
    i-1 and would otherwise fly straight through everyone else. Bodies beyond
    min(sensing, influence) contribute nothing; if sensing < influence the field
    is truncated (jumps to zero) at the sensing radius, so keep sensing >=
    influence. Rows of others_pos that are non-finite (unknown) are ignored.

    One code path for a fleet and for one vehicle:
        fleet:       vehicle_repulsion(P, P, ..., self_index=np.arange(N))
        vehicle i:   vehicle_repulsion(P[[i]], P, ..., self_index=[i])
    The second equals row i of the first.

    Coincident bodies (distance < 1e-9 m) are pushed along +-TIE_BREAK_DIR_NED at
    full gain: +north if query_index > j, else -north. query_index defaults to
    self_index (or to +north for every pair when neither is given).

    Cost: O(N M) time (interpreted here; sim_bridge.world.jit compiles the same kernel).

    Args:
        pos_ned_m: (N, 3) query vehicle positions, NED metres.
        others_pos_ned_m: (M, 3) positions of all other bodies, NED metres.
        gain_mps2: K4, peak acceleration from one body at contact, m/s^2, >= 0.
        influence_radius_m: distance at which the push vanishes, > 0.
        sensing_radius_m: bodies further than this are not perceived, > 0.
        kappa: profile shape, see psi.
        self_index: (N,) index in others_pos of each query vehicle itself (that
            entry is skipped), or -1 / None if it is not in others_pos.
        query_index: (N,) global indices of the query vehicles, for the
            coincidence tie-break only; default self_index.
        vel_ned_mps, others_vel_ned_mps: (N, 3) and (M, 3) velocities, m/s (default at
            rest); only closing_decel_mps2 > 0 uses them.
        closing_decel_mps2: judge a closing pair by its distance once braked at this
            deceleration (pair_repulsion_rows), m/s^2, >= 0; 0 (default): eq. 30 as printed.

    Returns:
        (N, 3) repulsive acceleration, NED m/s^2.

    Raises:
        ValueError: bad shapes, non-finite query positions, bad radii or gain.
    """
    p = _points("pos_ned_m", pos_ned_m)
    q = _points("others_pos_ned_m", others_pos_ned_m)
    n, m = p.shape[0], q.shape[0]
    _check_positive(influence_radius_m=influence_radius_m, sensing_radius_m=sensing_radius_m)
    if not (np.isfinite(gain_mps2) and gain_mps2 >= 0):
        raise ValueError(f"gain_mps2 must be finite and >= 0, got {gain_mps2!r}")
    if not np.all(np.isfinite(p)):
        raise ValueError("pos_ned_m has non-finite entries")
    self_idx = np.full(n, -1) if self_index is None else np.broadcast_to(np.asarray(self_index, dtype=int), (n,))
    qidx = self_idx if query_index is None else np.broadcast_to(np.asarray(query_index, dtype=int), (n,))
    decel = float(closing_decel_mps2)
    if not (np.isfinite(decel) and decel >= 0):
        raise ValueError(f"closing_decel_mps2 must be finite and >= 0, got {closing_decel_mps2!r}")
    cutoff = repel_cutoff_m(sensing_radius_m, influence_radius_m, decel)
    vel = np.zeros((n, 3)) if vel_ned_mps is None else np.broadcast_to(np.asarray(vel_ned_mps, float), (n, 3))
    qvel = np.zeros((m, 3)) if others_vel_ned_mps is None else np.broadcast_to(
        np.asarray(others_vel_ned_mps, float), (m, 3))
    if not np.isfinite(kappa):
        raise ValueError(f"kappa must be finite, got {kappa!r}")
    use = np.all(np.isfinite(q), axis=1)[None, :] & (np.arange(m)[None, :] != self_idx[:, None])
    out = np.zeros((n, 3))
    pair_repulsion_rows(p, np.ascontiguousarray(vel), np.broadcast_to(q, (n, m, 3)),
                        np.broadcast_to(qvel, (n, m, 3)), use, qidx.astype(np.int64), float(gain_mps2),
                        float(influence_radius_m), float(cutoff), float(kappa), decel, out)
    return out


@kernel
def _psi_scalar(dbar: float, kappa: float) -> float:
    """psi for one distance; the same formula as psi (kept for the compiled pair loop)."""
    if dbar >= 1.0:
        return 0.0
    x = min(max(dbar, 0.0), 1.0)
    if abs(kappa) < 1e-12:
        return 1.0 - x
    if kappa > 0:
        return math.exp(-kappa * x) * math.expm1(-kappa * (1.0 - x)) / math.expm1(-kappa)
    return math.expm1(kappa * (1.0 - x)) / math.expm1(kappa)


@kernel
def pair_repulsion_rows(p, v, q, qv, use, qidx, gain, infl, cutoff, kappa, decel, out):
    """Vehicle repulsion of eq. 30 added into out (n, 3), each row i with its own view.

    With decel > 0 a pair that closes in is pushed as if it were already as close as it
    will be once braked at decel (docs/formation.md, "Closing speed"): psi is taken at
    d - c^2 / (2 decel) (at least 0), c = -(x_i - x_j).(v_i - v_j) / d the closing speed,
    instead of at d. A pair that keeps its distance or parts (c <= 0) gets eq. 30 as
    printed, so a formation that flies together is pushed exactly as the paper's.

    Args (arrays indexed element by element, so one vehicle interpreted and a fleet
    compiled both stay cheap):
        p: (n, 3) query positions, m; v: (n, 3) their velocities, m/s;
        q: (n, M, 3) other bodies as row i knows them, m; qv: (n, M, 3) their velocities, m/s;
        use: (n, M) bool, body j counts for row i (known, airborne, not itself);
        qidx: (n,) global index of each query vehicle (coincidence tie-break only);
        gain, infl, cutoff, kappa: as vehicle_repulsion (bodies at cutoff or further are
            not perceived); decel: the braking the closing speed is judged by, m/s^2
            (0: eq. 30 alone).
    """
    for i in range(p.shape[0]):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        for j in range(q.shape[1]):
            if not use[i, j]:
                continue
            dx, dy, dz = px - q[i, j, 0], py - q[i, j, 1], pz - q[i, j, 2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not d < cutoff:  # also skips a NaN distance
                continue
            de = d
            if decel > 0.0 and d >= 1e-9:
                close = -(dx * (v[i, 0] - qv[i, j, 0]) + dy * (v[i, 1] - qv[i, j, 1])
                          + dz * (v[i, 2] - qv[i, j, 2])) / d
                if close > 0.0:  # (a NaN velocity compares False: eq. 30 alone)
                    de = max(d - close * close / (2.0 * decel), 0.0)
            if not de < infl:
                continue
            mag = gain * _psi_scalar(de / infl, kappa)
            if d < 1e-9:
                sign = 1.0 if (qidx[i] < 0 or qidx[i] > j) else -1.0
                out[i, 0] += sign * mag * TIE_BREAK_DIR_NED[0]
                out[i, 1] += sign * mag * TIE_BREAK_DIR_NED[1]
                out[i, 2] += sign * mag * TIE_BREAK_DIR_NED[2]
            else:
                out[i, 0] += mag * dx / d
                out[i, 1] += mag * dy / d
                out[i, 2] += mag * dz / d


def obstacle_repulsion(
    pos_ned_m: np.ndarray,
    centres_ned_m: np.ndarray,
    radii_m: np.ndarray,
    gain_mps2: float,
    influence_m: float,
    kappa: float,
) -> np.ndarray:
    """Spherical-obstacle repulsion, second term of eq. 30 (normalised, repulsive).

    Distance is measured to the sphere SURFACE, d = |x - o| - R, so the push is
    the full gain at and inside the surface (d <= 0) and vanishes at d >=
    influence_m. Direction: away from the centre (+north at the exact centre).

    Args:
        pos_ned_m: (N, 3) vehicle positions, NED metres.
        centres_ned_m: (K, 3) sphere centres, NED metres (K may be 0).
        radii_m: (K,) sphere radii, metres, >= 0.
        gain_mps2: K5, peak acceleration from one obstacle, m/s^2, >= 0.
        influence_m: surface distance at which the push vanishes, > 0.
        kappa: profile shape, see psi.

    Returns:
        (N, 3) repulsive acceleration, NED m/s^2.

    Raises:
        ValueError: bad shapes, non-finite inputs, negative radii, bad gain.
    """
    p = _points("pos_ned_m", pos_ned_m)
    o = np.asarray(centres_ned_m, dtype=float).reshape(-1, 3)
    r = np.asarray(radii_m, dtype=float).reshape(-1)
    if r.shape[0] != o.shape[0]:
        raise ValueError(f"radii_m has {r.shape[0]} entries for {o.shape[0]} centres")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(o)) and np.all(np.isfinite(r))):
        raise ValueError("obstacle_repulsion inputs must be finite")
    if np.any(r < 0):
        raise ValueError("obstacle radii must be >= 0")
    _check_positive(influence_m=influence_m)
    if not (np.isfinite(gain_mps2) and gain_mps2 >= 0):
        raise ValueError(f"gain_mps2 must be finite and >= 0, got {gain_mps2!r}")
    if not np.isfinite(kappa):
        raise ValueError(f"kappa must be finite, got {kappa!r}")
    n, k = p.shape[0], o.shape[0]
    out = np.zeros((n, 3))
    ends = np.broadcast_to(o, (n, k, 3))
    segment_repulsion_rows(p, ends, ends, np.broadcast_to(r, (n, k)), np.ones((n, k), dtype=bool), float(gain_mps2),
                           float(influence_m), float(kappa), out)
    return out


@kernel
def segment_repulsion_rows(p, a, b, radius, use, gain, infl, kappa, out):
    """Repulsion from rounded segments (capsules) added into out (n, 3).

    Body k of row i is the set of points within radius[i, k] of the segment from
    a[i, k] to b[i, k]; the distance is measured to its surface, so a sphere is the
    case a == b. The push is gain * psi(surface distance / infl), away from the
    closest point of the segment (+TIE_BREAK_DIR_NED on the segment itself).
    Static obstacles (spheres) and silent vehicles (the column a lost vehicle can
    occupy while its autopilot holds and then lands) both go through here.
    """
    for i in range(p.shape[0]):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        for k in range(a.shape[1]):
            if not use[i, k]:
                continue
            ax, ay, az = a[i, k, 0], a[i, k, 1], a[i, k, 2]
            sx, sy, sz = b[i, k, 0] - ax, b[i, k, 1] - ay, b[i, k, 2] - az
            ss = sx * sx + sy * sy + sz * sz
            f = 0.0
            if ss > 0.0:
                f = min(1.0, max(0.0, ((px - ax) * sx + (py - ay) * sy + (pz - az) * sz) / ss))
            dx, dy, dz = px - (ax + f * sx), py - (ay + f * sy), pz - (az + f * sz)
            dc = math.sqrt(dx * dx + dy * dy + dz * dz)
            mag = gain * _psi_scalar((dc - radius[i, k]) / infl, kappa)
            if not mag > 0.0:
                continue
            if dc < 1e-9:
                ux, uy, uz = TIE_BREAK_DIR_NED[0], TIE_BREAK_DIR_NED[1], TIE_BREAK_DIR_NED[2]
            else:
                ux, uy, uz = dx / dc, dy / dc, dz / dc
            out[i, 0] += mag * ux
            out[i, 1] += mag * uy
            out[i, 2] += mag * uz


@kernel
def clip_sum_rows(u1, u2, u1_max, total_max, out):
    """Row-wise out = clip(clip(u1, u1_max) + u2, total_max) for (N, 3) arrays (eq. 31)."""
    for i in range(u1.shape[0]):
        n1 = math.sqrt(u1[i, 0] ** 2 + u1[i, 1] ** 2 + u1[i, 2] ** 2)
        s1 = min(1.0, u1_max / max(n1, 1e-300))
        for a in range(3):
            out[i, a] = s1 * u1[i, a] + u2[i, a]
        nt = math.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2 + out[i, 2] ** 2)
        st = min(1.0, total_max / max(nt, 1e-300))
        for a in range(3):
            out[i, a] *= st


def combined_accel(
    u1_ned_mps2: np.ndarray,
    u2_ned_mps2: np.ndarray,
    u1_max_mps2: float,
    total_max_mps2: float,
) -> np.ndarray:
    """Eq. 31, u = u1 + u2, with acceleration limits.

    The consensus part u1 is norm-clipped to u1_max first, then the APF part u2
    is added, then the total is norm-clipped to total_max. Clipping u1 first
    bounds how hard the formation can pull: a large slot error (e.g. the
    formation centre on the far side of an obstacle) would otherwise give a u1
    of tens of m/s^2 that swamps the repulsion. With u1 bounded, a vehicle at an
    obstacle surface gets an outward component of at least K5 - u1_max > 0 when
    K5 > u1_max (other vehicles' pushes aside), and norm clipping only rescales
    the vector, so the final total keeps that outward sign. Clipping only the
    sum would not give this guarantee.

    Args:
        u1_ned_mps2: (N, 3) consensus acceleration (eq. 27).
        u2_ned_mps2: (N, 3) repulsion (eq. 30).
        u1_max_mps2: norm limit of u1, > 0 (np.inf allowed).
        total_max_mps2: norm limit of the sum, > 0 (np.inf allowed).

    Returns:
        (N, 3) commanded acceleration, NED m/s^2.

    Raises:
        ValueError: shape mismatch or non-positive limits.
    """
    u1 = np.asarray(u1_ned_mps2, dtype=float)
    u2 = np.asarray(u2_ned_mps2, dtype=float)
    if u1.shape != u2.shape or u1.ndim != 2 or u1.shape[1] != 3:
        raise ValueError(f"u1 and u2 must both be (N, 3), got {u1.shape} and {u2.shape}")
    for name, v in (("u1_max_mps2", u1_max_mps2), ("total_max_mps2", total_max_mps2)):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v!r}")
    out = np.empty_like(u1)
    clip_sum_rows(u1, u2, float(u1_max_mps2), float(total_max_mps2), out)
    return out
