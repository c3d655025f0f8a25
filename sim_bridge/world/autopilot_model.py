"""What a simulated autopilot does on its own, shared by the SITL and the headless runner.

Its position and velocity loops (`PositionController`, sim_bridge/world/position_loop.py) are one kernel for every
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
from companion.control.geometric import pack_setpoint
from companion.link.dialects import DIALECTS, dialect_named
from companion.link.dialects.base import AfterLoss, CarryOn, LossBehaviour
from companion.state import FleetSetpoint, FleetState
from sim_bridge.world.position_loop import PositionController

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

