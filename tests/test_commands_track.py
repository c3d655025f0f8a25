"""The reference every vehicle flies under a plan (companion/commands/track.py): bit for bit
the agent's own under the mission's plan; excluded vehicles park above the formation; landings
in layers, never onto a vehicle that stays; the consensus graph over the vehicles left."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.commands import (
    LAND,
    PARK,
    SLOT,
    CommandError,
    CommandSource,
    centre_state,
    enter,
    hold_brake_mps2,
    initial_plan,
    initial_track,
    landing_start_offsets_s,
    plan_offsets_ned_m,
)
from companion.commands.slots import horizontal_closest_m, quintic_move
from companion.commands.track import clear_m, consensus_graph
from companion.control import topology
from companion.control.shapes import FormationSpec, offsets_for
from companion.mission import FormationConfig, Mission, MissionConfig, TopologyConfig
from sim_bridge.scenario import load_scenario

T_GO = 65.0


@pytest.fixture(scope="module")
def paper() -> Mission:
    return Mission(load_scenario("configs/paper_40.yaml", runner=None).mission)


def _hover_s(m: Mission) -> float:
    return T_GO + m.path.duration_s


def _min_pair(track, m: Mission, t0: float, t1: float, dt: float = 0.1, t_go: float = T_GO):
    """Smallest distance between any two vehicles' references over [t0, t1], and when."""
    ts = np.arange(t0, t1, dt)
    pos = track.positions(ts, m, t_go)
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    d[:, np.arange(m.n), np.arange(m.n)] = np.inf
    k = int(np.argmin(d))
    s, i, j = np.unravel_index(k, d.shape)
    return float(d[s, i, j]), float(ts[s]), int(i), int(j)


def _fly(plans, m: Mission, t_go: float = T_GO):
    """The track chain of a vehicle that hears every plan on time."""
    tr = initial_track(initial_plan(m), m)
    for p in plans:
        tr = enter(p, tr, m, t_go)
    return tr


# ----------------------------------------------------------------------------- the mission's own plan
def test_reference_under_the_mission_plan_is_the_agents_bit_for_bit(paper):
    """companion.agent.Agent._consensus builds h_pos = m.offsets_ned_m + c, h_vel = c',
    h_acc = c'' from c = m.path.at(m.tau_s(t, t_go)) and flies m.weights / m.neighbours: the
    track of plan 0 gives the very same bits and arrays (the headless paper_40 result cannot
    move while no command is given)."""
    m = paper
    tr = initial_track(initial_plan(m), m)
    assert tr.weights is m.weights and tr.neighbours is m.neighbours and tr.consensus.all()
    assert (tr.role == SLOT).all() and np.isnan(tr.land_start_s).all()
    h_pos, h_vel, h_acc = (np.empty((m.n, 3)) for _ in range(3))
    for t_go in (math.nan, T_GO):
        for t in np.linspace(0.0, 400.0, 801).tolist():
            c_pos, c_vel, c_acc = m.path.at(m.tau_s(t, t_go))
            h_pos[:], h_vel[:], h_acc[:] = m.offsets_ned_m + c_pos, c_vel, c_acc
            pos, vel, acc = tr.at(t, m, t_go)
            assert pos.tobytes() == h_pos.tobytes() and vel.tobytes() == h_vel.tobytes() \
                and acc.tobytes() == h_acc.tobytes(), t
        assert tr.centre_end_s(m, t_go) == t_go + m.path.duration_s or math.isnan(t_go)


# ----------------------------------------------------------------------------- parking
def test_exclude_parks_the_vehicle_above_the_formation(paper):
    """EXCLUDE (hold) of one vehicle of the 40-circle in the final hover: the 39-circle puts a
    slot exactly where the excluded vehicle was (before: it held there, 0.000 m from that
    slot). It now climbs clear_m above the formation first, smoothly from its state, and no
    two vehicles are ever closer than the separation."""
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    x = src.exclude(_hover_s(m) + 10.0, [5])
    tr = src.track
    assert tr.role[5] == PARK and not tr.consensus[5] and tr.consensus.sum() == 39
    new = plan_offsets_ned_m(x)
    hold = m.offsets_ned_m[5]
    assert np.min(np.linalg.norm(new[~np.isnan(new[:, 0])] - hold, axis=1)) < 1e-6  # the old hazard is real
    e = x.effective_s
    top = centre_state(x, e, m, T_GO)[0][2]  # a planar formation: every slot at the centre's height
    assert tr.mv_target_ned_m[5, 2] == pytest.approx(top - clear_m(m))
    p0, v0, _ = _fly(src.plans[1:-1], m).at(e, m, T_GO)
    p1, v1, _ = tr.at(e, m, T_GO)
    np.testing.assert_allclose(p1[5], p0[5], atol=1e-9)
    np.testing.assert_allclose(v1[5], v0[5], atol=1e-9)
    end = e + float(tr.mv_duration_s[5])
    p_end, v_end, _ = tr.at(end + 1.0, m, T_GO)
    assert not np.abs(v_end[5]).max() > 1e-12 and p_end[5][2] == pytest.approx(top - clear_m(m))
    d, *_ = _min_pair(tr, m, e, e + x.morph_s + 10.0)
    assert d >= 1.0


def test_exclude_in_transit_keeps_pace_while_it_climbs(paper):
    """EXCLUDE while the formation cruises at 3 m/s: the vehicle climbs while keeping about
    the formation's pace (the quintic stop ends half its coasting distance ahead), then
    stops; no pair ever under the separation."""
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    x = src.exclude(T_GO + 40.0, [12])
    tr = src.track
    e = x.effective_s
    assert np.linalg.norm(centre_state(x, e, m, T_GO)[1]) == pytest.approx(3.0)
    stop = float(tr.mv_duration_s[12])
    assert stop >= 1.5 * 3.0 / hold_brake_mps2(m)
    d, *_ = _min_pair(tr, m, e, e + stop + 30.0, dt=0.05)
    assert d >= 1.0


def test_exclude_on_a_climbing_leg_parks_below(paper):
    """paper_40's first leg climbs at 0.85 m/s: a vehicle parked above would soon be in the
    rising formation's way (the source refused it). It parks clear_m below the formation's
    bottom instead, and the formation climbs away: no pair under the separation until the
    hover."""
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    x = src.exclude(100.0, [5])
    tr = src.track
    c = centre_state(x, x.effective_s, m, T_GO)
    assert c[1][2] < -0.8 and tr.mv_target_ned_m[5, 2] == pytest.approx(c[0][2] + clear_m(m))
    d, *_ = _min_pair(tr, m, x.effective_s, _hover_s(m), dt=0.1)
    assert d >= 1.0


def test_quintic_move_from_a_velocity_to_rest():
    p0, v0 = np.array([[0.0, 0.0, -10.0]]), np.array([[4.0, 0.0, -1.0]])
    T = np.array([5.0])
    target = np.array([[4.0 * 5.0 / 2.0, 0.0, -14.0]])
    ts = np.linspace(0.0, 5.0, 501)
    p, v, a = quintic_move(p0, v0, target, T, ts[:, None])
    np.testing.assert_allclose(p[0, 0], p0[0]) and np.testing.assert_allclose(v[0, 0], v0[0])
    np.testing.assert_allclose(a[0, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(p[-1, 0], target[0]) and np.testing.assert_allclose(v[-1, 0], 0.0, atol=1e-12)
    assert np.all(v[:, 0, 0] >= -1e-12)  # stopping over v0 T / 2: never backwards
    assert np.abs(a[:, 0, 0]).max() == pytest.approx(1.5 * 4.0 / 5.0, rel=1e-3)
    vn = np.gradient(p[:, 0], ts, axis=0)
    np.testing.assert_allclose(vn[1:-1], v[1:-1, 0], atol=2e-3)


# ----------------------------------------------------------------------------- landing
def _shell_mission(n: int = 12, radius: float = 6.0) -> Mission:
    return Mission(MissionConfig(n_vehicles=n, formation=FormationConfig(shape="shell", radius_m=radius),
                                 waypoints_ned_m=((0.0, 0.0, -20.0),)))


def test_land_of_a_subset_never_descends_onto_a_vehicle_that_stays():
    """In a 40-slot shell of 8 m two slots are 0.73 m apart horizontally, one above the other:
    LAND of the upper one alone is refused, naming the one below (before: it went straight
    down onto it); the lower one lands (nothing below it), and while it does no pair comes
    under the separation."""
    m = _shell_mission(40, 8.0)
    offs = m.offsets_ned_m
    d, i, j = horizontal_closest_m(offs)
    upper, lower = (i, j) if offs[i, 2] < offs[j, 2] else (j, i)
    assert d < 1.0 and offs[lower, 2] - offs[upper, 2] > 1.0  # the hazard is there
    src = CommandSource(m)
    with pytest.raises(CommandError, match=rf"UAV {upper + 1} would descend onto UAV {lower + 1}, which stays"):
        src.land(5.0, [upper])
    p = src.land(5.0, [lower])
    tr = src.track
    assert tr.role[lower] == LAND and tr.land_start_s[lower] == p.effective_s and not tr.consensus[lower]
    assert tr.consensus.sum() == 39
    d, *_ = _min_pair(tr, m, p.effective_s, p.effective_s + 40.0, t_go=math.nan)
    assert d >= 1.0


def test_landing_layers():
    z = np.array([-10.0, -10.1, -12.0, np.nan, -11.9, -15.0])
    off = landing_start_offsets_s(np.column_stack([np.zeros(6), np.zeros(6), z]), 0.5, 1.0)
    np.testing.assert_allclose(off[[0, 1]], 0.0)  # level (within 0.25 m): together, first
    np.testing.assert_allclose(off[[2, 4]], 2.0)  # the next layer when the one below has gone down 1 m at 0.5 m/s
    assert off[5] == pytest.approx(4.0) and np.isnan(off[3])
    with pytest.raises(ValueError):
        landing_start_offsets_s(np.zeros((1, 3)), 0.0, 1.0)


def test_land_all_of_a_shell_lands_in_layers_within_a_minute(paper):
    """paper_40 in its final hover (170 m up) as a 8 m shell: LAND of every vehicle. Its
    landing columns are 0.73 m apart, so it first spreads (by 1.38: columns >= the
    separation), then descends in 40 layers 1.43 s apart: the last starts 56 s after the
    slots are still (before: 1461 s). No two vehicles come under the separation."""
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    f = src.formation(_hover_s(m) + 5.0, FormationSpec("shell", radius_m=8.0))
    assert horizontal_closest_m(offsets_for(f.formation, 40))[0] < 1.0
    land = src.land(f.effective_s + f.morph_s + 5.0)
    tr = src.track
    assert land.formation.radius_m > 8.0 * 1.3 and horizontal_closest_m(tr.land_point_ned_m)[0] >= 1.0
    still = land.effective_s + land.morph_s
    starts = np.sort(tr.land_start_s)
    assert starts[0] == pytest.approx(still) and starts[-1] - still == pytest.approx(39 / 0.7, rel=1e-6)
    assert np.all((tr.role == LAND) & ~tr.consensus)
    d, *_ = _min_pair(tr, m, land.effective_s, starts[-1] + 20.0, dt=0.25)
    assert d >= 1.0


def test_land_in_transit_leaves_the_formation_downwards(paper):
    """LAND of one vehicle while the formation cruises: it descends at land speed while
    coasting at its slot's velocity until clear_m below the formation, then stops (quintic)
    and goes straight down; the agent hands it over to its LAND phase then."""
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    p = src.land(T_GO + 40.0, [7])
    tr = src.track
    e = p.effective_s
    v = centre_state(p, e, m, T_GO)[1]
    assert tr.land_start_s[7] == e and tr.land_coast_s[7] == pytest.approx(clear_m(m) / 0.7)
    assert tr.land_handover_s[7] == pytest.approx(e + tr.land_coast_s[7] + 1.5 * np.hypot(v[0], v[1])
                                                  / hold_brake_mps2(m))
    pos, vel, _ = tr.at(tr.land_handover_s[7] + 1e-6, m, T_GO)
    assert np.hypot(*vel[7, :2]) < 1e-3 and vel[7, 2] == pytest.approx(0.7)
    np.testing.assert_allclose(pos[7, :2], tr.land_point_ned_m[7, :2], atol=1e-6)
    d, *_ = _min_pair(tr, m, e, tr.land_handover_s[7] + 10.0, dt=0.05)
    assert d >= 1.0


def test_rtl_flies_home_and_lands_there_in_layers():
    m = _shell_mission(12, 6.0)
    src = CommandSource(m)
    src.goto(1.0, [(100.0, 0.0, -30.0)])
    p = src.rtl(60.0)
    assert p.kind == "rtl" and p.land_at_end and p.waypoints_ned_m[-1] == (0.0, 0.0, -20.0)
    tr = src.track
    arrive = tr.centre_end_s(m, math.nan)
    starts = tr.land_start_s
    assert np.all(starts >= arrive - 1e-9) and np.isfinite(starts).all()
    assert tr.consensus.sum() == 12  # RTL keeps its formation until its vehicles start down
    pts = tr.land_point_ned_m
    np.testing.assert_allclose(pts[:, :2], (np.array((0.0, 0.0, -20.0)) + plan_offsets_ned_m(p))[:, :2], atol=1e-4)
    layers = np.round((starts - starts.min()) / (1.0 / 0.7)).astype(int)
    assert sorted(layers.tolist()) == list(range(12))  # 12 heights: 12 layers, lowest first
    assert layers[np.argmax(pts[:, 2])] == 0


def test_the_operators_schedule_keeps_every_pair_apart(paper):
    """The issue's schedule on paper_40: HOLD in transit, RESUME, circle -> wedge in the
    hover, EXCLUDE one vehicle, LAND all: no pair under the separation at any time, and the
    parked vehicle lands from a column clear of every slot."""
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    plans = [src.hold(100.0), src.resume(110.0)]
    plans.append(src.formation(_hover_s(m) + 30.0, FormationSpec("wedge", spacing_m=6.0)))
    plans.append(src.exclude(plans[-1].effective_s + plans[-1].morph_s + 5.0, [4]))
    plans.append(src.land(plans[-1].effective_s + plans[-1].morph_s + 20.0))
    tr = src.track
    assert tr.role[4] == LAND and np.isfinite(tr.land_start_s).all()
    assert horizontal_closest_m(tr.land_point_ned_m)[0] >= 1.0
    end = float(np.nanmax(tr.land_start_s)) + 250.0
    best = math.inf
    cur = initial_track(initial_plan(m), m)
    bounds = [p.effective_s for p in plans] + [end]
    for p, t1 in zip(plans, bounds[1:]):
        cur = enter(p, cur, m, T_GO)
        best = min(best, _min_pair(cur, m, p.effective_s, t1, dt=0.2)[0])
    assert best >= 1.0


# ----------------------------------------------------------------------------- the consensus graph
def test_the_consensus_graph_is_the_mission_topology_over_the_vehicles_left(paper):
    m = paper  # a chain: vehicle i hears i - 1
    src = CommandSource(m)
    src.exclude(5.0, [0, 7])
    tr = src.track
    act = [v for v in range(m.n) if v not in (0, 7)]
    w = tr.weights
    assert not w[[0, 7]].any() and not w[:, [0, 7]].any()
    np.testing.assert_array_equal(w[np.ix_(act, act)], topology.chain(38))  # 1 is the new leader, 8 hears 6
    assert w[8, 6] == 1.0 and not w[1].any()
    assert np.array_equal(tr.neighbours, topology.neighbour_table(w))
    assert consensus_graph(m, tuple(act), tr.target_ned_m)[0] is w  # cached
    knn = Mission(MissionConfig(n_vehicles=12, topology=TopologyConfig(kind="k_nearest", k=3),
                                waypoints_ned_m=((0.0, 0.0, -20.0),)))
    s2 = CommandSource(knn)
    p = s2.formation(1.0, FormationSpec("line", spacing_m=3.0))
    w2 = s2.track.weights
    np.testing.assert_array_equal(w2, topology.k_nearest(plan_offsets_ned_m(p), 3))  # by the new slots


def test_a_vehicle_that_missed_a_plan_flies_the_same_centre_and_converges(paper):
    m = paper
    src = CommandSource(m)
    src.set_t_go(T_GO)
    a = src.formation(T_GO + 20.0, FormationSpec("circle", radius_m=30.0))
    b = src.hold(T_GO + 30.0)
    on_time = _fly([a, b], m)
    missed = _fly([b], m)  # never heard `a`
    for t in np.linspace(b.effective_s, b.effective_s + 100.0, 11):
        np.testing.assert_array_equal(centre_state(b, t, m, T_GO)[0], centre_state(b, t, m, T_GO)[0])
    end = b.effective_s + b.morph_s + 1.0
    np.testing.assert_allclose(missed.at(end, m, T_GO)[0], on_time.at(end, m, T_GO)[0], atol=1e-9)


def test_a_descent_never_stops_and_no_one_rejoins_from_it():
    """An RTL's vehicles that have started down keep landing under any later plan (it lists
    them as landing; before, a GOTO put them back in their slots, 30 m up), and REJOIN of
    one is refused."""
    m = Mission(MissionConfig(n_vehicles=12, formation=FormationConfig(radius_m=10.0),
                              waypoints_ned_m=((0.0, 0.0, -30.0), (100.0, 0.0, -40.0))))
    src = CommandSource(m)
    src.set_t_go(10.0)
    src.rtl(60.0)
    rtl = src.track
    first = float(np.nanmin(rtl.land_start_s))
    with pytest.raises(CommandError, match="have started to land"):
        src.rejoin(first + 5.0, [int(np.nanargmin(rtl.land_start_s))])
    g = src.goto(first + 30.0, [(0.0, 50.0, -30.0)])
    assert g.landing == frozenset(range(12)) and (src.track.role == LAND).all()
    t = first + 40.0
    np.testing.assert_allclose(src.track.at(t, m, 10.0)[0], rtl.at(t, m, 10.0)[0])  # the same descents


def test_no_landing_onto_a_vehicle_landed_before():
    """A vehicle landed at the assembly point; the formation, re-laid (its closed gap puts a
    slot right over it) and sent home (RTL), would land on it: refused, naming both."""
    m = Mission(MissionConfig(n_vehicles=12, formation=FormationConfig(radius_m=10.0, slot_order="sequential"),
                              waypoints_ned_m=((0.0, 0.0, -30.0), (100.0, 0.0, -40.0))))
    src = CommandSource(m)
    src.land(5.0, [3])
    src.set_t_go(40.0)
    src.formation(30.0, FormationSpec("circle", radius_m=10.0, rotation_rad=math.pi / 2))
    with pytest.raises(CommandError, match=r"UAV \d+ would land .* from UAV 4, which landed"):
        src.rtl(150.0)


def _random_chain(src: CommandSource, rng: np.random.Generator, n: int, commands: int) -> list:
    """Random commands through a source (refused ones skipped): the tracks flown, from when."""
    t, out = 0.0, [(0.0, src.track)]
    for _ in range(commands):
        t += float(rng.uniform(0.5, 25.0))
        kind = str(rng.choice(["hold", "resume", "goto", "formation", "exclude", "rejoin", "land", "land_all", "rtl"]))
        ids = sorted(rng.choice(n, size=int(rng.integers(1, 3)), replace=False).tolist())
        gone = sorted(src.plan.excluded | src.plan.landing)
        make = {"hold": lambda: src.hold(t), "resume": lambda: src.resume(t), "rtl": lambda: src.rtl(t),
                "goto": lambda: src.goto(t, [tuple(rng.uniform([-50, -50, -50], [150, 150, -20]))], rng.uniform(1, 5)),
                "formation": lambda: src.formation(t, FormationSpec(
                    str(rng.choice(["circle", "line", "grid", "wedge", "shell"])), radius_m=rng.uniform(4, 15),
                    spacing_m=rng.uniform(1.5, 6), rotation_rad=rng.uniform(-3, 3))),
                "exclude": lambda: src.exclude(t, ids, land=bool(rng.random() < 0.4)),
                "rejoin": lambda: src.rejoin(t, gone[:1] or [0]), "land": lambda: src.land(t, ids),
                "land_all": lambda: src.land(t)}
        try:
            p = make[kind]()
        except CommandError:
            continue
        out.append((p.effective_s, src.track))
    return out


def test_random_command_chains_keep_every_pair_apart():
    """Whatever the operator does, what the source issues keeps every pair of vehicles at
    least the separation apart (a vehicle that hears every plan on time). 30 seeded chains of
    6 random commands (refused ones skipped) on 10 vehicles, sampled every 0.2 s."""
    m = Mission(MissionConfig(n_vehicles=10, formation=FormationConfig(radius_m=10.0),
                              waypoints_ned_m=((0.0, 0.0, -30.0), (100.0, 0.0, -40.0), (100.0, 100.0, -30.0))))
    rng = np.random.default_rng(11)
    worst = math.inf
    for k in range(30):
        src = CommandSource(m)
        if k % 2:
            src.set_t_go(20.0)
        chain = _random_chain(src, rng, m.n, 6)
        ends = [e for e, _ in chain[1:]] + [chain[-1][0] + 200.0]
        for (e, tr), e1 in zip(chain, ends):
            if e1 > e:
                worst = min(worst, _min_pair(tr, m, e, e1, dt=0.2, t_go=src.t_go_s)[0])
    assert worst >= 1.0
