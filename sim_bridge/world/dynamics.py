"""Quadrotor rigid-body dynamics, paper eq. 1-6, NED world / FRD body.

Mixer geometry: rotor k = 1..4 sits at (x_k, y_k) in the body plane, at distance d from
the centre: on the axes +x, +y, -x, -y for the paper's "plus" frame (eq. 6), on the
diagonals front-right, back-right, back-left, front-left for the "x" frame of the real
Crazyflie. Rotor k produces thrust T_k = k_f Q_k^2 along -b3 and a reaction torque
s_k c T_k about b3 with s = (-1, +1, -1, +1): rotors 1 and 3 spin clockwise seen from above.
With r x (-T b3): rotor at (x, y, 0) gives moment (-y T, x T, 0), hence
    M1 = sum(-y_k T_k), M2 = sum(x_k T_k), M3 = c sum(s_k T_k);
for the plus frame M1 = d (T4 - T2), M2 = d (T1 - T3): exactly the matrix of eq. 6.

Integrator (per step of length h, wrench held constant over the step):
    * rotors: first-order lag discretised exactly, Q1 = Qc + (Q0 - Qc) exp(-h/tau); the
      wrench uses the exact step average of Q^2 along that exponential;
    * Omega: classic RK4 on J Omegadot = M - Omega x J Omega;
    * R: R1 = R0 exp(hat(theta)), theta the 4th-order Magnus increment
      h/2 (W0 + W1) + h^2/12 (Wdot0 - Wdot1) + h^2/12 W0 x W1 (Hermite-Simpson), so R
      stays on SO(3) to round-off and R J Omega is conserved to O(h^4) when M = 0;
    * translation: thrust direction averaged over the step (trapezoid), linear drag
      implicit, an external acceleration per vehicle (what an estimator's bias does to the
      vehicle its autopilot flies: sim_bridge/world/estimator.py) added to gravity,
      position by the trapezoid rule (exact for constant acceleration).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from companion.control import so3
from companion.params import GRAVITY_MPS2, VehicleParams
from companion.state import FleetState
from sim_bridge.world.jit import compiled

# The SO(3) kernels, compiled (companion.control.kernel): called from the njit cores below.
add, cross, exp_so3, load_mat, matmul, mul, scale, store_mat = (
    compiled(getattr(so3, name)) for name in ("add", "cross", "exp_so3", "load_mat", "matmul", "mul", "scale", "store_mat"))

VP_MASS, VP_G, VP_JXX, VP_JYY, VP_JZZ, VP_ARM, VP_KF, VP_CTF = 0, 1, 2, 3, 4, 5, 6, 7
VP_QMIN, VP_QMAX, VP_TAU, VP_DRAG = 8, 9, 10, 11
VP_ROLL_ARM, VP_PITCH_ARM = 12, 16
"""Per rotor k (4 values each): its roll lever -y_k and pitch lever x_k, m."""
N_VP = 20
YAW_SIGN = (-1.0, 1.0, -1.0, 1.0)


def rotor_positions_m(vp: VehicleParams) -> np.ndarray:
    """(4, 2) body-plane (x, y) of rotors 1..4, FRD, m (see the module docstring)."""
    d = vp.arm_length_m
    if vp.frame == "plus":
        return np.array([[d, 0.0], [0.0, d], [-d, 0.0], [0.0, -d]])
    h = d / math.sqrt(2.0)
    return np.array([[h, h], [-h, h], [-h, -h], [h, -h]])


def pack_vehicle_params(vp: VehicleParams) -> np.ndarray:
    """Flatten VehicleParams into the float64 (N_VP,) array the njit cores read."""
    p = np.zeros(N_VP)
    p[VP_MASS], p[VP_G] = vp.mass_kg, GRAVITY_MPS2
    p[VP_JXX], p[VP_JYY], p[VP_JZZ] = vp.inertia_xx_kgm2, vp.inertia_yy_kgm2, vp.inertia_zz_kgm2
    p[VP_ARM], p[VP_KF], p[VP_CTF] = vp.arm_length_m, vp.thrust_coeff_n_per_radps2, vp.torque_to_thrust_m
    p[VP_QMIN], p[VP_QMAX] = vp.rotor_speed_min_radps, vp.rotor_speed_max_radps
    p[VP_TAU], p[VP_DRAG] = vp.motor_time_constant_s, vp.drag_coeff_n_per_mps
    xy = rotor_positions_m(vp)
    p[VP_ROLL_ARM:VP_ROLL_ARM + 4] = -xy[:, 1]
    p[VP_PITCH_ARM:VP_PITCH_ARM + 4] = xy[:, 0]
    return p


def motor_coeffs(tau_s: float, dt_s: float) -> tuple[float, float, float]:
    """(alpha, c1, c2) of the exact motor-lag step: Q1 = Qc + (Q0-Qc) alpha and
    mean(Q^2) = Qc^2 + 2 Qc (Q0-Qc) c1 + (Q0-Qc)^2 c2 over the step."""
    if tau_s <= 0.0:
        return 0.0, 0.0, 0.0
    alpha = math.exp(-dt_s / tau_s)
    return alpha, (1.0 - alpha) * tau_s / dt_s, (1.0 - alpha * alpha) * tau_s / (2.0 * dt_s)


@njit(cache=True)
def mixer(t1, t2, t3, t4, vp):
    """eq. 6 (generalised to the frame) on rotor thrusts T_k = k_f Q_k^2 (N): (f, (M1, M2, M3))."""
    c, r, p = vp[VP_CTF], VP_ROLL_ARM, VP_PITCH_ARM
    return t1 + t2 + t3 + t4, (vp[r] * t1 + vp[r + 1] * t2 + vp[r + 2] * t3 + vp[r + 3] * t4,
                               vp[p] * t1 + vp[p + 1] * t2 + vp[p + 2] * t3 + vp[p + 3] * t4,
                               c * (-t1 + t2 - t3 + t4))


@njit(cache=True)
def _spread(a, b, c, d):
    return max(max(a, b), max(c, d)) - min(min(a, b), min(c, d))


@njit(cache=True)
def allocate(f, m, vp):
    """Inverse mixer with desaturation -> rotor speed commands (4-tuple, rad/s in limits).

    Priority when rotor limits bind: roll/pitch moment, then yaw moment, then collective.
    The differential part is scaled (yaw first) until it fits the thrust range, then the
    collective is shifted into the feasible band (may exceed or undercut f: attitude first).
    """
    d, c, kf = vp[VP_ARM], vp[VP_CTF], vp[VP_KF]
    tmin, tmax = kf * vp[VP_QMIN] ** 2, kf * vp[VP_QMAX] ** 2
    rng = tmax - tmin
    # The levers of either frame are orthogonal with sum of squares 2 d^2 per axis, so the
    # exact inverse is T_k = f/4 + (roll_k M1 + pitch_k M2) / (2 d^2) + s_k M3 / (4 c).
    s2, r, p = 2.0 * d * d, VP_ROLL_ARM, VP_PITCH_ARM
    a = (vp[r] * m[0] + vp[p] * m[1]) / s2
    b = (vp[r + 1] * m[0] + vp[p + 1] * m[1]) / s2
    e = (vp[r + 2] * m[0] + vp[p + 2] * m[1]) / s2
    g = (vp[r + 3] * m[0] + vp[p + 3] * m[1]) / s2
    y = m[2] / (4.0 * c)
    if _spread(a - y, b + y, e - y, g + y) > rng:
        s_rp = _spread(a, b, e, g)
        if s_rp >= rng:
            k = rng / s_rp
            a, b, e, g, y = a * k, b * k, e * k, g * k, 0.0
        else:  # bisection on the yaw share; spread is monotone in |y| here
            lo, hi = 0.0, 1.0
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                if _spread(a - mid * y, b + mid * y, e - mid * y, g + mid * y) > rng:
                    hi = mid
                else:
                    lo = mid
            y = lo * y
    d1, d2, d3, d4 = a - y, b + y, e - y, g + y
    lo_c = tmin - min(min(d1, d2), min(d3, d4))
    hi_c = tmax - max(max(d1, d2), max(d3, d4))
    c0 = min(max(0.25 * f, lo_c), hi_c)
    q1 = math.sqrt(min(max(c0 + d1, tmin), tmax) / kf)
    q2 = math.sqrt(min(max(c0 + d2, tmin), tmax) / kf)
    q3 = math.sqrt(min(max(c0 + d3, tmin), tmax) / kf)
    q4 = math.sqrt(min(max(c0 + d4, tmin), tmax) / kf)
    return q1, q2, q3, q4


@njit(cache=True, inline="always")
def _motor(q0, qc, kf, alpha, c1, c2):
    """(Q at step end, step-mean rotor thrust) of the exact first-order lag."""
    dq = q0 - qc
    return qc + dq * alpha, kf * (qc * qc + 2.0 * qc * dq * c1 + dq * dq * c2)


@njit(cache=True, inline="always")
def _omega_dot(w, m, j):
    jw = mul(j, w)
    g = cross(w, jw)
    return ((m[0] - g[0]) / j[0], (m[1] - g[1]) / j[1], (m[2] - g[2]) / j[2])


@njit(cache=True)
def rigid_body_step(pos, vel, rot, om, q, q_cmd, vp, dt, mot, wind, ground_z, acc_ext):
    """One vehicle, one step of length dt. mot = (alpha, c1, c2) from motor_coeffs;
    wind NED 3-tuple (m/s); ground_z = +inf for no ground; acc_ext NED 3-tuple (m/s^2), an
    external acceleration acting beside gravity and drag. Returns (pos, vel, rot, om, q)."""
    kf = vp[VP_KF]
    qmin, qmax = vp[VP_QMIN], vp[VP_QMAX]
    alpha, c1, c2 = mot
    # rotor commands inside the speed limits, then exact first-order lag
    qc = (min(max(q_cmd[0], qmin), qmax), min(max(q_cmd[1], qmin), qmax),
          min(max(q_cmd[2], qmin), qmax), min(max(q_cmd[3], qmin), qmax))
    n1, t1 = _motor(q[0], qc[0], kf, alpha, c1, c2)
    n2, t2 = _motor(q[1], qc[1], kf, alpha, c1, c2)
    n3, t3 = _motor(q[2], qc[2], kf, alpha, c1, c2)
    n4, t4 = _motor(q[3], qc[3], kf, alpha, c1, c2)
    f, m = mixer(t1, t2, t3, t4, vp)
    # rotation: RK4 on Omega, Magnus/Hermite increment on R
    j = (vp[VP_JXX], vp[VP_JYY], vp[VP_JZZ])
    h = dt
    k1 = _omega_dot(om, m, j)
    k2 = _omega_dot(add(om, scale(k1, 0.5 * h)), m, j)
    k3 = _omega_dot(add(om, scale(k2, 0.5 * h)), m, j)
    k4 = _omega_dot(add(om, scale(k3, h)), m, j)
    om1 = (om[0] + h / 6.0 * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]),
           om[1] + h / 6.0 * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]),
           om[2] + h / 6.0 * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2]))
    wd1 = _omega_dot(om1, m, j)
    cr = cross(om, om1)
    h12 = h * h / 12.0
    theta = (0.5 * h * (om[0] + om1[0]) + h12 * (k1[0] - wd1[0]) + h12 * cr[0],
             0.5 * h * (om[1] + om1[1]) + h12 * (k1[1] - wd1[1]) + h12 * cr[1],
             0.5 * h * (om[2] + om1[2]) + h12 * (k1[2] - wd1[2]) + h12 * cr[2])
    rot1 = matmul(rot, exp_so3(theta))
    # translation
    mass, g, cd = vp[VP_MASS], vp[VP_G], vp[VP_DRAG]
    fm = f / mass
    b3x, b3y, b3z = 0.5 * (rot[2] + rot1[2]), 0.5 * (rot[5] + rot1[5]), 0.5 * (rot[8] + rot1[8])
    kd = cd / mass
    den = 1.0 + kd * h
    v1 = ((vel[0] + h * (-fm * b3x + kd * wind[0] + acc_ext[0])) / den,
          (vel[1] + h * (-fm * b3y + kd * wind[1] + acc_ext[1])) / den,
          (vel[2] + h * (g - fm * b3z + kd * wind[2] + acc_ext[2])) / den)
    p1 = (pos[0] + 0.5 * h * (vel[0] + v1[0]), pos[1] + 0.5 * h * (vel[1] + v1[1]),
          pos[2] + 0.5 * h * (vel[2] + v1[2]))
    q1 = (n1, n2, n3, n4)
    if p1[2] >= ground_z:  # ground contact (NED: down is +z)
        p1 = (p1[0], p1[1], ground_z)
        if f * rot1[8] < mass * (g + acc_ext[2]):  # not enough upward thrust to lift off: rest, levelled to yaw
            yaw = math.atan2(rot1[3], rot1[0])
            cy, sy = math.cos(yaw), math.sin(yaw)
            return p1, (0.0, 0.0, 0.0), (cy, -sy, 0.0, sy, cy, 0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), q1
        v1 = (v1[0], v1[1], min(v1[2], 0.0))
    return p1, v1, rot1, om1, q1


@njit(cache=True)
def _open_loop(pos, vel, rot, om, rotor, q_cmd, vp, dt, mot, wind, ground_z, n_steps):
    for i in range(pos.shape[0]):
        p = (pos[i, 0], pos[i, 1], pos[i, 2])
        v = (vel[i, 0], vel[i, 1], vel[i, 2])
        r = load_mat(rot, i)
        w = (om[i, 0], om[i, 1], om[i, 2])
        q = (rotor[i, 0], rotor[i, 1], rotor[i, 2], rotor[i, 3])
        qc = (q_cmd[i, 0], q_cmd[i, 1], q_cmd[i, 2], q_cmd[i, 3])
        wd = (wind[0], wind[1], wind[2])
        for _ in range(n_steps):
            p, v, r, w, q = rigid_body_step(p, v, r, w, q, qc, vp, dt, mot, wd, ground_z, (0.0, 0.0, 0.0))
        pos[i, 0], pos[i, 1], pos[i, 2] = p
        vel[i, 0], vel[i, 1], vel[i, 2] = v
        store_mat(rot, i, r)
        om[i, 0], om[i, 1], om[i, 2] = w
        rotor[i, 0], rotor[i, 1], rotor[i, 2], rotor[i, 3] = q


@njit(cache=True)
def _allocate_batch(f, m, vp, out):
    for i in range(f.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = allocate(f[i], (m[i, 0], m[i, 1], m[i, 2]), vp)


# ----------------------------------------------------------------------------- numpy wrappers

def mixer_matrix(vp: VehicleParams) -> np.ndarray:
    """(4, 4) matrix of eq. 6 for the vehicle's frame: (f, M1, M2, M3) = A @ (T1..T4)."""
    xy = rotor_positions_m(vp)
    return np.stack([np.ones(4), -xy[:, 1], xy[:, 0], vp.torque_to_thrust_m * np.asarray(YAW_SIGN)])


def mixer_np(rotor_speed_radps: np.ndarray, vp: VehicleParams) -> tuple[np.ndarray, np.ndarray]:
    """eq. 6: (N, 4) rotor speeds -> thrust_n (N,), moment_body_nm (N, 3)."""
    t = vp.thrust_coeff_n_per_radps2 * np.asarray(rotor_speed_radps, float) ** 2
    w = t @ mixer_matrix(vp).T
    return w[:, 0], w[:, 1:]


def inverse_mixer_np(thrust_n: np.ndarray, moment_body_nm: np.ndarray, vp: VehicleParams) -> np.ndarray:
    """Exact inverse of eq. 6 (no limits): rotor thrusts (N, 4) in newtons (may be negative)."""
    w = np.column_stack([np.asarray(thrust_n, float), np.asarray(moment_body_nm, float)])
    return np.linalg.solve(mixer_matrix(vp), w.T).T


def allocate_np(thrust_n: np.ndarray, moment_body_nm: np.ndarray, vp: VehicleParams) -> np.ndarray:
    """Saturating allocation (njit ``allocate``): (N,), (N, 3) -> rotor speed commands (N, 4) rad/s."""
    f = np.ascontiguousarray(thrust_n, float)
    out = np.empty((f.shape[0], 4))
    _allocate_batch(f, np.ascontiguousarray(moment_body_nm, float), pack_vehicle_params(vp), out)
    return out


def step_open_loop(state: FleetState, rotor_cmd_radps: np.ndarray, vp: VehicleParams, dt_s: float,
                   n_steps: int = 1, wind_ned_mps=(0.0, 0.0, 0.0), ground_z_m: float | None = None) -> None:
    """Advance all vehicles n_steps with held rotor speed commands (N, 4), in place.

    Raises:
        ValueError: on a shape mismatch or non-positive dt_s.
    """
    if not dt_s > 0:
        raise ValueError("dt_s must be > 0")
    cmd = np.ascontiguousarray(rotor_cmd_radps, float)
    if cmd.shape != (state.n, 4):
        raise ValueError(f"rotor_cmd_radps must be ({state.n}, 4), got {cmd.shape}")
    arrays = [np.ascontiguousarray(getattr(state, k), float) for k in
              ("pos_ned_m", "vel_ned_mps", "rot_body_to_ned", "omega_body_radps", "rotor_speed_radps")]
    gz = math.inf if ground_z_m is None else float(ground_z_m)
    # (numba's stubs type the call by the kernel's parameters; mypy cannot count the five arrays in *arrays)
    _open_loop(*arrays, cmd, pack_vehicle_params(vp), float(dt_s), motor_coeffs(vp.motor_time_constant_s, dt_s),  # type: ignore[call-arg]
               np.asarray(wind_ned_mps, float), gz, int(n_steps))
    for k, a in zip(("pos_ned_m", "vel_ned_mps", "rot_body_to_ned", "omega_body_radps", "rotor_speed_radps"), arrays):
        getattr(state, k)[...] = a
