"""The receiver side (companion/commands/book.py): per row the plan in force and one pending
plan, the newest seq wins, late rows join the on-time rows' track, bounded memory, the
references the agent flies (bit for bit its own under the mission's plan), what to relay,
and the leads on a lossy relayed link."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.commands import (
    DEFAULT_LEAD_S,
    URGENT_LEAD_S,
    CommandSource,
    PlanBook,
    enter,
    initial_plan,
    initial_track,
    plan_messages,
)
from companion.control.shapes import FormationSpec
from companion.mission import Mission, MissionConfig
from sim_bridge.scenario import load_scenario

EPOCH = 1_767_225_600.0
T_GO = 65.0


@pytest.fixture(scope="module")
def paper() -> Mission:
    return Mission(load_scenario("configs/paper_40.yaml", runner=None).mission)


def _plans(m: Mission):
    src = CommandSource(m)
    src.set_t_go(T_GO)
    return src, [src.formation(T_GO + 10.0, FormationSpec("circle", radius_m=35.0)), src.hold(T_GO + 20.0),
                 src.resume(T_GO + 40.0)]


def test_a_plan_takes_force_at_its_effective_time(paper):
    src, (a, b, c) = _plans(paper)
    book = PlanBook(paper, 4)
    t_go = np.full(4, T_GO)
    assert book.receive([0, 1], a).tolist() == [0, 1]
    assert book.pending_seq.tolist() == [1, 1, 0, 0] and book.plan_seq.tolist() == [0, 0, 0, 0]
    assert not len(book.advance(a.effective_s - 0.01, t_go))
    assert book.advance(a.effective_s, t_go).tolist() == [0, 1]
    assert book.plan_seq.tolist() == [1, 1, 0, 0] and book.pending_seq.tolist() == [0, 0, 0, 0]
    groups = book.references(a.effective_s + 5.0, t_go)
    assert len(groups) == 2 and sorted(g.rows.tolist() for g in groups) == [[0, 1], [2, 3]]
    g1 = next(g for g in groups if 0 in g.rows)
    on_time = enter(a, initial_track(initial_plan(paper), paper), paper, T_GO)  # as the source flew it
    np.testing.assert_array_equal(g1.h_pos[0], on_time.at(a.effective_s + 5.0, paper, T_GO)[0])
    assert book.stats.received == 2 and book.stats.applied == 2


def test_the_newest_seq_wins_and_nothing_older_undoes_it(paper):
    _, (a, b, c) = _plans(paper)
    book = PlanBook(paper, 3)
    book.receive([0, 1, 2], c)
    assert not len(book.receive([0, 1, 2], a)) and book.stats.stale == 3  # reordered: older, dropped
    assert not len(book.receive([0], c)) and book.stats.duplicates == 1  # a relayed copy
    book.advance(c.effective_s + 1.0, T_GO)
    assert book.plan_seq.tolist() == [3, 3, 3]
    assert not len(book.receive([1], b)) and book.plan_seq.tolist() == [3, 3, 3]
    forged = type(c)(**{**c.__dict__, "speed_mps": 9.0})
    book2 = PlanBook(paper, 2)
    book2.receive([0], c)
    assert not len(book2.receive([1], forged)) and book2.stats.conflicts == 1  # same seq, other content


def test_a_plan_whose_slots_would_collide_is_refused_by_its_receivers(paper):
    """The sender's checks do not protect receivers from a forged or buggy sender: a formation
    whose 40 slots lie within 2 mm (as an attacker sent it, seq 1000, no morph) is dropped and
    counted; the same plan with slots the separation apart is taken; an ABORT always is."""
    import dataclasses

    _, (a, _b, _c) = _plans(paper)
    book = PlanBook(paper, 2)
    tiny = dataclasses.replace(a, seq=1000, formation=FormationSpec("circle", radius_m=1e-3), morph_s=0.0)
    assert not len(book.receive([0, 1], tiny)) and book.stats.rejected == 2 and book.pending_seq.tolist() == [0, 0]
    assert book.receive([0], dataclasses.replace(tiny, formation=FormationSpec("circle", radius_m=35.0))).tolist() == [0]
    assert book.receive([1], dataclasses.replace(tiny, seq=1001, abort=True)).tolist() == [1]


def test_late_rows_fly_what_the_on_time_rows_fly(paper):
    """Rows that hear a plan after its effective time apply it at once, as if on time: they
    join the on-time rows' track (one track, one reference), so consensus sees one reference."""
    _, (a, *_) = _plans(paper)
    book = PlanBook(paper, 40)
    t_go = np.full(40, T_GO)
    book.receive(np.arange(30), a)
    book.advance(a.effective_s, t_go)
    book.receive(np.arange(30, 40), a)
    book.advance(a.effective_s + 2.0, t_go)
    assert len(set(book.track_of.tolist())) == 1 and (book.plan_seq == 1).all()
    groups = book.references(a.effective_s + 3.0, t_go)
    assert len(groups) == 1 and groups[0].h_pos.shape == (1, 40, 3) and not groups[0].h_sel.any()


def test_memory_stays_bounded_under_a_flood_of_new_seqs(paper):
    src = CommandSource(paper)
    book = PlanBook(paper, 40)
    for k in range(300):
        plan = src.formation(1.0 + k, FormationSpec("circle", radius_m=40.0 + (k % 3)))
        book.receive(np.arange(k % 40, 40), plan)
        book.advance(0.0, math.nan)  # none is due yet
        assert book.plans_held <= 2 * 40 + 1
    assert book.stats.superseded > 0 and (book.pending_seq > 0).all()
    book.advance(1e6, math.nan)
    in_force = set(book.plan_seq.tolist())  # the newest each row heard (20 distinct)
    assert book.plans_held == len(in_force) + 1 and len(book._tracks) == len(in_force)  # (+ the mission's)


def test_references_under_the_mission_plan_are_the_agents(paper):
    """Rows holding different transit starts (NaN: none yet) fly one reference each, stacked as
    consensus_rows takes them: h_pos[g] = m.offsets_ned_m + c, h_vel[g] = c', h_acc[g] = c''
    bit for bit, and the mission's own weights and neighbours."""
    m = paper
    book = PlanBook(m, 5)
    t_go = np.array([T_GO, math.nan, T_GO, 66.0, math.nan])
    (g,) = book.references(80.0, t_go)
    assert g.track.weights is m.weights and g.track.neighbours is m.neighbours
    assert [x if x == x else None for x in g.t_go_s.tolist()] == [None, T_GO, 66.0]
    assert g.h_sel.tolist() == [1, 0, 1, 2, 0]
    for k, tg in enumerate(g.t_go_s.tolist()):
        c_pos, c_vel, c_acc = m.path.at(m.tau_s(80.0, tg))
        assert g.h_pos[k].tobytes() == (m.offsets_ned_m + c_pos).tobytes()
        assert np.array_equal(g.h_vel[k], np.broadcast_to(c_vel, (m.n, 3)))
        assert np.array_equal(g.h_acc[k], np.broadcast_to(c_acc, (m.n, 3)))
        assert g.centre_end_s[k] == tg + m.path.duration_s or math.isnan(tg)
    (one,) = book.references(80.0, np.full(5, T_GO), rows=[0, 2])
    assert one.rows.tolist() == [0, 2] and one.h_pos.shape == (1, m.n, 3)


def test_what_a_row_relays_is_the_newest_plan_it_holds(paper):
    _, (a, b, _) = _plans(paper)
    book = PlanBook(paper, 2)
    assert book.relay_messages(0, EPOCH) == []
    book.receive([0], a)
    book.advance(a.effective_s, T_GO)
    book.receive([0], b)
    msgs = book.relay_messages(0, EPOCH)
    assert msgs == plan_messages(b, EPOCH) and book.relay_messages(0, EPOCH) is msgs  # cached
    assert book.relay_messages(1, EPOCH) == []


def _lossy_delivery(n_rows: int, lead_s: float, rng: np.random.Generator, loss: float = 0.2, delay_s: float = 0.1,
                    rate_hz: float = 10.0, repeats=(0.0, 0.3, 0.6)) -> np.ndarray:
    """When each of n_rows receivers completes a plan (its SWARMDROP_PLAN and SLOTS both held),
    s after issue: the source sends at `repeats` (the console's), every receiver that holds it
    relays both messages at the swarm rate, each copy reaches each receiver with probability
    1 - loss after delay_s. Returns the completion times (inf: not by lead + 2 s)."""
    have = np.zeros((n_rows, 2), bool)
    done = np.full(n_rows, np.inf)
    tick = 1.0 / rate_hz
    t = 0.0
    in_flight: list[tuple[float, np.ndarray]] = []
    while t <= lead_s + 2.0 + 1e-9:
        senders = int(np.sum(done < t - 1e-9)) + sum(1 for r in repeats if abs(r - t) < 1e-9)
        if senders:  # each copy of each message independently
            got = (rng.random((senders, n_rows, 2)) >= loss).any(axis=0)
            in_flight.append((t + delay_s, got))
        for arrive, got in [f for f in in_flight if f[0] <= t + 1e-9]:
            have |= got
        in_flight = [f for f in in_flight if f[0] > t + 1e-9]
        done = np.where(np.isinf(done) & have.all(axis=1), t, done)
        t = round(t + tick, 9)
    return done


def test_the_leads_suffice_on_a_lossy_relayed_link():
    """20 % loss, 100 ms delay, relays at 10 Hz (docs/swarm.md): with the normal lead (1 s) every
    vehicle of 40 holds the plan before it applies in 200 trials; with HOLD's urgent lead
    (0.3 s) a few apply it late, and every one within 1 s of its effective time."""
    rng = np.random.default_rng(19)
    normal = np.array([_lossy_delivery(40, DEFAULT_LEAD_S, rng) for _ in range(200)])
    assert np.all(normal <= DEFAULT_LEAD_S)
    urgent = np.array([_lossy_delivery(40, URGENT_LEAD_S, rng) for _ in range(200)])
    late = urgent - URGENT_LEAD_S
    assert np.all(late <= 1.0) and np.mean(late > 0) < 0.05


def test_a_book_for_one_row_and_a_bad_plan(paper):
    with pytest.raises(ValueError):
        PlanBook(paper, 0)
    other = CommandSource(Mission(MissionConfig(n_vehicles=6, waypoints_ned_m=((0.0, 0.0, -10.0),)))).hold(1.0)
    book = PlanBook(paper, 1)
    assert not len(book.receive([0], other)) and book.stats.rejected == 1
