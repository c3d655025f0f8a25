"""GPS/estimator errors and latency on what the agent sees (headless and SITL alike)."""
import numpy as np
import pytest

from sim_bridge.world.estimator import Estimator, EstimatorConfig


def _truth(n, t):
    pos = np.zeros((n, 3))
    pos[:, 0] = t  # 1 m/s north: the value at time t is t
    return pos, np.zeros((n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)).copy()


def test_inactive_estimator_reports_the_truth_as_copies():
    est = Estimator(EstimatorConfig(), 3, np.random.default_rng(0))
    p, v, r = _truth(3, 1.0)
    po, vo, ro = est.observe(1.0, p, v, r)
    np.testing.assert_array_equal(po, p)
    assert po is not p and ro is not r


def test_latency_reports_the_state_of_latency_ago():
    est = Estimator(EstimatorConfig(latency_s=0.1), 2, np.random.default_rng(0))
    for k in range(100):
        t = k * 0.02
        po, _, _ = est.observe(t, *_truth(2, t))
    assert po[0, 0] == pytest.approx(t - 0.1)


def test_position_error_is_gauss_markov_with_the_configured_std_and_correlation():
    cfg = EstimatorConfig(pos_noise_std_m=0.5, pos_noise_std_vertical_m=1.0, pos_noise_tau_s=2.0)
    n, dt = 2000, 0.1
    est = Estimator(cfg, n, np.random.default_rng(1))
    errs = []
    for k in range(40):
        po, _, _ = est.observe(k * dt, *_truth(n, 0.0))
        errs.append(po.copy())
    e = np.array(errs)
    np.testing.assert_allclose(e[-1].std(axis=0), [0.5, 0.5, 1.0], rtol=0.06)
    lag = np.mean(e[-1, :, 0] * e[-11, :, 0]) / 0.25  # 1 s apart: exp(-1/2)
    assert lag == pytest.approx(np.exp(-0.5), abs=0.05)


def test_sitl_reports_the_estimate_not_the_truth():
    from companion.config import replace
    from sim_bridge.sitl.config import default_scenario, sitl_config
    from sim_bridge.sitl.server import SitlServer

    sc = replace(default_scenario(), estimator=EstimatorConfig(pos_noise_std_m=2.0, vel_noise_std_mps=0.5))
    s = SitlServer(sitl_config(4, scenario=sc))
    snap = s.telemetry.snapshot(1.0)
    d = snap.pos_ned_m - s.state.pos_ned_m
    assert np.abs(d[:, :2]).max() > 0.1 and np.abs(d[:, 2]).max() == 0.0
    assert np.abs(snap.vel_ned_mps - s.state.vel_ned_mps).max() > 0.05


def test_gps_error_does_not_walk_a_headless_formation_away():
    """The autopilot flies on its estimate: with a wandering 0.3 m GPS error the small scenario
    still completes within 1 m (before the setpoint shift, vehicles chased their own error
    and ended tens of metres from their slots). The calm and in-slot tests are loosened for
    the noise, as configs/paper_40_disturbed.yaml does: with the speed test at 0.2 m/s one
    vehicle took 57 s to pass it, and since a vehicle recovering no longer holds the start
    for more than go_stall_s, the formation left without it."""
    import dataclasses
    from pathlib import Path

    from sim_bridge.reports.metrics import compute_metrics
    from sim_bridge.runs.headless import run_scenario
    from sim_bridge.scenario import load_scenario

    cfg = load_scenario(Path(__file__).resolve().parents[1] / "configs" / "small_6.yaml")
    cfg = dataclasses.replace(cfg, completion_tol_m=1.0, estimator=EstimatorConfig(
        pos_noise_std_m=0.3, pos_noise_std_vertical_m=0.5, vel_noise_std_mps=0.05, latency_s=0.05))
    cfg = dataclasses.replace(cfg, mission=dataclasses.replace(cfg.mission, phases=dataclasses.replace(
        cfg.mission.phases, assembled_pos_m=2.0, assembled_speed_mps=1.0, stable_speed_mps=1.0)))
    m = compute_metrics(run_scenario(cfg, progress=False), None)
    assert m.mission.completed and m.formation_deviation.final_max_m < 1.0, m.checks
    assert m.separation.pairs_below_safety_distance == 0
