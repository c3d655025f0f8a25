"""The one sans-IO output stage: from the planner's last setpoint to what each autopilot is sent now.

`swarmdrop agent` (one row) and the headless runner (every vehicle of every run) call the
same `OutputStage`, so the flight policy between the planner and the autopilot is the same
lines in both (docs/agent.md, "The output stage"):

1. **Extrapolation.** The planner runs on some ticks only (the agent: every plan_every-th
   and its publishing ticks); in between, a state plan (position and velocity given) is
   advanced along its acceleration to now: p + v dt + a dt^2 / 2, v + a dt.
2. **Slot-hold drive** (acceleration output, companion.slot_hold): a state plan's position
   target is moved by the agent's drive d, so the autopilot's velocity integrator learns
   the bias, and the pull of its P loops on d (vel_p pos_p d per axis: `set_loop`) is taken
   out of the feed-forward, so the vehicle flies the planner's acceleration as before.
3. **Feed-forward bound.** The acceleration sent is at most `acc_ff_max_mps2` (norm). It is
   what an autopilot keeps acting on when the companion falls silent (ArduPilot extrapolates
   velocity and acceleration for GUID_TIMEOUT; PX4 flies the last setpoint for
   COM_OF_LOSS_T), so it bounds the overshoot: v T + A T^2 / 2 (docs/agent.md). A row
   with a tighter bound of its own (settled at station: `set_plan`'s acc_ff_max_mps2) has
   it on the acceleration *less the bias the agent has learnt* (its slot-hold integral,
   acc_bias_ned_mps2): that part only cancels the vehicle's bias, and keeps cancelling it
   after a loss, so it moves nothing; bounding it too would leave a biased vehicle off its
   slot (docs/swarm.md, "Ghosts").
4. **Limits.** PX4's offboard velocity limits (companion.link.limits, the same functions the
   SITL applies to what it receives): nothing the autopilot would clamp is sent.
5. **Geofence.** `mission.geofence`: the position is clipped into the box, and at a face the
   velocity and acceleration pointing further out are zeroed.
6. **Attitude law** (attitude output): eq. 12-16 on the companion (the geometric position law,
   companion.control.geometric.position_law) gives the attitude and collective thrust, the
   tilt is clamped to the autopilot's limit, and the thrust is turned into the autopilot's
   SET_ATTITUDE_TARGET thrust field with the *estimated* hover thrust (`HoverThrustEstimator`:
   a hover-thrust parameter is trusted to ~10 % at best: docs/agent.md).

The row loops are @kernel functions: plain Python for one onboard vehicle, compiled by
sim_bridge.world.jit for a fleet (`OutputKernels`). No I/O, no clock: time is an argument.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from companion.control.geometric import position_law
from companion.control.kernel import kernel
from companion.frames import quat_wxyz_to_rot9, rot9_to_quat_wxyz
from companion.link.dialects.base import PositionLoop
from companion.link.limits import SetpointLimits, clamp_tilt_wxyz, clamp_velocity3, fence_axis
from companion.mission import HoverThrustConfig, MissionConfig
from companion.params import GRAVITY_MPS2
from companion.state import FleetSetpoint

PLAN_NONE, PLAN_FIXED, PLAN_STATE = 0, 1, 2
"""A row's plan: nothing to send; a setpoint sent as it is (a stop, a descent); a state
(position and velocity) advanced along its acceleration between plans."""
SEND_NOTHING, SEND_TRAJECTORY, SEND_ATTITUDE = 0, 1, 2
"""What a row sends now: nothing; SET_POSITION_TARGET_LOCAL_NED; SET_ATTITUDE_TARGET."""


class HoverThrustEstimator:
    """Online estimate of each vehicle's hover thrust (normalised, 0..1), from the
    parameter's value and what the vehicle did with the thrust it was sent.

    Model, per window of `window_s` (NED, z down): the vehicle was sent, in thrust field
    terms, a collective of T/W times the *estimate* h; the autopilot turns that into
    (T/W) (h / h_true) of the weight. So dv_z = g dt - S / h_true (S = the sum of
    g (T/W) cos(tilt) h dt over the window), and one window measures
    h_true = S / (g dt - dv_z). The estimate moves towards each measurement with time
    constant tau_s and stays within the parameter's value times 1 -+ bound_frac.
    Unmodelled vertical disturbances (accelerometer bias, vertical drag) are absorbed
    into it, as in PX4's own hover-thrust estimator.

    Args:
        param: (n,) each autopilot's hover-thrust parameter (NaN: not known yet; set_param).
        cfg: the estimator's settings.
    """

    def __init__(self, param: np.ndarray, cfg: HoverThrustConfig | None = None):
        self.cfg = cfg or HoverThrustConfig()
        n = len(param)
        self.param = np.array(param, float)
        self.estimate = self.param.copy()
        """(n,) the hover thrust the thrust field is computed with."""
        self._t0 = np.full(n, np.nan)
        """(n,) start of each row's open window (NaN: none open)."""
        self._vz0 = np.zeros(n)
        self._s = np.zeros(n)
        self._rate = np.zeros(n)
        """(n,) g (T/W) cos(tilt) h of the last setpoint: it acts until the next one."""
        self._t_last = np.full(n, np.nan)
        self.windows = 0
        """Windows that updated an estimate (statistics)."""

    def set_param(self, row: int, value: float) -> None:
        """The autopilot's parameter became known (or changed): the estimate restarts from it."""
        self.param[row] = value
        self.estimate[row] = value
        self._t0[row] = math.nan

    def update(self, t_s: float, rows: np.ndarray, vz_mps: np.ndarray, tw: np.ndarray, cos_tilt: np.ndarray) -> None:
        """Account one attitude setpoint per row: sent at t_s with collective thrust tw times
        the weight, the vehicle tilted by arccos(cos_tilt), its NED vertical velocity vz_mps.

        Args: rows (R,) the rows that were sent an attitude setpoint; vz_mps, tw, cos_tilt (R,).
        """
        c, g = self.cfg, GRAVITY_MPS2
        cos_min = math.cos(math.radians(c.tilt_max_deg))
        for k, i in enumerate(rows.tolist()):
            t0, vz = self._t0[i], float(vz_mps[k])
            if t0 == t0:  # a window is open: the last setpoint acted from then until now
                gap = t_s - self._t_last[i]
                if 0.0 < gap <= c.window_s:
                    self._s[i] += self._rate[i] * gap
                    if t_s - t0 >= c.window_s - 1e-9:
                        self._measure(i, t_s - t0, vz - self._vz0[i])
                        t0 = math.nan
                else:  # a gap in the stream (or time went back): start afresh
                    t0 = math.nan
            ok = cos_tilt[k] > cos_min and math.isfinite(vz + tw[k])
            if not ok:
                t0 = math.nan
            elif t0 != t0:
                t0, self._vz0[i], self._s[i] = t_s, vz, 0.0
            self._t0[i] = t0
            self._rate[i] = g * tw[k] * cos_tilt[k] * self.estimate[i]
            self._t_last[i] = t_s

    def _measure(self, i: int, dt: float, dvz: float) -> None:
        """One window's measurement h_true = S / (g dt - dv_z), filtered into the estimate."""
        c = self.cfg
        den = GRAVITY_MPS2 * dt - dvz
        if den > 0.25 * GRAVITY_MPS2 * dt and self._s[i] > 0.0:  # the thrust carried the vehicle
            h0 = self.param[i]
            meas = self._s[i] / den
            est = self.estimate[i] + min(1.0, dt / c.tau_s) * (meas - self.estimate[i])
            self.estimate[i] = min(max(est, h0 * (1.0 - c.bound_frac)), h0 * (1.0 + c.bound_frac))
            self.windows += 1


@kernel
def trajectory_rows(t_s, plan_t, kind, pp, pv, pa, bias, drive, stiff, own_p, lim, ff_cap, ff_max, fence, out_kind,
                    out_p, out_v, out_a):
    """Steps 1-5 of the module docstring for every row: the trajectory setpoint now.

    Args:
        t_s: now, mission time, s. plan_t (n,) when each row's plan was made, s; kind (n,)
            PLAN_*; pp, pv, pa (n, 3) the plan's position, velocity, acceleration (mission NED;
            NaN axes not commanded); bias (n, 3) the learnt bias in pa (finite), m/s^2;
            own_p (n, 3) the vehicles' positions (the fence's faces).
        lim: (3,) horizontal speed, climb speed and descent speed limits (m/s); ff_cap the
            acceleration feed-forward bound (m/s^2); ff_max (n,) each row's own bound on its
            acceleration less its bias, where under ff_cap (m/s^2); fence: (7,) 1/0 fence on,
            then its min (3,) and max (3,) corners, mission NED m.
    Written: out_kind (n,) SEND_NOTHING or SEND_TRAJECTORY; out_p, out_v, out_a (n, 3).
    """
    for i in range(kind.shape[0]):
        k = kind[i]
        if k == PLAN_NONE:
            out_kind[i] = SEND_NOTHING
            for j in range(3):
                out_p[i, j], out_v[i, j], out_a[i, j] = math.nan, math.nan, math.nan
            continue
        out_kind[i] = SEND_TRAJECTORY
        a0, a1, a2 = pa[i, 0], pa[i, 1], pa[i, 2]
        if ff_max[i] < ff_cap:  # the row's own bound, on what moves the vehicle: a less the bias
            b0, b1, b2 = bias[i, 0], bias[i, 1], bias[i, 2]
            m0, m1, m2 = a0 - b0, a1 - b1, a2 - b2
            mn = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
            if mn > ff_max[i]:  # (False for NaN)
                s = ff_max[i] / mn
                a0, a1, a2 = b0 + m0 * s, b1 + m1 * s, b2 + m2 * s
        an = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        if an > ff_cap:  # (False for NaN: an acceleration not commanded stays so)
            s = ff_cap / an
            a0, a1, a2 = a0 * s, a1 * s, a2 * s
        p0, p1, p2 = pp[i, 0], pp[i, 1], pp[i, 2]
        v0, v1, v2 = pv[i, 0], pv[i, 1], pv[i, 2]
        if k == PLAN_STATE:
            dt = t_s - plan_t[i]
            h = 0.5 * dt * dt
            p0, p1, p2 = p0 + v0 * dt + a0 * h, p1 + v1 * dt + a1 * h, p2 + v2 * dt + a2 * h
            v0, v1, v2 = v0 + a0 * dt, v1 + a1 * dt, v2 + a2 * dt
            d0, d1, d2 = drive[i, 0], drive[i, 1], drive[i, 2]
            if d0 != 0.0 or d1 != 0.0 or d2 != 0.0:  # the drive, and the P loops' pull on it out of the feed-forward
                p0, p1, p2 = p0 + d0, p1 + d1, p2 + d2
                a0, a1, a2 = a0 - stiff[i, 0] * d0, a1 - stiff[i, 1] * d1, a2 - stiff[i, 2] * d2
                an = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
                if an > ff_cap:  # (the pull it cancels moves nothing: only the stage's bound)
                    s = ff_cap / an
                    a0, a1, a2 = a0 * s, a1 * s, a2 * s
        v0, v1, v2 = clamp_velocity3(v0, v1, v2, lim[0], lim[1], lim[2])
        if fence[0] > 0.0:
            p0, v0, a0 = fence_axis(p0, v0, a0, fence[1], fence[4], own_p[i, 0])
            p1, v1, a1 = fence_axis(p1, v1, a1, fence[2], fence[5], own_p[i, 1])
            p2, v2, a2 = fence_axis(p2, v2, a2, fence[3], fence[6], own_p[i, 2])
        out_p[i, 0], out_p[i, 1], out_p[i, 2] = p0, p1, p2
        out_v[i, 0], out_v[i, 1], out_v[i, 2] = v0, v1, v2
        out_a[i, 0], out_a[i, 1], out_a[i, 2] = a0, a1, a2


@kernel
def attitude_rows(rows, own_p, own_v, own_q, tp, tv, ta, yaw, yaw_rate, prm, tilt_max_rad, out_q, out_tw, out_cos):
    """Step 5 for the rows `rows`: eq. 12-16 on the companion, the tilt clamped.

    Args:
        rows (R,); own_p, own_v (n, 3) the vehicles' states; own_q (n, 4) their attitudes
            (w, x, y, z, NED -> FRD); tp, tv, ta (n, 3), yaw, yaw_rate (n,) the trajectory
            setpoint (trajectory_rows); prm the controller's packed parameters
            (companion.control.geometric.pack_control_params); tilt_max_rad the autopilot's.
    Written, rows only: out_q (n, 4) the attitude to fly; out_tw (n,) the collective thrust
        over the weight; out_cos (n,) the vehicle's cos(tilt) now (the thrust field's and the
        estimator's).
    """
    g = prm[1] * prm[0]  # m g (CP_MASS, CP_G)
    for r in range(rows.shape[0]):
        i = rows[r]
        rot = quat_wxyz_to_rot9(own_q[i, 0], own_q[i, 1], own_q[i, 2], own_q[i, 3])
        row = (tp[i, 0], tp[i, 1], tp[i, 2], tv[i, 0], tv[i, 1], tv[i, 2], ta[i, 0], ta[i, 1], ta[i, 2], yaw[i],
               yaw_rate[i], math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan)
        rot_d, f, _ = position_law((own_p[i, 0], own_p[i, 1], own_p[i, 2]), (own_v[i, 0], own_v[i, 1], own_v[i, 2]),
                                   rot, row, prm)
        w, x, y, z = rot9_to_quat_wxyz(rot_d)
        w, x, y, z = clamp_tilt_wxyz(w, x, y, z, tilt_max_rad)
        out_q[i, 0], out_q[i, 1], out_q[i, 2], out_q[i, 3] = w, x, y, z
        out_tw[i] = f / g
        out_cos[i] = rot[8]


@dataclass(frozen=True)
class OutputKernels:
    """The row loops the stage calls: interpreted by default (onboard); the simulator passes
    their compiled twins (sim_bridge.world.jit.output_kernels)."""

    trajectory_rows: Callable = trajectory_rows
    attitude_rows: Callable = attitude_rows


@dataclass
class OutputRows:
    """What each row sends now (views of the stage's buffers: valid until its next step).

    Attributes:
        send: (n,) SEND_* per row.
        pos_ned_m, vel_ned_mps, acc_ned_mps2: (n, 3) the trajectory setpoint, mission NED
            (NaN axes not commanded); yaw_rad, yaw_rate_radps: (n,).
        att_q_wxyz: (n, 4) attitude rows' attitude (NED -> FRD, w first); thrust_field: (n,)
            their SET_ATTITUDE_TARGET thrust (the autopilot's meaning: the dialect's
            thrust_field); thrust_over_weight: (n,) the collective it stands for.
    """

    send: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    acc_ned_mps2: np.ndarray
    yaw_rad: np.ndarray
    yaw_rate_radps: np.ndarray
    att_q_wxyz: np.ndarray
    thrust_field: np.ndarray
    thrust_over_weight: np.ndarray


class OutputStage:
    """The output stage of n vehicles (module docstring).

    Args:
        n: rows.
        limits: the autopilot's offboard limits (PX4's defaults unless read from it).
        acc_ff_max_mps2: bound on the acceleration feed-forward, m/s^2.
        geofence: (min, max) corners of the mission-frame box, m, or None.
        attitude: send attitude setpoints (else trajectory setpoints).
        ctrl_prm: the geometric controller's packed parameters (attitude output).
        thrust_field: (T/W, hover thrust, cos tilt) -> the autopilot's thrust field (the
            dialect's thrust_field; attitude output).
        hover_thrust: (n,) the autopilots' hover-thrust parameters (NaN: not known yet).
        hover: the hover-thrust estimator's settings.
        kernels: the row loops (default: interpreted).
    """

    def __init__(self, n: int, *, limits: SetpointLimits, acc_ff_max_mps2: float,
                 geofence: tuple | None = None, attitude: bool = False, ctrl_prm: np.ndarray | None = None,
                 thrust_field: Callable[[float, float, float], float] | None = None,
                 hover_thrust: np.ndarray | None = None, hover: HoverThrustConfig | None = None,
                 kernels: OutputKernels | None = None):
        if attitude and (ctrl_prm is None or thrust_field is None):
            raise ValueError("attitude output needs the controller parameters and the dialect's thrust field")
        self.n = n
        self.kernels = kernels or OutputKernels()
        self.limits = limits
        self.lim = np.array([limits.xy_vel_max_mps, limits.z_vel_max_up_mps, limits.z_vel_max_dn_mps])
        self.acc_ff_max_mps2 = float(acc_ff_max_mps2)
        self.ff_max = np.full(n, self.acc_ff_max_mps2)
        """(n,) each row's feed-forward bound for its plan (set_plan), m/s^2: on the acceleration
        less the learnt bias where under acc_ff_max_mps2."""
        self.bias = np.zeros((n, 3))
        """(n, 3) the learnt bias in each row's plan acceleration (set_plan), m/s^2."""
        self.fence = np.zeros(7)
        if geofence is not None:
            self.fence[0], self.fence[1:4], self.fence[4:7] = 1.0, geofence[0], geofence[1]
        self.attitude = attitude
        self.ctrl_prm = ctrl_prm
        self.thrust_field = thrust_field
        self.hover = HoverThrustEstimator(np.full(n, np.nan) if hover_thrust is None else hover_thrust, hover)
        # the plan (set_plan)
        self.plan_t = np.full(n, np.nan)
        self.kind = np.zeros(n, np.int8)
        self.plan = FleetSetpoint.empty(n)
        self.attitude_ok = np.zeros(n, bool)
        # output buffers
        b = self.setpoint = FleetSetpoint.empty(n)
        """The output as a FleetSetpoint (mission frame; attitude rows: att_q_wxyz and, in
        thrust_norm, the thrust field): what a simulated autopilot is handed."""
        self.out = OutputRows(np.zeros(n, np.int8), b.pos_ned_m, b.vel_ned_mps, b.acc_ned_mps2, b.yaw_rad,
                              b.yaw_rate_radps, b.att_q_wxyz, b.thrust_norm, np.full(n, np.nan))
        self._cos = np.full(n, np.nan)
        self.drive = np.zeros((n, 3))
        """(n, 3) the plan's slot-hold drive (AgentOutput.drive_ned_m), m."""
        self.stiffness = np.zeros((n, 3))
        """(n, 3) each autopilot's P-loop acceleration per metre of target offset (set_loop), 1/s^2."""

    def set_loop(self, rows, loop: PositionLoop | None) -> None:
        """The autopilots of rows have these position loops (None: unknown, no compensation).
        Attitude output has no autopilot position loop: nothing is kept."""
        if not self.attitude and loop is not None:
            self.stiffness[rows] = loop.stiffness_per_s2()

    def set_plan(self, t_s: float, sp: FleetSetpoint, q_ok: np.ndarray, drive_ned_m: np.ndarray | None = None,
                 acc_ff_max_mps2: np.ndarray | None = None, acc_bias_ned_mps2: np.ndarray | None = None) -> None:
        """Keep the planner's setpoint (mission frame) as each row's plan from t_s.

        Args:
            sp: n rows (NaN = not commanded; an all-NaN row: send nothing).
            q_ok: (n,) bool, the vehicle's attitude was known when it was planned (attitude
                output flies a state plan only then).
            drive_ned_m: (n, 3) the slot-hold drive (AgentOutput.drive_ned_m), m; None: none.
                Ignored in attitude output and where not finite.
            acc_ff_max_mps2: (n,) each row's feed-forward bound for this plan
                (AgentOutput.acc_ff_max_mps2: tighter settled at station), m/s^2, at most the
                stage's; where tighter, it bounds the acceleration less acc_bias_ned_mps2.
                None: the stage's bound.
            acc_bias_ned_mps2: (n, 3) the bias the agent has learnt, in sp's acceleration
                (AgentOutput.acc_bias_ned_mps2), m/s^2; None or not finite: 0.
        """
        self.ff_max[:] = self.acc_ff_max_mps2 if acc_ff_max_mps2 is None else \
            np.fmin(np.where(np.isfinite(acc_ff_max_mps2), acc_ff_max_mps2, self.acc_ff_max_mps2), self.acc_ff_max_mps2)
        if acc_bias_ned_mps2 is None:
            self.bias.fill(0.0)
        else:
            self.bias[:] = np.where(np.isfinite(acc_bias_ned_mps2), acc_bias_ned_mps2, 0.0)
        if drive_ned_m is None or self.attitude:
            self.drive.fill(0.0)
        else:
            self.drive[:] = np.where(np.isfinite(drive_ned_m), drive_ned_m, 0.0)
        p, v, a = sp.pos_ned_m, sp.vel_ned_mps, sp.acc_ned_mps2
        fp, fv, fa = (np.isfinite(x).all(axis=1) for x in (p, v, a))
        state = fp & fv
        anything = np.isfinite(p).any(axis=1) | np.isfinite(v).any(axis=1) | np.isfinite(a).any(axis=1)
        self.kind[:] = np.where(state, PLAN_STATE, np.where(anything, PLAN_FIXED, PLAN_NONE))
        self.plan_t[:] = t_s
        self.plan.pos_ned_m[:] = p
        self.plan.vel_ned_mps[:] = v
        self.plan.acc_ned_mps2[:] = np.where((state & ~fa)[:, None], 0.0, a)  # a state flies on with no acceleration
        self.plan.yaw_rad[:] = sp.yaw_rad
        self.plan.yaw_rate_radps[:] = sp.yaw_rate_radps
        self.attitude_ok[:] = state & q_ok

    def step(self, t_s: float, own_pos: np.ndarray, own_vel: np.ndarray, own_q: np.ndarray) -> OutputRows:
        """What every row sends at t_s.

        Args:
            own_pos, own_vel: (n, 3) the vehicles' states, mission NED (m, m/s).
            own_q: (n, 4) their attitudes, w first (attitude output only).
        Returns:
            OutputRows (the stage's buffers).
        """
        o, pl = self.out, self.plan
        self.kernels.trajectory_rows(t_s, self.plan_t, self.kind, pl.pos_ned_m, pl.vel_ned_mps, pl.acc_ned_mps2,
                                     self.bias, self.drive, self.stiffness, own_pos, self.lim, self.acc_ff_max_mps2,
                                     self.ff_max, self.fence, o.send, o.pos_ned_m, o.vel_ned_mps, o.acc_ned_mps2)
        o.yaw_rad[:] = pl.yaw_rad
        o.yaw_rate_radps[:] = pl.yaw_rate_radps
        if self.attitude:
            o.att_q_wxyz[:] = math.nan
            h = self.hover.estimate
            rows = np.flatnonzero(self.attitude_ok & (o.send == SEND_TRAJECTORY) & np.isfinite(h)
                                  & np.isfinite(own_q).all(axis=1))
            if len(rows):
                self.kernels.attitude_rows(rows, own_pos, own_vel, own_q, o.pos_ned_m, o.vel_ned_mps,
                                           o.acc_ned_mps2, o.yaw_rad, o.yaw_rate_radps, self.ctrl_prm,
                                           self.limits.tilt_max_rad, o.att_q_wxyz, o.thrust_over_weight, self._cos)
                field = self.thrust_field
                assert field is not None  # (checked at construction)
                for i in rows.tolist():
                    o.thrust_field[i] = field(float(o.thrust_over_weight[i]), float(h[i]), float(self._cos[i]))
                o.send[rows] = SEND_ATTITUDE
                self.hover.update(t_s, rows, own_vel[rows, 2], o.thrust_over_weight[rows], self._cos[rows])
        return o


def output_stage_for(mission: MissionConfig, n: int, *, limits: SetpointLimits, attitude: bool = False,
                     ctrl_prm: np.ndarray | None = None,
                     thrust_field: Callable[[float, float, float], float] | None = None,
                     hover_thrust: np.ndarray | None = None, kernels: OutputKernels | None = None) -> OutputStage:
    """The output stage a mission asks for: its geofence, feed-forward bound and hover-thrust
    estimator settings (mission.geofence, mission.setpoint); the rest as OutputStage."""
    fence = None if mission.geofence is None else (mission.geofence.min_ned_m, mission.geofence.max_ned_m)
    sp = mission.setpoint
    return OutputStage(n, limits=limits, acc_ff_max_mps2=sp.acc_ff_max_mps2, geofence=fence, attitude=attitude,
                       ctrl_prm=ctrl_prm, thrust_field=thrust_field, hover_thrust=hover_thrust, hover=sp.hover_thrust,
                       kernels=kernels)
