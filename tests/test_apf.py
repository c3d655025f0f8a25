"""APF repulsion and command combination, eq. 29-31 (companion/control/apf.py)."""
import numpy as np
import pytest

from companion.control import apf
from companion.control.apf import combined_accel, obstacle_repulsion, psi, vehicle_repulsion

KAPPA = 3.0


@pytest.mark.parametrize("kappa", [-4.0, 0.0, 1e-13, 0.5, 3.0, 50.0, 1e4])
def test_psi_shape(kappa):
    d = np.linspace(0, 1.2, 241)
    y = psi(d, kappa)
    assert np.all(np.isfinite(y))
    assert y[0] == pytest.approx(1.0) and psi(1.0, kappa) == 0.0
    assert np.all(y[d >= 1] == 0)
    inside = y[d < 1]
    assert np.all(np.diff(inside) < 0) or kappa > 40  # huge kappa underflows to 0 early
    assert np.all(np.diff(y) <= 0)


def test_psi_equals_printed_eq29_with_negated_exponent():
    # phi(d) = -(e^{k d} - e^{k}) with k = -kappa equals -(1 - e^{-kappa}) psi(d).
    d = np.linspace(0, 0.999, 50)
    for kappa in (0.7, 3.0, 8.0):
        k = -kappa
        phi = -(np.exp(k * d) - np.exp(k))
        np.testing.assert_allclose(phi, -(1 - np.exp(-kappa)) * psi(d, kappa), rtol=1e-12)


def test_vehicle_push_points_away_and_vanishes_at_influence():
    gain, infl = 6.0, 4.0
    rng = np.random.default_rng(0)
    for _ in range(20):
        xj = rng.normal(size=3) * 3
        xi = xj + rng.normal(size=3)
        u = vehicle_repulsion(xi[None], xj[None], gain, infl, 10.0, KAPPA)[0]
        d = np.linalg.norm(xi - xj)
        if d < infl:
            assert np.dot(u, xi - xj) > 0
            np.testing.assert_allclose(np.cross(u, xi - xj), 0, atol=1e-12)  # radial
            assert np.linalg.norm(u) == pytest.approx(gain * psi(d / infl, KAPPA))
    for d in (infl, infl + 1e-9, 5.0, 100.0):
        u = vehicle_repulsion(np.array([[d, 0, 0]]), np.zeros((1, 3)), gain, infl, 10.0, KAPPA)
        np.testing.assert_array_equal(u, 0.0)


def test_vehicle_push_monotone_in_distance():
    d = np.linspace(0.01, 3.99, 200)
    p = np.stack([d, np.zeros_like(d), np.zeros_like(d)], axis=1)
    u = vehicle_repulsion(p, np.zeros((1, 3)), 6.0, 4.0, 10.0, KAPPA)
    assert np.all(np.diff(u[:, 0]) < 0) and np.all(u[:, 0] > 0)
    assert np.all(u[:, 1:] == 0)


def test_sensing_radius_truncates():
    u = vehicle_repulsion(np.array([[3.0, 0, 0]]), np.zeros((1, 3)), 6.0, 8.0, 2.5, KAPPA)
    np.testing.assert_array_equal(u, 0.0)
    u = vehicle_repulsion(np.array([[2.0, 0, 0]]), np.zeros((1, 3)), 6.0, 8.0, 2.5, KAPPA)
    assert u[0, 0] > 0


def test_coincident_vehicles_separate_without_nan():
    p = np.array([[1.0, 2, 3], [1.0, 2, 3], [1.0, 2, 3]])
    u = vehicle_repulsion(p, p, 6.0, 4.0, 10.0, KAPPA, self_index=np.arange(3))
    assert np.all(np.isfinite(u))
    # vehicle 0 pushed -north twice, 2 +north twice, 1 once each way.
    np.testing.assert_allclose(u, [[-12.0, 0, 0], [0, 0, 0], [12.0, 0, 0]])
    u = obstacle_repulsion(p[:1], p[:1], [0.0], 10.0, 5.0, KAPPA)
    np.testing.assert_allclose(u, [[10.0, 0, 0]])


def test_one_vehicle_call_equals_batch_row_and_uses_every_sensed_body():
    rng = np.random.default_rng(3)
    n = 60
    p = rng.uniform(-8, 8, (n, 3))
    p[7] = p[8]  # a coincident pair too
    args = (5.0, 4.0, 6.0, KAPPA)
    batch = vehicle_repulsion(p, p, *args, self_index=np.arange(n))
    assert np.all(np.isfinite(batch))
    for i in range(n):
        one = vehicle_repulsion(p[[i]], p, *args, self_index=[i])
        np.testing.assert_allclose(one[0], batch[i], atol=1e-12)
    # Equal to the explicit pairwise sum (all bodies, not consensus neighbours).
    i = 11
    expect = np.zeros(3)
    for j in range(n):
        d = np.linalg.norm(p[i] - p[j])
        if j != i and d < 4.0:
            expect += 5.0 * psi(d / 4.0, KAPPA) * (p[i] - p[j]) / d
    np.testing.assert_allclose(batch[i], expect, atol=1e-12)
    # Unknown (NaN) bodies are ignored.
    q = p.copy()
    q[20:] = np.nan
    np.testing.assert_allclose(
        vehicle_repulsion(p[:20], q, *args, self_index=np.arange(20)),
        vehicle_repulsion(p[:20], p[:20], *args, self_index=np.arange(20)),
    )


@pytest.mark.parametrize("kappa", [-4.0, 0.0, 1e-13, 0.5, 3.0, 40.0])
def test_compiled_profile_equals_numpy_profile(kappa):
    """The pair loop's scalar psi is the same function as the public psi."""
    d = np.linspace(-0.5, 1.5, 201)
    np.testing.assert_allclose([apf._psi_scalar(x, kappa) for x in d], psi(d, kappa), atol=1e-14)


def test_obstacle_push_from_surface():
    centre, radius, gain, infl = np.array([120.0, 120, -30]), 15.0, 10.0, 8.0
    dirs = np.random.default_rng(1).normal(size=(10, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for s in (-5.0, 0.0):  # inside and at the surface: full gain, outward
        u = obstacle_repulsion(centre + (radius + s) * dirs, centre[None], [radius], gain, infl, KAPPA)
        np.testing.assert_allclose(u, gain * dirs, atol=1e-12)
    for s in (infl, infl + 0.1, 50.0):  # (at s = infl the built point may round to just inside)
        u = obstacle_repulsion(centre + (radius + s) * dirs, centre[None], [radius], gain, infl, KAPPA)
        np.testing.assert_allclose(u, 0.0, atol=1e-12)
    u = obstacle_repulsion(np.array([[radius + infl, 0, 0]]), np.zeros((1, 3)), [radius], gain, infl, KAPPA)
    np.testing.assert_array_equal(u, 0.0)  # exactly at the influence distance
    s = np.linspace(0, infl, 100)
    u = obstacle_repulsion(centre + (radius + s)[:, None] * dirs[0], centre[None], [radius], gain, infl, KAPPA)
    mag = u @ dirs[0]
    assert np.all(np.diff(mag) < 0) and abs(mag[-1]) < 1e-12
    assert obstacle_repulsion(dirs, np.zeros((0, 3)), [], gain, infl, KAPPA).shape == (10, 3)


def test_combined_clips_consensus_first_so_repulsion_wins_at_obstacle():
    u1_max, total_max, k5 = 3.0, 8.0, 10.0
    outward = np.array([[0.0, 1.0, 0.0]])
    u1 = -40.0 * outward + np.array([[25.0, 0, 0]])  # huge pull into the obstacle
    u2 = k5 * outward  # full push at the surface
    u = combined_accel(u1, u2, u1_max, total_max)
    assert np.linalg.norm(u) <= total_max + 1e-12
    assert u @ outward[0] >= 0  # still outward; clipping the sum only would point inward
    assert (u1 + u2) @ outward[0] < 0
    small = combined_accel(np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]), u1_max, total_max)
    np.testing.assert_allclose(small, [[1.0, 1.0, 0]])
    np.testing.assert_allclose(combined_accel(np.zeros((2, 3)), np.zeros((2, 3)), 1.0, 1.0), 0.0)
    with pytest.raises(ValueError):
        combined_accel(u1, u2, 0.0, total_max)


def test_input_validation():
    with pytest.raises(ValueError):
        vehicle_repulsion(np.zeros((2, 2)), np.zeros((2, 3)), 1.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        vehicle_repulsion(np.zeros((2, 3)), np.zeros((2, 3)), 1.0, 0.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        obstacle_repulsion(np.zeros((1, 3)), np.zeros((1, 3)), [-1.0], 1.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        psi(0.5, np.inf)


# ---------------------------------------------------------------- closing speed (docs/formation.md)
def _push(d_m, vel_mps, decel, gain=8.0, infl=4.0, sensing=10.0):
    """Push on a vehicle at (d, 0, 0) flying vel, from a body at rest at the origin."""
    return vehicle_repulsion(np.array([[d_m, 0.0, 0.0]]), np.zeros((1, 3)), gain, infl, sensing, KAPPA,
                             vel_ned_mps=np.array([vel_mps], float), closing_decel_mps2=decel)[0]


def test_closing_pair_is_pushed_as_if_already_braked():
    gain, infl, decel = 8.0, 4.0, 1.5
    for d, c in ((3.0, 1.0), (2.0, 1.5), (5.0, 3.0), (1.2, 0.4)):
        d_eff = max(d - c * c / (2 * decel), 0.0)
        want = gain * psi(d_eff / infl, KAPPA)
        np.testing.assert_allclose(_push(d, (-c, 0.0, 0.0), decel), [want, 0, 0], rtol=1e-12, atol=1e-12)
    # closing from beyond the influence distance: pushed before it is within it
    assert _push(5.0, (-3.0, 0.0, 0.0), decel)[0] > 0.0 and _push(5.0, (-3.0, 0.0, 0.0), 0.0)[0] == 0.0


def test_a_pair_that_keeps_its_distance_or_parts_gets_eq30_as_printed():
    gain, infl = 8.0, 4.0
    for d in (0.5, 1.5, 3.0):
        plain = gain * psi(d / infl, KAPPA)
        for vel in ((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 3.0, 0.0), (np.nan, 0.0, 0.0)):
            np.testing.assert_allclose(_push(d, vel, 1.5), [plain, 0, 0], rtol=1e-12)
        np.testing.assert_allclose(_push(d, (-2.0, 0.0, 0.0), 0.0), [plain, 0, 0], rtol=1e-12)
    with pytest.raises(ValueError, match="closing_decel_mps2"):
        _push(1.0, (0, 0, 0), -1.0)


def test_closing_speed_damps_a_vehicle_pulled_at_a_neighbour_that_does_not_give_way():
    """A vehicle pulled straight at a neighbour at rest (e.g. one still recovering from its
    launch) by a steady consensus term u1, arriving at the influence distance at up to 2.5 m/s
    (double integrator, the command bounded as the output stage bounds it). Eq. 30 alone is a
    conservative field: nothing damps the approach and the vehicle is carried through. With
    the closing speed judged (defaults), half the consensus bound stops it beyond the 1 m
    separation, and the full bound, straight at the neighbour, beyond 0.7 m."""
    from companion.feasibility import SEPARATION_M
    from companion.mission import ApfConfig, MissionConfig, SetpointConfig

    a = ApfConfig()
    u1_max = MissionConfig.__pydantic_fields__["consensus_accel_max_mps2"].default
    ff_max = SetpointConfig().acc_ff_max_mps2
    # at rest, the push at the separation beats the consensus bound
    assert a.vehicle_gain_mps2 * psi(SEPARATION_M / a.vehicle_influence_m, a.kappa) > u1_max

    def closest(decel: float, u1: float, v0: float) -> float:
        x, v, dt, d_min = a.vehicle_influence_m, v0, 0.005, np.inf
        for _ in range(int(12.0 / dt)):
            u2 = vehicle_repulsion(np.array([[x, 0.0, 0.0]]), np.zeros((1, 3)), a.vehicle_gain_mps2,
                                   a.vehicle_influence_m, a.sensing_radius_m, a.kappa,
                                   vel_ned_mps=np.array([v, 0.0, 0.0]), closing_decel_mps2=decel)[0, 0]
            u = float(np.clip(-u1 + u2, -ff_max, ff_max))
            v += u * dt
            x += v * dt
            d_min = min(d_min, x)
        return d_min

    for v0 in (0.0, -1.0, -2.5):
        assert closest(a.closing_decel_mps2, 0.5 * u1_max, v0) > SEPARATION_M
        assert closest(a.closing_decel_mps2, u1_max, v0) > 0.7
    assert closest(0.0, u1_max, 0.0) < 0.0  # eq. 30 alone: carried through
