"""What a simulated autopilot does on its own, shared by the SITL and the headless runner.

Its position and velocity loops (`PositionController`, below) are one kernel for every
autopilot, run by the fused physics stepper; each autopilot's parameters set its gains.

After a carrier release the autopilot, not the companion, recovers the vehicle
(PX4 COM_THROW_EN, ArduCopter THROW): it commands zero velocity until the vehicle
is upright, slow and no longer spinning, then holds where it comes to rest. The
SITL's per-vehicle state machine and the headless runner's vectorised model
(`AutopilotModel`) call these same functions, so both simulators recover a vehicle
identically.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from pydantic import Field, field_validator
from pydantic.dataclasses import dataclass as pydantic_dataclass

from companion import frames
from companion.config import STRICT
from companion.control.geometric import SP_ACC, SP_POS, SP_VEL, pack_setpoint
from companion.link.dialects import DIALECTS, dialect_named
from companion.link.dialects.base import AfterLoss, CarryOn, LossBehaviour
from companion.state import FleetSetpoint, FleetState

THROW_TILT_DEG = 10.0
"""Throw recovery is done below this tilt (SITL parameter SD_THR_TILT)."""
THROW_RATE_RADPS = 0.5
"""... and below this body-rate norm (SD_THR_RATE)."""
THROW_SPEED_MPS = 0.5
"""... and below this speed (SD_THR_SPEED)."""
THROW_UPRIGHT_COS = 0.866
"""An autopilot that uprights a throw first (ArduCopter Throw_Uprighting) flies a level attitude
on attitude alone until cos(tilt) exceeds this (30 deg; mode_throw.cpp throw_attitude_good) ..."""
THROW_UPRIGHT_THRUST = 0.5
"""... at this throttle, without angle boost (mode_throw.cpp: 50 %, to maximise the righting moment)."""
HOLD_BRAKE_MPS2 = 3.0
"""Deceleration assumed when Hold captures the point where the vehicle will stop."""
HOLD_BRAKE_MAX_M = 10.0
"""Longest braking distance Hold looks ahead."""
ON_GROUND_TOL_M = 0.02
"""A vehicle this close to the ground counts as on it (land detection)."""
LAND_SPEED_MAX_MPS = 0.3
"""... and slower than this ..."""
LAND_DETECT_S = 0.2
"""... for this long: landed."""
DISARM_LAND_S = 2.0
"""Auto-disarm this long after landing (PX4 COM_DISARM_LAND's default; the headless model's)."""


def throw_recovered(cos_tilt, rate_radps, speed_mps, tilt_deg: float = THROW_TILT_DEG,
                    rate_max_radps: float = THROW_RATE_RADPS, speed_max_mps: float = THROW_SPEED_MPS):
    """True where a thrown vehicle counts as recovered; scalars or arrays of one shape.

    Args:
        cos_tilt: cosine of the angle between body z and world z (R[2, 2]).
        rate_radps: body-rate norm, rad/s.
        speed_mps: speed, m/s.
    """
    return (cos_tilt > np.cos(np.radians(tilt_deg))) & (rate_radps < rate_max_radps) & (speed_mps < speed_max_mps)


def on_ground_and_slow(pos_z_m, speed_mps, ground_z_m: float):
    """True where a vehicle touches the ground and barely moves (landing detection, before its
    LAND_DETECT_S dwell); scalars or arrays of one shape. NED: the ground is at z = ground_z_m."""
    return (pos_z_m >= ground_z_m - ON_GROUND_TOL_M) & (speed_mps < LAND_SPEED_MAX_MPS)


def hold_point(pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray) -> np.ndarray:
    """Where Hold brings a flying vehicle to rest: its position plus the braking
    distance at HOLD_BRAKE_MPS2 along its velocity (at most HOLD_BRAKE_MAX_M).

    Args:
        pos_ned_m, vel_ned_mps: (..., 3).
    Returns:
        (..., 3) NED point, m.
    """
    v = np.asarray(vel_ned_mps, float)
    speed = np.sqrt(np.sum(v * v, axis=-1, keepdims=True))
    ahead = np.minimum(speed / (2.0 * HOLD_BRAKE_MPS2), HOLD_BRAKE_MAX_M / np.maximum(speed, 1e-9))
    return np.asarray(pos_ned_m, float) + np.where(speed > 0.05, v * ahead, 0.0)


AP_DOCKED, AP_THROW, AP_HOLD, AP_OFFBOARD, AP_LOST, AP_LAND, AP_DESCEND, AP_FALL = 0, 1, 2, 3, 4, 5, 6, 7
"""AutopilotModel modes: on the carrier; recovering a throw; holding; flying the agent's
setpoints; the agent silent, its last setpoint still acting (until the LossBehaviour's
timeout); then landing, descending with no horizontal control, or falling (motors off)."""


@njit(cache=True)
def _commanded(pos, vel, acc):
    """(N,) bool: the row commands something, a finite position, velocity or acceleration
    component (an all-NaN row is the agent sending nothing)."""
    out = np.zeros(pos.shape[0], np.bool_)
    for i in range(pos.shape[0]):
        for a in range(3):
            if pos[i, a] == pos[i, a] or vel[i, a] == vel[i, a] or acc[i, a] == acc[i, a]:
                out[i] = True
                break
    return out


def moved_on(pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray, acc_ned_mps2: np.ndarray,
             tau_s) -> tuple[np.ndarray, np.ndarray]:
    """(position, velocity) of targets that moved on for tau_s along their velocity and
    acceleration (ArduPilot GUIDED between setpoints and until GUID_TIMEOUT); (..., 3) arrays,
    tau_s broadcast against their leading axes; NaN axes stay NaN."""
    tau = np.asarray(tau_s, float)[..., None]
    acc = np.where(np.isfinite(acc_ned_mps2), acc_ned_mps2, 0.0)
    vel0 = np.where(np.isfinite(vel_ned_mps), vel_ned_mps, 0.0)
    return pos_ned_m + vel0 * tau + 0.5 * acc * tau * tau, vel_ned_mps + acc * tau


def braked_velocity(vel0_ned_mps: np.ndarray, tau_s, brake_hor_mps2: float,
                    brake_ver_mps2: float) -> tuple[np.ndarray, np.ndarray]:
    """(velocity, acceleration) of velocity targets zeroed tau_s ago from vel0 and brought to
    rest at the braking limits, horizontally and vertically (ArduPilot GUIDED at GUID_TIMEOUT:
    the zeroed velocity target through its kinematic shaping, without the jerk limit);
    (..., 3) arrays, tau_s broadcast against their leading axes."""
    v0 = np.asarray(vel0_ned_mps, float)
    tau = np.asarray(tau_s, float)[..., None]
    vel, acc = np.zeros_like(v0), np.zeros_like(v0)
    for axes, brake in ((slice(0, 2), brake_hor_mps2), (slice(2, 3), brake_ver_mps2)):
        speed = np.sqrt(np.sum(v0[..., axes] ** 2, axis=-1, keepdims=True))
        going = (speed > 0.0) & (brake * tau < speed)
        unit = np.divide(v0[..., axes], speed, out=np.zeros_like(v0[..., axes]), where=speed > 0.0)
        vel[..., axes] = np.where(going, v0[..., axes] - unit * brake * tau, 0.0)
        acc[..., axes] = np.where(going, -unit * brake, 0.0)
    return vel, acc


def _default_loss() -> LossBehaviour:
    return dialect_named("px4").loss_behaviour({})


@dataclass
class AutopilotModel:
    """The headless stand-in for each vehicle's autopilot, vectorised (N vehicles).

    It does what the SITL's autopilot does on its own (sim_bridge.world.autopilot_model):
    after a release it recovers the vehicle (zero velocity, heading held) until the
    throw thresholds hold, then holds where it comes to rest, and flies the agent's
    setpoints once the agent sends any (the agent sends nothing while it lets the
    autopilot recover the vehicle). Its `ready` is what the agent is told. When the agent
    falls silent it does what `loss` (the autopilot's LossBehaviour, from the companion
    dialect and its parameters) says: the last setpoint keeps acting for loss.timeout_s
    (as it was, or moving on along its velocity and acceleration), then hold (at the
    target where it stopped, or where the vehicle comes to rest), land, descend with no
    horizontal control, or motors off. Its position loops (`loop`) are what the caller
    hands Physics.step; it clears their memory at a release.
    """

    mode: np.ndarray
    hold_pos: np.ndarray
    hold_yaw: np.ndarray
    all_offboard: bool = False
    """Every vehicle flew offboard after the last call (then a call that finds every
    vehicle still commanded only returns the agent's setpoints)."""
    ground_z_m: float = math.inf
    """NED z of the ground (inf: none; nothing ever lands)."""
    disarmed: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, bool))
    """(N,) landed and auto-disarmed: the vehicle rests, its rotors stopped."""
    ground_since_s: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    """(N,) since when the vehicle has rested on the ground (NaN: it does not)."""
    loss: LossBehaviour = dataclasses.field(default_factory=_default_loss)
    """What the modelled autopilot does when the agent falls silent (default: PX4's defaults)."""
    loop: PositionController = dataclasses.field(default_factory=lambda: PositionController(0))
    """(N rows) the autopilots' position loops; the caller sets their gains."""
    last_sp: FleetSetpoint = dataclasses.field(default_factory=lambda: FleetSetpoint.empty(0))
    """(N) the last setpoint each agent sent."""
    last_cmd_s: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    """(N) when each agent last sent one, s."""
    brake_vel0: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    """(N, 3) a velocity target zeroed at its timeout (ArduPilot), NaN where none: braked to rest."""
    upright_first: bool = False
    """A throw is first uprighted on attitude alone (level, THROW_UPRIGHT_THRUST) until
    cos(tilt) > THROW_UPRIGHT_COS (ArduCopter; AutopilotBehaviour.throw_uprights_first)."""
    _touching: bool = False

    @classmethod
    def docked(cls, n: int, ground_z_m: float | None = None, loss: LossBehaviour | None = None) -> "AutopilotModel":
        return cls(np.full(n, AP_DOCKED, dtype=np.int8), np.zeros((n, 3)), np.zeros(n),
                   ground_z_m=math.inf if ground_z_m is None else float(ground_z_m), disarmed=np.zeros(n, bool),
                   ground_since_s=np.full(n, np.nan), loss=loss or _default_loss(), loop=PositionController(n),
                   last_sp=FleetSetpoint.empty(n), last_cmd_s=np.full(n, -math.inf),
                   brake_vel0=np.full((n, 3), np.nan))

    @property
    def ready(self) -> np.ndarray:
        return self.mode >= AP_HOLD

    def detect_landing(self, t_s: float, state: FleetState) -> None:
        """Land detection and auto-disarm in any mode, as the SITL's autopilot does
        (sim_bridge.world.autopilot_model): on the ground and slow for LAND_DETECT_S is landed,
        DISARM_LAND_S later it disarms. A disarmed vehicle rests with its rotors stopped.
        Costs one comparison per vehicle while nobody is near the ground."""
        if self.ground_z_m == math.inf:
            return
        z = state.pos_ned_m[:, 2]
        if not self._touching and not (z >= self.ground_z_m - ON_GROUND_TOL_M).any():
            return
        touch = on_ground_and_slow(z, np.linalg.norm(state.vel_ned_mps, axis=1), self.ground_z_m) \
            & (self.mode != AP_DOCKED) & ~self.disarmed
        self.ground_since_s[touch & np.isnan(self.ground_since_s)] = t_s
        self.ground_since_s[~touch & ~self.disarmed] = np.nan
        done = touch & (t_s - self.ground_since_s >= LAND_DETECT_S + DISARM_LAND_S - 1e-9)
        if done.any():
            self.disarmed |= done
            state.vel_ned_mps[done] = 0.0
            state.omega_body_radps[done] = 0.0
            state.rotor_speed_radps[done] = 0.0
            self.loop.reset(done)
        self._touching = bool(touch.any())

    def release(self, rows: np.ndarray, state: FleetState) -> None:
        self.mode[rows] = AP_THROW
        self.all_offboard = False
        self.hold_yaw[rows] = frames.yaw_rad(state.rot_body_to_ned[rows])
        self.loop.reset(rows)

    def setpoint(self, state: FleetState, agent_sp: FleetSetpoint, t_s: float) -> FleetSetpoint:
        """The inner-loop setpoint of every vehicle at t_s (advances the mode machine).
        When every vehicle flies offboard this is agent_sp itself, not a copy."""
        commanded = _commanded(agent_sp.pos_ned_m, agent_sp.vel_ned_mps, agent_sp.acc_ned_mps2)
        self._remember(agent_sp, commanded, t_s)
        if self.all_offboard and commanded.all():
            return agent_sp  # the usual case once the swarm flies
        thr = self.mode == AP_THROW
        if thr.any():
            r = state.rot_body_to_ned[thr]
            done = throw_recovered(r[:, 2, 2], np.linalg.norm(state.omega_body_radps[thr], axis=1),
                                   np.linalg.norm(state.vel_ned_mps[thr], axis=1))
            rows = np.flatnonzero(thr)[done]
            self.mode[rows] = AP_HOLD
            self.hold_pos[rows] = hold_point(state.pos_ned_m[rows], state.vel_ned_mps[rows])
            self.hold_yaw[rows] = frames.yaw_rad(state.rot_body_to_ned[rows])
        self._lose(state, commanded, t_s)
        back = ((self.mode == AP_HOLD) | (self.mode == AP_LOST) | (self.mode == AP_LAND) | (self.mode == AP_DESCEND))
        self.mode[back & commanded] = AP_OFFBOARD  # the agent speaks again (and re-engages)
        self.brake_vel0[back & commanded] = np.nan
        off = self.mode == AP_OFFBOARD
        self.all_offboard = bool(off.all())
        if self.all_offboard:
            return agent_sp
        sp = FleetSetpoint.empty(len(self.mode))
        sp.assign(off, agent_sp.select(off))
        thr = self.mode == AP_THROW
        sp.vel_ned_mps[thr] = 0.0
        sp.yaw_rad[thr] = self.hold_yaw[thr]
        if self.upright_first and thr.any():
            up = thr & (state.rot_body_to_ned[:, 2, 2] <= THROW_UPRIGHT_COS)
            if up.any():  # level on attitude alone, half throttle
                sp.vel_ned_mps[up], sp.yaw_rad[up] = np.nan, np.nan
                yaw = self.hold_yaw[up]
                sp.att_q_wxyz[up] = np.column_stack([np.cos(yaw / 2), np.zeros_like(yaw), np.zeros_like(yaw),
                                                     np.sin(yaw / 2)])
                sp.thrust_norm[up] = THROW_UPRIGHT_THRUST
                sp.body_rate_radps[up] = 0.0
        hold = self.mode == AP_HOLD
        sp.pos_ned_m[hold] = self.hold_pos[hold]
        sp.yaw_rad[hold] = self.hold_yaw[hold]
        braking = hold & np.isfinite(self.brake_vel0[:, 0])
        if braking.any():  # a zeroed velocity target: no position, brought to rest
            lb = self.loss
            sp.pos_ned_m[braking] = np.nan
            sp.vel_ned_mps[braking], sp.acc_ned_mps2[braking] = braked_velocity(
                self.brake_vel0[braking], t_s - self.last_cmd_s[braking] - lb.timeout_s, lb.brake_hor_mps2,
                lb.brake_ver_mps2)
        lost = self.mode == AP_LOST
        if lost.any():
            sp.assign(lost, self.last_sp.select(lost))
            if self.loss.carry_on == CarryOn.VELOCITY_ACCELERATION:
                sp.pos_ned_m[lost], sp.vel_ned_mps[lost] = moved_on(
                    sp.pos_ned_m[lost], sp.vel_ned_mps[lost], sp.acc_ned_mps2[lost], t_s - self.last_cmd_s[lost])
        land = self.mode == AP_LAND
        sp.pos_ned_m[land, :2] = self.hold_pos[land, :2]
        sp.vel_ned_mps[land, 2] = self.loss.descent_speed_mps
        sp.yaw_rad[land] = self.hold_yaw[land]
        down = self.mode == AP_DESCEND
        sp.acc_ned_mps2[down, :2] = 0.0
        sp.vel_ned_mps[down, 2] = self.loss.descent_speed_mps
        sp.yaw_rad[down] = self.hold_yaw[down]
        fall = self.mode == AP_FALL
        if fall.any():
            sp.att_q_wxyz[fall] = frames.rot_to_quat_wxyz(state.rot_body_to_ned[fall])
            sp.thrust_norm[fall] = 0.0
            sp.body_rate_radps[fall] = 0.0
        return sp

    def _remember(self, agent_sp: FleetSetpoint, commanded: np.ndarray, t_s: float) -> None:
        """Keep each agent's last setpoint and when it came (what acts on after a loss)."""
        if commanded.all():
            np.copyto(self._last_block, pack_setpoint(agent_sp))
            self.last_cmd_s.fill(t_s)
        elif commanded.any():
            np.copyto(self._last_block, pack_setpoint(agent_sp), where=commanded[:, None])
            self.last_cmd_s[commanded] = t_s

    @property
    def _last_block(self) -> np.ndarray:
        block = self.last_sp.pos_ned_m.base
        assert block is not None  # (last_sp is made by FleetSetpoint.empty: its fields share one block)
        return block

    def _lose(self, state: FleetState, commanded: np.ndarray, t_s: float) -> None:
        """Offboard rows whose agent fell silent fly its last setpoint; past the timeout they
        do what the LossBehaviour says."""
        self.mode[(self.mode == AP_OFFBOARD) & ~commanded] = AP_LOST
        lb = self.loss
        over = (self.mode == AP_LOST) & ~commanded & (t_s - self.last_cmd_s > lb.timeout_s + 1e-9)
        if not over.any():
            return
        rows = np.flatnonzero(over)
        pos, vel = state.pos_ned_m[rows], state.vel_ned_mps[rows]
        self.hold_pos[rows] = hold_point(pos, vel)
        self.hold_yaw[rows] = frames.yaw_rad(state.rot_body_to_ned[rows])
        if lb.then == AfterLoss.HOLD:
            self.mode[rows] = AP_HOLD
            if lb.carry_on == CarryOn.VELOCITY_ACCELERATION:
                # a position target stops where it moved on to; a velocity target is zeroed, braking
                last = self.last_sp
                target, vel = moved_on(last.pos_ned_m[rows], last.vel_ned_mps[rows], last.acc_ned_mps2[rows],
                                       np.full(len(rows), lb.timeout_s))
                has = np.isfinite(target).all(axis=1)
                self.hold_pos[rows[has]] = target[has]
                vel_only = ~has & np.isfinite(vel).all(axis=1)
                self.brake_vel0[rows[vel_only]] = vel[vel_only]
        elif lb.then in (AfterLoss.LAND, AfterLoss.RETURN):
            self.mode[rows] = AP_LAND
        elif lb.then == AfterLoss.MOTORS_OFF:
            self.mode[rows] = AP_FALL
        else:  # DESCEND (a pilot's mode without a pilot)
            self.mode[rows] = AP_DESCEND


# ----------------------------------------------------------------------------- the autopilot's config
@pydantic_dataclass(config=STRICT)
class AutopilotConfig:
    """The simulated autopilots (scenario `autopilot:`): which one the headless runner's
    AutopilotModel stands in for (a companion dialect's name; the SITL flies the autopilot
    its own `dialect` / --dialect names), and how far off each vehicle's hover-thrust
    parameter is (hover_thrust_error: e_k uniform in +-this fraction per vehicle; the real
    ArduPilot 4.6 SITL read 0.390 while hovering at 0.364, 7 %).

    Raises:
        pydantic.ValidationError: an unknown autopilot, or hover_thrust_error not in [0, 0.5).
    """

    name: str = "px4"
    hover_thrust_error: float = Field(default=0.0, ge=0.0, lt=0.5)

    @field_validator("name")
    @classmethod
    def _known(cls, name: str) -> str:
        if name not in DIALECTS:
            raise ValueError(f"unknown autopilot {name!r} (known: {', '.join(sorted(DIALECTS))})")
        return name


# ----------------------------------------------------------------------------- hover thrust
_HOVER_STREAM = 0x484F5652  # "HOVR": the hover-thrust parameter errors, apart from every other stream


def hover_thrust_errors(max_fraction: float, n: int, seed: int) -> np.ndarray:
    """(n,) fractional error e_k of each vehicle's hover-thrust parameter (MPC_THR_HOVER,
    MOT_THST_HOVER): uniform in +-max_fraction, from the seed's own stream. The parameter
    the autopilot reports and flies by is the airframe's true hover thrust times (1 + e_k);
    the physics keeps the true thrust. 0 (the default) draws nothing: all zero."""
    if max_fraction <= 0.0 or n == 0:
        return np.zeros(n)
    return np.random.default_rng([seed, _HOVER_STREAM]).uniform(-max_fraction, max_fraction, n)


# ----------------------------------------------------------------------------- position loops
# The autopilot's own position and velocity loops (PX4 mc_pos_control PositionControl.cpp,
# ArduCopter AC_PosControl), run by the fused physics stepper at every physics step on every
# position-family setpoint (position, velocity, acceleration; attitude setpoints bypass it):
# they turn the setpoint into the acceleration the inner geometric controller then flies, as
# the real autopilots hand their attitude controller a thrust vector. One kernel for both
# autopilots: a row's STYLE picks PX4's or ArduPilot's structure, its gains come from the
# autopilot's own parameter table (sim_bridge/sitl/autopilots/, `position_loop`).

LOOP_OFF, LOOP_PX4, LOOP_ARDUPILOT = 0, 1, 2
"""Gain-row STYLE: no loop (the setpoint goes to the inner controller as it is), PX4, ArduPilot."""

(G_STYLE, G_POS_P_XY, G_POS_P_Z, G_VEL_P_XY, G_VEL_I_XY, G_VEL_D_XY, G_VEL_P_Z, G_VEL_I_Z, G_VEL_D_Z,
 G_VEL_MAX_XY, G_VEL_MAX_UP, G_VEL_MAX_DN, G_TILT_MAX, G_THR_MIN, G_THR_MAX, G_THR_XY_MARGIN, G_HOVER_PARAM,
 G_HOVER_TRUE, G_VEL_IMAX_XY, G_VEL_IMAX_Z, G_ACC_Z_P, G_ACC_Z_I, G_ACC_Z_IMAX, G_VEL_ERR_LP_HZ, G_VEL_Z_ERR_LP_HZ,
 G_VEL_D_LP_HZ, G_ACC_ERR_LP_HZ, G_POS_ACC_XY, G_POS_ACC_Z, G_TILT_COS, G_TILT_SIN) = range(31)
N_G = 31
"""Gain-row layout (SI units: 1/s, 1/s^2, m/s, m/s^2, rad, normalised thrust, Hz)."""
M_INT, M_VPREV, M_DFILT, M_EFILT, M_ACC_I, M_ACC_E, M_LIMIT, M_STARTED = 0, 3, 6, 9, 12, 13, 14, 17
N_M = 18
"""Memory-row layout: velocity integrator (3, m/s^2), previous velocity (3), filtered
derivative term (3), filtered velocity error (3, ArduPilot), vertical acceleration-loop
integrator (thrust) and its filtered error (ArduPilot), the limit vector of the last
step (3, ArduPilot), and whether the row has run since its last reset."""

_ANGLE_BOOST_COS_MIN = 0.1
"""ArduPilot's angle boost divides by max(cos(lean), 0.1) (companion.link.dialects.ardupilot)."""


@dataclass(frozen=True)
class PositionLoopGains:
    """One vehicle's position and velocity loops in SI units, as its autopilot's parameters
    set them (built by the autopilot behaviour from its table: PX4 MPC_*, ArduPilot PSC_*
    converted from cm). Defaults: PX4's (mc_pos_control, v1.14-v1.16).

    style: LOOP_PX4 (P on position, PID on velocity with D on the measured velocity
    derivative, tracking anti-windup horizontally, conditional integration and |I| <= g
    vertically, thrust from the hover-thrust parameter) or LOOP_ARDUPILOT (square-root
    P on position, PID on the filtered velocity error with the integrator held against
    the acceleration limit and clamped to IMAX, an acceleration PI loop to throttle
    vertically). hover_param is what the autopilot believes hovers, hover_true what does.
    """

    style: int = LOOP_PX4
    pos_p_xy_per_s: float = 0.95
    pos_p_z_per_s: float = 1.0
    vel_p_xy_per_s: float = 1.8
    vel_i_xy_per_s2: float = 0.4
    vel_d_xy: float = 0.2
    vel_p_z_per_s: float = 4.0
    vel_i_z_per_s2: float = 2.0
    vel_d_z: float = 0.0
    vel_max_xy_mps: float = 12.0
    vel_max_up_mps: float = 3.0
    vel_max_dn_mps: float = 1.5
    tilt_max_rad: float = math.radians(45.0)
    thr_min: float = 0.12
    thr_max: float = 1.0
    thr_xy_margin: float = 0.3
    hover_param: float = 0.5
    hover_true: float = 0.5
    vel_imax_xy_mps2: float = math.inf
    vel_imax_z_mps2: float = math.inf
    acc_z_p_per_mps2: float = 0.0
    """ArduPilot: throttle per m/s^2 of vertical acceleration error (PSC_ACCZ_P / 10)."""
    acc_z_i_per_mps2s: float = 0.0
    """ArduPilot: throttle per m/s^2 s (PSC_ACCZ_I / 10)."""
    acc_z_imax: float = 0.0
    """ArduPilot: integrator limit, throttle (PSC_ACCZ_IMAX / 1000; at least the hover throttle)."""
    vel_err_lp_hz: float = 0.0
    """Low-pass on the horizontal velocity error (ArduPilot PSC_VELXY_FLTE; 0: none)."""
    vel_z_err_lp_hz: float = 0.0
    """Low-pass on the vertical velocity error (ArduPilot PSC_VELZ_FLTE; 0: none)."""
    vel_d_lp_hz: float = 5.0
    """Low-pass of the D term's input (PX4 MPC_VELD_LP, ArduPilot PSC_VELXY_FLTD; 0: none)."""
    acc_err_lp_hz: float = 0.0
    """ArduPilot: low-pass on the vertical acceleration error (PSC_ACCZ_FLTE)."""
    pos_acc_xy_mps2: float = 0.0
    """ArduPilot: the square-root position controller's acceleration (WPNAV_ACCEL; 0: linear P)."""
    pos_acc_z_mps2: float = 0.0
    """ArduPilot: the same vertically (WPNAV_ACCEL_Z)."""

    def row(self) -> np.ndarray:
        """The (N_G,) gain row the kernel reads."""
        return np.array([self.style, self.pos_p_xy_per_s, self.pos_p_z_per_s, self.vel_p_xy_per_s,
                         self.vel_i_xy_per_s2, self.vel_d_xy, self.vel_p_z_per_s, self.vel_i_z_per_s2, self.vel_d_z,
                         self.vel_max_xy_mps, self.vel_max_up_mps, self.vel_max_dn_mps, self.tilt_max_rad,
                         self.thr_min, self.thr_max, self.thr_xy_margin, self.hover_param, self.hover_true,
                         self.vel_imax_xy_mps2, self.vel_imax_z_mps2, self.acc_z_p_per_mps2, self.acc_z_i_per_mps2s,
                         self.acc_z_imax, self.vel_err_lp_hz, self.vel_z_err_lp_hz, self.vel_d_lp_hz, self.acc_err_lp_hz,
                         self.pos_acc_xy_mps2, self.pos_acc_z_mps2, math.cos(self.tilt_max_rad),
                         math.sin(self.tilt_max_rad)], dtype=np.float64)


class PositionController:
    """The position loops of N vehicles: per-row gains (N, N_G) and memory (N, N_M), which
    the physics stepper runs and updates (Physics.step(..., loop=...)).

    Args:
        n: vehicles; every row starts with no loop (LOOP_OFF) until `set_gains`.
    """

    def __init__(self, n: int):
        self.gains = np.zeros((n, N_G))
        self.memory = np.zeros((n, N_M))

    def set_gains(self, rows, gains: PositionLoopGains) -> None:
        """Give rows (an index, slice, mask or index array) these gains; memory is kept."""
        self.gains[rows] = gains.row()

    def reset(self, rows) -> None:
        """Clear the integrators and filters of rows (on the ground, at a release, disarmed):
        the next step starts them from the vehicle's state."""
        self.memory[rows] = 0.0

    def view(self, rows: slice) -> "PositionController":
        """A controller over a contiguous block of rows that shares this one's arrays."""
        out = PositionController(0)
        out.gains, out.memory = self.gains[rows], self.memory[rows]
        return out


@njit(cache=True, inline="always")
def _lp_alpha(dt, hz):
    """First-order low-pass coefficient for cut-off hz at step dt (1: no filter)."""
    if hz <= 0.0:
        return 1.0
    b = 2.0 * math.pi * hz * dt
    return b / (1.0 + b)


@njit(cache=True, inline="always")
def _sqrt_controller(err, p, acc, dt):
    """ArduPilot's sqrt_controller: P for small errors, a square root beyond acc/p^2 so that
    braking needs at most acc; never asks for more than closes the error in one step."""
    if acc <= 0.0 or p <= 0.0:
        out = err * p
    else:
        lin = acc / (p * p)
        if err > lin:
            out = math.sqrt(2.0 * acc * (err - 0.5 * lin))
        elif err < -lin:
            out = -math.sqrt(2.0 * acc * (-err - 0.5 * lin))
        else:
            out = err * p
    if dt > 0.0:
        lim = abs(err) / dt
        out = min(max(out, -lim), lim)
    return out


@njit(cache=True, inline="always")
def _add_if_finite(setpoint, addition):
    """PX4 ControlMath::addIfNotNan: the sum if both are finite, the one that is if one is."""
    if math.isfinite(setpoint):
        return setpoint + addition if math.isfinite(addition) else setpoint
    return addition


@njit(cache=True, inline="always")
def _p_axis(ps, x, kp):
    return kp * (ps - x) if math.isfinite(ps) else math.nan


@njit(cache=True, inline="always")
def _px4_loop(p, v, sp, g, m, dt, grav):
    """PX4 PositionControl::_positionControl, _velocityControl, _accelerationControl (one
    step): the normalised thrust vector (NED, up is -z) the attitude controller gets."""
    hov = g[G_HOVER_PARAM]
    # velocity derivative (BlockDerivative on the velocity, low-passed at MPC_VELD_LP), kept in m
    a_d = _lp_alpha(dt, g[G_VEL_D_LP_HZ])
    if m[M_STARTED] == 0.0:
        for k in range(3):
            m[M_VPREV + k] = v[k]
            m[M_DFILT + k] = 0.0
        m[M_STARTED] = 1.0
    inv_dt = 1.0 / dt
    for k in range(3):
        m[M_DFILT + k] += ((v[k] - m[M_VPREV + k]) * inv_dt - m[M_DFILT + k]) * a_d
        m[M_VPREV + k] = v[k]
    # position P, added to the velocity feed-forward where both are given
    vp0 = _p_axis(sp[SP_POS], p[0], g[G_POS_P_XY])
    vp1 = _p_axis(sp[SP_POS + 1], p[1], g[G_POS_P_XY])
    vp2 = _p_axis(sp[SP_POS + 2], p[2], g[G_POS_P_Z])
    vs0 = _add_if_finite(sp[SP_VEL], vp0)
    vs1 = _add_if_finite(sp[SP_VEL + 1], vp1)
    vs2 = _add_if_finite(sp[SP_VEL + 2], vp2)
    # constrainXY: the position part has priority over the feed-forward; then z
    if math.isfinite(vs0) and math.isfinite(vs1):
        v0x = vp0 if math.isfinite(vp0) else 0.0
        v0y = vp1 if math.isfinite(vp1) else 0.0
        v1x, v1y = vs0 - v0x, vs1 - v0y
        vmax = g[G_VEL_MAX_XY]
        if (v0x + v1x) ** 2 + (v0y + v1y) ** 2 > vmax * vmax:
            n0 = math.sqrt(v0x * v0x + v0y * v0y)
            if n0 >= vmax or (v1x - v0x) ** 2 + (v1y - v0y) ** 2 < 1e-6:
                vs0, vs1 = v0x / n0 * vmax, v0y / n0 * vmax
            elif n0 < 0.001:
                n1 = math.sqrt(v1x * v1x + v1y * v1y)
                vs0, vs1 = v1x / n1 * vmax, v1y / n1 * vmax
            else:
                n1 = math.sqrt(v1x * v1x + v1y * v1y)
                ux, uy = v1x / n1, v1y / n1
                mm = ux * v0x + uy * v0y
                c = v0x * v0x + v0y * v0y - vmax * vmax
                sc = -mm + math.sqrt(mm * mm - c)
                vs0, vs1 = v0x + ux * sc, v0y + uy * sc
    if math.isfinite(vs2):
        vs2 = min(max(vs2, -g[G_VEL_MAX_UP]), g[G_VEL_MAX_DN])
    # velocity PID (D on the measured velocity derivative), added to the acceleration feed-forward
    kv, kvz = g[G_VEL_P_XY], g[G_VEL_P_Z]
    e0, e1, e2 = vs0 - v[0], vs1 - v[1], vs2 - v[2]
    a0 = _add_if_finite(sp[SP_ACC], e0 * kv + m[M_INT] - m[M_DFILT] * g[G_VEL_D_XY])
    a1 = _add_if_finite(sp[SP_ACC + 1], e1 * kv + m[M_INT + 1] - m[M_DFILT + 1] * g[G_VEL_D_XY])
    a2 = _add_if_finite(sp[SP_ACC + 2], e2 * kvz + m[M_INT + 2] - m[M_DFILT + 2] * g[G_VEL_D_Z])
    a0 = a0 if math.isfinite(a0) else 0.0  # (an axis with no source: the hygiene refuses it before)
    a1 = a1 if math.isfinite(a1) else 0.0
    a2 = a2 if math.isfinite(a2) else 0.0
    # _accelerationControl: tilt from the horizontal acceleration against 1 g, thrust from the hover thrust
    bx, by, bz = -a0, -a1, grav
    nb = math.sqrt(bx * bx + by * by + bz * bz)
    bx, by, bz = bx / nb, by / nb, bz / nb
    if bz < g[G_TILT_COS]:  # limitTilt (the angle from vertical beyond the limit)
        nr = math.sqrt(bx * bx + by * by)
        if nr < 1e-9:
            bx, by, nr = 1.0, 0.0, 1.0
        sn = g[G_TILT_SIN]
        bx, by, bz = sn * bx / nr, sn * by / nr, g[G_TILT_COS]
    coll = min((a2 * (hov / grav) - hov) / bz, -g[G_THR_MIN])
    tx, ty, tz = bx * coll, by * coll, bz * coll
    # anti-windup, vertical
    thr_min, thr_max = g[G_THR_MIN], g[G_THR_MAX]
    if (tz >= -thr_min and e2 >= 0.0) or (tz <= -thr_max and e2 <= 0.0):
        e2 = 0.0
    # vertical priority with a horizontal margin
    txy = math.sqrt(tx * tx + ty * ty)
    alloc = min(txy, g[G_THR_XY_MARGIN])
    tz = max(tz, -math.sqrt(max(thr_max * thr_max - alloc * alloc, 0.0)))
    rest = thr_max * thr_max - tz * tz
    txy_max = math.sqrt(rest) if rest > 0.0 else 0.0
    if txy > txy_max:
        tx, ty = tx / txy * txy_max, ty / txy * txy_max
    # tracking anti-windup, horizontal (Rundqwist): the integrator unsaturates the output
    px, py = tx * (grav / hov), ty * (grav / hov)
    if a0 * a0 + a1 * a1 > px * px + py * py:
        lx, ly = px, py
    else:
        lx, ly = a0, a1
    arw = 2.0 / kv if kv > 0.0 else 0.0
    e0 -= arw * (a0 - lx)
    e1 -= arw * (a1 - ly)
    ki, kiz = g[G_VEL_I_XY], g[G_VEL_I_Z]
    m[M_INT] += (e0 if math.isfinite(e0) else 0.0) * ki * dt
    m[M_INT + 1] += (e1 if math.isfinite(e1) else 0.0) * ki * dt
    iz = m[M_INT + 2] + (e2 if math.isfinite(e2) else 0.0) * kiz * dt
    m[M_INT + 2] = min(max(iz, -grav), grav)
    return tx, ty, tz


@njit(cache=True, inline="always")
def _ardupilot_loop(p, v, sp, g, m, dt, grav):
    """ArduCopter AC_PosControl::update_xy_controller and update_z_controller (one step),
    with the setpoint as the guided target: the normalised thrust vector (NED, up is -z)."""
    hov = g[G_HOVER_PARAM]
    a_e = _lp_alpha(dt, g[G_VEL_ERR_LP_HZ])
    a_ez = _lp_alpha(dt, g[G_VEL_Z_ERR_LP_HZ])
    a_d = _lp_alpha(dt, g[G_VEL_D_LP_HZ])
    a_a = _lp_alpha(dt, g[G_ACC_ERR_LP_HZ])
    first = m[M_STARTED] == 0.0
    if first:
        for k in range(3):
            m[M_VPREV + k] = v[k]
        m[M_STARTED] = 1.0
    a_meas_up = -(v[2] - m[M_VPREV + 2]) / dt
    for k in range(3):
        m[M_VPREV + k] = v[k]
    # horizontal position: square-root controller on the error vector, at most the speed limit
    has_pos = math.isfinite(sp[SP_POS]) and math.isfinite(sp[SP_POS + 1])
    has_vel = math.isfinite(sp[SP_VEL]) and math.isfinite(sp[SP_VEL + 1])
    cx, cy = 0.0, 0.0
    if has_pos:
        ex, ey = sp[SP_POS] - p[0], sp[SP_POS + 1] - p[1]
        en = math.hypot(ex, ey)
        if en > 0.0:
            cn = min(_sqrt_controller(en, g[G_POS_P_XY], g[G_POS_ACC_XY], dt), g[G_VEL_MAX_XY])
            cx, cy = ex / en * cn, ey / en * cn
    vt0 = cx + (sp[SP_VEL] if has_vel else 0.0)
    vt1 = cy + (sp[SP_VEL + 1] if has_vel else 0.0)
    # horizontal velocity PID (AC_PID_2D): filtered error, filtered derivative, integrator
    # held against the last limit vector and clamped to IMAX; no velocity target: no correction
    stab_vel = has_pos or has_vel
    ax, ay = 0.0, 0.0
    if stab_vel:
        ex, ey = vt0 - v[0], vt1 - v[1]
        if first:
            m[M_EFILT], m[M_EFILT + 1] = ex, ey
            m[M_DFILT], m[M_DFILT + 1] = 0.0, 0.0
        else:
            lx, ly = m[M_EFILT], m[M_EFILT + 1]
            m[M_EFILT] += (ex - lx) * a_e
            m[M_EFILT + 1] += (ey - ly) * a_e
            m[M_DFILT] += ((m[M_EFILT] - lx) / dt - m[M_DFILT]) * a_d
            m[M_DFILT + 1] += ((m[M_EFILT + 1] - ly) / dt - m[M_DFILT + 1]) * a_d
        ki = g[G_VEL_I_XY]
        dix, diy = m[M_EFILT] * ki * dt, m[M_EFILT + 1] * ki * dt
        if dix * m[M_LIMIT] + diy * m[M_LIMIT + 1] > 0.0:
            dix, diy = 0.0, 0.0
        ix, iy = m[M_INT] + dix, m[M_INT + 1] + diy
        il = math.hypot(ix, iy)
        imax = g[G_VEL_IMAX_XY]
        if il > imax:
            ix, iy = ix * imax / il, iy * imax / il
        m[M_INT], m[M_INT + 1] = ix, iy
        kp, kd = g[G_VEL_P_XY], g[G_VEL_D_XY]
        ax = m[M_EFILT] * kp + ix + m[M_DFILT] * kd
        ay = m[M_EFILT + 1] * kp + iy + m[M_DFILT + 1] * kd
    else:  # acceleration only: stop_vel_NE_stabilisation (no correction, integrator cleared)
        m[M_INT], m[M_INT + 1] = 0.0, 0.0
    if math.isfinite(sp[SP_ACC]) and math.isfinite(sp[SP_ACC + 1]):
        ax += sp[SP_ACC]
        ay += sp[SP_ACC + 1]
    # acceleration limit from the lean angle; the limit vector holds the integrator next step
    amax = grav * math.tan(g[G_TILT_MAX])
    an = math.hypot(ax, ay)
    if an > amax:
        m[M_LIMIT], m[M_LIMIT + 1] = ax, ay
        ax, ay = ax * amax / an, ay * amax / an
    else:
        m[M_LIMIT], m[M_LIMIT + 1] = 0.0, 0.0
    # vertical: square-root position controller (up is -z), velocity P(I), acceleration PI to throttle
    up_pos = -sp[SP_POS + 2]
    up_vel = -sp[SP_VEL + 2]
    up_acc = -sp[SP_ACC + 2]
    vt_up = 0.0
    if math.isfinite(up_pos):
        vt_up = _sqrt_controller(up_pos + p[2], g[G_POS_P_Z], g[G_POS_ACC_Z], dt)
        vt_up = min(max(vt_up, -g[G_VEL_MAX_DN]), g[G_VEL_MAX_UP])
    if math.isfinite(up_vel):
        vt_up += up_vel
    at_up = 0.0
    if math.isfinite(up_pos) or math.isfinite(up_vel):
        ez = vt_up - (-v[2])
        if first:
            m[M_EFILT + 2] = ez
        else:
            m[M_EFILT + 2] += (ez - m[M_EFILT + 2]) * a_ez
        lim_up, lim_dn = m[M_LIMIT + 2] > 0.0, m[M_LIMIT + 2] < 0.0
        ez_f = m[M_EFILT + 2]
        if not ((ez_f > 0.0 and lim_up) or (ez_f < 0.0 and lim_dn)):
            m[M_INT + 2] += ez_f * g[G_VEL_I_Z] * dt
            m[M_INT + 2] = min(max(m[M_INT + 2], -g[G_VEL_IMAX_Z]), g[G_VEL_IMAX_Z])
        at_up = ez_f * g[G_VEL_P_Z] + m[M_INT + 2]
    if math.isfinite(up_acc):
        at_up += up_acc
    ea = at_up - a_meas_up
    if first:
        m[M_ACC_E] = ea
    else:
        m[M_ACC_E] += (ea - m[M_ACC_E]) * a_a
    ea_f = m[M_ACC_E]
    limited = m[M_LIMIT + 2] != 0.0
    ia = m[M_ACC_I]
    if not limited or (ia > 0.0 and ea_f < 0.0) or (ia < 0.0 and ea_f > 0.0):
        ia += ea_f * g[G_ACC_Z_I] * dt
        imax = max(g[G_ACC_Z_IMAX], hov)
        ia = min(max(ia, -imax), imax)
    m[M_ACC_I] = ia
    thr = hov + ea_f * g[G_ACC_Z_P] + ia
    # thrust along the lean that gives (ax, ay) at 1 g, with angle boost
    dx, dy, dz = ax, ay, -grav
    dn = math.sqrt(dx * dx + dy * dy + dz * dz)
    cos_tilt = grav / dn
    thr = thr / max(cos_tilt, _ANGLE_BOOST_COS_MIN)
    if thr >= g[G_THR_MAX]:
        thr, m[M_LIMIT + 2] = g[G_THR_MAX], 1.0
    elif thr <= g[G_THR_MIN]:
        thr, m[M_LIMIT + 2] = g[G_THR_MIN], -1.0
    else:
        m[M_LIMIT + 2] = 0.0
    return thr * dx / dn, thr * dy / dn, thr * dz / dn


@njit(cache=True, inline="always")
def position_loop_accel(p, v, sp, g, m, dt, grav):
    """One physics step of a vehicle's position loops (gain row g, memory row m, packed
    setpoint row sp): the acceleration (NED m/s^2) the inner controller must realise so that
    the rotors give the autopilot's thrust. The autopilot scales thrust by its hover-thrust
    parameter; the airframe's true hover thrust turns that thrust back into acceleration."""
    if g[G_STYLE] == LOOP_ARDUPILOT:
        tx, ty, tz = _ardupilot_loop(p, v, sp, g, m, dt, grav)
    else:
        tx, ty, tz = _px4_loop(p, v, sp, g, m, dt, grav)
    k = grav / g[G_HOVER_TRUE]
    return tx * k, ty * k, tz * k + grav
