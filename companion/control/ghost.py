"""Where a silent vehicle can be: the capsules of its autopilot's companion-loss behaviour.

When a vehicle's companion falls silent, its autopilot flies on by itself (its
`LossBehaviour`, built by the dialect from its parameters, companion/link/dialects/):
for `timeout_s` the last setpoint keeps acting (the coast), then the autopilot brakes and
holds (HOLD), brakes and lands (LAND), descends with no horizontal control (DESCEND) or
falls (MOTORS_OFF). `ghost_capsules` bounds every position that path can reach from the
vehicle's last heard state, as up to three capsules (segment ends and a radius; a sphere
when the ends meet), in the arrays `companion.avoidance.Avoidance.ghosts` (through `ghost_grid`) and
`companion.control.apf.segment_repulsion_rows` use.

The bounds (all closed form; docs/swarm.md, "Ghosts"), with p, v the last heard position
and velocity, A the bound on the acceleration the agent sends (the last setpoint's
feed-forward can point anywhere, and the swarm state carries no acceleration), r the
vehicle's radius (its size and hold error), and Tc = timeout_s + lag_s:

* **Coast.** The vehicle moves as p + v t + d(t) with |d(t)| <= A t^2 / 2 for t <= Tc:
  the capsule from p to c = p + v Tc of radius r + A Tc^2 / 2 (so v Tc + A Tc^2 / 2 along
  v and A Tc^2 / 2 sideways). Its velocity at the end is u = v + w, |w| <= W = A Tc.
* **Brake,** per axis group (horizontal, vertical: autopilots limit them apart), from a
  speed s, a deceleration of at most a, a jerk of at most j, and an acceleration of up to A
  still acting when braking starts: the deceleration needs t1 = (A + a) / j to build up, and
  the stop that ramps to -a, holds it and ramps back to 0 covers exactly
  D(s) = c0 + c1 s + s^2 / (2 a), c1 = (A + a)^2 / (2 a j) (brake_bound gives c0; 0 for
  A = 0, where D is the S-curve s^2 / (2 a) + s a / (2 j)). A shorter stop exists only for
  speeds too small to reach -a, and D bounds those too (checked against a simulated
  shortest stop in tests/test_ghost.py). PX4 flies to its own predicted stop point,
  s^2 / (2 a) + stop_lead_s s, when that lies further. The
  acceleration's component across the velocity pushes the path aside by at most
  A t1^2 / 2. D(s) in the direction of u is c0 u/|u| + (c1 + s / (2 a)) u: a point on
  c + [0, mu] v (mu = c1 + S / (2 a) at the largest speed S = |v| + W of the group) within
  c0 + A t1^2 / 2 (both groups: their hypot) + max(mu_h, mu_z) W (w is one vector, split
  between the groups) of it. The horizontal and vertical stops end at different times,
  so the path lies in the rectangle spanned by the two; the capsule from c to c + n (n the
  two groups' mu v) covers it with the corner distance |n_h| |n_z| / |n| added.
* **Hold:** the brake capsule's end region (ArduPilot GUIDED: for ever, never landing).
* **Land:** straight down from wherever the brake ends (anywhere on c + [0, 1] n, D being a
  bound): a vertical capsule through the middle of that span, half its horizontal length
  added to the radius, from its highest point down to the ground.
* **Descend** (PX4's fallback without RC): no brake, no horizontal control; the vehicle
  keeps its horizontal speed (at most S_h) for the whole descent at descent_speed_mps,
  plus `drift_m` (tilt and bias drift, measured). **Motors off:** a fall, the same with the
  time to fall.
* **Return, pilot:** no bound near the vehicle (ValueError).

PX4 keeps the last setpoint as it was, position target included, and its position loop
pulls the vehicle back towards that target: inside the coast bound while the target was
where the vehicle was (the agent's state setpoints lead it by one setpoint period); a
target further off adds its distance, which the radius must then cover.

The ghost starts at the last heard state. The companion may have flown formation for a
while after it (states lost on the radio before the loss): `lag_s` adds that time to the
coast with the same acceleration bound A, and lets the coast be trimmed once the vehicle is
certainly past its start (age - lag_s into it): positions it has already left drop out.

Pure numpy, no I/O. Shapes: ``...`` is any batch shape (the agent's (R, N) receiver x
vehicle grid); K = 3 capsules per vehicle: COAST, BRAKE, COLUMN.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # (companion.control stays free of the link layer at run time)
    from companion.link.dialects.base import LossBehaviour

COAST, BRAKE, COLUMN = 0, 1, 2
"""Capsule indices along the K axis."""
N_CAPSULES = 3
GHOST_COLUMN_M = 100.0
"""Depth of a landing or falling column when the ground height is unknown, m (as the agent's)."""
G_MPS2 = 9.80665


@dataclass(frozen=True)
class GhostCapsules:
    """Capsules that contain every position a silent vehicle can reach.

    Capsule k of vehicle i is the set of points within radius_m[i, k] of the segment from
    a_ned_m[i, k] to b_ned_m[i, k]; only capsules with use[i, k] count (a coast already
    left behind, a brake for a vehicle that does not brake, no column for one that holds).
    """

    a_ned_m: np.ndarray
    """(..., K, 3) segment starts, mission NED frame, m."""
    b_ned_m: np.ndarray
    """(..., K, 3) segment ends, m."""
    radius_m: np.ndarray
    """(..., K) radii, m."""
    use: np.ndarray
    """(..., K) bool: the capsule is part of the ghost."""

    def capsule(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Capsule k of every vehicle as contiguous arrays: (a (..., 3), b (..., 3), radius (...),
        use (...)), the arguments of companion.control.apf.segment_repulsion_rows."""
        return (np.ascontiguousarray(self.a_ned_m[..., k, :]), np.ascontiguousarray(self.b_ned_m[..., k, :]),
                np.ascontiguousarray(self.radius_m[..., k]), np.ascontiguousarray(self.use[..., k]))

    def contains(self, x_ned_m: np.ndarray, tol_m: float = 1e-9) -> np.ndarray:
        """Whether points lie inside the ghost (inside any used capsule).

        Args:
            x_ned_m: (..., 3) one point per vehicle, or (..., M, 3) M points per vehicle when
                given with an extra axis (tests sample whole paths so).
        Returns:
            (...) or (..., M) bool.
        """
        x = np.asarray(x_ned_m, float)
        extra = x.ndim == self.a_ned_m.ndim  # (..., M, 3): a points axis before the coordinates
        a, b = self.a_ned_m, self.b_ned_m
        r, use = self.radius_m, self.use
        if extra:
            x = x[..., :, None, :]  # (..., M, 1, 3)
            a, b, r, use = a[..., None, :, :], b[..., None, :, :], r[..., None, :], use[..., None, :]
        else:
            x = x[..., None, :]  # (..., 1, 3)
        return np.any(use & (segment_distance_m(x, a, b) <= r + tol_m), axis=-1)


def segment_distance_m(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points x to segments [a, b] (broadcast (..., 3) arrays), m."""
    s = b - a
    ss = np.einsum("...i,...i->...", s, s)
    f = np.where(ss > 0.0, np.einsum("...i,...i->...", x - a, s) / np.where(ss > 0.0, ss, 1.0), 0.0)
    f = np.clip(f, 0.0, 1.0)
    d = x - (a + f[..., None] * s)
    return np.sqrt(np.einsum("...i,...i->...", d, d))


@dataclass(frozen=True)
class BrakeBound:
    """Stopping distance bound of one axis group: D(s) = c0_m + c1_s s + c2_s2pm s^2 for a
    speed s (m/s), and how far the path can be pushed across the velocity (aside_m)."""

    c0_m: float
    c1_s: float
    c2_s2pm: float
    aside_m: float

    def distance_m(self, speed_mps: np.ndarray | float) -> np.ndarray | float:
        """D(s), m."""
        return self.c0_m + self.c1_s * speed_mps + self.c2_s2pm * speed_mps * speed_mps


def brake_bound(decel_mps2: float, jerk_mps3: float, accel_ff_max_mps2: float, stop_lead_s: float = 0.0) -> BrakeBound:
    """The stopping distance bound of one axis group (module docstring, "Brake").

    Args:
        decel_mps2: the autopilot's braking deceleration limit, > 0.
        jerk_mps3: its jerk limit, > 0 (inf: the deceleration is there at once).
        accel_ff_max_mps2: A, the largest acceleration that may still act when braking starts.
        stop_lead_s: the autopilot flies to its own stop point s^2/(2a) + stop_lead_s s (PX4: 0.6 s).
    Raises:
        ValueError: a deceleration or jerk that is not positive, or a negative A.
    """
    a, j, acc = float(decel_mps2), float(jerk_mps3), float(accel_ff_max_mps2)
    if not (a > 0.0 and j > 0.0 and acc >= 0.0 and math.isfinite(a) and math.isfinite(acc)):
        raise ValueError(f"brake bound: deceleration {a} and jerk {j} must be > 0 and A {acc} >= 0")
    # The stop that starts with +acc and ramps to -a at the jerk limit (t1), holds -a, and
    # ramps back to 0 as the speed reaches 0; its distance is exactly c0 + c1 s + s^2/(2a)
    # with these (an infinite jerk gives the constant-deceleration stop s^2/(2a)).
    t1 = (acc + a) / j
    dv = (acc * acc - a * a) / (2.0 * j)  # speed change while the deceleration builds up
    c1 = (acc + a) ** 2 / (2.0 * a * j)
    c0 = acc * t1 * t1 / 2.0 - j * t1 ** 3 / 6.0 + dv * dv / (2.0 * a) + a ** 3 / (24.0 * j * j) if j < math.inf else 0.0
    return BrakeBound(c0_m=max(c0, 0.0), c1_s=max(c1, float(stop_lead_s)), c2_s2pm=1.0 / (2.0 * a),
                      aside_m=0.5 * acc * t1 * t1)


def _norm(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", x, x))


def ghost_capsules(pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray, age_s: np.ndarray | float,
                   loss: LossBehaviour, accel_ff_max_mps2: float, ground_z_m: float | None, radius_m: float, *,
                   lag_s: float, column_m: float = GHOST_COLUMN_M) -> GhostCapsules:
    """The capsules that contain every position a silent vehicle can reach from now on.

    Args:
        pos_ned_m: (..., 3) last heard position, mission NED frame, m.
        vel_ned_mps: (..., 3) last heard velocity, m/s (NaN rows give NaN capsules: the caller
            masks them, as it does today).
        age_s: (...) or scalar: how old that state is now, s (>= 0).
        loss: what the autopilot does on companion loss (the mission's shared assumption, so
            that every agent draws every ghost alike).
        accel_ff_max_mps2: A, the bound on the acceleration feed-forward the agent sends, m/s^2.
        ground_z_m: the ground's NED z, m (None: unknown; a column then reaches column_m down).
        radius_m: r, the vehicle's size plus its autopilot's hold error, m.
        lag_s: how long after its last heard state the loss may have begun (the vehicle flew
            formation meanwhile, within the same A), s; e.g. the swarm's stale_after_s.
        column_m: column depth when the ground is unknown, m.
    Returns:
        GhostCapsules with K = 3 (COAST, BRAKE, COLUMN).
    Raises:
        ValueError: a behaviour with no bound near the vehicle (it returns home, or a pilot
            flies it), or a negative A, lag or radius.
    """
    from companion.link.dialects.base import AfterLoss  # (the enum only; see TYPE_CHECKING above)

    then = loss.then
    if then not in (AfterLoss.HOLD, AfterLoss.LAND, AfterLoss.DESCEND, AfterLoss.MOTORS_OFF):
        raise ValueError(f"no ghost bounds a vehicle whose autopilot does {then.value!r} on companion loss")
    if not (accel_ff_max_mps2 >= 0.0 and lag_s >= 0.0 and radius_m >= 0.0):
        raise ValueError(f"ghost: A {accel_ff_max_mps2}, lag {lag_s} and radius {radius_m} must be >= 0")
    p = np.asarray(pos_ned_m, float)
    v = np.asarray(vel_ned_mps, float)
    shape = np.broadcast_shapes(p.shape, v.shape)[:-1]
    p, v = np.broadcast_to(p, (*shape, 3)), np.broadcast_to(v, (*shape, 3))
    age = np.broadcast_to(np.asarray(age_s, float), shape)
    acc = float(accel_ff_max_mps2)

    # coast
    tc = float(loss.timeout_s) + float(lag_s)
    t0 = np.clip(age - lag_s, 0.0, tc)  # the vehicle is at least this far into its coast
    r_coast = radius_m + 0.5 * acc * tc * tc
    w = acc * tc  # velocity change over the coast
    c = p + v * tc
    a_caps, b_caps = np.empty((*shape, N_CAPSULES, 3)), np.empty((*shape, N_CAPSULES, 3))
    rad, use = np.empty((*shape, N_CAPSULES)), np.zeros((*shape, N_CAPSULES), bool)
    a_caps[..., COAST, :] = p + v * t0[..., None]
    b_caps[..., COAST, :] = c
    rad[..., COAST] = r_coast
    use[..., COAST] = age - lag_s < tc

    # brake, per axis group
    v_h, v_z = v[..., :2], v[..., 2]
    s_h, s_z = _norm(v_h), np.abs(v_z)
    hor = brake_bound(loss.brake_hor_mps2, loss.jerk_hor_mps3, acc, loss.stop_lead_s)
    ver = brake_bound(loss.brake_ver_mps2, loss.jerk_ver_mps3, acc)
    top_h, top_z = s_h + w, s_z + w  # largest speed of each group at the coast's end
    mu_h, mu_z = hor.c1_s + hor.c2_s2pm * top_h, ver.c1_s + ver.c2_s2pm * top_z
    n = np.concatenate([mu_h[..., None] * v_h, (mu_z * v_z)[..., None]], axis=-1)
    # off the nominal stop: (mu_h w_h, mu_z w_z) with |w| <= W, plus each group's c0 and push aside
    dev = math.hypot(hor.c0_m + hor.aside_m, ver.c0_m + ver.aside_m) + np.maximum(mu_h, mu_z) * w
    n_h, n_z = mu_h * s_h, mu_z * s_z
    n_len = np.hypot(n_h, n_z)
    corner = np.where(n_len > 0.0, n_h * n_z / np.where(n_len > 0.0, n_len, 1.0), 0.0)
    r_stop = r_coast + dev  # around any point a stop can end at

    def bottom_z(top: np.ndarray) -> np.ndarray:
        return np.maximum(top, top + column_m if ground_z_m is None else float(ground_z_m))

    if then in (AfterLoss.HOLD, AfterLoss.LAND):
        a_caps[..., BRAKE, :] = c
        b_caps[..., BRAKE, :] = c + n
        rad[..., BRAKE] = r_stop + corner
        use[..., BRAKE] = True
    else:
        a_caps[..., BRAKE, :] = b_caps[..., BRAKE, :] = c
        rad[..., BRAKE] = 0.0
    if then == AfterLoss.HOLD:
        a_caps[..., COLUMN, :] = b_caps[..., COLUMN, :] = c
        rad[..., COLUMN] = 0.0
        return GhostCapsules(a_caps, b_caps, rad, use)

    if then == AfterLoss.LAND:
        # It lands straight down from wherever it stops: anywhere on c + [0, 1] n (D is a
        # bound, the actual stop can be shorter) within r_stop. A vertical capsule through the
        # middle of that span, half its horizontal length wider, from its highest point down.
        top = c[..., 2] + np.minimum(n[..., 2], 0.0)
        a_caps[..., COLUMN, :2] = b_caps[..., COLUMN, :2] = c[..., :2] + 0.5 * n[..., :2]
        a_caps[..., COLUMN, 2] = top
        b_caps[..., COLUMN, 2] = bottom_z(top)
        rad[..., COLUMN] = r_stop + 0.5 * n_h
        use[..., COLUMN] = True
        return GhostCapsules(a_caps, b_caps, rad, use)

    # DESCEND or MOTORS_OFF: no brake, no horizontal control; it keeps its horizontal speed
    if then == AfterLoss.DESCEND:
        descent = float(loss.descent_speed_mps)
        if not descent > 0.0:
            raise ValueError(f"ghost: a descent needs a descent speed > 0, not {descent}")
        top = c[..., 2] - ver.distance_m(top_z)  # an upward speed is braked first
        depth = bottom_z(top) - top
        t_down = depth / descent + top_z / loss.brake_ver_mps2
    else:  # falls from c, an upward speed first carrying it up
        top = c[..., 2] - top_z * top_z / (2.0 * G_MPS2)
        depth = bottom_z(top) - top
        t_down = (top_z + np.sqrt(top_z * top_z + 2.0 * G_MPS2 * depth)) / G_MPS2
    a_caps[..., COLUMN, :2] = b_caps[..., COLUMN, :2] = c[..., :2]
    a_caps[..., COLUMN, 2] = top
    b_caps[..., COLUMN, 2] = top + depth
    rad[..., COLUMN] = r_coast + top_h * t_down + float(loss.drift_m)
    use[..., COLUMN] = True
    return GhostCapsules(a_caps, b_caps, rad, use)


def coast_overshoot_m(speed_mps: float, timeout_s: float, accel_ff_max_mps2: float) -> float:
    """How far past its last heard position a vehicle can coast along its velocity before its
    autopilot acts on the loss: v T + A T^2 / 2 (docs/agent.md, "Companion loss"), m."""
    return speed_mps * timeout_s + 0.5 * accel_ff_max_mps2 * timeout_s * timeout_s


def ghost_grid(pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray, age_s: np.ndarray, hover: np.ndarray,
               mask: np.ndarray, loss: LossBehaviour, accel_hover_mps2: float, accel_other_mps2: float,
               ground_z_m: float | None, radius_m: float, *, lag_s: float) -> GhostCapsules:
    """The swarm's ghosts on an agent's (R, N) receiver x vehicle grid (Agent's APF): the
    capsules of `ghost_capsules` where mask is set, with A by the phase each silent vehicle
    was last heard in (accel_hover_mps2 for HOVER, accel_other_mps2 otherwise), and no
    capsule in use elsewhere. Only the masked entries are computed (ghosts are rare).

    Args:
        pos_ned_m, vel_ned_mps: (R, N, 3) last heard positions (m) and velocities (m/s);
            a non-finite velocity counts as rest.
        age_s: (R, N) their ages, s. hover: (R, N) bool, last heard in HOVER.
        mask: (R, N) bool, which entries are ghosts.
        loss, ground_z_m, radius_m, lag_s: as ghost_capsules.
    Returns:
        GhostCapsules of shape (R, N, K).
    """
    shape = mask.shape
    a = np.zeros((*shape, N_CAPSULES, 3))
    b = np.zeros((*shape, N_CAPSULES, 3))
    rad = np.zeros((*shape, N_CAPSULES))
    use = np.zeros((*shape, N_CAPSULES), bool)
    idx = np.nonzero(mask)
    if len(idx[0]):
        p, v = pos_ned_m[idx], vel_ned_mps[idx]
        v = np.where(np.isfinite(v), v, 0.0)
        age, hov = age_s[idx], hover[idx]
        for sel, acc in ((hov, accel_hover_mps2), (~hov, accel_other_mps2)):
            if sel.any():
                at = tuple(i[sel] for i in idx)
                g = ghost_capsules(p[sel], v[sel], age[sel], loss, acc, ground_z_m, radius_m, lag_s=lag_s)
                a[at], b[at], rad[at], use[at] = g.a_ned_m, g.b_ned_m, g.radius_m, g.use
    return GhostCapsules(a, b, rad, use)
