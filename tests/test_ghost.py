"""The ghost of a silent vehicle (companion.control.ghost): closed-form capsules per loss
behaviour, and every position a vehicle following that behaviour reaches lies inside."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control.ghost import (
    BRAKE,
    COAST,
    COLUMN,
    G_MPS2,
    GHOST_COLUMN_M,
    brake_bound,
    coast_overshoot_m,
    ghost_capsules,
    ghost_grid,
)
from companion.link.dialects import Mode, dialect_named
from companion.link.dialects.base import AfterLoss, CarryOn, LossBehaviour

R = 1.0  # vehicle radius, m
P = np.array([10.0, -5.0, -20.0])


def _loss(then: AfterLoss, timeout_s: float = 1.0, **kw) -> LossBehaviour:
    kw.setdefault("descent_speed_mps", 0.7 if then in (AfterLoss.LAND, AfterLoss.DESCEND) else 0.0)
    return LossBehaviour(timeout_s=timeout_s, carry_on=CarryOn.VELOCITY_ACCELERATION, then=then, mode=Mode.HOLD, **kw)


# ---------------------------------------------------------------------------- closed form
def test_a_vehicle_at_rest_with_no_feed_forward_is_a_sphere_where_it_is():
    g = ghost_capsules(P, np.zeros(3), 0.0, _loss(AfterLoss.HOLD, brake_hor_mps2=2.5, jerk_hor_mps3=5.0), 0.0,
                       0.0, R, lag_s=0.0)
    assert g.use.tolist() == [True, True, False]
    for k in (COAST, BRAKE):
        np.testing.assert_allclose(g.a_ned_m[k], P)
        np.testing.assert_allclose(g.b_ned_m[k], P)
        assert g.radius_m[k] == pytest.approx(R)


def test_coast_reaches_vT_plus_half_AT2_along_v_and_half_AT2_sideways():
    v, t, acc = np.array([2.0, 0.0, 0.0]), 3.0, 0.5
    g = ghost_capsules(P, v, 0.0, _loss(AfterLoss.HOLD, timeout_s=t), acc, 0.0, R, lag_s=0.0)
    np.testing.assert_allclose(g.a_ned_m[COAST], P)
    np.testing.assert_allclose(g.b_ned_m[COAST], P + v * t)
    assert g.radius_m[COAST] == pytest.approx(R + 0.5 * acc * t * t)
    reach = g.b_ned_m[COAST, 0] - P[0] + g.radius_m[COAST] - R
    assert reach == pytest.approx(coast_overshoot_m(2.0, t, acc)) == pytest.approx(2.0 * 3.0 + 0.5 * 0.5 * 9.0)


def test_lag_lengthens_the_coast_and_age_trims_what_the_vehicle_has_left_behind():
    v, loss = np.array([0.0, 3.0, 0.0]), _loss(AfterLoss.HOLD, timeout_s=1.0)
    young = ghost_capsules(P, v, 0.2, loss, 1.0, 0.0, R, lag_s=0.5)  # the loss may not have begun: all of it
    np.testing.assert_allclose(young.a_ned_m[COAST], P)
    np.testing.assert_allclose(young.b_ned_m[COAST], P + v * 1.5)
    assert young.radius_m[COAST] == pytest.approx(R + 0.5 * 1.5 ** 2)
    mid = ghost_capsules(P, v, 1.0, loss, 1.0, 0.0, R, lag_s=0.5)  # at least 0.5 s into it
    np.testing.assert_allclose(mid.a_ned_m[COAST], P + v * 0.5)
    assert mid.use[COAST]
    old = ghost_capsules(P, v, 2.01, loss, 1.0, 0.0, R, lag_s=0.5)  # past the coast: only where it stops
    assert not old.use[COAST] and old.use[BRAKE]
    np.testing.assert_allclose(old.a_ned_m[BRAKE], P + v * 1.5)


def test_brake_capsule_of_ardupilot_defaults_in_closed_form():
    """ArduPilot GUIDED, GUID_TIMEOUT 3 s, WPNAV_ACCEL 2.5, WPNAV_ACCEL_Z 1, PSC_JERK_XY/Z 5, no
    feed-forward (A = 0): the stop from 1.5 m/s is the S-curve 1.5^2/5 + 1.5 * 2.5/10 along v."""
    v = np.array([1.5, 0.0, 0.0])
    loss = _loss(AfterLoss.HOLD, timeout_s=3.0, brake_hor_mps2=2.5, brake_ver_mps2=1.0, jerk_hor_mps3=5.0,
                 jerk_ver_mps3=5.0)
    g = ghost_capsules(P, v, 0.0, loss, 0.0, None, R, lag_s=0.0)
    stop = 1.5 ** 2 / (2 * 2.5) + 1.5 * 2.5 / (2 * 5.0)
    np.testing.assert_allclose(g.a_ned_m[BRAKE], P + v * 3.0)
    np.testing.assert_allclose(g.b_ned_m[BRAKE], P + v * 3.0 + [stop, 0.0, 0.0])
    assert g.radius_m[BRAKE] == pytest.approx(R)
    assert not g.use[COLUMN]  # it holds in GUIDED for ever: no column to the ground


def test_brake_bound_terms():
    b = brake_bound(3.0, 4.0, 1.0, stop_lead_s=0.6)
    t1 = (1.0 + 3.0) / 4.0
    assert b.c1_s == pytest.approx(max((1.0 + 3.0) ** 2 / (2 * 3.0 * 4.0), 0.6))
    assert b.c2_s2pm == pytest.approx(1 / 6)
    assert b.aside_m == pytest.approx(0.5 * 1.0 * t1 * t1)
    assert brake_bound(3.0, math.inf, 0.0).distance_m(2.0) == pytest.approx(4.0 / 6.0)  # constant deceleration
    assert brake_bound(3.0, 4.0, 0.0, stop_lead_s=0.6).distance_m(1.0) == pytest.approx(1 / 6 + 0.6)  # PX4's stop point
    with pytest.raises(ValueError):
        brake_bound(0.0, 4.0, 1.0)


def _shortest_stop_m(s: float, a0: float, a: float, j: float, dt: float = 2e-4) -> float:
    """A simulated shortest jerk-limited stop from speed s with acceleration a0 along it."""
    x, v, acc = 0.0, s, a0
    while v > 0.0:
        jerk = j if acc < 0.0 and v - acc * acc / (2 * j) <= 0.0 else (-j if acc > -a else 0.0)
        nxt = min(max(acc + jerk * dt, -a), 0.0) if jerk > 0 else max(acc + jerk * dt, -a)
        v_n = v + 0.5 * (acc + nxt) * dt
        x += 0.5 * (v + max(v_n, 0.0)) * dt
        acc, v = nxt, v_n
        if jerk > 0 and acc >= 0.0:
            break
    return x


@pytest.mark.parametrize("a,j,acc", [(2.5, 5.0, 0.0), (2.5, 5.0, 1.0), (3.0, 4.0, 1.0), (1.0, 5.0, 2.0)])
def test_brake_bound_covers_the_shortest_stop_at_every_speed(a, j, acc):
    b = brake_bound(a, j, acc)
    for s in np.linspace(0.0, 5.0, 26):
        assert b.distance_m(s) >= _shortest_stop_m(s, acc, a, j) - 1e-3, s


def test_land_is_a_column_from_the_stop_down_to_the_ground():
    v = np.array([0.0, 2.0, 0.0])
    loss = _loss(AfterLoss.LAND, timeout_s=1.0, brake_hor_mps2=3.0, jerk_hor_mps3=math.inf, brake_ver_mps2=3.0,
                 jerk_ver_mps3=math.inf)
    g = ghost_capsules(P, v, 0.0, loss, 0.0, -2.0, R, lag_s=0.0)
    stop = 4.0 / 6.0
    assert g.use.all()
    np.testing.assert_allclose(g.b_ned_m[BRAKE], P + v + [0.0, stop, 0.0])
    np.testing.assert_allclose(g.a_ned_m[COLUMN], P + v + [0.0, stop / 2, 0.0])  # the middle of the stop span
    np.testing.assert_allclose(g.b_ned_m[COLUMN], [P[0], P[1] + 2.0 + stop / 2, -2.0])
    assert g.radius_m[COLUMN] == pytest.approx(R + stop / 2)
    unknown = ghost_capsules(P, v, 0.0, loss, 0.0, None, R, lag_s=0.0)
    assert unknown.b_ned_m[COLUMN, 2] == pytest.approx(P[2] + GHOST_COLUMN_M)


def test_descent_without_horizontal_control_widens_by_carried_speed_and_drift():
    v, t, acc = np.array([1.0, 0.0, 0.0]), 1.0, 0.5
    loss = _loss(AfterLoss.DESCEND, timeout_s=t, descent_speed_mps=0.7, brake_ver_mps2=3.0, jerk_ver_mps3=math.inf,
                 drift_m=4.0)
    g = ghost_capsules(P, v, 0.0, loss, acc, 0.0, R, lag_s=0.0)
    w = acc * t
    top = P[2]  # no vertical speed, inf jerk, A's vertical part reverses at once: D_v(w) = w^2/6
    top -= w * w / 6.0
    t_down = (0.0 - top) / 0.7 + w / 3.0
    assert not g.use[BRAKE] and g.use[COLUMN]
    np.testing.assert_allclose(g.a_ned_m[COLUMN], [P[0] + 1.0, P[1], top])
    np.testing.assert_allclose(g.b_ned_m[COLUMN], [P[0] + 1.0, P[1], 0.0])
    assert g.radius_m[COLUMN] == pytest.approx(R + 0.5 * acc * t * t + (1.0 + w) * t_down + 4.0)


def test_motors_off_falls_carrying_its_speed():
    v = np.array([0.0, 2.0, 0.0])
    g = ghost_capsules(P, v, 0.0, _loss(AfterLoss.MOTORS_OFF, timeout_s=0.5), 0.0, 0.0, R, lag_s=0.0)
    t_fall = math.sqrt(2 * 20.0 / G_MPS2)
    assert g.radius_m[COLUMN] == pytest.approx(R + 2.0 * t_fall)
    np.testing.assert_allclose(g.a_ned_m[COLUMN], P + v * 0.5)


@pytest.mark.parametrize("then", [AfterLoss.RETURN, AfterLoss.PILOT])
def test_no_ghost_for_a_vehicle_that_flies_home_or_to_a_pilot(then):
    with pytest.raises(ValueError, match=then.value):
        ghost_capsules(P, np.zeros(3), 0.0, _loss(then), 1.0, 0.0, R, lag_s=0.0)


def test_batched_shapes_follow_the_agents_receiver_by_vehicle_grid():
    rng = np.random.default_rng(3)
    pos, vel = rng.normal(size=(2, 5, 3)), rng.normal(size=(2, 5, 3))
    g = ghost_capsules(pos, vel, np.full((2, 5), 0.7), _loss(AfterLoss.LAND), 1.0, 0.0, R, lag_s=0.5)
    assert g.a_ned_m.shape == g.b_ned_m.shape == (2, 5, 3, 3) and g.radius_m.shape == g.use.shape == (2, 5, 3)
    one = ghost_capsules(pos[1, 3], vel[1, 3], 0.7, _loss(AfterLoss.LAND), 1.0, 0.0, R, lag_s=0.5)
    np.testing.assert_allclose(g.a_ned_m[1, 3], one.a_ned_m)
    np.testing.assert_allclose(g.radius_m[1, 3], one.radius_m)
    a, b, r, use = g.capsule(BRAKE)  # what segment_repulsion_rows takes, one capsule at a time
    assert a.shape == b.shape == (2, 5, 3) and r.shape == use.shape == (2, 5) and a.flags.c_contiguous
    np.testing.assert_allclose(b[1, 3], one.b_ned_m[BRAKE])


# ---------------------------------------------------------------------------- containment
def _simulated_path(p, v, a_ff, loss: LossBehaviour, lag_s: float, dt: float = 0.01) -> np.ndarray:
    """A vehicle that flies formation with a constant acceleration a_ff (|a_ff| <= A) for lag_s,
    coasts on it for timeout_s, then stops each axis group along its velocity with the
    shortest jerk-limited stop, holding (or, for LAND, descending at 0.7 m/s to z = 0)."""
    pts = []
    x, u = p.astype(float).copy(), v.astype(float).copy()
    for _ in range(int(round((loss.timeout_s + lag_s) / dt))):
        x = x + u * dt + 0.5 * a_ff * dt * dt
        u = u + a_ff * dt
        pts.append(x.copy())
    for group, (a, j) in (((0, 1), (loss.brake_hor_mps2, loss.jerk_hor_mps3)),
                          ((2,), (loss.brake_ver_mps2, loss.jerk_ver_mps3))):
        g = list(group)
        s = float(np.linalg.norm(u[g]))
        if s == 0.0:
            continue
        along = float(np.dot(a_ff[g], u[g]) / s)
        d = max(_shortest_stop_m(s, max(along, 0.0), a, j), loss.stop_lead_s * s + s * s / (2 * a)
                if len(g) == 2 else 0.0)
        end = x.copy()
        end[g] += d * u[g] / s
        for f in np.linspace(0.0, 1.0, 21):
            y = x.copy()
            y[g] += f * d * u[g] / s
            pts.append(y)
        x = end
    if loss.then == AfterLoss.LAND:
        for z in np.linspace(x[2], 0.0, 21):
            pts.append(np.array([x[0], x[1], z]))
    return np.array(pts)


@pytest.mark.parametrize("dialect,params", [
    ("px4", {"COM_OBL_RC_ACT": 5}), ("px4", {"COM_OBL_RC_ACT": 4}), ("ardupilot", {})])
def test_every_simulated_path_stays_inside_its_ghost(dialect, params):
    """Random last states and feed-forward accelerations (|a| <= A): the whole path, with the
    dialect's stock parameters, lies inside the ghost of the last heard state."""
    loss = dialect_named(dialect).loss_behaviour(params)
    rng = np.random.default_rng(2024)
    acc, lag = 1.0, 0.3
    for _ in range(60):
        p = np.array([0.0, 0.0, -rng.uniform(5.0, 30.0)])
        v = rng.normal(size=3) * np.array([2.0, 2.0, 0.5])
        # the worst directions (along v, against it, across it, up, down) and random ones, at |a| = A
        along = v / np.linalg.norm(v)
        across = np.cross(along, [0.0, 0.0, 1.0])
        a_ff = [along, -along, across / np.linalg.norm(across), np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0]),
                rng.normal(size=3)][rng.integers(6)]
        a_ff = a_ff * acc / np.linalg.norm(a_ff)
        path = _simulated_path(p, v, a_ff, loss, lag)
        g = ghost_capsules(p, v, 0.0, loss, acc, 0.0, R, lag_s=lag)
        inside = g.contains(path, tol_m=1e-6)
        assert inside.all(), (p, v, a_ff, path[~inside][:3])


def test_the_measured_ardupilot_kill_lies_inside_its_ghost():
    """Copter 4.6 SITL, GUID_TIMEOUT 3 s: a vehicle killed at 1.5 m/s with a feed-forward that
    took it to 3.5 m/s (A = 2/3 m/s^2 along v) peaked 11.1 m past its last heard position and
    settled 7.4 m past it (../shared/notes/mavlink-facts.md). The old brake-Hold-Land ghost
    reached 1.5^2 / 6 = 0.4 m past it."""
    loss = dialect_named("ardupilot").loss_behaviour({"GUID_TIMEOUT": 3.0})
    p, v = np.array([0.0, 0.0, -10.0]), np.array([1.5, 0.0, 0.0])
    g = ghost_capsules(p, v, 0.0, loss, 2.0 / 3.0, 0.0, R, lag_s=0.0)
    assert g.contains(p + [[11.1, 0.0, 0.0], [7.4, 0.0, 0.0], [0.0, 0.0, 0.0]]).all()


def test_ghost_grid_is_ghost_capsules_per_silent_entry_with_a_by_phase():
    """The agents' grid (receiver x vehicle): each masked entry is ghost_capsules of its own
    state and age with A by its last phase; unmasked entries have no capsule in use; a
    non-finite velocity counts as rest."""
    rng = np.random.default_rng(7)
    pos, vel = rng.normal(0.0, 10.0, (2, 5, 3)), rng.normal(0.0, 1.5, (2, 5, 3))
    vel[1, 4] = np.nan
    age = rng.uniform(0.5, 3.0, (2, 5))
    hover = rng.random((2, 5)) < 0.5
    mask = np.zeros((2, 5), bool)
    mask[0, [1, 3]] = mask[1, [0, 4]] = True
    loss = _loss(AfterLoss.LAND)
    g = ghost_grid(pos, vel, age, hover, mask, loss, 1.0, 0.4, 0.0, R, lag_s=0.5)
    assert g.radius_m.shape == (2, 5, 3) and not g.use[~mask].any()
    for r, j in zip(*np.nonzero(mask)):
        v = np.nan_to_num(vel[r, j]) if not np.isfinite(vel[r, j]).all() else vel[r, j]
        one = ghost_capsules(pos[r, j], v, age[r, j], loss, 1.0 if hover[r, j] else 0.4, 0.0, R, lag_s=0.5)
        np.testing.assert_array_equal(g.use[r, j], one.use)
        np.testing.assert_allclose(g.radius_m[r, j], one.radius_m, rtol=1e-12)
        np.testing.assert_allclose(g.a_ned_m[r, j], one.a_ned_m, rtol=1e-12)
        np.testing.assert_allclose(g.b_ned_m[r, j], one.b_ned_m, rtol=1e-12)
    empty = ghost_grid(pos, vel, age, hover, np.zeros((2, 5), bool), loss, 1.0, 0.4, 0.0, R, lag_s=0.5)
    assert not empty.use.any()
