"""The sans-IO Agent: phase transitions and one code path for one or many vehicles."""
import numpy as np
import pytest

from companion.agent import Agent, OwnState, Phase, SwarmView
from companion.mission import Mission, MissionConfig


def _mission(n=4, **kw):
    return Mission(MissionConfig(n_vehicles=n, formation={"radius_m": 5.0}, waypoints_ned_m=((0.0, 0.0, -10.0),), **kw))


def _own(pos, vel, tilt, released):
    return OwnState(np.asarray(pos, float), np.asarray(vel, float), np.asarray(tilt, float), np.asarray(released))


def test_launch_to_stabilise_to_assemble_with_dwell():
    m = _mission(1)
    a = Agent(m, np.array([0]))
    sw = SwarmView.unknown(1)
    out = a.step(0.0, _own([[0, 0, -10]], [[5, 0, 0]], [1.5], [False]), sw)
    assert out.phase[0] == Phase.LAUNCH and np.all(np.isnan(out.setpoint.vel_ned_mps))
    out = a.step(0.02, _own([[0, 0, -10]], [[5, 0, 0]], [1.5], [True]), sw)
    assert out.phase[0] == Phase.STABILISE
    np.testing.assert_array_equal(out.setpoint.vel_ned_mps[0], 0.0)  # brake
    assert np.isnan(out.setpoint.acc_ned_mps2[0]).all()
    calm = _own([[0, 0, -10]], [[0.1, 0, 0]], [np.radians(3)], [True])
    dwell = m.cfg.phases.stable_dwell_s
    for t in np.arange(0.04, 0.04 + dwell - 0.02, 0.02):
        assert a.step(t, calm, sw).phase[0] == Phase.STABILISE
    # a disturbance restarts the dwell
    assert a.step(1.0, _own([[0, 0, -10]], [[0.5, 0, 0]], [0.0], [True]), sw).phase[0] == Phase.STABILISE
    assert a.step(1.02, calm, sw).phase[0] == Phase.STABILISE
    assert a.step(1.02 + dwell, calm, sw).phase[0] == Phase.ASSEMBLE


def test_transit_starts_on_common_quantum_after_all_assembled():
    m = _mission(2)
    a = Agent(m, np.array([0, 1]))
    a.phase[:] = Phase.ASSEMBLE
    slots = m.slot_ned_m(-1.0)
    own = _own(slots, np.zeros((2, 3)), [0, 0], [True, True])
    sw = SwarmView(slots.copy(), np.zeros((2, 3)), np.full(2, int(Phase.ASSEMBLE)), np.array([True, False]))
    out = a.step(3.3, own, sw)
    assert np.isnan(out.t_go_s)
    assert out.assembled.all()  # both at their slot now
    sw.assembled[:] = True
    out = a.step(3.34, own, sw)
    assert out.t_go_s == pytest.approx(4.0)
    assert np.all(a.step(4.0, own, sw).phase == Phase.HOVER)  # one waypoint: zero-length transit


def test_one_vehicle_agent_equals_batch_row():
    """The companion's single-vehicle agent computes exactly the batch's row."""
    n = 6
    m = _mission(n, obstacles=({"centre_ned_m": (0.0, 6.0, -10.0), "radius_m": 1.0},))
    rng = np.random.default_rng(3)
    pos = m.slot_ned_m(-1.0) + rng.normal(0, 1.5, (n, 3))
    vel = rng.normal(0, 0.5, (n, 3))
    phases = np.full(n, int(Phase.ASSEMBLE), dtype=np.int8)
    phases[4] = Phase.STABILISE
    sw = SwarmView(pos.copy(), vel.copy(), phases, np.zeros(n, bool))

    batch = Agent(m, np.arange(n))
    batch.phase[:] = phases
    out_b = batch.step(10.0, _own(pos, vel, np.zeros(n), np.ones(n, bool)), sw)
    for i in range(n):
        one = Agent(m, np.array([i]))
        one.phase[:] = phases[i]
        # the single agent hears the others through the swarm link: its own row may be stale
        sw_i = SwarmView(sw.pos_ned_m.copy(), sw.vel_ned_mps.copy(), sw.phase.copy(), sw.assembled.copy())
        sw_i.pos_ned_m[i] = np.nan
        out_1 = one.step(10.0, _own(pos[i : i + 1], vel[i : i + 1], [0.0], [True]), sw_i)
        for f in ("acc_ned_mps2", "vel_ned_mps", "yaw_rad"):
            np.testing.assert_allclose(getattr(out_1.setpoint, f)[0], getattr(out_b.setpoint, f)[i], atol=1e-12)
        assert out_1.phase[0] == out_b.phase[i]


def test_apf_pushes_apart_close_vehicles():
    m = _mission(2)
    a = Agent(m, np.arange(2))
    a.phase[:] = Phase.ASSEMBLE
    slots = m.slot_ned_m(-1.0)
    mid = slots.mean(axis=0)
    pos = np.array([mid + [0, -0.3, 0], mid + [0, 0.3, 0]])
    sw = SwarmView(pos.copy(), np.zeros((2, 3)), np.full(2, int(Phase.ASSEMBLE)), np.zeros(2, bool))
    out = a.step(1.0, _own(pos, np.zeros((2, 3)), [0, 0], [True, True]), sw)
    acc = out.setpoint.acc_ned_mps2
    assert acc[0, 1] < 0 < acc[1, 1]
