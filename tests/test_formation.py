"""Consensus formation law, eq. 23-28 (companion/control/formation.py)."""
import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.linalg import expm
from scipy.optimize import linear_sum_assignment

from companion.control import topology as T
from companion.control.formation import (
    KRON_MAX_N,
    ConsensusGains,
    FormationUnstableError,
    check_stability,
    closed_loop_matrix,
    consensus_accel,
    formation_reference,
    mode_eigenvalues,
)

CENTRE = np.array([100.0, 0.0, -10.0])
EQ27 = ConsensusGains(ki_pos_per_s3=0.0)
"""The paper's law exactly (no integral action): what eq. 28's closed forms describe."""


def circle(n, radius_m=40.0):
    b = 2 * np.pi * np.arange(n) / n
    return np.stack([radius_m * np.cos(b), radius_m * np.sin(b), np.zeros(n)], axis=1)


def rk4(pos, vel, t_end, dt, accel):
    """Integrate eq. 23 (p' = v, v' = u) with classical RK4; accel(t, p, v) -> (N, 3)."""
    t = 0.0
    for _ in range(int(round(t_end / dt))):
        k1p, k1v = vel, accel(t, pos, vel)
        k2p, k2v = vel + 0.5 * dt * k1v, accel(t + 0.5 * dt, pos + 0.5 * dt * k1p, vel + 0.5 * dt * k1v)
        k3p, k3v = vel + 0.5 * dt * k2v, accel(t + 0.5 * dt, pos + 0.5 * dt * k2p, vel + 0.5 * dt * k2v)
        k4p, k4v = vel + dt * k3v, accel(t + dt, pos + dt * k3p, vel + dt * k3v)
        pos = pos + dt / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
        vel = vel + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        t += dt
    return pos, vel


def fixed_law(W, gains, offsets, centre=CENTRE):
    h = formation_reference(offsets, centre, np.zeros(3), np.zeros(3))
    return lambda t, p, v: consensus_accel(p, v, *h, W, gains)


# --- gains -----------------------------------------------------------------------


def test_gain_matrices_and_validation():
    g = ConsensusGains()
    assert g.k2.shape == (3, 6)
    np.testing.assert_array_equal(g.k2, np.hstack([-0.6 * np.eye(3), -1.6 * np.eye(3)]))
    np.testing.assert_array_equal(g.k1, np.zeros((3, 6)))
    with pytest.raises(ValidationError):
        ConsensusGains(k2_pos=1.0)  # extra fields forbidden
    with pytest.raises(ValidationError):
        ConsensusGains(k3_vel_per_s=float("nan"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.k2_pos_per_s2 = 1.0


def test_formation_reference():
    r = circle(5)
    hp, hv, ha = formation_reference(r, CENTRE, [1.0, 2, 3], [0.1, 0, 0])
    np.testing.assert_allclose(hp, r + CENTRE)
    np.testing.assert_allclose(hv, np.tile([1.0, 2, 3], (5, 1)))
    np.testing.assert_allclose(ha, np.tile([0.1, 0, 0], (5, 1)))
    hv[0, 0] = 7.0  # writable, not a broadcast view
    with pytest.raises(ValueError):
        formation_reference(r, [0, 0], [0, 0, 0], [0, 0, 0])


# --- the law itself --------------------------------------------------------------


def test_zero_command_in_formation():
    n = 12
    r = circle(n)
    h = formation_reference(r, CENTRE, np.zeros(3), np.zeros(3))
    u = consensus_accel(h[0], h[1], *h, T.chain(n), ConsensusGains())
    np.testing.assert_allclose(u, 0.0, atol=1e-12)


def test_one_vehicle_with_only_neighbours_equals_batch_row():
    rng = np.random.default_rng(7)
    n = 15
    r = circle(n)
    W = T.k_nearest(r, 2, weight=0.7, symmetric=False)
    W[3, 9] = 1.3  # an extra long link
    g = ConsensusGains(k1_pos_per_s2=0.01, k1_vel_per_s=-0.02)
    pos = r + CENTRE + rng.normal(size=(n, 3))
    vel = rng.normal(size=(n, 3))
    h = formation_reference(r, CENTRE, [0.5, 0, 0], [0.1, 0.2, 0])
    batch = consensus_accel(pos, vel, *h, W, g)
    for i in range(n):
        known = np.r_[i, T.neighbours(W, i)]
        p_i = np.full_like(pos, np.nan)
        v_i = np.full_like(vel, np.nan)
        p_i[known], v_i[known] = pos[known], vel[known]
        u_i = consensus_accel(p_i, v_i, *h, W, g, rows=np.array([i]))
        assert u_i.shape == (1, 3)
        np.testing.assert_allclose(u_i[0], batch[i], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(consensus_accel(pos, vel, *h, W, g, rows=np.array([9, 3])), batch[[9, 3]])


def test_missing_neighbour_state_is_an_error():
    n = 5
    r = circle(n)
    h = formation_reference(r, CENTRE, np.zeros(3), np.zeros(3))
    pos = h[0].copy()
    pos[2] = np.nan
    with pytest.raises(ValueError, match=r"vehicle\(s\) \[2\]"):
        consensus_accel(pos, h[1], *h, T.chain(n), ConsensusGains(), rows=np.array([3]))
    consensus_accel(pos, h[1], *h, T.chain(n), ConsensusGains(), rows=np.array([4]))  # 2 unread: fine


@pytest.mark.parametrize("topo", ["chain", "ring"])
def test_rk4_of_the_law_matches_matrix_exponential_of_eq28(topo):
    """Integrating eq. 23 under consensus_accel reproduces the closed-form solution
    of eq. 28, x(t) = exp(M t) x0 + forcing, including its (L kron BK3 - I kron BK2) h
    term; nonzero K1 exercises the full equation."""
    rng = np.random.default_rng(11)
    n = 6
    W = getattr(T, topo)(n)
    g = ConsensusGains(k1_pos_per_s2=-0.05, k1_vel_per_s=-0.1, ki_pos_per_s3=0.0)
    r = circle(n, 10.0)
    h = formation_reference(r, CENTRE, np.zeros(3), np.zeros(3))
    pos0 = h[0] + rng.uniform(-3, 3, (n, 3))
    vel0 = rng.uniform(-1, 1, (n, 3))
    t_end = 8.0
    pos, vel = rk4(pos0, vel0, t_end, 0.01, fixed_law(W, g, r))

    M = closed_loop_matrix(W, g)
    L = T.laplacian(W)
    B = np.vstack([np.zeros((3, 3)), np.eye(3)])
    hx = np.hstack([h[0], h[1]]).ravel()
    f = (np.kron(L, B @ g.k3) - np.kron(np.eye(n), B @ g.k2)) @ hx
    aug = np.zeros((6 * n + 1, 6 * n + 1))
    aug[:-1, :-1], aug[:-1, -1] = M, f
    x = (expm(aug * t_end) @ np.r_[np.hstack([pos0, vel0]).ravel(), 1.0])[:-1].reshape(n, 6)
    np.testing.assert_allclose(pos, x[:, :3], atol=1e-7)
    np.testing.assert_allclose(vel, x[:, 3:], atol=1e-7)


def test_chain40_converges_within_time_bound_from_slowest_eigenvalue():
    """Paper set-up: 40-vehicle chain, 40 m circle. Bound: with sigma = slowest decay
    rate (-max Re of eq. 28's eigenvalues) and any sigma' < sigma,
    |e(t)| <= C e^{-sigma' t} |e(0)|, C = sup_t |exp((M + sigma' I) t)|_2 (finite
    because M + sigma' I is Hurwitz; it absorbs the chain's Jordan-block
    polynomial growth). So |e| < tol for t >= T = ln(C |e(0)| / tol) / sigma'."""
    n, tol = 40, 1e-3
    W, g = T.chain(n), EQ27
    sigma = -check_stability(W, g).real.max()
    np.testing.assert_allclose(sigma, (2.2 - np.sqrt(2.2**2 - 3.6)) / 2, rtol=1e-12)  # follower pole
    M = closed_loop_matrix(W, g)
    axis = np.r_[6 * np.arange(n), 6 * np.arange(n) + 3]  # north p and v; axes are decoupled
    Mx = M[np.ix_(axis, axis)]
    sigma_p = sigma / 2
    step = expm((Mx + sigma_p * np.eye(2 * n)) * 0.5)
    X, C = np.eye(2 * n), 1.0
    for _ in range(240):  # 120 s; the norm has long peaked by then
        X = step @ X
        C = max(C, np.linalg.norm(X, 2))

    rng = np.random.default_rng(5)
    r = circle(n)
    pos0 = r + CENTRE + rng.uniform(-5, 5, (n, 3))
    e0 = np.linalg.norm(pos0 - r - CENTRE)
    t_bound = np.log(C * e0 / tol) / sigma_p
    assert t_bound < 60.0  # "bounded": C is ~1.4 thanks to string stability
    pos, vel = rk4(pos0, np.zeros((n, 3)), np.ceil(t_bound), 0.05, fixed_law(W, g, r))
    assert np.linalg.norm(pos - r - CENTRE, axis=1).max() < tol
    assert np.abs(vel).max() < tol
    # ...and it stays converged (exact solution up to 3x the bound).
    x0 = np.hstack([pos0 - r - CENTRE, np.zeros((n, 3))]).ravel()
    for t in np.linspace(t_bound, 3 * t_bound, 7):
        assert np.linalg.norm((expm(M * t) @ x0).reshape(n, 6)[:, :3], axis=1).max() < tol


def _moving(n, c_acc, feedforward):
    rng = np.random.default_rng(2)
    W, g = T.ring(n), ConsensusGains()
    r = circle(n, 10.0)
    v0 = np.array([3.0, -1.0, 0.5])

    def centre(t):
        return CENTRE + v0 * t + 0.5 * c_acc * t**2, v0 + c_acc * t, c_acc

    def law(t, p, v):
        hp, hv, ha = formation_reference(r, *centre(t))
        return consensus_accel(p, v, hp, hv, ha if feedforward else 0 * ha, W, g)

    t_end = 30.0
    hp0, hv0, _ = formation_reference(r, *centre(0.0))
    pos, vel = rk4(hp0 + rng.normal(size=(n, 3)), hv0, t_end, 0.05, law)
    hp, hv, _ = formation_reference(r, *centre(t_end))
    return pos - hp, vel - hv, g


def test_constant_velocity_centre_tracked_with_zero_steady_error():
    e_pos, e_vel, _ = _moving(8, np.zeros(3), feedforward=True)
    assert np.abs(e_pos).max() < 1e-5 and np.abs(e_vel).max() < 1e-5


def test_accelerating_centre_needs_the_feedforward():
    a = np.array([0.2, -0.1, 0.05])
    e_pos, _, _ = _moving(8, a, feedforward=True)
    assert np.abs(e_pos).max() < 1e-5
    e_pos, e_vel, g = _moving(8, a, feedforward=False)
    # Without h'' the lam = 0 mode settles at K2 e = c'': a lag of c''/|k2_pos|.
    np.testing.assert_allclose(e_pos, np.tile(a / g.k2_pos_per_s2, (8, 1)), atol=1e-5)


# --- stability check -------------------------------------------------------------


def test_default_gains_chain40_eigenvalues_are_exact():
    eig = check_stability(T.chain(40), EQ27)
    assert eig.shape == (240,)
    f1, f2 = (-2.2 + np.array([1, -1]) * np.sqrt(2.2**2 - 3.6)) / 2
    np.testing.assert_allclose(np.unique(np.round(eig.real, 9)), np.sort([-1.0, -0.6, f1, f2]))
    assert np.all(eig.imag == 0)


def test_positive_k2_is_refused_naming_eigenvalue_and_mode():
    g = ConsensusGains(k2_pos_per_s2=0.5, ki_pos_per_s3=0.0)
    with pytest.raises(FormationUnstableError) as ei:
        check_stability(T.chain(40), g)
    s = (-1.6 + np.sqrt(1.6**2 + 4 * 0.5)) / 2  # root of s^2 + 1.6 s - 0.5
    assert ei.value.eigenvalue.real == pytest.approx(s)
    assert ei.value.laplacian_eigenvalue == 0
    msg = str(ei.value)
    assert f"closed-loop eigenvalue {s:.3g}+0j" in msg
    assert "Laplacian eigenvalue 0" in msg and "chain(40)" in msg and "K2=(pos 0.5/s^2" in msg
    assert isinstance(ei.value, ValueError)


def test_failure_in_a_coupled_mode_is_attributed_to_it():
    g = ConsensusGains(k3_pos_per_s2=-1.0)  # lam = 1 mode: -0.6 + 1.0 > 0
    with pytest.raises(FormationUnstableError, match=r"Laplacian eigenvalue 1, mode [1-9]"):
        check_stability(T.chain(10), g)


def test_marginal_stability_is_refused():
    with pytest.raises(FormationUnstableError, match=r"eigenvalue 0\+0j \(Laplacian eigenvalue 0, mode 0\)"):
        check_stability(T.complete(5), ConsensusGains(k2_pos_per_s2=0.0, ki_pos_per_s3=0.0))  # pure consensus: drift


def _knn_directed(n):
    return T.k_nearest(np.random.default_rng(4).normal(size=(n, 3)), 2, symmetric=False)


@pytest.mark.parametrize("ki", [0.0, 0.15])
@pytest.mark.parametrize("topo", ["chain", "ring", "complete", "knn_sym", "knn_directed"])
@pytest.mark.parametrize("n", [1, 2, 4])
def test_kron_and_reduction_agree(topo, n, ki):
    builders = {
        "chain": T.chain,
        "ring": T.ring,
        "complete": T.complete,
        "knn_sym": lambda n: T.k_nearest(np.random.default_rng(4).normal(size=(n, 3)), 2),
        "knn_directed": _knn_directed,
    }
    W = 0.8 * builders[topo](n)
    g = ConsensusGains(k2_pos_per_s2=-0.4, k2_vel_per_s=-1.2, k3_pos_per_s2=0.5, k3_vel_per_s=0.3, ki_pos_per_s3=ki)
    a = check_stability(W, g, method="reduction")
    b = check_stability(W, g, method="kron")
    cost = np.abs(a[:, None] - b[None, :])
    i, j = linear_sum_assignment(cost)
    # Chain: kron eigenvalues of the Jordan blocks are perturbed by ~eps**(1/(n-1)).
    assert cost[i, j].max() < (1e-4 if topo == "chain" else 1e-8)


def test_reduction_handles_complex_laplacian_modes():
    W = _knn_directed(12)
    per_mode, lam = mode_eigenvalues(W, EQ27)
    assert per_mode.shape == (12, 6)
    b = np.linalg.eigvals(closed_loop_matrix(W, EQ27))
    for z in per_mode.ravel():
        assert np.min(np.abs(b - z)) < 1e-6


def test_large_fleet_uses_reduction_and_kron_is_refused():
    W = T.chain(2000)
    eig = check_stability(W, EQ27)
    assert eig.shape == (12000,) and eig.real.max() < 0
    assert check_stability(W, ConsensusGains()).shape == (18000,)  # with the integral states
    with pytest.raises(ValueError, match="reduction"):
        check_stability(T.chain(KRON_MAX_N + 1), ConsensusGains(), method="kron")


# --- integral action (our addition) ------------------------------------------------


def test_integral_mode_blocks_are_the_third_order_loop():
    """A lone vehicle (Laplacian mode 0): each axis is s^3 - k2_vel s^2 - k2_pos s + k_i."""
    g = ConsensusGains()
    per_mode, lam = mode_eigenvalues(T.complete(1), g)
    roots = np.roots([1.0, -g.k2_vel_per_s, -g.k2_pos_per_s2, g.ki_pos_per_s3])
    assert per_mode.shape == (1, 9)
    for z in per_mode[0]:
        assert np.min(np.abs(roots - z)) < 1e-9
    for z in roots:
        assert np.sum(np.abs(per_mode[0] - z) < 1e-9) == 3  # once per axis


@pytest.mark.parametrize("topo", ["chain", "ring"])
def test_rk4_with_integral_matches_matrix_exponential(topo):
    """u = eq. 27 - k_i z, z' = the law's position residual e_i + (k3_pos/k2_pos) sum_j
    w_ij (e_j - e_i): integrating it reproduces exp(M t) of the (9N) closed loop that
    check_stability analyses (fixed slots; start off the slots)."""
    rng = np.random.default_rng(12)
    n, dt, t_end = 5, 0.01, 6.0
    W, g = getattr(T, topo)(n), ConsensusGains(ki_pos_per_s3=0.3)
    r = circle(n, 10.0)
    law = fixed_law(W, g, r)
    e_p, e_v, z = rng.uniform(-2, 2, (n, 3)), rng.uniform(-1, 1, (n, 3)), rng.uniform(-1, 1, (n, 3))
    x0 = np.hstack([e_p, e_v, z]).ravel()

    q = g.k3_pos_per_s2 / g.k2_pos_per_s2

    def deriv(p, v, zz):
        return v, law(0.0, p + r + CENTRE, v) - g.ki_pos_per_s3 * zz, p + q * (W @ p - W.sum(axis=1)[:, None] * p)

    p, v = e_p.copy(), e_v.copy()
    for _ in range(int(round(t_end / dt))):
        k1 = deriv(p, v, z)
        k2 = deriv(*(a + 0.5 * dt * b for a, b in zip((p, v, z), k1)))
        k3 = deriv(*(a + 0.5 * dt * b for a, b in zip((p, v, z), k2)))
        k4 = deriv(*(a + dt * b for a, b in zip((p, v, z), k3)))
        p, v, z = (a + dt / 6 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip((p, v, z), k1, k2, k3, k4))
    x = (expm(closed_loop_matrix(W, g) * t_end) @ x0).reshape(n, 9)
    np.testing.assert_allclose(np.hstack([p, v, z]), x, atol=1e-7)


def test_too_much_integral_gain_is_refused_with_the_routh_condition():
    g = ConsensusGains(ki_pos_per_s3=1.2)  # |k2_pos k2_vel| = 0.96 < 1.2
    with pytest.raises(FormationUnstableError, match=r"product above ki_pos \(0.96 > 1.2\?\)"):
        check_stability(T.chain(5), g)
    check_stability(T.chain(5), ConsensusGains(ki_pos_per_s3=0.9))
