"""The Agent flies swarm plans (companion.commands): a plan takes force at its effective
time on every vehicle that holds it, HOLD stops the centre, LAND lands, ABORT hands over.
Double integrators fly the agent's accelerations exactly (no autopilot model)."""
import numpy as np

from companion.agent import Agent, OwnState, Phase
from companion.commands import CommandSource
from companion.mission import Mission, MissionConfig
from companion.swarm import FLAG_HANDED_OVER, SwarmView

Q = [1.0, 0.0, 0.0, 0.0]


def _mission(n=4):
    return Mission(MissionConfig(n_vehicles=n, formation={"radius_m": 6.0}, transit_speed_mps=3.0,
                                 waypoints_ned_m=((0.0, 0.0, -10.0), (200.0, 0.0, -10.0))))


class Swarm:
    """n double integrators at their slots, flown by one batched Agent at 20 Hz, every state
    heard by every vehicle at once; `plans[t] = plan` hands a plan to `rows` at time t."""

    def __init__(self, m, dt=0.05):
        self.m, self.dt = m, dt
        n = self.n = m.n
        self.agent = Agent(m, np.arange(n))
        self.agent.phase[:] = Phase.ASSEMBLE
        self.view = SwarmView.unknown(n, n)
        self.pos, self.vel = m.slot_ned_m(-1.0).copy(), np.zeros((n, 3))
        self.t = 0.0
        self.log = []

    def run(self, until, deliveries=()):
        deliveries = sorted(deliveries, key=lambda d: d[0])
        while self.t < until - 1e-9:
            t = self.t
            while deliveries and deliveries[0][0] <= t + 1e-9:
                _, rows, plan = deliveries.pop(0)
                self.agent.plans.receive(rows, plan)
            own = OwnState(self.pos, self.vel, np.tile(Q, (self.n, 1)), np.full(self.n, t), np.ones(self.n, bool),
                           np.ones(self.n, bool))
            out = self.agent.step(t, own, self.view)
            self.view.receive_all(out.published)
            acc = np.nan_to_num(out.setpoint.acc_ned_mps2)
            land = out.phase == Phase.LAND
            acc[land] = 2.0 * (np.array([0.0, 0.0, 1.0]) - self.vel[land])  # descend at 1 m/s
            dt = self.dt
            self.pos, self.vel = self.pos + self.vel * dt + 0.5 * acc * dt * dt, self.vel + acc * dt
            self.log.append((t, self.pos.copy(), self.vel.copy(), out))
            self.t = round(t + dt, 9)
        return self.log[-1][3]


def _flying(m, until_s):
    """A Swarm flown to until_s, and a CommandSource that knows its agreed transit start."""
    sw = Swarm(m)
    sw.run(until_s)
    src = CommandSource(m)
    src.set_t_go(float(sw.agent.t_go_s[0]))
    return sw, src


def test_hold_in_transit_stops_the_centre_and_keeps_the_formation():
    m = _mission()
    sw, src = _flying(m, 20.0)
    assert (sw.agent.phase == Phase.TRANSIT).all()
    plan = src.hold(20.0)
    assert 20.0 < plan.effective_s < 21.0
    out = sw.run(40.0, [(20.0, np.arange(4), plan)])
    t_stop = plan.effective_s + 2.0
    speeds = [np.linalg.norm(v.mean(axis=0)) for t, p, v, o in sw.log if t > t_stop]
    assert max(speeds) < 0.1  # the centre stopped within 2 s of taking force (HOLD brakes at 2.4 m/s^2)
    assert (out.plan_seq == plan.seq).all() and (out.published.plan_seq == plan.seq).all()
    assert (out.phase == Phase.HOVER).all()  # the centre at rest: hover
    slots = src.reference(39.95)[0]
    assert np.abs(sw.pos - slots).max() < 0.05  # the formation kept, where the source says


def test_a_plan_missed_by_some_vehicles_is_flown_by_every_vehicle_that_hears_it_later():
    """A vehicle that hears the newest plan late (after its effective time) flies the same
    reference as those that heard it on time (Agreement rules, docs/swarm.md)."""
    m = _mission()
    sw, src = _flying(m, 20.0)
    plan = src.hold(20.0)
    sw.run(22.0, [(20.0, np.array([0, 1, 2]), plan)])
    assert sw.agent.plans.plan_seq.tolist() == [plan.seq] * 3 + [0]
    sw.run(40.0, [(22.0, np.array([3]), plan)])
    assert (sw.agent.plans.plan_seq == plan.seq).all()
    assert np.abs(sw.pos - src.reference(39.95)[0]).max() < 0.1


def test_land_all_lands_everyone_and_abort_hands_over():
    m = _mission()
    sw, src = _flying(m, 10.0)
    plan = src.land(10.0)
    out = sw.run(40.0, [(10.0, np.arange(4), plan)])
    assert (out.phase == Phase.LAND).all()
    assert (sw.pos[:, 2] > -3.0).all()  # well on the way down from 10 m

    sw = Swarm(m)
    sw.run(10.0)
    src = CommandSource(m)
    plan = src.abort(10.0)
    out = sw.run(11.0, [(10.0, np.arange(4), plan)])
    assert out.handed_over.all() and np.isnan(out.setpoint.acc_ned_mps2).all()
    assert np.isnan(out.setpoint.pos_ned_m).all() and np.isnan(out.setpoint.vel_ned_mps).all()
    assert (out.published.flags & FLAG_HANDED_OVER).all()


def test_a_landing_vehicle_is_held_over_the_point_where_its_descent_began():
    """LAND sends the column over where the descent began (position x, y held, the height
    leading by the descent speed), so the autopilot's loops take a drift out instead of
    flying the vehicle wherever a bias pushes it (paper_40 with a schedule: two vehicles
    drifted to 0.54 m apart on the way down)."""
    m = _mission()
    sw, src = _flying(m, 10.0)
    plan = src.land(10.0)
    sw.run(25.0, [(10.0, np.arange(4), plan)])
    assert (sw.agent.phase == Phase.LAND).all()
    start_xy = sw.agent.land_xy_ned_m.copy()
    assert np.isfinite(start_xy).all()
    sw.pos[:, 1] += 0.7  # pushed sideways while descending
    t = sw.t
    own = OwnState(sw.pos, sw.vel, np.tile(Q, (4, 1)), np.full(4, t), np.ones(4, bool), np.ones(4, bool))
    out = sw.agent.step(t, own, sw.view)
    np.testing.assert_array_equal(out.setpoint.pos_ned_m[:, :2], start_xy)  # back over the landing point
    lead = m.cfg.setpoint.lead_s
    land = m.cfg.phases.land_speed_mps
    np.testing.assert_allclose(out.setpoint.pos_ned_m[:, 2], sw.pos[:, 2] + land * lead)
    np.testing.assert_array_equal(out.setpoint.vel_ned_mps, np.tile([0.0, 0.0, land], (4, 1)))
