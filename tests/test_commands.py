"""Swarm commands, the source side (companion/commands/): plan snapshots, the centre function
both sides share (no velocity jumps: HOLD brakes, GOTO turns from the current motion), leads,
slot morphs and what the source refuses (separation, morph, ground and geofence on the path
still to fly). Wire: test_commands_wire.py; references, parking, landing:
test_commands_track.py; the receiver: test_commands_book.py; the schedule:
test_commands_schedule.py."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from companion.commands import (
    DEFAULT_LEAD_S,
    PLAN_WAYPOINTS_MAX,
    URGENT_LEAD_S,
    CommandError,
    CommandSource,
    centre_ned_m,
    centre_state,
    centre_velocity_ned_mps,
    hold_brake_mps2,
    initial_plan,
    morph_closest_m,
    morph_fraction,
    morph_offsets_ned_m,
    plan_centre,
    plan_offsets_ned_m,
    remaining_waypoints,
)
from companion.control.assignment import squared_distances
from companion.control.shapes import FormationSpec, min_separation_m, offsets_for
from companion.mission import FormationConfig, GeofenceConfig, Mission, MissionConfig
from sim_bridge.scenario import load_scenario

WPS = ((100.0, 0.0, -10.0), (300.0, 0.0, -10.0), (300.0, 200.0, -20.0), (100.0, 200.0, -20.0))


def _mission(n: int = 40, **kw) -> Mission:
    kw.setdefault("waypoints_ned_m", WPS)
    return Mission(MissionConfig(n_vehicles=n, **kw))


@pytest.fixture(scope="module")
def mission() -> Mission:
    return _mission()


def _config_mission(name: str) -> Mission:
    return Mission(load_scenario(f"configs/{name}.yaml", runner=None).mission)


def _speeds(plan, mission, ts, t_go):
    return np.linalg.norm(centre_velocity_ned_mps(plan, np.asarray(ts), mission, t_go), axis=-1)


# ----------------------------------------------------------------------------- the plan model
def test_plan_zero_is_the_mission(mission):
    p = initial_plan(mission)
    assert p.seq == 0 and p.kind == "none" and p.follows_mission and p.start_velocity_ned_mps == (0.0, 0.0, 0.0)
    assert p.slot_of == tuple(range(mission.n))
    assert np.array_equal(plan_offsets_ned_m(p), mission.offsets_ned_m)
    for t_go in (math.nan, 30.0):
        for t in (0.0, 29.0, 31.5, 80.0, 1000.0):
            c, v, a = centre_state(p, t, mission, t_go)
            ref = mission.path.at(Mission.tau_s(t, t_go))
            for x, y in zip((c, v, a), ref):
                assert np.array_equal(x, y)


def test_centre_is_vectorised_over_time(mission):
    src = CommandSource(mission)
    plan = src.goto(5.0, [(150.0, 50.0, -12.0), (0.0, 0.0, -15.0)], 3.0)
    t = np.linspace(0, 200, 41).reshape(-1, 41)
    c = centre_ned_m(plan, t, mission, math.nan)
    v = centre_velocity_ned_mps(plan, t, mission, math.nan)
    assert c.shape == (1, 41, 3) and v.shape == (1, 41, 3)
    for k in range(41):
        cs = centre_state(plan, float(t[0, k]), mission, math.nan)
        assert np.array_equal(c[0, k], cs[0]) and np.array_equal(v[0, k], cs[1])


def test_leads_hold_is_urgent_abort_is_at_once_and_seq_increases(mission):
    src = CommandSource(mission)
    p1 = src.hold(10.3)
    assert p1.seq == 1 and p1.effective_s == pytest.approx(10.3 + URGENT_LEAD_S) and URGENT_LEAD_S < DEFAULT_LEAD_S
    p2 = src.resume(10.4)
    assert p2.seq == 2 and p2.effective_s == pytest.approx(10.4 + DEFAULT_LEAD_S)
    p3 = src.hold(10.5)  # never before the plan before it
    assert p3.effective_s == p2.effective_s
    assert [p.seq for p in src.plans] == [0, 1, 2, 3]
    assert src.abort(10.6).effective_s == 10.6
    slow = CommandSource(mission, lead_s=3.0, urgent_lead_s=2.0)
    assert slow.hold(1.0).effective_s == 3.0 and slow.goto(1.0, [(0.0, 0.0, -10.0)]).effective_s == 4.0
    with pytest.raises(CommandError, match="time order"):
        slow.hold(0.5)


# ----------------------------------------------------------------------------- the centre: no velocity jumps
def test_hold_brakes_to_a_stop_at_the_hold_deceleration(mission):
    """The centre was flying 4 m/s: HOLD keeps its position and velocity at the effective
    time, then decelerates at exactly hold_brake_mps2 along its velocity and rests at
    p0 + v0 |v0| / (2 a), |v0| / a later (before: the velocity stepped to 0)."""
    src = CommandSource(mission)
    src.set_t_go(50.0)
    before = src.plan
    p = src.hold(80.0)
    e = p.effective_s
    c0, v0, _ = centre_state(before, e, mission, 50.0)
    assert np.linalg.norm(v0) == pytest.approx(4.0)
    np.testing.assert_allclose(p.waypoints_ned_m[0], c0, atol=1e-4)  # (float32 on the wire)
    np.testing.assert_allclose(p.start_velocity_ned_mps, v0, atol=1e-6)
    a = hold_brake_mps2(mission)
    assert a == pytest.approx(0.8 * mission.cfg.consensus_accel_max_mps2)
    c, v, acc = centre_state(p, e + 1e-9, mission, 50.0)
    np.testing.assert_allclose(v, v0, atol=1e-5)
    brake_s = 4.0 / a
    for t in np.linspace(e + 0.01, e + brake_s - 0.01, 9):
        c, v, acc = centre_state(p, t, mission, 50.0)
        np.testing.assert_allclose(acc, -a * v0 / 4.0, atol=1e-6)  # constant deceleration along v0
        assert np.linalg.norm(v) == pytest.approx(4.0 - a * (t - e), abs=1e-5)
    stop = np.asarray(p.waypoints_ned_m[0]) + np.asarray(p.start_velocity_ned_mps) * 4.0 / (2 * a)
    for t in (e + brake_s + 1e-6, e + 100.0):
        c, v, acc = centre_state(p, t, mission, 50.0)
        np.testing.assert_allclose(c, stop, atol=1e-6)
        assert not np.abs(v).max() > 1e-9 and not np.abs(acc).max() > 1e-9
    assert plan_centre(p, mission).duration_s == pytest.approx(brake_s)
    assert np.array_equal(plan_offsets_ned_m(p), mission.offsets_ned_m) and p.morph_s == 0.0  # the formation is kept


def test_hold_stops_small_6_within_two_seconds_of_the_press():
    """The operator's test (small_6 in transit at 3 m/s): the reference centre is below
    0.1 m/s 0.3 s + 3 / 2.4 s = 1.55 s after HOLD is pressed, leaving the vehicles 0.45 s."""
    m = _config_mission("small_6")
    src = CommandSource(m)
    src.set_t_go(30.0)
    press = 30.0 + 3.0 / m.cfg.transit_accel_mps2 + 2.0  # cruising
    assert _speeds(src.plan, m, [press], 30.0)[0] == pytest.approx(3.0)
    p = src.hold(press)
    ts = press + np.linspace(0.0, 2.0, 201)
    speed = _speeds(p, m, ts, 30.0)
    below = ts[np.argmax(speed < 0.1)]
    assert below - press <= 1.6 and np.all(speed[ts >= below] < 0.1)
    assert np.all(np.diff(speed) <= 1e-9)  # braking only


def _velocity_jump(before, after, e, mission, t_go):
    v_b = centre_state(before, e, mission, t_go)[1]
    v_a = centre_state(after, e + 1e-9, mission, t_go)[1]
    return float(np.linalg.norm(v_a - v_b))


@pytest.mark.parametrize("command", ["formation", "exclude", "land", "abort", "goto", "rtl", "hold"])
def test_no_command_makes_the_centre_velocity_jump_on_a_commanded_path(mission, command):
    """While a GOTO path is flown at 3 m/s, every command starts from the centre's velocity
    (float32 on the wire: < 1e-6 m/s), and its acceleration stays within the blend's bound.
    (Before: a 2.1 m/s step to rest.)"""
    src = CommandSource(mission)
    src.set_t_go(20.0)
    g = src.goto(30.0, [(150.0, 150.0, -30.0)], 3.0)
    t = g.effective_s + 25.0  # cruising
    make = {"formation": lambda: src.formation(t, FormationSpec("circle", radius_m=45.0)),
            "exclude": lambda: src.exclude(t, [3]), "land": lambda: src.land(t, [5]), "abort": lambda: src.abort(t),
            "goto": lambda: src.goto(t, [(0.0, 300.0, -30.0)], 2.0), "rtl": lambda: src.rtl(t),
            "hold": lambda: src.hold(t)}[command]
    p = make()
    assert np.linalg.norm(centre_state(g, p.effective_s, mission, 20.0)[1]) == pytest.approx(3.0)
    assert _velocity_jump(g, p, p.effective_s, mission, 20.0) < 1e-5
    a_max = mission.cfg.transit_accel_mps2 + (hold_brake_mps2(mission) if p.hold else mission.cfg.transit_accel_mps2)
    for tt in np.linspace(p.effective_s, p.effective_s + 120.0, 241):
        assert np.linalg.norm(centre_state(p, tt, mission, 20.0)[2]) <= a_max + 1e-9


def test_a_command_that_keeps_the_path_keeps_the_motion(mission):
    """FORMATION during a cruise keeps the centre's motion: the lag and the new path's
    acceleration cancel (both at transit_accel), so the speed stays 3 m/s and the centre
    arrives where and when the GOTO would have (to float32)."""
    src = CommandSource(mission)
    g = src.goto(1.0, [(100.0, 150.0, -10.0)], 3.0)
    f = src.formation(g.effective_s + 20.0, FormationSpec("circle", radius_m=45.0))
    ts = np.linspace(f.effective_s, f.effective_s + 60.0, 121)
    np.testing.assert_allclose(centre_ned_m(f, ts, mission, math.nan), centre_ned_m(g, ts, mission, math.nan), atol=2e-3)
    np.testing.assert_allclose(centre_velocity_ned_mps(f, ts, mission, math.nan),
                               centre_velocity_ned_mps(g, ts, mission, math.nan), atol=1e-4)


def test_goto_turns_from_the_current_motion(mission):
    """A GOTO back the way the centre came: it keeps its velocity at the effective time, then
    turns within transit_accel (blend) + transit_accel (path), and comes to rest at the target."""
    src = CommandSource(mission)
    src.set_t_go(20.0)
    before = src.plan
    e_cmd = 60.0
    p = src.goto(e_cmd, [(0.0, 0.0, -12.0), (10.0, 10.0, -12.0)], speed_mps=2.0)
    e = p.effective_s
    c0, v0, _ = centre_state(before, e, mission, 20.0)
    np.testing.assert_allclose(p.waypoints_ned_m[0], c0, atol=1e-4)
    assert p.waypoints_ned_m[1:] == ((0.0, 0.0, -12.0), (10.0, 10.0, -12.0)) and p.speed_mps == 2.0
    assert not p.hold and not p.land_at_end and p.kind == "goto"
    assert _velocity_jump(before, p, e, mission, 20.0) < 1e-5
    end = e + plan_centre(p, mission).duration_s
    np.testing.assert_allclose(centre_ned_m(p, end + 1.0, mission, 20.0), (10.0, 10.0, -12.0), atol=1e-9)
    with pytest.raises(CommandError):
        src.goto(61.0, [])
    with pytest.raises(CommandError):
        src.goto(61.0, [(0.0, 0.0, -10.0)] * PLAN_WAYPOINTS_MAX)
    with pytest.raises(CommandError):
        src.goto(61.0, [(0.0, math.nan, -10.0)])
    with pytest.raises(CommandError):
        src.goto(61.0, [(0.0, 0.0, -10.0)], speed_mps=0.0)
    with pytest.raises(CommandError, match="below the ground"):
        src.goto(61.0, [(0.0, 0.0, 5.0)])
    assert src.plan is p  # refused commands change nothing


def test_resume_flies_the_rest_of_the_held_path(mission):
    src = CommandSource(mission)
    src.set_t_go(50.0)
    tau_hold = 80.3 - 50.0  # on the first leg (200 m at 4 m/s)
    held = src.hold(80.0)
    stop = plan_centre(held, mission).stop_ned_m
    p = src.resume(200.0)
    assert not p.hold and p.speed_mps == mission.cfg.transit_speed_mps
    np.testing.assert_allclose(p.waypoints_ned_m[0], stop, atol=1e-4)  # from where the held centre rests
    assert p.waypoints_ned_m[1:] == WPS[1:]  # the rest: what the first leg was heading to, and on
    assert remaining_waypoints(mission.path, tau_hold)[1:] == WPS[1:]
    np.testing.assert_allclose(centre_ned_m(p, 201.0 + 500.0, mission, 50.0), WPS[-1], atol=1e-4)
    with pytest.raises(CommandError, match="not held"):
        src.resume(210.0)


def test_resume_of_a_hold_on_the_second_leg_skips_what_was_flown(mission):
    src = CommandSource(mission)
    src.set_t_go(0.0)
    leg1 = 200 / 4.0 + 4.0 / 0.5  # trapezoid: distance / v + v / a
    src.hold(leg1 + 10.0)
    p = src.resume(leg1 + 20.0)
    assert p.waypoints_ned_m[1:] == WPS[2:]


def test_resume_before_the_transit_started(mission):
    """Held during assembly: RESUME gives back the mission's own plan (the agreed t_go then
    starts the transit), unless the agreed start passed during the hold."""
    src = CommandSource(mission)
    src.hold(10.0)
    p = src.resume(20.0)
    assert p.follows_mission
    src.hold(30.0)
    src.set_t_go(40.0)
    p = src.resume(60.0)
    assert not p.follows_mission and p.waypoints_ned_m == WPS  # from waypoint 0, now
    later = CommandSource(mission)
    later.hold(10.0)
    later.set_t_go(100.0)  # agreed, but still ahead when the resume applies
    assert later.resume(20.0).follows_mission


def test_abort_is_final(mission):
    src = CommandSource(mission)
    src.hold(2.0)
    p = src.abort(2.5)
    assert p.abort and p.kind == "abort" and p.effective_s == 2.5  # no lead: at once
    with pytest.raises(CommandError, match="aborted"):
        src.hold(4.0)


# ----------------------------------------------------------------------------- slots and morphs
def test_formation_is_an_optimal_assignment_with_a_documented_morph_time(mission):
    src = CommandSource(mission)
    spec = FormationSpec("grid", spacing_m=6.0, rotation_rad=0.3)
    p = src.formation(10.0, spec)
    old, new = mission.offsets_ned_m, offsets_for(spec, mission.n)
    c = squared_distances(old, new)
    r, s = linear_sum_assignment(c)
    take = np.array(p.slot_of)
    assert sorted(take) == list(range(mission.n))
    assert float(c[np.arange(mission.n), take].sum()) == pytest.approx(float(c[r, s].sum()))
    moves = np.linalg.norm(new[take] - old, axis=1)
    assert p.morph_s == pytest.approx(src.morph_time_s(moves.max()), rel=1e-6)
    # the peak slot speed and acceleration stay within the morph speed and the mission's acceleration
    ts = np.linspace(p.effective_s, p.effective_s + p.morph_s, 2001)
    speeds = [np.linalg.norm(morph_offsets_ned_m(old, new[take], t, p.effective_s, p.morph_s)[1], axis=1).max() for t in ts]
    accels = [np.linalg.norm(morph_offsets_ned_m(old, new[take], t, p.effective_s, p.morph_s)[2], axis=1).max() for t in ts]
    assert max(speeds) <= src.morph_speed_mps * (1 + 1e-6)
    assert max(accels) <= mission.cfg.transit_accel_mps2 * (1 + 1e-6)
    assert p.formation == dataclasses.replace(spec, rotation_rad=float(np.float32(0.3)))


def test_a_circle_command_keeps_the_mission_slot_order(mission):
    src = CommandSource(mission)
    p = src.formation(1.0, FormationSpec("circle", radius_m=30.0))
    assert p.formation.slot_order == mission.cfg.formation.slot_order == "interleaved"
    seq = CommandSource(_mission(formation=FormationConfig(slot_order="sequential")))
    assert seq.formation(1.0, FormationSpec("circle", radius_m=30.0, slot_order="interleaved")).formation.slot_order \
        == "sequential"


def test_morph_profile():
    assert morph_fraction(5.0, 10.0, 4.0) == (0.0, 0.0, 0.0)
    assert morph_fraction(20.0, 10.0, 4.0) == (1.0, 0.0, 0.0)
    assert morph_fraction(12.0, 10.0, 4.0)[0] == pytest.approx(0.5)
    assert morph_fraction(12.0, 10.0, 4.0)[1] == pytest.approx(1.875 / 4.0)  # peak speed, mid-way
    assert morph_fraction(9.9, 10.0, 0.0)[0] == 0.0 and morph_fraction(10.0, 10.0, 0.0)[0] == 1.0
    old = np.array([[0.0, 0.0, 0.0], [np.nan] * 3, [1.0, 1.0, 1.0]])
    new = np.array([[2.0, 0.0, 0.0], [5.0, 5.0, 5.0], [np.nan] * 3])
    pos, vel, _ = morph_offsets_ned_m(old, new, 12.0, 10.0, 4.0)
    np.testing.assert_allclose(pos[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(pos[1], new[1])  # no old slot: the new one at once
    assert not vel[1].any() and np.isnan(pos[2]).all()


def test_a_command_during_a_morph_lets_it_go_on_unchanged(mission):
    """HOLD during a formation change: the slots' morph goes on exactly as planned (no jump
    of the slots' velocity), and a vehicle that missed the FORMATION plan is told how long
    is left of it."""
    src = CommandSource(mission)
    p1 = src.formation(0.0, FormationSpec("line", spacing_m=5.0))
    track1 = src.track
    p2 = src.hold(10.0)
    assert p2.slot_of == p1.slot_of
    assert p2.effective_s + p2.morph_s == pytest.approx(p1.effective_s + p1.morph_s, abs=1e-4)
    for t in np.linspace(p2.effective_s, p1.effective_s + p1.morph_s + 5.0, 50):
        _, v1, _ = track1.at(t, mission, math.nan)
        _, v2, _ = src.track.at(t, mission, math.nan)
        c1 = centre_state(p1, t, mission, math.nan)[1]
        c2 = centre_state(p2, t, mission, math.nan)[1]
        np.testing.assert_allclose(v2 - c2, v1 - c1, atol=1e-9)  # the slots' own motion, relative to the centre


def test_exact_closest_approach_of_a_morph():
    a = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [np.nan] * 3])
    b = np.array([[4.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]])
    d, i, j, s = morph_closest_m(a, b)  # |d(s)|^2 = (8 s - 4)^2 + (2 s)^2: least at s = 8/17
    assert (i, j) == (0, 1) and s == pytest.approx(8 / 17) and d == pytest.approx(math.sqrt(16 / 17))
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(12, 3)) * 5, rng.normal(size=(12, 3)) * 5
    s = np.linspace(0, 1, 20001)[:, None, None, None]
    x = a * (1 - s) + b * s  # (S, 1, 12, 3)
    d = np.linalg.norm(x[:, 0, :, None, :] - x[:, 0, None, :, :], axis=-1)
    d[:, np.arange(12), np.arange(12)] = np.inf
    brute = float(d.min())
    assert morph_closest_m(a, b)[0] == pytest.approx(brute, abs=1e-4)


# ----------------------------------------------------------------------------- what the source refuses
def test_a_shape_closer_than_the_separation_is_refused(mission):
    src = CommandSource(mission, separation_m=1.0)
    with pytest.raises(CommandError, match=r"grid of 40 with spacing_m 0.5 puts slots 0.5 m apart"):
        src.formation(10.0, FormationSpec("grid", spacing_m=0.5))
    with pytest.raises(CommandError, match="separation"):
        CommandSource(mission, separation_m=2.5).formation(10.0, FormationSpec("wedge", spacing_m=2.0))
    assert src.plan.seq == 0


def test_a_morph_that_brings_two_vehicles_under_the_separation_is_refused(mission):
    """circle (40 m) -> grid of spacing 1.0: every slot is 1.0 m from its neighbours, yet two
    vehicles pass 0.988 m apart on the way: refused, naming them. Spacing 2.0 passes, and
    its exact closest approach is then at least the separation."""
    src = CommandSource(mission)
    with pytest.raises(CommandError, match=r"UAV \d+ and UAV \d+ would pass 0.98\d m apart"):
        src.formation(10.0, FormationSpec("grid", spacing_m=1.0))
    p = src.formation(10.0, FormationSpec("grid", spacing_m=2.0))
    d, *_ = morph_closest_m(mission.offsets_ned_m, plan_offsets_ned_m(p))
    assert d >= 1.0 and min_separation_m(offsets_for(p.formation, 40)) == pytest.approx(2.0)
    # the assignment's bound: never under min(old gap, new gap) / sqrt(2)
    assert d >= min(min_separation_m(mission.offsets_ned_m), 2.0) / math.sqrt(2)


def test_ground_is_checked_only_on_the_path_still_to_fly():
    """paper_40's path: assembly 10 m up, final hover 170 m up. A 15 m shell at the final
    hover is flown; the same at the assembly point is refused (before: refused at both, as
    the assembly point was checked although flown already)."""
    m = _config_mission("paper_40")
    shell = FormationSpec("shell", radius_m=15.0)
    src = CommandSource(m)
    src.set_t_go(65.0)
    end = 65.0 + m.path.duration_s
    p = src.formation(end + 10.0, shell)
    assert p.formation.shape == "shell"
    early = CommandSource(m)
    with pytest.raises(CommandError, match="below the ground"):
        early.formation(10.0, shell)  # the whole path is still ahead: the assembly point is 10 m up
    mid = CommandSource(m)
    mid.set_t_go(65.0)
    with pytest.raises(CommandError, match="below the ground"):
        mid.formation(70.0, shell)  # still 12 m up when the morph runs


def test_a_formation_outside_the_geofence_is_refused():
    fence = GeofenceConfig(min_ned_m=(-10.0, -60.0, -100.0), max_ned_m=(400.0, 260.0, 0.0))
    m = _mission(geofence=fence)
    src = CommandSource(m)
    src.formation(1.0, FormationSpec("circle", radius_m=50.0))
    with pytest.raises(CommandError, match="geofence"):
        src.formation(2.0, FormationSpec("line", spacing_m=5.0, rotation_rad=0.0))  # 195 m wide: east 97.5 m


def test_a_formation_into_the_ground_is_refused(mission):
    src = CommandSource(mission)
    with pytest.raises(CommandError, match="below the ground"):
        src.formation(1.0, FormationSpec("shell", radius_m=12.0))  # centre at 10 m, shell of 12 m
    assert src.plan.seq == 0
