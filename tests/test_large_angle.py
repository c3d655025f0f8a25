"""Recovery from any attitude (issue 9): the large-angle geometric law against PID.

Both controllers fly the same X-frame Crazyflie, mixer and limits, with the same
small-angle poles; the launches are those of the issue's must-show list.
"""
import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion import frames
from companion.control.geometric import max_thrust_n, pack_control_params, pack_setpoint, position_law, tilt_first_error
from companion.params import GRAVITY_MPS2, GeometricGains, VehicleParams
from companion.state import FleetSetpoint
from sim_bridge.reports.launch_so3 import run_so3_study
from sim_bridge.reports.launch_study import fly_launch, launch_metrics
from sim_bridge.scenario import ScenarioConfig

CFG = ScenarioConfig()


def _t(m):
    return tuple(np.asarray(m, float).reshape(-1))


def test_error_is_eq7_to_first_order_near_hover():
    rng = np.random.default_rng(4)
    for _ in range(50):
        rot = Rotation.from_rotvec(rng.normal(0, 0.4, 3)).as_matrix()
        small = rng.normal(0, 1e-3, 3)
        rot_d = rot @ Rotation.from_rotvec(small).as_matrix()
        e = np.array(tilt_first_error(_t(rot), _t(rot_d), (0.0, 0.0, 0.0), False))
        skew = rot_d.T @ rot - rot.T @ rot_d
        e_r = 0.5 * np.array([skew[2, 1], skew[0, 2], skew[1, 0]])  # eq. 7
        np.testing.assert_allclose(e, -e_r, atol=3e-6)  # O(|small|^2)


def test_error_does_not_vanish_near_180_where_eq7_does():
    rot = frames.euler_zyx_to_rot(math.radians(179.0), 0.0, 0.0)
    e = tilt_first_error(_t(rot), _t(np.eye(3)), (0.0, 0.0, 0.0), True)
    assert np.isclose(np.linalg.norm(e), 2.0 * math.sin(math.radians(89.5)), rtol=1e-9)
    assert e[0] < 0  # back towards level the short way (roll decreases)
    skew = rot.T - rot
    assert np.linalg.norm(0.5 * np.array([skew[2, 1], skew[0, 2], skew[1, 0]])) < 0.02


def test_exactly_inverted_turns_the_way_it_already_turns():
    rot = frames.euler_zyx_to_rot(math.pi, 0.0, 0.0)
    e_still = tilt_first_error(_t(rot), _t(np.eye(3)), (0.0, 0.0, 0.0), True)
    e_turning = tilt_first_error(_t(rot), _t(np.eye(3)), (-3.0, 0.0, 0.0), True)
    assert np.isclose(np.linalg.norm(e_still), 2.0) and np.isclose(np.linalg.norm(e_turning), 2.0)
    assert e_turning[0] < 0  # same sense as the body rate, not against it


def _thrust_at(rot, large_angle=True):
    sp = FleetSetpoint.empty(1)
    sp.vel_ned_mps[0] = 0.0
    prm = pack_control_params(VehicleParams(), GeometricGains(large_angle=large_angle))
    _, f, _ = position_law((0.0, 0.0, -10.0), (0.0, 0.0, 0.0), _t(rot), pack_setpoint(sp)[0], prm)
    return f


def test_thrust_schedule_hover_tilted_and_inverted():
    m_g = VehicleParams().mass_kg * GRAVITY_MPS2
    assert np.isclose(_thrust_at(np.eye(3)), m_g) and np.isclose(_thrust_at(np.eye(3), False), m_g)
    tilted = frames.euler_zyx_to_rot(math.radians(45.0), 0.0, 0.0)
    assert np.isclose(_thrust_at(tilted), m_g / math.cos(math.radians(45.0)))  # vertical part held
    assert np.isclose(_thrust_at(tilted, False), m_g * math.cos(math.radians(45.0)))  # eq. 14's projection
    steep = frames.euler_zyx_to_rot(math.radians(70.0), 0.0, 0.0)
    assert np.isclose(_thrust_at(steep), max_thrust_n(VehicleParams()))  # ... up to f_max
    for roll in (100.0, 179.0, 180.0):  # body z above the horizon: never push at the ground
        assert _thrust_at(frames.euler_zyx_to_rot(math.radians(roll), 0.0, 0.0)) == 0.0


def _pair(roll_deg, cfg=CFG):
    g = launch_metrics(fly_launch(cfg, "geometric", roll_deg), cfg.launch_study)
    p = launch_metrics(fly_launch(cfg, "pid", roll_deg), cfg.launch_study)
    return g, p


def test_roll90_at_5mps_settles_within_1s_and_beats_pid_on_every_figure():
    g, p = _pair(90.0)
    assert g.settled and g.settling_time_s <= 1.0
    assert g.settling_time_s < p.settling_time_s and g.drift_m < p.drift_m and g.altitude_loss_m < p.altitude_loss_m


def test_roll179_from_30m_loses_under_5m_and_beats_pid_on_every_figure():
    assert CFG.launch_study.release_height_m == 30.0
    g, p = _pair(179.0)
    assert g.settled and g.altitude_loss_m <= 5.0
    assert g.settling_time_s < p.settling_time_s and g.drift_m < p.drift_m and g.altitude_loss_m < p.altitude_loss_m


def test_the_paper_law_verbatim_is_what_the_large_angle_law_fixes():
    """Ablation: eq. 7-14 as printed start the 179 deg flip with |e_R| = sin(179 deg)."""
    inner = dataclasses.replace(CFG.inner_loop, geometric=GeometricGains(large_angle=False))
    paper = launch_metrics(fly_launch(dataclasses.replace(CFG, inner_loop=inner), "geometric", 179.0), CFG.launch_study)
    g, _ = _pair(179.0)
    assert paper.altitude_loss_m > 3.0 * g.altitude_loss_m and paper.settling_time_s > g.settling_time_s + 0.5


def test_random_attitudes_with_tumble_all_recover_and_geometric_wins_at_p50_and_p95():
    """300 of the issue's 1,000 draws (uniform SO(3), rates up to 10 rad/s, 5 m/s, 30 m): make demo runs all."""
    study = run_so3_study(CFG, draws=300, seed=9)
    assert study.geometric.settled.all() and study.geometric_wins(), study.summary()
    assert np.isclose(study.draws.omega_body_radps.max(), 10.0, atol=1.5)  # the bound is reached, not exceeded
    assert np.linalg.norm(study.draws.omega_body_radps, axis=1).max() <= 10.0


@pytest.mark.parametrize("frame", ["x", "plus"])
def test_both_frames_recover_from_179_deg(frame):
    cfg = dataclasses.replace(CFG, vehicle=VehicleParams(frame=frame))
    g, _ = _pair(179.0, cfg)
    assert g.settled and g.altitude_loss_m <= 5.0
