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

    * Geodetic <-> local NED: WGS-84 via pymap3d, local NED being the tangent plane at
      an origin (lat, lon, alt). Altitudes are taken as heights above the ellipsoid on
      both sides; since every vehicle and the mission use the same convention (MAVLink's
      AMSL altitudes), the geoid offset cancels out.

All functions are vectorised over leading axes and are pure numpy.
"""
from __future__ import annotations

import math

import numpy as np
import pymap3d

from companion.control.kernel import kernel


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

    Shepperd's method: of the four algebraically equal formulas, each row uses the
    one whose divisor (from the largest of trace and diagonal) is largest, so
    accuracy holds near 180 degrees too. Branch-free over rows.

    Args:
        rot: (..., 3, 3) rotation matrix (body -> NED).
    Returns:
        (..., 4) unit quaternion, scalar first, canonical sign w >= 0.
    """
    r = np.asarray(rot, dtype=float)
    shape = r.shape[:-2]
    r = r.reshape(-1, 3, 3)
    r00, r01, r02 = r[:, 0, 0], r[:, 0, 1], r[:, 0, 2]
    r10, r11, r12 = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    r20, r21, r22 = r[:, 2, 0], r[:, 2, 1], r[:, 2, 2]
    # 4 * (w^2, x^2, y^2, z^2), each from one diagonal combination
    sq = np.stack([1.0 + r00 + r11 + r22, 1.0 + r00 - r11 - r22, 1.0 - r00 + r11 - r22, 1.0 - r00 - r11 + r22])
    k = np.argmax(sq, axis=0)
    s = 2.0 * np.sqrt(_nonneg(np.take_along_axis(sq, k[None], axis=0)[0]))  # 4 * |largest component|
    a, b, c = r21 - r12, r02 - r20, r10 - r01  # 4 w x, 4 w y, 4 w z
    d, e, f = r01 + r10, r02 + r20, r12 + r21  # 4 x y, 4 x z, 4 y z
    cand = np.array([[0.25 * s, a / s, b / s, c / s],
                     [a / s, 0.25 * s, d / s, e / s],
                     [b / s, d / s, 0.25 * s, f / s],
                     [c / s, e / s, f / s, 0.25 * s]])  # (4 cases, 4 components, rows)
    q = cand[k, :, np.arange(len(k))]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(shape + (4,))


@kernel
def rot_to_quat_rows(rot: np.ndarray, out: np.ndarray) -> None:
    """rot_to_quat_wxyz row by row, into out: the loop twin that compiled hot loops call
    (the simulator converts 40 attitudes per tick; numpy's per-call overhead dominates).
    Same case choice (first largest of the four), same sign convention.

    Args:
        rot: (n, 3, 3) rotation matrices; out: (n, 4), written with [w, x, y, z].
    """
    for i in range(rot.shape[0]):
        r00, r01, r02 = rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2]
        r10, r11, r12 = rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2]
        r20, r21, r22 = rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2]
        k, best = 0, 1.0 + r00 + r11 + r22
        sq = 1.0 + r00 - r11 - r22
        if sq > best:
            k, best = 1, sq
        sq = 1.0 - r00 + r11 - r22
        if sq > best:
            k, best = 2, sq
        sq = 1.0 - r00 - r11 + r22
        if sq > best:
            k, best = 3, sq
        s = 2.0 * math.sqrt(max(best, 0.0))
        a, b, c = (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
        d, e, f = (r01 + r10) / s, (r02 + r20) / s, (r12 + r21) / s
        h = 0.25 * s
        if k == 0:
            w, x, y, z = h, a, b, c
        elif k == 1:
            w, x, y, z = a, h, d, e
        elif k == 2:
            w, x, y, z = b, d, h, f
        else:
            w, x, y, z = c, e, f, h
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if w < 0.0:
            n = -n
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = w / n, x / n, y / n, z / n


@kernel
def quat_wxyz_to_rot9(q0, q1, q2, q3):
    """quat_wxyz_to_rot for one quaternion, as scalars: Hamilton [w, x, y, z] (need not be
    normalised) -> row-major R (body FRD -> NED) as a 9-tuple. The kernel that compiled
    controllers call; bit for bit the vectorised function's result (tests/test_frames.py)."""
    n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    w, x, y, z = q0 / n, q1 / n, q2 / n, q3 / n
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


@kernel
def rot9_to_quat_wxyz(r):
    """Row-major R (a 9-tuple) -> quaternion (w, x, y, z) with w >= 0: the scalar kernel the
    geometric controller's large-angle law calls.

    Its branch choice is the classic trace-first one (the w branch whenever the trace is
    positive), not rot_to_quat_wxyz's largest-of-four, and it does not renormalise: the
    two agree to rounding (tests/test_frames.py), not to the bit. They are kept apart
    because each is part of seeded results that must not move (the controller's output,
    the recorded attitudes); both live here, in the one module for conversions."""
    tr = r[0] + r[4] + r[8]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (r[7] - r[5]) / s, (r[2] - r[6]) / s, (r[3] - r[1]) / s
    elif r[0] > r[4] and r[0] > r[8]:
        s = 2.0 * math.sqrt(max(1.0 + r[0] - r[4] - r[8], 1e-300))
        w, x, y, z = (r[7] - r[5]) / s, 0.25 * s, (r[1] + r[3]) / s, (r[2] + r[6]) / s
    elif r[4] > r[8]:
        s = 2.0 * math.sqrt(max(1.0 + r[4] - r[0] - r[8], 1e-300))
        w, x, y, z = (r[2] - r[6]) / s, (r[1] + r[3]) / s, 0.25 * s, (r[5] + r[7]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + r[8] - r[0] - r[4], 1e-300))
        w, x, y, z = (r[3] - r[1]) / s, (r[2] + r[6]) / s, (r[5] + r[7]) / s, 0.25 * s
    if w < 0.0:
        return -w, -x, -y, -z
    return w, x, y, z


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


def rotvec_to_rot(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors (axis * angle, rad) by Rodrigues' formula.

    exp(hat(w)) = I + sin(a)/a hat(w) + (1 - cos a)/a^2 hat(w)^2, a = |w|, with Taylor
    coefficients below a = 1e-4 so that tiny rotations stay accurate to round-off.

    Args:
        rotvec: (..., 3) rotation vectors, rad.
    Returns:
        (..., 3, 3) rotation matrices.
    """
    w = np.asarray(rotvec, float)
    a2 = np.sum(w * w, axis=-1)[..., None, None]
    small = a2 < 1e-8
    a = np.sqrt(np.where(small, 1.0, a2))
    s = np.where(small, 1.0 - a2 / 6.0, np.sin(a) / a)
    c = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(a)) / np.where(small, 1.0, a2))
    h = np.zeros(w.shape[:-1] + (3, 3))
    h[..., 0, 1], h[..., 0, 2] = -w[..., 2], w[..., 1]
    h[..., 1, 0], h[..., 1, 2] = w[..., 2], -w[..., 0]
    h[..., 2, 0], h[..., 2, 1] = -w[..., 1], w[..., 0]
    return np.eye(3) + s * h + c * (h @ h)


def integrate_quat_body_rates(q_wxyz: np.ndarray, omega_body_radps: np.ndarray, dt_s: float) -> np.ndarray:
    """Attitude after rotating at constant body rates for dt_s: q <- q * exp(omega dt).

    Args:
        q_wxyz: (N, 4) attitudes [w, x, y, z] (body FRD -> NED).
        omega_body_radps: (N, 3) body rates, FRD, rad/s.
        dt_s: time step, s.
    Returns:
        (N, 4) unit quaternions [w, x, y, z], w >= 0.
    """
    rot = quat_wxyz_to_rot(q_wxyz) @ rotvec_to_rot(np.asarray(omega_body_radps, float) * dt_s)
    return rot_to_quat_wxyz(rot)


def geodetic_to_ned(lat_deg, lon_deg, alt_m, origin_lat_deg: float, origin_lon_deg: float,
                    origin_alt_m: float) -> np.ndarray:
    """WGS-84 point(s) -> NED metres in the tangent frame at the origin.

    Args:
        lat_deg, lon_deg, alt_m: broadcastable arrays (degrees, degrees, metres).
        origin_*: the local frame's origin.
    Returns:
        (..., 3) north, east, down, m.
    """
    n, e, d = pymap3d.geodetic2ned(lat_deg, lon_deg, alt_m, origin_lat_deg, origin_lon_deg, origin_alt_m)
    return np.stack(np.broadcast_arrays(n, e, d), axis=-1).astype(float)


def ned_to_geodetic(ned_m: np.ndarray, origin_lat_deg: float, origin_lon_deg: float,
                    origin_alt_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NED metres in the tangent frame at the origin -> WGS-84 (lat_deg, lon_deg, alt_m).

    Args:
        ned_m: (..., 3).
    """
    p = np.asarray(ned_m, float)
    lat, lon, alt = pymap3d.ned2geodetic(p[..., 0], p[..., 1], p[..., 2], origin_lat_deg, origin_lon_deg,
                                         origin_alt_m)
    return np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float)
