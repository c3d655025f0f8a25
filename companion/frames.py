"""Frame and quaternion conversions: the one place where conventions live.

Conventions (used everywhere in swarmdrop):
    * World frame NED (e1 north, e2 east, e3 down); body frame FRD (b3 down).
    * ``R`` (..., 3, 3) is the rotation matrix of the body attitude: it maps FRD body
      vectors to NED, ``v_ned = R @ v_frd``; its columns are b1, b2, b3 in NED.
    * Quaternions in swarmdrop are Hamilton, scalar first, ``q = [w, x, y, z]``, as in
      MAVLink ATTITUDE_QUATERNION / SET_ATTITUDE_TARGET ("NED -> FRD" attitude, null
      rotation = [1, 0, 0, 0]); ``quat_wxyz_to_rot(q)`` is that attitude's R (the same
      matrix PX4's ``Dcmf(q)`` builds). scipy's ``Rotation.from_quat`` uses scalar-last
      ``[x, y, z, w]``: convert with ``wxyz_to_xyzw`` / ``xyzw_to_wxyz``.
    * Euler angles are ZYX (yaw psi about e3, then pitch theta, then roll phi):
      ``R = Rz(psi) @ Ry(theta) @ Rx(phi)``, as MAVLink ATTITUDE reports them.

All functions are vectorised over leading axes and are pure numpy.
"""
from __future__ import annotations

import numpy as np


def quat_wxyz_to_rot(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix R (body FRD -> NED) of a Hamilton quaternion [w, x, y, z].

    Args:
        q_wxyz: (..., 4); need not be normalised (it is normalised here).
    Returns:
        (..., 3, 3) rotation matrix.
    Raises:
        ValueError: if the last axis is not 4 or a quaternion has zero norm.
    """
    q = np.asarray(q_wxyz, dtype=float)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion last axis must be 4, got shape {q.shape}")
    nrm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(nrm == 0):
        raise ValueError("zero-norm quaternion")
    w, x, y, z = np.moveaxis(q / nrm, -1, 0)
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def rot_to_quat_wxyz(rot: np.ndarray) -> np.ndarray:
    """Hamilton quaternion [w, x, y, z] of a rotation matrix, with w >= 0.

    Uses Shepperd's method (branch on the largest diagonal term) for accuracy.

    Args:
        rot: (..., 3, 3) rotation matrix (body -> NED).
    Returns:
        (..., 4) unit quaternion, scalar first, canonical sign w >= 0.
    """
    r = np.asarray(rot, dtype=float)
    shape = r.shape[:-2]
    r = r.reshape(-1, 3, 3)
    tr = np.trace(r, axis1=1, axis2=2)
    cand = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((r.shape[0], 4))
    for case in range(4):
        m = k == case
        if not np.any(m):
            continue
        a = r[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack([0.25 * s, (a[:, 2, 1] - a[:, 1, 2]) / s,
                             (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s], axis=1)
        elif case == 1:
            s = 2.0 * np.sqrt(_nonneg(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2]))
            q[m] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, 0.25 * s,
                             (a[:, 0, 1] + a[:, 1, 0]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s], axis=1)
        elif case == 2:
            s = 2.0 * np.sqrt(_nonneg(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2]))
            q[m] = np.stack([(a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 0, 1] + a[:, 1, 0]) / s,
                             0.25 * s, (a[:, 1, 2] + a[:, 2, 1]) / s], axis=1)
        else:
            s = 2.0 * np.sqrt(_nonneg(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1]))
            q[m] = np.stack([(a[:, 1, 0] - a[:, 0, 1]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s,
                             (a[:, 1, 2] + a[:, 2, 1]) / s, 0.25 * s], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(shape + (4,))


def _nonneg(x: np.ndarray) -> np.ndarray:
    """Clamp at zero (guards sqrt against -1e-17 round-off)."""
    return np.maximum(x, 0.0)


def wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    """MAVLink/swarmdrop scalar-first [w,x,y,z] -> scipy scalar-last [x,y,z,w]; (..., 4)."""
    return np.roll(np.asarray(q_wxyz, dtype=float), -1, axis=-1)


def xyzw_to_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """scipy scalar-last [x,y,z,w] -> MAVLink/swarmdrop scalar-first [w,x,y,z]; (..., 4)."""
    return np.roll(np.asarray(q_xyzw, dtype=float), 1, axis=-1)


def euler_zyx_to_rot(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll); broadcasting inputs of shape (...) -> (..., 3, 3)."""
    phi, theta, psi = np.broadcast_arrays(np.asarray(roll_rad, float), np.asarray(pitch_rad, float),
                                          np.asarray(yaw_rad, float))
    cf, sf, ct, st, cp, sp = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta), np.cos(psi), np.sin(psi)
    r = np.empty(phi.shape + (3, 3))
    r[..., 0, 0] = cp * ct
    r[..., 0, 1] = cp * st * sf - sp * cf
    r[..., 0, 2] = cp * st * cf + sp * sf
    r[..., 1, 0] = sp * ct
    r[..., 1, 1] = sp * st * sf + cp * cf
    r[..., 1, 2] = sp * st * cf - cp * sf
    r[..., 2, 0] = -st
    r[..., 2, 1] = ct * sf
    r[..., 2, 2] = ct * cf
    return r


def rot_to_euler_zyx(rot: np.ndarray) -> np.ndarray:
    """ZYX Euler angles (..., 3) = [roll, pitch, yaw] in rad of R (..., 3, 3).

    Pitch is in [-pi/2, pi/2]; at gimbal lock (|pitch| = 90 deg) roll is set to 0.
    """
    r = np.asarray(rot, dtype=float)
    pitch = np.arcsin(np.clip(-r[..., 2, 0], -1.0, 1.0))
    lock = np.abs(r[..., 2, 0]) > 1.0 - 1e-12
    roll = np.where(lock, 0.0, np.arctan2(r[..., 2, 1], r[..., 2, 2]))
    yaw = np.where(lock, np.arctan2(-r[..., 0, 1], r[..., 1, 1]), np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    return np.stack([roll, pitch, yaw], axis=-1)


def quat_wxyz_to_euler_zyx(q_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) quaternion -> (..., 3) [roll, pitch, yaw] rad."""
    return rot_to_euler_zyx(quat_wxyz_to_rot(q_wxyz))


def euler_zyx_to_quat_wxyz(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """ZYX Euler angles -> (..., 4) quaternion [w, x, y, z], w >= 0."""
    return rot_to_quat_wxyz(euler_zyx_to_rot(roll_rad, pitch_rad, yaw_rad))


def tilt_rad(rot: np.ndarray) -> np.ndarray:
    """Angle between body z (b3) and world z (e3): arccos(R[2,2]); (..., 3, 3) -> (...)."""
    return np.arccos(np.clip(np.asarray(rot, float)[..., 2, 2], -1.0, 1.0))


def yaw_rad(rot: np.ndarray) -> np.ndarray:
    """Heading of b1 projected on the horizontal plane, atan2(R[1,0], R[0,0]); (..., 3, 3) -> (...).

    Equals the ZYX Euler yaw away from gimbal lock.
    """
    r = np.asarray(rot, float)
    return np.arctan2(r[..., 1, 0], r[..., 0, 0])


def wrap_pi(angle_rad):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle_rad, float) + np.pi) % (2.0 * np.pi) - np.pi


def integrate_quat_body_rates(q_wxyz: np.ndarray, omega_body_radps: np.ndarray, dt_s: float) -> np.ndarray:
    """Attitude after rotating at constant body rates for dt_s: q <- q * exp(omega dt).

    Args:
        q_wxyz: (N, 4) attitudes [w, x, y, z] (body FRD -> NED).
        omega_body_radps: (N, 3) body rates, FRD, rad/s.
        dt_s: time step, s.
    Returns:
        (N, 4) unit quaternions [w, x, y, z], w >= 0.
    """
    from companion.control.so3 import exp_so3_np  # so3 is pure math; import here to keep frames light

    rot = quat_wxyz_to_rot(q_wxyz) @ exp_so3_np(np.asarray(omega_body_radps, float) * dt_s)
    return rot_to_quat_wxyz(rot)
