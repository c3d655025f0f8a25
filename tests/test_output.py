"""The one output stage (companion/output.py): extrapolation, feed-forward bound, limits,
geofence, attitude law, hover-thrust estimate; the same lines onboard and headless."""
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion.control.geometric import pack_control_params
from companion.link.dialects import dialect_named
from companion.link.limits import SetpointLimits
from companion.mission import GeofenceConfig, HoverThrustConfig
from companion.output import (
    SEND_ATTITUDE,
    SEND_NOTHING,
    SEND_TRAJECTORY,
    HoverThrustEstimator,
    OutputStage,
)
from companion.params import GRAVITY_MPS2, GeometricGains, VehicleParams
from companion.state import FleetSetpoint
from sim_bridge.scenario import load_scenario
from sim_bridge.world.jit import output_kernels

ROOT = Path(__file__).resolve().parents[1]
LIM = SetpointLimits()


def _plan(n, p=None, v=None, a=None, yaw=0.0):
    sp = FleetSetpoint.empty(n)
    for field, val in (("pos_ned_m", p), ("vel_ned_mps", v), ("acc_ned_mps2", a)):
        if val is not None:
            getattr(sp, field)[:] = val
    sp.yaw_rad[:] = yaw
    return sp


def test_a_state_plan_is_advanced_along_its_acceleration_between_plans():
    st = OutputStage(1, limits=LIM, acc_ff_max_mps2=3.0)
    st.set_plan(10.0, _plan(1, [1.0, 2.0, -5.0], [1.0, 0.0, -0.5], [0.4, -0.2, 0.1]), np.ones(1, bool))
    o = st.step(10.5, np.zeros((1, 3)), np.zeros((1, 3)), np.full((1, 4), np.nan))
    dt = 0.5
    assert o.send[0] == SEND_TRAJECTORY
    np.testing.assert_allclose(o.pos_ned_m[0], [1 + dt + 0.5 * 0.4 * dt * dt, 2 - 0.5 * 0.2 * dt * dt,
                                                -5 - 0.5 * dt + 0.5 * 0.1 * dt * dt], rtol=1e-15)
    np.testing.assert_allclose(o.vel_ned_mps[0], [1 + 0.4 * dt, -0.2 * dt, -0.5 + 0.1 * dt], rtol=1e-15)
    np.testing.assert_array_equal(o.acc_ned_mps2[0], [0.4, -0.2, 0.1])


def test_fixed_and_empty_plans_are_sent_as_they_are_or_not_at_all():
    st = OutputStage(2, limits=LIM, acc_ff_max_mps2=3.0)
    sp = _plan(2)
    sp.vel_ned_mps[0] = [0.0, 0.0, 0.7]  # a descent: velocity only
    st.set_plan(0.0, sp, np.ones(2, bool))
    o = st.step(3.0, np.zeros((2, 3)), np.zeros((2, 3)), np.full((2, 4), np.nan))
    assert o.send.tolist() == [SEND_TRAJECTORY, SEND_NOTHING]
    np.testing.assert_array_equal(o.vel_ned_mps[0], [0.0, 0.0, 0.7])
    assert np.isnan(o.pos_ned_m[0]).all() and np.isnan(o.acc_ned_mps2[0]).all()
    assert np.isnan(o.pos_ned_m[1]).all() and np.isnan(o.vel_ned_mps[1]).all()


def test_feed_forward_bound_and_px4_velocity_limits():
    """|a| <= acc_ff_max (its direction kept); horizontal speed <= MPC_XY_VEL_MAX, climb <=
    MPC_Z_VEL_MAX_UP, descent <= MPC_Z_VEL_MAX_DN."""
    st = OutputStage(2, limits=LIM, acc_ff_max_mps2=2.0)
    sp = _plan(2, [0.0, 0.0, -10.0], [[9.0, 12.0, -5.0], [0.0, 0.0, 4.0]], [[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]])
    st.set_plan(0.0, sp, np.ones(2, bool))
    o = st.step(0.0, np.zeros((2, 3)), np.zeros((2, 3)), np.full((2, 4), np.nan))
    np.testing.assert_allclose(o.acc_ned_mps2[0], [1.2, 1.6, 0.0])
    np.testing.assert_allclose(o.vel_ned_mps[0], [7.2, 9.6, -3.0])
    np.testing.assert_allclose(o.vel_ned_mps[1], [0.0, 0.0, 1.5])
    np.testing.assert_array_equal(o.acc_ned_mps2[1], [0.0, 0.0, 1.0])


def test_a_row_in_hover_gets_the_tighter_feed_forward_bound_and_nan_falls_back():
    """AgentOutput.acc_ff_max_mps2 per row (settled at station: setpoint.acc_ff_hover_mps2):
    the bound is applied to the plan, never looser than the stage's; after the slot-hold drive
    only the stage's (the pull taken out cancels the P loops' and moves nothing)."""
    st = OutputStage(3, limits=LIM, acc_ff_max_mps2=3.0)
    sp = _plan(3, [0.0, 0.0, -10.0], [0.0, 0.0, 0.0], [[0.0, 2.0, 0.0]] * 3)
    st.set_plan(0.0, sp, np.ones(3, bool), acc_ff_max_mps2=np.array([1.0, np.nan, 5.0]))
    o = st.step(0.0, np.zeros((3, 3)), np.zeros((3, 3)), np.full((3, 4), np.nan))
    np.testing.assert_allclose(o.acc_ned_mps2, [[0.0, 1.0, 0.0], [0.0, 2.0, 0.0], [0.0, 2.0, 0.0]])
    big = _plan(3, [0.0, 0.0, -10.0], [0.0, 0.0, 0.0], [[4.0, 0.0, 0.0]] * 3)
    st.set_plan(1.0, big, np.ones(3, bool), acc_ff_max_mps2=np.array([1.0, np.nan, 5.0]))
    o = st.step(1.0, np.zeros((3, 3)), np.zeros((3, 3)), np.full((3, 4), np.nan))
    np.testing.assert_allclose(np.linalg.norm(o.acc_ned_mps2, axis=1), [1.0, 3.0, 3.0])
    # with a drive: the P loops' pull comes out of the feed-forward, bounded by the stage's bound
    st.stiffness[:] = 1.7
    st.set_plan(2.0, _plan(3, [0.0, 0.0, -10.0], [0.0, 0.0, 0.0], [[0.9, 0.0, 0.0]] * 3), np.ones(3, bool),
                np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]), acc_ff_max_mps2=np.ones(3))
    o = st.step(2.0, np.zeros((3, 3)), np.zeros((3, 3)), np.full((3, 4), np.nan))
    np.testing.assert_allclose(o.acc_ned_mps2[:, 0], [2.6, 2.6, 3.0])  # 0.9 + 1.7 d: 2.6; 4.3 bounded to 3
    np.testing.assert_allclose(o.pos_ned_m[:, 0], [-1.0, -1.0, -2.0])


def test_the_tighter_bound_leaves_out_the_bias_the_agent_has_learnt():
    """A settled row's bound is on its acceleration less the learnt bias (AgentOutput.
    acc_bias_ned_mps2): the bias part moves nothing, so it is sent whole; what would move
    the vehicle is bounded; the stage's bound still caps the sum; a row at the stage's bound
    is bounded as before, its bias ignored; a bias not finite counts as 0."""
    st = OutputStage(5, limits=LIM, acc_ff_max_mps2=3.0)
    a = [[0.8, 0.0, 0.0], [0.7, 1.0, 0.0], [0.8, 0.0, 0.0], [3.0, 2.0, 0.0], [-2.5, 0.0, 0.0]]
    bias = [[0.7, 0.0, 0.0], [0.7, 0.0, 0.0], [np.nan, 0.0, 0.0], [3.0, 0.0, 0.0], [1.5, 0.0, 0.0]]
    st.set_plan(0.0, _plan(5, [0.0, 0.0, -10.0], [0.0, 0.0, 0.0], a), np.ones(5, bool),
                acc_ff_max_mps2=np.array([0.5, 0.5, 0.5, 0.5, 3.0]), acc_bias_ned_mps2=np.array(bias))
    o = st.step(0.0, np.zeros((5, 3)), np.zeros((5, 3)), np.full((5, 4), np.nan))
    capped = np.array([3.0, 0.5, 0.0]) * 3.0 / math.hypot(3.0, 0.5)  # 3.04 over the stage's bound
    np.testing.assert_allclose(o.acc_ned_mps2, [[0.8, 0.0, 0.0], [0.7, 0.5, 0.0], [0.5, 0.0, 0.0], capped,
                                                [-2.5, 0.0, 0.0]], atol=1e-12)


def test_geofence_clips_the_position_and_stops_outward_motion_at_a_face():
    st = OutputStage(1, limits=LIM, acc_ff_max_mps2=3.0, geofence=((-10.0, -10.0, -20.0), (10.0, 10.0, 0.0)))
    st.set_plan(0.0, _plan(1, [30.0, 0.0, -5.0], [3.0, -1.0, 0.0], [1.0, 0.0, 0.0]), np.ones(1, bool))
    o = st.step(0.0, np.array([[10.5, 0.0, -5.0]]), np.zeros((1, 3)), np.full((1, 4), np.nan))
    np.testing.assert_array_equal(o.pos_ned_m[0], [10.0, 0.0, -5.0])
    np.testing.assert_array_equal(o.vel_ned_mps[0], [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(o.acc_ned_mps2[0], [0.0, 0.0, 0.0])


def _geometric():
    vp = VehicleParams()
    return vp, pack_control_params(vp, GeometricGains())


def test_attitude_law_at_hover_asks_for_the_weight_level_with_the_heading():
    vp, prm = _geometric()
    px4 = dialect_named("px4")
    st = OutputStage(1, limits=LIM, acc_ff_max_mps2=3.0, attitude=True, ctrl_prm=prm,
                     thrust_field=px4.thrust_field, hover_thrust=np.array([0.4]))
    yaw = 0.7
    st.set_plan(0.0, _plan(1, [0.0, 0.0, -10.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], yaw=yaw), np.ones(1, bool))
    q_level = np.array([[math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]])
    o = st.step(0.0, np.array([[0.0, 0.0, -10.0]]), np.zeros((1, 3)), q_level)
    assert o.send[0] == SEND_ATTITUDE
    assert o.thrust_over_weight[0] == pytest.approx(1.0, abs=1e-12)
    assert o.thrust_field[0] == pytest.approx(0.4, abs=1e-12)  # PX4: T/W times the hover thrust
    np.testing.assert_allclose(np.abs(o.att_q_wxyz[0]), np.abs(q_level[0]), atol=1e-12)
    # No attitude known: nothing to fly the law on, so the trajectory setpoint goes instead.
    o = st.step(0.0, np.array([[0.0, 0.0, -10.0]]), np.zeros((1, 3)), np.full((1, 4), np.nan))
    assert o.send[0] == SEND_TRAJECTORY


def test_attitude_law_tilt_is_clamped_to_the_autopilot_limit():
    vp, prm = _geometric()
    lim = dataclasses.replace(LIM, tilt_max_rad=math.radians(20.0))
    st = OutputStage(1, limits=lim, acc_ff_max_mps2=8.0, attitude=True, ctrl_prm=prm,
                     thrust_field=dialect_named("px4").thrust_field, hover_thrust=np.array([0.4]))
    st.set_plan(0.0, _plan(1, [50.0, 0.0, -10.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), np.ones(1, bool))
    o = st.step(0.0, np.array([[0.0, 0.0, -10.0]]), np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]]))
    w, x, y, z = o.att_q_wxyz[0]
    assert math.degrees(math.acos(1 - 2 * (x * x + y * y))) == pytest.approx(20.0, abs=1e-9)
    assert y < 0 and abs(x) < 1e-9  # pitched nose down (negative pitch), towards north


def test_interpreted_and_compiled_stage_agree():
    """The companion's rows (interpreted) and the simulator's (compiled) are one source."""
    rng = np.random.default_rng(5)
    n = 64
    vp, prm = _geometric()
    kw = dict(limits=LIM, acc_ff_max_mps2=2.5, geofence=((-20.0, -20.0, -30.0), (20.0, 20.0, 0.0)), attitude=True,
              ctrl_prm=prm, thrust_field=dialect_named("ardupilot").thrust_field, hover_thrust=np.full(n, 0.35))
    a, b = OutputStage(n, **kw), OutputStage(n, **kw, kernels=output_kernels())
    sp = _plan(n, rng.normal(0, 15, (n, 3)), rng.normal(0, 6, (n, 3)), rng.normal(0, 3, (n, 3)))
    sp.pos_ned_m[::7] = np.nan  # some fixed rows
    sp.vel_ned_mps[::11] = np.nan  # and some empty ones
    q = rng.normal(size=(n, 4)) * [3, 0.2, 0.2, 1]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    own_p, own_v = rng.normal(0, 15, (n, 3)), rng.normal(0, 2, (n, 3))
    for st in (a, b):
        st.set_plan(1.0, sp, np.ones(n, bool))
    oa, ob = a.step(1.3, own_p, own_v, q), b.step(1.3, own_p, own_v, q)
    for f in ("send", "pos_ned_m", "vel_ned_mps", "acc_ned_mps2", "att_q_wxyz", "thrust_field",
              "thrust_over_weight"):
        np.testing.assert_allclose(getattr(oa, f), getattr(ob, f), rtol=1e-13, atol=1e-13, err_msg=f)
    assert (oa.send == SEND_ATTITUDE).sum() > n // 2


def _hover_flight(h_true, h_param, t_end=30.0, dt=0.02, cfg=None, noise_mps=0.0):
    """A vertical 1-D vehicle held at z = -10 m by a PD law through the estimator: it is sent
    the thrust field (T/W) h_est (PX4's meaning) and produces (T/W) h_est / h_true of its weight.
    Returns (estimate, height error at the end, m)."""
    rng = np.random.default_rng(1)
    est = HoverThrustEstimator(np.array([h_param]), cfg)
    z, vz = -10.0, 0.0
    for k in range(int(round(t_end / dt))):
        t = k * dt
        vz_meas = vz + rng.normal(0.0, noise_mps) if noise_mps else vz
        tw = 1.0 - (-1.0 * (z + 10.0) - 1.8 * vz_meas) / GRAVITY_MPS2  # T/W for a = -kx e - kv v (down +)
        est.update(t, np.array([0]), np.array([vz_meas]), np.array([tw]), np.array([1.0]))
        a = GRAVITY_MPS2 * (1.0 - tw * est.estimate[0] / h_true)
        z, vz = z + vz * dt + 0.5 * a * dt * dt, vz + a * dt
    return est.estimate[0], z + 10.0


def test_hover_thrust_estimate_learns_arducopters_7_percent():
    """ArduPilot 4.6 SITL: MOT_THST_HOVER 0.390, hovering at 0.364 (mavlink-facts.md). With the
    parameter alone the PD loop sits g (1 - h/h_true) / kx = 0.70 m off; the estimate learns the
    truth and takes the height error to zero."""
    h, err = _hover_flight(0.364, 0.390, t_end=0.02)
    h, err = _hover_flight(0.364, 0.390)
    assert h == pytest.approx(0.364, rel=2e-3)
    assert abs(err) < 0.01
    h, _ = _hover_flight(0.364, 0.390, noise_mps=0.05, t_end=60.0)  # EKF-like velocity noise
    assert h == pytest.approx(0.364, rel=0.02)


def test_hover_thrust_estimate_stays_within_its_bound():
    h, _ = _hover_flight(0.25, 0.39)  # 36 % off: beyond the +-20 % the estimate may move
    assert h == pytest.approx(0.39 * 0.8)
    h, _ = _hover_flight(0.40, 0.40, cfg=HoverThrustConfig(bound_frac=0.05))
    assert h == pytest.approx(0.40, rel=1e-6)


def test_headless_honours_the_mission_geofence(tmp_path):
    """simulate flies the output stage the agent flies: a fence that cuts the path keeps the
    vehicles inside it (before the shared output stage, headless runs flew through)."""
    from sim_bridge.runs.headless import run_scenario

    cfg = load_scenario(ROOT / "configs" / "small_6.yaml")
    fence = GeofenceConfig(min_ned_m=(-50.0, -50.0, -40.0), max_ned_m=(45.0, 50.0, 1.0))
    cfg = dataclasses.replace(cfg, duration_s=60.0, mission=dataclasses.replace(cfg.mission, geofence=fence))
    res = run_scenario(cfg, progress=False)
    north = res.log["pos_ned_m"][..., 0]
    # Slots reach 70 m north; the fence face is at 45 m. The fence stops outward setpoints once
    # a vehicle is at the face, so it overshoots by its braking (3 m/s transit: ~1 m).
    assert np.nanmax(north) < 45.0 + 1.5
    assert np.nanmax(north) > 40.0  # and they did fly up to it
