"""Who each agent trusts, and its avoidance of what is not a trusted neighbour (docs/swarm.md):
`neighbour_sets_rows` sorts the view into consensus, repulsion and ghosts; then the take-off
columns of vehicles still on the ground, the ghosts of silent vehicles (every place their
autopilots can take them: companion.control.ghost) and senders that claim an own vehicle's
id. Each adds eq. 30's push into the agent's repulsion sum through the agent's kernels
(`AgentKernels`: plain Python onboard, compiled in the simulator). No I/O."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from companion.control.apf import repel_cutoff_m
from companion.control.ghost import N_CAPSULES, ghost_grid
from companion.mission import ApfConfig, Mission
from companion.phases import _HOVER, _STABILISE, IN_FORMATION
from companion.swarm import FLAG_OWN_VALID, Intruders, SwarmView

if TYPE_CHECKING:
    from companion.agent import AgentKernels


def vehicle_cutoff_m(a: ApfConfig) -> float:
    """apf.repel_cutoff_m for the mission's vehicle repulsion, m."""
    return repel_cutoff_m(a.sensing_radius_m, a.vehicle_influence_m, a.closing_decel_mps2)


def settled_rows(phase: np.ndarray, vel_ned_mps: np.ndarray, speed_max_mps: float) -> np.ndarray:
    """Settled at station: in HOVER and slower than speed_max_mps (phases.assembled_speed_mps).
    The output stage holds such a vehicle's feed-forward, less the bias the agent has learnt, to
    setpoint.acc_ff_hover_mps2, and a silent vehicle last heard so gets a ghost with at most
    that A (docs/swarm.md, "Ghosts").

    Args: phase (...) Phase values; vel_ned_mps (..., 3) m/s (NaN: not settled).
    Returns: (...) bool.
    """
    v = np.asarray(vel_ned_mps, float)
    return (phase == _HOVER) & (np.einsum("...i,...i->...", v, v) < speed_max_mps * speed_max_mps)


def neighbour_sets_rows(rows, ids, p, v_pos, v_vel, v_flags, v_phase, age, stale_after_s, in_formation, cutoff_m,
                        pred, usable, repel, ghost):
    """Who each own row uses for what this tick (docs/agent.md, "Who takes part in what").

    Row r (own vehicle ids[r], view row rows[r]) and vehicle j:
      trusted: heard within stale_after_s, published with FLAG_OWN_VALID, position and
        velocity finite (p.v not NaN), not the own vehicle;
      pred[r, j] = p_j + v_j age (trusted), p_j otherwise;
      usable: trusted and in a formation phase (consensus);
      repel: trusted, airborne (phase >= STABILISE) and within cutoff_m of the own
        position (pair repulsion; the kernel checks the cutoff again);
      ghost: heard, not trusted, airborne, with a position, not the own vehicle.

    Whole-array numpy, not a @kernel: interpreted onboard, the element loop cost a
    companion about 0.3 ms per plan step with 39 neighbours (10 % of its CPU); this is
    about 15 numpy calls for any R x N, and the simulator's batch takes the same lines.

    Args: rows, ids (R,), rows sorted and unique; p (R, 3); v_pos, v_vel (n, N, 3), v_flags, v_phase, age (n, N):
        the whole view; in_formation: bool by phase value. Outputs pred (R, N, 3),
        usable, repel, ghost (R, N) bool, written.
    """
    if len(rows) == v_pos.shape[0]:  # every receiver row (rows is sorted and unique): the view itself, no copies
        x, u, a, ph, fl = v_pos, v_vel, age, v_phase, v_flags
    else:
        x, u, a, ph, fl = v_pos[rows], v_vel[rows], age[rows], v_phase[rows], v_flags[rows]
    n_veh = x.shape[1]
    not_own = np.arange(n_veh)[None, :] != ids[:, None]
    # One dot product is NaN iff some term is NaN (also inf * 0): "position and velocity known".
    known = ~np.isnan(np.einsum("rjk,rjk->rj", x, u))
    tr = (a <= stale_after_s) & ((fl & FLAG_OWN_VALID) != 0) & known & not_own
    air = ph >= _STABILISE
    # p_j + v_j age where trusted; untrusted entries add 0 * 0 (their age may be inf).
    np.add(x, np.where(tr[:, :, None], u, 0.0) * np.where(tr, a, 0.0)[:, :, None], out=pred)
    usable[:] = tr & in_formation[ph]
    d = pred - p[:, None, :]
    repel[:] = tr & air & (np.einsum("rjk,rjk->rj", d, d) < cutoff_m * cutoff_m)
    ghost[:] = (a < math.inf) & ~tr & air & ~np.isnan(pred[:, :, 0]) & not_own


class Avoidance:
    """The agent's avoidance rules for one mission (every agent draws them alike).

    Args:
        mission: the shared mission (its swarm, apf, setpoint and loss-envelope settings).
        kernels: the agent's row loops (segment_repulsion_rows, pair_repulsion_rows).
    """

    def __init__(self, mission: Mission, kernels: AgentKernels):
        self.mission = mission
        self.kernels = kernels
        self._loss = mission.cfg.swarm.loss.behaviour()  # the mission's model of a silent vehicle

    def takeoff_columns(self, rows: np.ndarray, p: np.ndarray, view: SwarmView, age: np.ndarray, ids: np.ndarray,
                        whole: bool, repel: np.ndarray, u2: np.ndarray) -> None:
        """Ground launch (docs/swarm.md, "Ground take-off"): a neighbour heard on the ground
        (LAUNCH) or taking off (STABILISE) will occupy the column above its take-off point up
        to takeoff_alt_m, whenever its arming succeeds (retries delay some by seconds). Each
        such column repels as a capsule of ghost_radius_m instead of as a point, so an
        assembling vehicle routes around it rather than across it.

        Args: rows (R,) own rows; p (R, 3); view, age (n, N) the swarm as heard; ids (R,) own
            ids; whole: every own row flies formation. Writes: repel (R, N) loses the column
            vehicles (their capsule replaces the point); u2 (R, 3) gains their push.
        """
        m, sw, a = self.mission, self.mission.cfg.swarm, self.mission.cfg.apf
        phase = view.phase if whole else view.phase[rows]
        flags = view.flags if whole else view.flags[rows]
        pos = view.pos_ned_m if whole else view.pos_ned_m[rows]
        col = (phase <= _STABILISE) & (age[rows] <= sw.stale_after_s) & ((flags & FLAG_OWN_VALID) != 0) \
            & np.isfinite(pos).all(axis=-1)
        col[np.arange(len(rows)), ids] = False
        if not col.any():
            return
        repel &= ~col
        ground = m.cfg.ground_z_m
        top = pos.copy()
        top[..., 2] = np.minimum(pos[..., 2], (pos[..., 2] if ground is None else ground) - m.cfg.takeoff_alt_m)
        self.kernels.segment_repulsion_rows(p, top, pos, np.full(col.shape, sw.ghost_radius_m), col,
                                            a.vehicle_gain_mps2, a.vehicle_influence_m, a.kappa, u2)

    def intruders(self, rows: np.ndarray, p: np.ndarray, v: np.ndarray, it: Intruders, age: np.ndarray,
                  u2: np.ndarray) -> None:
        """Senders that claim an own vehicle's id (identity conflicts, docs/swarm.md) repel it
        as vehicles do, by the neighbours' rules: a fresh, valid, airborne one at its predicted
        position within the sensing radius, a silent one as a ghost. Adds into u2 (R, 3).

        Args: rows (R,) own rows; p, v (R, 3) their positions and velocities; it: the view's intruders;
            age (n, K) of every intruder slot, s (inf where unused).
        """
        sw, a, kern = self.mission.cfg.swarm, self.mission.cfg.apf, self.kernels
        n_rows, k = len(rows), it.stamp_s.shape[1]
        nobody = np.full(n_rows, -1, np.int64)  # no slot is the own vehicle; coincidence pushes north
        pred = np.empty((n_rows, k, 3))
        usable, repel, ghost = (np.empty((n_rows, k), np.bool_) for _ in range(3))
        cutoff = vehicle_cutoff_m(a)
        neighbour_sets_rows(rows, nobody, p, it.pos_ned_m, it.vel_ned_mps, it.flags, it.phase, age,
                            sw.stale_after_s, IN_FORMATION, cutoff, pred, usable, repel, ghost)
        kern.pair_repulsion_rows(p, v, pred, it.vel_ned_mps[rows], repel, nobody, a.vehicle_gain_mps2,
                                 a.vehicle_influence_m, cutoff, a.kappa, a.closing_decel_mps2, u2)
        if ghost.any():
            self.ghosts(p, it.pos_ned_m[rows], it.vel_ned_mps[rows], age[rows], it.phase[rows], ghost, u2)

    def ghosts(self, p: np.ndarray, pos: np.ndarray, vel: np.ndarray, age: np.ndarray, phase: np.ndarray,
               ghost: np.ndarray, u2: np.ndarray) -> None:
        """Eq. 30 from the ghosts of silent vehicles (docs/swarm.md, "Ghosts"): every place
        each can reach by its autopilot's companion-loss behaviour, as the mission assumes it
        (swarm.loss), as capsules (companion.control.ghost), with A swarm.ghost_accel_mps2,
        or the feed-forward bound the output stage enforced in the state it was last heard in
        if smaller (settled at station, settled_rows: setpoint.acc_ff_hover_mps2; otherwise
        setpoint.acc_ff_max_mps2).

        Args: p (R, 3) own positions; pos, vel (R, N, 3) last heard; age, phase, ghost (R, N).
            Adds into u2 (R, 3).
        """
        cfg = self.mission.cfg
        sw, a = cfg.swarm, cfg.apf
        sp = cfg.setpoint
        caps = ghost_grid(pos, vel, age, settled_rows(phase, vel, cfg.phases.assembled_speed_mps), ghost, self._loss,
                          min(sp.acc_ff_hover_mps2, sw.ghost_accel_mps2), min(sp.acc_ff_max_mps2, sw.ghost_accel_mps2),
                          cfg.ground_z_m, sw.ghost_radius_m, lag_s=sw.stale_after_s)
        for k in range(N_CAPSULES):
            ca, cb, cr, cu = caps.capsule(k)
            self.kernels.segment_repulsion_rows(p, ca, cb, cr, cu, a.vehicle_gain_mps2, a.vehicle_influence_m,
                                                a.kappa, u2)
