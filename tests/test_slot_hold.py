"""The slot hold driven into the autopilot's velocity integrator (companion.slot_hold).

A vehicle is a double integrator under an emulated autopilot position loop of PX4's form
(P on position, PI on velocity, feed-forward added) that flies the agent's trajectory
setpoints through the one output stage, with a steady bias b the law never sees.
"""
from __future__ import annotations

import numpy as np
import pytest

from companion.agent import Agent, OwnState, Phase
from companion.link.dialects.ardupilot import ArduPilot
from companion.link.dialects.base import PositionLoop
from companion.link.dialects.px4 import Px4
from companion.link.limits import SetpointLimits
from companion.mission import Mission, MissionConfig
from companion.output import output_stage_for
from companion.state import FleetSetpoint
from companion.swarm import SwarmView

PX4_LOOP = Px4().position_loop({})
Q_LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _mission(**kw) -> Mission:
    return Mission(MissionConfig(n_vehicles=1, formation={"radius_m": 5.0}, waypoints_ned_m=((0.0, 0.0, -10.0),),
                                 **kw))


def test_drive_gain_and_stiffness_from_each_autopilots_parameters():
    # PX4 defaults: MPC_XY_P 0.95, MPC_XY_VEL_P_ACC 1.8, MPC_XY_VEL_I_ACC 0.4; MPC_Z_P 1, _VEL_P_ACC 4, _VEL_I_ACC 2
    assert PX4_LOOP.stiffness_per_s2() == pytest.approx((0.95 * 1.8, 0.95 * 1.8, 4.0))
    assert PX4_LOOP.drive_gain(0.05) == pytest.approx((0.05 / (0.4 * 0.95), 0.05 / (0.4 * 0.95), 0.05 / 2.0))
    # a parameter read from the autopilot replaces the default
    assert Px4().position_loop({"MPC_XY_VEL_I_ACC": 0.1}).drive_gain(0.05)[0] == pytest.approx(0.05 / (0.1 * 0.95))
    # ArduPilot: PSC_VELZ_I is 0 by default: no vertical drive (the agent integrates that axis)
    ap = ArduPilot().position_loop({})
    assert ap.drive_gain(0.05) == pytest.approx((0.05, 0.05, 0.0))
    assert ap.stiffness_per_s2() == pytest.approx((2.0, 2.0, 5.0))
    # never more than the whole residual, and nothing from an integrator that is off or not finite
    assert PositionLoop(1, 1, 0.01, 1, 1, float("nan")).drive_gain(0.05) == (1.0, 1.0, 0.0)


def _fly(m: Mission, bias: np.ndarray, loop: PositionLoop | None, t_end: float = 120.0, off0=(0.0, 0.0, 0.0),
         integ0=(0.0, 0.0, 0.0)):
    """One vehicle at its slot; the agent at 10 Hz, the emulated autopilot loop and the
    physics at 100 Hz (the output stage extrapolates the plan between agent steps).
    off0: where the vehicle starts off its slot, m; integ0: the autopilot's integrator then, m/s^2.
    Returns (slot error (3,), the autopilot's integrator (3,), the agent)."""
    agent = Agent(m, np.array([0]))
    agent.phase[:] = Phase.ASSEMBLE
    out_stage = output_stage_for(m.cfg, 1, limits=SetpointLimits())
    agent.set_autopilot_loop([0], loop)
    out_stage.set_loop([0], loop)
    view = SwarmView.unknown(1, 1)
    lp = PX4_LOOP
    kp = np.array([lp.pos_p_xy_per_s, lp.pos_p_xy_per_s, lp.pos_p_z_per_s])
    kv = np.array([lp.vel_p_xy_per_s, lp.vel_p_xy_per_s, lp.vel_p_z_per_s])
    ki = np.array([lp.vel_i_xy_per_s2, lp.vel_i_xy_per_s2, lp.vel_i_z_per_s2])
    pos, vel, integ = m.slot_ned_m(-1.0)[0] + off0, np.zeros(3), np.array(integ0, float)
    dt = 0.01
    for k in range(int(round(t_end / dt))):
        t = k * dt
        own = OwnState(pos[None].copy(), vel[None].copy(), Q_LEVEL[None].copy(), np.array([t]), np.ones(1, bool),
                       np.ones(1, bool))
        if k % 10 == 0:
            out = agent.step(t, own, view)
            view.receive_all(out.published)
            out_stage.set_plan(t, out.setpoint, np.ones(1, bool), out.drive_ned_m)
        sp = out_stage.step(t, own.pos_ned_m, own.vel_ned_mps, own.att_q_wxyz)
        e_v = kp * (sp.pos_ned_m[0] - pos) + sp.vel_ned_mps[0] - vel
        acc = kv * e_v + integ + sp.acc_ned_mps2[0] + bias
        integ = integ + ki * e_v * dt
        pos, vel = pos + vel * dt + 0.5 * acc * dt * dt, vel + acc * dt
    return pos - out.slot_ned_m[0], integ, agent


def test_the_drive_hands_the_bias_to_the_autopilots_integrator_sooner():
    """Without the drive the autopilot's integrator learns b only from how far the vehicle
    drifts off the extrapolated setpoint between two agent steps (the state setpoint leads
    it by one setpoint period: issue 18's PX4 symptom); with it, from the residual as
    well. Either way the two integrators together hold b (the agent's as -k_i z) and the
    slot error goes to zero."""
    b = np.array([0.3, -0.2, 0.25])
    m = _mission()
    k_i = m.cfg.consensus.ki_pos_per_s3
    share = {}
    for name, loop in (("agent only", None), ("driven", PX4_LOOP)):
        _, integ30, _ = _fly(m, b, loop, 30.0)
        share[name] = -integ30[:2] / b[:2]  # the autopilot's share of the horizontal bias at 30 s
        err, integ, agent = _fly(m, b, loop, 120.0)
        assert np.abs(err).max() < 0.01
        np.testing.assert_allclose(integ - k_i * agent.slot_hold.z_ms[0], -b, atol=0.01)
    assert (share["driven"] > share["agent only"] + 0.05).all()
    assert (share["driven"] < 1.0).all()


def test_the_drive_unwinds_an_autopilot_integrator_wound_against_the_agent():
    """PX4's horizontal anti-windup winds its velocity integrator against a sustained
    feed-forward while the vertical demand points down (a climb in transit; docs/agent.md):
    at the end of a transit a vehicle was held 4 m off its slot by 2.4 m/s^2 of it against the
    agent's law (paper_40 seed 9). The agent's own integral may not act that far off
    (slot_integral.zone_m); the drive's wider gate takes the integrator back."""
    m = _mission()
    off = np.array([4.0, 0.0, 0.0])
    wound = -m.cfg.consensus.k2_pos_per_s2 * off  # what holds the vehicle there against eq. 27
    # Without the drive only the setpoint's lead reaches that integrator (lead x demand: 0.05 m/s
    # here; PX4's anti-windup leak, which wound it, can cancel even that: seed 9 stayed 2 m off).
    err_lead, _, _ = _fly(m, np.zeros(3), None, 20.0, off, wound)
    err, integ, _ = _fly(m, np.zeros(3), PX4_LOOP, 20.0, off, wound)
    assert np.linalg.norm(err) < 0.5 * np.linalg.norm(err_lead)
    err, integ, agent = _fly(m, np.zeros(3), PX4_LOOP, 90.0, off, wound)
    assert np.linalg.norm(err) < 0.05
    # no bias: what the two integrators still hold cancels (the agent's caught part of the swing)
    assert np.abs(integ - m.cfg.consensus.ki_pos_per_s3 * agent.slot_hold.z_ms[0]).max() < 0.05


def test_the_drive_learns_no_obstacles_push():
    """Held off its slot by an obstacle's repulsion, with no bias, the vehicle stays where
    eq. 27 + eq. 30 hold it: neither integrator learns the push."""
    slot = _mission().slot_ned_m(-1.0)[0]
    obstacle = {"centre_ned_m": (slot[0] + 2.0, slot[1], slot[2]), "radius_m": 1.0}
    m = _mission(obstacles=(obstacle,))
    err0, _, _ = _fly(_mission(obstacles=(obstacle,), consensus={"ki_pos_per_s3": 0.0}), np.zeros(3), None, 60.0)
    assert np.linalg.norm(err0) > 0.05
    push = abs(m.cfg.consensus.k2_pos_per_s2) * np.linalg.norm(err0)  # what eq. 30 exerts there, m/s^2
    k_i = m.cfg.consensus.ki_pos_per_s3
    err, integ, agent = _fly(m, np.zeros(3), PX4_LOOP, 60.0)
    np.testing.assert_allclose(err, err0, atol=0.01)  # (of a 3 m push)
    # the approach leaves both a little, in opposite senses: together under 1 % of the push
    assert np.abs(integ - k_i * agent.slot_hold.z_ms[0]).max() < 0.01 * push
    _, integ, agent = _fly(m, np.zeros(3), PX4_LOOP, 240.0)  # and it fades
    assert np.abs(integ).max() < 0.01 * push and k_i * np.abs(agent.slot_hold.z_ms).max() < 0.01 * push


def test_the_output_stage_takes_the_p_loops_pull_on_the_drive_out_of_the_feed_forward():
    m = _mission()
    stage = output_stage_for(m.cfg, 1, limits=SetpointLimits())
    stage.set_loop([0], PX4_LOOP)

    sp = FleetSetpoint.empty(1)
    sp.pos_ned_m[0], sp.vel_ned_mps[0], sp.acc_ned_mps2[0] = (1.0, 2.0, -10.0), (0.5, 0.0, 0.0), (0.2, 0.0, 0.1)
    sp.yaw_rad[0] = 0.0
    d = np.array([[0.1, -0.2, 0.05]])
    stage.set_plan(0.0, sp, np.ones(1, bool), d)
    out = stage.step(0.0, sp.pos_ned_m, sp.vel_ned_mps, np.tile(Q_LEVEL, (1, 1)))
    np.testing.assert_allclose(out.pos_ned_m[0], sp.pos_ned_m[0] + d[0])
    np.testing.assert_allclose(out.acc_ned_mps2[0], sp.acc_ned_mps2[0] - np.array(PX4_LOOP.stiffness_per_s2()) * d[0])
    # 0.1 s on: the plan advanced along the planned acceleration, not the compensated one
    out = stage.step(0.1, sp.pos_ned_m, sp.vel_ned_mps, np.tile(Q_LEVEL, (1, 1)))
    np.testing.assert_allclose(out.vel_ned_mps[0], sp.vel_ned_mps[0] + 0.1 * sp.acc_ned_mps2[0])
    # attitude output has no autopilot position loop: no drive, no compensation
    stage.set_plan(0.0, sp, np.ones(1, bool), None)
    out = stage.step(0.0, sp.pos_ned_m, sp.vel_ned_mps, np.tile(Q_LEVEL, (1, 1)))
    np.testing.assert_allclose(out.acc_ned_mps2[0], sp.acc_ned_mps2[0])
