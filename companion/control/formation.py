"""Consensus formation control, paper eq. 23-28 (pure numpy, no I/O).

Model (eq. 23-24): every vehicle is a double integrator with 6-state
x_i = [p_i; v_i] (NED metres, m/s) and input u_i = commanded acceleration (NED
m/s^2):  x_i' = A x_i + B u_i,  A = [[0, I3], [0, 0]],  B = [[0], [I3]].

Formation reference (eq. 25): h_i(t) = r_i + c(t), with r_i the constant slot
offset and c(t) the virtual centre; as a 6-state h_i = [r_i + c; c'].

Control law (eq. 27, plus our feed-forward term, docs/formation.md):
    u1_i = K1 x_i + K2 (x_i - h_i) + K3 sum_j w_ij ((x_j - h_j) - (x_i - h_i)) + h_i''

Closed loop (eq. 28), stacked vehicle-major (x = [x_1; ...; x_N]):
    x' = (I_N kron (A + B K1 + B K2) - L kron B K3) x + (L kron B K3 - I_N kron B K2) h
         + (I_N kron B) h''.

Integral action (our addition, docs/formation.md "Integral action"): each vehicle adds
-k_i z_i with z_i' = p_i - h_i (its own slot-position error), because on a real autopilot
a steady unmodelled acceleration b (estimator bias, tilt error, a wrong hover thrust)
leaves the proportional-derivative law of eq. 27 off its slot by b / |k2_pos| for ever.
The agent (companion/agent.py) integrates only near the slot and with the repulsion
quiet, and bounds k_i |z_i| (anti-windup); the stability analysis below covers z.

Gain signs. The paper gives no signs. We keep the literal sign of eq. 27: K2
multiplies (x - h), so it must be NEGATIVE (k2_pos < 0, k2_vel < 0) to pull
towards the slot; K3 multiplies (neighbour error - own error), so it must be
POSITIVE. K1 acts on the absolute state; it defaults to zero because any nonzero
K1 biases the formation (the forcing B K1 h does not vanish at x = h).
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.control import topology as _topo
from companion.control.kernel import kernel

__all__ = [
    "A_DOUBLE_INTEGRATOR",
    "B_DOUBLE_INTEGRATOR",
    "ConsensusGains",
    "FormationUnstableError",
    "formation_reference",
    "consensus_accel",
    "consensus_rows",
    "gains_vector",
    "closed_loop_matrix",
    "mode_eigenvalues",
    "check_stability",
    "STABILITY_MARGIN",
    "KRON_MAX_N",
]


_I3 = np.eye(3)
_Z3 = np.zeros((3, 3))
A_DOUBLE_INTEGRATOR = np.block([[_Z3, _I3], [_Z3, _Z3]])  # eq. 24, (6, 6)
B_DOUBLE_INTEGRATOR = np.vstack([_Z3, _I3])  # eq. 24, (6, 3)

STABILITY_MARGIN = 1e-9
"""Closed-loop eigenvalues with real part > -STABILITY_MARGIN count as unstable
(marginal stability is a failure: a zero eigenvalue leaves an error that never decays)."""

KRON_MAX_N = 150
"""Largest fleet for which check_stability(method="kron") builds the (6N, 6N) matrix."""


@dataclass(config=STRICT)
class ConsensusGains:
    """Gains K1, K2, K3 of eq. 27 as per-block scalars: K = [k_pos I3, k_vel I3] (3x6).

    Literal sign of eq. 27 (see module docstring): k2_* < 0, k3_* > 0 for
    stability; no sign is enforced here because check_stability is the authority
    (it also covers the coupling with the topology). Defaults give, per axis,
    leader poles s = -0.6, -1.0 and chain-follower poles s = -0.54, -1.66 (all real:
    no overshoot into neighbours) and a string-stable chain (docs/formation.md).
    """

    k1_pos_per_s2: float = Field(default=0.0, allow_inf_nan=False)
    k1_vel_per_s: float = Field(default=0.0, allow_inf_nan=False)
    k2_pos_per_s2: float = Field(default=-0.6, allow_inf_nan=False)
    k2_vel_per_s: float = Field(default=-1.6, allow_inf_nan=False)
    k3_pos_per_s2: float = Field(default=0.3, allow_inf_nan=False)
    k3_vel_per_s: float = Field(default=0.6, allow_inf_nan=False)
    ki_pos_per_s3: float = Field(default=0.1, ge=0, allow_inf_nan=False)
    """Integral gain on the own slot-position error (our addition; 0 = eq. 27 exactly).
    With the default K2 the single-vehicle loop s^3 + 1.6 s^2 + 0.6 s + k_i has poles
    -1.16 and -0.22 +- 0.19j: a steady bias is removed with a ~4.5 s time constant.
    Routh: stable for k_i < |k2_pos k2_vel| (0.96); check_stability covers the swarm."""

    @property
    def integral(self) -> bool:
        """The law has integral states (ki_pos_per_s3 > 0): 9 closed-loop states per vehicle, else 6."""
        return self.ki_pos_per_s3 > 0

    @staticmethod
    def _block(k_pos: float, k_vel: float) -> np.ndarray:
        return np.hstack([k_pos * _I3, k_vel * _I3])

    @property
    def k1(self) -> np.ndarray:
        """K1, (3, 6)."""
        return self._block(self.k1_pos_per_s2, self.k1_vel_per_s)

    @property
    def k2(self) -> np.ndarray:
        """K2, (3, 6)."""
        return self._block(self.k2_pos_per_s2, self.k2_vel_per_s)

    @property
    def k3(self) -> np.ndarray:
        """K3, (3, 6)."""
        return self._block(self.k3_pos_per_s2, self.k3_vel_per_s)

    def summary(self) -> str:
        return (
            f"K1=(pos {self.k1_pos_per_s2:g}/s^2, vel {self.k1_vel_per_s:g}/s), "
            f"K2=(pos {self.k2_pos_per_s2:g}/s^2, vel {self.k2_vel_per_s:g}/s), "
            f"K3=(pos {self.k3_pos_per_s2:g}/s^2, vel {self.k3_vel_per_s:g}/s)"
            + (f", Ki={self.ki_pos_per_s3:g}/s^3" if self.integral else "")
        )


class FormationUnstableError(ValueError):
    """The closed loop of eq. 28 is not Hurwitz for these gains and this topology.

    Attributes:
        eigenvalue: the worst closed-loop eigenvalue (largest real part).
        laplacian_eigenvalue: the eigenvalue of L whose mode it belongs to.
    """

    def __init__(self, message: str, eigenvalue: complex, laplacian_eigenvalue: complex):
        super().__init__(message)
        self.eigenvalue = eigenvalue
        self.laplacian_eigenvalue = laplacian_eigenvalue


def _vec3(name: str, a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {a.shape}")
    return a


def formation_reference(
    offsets_ned_m: np.ndarray,
    c_pos_ned_m: np.ndarray,
    c_vel_ned_mps: np.ndarray,
    c_acc_ned_mps2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slot references of eq. 25, h_i = r_i + c(t), and their derivatives.

    The offsets r_i are constant, so h_i' = c' and h_i'' = c''.

    Args:
        offsets_ned_m: (N, 3) slot offsets r_i, NED metres.
        c_pos_ned_m: (3,) formation centre c(t), NED metres.
        c_vel_ned_mps: (3,) c'(t), NED m/s.
        c_acc_ned_mps2: (3,) c''(t), NED m/s^2.

    Returns:
        (h_pos_ned_m, h_vel_ned_mps, h_acc_ned_mps2), each (N, 3), writable.

    Raises:
        ValueError: wrong shapes.
    """
    r = np.asarray(offsets_ned_m, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3:
        raise ValueError(f"offsets_ned_m must be (N, 3), got {r.shape}")
    c = _vec3("c_pos_ned_m", c_pos_ned_m)
    cd = _vec3("c_vel_ned_mps", c_vel_ned_mps)
    cdd = _vec3("c_acc_ned_mps2", c_acc_ned_mps2)
    n = r.shape[0]
    return r + c, np.tile(cd, (n, 1)), np.tile(cdd, (n, 1))


def consensus_accel(
    pos_ned_m: np.ndarray,
    vel_ned_mps: np.ndarray,
    h_pos_ned_m: np.ndarray,
    h_vel_ned_mps: np.ndarray,
    h_acc_ned_mps2: np.ndarray,
    W: np.ndarray,
    gains: ConsensusGains,
    rows: np.ndarray | None = None,
) -> np.ndarray:
    """Consensus formation acceleration u1 of eq. 27 (+ feed-forward h''), NED m/s^2.

        u1_i = K1 x_i + K2 (x_i - h_i) + K3 sum_j w_ij ((x_j - h_j) - (x_i - h_i)) + h_i''

    The feed-forward h_i'' = c'' is our addition. With it the slot error
    e_i = x_i - h_i obeys the autonomous closed loop of eq. 28 for ANY smooth c(t)
    (because h_i' = A h_i + B h_i''), so a manoeuvring centre is tracked with zero
    steady error. Without it an accelerating centre (e.g. the trapezoidal
    transit profile) is followed with a lag of c''/|k2_pos| metres. A
    constant-velocity centre needs no feed-forward: the velocity part of h_i in
    K2 (x_i - h_i) already carries c'.

    One code path for the whole fleet and for one onboard vehicle: `rows` selects
    the vehicles whose command is computed. Only the states of `rows` and of the
    vehicles they hear (W[rows, j] != 0) are read; every other row of pos/vel may
    be NaN (the onboard companion knows only its neighbours). h is read for the
    same vehicles (every agent can compute all slots from the shared mission).

    Args:
        pos_ned_m: (N, 3) positions, NED metres.
        vel_ned_mps: (N, 3) velocities, NED m/s.
        h_pos_ned_m, h_vel_ned_mps, h_acc_ned_mps2: (N, 3) slot references from
            formation_reference (metres, m/s, m/s^2).
        W: (N, N) weights, W[i, j] = how strongly i hears j (topology module).
        gains: ConsensusGains.
        rows: (R,) int indices of the vehicles to command; None = all N.

    Returns:
        (R, 3) commanded acceleration u1 (R = N when rows is None), NED m/s^2.

    Raises:
        ValueError: inconsistent shapes, rows out of range, or a state/reference
            that is read (own or heard vehicle) is not finite.
    """
    pos = np.asarray(pos_ned_m, dtype=float)
    vel = np.asarray(vel_ned_mps, dtype=float)
    W = np.asarray(W, dtype=float)
    n = pos.shape[0] if pos.ndim == 2 else -1
    arrays = (pos, vel, h_pos_ned_m, h_vel_ned_mps, h_acc_ned_mps2)
    if any(np.shape(a) != (n, 3) for a in arrays) or W.shape != (n, n):
        shapes = ", ".join(str(np.shape(a)) for a in arrays)
        raise ValueError(f"need pos, vel, h_pos, h_vel, h_acc of shape (N, 3) and W (N, N); got {shapes}, W {W.shape}")
    if rows is not None:
        rows = np.atleast_1d(np.asarray(rows))
        if rows.ndim != 1 or not np.issubdtype(rows.dtype, np.integer) or np.any((rows < 0) | (rows >= n)):
            raise ValueError(f"rows must be a 1-D integer array of indices in [0, {n}), got {rows!r}")

    rows = np.arange(n) if rows is None else rows.astype(np.int64)
    out = np.empty((len(rows), 3))
    usable = np.broadcast_to(np.ones(n, dtype=bool), (len(rows), n))
    bad = consensus_rows(pos[rows], vel[rows], rows, np.broadcast_to(pos, (len(rows), n, 3)),
                         np.broadcast_to(vel, (len(rows), n, 3)), usable, np.asarray(h_pos_ned_m, float)[None],
                         np.asarray(h_vel_ned_mps, float)[None], np.asarray(h_acc_ned_mps2, float)[None],
                         np.zeros(len(rows), np.int64), W, _topo.neighbour_table(W), gains_vector(gains), math.inf, out,
                         np.empty((len(rows), 3)))
    if bad >= 0:
        who = rows.tolist() if len(rows) <= 10 else "..."
        raise ValueError(f"non-finite state or reference for vehicle(s) [{bad}] read by vehicle(s) {who}")
    return out


def gains_vector(gains: ConsensusGains) -> np.ndarray:
    """(k1_pos, k1_vel, k2_pos, k2_vel, k3_pos, k3_vel) as the (6,) array consensus_rows reads."""
    g = gains
    return np.array([g.k1_pos_per_s2, g.k1_vel_per_s, g.k2_pos_per_s2, g.k2_vel_per_s, g.k3_pos_per_s2,
                     g.k3_vel_per_s])


@kernel
def consensus_rows(own_pos, own_vel, ids, nb_pos, nb_vel, usable, h_pos, h_vel, h_acc, h_sel, W, nbr, k, err_max,
                   out, resid) -> int:
    """eq. 27 (+ h'') for the vehicles ids[r], each with its own view of its neighbours.

        out[r] = K1 x_i + K2 e_i + K3 sum_j w_ij (e_j - e_i) + h_i'',  i = ids[r], e = x - h

    Args (arrays indexed element by element: interpreted for one onboard vehicle,
    compiled by sim_bridge.world.jit for a fleet):
        own_pos, own_vel: (R, 3) states of the commanded vehicles (first-hand).
        ids: (R,) their indices in the mission.
        nb_pos, nb_vel: (R, N, 3) every vehicle's state as row r knows it.
        usable: (R, N) bool, vehicle j may enter row r's sum (heard, fresh,
            flying in formation); a neighbour that is not usable has weight 0.
        h_pos, h_vel, h_acc: (G, N, 3) slot references, G alternatives (vehicles that
            hold different transit starts fly different references); h_sel: (R,) which
            one row r flies; W: (N, N) weights;
        nbr: (N, K) who each vehicle hears (topology.neighbour_table; -1 padded), so the
            loop costs the in-degree, not N;
        k: (6,) gains (gains_vector); err_max: slot-position errors longer than
            this (m) are shortened to it before the law (math.inf = eq. 27 exactly).
        out: (R, 3) written; NaN in a row that read a non-finite value.
        resid: (R, 3) written: the law's position residual e_i + (k3_pos / k2_pos) sum_j
            w_ij (e_j - e_i), m (e clipped as above): its proportional part divided by
            k2_pos. It is 0 wherever the law is at rest without a disturbance, also where
            the consensus term holds a vehicle off its slot for its neighbours; a steady
            disturbance b leaves it at b / |k2_pos|. What integral action integrates
            (companion.agent, SlotIntegralConfig). NaN with out.
    Returns:
        -1, or the index of the first vehicle read whose state or reference is not
        finite (the rows that read one are NaN; the others are computed). A self-loop
        w_ii adds 0 and is skipped.
    """
    first_bad = -1
    for r in range(ids.shape[0]):
        i, g = ids[r], h_sel[r]
        e0, e1, e2 = own_pos[r, 0] - h_pos[g, i, 0], own_pos[r, 1] - h_pos[g, i, 1], own_pos[r, 2] - h_pos[g, i, 2]
        f0, f1, f2 = own_vel[r, 0] - h_vel[g, i, 0], own_vel[r, 1] - h_vel[g, i, 1], own_vel[r, 2] - h_vel[g, i, 2]
        en = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        bad = -1
        if not (math.isfinite(en) and math.isfinite(f0 + f1 + f2) and math.isfinite(h_acc[g, i, 0] + h_acc[g, i, 1]
                                                                                   + h_acc[g, i, 2])):
            bad = i
        if en > err_max:
            s = err_max / en
            e0, e1, e2 = e0 * s, e1 * s, e2 * s
        c0 = c1 = c2 = c3 = c4 = c5 = 0.0
        for m in range(nbr.shape[1]):
            if bad >= 0:
                break
            j = nbr[i, m]
            if j < 0:
                break
            w = W[i, j]
            if w == 0.0 or j == i or not usable[r, j]:
                continue
            g0 = nb_pos[r, j, 0] - h_pos[g, j, 0]
            g1 = nb_pos[r, j, 1] - h_pos[g, j, 1]
            g2 = nb_pos[r, j, 2] - h_pos[g, j, 2]
            v0 = nb_vel[r, j, 0] - h_vel[g, j, 0]
            v1 = nb_vel[r, j, 1] - h_vel[g, j, 1]
            v2 = nb_vel[r, j, 2] - h_vel[g, j, 2]
            gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
            if not (math.isfinite(gn) and math.isfinite(v0 + v1 + v2)):
                bad = j
                break
            if gn > err_max:
                s = err_max / gn
                g0, g1, g2 = g0 * s, g1 * s, g2 * s
            c0 += w * (g0 - e0)
            c1 += w * (g1 - e1)
            c2 += w * (g2 - e2)
            c3 += w * (v0 - f0)
            c4 += w * (v1 - f1)
            c5 += w * (v2 - f2)
        if bad >= 0:
            out[r, 0], out[r, 1], out[r, 2] = math.nan, math.nan, math.nan
            resid[r, 0], resid[r, 1], resid[r, 2] = math.nan, math.nan, math.nan
            if first_bad < 0:
                first_bad = bad
            continue
        q = k[4] / k[2] if k[2] != 0.0 else 0.0
        resid[r, 0], resid[r, 1], resid[r, 2] = e0 + q * c0, e1 + q * c1, e2 + q * c2
        # K = [k_pos I3, k_vel I3], so K x = k_pos p + k_vel v.
        out[r, 0] = k[0] * own_pos[r, 0] + k[1] * own_vel[r, 0] + k[2] * e0 + k[3] * f0 + k[4] * c0 + k[5] * c3 \
            + h_acc[g, i, 0]
        out[r, 1] = k[0] * own_pos[r, 1] + k[1] * own_vel[r, 1] + k[2] * e1 + k[3] * f1 + k[4] * c1 + k[5] * c4 \
            + h_acc[g, i, 1]
        out[r, 2] = k[0] * own_pos[r, 2] + k[1] * own_vel[r, 2] + k[2] * e2 + k[3] * f2 + k[4] * c2 + k[5] * c5 \
            + h_acc[g, i, 2]
    return first_bad


def _mode_blocks(gains: ConsensusGains) -> tuple[np.ndarray, np.ndarray]:
    """M1 = A + B K1 + B K2 and M2 = B K3, both (6, 6); with integral action (9, 9) over
    [p; v; z], z' = p + (k3_pos / k2_pos) sum_j w_ij (p_j - p_i) (the law's position residual,
    consensus_rows' resid) and u gaining -k_i z:
    M1 = [[A + B K1 + B K2, -k_i B], [[I3, 0], 0]], M2 = [[B K3, 0], [[(k3_pos / k2_pos) I3, 0], 0]]
    (z_i' = e_i - q (L e)_i with q = k3_pos / k2_pos, L the Laplacian)."""
    A, B = A_DOUBLE_INTEGRATOR, B_DOUBLE_INTEGRATOR
    m1, m2 = A + B @ gains.k1 + B @ gains.k2, B @ gains.k3
    if not gains.integral:
        return m1, m2
    e1, e2 = np.zeros((9, 9)), np.zeros((9, 9))
    e1[:6, :6], e1[:6, 6:] = m1, -gains.ki_pos_per_s3 * B
    e1[6:, :3] = _I3
    e2[:6, :6] = m2
    if gains.k2_pos_per_s2 != 0.0:
        e2[6:, :3] = (gains.k3_pos_per_s2 / gains.k2_pos_per_s2) * _I3
    return e1, e2


def closed_loop_matrix(W: np.ndarray, gains: ConsensusGains) -> np.ndarray:
    """State matrix of eq. 28: I_N kron (A + B K1 + B K2) - L kron (B K3).

    State order is vehicle-major: rows 6i..6i+5 are [p_i; v_i] of vehicle i (with integral
    action 9i..9i+8, [p_i; v_i; z_i]: _mode_blocks). Memory is 288 N^2 bytes (648 N^2 with
    integral action); prefer mode_eigenvalues for large N.

    Args:
        W: (N, N) weights.
        gains: ConsensusGains.

    Returns:
        (6N, 6N) float array ((9N, 9N) with integral action).

    Raises:
        ValueError: see topology.check_weights.
    """
    L = _topo.laplacian(W)
    M1, M2 = _mode_blocks(gains)
    return np.kron(np.eye(L.shape[0]), M1) - np.kron(L, M2)


def mode_eigenvalues(W: np.ndarray, gains: ConsensusGains) -> tuple[np.ndarray, np.ndarray]:
    """Closed-loop eigenvalues of eq. 28 without building the Kronecker matrix.

    eig(I_N kron M1 - L kron M2) = union over eigenvalues lam_k of L of
    eig(M1 - lam_k M2). Proof: Schur-triangularise L = Q T Q^H (always possible,
    also for defective L). Then (Q kron I6)^H (I kron M1 - L kron M2)(Q kron I6)
    = I kron M1 - T kron M2, which is block upper triangular with diagonal
    blocks M1 - T_kk M2; a block triangular matrix's eigenvalues are those of its
    diagonal blocks. No eigenvectors of L are needed, so the chain Laplacian,
    which has a single (N-1)-sized Jordan block and is NOT diagonalisable, is
    covered; its lam_k are taken exactly from its diagonal (laplacian_spectrum).

    Args:
        W: (N, N) weights.
        gains: ConsensusGains.

    Returns:
        (eigenvalues (N, 6) complex, lam (N,) complex): row k holds the six (nine with
        integral action) closed-loop eigenvalues of Laplacian mode lam[k].

    Raises:
        ValueError: see topology.check_weights.
    """
    lam = _topo.laplacian_spectrum(_topo.laplacian(W))
    M1, M2 = _mode_blocks(gains)
    blocks = M1[None, :, :] - lam[:, None, None] * M2[None, :, :]  # (N, 6, 6)
    return np.linalg.eigvals(blocks), lam


def _fmt(z: complex) -> str:
    return f"{z.real:.3g}{z.imag:+.3g}j"


def check_stability(
    W: np.ndarray,
    gains: ConsensusGains,
    *,
    topology_name: str | None = None,
    method: Literal["reduction", "kron"] = "reduction",
) -> np.ndarray:
    """Check that the closed loop of eq. 28 is Hurwitz; return its eigenvalues.

    method="reduction" (default, any N) uses mode_eigenvalues: exact Laplacian
    spectrum per mode, O(N) small 6x6 problems, and it tells which mode failed.
    method="kron" eigen-decomposes closed_loop_matrix (N <= KRON_MAX_N only); it
    exists to cross-check the reduction. For directed chains it is numerically
    poor: the closed loop inherits L's (N-1)-sized Jordan blocks, whose computed
    eigenvalues scatter by ~eps**(1/(N-1)).

    Marginal stability (real part > -STABILITY_MARGIN) is a failure: e.g. K2 = 0
    (pure consensus, eq. 20) leaves the lam = 0 mode undamped and the swarm would
    drift off its slots together.

    For real lam >= 0 each axis has characteristic polynomial
    s^2 - (k1v + k2v - lam k3v) s - (k1p + k2p - lam k3p), Hurwitz iff both
    brackets are negative (with integral action s^3 + a s^2 + b s + k_i, with a and b
    those brackets negated: Hurwitz iff a, b, k_i > 0 and a b > k_i); complex lam
    (directed cycles) need the eigenvalues.

    Args:
        W: (N, N) weights.
        gains: ConsensusGains.
        topology_name: for the error message; default inferred (topology.describe).
        method: "reduction" or "kron".

    Returns:
        (6N,) complex closed-loop eigenvalues ((9N,) with integral action; mode-major
        for "reduction").

    Raises:
        FormationUnstableError: some eigenvalue has real part > -STABILITY_MARGIN;
            the message names the worst one, its real part, its Laplacian mode and
            the gains and topology.
        ValueError: bad W, unknown method, or kron requested for N > KRON_MAX_N.
    """
    W = _topo.check_weights(W)
    n = W.shape[0]
    per_mode, lam = mode_eigenvalues(W, gains)
    if method == "reduction":
        eig = per_mode.ravel()
    elif method == "kron":
        if n > KRON_MAX_N:
            d = 9 if gains.integral else 6
            raise ValueError(f"method='kron' builds a ({d * n}, {d * n}) matrix; use 'reduction' for N > {KRON_MAX_N}")
        eig = np.linalg.eigvals(closed_loop_matrix(W, gains))
    else:
        raise ValueError(f"unknown method {method!r}; use 'reduction' or 'kron'")
    worst = int(np.argmax(eig.real))
    s = complex(eig[worst])
    if s.real > -STABILITY_MARGIN:
        # Attribute to the Laplacian mode with the nearest per-mode eigenvalue
        # (identity for "reduction", nearest match for "kron").
        k = int(np.argmin(np.abs(per_mode - s).min(axis=1)))
        lam_k = complex(lam[k])
        n_bad = int(np.sum(eig.real > -STABILITY_MARGIN))
        name = topology_name or _topo.describe(W)
        hint = ""
        if abs(lam_k.imag) < 1e-12:
            lr = lam_k.real
            a_p = gains.k1_pos_per_s2 + gains.k2_pos_per_s2 - lr * gains.k3_pos_per_s2
            a_v = gains.k1_vel_per_s + gains.k2_vel_per_s - lr * gains.k3_vel_per_s
            hint = (
                f"; this mode needs k1_pos + k2_pos - lam*k3_pos < 0 (is {a_p:.3g}) "
                f"and k1_vel + k2_vel - lam*k3_vel < 0 (is {a_v:.3g})"
                + (f", and their product above ki_pos ({a_p * a_v:.3g} > {gains.ki_pos_per_s3:g}?)"
                   if gains.integral else "")
            )
        msg = (
            f"closed-loop eigenvalue {_fmt(s)} (Laplacian eigenvalue {lam_k.real:.3g}"
            f"{'' if abs(lam_k.imag) < 1e-12 else f'{lam_k.imag:+.3g}j'}, mode {k}) has real part "
            f"{s.real:.3g} >= -{STABILITY_MARGIN:g}: formation gains {gains.summary()} are not "
            f"Hurwitz for topology {name} ({n_bad} of {eig.size} eigenvalues fail){hint}"
        )
        raise FormationUnstableError(msg, s, lam_k)
    return eig
