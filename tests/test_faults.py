"""Rotor failure: the physics, the failed vehicle's own detection, its neighbours' reaction,
and a whole run (headless) in which one vehicle goes down and the rest finish."""
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion import frames
from companion.agent import Agent, OwnState, Phase
from companion.config import replace
from companion.mission import Mission, MissionConfig
from companion.params import InnerLoopConfig, VehicleParams
from companion.state import FleetSetpoint
from companion.swarm import FLAG_ASSEMBLED, FLAG_OWN_VALID, SwarmStates, SwarmView
from sim_bridge.sitl.config import sitl_config
from sim_bridge.world.faults import FaultsConfig, RotorFailure, RotorFailureConfig, RotorFaults, resolve_rotor_failures
from sim_bridge.world.physics import Physics, hover_state

ROOT = Path(__file__).resolve().parents[1]


def test_a_stopped_rotor_brings_the_vehicle_down_and_leaves_the_others_hovering():
    vp = VehicleParams()
    phys = Physics(vp, InnerLoopConfig(), dt_s=0.001, ground_z_m=0.0)
    st = hover_state(2, vp, [[0.0, 0.0, -10.0], [5.0, 0.0, -10.0]])
    sp = FleetSetpoint.empty(2)
    sp.pos_ned_m[...] = st.pos_ned_m
    sp.yaw_rad[...] = 0.0
    faults = RotorFaults((RotorFailure(vehicle=0, rotor=1, time_s=0.0),), 2)
    faults.update(0.0)
    phys.step(st, sp, 500, rotor_scale=faults.scale)  # 0.5 s
    assert frames.tilt_rad(st.rot_body_to_ned[0]) > math.radians(60.0)  # lost attitude
    assert st.rotor_speed_radps[0, 1] < 0.01 * st.rotor_speed_radps[1, 1]  # spun down (tau 72 ms)
    phys.step(st, sp, 9500, rotor_scale=faults.scale)  # 10 s in all
    assert st.pos_ned_m[0, 2] == pytest.approx(0.0, abs=1e-3)  # on the ground
    np.testing.assert_allclose(st.pos_ned_m[1], [5.0, 0.0, -10.0], atol=1e-3)  # the healthy one hovers on
    assert frames.tilt_rad(st.rot_body_to_ned[1]) < 1e-3


def test_failures_resolve_from_the_seed_and_config_numbers_are_one_based():
    cfg = FaultsConfig(rotor_failures=(RotorFailureConfig(vehicle=3, time_s=80.0, rotor=4),),
                       random_rotor_failures=2, random_window_s=(50.0, 60.0))
    a, b, c = (resolve_rotor_failures(cfg, 10, s) for s in (1, 1, 2))
    assert a == b and a != c
    assert RotorFailure(vehicle=2, rotor=3, time_s=80.0) in a
    rand = [f for f in a if f.time_s != 80.0]
    assert len(rand) == 2 and len({f.vehicle for f in a}) == 3  # distinct vehicles
    assert all(50.0 <= f.time_s <= 60.0 and 0 <= f.rotor < 4 for f in rand)
    assert [f.time_s for f in a] == sorted(f.time_s for f in a)
    with pytest.raises(ValueError, match="vehicle 11"):
        resolve_rotor_failures(FaultsConfig(rotor_failures=(RotorFailureConfig(vehicle=11, time_s=1.0),)), 10, 0)
    with pytest.raises(ValueError, match="only 0"):
        resolve_rotor_failures(FaultsConfig(rotor_failures=(RotorFailureConfig(vehicle=1, time_s=1.0),),
                                            random_rotor_failures=1), 1, 0)


def _mission(n=3):
    return Mission(MissionConfig(n_vehicles=n, formation={"radius_m": 5.0}, waypoints_ned_m=((0.0, 0.0, -10.0),)))


def _own(pos, t, q=(1.0, 0.0, 0.0, 0.0)):
    return OwnState(np.atleast_2d(np.asarray(pos, float)), np.zeros((1, 3)), np.atleast_2d(np.asarray(q, float)),
                    np.array([t]), np.array([True]), np.array([True]))


def _assembled_agent(m, vid):
    """An agent in ASSEMBLE at its slot."""
    a = Agent(m, np.array([vid]))
    slot = m.offsets_ned_m[vid] + np.array([0.0, 0.0, -10.0])
    view = SwarmView.unknown(1, m.n)
    t = 0.0
    while a.phase[0] != Phase.ASSEMBLE:
        a.step(t, _own(slot, t), view)
        t += 0.02
    return a, slot, view, t


def test_the_agent_declares_loss_of_control_after_60_deg_for_0_3_s_and_then_commands_nothing():
    m = _mission()
    a, slot, view, t = _assembled_agent(m, 1)
    roll70 = (math.cos(math.radians(35.0)), math.sin(math.radians(35.0)), 0.0, 0.0)
    roll50 = (math.cos(math.radians(25.0)), math.sin(math.radians(25.0)), 0.0, 0.0)
    t0 = t
    while t < t0 + 1.0:  # 50 deg is a hard manoeuvre, not a failure
        assert a.step(t, _own(slot, t, roll50), view).phase[0] == Phase.ASSEMBLE
        t += 0.02
    t0 = t
    while t < t0 + 0.28:
        assert a.step(t, _own(slot, t, roll70), view).phase[0] == Phase.ASSEMBLE
        t += 0.02
    a.step(t, _own(slot, t, (1.0, 0, 0, 0)), view)  # a level sample restarts the dwell
    t0 = t = t + 0.02
    while a.step(t, _own(slot, t, roll70), view).phase[0] != Phase.FAILED:
        t += 0.02
        assert t < t0 + 1.0
    assert t - t0 == pytest.approx(0.3, abs=0.021)
    out = a.step(t + 1.0, _own(slot, t + 1.0), view)  # level again: FAILED is final
    assert out.phase[0] == Phase.FAILED and out.published.phase[0] == Phase.FAILED
    for f in ("pos_ned_m", "vel_ned_mps", "acc_ned_mps2"):
        assert np.isnan(getattr(out.setpoint, f)).all()  # the autopilot's failsafe owns it


def test_a_tumbling_vehicle_in_stabilise_is_not_declared_failed():
    m = _mission()
    a = Agent(m, np.array([0]))
    view = SwarmView.unknown(1, m.n)
    inverted = (0.0, 1.0, 0.0, 0.0)
    for k in range(100):
        out = a.step(k * 0.02, _own([0, 0, -10], k * 0.02, inverted), view)
    assert out.phase[0] == Phase.STABILISE


def _heard(view, vid, t, pos, phase, flags=FLAG_OWN_VALID | FLAG_ASSEMBLED):
    view.receive(np.array([0]), SwarmStates(np.array([vid]), np.array([t]), np.atleast_2d(pos).astype(float),
                                            np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]),
                                            np.array([int(phase)], np.int8), np.array([flags], np.uint8),
                                            np.array([math.nan])))


def test_neighbours_drop_a_failed_vehicle_from_consensus_but_still_avoid_it():
    m = _mission()
    a, slot, _, t = _assembled_agent(m, 1)  # chain topology: vehicle 1 listens to vehicle 0
    nb_slot = m.offsets_ned_m[0] + np.array([0.0, 0.0, -10.0])
    far = nb_slot + np.array([3.0, 0.0, 0.0])  # vehicle 0 is 3 m off its slot
    acc = {}
    for ph in (Phase.ASSEMBLE, Phase.FAILED, None):
        view = SwarmView.unknown(1, m.n)
        if ph is not None:
            _heard(view, 0, t, far, ph)
        acc[ph] = a._formation_accel(t, np.array([0]), _own(slot, t), view, view.age_s(t), a.plans.references(t, a.t_go_s))[0][0]
    assert np.linalg.norm(acc[Phase.ASSEMBLE] - acc[None]) > 0.1  # a healthy neighbour pulls
    np.testing.assert_allclose(acc[Phase.FAILED], acc[None], atol=1e-12)  # a failed one does not
    # ...but a failed vehicle falling close by still repels
    view = SwarmView.unknown(1, m.n)
    _heard(view, 0, t, slot + np.array([0.0, 0.6, 0.0]), Phase.FAILED)
    push = a._formation_accel(t, np.array([0]), _own(slot, t), view, view.age_s(t), a.plans.references(t, a.t_go_s))[0][0]
    assert push[1] < acc[None][1] - 0.5


def test_a_failed_unassembled_vehicle_does_not_hold_up_the_transit_start():
    m = _mission()
    a, slot, _, t = _assembled_agent(m, 1)
    for ph, expect_go in ((Phase.ASSEMBLE, False), (Phase.FAILED, True)):
        b, slot, _, t = _assembled_agent(m, 1)
        view = SwarmView.unknown(1, m.n)
        t1 = t + 0.5
        _heard(view, 0, t1, slot + 3.0, ph, flags=FLAG_OWN_VALID)  # never assembled
        _heard(view, 2, t1, m.offsets_ned_m[2] + [0, 0, -10.0], Phase.ASSEMBLE)
        out = b.step(t1, _own(slot, t1), view)
        assert (not math.isnan(out.t_go_s[0])) == expect_go, ph


def test_headless_run_with_a_rotor_failure_finishes_with_the_healthy_vehicles():
    from sim_bridge.reports.metrics import compute_metrics
    from sim_bridge.runs.headless import run_scenario
    from sim_bridge.scenario import load_scenario

    cfg = load_scenario(ROOT / "configs" / "small_6.yaml")
    cfg = dataclasses.replace(cfg, faults=FaultsConfig(rotor_failures=(RotorFailureConfig(vehicle=3, time_s=20.0, rotor=2),)))
    res = run_scenario(cfg, progress=False)
    m = compute_metrics(res, None)
    assert m.mission.completed and m.checks["mission_completed"], m.checks
    (f,) = m.rotor_failures
    assert f.vehicle == 3 and f.failed_at_s == pytest.approx(20.0)
    assert 0.3 <= f.detection_latency_s <= 1.5  # the dwell, plus the time to tip past 60 deg
    assert f.final_height_m == pytest.approx(0.0, abs=0.01)  # it came down
    assert m.separation.collisions == 0 and m.separation.failed_contacts == 0
    assert m.separation.min_failed_distance_m is not None and m.separation.min_failed_distance_m > 1.0
    # the run judged completion on the five healthy vehicles: the failed one is far from its slot
    log = res.log
    assert np.linalg.norm(log["pos_ned_m"][-1, 2] - log["slot_ned_m"][-1, 2]) > 5.0
    assert m.checks["rotor_failures_detected"] and m.passed


def test_safety_tracker_judges_healthy_pairs_and_tracks_a_failed_vehicle_apart():
    from sim_bridge.reports.record import SafetyTracker

    m = _mission(4)
    s = SafetyTracker(1.0, collision_m=0.2)
    ids = np.arange(4)
    pos = np.array([[0.0, 0.0, -10.0], [0.1, 0.0, -10.0], [5.0, 0.0, -10.0], [5.5, 0.0, -10.0]])
    s.update(0.0, ids, pos, m, healthy=np.array([False, True, True, True]))
    assert s.failed_contacts == {(0, 1)} and s.min_failed_dist_m == pytest.approx(0.1)
    assert s.min_pair_dist_m == pytest.approx(0.5) and s.min_pair == (2, 3)  # 0-1 is not a healthy pair
    assert s.violating_pairs == {(2, 3)} and not s.colliding_pairs
    pos[3, 0] = 5.15
    s.update(0.02, ids, pos, m)  # everyone healthy: 0-1 and 2-3 now both collide
    assert s.colliding_pairs == {(0, 1), (2, 3)}
    back = SafetyTracker.from_json(s.to_json())
    assert back == s


def test_sitl_applies_a_scheduled_failure_and_says_so():
    """A `faults` entry in the SITL config stops the rotor at its time, with a CRITICAL STATUSTEXT."""
    from sim_bridge.sitl.background import BackgroundSitl
    from sim_bridge.sitl.testing import MavClient, local_endpoints

    cfg = sitl_config(2, endpoints=local_endpoints(2))
    fail = FaultsConfig(rotor_failures=(RotorFailureConfig(vehicle=2, time_s=0.5, rotor=2),))
    cfg = replace(cfg, scenario=replace(cfg.scenario, faults=fail))
    with BackgroundSitl(cfg) as sitl:
        c = MavClient(cfg.endpoints.remote_base_port + 1)
        try:
            st = c.wait("STATUSTEXT", lambda m: "motor 2 failed" in m.text, 5.0)
            assert st is not None and st.get_srcSystem() == 2 and st.severity == 2  # MAV_SEVERITY_CRITICAL
            assert sitl.rotor_faults.scale.tolist() == [[1.0] * 4, [1.0, 0.0, 1.0, 1.0]]
            assert sitl.rotor_faults.failed_at_s[1] == pytest.approx(0.5, abs=0.05)
        finally:
            c.close()
