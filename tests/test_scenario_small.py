"""A six-vehicle end-to-end scenario: launch, recover, assemble, avoid, hold."""
import json
from pathlib import Path

import numpy as np
import pytest

from sim_bridge.runs.simulate import simulate
from sim_bridge.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("small_6")
    cfg = load_scenario(ROOT / "configs" / "small_6.yaml")
    metrics = simulate(cfg, out, progress=False, figures=True)
    return cfg, metrics, out


def test_everyone_stabilises_and_formation_is_reached(run):
    cfg, m, _ = run
    assert m.stabilisation.all_stabilised
    assert m.mission.completed, m.mission
    assert m.formation_deviation.final_max_m < cfg.completion_tol_m


def test_no_separation_violation_and_obstacle_clearance(run):
    cfg, m, _ = run
    assert m.separation.pairs_below_safety_distance == 0
    assert m.separation.min_pair_distance_m >= cfg.safety.separation_m
    assert m.obstacles.min_clearance_m >= cfg.safety.obstacle_margin_m


def test_obstacle_actually_deflected_someone(run):
    """The obstacle lies across the path: without repulsion a slot would pass inside it."""
    cfg, m, out = run
    log = np.load(out / "telemetry.npz")
    c = np.array(cfg.mission.obstacles[0].centre_ned_m)
    r = cfg.mission.obstacles[0].radius_m
    slot_gap = np.linalg.norm(log["slot_ned_m"] - c, axis=2) - r
    assert slot_gap.min() < 0, "test scenario no longer puts a slot path through the obstacle"
    assert m.obstacles.min_clearance_m > 0


def test_run_directory_contents(run):
    _, m, out = run
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk == m.to_json() and m.passed and m.checks
    log = np.load(out / "telemetry.npz")
    n = m.n_vehicles
    assert log["pos_ned_m"].shape[1:] == (n, 3) and log["att_q_wxyz"].shape[1:] == (n, 4)
    np.testing.assert_allclose(np.linalg.norm(log["att_q_wxyz"], axis=2), 1.0, atol=1e-5)
    for name in ("fig5_trajectories_3d", "fig6_attitude_recovery", "fig7_formation_assembly",
                 "fig8_formation_deviation", "fig9_avoidance", "fig10_snapshots"):
        p = out / f"{name}.png"
        assert p.stat().st_size > 10_000, name


def _fly(**changes):
    import dataclasses

    from sim_bridge.reports.metrics import compute_metrics
    from sim_bridge.runs.headless import run_scenario

    cfg = load_scenario(ROOT / "configs" / "small_6.yaml")
    for key, value in changes.items():
        cfg = dataclasses.replace(cfg, **{key: value})
    return compute_metrics(run_scenario(cfg, progress=False), None)


def test_lossy_delayed_link_still_converges_without_collision():
    """20 % of neighbour states lost, 100 ms delay plus up to 40 ms jitter (seeded)."""
    from sim_bridge.world.transport import LinkConfig

    m = _fly(link=LinkConfig(kind="lossy", loss=0.2, delay_s=0.1, jitter_s=0.04))
    assert m.passed, m.checks
    link = m.link
    assert 0.75 < link.delivered_fraction < 0.85
    assert 0.1 <= link.age_at_delivery_s.p50 <= 0.16
    assert m.assembly.transit_start_spread_s == 0.0  # every vehicle holds the same t_go


def test_state_setpoints_fly_the_mission_as_well_as_acceleration_only(run):
    """Position and velocity that agree with the acceleration do not degrade the paper metrics
    (formation, separation); they do slow the completion: the autopilot's own velocity loop
    (PX4's, headless) then runs, its D term damps the agent's acceleration, and what its
    integrator kept from the throw recovery acts as a bias that only the agent's own integral
    action removes, while an acceleration-only setpoint passes the velocity loop by."""
    import dataclasses

    cfg, m_state, _ = run
    assert cfg.mission.setpoint.kind == "state"
    mission = dataclasses.replace(cfg.mission, setpoint=dataclasses.replace(cfg.mission.setpoint, kind="acceleration"))
    m_acc = _fly(mission=mission)
    assert m_acc.passed
    dev_s, dev_a = m_state.formation_deviation, m_acc.formation_deviation
    assert dev_s.final_max_m < cfg.completion_tol_m
    assert dev_s.max_during_transit_m <= 1.25 * dev_a.max_during_transit_m + 0.05
    assert m_state.separation.min_pair_distance_m >= 0.9 * m_acc.separation.min_pair_distance_m
    assert m_state.mission.completion_time_s <= 1.6 * m_acc.mission.completion_time_s  # (72.9 s against 49.0 s)
