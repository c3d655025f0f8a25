"""Holding the slot against a bias: the agent's integral, and the autopilot's (sans-IO).

Eq. 27 is proportional-derivative: a steady bias (estimator tilt error, accelerometer bias,
a wrong hover thrust, steady wind) leaves a steady slot error of b / |k2_pos|. Something
must integrate it away (docs/formation.md, "Integral action"; docs/agent.md, "Whose
integrator"). Both places that can, do, on one gated residual r (`update`):

* **The agent's own integral** z, at consensus.ki_pos_per_s3 on every axis: it holds what it
  learnt through transit (PX4's horizontal anti-windup bleeds the autopilot's integrator
  whenever the vertical demand points down), and it is all there is in attitude output
  and on axes without an autopilot velocity integrator (ArduPilot's vertical).
* **The autopilot's velocity integrator** (PX4 MPC_XY_VEL_I_ACC, MPC_Z_VEL_I_ACC; ArduPilot
  PSC_VELXY_I), in acceleration output with state setpoints: the agent moves the position
  target by a *drive* d = -c r off the lead state, so that integrator learns at
  vel_i pos_p c = slot_integral.autopilot_ki_per_s3 per metre of r; the output stage
  takes the P loops' pull on d (vel_p pos_p d) out of the feed-forward, so the vehicle
  flies the planner's acceleration as before. Both integrators now integrate the same
  signal, so they share the bias instead of winding against each other (before, PX4's
  integrator saw only the lead of the state setpoint and its anti-windup's leak).

The total rate on a driven axis is their sum; Mission checks the law's stability with it
(MissionConfig.stability_gains). r itself leaves out what eq. 27's consensus term and
eq. 30's repulsion ask of the vehicle, so neither learns a neighbour's lag or an obstacle's
push. The agent's integral grows only near a still slot, unsaturated, with the error stuck
(SlotIntegralConfig); the drive needs only the error stuck within drive_zone_m, also in
transit: PX4's horizontal anti-windup winds its integrator against a sustained
feed-forward while the vertical demand points down, and the drive is what unwinds it
(docs/agent.md, "Whose integrator").
"""
from __future__ import annotations

import numpy as np

from companion.link.dialects.base import PositionLoop
from companion.mission import MissionConfig


class SlotIntegral:
    """The slot-hold integral of n vehicles (module docstring).

    Args:
        cfg: the mission (consensus.ki_pos_per_s3, consensus.k2_pos_per_s2, slot_integral,
            consensus_accel_max_mps2).
        n: vehicles.
    """

    def __init__(self, cfg: MissionConfig, n: int):
        self.cfg = cfg
        self.z_ms = np.zeros((n, 3))
        """(n, 3) the agent's own integral of each vehicle's slot residual, m s (every axis);
        kept across phases: it is a property of the vehicle (its bias)."""
        self.drive_gain = np.zeros((n, 3))
        """(n, 3) metres of drive per metre of residual, per axis (0: no autopilot integrator
        is driven on that axis); set_autopilot_loop."""
        self._drives = False
        """Some row has a drive gain (else update skips the drive: attitude output, unknown loops)."""
        self.drive_ned_m = np.zeros((n, 3))
        """(n, 3) this step's drive: the offset of the position target from the lead state,
        NED m (0 where none)."""

    def set_autopilot_loop(self, rows, loop: PositionLoop | None) -> None:
        """The autopilot of rows has these position loops (acceleration output with state
        setpoints only: the caller decides). None: unknown, nothing is driven (the agent's
        own integral acts on every axis either way)."""
        ki = self.cfg.slot_integral.autopilot_ki_per_s3 if self.cfg.consensus.ki_pos_per_s3 > 0 else 0.0
        self.drive_gain[rows] = (0.0, 0.0, 0.0) if loop is None or ki <= 0 else loop.drive_gain(ki)
        self._drives = bool(self.drive_gain.any())

    def update(self, dt_s: float, rows: np.ndarray, p: np.ndarray, v: np.ndarray, h_pos: np.ndarray,
               h_vel: np.ndarray, resid: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> None:
        """One plan step: integrate the residual where it may grow and drive it where the
        drive's gate is open, then u1 -= k_i z.

        The residual r is the law's position residual (consensus_rows' resid: the slot error
        less what the consensus term asks of the vehicle for its neighbours) plus the repulsion
        over k2_pos: at rest by an obstacle (u1 + u2 = 0) it is 0, with a steady bias b it is
        b / |k2_pos|. It may grow (SlotIntegralConfig) only near a still slot, unsaturated, and
        while the error is stuck; |k_i z| <= accel_max.

        Args:
            dt_s: time since the last plan step, s (NaN or <= 0: nothing to integrate).
            rows: (R,) own rows. p, v: (R, 3) their positions, velocities (m, m/s); h_pos,
                h_vel (R, 3) their slots'; resid (R, 3) m; u1 (R, 3) eq. 27, m/s^2, updated in
                place; u2 (R, 3) the repulsion, m/s^2.
        Writes: drive_ned_m[rows].
        """
        cfg = self.cfg
        si, ki = cfg.slot_integral, cfg.consensus.ki_pos_per_s3
        z = self.z_ms[rows]
        drive = np.zeros((len(rows), 3))
        if dt_s > 0:  # (False for NaN: the first step has nothing to integrate)
            r = resid + u2 / cfg.consensus.k2_pos_per_s2
            # The five squared norms in one call (r, e = p - h, ev = v - h', u1, h'): this runs on
            # every plan step of a small companion, where each numpy call costs more than its maths.
            sq = np.array((r, p - h_pos, v - h_vel, u1, h_vel))
            r2, e2, ev2, u12, hv2 = np.einsum("kij,kij->ki", sq, sq)
            # Stuck, not closing: the vehicle moves slower than eq. 27's slowest pole would move
            # it to cover r (a bias holds it still; a transient's tail decays at >= 0.54/s).
            stuck = np.sqrt(ev2) < si.stuck_rate_per_s * np.sqrt(np.minimum(r2, e2)) + si.stuck_speed_mps
            grow = stuck & (r2 < si.zone_m ** 2) & (u12 < cfg.consensus_accel_max_mps2 ** 2) \
                & (hv2 < si.slot_speed_max_mps ** 2)
            if grow.any():  # (every test above is False where a value is NaN)
                z[grow] += r[grow] * min(dt_s, si.dt_max_s)
                zn = np.sqrt(np.einsum("ij,ij->i", z, z))
                z *= np.minimum(1.0, (si.accel_max_mps2 / ki) / np.maximum(zn, 1e-300))[:, None]
                self.z_ms[rows] = z
            # The drive's gate is wider: stuck is enough (also in transit, also saturated),
            # within drive_zone_m. What holds a vehicle stuck off its slot while the law asks
            # it back is a disturbance, or PX4's velocity integrator wound against the agent's
            # feed-forward by its own anti-windup (docs/agent.md, "Whose integrator"): both are
            # for the integrator to take out.
            go = stuck & (r2 < si.drive_zone_m ** 2)
            if self._drives and go.any():
                d = -self.drive_gain[rows[go]] * r[go]  # (r points from the slot to the vehicle: slot-wards)
                dn = np.sqrt(np.einsum("ij,ij->i", d, d))
                drive[go] = d * np.minimum(1.0, si.drive_max_m / np.maximum(dn, 1e-300))[:, None]
        self.drive_ned_m[rows] = drive
        u1 += self.bias_accel(rows)

    def bias_accel(self, rows) -> np.ndarray:
        """(R, 3) the acceleration the rows' integral adds to eq. 27, -k_i z, NED m/s^2: the bias
        learnt so far (AgentOutput.acc_bias_ned_mps2; 0 with consensus.ki_pos_per_s3 0)."""
        return -self.cfg.consensus.ki_pos_per_s3 * self.z_ms[rows]

    def clear_drive(self) -> None:
        """No drive this step (rows outside formation send none)."""
        self.drive_ned_m.fill(0.0)

