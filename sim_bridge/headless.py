"""Headless runner: the paper's whole scenario in-process, far faster than real time.

The loop is: release due vehicles from the carrier -> deliver the neighbour
states the transport has due -> one batched Agent.step for every vehicle (the
same Agent the MAVLink companion runs for one vehicle, its loops compiled) ->
publish states at the swarm rate -> the autopilot model turns agent setpoints
into inner-loop setpoints (throw recovery, hold, offboard) -> injected rotor
failures due -> record -> Physics.step for
physics_rate/agent_rate steps with the setpoints held (the inner-loop geometric
or PID controller runs at the physics rate).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from companion import frames
from companion.agent import Agent, OwnState, Phase
from companion.config import ConfigError
from companion.mission import Mission
from companion.state import FleetSetpoint, FleetState
from companion.swarm import SwarmView, receive_rows, swarm_due
from sim_bridge.autopilot_model import hold_point, throw_recovered
from sim_bridge.carrier import carrier_position_ned_m, release_times_s, sample_release_attitudes
from sim_bridge.estimator import Estimator, to_true_frame
from sim_bridge.faults import RotorFaults, resolve_rotor_failures
from sim_bridge.jit import agent_kernels, compiled
from sim_bridge.physics import Physics, hover_rotor_speed_radps
from sim_bridge.record import MissionTracker, RunResult
from sim_bridge.scenario import ScenarioConfig
from sim_bridge.transport import NeighbourTransport, make_transport


def release_into(state: FleetState, rows: np.ndarray, cfg: ScenarioConfig, t_s: float, rng: np.random.Generator) -> None:
    """Put vehicles `rows` into free flight at the carrier's position and velocity
    with attitudes drawn from the carrier's distribution, rotors at hover speed."""
    rot, omega = sample_release_attitudes(cfg.carrier, len(rows), rng)
    state.pos_ned_m[rows] = carrier_position_ned_m(cfg.carrier, t_s)
    state.vel_ned_mps[rows] = cfg.carrier.vel_ned_mps
    state.rot_body_to_ned[rows] = rot
    state.omega_body_radps[rows] = omega
    state.rotor_speed_radps[rows] = hover_rotor_speed_radps(cfg.vehicle)
    state.ctrl_integral[rows] = 0.0


AP_DOCKED, AP_THROW, AP_HOLD, AP_OFFBOARD = 0, 1, 2, 3


@dataclass
class AutopilotModel:
    """The headless stand-in for each vehicle's autopilot, vectorised (N vehicles).

    It does what the SITL's autopilot does on its own (sim_bridge.autopilot_model):
    after a release it recovers the vehicle (zero velocity, heading held) until the
    throw thresholds hold, then holds where it comes to rest, and flies the agent's
    setpoints once the agent sends any (the agent sends nothing while it lets the
    autopilot recover the vehicle). Its `ready` is what the agent is told.
    """

    mode: np.ndarray
    hold_pos: np.ndarray
    hold_yaw: np.ndarray

    @classmethod
    def docked(cls, n: int) -> "AutopilotModel":
        return cls(np.full(n, AP_DOCKED, dtype=np.int8), np.zeros((n, 3)), np.zeros(n))

    @property
    def ready(self) -> np.ndarray:
        return self.mode >= AP_HOLD

    def release(self, rows: np.ndarray, state: FleetState) -> None:
        self.mode[rows] = AP_THROW
        self.hold_yaw[rows] = frames.yaw_rad(state.rot_body_to_ned[rows])

    def setpoint(self, state: FleetState, agent_sp: FleetSetpoint) -> FleetSetpoint:
        """The inner-loop setpoint of every vehicle this tick (advances the mode machine).
        When every vehicle flies offboard this is agent_sp itself, not a copy."""
        thr = self.mode == AP_THROW
        if thr.any():
            r = state.rot_body_to_ned[thr]
            done = throw_recovered(r[:, 2, 2], np.linalg.norm(state.omega_body_radps[thr], axis=1),
                                   np.linalg.norm(state.vel_ned_mps[thr], axis=1))
            rows = np.flatnonzero(thr)[done]
            self.mode[rows] = AP_HOLD
            self.hold_pos[rows] = hold_point(state.pos_ned_m[rows], state.vel_ned_mps[rows])
            self.hold_yaw[rows] = frames.yaw_rad(state.rot_body_to_ned[rows])
        commanded = ~np.all(np.isnan(agent_sp.pos_ned_m) & np.isnan(agent_sp.vel_ned_mps)
                            & np.isnan(agent_sp.acc_ned_mps2), axis=1)
        lost = (self.mode == AP_OFFBOARD) & ~commanded
        if lost.any():
            self.hold_pos[lost] = hold_point(state.pos_ned_m[lost], state.vel_ned_mps[lost])
            self.hold_yaw[lost] = frames.yaw_rad(state.rot_body_to_ned[lost])
            self.mode[lost] = AP_HOLD
        self.mode[(self.mode == AP_HOLD) & commanded] = AP_OFFBOARD
        off = self.mode == AP_OFFBOARD
        if off.all():  # the usual case once the swarm flies: the agent's setpoints, as they are
            return agent_sp
        sp = FleetSetpoint.empty(len(self.mode))
        sp.assign(off, agent_sp.select(off))
        thr = self.mode == AP_THROW
        sp.vel_ned_mps[thr] = 0.0
        sp.yaw_rad[thr] = self.hold_yaw[thr]
        hold = self.mode == AP_HOLD
        sp.pos_ned_m[hold] = self.hold_pos[hold]
        sp.yaw_rad[hold] = self.hold_yaw[hold]
        return sp


def run_scenario(cfg: ScenarioConfig, progress: bool = True, clock=None,
                 transport: NeighbourTransport | None = None) -> RunResult:
    """Fly the scenario headless and return the recorded run.

    Args:
        cfg: validated scenario.
        progress: show a tqdm progress bar over simulated time.
        clock: wall-clock function (seconds) for the timing figures; time.perf_counter by default.
        transport: how published states reach the other vehicles; default from cfg.link
            (seeded from cfg.seed, independent of the physics' random draws).
    Raises:
        FormationUnstableError: the mission's consensus gains are not stabilising.
        ConfigError: a ground-launch mission (only the fleet flies those).
    """
    if cfg.mission.launch != "carrier":
        raise ConfigError(f"{cfg.name}: mission.launch is {cfg.mission.launch!r}: the headless runner flies carrier "
                          "launches only; fly a ground launch with `swarmdrop run` (the SITL and agents)")
    clock = clock or time.perf_counter
    rng = np.random.default_rng(cfg.seed)
    mission = Mission(cfg.mission)
    n = mission.n
    physics = Physics(
        cfg.vehicle, cfg.inner_loop, dt_s=1.0 / cfg.physics.rate_hz, wind=cfg.physics.wind,
        ground_z_m=cfg.physics.ground_z_m, rng=rng,
    )
    ids = np.arange(n)
    agent = Agent(mission, ids, kernels=agent_kernels())
    transport = transport or make_transport(cfg.link, n, cfg.seed)
    estimator = Estimator(cfg.estimator, n, np.random.default_rng([cfg.seed, 0x455354])) if cfg.estimator.active else None
    faults = RotorFaults(resolve_rotor_failures(cfg.faults, n, cfg.seed), n) if cfg.faults.active else None
    view = SwarmView.unknown(n, n, receive_kernel=compiled(receive_rows))
    autopilot = AutopilotModel.docked(n)
    dt_agent = 1.0 / cfg.agent.rate_hz
    sub_steps = int(round(cfg.physics.rate_hz / cfg.agent.rate_hz))
    log_every = int(round(cfg.agent.rate_hz / cfg.output.log_rate_hz))

    state = FleetState.zeros(n)
    to_quat, q_own = compiled(frames.rot_to_quat_rows), np.empty((n, 4))  # 1 us, numpy's twin 100 us
    released = np.zeros(n, dtype=bool)
    rel_s = release_times_s(cfg.carrier, n)
    rel_pos = carrier_position_ned_m(cfg.carrier, rel_s)
    tracker = MissionTracker(cfg, mission, log_every)
    wall0 = clock()
    n_ticks = int(math.ceil(cfg.duration_s / dt_agent))
    vehicle_steps = 0
    bar = tqdm(total=round(cfg.duration_s), unit="sim-s", disable=not progress, desc=cfg.name, mininterval=0.5)
    for k in range(n_ticks + 1):
        t = k * dt_agent
        due = ~released & (rel_s <= t + 1e-9)
        if due.any():
            release_into(state, np.flatnonzero(due), cfg, t, rng)
            autopilot.release(np.flatnonzero(due), state)
            released |= due
        docked = ~released
        state.pos_ned_m[docked] = carrier_position_ned_m(cfg.carrier, t)
        state.vel_ned_mps[docked] = cfg.carrier.vel_ned_mps

        transport.deliver(t, view)
        if estimator is None:
            to_quat(state.rot_body_to_ned, q_own)
            own = OwnState(state.pos_ned_m, state.vel_ned_mps, q_own, np.full(n, t), released, autopilot.ready)
        else:  # what the autopilot's estimator would report (the SITL applies the same model)
            p_obs, v_obs, r_obs = estimator.observe(t, state.pos_ned_m, state.vel_ned_mps, state.rot_body_to_ned)
            to_quat(r_obs, q_own)
            own = OwnState(p_obs, v_obs, q_own, np.full(n, t), released, autopilot.ready)
        out = agent.step(t, own, view)
        publish = swarm_due(round(t * 1e6), cfg.mission.swarm.rate_hz, ids, round(dt_agent * 1e6))
        if publish.any():
            transport.publish(t, out.published.select(publish), state.pos_ned_m)
        sp = autopilot.setpoint(state, out.setpoint)
        if estimator is not None:  # the autopilot flies on its estimate (sim_bridge/estimator.py)
            sp.pos_ned_m = to_true_frame(sp.pos_ned_m, estimator.offset_ned_m)
        if faults is not None:
            faults.update(t)
        done = tracker.update(t, state, sp, released, out.phase, out.assembled, out.t_go_s,
                              failed_at_s=None if faults is None else faults.failed_at_s)
        if done or k == n_ticks:
            break
        physics.step(state, sp, n_steps=sub_steps, active=released,
                     rotor_scale=None if faults is None else faults.scale)
        vehicle_steps += sub_steps * int(released.sum())
        if int(t + dt_agent) != int(t):
            bar.update(1)
            bar.set_postfix_str(_phase_summary(out.phase))
    bar.total = bar.n  # finished early (mission complete): close the bar at 100 %
    bar.close()
    return tracker.result(rel_s, rel_pos, clock() - wall0, t, vehicle_steps, transport.stats())


def _phase_summary(phase: np.ndarray) -> str:
    counts = np.bincount(phase, minlength=len(Phase))
    return " ".join(f"{p.name.lower()}:{counts[p]}" for p in Phase if counts[p])


