"""Rigid-body dynamics (eq. 1-6): equilibrium, mixer, saturation, conservation, SO(3), ground, wind."""
import numpy as np
import pytest

from companion.control.geometric import max_thrust_n
from companion.frames import euler_zyx_to_rot, yaw_rad
from companion.params import GRAVITY_MPS2, InnerLoopConfig, VehicleParams
from companion.state import FleetSetpoint, FleetState
from sim_bridge.world.dynamics import allocate_np, inverse_mixer_np, mixer_np, step_open_loop
from sim_bridge.world.physics import Physics, WindConfig, hover_rotor_speed_radps, hover_state

VP = VehicleParams()


def test_hover_equilibrium_open_loop():
    q_h = hover_rotor_speed_radps(VP)
    f, m = mixer_np(np.full((1, 4), q_h), VP)
    assert np.isclose(f[0], VP.mass_kg * GRAVITY_MPS2, rtol=1e-12)
    np.testing.assert_allclose(m, 0.0, atol=1e-15)
    st = hover_state(3, VP, pos_ned_m=[[0, 0, -5], [1, 2, -3], [0, 0, -1]])
    pos0 = st.pos_ned_m.copy()
    step_open_loop(st, np.full((3, 4), q_h), VP, 1e-3, n_steps=1000)
    np.testing.assert_allclose(st.pos_ned_m, pos0, atol=1e-10)
    np.testing.assert_allclose(st.vel_ned_mps, 0.0, atol=1e-10)
    np.testing.assert_allclose(st.rot_body_to_ned, np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-12)


def test_mixer_geometry_signs_plus_frame_is_eq6():
    """Plus frame: front rotor (1) harder -> nose up (+M2); right rotor (2) harder -> left wing down (-M1)."""
    vp = VehicleParams(frame="plus")
    q = np.full((2, 4), 1500.0)
    q[0, 0] += 100
    q[1, 1] += 100
    _, m = mixer_np(q, vp)
    assert m[0, 1] > 0 and abs(m[0, 0]) < 1e-15 and m[0, 2] < 0
    assert m[1, 0] < 0 and abs(m[1, 1]) < 1e-15 and m[1, 2] > 0
    d, c = vp.arm_length_m, vp.torque_to_thrust_m  # eq. 6's matrix, verbatim
    a = np.array([[1, 1, 1, 1], [0, -d, 0, d], [d, 0, -d, 0], [-c, c, -c, c]])
    t = vp.thrust_coeff_n_per_radps2 * q ** 2
    f, m = mixer_np(q, vp)
    np.testing.assert_allclose(np.column_stack([f, m]), t @ a.T, rtol=1e-12)


def test_mixer_geometry_signs_x_frame():
    """X frame: front-right rotor (1) harder -> nose up and left wing down; rotors 1, 3 clockwise."""
    q = np.full((1, 4), 1500.0)
    q[0, 0] += 100
    _, m = mixer_np(q, VP)
    assert VP.frame == "x" and m[0, 1] > 0 and m[0, 0] < 0 and np.isclose(-m[0, 0], m[0, 1]) and m[0, 2] < 0


def test_x_frame_has_sqrt2_more_roll_and_pitch_authority_than_plus():
    """At saturation (two rotors full, two off) the X frame rolls with 2 d/sqrt(2) T_max, the plus
    frame with d T_max: the real Crazyflie has sqrt(2) times the plus model's authority."""
    qmax = VP.rotor_speed_max_radps
    _, m_x = mixer_np(np.array([[0.0, 0.0, qmax, qmax]]), VP)           # left pair full: roll right
    _, m_p = mixer_np(np.array([[0.0, 0.0, 0.0, qmax]]), VehicleParams(frame="plus"))
    t_max = VP.thrust_coeff_n_per_radps2 * qmax ** 2
    assert np.isclose(m_x[0, 0], np.sqrt(2.0) * VP.arm_length_m * t_max)
    assert np.isclose(m_x[0, 0] / m_p[0, 0], np.sqrt(2.0))


@pytest.mark.parametrize("frame", ["x", "plus"])
def test_mixer_inverse_round_trip(frame):
    vp = VehicleParams(frame=frame)
    rng = np.random.default_rng(3)
    q = rng.uniform(800, 2400, size=(100, 4))
    f, m = mixer_np(q, vp)
    t = inverse_mixer_np(f, m, vp)
    np.testing.assert_allclose(np.sqrt(t / vp.thrust_coeff_n_per_radps2), q, rtol=1e-10)
    # the saturating allocator is the exact inverse whenever the wrench is feasible
    np.testing.assert_allclose(allocate_np(f, m, vp), q, rtol=1e-9)


def test_rotor_saturation_limits_thrust():
    fmax = max_thrust_n(VP)
    q = allocate_np(np.array([10.0 * fmax, 0.3]), np.array([[0.0, 0.0, 0.0], [0.05, -0.05, 0.02]]), VP)
    assert np.all(q <= VP.rotor_speed_max_radps + 1e-9) and np.all(q >= VP.rotor_speed_min_radps)
    f, m = mixer_np(q, VP)
    assert f[0] <= fmax * (1 + 1e-12)
    # infeasible moment: direction of the roll/pitch moment is kept (scaled), not distorted
    assert np.sign(m[1, 0]) == 1 and np.sign(m[1, 1]) == -1
    assert np.isclose(m[1, 0] / m[1, 1], -1.0, rtol=1e-9)
    # open loop: a command far above Q_max climbs at most with (f_max/m - g)
    st = hover_state(1, VP)
    step_open_loop(st, np.full((1, 4), 1e5), VP, 1e-3, n_steps=500)
    assert np.all(st.rotor_speed_radps <= VP.rotor_speed_max_radps)
    a_up_max = fmax / VP.mass_kg - GRAVITY_MPS2
    assert -st.vel_ned_mps[0, 2] <= a_up_max * 0.5 + 1e-9


def test_motor_lag_exact_exponential():
    st = FleetState.zeros(1)
    n = round(VP.motor_time_constant_s / 1e-3)  # one time constant of 1 ms steps
    step_open_loop(st, np.full((1, 4), 2000.0), VP, 1e-3, n_steps=n)
    np.testing.assert_allclose(st.rotor_speed_radps, 2000.0 * (1 - np.exp(-n * 1e-3 / VP.motor_time_constant_s)), rtol=1e-12)


def _spin_state(omega):
    st = FleetState.zeros(1)
    st.omega_body_radps[0] = omega
    return st


def test_torque_free_rotation_conserves_momentum_and_energy():
    vp = VehicleParams(inertia_xx_kgm2=1.0e-5, inertia_yy_kgm2=2.0e-5, inertia_zz_kgm2=3.0e-5)
    j = np.diag([1.0e-5, 2.0e-5, 3.0e-5])
    st = _spin_state([3.0, 20.0, 1.0])  # near the unstable intermediate axis: tumbles
    l0 = j @ st.omega_body_radps[0]
    e0 = 0.5 * st.omega_body_radps[0] @ l0
    for _ in range(10):  # 10 s total, check along the way
        step_open_loop(st, np.zeros((1, 4)), vp, 1e-3, n_steps=1000)  # rotors off: M = 0
        r, w = st.rot_body_to_ned[0], st.omega_body_radps[0]
        l_world = r @ j @ w
        assert np.linalg.norm(l_world - l0) / np.linalg.norm(l0) < 5e-9  # O(h^4): 1.7e-9 measured
        assert abs(np.linalg.norm(l_world) - np.linalg.norm(l0)) / np.linalg.norm(l0) < 5e-10
        assert abs(0.5 * w @ j @ w - e0) / e0 < 1e-9
    assert np.abs(st.omega_body_radps[0, 1] - 20.0) > 1.0  # it really tumbled


def test_rotation_stays_orthonormal_1e5_steps():
    st = _spin_state([15.0, -9.0, 30.0])
    step_open_loop(st, np.zeros((1, 4)), VP, 1e-3, n_steps=100_000)
    r = st.rot_body_to_ned[0]
    assert np.abs(r.T @ r - np.eye(3)).max() < 1e-9
    assert abs(np.linalg.det(r) - 1.0) < 1e-9


def test_ground_contact_rests_levelled_to_yaw():
    st = FleetState.zeros(1)
    st.pos_ned_m[0] = [0.0, 0.0, -1.0]
    st.rot_body_to_ned[0] = euler_zyx_to_rot(0.3, -0.2, 0.7)
    st.omega_body_radps[0] = [1.0, 2.0, 0.5]
    step_open_loop(st, np.zeros((1, 4)), VP, 1e-3, n_steps=1000, ground_z_m=0.0)
    assert st.pos_ned_m[0, 2] == 0.0
    np.testing.assert_array_equal(st.vel_ned_mps[0], 0.0)
    np.testing.assert_array_equal(st.omega_body_radps[0], 0.0)
    assert np.isclose(st.rot_body_to_ned[0, 2, 2], 1.0)
    # a hovering vehicle on the ground can take off again
    step_open_loop(st, np.full((1, 4), 2300.0), VP, 1e-3, n_steps=300, ground_z_m=0.0)
    assert st.pos_ned_m[0, 2] < -0.05


def test_drag_and_steady_wind_and_reproducible_gusts():
    vp = VehicleParams(drag_coeff_n_per_mps=0.01)
    q_h = hover_rotor_speed_radps(vp)
    st = hover_state(1, vp)
    step_open_loop(st, np.full((1, 4), q_h), vp, 1e-3, n_steps=40000, wind_ned_mps=(2.0, -1.0, 0.0))
    np.testing.assert_allclose(st.vel_ned_mps[0], [2.0, -1.0, 0.0], atol=1e-3)  # tau = m/c = 3 s, 40 s run

    def run(seed):
        ph = Physics(vp, InnerLoopConfig(), wind=WindConfig(steady_ned_mps=(1.0, 0, 0), gust_std_mps=1.0,
                                                             gust_tau_s=0.5), rng=np.random.default_rng(seed))
        s = hover_state(2, vp)
        sp = FleetSetpoint.empty(2)
        sp.pos_ned_m[:] = 0.0
        ph.step(s, sp, n_steps=2000)
        return s.pos_ned_m.copy()

    a, b, c = run(7), run(7), run(8)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-6
    np.testing.assert_allclose(a[0], a[1])  # one wind field per fleet


def test_physics_active_mask_and_errors():
    ph = Physics(VP, InnerLoopConfig())
    st = hover_state(3, VP)
    st.vel_ned_mps[:] = 1.0
    before = st.copy()
    sp = FleetSetpoint.empty(3)
    ph.step(st, sp, n_steps=10, active=np.array([True, False, True]))
    for name in before.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(st, name)[1], getattr(before, name)[1])
        assert not np.array_equal(getattr(st, "pos_ned_m")[0], before.pos_ned_m[0])
    with pytest.raises(ValueError):
        ph.step(st, FleetSetpoint.empty(2))
    with pytest.raises(ValueError):
        hover_rotor_speed_radps(VehicleParams(rotor_speed_max_radps=1000.0))
    assert np.isclose(yaw_rad(st.rot_body_to_ned[0]), 0.0)


def test_shared_wind_field_blows_the_same_on_every_group():
    """The SITL steps each parameter group's Physics on one WindField it advances per tick."""
    from sim_bridge.world.physics import WindField

    vp = VehicleParams(drag_coeff_n_per_mps=0.01)
    field = WindField(WindConfig(steady_ned_mps=(1.0, 0, 0), gust_std_mps=2.0, gust_tau_s=0.5), 1e-3,
                      np.random.default_rng(3))
    groups = [Physics(vp, InnerLoopConfig(controller=c), wind=field) for c in ("geometric", "geometric")]
    states = [hover_state(1, vp), hover_state(1, vp)]
    sp = FleetSetpoint.empty(1)
    sp.pos_ned_m[:] = 0.0
    for _ in range(50):
        field.advance(10)
        for ph, st in zip(groups, states):
            ph.step(st, sp, n_steps=10)
    np.testing.assert_array_equal(states[0].pos_ned_m, states[1].pos_ned_m)
    assert np.abs(states[0].pos_ned_m).max() > 1e-3  # the gusts did push
    with pytest.raises(ValueError, match="shared wind block"):
        groups[0].step(states[0], sp, n_steps=7)


@pytest.mark.parametrize("where", ["scenario", "sitl"])
def test_wind_without_drag_is_a_config_error(where):
    from companion.config import ConfigError, validate
    from sim_bridge.scenario import ScenarioConfig
    from sim_bridge.sitl.config import SitlConfig

    wind = {"steady_ned_mps": [3.0, 0.0, 0.0]}
    # the SITL reads the scenario schema for its world: one validator for both
    data: dict = {"physics": {"wind": wind}}
    ok: dict = dict(data, vehicle={"drag_coeff_n_per_mps": 0.0065})
    cls: type = ScenarioConfig
    if where == "sitl":
        data, ok, cls = {"scenario": data}, {"scenario": ok}, SitlConfig
    with pytest.raises(ConfigError, match="drag_coeff_n_per_mps is 0"):
        validate(cls, data, "cfg.yaml")
    validate(cls, ok, "cfg.yaml")
