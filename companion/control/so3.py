"""SO(3) algebra for the per-vehicle kernels, plus thin numpy wrappers.

The kernels (companion.control.kernel) work on tuples so that nothing is
heap-allocated inside the compiled physics loop: a vector is a 3-tuple, a matrix a row-major 9-tuple
``(r00, r01, r02, r10, r11, r12, r20, r21, r22)``.
"""
from __future__ import annotations

import math

import numpy as np

from companion.control.kernel import kernel
from companion.frames import rotvec_to_rot


@kernel(inline="always")
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@kernel(inline="always")
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@kernel(inline="always")
def norm(a):
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


@kernel(inline="always")
def scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


@kernel(inline="always")
def add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@kernel(inline="always")
def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@kernel(inline="always")
def mul(a, b):
    """Element-wise product (diagonal matrix times vector)."""
    return (a[0] * b[0], a[1] * b[1], a[2] * b[2])


@kernel(inline="always")
def matvec(m, v):
    return (m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
            m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
            m[6] * v[0] + m[7] * v[1] + m[8] * v[2])


@kernel(inline="always")
def mattvec(m, v):
    """m.T @ v."""
    return (m[0] * v[0] + m[3] * v[1] + m[6] * v[2],
            m[1] * v[0] + m[4] * v[1] + m[7] * v[2],
            m[2] * v[0] + m[5] * v[1] + m[8] * v[2])


@kernel(inline="always")
def matmul(a, b):
    return (a[0] * b[0] + a[1] * b[3] + a[2] * b[6], a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
            a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
            a[3] * b[0] + a[4] * b[3] + a[5] * b[6], a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
            a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
            a[6] * b[0] + a[7] * b[3] + a[8] * b[6], a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
            a[6] * b[2] + a[7] * b[5] + a[8] * b[8])


@kernel(inline="always")
def transpose(a):
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


@kernel(inline="always")
def mattmul(a, b):
    """a.T @ b."""
    return matmul(transpose(a), b)


@kernel
def hat(w):
    """Skew matrix of w (eq. 5): hat(w) @ v == cross(w, v)."""
    return (0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0)


@kernel
def vee(m):
    """Inverse of hat, taken from the antisymmetric part (robust to round-off)."""
    return (0.5 * (m[7] - m[5]), 0.5 * (m[2] - m[6]), 0.5 * (m[3] - m[1]))


@kernel
def exp_so3(w):
    """Rodrigues: exp(hat(w)) = I + sin(a)/a hat(w) + (1 - cos a)/a^2 hat(w)^2, a = |w|.

    Taylor coefficients below a = 1e-4 keep the result accurate to round-off.
    """
    a2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if a2 < 1e-8:
        s = 1.0 - a2 / 6.0
        c = 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s = math.sin(a) / a
        c = (1.0 - math.cos(a)) / a2
    x, y, z = w[0], w[1], w[2]
    return (1.0 - c * (y * y + z * z), -s * z + c * x * y, s * y + c * x * z,
            s * z + c * x * y, 1.0 - c * (x * x + z * z), -s * x + c * y * z,
            -s * y + c * x * z, s * x + c * y * z, 1.0 - c * (x * x + y * y))


@kernel
def orthonormalize(m):
    """Nearest-ish rotation by Gram-Schmidt on the columns (b3 kept exact, then b1)."""
    b3 = (m[2], m[5], m[8])
    b3 = scale(b3, 1.0 / norm(b3))
    b1 = (m[0], m[3], m[6])
    b1 = sub(b1, scale(b3, dot(b1, b3)))
    b1 = scale(b1, 1.0 / norm(b1))
    b2 = cross(b3, b1)
    return (b1[0], b2[0], b3[0], b1[1], b2[1], b3[1], b1[2], b2[2], b3[2])


@kernel
def load_mat(a, i):
    """Row-major 9-tuple from a (N, 3, 3) array row i."""
    return (a[i, 0, 0], a[i, 0, 1], a[i, 0, 2], a[i, 1, 0], a[i, 1, 1], a[i, 1, 2],
            a[i, 2, 0], a[i, 2, 1], a[i, 2, 2])


@kernel
def store_mat(a, i, m):
    a[i, 0, 0], a[i, 0, 1], a[i, 0, 2] = m[0], m[1], m[2]
    a[i, 1, 0], a[i, 1, 1], a[i, 1, 2] = m[3], m[4], m[5]
    a[i, 2, 0], a[i, 2, 1], a[i, 2, 2] = m[6], m[7], m[8]


# ----------------------------------------------------------------------------- numpy wrappers

def hat_np(w: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) skew matrices."""
    w = np.asarray(w, float)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def vee_np(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3), antisymmetric part."""
    m = np.asarray(m, float)
    return 0.5 * np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                           m[..., 1, 0] - m[..., 0, 1]], axis=-1)


def exp_so3_np(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (Rodrigues; see frames.rotvec_to_rot)."""
    return rotvec_to_rot(w)


def orthonormalize_np(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> nearest rotation matrices (polar decomposition by SVD, det +1)."""
    u, _, vt = np.linalg.svd(np.asarray(m, float))
    d = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= d[..., None]
    return u @ vt
