"""Headless runner: the paper's whole scenario in-process, far faster than real time.

The loop is: release due vehicles from the carrier -> deliver the neighbour
states the transport has due -> one batched Agent.step for every vehicle (the
same Agent the MAVLink companion runs for one vehicle, its loops compiled) ->
the autopilot model turns agent setpoints into inner-loop setpoints (throw
recovery, hold, offboard) -> publish states at the swarm rate -> injected rotor
failures due -> record -> Physics.step for physics_rate/agent_rate steps with the
setpoints held (the inner-loop geometric or PID controller runs at the physics rate).

`run_batch` flies several seeds of one scenario side by side: their vehicles are
rows of the same Agent.step and autopilot-model call; everything else is per run.
A sweep uses it to pay the per-tick Python cost once for many runs.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
from numba import njit
from tqdm import tqdm

from companion import frames
from companion.agent import Agent, OwnState, Phase
from companion.config import ConfigError
from companion.control.geometric import pack_setpoint
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
    all_offboard: bool = False
    """Every vehicle flew offboard after the last call (then a call that finds every
    vehicle still commanded only returns the agent's setpoints)."""

    @classmethod
    def docked(cls, n: int) -> "AutopilotModel":
        return cls(np.full(n, AP_DOCKED, dtype=np.int8), np.zeros((n, 3)), np.zeros(n))

    @property
    def ready(self) -> np.ndarray:
        return self.mode >= AP_HOLD

    def release(self, rows: np.ndarray, state: FleetState) -> None:
        self.mode[rows] = AP_THROW
        self.all_offboard = False
        self.hold_yaw[rows] = frames.yaw_rad(state.rot_body_to_ned[rows])

    def setpoint(self, state: FleetState, agent_sp: FleetSetpoint) -> FleetSetpoint:
        """The inner-loop setpoint of every vehicle this tick (advances the mode machine).
        When every vehicle flies offboard this is agent_sp itself, not a copy."""
        commanded = _commanded(agent_sp.pos_ned_m, agent_sp.vel_ned_mps, agent_sp.acc_ned_mps2)
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
        lost = (self.mode == AP_OFFBOARD) & ~commanded
        if lost.any():
            self.hold_pos[lost] = hold_point(state.pos_ned_m[lost], state.vel_ned_mps[lost])
            self.hold_yaw[lost] = frames.yaw_rad(state.rot_body_to_ned[lost])
            self.mode[lost] = AP_HOLD
        self.mode[(self.mode == AP_HOLD) & commanded] = AP_OFFBOARD
        off = self.mode == AP_OFFBOARD
        self.all_offboard = bool(off.all())
        if self.all_offboard:
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
    """Fly the scenario headless and return the recorded run (a batch of one: run_batch).

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
    return run_batch([cfg], progress, clock, None if transport is None else [transport])[0]


class _Run:
    """One seed of a batch: its rows of the batch's arrays, its own random streams,
    physics (wind), link, estimator, faults and record. Everything here is what a
    single run has; only the agent and the autopilot model are shared, row by row."""

    def __init__(self, cfg: ScenarioConfig, mission: Mission, rows: slice, state: FleetState, view: SwarmView,
                 released: np.ndarray, transport: NeighbourTransport | None, log_every: int):
        n = mission.n
        self.cfg, self.rows = cfg, rows
        self.rng = np.random.default_rng(cfg.seed)
        self.physics = Physics(cfg.vehicle, cfg.inner_loop, dt_s=1.0 / cfg.physics.rate_hz, wind=cfg.physics.wind,
                               ground_z_m=cfg.physics.ground_z_m, rng=self.rng)
        self.transport = transport or make_transport(cfg.link, n, cfg.seed)
        self.estimator = Estimator(cfg.estimator, n, np.random.default_rng([cfg.seed, 0x455354])) \
            if cfg.estimator.active else None
        self.faults = RotorFaults(resolve_rotor_failures(cfg.faults, n, cfg.seed), n) if cfg.faults.active else None
        # Row views of the batch's arrays: what this run's parts write lands in the batch.
        self.state = FleetState(*(getattr(state, f)[rows] for f in FleetState.__dataclass_fields__))
        self.view = SwarmView(*(getattr(view, f)[rows] for f in _VIEW_ARRAYS), receive_kernel=view.receive_kernel)
        self.tracker = MissionTracker(cfg, mission, log_every)
        self.released = released[rows]
        self.rel_s = release_times_s(cfg.carrier, n)
        self.next_release = min(self.rel_s) if n else math.inf  # (a float compare per tick)
        self.n_released = 0
        self.vehicle_steps = 0
        self.result: RunResult | None = None


_VIEW_ARRAYS = ("pos_ned_m", "vel_ned_mps", "stamp_s", "phase", "flags", "t_go_s", "received", "ignored_old")


def run_batch(cfgs: list[ScenarioConfig], progress: bool = False, clock=None,
              transports: list[NeighbourTransport] | None = None) -> list[RunResult]:
    """Fly several runs of one scenario that differ only in their seed, side by side.

    Each run's vehicles are rows of one batch: one Agent.step and one autopilot-model
    call cover every run's vehicles (both work row by row, so a row's result does not
    depend on its neighbours in the batch), while every run keeps its own random
    streams, physics, link, estimator, faults and record. So a run's result is the same,
    to the last bit, alone or in any batch (tests/test_headless_batch.py); what a batch
    saves is the per-tick cost of the Python and numpy calls, paid once for all runs.
    A run that completes stops there; the batch goes on until every run has.

    Args:
        cfgs: validated scenarios, equal except for their seed.
        progress: tqdm progress bar over simulated time.
        clock: wall-clock function (s); time.perf_counter by default. Each run's wall_s is
            the batch's wall time until that run ended, divided by the batch size.
        transports: one per run (default: from each cfg.link and seed).
    Returns:
        One RunResult per cfg, in order.
    Raises:
        ValueError: the scenarios differ in more than their seed, or no scenario.
        FormationUnstableError: the mission's consensus gains are not stabilising.
        ConfigError: a ground-launch mission (only the fleet flies those).
    """
    if not cfgs:
        raise ValueError("run_batch needs at least one scenario")
    cfg = cfgs[0]
    if any(dataclasses.replace(c, seed=cfg.seed) != cfg for c in cfgs[1:]):
        raise ValueError("run_batch: the scenarios must differ in their seed only")
    if cfg.mission.launch != "carrier":
        raise ConfigError(f"{cfg.name}: mission.launch is {cfg.mission.launch!r}: the headless runner flies carrier "
                          "launches only; fly a ground launch with `swarmdrop run` (the SITL and agents)")
    clock = clock or time.perf_counter
    mission = Mission(cfg.mission)
    n, n_runs = mission.n, len(cfgs)
    ids = np.arange(n)
    agent = Agent(mission, np.tile(ids, n_runs), kernels=agent_kernels())
    view = SwarmView.unknown(n * n_runs, n, receive_kernel=compiled(receive_rows))
    autopilot = AutopilotModel.docked(n * n_runs)
    dt_agent = 1.0 / cfg.agent.rate_hz
    sub_steps = int(round(cfg.physics.rate_hz / cfg.agent.rate_hz))
    log_every = int(round(cfg.agent.rate_hz / cfg.output.log_rate_hz))
    state = FleetState.zeros(n * n_runs)
    released = np.zeros(n * n_runs, dtype=bool)
    runs = [_Run(c, mission, slice(k * n, (k + 1) * n), state, view, released,
                 None if transports is None else transports[k], log_every) for k, c in enumerate(cfgs)]
    to_quat, q_own = compiled(frames.rot_to_quat_rows), np.empty((n * n_runs, 4))  # 1 us, numpy's twin 100 us
    estimated = runs[0].estimator is not None  # (the same estimator config in every run)
    p_obs, v_obs, r_obs = np.empty((n * n_runs, 3)), np.empty((n * n_runs, 3)), np.empty((n * n_runs, 3, 3))
    wall0 = clock()
    n_ticks = int(math.ceil(cfg.duration_s / dt_agent))
    bar = tqdm(total=round(cfg.duration_s), unit="sim-s", disable=not progress, desc=cfg.name, mininterval=0.5)
    # Who publishes at tick k depends on k modulo the ticks per swarm period only: one
    # mask per offset, from swarm_due itself.
    period_us = round(dt_agent * 1e6)
    n_offsets = max(1, int(round(1e6 / (cfg.mission.swarm.rate_hz * period_us))))
    publish_at = [swarm_due(j * period_us, cfg.mission.swarm.rate_hz, ids, period_us) for j in range(n_offsets)]
    publish_all = [np.tile(m, n_runs) for m in publish_at]
    live = list(runs)
    for k in range(n_ticks + 1):
        t = k * dt_agent
        for r in live:
            if r.next_release <= t + 1e-9:
                due = ~r.released & (r.rel_s <= t + 1e-9)
                release_into(r.state, np.flatnonzero(due), r.cfg, t, r.rng)
                autopilot.release(r.rows.start + np.flatnonzero(due), state)
                r.released |= due  # (a view: the batch's released too)
                r.n_released = int(r.released.sum())
                r.next_release = min(r.rel_s[~r.released], default=math.inf)
            if r.n_released < n:
                docked = ~r.released
                r.state.pos_ned_m[docked] = carrier_position_ned_m(r.cfg.carrier, t)
                r.state.vel_ned_mps[docked] = r.cfg.carrier.vel_ned_mps
            r.transport.deliver(t, r.view)
            if r.estimator is not None:  # what the autopilot's estimator would report (as the SITL does)
                p_obs[r.rows], v_obs[r.rows], r_obs[r.rows] = r.estimator.observe(
                    t, r.state.pos_ned_m, r.state.vel_ned_mps, r.state.rot_body_to_ned)
        if estimated:
            to_quat(r_obs, q_own)
            own = OwnState(p_obs, v_obs, q_own, np.full(n * n_runs, t), released, autopilot.ready)
        else:
            to_quat(state.rot_body_to_ned, q_own)
            own = OwnState(state.pos_ned_m, state.vel_ned_mps, q_own, np.full(n * n_runs, t), released,
                           autopilot.ready)
        out = agent.step(t, own, view)
        offset = ((round(t * 1e6) + period_us // 2) // period_us) % n_offsets
        per_run = int(publish_at[offset].sum())
        published = out.published.select(publish_all[offset]) if per_run else None
        sp = autopilot.setpoint(state, out.setpoint)
        if estimated:  # the autopilot flies on its estimate (sim_bridge/estimator.py)
            for r in live:
                if r.estimator is not None:
                    sp.pos_ned_m[r.rows] = to_true_frame(sp.pos_ned_m[r.rows], r.estimator.offset_ned_m)
        packed = pack_setpoint(sp)  # once for every run
        for r in list(live):
            i = r.rows.start // n
            if published is not None:  # the selected rows come run by run, per_run each
                r.transport.publish(t, published.rows(slice(i * per_run, (i + 1) * per_run)), r.state.pos_ned_m)
            if r.faults is not None:
                r.faults.update(t)
            sp_r = FleetSetpoint(*(getattr(sp, f)[r.rows] for f in FleetSetpoint.__dataclass_fields__))
            done = r.tracker.update(t, r.state, sp_r, r.released, out.phase[r.rows], out.assembled[r.rows],
                                    out.t_go_s[r.rows], failed_at_s=None if r.faults is None else r.faults.failed_at_s)
            if done or k == n_ticks:
                r.result = r.tracker.result(r.rel_s, carrier_position_ned_m(r.cfg.carrier, r.rel_s),
                                            (clock() - wall0) / n_runs, t, r.vehicle_steps, r.transport.stats())
                live.remove(r)
                continue
            r.physics.step(r.state, packed[r.rows], n_steps=sub_steps, active=r.released,
                           rotor_scale=None if r.faults is None else r.faults.scale)
            r.vehicle_steps += sub_steps * r.n_released
        if not live:
            break
        if int(t + dt_agent) != int(t):
            bar.update(1)
            bar.set_postfix_str(_phase_summary(out.phase))
    bar.total = bar.n  # finished early (mission complete): close the bar at 100 %
    bar.close()
    return [r.result for r in runs]


def _phase_summary(phase: np.ndarray) -> str:
    counts = np.bincount(phase, minlength=len(Phase))
    return " ".join(f"{p.name.lower()}:{counts[p]}" for p in Phase if counts[p])


