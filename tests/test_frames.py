"""Frame conventions: quaternion/Euler/matrix round trips, scipy ordering, SO(3) helpers."""
import numpy as np
from scipy.spatial.transform import Rotation

from companion import frames
from companion.control import so3


def _random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_quat_matrix_round_trip_and_scipy_agreement():
    q = _random_quats(200)
    r = frames.quat_wxyz_to_rot(q)
    r_scipy = Rotation.from_quat(frames.wxyz_to_xyzw(q)).as_matrix()
    np.testing.assert_allclose(r, r_scipy, atol=1e-12)
    q2 = frames.rot_to_quat_wxyz(r)
    q_canon = q * np.sign(q[:, :1])
    np.testing.assert_allclose(q2, q_canon, atol=1e-12)
    # scipy's canonical sign may differ: compare up to sign
    qs = frames.xyzw_to_wxyz(Rotation.from_matrix(r).as_quat())
    np.testing.assert_allclose(np.abs(np.sum(qs * q2, axis=1)), 1.0, atol=1e-12)


def test_wxyz_xyzw_helpers():
    q = np.array([[0.1, 0.2, 0.3, 0.4]])
    np.testing.assert_array_equal(frames.wxyz_to_xyzw(q), [[0.2, 0.3, 0.4, 0.1]])
    np.testing.assert_array_equal(frames.xyzw_to_wxyz(frames.wxyz_to_xyzw(q)), q)
    assert np.allclose(frames.quat_wxyz_to_rot(np.array([1.0, 0, 0, 0])), np.eye(3))


def test_euler_round_trip_and_scipy_zyx():
    rng = np.random.default_rng(1)
    n = 300
    eul = np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-np.pi, np.pi, n)], 1)
    r = frames.euler_zyx_to_rot(eul[:, 0], eul[:, 1], eul[:, 2])
    r_scipy = Rotation.from_euler("ZYX", eul[:, ::-1]).as_matrix()  # intrinsic yaw, pitch, roll
    np.testing.assert_allclose(r, r_scipy, atol=1e-12)
    np.testing.assert_allclose(frames.rot_to_euler_zyx(r), eul, atol=1e-10)
    q = frames.euler_zyx_to_quat_wxyz(eul[:, 0], eul[:, 1], eul[:, 2])
    np.testing.assert_allclose(frames.quat_wxyz_to_euler_zyx(q), eul, atol=1e-10)


def test_euler_vectorised_over_leading_axes():
    r = frames.euler_zyx_to_rot(np.zeros((2, 5)), 0.1, np.linspace(0, 1, 5))
    assert r.shape == (2, 5, 3, 3)
    assert frames.rot_to_euler_zyx(r).shape == (2, 5, 3)
    assert frames.rot_to_quat_wxyz(r).shape == (2, 5, 4)


def test_tilt_and_yaw():
    r = frames.euler_zyx_to_rot(np.radians(30.0), 0.0, 1.2)
    assert np.isclose(frames.tilt_rad(r), np.radians(30.0))
    assert np.isclose(frames.yaw_rad(r), 1.2)
    r = frames.euler_zyx_to_rot(np.radians(20.0), np.radians(-25.0), -2.0)
    b3 = r[:, 2]
    assert np.isclose(frames.tilt_rad(r), np.arccos(b3 @ [0, 0, 1]))
    upside_down = frames.euler_zyx_to_rot(np.pi, 0.0, 0.0)
    assert np.isclose(frames.tilt_rad(upside_down), np.pi)
    assert np.isclose(frames.wrap_pi(3 * np.pi / 2), -np.pi / 2)


def test_so3_hat_vee_exp_orthonormalize():
    rng = np.random.default_rng(2)
    w = rng.normal(size=(50, 3))
    v = rng.normal(size=(50, 3))
    h = so3.hat_np(w)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", h, v), np.cross(w, v), atol=1e-12)
    np.testing.assert_allclose(so3.vee_np(h), w)
    np.testing.assert_allclose(so3.exp_so3_np(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    tiny = np.array([[1e-9, -2e-9, 3e-9]])
    np.testing.assert_allclose(so3.exp_so3_np(tiny), Rotation.from_rotvec(tiny).as_matrix(), atol=1e-15)
    noisy = Rotation.from_rotvec(w).as_matrix() + 1e-3 * rng.normal(size=(50, 3, 3))
    for m in (so3.orthonormalize_np(noisy),
              np.array([np.reshape(so3.orthonormalize(tuple(x.ravel())), (3, 3)) for x in noisy])):
        np.testing.assert_allclose(np.einsum("nji,njk->nik", m, m), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)


def test_integrate_quat_body_rates_closed_form():
    """Constant body rate about one axis turns the attitude by rate * dt about that body axis."""
    q0 = frames.euler_zyx_to_quat_wxyz(np.radians(20.0), np.radians(-10.0), np.radians(30.0))[None]
    q = q0.copy()
    for _ in range(100):
        q = frames.integrate_quat_body_rates(q, np.array([[0.0, 0.0, 0.5]]), 0.01)
    expected = frames.quat_wxyz_to_rot(q0)[0] @ frames.euler_zyx_to_rot(0.0, 0.0, 0.5)
    np.testing.assert_allclose(frames.quat_wxyz_to_rot(q)[0], expected, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)


def test_rot_to_quat_rows_loop_twin_equals_the_vectorised_conversion():
    from scipy.spatial.transform import Rotation

    from companion.frames import rot_to_quat_rows, rot_to_quat_wxyz
    from sim_bridge.world.jit import compiled

    rot = Rotation.random(500, random_state=3).as_matrix()
    rot[:4] = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]  # 0 and 180 deg
    ref = rot_to_quat_wxyz(rot)
    for fn in (rot_to_quat_rows, compiled(rot_to_quat_rows)):
        out = np.empty((500, 4))
        fn(rot, out)
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-15)


def test_the_scalar_pair_agrees_with_the_vectorised_pair_interpreted_and_compiled():
    """The controllers' scalar kernels (quat_wxyz_to_rot9, rot9_to_quat_wxyz) against the
    vectorised conversions: quaternion -> matrix bit for bit; matrix -> quaternion to
    rounding (another branch choice, no renormalisation: frames.rot9_to_quat_wxyz), with the
    same sign convention (w >= 0), over random rotations and the 0/180-degree corners."""
    from companion.frames import quat_wxyz_to_rot, quat_wxyz_to_rot9, rot9_to_quat_wxyz, rot_to_quat_wxyz
    from sim_bridge.world.jit import compiled

    q = _random_quats(500, seed=5) * np.random.default_rng(6).uniform(0.5, 2.0, (500, 1))  # not normalised
    rot = Rotation.random(500, random_state=7).as_matrix()
    rot[:4] = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    ref_r, ref_q = quat_wxyz_to_rot(q), rot_to_quat_wxyz(rot)
    for q2r, r2q in ((quat_wxyz_to_rot9, rot9_to_quat_wxyz), (compiled(quat_wxyz_to_rot9), compiled(rot9_to_quat_wxyz))):
        r9 = np.array([q2r(*row) for row in q])
        np.testing.assert_allclose(r9, ref_r.reshape(-1, 9), rtol=0, atol=1e-15)
        qq = np.array([r2q(tuple(m.ravel())) for m in rot])
        assert np.all(qq[:, 0] >= 0)
        np.testing.assert_allclose(qq, ref_q, rtol=0, atol=1e-12)
        back = np.array([q2r(*row) for row in qq]).reshape(-1, 3, 3)
        np.testing.assert_allclose(back, rot, rtol=0, atol=1e-12)  # a round trip
